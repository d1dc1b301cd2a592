"""Streaming transient search on image time series: dedispersion, sliding statistics, boxcars.

One code path for NumPy and CuPy (the arrays' namespace does the work, where they live), with two
CUDA kernels where the array code's passes cost too much on the GPU: the tree dedispersion's
(:mod:`.tree`) and the statistics' (``statistics.cu``: the ring, the running sums and every
boxcar's S/N in one pass per series and pixel, checked against the array code on the GPU).

Definitions (all times in images; ``dt`` = seconds per image)
-------------------------------------------------------------
* Dispersion: a burst of dispersion measure DM (pc cm^-3) reaches frequency f later than the
  reference frequency f_ref (the band's HIGHEST channel) by
  ``delay(f) = 4.149 ms * DM * ((f/GHz)^-2 - (f_ref/GHz)^-2)``, rounded to whole images per channel
  (:func:`.dispersion.dm_delays`).
* Incoherent dedispersion, causal: the series of trial d at image j is
  ``D_d(j) = mean_c I_c(j - (delay_max_d - delay_d,c))``, i.e. every channel is aligned on the
  lowest channel's arrival; the event time at f_ref is ``j - delay_max_d``. With
  ``average_channels=False`` every channel is its own series (no dedispersion; DM trials must be [0]).
* Statistics: for the series value at j, mean and variance per pixel over the W values
  ``D(j - wmax - W + 1) ... D(j - wmax)`` (W = window, wmax = the widest boxcar), so a burst never
  sits in its own statistics; sums are kept in float64 about a per-pixel offset (the first value
  after a reset), which avoids the cancellation of sum(x^2) - sum(x)^2 / W.
* Boxcar S/N of width w ending at j: ``(mean(D(j-w+1..j)) - mu) * sqrt(w) / sigma`` -- the S/N of
  the w-image mean if images are independent (they are for receiver- and sky-noise-limited images:
  each image is made from its own samples).
* Search starts once W + wmax dedispersed values exist since the last reset (a new sequence or a
  lost stretch of images): no S/N is ever formed from a partly filled window.
"""
from __future__ import annotations

import functools
import math
import time

import numpy as np

from ..conventions import dispersion_delay_s
from ..cuda import get_kernel, register
from ..imaging._xp import to_numpy
from .clustering import Crossings
from .dispersion import dm_delays
from .tree import FDMTPlan, HalfRows, StreamingFDMT, effective_back

__all__ = ["TREE_CHANNELS", "TransientSearch"]

#: ``dedisperse="auto"`` uses the tree (:mod:`.tree`) from this many channels up: shifted sums cost
#: trials x channels adds per pixel-image, the tree ~trials x log2(channels)
TREE_CHANNELS = 64

#: trials either side of a found one that :meth:`TransientSearch.refine_dm` looks at first, and the starts
#: either side of the event's (plus one per trial away) that :meth:`TransientSearch.snr_by_series` tries
REFINE_SPAN, REFINE_SLACK = 16, 2


class TransientSearch:
    """Streaming per-pixel search state (arrays in ``xp``: numpy or cupy).

    Parameters
    ----------
    freq_hz : (nchan,) channel centres, Hz; dt_s : seconds per image.
    npix : pixels per image (the caller flattens and drops pixels that are never imaged).
    window : W, images in the sliding statistics window (>= 3).
    dms : trial DMs (pc cm^-3); widths : boxcar widths in images (positive integers).
    threshold : S/N above which a trial is a crossing.
    average_channels : True (dedisperse and average the channels) or False (search each channel).
    xp : numpy or cupy; max_batch : images processed per internal step (bounds memory).
    dedisperse : 'shifts' (each DM trial a sum of shifted channels: ``dms`` as given), 'tree' (the
        streaming FDMT of :mod:`.tree`: every sweep from 0 to the largest DM's, one image apart, each
        channel within 1-2 images of the dispersion curve; ``dms`` becomes the DM of each sweep,
        ``sweep / (delay per unit DM across the band)``), or 'auto' (the tree from
        ``TREE_CHANNELS`` channels). pixel_chunk : pixels per pass of the tree (its working memory).
    tree_precision : 'fp32' or 'fp16', the values the tree stores (:class:`~.tree.StreamingFDMT`:
        float16 halves its memory traffic and rings, rounding fluctuations about a reference; the S/N and
        every later step stay float32/float64).
    max_pixels : at most this many crossings (the brightest) are kept per trial image (series, value,
        width), so a bright event costs what a faint one does (default 32).
    hold : values kept beyond what the search itself needs (window + widest boxcar + a batch), so
        that :meth:`window_statistics` and :meth:`box_image` can still look back at an event that
        far behind the newest value (default 0).
    sky_fraction : a trial image with more than this fraction of its pixels over the threshold is one
        sky-wide crossing at its peak pixel (lightning, RFI, a flash), not a crossing per pixel (0.1).

    :meth:`push` takes images ``(nimage, nchan, npix)`` (float, finite) and returns
    :class:`Crossings`; :meth:`reset` forgets the history (call at a gap or a new sequence, with the
    sequence index of the next image to be pushed).
    """

    def __init__(self, freq_hz, dt_s, npix, window, dms=(0.0,), widths=(1, 2, 4, 8), threshold=6.0,
                 average_channels=True, xp=np, max_batch=256, max_pixels=32, sky_fraction=0.1, hold=0,
                 dedisperse="shifts", pixel_chunk=None, allocate=True, tree_precision="fp32"):
        self.freq_hz = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        if self.freq_hz.ndim != 1 or not np.all(self.freq_hz > 0):
            raise ValueError(f"freq_hz: expected a 1-D array of positive frequencies, got {freq_hz!r}")
        if not (dt_s > 0):
            raise ValueError(f"dt_s: expected seconds per image > 0, got {dt_s!r}")
        if int(window) != window or window < 3:
            raise ValueError(f"window: expected an integer number of images >= 3, got {window!r}")
        widths = [int(w) for w in np.atleast_1d(widths)]
        if not widths or any(w < 1 for w in widths) or len(set(widths)) != len(widths):
            raise ValueError(f"widths: expected distinct positive integers (images), got {widths!r}")
        dms = [float(d) for d in np.atleast_1d(dms)]
        if not dms or any(not np.isfinite(d) or d < 0 for d in dms):
            raise ValueError(f"dms: expected finite DMs >= 0 (pc cm^-3), got {dms!r}")
        if not average_channels and dms != [0.0]:
            raise ValueError("dms: without channel averaging every channel is searched on its own, so the "
                             f"only DM trial is 0; got {dms!r} (set average_channels=True to dedisperse)")
        self.nchan, self.npix = self.freq_hz.size, int(npix)
        self.dt_s, self.window, self.widths, self.dms = float(dt_s), int(window), widths, dms
        self.threshold, self.average = float(threshold), bool(average_channels)
        self.xp, self.max_batch = xp, int(max_batch)
        if int(max_pixels) != max_pixels or max_pixels < 1:
            raise ValueError(f"max_pixels: expected an integer >= 1, got {max_pixels!r}")
        if not 0 < sky_fraction <= 1:
            raise ValueError(f"sky_fraction: expected a fraction in (0, 1], got {sky_fraction!r}")
        self.max_pixels, self.sky_fraction = int(max_pixels), float(sky_fraction)
        if dedisperse == "auto":
            dedisperse = "tree" if self.average and self.nchan >= TREE_CHANNELS else "shifts"
        if tree_precision not in ("fp32", "fp16"):
            raise ValueError(f"tree_precision: expected 'fp32' or 'fp16', got {tree_precision!r}")
        if dedisperse not in ("shifts", "tree"):
            raise ValueError(f"dedisperse: expected 'shifts', 'tree' or 'auto', got {dedisperse!r}")
        if dedisperse == "tree" and not self.average:
            raise ValueError("dedisperse: 'tree' dedisperses the channels' average; with average_channels=False "
                             "use 'shifts'")
        self.dedisperse = dedisperse
        self._tree = None
        if dedisperse == "tree":
            # every sweep from 0 to the largest DM's, one image apart: row s is read s images back at
            # the highest channel and 0 at the lowest (tree.py), the DM of a sweep from the band's edges
            per_dm = float(dispersion_delay_s(1.0, self.freq_hz.min(), self.freq_hz.max())) / self.dt_s
            smax = int(np.rint(max(dms) * per_dm))
            plan = FDMTPlan(self.freq_hz, smax)
            self._tree = StreamingFDMT(plan, self.npix, xp=xp, pixel_chunk=pixel_chunk, allocate=allocate,
                                       precision=tree_precision, block=self.max_batch)
            self.dms = [float(x) for x in (np.arange(smax + 1) / per_dm if per_dm > 0 else np.zeros(1))]
            self._back = effective_back(plan)                              # (nsweep, nchan)
            self.delay_max = np.arange(smax + 1)
            self.delays = self.delay_max[:, None] - self._back
        else:
            self.delays = dm_delays(dms, self.freq_hz, dt_s)                 # (ndm, nchan)
            self.delay_max = self.delays.max(axis=1)                          # (ndm,)
            # channel c of trial d is read `back[d, c]` images before the newest one
            self._back = (self.delay_max[:, None] - self.delays) if self.average else None
        self.shift = int(self.delay_max.max()) if self.average else 0     # channel history needed
        self.wmax = max(widths)
        self.nser = len(self.dms) if self.average else self.nchan
        if int(hold) != hold or hold < 0:
            raise ValueError(f"hold: expected an integer number of values >= 0, got {hold!r}")
        self.capacity = self.window + self.wmax + self.max_batch + int(hold)
        if allocate:                             # (False: the sizes only, for :meth:`memory_bytes`)
            self.reset(0)

    @property
    def reads_cells(self):
        """Whether :meth:`push` given an ``index`` reads the pixels out of the cells in the passes it
        makes anyway (the float16 tree on a GPU), so that a caller need not gather them first."""
        return self._tree is not None and self.xp is not np and self._tree.dtype is np.float16

    @property
    def tree_rows(self):
        """Shifted-add rows per image and pixel of the tree (None for shifted sums)."""
        return self._tree.plan.rows() if self._tree is not None else None

    def memory_bytes(self, gpu=None):
        """Bytes the search holds where its arrays live (the GPU's memory with CuPy), by part:
        ``history`` (every series' last ``capacity`` values, float32), ``statistics`` (the window
        sums, float64, and offsets), ``channels`` (shifted sums: each channel's last ``shift`` images)
        or ``tree`` (the tree's rings), and ``working``, the most a push of ``max_batch`` images adds
        while it runs (the tree's pass and its output -- none on a GPU where the statistics read the
        float16 tree's rows where they are --, one chunk of S/N values). gpu: for a search on a GPU
        (default: where this one's arrays are)."""
        B, P = self.max_batch, self.npix
        gpu = self.xp is not np if gpu is None else bool(gpu)
        step = max(1, min(self.nser, self.CHUNK_BYTES // max(1, B * P * 8)))
        rows = (gpu and self._tree is not None and self._tree.dtype is np.float16 and self.FUSED_STATS
                and self.wmax <= _STATS_MAXW and self._tree._chunk(B, gpu) >= P)
        working = 4 * len(self.widths) * step * B * P + (0 if rows else 4 * self.nser * B * P)
        parts = {"history": 4 * self.nser * self.capacity * P, "statistics": (8 + 8 + 4) * self.nser * P}
        if self._tree is not None:
            parts["tree"] = self._tree.ring_bytes(gpu)
            working += self._tree.memory_bytes(B, gpu) - parts["tree"]
        else:
            parts["channels"] = 4 * self.nchan * self.shift * P if self.average else 0
            working += 4 * self.nchan * (self.shift + B) * P if self.average else 0     # the joined past
        parts["working"] = working
        return parts

    # ------------------------------------------------------------------ state
    def reset(self, next_image=0):
        """Forget everything; the next pushed image has sequence index ``next_image``."""
        self.next_image = int(next_image)
        self.first_image = int(next_image)       # sequence index of the first image since the reset
        self.nimages = 0                         # images pushed since the reset
        self.nvalues = 0                         # dedispersed values since the reset
        # a reset (every sequence, every gain solution) clears the arrays in place: the history is most of
        # the search's memory, and made again it would be freed and taken again from the pool (or, where
        # shapes differ, the old arrays let go first: held once, not twice)
        self._zeros("_chan", (self.nchan, 0 if self._tree else self.shift, self.npix), np.float32)
        if self._tree is not None:
            self._tree.reset()
        self._zeros("_hist", (self.nser, self.capacity, self.npix), np.float32)
        self._ref = None                         # per-pixel offset of the sums (nser, npix)
        self._zeros("_s1", (self.nser, self.npix), np.float64)
        self._zeros("_s2", (self.nser, self.npix), np.float64)
        self._no_snr = None              # the statistics kernel's snr argument when it writes none
        self._staged, self.staged_images = None, 0   # push(defer=True)'s last batch, values not yet searched

    def _zeros(self, name, shape, dtype):
        """Attribute ``name`` set to zeros of ``shape``, ``dtype``: its array cleared in place where it has
        that shape and dtype, else let go before a new one is made."""
        a = self.__dict__.pop(name, None)
        if a is not None and isinstance(a, self.xp.ndarray) and a.shape == tuple(shape) and a.dtype == dtype:
            a.fill(0)
        else:
            a = None
            a = self.xp.zeros(shape, dtype=dtype)
        setattr(self, name, a)

    @property
    def ready(self):
        """True once S/N values are being formed (the window is full)."""
        return self.nvalues >= self.window + self.wmax

    def value_image(self, n):
        """Sequence index of the newest image in dedispersed value ``n`` (counted since the reset)."""
        return self.first_image + self.shift + n

    # ------------------------------------------------------------------ kernels
    def _dedisperse(self, x, index=None):
        """(B, nchan, npix) new images -> (nser, B', npix) new series values, B' = the values that
        have every channel (all of them once ``shift`` images have been seen since the reset).
        index: with the tree, as :meth:`push`."""
        xp = self.xp
        if not self.average:
            return xp.ascontiguousarray(xp.moveaxis(x, 0, 1))
        B = x.shape[0]
        if self._tree is not None:
            # a view: the tree copies each pixel chunk once, and scales its sums to means as it copies out
            rows = xp is not np and self.FUSED_STATS and self.wmax <= _STATS_MAXW
            out = self._tree.push(xp.moveaxis(x, 0, 1), factor=1.0 / self.nchan, index=index, rows=rows)
            first = max(0, self.shift - self.nimages)      # values before the tree has every channel's past
            if isinstance(out, HalfRows):
                return out.from_time(min(first, B))
            return out[:, first:] if first < B else out[:, :0]
        ext = xp.concatenate([self._chan, xp.moveaxis(x, 0, 1)], axis=1)   # (nchan, shift + B, npix)
        self._chan = xp.ascontiguousarray(ext[:, ext.shape[1] - self.shift:])
        first = max(0, self.shift - self.nimages)          # first new image whose values are complete
        nnew = B - first
        if nnew <= 0:
            return xp.zeros((self.nser, 0, self.npix), dtype=xp.float32)
        out = xp.zeros((self.nser, nnew, self.npix), dtype=xp.float32)
        base = self.shift + first                          # ext index of the first complete image
        for d in range(self.nser):                         # contiguous slices: no gather
            for c in range(self.nchan):
                a = base - int(self._back[d, c])
                out[d] += ext[c, a:a + nnew]
        out *= 1.0 / self.nchan
        return out

    #: working memory of one series chunk's float64 sums (bytes): a search of many series (a tree's
    #: every sweep) runs them in chunks, so its temporaries do not grow with the trials
    CHUNK_BYTES = 256 * 2**20

    def _push_values(self, v):
        """Append series values (nser, B, npix); returns crossings found among them."""
        xp = self.xp
        B = v.shape[1]
        if B == 0:
            return Crossings()
        kernel = xp is not np and self.FUSED_STATS and self.wmax <= _STATS_MAXW
        if isinstance(v, HalfRows) and (self._ref is None or not kernel):
            # the first values (their first image is the reference) or a search without the kernel: as floats
            v = v.array()
        if self._ref is None:
            self._ref = v[:, 0].astype(xp.float32)
        n0 = self.nvalues
        step = max(1, min(self.nser, self.CHUNK_BYTES // max(1, B * self.npix * 8)))
        if kernel:
            found = [self._push_values_gpu(v, n0, step)]
        else:
            found = [self._push_chunk(v[s0:s0 + step], slice(s0, min(self.nser, s0 + step)), n0)
                     for s0 in range(0, self.nser, step)]
        self.nvalues += B
        return Crossings.concat(found)

    #: on the GPU, the statistics in one kernel (False: the array code, as on the CPU)
    FUSED_STATS = True

    def _push_chunk(self, v, ss, n0):
        """:meth:`_push_values` for the series ``ss`` (a slice), values v (len ss, B, npix) from value n0."""
        xp = self.xp
        B, ns = v.shape[1], v.shape[0]
        v = v - self._ref[ss, None, :]                                      # offset about the reference
        W, wmax = self.window, self.wmax
        n = np.arange(n0, n0 + B)
        self._ring_write(n0, v, ss)
        # running sums: value n - wmax enters the window of value n, n - wmax - W leaves it
        enter, leave = n - wmax, n - wmax - W
        de = xp.zeros((ns, B, self.npix), dtype=xp.float64)
        dl = xp.zeros_like(de)
        ne, nl = int((enter >= 0).sum()), int((leave >= 0).sum())
        if ne:
            de[:, B - ne:] = self._ring_read(int(enter[B - ne]), ne, ss)
        if nl:
            dl[:, B - nl:] = self._ring_read(int(leave[B - nl]), nl, ss)
        s1 = self._s1[ss, None] + xp.cumsum(de - dl, axis=1)                 # (ns, B, npix) after value n
        s2 = self._s2[ss, None] + xp.cumsum(de * de - dl * dl, axis=1)
        del de, dl
        self._s1[ss], self._s2[ss] = s1[:, -1], s2[:, -1]
        ok = n >= W + wmax - 1                                              # window full for these
        if not ok.any():
            return Crossings()
        k0 = int(np.argmax(ok))
        s1, s2 = s1[:, k0:], s2[:, k0:]
        mean = s1 / W
        sigma = xp.sqrt(xp.maximum(s2 - s1 * mean, 0.0) / (W - 1))
        del s1, s2
        # boxcar sums over the newest w values, from a cumulative sum of the last wmax - 1 + B' values
        nb = B - k0
        first = n0 + k0 - (wmax - 1)
        c = xp.cumsum(self._ring_read(first, n0 + B - first, ss).astype(xp.float64), axis=1)
        c = xp.concatenate([xp.zeros((ns, 1, self.npix), dtype=xp.float64), c], axis=1)
        out = []
        with np.errstate(divide="ignore", invalid="ignore"):
            for wi, w in enumerate(self.widths):
                e = np.arange(wmax - 1, wmax - 1 + nb) + 1
                box = c[:, e] - c[:, e - w]
                snr = (box / w - mean) * math.sqrt(w) / sigma
                out.append(self._as_crossings(self._crossings(snr), ss, n0 + k0, wi))
        return Crossings.concat(out)

    def _as_crossings(self, found, ss, first, wi):
        """:class:`Crossings` of width ``wi`` from :meth:`_crossings`' indices (series within the chunk
        ``ss``, value within the values from ``first`` on)."""
        if found is None:
            return Crossings()
        s, b, p, val, frac, sky = found
        s = s + ss.start
        w = self.widths[wi]
        dmax = self.delay_max[s] if self.average else 0
        end = self.value_image(first + b)
        return Crossings(image=end - w + 1 - dmax, end_image=end, series=s, width_index=np.full(s.size, wi),
                         pixel=p, snr=val, frac=frac, skywide=sky)

    def _push_values_gpu(self, v, n0, step):
        """:meth:`_push_values` on the GPU, the statistics in one CUDA kernel: a thread per (series, pixel)
        runs through the B new values in order (the ring write, the running float64 sums, the widths'
        boxcars from the newest values it holds), counting crossings per trial image. One launch for
        every series, then one copy of the counts to the host; only a chunk of ``step`` series that has
        a crossing is run again, from its saved window sums, writing its float32 S/N per width (the
        ring writes repeat the same values), and its crossings are taken from the widths and trial
        images that have any.

        Why: the S/N cube would be half the kernel's memory traffic (16 of 32 bytes per trial value)
        and nearly every chunk of a real search has no crossing; and a host wait per chunk would leave
        the kernels waiting on Python."""
        xp = self.xp
        ns, B = int(v.shape[0]), int(v.shape[1])
        W, wmax = self.window, self.wmax
        k0 = max(0, W + wmax - 1 - n0)                                      # first value whose window is full
        nb = max(0, B - k0)
        nw = len(self.widths)
        if self._no_snr is None:
            self._no_snr = xp.empty(1, xp.float32)
        half = isinstance(v, HalfRows)
        if not half:
            v = xp.ascontiguousarray(v, dtype=xp.float32)
        k = _stats_kernel(self.widths)
        threads = 128

        # the kernel steps a series' values by a 32-bit offset: B rows' bytes must fit
        row_bytes = 2 * int(v.W.shape[2]) if half else 4 * self.npix
        if B * row_bytes >= 2 ** 31:
            raise ValueError(f"search: a push of {B} images of {row_bytes} bytes a row is past the statistics "
                             f"kernel's 2 GiB a series; push fewer images at a time (max_batch)")

        def run(ss, snr, count, write):
            hist, s1, s2 = self._hist[ss], self._s1[ss], self._s2[ss]         # views: the kernel updates them
            if half:   # the tree's float16 rows of series ss: (v.top + ss, its times, its row length)
                hB, hld = int(v.W.shape[1]), int(v.W.shape[2])
                src = (np.uint64(0), v.W[v.top + ss.start:v.top + ss.stop], v.ksum, np.float32(v.a),
                       np.float32(v.b), np.int32(hB), np.int32(v.first), np.int32(hld))
            else:
                src = (v[ss], np.uint64(0), np.uint64(0), np.float32(0), np.float32(0), np.int32(0), np.int32(0),
                       np.int32(0))
            k(((self.npix + threads - 1) // threads, ss.stop - ss.start), (threads,),
              (src[0], self._ref[ss], hist, s1, s2, snr, count, np.int32(B),
               np.int32(self.npix), np.int32(self.capacity), np.int64(hist.strides[0] // 4), np.int64(n0),
               np.int32(W), np.int32(k0), np.int32(nb), np.float32(self.threshold), np.int32(write)) + src[1:])
        count = xp.zeros((nw, ns, max(nb, 1)), xp.int32)
        saved = (self._s1.copy(), self._s2.copy()) if nb else None
        run(slice(0, ns), self._no_snr, count, 0)
        if nb == 0:
            return Crossings()
        cnt = to_numpy(count)
        if not cnt.any():
            return Crossings()
        out = []
        for s0 in range(0, ns, step):
            ss = slice(s0, min(ns, s0 + step))
            if not cnt[:, ss].any():
                continue
            self._s1[ss], self._s2[ss] = saved[0][ss], saved[1][ss]
            c = xp.zeros((nw, ss.stop - s0, nb), xp.int32)
            snr = xp.empty((nw, ss.stop - s0, nb, self.npix), xp.float32)
            run(ss, snr, c, 1)
            cc = to_numpy(c)
            out += [self._as_crossings(self._crossings(snr[wi], cc[wi]), ss, n0 + k0, wi)
                    for wi in range(nw) if cc[wi].any()]
        return Crossings.concat(out)

    def _crossings(self, snr, count=None):
        """Crossings of one width's S/N cube (nser, nb, npix), bounded whatever the sky does: per trial
        image (series, value) at most ``max_pixels`` (its brightest), and a trial image with more than
        ``sky_fraction`` of its pixels over the threshold gives one sky-wide crossing at its peak.
        Reduced where the arrays live; returns host (series, value, pixel, snr, frac, skywide) or None."""
        xp = self.xp
        over = snr > self.threshold                           # NaN (sigma 0) never crosses
        if count is None:
            count = to_numpy(over.sum(axis=2))                # (nser, nb)
        if not count.any():
            return None
        frac_all = count / self.npix
        skyrow = frac_all > self.sky_fraction
        if count.max() <= self.max_pixels and not skyrow.any():
            hit = xp.nonzero(over)
            s, b, p = (to_numpy(h) for h in hit)
            val = to_numpy(snr[hit]).astype(np.float64)
        else:
            k = min(self.max_pixels, self.npix)
            masked = xp.where(over, snr, -xp.inf)
            # (a writable copy when every pixel is kept: a sky-wide row's peak is written into it below)
            idx = xp.argpartition(-masked, k - 1, axis=2)[:, :, :k] if k < self.npix else \
                xp.broadcast_to(xp.arange(self.npix), masked.shape).copy()
            top = to_numpy(xp.take_along_axis(masked, idx, axis=2))
            idx = to_numpy(idx)
            if skyrow.any():                                   # the peak alone stands for a sky-wide row
                peak = to_numpy(xp.argmax(masked, axis=2))
                top[skyrow] = -np.inf
                ss, bb = np.nonzero(skyrow)
                idx[ss, bb, 0] = peak[ss, bb]
                top[ss, bb, 0] = to_numpy(masked[xp.asarray(ss), xp.asarray(bb), xp.asarray(peak[ss, bb])])
            s, b, j = np.nonzero(top > self.threshold)
            p, val = idx[s, b, j], top[s, b, j].astype(np.float64)
        return s, b, p, val, frac_all[s, b], skyrow[s, b].astype(np.int64)

    def _ring_read(self, first, count, ss=slice(None)):
        """Values [first, first + count) of the circular history of the series ``ss``, (nser, count,
        npix) (a view when they do not wrap)."""
        a = first % self.capacity
        if a + count <= self.capacity:
            return self._hist[ss, a:a + count]
        k = self.capacity - a
        return self.xp.concatenate([self._hist[ss, a:], self._hist[ss, :count - k]], axis=1)

    def _ring_write(self, first, v, ss=slice(None)):
        a, count = first % self.capacity, v.shape[1]
        k = min(count, self.capacity - a)
        self._hist[ss, a:a + k] = v[:, :k]
        if k < count:
            self._hist[ss, :count - k] = v[:, k:]

    # ------------------------------------------------------------------ warm-up
    def warm_up(self):
        """Run every GPU kernel this search's candidates need, once, on a small twin (same pixels, window,
        widths, threshold, dedispersion, tree precision and caps; 16 channels), through a
        dispersed burst and a sky-wide flash, then forget the twin; returns the seconds it took
        (0 on the CPU). This search's own state is untouched.

        Why: CuPy compiles a kernel at its first use (0.1 s each on an empty kernel cache), and the
        crossing path (the dense S/N rerun, the brightest-pixel caps, the event's window statistics
        and boxcar, its light curve) is first used at the first burst: ~3 s of compiling there
        stalls a whole-band run on a fresh machine while the imager's ring fills -- for a live
        stream, packets lost at the very event. Call before data flows."""
        if self.xp is np:
            return 0.0
        t0 = time.perf_counter()
        self._warm_twin()
        self.xp.cuda.get_current_stream().synchronize()
        return time.perf_counter() - t0

    def _warm_twin(self):
        """:meth:`warm_up`'s work on any array namespace; returns the twin's crossings."""
        xp = self.xp
        nchan = min(self.nchan, 16)
        freq = self.freq_hz[np.linspace(0, self.nchan - 1, nchan).round().astype(int)]
        # the same pixels and window: CuPy's argpartition, CUB's argmax and its reductions' block shapes
        # are specialised on the lengths they reduce (a smaller twin would leave some to compile)
        npix, window = self.npix, self.window
        if self.average:
            span = float(dispersion_delay_s(1.0, freq.min(), freq.max())) / self.dt_s
            dms = [min(max(self.dms), 6.0 / span) if span > 0 else 0.0]
        else:
            dms = [0.0]
        B = self.max_batch                     # pushes as long as the search's: the S/N rerun's shapes
        twin = TransientSearch(freq, self.dt_s, npix, window, dms=dms, widths=self.widths,
                               threshold=self.threshold, average_channels=self.average, xp=xp,
                               max_batch=B, max_pixels=self.max_pixels, sky_fraction=self.sky_fraction,
                               dedisperse=self.dedisperse, tree_precision=self._tree.precision if self._tree else "fp32")
        rng = np.random.default_rng(0)
        n = -(-(window + twin.wmax + twin.shift) // B) * B + 3 * B
        x = rng.normal(10.0, 1.0, (n, nchan, npix)).astype(np.float32)
        # a dispersed burst at pixel 0 and, a push later, a sky-wide flash: a push's crossings go through
        # one of two paths (a few pixels: nonzero; a sky-wide row or too many: the brightest-pixel caps)
        t_b = n - 2 * B + B // 2
        for c in range(nchan):
            x[t_b - int(twin.delays[-1, c]) if self.average else t_b, c, 0] += 40.0
        x[n - B // 4] += 60.0
        found = Crossings.concat([twin.push(xp.asarray(x[a:a + B])) for a in range(0, n, B)])
        twin.statistics()
        if len(found):
            k = int(np.argmax(found.snr))
            ser, pix = int(found.series[k]), int(found.pixel[k])
            # an event's window, boxcars and light curve, at every value still held: reads of the history
            # that wrap around its end take other kernels than those that do not
            for n_end in range(twin.nvalues - twin.capacity + twin.window + twin.wmax, twin.nvalues):
                twin.window_statistics(ser, n_end)
                for w in self.widths:
                    twin.box_image(ser, n_end, w)
                twin.series_values(ser, pix, n_end - 4, n_end + 2)
        return found

    # ------------------------------------------------------------------ public
    def push(self, images, index=None, defer=False):
        """Search new images ``(nimage, nchan, npix)`` (the next ones in time); returns Crossings.

        index : None, or (npix,) the cell of each pixel in ``images`` (nimage, nchan, ncell), e.g. an
            imager's grid: the tree reads the cells where they are (:meth:`.tree.StreamingFDMT.push`);
            the other searches gather them first.
        defer : the last batch's images are dedispersed now (``images`` are not read after this
            returns) but its statistics and crossings wait for the next push or :meth:`flush`, whose
            crossings they join (``staged_images`` counts its images). A block on a GPU releases its
            input span before the statistics' host wait: the writer's next kernels are then queued
            while the search's host code runs, rather than the GPU idling meanwhile."""
        xp = self.xp
        x = images
        if index is not None:
            if x.ndim != 3 or x.shape[1] != self.nchan or int(index.shape[0]) != self.npix:
                raise ValueError(f"images: expected shape (nimage, nchan={self.nchan}, ncell) and the cells of "
                                 f"{self.npix} pixels, got {x.shape} and {tuple(index.shape)}")
            if self._tree is None:
                x, index = xp.take(x, xp.asarray(index), axis=-1), None
        if x.ndim != 3 or (index is None and x.shape[1:] != (self.nchan, self.npix)):
            raise ValueError(f"images: expected shape (nimage, nchan={self.nchan}, npix={self.npix}), got {x.shape}")
        found = [self.flush()]
        for a in range(0, x.shape[0], self.max_batch):
            chunk = xp.asarray(x[a:a + self.max_batch], dtype=xp.float32)
            v = self._dedisperse(chunk, index)
            self.nimages += chunk.shape[0]
            self.next_image += chunk.shape[0]
            if defer and a + self.max_batch >= x.shape[0]:
                self._staged, self.staged_images = v, int(chunk.shape[0])
            else:
                found.append(self._push_values(v))
        return Crossings.concat(found)

    def flush(self):
        """The crossings of the batch a ``push(defer=True)`` left staged (none if nothing is)."""
        v, self._staged, self.staged_images = self._staged, None, 0
        return Crossings() if v is None else self._push_values(v)

    def statistics(self):
        """Current window mean and sigma per series and pixel, (nser, npix) float64 each, in ``xp``
        (NaN before the first value)."""
        xp = self.xp
        W = self.window
        if self._ref is None:
            nan = xp.full((self.nser, self.npix), np.nan)
            return nan, nan
        n = min(max(self.nvalues - self.wmax, 0), W)
        if n < 2:
            nan = xp.full((self.nser, self.npix), np.nan)
            return self._ref.astype(xp.float64) + nan, nan
        mean = self._s1 / n
        sigma = xp.sqrt(xp.maximum(self._s2 - self._s1 * mean, 0.0) / (n - 1))
        return mean + self._ref, sigma

    def _held(self, first, last):
        """True if values [first, last] (since the reset) are all still in the history."""
        return first >= 0 and last < self.nvalues and first > self.nvalues - 1 - self.capacity

    def window_statistics(self, series, n):
        """Mean and sigma per pixel, host float64 (npix,) each, of series ``series`` over the W values
        value ``n`` was compared with (``n - wmax - W + 1 .. n - wmax``): an event's own noise level,
        which a later window that holds the event itself would overstate. None if not all held."""
        a, b = n - self.wmax - self.window + 1, n - self.wmax
        if self._ref is None or not self._held(a, b):
            return None
        # the one series read (a wrapped window of every series would copy the whole history: ~5 GB)
        v = self._ring_read(a, b - a + 1, slice(series, series + 1))[0].astype(self.xp.float64)   # (W, npix), offset
        ref = to_numpy(self._ref[series]).astype(np.float64)
        # reduced where the history lives: only (npix,) pairs cross to the host
        return to_numpy(v.mean(axis=0)) + ref, to_numpy(v.std(axis=0, ddof=1))

    def box_image(self, series, n_end, width):
        """Mean of series ``series`` over values ``n_end - width + 1 .. n_end`` per pixel (the boxcar
        the search formed), host float64 (npix,); None if not all held."""
        a = n_end - int(width) + 1
        if self._ref is None or not self._held(a, n_end):
            return None
        v = to_numpy(self._ring_read(a, int(width), slice(series, series + 1))[0].astype(self.xp.float64).mean(axis=0))
        return v + to_numpy(self._ref[series]).astype(np.float64)

    def snr_by_series(self, pixel, n, first, last, slack=REFINE_SLACK, center=None):
        """A found event's S/N in the series around the one it was found in: for each series ``first ..
        last`` (clipped to those searched), the best boxcar S/N at ``pixel`` over every width and every
        start within ``slack`` values of value index ``n`` -- and, with ``center`` (the series the event
        was found in), ``slack + |series - center|``: one trial more sweep moves the event by up to one
        image wherever in the band the series are aligned -- each against its own window (the W values
        ending ``wmax`` before the boxcar's start, as :meth:`window_statistics`). In float64 from the
        history (the search's own S/N rounds its running sums).

        Returns (series (m,) int, snr (m,) float64): host arrays, NaN where a value is no longer held;
        m is tens to hundreds of series (:meth:`refine_dm`'s use), one small read from the device."""
        first, last = max(0, int(first)), min(self.nser - 1, int(last))
        ser = np.arange(first, last + 1)
        out = np.full(ser.size, np.nan)
        reach = slack + (np.abs(ser - int(center)) if center is not None else np.zeros(ser.size, int))
        R = int(reach.max()) if ser.size else 0
        W, wm = self.window, self.wmax
        a, b = n - R - wm - W + 1, n + R + wm - 1                 # every value a window or boxcar reads
        if self._ref is None or ser.size == 0 or not self._held(a, b):
            return ser, out
        idx = self.xp.asarray(np.arange(a, b + 1) % self.capacity)
        v = to_numpy(self._hist[first:last + 1, idx, int(pixel)]).astype(np.float64)       # (m, b - a + 1)
        c1 = np.concatenate([np.zeros((ser.size, 1)), np.cumsum(v, axis=1)], axis=1)
        c2 = np.concatenate([np.zeros((ser.size, 1)), np.cumsum(v * v, axis=1)], axis=1)
        best = np.full(ser.size, -np.inf)
        for o in range(-R, R + 1):
            m0 = n + o - a                                           # the boxcar's start in v
            lo, hi = m0 - wm - W + 1, m0 - wm + 1                    # its window, [lo, hi)
            mean = (c1[:, hi] - c1[:, lo]) / W
            sigma = np.sqrt(np.maximum(c2[:, hi] - c2[:, lo] - W * mean * mean, 0.0) / (W - 1))
            ok = np.abs(o) <= reach
            for w in self.widths:
                box = (c1[:, m0 + w] - c1[:, m0]) / w
                with np.errstate(divide="ignore", invalid="ignore"):
                    z = (box - mean) * np.sqrt(w) / sigma
                best = np.where(ok, np.fmax(best, z), best)
        out[:] = np.where(np.isfinite(best), best, np.nan)
        return ser, out

    def refine_dm(self, series, pixel, n, *, span=REFINE_SPAN, most=256):
        """The DM of an event found in DM trial ``series`` at ``pixel`` starting at value ``n``, between
        trials: :func:`~bf_epic_blocks.search.clustering.refine_peak` of :meth:`snr_by_series` across the
        trials around it, ``span`` either side, widened (up to ``most``) while its S/N hump reaches the
        edge -- unless the wider view's highest S/N lies outside the narrower one (another event: a bright
        burst whose DM sidelobe this is), where the narrower view is kept. The trial's own DM where the
        search does not average channels into DM trials, has fewer than three or trials not in increasing
        order, no longer holds the values, or the peak cannot be placed (``refine_peak``'s NaN)."""
        from .clustering import PEAK_LEVEL, refine_peak
        own = float(self.dms[series]) if self.average else 0.0
        if not self.average or len(self.dms) < 3 or np.any(np.diff(self.dms) <= 0):
            return own
        view = None
        while True:
            ser, snr = self.snr_by_series(pixel, n, series - span, series + span, center=series)
            if not np.isfinite(snr).any():
                break
            if view is not None and not view[0][0] <= ser[int(np.nanargmax(snr))] <= view[0][-1]:
                break
            view = (ser, snr)
            reaches = any(np.isfinite(e) and e >= PEAK_LEVEL * np.nanmax(snr) for e in (snr[0], snr[-1]))
            if not (reaches and span < most and (ser[0] > 0 or ser[-1] < self.nser - 1)):
                break
            span *= 4
        if view is None:
            return own
        ser, snr = view
        got = refine_peak(np.asarray(self.dms, np.float64)[ser], snr, at=int(series - ser[0]))
        return own if not np.isfinite(got) else got

    def series_values(self, series, pixel, first, last):
        """Dedispersed values of one series and pixel for value indices [first, last] (since the
        reset), host float64; NaN where not (or no longer) held."""
        out = np.full(last - first + 1, np.nan)
        if self._ref is None:
            return out
        n = np.arange(first, last + 1)
        keep = (n >= 0) & (n < self.nvalues) & (n > self.nvalues - 1 - self.capacity)
        if keep.any():
            vals = self._hist[series, self.xp.asarray(n[keep] % self.capacity), pixel]
            out[keep] = to_numpy(vals).astype(np.float64) + float(to_numpy(self._ref[series, pixel]))
        return out


#: widest boxcar the statistics kernel holds in registers (wider ones use the array code)
_STATS_MAXW = 64

#: the boxcar widths the shipped pipelines search (the compile test builds the kernel for them)
_SHIPPED_WIDTHS = ((1, 2, 4, 8),)


@functools.lru_cache(maxsize=None)
def _stats_defines(widths):
    """The statistics kernel's compile-time constants for the boxcar ``widths`` (a tuple of ints;
    statistics.cu's header). Made once per widths: the kernel is asked for at every push."""
    rw = ",".join(f"{np.float32(1.0 / np.sqrt(w)):.9e}f" for w in widths)   # (9 digits: the float32 exactly)
    return {"WMAX": max(widths), "WLIST": ",".join(map(str, widths)), "RWLIST": rw}


def _stats_kernel(widths):
    """The statistics kernel compiled for these boxcar widths."""
    return get_kernel("search/statistics.cu", "bf_search_stats", defines=_stats_defines(tuple(int(w) for w in widths)))


register("search/statistics.cu", *[(_stats_defines(w), None) for w in _SHIPPED_WIDTHS])
