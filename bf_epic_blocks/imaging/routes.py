"""The imaging routes: how a :class:`~.dft.DFTOperator` turns voltages into images.

Each route is an object with one interface, the same for all of them:

* ``add(efield)``: accumulate a gulp of one integration (an integration may span calls);
* ``result()``: the integration's image (nchan, nprod, npix); ``reset()`` starts the next;
* ``images(efield, n, *, ci4=False, place=None, out=None)``: one image per ``n`` samples of a gulp
  in one batched pass, leaving any integration in progress untouched;
* ``ntime`` (samples accumulated), ``products``, ``method`` ("direct" or "covariance"),
  ``takes_ci4`` (whether ``images`` takes ci4 bytes as they are).

The routes (conventions and the image's definition: :mod:`.dft`):

* :class:`DirectRoute`: F = D X, then sum_t F_p F_q^* per pixel;
* :class:`CovarianceRoute`: R = X X^H (exactly, in integers, for integer voltages), then
  Re diag(D R D^H);
* :class:`FusedIntegerRoute`: the direct route in a fused integer precision (:mod:`.fused`): the GEMM
  and |F|^2 in one kernel, and on a Hopper GPU the images written straight onto the grid.

:func:`make_route` makes the route for an operator, products and method ("auto": the one
:func:`.plan.resolve` picks); :func:`ImageAccumulator` is the same factory under its public name.
"""
from __future__ import annotations

import numpy as np

from .fused import FUSED
from .gemm import cmatmul, int_gram
from .layout import cov_rhs, direct_rhs, gram_rows
from .products import needs_cross, resolve_products
from .reduce import block_corr, group_power, product_coefficients, products_from_blocks, row_dot

__all__ = ["METHODS", "CovarianceRoute", "DirectRoute", "FusedIntegerRoute", "ImageAccumulator", "Route",
           "correlation_blocks", "make_route"]

METHODS = ("auto", "direct", "covariance")


def correlation_blocks(npol, products):
    """The correlation blocks (p, q) the products need: the auto-pols (0, 0), (1, 1) the products read,
    plus (0, 1) if any cross product is asked. ``products``: resolved names (:func:`.products.resolve_products`)."""
    blocks = []
    if any(p in ("XX", "I", "Q") for p in products):
        blocks.append((0, 0))
    if npol == 2 and any(p in ("YY", "I", "Q") for p in products):
        blocks.append((1, 1))
    if needs_cross(products):
        blocks.append((0, 1))
    return blocks


def make_route(op, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):
    """The route that images ``products`` with operator ``op`` by ``method``.

    method : "direct", "covariance", or "auto" (the route :func:`.plan.resolve` picks for
        integrations of ``ntime_hint`` samples: the cheaper one). A fused integer precision (:data:`.fused.FUSED`) is
        the direct route's kernel for the pols' own powers: it takes "auto" or "direct" and products
        of XX, YY, I, Q.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    names = resolve_products(op.npol, products)
    if op.precision in FUSED:
        if method == "covariance" or needs_cross(names):
            raise ValueError(f"precision {op.precision!r} images the direct route's XX/YY powers (products "
                             f"XX, YY, I, Q); asked for method={method!r}, products {names}: "
                             "use 'fp16x3' or 'fp32' for the covariance route or cross-pol products")
        return FusedIntegerRoute(op, products, remove_autocorr=remove_autocorr)
    if method == "auto":     # the resolver's pick, as everywhere (DFTOperator.route)
        method = op.route(products, ntime_hint)
    cls = CovarianceRoute if method == "covariance" else DirectRoute
    return cls(op, products, remove_autocorr=remove_autocorr)


def ImageAccumulator(op, products=None, *, remove_autocorr=False, method="auto", ntime_hint=1024):  # noqa: N802
    """The route for ``op`` (:func:`make_route`), under the name the public API has always used."""
    return make_route(op, products, remove_autocorr=remove_autocorr, method=method, ntime_hint=ntime_hint)


class Route:
    """What every route shares: the products' correlation blocks, the static per-block factors, and the
    last pass from correlation sums to products (scales, 1/N_A^2, the pattern, dead channel-pols NaN,
    the grid placement). Subclasses keep the sums: :meth:`_reset`, :meth:`_add`, :meth:`_sums`,
    :meth:`_images`."""

    method = None

    def __init__(self, op, products=None, *, remove_autocorr=False):
        self.op = op
        xp = op.xp
        self.products = resolve_products(op.npol, products)
        self.cross = needs_cross(self.products)
        self.blocks = blocks = correlation_blocks(op.npol, self.products)
        self.pols = sorted({p for b in blocks for p in b})
        self.remove_autocorr = bool(remove_autocorr)
        self.nchan_live = op.nchan if op.chan_index is None else int(op.chan_index.shape[0])
        # Static per-block factors of the image, made once: 1/(N_p N_q) (C', nblk, 1), and the
        # antenna-independent pattern B_p conj(B_q) (C'|1, nblk, K) if there is one.
        norm = op.norm if op.chan_index is None else op.norm[op.chan_index]
        self._blkscale = xp.stack([norm[:, p] * norm[:, q] for p, q in blocks], axis=1)[..., None].astype(op.rdtype)
        self._bw = self._pattern_factors()
        self._bidx = [(self.pols.index(p), self.pols.index(q)) for p, q in blocks]
        self._coef = None
        self.reset()
        op._routes.add(self)

    def _pattern_factors(self):
        """B_p conj(B_q) per block, (C'|1, nblk, K), of the operator's antenna-independent pattern, or None."""
        op, xp = self.op, self.op.xp
        if op.pixel_pattern is None:
            return None
        B = op.pixel_pattern if op.chan_index is None or op.pixel_pattern.shape[0] == 1 \
            else op.pixel_pattern[op.chan_index]                                     # (C'|1, K, P|1)
        return xp.stack([B[:, :, min(p, B.shape[2] - 1)] * xp.conj(B[:, :, min(q, B.shape[2] - 1)])
                         for p, q in self.blocks], axis=1)

    def refresh(self):
        """The operator's pixels moved (:meth:`.dft.DFTOperator.repoint`): what this route keeps of them is
        formed again in place (the arrays a captured CUDA graph reads stay where they are)."""
        if self._bw is not None:
            self._bw[...] = self._pattern_factors()

    # ------------------------------------------------------------------ the interface
    def reset(self):
        """Forget the integration in progress."""
        self.ntime = 0
        self._reset()

    def add(self, efield):
        """Accumulate voltages (ntime, nchan, nant, npol) complex, or integer (re, im) pairs."""
        if efield.shape[0] == 0:
            return
        ints = self.op._check_efield(efield)
        self._add(efield, ints)
        self.ntime += int(efield.shape[0])

    def result(self):
        """The image (nchan, nprod, npix), real, in the operator's precision; NaN where all antennas of a
        contributing channel-pol are flagged. Raises if nothing was accumulated."""
        if self.ntime == 0:
            raise ValueError("no samples were accumulated: cannot form an image from zero time samples")
        return self._result()

    @property
    def takes_ci4(self):
        """Whether :meth:`images` takes ci4 bytes as they are (``ci4=True``): only a fused integer mode's
        direct route without autocorrelation removal lays the bytes out for its kernel in one pass."""
        return False

    def images(self, efield, n, *, ci4=False, place=None, out=None):
        """One image per ``n`` consecutive samples of ``efield``: (ntime // n, nchan, nprod, npix).

        Independent of (and leaving untouched) any integration in progress. Direct route: one batched
        pass; covariance route: one exact covariance per group (chosen only for long groups).

        ci4 : ``efield`` is ci4 bytes, uint8 (ntime, nchan, nant, npol) (high nibble real), imaged
            without unpacking (only where :attr:`takes_ci4`).
        place, out : a :class:`.pixels.GridPlacement` and the float32 (ntime // n, nchan, nprod, N)
            array the images are placed into (cells with no pixel NaN; on the GPU in the same pass as
            the products). Returns ``out``."""
        op, xp = self.op, self.op.xp
        if ci4:
            return self._images_ci4(efield, n, place, out)
        ints = op._check_efield(efield)
        g = int(efield.shape[0]) // n
        if g == 0:
            return out if out is not None else xp.zeros((0, op.nchan, len(self.products), op.npix), op.rdtype)
        return self._images(efield[:g * n], ints, n, g, place, out)

    def _images_ci4(self, efield, n, place, out):
        raise ValueError("ImageAccumulator.images: ci4 bytes are imaged as they are only by a fused "
                         "integer mode's direct route without autocorrelation removal")

    # ------------------------------------------------------------------ correlation sums -> products
    def _finish(self, corr, factor, place=None, out=None):
        """(..., C', nblk, K) complex correlation sums, times ``factor`` -> (..., nchan, nprod, K) products;
        with a :class:`.pixels.GridPlacement` ``place``, placed into ``out`` (..., nchan, nprod, N)."""
        xp, op = self.op.xp, self.op
        # one pass: scale, 1/N_A^2, the pattern and the products' Re/Im combinations together (reduce.py);
        # on the GPU also the placement on the grid when every channel is live
        if self._coef is None:
            self._coef = xp.asarray(product_coefficients(self.products, self.blocks))
        scale = self._blkscale[..., 0] * op.rdtype(factor)
        gather = None if place is None or op.chan_index is not None or out is None else place.gather
        if gather is not None and out.dtype == np.float32 and out.flags.c_contiguous:
            products_from_blocks(corr, scale, self._coef, weight=self._bw, gather=gather, out=out)
            self._fill_dead(out)
            if place.extra:          # the directions beside the grid (few): their products on their own
                k0 = place.ngrid
                bw = None if self._bw is None else self._bw[..., k0:]
                products_from_blocks(xp.ascontiguousarray(corr[..., k0:]), scale, self._coef, weight=bw,
                                     out=place.xout)
                self._fill_dead(place.xout)
            return out
        res = products_from_blocks(corr, scale, self._coef, weight=self._bw).astype(op.rdtype, copy=False)
        if op.chan_index is not None:
            full = xp.full(res.shape[:-3] + (op.nchan,) + res.shape[-2:], xp.nan, dtype=op.rdtype)
            full[..., op.chan_index, :, :] = res
            res = full
        self._fill_dead(res)
        return res if place is None else place(res, out=out)   # (and the pixels beside the grid, if any)

    def _fill_dead(self, res):
        """NaN where all antennas of a contributing channel-pol are flagged (res: (..., nchan, nprod, cells))."""
        op, xp = self.op, self.op.xp
        if op.any_dead:
            for k, name in enumerate(self.products):
                pols = {"XX": (0,), "YY": (1,)}.get(name, tuple(range(op.npol)))
                bad = xp.any(op.dead[:, list(pols)], axis=1)
                res[..., bad, k, :] = xp.nan

    def _autocorr_term(self, auto):
        """sum_a D^p_ka conj(D^q_ka) sum_t x_ap conj(x_aq): (..., C', nblk, K); data already weighted."""
        xp, op = self.op.xp, self.op
        if op.shared_geometry:  # |G| = 1: the term is the same for every pixel
            s = auto.sum(axis=-1)
            return xp.broadcast_to(s[..., None], s.shape + (op.npix,))
        terms = []
        for i, (pp, qq) in enumerate(self.blocks):
            gg = op.live_G(pp) * xp.conj(op.live_G(qq))  # (C', K, A)
            terms.append(xp.matmul(gg, auto[..., i, :, None])[..., 0])
        return xp.stack(terms, axis=-2)

    def _auto_sums(self, x, n):
        """(c, nblk, A, groups): sums over groups of n samples of x_p conj(x_q) per antenna."""
        xp = self.op.xp
        return xp.stack([group_power(x[:, pp], x[:, qq] if pp != qq else None, n).astype(self.op.cdtype)
                         for pp, qq in self.blocks], axis=1)


class DirectRoute(Route):
    """F = D X for each gulp, then per-pixel sums of F_p F_q^* (and, to remove the autocorrelations,
    per-antenna sums of x_p x_q^*). :meth:`images` is one batched pass: one GEMM for the whole gulp,
    the sums taken per group of ``n`` samples."""

    method = "direct"

    def _reset(self):
        self._S = None      # (C', nblk, K) sums of F_p F_q^*
        self._auto = None   # (C', nblk, A) sums of x_p x_q^*

    def _add(self, efield, ints):
        sums, auto = self._direct_sums(efield, ints, int(efield.shape[0]))
        if self._S is None:
            self._S, self._auto = sums[0], (None if auto is None else auto[0])
        else:
            self._S += sums[0]
            if auto is not None:
                self._auto += auto[0]

    def _result(self):
        corr = self._S
        if self.remove_autocorr:
            corr = corr - self._autocorr_term(self._auto)
        return self._finish(corr, 1.0 / self.ntime)

    def _images(self, efield, ints, n, g, place, out):
        S, auto = self._direct_sums(efield, ints, n)                        # (g, C', nblk, K)
        if auto is not None:
            S = S - self._autocorr_term(auto)
        return self._finish(S, 1.0 / n, place=place, out=out)

    def _direct_sums(self, efield, ints, n):
        """Direct route over one gulp: ((g, C', nblk, K) sums over groups of n samples of F_p F_q^*,
        (g, C', nblk, A) autocorrelation sums or None), g = ntime // n."""
        op, xp = self.op, self.op.xp
        t = int(efield.shape[0])
        g = t // n
        per_chan = op.npix * len(self.pols) * t * np.dtype(op.cdtype).itemsize
        fast = ints and op.unit_weights and op.shared_geometry and per_chan <= op.chunk_bytes()
        x = op.prepare(efield) if (self.remove_autocorr or not fast) else None
        auto = xp.moveaxis(self._auto_sums(x, n), -1, 0) if self.remove_autocorr else None
        S = xp.zeros((g, self.nchan_live, len(self.blocks), op.npix), dtype=op.cdtype)
        if fast:
            # integer voltages straight into the GEMM's operand form: one transpose kernel, no copies
            rhs = direct_rhs(efield, op.sel, self.pols, op.precision, op.stacked)
            cchunk = max(1, min(self.nchan_live, op.chunk_bytes() // per_chan))
            for c0 in range(0, self.nchan_live, cchunk):
                cs = slice(c0, min(self.nchan_live, c0 + cchunk))
                F, stacked = op.field_gemm_parts(0, [rhs[cs]], cs, exact=True)
                S[:, cs] = block_corr(F, self._bidx, n, npol=len(self.pols), stacked=stacked)
            return S, auto
        for cs, t0, F, stacked, scale in self._fields(x, ints and op.unit_weights):
            nt = F.shape[-1] // len(self.pols)
            sc = None if scale is None else scale * scale
            if t0 % n == 0 and nt % n == 0:
                S[t0 // n:(t0 + nt) // n, cs] += block_corr(F, self._bidx, n, npol=len(self.pols), stacked=stacked,
                                                            scale=sc)
            else:   # a group split across time chunks (CPU memory cap): sum its parts one by one
                Fc = F[:, 0] + 1j * F[:, 1] if stacked else F
                Fc = Fc.reshape(Fc.shape[0], op.npix, len(self.pols), nt)
                for j in range(t0 // n, min(g, -(-(t0 + nt) // n))):
                    lo, hi = max(j * n, t0) - t0, min((j + 1) * n, t0 + nt) - t0
                    part = xp.ascontiguousarray(Fc[..., lo:hi]).reshape(Fc.shape[0], op.npix, -1)
                    S[j, cs] += block_corr(part, self._bidx, hi - lo, npol=len(self.pols), scale=sc)[0]
        return S, auto

    def _fields(self, x, exact):
        """Yield (channel slice, t0, F, stacked, scale) chunks of the beamformed fields.

        F: complex (c, K, P' t) or stacked float32 (c, 2, K, P' t), columns p' * t + time (p' over
        ``self.pols``); see :meth:`.dft.DFTOperator.field_gemm` for ``stacked`` and ``scale``."""
        op, xp = self.op, self.op.xp
        c, p, a, t = x.shape
        per_chan_t = op.npix * len(self.pols) * np.dtype(op.cdtype).itemsize
        tchunk = max(1, min(t, op.chunk_bytes() // max(1, per_chan_t)))
        cchunk = max(1, min(c, op.chunk_bytes() // max(1, per_chan_t * tchunk)))
        for c0 in range(0, c, cchunk):
            cs = slice(c0, min(c, c0 + cchunk))
            for t0 in range(0, t, tchunk):
                xs = x[cs, :, :, t0:t0 + tchunk]
                nc, nt = xs.shape[0], xs.shape[-1]
                if op.shared_geometry:
                    # both pols in one GEMM: (c, K, A) @ (c, A, P' t)
                    rhs = xs[:, self.pols].transpose(0, 2, 1, 3).reshape(nc, a, len(self.pols) * nt)
                    yield (cs, t0) + op.field_gemm(0, rhs, cs, exact=exact)
                else:   # antenna-dependent pattern: one operator per pol (a rarer, slower path)
                    F = xp.concatenate([op.field_gemm_complex(pp, xp.ascontiguousarray(xs[:, pp]), cs, exact=exact)
                                        for pp in self.pols], axis=-1)
                    yield cs, t0, F, False, None


class FusedIntegerRoute(DirectRoute):
    """The direct route in a fused integer precision (:mod:`.fused`): integer voltages of at most 4 bits,
    groups of a multiple of 16 samples, the GEMM and |F|^2 in one kernel, products of the pols' own
    powers (XX, YY, I, Q). ci4 bytes are laid out for the kernel as they are (:attr:`takes_ci4`); on a
    Hopper GPU 16-sample images of one such product go straight onto the grid (:meth:`_grid_images`)."""

    @property
    def takes_ci4(self):
        return not self.remove_autocorr

    def _direct_sums(self, efield, ints, n):
        """:meth:`DirectRoute._direct_sums` in a fused integer mode: the GEMM and |F|^2 in one kernel."""
        op, t = self.op, int(efield.shape[0])
        if not ints or not op.fused.supports(t, n):
            raise ValueError(
                f"precision {op.precision!r} images integer (re, im) voltages of at most 4 bits in groups of a "
                f"multiple of 16 samples; got {'integer' if ints else 'complex'} voltages, {t} samples in groups "
                f"of {n}: use 'fp16x3' or 'fp32'")
        S = op.fused.sums(efield, self.pols, n)                       # (g, C', nblk, K), blocks (p, p)
        auto = None
        if self.remove_autocorr:
            auto = op.xp.moveaxis(self._auto_sums(op.prepare(efield[:(t // n) * n]), n), -1, 0)
        return S, auto

    def _images(self, efield, ints, n, g, place, out):
        if ints and not self.remove_autocorr and self._onto_grid(n, g, place, out):
            return self._grid_images(efield, 1.0 / n, place, out)
        return super()._images(efield, ints, n, g, place, out)

    def _images_ci4(self, efield, n, place, out):
        op = self.op
        if not self.takes_ci4:
            super()._images_ci4(efield, n, place, out)
        t, c, a, p = efield.shape
        if efield.dtype != np.uint8 or (c, a, p) != (op.nchan, op.nant_in, op.npol):
            raise ValueError(f"ci4 bytes must be uint8 (ntime, {op.nchan}, {op.nant_in}, {op.npol}), got "
                             f"{efield.dtype} {tuple(efield.shape)}")
        g = t // n
        if not op.fused.supports(g * n, n):
            raise ValueError(f"precision {op.precision!r} images groups of a multiple of 16 samples, got {n}")
        if self._onto_grid(n, g, place, out):
            return self._grid_images(efield[:g * n], 1.0 / n, place, out, ci4=True)
        S = op.fused.sums(efield[:g * n], self.pols, n, ci4=True)
        return self._finish(S, 1.0 / n, place=place, out=out)

    def _onto_grid(self, n, g, place, out):
        """Whether a fused mode's images of ``n`` samples go straight onto the grid (:meth:`_grid_images`):
        the Hopper kernel, 16-sample images, one product that is a real sum of the pols' powers (XX, YY, I,
        Q), every channel live, and ``out`` the float32 (g, nchan, 1, cells) array of ``place``."""
        op = self.op
        if place is None or out is None or op.precision not in FUSED or op.chan_index is not None or n != 16:
            return False
        if not op.fused.onto_grid() or len(self.products) != 1 or place.gather is None:
            return False
        coef = product_coefficients(self.products, self.blocks)          # (host: a few numbers)
        return (out.dtype == np.float32 and out.flags.c_contiguous and out.shape == (g, op.nchan, 1, place.n)
                and not bool(np.any(coef[..., 1])))

    def _grid_factor(self, factor):
        """(C', P', Kpad) float32: what the fused kernel's pol sums are multiplied by to give the product
        (the operator's scale, 1/(N_p N_q) times ``factor``, the pattern, the product's coefficient) --
        what :func:`.reduce.products_from_blocks` applies, made once per factor."""
        key = float(factor)
        if getattr(self, "_fac_key", None) != key:
            self._fac, self._fac_key = self._grid_factor_array(key), key
        return self._fac

    def refresh(self):
        super().refresh()
        if getattr(self, "_fac_key", None) is not None:
            self._fac[...] = self._grid_factor_array(self._fac_key)

    def _grid_factor_array(self, factor):
        op, xp = self.op, self.op.xp
        osc = op.fused.osc                                                  # (C', PA, Kpad)
        PA, K = int(osc.shape[1]), op.npix
        coef = product_coefficients(self.products, self.blocks)
        scale = self._blkscale[..., 0] * op.rdtype(factor)                  # (C', nblk)
        fac = xp.zeros((osc.shape[0], len(self.pols), osc.shape[2]), xp.float32)
        for b, (p, q) in enumerate(self.blocks):
            i = self.pols.index(p)
            f = osc[:, i if PA > 1 else 0].astype(xp.float64) * (scale[:, b].astype(xp.float64) * float(coef[0, b, 0]))[:, None]
            if self._bw is not None:
                f[:, :K] *= self._bw[:, b, :].real.astype(xp.float64)
            fac[:, i] = f
        return fac

    def _grid_images(self, efield, factor, place, out, ci4=False):
        """A fused mode's 16-sample images made straight into ``out`` (g, nchan, 1, cells) by the kernel
        (:meth:`.fused.FusedOperator.place`), each pol's share added to the cleared cells (0; NaN where no
        pixel is): no per-pol sums in memory and no products pass; dead channel-pols NaN as elsewhere."""
        op = self.op
        o3 = out.reshape(out.shape[0], out.shape[1], out.shape[3])
        place.clear(o3)
        x3 = None
        if place.extra:                                  # the directions beside the grid, in the same kernel
            x = place.xout
            if x is None or not x.flags.c_contiguous or x.shape != out.shape[:3] + (place.extra,):
                raise ValueError(f"the pixels beside the grid need a contiguous {out.shape[:3] + (place.extra,)} "
                                 f"destination, got {None if x is None else tuple(x.shape)}")
            x.fill(0)
            x3 = x.reshape(x.shape[0], x.shape[1], x.shape[3])
        op.fused.place(efield, self.pols, self._grid_factor(factor), place.cells, o3, ci4=ci4, xout=x3)
        self._fill_dead(out)
        if x3 is not None:
            self._fill_dead(place.xout)
        return out


class CovarianceRoute(Route):
    """R = X X^H summed over the integration (only the polarisation blocks the products need; exactly,
    in integers, for integer voltages, the weights applied afterwards), then Re diag(D R D^H) / T.
    :meth:`images` makes one exact covariance per group of ``n`` samples (the route is chosen only for
    long groups)."""

    method = "covariance"

    def _reset(self):
        self._R = None      # complex input: (C', nblk, A, A)
        self._W = None      # integer input: (C', R, R) int32 (GPU) / float64 (CPU) Gram sums
        self._W64 = None    # GPU: int64 bank the int32 sums are flushed to before they could overflow
        self._wn = 0        # samples in the int32 sums

    def _add(self, efield, ints):
        op = self.op
        if ints:
            if self._R is not None:
                raise TypeError("one integration cannot mix complex and integer voltages")
            self._add_int_covariance(gram_rows(efield, op.sel))
        else:
            if self._W is not None or self._W64 is not None:
                raise TypeError("one integration cannot mix complex and integer voltages")
            self._add_covariance(op.prepare(efield))

    def _result(self):
        return self._finish(self._image_covariance(), 1.0)   # already divided by ntime

    def _images(self, efield, ints, n, g, place, out):
        xp = self.op.xp
        sub = CovarianceRoute(self.op, self.products, remove_autocorr=self.remove_autocorr)
        imgs = []
        for i in range(g):
            sub.add(efield[i * n:(i + 1) * n])
            imgs.append(sub.result())
            sub.reset()
        imgs = xp.stack(imgs)
        return imgs if place is None else place(imgs, out=out)

    def _add_covariance(self, x):
        op, xp = self.op, self.op.xp
        c, p, a, t = x.shape
        if self._R is None:
            self._R = xp.zeros((c, len(self.blocks), a, a), dtype=op.cdtype)
        prec = "fp64" if op.precision == "fp64" else "fp32"   # the data are not integers: R in fp32
        for i, (pp, qq) in enumerate(self.blocks):
            xq_h = xp.ascontiguousarray(xp.conj(x[:, qq]).swapaxes(1, 2))
            self._R[:, i] += cmatmul(x[:, pp], xq_h, prec)

    # int32 sums of 4/8-bit products: a sample adds at most 2 * 128^2 to an entry
    _INT32_SAMPLES = (2**31 - 1) // (2 * 128 * 128)

    def _add_int_covariance(self, z):
        xp = self.op.xp
        t = z.shape[-1]
        if xp is np:
            step = (2**24 - 1) // (2 * 128 * 128)     # float32 sums stay exact below 2^24
            if self._W is None:
                self._W = np.zeros((z.shape[0], z.shape[1], z.shape[1]), np.float64)
            for t0 in range(0, t, step):
                int_gram(z[..., t0:t0 + step], out=self._W, accumulate=True)
            return
        if self._W is not None and self._wn + t > self._INT32_SAMPLES:
            self._W64 = self._W.astype(xp.int64) if self._W64 is None else self._W64 + self._W
            self._W, self._wn = None, 0
        self._W = int_gram(z, out=self._W, accumulate=self._W is not None)
        self._wn += t

    def _gram(self):
        """The integer Gram sums W (C', R, R) (int32/int64 on the GPU, float64 on the CPU) or None."""
        if self._W64 is None:
            return self._W
        return self._W64 if self._W is None else self._W64 + self._W

    def _int_weights(self):
        op = self.op
        return op.weights128 if op.chan_index is None else op.weights128[op.chan_index]   # (C', A, P)

    def _covariance_blocks(self):
        """Weighted covariance blocks (C', nblk, A, A) complex, unnormalised (sums over time)."""
        W = self._gram()
        if W is None:
            return self._R
        op, xp = self.op, self.op.xp
        rhs = cov_rhs(W, self._int_weights(), self.blocks, op.npol, "fp64" if op.precision == "fp64" else "fp32",
                      False, unit=op.unit_weights)[0][0]                         # (C', A, nblk A)
        c, a = rhs.shape[0], rhs.shape[1]
        return xp.ascontiguousarray(rhs.reshape(c, a, len(self.blocks), a).transpose(0, 2, 1, 3))

    def _image_covariance(self):
        """(C', nblk, K): Re diag(D_p R_pq D_q^H) / ntime (complex for XY), minus the autocorrelations if asked."""
        xp, op = self.op.xp, self.op
        W = self._gram()
        nblk, a = len(self.blocks), op.nant
        itemsize = np.dtype(op.cdtype).itemsize
        c = self.nchan_live
        cchunk = max(1, min(c, op.chunk_bytes() // max(1, op.npix * nblk * a * itemsize)))
        out = xp.empty((c, nblk, op.npix), dtype=xp.complex128 if op.precision == "fp64" else xp.complex64)
        if W is not None and op.shared_geometry:
            # exact integer sums straight into the GEMM's operand form (weights, 1/T and the fp16
            # range scale applied in the same pass). The same-antenna terms stay out of the GEMM and
            # are added exactly here (|D| = 1: a constant per channel and block): the GEMM's rounding
            # is then relative to the cross-correlations, not to the much larger autocorrelations.
            s = op.cov_scale
            rhs, diag = cov_rhs(W, self._int_weights(), self.blocks, op.npol, op.precision, op.stacked,
                                scale=s / self.ntime, unit=op.unit_weights, nodiag=True)
            for c0 in range(0, c, cchunk):
                cs = slice(c0, min(c, c0 + cchunk))
                M, stacked = op.field_gemm_parts(0, [p[cs] for p in rhs], cs)
                r = row_dot(M, op.live_G(0)[cs], nblk, stacked=stacked, scale=None if s == 1 else 1.0 / s)
                if cchunk >= c:
                    out = r          # one chunk: no copy
                else:
                    out[cs] = r
            if not self.remove_autocorr:
                out = out + (diag.sum(axis=-1) / self.ntime).astype(out.dtype)[..., None]
            return out
        else:
            R = self._covariance_blocks()                         # (C', nblk, A, A) sums
            for c0 in range(0, c, cchunk):
                cs = slice(c0, min(c, c0 + cchunk))
                nc = cs.stop - cs.start
                if op.shared_geometry:
                    rhs = R[cs].transpose(0, 2, 1, 3).reshape(nc, a, nblk * a)      # [R_b0 | R_b1 | ...]
                    M, stacked, scale = op.field_gemm(0, rhs, cs)
                    out[cs] = row_dot(M, op.live_G(0)[cs], nblk, stacked=stacked, scale=scale)
                else:
                    for i, (pp, qq) in enumerate(self.blocks):
                        M = op.field_gemm_complex(pp, xp.ascontiguousarray(R[cs, i]), cs)
                        out[cs, i] = row_dot(M, op.live_G(qq)[cs], 1)[:, 0]
            out = out / self.ntime
        if self.remove_autocorr:   # the diagonal's contribution, subtracted: R itself is not copied
            out = out - self._autocorr_term(self._covariance_diag()) / self.ntime
        return out

    def _covariance_diag(self):
        """(C', nblk, A): the weighted same-antenna terms sum_t w_p x_ap conj(w_q x_aq)."""
        xp, op = self.op.xp, self.op
        W = self._gram()
        if W is None:
            return xp.diagonal(self._R, axis1=-2, axis2=-1)
        c, r, _ = W.shape
        a, P = op.nant, op.npol
        d = W.reshape(c, a, P * 2, a, P * 2)
        d = d[:, xp.arange(a), :, xp.arange(a), :]            # (A, C', 2P, 2P): same-antenna blocks
        d = xp.moveaxis(d, 0, 1).astype(xp.float64)             # (C', A, 2P, 2P)
        w = self._int_weights()
        out = []
        for p, q in self.blocks:
            re = d[:, :, 2 * p, 2 * q] + d[:, :, 2 * p + 1, 2 * q + 1]
            im = d[:, :, 2 * p + 1, 2 * q] - d[:, :, 2 * p, 2 * q + 1]
            out.append((re + 1j * im) * w[:, :, p] * xp.conj(w[:, :, q]))
        return xp.stack(out, axis=1).astype(op.cdtype)
