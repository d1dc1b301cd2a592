"""Independent float64 truth for the imaging tests.

Written straight from the definition in docs/CONVENTIONS.md with no code shared with the package:
D[k, a] = w_a B[k, a] exp(-2 pi i nu (l x + m y + n z) / c) / N_A, F = D x(t), I = mean_t |F|^2.
"""
import numpy as np

C = 299792458.0


def brute_fields(efield, xyz_m, freq_hz, lm, weights=None, pattern=None):
    """Beamformed fields F, complex128 (ntime, nchan, npix, npol), by an explicit sum over antennas."""
    efield = np.asarray(efield, dtype=np.complex128)
    T, C_, A, P = efield.shape
    l, m = lm[:, 0].astype(np.float64), lm[:, 1].astype(np.float64)
    n = np.sqrt(1.0 - l * l - m * m)
    w = np.ones((C_, A, P), complex) if weights is None else np.broadcast_to(weights, (C_, A, P))
    F = np.zeros((T, C_, len(l), P), complex)
    for c, nu in enumerate(freq_hz):
        for p in range(P):
            live = w[c, :, p] != 0
            na = live.sum()
            for a in np.flatnonzero(live):
                x, y, z = xyz_m[a]
                d = w[c, a, p] * np.exp(-2j * np.pi * nu / C * (l * x + m * y + n * z)) / na
                if pattern is not None:
                    b = np.broadcast_to(pattern, (C_, len(l), A, P))
                    d = d * b[c, :, a, p]
                F[:, c, :, p] += efield[:, c, a, p][:, None] * d[None, :]
    return F


def brute_autocorr(efield, xyz_m, freq_hz, lm, weights=None, pattern=None):
    """Autocorrelation terms (nchan, npix) for XX, YY and complex XY: sum_a D^p conj(D^q) mean x_p conj(x_q)."""
    efield = np.asarray(efield, dtype=np.complex128)
    T, C_, A, P = efield.shape
    out = {}
    for a in range(A):
        # one antenna's own field: image of that antenna alone, with the full-array weights
        only = np.zeros_like(efield)
        only[:, :, a, :] = efield[:, :, a, :]
        if weights is not None and np.all(np.broadcast_to(weights, (C_, A, P))[:, a, :] == 0):
            continue
        F = brute_fields(only, xyz_m, freq_hz, lm, weights, pattern)
        xx = (np.abs(F[..., 0]) ** 2).mean(0)
        out["XX"] = out.get("XX", 0) + xx
        if P == 2:
            out["YY"] = out.get("YY", 0) + (np.abs(F[..., 1]) ** 2).mean(0)
            out["XY"] = out.get("XY", 0) + (F[..., 0] * np.conj(F[..., 1])).mean(0)
    return out


def brute_image(efield, xyz_m, freq_hz, lm, products, remove_autocorr=False, weights=None, pattern=None):
    """float64 (nchan, nprod, npix) image by definition, products from XX, YY, XY, YX, I, Q, U, V."""
    F = brute_fields(efield, xyz_m, freq_hz, lm, weights, pattern)
    xx = (np.abs(F[..., 0]) ** 2).mean(0)
    yy = (np.abs(F[..., -1]) ** 2).mean(0)
    xy = (F[..., 0] * np.conj(F[..., -1])).mean(0)
    if remove_autocorr:
        ac = brute_autocorr(efield, xyz_m, freq_hz, lm, weights, pattern)
        xx = xx - ac["XX"]
        if "YY" in ac:
            yy = yy - ac["YY"]
            xy = xy - ac["XY"]
    table = {"XX": xx, "YY": yy, "XY": xy.real, "YX": xy.real, "I": xx + yy, "Q": xx - yy,
             "U": 2 * xy.real, "V": -2 * xy.imag}
    return np.stack([table[p] for p in products], axis=1)


def calibration_weights(delay_s, gain, flags, freq_hz):
    """Direction-independent weights w_a = exp(+2 pi i nu tau_a) / sqrt(G_a) (PHYSICS.md's calibration),
    0 for a flagged antenna or a gain <= 0: delay_s, gain (nchan, nant, 2), flags (nant, >= 2) ->
    complex128 (nchan, nant, 2)."""
    tau, g = np.asarray(delay_s, np.float64), np.asarray(gain, np.float64)
    ok = (g > 0) & np.isfinite(g) & np.isfinite(tau) & ~np.asarray(flags, bool)[None, :, :2]
    nu = np.asarray(freq_hz, np.float64)[:, None, None]
    return np.where(ok, np.exp(2j * np.pi * nu * np.where(ok, tau, 0.0)) / np.sqrt(np.where(ok, g, 1.0)), 0.0)


def point_source_efield(xyz_m, freq_hz, l, m, power, ntime, npol=1, rng=None):
    """Voltages of one point source of the given power per pol (sigma = +1, constant-modulus signal).

    The signal has |s(t)|^2 = power exactly, so a perfect imager returns exactly ``power`` at the
    source pixel (for XX and YY; I = 2 power).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    n = np.sqrt(1.0 - l * l - m * m)
    phase = np.exp(+2j * np.pi * np.asarray(freq_hz)[:, None] / C *
                   (l * xyz_m[:, 0] + m * xyz_m[:, 1] + n * xyz_m[:, 2])[None, :])  # (nchan, nant)
    s = np.sqrt(power) * np.exp(2j * np.pi * rng.random((ntime, len(freq_hz), 1, npol)))
    return s * phase[None, :, :, None]
