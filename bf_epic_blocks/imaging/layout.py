"""Integer voltages into GEMM operands, in one pass each (NumPy, or a CUDA kernel through CuPy).

F-engine voltages arrive as 4- or 8-bit integers, (re, im) int8 pairs shaped (T, C, A, P, 2) after
ci4/ci8 unpacking: time outermost, the layout of a ring gulp. The GEMMs want antennas x time
matrices per channel. The functions here do the transpose together with everything else that must
happen on the way -- channel and antenna selection, zeroing flagged antenna-pols, the stacked
[re; im] split and the conversion to the GEMM's operand type -- so the data are read once and
written once (a 32 x 32 tile transpose through shared memory on the GPU):

* :func:`gram_rows` -- int8 rows for the exact covariance ``int_gram`` (rows in the input's own
  (antenna, pol, re/im) order, time padded to a multiple of 16 with zeros);
* :func:`direct_rhs` -- the direct route's right-hand side: complex (C', A', P' T), or stacked
  [Re; Im] (C', 2 A', P' T) in fp16 / bf16 bits / float32 for the tensor-core modes;
* :func:`cov_rhs` -- from the integer Gram sums W to the covariance route's right-hand side
  [R_b0 | R_b1 | ...] (weights, and a scale, applied), complex or stacked, in the same types.
"""
from __future__ import annotations

import numpy as np

from ._xp import get_xp
from .reduce import device_ints

__all__ = ["gram_rows", "direct_rhs", "cov_rhs", "TPAD"]

TPAD = 16   # time padding of gram_rows (cuBLAS' integer kernels want multiples of 4; 16 keeps rows aligned)

_COMMON = r"""
#include <cuda_fp16.h>
typedef signed char i8;
__device__ __forceinline__ void put(double v, float* p) { *p = (float)v; }
__device__ __forceinline__ void put(double v, double* p) { *p = v; }
__device__ __forceinline__ void put(double v, __half* p) { *p = __float2half_rn((float)v); }
__device__ __forceinline__ void put(double v, i8* p) { *p = (i8)v; }
__device__ __forceinline__ float get(const float* p) { return *p; }
__device__ __forceinline__ double get(const double* p) { return *p; }
__device__ __forceinline__ float get(const __half* p) { return __half2float(*p); }
__device__ __forceinline__ float get(const i8* p) { return (float)*p; }
__device__ __forceinline__ float get(const unsigned short* p) { return __uint_as_float(((unsigned int)*p) << 16); }
__device__ __forceinline__ void put(double v, unsigned short* p) {   // bfloat16 bits, round to nearest even
    unsigned int u = __float_as_uint((float)v);
    *p = (unsigned short)((u + 0x7FFFu + ((u >> 16) & 1u)) >> 16);
}
"""

# Tile transpose: input element (t, c, a, p, h) of the int8 pairs, with c = chan[c'], a = ant[a'],
# p = pols[p']; r' = (a' * P' + p') * 2 + h enumerates one channel's selected values. A block of
# 32 x 8 threads moves a 32 (t) x 32 (r') tile: coalesced reads along r', coalesced writes along t.
# Output offset: c' osc + a' osa + p' osp + h osh + t ost.
_TRANSPOSE = _COMMON + r"""
extern "C" __global__ void NAME(
    const i8* __restrict__ x, OUT_T* __restrict__ out,
    const int T, const int Cin, const int Ain, const int P,
    const int C, const int A, const int Pp, const int Tout,
    const int* __restrict__ chan, const int* __restrict__ ant, const int* __restrict__ pols,
    const unsigned char* __restrict__ live,
    const long long osc, const long long osa, const long long osp, const long long osh, const long long ost)
{
    __shared__ float tile[32][33];
    const int R = A * Pp * 2;
    const int c = blockIdx.z;
    const int r0 = blockIdx.x * 32, t0 = blockIdx.y * 32;
    const int tx = threadIdx.x, ty = threadIdx.y;
    const long long tstride = (long long)Cin * Ain * P * 2;      // bytes between samples
    // load: this thread's column r = r0 + tx is fixed; decode it (and its gathers) once
    {
        const int r = r0 + tx;
        bool ok = r < R;
        long long base = 0;
        if (ok) {
            int h = r & 1, q = r >> 1, pp = q % Pp, a = q / Pp;
            ok = live[((long long)c * A + a) * Pp + pp] != 0;
            base = (((long long)chan[c] * Ain + ant[a]) * P + pols[pp]) * 2 + h;
        }
        for (int j = ty; j < 32; j += 8) {
            int t = t0 + j;
            tile[j][tx] = (ok && t < T) ? (float)x[(long long)t * tstride + base] : 0.f;
        }
    }
    __syncthreads();
    // store: this thread's time t = t0 + tx is fixed; rows r0 + j
    const int t = t0 + tx;
    if (t >= Tout) return;
    OUT_T* ot = out + c * osc + t * ost;
    for (int j = ty; j < 32; j += 8) {
        int r = r0 + j;
        if (r < R) {
            int h = r & 1, q = r >> 1, pp = q % Pp, a = q / Pp;
            put(tile[tx][j], ot + a * osa + pp * osp + h * osh);
        }
    }
}
"""

# Covariance right-hand side from the integer Gram sums W (c, R, R), rows r = (a * P + p) * 2 + h
# (all pols of the input): for block b = (p, q) and antennas a, a2
#   R_pq[a, a2] = W[(a,p,0),(a2,q,0)] + W[(a,p,1),(a2,q,1)] + i (W[(a,p,1),(a2,q,0)] - W[(a,p,0),(a2,q,1)])
# times w_p[a] conj(w_q[a2]) * scale, written to out at c osc + a osa + (b A + a2) oes (+ o_im: imag).
_COV_RHS = _COMMON + r"""
extern "C" __global__ void NAME(
    const int* __restrict__ W, OUT_T* __restrict__ out, const double* __restrict__ w,
    const int C, const int A, const int P, const int nblk,
    const int* __restrict__ bp, const int* __restrict__ bq, const double scale, const int unit,
    const long long osc, const long long osa, const long long oes, const long long o_im,
    double* __restrict__ diag, OUT_T* __restrict__ lo)
{
    long long idx = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)C * A * nblk * A;
    if (idx >= total) return;
    int a2 = (int)(idx % A); long long r = idx / A;
    int b = (int)(r % nblk); r /= nblk;
    int a = (int)(r % A); int c = (int)(r / A);
    int p = bp[b], q = bq[b];
    long long R = (long long)A * P * 2;
    const int* Wc = W + (long long)c * R * R;
    long long ra = ((long long)a * P + p) * 2, rb = ((long long)a2 * P + q) * 2;
    // int64 sums: exact, then double (exact below 2^53)
    double re = (double)((long long)Wc[ra * R + rb] + (long long)Wc[(ra + 1) * R + rb + 1]);
    double im = (double)((long long)Wc[(ra + 1) * R + rb] - (long long)Wc[ra * R + rb + 1]);
    if (!unit) {   // w_p[a] R conj(w_q[a2]); w is complex128 (c, A, P) as double pairs
        const double* wa = w + 2 * (((long long)c * A + a) * P + p);
        const double* wb = w + 2 * (((long long)c * A + a2) * P + q);
        double xr = wa[0] * re - wa[1] * im, xi = wa[0] * im + wa[1] * re;       // w_a * R
        re = xr * wb[0] + xi * wb[1];                                            // * conj(w_b)
        im = xi * wb[0] - xr * wb[1];
    }
    if (diag != 0 && a == a2) {   // the same-antenna term leaves the GEMM; the caller adds it exactly
        double* d = diag + 2 * (((long long)c * nblk + b) * A + a);
        d[0] = re; d[1] = im;
        re = 0.0; im = 0.0;
    }
    long long off = c * osc + a * osa + ((long long)b * A + a2) * oes;
    put(re * scale, out + off);
    put(im * scale, out + off + o_im);
    if (lo != 0) {                // split storage: lo = v - hi, in the same type (fp16x3)
        put(re * scale - (double)get(out + off), lo + off);
        put(im * scale - (double)get(out + off + o_im), lo + off + o_im);
    }
}
"""

# gram_rows when nothing is selected or flagged: a plain batched byte transpose (T, C, R) -> (C, R, Tp),
# moved as 32-bit words (4 bytes of r read, 4 bytes of t written per thread and access) through a
# 64 x 64-byte shared tile -- the byte-per-thread kernel above moved too little per transaction
# (78 us for case P's 16 MB on an H100).
_GRAM_ROWS4 = r"""
extern "C" __global__ void bf_gram_rows4(
    const unsigned int* __restrict__ x, unsigned int* __restrict__ out,
    const int T, const int C, const int R4, const int Tp4)
{
    __shared__ unsigned char tile[64][65];           // [t][r byte]
    const int c = blockIdx.z;
    const int w0 = blockIdx.x * 16, t0 = blockIdx.y * 64;
    for (int i = threadIdx.x; i < 64 * 16; i += blockDim.x) {
        const int tt = i >> 4, w = i & 15, t = t0 + tt, r4 = w0 + w;
        unsigned int v = 0;
        if (t < T && r4 < R4) v = x[((long long)t * C + c) * R4 + r4];
        tile[tt][4 * w] = v & 0xffu;
        tile[tt][4 * w + 1] = (v >> 8) & 0xffu;
        tile[tt][4 * w + 2] = (v >> 16) & 0xffu;
        tile[tt][4 * w + 3] = v >> 24;
    }
    __syncthreads();
    const long long R = 4LL * R4;
    for (int i = threadIdx.x; i < 64 * 16; i += blockDim.x) {
        const int rr = i >> 4, w = i & 15;
        const long long r = 4LL * w0 + rr;
        const int t4 = (t0 >> 2) + w;
        if (r < R && t4 < Tp4) {
            out[((long long)c * R + r) * Tp4 + t4] = (unsigned int)tile[4 * w][rr]
                | ((unsigned int)tile[4 * w + 1][rr] << 8) | ((unsigned int)tile[4 * w + 2][rr] << 16)
                | ((unsigned int)tile[4 * w + 3][rr] << 24);
        }
    }
}
"""

_OUT_TYPES = {"int8": "i8", "float16": "__half", "bfloat16": "unsigned short", "float32": "float",
              "float64": "double"}
_KERNELS = {}
_ZERO_W = {}


def _kernel(kind, out_type):
    key = (kind, out_type)
    if key not in _KERNELS:
        import cupy as cp
        name = f"bf_{kind}_{out_type}"
        src = {"transpose": _TRANSPOSE, "cov_rhs": _COV_RHS}[kind]
        src = src.replace("NAME", name).replace("OUT_T", _OUT_TYPES[out_type])
        _KERNELS[key] = cp.RawKernel(src, name)
    return _KERNELS[key]


def _storage(precision, xp):
    """(array dtype, kernel output type name) of a precision's stacked operands."""
    return {"fp16": (xp.float16, "float16"), "fp16x3": (xp.float16, "float16"),
            "bf16": (xp.uint16, "bfloat16")}.get(precision, (xp.float32, "float32"))


def _select_np(pairs, sel, pols):
    """NumPy: (T, C', A', P', 2) float32 of the selected channels, antennas, pols; flagged ones zeroed."""
    x = pairs
    if sel.ant is not None:
        x = x[:, :, sel.ant]
    if sel.chan is not None:
        x = x[:, sel.chan]
    x = x[:, :, :, list(pols)].astype(np.float32)
    if sel.live is not None:
        x = x * sel.live[None, :, :, list(pols), None]
    return x


def _transpose_gpu(pairs, sel, pols, out, out_type, T, Tout, strides):
    import cupy as cp
    Tin, Cin, Ain, P, _ = pairs.shape
    C = Cin if sel.chan is None else len(sel.chan_list)
    A = Ain if sel.ant is None else len(sel.ant_list)
    Pp = len(pols)
    chan = sel.device_index("chan", C)
    ant = sel.device_index("ant", A)
    polsd = device_ints(cp, pols)
    live = sel.device_live(pols, C, A)
    R = A * Pp * 2
    grid = ((R + 31) // 32, (Tout + 31) // 32, C)
    _kernel("transpose", out_type)(grid, (32, 8), (
        cp.ascontiguousarray(pairs), out, np.int32(T), np.int32(Cin), np.int32(Ain), np.int32(P), np.int32(C),
        np.int32(A), np.int32(Pp), np.int32(Tout), chan, ant, polsd, live,
        *(np.int64(s) for s in strides)))
    return out


def gram_rows(pairs, sel):
    """int8 (C', A' P 2, Tp): per channel the rows (antenna, pol, re/im) over time, flagged values
    zeroed, time zero-padded to Tp = a multiple of :data:`TPAD` (zero samples change no sum).
    ``sel``: the operator's selection (kept channels and antennas, live mask); all pols are kept."""
    xp = get_xp(pairs)
    T, _, _, P, _ = pairs.shape
    pols = tuple(range(P))
    if xp is np:
        x = _select_np(pairs, sel, pols)                    # (T, C', A', P, 2)
        C, A = x.shape[1], x.shape[2]
        return np.ascontiguousarray(x.transpose(1, 2, 3, 4, 0)).reshape(C, A * P * 2, T).astype(np.int8)
    C = pairs.shape[1] if sel.chan is None else len(sel.chan_list)
    A = pairs.shape[2] if sel.ant is None else len(sel.ant_list)
    Tp = -(-T // TPAD) * TPAD
    out = xp.empty((C, A * P * 2, Tp), xp.int8)
    R = A * P * 2
    if sel.chan is None and sel.ant is None and sel.live is None and pairs.dtype == xp.int8 \
            and pairs.flags.c_contiguous and R % 4 == 0 and pairs.data.ptr % 4 == 0:
        if "gram_rows4" not in _KERNELS:
            _KERNELS["gram_rows4"] = xp.RawKernel(_GRAM_ROWS4, "bf_gram_rows4")
        _KERNELS["gram_rows4"](((R // 4 + 15) // 16, (Tp + 63) // 64, C), (256,), (
            pairs, out, np.int32(T), np.int32(C), np.int32(R // 4), np.int32(Tp // 4)))
        return out
    return _transpose_gpu(pairs, sel, pols, out, "int8", T, Tp,
                          (A * P * 2 * Tp, P * 2 * Tp, 2 * Tp, Tp, 1))


def direct_rhs(pairs, sel, pols, precision, stacked):
    """The direct route's right-hand side from integer pairs (unit weights: values stay integers).

    stacked False: complex (C', A', P' T) (complex64; complex128 for fp64), columns p' T + t.
    stacked True: [Re; Im] (C', 2 A', P' T) in the precision's operand storage (fp16, bf16 bits,
    float32). NumPy always returns the complex form.
    """
    xp = get_xp(pairs)
    T = pairs.shape[0]
    Pp = len(pols)
    cdt = xp.complex128 if precision == "fp64" else xp.complex64
    if xp is np:
        x = _select_np(pairs, sel, pols)                    # (T, C', A', P', 2)
        z = (x[..., 0] + 1j * x[..., 1]).astype(cdt)
        C, A = z.shape[1], z.shape[2]
        return np.ascontiguousarray(z.transpose(1, 2, 3, 0)).reshape(C, A, Pp * T)
    C = pairs.shape[1] if sel.chan is None else len(sel.chan_list)
    A = pairs.shape[2] if sel.ant is None else len(sel.ant_list)
    if stacked:
        dt, name = _storage(precision, xp)
        out = xp.empty((C, 2 * A, Pp * T), dt)
        return _transpose_gpu(pairs, sel, pols, out, name, T, T, (2 * A * Pp * T, Pp * T, T, A * Pp * T, 1))
    out = xp.empty((C, A, Pp * T), cdt)
    fl = out.view(xp.float64 if cdt == xp.complex128 else xp.float32)
    _transpose_gpu(pairs, sel, pols, fl, "float64" if cdt == xp.complex128 else "float32", T, T,
                   (2 * A * Pp * T, 2 * Pp * T, 2 * T, 1, 2))
    return out


def cov_rhs(W, weights, blocks, npol_in, precision, stacked, scale=1.0, unit=False, nodiag=False):
    """[R_b0 | R_b1 | ...] * scale from integer Gram sums, weights applied.

    W : (C', R, R) int32 (GPU) or float64 (CPU) sums of :func:`gram_rows` products, R = A (npol_in) 2.
    weights : complex (C', A, npol_in);  blocks : (p, q) pairs;  unit : weights are all 0/1 (skip them;
    flagged antennas are already zero in W).
    nodiag : leave the same-antenna terms R_pq[a, a] out (zeros) and return them separately, weighted
    and unscaled, complex128 (C', nblk, A): the caller adds their exact contribution, so that the
    low-precision GEMM carries only the cross-correlations -- far smaller than the autocorrelations
    in noise-dominated data, so the GEMM's rounding is relative to a smaller quantity.
    Returns a list of parts and the diagonal (None unless ``nodiag``): parts are [complex (C', A, nblk A)]
    (complex64, complex128 for fp64), or the stacked (C', 2 A, nblk A) operand in the precision's
    storage -- for ``fp16x3`` (C', 4 A, nblk A), rows [hi; lo] with lo = value - hi.
    """
    xp = get_xp(W)
    C, R, _ = W.shape
    A = R // (2 * npol_in)
    nblk = len(blocks)
    cdt = xp.complex128 if precision == "fp64" else xp.complex64
    if xp is np or W.dtype != xp.int32:
        Wr = W.reshape(C, A, npol_in, 2, A, npol_in, 2)
        cols, diags = [], []
        ii = xp.arange(A)
        for p, q in blocks:
            re = Wr[:, :, p, 0, :, q, 0] + Wr[:, :, p, 1, :, q, 1]
            im = Wr[:, :, p, 1, :, q, 0] - Wr[:, :, p, 0, :, q, 1]
            r = re + 1j * im
            if not unit:
                r = weights[:, :, p, None] * r * xp.conj(weights[:, None, :, q])
            if nodiag:
                diags.append(r[:, ii, ii].astype(xp.complex128))
                r[:, ii, ii] = 0
            cols.append(r * scale)
        rhs = xp.concatenate(cols, axis=2).astype(cdt)
        diag = xp.stack(diags, axis=1) if nodiag else None
        if stacked:
            from .gemm import stack_rhs
            return stack_rhs(rhs, precision), diag
        return [rhs], diag
    import cupy as cp
    dev = cp.cuda.runtime.getDevice()
    if unit:   # unit weights are not read: no copy (small, but a kernel and host time on every image)
        if dev not in _ZERO_W:
            _ZERO_W[dev] = cp.zeros(2, cp.float64)
        w = _ZERO_W[dev]
    else:
        w = cp.ascontiguousarray(weights, dtype=cp.complex128).view(cp.float64)
    bp = device_ints(cp, [p for p, _ in blocks])
    bq = device_ints(cp, [q for _, q in blocks])
    total = C * A * nblk * A
    lo = None
    if stacked:
        dt, name = _storage(precision, xp)
        split = precision == "fp16x3"          # [hi; lo] rows in one array (gemm.stacked_matmul's form)
        out = xp.empty((C, (4 if split else 2) * A, nblk * A), dt)
        strides = ((4 if split else 2) * A * nblk * A, nblk * A, 1, A * nblk * A)
        if split:
            lo = np.uintp(out.data.ptr + 2 * A * nblk * A * out.itemsize)
        target = out
    else:
        out = xp.empty((C, A, nblk * A), cdt)
        name = "float64" if cdt == xp.complex128 else "float32"
        target = out.view(xp.float64 if cdt == xp.complex128 else xp.float32)
        strides = (2 * A * nblk * A, 2 * nblk * A, 2, 1)
    diag = xp.empty((C, nblk, A), xp.complex128) if nodiag else None
    null = np.uintp(0)
    _kernel("cov_rhs", name)(((total + 255) // 256,), (256,), (
        cp.ascontiguousarray(W), target, w, np.int32(C), np.int32(A), np.int32(npol_in), np.int32(nblk), bp, bq,
        np.float64(scale), np.int32(1 if unit else 0), *(np.int64(s) for s in strides),
        null if diag is None else diag.view(xp.float64), null if lo is None else lo))
    return [out], diag
