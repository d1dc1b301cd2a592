"""Tree dedispersion (the fast dispersion measure transform, FDMT; Zackay & Ofek 2017) of image series.

Why: incoherent dedispersion by shifted sums costs ``ntrial x nchan`` adds per pixel and image. At the
whole band's cadence (784 channels of LWA-SV from 74 MHz, 0.64-ms images, DM 0-3: a sweep of 1,330
images, so 1,331 trials one image apart) that is ~1.0e6 adds per pixel-image; the tree needs
~``ntrial x log2(nchan)`` (12,283 rows of shifted adds against 1,043,504). :func:`fdmt` transforms a
whole series (array code, NumPy or CuPy; one gather-add per merge); :class:`StreamingFDMT` does the
same a block at a time, for :mod:`.statistics`' streaming search (``dedisperse='tree'``).

Definitions (images, channels sorted by frequency; f in any unit)
-------------------------------------------------------------------
For a range R of channels a..b (a the lowest frequency) and a sweep d (images between the arrival at
f_b and at f_a), channel c of R is read ``back_R(d, c)`` images before the range's newest time:

    A_R[d, t] = sum_{c in R} I_c(t - back_R(d, c)),   back_R(d, a) = 0,  back_R(d, b) = d.

A single channel has d = 0 only. Two ranges L = a..m-1 and U = m..b merge as

    A_R[d, t] = A_L[d_L, t] + A_U[d_U, t - o],
    d_L = rint(d * (f_a^-2 - f_{m-1}^-2) / (f_a^-2 - f_b^-2)),
    o   = rint(d * (f_a^-2 - f_m^-2)     / (f_a^-2 - f_b^-2)),   d_U = d - o,

so every trial's highest channel sits exactly d images back and the others within a rounding or two
of the dispersion curve, whose delay ~f^-2: the levels' roundings add up to at most 1 image off
``rint(d (f_a^-2 - f_c^-2) / (f_a^-2 - f_b^-2))`` for 40 channels and 2 for 784 channels and sweeps to
1,875 (tests/test_fdmt.py); :func:`effective_back` gives each channel's read offset exactly. Ranges are
split in halves; the plan (which d each range must provide) is made top-down from the trials asked for.

Cost and memory: one shifted add per (range, d) of its level, ``sum_levels sum_R (dmax_R + 1)``
rows of ``T x npix`` (~ntrial x log2(nchan) rows); the largest array is the last level's
``(ntrial, T, npix)``, so callers bound memory by passing pixels in chunks.
"""
from __future__ import annotations

import numpy as np

from ..cuda import get_kernel, get_module, register
from ..imaging._xp import Workspace, get_xp, to_numpy

__all__ = ["FDMTPlan", "fdmt", "effective_back", "StreamingFDMT", "HalfRows"]


class FDMTPlan:
    """The merge tables for channels at ``freq`` (any order; any unit) and sweeps ``0 .. dmax`` images
    across the band (every integer; the trials are rows of the result).

    ``order`` sorts the channels by frequency (ascending); ``levels`` is a list, bottom-up, of merges
    ``(range, (lo_range, hi_range, row_L (n,), row_U (n,), o (n,)))`` per range of that level, each
    range a pair of channel indices (first, last) in sorted order, ``row_*`` the rows of the halves'
    arrays that hold the sweeps d_L and d_U (made here, once, not on every transform).
    """

    def __init__(self, freq, dmax):
        f = np.asarray(freq, dtype=np.float64).ravel()
        if f.size == 0 or not np.all(f > 0):
            raise ValueError(f"freq: expected positive channel frequencies, got {freq!r}")
        if int(dmax) != dmax or dmax < 0:
            raise ValueError(f"dmax: expected the largest sweep in whole images (>= 0), got {dmax!r}")
        self.order = np.argsort(f, kind="stable")
        self.f = f[self.order]
        self.nchan, self.dmax = f.size, int(dmax)
        self.k = self.f ** -2.0                                   # delay ~ k; k decreases with f
        # top-down: which sweeps each range must provide
        need = {(0, self.nchan - 1): np.arange(self.dmax + 1)}
        merges = {}                                               # range -> (L, U, dL, dU, o)
        stack = [(0, self.nchan - 1)]
        while stack:
            a, b = stack.pop()
            d = need[(a, b)]
            if a == b:
                continue
            m = (a + b + 1) // 2
            span = self.k[a] - self.k[b]
            if span <= 0:                                         # equal frequencies: no sweep inside
                dL, o = np.zeros_like(d), np.zeros_like(d)
            else:
                dL = np.rint(d * (self.k[a] - self.k[m - 1]) / span).astype(np.int64)
                o = np.rint(d * (self.k[a] - self.k[m]) / span).astype(np.int64)
            dU = d - o
            L, U = (a, m - 1), (m, b)
            merges[(a, b)] = (L, U, dL, dU, o)
            for rng, dd in ((L, dL), (U, dU)):
                if rng[0] == rng[1]:
                    dd = np.zeros(1, np.int64)
                need[rng] = np.union1d(need.get(rng, np.zeros(0, np.int64)), dd)
                stack.append(rng)
        self.need = need
        # group merges by level (depth from the leaves), bottom-up
        def depth(r):
            return 0 if r[0] == r[1] else 1 + max(depth(merges[r][0]), depth(merges[r][1]))
        by = {}
        for r in merges:
            by.setdefault(depth(r), []).append(r)

        def sweeps(r):
            return np.zeros(1, np.int64) if r[0] == r[1] else need[r]

        def rows(r):
            L, U, dL, dU, o = merges[r]
            return L, U, np.searchsorted(sweeps(L), dL), np.searchsorted(sweeps(U), dU), o
        self.levels = [[(r, rows(r)) for r in sorted(by[k])] for k in sorted(by)]

    def rows(self):
        """Shifted-add rows the transform does (its cost in units of one T x npix add)."""
        return int(sum(len(m[1][2]) for lvl in self.levels for m in lvl))


def fdmt(images, plan: FDMTPlan):
    """Dedispersed series for every sweep 0 .. plan.dmax: ``images`` (nchan, T, npix) -> (dmax + 1, T,
    npix), same dtype and array namespace; row d, time t is ``sum_c I_c(t - back(d, c))``
    (:func:`effective_back`), complete for t >= plan.dmax (earlier times lack the higher channels'
    past: those terms count as 0)."""
    xp = get_xp(images)
    x = xp.asarray(images)
    if x.ndim != 3 or x.shape[0] != plan.nchan:
        raise ValueError(f"images: expected (nchan={plan.nchan}, T, npix), got shape {tuple(x.shape)}")
    T = x.shape[1]
    if not np.array_equal(plan.order, np.arange(plan.nchan)):
        x = x[xp.asarray(plan.order)]
    # state: range -> (array (n sweeps it holds, T, npix)); leaves hold sweep 0; the sweeps of a range
    # are plan.need[range], sorted
    state = {(c, c): x[c][None] for c in range(plan.nchan)}
    t = np.arange(T)
    for level in plan.levels:
        for rng, (L, U, rowL, rowU, o) in level:
            aL, aU = state.pop(L), state.pop(U)
            # A_U read o images back, zero before its first time: one gather from a zero-padded copy
            oc = np.minimum(o, T)
            pad = int(oc.max()) if oc.size else 0
            if pad:
                aU = xp.concatenate([xp.zeros((aU.shape[0], pad) + aU.shape[2:], aU.dtype), aU], axis=1)
            tix = xp.asarray(t[None, :] - oc[:, None] + pad)                     # (n, T)
            state[rng] = aL[xp.asarray(rowL)] + aU[xp.asarray(rowU)[:, None], tix]
    return state[(0, plan.nchan - 1)]


def effective_back(plan: FDMTPlan):
    """(dmax + 1, nchan) int64: how many images before t each channel (in the caller's order) is read
    for trial d -- what :func:`fdmt` sums, from the same merge tables."""
    back = {(c, c): np.zeros((1, 1), np.int64) for c in range(plan.nchan)}       # (n sweeps, channels)
    for level in plan.levels:
        for rng, (L, U, rowL, rowU, o) in level:
            bL = back.pop(L)[rowL]
            bU = back.pop(U)[rowU] + o[:, None]
            back[rng] = np.concatenate([bL, bU], axis=1)
    top = back[(0, plan.nchan - 1)]
    out = np.empty_like(top)
    out[:, plan.order] = top
    return out


class StreamingFDMT:
    """:func:`fdmt` on a stream: images arrive a block at a time, each call returns the block's
    dedispersed values, equal to :func:`fdmt` of the whole series so far at those times.

    plan : :class:`FDMTPlan`;  npix : pixels per image;  xp : numpy or cupy;  pixel_chunk : pixels
    per pass (the working memory is ``(nchan + plan.rows()) x B x pixel_chunk`` values; default:
    as many as fit in ``WORK_BYTES`` for the block being pushed);  allocate : False makes the tables
    and sizes only (:meth:`memory_bytes`), no ring.
    block : the most images a push is made in (default 64; longer pushes are split, on the host too, so
    that both make a float16 scale's choices at the same points): the GPU's rings hold a block's values.
    precision : 'fp32' (default) or 'fp16': the values the tree stores (its rows and rings) -- each
    add is done in float32 and rounded to float16: half the tree's memory traffic (the tree is bound
    by it) and half its rings. What is stored is each value less its channel and pixel's value in
    the first image after a reset (``ref``; added back, summed over the channels, in float32 as the
    rows are copied out), so float16's 11 bits carry the fluctuations, not the sky's mean: a sum's
    error after its ~log2(nchan) roundings is ~3e-4 of the fluctuations' size rms, far below their
    noise (rounding whole values instead would err by ~3e-4 of the value: at a bright burst's peak a
    sizeable fraction of a sigma of the whole band's noise, enough to move its best trial). The
    reference holds until a reset, so a sky that drifts by D since then is rounded at ~3e-4 D: below
    the noise while D is under ~1,000 noise sigmas of a value -- for images of a few samples, whose sigma
    is a sizeable fraction of the sky, any drift; for long integrations a pixel's whole brightness. The past
    before the first push counts as equal to ``ref`` (float32: as 0), so the first ``dmax`` images'
    values, which lack part of the band's past, differ accordingly (a search does not use them).
    Values are scaled by a power of two so that a whole-band sum of the largest fluctuation pushed
    sits near ``FP16_HEAD`` (float16 overflows at 65,504); a later push whose sums could pass
    ``FP16_LIMIT`` (a flash) rescales the rings first (exact: powers of two), counted in
    ``rescales``. The output is float32 in the input's units either way.

    State: in each merge the upper half's rows are read up to ``o`` images back, so every row any
    merge reads that way keeps its last ``max o`` values in a ring (float32 ``(sum max o, npix)``:
    fixed by the plan, whatever the run's length; on a GPU the merged rows live in their rings, with ``block`` more
    slots each, see the constructor). Rows are numbered leaves first (the channels in frequency
    order), then each merge's output rows, level by level; a level is one gather-add over all its
    rows (one CUDA kernel on the GPU; the same array code on the CPU).
    """

    #: working memory of one pass when ``pixel_chunk`` is not given (bytes): room for a whole band's
    #: all-sky grid in one pass of a 64-image push, so that the search reads the tree's rows where they are
    #: (:class:`HalfRows`); fewer, larger passes also launch fewer kernels
    WORK_BYTES = 6 << 30
    #: float16 storage: a whole-band sum of the largest value is scaled to about this ...
    FP16_HEAD = 2.0 ** 8
    #: ... and the rings are rescaled before a push whose sums could pass this (float16's largest: 65,504)
    FP16_LIMIT = 2.0 ** 14
    #: float16 values a GPU thread of the levels moves at once (2, 4 or 8: a 4-, 8- or 16-byte load)
    HALF_VEC = 8

    def __init__(self, plan: FDMTPlan, npix, xp=np, pixel_chunk=None, allocate=True, precision="fp32", block=64):
        if precision not in ("fp32", "fp16"):
            raise ValueError(f"precision: the tree stores 'fp32' or 'fp16' values, got {precision!r}")
        self.plan, self.npix, self.xp, self.precision = plan, int(npix), xp, precision
        self.dtype = np.float16 if precision == "fp16" else np.float32
        # a push's working rows (its largest array): two buffers that take turns, since a search reads a
        # push's rows (staged, ``defer``) while the next push makes its own
        self._work = Workspace(depth=2)
        # float16 rows are read HALF_VEC pixels at a time (one 16-byte load per thread): rows (and pixel
        # chunks) a whole number of those long
        self.pad = self.HALF_VEC if precision == "fp16" else 1
        self.ld = -(-self.npix // self.pad) * self.pad
        base, nrow = {}, plan.nchan
        for level in plan.levels:
            for rng, (L, U, rowL, rowU, o) in level:
                base[rng] = nrow
                nrow += len(rowL)
        self.nrow = nrow

        def gid(rng, j):
            return (rng[0] + np.zeros_like(j)) if rng[0] == rng[1] else base[rng] + j
        self._levels = []
        ring_len = np.zeros(nrow, np.int64)
        for level in plan.levels:
            out, inL, inU, off = [], [], [], []
            for rng, (L, U, rowL, rowU, o) in level:
                out.append(base[rng] + np.arange(len(rowL)))
                inL.append(gid(L, rowL))
                u = gid(U, rowU)
                inU.append(u)
                off.append(o)
                np.maximum.at(ring_len, u, o)
            self._levels.append(tuple(np.concatenate(a).astype(np.int64) for a in (out, inL, inU, off)))
        self.ring_rows = np.flatnonzero(ring_len > 0)
        self.ring_len = ring_len
        self.ring_base = np.full(nrow, -1, np.int64)
        self.ring_base[self.ring_rows] = np.concatenate([[0], np.cumsum(ring_len[self.ring_rows])[:-1]]) \
            if self.ring_rows.size else np.zeros(0, np.int64)
        self.ring_size = int(ring_len.sum())
        # On a GPU the merged rows that keep a ring live only in it, with room for a block's values
        # too (``ring_len + block`` slots, time tau at slot tau mod that): the level that makes such a row
        # writes it there and the levels that read it read it there, so no pass copies a block's newest
        # values into the rings afterwards (every merged row's block read and written again a gulp). The
        # working array loses those rows, so at a push of ``block`` images in one pass the memory is the
        # same. The channels' own rows (the leaves) stay in the working array, their few ring values copied
        # after the levels. Pushes longer than ``block`` are made ``block`` at a time.
        self.block = int(block)
        if self.block < 1:
            raise ValueError(f"block: expected the most images a push holds (>= 1), got {block!r}")
        inplace = ring_len > 0
        inplace[:plan.nchan] = False
        self._inplace = inplace
        self.wrow = np.where(inplace, -1, np.cumsum(~inplace) - 1).astype(np.int64)   # row -> working row
        self.nwrow = int((~inplace).sum())
        self.ring_cap = np.where(inplace, ring_len + self.block, ring_len)            # GPU ring slots a row
        self.dev_ring_size = int(self.ring_cap.sum())
        top = (0, plan.nchan - 1)
        t0 = base[top] if plan.nchan > 1 else 0
        self.top = slice(t0, t0 + plan.dmax + 1)          # the whole band's rows: one contiguous run
        self.pixel_chunk = int(pixel_chunk) if pixel_chunk else None
        # the channels' frequency order, where the input's is not already it (applied to every push)
        self._order = None if np.array_equal(plan.order, np.arange(plan.nchan)) else xp.asarray(plan.order)
        self._dev = None
        if xp is not np:
            self._dev = {k: [xp.asarray(a.astype(np.int32)) for a in lv] for k, lv in enumerate(self._levels)}
            cap = self.ring_cap
            dbase = np.full(nrow, -1, np.int64)
            dbase[cap > 0] = np.concatenate([[0], np.cumsum(cap[cap > 0])[:-1]])
            copied = self.ring_rows[~inplace[self.ring_rows]]          # the leaves' rings: copied after the levels
            self._dev_ring = (xp.asarray(dbase), xp.asarray(cap.astype(np.int32)), xp.asarray(copied.astype(np.int32)),
                              xp.asarray(self.wrow.astype(np.int32)))
        if allocate:                                    # (False: sizes only, e.g. for a plan)
            self.reset()

    def reset(self):
        """Forget the past (its values count as 0, as :func:`fdmt`'s before its first time; float16: as
        the next push's first image)."""
        # the ring cleared where it is (a reset at each gain solution makes no allocation); one of another
        # shape let go first, so that the new one takes its memory: never both at once
        shape = (self.ring_size if self.xp is np else self.dev_ring_size, self.ld)
        if getattr(self, "ring", None) is not None and self.ring.shape == shape:
            self.ring.fill(0)       # in place: a reset (each gain solution) makes no allocation
        else:
            self.ring = None
            self.ring = self.xp.zeros(shape, self.dtype)
        self.ntime = 0
        self._phase_at = -1
        self.scale = None           # float16: the values' scale (a power of two), set by the first push
        self.ref = None             # float16: (nchan, npix) float32, each channel's first image since the reset
        self._ref_sum = None        # (npix,) float32: ref summed over the channels (in float64, on the host)
        self.rescales = 0

    def _set_ref_and_scale(self, x, index=None):
        """float16: the reference (the first push's first image) and the scale (a power of two) under
        which no sum of this push or of the past can overflow; returns the scale. ``index``: as
        :meth:`push` (GPU only)."""
        xp = self.xp
        if self.ref is None:
            # a copy: x may be a view of the caller's (reused) buffer
            self.ref = x[:, 0].copy() if index is None else xp.take(x[:, 0], index, axis=-1)
            self._ref_sum = xp.asarray(to_numpy(self.ref).astype(np.float64).sum(axis=0).astype(np.float32))
        if xp is np:
            amax = float(np.max(np.abs(x - self.ref[:, None])))
        else:
            # one kernel, each warp's maximum into one word (a whole-array ReductionKernel runs as one
            # block, and one per (channel, image) row on the strided view is slow too)
            amax = _abs_dev_max_gpu(xp, x, self.ref, index)
        return self._scale_for(amax)

    def _scale_for(self, amax):
        """The scale for a push whose largest |value - ref| is ``amax`` (the past rescaled if a brighter
        push needs it; a ValueError if it is not finite)."""
        xp = self.xp
        if not np.isfinite(amax):
            raise ValueError("images: non-finite values reached the tree (NaN or Inf)")
        bound = amax * self.plan.nchan                 # no sum of nchan values can exceed it
        if self.scale is not None and bound * self.scale <= self.FP16_LIMIT:
            return self.scale
        new = 2.0 ** np.floor(np.log2(self.FP16_HEAD / bound)) if bound > 0 else 1.0
        if self.scale is not None:
            # a brighter push (past FP16_LIMIT, so new <= scale / 64): the past rescaled to match
            f = np.float32(new / self.scale)
            if xp is np:
                self.ring[...] = (self.ring.astype(np.float32) * f).astype(np.float16)
            else:
                xp.multiply(self.ring, f, out=self.ring, casting="unsafe")
            self.rescales += 1
        self.scale = new
        return new

    def _gpu(self, gpu):
        return self.xp is not np if gpu is None else bool(gpu)

    def _chunk(self, B, gpu=None):
        """Pixels per pass for a block of ``B`` images: ``pixel_chunk``, or as many as ``WORK_BYTES``
        holds, evened out over the passes and rounded up to a warp's 32 (a 321-pixel chunk would run its
        second 256-thread block a quarter full). gpu: the GPU's layout (default: where the tree is)."""
        if self.pixel_chunk:                        # (float16: a whole number of HALF_VEC pixels)
            return min(self.npix, -(-self.pixel_chunk // self.pad) * self.pad)
        rows = self.nwrow if self._gpu(gpu) else self.nrow
        most = max(1, self.WORK_BYTES // (np.dtype(self.dtype).itemsize * rows * min(B, self.block)))
        npass = -(-self.npix // most)
        per = -(-self.npix // npass)
        return min(self.npix, -(-per // 32) * 32)

    def ring_bytes(self, gpu=None):
        """Device bytes of the rings (on a GPU with the merged rows' ``block`` slots: see the constructor)."""
        return np.dtype(self.dtype).itemsize * (self.dev_ring_size if self._gpu(gpu) else self.ring_size) * self.ld

    def memory_bytes(self, B, gpu=None):
        """Device bytes: the rings, and the working array of a push of ``B`` images (made ``block`` at a
        time, on the host too); gpu: the GPU's layout (default: where the tree is)."""
        g = self._gpu(gpu)
        b = min(B, self.block)
        pc = self._chunk(B, gpu=g)
        pc = -(-pc // self.pad) * self.pad                        # (float16 rows: HALF_VEC pixels a load)
        return self.ring_bytes(g) + np.dtype(self.dtype).itemsize * (self.nwrow if g else self.nrow) * b * pc

    def push(self, images, factor=1.0, index=None, rows=False):
        """(nchan, B, npix) new images (channels in the plan's order of ``freq``) -> (dmax + 1, B, npix)
        float32: row d, time t is the sum over channels of I_c(t - back(d, c)) (:func:`effective_back`),
        times ``factor`` (e.g. 1 / nchan for the channels' mean: applied as the rows are copied out).

        index : None, or (npix,) the cell of each pixel: ``images`` are then (nchan, B, ncell) (an
            imager's grid, a view whose last axis is contiguous) and pixel p is cell ``index[p]``. The
            float16 tree on a GPU reads the cells where they are (its scale's maximum and its input
            pass gather them: no gathered copy of the images);
            elsewhere they are gathered first.
        rows : the float16 tree on a GPU whose pixels fit one pass returns a :class:`HalfRows` (the
            rows where the tree left them) instead of the float32 array; otherwise the array."""
        xp, plan = self.xp, self.plan
        x = xp.asarray(images, dtype=xp.float32)
        half = self.dtype is np.float16
        if index is not None:
            index = xp.asarray(index, dtype=xp.int32)
            if index.ndim != 1 or index.shape[0] != self.npix:
                raise ValueError(f"index: expected the cell of each of {self.npix} pixels, got shape {tuple(index.shape)}")
            if x.ndim != 3 or x.shape[0] != plan.nchan:
                raise ValueError(f"images: expected (nchan={plan.nchan}, B, ncell), got {tuple(x.shape)}")
            if xp is np or not half or x.strides[-1] != 4:
                x, index = xp.take(x, index, axis=-1), None
        if x.ndim != 3 or x.shape[0] != plan.nchan or (index is None and x.shape[2] != self.npix):
            raise ValueError(f"images: expected (nchan={plan.nchan}, B, npix={self.npix}), got {tuple(x.shape)}")
        B = int(x.shape[1])
        if B == 0:
            return xp.empty((plan.dmax + 1, 0, self.npix), xp.float32)
        if B > self.block:
            # the GPU's rings hold a block's values (see the constructor); the host splits its pushes the
            # same way so that a float16 tree's scale (set a push at a time) is the same on both
            return xp.concatenate([self.push(x[:, a:a + self.block], factor, index)
                                   for a in range(0, B, self.block)], axis=1)
        out = None
        if self._order is not None:
            x = x[self._order]
        pc = self._chunk(B)
        # on the GPU, one pass and a scale already set: the scale's maximum taken in the input pass itself
        # (one read of the images, not two), checked before any
        # level runs, and the pass made again at a new scale in the rare push that needs one (a flash)
        one_pass = half and xp is not np and pc >= self.npix and self.scale is not None
        scale = (self.scale if one_pass else self._set_ref_and_scale(x, index)) if half else 1.0
        rows = rows and half and xp is not np and pc >= self.npix
        top = self.top if xp is np else slice(int(self.wrow[self.top.start]), int(self.wrow[self.top.start]) + plan.dmax + 1)
        for p0 in range(0, self.npix, pc):
            p1 = min(self.npix, p0 + pc)
            n = p1 - p0
            # the working rows: one array kept for every push (its lease rides in a HalfRows that still reads it)
            W, lease = self._work.take(xp, (self.nrow if xp is np else self.nwrow, B, -(-n // self.pad) * self.pad),
                                       self.dtype)
            if not half:
                W[:plan.nchan] = x[:, :, p0:p1]
            elif xp is np:
                W[:plan.nchan, :, :n] = (x[:, :, p0:p1] - self.ref[:, None, p0:p1]) * np.float32(scale)
            elif one_pass:
                amax = xp.zeros(1, xp.uint32)
                _in_half_gpu(xp, x, self.ref, np.float32(scale), W, p0, n, index, amax)
                new = self._scale_for(float(amax.get().view(np.float32)[0]))
                if new != scale:                          # (the rings were rescaled to it)
                    scale = new
                    _in_half_gpu(xp, x, self.ref, np.float32(scale), W, p0, n, index)
            else:                                         # (the row's spare pixels written 0)
                _in_half_gpu(xp, x, self.ref, np.float32(scale), W, p0, n, index)
            if xp is np and W.shape[2] > n:
                W[:plan.nchan, :, n:] = 0                 # the row's spare pixels
            if xp is np:
                self._levels_host(W, p0, p1, B)
            else:
                self._levels_gpu(W, p0, p1, B)
            if rows:                                      # one pass: the rows stay where they are
                self.ntime += B
                return HalfRows(W, top.start, plan.dmax + 1, self._ref_sum, factor / scale, factor, self.npix,
                                lease=lease)
            if out is None:
                out = xp.empty((plan.dmax + 1, B, self.npix), xp.float32)
            # a slice: copied (and scaled) once, not gathered first
            if not half:
                xp.multiply(W[top], np.float32(factor), out=out[:, :, p0:p1])
            else:
                a, b = np.float32(factor / scale), np.float32(factor)
                if xp is np:
                    out[:, :, p0:p1] = W[top, :, :n].astype(np.float32) * a + self._ref_sum[p0:p1] * b
                else:
                    _out_half_gpu(xp, W, top.start, plan.dmax + 1, self._ref_sum, a, b, out, p0, n)
        self.ntime += B
        return out

    def _levels_host(self, W, p0, p1, B):
        t = np.arange(B)
        for out, inL, inU, o in self._levels:
            s = t[None, :] - o[:, None]                                   # (n, B) source time in the block
            b = W[inU[:, None], np.maximum(s, 0)]                          # (n, B, pc)
            old = s < 0
            if old.any():
                r, tt = np.nonzero(old)
                u = inU[r]
                at = (self.ntime + s[r, tt]) % self.ring_len[u]
                b[r, tt] = self.ring[self.ring_base[u] + at, p0:p0 + W.shape[2]]
            W[out] = W[inL] + b
        for g in self.ring_rows:                                           # keep each ring row's last values
            L = int(self.ring_len[g])
            t0 = max(0, B - L)
            self.ring[self.ring_base[g] + (self.ntime + np.arange(t0, B)) % L, p0:p0 + W.shape[2]] = W[g, t0:]

    def _levels_gpu(self, W, p0, p1, B):
        # float16: a thread per HALF_VEC pixels (one load); rows and rings a whole number of them long
        per = self.pad
        pc, ld, q0 = W.shape[2] // per, self.ld // per, p0 // per
        # (64, 128 or 256 threads a block run at the same speed)
        bx = min(128, pc)
        grid_x = -(-pc // bx)
        k_level, k_ring = _gpu_kernels(self.precision, self.pad)
        rbase, rcap, rrows, wrow = self._dev_ring
        if self._phase_at != self.ntime:
            # each ring row's slot of time ntime, once per push: the kernels index the rings in 32-bit
            # arithmetic
            self._phase = self.xp.asarray((self.ntime % np.maximum(self.ring_cap, 1)).astype(np.int32))
            self._phase_at = self.ntime
        Y = 65535                                                  # CUDA's largest grid y: rows in slices
        for k in range(len(self._levels)):
            out, inL, inU, o = self._dev[k]
            for j in range(0, int(out.shape[0]), Y):
                k_level((grid_x, min(Y, int(out.shape[0]) - j)), (bx,),
                        (W, self.ring, out[j:], inL[j:], inU[j:], o[j:], rbase, rcap, self._phase, wrow, np.int32(B),
                         np.int32(pc), np.int32(ld), np.int32(q0)))
        for j in range(0, int(rrows.shape[0]), Y):
            k_ring((grid_x, min(Y, int(rrows.shape[0]) - j)), (bx,),
                   (W, self.ring, rrows[j:], rbase, rcap, self._phase, wrow, np.int32(B), np.int32(pc), np.int32(ld),
                    np.int32(q0)))


#: the tree's kernels as a shipped path compiles them: float32, and float16 HALF_VEC pixels a load
register("search/tree.cu", ({}, None), ({"HALF": StreamingFDMT.HALF_VEC}, None))
register("search/abs_dev.cu")
register("search/tree_half.cu")


def _gpu_kernels(precision="fp32", vec=2):
    """(bf_fdmt_level, bf_fdmt_ring) of tree.cu for the tree's ``precision`` (float16: ``vec`` pixels a load)."""
    mod = get_module("search/tree.cu", defines={"HALF": int(vec)} if precision == "fp16" else None)
    return mod.get_function("bf_fdmt_level"), mod.get_function("bf_fdmt_ring")


def _abs_dev_max_gpu(cp, x, ref, index=None):
    """max |x - ref| (host float) of x (nchan, B, npix) float32, a view whose last axis is contiguous,
    and ref (nchan, npix): one kernel and one 4-byte copy to the host. index: None, or (npix,) int32,
    x is then (nchan, B, ncell) and pixel p its cell index[p]."""
    nchan, B = (int(v) for v in x.shape[:2])
    npix = int(ref.shape[-1])
    if x.strides[-1] != 4:
        x = cp.ascontiguousarray(x)
    out = cp.zeros(1, cp.uint32)
    sc, sb = (int(v) // 4 for v in x.strides[:2])
    k = get_kernel("search/abs_dev.cu", "bf_abs_dev_max")
    k(((npix + 255) // 256, min(nchan * B, 512)), (256,),
      (x, cp.ascontiguousarray(ref, dtype=cp.float32), out, np.int32(nchan), np.int32(B), np.int32(npix),
       np.int64(sc), np.int64(sb), np.uint64(0) if index is None else index))
    return float(out.get().view(np.float32)[0])


def _half_kernel(cp, name):
    """``name`` of tree_half.cu (bf_fdmt_in_half or bf_fdmt_out_half)."""
    return get_kernel("search/tree_half.cu", name)


def _in_half_gpu(cp, x, ref, scale, W, p0, n, index=None, amax=None):
    """W[:nchan, :, :] = float16((x[:, :, p0:p0 + n] - ref[:, p0:p0 + n]) * scale), the spare pixel 0.
    x: (nchan, B, npix) float32 whose last axis is contiguous; ref (nchan, npix); W (nrow, B, ld) float16;
    index: as :func:`_abs_dev_max_gpu`; amax: None, or a uint32 device word (zero) that receives the
    float bits of max |x - ref| over the pixels read, as :func:`_abs_dev_max_gpu` returns it. (A kernel
    of its own: CuPy's elementwise kernels are slow on these strided views.)"""
    nchan, B = (int(v) for v in x.shape[:2])
    npix = int(ref.shape[-1])
    if x.strides[-1] != 4:
        x = cp.ascontiguousarray(x)
    ld2 = int(W.shape[2]) // 2
    sc, sb = (int(v) // 4 for v in x.strides[:2])
    _half_kernel(cp, "bf_fdmt_in_half")(
        ((ld2 + 127) // 128, min(nchan * B, 512)), (128,),
        (x, cp.ascontiguousarray(ref, dtype=cp.float32), np.float32(scale), W, np.int32(nchan), np.int32(B),
         np.int32(n), np.int32(ld2), np.int64(sc), np.int64(sb), np.int32(p0), np.int32(npix),
         np.uint64(0) if index is None else index, np.uint64(0) if amax is None else amax))


class HalfRows:
    """The whole band's rows of a float16 tree push, where the tree left them (GPU): row d, time t,
    pixel p is ``W[top + d, t, p] * a + ksum[p] * b`` in float32 (rounded as :func:`_out_half_gpu`),
    for times ``first ..`` of the push. A consumer that reads them so (the search's statistics kernel)
    saves writing and reading them back as float32 (twice the float16 rows' bytes). ``shape`` is the
    float32 array's, (D, B - first, npix); :meth:`array` makes it."""

    def __init__(self, W, top, D, ksum, a, b, npix, first=0, lease=None):
        self.W, self.top, self.D, self.ksum, self.a, self.b = W, int(top), int(D), ksum, float(a), float(b)
        self.npix, self.first = int(npix), int(first)
        self.lease = lease          # the tree's Workspace lease: W is not used again while this is alive
        self.shape = (self.D, int(W.shape[1]) - self.first, self.npix)

    def from_time(self, first):
        """The same rows from time ``first`` of the push on."""
        return HalfRows(self.W, self.top, self.D, self.ksum, self.a, self.b, self.npix, self.first + int(first),
                        lease=self.lease)

    def array(self):
        """The float32 rows (D, B - first, npix), as :meth:`StreamingFDMT.push` returns them."""
        cp = get_xp(self.W)
        B = int(self.W.shape[1])
        out = cp.empty((self.D, B, self.npix), cp.float32)
        _out_half_gpu(cp, self.W, self.top, self.D, self.ksum, self.a, self.b, out, 0, self.npix)
        return out[:, self.first:]


def _out_half_gpu(cp, W, t0, D, ksum, a, b, out, p0, n):
    """out[:, :, p0:p0 + n] = W[t0:t0 + D, :, :n] * a + ksum[p0:p0 + n] * b (float32 rows out of float16
    storage). W (nrow, B, ld) float16; out (D, B, npix) float32 contiguous."""
    B, npix = int(out.shape[1]), int(out.shape[2])
    ld2 = int(W.shape[2]) // 2
    rows = D * B
    _half_kernel(cp, "bf_fdmt_out_half")(
        ((ld2 + 127) // 128, min(rows, 512)), (128,),
        (W, ksum, np.float32(a), np.float32(b), out, np.int32(rows), np.int64(t0 * B), np.int32(n), np.int32(ld2),
         np.int32(p0), np.int32(npix)))
