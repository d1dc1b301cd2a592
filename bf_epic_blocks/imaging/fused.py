"""The direct route's high-cadence imaging in one kernel: integer tensor-core GEMM with |F|^2 in its epilogue.

Regime B (one image per 16 samples) spends its time after the GEMM when the field F = D X reaches
memory: F is ~0.4-0.8 GB per 16-channel gulp, written by the GEMM and read back to square and sum,
a pass about as long as the GEMM itself. This module never lets F leave the registers.

**Operands.** 4-bit voltages are exact int8. The operator D = G w (geometry times the folded gains,
one row per pixel) is scaled per pixel row by s_k = max_a max(|Re D_ka|, |Im D_ka|) and written as
``pieces`` int8 numbers in base ``b``:

    D_ka / s_k * 127 = q1 + q2 / b + q3 / b^2 (+ rounding),   |q_i| <= 127

so that  D X * 127 b^(pieces-1) / s_k = b^(pieces-1) Q1 X + ... + Q_pieces X  is an *integer*,
summed exactly in int32 by the integer tensor cores (s8 x s8 -> s32): the kernel runs the
K loop once per piece and multiplies its int32 accumulators by b between pieces, so one set of
accumulators serves every piece. b is the largest (<= 254 for two pieces, <= 63 for three; one piece has none) with
no int32 overflow for 4-bit voltages: |acc| <= sum_k |x_k| * 127 (b^(p-1) + ... + 1) < 2^31.
Larger samples (8-bit data) are checked on the device as they are laid out: any |x| above what the
accumulators can hold (:func:`bases`) turns that call's images to NaN -- never a silently wrong image.

=========  ==================================  ================================  ==================
mode       operator resolution (of s_k)        int8 MMAs per complex MAC          image error, case P
=========  ==================================  ================================  ==================
``i8x1``   1 / 127 = 7.9e-3                    4 (one piece of the 4 real ones)   3.5e-4
``i8x2``   1 / (127 * 254) = 3.1e-5            8 (two pieces of the 4 real ones)  3.1e-6
``i8x3``   1 / (127 * 63^2) = 2.0e-6           12                                 3.5e-7
=========  ==================================  ================================  ==================

i8x1 is for searches: its rounding (1/sqrt(12) of a step, rms) makes each pixel's beam a slightly
different beam, so a pixel's time series keeps its noise statistics and a burst its place, while the
images' error beside a bright source is the largest of the integer modes (its bound: measured.json).

(fp16 operands, for comparison: 2^-11 = 4.9e-4 relative.) After the integer GEMM, F is converted
to float32 (6e-8 relative) and squared, and each 16 columns (16 samples of one pol) are summed in the
epilogue: the kernel writes sum_t |F_kt|^2 per pixel, pol and 16-sample unit, scaled by
(s_k / (127 b^(pieces-1)))^2.

**Layout.** A: (C, PA, pieces, M, KD) int8, M = 2 Kpad rows: each run of 16 rows holds the real
rows of 8 pixels then their imaginary rows (so one thread's accumulator fragment holds Re and Im of
the same pixel), KD = 2 Apad with column 2a + (0 re | 1 im) -- the order of the (re, im) int8 pairs
the voltages come in. Real row of pixel k: (Re D_ka, -Im D_ka) on (Re x_a, Im x_a); imaginary row:
(Im D_ka, Re D_ka). PA = 1 when both pols share the gains, else 2. Kpad: pixels rounded up to 64;
Apad: antennas rounded up to 64. B: (C, P' Tp, KD) int8, column p' Tp + t, Tp = T rounded up to
a whole block of 128 columns (zero samples beyond T).

**Kernels** (CUDA sources beside this module, loaded by :mod:`bf_epic_blocks.cuda`; each file's
header gives its shapes and launch geometry). Both take 128-row x 128-column blocks of (pixel rows,
samples) and keep B whole in shared memory, so that the pieces after the first reread only A:

* ``fused_hopper.cu`` (compute capability 9.0, compiled for sm_90a; :data:`HOPPER_CONFIG`): two
  warpgroups, each ``wgmma.mma_async m64n128k32 s32.s8.s8`` on 128-byte-swizzled shared memory,
  128-byte K stages. The operands are stored in 16-KB tiles already in that swizzled order
  (:func:`tile_operator`, and the layout kernels' ``tiled`` output), so one thread of a producer
  warpgroup brings each stage in with one bulk copy (``cp.async.bulk``) counted on an mbarrier, and the
  MMA warps free stages by mbarriers of their own. Each MMA warpgroup holds two sets of accumulators
  and squares and sums one row tile while the MMAs of the next run: the int32 -> float32 conversions
  of the epilogue run at a quarter of the FP32 rate, and the tensor cores would otherwise wait for
  them. Its accumulator fragment has the mma.sync layout per 8 columns, so the epilogue is the same.
  With ``grid`` (:func:`fused_power`) the same kernel adds each pol's image straight onto a grid.
* ``fused.cu`` everywhere else, and on Hopper for arrays whose B does not fit the Hopper kernel's
  shared memory (:data:`PORTABLE_CONFIG`): four warps of 64 x 64, ``mma.sync m16n8k32`` with
  ``ldmatrix`` fragment loads (double-buffered), four 64-byte K stages; B staged with A when even
  this kernel cannot hold it whole.
* ``fused_layout.cu``: the voltages (int8 pairs or ci4 bytes) into B, plain or tiled.
* ``quantise.cu``: the operator into A's pieces and row scales, plain or tiled, one launch for every
  channel (:func:`quantise_operator`), so a new gain solution costs the imager's thread a few launches.
"""
from __future__ import annotations

import math

import numpy as np

from ..cuda import get_kernel, register
from ._xp import Workspace, get_xp, to_numpy

__all__ = ["FUSED", "PIECES", "bases", "quantise_operator", "padded_ntime", "layout_voltages", "fused_power",
           "reference_power", "kernel_config", "FusedOperator"]

#: the fused modes and their number of int8 pieces
PIECES = {"i8x1": 1, "i8x2": 2, "i8x3": 3}
FUSED = tuple(PIECES)
_BASE0 = {1: 1, 2: 254, 3: 63}      # one piece has no base: b^0 = 1 scales the only piece
BM, BN = 128, 128   # default block tile (rows, columns): Kpad is a multiple of BM / 2
_INT32_MAX = 2 ** 31 - 1


def bases(pieces: int, kd: int) -> tuple[int, int]:
    """(b, xmax) for ``pieces`` int8 pieces and KD = 2 Apad: the base, and the largest |sample| whose
    sums cannot overflow int32 (at least 8, so 4-bit voltages are always exact; at most 128)."""
    return int_bases(pieces, kd, 128, f"{kd // 2} antennas")


def int_bases(pieces, terms, cap, what):
    """(b, xmax): the largest base b (from :data:`_BASE0`) for which a sum of ``terms`` products of an operator
    of ``pieces`` int8 pieces (|q| <= 127) and samples |x| <= xmax fits int32 with xmax >= 8, and that xmax (at
    most ``cap``); ``what`` names the array in the error raised where no base fits."""
    if pieces not in _BASE0:
        raise ValueError(f"pieces must be one of {tuple(_BASE0)}, got {pieces!r}")
    b = _BASE0[pieces]
    while True:
        cmax = 127 * sum(b ** i for i in range(pieces))
        xmax = _INT32_MAX // (cmax * terms)
        if xmax >= 8 or b <= 2:
            break
        b -= 1
    if xmax < 8:
        raise ValueError(f"{what} are too many for int32 sums of {pieces} int8 pieces")
    return b, min(int(xmax), cap)


def _pad(n, m):
    return -(-n // m) * m


#: bytes of one chunk of an operator that :func:`quantise_operator` must cast to complex64 on a GPU first
#: (a complex64 operator, the fused modes' own, is read as it is, every channel in one launch)
_CHUNK_BYTES_GPU = 64 * 2**20
#: bytes of complex64 phases formed at once where an operator does not hold its phases (:class:`FusedOperator`)
_REFORM_BYTES_GPU = 256 * 2**20


def pol_sets(weights_host) -> int:
    """Sets of pieces an operator needs for host weights (C, A, P): one where the pols' weights agree
    everywhere (or P = 1), else P."""
    P = int(weights_host.shape[-1])
    return 1 if P == 1 or bool(np.all(weights_host == weights_host[..., :1])) else P


def reform_channels(npix, nant):
    """Channels whose complex64 phases :class:`FusedOperator` forms at once where an operator does not hold
    them (:data:`_REFORM_BYTES_GPU` of them, at least one)."""
    return max(1, _REFORM_BYTES_GPU // (int(npix) * max(1, int(nant)) * 8))


def operand_shape(C, PA, K, nant_in, pieces, tiled):
    """Shape of the int8 pieces :func:`quantise_operator` makes (int8: its bytes are its size): ``C``
    channels, ``PA`` pol sets, ``K`` pixels, ``nant_in`` input antennas; (C, PA, 2 Kpad/128, pieces, KD/128,
    16384) tiled for the Hopper kernel, else (C, PA, pieces, 2 Kpad, KD), Kpad = K and KD = 2 nant_in
    padded to 64 and 128."""
    Kpad, KD = _pad(K, 64), 2 * _pad(nant_in, 64)
    return (C, PA, 2 * Kpad // 128, pieces, KD // 128, TILE) if tiled else (C, PA, pieces, 2 * Kpad, KD)


def operand_bytes(C, PA, K, nant_in, pieces):
    """Bytes of what :func:`quantise_operator` returns for these sizes: its int8 pieces (tiled or not, the
    same bytes) and a float32 scale per padded row."""
    return math.prod(operand_shape(C, PA, K, nant_in, pieces, False)) + 4 * C * PA * _pad(K, 64)


def gpu_chunk_channels(K, nant_in, chunk=16):
    """Channels :func:`quantise_operator` quantises at once on a GPU: at least ``chunk``, and as many as
    :data:`_CHUNK_BYTES_GPU` of padded complex64 operator hold."""
    return max(int(chunk), _CHUNK_BYTES_GPU // (_pad(K, 64) * _pad(nant_in, 64) * 8))


def quantise_operator(G, weights, keep_index, nant_in, pieces, *, chunk=16, tiled=False, out=None, weights_host=None,
                      first=0, g_first=0):
    """The operator as int8 pieces in the kernel's layout (module docstring).

    G : complex (C, K, A_kept) geometric operator (live channels);  weights : complex (C, A_kept, P)
    folded gains (0 = flagged);  keep_index : (A_kept,) input antenna of each kept antenna;
    nant_in : antennas in the voltages.  Returns (A int8 (C, PA, pieces, M, KD), oscale float32
    (C, PA, Kpad), base, xmax). Works in G's array namespace, ``chunk`` channels at a time.
    tiled : A in the Hopper kernel's tiles instead, (C, PA, M/128, pieces, KD/128, 16384)
    (:func:`tile_operator`), made chunk by chunk (no second whole copy of A).
    out : (A, oscale) arrays of those shapes to write into (an operator's pixels moved), or None.
    On a GPU one kernel makes every channel (:func:`_quantise_gpu`; ``chunk`` only where G must be cast).
    weights_host : the same weights as a NumPy array, or None (read back from the device: a wait for the
        stream's queued work, which an imager folding in a new solution must not make).
    first : with ``out``, on a GPU, only pixels ``first`` .. K - 1 (and the padding) are made again: the
        others' directions did not move (a grid's pixels with a watchlist's beside them). On the CPU every
        pixel is (the same numbers for the others).
    g_first : G holds only pixels ``g_first`` .. K - 1 (its shape (C, K - g_first, A_kept)): the phases of the
        pixels that moved, formed alone. Needs a GPU, ``out`` and ``first >= g_first``.
    """
    xp = get_xp(G)
    C, Kg, Ak = (int(s) for s in G.shape)
    g_first = int(g_first)
    K = g_first + Kg
    if g_first:
        if xp is np or out is None or first < g_first:
            raise ValueError(f"quantise_operator: phases of pixels {g_first} on alone need a GPU, out and first >= "
                             f"g_first (first {first})")
    w = xp.asarray(weights)
    # decided on the host (a few MB): on a GPU the whole-array test is a CUB reduction, whose
    # compilation costs seconds of a fresh process's first image
    wh = to_numpy(weights) if weights_host is None else np.asarray(weights_host)
    # given arrays to write into, their pol sets (a chunk of channels whose pols' weights happen to agree
    # is written into the two sets of an operator whose other channels' do not)
    PA = int(out[1].shape[1]) if out is not None else pol_sets(wh)
    Kpad, Apad = _pad(K, 64), _pad(nant_in, 64)          # rows a multiple of 128, KD of 128
    KD = 2 * Apad
    b, xmax = bases(pieces, KD)
    shape = operand_shape(C, PA, K, nant_in, pieces, tiled)
    if out is None:
        new = xp.zeros if xp is np else xp.empty                 # the GPU kernel writes every byte
        Aq, osc = new(shape, xp.int8), new((C, PA, Kpad), xp.float32)
    else:
        Aq, osc = out
        if Aq.shape != shape or osc.shape != (C, PA, Kpad):
            raise ValueError(f"quantise_operator: out shaped {Aq.shape}, {osc.shape}; expected {shape}, {(C, PA, Kpad)}")
    if xp is not np:
        _quantise_gpu(G, w, keep_index, Apad, pieces, b, tiled, Aq, osc, chunk, first if out is not None else 0,
                      g_first)
        return Aq, osc, b, xmax
    kidx = xp.asarray(keep_index)
    for c0 in range(0, C, chunk):
        cs = slice(c0, min(C, c0 + chunk))
        nc = cs.stop - cs.start
        for pa in range(PA):
            # D = G w (nc, K, Ak) as float32 halves, each product and sum rounded on its own: NumPy's own
            # complex64 product may fuse them, and the GPU kernel's pieces are these, byte for byte
            g, ww = G[cs].astype(xp.complex64), w[cs, None, :, pa].astype(xp.complex64)
            Dre = g.real * ww.real - g.imag * ww.imag
            Dim = g.real * ww.imag + g.imag * ww.real
            s = xp.maximum(xp.abs(Dre), xp.abs(Dim)).max(axis=-1)                          # (nc, K)
            s = xp.where(s > 0, s, xp.float32(1)).astype(xp.float32)
            # residuals in float32: |d| <= 127 carries 7.6e-6 absolute rounding, well below the
            # finest step 1/b^2 = 2.5e-4 (b = 63); real halves divided as such, as the GPU kernel does
            dr, di = (xp.zeros((nc, Kpad, Apad), xp.float32) for _ in range(2))
            dr[:, :K, kidx] = Dre / s[..., None] * xp.float32(127)
            di[:, :K, kidx] = Dim / s[..., None] * xp.float32(127)
            part = xp.empty((nc, pieces, 2 * Kpad, KD), xp.int8) if tiled else None
            for i in range(pieces):
                qr, qi = xp.rint(dr), xp.rint(di)
                dr, di = (dr - qr) * xp.float32(b), (di - qi) * xp.float32(b)
                re_row = xp.stack([qr, -qi], axis=-1).reshape(nc, Kpad // 8, 8, KD)
                im_row = xp.stack([qi, qr], axis=-1).reshape(nc, Kpad // 8, 8, KD)
                piece = xp.concatenate([re_row, im_row], axis=2).reshape(nc, 2 * Kpad, KD).astype(xp.int8)
                if tiled:
                    part[:, i] = piece
                else:
                    Aq[cs, pa, i] = piece
            if tiled:
                Aq[cs, pa] = tile_operator(part[:, None])[:, 0]
            sc = (s.astype(xp.float64) / (127.0 * float(b) ** (pieces - 1))) ** 2
            osc[cs, pa, :K] = sc.astype(xp.float32)
    return Aq, osc, b, xmax


def _quantise_gpu(G, w, keep_index, Apad, pieces, b, tiled, Aq, osc, chunk, first=0, g_first=0):
    """:func:`quantise_operator` on a GPU: one kernel (``quantise.cu``) per launch of whole channels, the same
    arithmetic as the NumPy path (bit-equal pieces). A complex64 contiguous G is read as it is, every channel in
    one launch; another G is cast ``chunk`` channels (or :data:`_CHUNK_BYTES_GPU`) at a time.

    Why one kernel: the array expressions make ~40 launches a 16-channel chunk, ~2,000 at the whole band,
    and an imager folding in a new solution makes them from its own thread behind the images it has
    queued: past the stream's ~1,000 pending launches each one waits for the GPU, so the thread spends
    seconds there and the GPU idles while the host makes the rest.

    G holds pixels ``g_first`` .. K - 1 (:func:`quantise_operator`)."""
    import cupy as cp
    C, Kg, Ak = (int(s) for s in G.shape)
    K = g_first + Kg
    P, PA, Kpad = int(w.shape[-1]), int(osc.shape[1]), int(osc.shape[2])
    for name, a in (("A", Aq), ("oscale", osc)):
        if not a.flags.c_contiguous:
            raise ValueError(f"quantise_operator: out {name} must be C-contiguous")
    inv = cp.full(Apad, -1, cp.int32)
    inv[cp.asarray(keep_index)] = cp.arange(Ak, dtype=cp.int32)
    wc = cp.ascontiguousarray(w, dtype=cp.complex64)
    whole = G.dtype == cp.complex64 and G.flags.c_contiguous
    step = C if whole else gpu_chunk_channels(Kg, Apad, chunk)
    kernel = get_kernel("imaging/quantise.cu", "bf_quantise_operator")
    oscale = np.float64(127.0 * float(b) ** (pieces - 1))
    for c0 in range(0, C, step):
        c1 = min(C, c0 + step)
        g = G[c0:c1] if whole else cp.ascontiguousarray(G[c0:c1], dtype=cp.complex64)
        kernel((Kpad - first, c1 - c0, PA), (256,), (g, wc[c0:c1], inv, Aq[c0:c1], osc[c0:c1], np.int32(K),
                                                     np.int32(Ak), np.int32(P), np.int32(Apad), np.int32(pieces),
                                                     np.float32(b), oscale, np.int32(bool(tiled)), np.int32(first),
                                                     np.int32(Kpad), np.int32(g_first), np.int32(Kg)))


def padded_ntime(T):
    """Samples per pol in the kernel's B: T rounded up to a whole block of columns (the extra samples
    are zeros, whose power is zero and is not returned)."""
    return _pad(int(T), BN)


#: bytes of one bulk-copied tile: 128 rows x 128 bytes (one K stage of A, one K block of B)
TILE = 128 * 128


def _tile_rows(X):
    """(..., R, KD) int8 -> (..., R/128, KD/128, 16384): 128-row x 128-byte tiles, each in the
    128-byte-swizzled order the warpgroup MMA reads (chunk j of row r at 16 (j ^ r % 8) in the row's
    128 bytes, rows in 8-row atoms of 1 KB) -- what ``soff`` in the kernels computes."""
    xp = get_xp(X)
    *lead, R, KD = (int(v) for v in X.shape)
    n = len(lead)
    X = X.reshape(*lead, R // 128, 16, 8, KD // 128, 8, 16)                   # (.., mt, r8, rlo, kb, j, b)
    X = X.transpose(*range(n), n, n + 3, n + 1, n + 2, n + 4, n + 5)         # (.., mt, kb, r8, rlo, j, b)
    ar = xp.arange(8)
    X = X[(slice(None),) * (n + 3) + (ar[:, None], ar[None, :] ^ ar[:, None])]   # stored chunk j' = chunk j' ^ rlo
    return xp.ascontiguousarray(X).reshape(*lead, R // 128, KD // 128, TILE)


def tile_operator(Aq):
    """Logical A (C, PA, pieces, M, KD) -> the Hopper kernel's (C, PA, M/128, pieces, KD/128, 16384):
    each block's K stages one contiguous 16-KB tile after another."""
    return get_xp(Aq).ascontiguousarray(_tile_rows(Aq).swapaxes(2, 3))


def tile_voltages(Bv):
    """Logical B (C, NCOL, KD) -> the Hopper kernel's (C, NCOL/128, KD/128, 16384)."""
    return _tile_rows(Bv)


def layout_voltages(pairs, chan, pols, KD, xmax, flag=None, ci4=False, tiled=False, work=None):
    """Integer (re, im) voltages (T, C_in, A_in, P_in, 2) int8 -> B (C', P' Tp, KD) int8, column
    p' Tp + t, Tp = :func:`padded_ntime` (T); samples t >= T are zero.

    chan : None (all channels) or (C',) input channel per live channel;  pols : the pols imaged
    (a list, or on the GPU an int32 device array).  Antennas beyond A_in are zero. On the GPU any
    |sample| > ``xmax`` sets ``flag[0]`` (int32, device).
    ci4 : ``pairs`` are ci4 bytes, uint8 (T, C_in, A_in, P_in), decoded as they are read (on the GPU
        for two pols and antennas a multiple of 8 -- the stations' case -- in the layout kernel itself:
        no unpacked copy; |x| <= 8 <= xmax always).
    tiled : B in the Hopper kernel's tiles, (C', P' Tp / 128, KD / 128, 16384) (:func:`tile_voltages`),
        written there by the GPU kernels directly.
    work : None, or a :class:`~bf_epic_blocks.imaging._xp.Workspace` whose array B is on the GPU (used
        again by the next call on this stream: B must be read by work queued on it before then).
    """
    xp = get_xp(pairs)
    if ci4:
        if pairs.dtype != np.uint8 or pairs.ndim != 4:
            raise ValueError(f"ci4 bytes must be uint8 (T, C, A, P), got {pairs.dtype} {tuple(pairs.shape)}")
        T, Cin, Ain, Pin = (int(s) for s in pairs.shape)
        if xp is np or not (Pin == 2 and Ain % 8 == 0):
            pairs = _ci4_pairs(pairs)
        else:
            Tp = padded_ntime(T)
            cmap = xp.arange(Cin, dtype=xp.int32) if chan is None else xp.asarray(chan, dtype=xp.int32)
            pmap = xp.asarray(pols, dtype=xp.int32)
            Cl, Pp = int(cmap.shape[0]), int(pmap.shape[0])
            out = _b_array(xp, _b_shape(Cl, Pp * Tp, KD, tiled), work)
            total = Cl * Tp * (KD // 16)
            get_kernel("imaging/fused_layout.cu", "bf_layout_ci4_p2")(
                ((total + 255) // 256,), (256,),
                (xp.ascontiguousarray(pairs), out, cmap, pmap, np.int32(T), np.int32(Tp), np.int32(Cin),
                 np.int32(Ain), np.int32(Pp), np.int32(KD // 2), np.int32(Cl), np.int32(tiled)))
            return out
    T, Cin, Ain, Pin = (int(s) for s in pairs.shape[:4])
    Tp = padded_ntime(T)
    if xp is np:
        pols = [int(p) for p in pols]
        x = pairs if chan is None else pairs[:, np.asarray(chan)]
        x = x[:, :, :, pols]                                           # (T, C', A, P', 2)
        out = np.zeros((x.shape[1], len(pols), Tp, KD), np.int8)
        out[:, :, :T, :2 * Ain] = x.transpose(1, 3, 0, 2, 4).reshape(x.shape[1], len(pols), T, 2 * Ain)
        out = out.reshape(x.shape[1], len(pols) * Tp, KD)
        return tile_voltages(out) if tiled else out
    cmap = xp.arange(Cin, dtype=xp.int32) if chan is None else xp.asarray(chan, dtype=xp.int32)
    pmap = xp.asarray(pols, dtype=xp.int32)
    Cl, Pp = int(cmap.shape[0]), int(pmap.shape[0])
    out = _b_array(xp, _b_shape(Cl, Pp * Tp, KD, tiled), work)
    if flag is None:
        flag = xp.zeros(1, xp.int32)
    total = Cl * Tp * (KD // 16)
    head = (xp.ascontiguousarray(pairs), out, cmap, pmap, flag, np.int32(T), np.int32(Tp), np.int32(Cin), np.int32(Ain))
    tail = (np.int32(Pp), np.int32(KD // 2), np.int32(Cl), np.int32(xmax), np.int32(tiled))
    grid = ((total + 255) // 256,)
    if Pin == 2 and Ain % 8 == 0:                  # two pols a sample: the kernel knows Pin
        get_kernel("imaging/fused_layout.cu", "bf_layout_i8_p2")(grid, (256,), head + tail)
    else:
        get_kernel("imaging/fused_layout.cu", "bf_layout_i8")(grid, (256,), head + (np.int32(Pin),) + tail)
    return out


def _b_array(xp, shape, work):
    """An int8 array of ``shape`` for B (every element written by the layout kernels): ``work``'s, or new."""
    return xp.empty(shape, xp.int8) if work is None else work.take(xp, shape, np.int8)[0]


def _ci4_pairs(b):
    """ci4 bytes (uint8: high nibble real, two's complement) -> int8 (..., 2) (re, im) pairs."""
    xp = get_xp(b)
    re = ((b >> 4) ^ 8).astype(xp.int8) - 8
    im = ((b & 15) ^ 8).astype(xp.int8) - 8
    return xp.stack([re, im], axis=-1).astype(xp.int8)


def _b_shape(C, ncol, KD, tiled):
    return (C, ncol // 128, KD // 128, TILE) if tiled else (C, ncol, KD)


def reference_power(Aq, osc, Bv, T, n=16, base=None):
    """NumPy emulation of the kernel, in int64: (C, P', T // 16, Kpad) float64 sums of |F|^2 per
    16 samples, scaled. For tests: it checks the layout and the quantisation against a float64 DFT,
    and the kernel against it."""
    C, PA, NP, M, KD = Aq.shape
    P = Bv.shape[1] // T
    b = base if base is not None else bases(NP, KD)[0]
    out = np.zeros((C, P, T // 16, M // 2))
    for c in range(C):
        for p in range(P):
            pa = p if PA > 1 else 0
            X = Bv[c, p * T:(p + 1) * T].astype(np.int64)                    # (T, KD)
            acc = np.zeros((M, T), np.int64)
            for i in range(NP):
                acc = acc * b + Aq[c, pa, i].astype(np.int64) @ X.T
            acc = acc.reshape(M // 16, 2, 8, T)                              # (blocks, re|im, 8, T)
            pw = (acc.astype(np.float64) ** 2).sum(axis=1).reshape(M // 2, T // 16, 16).sum(-1)
            out[c, p] = pw.T * osc[c, pa][None, :]
    return out


def fused_power(Aq, osc, Bv, T, P, flag, npix=None, config=None, grid=None):
    """GPU: the fused GEMM and power sums. Aq, osc: :func:`quantise_operator`; Bv: :func:`layout_voltages`
    (C', P T, KD); flag: int32 device scalar (nonzero: NaN images); npix: pixels kept (default Kpad).
    Returns float32 (T // 16, C', P, npix): [g, c, p, k] is the sum over samples 16 g .. 16 g + 15
    of |F_pk|^2 -- the direct route's block sums of the pols' own powers, as :mod:`.dft` keeps them.

    grid : None, or (out, fac, cell) or (out, fac, cell, xout) to image straight onto a grid (the Hopper
    kernel only): out float32 (G, C', ncell), G <= T // 16, gets sum_p fac[c, p, k] * (the sum above)
    added to cell ``cell[k]`` of pixel k (int32 (npix,)); fac float32 (C', P, Kpad) (``osc`` is then not
    used: fac holds it times what the image's products need). Each pol's share is one atomic add to a
    cell the caller cleared (two terms onto 0: the same bits in either order); cells no pixel has are not
    written. A pixel whose cell is ncell + j is a direction imaged beside the grid (a watchlist's): its
    image is added to xout float32 (G, C', nx) at j (cleared by the caller). It costs about what the
    per-pol sums do and saves the products pass that would follow them. Returns ``out``.

    config : None (the device's kernel, :func:`kernel_config`), or a kernel shape: a dict with
    ``kernel='wgmma'`` (:data:`HOPPER_CONFIG`), else the portable kernel (:data:`PORTABLE_CONFIG`
    updated by the dict)."""
    import cupy as cp
    if Aq.ndim == 6:                                 # already in the Hopper kernel's tiles
        C, PA, MT_, NP, KB_, _ = (int(s) for s in Aq.shape)
        M, KD = 128 * MT_, 128 * KB_
    else:
        C, PA, NP, M, KD = (int(s) for s in Aq.shape)
    cfg = dict(config) if config is not None else kernel_config(KD, cp.cuda.Device().compute_capability)
    hopper = _hopper(cfg)
    if hopper:
        # tiles for the bulk copies (the pipeline's arrays come tiled; tests' logical ones are tiled here)
        Aq = Aq if Aq.ndim == 6 else tile_operator(Aq)
        Bv = Bv if Bv.ndim == 4 else tile_voltages(Bv)
    else:
        cfg = dict(PORTABLE_CONFIG, **cfg)
        if Aq.ndim == 6 or Bv.ndim == 4:
            raise ValueError("tiled operands need the Hopper kernel (config kernel='wgmma')")
    ncol = int(Bv.shape[1]) * (128 if Bv.ndim == 4 else 1)
    bm = 128 if hopper else 64 * cfg["WMW"]
    kstep = 128 if hopper else cfg["BK"]
    if ncol != P * T or ncol % BN or KD % kstep or M % bm or (PA > 1 and T % BN):
        raise ValueError(f"fused imaging needs P*T a multiple of {BN} (and T too with per-pol gains), got T={T}, P={P}")
    npix = int(M // 2 if npix is None else npix)
    nt = 384 if hopper else 32 * cfg["WMW"] * (BN // cfg["WN"])
    rows = -(-(M // bm) // (cfg["MT"] if hopper else 1))
    base = np.int32(_base_of(NP, KD))
    if grid is not None:
        if not hopper:
            raise ValueError("fused imaging onto a grid needs the Hopper kernel (config kernel='wgmma')")
        out, fac, cell = grid[:3]
        xout = grid[3] if len(grid) > 3 else None
        G, ncell = int(out.shape[0]), int(out.shape[-1])
        nx = 0 if xout is None else int(xout.shape[-1])
        if (out.dtype != cp.float32 or not out.flags.c_contiguous or out.size != G * C * ncell or G > T // 16
                or fac.shape != (C, P, M // 2) or fac.dtype != cp.float32 or cell.shape != (npix,)
                or cell.dtype != cp.int32):
            raise ValueError("fused_power: grid expects out float32 (G <= T/16, C', ncell) contiguous, fac float32 "
                             f"({C}, {P}, {M // 2}) and cell int32 ({npix},); got {out.dtype} {tuple(out.shape)}, "
                             f"{fac.dtype} {tuple(fac.shape)}, {cell.dtype} {tuple(cell.shape)}")
        if xout is not None and (xout.dtype != cp.float32 or not xout.flags.c_contiguous or xout.size != G * C * nx):
            raise ValueError(f"fused_power: grid's xout must be float32 ({G}, {C}, nx) contiguous, got {xout.dtype} "
                             f"{tuple(xout.shape)}")
        k, smem = _fused_kernel(NP, KD, cfg, grid=True)
        k((rows, ncol // BN, C), (nt,), (Aq, Bv, fac, flag, out, np.int32(M), np.int32(ncol), np.int32(T), np.int32(PA),
                                         base, np.int32(npix), cell, np.int32(ncell), np.int32(G),
                                         out if xout is None else xout, np.int32(nx)), shared_mem=smem)
        return out
    out = cp.empty((T // 16, C, P, npix), cp.float32)
    k, smem = _fused_kernel(NP, KD, cfg)
    k((rows, ncol // BN, C), (nt,), (Aq, Bv, osc, flag, out, np.int32(M), np.int32(ncol), np.int32(T), np.int32(PA),
                                     base, np.int32(npix)), shared_mem=smem)
    return out


def _base_of(pieces, kd):
    return bases(pieces, kd)[0]


class FusedOperator:
    """The operator's int8 pieces and the call that images with them (made once per operator and mode).

    op : a :class:`.dft.DFTOperator` on the GPU;  precision : 'i8x2' | 'i8x3'."""

    def __init__(self, op, precision):
        import cupy as cp
        xp = op.xp
        self.pieces = PIECES[precision]
        w = op.data_weights if op.chan_index is None else op.data_weights[op.chan_index]
        self._w_host = op.live_weights_host()
        kd = 2 * _pad(op.nant_in, 64)
        self.config = kernel_config(kd, cp.cuda.Device().compute_capability)
        self.tiled = _hopper(self.config)          # operands in the Hopper kernel's tiles
        self._w = w
        self.Aq, self.osc, self.base, self.xmax = self._quantise(op)
        self.KD = kd
        self.chan = (xp.arange(op.nchan, dtype=xp.int32) if op.chan_index is None
                     else xp.asarray(op.chan_index, dtype=xp.int32))
        self.npix = op.npix
        self.flag = xp.zeros(1, xp.int32)
        self._pmaps = {}
        # the voltages' layout, kept from gulp to gulp (a whole band's is most of a gulp's temporaries): the
        # operator, like its range flag, is used on one stream
        self._b_work = Workspace()

    def requantise(self, op, first=0):
        """The pieces of ``op``'s operator again, written into the arrays that held them (its pixels moved:
        :meth:`.dft.DFTOperator.repoint`; only pixels ``first`` onwards, where those are the ones that
        moved); the base and sample range are the same (they depend on the antennas only)."""
        self._quantise(op, out=(self.Aq, self.osc), first=first)

    def _quantise(self, op, out=None, first=0):
        """:func:`quantise_operator` of ``op``'s phases with this operator's weights: from the phases it holds,
        else formed and quantised :data:`_REFORM_BYTES_GPU` of phases at a time (the same pieces) -- only
        pixels ``first`` onwards where only those moved (a watchlist's directions beside a grid: only
        their phases are formed)."""
        if op.G is not None:
            return quantise_operator(op.live_G(0), self._w, op.keep_index, op.nant_in, self.pieces, tiled=self.tiled,
                                     out=out, weights_host=self._w_host, first=first)
        xp, wh = op.xp, self._w_host
        C, K = int(wh.shape[0]), int(op.npix)
        if out is None:
            PA = pol_sets(wh)
            out = (xp.empty(operand_shape(C, PA, K, op.nant_in, self.pieces, self.tiled), xp.int8),
                   xp.empty((C, PA, _pad(K, 64)), xp.float32))
        step = reform_channels(K - first, op.nant)
        for c0 in range(0, C, step):
            cs = slice(c0, min(C, c0 + step))
            _, _, b, xmax = quantise_operator(op.phases(cs, first), self._w[cs], op.keep_index, op.nant_in,
                                              self.pieces, tiled=self.tiled, out=(out[0][cs], out[1][cs]),
                                              weights_host=wh[cs], first=first, g_first=first)
        return out[0], out[1], b, xmax

    def can_reweight(self, w):
        """Whether weights ``w`` (C', A_kept, P) of the live channels fit this operator's pieces: one set for
        both pols (PA = 1) holds only weights the pols share."""
        return int(self.osc.shape[1]) == pol_sets(w)

    def reweight(self, op):
        """The pieces for ``op``'s new weights (:meth:`.dft.DFTOperator.reweight`), written into the arrays
        that held them."""
        w = op.data_weights if op.chan_index is None else op.data_weights[op.chan_index]
        if w is not self._w:
            self._w[...] = w
        self._w_host = op.live_weights_host()
        self.requantise(op)

    @staticmethod
    def supports(T, n):
        """Whether groups of ``n`` of T samples can be summed: the kernel sums 16 samples at a time, and
        pads a gulp with zero samples to whole tiles, so n must be a multiple of 16 -- or all T samples
        (one integration's part in this gulp, any length)."""
        return n % 16 == 0 or n == T

    def onto_grid(self):
        """Whether :meth:`place` can image straight onto a grid here (the Hopper kernel)."""
        return _hopper(self.config)

    def place(self, pairs, pols, fac, cell, out, ci4=False, xout=None):
        """Images of 16 samples each straight onto a grid: out[g, c, cell[k]] = sum_p fac[c, p, k] *
        (:meth:`sums` with n = 16)[g, c, p, k] (:func:`fused_power`'s ``grid``); out float32 (G, C', ncell),
        G = T // 16 of the T samples in ``pairs``; cells no pixel has are left as they are. xout: None, or
        float32 (G, C', nx) for the pixels beside the grid (cells ncell + j)."""
        T = int(pairs.shape[0])
        grid = (out, fac, cell) if xout is None else (out, fac, cell, xout)
        return fused_power(self.Aq, self.osc, self._layout(pairs, pols, ci4), padded_ntime(T), len(pols), self.flag,
                           self.npix, self.config, grid=grid)

    def _layout(self, pairs, pols, ci4):
        """The voltages in the kernel's layout (:func:`layout_voltages`), the range flag cleared first."""
        key = tuple(pols)
        if key not in self._pmaps:
            xp = get_xp(pairs)
            self._pmaps[key] = xp.asarray(list(pols), dtype=xp.int32)
        self.flag.fill(0)
        return layout_voltages(pairs, self.chan, self._pmaps[key], self.KD, self.xmax, self.flag, ci4=ci4,
                               tiled=self.tiled, work=self._b_work)

    def sums(self, pairs, pols, n, ci4=False):
        """(g, C', P', npix) float32 sums of |F_p|^2 over groups of ``n`` samples (:meth:`supports`);
        ``ci4``: ``pairs`` are ci4 bytes (T, C, A, P) uint8, laid out without unpacking."""
        T = int(pairs.shape[0])
        out = fused_power(self.Aq, self.osc, self._layout(pairs, pols, ci4), padded_ntime(T), len(pols), self.flag,
                          self.npix, self.config)                               # (Tp/16, C', P, K)
        if n == T:                                  # one group: every 16-sample unit, the last one partial
            u = -(-T // 16)
            return out[:u].sum(axis=0, keepdims=True) if u > 1 else out[:1]
        g, u = T // n, n // 16
        out = out[:g * u]
        if u > 1:
            out = out.reshape(g, u, *out.shape[1:]).sum(axis=1)
        return out


#: The portable kernel's shape (``fused.cu``): warps along M (64 rows each), columns a warp, bytes of K
#: a stage, stages, and B whole in shared memory across the pieces (BFULL=1; BFULL=0 stages B with A,
#: for arrays whose B does not fit).
PORTABLE_CONFIG = dict(kernel="mma.sync", WMW=2, WN=64, BK=64, ST=4, BFULL=1)
#: The Hopper kernel's shape (``fused_hopper.cu``, compute capability 9.0): 128-byte K stages of A in
#: shared memory, and row tiles a block (B is loaded once for all of them). Six stages rather than four
#: hide more of A's latency from L2; where B leaves too little shared memory for six, fewer are taken
#: (:func:`kernel_config`, down to :data:`HOPPER_MIN_ST`).
HOPPER_CONFIG = dict(kernel="wgmma", ST=6, MT=4)
HOPPER_MIN_ST = 4
_SMEM_MAX = 227 * 1024


def kernel_config(kd, device_cc):
    """The kernel and its shape for KD = 2 Apad on a device of compute capability ``device_cc`` ('90',
    '80'): the Hopper kernel on compute capability 9.0 while its shared memory holds B whole and
    at least :data:`HOPPER_MIN_ST` stages of A (as many as fit, up to :data:`HOPPER_CONFIG`'s), else the
    portable one (B whole while it fits, else staged)."""
    if str(device_cc) == "90":
        for st in range(HOPPER_CONFIG["ST"], HOPPER_MIN_ST - 1, -1):
            if _smem(dict(HOPPER_CONFIG, ST=st), kd) <= _SMEM_MAX:
                return dict(HOPPER_CONFIG, ST=st)
    if _smem(PORTABLE_CONFIG, kd) <= _SMEM_MAX:
        return dict(PORTABLE_CONFIG)
    return dict(PORTABLE_CONFIG, BFULL=0)


def _hopper(cfg):
    return cfg.get("kernel") == "wgmma"


def _smem(cfg, kd):
    """Dynamic shared memory of a kernel shape: A's stages plus B (whole, or its stages); the Hopper
    kernel also its mbarriers (8 bytes each: full and empty per stage, one for B)."""
    if _hopper(cfg):
        return (cfg["ST"] + kd // 128) * TILE + 8 * (2 * cfg["ST"] + 1)
    bm = 64 * cfg["WMW"]
    a = cfg["ST"] * bm * (cfg["BK"] + 16)
    b = BN * (kd + 16) if cfg["BFULL"] else cfg["ST"] * BN * (cfg["BK"] + 16)
    return a + b


def _defines(cfg, pieces, kd, grid=False):
    """The -D constants of a kernel shape (the .cu files' headers list them)."""
    d = {k: v for k, v in cfg.items() if k != "kernel"}
    d.update(NP=pieces, KD=kd)
    if _hopper(cfg):
        d["GRID"] = int(grid)
    return d


_FUSED_KERNELS: dict = {}


def _fused_kernel(pieces, kd, cfg, grid=False):
    """(kernel, dynamic shared memory bytes) of a kernel shape (:func:`kernel_config`), cached per device:
    every launch asks, so a repeat is one lookup (no defines built, no attribute read from the driver)."""
    import cupy as cp
    key = (pieces, kd, tuple(sorted(cfg.items())), bool(grid), cp.cuda.runtime.getDevice())
    got = _FUSED_KERNELS.get(key)
    if got is None:
        hopper = _hopper(cfg)
        k = get_kernel("imaging/fused_hopper.cu" if hopper else "imaging/fused.cu", "bf_fused_power",
                       defines=_defines(cfg, pieces, kd, grid), arch="sm_90a" if hopper else None)
        smem = _smem(cfg, kd)
        if k.max_dynamic_shared_size_bytes < smem:
            k.max_dynamic_shared_size_bytes = smem
        got = _FUSED_KERNELS[key] = (k, smem)
    return got


# The configurations the shipped paths compile: both piece counts; an array of 256 antennas (KD = 512)
# for either kernel, and for the portable one also B staged (KD = 1536, beyond what B whole fits).
register("imaging/fused_layout.cu")
register("imaging/quantise.cu")
register("imaging/fused.cu", *[(_defines(PORTABLE_CONFIG, np_, 512), None) for np_ in PIECES.values()],
         *[(_defines(dict(PORTABLE_CONFIG, BFULL=0), np_, 1536), None) for np_ in PIECES.values()])
register("imaging/fused_hopper.cu", *[(_defines(HOPPER_CONFIG, np_, 512, g), "sm_90a")
                                      for np_ in PIECES.values() for g in (False, True)])
