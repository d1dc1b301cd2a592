"""Matrix products at a chosen precision: the precision ladder of the DFT imager.

Every route of the imager is one or two batched complex GEMMs (F = D X; R = X X^H; M = D R) plus
elementwise reductions. This module runs those GEMMs at the precision asked for:

===========  =====================================================================  ===============
name         what the GEMM does                                                      where
===========  =====================================================================  ===============
``fp64``     complex128 operands, float64 arithmetic                                 CPU, GPU
``fp32``     complex64 operands, float32 arithmetic (no tensor cores)                CPU, GPU
``tf32x3``   split precision: A = A_hi + A_lo, B = B_hi + B_lo (hi = A rounded to    GPU (tensor cores)
             tf32), A_hi B_hi + A_hi B_lo + A_lo B_hi in tf32 with fp32 accumulation:
             ~fp32 accuracy at tensor-core speed (B_lo is skipped when B is exact in
             tf32, e.g. 4-bit voltages or integer covariances below 2^11)
``tf32``     complex64 operands rounded to tf32 (10-bit mantissa), fp32 accumulation GPU (tensor cores)
``fp16``     operands rounded to fp16 (10-bit mantissa, 5-bit exponent), fp32        GPU (tensor cores)
             accumulation; 4-bit voltages are exact in fp16
``bf16``     operands rounded to bf16 (7-bit mantissa), fp32 accumulation            GPU (tensor cores)
===========  =====================================================================  ===============

and, for the covariance route only, :func:`int_gram`: R = Z Z^T of integer voltages (4- or
8-bit) summed in int32 on the GPU's integer tensor cores (in float32 on the CPU, exact while the
sums stay below 2^24): R carries no rounding error at all.

On the GPU the products are cuBLAS ``cublasGemmStridedBatchedEx`` calls through CuPy's binding,
with the compute type setting the precision (``CUBLAS_COMPUTE_32F_FAST_TF32`` / ``_FAST_16F`` /
``_FAST_16BF`` on complex64 operands: cuBLAS converts the operands itself, so one complex64 copy of
the operator serves every mode). The CPU has no tensor cores: asking for tf32, tf32x3, fp16 or bf16
there raises :class:`PrecisionUnavailable` naming what to use instead.

Shapes: ``cmatmul(a, b)`` takes row-major (batch, m, k) and (batch, k, n) arrays (a batch of 1
broadcasts) and returns (batch, m, n).
"""
from __future__ import annotations

import numpy as np

from ._xp import get_xp

__all__ = ["PRECISIONS", "PrecisionUnavailable", "check_precision", "cmatmul", "int_gram", "split_tf32",
           "round_tf32", "precision_available"]


class PrecisionUnavailable(ValueError):
    """The precision needs hardware (tensor cores) that the arrays' device does not have."""


#: name -> (real dtype of the result, complex dtype of the operands, needs tensor cores)
PRECISIONS = {
    "fp64": (np.float64, np.complex128, False),
    "fp32": (np.float32, np.complex64, False),
    "tf32x3": (np.float32, np.complex64, True),
    "tf32": (np.float32, np.complex64, True),
    "fp16": (np.float32, np.complex64, True),
    "bf16": (np.float32, np.complex64, True),
}

# cuBLAS enums (cublas_api.h / library_types.h); CuPy's binding takes them as ints.
_CUDA_C_32F, _CUDA_C_64F, _CUDA_R_8I, _CUDA_R_32I = 4, 5, 3, 10
_COMPUTE = {"fp64": 70, "fp32": 68, "tf32": 77, "tf32x3": 77, "fp16": 74, "bf16": 75}  # CUBLAS_COMPUTE_*
_COMPUTE_32I = 72
_OP_N, _OP_T = 0, 1
_GEMM_DEFAULT = -1


def precision_available(precision: str, xp) -> bool:
    """Whether ``precision`` runs on arrays of namespace ``xp`` (tensor-core modes: CuPy only)."""
    return precision in PRECISIONS and (xp.__name__ == "cupy" or not PRECISIONS[precision][2])


def check_precision(precision, xp=np):
    """(real dtype, complex dtype) of ``precision``; a clear error if unknown or unavailable on ``xp``."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    rdt, cdt, tc = PRECISIONS[precision]
    if tc and xp.__name__ != "cupy":
        raise PrecisionUnavailable(
            f"precision {precision!r} needs tensor cores (a CUDA GPU with CuPy); the CPU has none: use "
            "'fp32' or 'fp64' there, or tolerance=... to let the imager pick what this machine offers")
    return rdt, cdt


def round_tf32(a):
    """``a`` (float32 or complex64) rounded to the nearest tf32 value (10 explicit mantissa bits),
    returned as the same dtype; what the tensor cores would read, rounded instead of truncated."""
    xp = get_xp(a)
    f = a.view(xp.float32) if a.dtype == xp.complex64 else a
    u = f.view(xp.uint32)
    r = ((u + xp.uint32(0x1000)) & xp.uint32(0xFFFFE000)).view(xp.float32)
    return r.view(a.dtype) if a.dtype == xp.complex64 else r


def split_tf32(a):
    """(hi, lo) with hi = tf32(a), lo = a - hi (exact in float32): a = hi + lo to ~2^-22."""
    hi = round_tf32(a)
    return hi, a - hi


def _as_batched(a):
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ValueError(f"GEMM operands must be 2-D or 3-D (batch, rows, cols); got shape {tuple(a.shape)}")
    return a


def _cublas_gemm(a, b, c, compute, beta):
    """c[i] = a[i] @ b[i] (+ beta c[i]) row-major, complex, with a cuBLAS compute type.

    Row-major C = A B is column-major C^T = B^T A^T, so cuBLAS gets (B, A) with no transposes.
    A batch dimension of 1 broadcasts (stride 0)."""
    import cupy as cp
    from cupy_backends.cuda.libs import cublas
    batch = max(a.shape[0], b.shape[0])
    m, k = a.shape[1:]
    n = b.shape[2]
    dt = _CUDA_C_64F if a.dtype == cp.complex128 else _CUDA_C_32F
    sdt = np.complex128 if a.dtype == cp.complex128 else np.complex64
    alpha = np.array(1, sdt)
    beta_ = np.array(beta, sdt)
    sa = 0 if a.shape[0] == 1 else m * k
    sb = 0 if b.shape[0] == 1 else k * n
    handle = cp.cuda.device.get_cublas_handle()
    cublas.gemmStridedBatchedEx(handle, _OP_N, _OP_N, n, m, k, alpha.ctypes.data,
                                b.data.ptr, dt, n, sb, a.data.ptr, dt, k, sa,
                                beta_.ctypes.data, c.data.ptr, dt, n, m * n, batch, compute, _GEMM_DEFAULT)
    return c


def cmatmul(a, b, precision="fp32", *, out=None, b_exact=False, a_split=None):
    """Batched complex product a @ b at ``precision`` (see the module table).

    a : (batch|1, m, k) complex;  b : (batch|1, k, n) complex, same namespace and dtype family.
    out : optional (batch, m, n) result array to write into (CuPy: contiguous complex64/128).
    b_exact : b is exactly representable in tf32 (tf32x3 then needs two products, not three).
    a_split : optional precomputed ``split_tf32(a)`` for tf32x3 (operators are split once).
    Returns complex64 (complex128 for fp64), shaped (batch, m, n).
    """
    xp = get_xp(a, b)
    _, cdt = check_precision(precision, xp)
    a = _as_batched(a)
    b = _as_batched(b)
    if a.shape[2] != b.shape[1]:
        raise ValueError(f"GEMM shapes do not match: {tuple(a.shape)} @ {tuple(b.shape)}")
    if xp is np:
        res = np.matmul(a.astype(cdt, copy=False), b.astype(cdt, copy=False))
        if out is not None:
            out[...] = res
            return out
        return res
    a = xp.ascontiguousarray(a.astype(cdt, copy=False))
    b = xp.ascontiguousarray(b.astype(cdt, copy=False))
    batch = max(a.shape[0], b.shape[0])
    if out is None:
        out = xp.empty((batch, a.shape[1], b.shape[2]), cdt)
    compute = _COMPUTE[precision]
    if precision != "tf32x3":
        return _cublas_gemm(a, b, out, compute, 0)
    a_hi, a_lo = a_split if a_split is not None else split_tf32(a)
    b_hi, b_lo = (b, None) if b_exact else split_tf32(b)
    _cublas_gemm(a_lo, b_hi, out, compute, 0)     # small terms first: they round least
    if b_lo is not None:
        _cublas_gemm(a_hi, b_lo, out, compute, 1)
    _cublas_gemm(a_hi, b_hi, out, compute, 1)
    return out


def int_gram(z, out=None, accumulate=False):
    """Exact Gram matrix Z Z^T of integer voltages, batched: (batch, r, t) int8 -> (batch, r, r).

    GPU: int8 x int8 products summed in int32 by cuBLAS (``CUBLAS_COMPUTE_32I``); ``out`` int32,
    ``accumulate`` adds to it (beta = 1). The caller keeps the sums below 2^31 (t x 2 x 128^2 for
    8-bit data; 64 per sample for 4-bit). cuBLAS' integer kernels want t a multiple of 4: pad with
    zero samples, which change nothing.
    CPU: float32 GEMM of the integers, exact while every sum stays below 2^24 (the caller chunks t);
    ``out`` float64.
    """
    xp = get_xp(z)
    z = _as_batched(z)
    nb, r, t = z.shape
    if xp is np:
        zf = z.astype(np.float32)
        res = np.matmul(zf, zf.transpose(0, 2, 1)).astype(np.float64)
        if out is None:
            return res
        if accumulate:
            out += res
        else:
            out[...] = res
        return out
    import cupy as cp
    from cupy_backends.cuda.libs import cublas
    if z.dtype != cp.int8:
        raise TypeError(f"int_gram on the GPU takes int8 voltages, got {z.dtype}")
    if t % 4:
        z = cp.concatenate([z, cp.zeros((nb, r, 4 - t % 4), cp.int8)], axis=2)
        t = z.shape[2]
    z = cp.ascontiguousarray(z)
    if out is None:
        out = cp.empty((nb, r, r), cp.int32)
        accumulate = False
    alpha = np.array(1, np.int32)
    beta = np.array(1 if accumulate else 0, np.int32)
    # Row-major Z (r x t) is column-major Z^T (t x r, ld t); C = (Z^T)^T Z^T: "TN", IMMA's favourite.
    handle = cp.cuda.device.get_cublas_handle()
    cublas.gemmStridedBatchedEx(handle, _OP_T, _OP_N, r, r, t, alpha.ctypes.data,
                                z.data.ptr, _CUDA_R_8I, t, r * t, z.data.ptr, _CUDA_R_8I, t, r * t,
                                beta.ctypes.data, out.data.ptr, _CUDA_R_32I, r, r * r, nb, _COMPUTE_32I,
                                _GEMM_DEFAULT)
    return out
