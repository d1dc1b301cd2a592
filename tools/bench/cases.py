"""Benchmark scenes shared by the tools/bench/ scripts (not part of the package API).

Case P (the seed paper's table): 256 antennas laid out like LWA-SV, a 64 x 64 all-sky grid of which
the ~3,205 pixels above the horizon are imaged, 1,024 samples, 16 channels x 2 pols.
"""
import numpy as np

C = 299792458.0


def lwasv_like_layout(nant=256, seed=1):
    """(nant, 3) ENU metres: LWA-SV stand positions from LSL when it imports, else a look-alike
    (a 100 m x 110 m ellipse, z scatter ~0.3 m, the last stand an outrigger 293 m West, 10 m up)."""
    try:
        from bf_epic_blocks.station.offline import configure_offline
        configure_offline()
        from lsl.common import stations
        st = stations.lwasv
        xyz = np.array([[a.stand.x, a.stand.y, a.stand.z] for a in st.antennas[::2]])
        if len(xyz) >= nant:
            return xyz[:nant], "LSL lwasv stands"
    except Exception:
        pass
    rng = np.random.default_rng(seed)
    r = 50 * np.sqrt(rng.random(nant))
    th = 2 * np.pi * rng.random(nant)
    xyz = np.stack([r * np.cos(th), 1.1 * r * np.sin(th), rng.normal(0, 0.3, nant)], axis=1)
    xyz[-1] = [-293.0, 0.0, 10.0]
    return xyz, "synthetic LWA-SV-like layout"


def sky_efield(xyz, freq_hz, ntime, npol=2, nsrc=4, seed=2, dtype=np.complex64):
    """Noise plus a few point sources (powers 10..40 per pol), sigma = +1; (ntime, nchan, nant, npol)."""
    rng = np.random.default_rng(seed)
    nant, nchan = len(xyz), len(freq_hz)
    X = (rng.normal(size=(ntime, nchan, nant, npol)) + 1j * rng.normal(size=(ntime, nchan, nant, npol)))
    for s in range(nsrc):
        alt = np.deg2rad(rng.uniform(20, 85))
        az = rng.uniform(0, 2 * np.pi)
        l, m, n = np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az), np.sin(alt)
        ph = np.exp(2j * np.pi * np.asarray(freq_hz)[:, None] / C * (xyz @ [l, m, n])[None])
        amp = np.sqrt(10.0 * (s + 1)) * (rng.normal(size=(ntime, 1, 1, npol)) + 1j * rng.normal(size=(ntime, 1, 1, npol))) / np.sqrt(2)
        X += amp * ph[None, :, :, None]
    return X.astype(dtype)


def quantise4(X, rms=2.0):
    """4-bit F-engine voltages: (re, im) int8 pairs in -8..7, shape X.shape + (2,), rms ~``rms`` units."""
    s = rms / np.sqrt(np.mean(np.abs(X) ** 2) / 2)
    q = np.stack([np.clip(np.rint(X.real * s), -8, 7), np.clip(np.rint(X.imag * s), -8, 7)], axis=-1)
    return q.astype(np.int8)


def pairs_to_complex(q, dtype=np.complex64):
    return (q[..., 0].astype(np.float32) + 1j * q[..., 1].astype(np.float32)).astype(dtype)


def reference_image(X, xyz, freq_hz, lm, blocks=((0, 0), (1, 1)), accumulate=None):
    """float64 XX/YY (or given blocks) image on a (small) pixel subset, straight from the definition.

    X complex (T, C, A, P) or int8 (re, im) pairs; (C, nblk, npix), or (T // N, C, nblk, npix) with
    ``accumulate=N`` (one image per N samples)."""
    X = np.asarray(X)
    if X.dtype.kind == "i":
        X = X[..., 0].astype(np.float64) + 1j * X[..., 1]
    X = X.astype(np.complex128)
    T = X.shape[0]
    N = T if accumulate is None else int(accumulate)
    g = T // N
    l, m = lm[:, 0], lm[:, 1]
    n = np.sqrt(1 - l * l - m * m)
    out = np.zeros((g, len(freq_hz), len(blocks), len(lm)))
    for c, nu in enumerate(freq_hz):
        D = np.exp(-2j * np.pi * nu / C * (np.outer(l, xyz[:, 0]) + np.outer(m, xyz[:, 1]) + np.outer(n, xyz[:, 2])))
        D /= len(xyz)
        for i, (p, q) in enumerate(blocks):
            F = (D @ X[:g * N, c, :, p].T).reshape(len(lm), g, N)
            G = (D @ X[:g * N, c, :, q].T).reshape(len(lm), g, N)
            out[:, c, i] = (F * np.conj(G)).mean(axis=2).real.T
    return out[0] if accumulate is None else out


LWASV_SITE = {"lat_deg": 34.3484, "lon_deg": -106.8858, "elev_m": 1477.0}


def image_header(grid, freq, dt_img, time_tag=1717236000 * 196_000_000, products=("I",), name="img"):
    """An image sequence header at LWA-SV for feeding image blocks without an imager
    (:func:`bf_epic_blocks.blocks.headers.image_header`)."""
    from bf_epic_blocks.blocks.headers import image_header as header
    return header(name, time_tag, freq, dt_img, grid, {"name": "lwasv", **LWASV_SITE}, products)