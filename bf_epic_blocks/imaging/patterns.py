"""Direction-dependent antenna voltage patterns (A_i) folded into the DFT operator.

A pattern function takes ``(pixels_lm (npix, 2), freq_hz (nchan,), npol)`` and returns the voltage
pattern B shaped (npix, npol) (antenna- and frequency-independent) or (nchan|1, npix, nant|1,
npol|1). The imager multiplies D[k, a] by B, so a point source of power P images to |B|^2 P.

Built in: ``"dipole"``, the short (Hertzian) dipole with no ground screen: the voltage of a dipole
along unit vector d responds to a field from direction s with |d x s| = sqrt(1 - (d.s)^2), so the
X dipole (N-S, d = North) gives sqrt(1 - m^2) and the Y dipole (E-W, d = East) gives sqrt(1 - l^2).
Users add their own with :func:`register_pattern` (the name travels in pipeline headers).
"""
from __future__ import annotations

from ._xp import get_xp


def short_dipole(pixels_lm, freq_hz=None, npol=2):
    """(npix, npol) real voltage pattern: pol 0 (X, N-S) sqrt(1 - m^2), pol 1 (Y, E-W) sqrt(1 - l^2)."""
    xp = get_xp(pixels_lm)
    lm = xp.asarray(pixels_lm, dtype=xp.float64)
    bx = xp.sqrt(xp.clip(1.0 - lm[:, 1] ** 2, 0, None))
    by = xp.sqrt(xp.clip(1.0 - lm[:, 0] ** 2, 0, None))
    return xp.stack([bx, by][:npol], axis=-1)


_REGISTRY = {"dipole": short_dipole}


def register_pattern(name: str, fn):
    """Make ``fn(pixels_lm, freq_hz, npol)`` available by ``name`` to blocks and YAML pipelines."""
    if not callable(fn):
        raise TypeError(f"pattern {name!r} must be callable, got {type(fn).__name__}")
    _REGISTRY[name] = fn


def get_pattern(name: str):
    if name not in _REGISTRY:
        raise ValueError(f"unknown antenna pattern {name!r}; known: {sorted(_REGISTRY)} (register_pattern adds one)")
    return _REGISTRY[name]


def pattern_array(name_or_fn, pixels_lm, freq_hz, npol):
    """Evaluate a pattern into the 4-D form the operator takes: (nchan|1, npix, nant|1, npol|1)."""
    fn = get_pattern(name_or_fn) if isinstance(name_or_fn, str) else name_or_fn
    b = fn(pixels_lm, freq_hz, npol)
    xp = get_xp(b)
    b = xp.asarray(b)
    npix = int(pixels_lm.shape[0])
    if b.ndim == 2:
        if b.shape[0] != npix or b.shape[1] not in (1, npol):
            raise ValueError(f"pattern returned shape {tuple(b.shape)}; expected (npix={npix}, npol={npol})")
        b = b[None, :, None, :]
    if b.ndim != 4:
        raise ValueError(f"pattern returned shape {tuple(b.shape)}; expected (npix, npol) or 4-D")
    return b.astype(xp.complex128)
