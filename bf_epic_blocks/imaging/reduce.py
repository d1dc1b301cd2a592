"""The reductions that follow the imager's GEMMs: one pass over the GEMM output each.

* :func:`block_corr` -- direct route: for each polarisation block (p, q), the sum over groups of N
  consecutive samples of F_p conj(F_q) (|F_p|^2 when p = q), so a whole gulp gives one image per
  N samples without a Python loop and without temporaries the size of F.
* :func:`row_dot` -- covariance route: I_k = sum_a M[k, a] conj(D[k, a]) for M = D R, the image
  without forming D R D^H.

Both read the GEMM output in either layout the GEMMs produce (:mod:`.gemm`):

* ``complex``: complex (c, K, n) -- fp64/fp32 GEMMs;
* ``stacked``: float32 (c, 2, K, n), real parts then imaginary parts -- the tensor-core modes.

On the GPU each is one CUDA kernel (``reduce.cu`` beside this module gives each one's layout and
launch); on the CPU the same sums in NumPy.
"""
from __future__ import annotations

import numpy as np

from ..cuda import get_kernel, register
from ._xp import get_xp

__all__ = ["block_corr", "row_dot", "group_power", "products_from_blocks", "product_coefficients",
           "rows_nonzero"]


def _raw(name):
    return get_kernel("imaging/reduce.cu", name)


register("imaging/reduce.cu")


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


def channel_mean(x):
    """The mean over axis 1 (the channels) of x (n, C, ...), kept as an axis of 1, accumulated in float64:
    (n, 1, ...) float64 (NaN where any channel is NaN). On the GPU, a C-contiguous float32 ``x`` is one
    kernel (``bf_channel_mean``, ``reduce.cu``); elsewhere ``mean(axis=1, dtype=float64)``."""
    xp = get_xp(x)
    if xp is np or x.dtype != np.float32 or not x.flags.c_contiguous or x.ndim < 2 or x.shape[0] > 65535 \
            or x.shape[1] == 0:
        return x.mean(axis=1, keepdims=True, dtype=xp.float64)
    n, C = int(x.shape[0]), int(x.shape[1])
    inner = int(np.prod(x.shape[2:])) if x.ndim > 2 else 1
    out = xp.empty((n, 1) + tuple(x.shape[2:]), xp.float64)
    if n and inner:
        _raw("bf_channel_mean")(((inner + 255) // 256, n), (256,), (x, out, np.int32(C), np.int64(inner)))
    return out


def rows_nonzero(x):
    """bool (n, C): whether each (i, c) of x (n, C, ...) holds any value that is neither zero nor NaN
    (``(x > 0) | (x < 0)``, any over the trailing axes): a channel image that imaged anything. On the GPU, a
    C-contiguous float32 ``x`` is one kernel (``bf_rows_nonzero``, ``reduce.cu``) that stops reading a row
    at its first such value; elsewhere the expression itself."""
    xp = get_xp(x)
    n, C = int(x.shape[0]), int(x.shape[1])
    if xp is np or x.dtype != np.float32 or not x.flags.c_contiguous or x.ndim < 3:
        return ((x > 0) | (x < 0)).reshape(n, C, -1).any(axis=2)
    inner = int(np.prod(x.shape[2:]))
    out = xp.zeros((n, C), xp.uint8)
    if n * C and inner:
        _raw("bf_rows_nonzero")((n * C,), (256,), (x, out, np.int64(inner)))
    return out.view(xp.bool_)
