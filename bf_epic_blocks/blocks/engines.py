"""Imaging engines: an imager block's per-sequence plan, one ``image_gulp`` call per gulp.

An imager block (:class:`~.dft_imager.DFTImagerBlock`, :class:`~.wstack.WStackBlock`) makes an
engine in ``on_sequence`` -- the operator and route for that sequence's header, kept while the next
sequence's header asks for the same one -- and its ``on_data`` is one call, ``engine.image_gulp(idata,
out)``, as Bifrost's ``FftBlock`` executes a plan made in ``on_sequence``. Every engine has:

* ``image_gulp(idata, out) -> nout``: one gulp (frames first) in, the images it completes written to
  output frames 0 .. nout;
* ``begin(...)``: a new sequence's state (frame count, output placement, non-finite tally);
* ``end_sequence() -> frames``: drop a partial integration, returning how many frames it held;
* ``products``, ``method``, ``nant_used``, ``npix``, ``ntime``: what the header records.

The engines:

* :class:`DFTEngine`: one device's :class:`~..imaging.dft.DFTOperator` and its route
  (:mod:`..imaging.routes`); 4/8-bit samples reach it as integers;
* :class:`ShardedEngine`: the channels over several GPUs (:mod:`..imaging.multigpu`), whole
  integrations only;
* :class:`GriddedEngine`: a gridded accumulator (:mod:`..imaging.wstack`).

An integration may span gulps and a gulp may hold several integrations; whole integrations at the
start of an integration are imaged in one batched call where the engine has one.
"""
from __future__ import annotations

import numpy as np

from ..imaging.pixels import check_lm
from ..runtime.dtypes import ci4_bytes, int8_pairs_decoder
from . import _compat
from ._compat import unpack_complex
from .nonfinite import zero_and_count

__all__ = ["DFTEngine", "Engine", "GriddedEngine", "ImageOutput", "ShardedEngine", "ShardedRoute"]


class ImageOutput:
    """Where a sequence's images go in the output span: frames of (nchan, nprod, npix), or (nchan, nprod,
    N, N) cells of a grid through a :class:`~..imaging.pixels.GridPlacement` ``place`` (N = ``size``).
    ``count(g)`` is told of every g images written. A placement with directions beside the grid (its
    ``extra``) writes those to frames of :attr:`xout` (nchan, nprod, extra), the second output span,
    set for each gulp by the block."""

    def __init__(self, place, size, count):
        self.place, self.size, self.count = place, size, count
        self.xout = None

    def _place(self, j, g):
        if not self.place.extra:
            return self.place
        return self.place.beside(self.xout[j:j + g])

    def write(self, out, j, imgs):
        """Images (g, nchan, nprod, npix) into output frames j .. j + g (scattered onto the grid)."""
        g = imgs.shape[0]
        if self.place is not None:
            N = self.size
            self._place(j, g)(imgs, out=out[j:j + g].reshape(imgs.shape[:3] + (N * N,)))
        else:
            out[j:j + g] = imgs
        self.count(g)

    def write_made(self, out, j, g, make):
        """g images made straight into output frames j .. j + g by ``make(place=, out=)``
        (a route's ``images``: on the GPU the products are placed on the grid as they are formed)."""
        dst = out[j:j + g]
        if self.place is not None:
            N = self.size
            make(place=self._place(j, g), out=dst.reshape(dst.shape[:3] + (N * N,)))
        else:
            dst[...] = make()
        self.count(g)


class Engine:
    """The gulp loop every engine shares: add frames to the route's integration, emit an image when it
    is full, image whole integrations in one call (:meth:`_whole`) where the engine can.

    Subclasses set :attr:`acc` (the route: ``add``, ``result``, ``reset``, ``ntime``, ``products``,
    ``method``) and give :meth:`_inputs` (the gulp as the route takes it) and, to batch,
    :meth:`_batch_min` and :meth:`_whole`."""

    def __init__(self, *, accumulate, dtype, name, pixels_fn=None):
        self.accumulate, self.dtype, self.name = int(accumulate), dtype, name
        self.pixels_fn = pixels_fn          # tracking: lm(time_tag), re-evaluated at each integration
        # time-variable gains folded into the operator: solution_hook(engine, pos, count) makes sure the
        # operator holds the solution in force at the integration starting at frame pos of the gulp, and
        # returns how many of the next ``count`` integrations share it
        self.solution_hook = None
        self.acc = None
        self.lm = None

    # ------------------------------------------------------------------ what the header records
    @property
    def products(self):
        return self.acc.products

    @property
    def method(self):
        return self.acc.method

    @property
    def ntime(self):
        return self.acc.ntime

    # ------------------------------------------------------------------ a sequence
    def begin(self, output, *, time_tag=0, ticks_per_frame=1, tally=None, seq_name=None):
        """A new sequence: its output placement, first time tag and non-finite tally (or None)."""
        self.output, self.time_tag, self.ticks_per_frame = output, time_tag, ticks_per_frame
        self.tally, self.seq_name = tally, seq_name
        self.frame = 0
        self.acc.reset()

    def end_sequence(self):
        """Frames of a partial integration, dropped (never emitted as a short image)."""
        n = self.acc.ntime
        self.acc.reset()
        return n

    # ------------------------------------------------------------------ a gulp
    def image_gulp(self, idata, out):
        """One gulp: ``idata`` the input span's array (frames first), ``out`` the output span's; returns the
        number of images written."""
        n = idata.shape[0]
        nout = 0
        A = self.accumulate
        tracking = self.pixels_fn is not None
        with _compat.stream_context():
            self._inputs(idata)
            try:
                pos = 0
                while pos < n:
                    if self.acc.ntime == 0 and tracking:
                        self._track(pos)
                    g = (n - pos) // A
                    if self.acc.ntime == 0 and self.solution_hook is not None:
                        g = min(g, self.solution_hook(self, pos, max(g, 1)))
                    least = self._batch_min()
                    if self.acc.ntime == 0 and least is not None and g >= least and tracking:
                        g = self._held_count(pos, g)        # those made with the pixels of now
                    if self.acc.ntime == 0 and least is not None and g >= least:
                        self._whole(pos, g, out, nout)
                        nout += g
                        pos += g * A
                        continue
                    take = min(A - self.acc.ntime, n - pos)
                    self.acc.add(self._frames(pos, take))
                    pos += take
                    if self.acc.ntime == A:
                        self.output.write(out, nout, self.acc.result()[None])   # (1, nchan, nprod, npix)
                        self.acc.reset()
                        nout += 1
            finally:
                self._release()
        self.frame += n
        return nout

    def _inputs(self, idata):
        """The gulp as complex voltages, non-finite samples zeroed and counted where the block counts them."""
        x = unpack_complex(idata, self.dtype)
        if self.tally is not None:
            x = zero_and_count(x, self.tally, self.frame, self.name, self.seq_name)
        self._x = x

    def _frames(self, pos, take):
        return self._x[pos:pos + take]

    def _release(self):
        """Let go of the gulp's arrays (the span's memory belongs to the ring)."""
        self._x = None

    def _batch_min(self):
        """Fewest whole integrations imaged in one call at the start of an integration; None: never."""
        return None

    def _whole(self, pos, g, out, nout):
        raise NotImplementedError

    def _track(self, pos):
        """A tracking pixel function's pixels at the integration starting at frame ``pos`` of the gulp: the
        operator rebuilt when they moved."""
        tag = self.time_tag + (self.frame + pos) * self.ticks_per_frame
        lm = check_lm(np.asarray(self.pixels_fn(tag), dtype=np.float64))
        if lm.shape != self.lm.shape or not np.array_equal(lm, self.lm):
            if lm.shape != self.lm.shape:
                raise ValueError("DFTImagerBlock: a tracking pixel function must keep the pixel count")
            self._move(lm)

    def _move(self, lm):
        """The operator for pixels ``lm`` (as many as before), where tracking pixels moved: built again
        unless the engine can move its pixels in place."""
        self._rebuild(lm)

    def _held_count(self, pos, g):
        """How many of the g integrations from frame ``pos`` a tracking pixel function gives the current
        pixels for (it holds them for steps of time, e.g. the watchlist's second): those are made by one
        batched call, and the next call starts at the integration whose pixels moved (rebuilt there), so
        that a gulp crossing a step is two batched calls, not one integration at a time. Pixels that
        move in steps do not come back within a gulp, so the last integration's are asked first: in
        most gulps they are the same, and one call answers."""
        def same(k):
            tag = self.time_tag + (self.frame + pos + k * self.accumulate) * self.ticks_per_frame
            lm = np.asarray(self.pixels_fn(tag), dtype=np.float64)
            return lm.shape == self.lm.shape and np.array_equal(lm, self.lm)
        if g <= 1 or same(g - 1):
            return g
        return next(k for k in range(1, g) if not same(k))

    def _rebuild(self, lm):
        raise NotImplementedError


class DFTEngine(Engine):
    """One device's DFT operator and route. ``build(lm) -> (operator, route)`` makes them for pixels
    ``lm`` (again when tracking pixels move). 4/8-bit voltages stay integers (exact covariances, exact
    fp16 operands), decoded inside the replayed CUDA graph when a gulp is one whole integration; a
    fused mode lays ci4 bytes out for its kernel as they are. ``products`` as the block was given them
    (the operator's graph cache and routes are keyed on them resolved)."""

    def __init__(self, build, lm, *, products, remove_autocorr, repoint=None, **kw):
        super().__init__(**kw)
        self.build, self.asked_products, self.remove_autocorr = build, products, remove_autocorr
        self.repoint = repoint
        self._rebuild(lm)

    def _rebuild(self, lm):
        # the old operator and route let go first: a whole band's are GBs, and a gain solution rebuilds them
        self.op = self.acc = None
        self.op, self.acc = self.build(lm)
        self.lm = np.asarray(lm)

    def _move(self, lm):
        """Tracking pixels moved: ``repoint(op, lm)`` forms the operator's phases again in place
        (:meth:`~..imaging.dft.DFTOperator.repoint`), keeping the route and its captured CUDA graphs; a
        new build costs ~0.6 s of host time for a watchlist's whole-band operator on a GPU, most of
        it in the graphs' captures and the int8 pieces' thousands of small kernels."""
        if self.repoint is None:
            return self._rebuild(lm)
        self.repoint(self.op, lm)
        self.lm = np.asarray(lm)

    @property
    def nant_used(self):
        return self.op.nant

    @property
    def npix(self):
        return self.op.npix

    def _inputs(self, idata):
        self._raw = idata
        if self.dtype in ("ci4", "ci8"):
            self._decode = int8_pairs_decoder(self.dtype)
            self._x = None
        else:
            self._decode = None
            super()._inputs(idata)

    def _frames(self, pos, take):
        if self._x is None:
            self._x = self._decode(self._raw)
        return self._x[pos:pos + take]

    def _release(self):
        self._x = self._raw = None

    def _batch_min(self):
        return 1 if self.op.graphs is not None else 2

    def _whole(self, pos, g, out, nout):
        A, x, idata, decode = self.accumulate, self._x, self._raw, self._decode
        if g == 1 and self.op.graphs is not None and idata.shape[0] < 2 * A:
            # a gulp of one whole integration: the operator's image(), replayed as a CUDA graph; its
            # output is used at once on this stream (placed into the span), so not copied. A lone
            # integration of a longer gulp (cut off by a gain solution or a tracking step) goes the
            # batched way below like its neighbours: the graph's eager first call would decode and place
            # with kernels the run has not used, compiled while the data flow
            sl = slice(pos, pos + A)
            imgs = self.op.image(idata[sl] if x is None else x[sl], self.asked_products,
                                 remove_autocorr=self.remove_autocorr, method=self.acc.method,
                                 decode=decode if x is None else None, static_out=True)[None]
            self.output.write(out, nout, imgs)
            return
        # several whole integrations in this gulp: one batched pass (one GEMM for all),
        # the products placed on the grid in the same pass; a fused mode lays ci4 bytes
        # out for its kernel as they are (no unpacked copy)
        ci4 = x is None and self.dtype == "ci4" and self.acc.takes_ci4
        if x is None and not ci4:
            x = self._x = decode(idata)
        sl = slice(pos, pos + g * A)
        self.output.write_made(out, nout, g, lambda **kw: self.acc.images(
            ci4_bytes(idata[sl]) if ci4 else x[sl], A, ci4=ci4, **kw))


class ShardedEngine(Engine):
    """The channels sharded over several GPUs: ``build(lm)`` gives the :class:`ShardedRoute` for pixels
    ``lm``. Whole integrations only, since a gulp holds whole integrations in that mode; the images land
    in the output span, already on the grid where the operator scatters them."""

    def __init__(self, build, lm, **kw):
        super().__init__(**kw)
        self.build = build
        self._rebuild(lm)

    def _rebuild(self, lm):
        self.acc = None             # the old route's GPU memory let go before the new is made
        self.acc = self.build(lm)
        self.lm = np.asarray(lm)

    @property
    def nant_used(self):
        return self.acc.sharded.ops[0].nant

    @property
    def npix(self):
        return self.acc.sharded.npix

    def _inputs(self, idata):
        self._x = self.acc.host_view(idata)          # packed samples: decoded on each GPU

    def _batch_min(self):
        return 1

    def _whole(self, pos, g, out, nout):
        self.acc.images_into(self._x[pos:pos + g * self.accumulate], self.accumulate, out[nout:nout + g])
        self.output.count(g)


class GriddedEngine(Engine):
    """A gridded imager (w-stacking, covariance w-gridding, MOFF): ``acc`` a gridded accumulator
    (:func:`~..imaging.wstack.gridded_accumulator`) fed complex voltages, one integration at a time."""

    def __init__(self, acc, lm, *, nant_used, npix, **kw):
        super().__init__(**kw)
        self.acc, self.lm = acc, np.asarray(lm)
        self.nant_used, self.npix = int(nant_used), int(npix)


class ShardedRoute:
    """The route interface over a :class:`~..imaging.multigpu.ShardedOperator` (several GPUs): whole
    integrations only (``images_into``), since a gulp holds whole integrations in that mode; ``method``
    "auto" resolved for integrations of ``accumulate`` samples."""

    def __init__(self, sharded, products, method, remove_autocorr, accumulate, dtype):
        from ..imaging.products import resolve_products
        self.sharded, self.dtype = sharded, dtype
        self.products = resolve_products(sharded.npol, products)
        # "auto": the resolver's pick for one GPU's operator (every GPU holds the same problem's channels)
        self.method = method if method != "auto" else sharded.ops[0].route(products, accumulate)
        self.remove_autocorr = remove_autocorr
        self.ntime = 0

    def host_view(self, idata):
        """The span as a plain host array the GPUs can copy in one piece (ci4/ci8 stay packed)."""
        names = getattr(idata.dtype, "names", None)
        if self.dtype == "ci4":
            return np.ascontiguousarray(idata[names[0]] if names else idata).view(np.uint8)
        if self.dtype == "ci8" and names:
            return np.stack([idata["re"], idata["im"]], axis=-1)
        return unpack_complex(idata, self.dtype)

    def images_into(self, x, n, out):
        """The g = len(x) // n whole integrations in x imaged into ``out`` (g, nchan, nprod, ...): the
        output span's frames, written by the GPUs' copies (pixels as the sharded operator places them)."""
        decode = int8_pairs_decoder("ci4") if self.dtype == "ci4" else None
        kw = dict(remove_autocorr=self.remove_autocorr, method=self.method, decode=decode)
        g = x.shape[0] // n
        rdtype = self.sharded.ops[0].rdtype
        in_place = out.flags.c_contiguous and out.dtype == rdtype
        flat = out.reshape(out.shape[:3] + (-1,)) if in_place else \
            np.empty(out.shape[:3] + (self.sharded.npix_out,), rdtype)   # (fp64 images, or a strided span)
        if self.method == "direct":     # one batched pass for all integrations
            self.sharded.image(x, self.products, accumulate=n, out=flat, **kw)
        else:
            # covariance route: each integration as one whole-gulp call (replayed as a CUDA graph on
            # each GPU), all of them in flight before the first is waited for
            pending = [self.sharded.submit(x[i * n:(i + 1) * n], self.products, out=flat[i], **kw)
                       for i in range(g)]
            for p in pending:
                p.result()
        if not in_place:
            out[...] = flat.reshape(out.shape)

    def add(self, x):
        raise ValueError("DFTImagerBlock on several GPUs images whole integrations only: make gulp_nframe a "
                         "multiple of accumulate (the integration)")

    def reset(self):
        pass
