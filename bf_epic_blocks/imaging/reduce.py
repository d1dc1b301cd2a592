"""The reductions that follow the imager's GEMMs: one pass over the GEMM output each.

* :func:`block_corr` -- direct route: for each polarisation block (p, q), the sum over groups of N
  consecutive samples of F_p conj(F_q) (|F_p|^2 when p = q), so a whole gulp gives one image per
  N samples without a Python loop and without temporaries the size of F.
* :func:`row_dot` -- covariance route: I_k = sum_a M[k, a] conj(D[k, a]) for M = D R, the image
  without forming D R D^H.

Both read the GEMM output in either layout the GEMMs produce (:mod:`.gemm`):

* ``complex``: complex (c, K, n) -- fp64/fp32 GEMMs;
* ``stacked``: float32 (c, 2, K, n), real parts then imaginary parts -- the tensor-core modes.

On the GPU each is one CUDA kernel (source below, launched through CuPy's RawKernel); on the CPU the
same sums in NumPy.
"""
from __future__ import annotations

import numpy as np

from ._xp import get_xp

__all__ = ["block_corr", "row_dot", "group_power", "products_from_blocks", "product_coefficients"]

# F element (row r = (c, k), column j) sits at F[c*sc + k*sk + j*es] (real) and + im_off (imag).
# One thread per output (c, b, k, g): consecutive threads take consecutive groups g of one row,
# so a warp reads one contiguous stretch of the row.
_BLOCK_CORR_SRC = r"""
extern "C" __global__ void bf_block_corr(
    const float* __restrict__ F, float2* __restrict__ out, const float* __restrict__ scale, const float sval,
    const int C, const int K, const int T, const int n, const int G, const int nblk,
    const int* __restrict__ bp, const int* __restrict__ bq,
    const long long sc, const long long sk, const long long im_off, const int es)
{
    // output: complex64 (G, C, nblk, K), times *scale
    long long idx = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)C * nblk * K * G;
    if (idx >= total) return;
    int g = (int)(idx % G);
    long long r = idx / G;
    int k = (int)(r % K); r /= K;
    int b = (int)(r % nblk);
    int c = (int)(r / nblk);
    int p = bp[b], q = bq[b];
    const float* row = F + c * sc + k * sk;
    const float* fp = row + ((long long)p * T + (long long)g * n) * es;
    const float* fq = row + ((long long)q * T + (long long)g * n) * es;
    float sr = 0.f, si = 0.f;
    if (es == 1 && (n & 3) == 0 && (T & 3) == 0 && (im_off & 3) == 0 && (sk & 3) == 0 && (sc & 3) == 0) {
        // stacked layout, aligned: 16-byte loads (the GEMM output is 256-byte aligned)
        const float4* pr = reinterpret_cast<const float4*>(fp);
        const float4* pi = reinterpret_cast<const float4*>(fp + im_off);
        const float4* qr = reinterpret_cast<const float4*>(fq);
        const float4* qi = reinterpret_cast<const float4*>(fq + im_off);
        for (int t = 0; t < (n >> 2); ++t) {
            float4 a = pr[t], ai = pi[t];
            if (p == q) {
                sr += a.x * a.x + a.y * a.y + a.z * a.z + a.w * a.w
                    + ai.x * ai.x + ai.y * ai.y + ai.z * ai.z + ai.w * ai.w;
            } else {
                float4 b2 = qr[t], bi = qi[t];
                sr += a.x * b2.x + a.y * b2.y + a.z * b2.z + a.w * b2.w
                    + ai.x * bi.x + ai.y * bi.y + ai.z * bi.z + ai.w * bi.w;
                si += ai.x * b2.x + ai.y * b2.y + ai.z * b2.z + ai.w * b2.w
                    - a.x * bi.x - a.y * bi.y - a.z * bi.z - a.w * bi.w;
            }
        }
    } else if (es == 2 && (n & 1) == 0 && (T & 1) == 0 && (sk & 3) == 0 && (sc & 3) == 0) {
        // complex layout, aligned: 16-byte loads of two complex values
        const float4* pv = reinterpret_cast<const float4*>(fp);
        const float4* qv = reinterpret_cast<const float4*>(fq);
        for (int t = 0; t < (n >> 1); ++t) {
            float4 a = pv[t];
            if (p == q) {
                sr += a.x * a.x + a.y * a.y + a.z * a.z + a.w * a.w;
            } else {
                float4 b2 = qv[t];
                sr += a.x * b2.x + a.y * b2.y + a.z * b2.z + a.w * b2.w;
                si += a.y * b2.x - a.x * b2.y + a.w * b2.z - a.z * b2.w;
            }
        }
    } else if (p == q) {
        for (int t = 0; t < n; ++t) {
            float a = fp[(long long)t * es], ai = fp[(long long)t * es + im_off];
            sr += a * a + ai * ai;
        }
    } else {
        for (int t = 0; t < n; ++t) {
            float a = fp[(long long)t * es], ai = fp[(long long)t * es + im_off];
            float b2 = fq[(long long)t * es], bi = fq[(long long)t * es + im_off];
            sr += a * b2 + ai * bi;
            si += ai * b2 - a * bi;
        }
    }
    float s = sval * (scale ? *scale : 1.f);
    out[(((long long)g * C + c) * nblk + b) * K + k] = make_float2(sr * s, si * s);
}
"""

# One warp per (c, k): lanes stride over the antennas, a shuffle reduction per block b.
# M element (c, k, b*A + a) at M[c*msc + k*msk + (b*A + a)*mes] (+ m_im for the imaginary part);
# D (complex64, (c, K, A)) at D[2*((c*K + k)*A + a)].
_ROW_DOT_SRC = r"""
extern "C" __global__ void bf_row_dot(
    const float* __restrict__ M, const float* __restrict__ D, float2* __restrict__ out,
    const float* __restrict__ scale, const float sval, const int C, const int K, const int A, const int nblk,
    const long long msc, const long long msk, const long long m_im, const int mes)
{
    // output: complex64 (C, nblk, K), times *scale
    long long warp = ((long long)blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    int lane = threadIdx.x & 31;
    if (warp >= (long long)C * K) return;
    int c = (int)(warp / K), k = (int)(warp % K);
    const float* mrow = M + c * msc + k * msk;
    const float* drow = D + 2 * ((long long)c * K + k) * A;
    for (int b = 0; b < nblk; ++b) {
        float sr = 0.f, si = 0.f;
        for (int a = lane; a < A; a += 32) {
            long long j = ((long long)b * A + a) * mes;
            float mr = mrow[j], mi = mrow[j + m_im];
            float dr = drow[2 * a], di = drow[2 * a + 1];
            sr += mr * dr + mi * di;          // Re(m conj(d))
            si += mi * dr - mr * di;          // Im(m conj(d))
        }
        for (int o = 16; o > 0; o >>= 1) {
            sr += __shfl_down_sync(0xffffffff, sr, o);
            si += __shfl_down_sync(0xffffffff, si, o);
        }
        if (lane == 0) {
            float s = sval * (scale ? *scale : 1.f);
            out[((long long)c * nblk + b) * K + k] = make_float2(sr * s, si * s);
        }
    }
}
"""

# Polarisation products from the block correlations in one pass: every product is a linear
# combination of Re and Im of the blocks (I = Re XX + Re YY, V = -2 Im XY, ...):
# out[g, c, p, k] = sum_b s[c, b] (a[p, b] Re corr[g, c, b, k] + i[p, b] Im corr[g, c, b, k]).
_PRODUCTS_SRC = r"""
// MAXB: correlation blocks held (2: the pols' own powers; 4: XX, YY, XY at most)
__device__ __forceinline__ float2 corr_at(const float2* p, long long i) { return p[i]; }
__device__ __forceinline__ float2 corr_at(const float* p, long long i) { return make_float2(p[i], 0.f); }

// One thread per output cell j of a channel c (grid.y strides over the channels) and a run of RUN
// groups g (grid.z): the pixel, the channel's scales and the weights are read once for the run, every
// block's value once for all products. (A thread per (g, c) row, re-reading the weights per row, ran
// latency-bound at a third of the memory's speed: 1.9 ms for a whole-band gulp on an H200.)
#define RUN 16
template <int MAXB, typename TC>
__device__ void products(const TC* __restrict__ corr, const float* __restrict__ s, const float* __restrict__ coef,
                         const float2* __restrict__ w, const int Cw, const int* __restrict__ gather,
                         float* __restrict__ out, const long long G, const int C, const int nblk, const int nprod,
                         const int K, const int Kout, const float fill)
{
    // SUB groups' values are requested before any is used: SUB x nblk loads in flight a thread
    constexpr int SUB = MAXB <= 2 ? 8 : 4;
    const int j = blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= Kout) return;
    const int k = gather ? gather[j] : j;
    const long long g0 = (long long)blockIdx.z * RUN, g1 = min(G, g0 + RUN);
    for (int c = blockIdx.y; c < C; c += gridDim.y) {
        if (k < 0) {
            for (long long g = g0; g < g1; ++g)
                for (int p = 0; p < nprod; ++p) out[((g * C + c) * nprod + p) * Kout + j] = fill;
            continue;
        }
        float2 wb[MAXB];
        float sb[MAXB];
#pragma unroll
        for (int b = 0; b < MAXB; ++b) {
            wb[b] = make_float2(0.f, 0.f);
            sb[b] = 0.f;
            if (b < nblk) {
                wb[b] = w ? w[((long long)(Cw == 1 ? 0 : c) * nblk + b) * K + k] : make_float2(1.f, 0.f);
                sb[b] = s[c * nblk + b];
            }
        }
        for (long long ga = g0; ga < g1; ga += SUB) {
            // every value of SUB groups requested first (the loads' latency overlapped), then used
            float2 z[SUB][MAXB];
#pragma unroll
            for (int u = 0; u < SUB; ++u)
#pragma unroll
                for (int b = 0; b < MAXB; ++b)
                    z[u][b] = (b < nblk && ga + u < g1)
                              ? corr_at(corr + ((ga + u) * C + c) * nblk * K + k, (long long)b * K)
                              : make_float2(0.f, 0.f);
#pragma unroll
            for (int u = 0; u < SUB; ++u) {
                if (ga + u >= g1) break;
                const long long row = (ga + u) * C + c;
                float zr[MAXB], zi[MAXB];
#pragma unroll
                for (int b = 0; b < MAXB; ++b) {
                    const float2 v = wb[b], q = z[u][b];
                    zr[b] = sb[b] * (q.x * v.x - q.y * v.y); zi[b] = sb[b] * (q.x * v.y + q.y * v.x);
                }
                for (int p = 0; p < nprod; ++p) {
                    float v = 0.f;
#pragma unroll
                    for (int b = 0; b < MAXB; ++b)
                        if (b < nblk) v += coef[(p * nblk + b) * 2] * zr[b] + coef[(p * nblk + b) * 2 + 1] * zi[b];
                    out[(row * nprod + p) * Kout + j] = v;
                }
            }
        }
    }
}

// complex block correlations; real ones (the fused integer modes' |F_p|^2: Im = 0)
extern "C" __global__ void bf_products(const float2* corr, const float* s, const float* coef, const float2* w,
                                       const int Cw, const int* gather, float* out, const long long G, const int C,
                                       const int nblk, const int nprod, const int K, const int Kout, const float fill)
{ products<4>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }
extern "C" __global__ void bf_products_real(const float* corr, const float* s, const float* coef, const float2* w,
                                            const int Cw, const int* gather, float* out, const long long G,
                                            const int C, const int nblk, const int nprod, const int K,
                                            const int Kout, const float fill)
{ products<4>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }
// the same for one or two blocks (the registers of two: more threads a SM, more loads in flight)
extern "C" __global__ void bf_products_real2(const float* corr, const float* s, const float* coef, const float2* w,
                                             const int Cw, const int* gather, float* out, const long long G,
                                             const int C, const int nblk, const int nprod, const int K,
                                             const int Kout, const float fill)
{ products<2>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }
"""

_KERNELS = {}


def _raw(name):
    if name not in _KERNELS:
        import cupy as cp
        src = {"bf_block_corr": _BLOCK_CORR_SRC, "bf_row_dot": _ROW_DOT_SRC, "bf_products": _PRODUCTS_SRC,
               "bf_products_real": _PRODUCTS_SRC, "bf_products_real2": _PRODUCTS_SRC}[name]
        _KERNELS[name] = cp.RawKernel(src, name)
    return _KERNELS[name]


def _layout(F, K, stacked):
    """(sc, sk, im_off, es, n) in float elements for a complex (c, K, n) or stacked (c, 2, K, n) array."""
    n = F.shape[-1]
    if stacked:
        return 2 * K * n, n, K * n, 1, n
    return 2 * K * n, 2 * n, 1, 2, n


def _scale_args(xp, scale):
    """(pointer, value) kernel arguments for ``scale``: a device scalar (read on the device: no host
    sync), a number, or None = 1. Small host->device copies would stall the host on every call."""
    if scale is None or isinstance(scale, (int, float, np.floating)):
        return np.uint64(0), np.float32(1.0 if scale is None else scale)
    return xp.asarray(scale, dtype=xp.float32).reshape(1), np.float32(1.0)


_INDEX_CACHE = {}


def device_ints(xp, values):
    """A cached int32 device array of ``values`` (a tuple): made once, not copied on every call."""
    dev = xp.cuda.runtime.getDevice() if xp.__name__ == "cupy" else None   # one copy per GPU
    key = (xp.__name__, dev, tuple(values))
    if key not in _INDEX_CACHE:
        _INDEX_CACHE[key] = xp.asarray(list(values), dtype=xp.int32)
    return _INDEX_CACHE[key]


def block_corr(F, blocks, n, *, npol, stacked=False, scale=None):
    """Sums over groups of ``n`` samples of F_p conj(F_q) for each block (p, q) of ``blocks``, times ``scale``.

    F : complex (c, K, npol * T) or float32 stacked (c, 2, K, npol * T); column j = p * T + t
        (p indexing the polarisations present in F).
    Returns complex (T // n, c, nblk, K) (complex64; complex128 for complex128 F); trailing samples
    that do not fill a group are ignored.
    """
    xp = get_xp(F)
    c = F.shape[0]
    K = F.shape[-2]
    T = F.shape[-1] // npol
    g = T // n
    if xp is np or F.dtype == xp.complex128:   # NumPy, or fp64 on the GPU: plain array code
        Fc = F[:, 0] + 1j * F[:, 1] if stacked else F
        Fc = Fc.reshape(c, K, npol, T)[..., :g * n].reshape(c, K, npol, g, n)
        out = xp.stack([(Fc[:, :, p] * xp.conj(Fc[:, :, q])).sum(-1) if p != q else
                        (Fc[:, :, p].real ** 2 + Fc[:, :, p].imag ** 2).sum(-1) for p, q in blocks], axis=1)
        out = xp.moveaxis(out, -1, 0)
        out = out.astype(xp.complex128 if F.dtype in (xp.complex128, xp.float64) else xp.complex64)
        return out if scale is None else out * scale
    F = xp.ascontiguousarray(F)
    fl = F.view(xp.float32) if F.dtype == xp.complex64 else F
    sc, sk, im_off, es, _ = _layout(F, K, stacked)
    nblk = len(blocks)
    out = xp.empty((g, c, nblk, K), xp.complex64)
    bp = device_ints(xp, [p for p, _ in blocks])
    bq = device_ints(xp, [q for _, q in blocks])
    total = c * nblk * K * g
    threads = 256
    _raw("bf_block_corr")(((total + threads - 1) // threads,), (threads,),
                          (fl, out, *_scale_args(xp, scale), np.int32(c), np.int32(K), np.int32(T), np.int32(n),
                           np.int32(g), np.int32(nblk), bp, bq, np.int64(sc), np.int64(sk), np.int64(im_off),
                           np.int32(es)))
    return out


def row_dot(M, D, nblk, *, stacked=False, scale=None):
    """I[c, b, k] = scale * sum_a M[c, k, b * A + a] conj(D[c, k, a]).

    M : complex (c, K, nblk * A) or float32 stacked (c, 2, K, nblk * A);  D : complex (c, K, A).
    Returns complex (c, nblk, K).
    """
    xp = get_xp(M, D)
    c, K, A = D.shape
    if xp is np or M.dtype == xp.complex128:
        Mc = M[:, 0] + 1j * M[:, 1] if stacked else M
        Mc = Mc.reshape(c, K, nblk, A)
        out = (Mc * xp.conj(D)[:, :, None, :]).sum(-1).transpose(0, 2, 1)
        return out if scale is None else out * scale
    M = xp.ascontiguousarray(M)
    D = xp.ascontiguousarray(D, dtype=xp.complex64)
    fl = M.view(xp.float32) if M.dtype == xp.complex64 else M
    sc, sk, im_off, es, _ = _layout(M, K, stacked)
    out = xp.empty((c, nblk, K), xp.complex64)
    threads = 256
    nwarps = c * K
    _raw("bf_row_dot")(((nwarps * 32 + threads - 1) // threads,), (threads,),
                       (fl, D.view(xp.float32), out, *_scale_args(xp, scale), np.int32(c), np.int32(K), np.int32(A),
                        np.int32(nblk), np.int64(sc), np.int64(sk), np.int64(im_off), np.int32(es)))
    return out


_RECIPES = {  # product -> {block: (coefficient of Re, coefficient of Im)}
    "XX": {(0, 0): (1, 0)}, "YY": {(1, 1): (1, 0)}, "XY": {(0, 1): (1, 0)}, "YX": {(0, 1): (1, 0)},
    "XYi": {(0, 1): (0, 1)}, "YXi": {(0, 1): (0, -1)}, "I": {(0, 0): (1, 0), (1, 1): (1, 0)},
    "Q": {(0, 0): (1, 0), (1, 1): (-1, 0)}, "U": {(0, 1): (2, 0)}, "V": {(0, 1): (0, -2)},
}


def product_coefficients(products, blocks):
    """(nprod, nblk, 2) float32: Re and Im coefficients of each block in each product (the one place,
    with :func:`bf_epic_blocks.imaging.products.combine`, where the Stokes convention lives in code)."""
    out = np.zeros((len(products), len(blocks), 2), np.float32)
    for p, name in enumerate(products):
        for blk, (a, b) in _RECIPES[name].items():
            out[p, blocks.index(blk)] = (a, b)
    return out


def products_from_blocks(corr, scale, coef, weight=None, gather=None, out=None):
    """Real products (..., C, nprod, K) = sum_b scale[c, b] (coef Re + coef Im) of weight * corr (..., C, nblk, K).

    corr : complex block correlations, or real ones (float32: the pols' own powers, Im = 0);
    scale : real (C, nblk); coef : :func:`product_coefficients`;
    weight : None, or complex (C|1, nblk, K) per-pixel factors (the pattern's B_p conj(B_q));
    gather : None, or int (N,) the pixel of each of N output cells (-1: no pixel, NaN there): the
        products placed on a grid in the same pass, (..., C, nprod, N) (:class:`.pixels.GridPlacement`);
    out : None, or a float32 array of the result's shape to write into (GPU).
    One CUDA kernel on the GPU (complex64 or float32 input), array code elsewhere."""
    xp = get_xp(corr)
    lead = corr.shape[:-3]
    C, nblk, K = corr.shape[-3:]
    nprod = coef.shape[0]
    real = xp is not np and corr.dtype == xp.float32
    if xp is np or not (real or corr.dtype == xp.complex64):
        c = xp.asarray(coef, dtype=corr.real.dtype)
        z = corr * scale[..., None]
        if weight is not None:
            z = z * weight
        res = xp.einsum("...cbk,pb->...cpk", z.real, c[..., 0]) + xp.einsum("...cbk,pb->...cpk", z.imag, c[..., 1])
        if gather is not None:
            gather = xp.asarray(gather)
            res = xp.where(gather >= 0, res[..., xp.maximum(gather, 0)], xp.asarray(np.nan, res.dtype))
        if out is not None:
            out[...] = res
            return out
        return res
    corr = xp.ascontiguousarray(corr)
    G = int(np.prod(lead)) if lead else 1
    kout = K if gather is None else int(gather.shape[0])
    shape = lead + (C, nprod, kout)
    if out is None:
        out = xp.empty(shape, xp.float32)
    elif out.shape != shape or out.dtype != xp.float32 or not out.flags.c_contiguous:
        raise ValueError(f"products_from_blocks: out must be C-contiguous float32 {shape}, got "
                         f"{out.dtype} {tuple(out.shape)}")
    if nblk > 4:
        raise ValueError(f"products_from_blocks: at most 4 correlation blocks, got {nblk}")
    if weight is not None:
        weight = xp.ascontiguousarray(weight, dtype=xp.complex64)
        if weight.shape[-2:] != (nblk, K) or weight.shape[0] not in (1, C):
            raise ValueError(f"products_from_blocks: weight must be (1|{C}, {nblk}, {K}), got {tuple(weight.shape)}")
    wp = weight if weight is not None else np.uint64(0)
    cw = np.int32(1 if weight is None else weight.shape[0])
    gp = xp.asarray(gather, dtype=xp.int32) if gather is not None else np.uint64(0)
    _raw(("bf_products_real2" if nblk <= 2 else "bf_products_real") if real else "bf_products")(
        ((kout + 255) // 256, max(1, min(C, 65535)), -(-G // 16)), (256,),
        (corr, xp.ascontiguousarray(scale, dtype=xp.float32), coef, wp, cw, gp, out, np.int64(G), np.int32(C),
         np.int32(nblk), np.int32(nprod), np.int32(K), np.int32(kout), np.float32(np.nan)))
    return out


def group_power(fp, fq=None, n=None):
    """Sums over groups of ``n`` samples along the last axis (any array namespace).

    fp, fq : complex (..., ntime) fields of polarisations p and q (fq None: p = q).
    Returns (..., ntime // n): float sum |fp|^2 (fq None) or complex sum fp conj(fq).
    Used for small arrays (autocorrelation sums); the beamformed fields go through :func:`block_corr`.
    """
    xp = get_xp(fp)
    t = fp.shape[-1]
    n = t if n is None else int(n)
    g = t // n
    shp = fp.shape[:-1] + (g, n)
    fp = fp[..., :g * n].reshape(shp)
    if fq is None:
        return (fp.real ** 2 + fp.imag ** 2).sum(axis=-1)
    return (fp * xp.conj(fq[..., :g * n].reshape(shp))).sum(axis=-1)


_MEAN_SRC = r"""
// out[i, j] = (sum_c x[i, c, j]) / C in float64, c in order: x (n, C, inner) float32 contiguous. A thread per
// (i, j): a warp reads 128 contiguous bytes a channel (CuPy's axis-1 reduction read the whole-band image
// gulp at ~1.8 TB/s on an H100)
extern "C" __global__ void bf_channel_mean(const float* __restrict__ x, double* __restrict__ out, const int C,
                                           const long long inner)
{
    const long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= inner) return;
    const float* p = x + (long long)blockIdx.y * C * inner + j;
    double s = 0.0;
#pragma unroll 8
    for (int c = 0; c < C; ++c) s += (double)p[(long long)c * inner];
    out[(long long)blockIdx.y * inner + j] = s / C;
}
"""


def channel_mean(x):
    """The mean over axis 1 (the channels) of x (n, C, ...), kept as an axis of 1, accumulated in float64:
    (n, 1, ...) float64 (NaN where any channel is NaN). On the GPU, a C-contiguous float32 ``x`` is one
    kernel (:data:`_MEAN_SRC`); elsewhere ``mean(axis=1, dtype=float64)``."""
    xp = get_xp(x)
    if xp is np or x.dtype != np.float32 or not x.flags.c_contiguous or x.ndim < 2 or x.shape[0] > 65535 \
            or x.shape[1] == 0:
        return x.mean(axis=1, keepdims=True, dtype=xp.float64)
    n, C = int(x.shape[0]), int(x.shape[1])
    inner = int(np.prod(x.shape[2:])) if x.ndim > 2 else 1
    out = xp.empty((n, 1) + tuple(x.shape[2:]), xp.float64)
    if n and inner:
        if "bf_channel_mean" not in _KERNELS:
            import cupy as cp
            _KERNELS["bf_channel_mean"] = cp.RawKernel(_MEAN_SRC, "bf_channel_mean")
        _KERNELS["bf_channel_mean"](((inner + 255) // 256, n), (256,), (x, out, np.int32(C), np.int64(inner)))
    return out
