"""Non-finite voltages: zero them and count them, so one bad sample cannot turn an image into NaN.

A NaN or Inf in float voltages (cf32 from an upstream block, a failed calibration solution...) would
spread through the operator product into every pixel of its integration. The policy is to treat that
antenna as flagged for that sample: the sample is set to 0 (which contributes nothing to the beam sums,
exactly as a flagged antenna's zeroed voltage does in CalFoldBlock) and counted. Integer voltages
(ci4/ci8/ci16) cannot be non-finite and need no check.
"""
from __future__ import annotations

from ._xp import get_xp, host_any

__all__ = ["zero_nonfinite"]


def zero_nonfinite(x, xp=None, *, per_time: bool = False, inplace: bool = False):
    """Zero the non-finite samples of float voltages and count them per antenna and polarisation.

    Parameters
    ----------
    x : float or complex array ``(ntime, nchan, nant, npol)`` (NumPy or CuPy; any number of leading
        axes before the last two is accepted). A complex sample is non-finite when either part is
        NaN or +-Inf; it is replaced by 0 (both parts).
    xp : the array module (default: the one owning ``x``).
    per_time : False -> counts summed over every axis but the last two; True -> summed over every
        axis but the first and the last two (for ``(ntime, nchan, nant, npol)``: per time sample).
    inplace : zero the samples in ``x`` itself (it must be writeable) instead of a copy.

    Returns
    -------
    clean : array like ``x`` with the non-finite samples set to 0. When there are none, ``x`` itself
        is returned (no copy).
    counts : int64 array in ``x``'s namespace, ``(nant, npol)`` (or ``(ntime, nant, npol)`` with
        ``per_time``): the number of samples zeroed.
    """
    xp = get_xp(x) if xp is None else xp
    if x.ndim < 2:
        raise ValueError(f"zero_nonfinite: expected (..., nant, npol) voltages, got shape {tuple(x.shape)}")
    if per_time and x.ndim < 3:
        raise ValueError(f"zero_nonfinite: per_time needs (ntime, ..., nant, npol), got shape {tuple(x.shape)}")
    if x.dtype.kind not in "fc":
        raise TypeError(f"zero_nonfinite: expected float or complex voltages, got dtype {x.dtype} "
                        "(integer samples cannot be non-finite)")
    bad = ~xp.isfinite(x)  # complex: False unless both parts are finite
    axes = tuple(range(1 if per_time else 0, x.ndim - 2))
    counts = bad.sum(axis=axes, dtype=xp.int64) if axes else bad.astype(xp.int64)
    if not host_any(counts):   # counts are small; on the host (see _xp.host_all), synchronised first
        return x, counts
    if inplace:
        x[bad] = 0
        return x, counts
    return xp.where(bad, xp.zeros((), dtype=x.dtype), x), counts
