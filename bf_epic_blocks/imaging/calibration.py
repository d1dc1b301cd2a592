"""Direction-independent calibration terms (A_c, A_s) and flags, as pure functions.

Conventions (docs/CONVENTIONS.md): a raw voltage carries sqrt(G) exp(-2 pi i nu tau) from its cable,
so the cable correction is ``exp(+2 pi i nu tau) / sqrt(G)``. Calibration solutions A_s are complex
multiplicative corrections (already inverted gains) applied to the voltages. A zero anywhere means
"flagged": the antenna is dropped from imaging (the imager is told through the header's flags).

Time tags are LWA ticks of a 196 MHz clock since the Unix epoch (:data:`FS_HZ`).
"""
from __future__ import annotations

import math

import numpy as np

from ..conventions import FS_HZ
from ._xp import get_xp



def cable_weights(delay_s, gain, freq_hz):
    """Cable correction exp(+2 pi i nu tau) / sqrt(G), complex128 (nchan, nant, npol).

    delay_s, gain : (nant, npol, nchan) seconds and power gain (as ``StationTable.cable_delay_s`` /
    ``cable_gain`` give them; (nant, npol) or (nant,) broadcast over channels).
    A gain <= 0 or non-finite term gives weight 0 (flagged).
    """
    f = np.asarray(freq_hz, dtype=np.float64)
    tau = np.asarray(delay_s, dtype=np.float64)
    g = np.asarray(gain, dtype=np.float64)
    while tau.ndim < 3:
        tau = tau[..., None]
    while g.ndim < 3:
        g = g[..., None]
    tau = np.broadcast_to(tau, tau.shape[:2] + (len(f),))
    g = np.broadcast_to(g, tau.shape)
    cyc = f[None, None, :] * tau
    cyc = cyc - np.rint(cyc)  # reduce in float64 before the exponential
    ok = np.isfinite(cyc) & np.isfinite(g) & (g > 0)
    w = np.where(ok, np.exp(2j * math.pi * np.where(ok, cyc, 0)) / np.sqrt(np.where(ok, g, 1.0)), 0)
    return np.ascontiguousarray(np.moveaxis(w, 2, 0))


class GainTable:
    """Time-variable complex corrections A_s: solution i applies from ``valid_from[i]`` (time tag)
    up to, not including, ``valid_from[i + 1]``.

    gains : complex (nsol, nchan|1, nant, npol|1). Frames before the first solution get unit gains
    (counted by the caller). A zero gain anywhere flags that antenna-pol for the whole sequence
    (:meth:`flags`), because the imager's normalisation N_A is fixed per sequence.
    """

    def __init__(self, valid_from, gains):
        vf = np.asarray(valid_from, dtype=np.int64).ravel()
        g = np.asarray(gains, dtype=np.complex128)
        if g.ndim != 4 or g.shape[0] != vf.shape[0]:
            raise ValueError(f"gains must be shaped (nsol, nchan|1, nant, npol|1) with nsol = len(valid_from) "
                             f"= {vf.shape[0]}; got {g.shape}")
        if vf.shape[0] == 0:
            raise ValueError("a gain table needs at least one solution")
        if np.any(np.diff(vf) <= 0):
            raise ValueError("valid_from time tags must be strictly increasing")
        if not np.all(np.isfinite(g)):
            raise ValueError("gains contain NaN or inf; use 0 to flag")
        self.valid_from, self.gains = vf, g
        self._device = {}

    @classmethod
    def load(cls, path):
        """From an .npz with arrays ``valid_from`` (int ticks) and ``gains`` (complex, as above)."""
        with np.load(path) as z:
            missing = {"valid_from", "gains"} - set(z.files)
            if missing:
                raise ValueError(f"gain table {path} lacks arrays {sorted(missing)}; it has {z.files}")
            return cls(z["valid_from"], z["gains"])

    def check_shape(self, nchan, nant, npol):
        _, c, a, p = self.gains.shape
        if c not in (1, nchan) or a != nant or p not in (1, npol):
            raise ValueError(f"gain table shaped {self.gains.shape} does not fit data with nchan={nchan}, "
                             f"nant={nant}, npol={npol}: expected (nsol, {nchan} or 1, {nant}, {npol} or 1)")

    def flags(self, nant, npol):
        """bool (nant, npol): True where any solution or channel has a zero gain."""
        z = np.any(self.gains == 0, axis=(0, 1))
        return np.broadcast_to(z, (nant, npol)).copy()

    def index(self, time_tags):
        """Solution index for each time tag (int64); -1 before the first solution."""
        return np.searchsorted(self.valid_from, np.asarray(time_tags, dtype=np.int64), side="right") - 1

    def segments(self, first_tag, ticks_per_frame, nframe):
        """[(start, stop, solution index)] runs of frames sharing one solution within a gulp."""
        tags = first_tag + ticks_per_frame * np.arange(nframe, dtype=np.int64)
        idx = self.index(tags)
        cuts = np.flatnonzero(np.diff(idx)) + 1
        starts = np.concatenate([[0], cuts])
        stops = np.concatenate([cuts, [nframe]])
        return [(int(s), int(e), int(idx[s])) for s, e in zip(starts, stops)]

    def corrections(self, i):
        """Solution i's corrections as stored, complex128 (nchan|1, nant, npol|1)."""
        return self.gains[i]

    def solution(self, i, like=None):
        """Gains of solution i (ones for i < 0) as a complex64 array in the namespace of ``like``."""
        xp = get_xp(like) if like is not None else np
        key = (xp.__name__, i)
        if key not in self._device:
            g = np.ones((1, 1, 1, 1), np.complex64)[0] if i < 0 else self.gains[i].astype(np.complex64)
            self._device[key] = xp.asarray(g)
        return self._device[key]


def apply_direction_independent(x, weights, live=None, gain=None, out=None):
    """x * weights (* gain), with exact zeros where ``live`` is False.

    x : complex (ntime, nchan, nant, npol); weights : complex (nchan, nant, npol) or broadcastable;
    live : bool (nant, npol) or broadcastable; gain : complex broadcastable to (nchan, nant, npol).
    out : optional array of x's shape and complex dtype (e.g. a ring span) that receives the result.
    Returns the calibrated voltages (``out`` when given).

    On CuPy, complex64 voltages and weights go through one fused kernel, straight into ``out``: the
    array form takes three passes over the gulp and two temporaries (a case-P gulp, 67 MB of complex64,
    is read and written three times), and a calibration block shares the GPU with the imager.
    """
    xp = get_xp(x)
    w = weights if gain is None else weights * gain
    if xp is not np and x.dtype == w.dtype == xp.complex64 and (out is None or out.dtype == xp.complex64):
        args = (x, w, True if live is None else live) + (() if out is None else (out,))
        return _calibrate_kernel()(*args)
    y = x * w[None]
    if live is not None:
        y = xp.where(live[None], y, 0)
    if out is not None:
        out[...] = y
        return out
    return y


_CALIBRATE = None


def _calibrate_kernel():
    """CuPy ElementwiseKernel y = live ? x * w : 0 (complex64; w and live broadcast over time)."""
    global _CALIBRATE
    if _CALIBRATE is None:
        import cupy as cp
        _CALIBRATE = cp.ElementwiseKernel("complex64 x, complex64 w, bool live", "complex64 y",
                                          "y = live ? x * w : complex<float>(0.0f, 0.0f)", "bf_calibrate")
    return _CALIBRATE
