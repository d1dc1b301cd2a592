"""The gridded field shared by the E-field w-stacking and MOFF imagers, and by covariance w-gridding.

:class:`FieldPlan` is the precomputed gridding operator (ES kernel, oversampled FFT grid, periodic
wrapping, optional w-planes and exact "direct" outlier antennas) described in the docstring of
:mod:`.wstack`; :func:`field_image` is the E-field driver both :func:`~.wstack.wstack_image` and
:func:`~.moff.moff_image` call. It lives here, below both, so that neither imports the other.
"""
from __future__ import annotations

import math
import os

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S
from ._xp import get_xp, to_numpy
from .dft import _as_freqs, _as_positions, _broadcast_weights
from .kernels import ESKernel, es_fourier, es_params, good_fft_size, spread_weights
from .pixels import LMGrid, n_from_lm
from .products import combine, needs_cross, resolve_products

__all__ = ["FieldPlan", "get_plan", "clear_plan_cache", "work_dtype", "field_image"]

# Bytes of the per-chunk uv-grid stack (planes x Ng^2 x batch); keeps CPU memory bounded.
_CPU_GRID_BYTES = 256 * 2**20
_GPU_GRID_BYTES = 2 * 2**30


def work_dtype(epsilon: float):
    """complex64 for epsilon >= 1e-5, complex128 below (float32 round-off limits fp32 to ~1e-6)."""
    return np.complex64 if epsilon >= 1e-5 else np.complex128


# ----------------------------------------------------------------------------- FFT helpers
def _fft(xp, a, axis):
    if xp is np:
        import scipy.fft
        return scipy.fft.fft(a, axis=axis, workers=os.cpu_count() or 1, overwrite_x=True)
    return xp.fft.fft(a, axis=axis)


def _sparse_module(xp):
    if xp is np:
        import scipy.sparse as sp
        return sp
    import cupyx.scipy.sparse as sp  # noqa: WPS433 - optional GPU dependency
    return sp


class FieldPlan:
    """Precomputed operator F = A_grid(Y) for fixed points (antennas or baselines) and grid.

    For points a with coordinates ``uvw`` (npts, 3) in wavelengths and coefficient columns Y
    (npts, B), :meth:`apply` returns F (npix, B) with
    ``F[k, b] = sum_a Y[a, b] exp(-2 pi i (u_a l_k + v_a m_k + w_a n_k))`` to accuracy epsilon
    (relative to sum_a |Y[a, b]|), at the kept pixels of ``grid`` in ``grid.lm`` order.

    Parameters: ``use_w`` False ignores w (MOFF); ``direct`` None, 'auto' or a boolean mask of
    points summed by an exact DFT; ``xp`` numpy or cupy; ``dtype`` complex64/complex128.
    Attributes useful for reports: ``Ng``, ``nplanes``, ``kernel``, ``ndirect``, ``dw``.
    """

    def __init__(self, uvw, grid: LMGrid, *, epsilon=1e-4, sigma=2.0, use_w=True, direct="auto",
                 xp=np, dtype=None):
        uvw = np.asarray(uvw, dtype=np.float64)
        if uvw.ndim != 2 or uvw.shape[1] != 3:
            raise ValueError(f"uvw must be shaped (npoints, 3); got {uvw.shape}")
        if not isinstance(grid, LMGrid):
            raise TypeError(f"grid must be an LMGrid (see bf_epic_blocks.imaging.pixels.lm_grid), got {type(grid).__name__}")
        self.xp = xp
        self.dtype = np.dtype(dtype or work_dtype(epsilon))
        self.kernel: ESKernel = es_params(epsilon, sigma)
        kern = self.kernel
        self.grid = grid
        N = grid.size
        self.npts = uvw.shape[0]
        lm = grid.lm
        n = to_numpy(n_from_lm(lm[:, 0], lm[:, 1]))
        npix = lm.shape[0]
        if not use_w:
            uvw = uvw.copy()
            uvw[:, 2] = 0.0
        self.Ng = Ng = good_fft_size(sigma * N)
        du = 1.0 / (Ng * grid.cell)
        nmin, nmax = float(n.min()), float(n.max())
        n0, h = 0.5 * (nmin + nmax), 0.5 * (nmax - nmin)
        self.dw = dw = 1.0 / (2.0 * sigma * h) if h > 0 else np.inf
        W = kern.W
        fft_cost = 0.75 * 5.0 * Ng * Ng * math.log2(Ng * Ng) + 8.0 * npix

        w = uvw[:, 2]

        def nplanes_for(wr):
            """Planes for a w range (scalar or array); 1 when a single plane is exact to eps/10."""
            wr = np.asarray(wr, dtype=np.float64)
            single = 2 * np.pi * wr * h <= 0.1 * epsilon
            P = np.where(single, 1, np.ceil(np.where(single, 0.0, wr) / dw) + W).astype(np.int64)
            return int(P) if P.ndim == 0 else P

        # ---- choose points for the direct DFT term
        if direct is None or direct is False:
            dmask = np.zeros(self.npts, bool)
        elif isinstance(direct, str):
            if direct != "auto":
                raise ValueError(f"direct must be None, 'auto' or a boolean mask; got {direct!r}")
            dmask = self._auto_direct(w, nplanes_for, fft_cost, npix, W)
        else:
            dmask = np.asarray(direct, dtype=bool).reshape(-1)
            if dmask.shape != (self.npts,):
                raise ValueError(f"direct mask must have one entry per point ({self.npts}), got shape {dmask.shape}")
        self.direct_mask = dmask
        self.ndirect = int(dmask.sum())
        gi = np.flatnonzero(~dmask)
        self.grid_index = gi
        lidx = np.rint(lm[:, 0] / grid.cell).astype(np.int64)   # j_l for each kept pixel
        midx = np.rint(lm[:, 1] / grid.cell).astype(np.int64)

        if gi.size:
            ug, vg, wg = uvw[gi, 0] / du, uvw[gi, 1] / du, w[gi]
            wr = float(wg.max() - wg.min())
            P = nplanes_for(wr)
            p0u, ku = spread_weights(ug, kern)
            p0v, kv = spread_weights(vg, kern)
            if P == 1:
                wp = np.array([0.5 * (wg.max() + wg.min())])
                fold = np.ones(gi.size)
                coef3 = (kv[:, :, None] * ku[:, None, :])[:, None]          # (A, 1, W, W)
                pl = np.zeros((gi.size, 1), np.int64)
                fres = np.exp(-2j * np.pi * wp[0] * n)[None]                # exact in w
                wcorr = np.ones(npix)
            else:
                wfirst = 0.5 * (wg.max() + wg.min()) - 0.5 * (P - 1) * dw
                wp = wfirst + dw * np.arange(P)
                p0w, kw = spread_weights((wg - wfirst) / dw, kern)
                pl = np.clip(p0w[:, None] + np.arange(W), 0, P - 1)
                coef3 = kw[:, :, None, None] * kv[:, None, :, None] * ku[:, None, None, :]
                fold = np.exp(-2j * np.pi * wg * n0)                         # exact part of the w phase
                nprime = n - n0
                fres = np.exp(-2j * np.pi * wp[:, None] * nprime[None, :])   # (P, npix)
                wcorr = es_fourier(dw * nprime, W, kern.beta)
            self.nplanes = P
            self.wplanes = wp
            cu = (p0u[:, None] + np.arange(W)) % Ng
            cv = (p0v[:, None] + np.arange(W)) % Ng
            rows = (pl[:, :, None, None] * Ng + cv[:, None, :, None]) * Ng + cu[:, None, None, :]
            # (-1)^(p_u + p_v) shifts the FFT output by Ng/2 in both axes, so the kept pixels
            # j = -N//2 .. N - N//2 - 1 become the contiguous outputs j + Ng/2 (a slice, no gather).
            checker = (1 - 2 * ((cv[:, None, :, None] + cu[:, None, None, :]) % 2))
            vals = coef3 * fold[:, None, None, None] * checker
            cols = np.broadcast_to(np.arange(gi.size)[:, None, None, None], rows.shape)
            sp_host = _sparse_module(np)
            S = sp_host.coo_matrix((vals.ravel().astype(self.dtype), (rows.ravel(), cols.ravel())),
                                   shape=(P * Ng * Ng, gi.size)).tocsr()
            S.sum_duplicates()
            self.nnz = int(S.nnz)
            self._S = S if xp is np else _sparse_module(xp).csr_matrix(S)
            phi_l = es_fourier(lidx / Ng, W, kern.beta)
            phi_m = es_fourier(midx / Ng, W, kern.beta)
            corr = fres / (phi_l * phi_m * wcorr)[None, :]
            self._corr = xp.asarray(corr.astype(self.dtype))                # (P, npix)
        else:
            self.nplanes = 0
            self.nnz = 0
            self.wplanes = np.zeros(0)
            self._S = None
        if self.ndirect:
            di = np.flatnonzero(dmask)
            ph = -2.0 * np.pi * (np.outer(lm[:, 0], uvw[di, 0]) + np.outer(lm[:, 1], uvw[di, 1])
                                 + np.outer(n, w[di]))
            self._Dd = xp.asarray(np.exp(1j * ph).astype(self.dtype))      # (npix, ndirect)
            self._di = di
        # after the checkerboard shift, pixel (j_m, j_l) is FFT output row j_m + Ng/2 and, in the
        # N-column slice starting at Ng/2 - N//2, column j_l + N//2
        self._u0 = Ng // 2 - N // 2
        self._prow_x = xp.asarray(midx + Ng // 2)
        self._pcol_x = xp.asarray(lidx + N // 2)
        self.npix = npix

    @staticmethod
    def _auto_direct(w, nplanes_for, fft_cost, npix, W):
        """Peel lo / hi points off the sorted-w ends where the operation count says it pays."""
        A = w.size
        if A < 3:
            return np.zeros(A, bool)
        order = np.argsort(w, kind="stable")
        ws = w[order]
        K = min(A // 4, 512)
        lo = np.arange(K + 1)[:, None]
        hi = np.arange(K + 1)[None, :]
        valid = lo + hi <= K
        wr = ws[np.clip(A - 1 - hi, 0, A - 1)] - ws[lo]
        P = nplanes_for(np.where(valid, wr, 0.0))
        cost = (P * fft_cost + 8.0 * (A - lo - hi) * np.where(P > 1, W ** 3, W ** 2)
                + 8.0 * npix * (lo + hi))
        cost = np.where(valid, cost, np.inf)
        blo, bhi = np.unravel_index(int(np.argmin(cost)), cost.shape)
        mask = np.zeros(A, bool)
        mask[order[:blo]] = True
        if bhi:
            mask[order[A - bhi:]] = True
        return mask

    def chunk_columns(self) -> int:
        """Batch columns per chunk that keep the uv-grid stack within the memory budget."""
        budget = _CPU_GRID_BYTES if self.xp is np else _GPU_GRID_BYTES
        per_col = max(1, self.nplanes) * self.Ng * self.Ng * self.dtype.itemsize
        return max(1, budget // per_col)

    def apply(self, Y):
        """F (npix, B) for coefficient columns Y (npts, B) (xp array, complex)."""
        xp = self.xp
        Y = xp.asarray(Y, dtype=self.dtype)
        B = Y.shape[1]
        F = xp.zeros((self.npix, B), dtype=self.dtype)
        if self._S is not None:
            N, Ng, P = self.grid.size, self.Ng, self.nplanes
            step = self.chunk_columns()
            Yg = Y[xp.asarray(self.grid_index)] if self.ndirect else Y
            for b0 in range(0, B, step):
                yb = xp.ascontiguousarray(Yg[:, b0:b0 + step])
                nb = yb.shape[1]
                G = (self._S @ yb).reshape(P, Ng, Ng, nb)                   # [plane, v, u, batch]
                G = _fft(xp, G, axis=2)
                G = G[:, :, self._u0:self._u0 + N, :]                         # keep N columns (l)
                G = _fft(xp, G, axis=1)
                G = G[:, self._prow_x, self._pcol_x, :]                      # kept pixels: (P, npix, nb)
                acc = G[0] * self._corr[0][:, None]
                for p in range(1, P):
                    acc += G[p] * self._corr[p][:, None]
                F[:, b0:b0 + nb] = acc
        if self.ndirect:
            F += self._Dd @ Y[xp.asarray(self._di)]
        return F


# ----------------------------------------------------------------------------- plan cache
# Plans depend only on geometry, frequency, grid and accuracy, which a pipeline keeps fixed, so
# they are cached (keyed by the exact bytes of the point coordinates); the cache holds at most
# _cache_nnz(xp) gridding-matrix entries in all and forgets the oldest plans first. The cap must hold
# one plan per channel of a pipeline, or every gulp rebuilds them all (seconds, on the host): on the
# GPU it is a quarter of the device memory (~12 bytes an entry), on the host 40 M entries.
_CACHE: "dict[tuple, FieldPlan]" = {}
_CACHE_NNZ = 40_000_000


def _cache_nnz(xp):
    if xp.__name__ == "cupy":
        try:
            total = xp.cuda.runtime.memGetInfo()[1]
            return max(_CACHE_NNZ, int(0.25 * total / 12))
        except Exception:
            pass
    return _CACHE_NNZ


def get_plan(uvw, grid: LMGrid, *, epsilon, sigma, use_w, direct, xp, dtype) -> FieldPlan:
    """A cached :class:`FieldPlan` (built on first use)."""
    uvw = np.ascontiguousarray(uvw, dtype=np.float64)
    dkey = direct if (direct is None or isinstance(direct, str)) else np.asarray(direct, bool).tobytes()
    key = (uvw.tobytes(), uvw.shape, grid.size, grid.cell, grid.mask.tobytes(), float(epsilon), float(sigma),
           bool(use_w), dkey, xp.__name__, np.dtype(dtype).str)
    plan = _CACHE.pop(key, None)
    if plan is None:
        plan = FieldPlan(uvw, grid, epsilon=epsilon, sigma=sigma, use_w=use_w, direct=direct, xp=xp, dtype=dtype)
    _CACHE[key] = plan                                  # (re)insert as the newest
    total = sum(p.nnz for p in _CACHE.values())
    cap = _cache_nnz(xp)
    while total > cap and len(_CACHE) > 1:
        oldest = next(iter(_CACHE))
        total -= _CACHE.pop(oldest).nnz
    return plan


def clear_plan_cache():
    """Forget all cached plans (frees their host/device memory)."""
    _CACHE.clear()


# ----------------------------------------------------------------------------- input checks
def _check_inputs(efield, xyz_m, freq_hz, grid, weights):
    xp = get_xp(efield)
    if not hasattr(efield, "ndim") or efield.ndim != 4:
        raise ValueError(f"efield must be shaped (ntime, nchan, nant, npol); got "
                         f"{getattr(efield, 'shape', type(efield).__name__)}")
    if efield.dtype.kind != "c":
        raise TypeError(f"efield must be complex (ntime, nchan, nant, npol) voltages; got dtype {efield.dtype}")
    T, C, A, npol = efield.shape
    if T < 1:
        raise ValueError("efield has no time samples (ntime = 0)")
    # the same checks as the exact DFT (host copies: plans are built on the host)
    xyz = _as_positions(to_numpy(xyz_m), np)
    if xyz.shape != (A, 3):
        raise ValueError(f"xyz_m must be shaped (nant, 3) = ({A}, 3) metres East, North, Up; got {xyz.shape}")
    freq = _as_freqs(to_numpy(freq_hz), np)
    if freq.shape != (C,):
        raise ValueError(f"freq_hz must have one frequency per channel ({C}); got shape {freq.shape}")
    if not isinstance(grid, LMGrid):
        raise TypeError(f"grid must be an LMGrid (bf_epic_blocks.imaging.pixels.lm_grid), got {type(grid).__name__}")
    wts = _broadcast_weights(None if weights is None else to_numpy(weights), C, A, npol, np)
    return xp, xyz, freq, wts


def _pol_scales(wts_c):
    """Per-pol scale w_a / N_A (N_A = unflagged antennas) for one channel; (A, npol) complex."""
    active = wts_c != 0
    nact = active.sum(axis=0)
    if np.any(nact == 0):
        p = int(np.argmax(nact == 0))
        raise ValueError(f"all antennas are flagged (weight 0) in polarisation {p}; nothing to image")
    return wts_c / nact[None, :]


def field_image(efield, xyz_m, freq_hz, grid, *, epsilon, products, remove_autocorr, weights,
                 sigma, use_w, direct):
    """Shared E-field driver of :func:`~.wstack.wstack_image` and :func:`~.moff.moff_image`: the gridded
    field F = A_grid(w x) per time sample, squared and averaged; arguments as ``wstack_image``."""
    xp, xyz, freq, wts = _check_inputs(efield, xyz_m, freq_hz, grid, weights)
    T, C, A, npol = efield.shape
    names = resolve_products(npol, products)
    cross = needs_cross(names)
    want_yy = npol == 2 and any(p in ("YY", "I", "Q") for p in names)
    pols = [0, 1] if npol == 2 and (want_yy or cross) else [0]
    cdt = work_dtype(epsilon)
    rdt = np.float32 if cdt == np.complex64 else np.float64
    xx = xp.zeros((C, grid.npix), rdt)
    yy = xp.zeros((C, grid.npix), rdt) if want_yy else None
    xy = xp.zeros((C, grid.npix), cdt) if cross else None
    for c in range(C):
        scale = _pol_scales(wts[c])                                   # (A, npol)
        keep = np.flatnonzero(np.any(scale[:, pols] != 0, axis=1))   # drop antennas flagged everywhere
        uvw = xyz[keep] * (freq[c] / SPEED_OF_LIGHT_M_S)
        plan = get_plan(uvw, grid, epsilon=epsilon, sigma=sigma, use_w=use_w, direct=direct, xp=xp, dtype=cdt)
        sc = xp.asarray(scale[keep][:, pols].astype(cdt))             # (A', npol')
        keep_x = xp.asarray(keep)
        # time chunk so that one chunk's batch (npol' x t) fits the plan's grid budget
        tstep = max(1, plan.chunk_columns() // len(pols))
        acc = {p: xp.zeros(grid.npix, rdt) for p in pols}
        accxy = xp.zeros(grid.npix, cdt) if cross else None
        auto = {p: 0.0 for p in pols}
        autoxy = 0.0
        for t0 in range(0, T, tstep):
            blk = efield[t0:t0 + tstep, c][:, keep_x][:, :, pols]        # (t, A', npol')
            nt = blk.shape[0]
            Y = (blk * sc[None]).transpose(1, 2, 0).reshape(len(keep), len(pols) * nt)
            F = plan.apply(Y).reshape(grid.npix, len(pols), nt)
            for i, p in enumerate(pols):
                acc[p] += (F[:, i].real ** 2 + F[:, i].imag ** 2).sum(axis=1).astype(rdt)
            if cross:
                accxy += (F[:, 0] * F[:, 1].conj()).sum(axis=1)
            if remove_autocorr:
                Yr = Y.reshape(len(keep), len(pols), nt)
                for i, p in enumerate(pols):
                    auto[p] = auto[p] + float((Yr[:, i].real ** 2 + Yr[:, i].imag ** 2).sum())
                if cross:
                    autoxy = autoxy + complex((Yr[:, 0] * Yr[:, 1].conj()).sum())
        xx[c] = acc[0] / T - (auto[0] / T if remove_autocorr else 0.0)
        if want_yy:
            yy[c] = acc[1] / T - (auto[1] / T if remove_autocorr else 0.0)
        if cross:
            xy[c] = accxy / T - (autoxy / T if remove_autocorr else 0.0)
    return combine(names, xx, yy, xy)
