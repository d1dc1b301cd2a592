"""The fused integer imaging with three real products a complex multiply-add (Gauss's form), on Hopper.

:mod:`.fused` forms F = D X with four int8 products a complex multiply-add a piece (Re D Re x - Im D Im x,
Re D Im x + Im D Re x). Three suffice:

    T = sum_a Re D_ka (Re x_a + Im x_a)
    U = sum_a -(Re D_ka + Im D_ka) Im x_a          Re F = T + U
    V = sum_a (Im D_ka - Re D_ka) Re x_a           Im F = T + V

**Operands.** The operator's three real rows R_0 = Re D, R_1 = -(Re D + Im D), R_2 = Im D - Re D share one
scale a pixel, s_k = max_a max_j |R_j,ka| (= max_a |Re D_ka| + |Im D_ka|), and are written in ``pieces`` int8
pieces in base b as :mod:`.fused` writes its rows (R / s_k 127 = q_1 + q_2 / b + ..., float32 residuals,
round to nearest even), so that T, U and V are integers in one unit and Re F, Im F are formed exactly in
int32. The voltages' third operand Re x + Im x is exact in int8 for |x| <= 63.

A: (C, PA, 3, pieces, M, KA) int8, M = pixels rounded up to 128, KA = antennas rounded up to 128;
B: (C, P' Tp, 3 KA) int8, K sections (Re x + Im x, Im x, Re x), column p' Tp + t as :mod:`.fused`'s.
The Hopper kernel (``fused_gauss.cu``) reads both in 16-KB swizzled tiles (:func:`tile_gauss`,
:func:`.fused.tile_voltages`) and writes what :func:`.fused.fused_power` writes: sums over 16 samples of
|F|^2 per pixel and pol, or images straight onto a grid.

**Range.** |Re F| <= 127 (b^(pieces-1) + ... + 1) (sum |Re x + Im x| + sum |Im x|) <= cmax 3 KA xmax:
:func:`gauss_bases` gives the largest |x| (at least 8: 4-bit voltages always exact) whose sums fit
int32, and at most 63, so that Re x + Im x is an int8 -- 63 at 256 antennas with two pieces, where the
four-product kernel takes 128 (all of 8-bit).

**Error.** One scale for the three rows is up to sqrt(2) coarser than the four-product form's
max(|Re D|, |Im D|), so the images' error grows a little, staying within regime B's 1e-5 at case P
(tools/bench/predict_gauss.py predicts it exactly; tools/bench/bench_gauss.py measures it).

**Speed.** Six int8 MACs a complex one instead of eight (two pieces); but the fused kernels are not bound
by their MACs, and this one runs in the four-product kernel's time (docs/benchmarks/bench_gauss.md), so
the pipelines keep the four-product kernel (:mod:`.fused`) and nothing here is on their path. The kernel,
its operands and its emulation stay, tested, for when the fused kernels are bound by their MACs.
"""
from __future__ import annotations


import numpy as np

from ..cuda import get_kernel, register
from ._xp import get_xp
from .fused import _INT32_MAX, BN, TILE, _pad, _tile_rows, int_bases, tile_voltages

__all__ = ["PRODUCTS", "GAUSS_CONFIG", "gauss_bases", "gauss_rows", "quantise_gauss", "layout_gauss",
           "tile_gauss", "reference_gauss", "gauss_power", "gauss_smem", "gauss_fits"]

#: real products a complex multiply-add
PRODUCTS = 3
#: the kernel's shape: K stages of A in shared memory, row tiles a block (B is loaded once for all)
GAUSS_CONFIG = dict(ST=6, MT=4)
_SMEM_MAX = 227 * 1024


def gauss_bases(pieces: int, ka: int) -> tuple[int, int]:
    """(b, xmax) for ``pieces`` int8 pieces and KA antenna bytes a product row: the base and the largest
    |sample| whose Re F, Im F fit int32 (at least 8; at most 63, so that Re x + Im x is an int8)."""
    # |Re F| <= |T| + |U|: sums of |Re x + Im x| <= 2 xmax and |Im x| <= xmax over KA antennas, 3 KA terms of xmax
    return int_bases(pieces, 3 * ka, 63, f"{ka} antennas in Gauss's form")


def gauss_smem(ka, cfg=None):
    """Dynamic shared memory of the kernel: ST stages of A, B whole (3 KA / 128 tiles), the mbarriers."""
    cfg = GAUSS_CONFIG if cfg is None else cfg
    return (cfg["ST"] + 3 * ka // 128) * TILE + 8 * (2 * cfg["ST"] + 1)


def gauss_fits(nant_in, cfg=None):
    """Whether the kernel's shared memory holds B whole for ``nant_in`` antennas (256: yes; 512: no)."""
    return gauss_smem(_pad(int(nant_in), 128), cfg) <= _SMEM_MAX


def gauss_rows(Dre, Dim):
    """The three real rows (R_0, R_1, R_2) = (Re D, -(Re D + Im D), Im D - Re D) of float32 Re D, Im D,
    each sum rounded on its own (as the GPU's float32 arithmetic without fused multiply-adds)."""
    xp = get_xp(Dre)
    return Dre, -(Dre + Dim).astype(xp.float32), (Dim - Dre).astype(xp.float32)


def quantise_gauss(G, weights, keep_index, nant_in, pieces, *, tiled=False):
    """The operator as Gauss's three rows in int8 pieces (module docstring), in G's array namespace.

    G : complex (C, K, A_kept) geometric operator;  weights : complex (C, A_kept, P) folded gains;
    keep_index : (A_kept,) input antenna of each kept antenna;  nant_in : antennas in the voltages.
    Returns (A int8 (C, PA, 3, pieces, M, KA) -- or the kernel's tiles (C, PA, M/128, 3, pieces, KA/128,
    16384) with ``tiled`` --, oscale float32 (C, PA, M), base, xmax); PA = 1 where the pols' weights agree,
    else P; oscale = (s_k / (127 b^(pieces-1)))^2 (0 for padding rows)."""
    from .fused import pol_sets
    from ._xp import to_numpy
    xp = get_xp(G)
    C, K, Ak = (int(s) for s in G.shape)
    w = xp.asarray(weights)
    PA = pol_sets(to_numpy(w))
    M, KA = _pad(K, 128), _pad(nant_in, 128)
    b, xmax = gauss_bases(pieces, KA)
    Aq = xp.zeros((C, PA, PRODUCTS, pieces, M, KA), xp.int8)
    osc = xp.zeros((C, PA, M), xp.float32)
    kidx = xp.asarray(keep_index)
    for pa in range(PA):
        g, ww = G.astype(xp.complex64), w[:, None, :, pa].astype(xp.complex64)
        # D = G w as float32 halves, each product and sum rounded on its own (as .fused quantises)
        Dre = (g.real * ww.real - g.imag * ww.imag).astype(xp.float32)
        Dim = (g.real * ww.imag + g.imag * ww.real).astype(xp.float32)
        rows = gauss_rows(Dre, Dim)
        s = xp.max(xp.stack([xp.abs(r).max(axis=-1) for r in rows]), axis=0)                 # (C, K)
        s = xp.where(s > 0, s, xp.float32(1)).astype(xp.float32)
        for j, r in enumerate(rows):
            d = xp.zeros((C, M, KA), xp.float32)
            d[:, :K, kidx] = r / s[..., None] * xp.float32(127)
            for i in range(pieces):
                q = xp.rint(d)
                d = ((d - q) * xp.float32(b)).astype(xp.float32)
                Aq[:, pa, j, i] = q.astype(xp.int8)
        osc[:, pa, :K] = ((s.astype(xp.float64) / (127.0 * float(b) ** (pieces - 1))) ** 2).astype(xp.float32)
    return (tile_gauss(Aq) if tiled else Aq), osc, b, xmax


def tile_gauss(Aq):
    """Logical A (C, PA, 3, pieces, M, KA) -> the kernel's tiles (C, PA, M/128, 3, pieces, KA/128, 16384):
    each row tile's stages (product, piece, K block) one contiguous 16-KB tile after another."""
    xp = get_xp(Aq)
    t = _tile_rows(Aq)                                          # (C, PA, 3, pieces, M/128, KA/128, 16384)
    return xp.ascontiguousarray(xp.moveaxis(t, 4, 2))


def layout_gauss(Bv, KA, tiled=False):
    """:mod:`.fused`'s voltages B (C, NCOL, KD) int8 (columns 2a, 2a + 1: Re x_a, Im x_a) -> Gauss's
    (C, NCOL, 3 KA): K sections (Re x + Im x, Im x, Re x), antennas beyond KD / 2 zero; the kernel's
    tiles (C, NCOL/128, 3 KA/128, 16384) with ``tiled``. |x| must be at most 63 (:func:`gauss_bases`)."""
    xp = get_xp(Bv)
    C, ncol, KD = (int(s) for s in Bv.shape)
    A = KD // 2
    if A > KA:
        raise ValueError(f"layout_gauss: {A} antennas do not fit KA = {KA}")
    xr, xi = Bv[..., 0::2], Bv[..., 1::2]
    out = xp.zeros((C, ncol, 3 * KA), xp.int8)
    out[..., :A] = (xr.astype(xp.int16) + xi).astype(xp.int8)
    out[..., KA:KA + A] = xi
    out[..., 2 * KA:2 * KA + A] = xr
    return tile_voltages(out) if tiled else out


def reference_gauss(Aq, osc, Bg, T, n=16, base=None):
    """NumPy emulation of the kernel in int64: (C, P', T // n, M) float64 sums of |F|^2 per n samples
    (n a multiple of 16), scaled by ``osc``. Aq logical (C, PA, 3, pieces, M, KA), Bg (C, P' T, 3 KA)."""
    Aq, osc, Bg = (np.asarray(getattr(v, "get", lambda: v)()) for v in (Aq, osc, Bg))
    C, PA, _, NP, M, KA = Aq.shape
    if base is None:
        base = gauss_bases(NP, KA)[0]
    P = Bg.shape[1] // T
    out = np.zeros((C, P, T // n, M))
    for c in range(C):
        for p in range(P):
            pa = p if PA > 1 else 0
            X = Bg[c, p * T:(p + 1) * T].astype(np.int64)                       # (T, 3 KA)
            acc = []
            for j in range(PRODUCTS):
                a = np.zeros((M, T), np.int64)
                for i in range(NP):
                    a = a * base + Aq[c, pa, j, i].astype(np.int64) @ X[:, j * KA:(j + 1) * KA].T
                acc.append(a)
            re, im = acc[0] + acc[1], acc[0] + acc[2]
            assert np.abs(re).max(initial=0) <= _INT32_MAX and np.abs(im).max(initial=0) <= _INT32_MAX
            pw = re.astype(np.float64) ** 2 + im.astype(np.float64) ** 2          # (M, T)
            out[c, p] = pw.reshape(M, T // n, n).sum(-1).T * osc[c, pa][None, :]
    return out


def _defines(cfg, pieces, ka, grid=False):
    cfg = dict(GAUSS_CONFIG, **cfg)
    return dict(ST=cfg["ST"], MT=cfg["MT"], NP=pieces, KA=ka, GRID=int(grid))


_KERNELS: dict = {}


def _kernel(pieces, ka, cfg, grid=False):
    """(kernel, dynamic shared memory bytes), cached per shape and device."""
    import cupy as cp
    key = (pieces, ka, tuple(sorted(cfg.items())), bool(grid), cp.cuda.runtime.getDevice())
    got = _KERNELS.get(key)
    if got is None:
        k = get_kernel("imaging/fused_gauss.cu", "bf_fused_gauss", defines=_defines(cfg, pieces, ka, grid),
                       arch="sm_90a")
        smem = gauss_smem(ka, cfg)
        if k.max_dynamic_shared_size_bytes < smem:
            k.max_dynamic_shared_size_bytes = smem
        got = _KERNELS[key] = (k, smem)
    return got


def gauss_power(Aq, osc, Bg, T, P, flag, npix=None, config=None, grid=None):
    """GPU (compute capability 9.0): Gauss's fused GEMM and power sums. Aq, osc: :func:`quantise_gauss`
    (logical or tiled); Bg: :func:`layout_gauss` (logical or tiled), P T columns; flag: int32 device scalar
    (nonzero: NaN images); npix: pixels kept (default M). Returns float32 (T // 16, C, P, npix) sums over
    16 samples of |F|^2, as :func:`.fused.fused_power`; ``grid`` as there (fac float32 (C, P, M))."""
    import cupy as cp
    cfg = dict(GAUSS_CONFIG, **(config or {}))
    if Aq.ndim == 6:
        Aq = tile_gauss(Aq)
    C, PA, MT_, _, NP, KB, _ = (int(s) for s in Aq.shape)
    M, KA = 128 * MT_, 128 * KB
    if Bg.ndim == 3:
        Bg = tile_voltages(Bg)
    ncol = int(Bg.shape[1]) * 128
    if int(Bg.shape[2]) != 3 * KB or int(Bg.shape[0]) != C:
        raise ValueError(f"gauss_power: B's tiles {tuple(Bg.shape)} do not match A's (C {C}, 3 x {KB} K blocks)")
    if ncol != P * T or ncol % BN or (PA > 1 and T % BN):
        raise ValueError(f"gauss_power needs P*T a multiple of {BN} (and T too with per-pol gains), got T={T}, P={P}")
    if gauss_smem(KA, cfg) > _SMEM_MAX:
        raise ValueError(f"gauss_power: {KA} antenna bytes a row need {gauss_smem(KA, cfg)} bytes of shared memory")
    npix = int(M if npix is None else npix)
    rows = -(-(M // 128) // cfg["MT"])
    base = np.int32(gauss_bases(NP, KA)[0])
    if grid is not None:
        out, fac, cell = grid[:3]
        xout = grid[3] if len(grid) > 3 else None
        G, ncell = int(out.shape[0]), int(out.shape[-1])
        nx = 0 if xout is None else int(xout.shape[-1])
        if (out.dtype != cp.float32 or not out.flags.c_contiguous or out.size != G * C * ncell or G > T // 16
                or fac.shape != (C, P, M) or fac.dtype != cp.float32 or cell.shape != (npix,)
                or cell.dtype != cp.int32):
            raise ValueError("gauss_power: grid expects out float32 (G <= T/16, C', ncell) contiguous, fac float32 "
                             f"({C}, {P}, {M}) and cell int32 ({npix},); got {out.dtype} {tuple(out.shape)}, "
                             f"{fac.dtype} {tuple(fac.shape)}, {cell.dtype} {tuple(cell.shape)}")
        k, smem = _kernel(NP, KA, cfg, grid=True)
        k((rows, ncol // BN, C), (384,), (Aq, Bg, fac, flag, out, np.int32(M), np.int32(ncol), np.int32(T),
                                          np.int32(PA), base, np.int32(npix), cell, np.int32(ncell), np.int32(G),
                                          out if xout is None else xout, np.int32(nx)), shared_mem=smem)
        return out
    out = cp.empty((T // 16, C, P, npix), cp.float32)
    k, smem = _kernel(NP, KA, cfg)
    k((rows, ncol // BN, C), (384,), (Aq, Bg, osc, flag, out, np.int32(M), np.int32(ncol), np.int32(T),
                                      np.int32(PA), base, np.int32(npix)), shared_mem=smem)
    return out


# The configurations the shipped paths compile: two pieces (i8x2's) and three, 256 antennas (KA = 256).
register("imaging/fused_gauss.cu", *[(_defines(GAUSS_CONFIG, np_, 256, g), "sm_90a")
                                     for np_ in (2, 3) for g in (False, True)])
