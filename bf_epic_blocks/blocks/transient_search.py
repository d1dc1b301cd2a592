"""TransientSearchBlock: searches an imager's output for short bursts, candidates on the sky.

A sink on the image ring (docs/HEADERS.md, "Written by DFTImagerBlock"), configured by one
:class:`~bf_epic_blocks.search.SearchSettings`. Per gulp it hands the chosen product's images (pixels
below the horizon dropped) to :class:`bf_epic_blocks.search.TransientSearch` (NumPy or CuPy, where the
ring lives), collects the threshold crossings, clusters them (:func:`cluster_crossings`) once no later
crossing can join, and at the end of each sequence makes every candidate so far one table
(``candidates``) and hands it to its writer, if it has one
(:class:`bf_epic_blocks.io.candidates.CandidateWriter`: the table and a PNG).

Resets: a new sequence, any images lost to an overrun (``guarantee=False``; ``on_skip``), and a new
gain solution (``gains``: each solution scales the whole sky's images at once, a step the window
would take for a sky-wide burst) clear the sliding window; the search restarts only once the window is
full again, so a gap or a step never produces candidates. The image that straddles a solution's start
(half its frames with each) is left out. Pending candidates are finished (with their light curves)
before a reset.
"""
from __future__ import annotations

import logging

import numpy as np

from ..imaging.pixels import take_pixels
from ..search import (ArrayBeam, Crossings, SearchSettings, TransientSearch, cluster_crossings, dm_sidelobe_snr,
                      locate_point_source)
from ..search.settings import look_ahead
from . import _compat
from ._compat import bfp, span_array
from .headers import image_layout, station_location

log = logging.getLogger(__name__)


class TransientSearchBlock(bfp.SinkBlock):
    """Search image sequences for transients.

    Parameters
    ----------
    iring : an imager's output ring (grid or pixel list).
    settings : :class:`~bf_epic_blocks.search.SearchSettings` (default: its defaults): thresholds,
        trials, clustering, light curves and sidelobe folding. Its ``sidelobe_factor`` folds a point
        candidate into a brighter one at the same time when the brighter explains its S/N: the point
        source that best explains the brighter one's S/N on every pixel through the array's beam
        (:class:`~bf_epic_blocks.search.ArrayBeam` from the header's station, flags and antenna
        pattern; :func:`~bf_epic_blocks.search.locate_point_source`, within a cell of its pixel: a grid
        coarser than the beam sees a source between pixels at a fraction of its peak), or, with
        dedispersion, its DM sidelobe (:func:`~bf_epic_blocks.search.dm_sidelobe_snr`: fainter
        candidates near its pixel, within a sweep of it in time, whose trial's sweep crosses the
        burst's in the band).
    writer : None, or an object whose ``write(table, sky, grid=, lm=)`` writes the candidates (e.g.
        :class:`~bf_epic_blocks.io.candidates.CandidateWriter`), called at the end of each sequence
        with every candidate so far and the window mean at the searched pixels.
    location : astropy EarthLocation (default: the header's station).
    flag_weights : the :class:`~.rfi_flag.FlagWeights` of the interference flagger before the imager (made
        with ``track_empty=True``): channel images that kept nothing are treated as missing (filled with
        their channel's mean), never as a dip or a signal.
    gains : the gain table the images were calibrated with, where its solutions change during a sequence
        (a :class:`~bf_epic_blocks.imaging.calibration.GainTable` or the live solver's
        :class:`~.gain_solver.LiveGainTable`: anything with ``valid_from`` time tags, every solution that
        applies to an image known by the time the image is in the ring): the window restarts at each.

    ``candidates`` is the astropy Table of all candidates so far; ``search_stats`` counts images
    searched, trials per width, crossings, resets (``gain_resets`` of them at a new gain solution) and
    images lost (``images_straddling_gains`` of them left out at a solution's start); ``written`` lists
    the writer's files.
    """

    def __init__(self, iring, settings=None, *args, writer=None, location=None, flag_weights=None, gains=None,
                 **kwargs):
        moved = sorted(set(kwargs) & set(SearchSettings.__dataclass_fields__))
        if moved:
            raise TypeError(f"TransientSearchBlock: {', '.join(moved)} is set in the settings object: pass "
                            f"settings=SearchSettings({moved[0]}=...)")
        if {"outdir", "prefix", "table_format", "png"} & set(kwargs):
            raise TypeError("TransientSearchBlock: outdir, prefix, table_format and png belong to the writer: pass "
                            "writer=CandidateWriter(outdir, prefix, table_format, png) (bf_epic_blocks.io.candidates)")
        settings = SearchSettings() if settings is None else settings
        if not isinstance(settings, SearchSettings):
            raise TypeError(f"TransientSearchBlock: settings must be a SearchSettings, got {type(settings).__name__}")
        super().__init__(iring, *args, **kwargs)
        # the search's clustering, sidelobe folding and false rates import these on its thread (see import_now)
        _compat.import_now("scipy.sparse.csgraph", "scipy.spatial", "scipy.stats")
        self.settings, self.writer, self.location = settings, writer, location
        self.flag_weights = flag_weights
        self.gains = gains
        self._gains_done = None       # the time tag through which gain solutions have been seen
        #: fit every point candidate's source at once (a pixel split's part: SearchParts folds the other
        #: parts' sidelobes with it), not only when a fainter one needs it
        self.fit_every_row = False
        self.rows = []
        self.candidates = None
        self.on_candidate = None      # a callable(row) told of each candidate as it is made (triggered saves)
        self._warmed = False            # the candidate path's GPU kernels compiled (TransientSearch.warm_up)
        self.search_stats = {"images": 0, "images_searched": 0, "crossings": 0, "candidates": 0, "resets": 0,
                             "images_lost": 0, "trials_per_width": [0] * len(self.widths), "sequences": 0,
                             "sky_wide": 0, "sidelobes_folded": 0, "crossings_dropped": 0, "gain_resets": 0,
                             "images_straddling_gains": 0, "out_of_memory": 0}
        self._sky = None

    # the settings SearchParts and the candidate code read, as the block uses them
    threshold = property(lambda self: self.settings.threshold)
    sidelobe_factor = property(lambda self: self.settings.sidelobe_factor)
    lc_before = property(lambda self: self.settings.lc_before)
    lc_after = property(lambda self: self.settings.lc_after)
    dms = property(lambda self: list(self.settings.dms))
    widths = property(lambda self: list(self.settings.widths))

    @property
    def written(self):
        """The files the writer has written (none without one)."""
        return list(getattr(self.writer, "written", []))

    # ------------------------------------------------------------------ set-up
    def _xp(self):
        if _compat.space_of(self.irings[0]) == "cuda":
            import cupy
            return cupy
        return np

    def on_sequence(self, iseq):
        hdr = iseq.header
        lay = image_layout(hdr, "TransientSearchBlock")
        product = self.settings.product
        if product is None:
            self._prod = 0
        elif product in lay["products"]:
            self._prod = lay["products"].index(product)
        else:
            raise ValueError(f"TransientSearchBlock: product {product!r} not in the images' products "
                             f"{lay['products']}")
        self.lay, self.hdr = lay, hdr
        self.xp = self._xp()
        settings = self.settings
        kw, self._tlink = settings.search_keywords(lay["freq_hz"], lay["dt_s"])
        # the last sequence's search let go first: its history (tens of GB for a whole band) is not held
        # twice while the new one is made
        self.search = None
        self.search = TransientSearch(lay["freq_hz"], lay["dt_s"], len(lay["lm"]), threshold=settings.threshold,
                                      xp=self.xp, max_pixels=settings.max_pixels, sky_fraction=settings.sky_fraction,
                                      **kw)
        if not self._warmed:
            # the crossing path's kernels compiled now, not at the first burst (TransientSearch.warm_up)
            dt = self.search.warm_up()
            self._warmed = True
            if dt:
                log.info("TransientSearchBlock: the candidate path's GPU kernels warmed up in %.2f s", dt)
        window = self.search.window
        st = hdr.get("station") or {}
        self._beam_ants = []            # antenna positions per polarisation, for the sidelobe test
        if st.get("xyz_m") is not None:
            xyz = np.asarray(st["xyz_m"], np.float64).reshape(-1, 3)
            fl = np.asarray(st.get("flags", np.zeros((len(xyz), 2), bool)), bool).reshape(len(xyz), -1)
            for pol in range(fl.shape[1]):
                ants = xyz[~fl[:, pol]]
                self._beam_ants.append(ants)
        self._autocorr_removed = bool((hdr.get("imager") or {}).get("remove_autocorr", False))
        self._beam = None               # ArrayBeam on the searched pixels, made when first needed
        self._fits = {}                 # row -> fitted S/N model of that point event at every pixel
        self._recent = []               # point rows that may have sidelobes still to come
        self._index = self.xp.asarray(lay["pixel_index"], dtype=np.int32)   # take_pixels' form: no cast a gulp
        if lay["grid"] is not None:
            N = lay["grid"].size
            self._xy = np.column_stack([lay["pixel_index"] % N, lay["pixel_index"] // N]).astype(np.float64)
            self._space = 2.0 if settings.space_link is None else settings.space_link
            self._cell = float(lay["grid"].cell)
        else:
            from scipy.spatial import cKDTree
            self._xy = lay["lm"]
            d, _ = cKDTree(self._xy).query(self._xy, k=2) if len(self._xy) > 1 else (np.ones((1, 2)), None)
            self._cell = float(np.median(d[:, 1]))
            self._space = 2.0 * self._cell if settings.space_link is None else settings.space_link
        self.loc = self.location if self.location is not None else station_location(hdr)
        self._pending = Crossings()
        self._looks = {}                # an open cluster's peak crossing -> what its row reads from the history
        self._ahead = look_ahead(settings.lc_after, max(self.widths), settings.average_channels)
        self._j = 0                                   # sequence index of the next image
        self._flag_seq, self._fill_mean = int(hdr.get("time_tag", 0)), None
        self._gains_done = int(lay["time_tag"])       # a solution from before the sequence is no step in it
        self.search_stats["sequences"] += 1
        log.info("TransientSearchBlock %s: %d pixels, %d channels, window %d images (%.3f s), DMs %s, widths %s, "
                 "threshold %.1f", hdr.get("name"), len(lay["lm"]), lay["nchan"], window, window * lay["dt_s"],
                 self.dms if self.search.dedisperse == "shifts" else
                 f"every sweep 0-{self.search.shift} images (DM 0-{self.search.dms[-1]:.3g}, tree)",
                 self.widths, self.threshold)

    # ------------------------------------------------------------------ per gulp
    def _lose(self, lost, why):
        """``lost`` images not searched: what was pending is finished and the window starts again."""
        self._flush()
        self._finish(final=True)
        self._j += lost
        self.search.reset(self._j)
        self.search_stats["resets"] += 1
        self.search_stats["images_lost"] += lost
        log.warning("TransientSearchBlock: %d images lost (%s); window reset at image %d", lost, why, self._j)

    def on_data(self, ispan):
        # images are placed by their index in the sequence, not by the order of calls (see _compat)
        gap = _compat.frames_lost_before(ispan, self._j)
        if gap:
            self._lose(gap, "reader overrun")
        data = span_array(ispan)
        n = data.shape[0]
        with _compat.stream_context():
            cells = data[:, :, self._prod].reshape(n, self.lay["nchan"], -1)
            if self.flag_weights is not None:
                cells = self._fill_flagged(cells)
            guaranteed = getattr(self, "guarantee", True)
            if guaranteed and self.search.reads_cells:
                # the span is held until this returns: the tree reads the pixels' cells where they are
                x, index = cells, self._index
            else:
                x, index = take_pixels(cells, self._index), None
            if not guaranteed:
                if self.xp is not np:   # the copy must be done before asking what was overwritten
                    self.xp.cuda.get_current_stream().synchronize()
                bad = _compat.frames_overwritten(ispan, n)
                if bad:
                    self._lose(bad, "overwritten while read")
                    x, n = x[bad:], n - bad
                    if n == 0:
                        return
            # a batch at a time, each finished before the next: an event is looked back at (its window,
            # its boxcar on every pixel) while the search still holds it, whatever the gulp size; the
            # window restarts where a new gain solution starts
            pos = 0
            for cut, skip in self._gain_cuts(n):
                self._push_batches(x[pos:cut], index)
                self._restart_at_gains(skip)
                pos = cut + skip
            self._push_batches(x[pos:], index)

    def _push_batches(self, x, index):
        for a in range(0, x.shape[0], self.search.max_batch):
            self._push(x[a:a + self.search.max_batch], index)

    def _gain_cuts(self, n):
        """[(offset, skip)]: where, among the next ``n`` images (from image ``_j``), a gain solution starts
        (the offset of the image holding its first frame) and whether that image straddles it (skip 1)."""
        if self.gains is None:
            return []
        t0, ticks = int(self.lay["time_tag"]), int(self.lay["integration_ticks"])
        end = t0 + (self._j + n) * ticks
        vf = np.asarray(self.gains.valid_from, np.int64)     # increasing; a day's table holds thousands
        a, b = np.searchsorted(vf, [self._gains_done, end], side="right")
        cuts = []
        for v in vf[a:b]:
            v = int(v)
            if v >= end:
                continue
            e, rem = divmod(v - t0, ticks)
            off = max(int(e) - self._j, 0)
            skip = min(int(rem > 0), n - off)
            if cuts and off < cuts[-1][0] + cuts[-1][1]:
                continue                  # two solutions in one image: one restart after both
            cuts.append((off, skip))
            self._gains_done = v
        return cuts

    def _restart_at_gains(self, skip):
        """A new gain solution from here: what is pending is finished, ``skip`` straddling images are left
        out, and the window starts again."""
        self._flush()
        self._finish(final=True)
        self._j += skip
        self.search.reset(self._j)
        self.search_stats["resets"] += 1
        self.search_stats["gain_resets"] += 1
        self.search_stats["images_straddling_gains"] += skip
        log.info("TransientSearchBlock: a new gain solution; window reset at image %d", self._j)

    def _fill_flagged(self, cells):
        """Channel images that kept nothing (interference flagged every stand) are missing data, not a
        dip to zero: each is replaced by its channel's mean over this gulp's unflagged images (or the last
        gulp's, where this gulp has none), so that it adds neither signal nor variance to the search."""
        xp = self.xp
        n = cells.shape[0]
        empty = self.flag_weights.take_empty(self._flag_seq, self._j, n)
        if empty is None:
            return cells
        ok = xp.asarray(~empty)[:, :, None]
        cnt = ok.sum(axis=0)                                                   # (nchan, 1)
        mean = xp.where(ok, cells, 0).sum(axis=0) / xp.maximum(cnt, 1)
        if self._fill_mean is not None:
            mean = xp.where(cnt > 0, mean, self._fill_mean)
        self._fill_mean = mean
        self.flag_weights.stats["channel_images_filled"] += int(empty.sum())     # a host array: no wait
        return xp.where(ok, cells, mean[None].astype(cells.dtype))

    def _push(self, x, index=None):
        n = x.shape[0]
        n_before = self.search.nvalues
        # on a GPU the last batch's statistics wait for the next gulp (TransientSearch.push's defer): this
        # span is released before their host wait, so the imager's next gulp is queued meanwhile
        defer = self.xp is not np if self.DEFER_STATS is None else bool(self.DEFER_STATS)
        try:
            cr = self.search.push(x, index, defer=defer)
        except MemoryError as e:            # CuPy's OutOfMemoryError too: the images go on, unsearched
            self.search_stats["out_of_memory"] += 1
            self.search.reset(self._j)      # the staged values dropped first: searching them may be what failed
            self._lose(n, f"out of memory in the search: {str(e)[:200]}")
            return
        self._j += n
        self.search_stats["images"] += n
        self._took(cr, n_before)
        self._finish(final=False)

    #: each gulp's statistics run at the next gulp (None: on a GPU, where it keeps the GPU busy)
    DEFER_STATS = None

    def _took(self, cr, n_before):
        """Count the values searched since ``n_before`` and the crossings ``cr``; hold them pending."""
        nsearched = max(0, self.search.nvalues - max(n_before, self.search.window + self.search.wmax - 1))
        if nsearched:
            for i in range(len(self.widths)):
                self.search_stats["trials_per_width"][i] += nsearched * self.search.nser * self.search.npix
        self.search_stats["images_searched"] += nsearched
        self.search_stats["crossings"] += len(cr)
        self._pending = self._bounded(Crossings.concat([self._pending, cr]))

    def _flush(self):
        """Search what the last push left staged (its crossings join the pending ones)."""
        if self.search.staged_images:
            n_before = self.search.nvalues
            self._took(self.search.flush(), n_before)

    #: pending crossings clustered at most (the brightest; a flood beyond is counted and logged)
    MAX_PENDING = 100_000

    def _bounded(self, cr):
        """What the clustering is given, bounded whatever the sky does. With the tree (every sweep a
        trial) a crossing's trials and widths at one (event image, pixel) are one crossing, its
        brightest: the clusters link all trials anyway and keep their peak, so only ``nmembers``
        changes meaning (crossings per image and pixel). Beyond ``MAX_PENDING`` the faintest are
        dropped (``search_stats['crossings_dropped']``): a bright source that steps, or RFI, can put
        millions over the threshold, whose friends-of-friends pairs grow as their square."""
        if self.search.dedisperse == "tree" and len(cr) > 1:
            key = cr.image.astype(np.int64) * (len(self._xy) + 1) + np.where(cr.skywide > 0, len(self._xy), cr.pixel)
            order = np.lexsort((-cr.snr, key))
            first = np.r_[True, key[order][1:] != key[order][:-1]]
            cr = cr.take(np.sort(order[first]))
        if len(cr) > self.MAX_PENDING:
            keep = np.sort(np.argpartition(-cr.snr, self.MAX_PENDING - 1)[:self.MAX_PENDING])
            lost = len(cr) - self.MAX_PENDING
            if not self.search_stats["crossings_dropped"]:
                log.warning("TransientSearchBlock: more than %d crossings pending (a flood: a bright source that "
                            "steps, RFI?); the faintest are dropped and counted", self.MAX_PENDING)
            self.search_stats["crossings_dropped"] += lost
            cr = cr.take(keep)
        return cr

    def on_skip(self, islices, ospans):
        lost = _compat.frames_lost_at_end(islices, self._j)   # those before a later span: in on_data
        if lost:
            self._lose(lost, "reader overrun")

    def on_sequence_end(self, iseq):
        self._flush()
        self._finish(final=True)
        self._write()

    # ------------------------------------------------------------------ candidates
    def _finish(self, final):
        """Cluster pending crossings; turn the clusters no later crossing can join into candidates."""
        cr = self._pending
        if not len(cr):
            return
        sky = cr.skywide.astype(bool)
        if sky.any() and not sky.all():
            # the other DM trials and widths see a sky-wide event smeared over up to the largest delay
            # (plus a boxcar): what crosses then, near it in time, is that event, not a source of its own
            span = self.search.shift + self.search.wmax
            near = np.abs(cr.image[:, None] - cr.image[sky][None, :]).min(axis=1) <= span
            cr.skywide[near] = 1
        xy = self._xy[cr.pixel].astype(np.float64)
        # sky-wide crossings are all in one place, far from every pixel: they link to each other by
        # time and DM only, never to a point crossing
        xy[cr.skywide.astype(bool)] = 1e12
        labels, peaks = cluster_crossings(cr.image, xy, cr.series, cr.snr, time_link=self._tlink,
                                          space_link=self._space, series_link=len(self.search.dms))
        if final:
            done = np.ones(labels.max() + 1, bool)
        else:
            newest = np.full(labels.max() + 1, -np.inf)
            np.maximum.at(newest, labels, cr.image.astype(float))
            # a later crossing starts no earlier than this image (widest boxcar, largest delay), counted
            # from the images searched (a staged batch's crossings are still to come)
            horizon = self._j - self.search.staged_images - self.search.wmax - self.search.shift - self.lc_after
            done = newest + self._tlink < horizon
            if not done.all() and done.any():
                # a cluster waits for any brighter one near it in time that is still open: it may be
                # that one's sidelobe, and a sidelobe can only fold into a row that exists
                first = np.full(labels.max() + 1, np.inf)
                np.minimum.at(first, labels, cr.image.astype(float))
                peak = np.full(labels.max() + 1, -np.inf)
                np.maximum.at(peak, labels, cr.snr)
                # (or its DM sidelobe: with dedispersion the sweeps of other trials meet it up to the
                # largest delay away)
                span = self._tlink + self.search.wmax + (self.search.shift if self.search.average else 0)
                open_ = np.flatnonzero(~done)
                for lab in np.flatnonzero(done):
                    near = (first[open_] <= newest[lab] + span) & (newest[open_] >= first[lab] - span)
                    if np.any(near & (peak[open_] > peak[lab])):
                        done[lab] = False
        # an open cluster's peak is looked back at once the values after it are there: it may stay open
        # for up to the largest sweep (its other trials' crossings are found that much later), longer than
        # the search holds its values
        for lab, k in zip(labels[peaks], peaks):
            if not done[lab]:
                self._take_look(cr, k)
        finals = sorted((k for lab, k in zip(labels[peaks], peaks) if done[lab]), key=lambda k: -cr.snr[k])
        self._sigma = _compat.to_numpy(self.search.statistics()[1]) if finals else None   # (nser, npix)
        for k in finals:                                 # brightest first: sidelobes fold into it
            members = labels == labels[k]
            if not cr.skywide[k] and self._sidelobe_of(cr, k, int(np.sum(members))):
                continue
            self._add_candidate(cr, k, int(np.sum(members)), float(cr.frac[members].max()))
        keep = self._j - 4 * (self._tlink + self.search.wmax + self.search.shift + self.lc_after)
        self._recent = [r for r in self._recent if r["image"] >= keep]
        self._fits = {r["row"]: self._fits[r["row"]] for r in self._recent if r["row"] in self._fits}
        self._pending = cr.take(~done[labels])
        still = {_look_key(cr, k) for lab, k in zip(labels[peaks], peaks) if not done[lab]}
        self._looks = {key: v for key, v in self._looks.items() if key in still}

    def _value_index(self, cr, k):
        """Value index (since the search's reset) of crossing k's first image, dedispersed at its trial."""
        s = self.search
        return int(cr.end_image[k]) - self.widths[int(cr.width_index[k])] + 1 - s.first_image - s.shift

    def _take_look(self, cr, k):
        """Crossing k's look-back (:meth:`_look`), kept for its row, where it has none and every value it
        reads after the event has been searched."""
        key = _look_key(cr, k)
        if key not in self._looks and self._value_index(cr, k) + self._ahead < self.search.nvalues:
            self._looks[key] = self._look(cr, k)

    def _look(self, cr, k):
        """What crossing k's candidate row reads from the search's history: the light curve's values
        (host float64), the window statistics at the event's first and last image (host (mean, sigma), each
        (npix,); None where not held), the boxcar image (npix,) or None, and the DM between the trials
        (``refine_dm``; NaN for a sky-wide crossing, which keeps its trial)."""
        s = self.search
        ser, p, w = int(cr.series[k]), int(cr.pixel[k]), self.widths[int(cr.width_index[k])]
        n_e = self._value_index(cr, k)
        look = {"values": s.series_values(ser, p, n_e - self.lc_before, n_e + self.lc_after),
                "window": s.window_statistics(ser, n_e), "dm": float("nan"), "box": None, "box_window": None}
        if s.average and not cr.skywide[k]:
            look["dm"] = s.refine_dm(ser, p, n_e)
        if not cr.skywide[k]:
            n_end = n_e + w - 1
            look["box_window"] = s.window_statistics(ser, n_end) if n_end != n_e else look["window"]
            look["box"] = s.box_image(ser, n_end, w)
        return look

    def _sidelobe_of(self, cr, k, nmembers):
        """Fold point candidate k into a brighter point row at (nearly) the same time whose sidelobe it
        can be: its S/N no more than ``sidelobe_factor`` times what the brighter one puts at its pixel.

        What the brighter one puts there is its fitted point source (:meth:`_fitted`) seen through the
        array's beam, in this pixel's noise; where that row's images were no longer held, the beam
        from that row's pixel centre and the ratio of the two pixels' window sigmas stand for it.
        True if folded (that row's ``nsidelobes`` and ``nmembers`` grow)."""
        if self._dm_sidelobe_of(cr, k, nmembers):
            return True
        beam = self._array_beam() if self.sidelobe_factor and self._beam_ants else None
        if beam is None:
            return False
        e, q, snr = int(cr.image[k]), int(cr.pixel[k]), float(cr.snr[k])
        span = self._tlink + self.search.wmax
        lm = self.lay["lm"]
        sigma_q = float(self._sigma[cr.series[k], q])
        for r in sorted(self._recent, key=lambda r: -r["snr"]):
            p, snr_p = r["pixel"], r["snr"]
            if snr_p <= snr or abs(r["image"] - e) > span or p == q:
                continue
            model = self._fitted(r)
            if model is not None:
                expect = float(model[q])
            elif sigma_q > 0:
                # the beam from that row's pixel centre: flux ratio = beam there over beam at the
                # centre (the antenna pattern differs), S/N scales as 1 / sigma (pixels near bright
                # sources are noisier)
                b = beam.at(lm[p:p + 1])[0]
                expect = snr_p * b[q] / b[p] * r["sigma"] / sigma_q if b[p] > 0 else 0.0
            else:
                continue
            if snr <= self.sidelobe_factor * expect:
                self.rows[r["row"]]["nsidelobes"] += 1
                self.rows[r["row"]]["nmembers"] += nmembers
                self.search_stats["sidelobes_folded"] += 1
                log.debug("candidate at image %d, pixel %d, S/N %.1f folded into the S/N %.1f one at pixel %d "
                          "(which puts S/N %.1f here)", e, q, snr, snr_p, p, expect)
                return True
        return False

    def _dm_sidelobe_of(self, cr, k, nmembers):
        """Fold point candidate k into a brighter point row at (nearly) the same place whose DM sidelobe
        it can be: another trial's sweep that crosses the burst's inside the band collects the channels
        where the two meet (a bright burst's "bow tie" in DM and time; at the whole band's S/N 370, S/N
        8-9 up to 0.25 s before it, measured). Its S/N no more than ``sidelobe_factor`` times what
        :func:`~bf_epic_blocks.search.dm_sidelobe_snr` says the burst puts there: folded
        (that row's ``nsidelobes`` and ``nmembers`` grow). Only where the search dedisperses."""
        s = self.search
        if not (self.sidelobe_factor and s.average and len(s.dms) > 1):
            return False
        e, q, snr = int(cr.image[k]), int(cr.pixel[k]), float(cr.snr[k])
        dm, w = float(s.dms[cr.series[k]]), int(self.widths[cr.width_index[k]])
        span = s.shift + self._tlink + s.wmax                 # the sweeps can only meet this close in time
        for r in sorted(self._recent, key=lambda r: -r["snr"]):
            if r["snr"] <= snr or abs(r["image"] - e) > span or r["dm"] == dm:
                continue
            if np.hypot(*(self._xy[r["pixel"]] - self._xy[q])) > self._space:
                continue
            expect = dm_sidelobe_snr(self.lay["freq_hz"], self.lay["dt_s"],
                                     (r["image"], r["dm"], r["width"], r["snr"]), (e, dm, w))
            if snr <= self.sidelobe_factor * expect:
                self.rows[r["row"]]["nsidelobes"] += 1
                self.rows[r["row"]]["nmembers"] += nmembers
                self.search_stats["sidelobes_folded"] += 1
                log.debug("candidate at image %d, pixel %d, DM %.4g, S/N %.1f folded into the S/N %.1f one at "
                          "image %d, DM %.4g (its DM sidelobe: S/N %.1f here)", e, q, dm, snr, r["snr"], r["image"],
                          r["dm"], expect)
                return True
        return False

    def _array_beam(self):
        """The :class:`~bf_epic_blocks.search.ArrayBeam` of the searched product on the
        searched pixels (the header's station, flags and antenna pattern), or None where the product
        is not a power the beam describes (Q, U, V, cross-hands)."""
        if self._beam is None:
            self._beam = self.beam_on(self.lay["lm"]) or False
        return self._beam or None

    def beam_on(self, lm):
        """The :class:`~bf_epic_blocks.search.ArrayBeam` of the searched product on the pixels
        ``lm`` (npix, 2), or None where the product is not a power the beam describes or the header
        has no antennas."""
        from ..imaging import patterns
        prod = self.lay["products"][self._prod]
        npol = len(self._beam_ants)
        w = {"I": [1.0] * npol, "XX": [1.0] + [0.0] * (npol - 1), "YY": [0.0, 1.0][:npol]}.get(prod)
        if not npol or w is None or not any(w):
            return None
        lm = np.asarray(lm, np.float64).reshape(-1, 2)
        pp, name = None, (self.hdr.get("imager") or {}).get("pattern")
        if name:
            try:
                b = patterns.pattern_array(name, lm, self.lay["freq_hz"], npol)
                b = np.abs(_compat.to_numpy(b)) ** 2                  # (nchan|1, npix, nant|1, npol|1)
                b = np.broadcast_to(b.mean(axis=(0, 2)), (len(lm), npol))
                pp = (b * np.asarray(w)[None]).sum(axis=1) / sum(w)
            except (ValueError, TypeError) as exc:
                log.warning("TransientSearchBlock: antenna pattern %r not known here (%s); the sidelobe "
                            "test takes it as 1", name, exc)
        return ArrayBeam(self._beam_ants, w, self.lay["freq_hz"], lm, pattern_power=pp,
                         remove_autocorr=self._autocorr_removed)

    def _fitted(self, r):
        """The S/N (npix,) that recent point row ``r``'s event puts at every pixel: the point source
        that best explains its S/N image through the array's beam (:func:`locate_point_source`, within a
        cell of its pixel: on a grid coarser than the beam a source between pixels shows in its nearest
        one at a fraction of its peak, and its sidelobes elsewhere at many times that fraction). None
        if its images were no longer held."""
        if r["row"] not in self._fits:
            model = None
            beam = self._array_beam() if r["snr_image"] is not None else None
            if beam is not None:
                lm_fit, model, explained = locate_point_source(r["snr_image"], r["sigma_image"], beam,
                                                               self.lay["lm"][r["pixel"]], self._cell)
                # the fitted source itself (position, amplitude in flux units), for what it puts on
                # pixels this search does not hold: a pixel split's other parts (SearchParts)
                p = r["pixel"]
                b = float(beam.at(np.asarray(lm_fit).reshape(1, 2))[0, p])
                sg = float(_compat.to_numpy(r["sigma_image"])[p])
                if b > 0 and model[p] > 0:
                    self.rows[r["row"]]["_fit"] = (float(lm_fit[0]), float(lm_fit[1]), float(model[p]) * sg / b)
                log.debug("row %d: point source fitted at l %.4f m %.4f (pixel %d at %s), explains %.0f%% of its "
                          "S/N image", r["row"], lm_fit[0], lm_fit[1], r["pixel"], self.lay["lm"][r["pixel"]],
                          100 * explained)
            self._fits[r["row"]] = model
        return self._fits[r["row"]]

    def _add_candidate(self, cr, k, nmembers, sky_fraction):
        from ..io.tbf import time_tag_to_time
        from ..sky.catalogue import lm_to_icrs
        lay, s = self.lay, self.search
        e, ser, wi, p = int(cr.image[k]), int(cr.series[k]), int(cr.width_index[k]), int(cr.pixel[k])
        t = time_tag_to_time(lay["time_tag"] + e * lay["integration_ticks"])
        l, m = (float(v) for v in lay["lm"][p])
        ra = dec = float("nan")
        if self.loc is not None:
            r, d = lm_to_icrs([[l, m]], t, self.loc)
            ra, dec = float(r[0]), float(d[0])
        w = self.widths[wi]
        look = self._looks.pop(_look_key(cr, k), None) or self._look(cr, k)
        vals = look["values"]
        # against the window the event was found with (a later one holds the event and overstates sigma)
        ws = look["window"]
        if ws is not None:
            mean, sigma = float(ws[0][p]), float(ws[1][p])
        else:
            mean, sigma = (float(_compat.to_numpy(a[ser, p])) for a in s.statistics())
        lc = (vals - mean) / sigma if sigma > 0 else vals * np.nan
        # between trials (a burst wider than an image fills the boxcar over a range of them); a sky-wide
        # event keeps its trial
        trial = float(s.dms[ser]) if s.average else 0.0
        dm = look["dm"] if s.average and not cr.skywide[k] and np.isfinite(look["dm"]) else trial
        grid = lay["grid"]
        gx, gy = (int(lay["pixel_index"][p] % grid.size), int(lay["pixel_index"][p] // grid.size)) if grid else (-1, -1)
        self.rows.append({"time_utc": t, "sequence": str(self.hdr.get("name", "")), "image": e, "pixel": p,
                          "grid_x": gx, "grid_y": gy, "l": l, "m": m, "ra_deg": ra, "dec_deg": dec,
                          "snr": float(cr.snr[k]), "dm": dm, "dm_trial": trial,
                          "channel": -1 if s.average else ser, "width": w, "width_ms": w * lay["dt_s"] * 1e3,
                          "nmembers": nmembers, "nsidelobes": 0, "kind": "sky-wide" if cr.skywide[k] else "point",
                          "sky_fraction": sky_fraction, "lightcurve": lc,
                          # (not a column: the window sigma at its pixel, for merging a pixel split's parts)
                          "_sigma": float(self._sigma[ser, p]) if self._sigma is not None else float("nan")})
        self.search_stats["candidates"] += 1
        if self.on_candidate is not None:
            try:
                self.on_candidate(self.rows[-1])
            except Exception as e:  # noqa: BLE001 - a listener must not stop the search
                log.warning("TransientSearchBlock: the candidate listener failed: %s", e)
        if not cr.skywide[k]:
            # kept for the sidelobe test of fainter candidates at the same time: the event's boxcar S/N
            # on every pixel, against the window it was found with (None once no longer held)
            ws, box = look["box_window"], look["box"]
            img = None
            if ws is not None and box is not None:
                with np.errstate(divide="ignore", invalid="ignore"):
                    img = (box - ws[0]) * np.sqrt(w) / ws[1]
            self._recent.append({"image": e, "pixel": p, "snr": float(cr.snr[k]), "row": len(self.rows) - 1,
                                 "dm": trial, "width": w,
                                 "sigma": float(self._sigma[ser, p]) if self._sigma is not None else float("nan"),
                                 "snr_image": img, "sigma_image": None if ws is None else ws[1]})
            if self.fit_every_row and self.sidelobe_factor:
                self._fitted(self._recent[-1])    # (its "_fit": for a pixel split's merge)
        if cr.skywide[k]:
            self.search_stats["sky_wide"] += 1
            log.warning("sky-wide event: %s UTC, peak S/N %.1f at l %.3f m %.3f, %.0f%% of the sky over the "
                        "threshold (lightning, RFI or a flash?), DM %g, width %d", t.isot, cr.snr[k], l, m,
                        100 * sky_fraction, self.rows[-1]["dm"], w)
            return
        log.info("transient candidate: %s UTC, S/N %.1f, DM %g, width %d, l %.3f m %.3f, RA %.2f Dec %.2f",
                 t.isot, cr.snr[k], self.rows[-1]["dm"], w, l, m, ra, dec)

    def meta(self):
        """The candidate table's metadata (the search's settings and its trial counts)."""
        lay = self.lay
        return {"threshold": self.threshold, "window_s": self.settings.window_s, "window_images": self.search.window,
                "dms": self.dms, "dedisperse": self.search.dedisperse, "widths": self.widths, "dt_s": lay["dt_s"],
                "f_ref_mhz": float(lay["freq_hz"].max() / 1e6),
                "average_channels": self.settings.average_channels, "product": lay["products"][self._prod],
                "lightcurve_first": -self.lc_before, "trials_per_width": list(self.search_stats["trials_per_width"]),
                "time_reference": "event start at the highest channel frequency (f_ref_mhz)"}

    def _write(self):
        """Every candidate so far as one table (``candidates``), handed to the writer."""
        from ..io.candidates import candidate_table
        self.candidates = candidate_table(self.rows, self.meta(), lc_length=self.lc_before + self.lc_after + 1)
        mean, _ = self.search.statistics()
        self._sky = _compat.to_numpy(mean[0])
        if self.writer is not None:
            self.writer.write(self.candidates, self._sky, grid=self.lay["grid"], lm=self.lay["lm"])


def _look_key(cr, k):
    """Crossing k of ``cr`` by what names it across calls (the pending crossings are re-clustered each)."""
    return int(cr.end_image[k]), int(cr.series[k]), int(cr.width_index[k]), int(cr.pixel[k])


def transient_search(iring, *args, **kwargs):
    """Factory for :class:`TransientSearchBlock`."""
    return TransientSearchBlock(iring, *args, **kwargs)
