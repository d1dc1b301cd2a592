"""The sky model a calibration solves against: catalogue sources at the data's time, through a pattern.

:func:`sky_model` places the sources (names such as ``CygA`` and ``Sun``, or mappings, as
:func:`.catalogue.resolve_source` takes them) at one instant seen from the station (astropy AltAz),
evaluates their spectra on the channels and the antennas' voltage pattern in their directions, and
returns what :func:`bf_epic_blocks.imaging.skycal.model_covariance` takes. Sources below
``min_alt_deg`` are left out: near the horizon a point-source model and a short-dipole pattern are
both poor.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..conventions import SIGMA
from .catalogue import source_directions

__all__ = ["SkyModel", "sky_model", "diffuse_model"]

log = logging.getLogger(__name__)

#: bytes of phases :func:`diffuse_model` forms at once on a GPU (the phases, their weighted copy, its
#: conjugate and the GEMM's contiguous copy of its transpose: four arrays of channels x pixels x antennas)
DIFFUSE_CHUNK_BYTES = 256 * 2**20


@dataclass
class SkyModel:
    """Model sources at one instant.

    lmn : float64 (nsrc, 3) direction cosines (l East, m North, n Up).
    flux_pol : float64 (nchan, nsrc, npol) apparent flux per polarisation, (S / 2) |B_p|^2, Jy.
    names : the sources kept; alt_deg : (nsrc,) their altitudes; dropped : names left out (below
    ``min_alt_deg``); pattern : the pattern's name or None.
    """
    lmn: np.ndarray
    flux_pol: np.ndarray
    names: list
    alt_deg: np.ndarray
    dropped: list
    pattern: str | None

    def describe(self) -> str:
        if not self.names:
            return "no source above the horizon limit"
        return ", ".join(f"{n} (alt {a:.1f} deg)" for n, a in zip(self.names, self.alt_deg))

    def to_dict(self) -> dict:
        """JSON-able provenance: names, altitudes, mean apparent flux per pol."""
        return {"sources": list(self.names), "alt_deg": [round(float(a), 3) for a in self.alt_deg],
                "apparent_flux_jy": np.round(self.flux_pol.mean(axis=0), 3).tolist(),
                "dropped": list(self.dropped), "pattern": self.pattern}


def sky_model(sources, time, location, freq_hz, *, pattern=None, npol=2, min_alt_deg=10.0) -> SkyModel:
    """The model of ``sources`` at ``time`` (astropy Time or ISO UTC) from ``location`` (EarthLocation).

    pattern : None (isotropic) or a registered pattern name (``"dipole"``): the voltage pattern B_p
    in each source's direction; the apparent flux per pol is (S / 2) |B_p|^2.
    """
    from ..imaging.patterns import get_pattern
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    d = source_directions(sources, time, location)
    alt = np.degrees(np.asarray(d.alt, np.float64))
    keep = alt >= min_alt_deg
    dropped = list(d.dropped) + [n for n, k in zip(d.names, keep) if not k]
    srcs = [s for s, k in zip(d.sources, keep) if k]
    lmn = np.stack([np.asarray(d.l)[keep], np.asarray(d.m)[keep], np.asarray(d.n)[keep]], axis=1) \
        if keep.any() else np.zeros((0, 3))
    flux = np.stack([s.flux_at(f) for s in srcs], axis=1) if srcs else np.zeros((f.size, 0))   # (c, s)
    fp = np.repeat(flux[:, :, None] / 2.0, npol, axis=2)
    if pattern not in (None, "none") and srcs:
        b = np.asarray(get_pattern(pattern)(lmn[:, :2], f, npol))
        b = b[None] if b.ndim == 2 else b.reshape(-1, len(srcs), npol) if b.ndim == 3 else b[:, :, 0, :]
        fp = fp * np.abs(np.broadcast_to(b, fp.shape)) ** 2
    if dropped:
        log.debug("sky model: left out (below %.1f deg): %s", min_alt_deg, ", ".join(dropped))
    return SkyModel(lmn, fp, [s.name for s in srcs], alt[keep], dropped,
                    None if pattern in (None, "none") else pattern)


def diffuse_model(xyz_m, freq_hz, time, location, *, pattern=None, xp=np, dtype=None, chunk=64):
    """The analytic Galactic sky's covariance (:mod:`.diffuse`) as a model term, (nchan, npol, nant, nant)
    complex in the namespace ``xp``: what the solver fits with a free scale per channel and polarisation
    (:func:`bf_epic_blocks.imaging.skycal.solve_gains`, ``extra``), so that the emission a compact
    station sees on every baseline does not bias the gains. Pixels and baselines as
    :func:`.diffuse.diffuse_covariance` (no correlation beyond the array's core); the sums are complex
    GEMMs over the pixels where ``xp`` computes: :func:`.diffuse.diffuse_covariance` on the CPU, the same
    sums as CuPy GEMMs on a GPU (which makes a whole band's in well under a second). On a GPU the
    phases are formed at most ``chunk`` channels and :data:`DIFFUSE_CHUNK_BYTES` at a time, in one
    kernel from the float64 path (no float64 or complex128 intermediates): a whole band's model then
    needs its output and ~0.3 GB more, not the ~10 GB of whole-chunk temporaries."""
    from ..imaging.dft import _geometric_from_path
    from .diffuse import _resolve_grid, diffuse_covariance, diffuse_pixels
    if xp is np:
        return diffuse_covariance(xyz_m, freq_hz, time, location, pattern=pattern).astype(dtype or np.complex128)
    xyz = np.asarray(xyz_m, np.float64)
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    npix, bmax = _resolve_grid(xyz, f, None, None)
    lmn, flux, _ = diffuse_pixels(f, time, location, pattern=pattern, npix=npix)
    dtype = np.dtype(dtype or xp.complex64)
    nchan, npol, nant = f.size, flux.shape[1], xyz.shape[0]
    # exp(+2 pi i nu/c (r_a . s)) per (pixel, antenna): the geometric operator's kernel, exp(-SIGMA 2 pi i
    # nu/c path), of path -SIGMA (r_a . s)
    path = xp.asarray(-SIGMA * (lmn @ xyz.T))                                       # (npix, nant) metres
    precision = "fp64" if dtype == np.complex128 else "fp32"
    step = max(1, min(int(chunk), DIFFUSE_CHUNK_BYTES // (4 * lmn.shape[0] * nant * dtype.itemsize)))
    out = xp.empty((nchan, npol, nant, nant), dtype)
    for c0 in range(0, nchan, step):
        c1 = min(nchan, c0 + step)
        a = _geometric_from_path(xp, path, f[c0:c1], precision)                    # (c, npix, nant)
        for p in range(npol):
            amp = xp.asarray(np.sqrt(flux[c0:c1, p] / 2.0)).astype(a.real.dtype)       # (c, npix)
            m = a * amp[:, :, None]
            out[c0:c1, p] = xp.matmul(m.swapaxes(-1, -2), xp.conj(m))              # sum over pixels: a_i a_j^*
            del m
    del a
    d = np.sqrt(((xyz[:, None] - xyz[None]) ** 2).sum(-1))
    far = d > bmax
    np.fill_diagonal(far, False)
    out *= xp.asarray(~far).astype(out.real.dtype)
    return out
