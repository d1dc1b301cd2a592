"""The watchlist in a pipeline: the targets' directions as a tracking pixel list, and the block that
writes their spectra.

A second :class:`~.dft_imager.DFTImagerBlock` images the watch directions (:mod:`bf_epic_blocks.sky.watch`)
from the same calibrated voltages as the main imager, with the same operator conventions (exact 3-D
DFT, the calibration folded in, images in Jy): every image the imager makes (``imager.accumulate_frames``),
every channel, the products ``watch.products`` asks. :class:`WatchPixels` gives that imager the
directions at each integration; :class:`WatchWriterBlock` writes its images to
``<output.dir>/<prefix>_watch.h5`` (:class:`~bf_epic_blocks.io.watchfile.WatchWriter`) as they come, and
each target's dynamic-spectrum PNG every ``png_every_s`` of data.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from ..conventions import FS_HZ
from ..sky.watch import direction_names, parse_targets, target_lm
from ..imaging._xp import get_xp
from . import _compat
from ._compat import bfp, span_array, to_numpy
from ._drawing import DrawingHelper

__all__ = ["WatchPixels", "WatchWriterBlock"]

log = logging.getLogger(__name__)


class WatchPixels:
    """The watch directions' (l, m) at a time tag, for a tracking DFTImagerBlock: ``pixels(time_tag) ->
    (ndir, 2)``.

    Directions are computed for steps of ``step_s`` seconds (at each step's middle, :data:`BATCH_STEPS`
    steps at a time) and held within a step, so that the imager rebuilds its small operator once a step,
    not once an image: the sky turns 0.004 deg in a second, a thousandth of the station's beam at 90 MHz.
    A direction below the horizon or outside its target's window is imaged at the zenith (the operator
    keeps its size) and marked inactive (:meth:`state`), so that its rows are written as NaN.

    targets : :class:`~bf_epic_blocks.sky.watch.WatchTarget` list (or entries); location : astropy
    EarthLocation or (lon_deg, lat_deg, height_m).
    """

    #: steps whose directions one astropy call computes, the first asked for and those after it: a call's
    #: cost is mostly its fixed part, so a minute of steps costs little more than one, and the imager asks
    #: from its own thread, where interpreter time delays its next kernels
    BATCH_STEPS = 60

    def __init__(self, targets, location, step_s=1.0):
        self.targets = parse_targets(targets)
        self.location, self.step_s = location, float(step_s)
        self._cache = {}
        # each direction's name ('CygA', 'CygA+off1') and each target's own (first) direction
        self.names, index = direction_names(self.targets)
        self.first = np.searchsorted(index, np.arange(len(self.targets)))

    def _step(self, time_tag):
        return int(math.floor(time_tag / FS_HZ / self.step_s))

    def state(self, time_tag):
        """(lm (ndir, 2) with inactive directions at the zenith, active (ndir,) bool, ra_dec (ntarget, 2))
        for the step holding ``time_tag``."""
        k = self._step(time_tag)
        hit = self._cache.get(k)
        if hit is None:
            self._fill(k)
            hit = self._cache[k]
        return hit

    def _fill(self, k):
        """Steps k .. k + BATCH_STEPS - 1 into the cache, which keeps the batch before them (a gulp that
        crosses into a new batch asks for its last step first, then for earlier ones) and drops older."""
        from astropy.time import Time
        ks = np.arange(k, k + self.BATCH_STEPS)
        d = target_lm(self.targets, Time((ks + 0.5) * self.step_s, format="unix", scale="utc"), self.location)
        self._cache = {j: v for j, v in self._cache.items() if k - self.BATCH_STEPS <= j < k}
        for i, j in enumerate(ks):
            active = d.active[i]
            lm = np.where(active[:, None], d.lm[i], 0.0)
            ra_dec = np.stack([d.ra_deg[i, self.first], d.dec_deg[i, self.first]], axis=-1)
            self._cache[int(j)] = (lm, active, ra_dec)

    def __call__(self, time_tag):
        return self.state(time_tag)[0]


class WatchWriterBlock(bfp.SinkBlock):
    """Write a watch imager's images (header as DFTImagerBlock's with a pixel list: (time, freq, pol,
    pixel), one pixel per watch direction) to the watch HDF5 file, and the PNGs.

    Parameters
    ----------
    iring : the watch imager's output ring.
    path : the HDF5 file (``<output.dir>/<prefix>_watch.h5``).
    pixels : the :class:`WatchPixels` the imager tracks with (for each image's active directions and
        the bodies' positions).
    png_every_s : seconds of data between rewrites of each target's PNG (``<stem>_<target>.png``, the last
        ``png_every_s`` of its first product, in at most PNG_COLUMNS time bins kept in memory); None: no PNG.
    bus, trigger_sigma, ring_s : a :class:`~.snippets.TriggerBus` told when a target's band-mean light
        curve (its first product) rises more than ``trigger_sigma`` robust sigma (1.4826 MAD) above its
        median over the last ``ring_s`` of data (once that holds 32 images; updated every
        BASELINE_EVERY_S of data); None: no triggers.
    png_process : draw the PNGs in a helper process (:meth:`write_pngs`; `bf-epic run` does on a GPU).
    ``rows`` counts the images received (the file holds them within WRITE_EVERY_S of data); ``inactive`` the direction-rows written as NaN; ``triggers`` the
    triggers posted; ``png_skipped`` the PNG rounds skipped while the last was still drawing.
    """

    #: time bins across a PNG (a minute of 0.64-ms images is ~94,000)
    PNG_COLUMNS = 1000
    #: seconds of data the file's writer holds before it writes them (each HDF5 write holds the lock the
    #: pipeline's other threads need for about as long for one gulp's rows as for a second's)
    WRITE_EVERY_S = 1.0
    #: seconds of data between updates of the light curves' baseline (median and MAD of the last
    #: ``ring_s``): a median of 2 s of 0.64-ms images at every gulp cost ~4 ms of host time for 10
    #: targets and ~14 ms for 100, and the baseline of 2 s moves little in a quarter of one
    BASELINE_EVERY_S = 0.25

    def __init__(self, iring, path, pixels, png_every_s=60.0, bus=None, trigger_sigma=None, ring_s=2.0,
                 png_process=False, **kwargs):
        super().__init__(iring, **kwargs)
        self._drawing = DrawingHelper("WatchWriterBlock", png_process)
        self.bus, self.trigger_sigma, self.ring_s = bus, trigger_sigma, float(ring_s)
        self.triggers = 0
        self._history = None
        self._was = None
        self.path, self.pixels = Path(path), pixels
        self.png_every_s = None if png_every_s is None else float(png_every_s)
        self._writer = None
        self.rows = self.inactive = 0
        self.pngs, self.files, self._nseq = [], [], 0

    def define_valid_input_spaces(self):
        return "any"

    @property
    def written(self):
        """The files written so far: the HDF5 files closed, and the PNGs."""
        return list(dict.fromkeys(self.files + [str(p) for p in self.pngs]))

    def on_sequence(self, iseq):
        from astropy.time import Time

        from ..io.watchfile import WatchWriter
        hdr = iseq.header
        tens = hdr["_tensor"]
        t0, self._dt = float(tens["scales"][0][0]), float(tens["scales"][0][1])
        f0, df = (float(v) for v in tens["scales"][1])
        nchan = int(tens["shape"][1])
        self._freq = f0 + df * np.arange(nchan)
        self._products = list(hdr.get("pol_products") or hdr["imager"]["products"])
        self._t0, self._tag0 = t0, int(hdr.get("time_tag", round(t0 * FS_HZ)))
        self._tag_per_image = self._dt * FS_HZ
        if self._writer is None:
            path = self.path if self._nseq == 0 else self.path.with_name(f"{self.path.stem}_s{self._nseq:02d}.h5")
            self._writer = WatchWriter(path, self.pixels.targets, self._freq, self._products,
                                       flush_s=self.WRITE_EVERY_S)
            log.info("WatchWriterBlock: %d targets (%d directions), %s, every %.3g ms image -> %s",
                     len(self.pixels.targets), self._writer.ndir, "/".join(self._products), 1e3 * self._dt,
                     self._writer.path)
        self._since_png = 0.0
        self._image = 0
        if self.png_every_s is not None:
            from ..io.watchfile import BinnedSpectra
            keep = max(1, int(round(self.png_every_s / self._dt)))
            per = max(1, -(-keep // self.PNG_COLUMNS))
            self._png = BinnedSpectra(len(self.pixels.targets), nchan, per, -(-keep // per))
        for tg in self.pixels.targets:
            if tg.stop is not None and tg.stop.unix < self._t0:
                log.warning("watch: %s's window ended at %s UTC, before these data begin (%s UTC): it is never "
                            "recorded (NaN rows)", tg.name, tg.stop.isot, Time(self._t0, format="unix").isot)

    def on_data(self, ispan):
        x = span_array(ispan)                                            # (n, nchan, nprod, ndir)
        n = int(x.shape[0])
        if n == 0:
            return
        # directions first, made on the device where it is one: the file's writer copies each target's
        # rows as one piece, and the host makes no transposed copy (100 targets' gulp is 20 MB)
        with _compat.stream_context():
            xd = get_xp(x).ascontiguousarray(x.transpose(3, 0, 1, 2))
            # the stream first, then the copy (to_numpy): a copy into pageable memory that waits for the
            # queued images inside the CUDA driver holds up every other thread's CUDA calls
            xd = to_numpy(xd) if hasattr(xd, "get") else np.array(xd, np.float32)   # a copy: rows get NaN
        first = getattr(ispan, "frame_offset", self._image)
        idx = first + np.arange(n)
        tu = self._t0 + (idx + 0.5) * self._dt                          # image centres, Unix s
        data = np.moveaxis(xd.astype(np.float32, copy=False), 0, 1)     # (n, ndir, nchan, nprod), a view
        ra_dec = np.empty((n, len(self.pixels.targets), 2))
        # the images of one step share its directions (WatchPixels holds them a step): one look-up a run
        tags = self._tag0 + idx * self._tag_per_image
        starts = np.r_[0, np.flatnonzero(np.diff(np.floor(tags / FS_HZ / self.pixels.step_s))) + 1, n]
        for a, b in zip(starts[:-1], starts[1:]):
            _, active, rd = self.pixels.state(tags[a])
            ra_dec[a:b] = rd
            if self._was is None or not np.array_equal(active, self._was):
                self._log_changes(active, tu[a])
            if not active.all():
                data[a:b, ~active] = np.nan
                self.inactive += int((~active).sum()) * int(b - a)
        self._writer.append(tu, data, ra_dec)
        own = self.pixels.first
        # each target's own direction, first product: (n, ntarget, nchan), a view where no target has offsets
        spec = data[..., 0] if len(own) == data.shape[1] else data[:, own][..., 0]
        if self.png_every_s is not None:
            self._png.add(tu, spec)
        if self.bus is not None and self.trigger_sigma is not None:
            self._light_curve_triggers(tu, spec)
        self.rows += n
        self._image = first + n
        self._since_png += n * self._dt
        if self.png_every_s is not None and self._since_png >= self.png_every_s:
            self._since_png = 0.0
            self.write_pngs()

    def _log_changes(self, active, t_unix):
        """Log the directions that set, rise, leave or enter their window (their rows are NaN while out)."""
        from astropy.time import Time
        names = self.pixels.names
        was = np.ones_like(active) if self._was is None else self._was
        when = Time(t_unix, format="unix").isot
        for j in np.flatnonzero(active != was):
            log.info("watch: %s is %s at %s UTC%s", names[j], "recorded again" if active[j] else "not recorded",
                     when, "" if active[j] else " (below the horizon or outside its window: NaN rows)")
        self._was = active.copy()

    def _light_curve_triggers(self, tu, spec):
        """Post a trigger for each target whose band-mean light curve crosses its threshold in this gulp
        (the baseline from the images before the gulp); ``spec`` (n, ntarget, nchan) each target's spectra."""
        import collections
        import warnings
        lc = spec.mean(axis=2, dtype=np.float64)                             # (n, ntarget)
        bad = ~np.isfinite(lc)
        if bad.any():                               # NaN channels or a target down: the NaN-aware mean
            with warnings.catch_warnings():         # of those (all-NaN rows are NaN, not warnings)
                warnings.simplefilter("ignore", RuntimeWarning)
                lc[bad] = np.nanmean(spec[bad], axis=-1)
        if self._history is None:
            self._history = collections.deque(maxlen=max(32, int(round(self.ring_s / self._dt))))
            self._baseline, self._baseline_at = None, -np.inf
        if len(self._history) >= 32:
            if self._baseline is None or tu[0] - self._baseline_at >= self.BASELINE_EVERY_S:
                self._baseline, self._baseline_at = self._robust_baseline(np.asarray(self._history)), tu[0]
            med, sd = self._baseline
            with np.errstate(invalid="ignore", divide="ignore"):
                z = (lc - med) / sd
            for j, tg in enumerate(self.pixels.targets):
                hit = np.flatnonzero(z[:, j] > self.trigger_sigma)
                if hit.size:
                    i = int(hit[0])
                    self.bus.post(tu[i], f"watch {tg.name} {z[i, j]:.1f} sigma")
                    self.triggers += 1
        for row in lc:
            self._history.append(row)

    @staticmethod
    def _robust_baseline(h):
        """(median, 1.4826 MAD) per target of a light-curve history h (nimage, ntarget), NaN-aware only
        where it has NaN (the plain median is several times faster)."""
        import warnings
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            median = np.nanmedian if np.isnan(h).any() else np.median
            med = median(h, axis=0)
            return med, 1.4826 * median(np.abs(h - med), axis=0)

    def write_pngs(self, wait=False):
        """Each target's dynamic spectrum and light curve (its first product) over the last
        ``png_every_s`` of data, in time bins (BinnedSpectra); the paths are kept in ``pngs``.

        With ``png_process`` the drawing runs in a helper process (matplotlib's interpreter time would
        hold the lock the pipeline's other threads need, and a stalled writer stalls the imagers through
        the rings); a round that finds the last one still drawing is skipped and counted
        (``png_skipped``); ``wait``: wait for this round (the sequence's last)."""
        if self._writer is None or self._writer.rows == 0:
            return []
        t, binned = self._png.rows()
        jobs = [(str(self._writer.path.with_name(f"{self._writer.path.stem}_{tg.name}.png")), t, self._freq,
                 binned[:, j].astype(np.float32), f"{tg.name} ({self._products[0]})")
                for j, tg in enumerate(self._writer.targets)]
        self._drawing.run(_draw_pngs, (jobs,), self._set_pngs, wait=wait)
        return self.pngs

    def _set_pngs(self, paths):
        self.pngs = paths

    @property
    def png_process(self):
        """Whether the PNGs are drawn in the helper process (False once it failed)."""
        return self._drawing.enabled

    @property
    def png_skipped(self):
        return self._drawing.skipped

    def close(self):
        """Wait for the PNGs being drawn and stop the helper process."""
        self._drawing.close()

    def on_sequence_end(self, iseq):
        """The PNGs brought up to date and the file closed (marked complete); a later sequence (a live
        stream that restarts) writes ``<stem>_s01.h5``, ... beside it."""
        if self._writer is not None:
            if self.png_every_s is not None:
                self.write_pngs(wait=True)
            self._writer.close()
            self.files.append(str(self._writer.path))
            self._writer = None
        self._nseq += 1


def _draw_pngs(jobs):
    """Draw each (path, time_unix, freq_hz, data (nbins, nchan), title) as a dynamic-spectrum PNG; the
    paths drawn (a failure is logged and left out: a quicklook must not stop the recording)."""
    from ..io.watchfile import dynamic_spectrum_png
    out = []
    for path, t, freq, d, title in jobs:
        try:
            out.append(dynamic_spectrum_png(path, t, freq, d, title=title))
        except Exception as e:  # noqa: BLE001
            log.warning("WatchWriterBlock: the PNG %s was not written: %s", path, e)
    return out
