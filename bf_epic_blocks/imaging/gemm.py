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
``fp16x3``   split precision as tf32x3 with fp16 halves (hi = fp16(A), lo =          GPU (tensor cores)
             fp16(A - hi), 22 bits together; operands scaled into fp16's range):
             three fp16 products at twice tf32's rate -- ~fp32 accuracy for about the
             cost of 1.5 tf32 products (integer covariances below 2^22 are exact in hi+lo)
``tf32``     operands rounded to tf32 (10-bit mantissa), fp32 accumulation           GPU (tensor cores)
``fp16``     operands rounded to fp16 (10-bit mantissa, 5-bit exponent: the caller   GPU (tensor cores)
             scales them into range), fp32 accumulation; as accurate as tf32 at twice
             the rate; 4-bit voltages are exact in fp16
``bf16``     operands rounded to bf16 (7-bit mantissa), fp32 accumulation            GPU (tensor cores)
``i8x2``     direct route, 4-bit integer voltages only: the operator as two int8     GPU (integer
             pieces (resolution 1/(127*254) of each pixel row's largest element),   tensor cores)
             the GEMM exact in int32 and |F|^2 summed in its epilogue (:mod:`.fused`)
``i8x3``     as i8x2 with three pieces (resolution 1/(127*63^2))                     GPU (integer TC)
``i8x1``     as i8x2 with one piece (resolution 1/127): half i8x2's integer MMAs,     GPU (integer TC)
             for searches, whose images are noise-dominated
===========  =====================================================================  ===============

The tensor-core modes are real GEMMs on the stacked form of the complex product
(:func:`stack_operator`, :func:`stack_rhs`, :func:`stacked_matmul`): for D = Dr + i Di and
B = Br + i Bi, ``[[Dr, -Di], [Di, Dr]] @ [Br; Bi] = [Re DB; Im DB]``, the same four real products
as a complex GEMM, on operands stored in the mode's own type (fp16, bf16 or fp32 for tf32), with an
fp32 result whose first half of rows is the real part and second half the imaginary part.
(cuBLAS' complex GEMM ignores the fp16/bf16 compute types and runs them as tf32: the stacked form
is what gives real fp16/bf16 tensor-core products.)

and, for the covariance route only, :func:`int_gram`: R = Z Z^T of integer voltages (4- or
8-bit) summed in int32 on the GPU's integer tensor cores (in float32 on the CPU, exact while the
sums stay below 2^24): R carries no rounding error at all.

On the GPU the products are cuBLAS ``cublasGemmStridedBatchedEx`` calls through CuPy's binding,
with the compute type setting the precision (``CUBLAS_COMPUTE_32F_FAST_TF32`` / ``_FAST_16F`` /
``_FAST_16BF`` on complex64 operands: cuBLAS converts the operands itself, so one complex64 copy of
the operator serves every mode). The CPU has no tensor cores: asking for tf32, tf32x3, fp16x3, fp16 or bf16
there raises :class:`PrecisionUnavailable` naming what to use instead.

Shapes: ``cmatmul(a, b)`` takes row-major (batch, m, k) and (batch, k, n) arrays (a batch of 1
broadcasts) and returns (batch, m, n).
"""
from __future__ import annotations

import numpy as np

from ._xp import device_kind, get_xp

__all__ = ["PRECISIONS", "PrecisionUnavailable", "check_precision", "cmatmul", "int_gram", "split_tf32", "SPLIT", "FP16",
           "round_tf32", "precision_available", "STACKED", "stack_operator", "stack_rhs", "stacked_matmul",
           "to_bf16", "pow2_scale"]


class PrecisionUnavailable(ValueError):
    """The precision needs hardware (tensor cores) that the arrays' device does not have."""


#: name -> (real dtype of the result, complex dtype of the operands, needs tensor cores)
PRECISIONS = {
    "fp64": (np.float64, np.complex128, False),
    "fp32": (np.float32, np.complex64, False),
    "tf32x3": (np.float32, np.complex64, True),
    "fp16x3": (np.float32, np.complex64, True),
    "tf32": (np.float32, np.complex64, True),
    "fp16": (np.float32, np.complex64, True),
    "bf16": (np.float32, np.complex64, True),
    "i8x1": (np.float32, np.complex64, True),
    "i8x2": (np.float32, np.complex64, True),
    "i8x3": (np.float32, np.complex64, True),
}

#: modes computed as stacked real GEMMs (everything on tensor cores)
STACKED = ("tf32x3", "fp16x3", "tf32", "fp16", "bf16")
#: split modes: operands as [hi, lo] pairs, three products (two when one side is exact)
SPLIT = ("tf32x3", "fp16x3")
#: modes whose operands are fp16 (scaled by a power of two into range)
FP16 = ("fp16", "fp16x3")

# cuBLAS enums (cublas_api.h / library_types.h); CuPy's binding takes them as ints.
_CUDA_C_32F, _CUDA_C_64F, _CUDA_R_8I, _CUDA_R_32I = 4, 5, 3, 10
_CUDA_R_32F, _CUDA_R_16F, _CUDA_R_16BF = 0, 2, 14
_COMPUTE = {"fp64": 70, "fp32": 68, "tf32": 77, "tf32x3": 77, "fp16": 74, "fp16x3": 74, "bf16": 75}  # CUBLAS_COMPUTE_*
_COMPUTE_32I = 72
_OP_N, _OP_T = 0, 1
_GEMM_DEFAULT = -1


def precision_available(precision: str, device) -> bool:
    """Whether ``precision`` runs on ``device`` ('cpu' | 'gpu' or the numpy / cupy module; see
    :func:`._xp.device_kind`): the tensor-core modes run on a GPU only."""
    return precision in PRECISIONS and (device_kind(device) == "gpu" or not PRECISIONS[precision][2])


def check_precision(precision, xp=np):
    """(real dtype, complex dtype) of ``precision``; a clear error if unknown or unavailable on ``xp``."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    rdt, cdt, tc = PRECISIONS[precision]
    if tc and device_kind(xp) != "gpu":
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


def _gemm_ex(a, b, c, in_type, out_type, compute, scalar_dtype, beta):
    """c[i] = a[i] @ b[i] (+ beta c[i]), row-major batches, through cublasGemmStridedBatchedEx.

    Row-major C = A B is column-major C^T = B^T A^T, so cuBLAS gets (B, A) with no transposes.
    A batch dimension of 1 broadcasts (stride 0). ``in_type``/``out_type``: CUDA data types;
    ``scalar_dtype``: NumPy type of alpha and beta (the compute type's)."""
    m, k = a.shape[1:]
    return _gemm_cols(a, 0, k, b, 0, c, in_type, out_type, compute, scalar_dtype, beta)


def _gemm_cols(a, a0, k, b, b0, c, in_type, out_type, compute, scalar_dtype, beta):
    """c[i] = a[i][:, a0:a0+k] @ b[i][b0:b0+k, :] (+ beta c[i]): a column block of a (row-major, its
    full width the leading dimension) times the matching row block of b; contiguous batches."""
    batch = max(a.shape[0], b.shape[0])
    m, lda = a.shape[1:]
    n = b.shape[2]
    alpha = np.array(1, scalar_dtype)
    beta_ = np.array(beta, scalar_dtype)
    sa = 0 if a.shape[0] == 1 else m * lda
    sb = 0 if b.shape[0] == 1 else b.shape[1] * n
    pa = a.data.ptr + a0 * a.itemsize
    pb = b.data.ptr + b0 * n * b.itemsize
    _call_gemm((_OP_N, _OP_N, n, m, k, alpha.ctypes.data, pb, in_type, n, sb, pa, in_type, lda, sa,
                beta_.ctypes.data, c.data.ptr, out_type, n, m * n, batch, compute, _GEMM_DEFAULT))
    return c


def _call_gemm(args):
    """cublasGemmStridedBatchedEx(handle, *args) on the current stream (CuPy's binding, or the library
    itself while the stream is being captured into a CUDA graph)."""
    import cupy as cp
    from cupy_backends.cuda.libs import cublas
    handle = cp.cuda.device.get_cublas_handle()
    stream = cp.cuda.get_current_stream()
    if stream.ptr not in (0, 1, 2) and stream.is_capturing():
        _capturing_gemm(handle, stream.ptr, args)
    else:
        # the handle is the thread's, and keeps the stream it was last given: a thread whose first cuBLAS
        # call is this one would otherwise run it on the legacy default stream, which waits for every
        # other stream's work and makes theirs wait for it (the gain solver's sums beside the imager)
        cublas.setStream(handle, stream.ptr)
        cublas.gemmStridedBatchedEx(handle, *args)


_CUBLAS = []


def _libcublas():
    """The cuBLAS library CuPy has loaded (ctypes), found in this process' memory map."""
    if not _CUBLAS:
        import ctypes
        import ctypes.util
        path = None
        try:
            with open("/proc/self/maps") as f:
                for line in f:
                    if "libcublas.so" in line and "libcublasLt" not in line:
                        path = line.split()[-1]
                        break
        except OSError:
            pass
        lib = ctypes.CDLL(path or ctypes.util.find_library("cublas"))
        lib.cublasSetStream_v2.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        c_int, c_ll, c_p = ctypes.c_int, ctypes.c_longlong, ctypes.c_void_p
        lib.cublasGemmStridedBatchedEx.argtypes = [
            c_p, c_int, c_int, c_int, c_int, c_int, c_p, c_p, c_int, c_int, c_ll, c_p, c_int, c_int, c_ll,
            c_p, c_p, c_int, c_int, c_ll, c_int, c_int, c_int]
        _CUBLAS.append(lib)
    return _CUBLAS[0]


def _capturing_gemm(handle, stream_ptr, args):
    """The same cuBLAS call while the stream is being captured into a CUDA graph (.graphs).

    CuPy's cuBLAS bindings refuse to run during a stream capture; cuBLAS itself supports it (the
    handle's default workspace is allocated when the handle is made, and host scalars are read at
    call time), so the capture calls the library directly."""
    lib = _libcublas()
    st = lib.cublasSetStream_v2(handle, stream_ptr)
    if st == 0:
        st = lib.cublasGemmStridedBatchedEx(handle, *args)
    if st != 0:
        raise RuntimeError(f"cuBLAS GEMM during stream capture failed with status {st}")


def _cublas_gemm(a, b, c, compute, beta):
    """Complex c = a @ b (+ beta c) with a cuBLAS compute type (complex64 or complex128 operands)."""
    wide = a.dtype == np.complex128
    dt = _CUDA_C_64F if wide else _CUDA_C_32F
    return _gemm_ex(a, b, c, dt, dt, compute, np.complex128 if wide else np.complex64, beta)


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
    if precision == "fp16x3":
        raise ValueError("cmatmul has no fp16x3 (cuBLAS' complex GEMM has no fp16 inputs): use "
                         "stack_operator / stack_rhs / stacked_matmul, as DFTOperator does")
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
    _call_gemm((_OP_T, _OP_N, r, r, t, alpha.ctypes.data, z.data.ptr, _CUDA_R_8I, t, r * t, z.data.ptr, _CUDA_R_8I,
                t, r * t, beta.ctypes.data, out.data.ptr, _CUDA_R_32I, r, r * r, nb, _COMPUTE_32I, _GEMM_DEFAULT))
    return out


# ------------------------------------------------------------------------------------------------
# Stacked real GEMMs for the tensor-core modes
# ------------------------------------------------------------------------------------------------
def to_bf16(a):
    """float32 -> bfloat16 bits (uint16 array, round to nearest even): CuPy has no bfloat16 dtype,
    cuBLAS reads these bits as CUDA_R_16BF."""
    xp = get_xp(a)
    u = xp.ascontiguousarray(a, dtype=xp.float32).view(xp.uint32)
    return ((u + xp.uint32(0x7FFF) + ((u >> 16) & xp.uint32(1))) >> 16).astype(xp.uint16)


def _bf16_to_float(b):
    xp = get_xp(b)
    return (b.astype(xp.uint32) << 16).view(xp.float32)


def _store(a, precision):
    """float32 array -> the storage of ``precision``'s operands (fp16, bf16 bits, or float32)."""
    xp = get_xp(a)
    if precision in FP16:
        return a.astype(xp.float16)
    if precision == "bf16":
        return to_bf16(a)
    return xp.ascontiguousarray(a, dtype=xp.float32)


def stack_operator(g, precision):
    """Stacked real form of a complex operator batch (b, m, k) -> list of (b, 2m, 2k) operands:
    ``[[Dr, -Di], [Di, Dr]]`` in the storage of ``precision``; for tf32x3 / fp16x3 the [hi, lo] pair."""
    xp = get_xp(g)
    b, m, k = g.shape
    s = xp.empty((b, 2 * m, 2 * k), xp.float32)
    s[:, :m, :k] = g.real
    s[:, :m, k:] = -g.imag
    s[:, m:, :k] = g.imag
    s[:, m:, k:] = g.real
    return _parts(s, precision, axis=2)


def stack_rhs(b, precision, scale=None):
    """Stacked real form of a complex right-hand side (batch, k, n) -> list of (batch, 2k, n):
    ``[Br; Bi]`` (times ``scale``) in the storage of ``precision``; for tf32x3 / fp16x3 [hi, lo]."""
    xp = get_xp(b)
    nb, k, n = b.shape
    s = xp.empty((nb, 2 * k, n), xp.float32)
    if scale is None:
        s[:, :k] = b.real
        s[:, k:] = b.imag
    else:
        s[:, :k] = b.real * scale
        s[:, k:] = b.imag * scale
    return _parts(s, precision)


def _parts(s, precision, axis=1):
    """float32 stacked operand -> its list of parts in the precision's storage: [hi, lo] for tf32x3;
    for fp16x3 one array, hi and lo concatenated along ``axis`` ([lo | hi] columns for an operator,
    axis 2; [hi; lo] rows for a right-hand side, axis 1), the form :func:`stacked_matmul` takes."""
    if precision == "tf32x3":
        return list(split_tf32(s))
    if precision == "fp16x3":
        xp = get_xp(s)
        hi = s.astype(xp.float16)
        lo = (s - hi.astype(s.dtype)).astype(hi.dtype)
        return [xp.concatenate([lo, hi] if axis == 2 else [hi, lo], axis=axis)]
    return [_store(s, precision)]


def pow2_scale(b):
    """A power of two s (0-d array, no host sync) with max |Re b|, |Im b| * s in [0.5, 1]: scaling by it
    is exact and brings fp16 operands into range (fp16 overflows above 65504)."""
    xp = get_xp(b)
    m = xp.maximum(xp.abs(b.real).max(), xp.abs(b.imag).max())
    m = xp.where(m > 0, m, 1)
    return xp.exp2(-xp.ceil(xp.log2(m))).astype(xp.float32)


def _stored_to_float(a):
    xp = get_xp(a)
    if a.dtype == xp.uint16:
        return _bf16_to_float(a)
    return a.astype(xp.float32)


def _cublas_rgemm(a, b, c, precision, beta):
    """c = a @ b (+ beta c), row-major real batches: operands in ``precision``'s storage, fp32 out."""
    atype = {"fp16": _CUDA_R_16F, "fp16x3": _CUDA_R_16F, "bf16": _CUDA_R_16BF}.get(precision, _CUDA_R_32F)
    compute = _COMPUTE["tf32"] if precision in ("tf32", "tf32x3") else _COMPUTE["fp32"]
    return _gemm_ex(a, b, c, atype, _CUDA_R_32F, compute, np.float32, beta)


#: blocks of k that fp16x3's big term is summed in (see :func:`stacked_matmul`)
FP16X3_SPLIT = 2


def _fp16x3_matmul(a, b, out):
    """out = a_lo b_hi + a_hi b_lo + a_hi b_hi from the concatenated fp16x3 operands (GPU)."""
    k = a.shape[2] // 2
    ints = b.shape[1] == k                       # exact right-hand side: no b_lo
    gemm = dict(in_type=_CUDA_R_16F, out_type=_CUDA_R_32F, compute=_COMPUTE["fp32"], scalar_dtype=np.float32)
    if ints:
        _gemm_cols(a, 0, k, b, 0, out, beta=0, **gemm)            # a_lo b
    else:
        _gemm_cols(a, 0, 2 * k, b, 0, out, beta=0, **gemm)    # [a_lo | a_hi] [b_hi; b_lo]
    step = -(-k // FP16X3_SPLIT)
    for j0 in range(0, k, step):
        kk = min(step, k - j0)
        _gemm_cols(a, k + j0, kk, b, j0, out, beta=1, **gemm)    # a_hi b_hi, one block of k
    return out


def stacked_matmul(a_parts, b_parts, precision, *, out=None, b_exact=False):
    """[Re; Im] of the complex product, float32 (batch, 2m, n), from :func:`stack_operator` and
    :func:`stack_rhs` parts. tf32x3: a_hi b_hi + a_hi b_lo + a_lo b_hi (b_lo skipped if ``b_exact``).

    fp16x3 (parts: the operator [a_lo | a_hi] (b, m, 2k), the right-hand side [b_hi; b_lo] (b, 2k, n)
    or an exact b (b, k, n)): the two small terms in one GEMM over the concatenation (K = 2k), then
    a_hi b_hi in ``FP16X3_SPLIT`` GEMMs over consecutive blocks of k, each added in the epilogue.
    Why the split: the tensor cores add the products of each k-step into the fp32 accumulator with
    truncation, a bias that grows with the steps one accumulator takes; half the steps per
    accumulator halves it, and the error with it.

    NumPy (for tests of the layout only; the CPU has no tensor cores): float32 products of the
    operands rounded to the mode, which is what the tensor cores compute up to summation order.
    """
    xp = get_xp(a_parts[0], b_parts[0])
    a0, b0 = a_parts[0], b_parts[0]
    batch = max(a0.shape[0], b0.shape[0])
    shape = (batch, a0.shape[1], b0.shape[2])
    if xp is np:
        def rnd(x):
            x = _stored_to_float(x)
            return round_tf32(x) if precision in ("tf32", "tf32x3") else x
        if precision == "fp16x3":    # the same decomposition as on the GPU, in float32
            k = a0.shape[2] // 2
            lo, hi = rnd(a0[:, :, :k]), rnd(a0[:, :, k:])
            bh = rnd(b0[:, :k])
            res = np.matmul(lo, bh) + np.matmul(hi, bh)
            if b0.shape[1] == 2 * k:
                res = res + np.matmul(hi, rnd(b0[:, k:]))
        else:
            terms = [(0, 0)] + ([] if precision not in SPLIT else ([(1, 0)] + ([] if b_exact else [(0, 1)])))
            res = sum(np.matmul(rnd(a_parts[i]), rnd(b_parts[j])) for i, j in terms)
        if out is None:
            return res.astype(np.float32)
        out[...] = res
        return out
    if out is None:
        out = xp.empty(shape, xp.float32)
    if precision not in SPLIT:
        return _cublas_rgemm(a0, b0, out, precision, 0)
    if precision == "fp16x3":
        return _fp16x3_matmul(a0, b0, out)
    _cublas_rgemm(a_parts[1], b0, out, precision, 0)      # small terms first
    if not b_exact:
        _cublas_rgemm(a0, b_parts[1], out, precision, 1)
    _cublas_rgemm(a0, b0, out, precision, 1)
    return out
