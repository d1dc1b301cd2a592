"""E-field w-stacking and covariance (visibility) w-gridding imagers, NumPy or CuPy.

Both compute, to a requested accuracy ``epsilon``, the same image as the exact DFT imager
(``bf_epic_blocks.imaging.dirty_image``): for pixel k of an :class:`~.pixels.LMGrid`

    F_k(t) = sum_a D[k,a] x_a(t),   D[k,a] = w_a exp(-2 pi i (u_a l_k + v_a m_k + w_a n_k)) / N_A
    I_k    = (1/T) sum_t |F_k(t)|^2            (XY: (1/T) sum_t F_X,k F_Y,k^*)

with (u, v, w) = (x, y, z) nu / c in wavelengths, sigma = +1 (PHYSICS.md), full n (the data are not
phased to any centre), w_a the complex weight (0 = flagged: the antenna is dropped, N_A counts the
rest, per polarisation).

The gridded field (the "field plan", :class:`FieldPlan`)
--------------------------------------------------------
Computing F_k for all kept pixels of an N x N grid with cell ``c`` (pixel centres l_j = j c,
j = -N//2 .. N - N//2 - 1) is a 3-D non-uniform FFT, done with a separable ES kernel
(:mod:`.kernels`) in u, v and w:

* FFT grid: Ng = smallest even 2^a 3^b 5^c >= sigma N (sigma = 2 by default); uv cell
  du = 1 / (Ng c). An antenna at u sits at x = u / du cells; FFT output index q = j mod Ng is pixel
  l_j. Grid cell p is multiplied by (-1)^p (folded into the gridding weights), which moves pixel j
  to output j + Ng/2: the image is the central N x N block of the Ng x Ng FFT output (rows
  Ng/2 - N//2 .. Ng/2 + N - N//2 - 1, likewise columns); the rest is discarded. The FFT is pruned:
  u-axis FFT of all rows, keep those N columns, v-axis FFT, keep the kept pixels.
* Periodic wrapping: cells are taken modulo Ng. Because exp(-2 pi i x j / Ng) is Ng-periodic in x for
  integer j, a wrapped antenna contributes EXACTLY what it would on an infinite grid, at every image
  pixel. So antennas beyond the grid's Nyquist limit (|u| > Ng/2 cells, e.g. LWA-SV's outrigger) are
  exact; no split is needed for u, v.
* w: the phase exp(-2 pi i w n) is split as exp(-2 pi i w n0) exp(-2 pi i w n') with
  n0 = (n_min + n_max)/2 over the kept pixels and |n'| <= h = (n_max - n_min)/2. The first factor is
  folded into each antenna's coefficient (exact). The second is a 1-D type-3 NUFFT in w: antennas
  are spread with the same ES kernel onto w-planes spaced dw = 1 / (2 sigma h) (so that
  |dw n'| <= 1/(2 sigma), the same cutoff as u, v), W planes per antenna; plane p (at w_p) is
  FFTed, multiplied by exp(-2 pi i w_p n'_k), and the planes are summed. Number of planes
  P = ceil((w_max - w_min)/dw) + W; a single plane (no w-kernel, exact in w) when all antennas share
  one w to within 2 pi (w_max - w_min) h <= epsilon / 10 (MOFF, coplanar arrays).
* Taper correction: divide F_k by phihat(j_l/Ng) phihat(j_m/Ng) psihat(dw n'_k), the kernel's
  Fourier transforms (:func:`.kernels.es_fourier`).
* Direct ("outlier") antennas: an antenna far from the others in w costs extra w-planes for every
  time sample; ``direct='auto'`` peels antennas off both ends of the sorted w list while that
  lowers an operation count (per sample: planes x (5 Ng^2 log2 Ng^2 x 3/4 FFT + 8 npix Fresnel sum)
  + 8 W^3 per gridded antenna + 8 npix per direct antenna) and sums the peeled ones by an exact
  DFT term added to F before squaring. For LWA-SV's outrigger (10 m up) this removes ~4 planes.
* The gridding step is time independent, so it is a sparse matrix (Ng^2 P x A, A W^3 non-zeros)
  applied to the (A x batch) voltages: scipy.sparse on the CPU, cupyx.scipy.sparse (cuSPARSE) on
  the GPU; the batch dimension (time samples x polarisations) is the FFT batch.

Accuracy knob (``epsilon``, oversampling ``sigma``)
---------------------------------------------------
W and beta from :func:`.kernels.es_params` (FINUFFT formulas: W = ceil(log10(1/epsilon)) + 1,
beta = 2.30 W at sigma = 2). Work precision complex64 for epsilon >= 1e-5, complex128 below
(float32 round-off is ~1e-7 per FFT). Achieved at sigma = 2 (tests/test_wstack.py: 3-D Gaussian
cloud, LWA-SV-like core + outrigger; point-source skies; max |I - I_DFT| / max I_DFT):

    epsilon      1e-2   1e-3   1e-4   1e-5   1e-6   1e-7   1e-9
    error/eps    0.1-1.4 0.8-3.0 0.5-2.2 0.5-2.3 0.3-1.3 0.4-1.7 1.1-3.8   (E-field w-stacking)

i.e. error <= 4 epsilon (the tested bound, epsilon = 1e-2 .. 1e-6); the covariance route with this
module's gridder is ~2x better, ducc0 ~20x better (it picks its own, more conservative kernel).
sigma = 1.5 measured up to 6 epsilon. The bound is for sky-dominated data: the field error is
~epsilon x sum_a |D x_a|, so for pure-noise data the error relative to the image peak grows like
epsilon sqrt(N_A).

Covariance route (:func:`cov_wgrid_image`)
------------------------------------------
R = X X^H / T per channel and polarisation pair (weights and 1/N_A folded in), so that
I_k = sum_ab R_ab exp(-2 pi i (b_ab . s_k) nu / c), b_ab = r_a - r_b. With Hermitian symmetry only
a < b is gridded: for XX/YY, I = sum_a R_aa + 2 Re sum_{a<b} R_ab E_ab; for XY the complex image is
Re: sum_{a<b} Re((R_ab + R_ba^*) E_ab), Im: sum_{a<b} Re(-i (R_ab - R_ba^*) E_ab), plus sum_a R_aa.
The diagonal (autocorrelations, baseline 0) is a constant over pixels, added unless
``remove_autocorr``. Gridding: ducc0.wgridder (CPU, ``backend='ducc0'``; its convention, checked
against brute force: dirty[ix, iy] = Re sum V exp(+2 pi i (u x + v y) - 2 pi i w (n - 1)), so we pass
(-u, -v, w) and fold exp(-2 pi i w) into V) or the same :class:`FieldPlan` as the E-field route
applied to baselines (``backend='xp'``, NumPy or CuPy; the GPU path).
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

__all__ = ["wstack_image", "cov_wgrid_image", "FieldPlan", "get_plan", "clear_plan_cache", "work_dtype"]

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


def _field_image(efield, xyz_m, freq_hz, grid, *, epsilon, products, remove_autocorr, weights,
                 sigma, use_w, direct):
    """Shared E-field driver of :func:`wstack_image` and :func:`~.moff.moff_image`."""
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


def wstack_image(efield, xyz_m, freq_hz, grid: LMGrid, *, epsilon=1e-4, products=None,
                 remove_autocorr=False, weights=None, sigma=2.0, direct="auto"):
    """E-field w-stacking image, (nchan, nprod, grid.npix), to accuracy ~epsilon of the exact DFT.

    Parameters
    ----------
    efield : (ntime, nchan, nant, npol) complex NumPy or CuPy array, calibrated voltages.
    xyz_m : (nant, 3) antenna positions, metres East, North, Up.
    freq_hz : (nchan,) channel frequencies, Hz.
    grid : LMGrid; the result is at ``grid.lm`` (kept pixels), use ``grid.to_image`` for 2-D.
    epsilon : accuracy knob, 1e-2 .. 1e-6 tested (see the module docstring for the bound).
    products, remove_autocorr, weights : as ``dirty_image`` (weights complex (nant,) or
        broadcastable to (nchan, nant, npol); 0 = flagged, the antenna is dropped).
    sigma : uv-grid oversampling (>= 1.2; 2 is the tested default).
    direct : 'auto' (peel w-outlier antennas into an exact DFT term when cheaper), None, or a
        boolean (nant,) mask (indexing the antennas kept after flagging) of antennas to sum directly.

    Returns float32 (epsilon >= 1e-5, complex64 work) or float64 in the namespace of ``efield``.
    """
    return _field_image(efield, xyz_m, freq_hz, grid, epsilon=epsilon, products=products,
                        remove_autocorr=remove_autocorr, weights=weights, sigma=sigma, use_w=True,
                        direct=direct)


# ----------------------------------------------------------------------------- covariance route
def _ducc_grid(uvw, V, grid, epsilon, nthreads):
    """Complex-coefficient sum via ducc0: returns Re sum_b V_b exp(-2 pi i (u l + v m + w n)) (npix, B)."""
    import ducc0
    N = grid.size
    # ducc0: dirty[ix, iy] = Re sum V exp(+2 pi i (u x + v y) - 2 pi i w (n - 1)); our operator has
    # exp(-2 pi i (u l + v m + w n)) = exp(-2 pi i w) * [ducc0 with (-u, -v, w)].
    uvw_d = np.ascontiguousarray(np.stack([-uvw[:, 0], -uvw[:, 1], uvw[:, 2]], axis=-1))
    ph = np.exp(-2j * np.pi * uvw[:, 2])
    cdt = work_dtype(epsilon)
    out = np.empty((grid.npix, V.shape[1]))
    mi, li = np.nonzero(grid.mask)                      # grid.lm order; ducc's image is [ix=l, iy=m]
    for b in range(V.shape[1]):
        vis = np.ascontiguousarray((V[:, b] * ph).astype(cdt)[:, None])
        img = ducc0.wgridder.experimental.vis2dirty(
            uvw=uvw_d, freq=np.array([SPEED_OF_LIGHT_M_S]), vis=vis, npix_x=N, npix_y=N,
            pixsize_x=grid.cell, pixsize_y=grid.cell, epsilon=max(epsilon, 2e-13), do_wgridding=True,
            divide_by_n=False, nthreads=nthreads)
        out[:, b] = img[li, mi]
    return out


class CovarianceGridder:
    """Covariance + w-gridding for one array, channel set, grid and accuracy: accumulate X X^H over
    any number of calls, grid the visibilities once per image.

    ``add(efield)`` sums R = X X^H (weights and 1/N_A folded in) per channel and polarisation pair;
    ``image()`` grids the baselines a < b of R / T (w-gridding to ``epsilon``) and adds the
    autocorrelations as a constant unless ``remove_autocorr``; ``reset()`` starts a new integration.
    ``backend``: 'ducc0' (CPU, needs ``pip install ducc0``, an even grid size >= 32), 'xp' (our
    FieldPlan on the visibilities: NumPy or CuPy) or 'auto' (ducc0 for NumPy input when usable,
    else 'xp'). Other arguments as :func:`wstack_image`.
    """

    method = "covariance"

    def __init__(self, xyz_m, freq_hz, grid, npol, *, xp=np, epsilon=1e-4, products=None, remove_autocorr=False,
                 weights=None, backend="auto", sigma=2.0, direct="auto", nthreads=None):
        probe = np.zeros((1, np.atleast_1d(to_numpy(freq_hz)).size, len(to_numpy(xyz_m)), npol), np.complex64)
        _, self.xyz, self.freq, self.wts = _check_inputs(probe, xyz_m, freq_hz, grid, weights)
        self.xp, self.grid, self.npol = xp, grid, npol
        self.products = names = resolve_products(npol, products)
        self.cross = needs_cross(names)
        self.want_yy = npol == 2 and any(p in ("YY", "I", "Q") for p in names)
        self.pols = [0, 1] if npol == 2 and (self.want_yy or self.cross) else [0]
        if backend not in ("auto", "ducc0", "xp"):
            raise ValueError(f"backend must be 'auto', 'ducc0' or 'xp'; got {backend!r}")
        ducc_ok = xp is np and grid.size % 2 == 0 and grid.size >= 32
        if backend == "auto":
            try:
                import ducc0  # noqa: F401 - availability probe
                backend = "ducc0" if ducc_ok else "xp"
            except ImportError:
                backend = "xp"
        if backend == "ducc0" and not ducc_ok:
            raise ValueError("backend='ducc0' needs NumPy input and an even grid size >= 32 "
                             f"(got {'CuPy' if xp is not np else 'NumPy'} input, size {grid.size})")
        self.backend, self.epsilon, self.sigma, self.direct = backend, epsilon, sigma, direct
        self.remove_autocorr = remove_autocorr
        self.nthreads = nthreads or os.cpu_count() or 1
        self.cdt = work_dtype(epsilon)
        self.rdt = np.float32 if self.cdt == np.complex64 else np.float64
        # per channel: the antennas kept and their scales w_a / N_A (pols in use)
        self._keep, self._scale = [], []
        for c in range(len(self.freq)):
            scale = _pol_scales(self.wts[c])
            keep = np.flatnonzero(np.any(scale[:, self.pols] != 0, axis=1))
            self._keep.append(keep)
            self._scale.append(xp.asarray(scale[keep][:, self.pols].astype(self.cdt)))
        self.reset()

    def reset(self):
        self.ntime = 0
        self._R = None

    def add(self, efield):
        """Accumulate (ntime, nchan, nant, npol) complex voltages (in this gridder's namespace)."""
        xp = self.xp
        T = int(efield.shape[0])
        if T == 0:
            return
        if self._R is None:
            self._R = [dict() for _ in self.freq]
        for c, keep in enumerate(self._keep):
            # covariance in complex128 when asked for high accuracy; one GEMM per pol pair
            Xs = efield[:, c][:, xp.asarray(keep)][:, :, self.pols].astype(self.cdt) * self._scale[c][None]
            Xp = [xp.ascontiguousarray(Xs[:, :, i].T) for i in range(len(self.pols))]   # (A', T)
            pairs = [(i, i) for i in range(len(self.pols))] + ([(0, 1)] if self.cross else [])
            for i, j in pairs:
                r = Xp[i] @ Xp[j].conj().T
                self._R[c][(i, j)] = r if (i, j) not in self._R[c] else self._R[c][(i, j)] + r
        self.ntime += T

    def image(self):
        """(nchan, nprod, grid.npix) image of the samples accumulated so far."""
        if self.ntime == 0:
            raise ValueError("no samples were accumulated: cannot form an image from zero time samples")
        xp, grid, C = self.xp, self.grid, len(self.freq)
        xx = xp.zeros((C, grid.npix), self.rdt)
        yy = xp.zeros((C, grid.npix), self.rdt) if self.want_yy else None
        xy = xp.zeros((C, grid.npix), self.cdt) if self.cross else None
        for c, keep in enumerate(self._keep):
            R = {k: v / self.ntime for k, v in self._R[c].items()}
            ia, ib = np.triu_indices(keep.size, k=1)
            ia_x, ib_x = xp.asarray(ia), xp.asarray(ib)
            cols, diag = [], []
            for i in range(len(self.pols)):
                cols.append(2.0 * R[(i, i)][ia_x, ib_x])
                diag.append(xp.trace(R[(i, i)]).real)
            if self.cross:
                Rxy = R[(0, 1)]
                rab, rba = Rxy[ia_x, ib_x], Rxy[ib_x, ia_x].conj()
                cols.append(rab + rba)
                cols.append(-1j * (rab - rba))
                diag.append(xp.trace(Rxy))
            V = xp.stack(cols, axis=1)                                         # (nbl, ncols)
            uvw = (self.xyz[keep][ia] - self.xyz[keep][ib]) * (self.freq[c] / SPEED_OF_LIGHT_M_S)
            if uvw.shape[0] == 0:
                img = xp.zeros((grid.npix, V.shape[1]), self.rdt)
            elif self.backend == "ducc0":
                img = _ducc_grid(uvw, np.asarray(V), grid, self.epsilon, self.nthreads)
            else:
                plan = get_plan(uvw, grid, epsilon=self.epsilon, sigma=self.sigma, use_w=True, direct=self.direct,
                                xp=xp, dtype=self.cdt)
                img = plan.apply(V).real
            add = 0.0 if self.remove_autocorr else 1.0
            xx[c] = img[:, 0] + add * diag[0]
            k = 1
            if len(self.pols) == 2:
                if self.want_yy:
                    yy[c] = img[:, 1] + add * diag[1]
                k = 2
            if self.cross:
                xy[c] = (img[:, k] + 1j * img[:, k + 1]) + add * diag[-1]
        return combine(self.products, xx, yy, xy)

    result = image


def cov_wgrid_image(efield, xyz_m, freq_hz, grid: LMGrid, *, epsilon=1e-4, products=None,
                    remove_autocorr=False, weights=None, backend="auto", sigma=2.0, direct="auto",
                    nthreads=None):
    """Covariance + w-gridding image, (nchan, nprod, grid.npix), = the DFT image to ~epsilon.

    R = X X^H / T per channel (weights and 1/N_A folded in), baselines a < b gridded with
    w-gridding, autocorrelations added as a constant (dropped if ``remove_autocorr``); see
    :class:`CovarianceGridder` (which also accumulates R over several calls) for ``backend``.
    Other arguments as :func:`wstack_image`.
    """
    xp, _, _, _ = _check_inputs(efield, xyz_m, freq_hz, grid, weights)
    g = CovarianceGridder(xyz_m, freq_hz, grid, efield.shape[3], xp=xp, epsilon=epsilon, products=products,
                          remove_autocorr=remove_autocorr, weights=weights, backend=backend, sigma=sigma,
                          direct=direct, nthreads=nthreads)
    g.add(efield)
    return g.image()


class GriddedAccumulator:
    """Running time mean of a gridded imager over an integration that spans several calls.

    Same interface as :class:`~.dft.ImageAccumulator` (``add``, ``ntime``, ``result``, ``reset``,
    ``products``, ``method``). The imagers return time means, which are linear in the samples, so
    the mean over the integration is the sample-weighted mean of per-call images: exact.

    route : 'efield' (:func:`wstack_image`) or 'moff' (:func:`~.moff.moff_image`); for
    'covariance' use :class:`CovarianceGridder` (it sums X X^H and grids once per image), which
    :func:`gridded_accumulator` picks.
    """

    def __init__(self, xyz_m, freq_hz, grid, npol, *, route="efield", epsilon=1e-4, products=None,
                 remove_autocorr=False, weights=None):
        from .moff import moff_image
        fns = {"efield": wstack_image, "moff": moff_image}
        if route not in fns:
            raise ValueError(f"route must be one of {tuple(fns)}, got {route!r}")
        self._fn, self.method = fns[route], route
        self.products = resolve_products(npol, products)
        self._kw = dict(epsilon=epsilon, products=self.products, remove_autocorr=remove_autocorr, weights=weights)
        self.xyz_m, self.freq_hz, self.grid = xyz_m, freq_hz, grid
        self.reset()

    def reset(self):
        self.ntime = 0
        self._sum = None

    def add(self, efield):
        n = int(efield.shape[0])
        if n == 0:
            return
        img = self._fn(efield, self.xyz_m, self.freq_hz, self.grid, **self._kw)
        self._sum = img * n if self._sum is None else self._sum + img * n
        self.ntime += n

    def result(self):
        if self.ntime == 0:
            raise ValueError("no samples were accumulated: cannot form an image from zero time samples")
        return (self._sum / self.ntime).astype(self._sum.dtype, copy=False)


def gridded_accumulator(xyz_m, freq_hz, grid, npol, *, route="efield", epsilon=1e-4, products=None,
                        remove_autocorr=False, weights=None, xp=np):
    """The accumulator for a gridded route: :class:`CovarianceGridder` for 'covariance' (R summed
    over the integration, gridded once), :class:`GriddedAccumulator` for 'efield' and 'moff'."""
    if route == "covariance":
        return CovarianceGridder(xyz_m, freq_hz, grid, npol, xp=xp, epsilon=epsilon, products=products,
                                 remove_autocorr=remove_autocorr, weights=weights)
    return GriddedAccumulator(xyz_m, freq_hz, grid, npol, route=route, epsilon=epsilon, products=products,
                              remove_autocorr=remove_autocorr, weights=weights)
