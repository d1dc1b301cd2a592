"""The elementwise reductions that follow the imager's GEMMs, one pass each over the GEMM output.

* :func:`group_power` -- direct route: sum over groups of N consecutive samples of |F|^2 or
  F_p F_q^*, so a whole gulp gives one image per N samples without a Python loop.
* :func:`row_dot` -- covariance route: diag(M D^H)_k = sum_a M[k, a] conj(D[k, a]), the image of
  M = D R without forming D R D^H.

On the GPU each is one CuPy ``ReductionKernel`` (map, then sum over the last axis): it reads the
GEMM output once and writes only the (small) result, instead of the three or four temporaries
that ``(F.real**2 + F.imag**2).sum(-1)`` makes. On the CPU the same functions use NumPy.
The CUDA source of each kernel is the string beside it.
"""
from __future__ import annotations

import numpy as np

from ._xp import get_xp

__all__ = ["group_power", "row_dot"]

_KERNELS = {}


def _kernel(name):
    """Build the CuPy kernels on first use (CuPy is optional)."""
    if not _KERNELS:
        import cupy as cp
        # |x|^2 summed over the reduced axis (thrust complex: norm() is the squared magnitude)
        for cdt, rdt in (("complex64", "float32"), ("complex128", "float64")):
            _KERNELS["power", cdt] = cp.ReductionKernel(f"{cdt} x", f"{rdt} y", "norm(x)", "a + b", "y = a",
                                                        "0", f"bf_group_power_{cdt}")
        # x conj(y) summed over the reduced axis
        _KERNELS["cross"] = cp.ReductionKernel("T x, T y", "T z", "x * conj(y)", "a + b", "z = a", "0",
                                               "bf_group_cross")
    return _KERNELS[name]


def group_power(fp, fq=None, n=None):
    """Sums over groups of ``n`` samples along the last axis.

    fp, fq : complex (..., ntime) beamformed fields of polarisations p and q (fq None: p = q).
    n : samples per group (default: all); ntime // n groups, trailing samples ignored.
    Returns (..., ntime // n): float sum |fp|^2 (real dtype of fp) when fq is None, else the
    complex sum fp conj(fq).
    """
    xp = get_xp(fp)
    t = fp.shape[-1]
    n = t if n is None else int(n)
    g = t // n
    shp = fp.shape[:-1] + (g, n)
    fp = fp[..., :g * n].reshape(shp)
    if fq is not None:
        fq = fq[..., :g * n].reshape(shp)
    if xp is np:
        if fq is None:
            return (fp.real ** 2 + fp.imag ** 2).sum(axis=-1)
        return (fp * np.conj(fq)).sum(axis=-1)
    if fq is None:
        return _kernel(("power", np.dtype(fp.dtype).name))(fp, axis=-1)
    return _kernel("cross")(fp, fq, axis=-1)


def row_dot(m, d):
    """sum_a m[..., a] conj(d[..., a]) over the last axis; ``d`` broadcasts against ``m``.

    m : complex (..., nant), d : complex broadcastable to m. Returns complex (...)."""
    xp = get_xp(m, d)
    if xp is np:
        return (m * np.conj(d)).sum(axis=-1)
    return _kernel("cross")(m, d, axis=-1)
