"""The diffuse Galactic sky (sky.diffuse) against independent truth: the model's temperatures, the
pixels' solid angles, the covariance against a float64 sum written here over hand-placed pixels and
against the closed form of a uniform sky (2 pi sin(kb)/(kb) for a horizontal baseline), the
Galactic Centre where astropy puts it, the eigenmodes against the covariance, and the time it takes
for LWA-SV's 256 stands and 16 channels."""
import time

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import AltAz, EarthLocation, SkyCoord
from astropy.time import Time

from bf_epic_blocks.sky import diffuse

C = 299792458.0
K_B = 1.380649e-23
LWASV = EarthLocation.from_geodetic(lon=-106.885783 * u.deg, lat=34.348358 * u.deg, height=1477.8 * u.m)
GC_UP = "2024-06-01T08:15:00"      # the Galactic Centre near its transit at LWA-SV (alt ~27 deg)


def test_model_temperatures_and_spectrum():
    lon, lat = np.meshgrid(np.arange(-180, 180, 0.5), np.arange(-90, 90.01, 0.5))
    t = diffuse.galactic_temperature_k(lon, lat, 74e6)
    assert 1500 <= t.min() <= 2000 and 20000 <= t.max() <= 30000
    assert diffuse.galactic_temperature_k(0, 0, 74e6) == t.max()                  # the peak: the Galactic Centre
    assert diffuse.galactic_temperature_k(80, 0, 74e6) > 1.5 * diffuse.galactic_temperature_k(180, 0, 74e6)
    ratio = diffuse.galactic_temperature_k(30, 5, 148e6) / diffuse.galactic_temperature_k(30, 5, 74e6)
    assert ratio == pytest.approx(2 ** -2.55, rel=1e-12)
    assert diffuse.galactic_temperature_k(np.zeros(3), 0, np.array([[50e6], [74e6]])).shape == (2, 3)


def test_pixels_tile_the_hemisphere():
    for npix in (16, 112):
        l, m, n, om, ij = diffuse.sky_pixels(npix)
        assert om.sum() == pytest.approx(2 * np.pi, rel=1e-12)
        assert np.all(n >= 0) and np.allclose(l ** 2 + m ** 2 + n ** 2, 1)
        dl = 2.0 / npix
        centre = np.c_[-1 + dl * (ij[:, 1] + 0.5), -1 + dl * (ij[:, 0] + 0.5)]
        inner = np.hypot(*(np.abs(centre) + dl / 2).T) < 0.9                      # whole cells well inside
        # dOmega = dl dm / n, to the midpoint rule's O(dl^2) (the 1/n weight's curvature)
        assert np.allclose(om[inner], dl * dl / n[inner], rtol=2 * dl * dl, atol=0)
        assert np.allclose(np.c_[l, m][inner], centre[inner], atol=dl * dl)


def brute_covariance(xyz, freq, lmn, flux):
    """float64 loops: R[c, p, a, b] = sum_k flux[c, p, k] / 2 exp(+2 pi i nu s_k . (r_a - r_b) / c0)."""
    nchan, npol, npix = flux.shape
    out = np.zeros((nchan, npol, len(xyz), len(xyz)), np.complex128)
    for c in range(nchan):
        for p in range(npol):
            for k in range(npix):
                for a in range(len(xyz)):
                    for b in range(len(xyz)):
                        out[c, p, a, b] += flux[c, p, k] / 2 * np.exp(
                            2j * np.pi * freq[c] / C * np.dot(lmn[k], xyz[a] - xyz[b]))
    return out


def test_pixel_covariance_against_a_brute_force_sum():
    rng = np.random.default_rng(3)
    xyz = np.c_[rng.uniform(-40, 40, (7, 2)), rng.uniform(-1, 1, 7)]
    xyz[6] = [-290.0, 5.0, 10.0]                                                  # an outrigger
    freq = np.array([60e6, 74e6, 74.3e6])                                        # unevenly spaced
    l, m = np.array([0.1, -0.7, 0.0, 0.999, -0.2]), np.array([0.3, 0.2, -0.99, 0.0, -0.5])
    lmn = np.c_[l, m, np.sqrt(np.clip(1 - l * l - m * m, 0, None))]
    flux = rng.uniform(100, 1000, (3, 2, 5))
    want = brute_covariance(xyz, freq, lmn, flux)
    got = diffuse.pixel_covariance(xyz, freq, lmn, flux)
    scale = np.max(np.abs(want))
    assert got.shape == (3, 2, 7, 7) and got.dtype == np.complex128
    assert np.max(np.abs(got - want)) / scale < 2e-6
    cut = diffuse.pixel_covariance(xyz, freq, lmn, flux, max_baseline_m=150.0)
    assert np.all(cut[:, :, 6, :6] == 0) and np.all(cut[:, :, :6, 6] == 0)
    assert np.max(np.abs(cut[:, :, :6, :6] - want[:, :, :6, :6])) / scale < 2e-6
    assert np.allclose(cut[:, :, 6, 6], want[:, :, 6, 6], rtol=2e-6)


def test_uniform_sky_gives_the_sinc():
    """An isotropic sky of brightness T over the hemisphere, isotropic antennas: per pol
    R_ab = (k T / lambda^2) 2 pi sin(k b) / (k b) for a horizontal baseline b (the half of the whole
    sphere's 4 pi sinc that lies above the horizon), in Jy. The (l, m) grid's cells hold their exact
    solid angles, so R_aa is exact; R_ab holds to 1e-3 of R_aa on baselines the grid resolves."""
    T, nu = 3000.0, 74e6
    lam = C / nu
    b = np.r_[0.0, np.linspace(0.5, 25.0, 30)]
    ang = np.radians(37.0)
    xyz = np.c_[b * np.cos(ang), b * np.sin(ang), np.zeros_like(b)]
    r = diffuse.diffuse_covariance(xyz, [nu], GC_UP, LWASV, sky=lambda gl, gb, f: np.full(np.broadcast(gl, gb, f).shape, T),
                                   npix=112, max_baseline_m=None)
    r0 = K_B * T / lam ** 2 / 1e-26 * 2 * np.pi
    kb = 2 * np.pi * b / lam
    want = r0 * np.sinc(kb / np.pi)
    assert r[0, 0, 0, 0].real == pytest.approx(r0, rel=1e-5)
    err = np.abs(r[0, :, 0, :] - want[None]) / r0
    assert err.max() < 1e-3, err.max()
    assert np.allclose(r[0, 0], r[0, 1])                                           # isotropic: the pols alike


def test_dipole_pattern_weights_the_pixels():
    lmn, iso, _ = diffuse.diffuse_pixels([74e6], GC_UP, LWASV, npix=32)
    _, dip, _ = diffuse.diffuse_pixels([74e6], GC_UP, LWASV, npix=32, pattern="dipole")
    assert np.allclose(dip[0, 0], iso[0, 0] * (1 - lmn[:, 1] ** 2))               # X: N-S dipole
    assert np.allclose(dip[0, 1], iso[0, 1] * (1 - lmn[:, 0] ** 2))               # Y: E-W dipole


def test_galactic_centre_is_where_astropy_puts_it():
    lmn, _, temp = diffuse.diffuse_pixels([74e6], GC_UP, LWASV, npix=256)
    k = np.argmax(temp[0])
    aa = SkyCoord(l=0 * u.deg, b=0 * u.deg, frame="galactic").transform_to(
        AltAz(obstime=Time(GC_UP), location=LWASV))
    gc = np.array([np.cos(aa.alt.rad) * np.sin(aa.az.rad), np.cos(aa.alt.rad) * np.cos(aa.az.rad), np.sin(aa.alt.rad)])
    assert aa.alt.deg > 20
    sep = np.degrees(np.arccos(np.clip(lmn[k] @ gc, -1, 1)))
    assert sep < 1.5, sep                                                          # cells there: ~1 deg in alt
    assert temp[0, k] > 20000


def test_modes_reproduce_the_covariance():
    rng = np.random.default_rng(9)
    xyz = np.c_[rng.uniform(-20, 20, (20, 2)), rng.uniform(-0.5, 0.5, 20)]
    freq = 74e6 + 25e3 * np.arange(2)
    r = diffuse.diffuse_covariance(xyz, freq, GC_UP, LWASV, pattern="dipole", npix=64)
    w, frac = diffuse.diffuse_weights(xyz, freq, GC_UP, LWASV, pattern="dipole", npix=64, nmode=24,
                                      return_fraction=True)
    assert w.shape == (2, 24, 20, 2) and np.all(w[:, 20:] == 0)                    # nmode > nant: zero columns
    full = 2 * np.einsum("ckap,ckbp->cpab", w, w.conj())
    assert np.max(np.abs(full - r)) / np.max(np.abs(r)) < 1e-5 and np.allclose(frac, 1, atol=1e-5)
    w6, frac6 = diffuse.diffuse_weights(xyz, freq, GC_UP, LWASV, pattern="dipole", npix=64, nmode=6,
                                        return_fraction=True)
    for c in range(2):
        for p in range(2):
            lam, vec = np.linalg.eigh(r[c, p])
            best = (vec[:, -6:] * lam[-6:]) @ vec[:, -6:].conj().T                # the best rank-6 approximation
            got = 2 * w6[c, :, :, p].T @ w6[c, :, :, p].conj()
            assert np.max(np.abs(got - best)) / lam[-1] < 1e-5
            assert frac6[c, p] == pytest.approx(lam[-6:].sum() / lam.sum(), rel=1e-5)


def test_lwasv_modes_take_a_second_or_two():
    """16 channels x 256 stands (LWA-SV's layout when LSL is here, else one like it): the grid the
    core needs (112 cells a side at 74 MHz), its covariance and 32 modes per channel and pol."""
    try:
        from bf_epic_blocks.station.offline import configure_offline
        configure_offline()
        from bf_epic_blocks.station.tables import load_station
        xyz = load_station("lwasv").xyz_m
    except Exception:
        rng = np.random.default_rng(1)
        xyz = np.c_[rng.uniform(-50, 50, (256, 2)), rng.uniform(-1, 1, 256)]
        xyz[-1] = [-293.3, 9.5, 10.2]
    freq = 74e6 + 25e3 * np.arange(16)
    assert diffuse.default_npix(diffuse.core_baseline_m(xyz), freq) <= 120
    t = time.perf_counter()
    w, frac = diffuse.diffuse_weights(xyz, freq, GC_UP, LWASV, pattern="dipole", return_fraction=True)
    dt = time.perf_counter() - t
    print(f"diffuse_weights, 16 channels x 256 stands, dipole: {dt:.2f} s; modes keep "
          f"{frac.min():.1%}-{frac.max():.1%} of the power")
    assert w.shape == (16, 32, 256, 2) and np.all((0 < frac) & (frac < 1))
    assert dt < 60      # ~1.5 s on 2 idle cores; the bound only catches a pathology on a shared machine
