"""The diffuse Galactic emission a station sees: an analytic model of the low-frequency sky, its
covariance across a station's antennas, and a few eigenmodes of it for the counter-based simulator.

Sky model (:func:`galactic_temperature_k`), rough and for simulation only
-------------------------------------------------------------------------
Brightness temperature, kelvin, at Galactic longitude ``l`` and latitude ``b``::

    T(l, b, nu) = [T_iso + f(l) (T_disk g(b; 3 deg) + T_thick g(b; 15 deg))] (nu / 74 MHz)^beta

* ``g(b; s) = exp(-b^2 / (2 s^2))``: a narrow disk (FWHM 7 deg) and a thick one (FWHM 35 deg).
* ``f(l) = 0.1 + 0.9 / (1 + (l / 40 deg)^2)`` (l wrapped to [-180, 180)): the plane peaks at the
  Galactic Centre, keeps ~30% of that near Cygnus (l = 80 deg) and ~15% towards the anticentre.
* T_iso = 1,600 K, T_disk = 17,000 K, T_thick = 6,400 K at 74 MHz: the coldest sky is ~1,600 K and
  the Galactic Centre 25,000 K.
* beta = -2.55, the spectral index EDGES measures for the diffuse sky (Mozdzen et al. 2017, MNRAS
  464, 4995; -2.5 to -2.6 over 50-200 MHz).

The numbers are chosen to put the model in the ballpark of the 45 MHz map of Guzmán et al. (2011,
A&A 525, A138) and of the 408 MHz map of Haslam et al. (1982) scaled with beta (x78 from 408 to 74
MHz: a cold 15-20 K patch -> ~1,200-1,600 K, the inner plane's 300-400 K -> 23,000-31,000 K).
The model is smooth and symmetric: it has no North Polar Spur, Loop I, HII-region absorption or
discrete sources (the point sources are :mod:`.catalogue`'s), and the CMB (2.7 K) is left out. Read
any value as right to tens of per cent.

Covariance (:func:`diffuse_covariance`)
---------------------------------------
Per polarisation p, channel frequency nu, antennas a and b (docs/CONVENTIONS.md, sigma = +1)::

    R[c, p, a, b] = sum_pix (S_pix / 2) |B_p(pix)|^2 exp(+2 pi i nu s_pix . (r_a - r_b) / c0)

with ``S_pix = 2 k T Omega_pix / lambda^2`` (Rayleigh-Jeans) in Jy (1e-26 W m^-2 Hz^-1): the same
units as the simulator's point sources, one of flux S giving S/2 per pol (:mod:`.efield`). The
pixels tile the direction cosines (l East, m North) above the horizon with an ``npix x npix`` grid of
cells of side dl = 2 / npix; each pixel's solid angle is the exact integral of dOmega = dl dm / n over
its cell's part inside the unit circle, and its direction is that part's centroid (weighted by 1/n).
So the lowest ~7 deg of sky, which the grid's outer ring of cells holds (dOmega diverges as 1/n at the
horizon), keeps its solid angle: the pixels' solid angles sum to 2 pi to rounding, and a uniform sky
gives the closed form 2 pi sin(kb) / (kb) (per unit brightness, horizontal baseline b) to 4e-4 of the
zero-spacing value with npix = 112 (1e-4 with 256) on baselines up to 25 m.

Which baselines it resolves: a grid of step dl samples fringes of baselines up to
``u_max = npix / 4`` wavelengths with their aliases falling beyond u_max, where a smooth sky's
visibility is small. The default ``npix`` resolves the array's core (:func:`core_baseline_m`: the
longest baseline among stands within 3x the median stand distance of the array's middle; 110 m at
LWA-SV, npix = 112 at 74 MHz). Longer baselines (LWA-SV's outrigger, ~300 m West of the core) get no
diffuse correlation (R_ab = 0 for |r_a - r_b| > ``max_baseline_m``): a smooth sky's visibility there
is below ~1% of the antennas' diffuse power, and large scales dominate what the diffuse sky does to
a station's data. Their own (a = b) power is kept.

Eigenmodes (:func:`diffuse_weights`)
------------------------------------
The simulator (:mod:`.fastsim`) drives each weight column k with its own complex normal of variance
1 per real part, so columns W with ``sum_k 2 W[c,k,a,p] conj(W[c,k,b,p]) = R[c,p,a,b]`` reproduce the
covariance. ``W = V sqrt(lambda / 2)`` for the top ``nmode`` eigenpairs of R per channel and pol
(the best rank-nmode approximation) keeps its largest part; the rest is left out, and the fraction
of the trace kept is returned and logged. A station's antennas stand more than half a wavelength
apart, so they see most of the diffuse sky's power uncorrelated: the covariance is far from low
rank (at LWA-SV its largest eigenvalue is 4.3 times the mean) and 32 modes keep about a quarter of
the power (18-27% with the dipole pattern; 16 modes 15%, 128 modes 66%), in the brightest, largest
structures (the Galactic Centre and the plane). Each input's simulated diffuse power is that
fraction of the model's, and its correlations on baselines are those of the kept modes.

Cost: for LWA-SV (256 stands, 16 channels, npix = 112: 10,000 pixels) ~1.1 s on two CPU cores
isotropic, ~1.5 s with the dipole pattern (one complex64 Hermitian rank-k update per channel and
pol, 25-30 ms each, and a partial eigendecomposition, ~8 ms each).
"""
from __future__ import annotations

import logging
import math

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S

__all__ = ["galactic_temperature_k", "sky_pixels", "diffuse_pixels", "pixel_covariance", "diffuse_covariance",
           "diffuse_weights", "core_baseline_m", "default_npix", "BETA", "REF_FREQ_HZ",
           "T_ISO_K", "T_DISK_K", "T_THICK_K"]

log = logging.getLogger(__name__)

BOLTZMANN_J_K = 1.380649e-23
JY = 1e-26                  # W m^-2 Hz^-1
REF_FREQ_HZ = 74e6
BETA = -2.55
T_ISO_K = 1600.0
T_DISK_K = 17000.0
T_THICK_K = 6400.0
DISK_SIGMA_DEG = 3.0
THICK_SIGMA_DEG = 15.0
LON_SCALE_DEG = 40.0
LON_FLOOR = 0.1


def galactic_temperature_k(glon_deg, glat_deg, freq_hz):
    """Brightness temperature (K) of the analytic sky model (module docstring).

    Parameters
    ----------
    glon_deg, glat_deg : array_like
        Galactic longitude and latitude, degrees.
    freq_hz : array_like
        Frequency, Hz.

    Returns
    -------
    float64 array: the three arguments broadcast together (NumPy rules).
    """
    lon = (np.asarray(glon_deg, np.float64) + 180.0) % 360.0 - 180.0
    lat = np.asarray(glat_deg, np.float64)
    f = np.asarray(freq_hz, np.float64)
    prof = LON_FLOOR + (1.0 - LON_FLOOR) / (1.0 + (lon / LON_SCALE_DEG) ** 2)
    plane = T_DISK_K * np.exp(-0.5 * (lat / DISK_SIGMA_DEG) ** 2) + T_THICK_K * np.exp(
        -0.5 * (lat / THICK_SIGMA_DEG) ** 2)
    return (T_ISO_K + prof * plane) * (f / REF_FREQ_HZ) ** BETA


# ------------------------------------------------------------------ the pixels
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(16)


def sky_pixels(npix: int):
    """The cells of an ``npix x npix`` grid over -1 <= l, m <= 1 that see sky (module docstring).

    Returns
    -------
    l, m, n : (nkeep,) float64
        Each cell's direction: the centroid, weighted by 1/n, of its part inside the unit circle;
        n >= 0 (Up).
    omega : (nkeep,) float64
        Its solid angle, sr: the integral of dl dm / n over that part (they sum to 2 pi).
    ij : (nkeep, 2) int
        The cell's (row along m, column along l) index in the grid.
    """
    npix = int(npix)
    if npix < 2:
        raise ValueError(f"npix: expected an integer >= 2, got {npix!r}")
    dl = 2.0 / npix
    edges = -1.0 + dl * np.arange(npix + 1)
    # l at the Gauss-Legendre nodes of each column: (npix, q)
    lq = edges[:-1, None] + dl * (0.5 + 0.5 * _GL_NODES[None, :])
    wq = 0.5 * dl * _GL_WEIGHTS
    a = np.sqrt(np.clip((1.0 - lq) * (1.0 + lq), 0.0, None))                # half-chord at each l
    safe = np.where(a > 0, a, 1.0)
    # the inner integrals over m in closed form, per row's edges: (npix_m + 1, npix_l, q)
    mc = np.clip(edges[:, None, None], -a[None], a[None])
    asin = np.arcsin(np.clip(mc / safe[None], -1.0, 1.0)) * (a[None] > 0)
    root = np.sqrt(np.clip(a[None] ** 2 - mc ** 2, 0.0, None))
    d_asin = asin[1:] - asin[:-1]                                           # int dm / n over the row
    d_root = root[:-1] - root[1:]                                           # int m dm / n
    omega = np.einsum("jiq,q->ji", d_asin, wq)                              # (row m, column l)
    lmom = np.einsum("jiq,iq,q->ji", d_asin, lq, wq)
    mmom = np.einsum("jiq,q->ji", d_root, wq)
    keep = omega > 1e-14
    j, i = np.nonzero(keep)
    om = omega[keep]
    l, m = lmom[keep] / om, mmom[keep] / om
    rho = np.hypot(l, m)
    n = np.sqrt(np.clip((1.0 - rho) * (1.0 + rho), 0.0, None))
    return l, m, n, om, np.stack([j, i], axis=1)


def core_baseline_m(xyz_m) -> float:
    """The longest baseline (m) among the stands of the array's core: those within 3x the median
    horizontal distance of the array's median position (LWA-SV: 110 m, its outrigger left out)."""
    xyz = np.asarray(xyz_m, np.float64)
    mid = np.median(xyz[:, :2], axis=0)
    r = np.hypot(*(xyz[:, :2] - mid).T)
    core = xyz[r <= 3.0 * max(np.median(r), 1e-9)]
    if len(core) < 2:
        return 0.0
    d = core[:, None, :] - core[None, :, :]
    return float(np.sqrt(np.max(np.sum(d * d, axis=-1))))


def default_npix(max_baseline_m: float, freq_hz) -> int:
    """The grid size that resolves baselines up to ``max_baseline_m`` at the highest of ``freq_hz``:
    u_max = npix / 4 wavelengths (module docstring), rounded up to a multiple of 8, at least 32."""
    lam = SPEED_OF_LIGHT_M_S / float(np.max(freq_hz))
    need = 4.0 * float(max_baseline_m) / lam
    return int(max(32, 8 * math.ceil(need / 8.0)))


def _altaz_to_galactic(l, m, n, time, location):
    """Galactic (lon, lat) degrees of directions (l, m, n) seen from ``location`` at ``time``
    (astropy AltAz, no refraction; offline IERS as :mod:`.catalogue` uses)."""
    import astropy.units as u
    from astropy.coordinates import AltAz, SkyCoord

    from .catalogue import _iers_offline, as_location, as_time
    alt = np.degrees(np.arctan2(n, np.hypot(l, m)))
    az = np.degrees(np.arctan2(l, m)) % 360.0
    frame = AltAz(obstime=as_time(time), location=as_location(location))
    with _iers_offline():
        g = SkyCoord(az=az * u.deg, alt=alt * u.deg, frame=frame).galactic
    return np.asarray(g.l.deg), np.asarray(g.b.deg)


def _pattern_power(pattern, l, m, freq_hz):
    """|B_p|^2, float64 broadcastable to (nchan, npol=2, npix): 1 for ``pattern=None``, else the named
    (or callable) voltage pattern of :mod:`..imaging.patterns`, the same for every antenna."""
    if pattern is None or pattern == "none":
        return np.ones((1, 2, 1))
    from ..imaging.patterns import pattern_array
    b = np.asarray(pattern_array(pattern, np.stack([l, m], axis=1), np.asarray(freq_hz, np.float64), 2))
    if b.shape[2] != 1:
        raise ValueError("pattern: the diffuse sky needs one voltage pattern for every antenna, got one per "
                         f"antenna (shape {b.shape})")
    p = np.abs(b[:, :, 0, :]) ** 2                                           # (nchan|1, npix, npol|1)
    return np.moveaxis(np.broadcast_to(p, p.shape[:2] + (2,)), -1, 1)      # (nchan|1, 2, npix)


def diffuse_pixels(freq_hz, time, location, *, pattern=None, scale: float = 1.0, npix: int = 112, sky=None):
    """The model's emission above the horizon on the pixels of :func:`sky_pixels`.

    Parameters
    ----------
    freq_hz : (nchan,) Hz.
    time, location : astropy Time (or ISO UTC string) and EarthLocation (or (lon_deg, lat_deg, h_m)).
    pattern : None (isotropic), a pattern name of :mod:`..imaging.patterns` ("dipole") or a pattern
        function: the antennas' voltage pattern B_p(l, m).
    scale : factor on the temperatures.
    npix : cells per side of the grid.
    sky : None (:func:`galactic_temperature_k`) or a function ``(glon_deg, glat_deg, freq_hz) -> T``
        of the same form (a test's uniform sky).

    Returns
    -------
    lmn : (npix_kept, 3) float64 directions (l East, m North, n Up).
    flux : (nchan, npol=2, npix_kept) float64: each pixel's flux density (Jy) times |B_p|^2.
    temp : (nchan, npix_kept) float64: the brightness temperature (K), scale applied, no pattern.
    """
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    if not (np.isfinite(scale) and scale >= 0):
        raise ValueError(f"scale: expected a finite number >= 0, got {scale!r}")
    l, m, n, om, _ = sky_pixels(npix)
    glon, glat = _altaz_to_galactic(l, m, n, time, location)
    temp = scale * np.asarray((sky or galactic_temperature_k)(glon[None], glat[None], f[:, None]), np.float64)
    temp = np.broadcast_to(temp, (f.size, l.size))
    lam2 = (SPEED_OF_LIGHT_M_S / f) ** 2
    s = (2.0 * BOLTZMANN_J_K / JY) * temp * om[None] / lam2[:, None]       # Jy, (nchan, npix)
    flux = s[:, None, :] * _pattern_power(pattern, l, m, f)
    return np.stack([l, m, n], axis=1), flux, temp


def pixel_covariance(xyz_m, freq_hz, lmn, flux, *, max_baseline_m=None):
    """Covariance of incoherent unpolarised pixels across the antennas, per channel and pol.

    ``R[c, p, a, b] = sum_k flux[c, p, k] / 2 exp(+2 pi i nu_c s_k . (r_a - r_b) / c0)``, zero where
    ``|r_a - r_b| > max_baseline_m`` (a != b). Phases formed in float64 cycles, then float32 cos and sin
    (~3e-7 rad); sums in complex64 (cherk): relative error ~1e-6 of the diagonal.

    Parameters
    ----------
    xyz_m : (nant, 3) East, North, Up metres.
    freq_hz : (nchan,) Hz.
    lmn : (npix, 3) direction cosines.
    flux : (nchan, npol, npix) flux density per pixel (Jy), pattern included; >= 0.
    max_baseline_m : None (every baseline) or the longest baseline given correlation.

    Returns
    -------
    complex128 (nchan, npol, nant, nant), Hermitian in (a, b).
    """
    from scipy.linalg.blas import cherk
    xyz = np.asarray(xyz_m, np.float64)
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    s = np.asarray(lmn, np.float64)
    flux = np.asarray(flux, np.float64)
    nchan, npol, nant = f.size, flux.shape[1], xyz.shape[0]
    if flux.shape != (nchan, npol, s.shape[0]):
        raise ValueError(f"flux: expected shape (nchan, npol, npix) = {(nchan, npol, s.shape[0])}, got {flux.shape}")
    if np.any(flux < 0):
        raise ValueError("flux: expected values >= 0")
    path = xyz @ s.T                                                         # (nant, npix) metres
    amp = np.sqrt(flux / 2.0).astype(np.float32)
    same_pols = npol == 2 and np.array_equal(amp[:, 0], amp[:, 1])
    out = np.zeros((nchan, npol, nant, nant), np.complex128)
    a = np.empty(path.shape, np.complex64)
    m = np.empty_like(a)
    cyc = np.empty_like(path)
    for c in range(nchan):
        # cycles in float64, reduced to [-1/2, 1/2] before the float32 cos and sin (phase error ~3e-7 rad)
        np.multiply(path, f[c] / SPEED_OF_LIGHT_M_S, out=cyc)
        cyc -= np.round(cyc)
        ph = (2.0 * np.pi * cyc).astype(np.float32)
        a.real, a.imag = np.cos(ph), np.sin(ph)
        for p in range(npol):
            if p and same_pols:
                out[c, p] = out[c, 0]
                continue
            np.multiply(a, amp[c, p][None, :], out=m)
            up = cherk(1.0, m)                                               # upper triangle of M M^H
            full = out[c, p]
            full[...] = np.triu(up)
            full += np.triu(up, 1).conj().T
    if max_baseline_m is not None:
        d = np.sqrt(np.sum((xyz[:, None, :] - xyz[None, :, :]) ** 2, axis=-1))
        far = d > float(max_baseline_m)
        np.fill_diagonal(far, False)
        out[:, :, far] = 0.0
    return out


def _resolve_grid(xyz, f, npix, max_baseline_m):
    if max_baseline_m is None:
        max_baseline_m = core_baseline_m(xyz)
    if npix is None:
        npix = default_npix(max_baseline_m, f)
    return int(npix), float(max_baseline_m)


def diffuse_covariance(xyz_m, freq_hz, time, location, *, pattern=None, scale: float = 1.0, npix=None,
                       max_baseline_m=None, sky=None):
    """Covariance of the diffuse sky across the antennas (module docstring).

    Parameters
    ----------
    xyz_m : (nant, 3) East, North, Up metres.
    freq_hz : (nchan,) channel frequencies, Hz.
    time, location : astropy Time (or ISO UTC string) and EarthLocation (or (lon, lat, h)).
    pattern : None (isotropic) or a pattern name ("dipole") or function (:mod:`..imaging.patterns`).
    scale : factor on the model's temperatures (0: no diffuse sky).
    npix : cells per side of the (l, m) grid; None: :func:`default_npix` for ``max_baseline_m``.
    max_baseline_m : longest baseline given diffuse correlation; None: :func:`core_baseline_m`.
    sky : None (the Galactic model) or a function ``(glon_deg, glat_deg, freq_hz) -> T_K``.

    Returns
    -------
    complex128 (nchan, npol=2, nant, nant): R[c, p, a, b] in Jy (a point source of flux S gives S/2
    per pol), Hermitian in (a, b).
    """
    xyz = np.asarray(xyz_m, np.float64)
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    npix, bmax = _resolve_grid(xyz, f, npix, max_baseline_m)
    lmn, flux, _ = diffuse_pixels(f, time, location, pattern=pattern, scale=scale, npix=npix, sky=sky)
    return pixel_covariance(xyz, f, lmn, flux, max_baseline_m=bmax)


def diffuse_weights(xyz_m, freq_hz, time, location, *, pattern=None, scale: float = 1.0, nmode: int = 32,
                    npix=None, max_baseline_m=None, sky=None, return_fraction: bool = False):
    """Simulator columns for the diffuse sky: the top ``nmode`` eigenmodes of its covariance.

    Parameters
    ----------
    As :func:`diffuse_covariance`, and
    nmode : int >= 1, columns per channel (padded with zeros where nant < nmode).
    return_fraction : also return the fraction of the diffuse power the modes keep.

    Returns
    -------
    W : complex128 (nchan, nmode, nant, npol=2), with ``sum_k 2 W[c,k,a,p] conj(W[c,k,b,p])`` the
        best rank-nmode approximation of R[c, p, a, b] (fastsim's columns: a complex normal of
        variance 1 per real part drives each).
    fraction : float64 (nchan, npol), sum of the kept eigenvalues / trace(R) (with return_fraction).
    """
    from scipy.linalg import eigh
    nmode = int(nmode)
    if nmode < 1:
        raise ValueError(f"nmode: expected an integer >= 1, got {nmode!r}")
    r = diffuse_covariance(xyz_m, freq_hz, time, location, pattern=pattern, scale=scale, npix=npix,
                           max_baseline_m=max_baseline_m, sky=sky)
    nchan, npol, nant, _ = r.shape
    k = min(nmode, nant)
    w = np.zeros((nchan, nmode, nant, npol), np.complex128)
    frac = np.zeros((nchan, npol))
    for c in range(nchan):
        for p in range(npol):
            tr = float(np.trace(r[c, p]).real)
            if tr <= 0:
                continue
            lam, vec = eigh(r[c, p], subset_by_index=[nant - k, nant - 1], driver="evr")
            lam = np.clip(lam[::-1], 0.0, None)
            w[c, :k, :, p] = (vec[:, ::-1] * np.sqrt(lam / 2.0)).T
            frac[c, p] = lam.sum() / tr
    log.info("diffuse sky: %d modes keep %.0f-%.0f%% of its power (channels and pols)", nmode,
             100 * frac.min(), 100 * frac.max())
    return (w, frac) if return_fraction else w
