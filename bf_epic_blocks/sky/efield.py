"""Simulated-sky antenna electric fields (the F-engine output an LWA station would record).

Data model (docs/CONVENTIONS.md, PHYSICS.md), for channel frequency nu, antenna a at r_a (East,
North, Up metres) and polarisation p (0 = X = N-S, 1 = Y = E-W)::

    X[t, c, a, p] = sqrt(G[c, a, p]) exp(-2 pi i nu_c tau[c, a, p])
                    * sum_s B[c, s, p] E_s,p(t, c) exp(sigma 2 pi i nu_c (s_hat . r_a) / c0)
                    + noise[t, c, a, p]

* Each source s is unpolarised: E_s,X and E_s,Y are independent circular complex Gaussians, each of
  power S_s(nu) / 2, so that I = XX + YY = S_s (flux density units, "Jy", no further scale) in an
  image normalised as the imaging operator is (a unit point source gives 1). Samples are
  independent across time, channel and source.
* ``S_s(nu) = flux_jy * (nu / ref_freq_hz) ** spectral_index`` (ref 74 MHz for the catalogue).
* sigma = +1 (LSL convention) by default; sigma = -1 is there to demonstrate the mirrored sky.
* Cable terms are optional: ``cable_delay_s`` tau and ``cable_gain`` G (power), each broadcastable to
  (nchan, nant, npol). :meth:`StationTable.cable_delay_s` returns (nstand, 2, nchan): pass
  ``np.moveaxis(station.cable_delay_s(f), -1, 0)`` (same for the gain).
* ``noise``: independent circular complex Gaussian per (t, c, a, p) of power ``noise_power``
  (same units), added after the cable terms as in PHYSICS.md.
* ``B``: optional antenna voltage pattern, identical for all antennas (default 1).
* The sky is frozen: source directions are computed once, at ``time``, and held for the whole
  simulated stretch (1024 samples at 25 kHz are 41 ms, during which the sky turns by 0.0002 deg).

Transients (``transients=[{ra_deg, dec_deg, start_s, duration_s, flux_jy, dm}, ...]``, or az_deg/alt_deg
or l/m instead of ra/dec; optional ``name``, ``spectral_index``): point sources that shine only for
``duration_s``, unpolarised with flux ``flux_jy`` like the steady ones, and dispersed: in channel c
the burst is on for samples whose start time t satisfies
``start_s + delay_c <= t < start_s + delay_c + duration_s``, with
``delay_c = 4.149 ms * dm * ((f_c/GHz)^-2 - (f_max/GHz)^-2)`` (f_max = the highest channel: ``start_s``
is the arrival time at the top of the band; :func:`bf_epic_blocks.conventions.dispersion_delay_s`).
Sample k starts at ``t0_s + k * sample_time_s`` (``sample_time_s`` defaults to 1 / channel spacing).

Randomness: ``numpy.random.SeedSequence(seed)`` spawns one stream for the source signals, one for
the noise and one for the transients, so a given seed gives the same sky signals whatever
``noise_power`` or the transients are.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S
from ..conventions import dispersion_delay_s
from .catalogue import source_directions

__all__ = ["simulate_efield", "quantize_ci4"]

log = logging.getLogger(__name__)


def cable_factor(cable_delay_s, cable_gain, freq_hz, nchan, nant, npol):
    """sqrt(G) exp(-2 pi i nu tau), complex128 (nchan, nant, npol): the cable terms the data model applies
    to the sky signal (each argument broadcastable to that shape; None for none)."""
    # Deliberately not imaging.calibration.cable_weights inverted: the simulator corrupts the
    # voltages from the data model on its own, so tests of CalFoldBlock check against independent code.
    shape = (nchan, nant, npol)
    hint = "pass np.moveaxis(station.cable_delay_s(freq_hz), -1, 0) (station order is (nstand, 2, nchan))"
    out = np.ones(shape, np.complex128)
    if cable_delay_s is not None:
        tau = np.asarray(cable_delay_s, np.float64)
        try:
            tau = np.broadcast_to(tau, shape)
        except ValueError:
            raise ValueError(f"cable_delay_s: expected shape broadcastable to (nchan, nant, npol) = {shape}, "
                             f"got {tau.shape}; {hint}") from None
        out *= np.exp(-2j * np.pi * freq_hz[:, None, None] * tau)
    if cable_gain is not None:
        g = np.asarray(cable_gain, np.float64)
        try:
            g = np.broadcast_to(g, shape)
        except ValueError:
            raise ValueError(f"cable_gain: expected shape broadcastable to (nchan, nant, npol) = {shape}, "
                             f"got {g.shape}; {hint.replace('delay_s', 'gain')}") from None
        if np.any(g < 0) or not np.all(np.isfinite(g)):
            raise ValueError("cable_gain: expected finite power gains >= 0")
        out *= np.sqrt(g)
    return out


def simulate_efield(xyz_m, freq_hz, ntime: int, *, sources, time=None, location=None,
                    cable_delay_s=None, cable_gain=None, noise_power: float = 1.0, seed: int = 0,
                    sigma: int = +1, pattern=None, return_directions: bool = False, transients=None,
                    t0_s: float = 0.0, sample_time_s: float | None = None):
    """Simulated antenna voltages, complex128 (ntime, nchan, nant, npol=2). See the module docstring.

    Parameters
    ----------
    xyz_m : (nant, 3) East, North, Up metres (one row per stand; both pols share it).
    freq_hz : (nchan,) channel frequencies, Hz.
    ntime : number of time samples.
    sources : names / dicts / :class:`Source` (see :func:`resolve_source`); below-horizon ones dropped.
    time, location : astropy Time (or ISO UTC string) and EarthLocation, for ICRS sources.
    cable_delay_s, cable_gain : tau (s) and power gain G, broadcastable to (nchan, nant, npol), or None.
    noise_power : receiver noise power per (antenna, pol, channel, sample), >= 0 (flux units).
    seed : random seed (deterministic output).
    sigma : geometric sign, +1 (LSL, default) or -1.
    pattern : None (isotropic), an array broadcastable to (nchan, nsrc, npol) of voltage gains for the
        kept sources, or a callable ``pattern(l, m, freq_hz) -> that array``.
    return_directions : also return the :class:`SourceDirections` used.
    transients, t0_s, sample_time_s : dispersed bursts and the time of sample 0 on their clock (s)
        (module docstring); a callable ``pattern`` applies to them too.
    """
    xyz = np.asarray(xyz_m, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz_m: expected shape (nant, 3) East/North/Up metres, got {xyz.shape}")
    f = np.atleast_1d(np.asarray(freq_hz, np.float64))
    if f.ndim != 1 or f.size == 0 or np.any(~np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"freq_hz: expected a 1-D array of positive frequencies in Hz, got shape {f.shape}")
    if isinstance(ntime, bool) or not isinstance(ntime, (int, np.integer)) or ntime < 1:
        raise ValueError(f"ntime: expected an integer >= 1, got {ntime!r}")
    if sigma not in (1, -1):
        raise ValueError(f"sigma: expected +1 or -1, got {sigma!r}")
    if not (np.isfinite(noise_power) and noise_power >= 0):
        raise ValueError(f"noise_power: expected a finite value >= 0, got {noise_power!r}")
    ntime, nchan, nant, npol = int(ntime), f.size, xyz.shape[0], 2
    dirs = source_directions(sources, time, location)
    nsrc = len(dirs.sources)
    sky_ss, noise_ss, burst_ss = np.random.SeedSequence(seed).spawn(3)
    sky_rng, noise_rng = np.random.default_rng(sky_ss), np.random.default_rng(noise_ss)

    x = np.zeros((nchan, npol, ntime, nant), np.complex128)
    if nsrc:
        # per-source per-pol power S(nu)/2 -> amplitude of each real component sqrt(S/4)
        flux = np.stack([s.flux_at(f) for s in dirs.sources], axis=1)            # (nchan, nsrc)
        amp = np.sqrt(flux / 4.0)[:, :, None] * np.ones(npol)                    # (nchan, nsrc, npol)
        if pattern is not None:
            b = pattern(dirs.l, dirs.m, f) if callable(pattern) else pattern
            try:
                b = np.broadcast_to(np.asarray(b), (nchan, nsrc, npol))
            except ValueError:
                raise ValueError(f"pattern: expected voltage gains broadcastable to (nchan, nsrc, npol) = "
                                 f"{(nchan, nsrc, npol)}, got {np.shape(b)}") from None
            amp = amp * b
        e = sky_rng.standard_normal((2, nchan, npol, ntime, nsrc))
        e = (e[0] + 1j * e[1]) * np.transpose(amp, (0, 2, 1))[:, :, None, :]    # (nchan, npol, ntime, nsrc)
        s_dot_r = np.stack([dirs.l, dirs.m, dirs.n], axis=1) @ xyz.T             # (nsrc, nant) metres
        # cycles = nu * path / c in float64, then the phase; no precision is lost before exp()
        phase = np.exp(sigma * 2j * np.pi * (f[:, None, None] / SPEED_OF_LIGHT_M_S) * s_dot_r[None])
        x += e @ phase[:, None, :, :]                                             # (nchan, npol, ntime, nant)
    if transients:
        if sample_time_s is None:
            if f.size < 2:
                raise ValueError("sample_time_s: needed for transients with a single channel")
            sample_time_s = 1.0 / abs(float(f[1] - f[0]))
        _add_transients(x, transients, f, xyz, float(t0_s), float(sample_time_s), time, location, sigma,
                        pattern if callable(pattern) else None, np.random.default_rng(burst_ss))
    x = np.ascontiguousarray(np.transpose(x, (2, 0, 3, 1)))                       # (ntime, nchan, nant, npol)
    if cable_delay_s is not None or cable_gain is not None:
        x *= cable_factor(cable_delay_s, cable_gain, f, nchan, nant, npol)[None]
    if noise_power > 0:
        nz = noise_rng.standard_normal((2, ntime, nchan, nant, npol))
        x += math.sqrt(noise_power / 2.0) * (nz[0] + 1j * nz[1])
    return (x, dirs) if return_directions else x


_TRANSIENT_KEYS = {"name", "start_s", "duration_s", "flux_jy", "dm", "spectral_index", "ra_deg", "dec_deg",
                   "az_deg", "alt_deg", "l", "m"}


def check_transient(i, tr):
    """(dm, duration_s, source dict) of ``transients[i]``, or a clear error naming what is wrong."""
    if not isinstance(tr, dict):
        raise TypeError(f"transients[{i}]: expected a mapping {{ra_deg, dec_deg, start_s, duration_s, flux_jy, dm}}, "
                        f"got {tr!r}")
    unknown = set(tr) - _TRANSIENT_KEYS
    missing = {"start_s", "duration_s", "flux_jy"} - set(tr)
    if unknown or missing:
        raise ValueError(f"transients[{i}]: " + "; ".join(
            ([f"unknown keys {sorted(unknown)}"] if unknown else []) + ([f"missing {sorted(missing)}"] if missing else [])))
    dm, dur = float(tr.get("dm", 0.0)), float(tr["duration_s"])
    if not (dur > 0 and dm >= 0):
        raise ValueError(f"transients[{i}]: duration_s must be > 0 and dm >= 0, got {dur!r}, {dm!r}")
    src = {k: tr[k] for k in tr if k in ("name", "flux_jy", "spectral_index", "ra_deg", "dec_deg", "az_deg",
                                          "alt_deg", "l", "m")}
    src.setdefault("name", f"transient{i}")
    return dm, dur, src


def _add_transients(x, transients, f, xyz, t0_s, dt_s, time, location, sigma, pattern, rng):
    """Add dispersed bursts to x (nchan, npol, ntime, nant) in place (module docstring)."""
    nchan, npol, ntime, _ = x.shape
    t = t0_s + dt_s * np.arange(ntime)
    for i, tr in enumerate(transients):
        dm, dur, src = check_transient(i, tr)
        start = float(tr["start_s"]) + dispersion_delay_s(dm, f, f.max())                  # (nchan,)
        on = (t[None, :] >= start[:, None]) & (t[None, :] < start[:, None] + dur)      # (nchan, ntime)
        if not on.any():
            continue
        d = source_directions([src], time, location)
        if not len(d.sources):
            log.warning("transient %s is below the horizon: not simulated", src["name"])
            continue
        cols = np.flatnonzero(on.any(axis=0))
        a, b = int(cols[0]), int(cols[-1]) + 1
        amp = np.sqrt(d.sources[0].flux_at(f) / 4.0)[:, None] * np.ones(npol)             # (nchan, npol)
        if pattern is not None:
            amp = amp * np.broadcast_to(np.asarray(pattern(d.l, d.m, f)), (nchan, 1, npol))[:, 0]
        e = rng.standard_normal((2, nchan, npol, b - a))
        e = (e[0] + 1j * e[1]) * amp[:, :, None] * on[:, None, a:b]
        s_dot_r = np.array([d.l[0], d.m[0], d.n[0]]) @ xyz.T                                # (nant,)
        phase = np.exp(sigma * 2j * np.pi * (f[:, None] / SPEED_OF_LIGHT_M_S) * s_dot_r[None])   # (nchan, nant)
        x[:, :, a:b, :] += e[..., None] * phase[:, None, None, :]


def quantize_ci4(efield, rms_target: float = 2.0, *, scale: float | None = None):
    """Quantise complex voltages to packed 4-bit (ci4) bytes, as an LWA F-engine delivers them.

    ``q = clip(round(efield * scale), -8, 7)`` on the real and imaginary parts separately, packed
    high nibble = real, low nibble = imaginary (:func:`bf_epic_blocks.io.tbf.pack_ci4`).
    ``scale`` defaults to ``rms_target / rms`` with rms the root-mean-square of the real and imaginary
    parts together (so the quantised parts have rms ~ rms_target 4-bit units); pass a fixed ``scale``
    to quantise consecutive gulps alike. Returns ``(packed uint8 same shape, scale)``; recover
    ``unpack_ci4(packed) / scale``. An all-zero input with no ``scale`` gives scale 1.
    """
    from ..io.tbf import pack_ci4
    x = np.asarray(efield)
    if not np.iscomplexobj(x):
        raise TypeError(f"quantize_ci4 expects complex voltages, got dtype {x.dtype}")
    if scale is None:
        if not (np.isfinite(rms_target) and rms_target > 0):
            raise ValueError(f"rms_target: expected a positive number of 4-bit units, got {rms_target!r}")
        rms = math.sqrt(float(np.mean(x.real.astype(np.float64) ** 2 + x.imag.astype(np.float64) ** 2)) / 2.0) \
            if x.size else 0.0
        scale = rms_target / rms if rms > 0 else 1.0
    elif not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale: expected a positive finite number, got {scale!r}")
    re = np.clip(np.rint(x.real * scale), -8, 7)
    im = np.clip(np.rint(x.imag * scale), -8, 7)
    return pack_ci4(re + 1j * im), float(scale)
