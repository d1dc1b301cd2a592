"""Integer voltages into GEMM operands, in one pass each (NumPy, or a CUDA kernel through CuPy).

F-engine voltages arrive as 4- or 8-bit integers, (re, im) int8 pairs shaped (T, C, A, P, 2) after
ci4/ci8 unpacking: time outermost, the layout of a ring gulp. The GEMMs want antennas x time
matrices per channel. The functions here do the transpose together with everything else that must
happen on the way -- channel and antenna selection, zeroing flagged antenna-pols, the stacked
[re; im] split and the conversion to the GEMM's operand type -- so the data are read once and
written once (a 32 x 32 tile transpose through shared memory on the GPU; the CUDA kernels are in
``layout.cu`` beside this module):

* :func:`gram_rows` -- int8 rows for the exact covariance ``int_gram`` (rows in the input's own
  (antenna, pol, re/im) order, time padded to a multiple of 16 with zeros);
* :func:`direct_rhs` -- the direct route's right-hand side: complex (C', A', P' T), or stacked
  [Re; Im] (C', 2 A', P' T) in fp16 / bf16 bits / float32 for the tensor-core modes;
* :func:`cov_rhs` -- from the integer Gram sums W to the covariance route's right-hand side
  [R_b0 | R_b1 | ...] (weights, and a scale, applied), complex or stacked, in the same types.
"""
from __future__ import annotations

import numpy as np

from ..cuda import get_kernel, register
from ._xp import get_xp
from .reduce import device_ints

__all__ = ["gram_rows", "direct_rhs", "cov_rhs", "TPAD"]

TPAD = 16   # time padding of gram_rows (cuBLAS' integer kernels want multiples of 4; 16 keeps rows aligned)

#: kernel output type name -> the CUDA type of layout.cu's template kernels
_OUT_TYPES = {"int8": "i8", "float16": "__half", "bfloat16": "unsigned short", "float32": "float",
              "float64": "double"}
_NAMES = tuple(f"bf_{kind}<{t}>" for kind in ("transpose", "cov_rhs") for t in _OUT_TYPES.values())
_ZERO_W = {}


def _kernel(kind, out_type):
    """``bf_transpose`` or ``bf_cov_rhs`` of layout.cu for output type ``out_type`` (a key of _OUT_TYPES)."""
    return get_kernel("imaging/layout.cu", f"bf_{kind}<{_OUT_TYPES[out_type]}>", name_expressions=_NAMES)


register("imaging/layout.cu")


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
        cp.ascontiguousarray(pairs), out, np.int32(T), np.int32(Cin), np.int32(Ain), np.int32(P),
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
        get_kernel("imaging/layout.cu", "bf_gram_rows4", name_expressions=_NAMES)(
            ((R // 4 + 15) // 16, (Tp + 63) // 64, C), (256,), (
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
