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

The imaging blocks and the pipeline do not take ``epsilon``: their knob is ``tolerance``, the
largest relative image error, and :func:`.plan.resolve` sets epsilon = tolerance / 4 from this
tested bound (:data:`.plan.GRIDDED_ERROR_FACTOR`). The functions here take the gridder's own
``epsilon``, as ducc0.wgridder does.

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

import os

import numpy as np

from ..conventions import SPEED_OF_LIGHT_M_S
from ._xp import to_numpy
from .fieldgrid import FieldPlan, _check_inputs, _pol_scales, clear_plan_cache, field_image, get_plan, work_dtype
from .pixels import LMGrid
from .products import combine, needs_cross, resolve_products

__all__ = ["wstack_image", "cov_wgrid_image", "FieldPlan", "get_plan", "clear_plan_cache", "work_dtype"]


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
    return field_image(efield, xyz_m, freq_hz, grid, epsilon=epsilon, products=products,
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
