"""Simulated sky: orientation (East = +l, North = +m), power normalisation, astropy positions,
cable terms, determinism, 4-bit quantisation. Truth: an explicit float64 beamformer written here."""
import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import AltAz, EarthLocation, SkyCoord
from astropy.time import Time

from bf_epic_blocks.io.tbf import unpack_ci4
from bf_epic_blocks.sky import (KNOWN_SOURCES, quantize_ci4, resolve_source, simulate_efield,
                                         source_directions)

C = 299792458.0
FREQS = np.array([50e6, 74e6])
LWASV = EarthLocation.from_geodetic(lon=-106.885783 * u.deg, lat=34.348358 * u.deg, height=1477.8 * u.m)


@pytest.fixture(scope="module")
def xyz():
    rng = np.random.default_rng(7)
    p = np.zeros((32, 3))
    p[:, :2] = rng.uniform(-50, 50, (32, 2))
    p[:, 2] = rng.uniform(-1, 1, 32)
    return p


def beam_power(x, xyz, freqs, l, m):
    """mean_t |sum_a x_a exp(-2 pi i nu s.r_a / c) / N_A|^2, float64 (nchan, npix, npol)."""
    l, m = np.atleast_1d(l).astype(float), np.atleast_1d(m).astype(float)
    n = np.sqrt(1 - l ** 2 - m ** 2)
    out = np.zeros((len(freqs), len(l), x.shape[-1]))
    for c, nu in enumerate(freqs):
        path = np.outer(xyz[:, 0], l) + np.outer(xyz[:, 1], m) + np.outer(xyz[:, 2], n)   # (A, K)
        d = np.exp(-2j * np.pi * nu * path / C) / xyz.shape[0]
        for p in range(x.shape[-1]):
            f = x[:, c, :, p] @ d
            out[c, :, p] = np.mean(np.abs(f) ** 2, axis=0)
    return out


def grid(step=0.02):
    g = np.arange(-0.96, 0.961, step)
    L, M = np.meshgrid(g, g, indexing="ij")
    keep = L ** 2 + M ** 2 < 0.98
    return L[keep], M[keep]


def test_point_source_peak_position_and_flux(xyz):
    l0, m0, flux = 0.3, -0.2, 4.0
    x = simulate_efield(xyz, FREQS, 1500, sources=[{"name": "p", "l": l0, "m": m0, "flux_jy": flux}],
                        noise_power=0.0, seed=3)
    assert x.shape == (1500, 2, 32, 2) and x.dtype == np.complex128
    L, M = grid()
    stokes_i = beam_power(x[:300], xyz, FREQS, L, M).sum(-1)          # XX + YY, (nchan, npix)
    for c in range(2):
        k = np.argmax(stokes_i[c])
        assert abs(L[k] - l0) <= 0.011 and abs(M[k] - m0) <= 0.011
    at_src = beam_power(x, xyz, FREQS, l0, m0)[:, 0, :]               # (nchan, npol)
    np.testing.assert_allclose(at_src, flux / 2, rtol=0.12)           # flux/2 per pol, ~2.6% sd
    np.testing.assert_allclose(at_src.sum(-1), flux, rtol=0.08)       # I = XX + YY = flux
    mirror = beam_power(x, xyz, FREQS, -l0, -m0)[:, 0, :].sum(-1)
    assert np.all(mirror < 0.3 * flux)


def test_east_is_plus_l_and_north_is_plus_m(xyz):
    d = source_directions([{"name": "east", "az_deg": 90, "alt_deg": 60, "flux_jy": 1},
                           {"name": "north", "az_deg": 0, "alt_deg": 45, "flux_jy": 1}])
    np.testing.assert_allclose(d.l, [0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(d.m, [0.0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(d.alt, np.radians([60, 45]))
    x = simulate_efield(xyz, FREQS, 400, sources=[{"name": "east", "az_deg": 90, "alt_deg": 60, "flux_jy": 2}],
                        noise_power=0.0)
    p = beam_power(x, xyz, FREQS, [0.5, -0.5], [0.0, 0.0]).sum(-1)    # (nchan, 2)
    assert np.all(p[:, 0] > 1.5) and np.all(p[:, 1] < 0.5)
    # the opposite geometric sign mirrors the sky through the zenith (exactly for a flat array;
    # with height differences the mirrored image also defocuses)
    flat = xyz * [1, 1, 0]
    xm = simulate_efield(flat, FREQS, 400, sources=[{"name": "east", "az_deg": 90, "alt_deg": 60, "flux_jy": 2}],
                         noise_power=0.0, sigma=-1)
    pm = beam_power(xm, flat, FREQS, [0.5, -0.5], [0.0, 0.0]).sum(-1)
    assert np.all(pm[:, 1] > 1.5) and np.all(pm[:, 0] < 0.5)


def test_catalogue_positions_match_astropy_and_horizon():
    t = Time("2024-07-01T06:00:00", scale="utc")   # local midnight in summer: Cyg A high
    names = ["Cyg A", "cyga", "CygA", "CYG-A"]
    assert len({resolve_source(n) for n in names}) == 1
    d = source_directions(["CygA", "CasA", "TauA", "VirA"], t, LWASV)
    # independent astropy calculation from the literal coordinates
    truth = {"CygA": ("19h59m28.3566s", "+40d44m02.097s"), "CasA": ("23h23m24s", "+58d48m54s"),
             "TauA": ("05h34m31.94s", "+22d00m52.2s"), "VirA": ("12h30m49.4234s", "+12d23m28.044s")}
    aa = {k: SkyCoord(ra, dec, frame="icrs").transform_to(AltAz(obstime=t, location=LWASV))
          for k, (ra, dec) in truth.items()}
    above = [k for k in truth if aa[k].alt.deg > 0]
    assert d.names == above and sorted(d.dropped) == sorted(set(truth) - set(above))
    assert "CygA" in above and d.dropped == ["TauA"]                    # Tau A is below the horizon then
    for i, k in enumerate(d.names):
        alt, az = aa[k].alt.rad, aa[k].az.rad
        assert d.alt[i] == pytest.approx(alt, abs=2e-6)
        assert d.l[i] == pytest.approx(np.cos(alt) * np.sin(az), abs=2e-6)
        assert d.m[i] == pytest.approx(np.cos(alt) * np.cos(az), abs=2e-6)
    l, m, alt = d                                                       # unpacks as (l, m, alt)
    assert np.all(alt > 0) and np.allclose(np.sin(alt), d.n)
    with pytest.raises(ValueError, match="needs time"):
        source_directions(["CygA"])
    with pytest.raises(ValueError, match="unknown source"):
        resolve_source("CygB")


def test_spectral_index_and_flux_normalisation(xyz):
    src = {"name": "s", "l": 0.0, "m": 0.1, "flux_jy": 10.0, "spectral_index": -0.7}
    x = simulate_efield(xyz, FREQS, 3000, sources=[src], noise_power=0.0, seed=11)
    i = beam_power(x, xyz, FREQS, 0.0, 0.1)[:, 0, :].sum(-1)
    expect = 10.0 * (FREQS / 74e6) ** -0.7
    np.testing.assert_allclose(i, expect, rtol=0.08)
    assert KNOWN_SOURCES["CygA"].flux_at(74e6) == KNOWN_SOURCES["CygA"].flux_jy


def test_noise_and_determinism(xyz):
    kw = dict(sources=[{"name": "p", "l": 0.1, "m": 0.2, "flux_jy": 3.0}], seed=5)
    clean = simulate_efield(xyz, FREQS, 2000, noise_power=0.0, **kw)
    noisy = simulate_efield(xyz, FREQS, 2000, noise_power=2.0, **kw)
    np.testing.assert_array_equal(noisy, simulate_efield(xyz, FREQS, 2000, noise_power=2.0, **kw))
    assert not np.allclose(clean, simulate_efield(xyz, FREQS, 2000, noise_power=0.0,
                                                  sources=kw["sources"], seed=6))
    nz = noisy - clean                                   # same seed: the sky part is unchanged
    np.testing.assert_allclose(np.mean(np.abs(nz) ** 2), 2.0, rtol=0.03)
    cross = np.mean(nz[:, 0, 0, 0] * np.conj(nz[:, 0, 1, 0]))
    assert abs(cross) < 0.2                               # independent per antenna (sd ~ 0.045)
    # every antenna sees the source at the same power flux/2 per pol
    np.testing.assert_allclose(np.mean(np.abs(clean) ** 2, axis=(0, 1)), 1.5, rtol=0.1)
    # only noise when all sources are below the horizon
    below = simulate_efield(xyz, FREQS, 10, sources=[{"name": "b", "az_deg": 0, "alt_deg": -5, "flux_jy": 9}],
                            noise_power=0.0)
    assert not below.any()


def test_cable_terms_round_trip(xyz):
    rng = np.random.default_rng(2)
    tau = rng.uniform(1e-7, 5e-7, (2, 32, 2))
    g = rng.uniform(0.1, 0.5, (2, 32, 2))
    kw = dict(sources=[{"name": "p", "l": -0.4, "m": 0.3, "flux_jy": 1.0}], noise_power=0.0, seed=1)
    clean = simulate_efield(xyz, FREQS, 50, **kw)
    raw = simulate_efield(xyz, FREQS, 50, cable_delay_s=tau, cable_gain=g, **kw)
    cal = np.exp(2j * np.pi * FREQS[:, None, None] * tau) / np.sqrt(g)
    np.testing.assert_allclose(raw * cal, clean, rtol=1e-12, atol=1e-13)
    with pytest.raises(ValueError, match="moveaxis"):
        simulate_efield(xyz, FREQS, 5, cable_delay_s=np.zeros((32, 2, 2)), **kw)


def test_with_lsl_station_cable_model():
    from bf_epic_blocks.station.offline import configure_offline
    configure_offline()
    pytest.importorskip("lsl")
    from bf_epic_blocks.station import load_station
    st = load_station("lwasv")
    f = np.array([74e6])
    kw = dict(sources=["CygA"], time="2024-07-01T06:00:00", location=st.location, noise_power=0.0, seed=4)
    clean = simulate_efield(st.xyz_m, f, 20, **kw)
    assert np.all(np.abs(clean) > 0)
    raw = simulate_efield(st.xyz_m, f, 20, cable_delay_s=np.moveaxis(st.cable_delay_s(f), -1, 0),
                          cable_gain=np.moveaxis(st.cable_gain(f), -1, 0), **kw)
    cal = raw * st.cable_weights(f)[None]
    good = ~st.flags
    np.testing.assert_allclose(cal[:, :, good], clean[:, :, good], rtol=1e-10, atol=1e-9)


def test_bad_inputs(xyz):
    src = [{"name": "p", "l": 0.0, "m": 0.0, "flux_jy": 1.0}]
    with pytest.raises(ValueError, match="xyz_m"):
        simulate_efield(xyz[:, :2], FREQS, 4, sources=src)
    with pytest.raises(ValueError, match="sigma"):
        simulate_efield(xyz, FREQS, 4, sources=src, sigma=0)
    with pytest.raises(ValueError, match="ntime"):
        simulate_efield(xyz, FREQS, 0, sources=src)
    with pytest.raises(ValueError, match="exactly one position pair"):
        resolve_source({"name": "x", "flux_jy": 1, "l": 0.1, "ra_deg": 3, "dec_deg": 4, "m": 0})
    with pytest.raises(ValueError, match="unknown key"):
        resolve_source({"name": "x", "flux": 1, "l": 0.1, "m": 0})
    with pytest.raises(ValueError, match="pattern"):
        simulate_efield(xyz, FREQS, 4, sources=src, pattern=np.ones((3, 3, 3)))


def test_pattern_scales_voltage(xyz):
    src = [{"name": "p", "l": 0.2, "m": 0.0, "flux_jy": 1.0}]
    a = simulate_efield(xyz, FREQS, 8, sources=src, noise_power=0.0)
    b = simulate_efield(xyz, FREQS, 8, sources=src, noise_power=0.0,
                        pattern=lambda l, m, f: np.full((len(f), len(l), 2), 0.5))
    np.testing.assert_allclose(b, 0.5 * a, rtol=1e-12)


def test_quantize_ci4_round_trip():
    rng = np.random.default_rng(0)
    x = 37.0 * (rng.standard_normal((200, 4, 16, 2)) + 1j * rng.standard_normal((200, 4, 16, 2)))
    packed, scale = quantize_ci4(x, rms_target=2.0)
    assert packed.dtype == np.uint8 and packed.shape == x.shape
    assert scale == pytest.approx(2.0 / 37.0, rel=0.02)
    q = unpack_ci4(packed, np.complex128)
    rms = np.sqrt(np.mean(q.real ** 2 + q.imag ** 2) / 2)
    assert rms == pytest.approx(2.0, rel=0.05)
    y = x * scale
    inside = (np.abs(y.real) < 7.5) & (y.real > -8.5) & (np.abs(y.imag) < 7.5) & (y.imag > -8.5)
    assert inside.mean() > 0.99
    err = q - y
    assert np.all(np.abs(err.real[inside]) <= 0.5 + 1e-12) and np.all(np.abs(err.imag[inside]) <= 0.5 + 1e-12)
    # fixed scale, by hand: 3.2-1.9j -> 3-2j -> 0x3E; clipping to 7 / -8
    p, s = quantize_ci4(np.array([3.2 - 1.9j, 100 + 0j, -100 - 100j]), scale=1.0)
    assert s == 1.0 and list(p) == [0x3E, 0x70, 0x88]
    np.testing.assert_array_equal(quantize_ci4(x, scale=scale)[0], packed)
    with pytest.raises(TypeError):
        quantize_ci4(np.ones(3))
