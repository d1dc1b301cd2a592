"""ImageWriterBlock: image sequences to FITS / pixel tables / PNG quicklooks on disk.

A sink for the imagers' output (docs/HEADERS.md): grids become FITS cubes with a zenith-centred SIN
WCS (one file per integration; channels with uneven spacing are split into runs of even spacing)
and an all-sky PNG of the channel-mean of the first product; pixel lists and tracked patches
become pixel tables (FITS binary tables) and a small PNG of the patch. The writing itself lives
in :mod:`bf_epic_blocks.io.fits` and :mod:`bf_epic_blocks.io.quicklook`.

With ``processes=1`` the grid files are written by a helper process: astropy's FITS, WCS and
coordinate work is several milliseconds of interpreter time per image, and in the block's own
thread it holds the interpreter lock that a GPU pipeline's source and imager threads need between
their CUDA calls (`bf-epic run` uses the helper on a GPU).
"""
from __future__ import annotations

import logging
import os
import sys
import time
import warnings
from collections import deque
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from ..conventions import FS_HZ
from ._compat import bfp, span_array, to_numpy

log = logging.getLogger(__name__)


def channel_runs(freq_hz):
    """Index runs [(start, stop)] over which the channel spacing is constant (a FITS FREQ axis each).

    These are the channel blocks the writer puts in separate files (``_r<index>`` when more than one).
    """
    f = np.asarray(freq_hz, dtype=np.float64)
    runs, start = [], 0
    while start < len(f):
        stop = start + 1
        if stop < len(f):
            step = f[stop] - f[start]
            while stop < len(f) and np.isclose(f[stop] - f[stop - 1], step, rtol=1e-9, atol=1e-3):
                stop += 1
        runs.append((start, stop))
        start = stop
    return runs


_even_runs = channel_runs


class ImageWriterBlock(bfp.SinkBlock):
    """Write each output frame (one integration) of an imager.

    outdir, prefix : where and under which name; fits / png / table : what to write.
    location : astropy EarthLocation of the station (default: from the header's station lat/lon).
    label_sources : catalogue sources (plus the Sun) drawn on the PNGs when above the horizon.
    pixels_fn : for tracked patches, the imager's ``pixels(time_tag)`` function, so each pixel
                table carries the directions of its own integration (the header has the first).
    run_index : when the input holds only channel block ``run_index`` of a larger channel set (see
                :func:`channel_runs`), name its files ``_r<run_index>`` as the whole set's would be.
    processes : 0 (write in the block's thread) or 1: grid images (FITS and PNG) are written, in order,
                by a helper process (spawned when the block is made, so its imports overlap the
                pipeline's start); at most ``MAX_PENDING`` integrations wait for it, and each sequence's
                files are all written when the sequence ends. Call :meth:`close` when the pipeline is done.
    ``written`` lists the files written (the newest ``KEEP_PATHS``; ``nwritten`` counts all). Each file
    records, as NONFINIT, the non-finite voltage samples zeroed upstream in its integration (from the tally
    the header's ``nonfinite`` names; 0 without one), and after interference flagging, as FLAGFRAC, the fraction of its stand-samples flagged (from the
    tally the header's ``flagging`` names, by gulp).
    """

    #: paths kept in ``written``: the newest this many (of ``nwritten``)
    KEEP_PATHS = 10000
    #: integrations handed to the helper process and not yet written, at most
    MAX_PENDING = 32

    def __init__(self, iring, outdir, prefix="image", fits=True, png=True, table=False, location=None,
                 label_sources=True, pixels_fn=None, *args, run_index=None, processes=0, **kwargs):
        if isinstance(processes, bool) or processes not in (0, 1):
            raise ValueError(f"ImageWriterBlock: processes must be 0 or 1, got {processes!r}")
        super().__init__(iring, *args, **kwargs)
        self.outdir, self.prefix = str(outdir), prefix
        self.do_fits, self.do_png, self.do_table = fits, png, table
        self.location, self.label_sources, self.pixels_fn = location, label_sources, pixels_fn
        self.run_index = run_index
        self.written = []
        self.nwritten = 0         # files written, all of them (``written`` keeps the newest KEEP_PATHS)
        self.frames = 0
        self._pool, self._ready, self._pending = None, None, deque()
        self._held = deque()      # integrations waiting for a helper that is still starting
        self.helper_files = 0     # of ``written``, the files the helper process wrote
        if processes:
            # one started ahead by start_helper (bf-epic run does, as soon as it has read the YAML), or a new one
            try:
                self._pool, self._ready = _STARTED.pop(0) if _STARTED else _new_helper(png)
            except Exception as e:  # noqa: BLE001 - e.g. inside a daemonic process (a Dask worker), which may not fork
                log.warning("ImageWriterBlock: no helper process (%s: %s); images are written in the writer's "
                            "thread", type(e).__name__, e)

    def _record(self, paths):
        """Note files written. A service writes one every few seconds for weeks: ``written`` keeps the newest
        KEEP_PATHS (trimmed at twice that), ``nwritten`` counts them all."""
        self.written += paths
        self.nwritten += len(paths)
        if len(self.written) > 2 * self.KEEP_PATHS:
            del self.written[:-self.KEEP_PATHS]

    def _write_here(self, stem, fn, job):
        try:
            self._record(fn(job))
        except Exception as e:
            raise RuntimeError(f"ImageWriterBlock: writing {stem} failed: {type(e).__name__}: {e}") from e

    def _helper_up(self):
        """True once the helper process has started (and from then on); False while it is still starting,
        or when it could not start (a script that spawns it without a ``__main__`` guard, a crash): its
        images are then written here, with a warning -- not lost."""
        if self._pool is None:
            return False
        if self._ready is not None:
            if not self._ready.done():
                return False
            try:
                self._ready.result()
            except Exception as e:  # noqa: BLE001 - BrokenProcessPool, or the initializer's own error
                log.warning("ImageWriterBlock: the helper process could not start (%s: %s); images are written "
                            "in the writer's thread", type(e).__name__, e)
                self.close()
                return False
            self._ready = None
            log.debug("ImageWriterBlock: helper process up, %.2f s after it was started", _since_start(self._pool))
        return True

    def _hand_over(self, stem, fn, job):
        """Write ``fn(job)`` -> paths: queued for the helper process, in order. While the helper is still
        starting, integrations are held (not written in this thread while the pipeline runs: that holds
        the interpreter lock the source and imager threads need, for a long time per image while
        astropy's modules are still to be imported) and handed over once it is up, or written at the sequence's end
        (:meth:`flush`); beyond ``MAX_PENDING`` held, the oldest is written here. Without a helper (none
        asked for, or it could not start) everything is written here."""
        if self._pool is None:
            self._write_here(stem, fn, job)
            return
        # the frame is a view of the span, which the ring reuses once on_data returns; the helper's
        # pickling happens later, on the pool's own thread
        self._held.append((stem, fn, dict(job, frame=np.array(job["frame"]))))
        if self._pending or self._helper_up():
            self._submit_held()
        elif self._pool is None:          # the helper could not start: write here
            self._write_held()
        elif len(self._held) > self.MAX_PENDING:
            s, f, j = self._held.popleft()
            self._write_here(s, f, j)

    def _write_held(self):
        while self._held:
            s, f, j = self._held.popleft()
            self._write_here(s, f, j)

    def _submit_held(self):
        """Hand every held integration to the helper, oldest first (at most ``MAX_PENDING`` in flight)."""
        while self._held:
            stem, fn, job = self._held.popleft()
            while len(self._pending) >= self.MAX_PENDING:
                self._collect(self._pending[0])
            if self._pool is None:        # lost while collecting: _helper_lost wrote what was queued
                self._write_here(stem, fn, job)
                continue
            try:
                fut = self._pool.submit(fn, job)
            except BrokenProcessPool as e:
                self._pending.append((stem, None, fn, job))
                self._helper_lost(e, stem)
                continue
            self._pending.append((stem, fut, fn, job))
        while self._pending and self._pending[0][1].done():
            self._collect(self._pending[0])

    def _collect(self, item):
        """The oldest queued integration: its paths from the helper, or its error."""
        stem, fut, fn, job = item
        try:
            paths = fut.result()
        except BrokenProcessPool as e:
            self._helper_lost(e, stem)
            return
        except Exception as e:
            self._pending.popleft()
            self.close()
            raise RuntimeError(f"ImageWriterBlock: writing {stem} failed in the helper process: "
                               f"{type(e).__name__}: {e}") from e
        self._pending.popleft()
        self._record(paths or [])
        self.helper_files += len(paths or [])

    def _helper_lost(self, err, stem):
        """A helper that died is not a lost image: every integration still queued (from ``stem`` on) is
        written here, and so is every later one, with a warning."""
        log.warning("ImageWriterBlock: the helper process ended (%s); images are written in this thread "
                    "from %s on", err, stem)
        self.close()
        while self._pending:
            s, _, fn, job = self._pending.popleft()
            self._write_here(s, fn, job)

    #: at a sequence's end, seconds to wait for a helper still starting when writing here would first
    #: have to import astropy (its start takes a few seconds from the run's launch, and overlaps it)
    HELPER_WAIT_S = 5.0

    def flush(self):
        """Every integration of the sequence written by the time this returns. Those held for a helper
        that is still starting: where this process has astropy's FITS and WCS already (a simulated
        sky's run), written here, oldest first, until the helper is up (then it takes the rest: the
        sequence's data is done, so this thread no longer competes with the source and imager); where
        it has not, writing here would first import them (about a second, more than what is left of
        the helper's start), so the helper is waited for, at most ``HELPER_WAIT_S``."""
        if self._held and self._ready is not None and self._pool is not None and not self._pending \
                and not _fits_loaded():
            try:
                self._ready.result(timeout=self.HELPER_WAIT_S)
            except Exception:  # noqa: BLE001 - still starting (TimeoutError) or failed: _helper_up says which
                pass
        while self._held:
            if self._pool is not None and (self._pending or self._helper_up()):
                self._submit_held()
                break
            s, f, j = self._held.popleft()
            self._write_here(s, f, j)
        while self._pending:
            self._collect(self._pending[0])

    def close(self):
        """Stop the helper process (after :meth:`flush`, or at once after an error) and wait for it to
        end: a helper left running when this process ends would never be told to stop, and would hold
        this process's output streams open (a caller reading them to the end would wait for ever). One
        still starting is stopped at once. Idempotent."""
        pool, self._pool = self._pool, None
        ready, self._ready = self._ready, None
        if pool is not None:
            _stop(pool, starting=ready is not None and not ready.done())

    def on_sequence_end(self, iseq):
        self.flush()

    def on_sequence(self, iseq):
        hdr = iseq.header
        self.hdr = hdr
        os.makedirs(self.outdir, exist_ok=True)
        st = hdr.get("station", {})
        loc = self.location
        if loc is None and "lat_deg" in st:
            # (lon_deg, lat_deg, height_m): what io.fits and sky take as a place (as_location), and what
            # crosses to the helper process without astropy being imported here
            loc = (float(st["lon_deg"]), float(st["lat_deg"]), float(st.get("elev_m", 0.0)))
        if loc is None:
            raise ValueError("ImageWriterBlock: no station location: give location= or a header station with lat/lon")
        self.loc = loc
        self.freq = np.asarray(hdr.get("freq_hz"), dtype=np.float64)
        self.products = list(hdr["pol_products"])
        pix = hdr["pixels"]
        self.grid = None
        if pix["kind"] == "grid":
            from ..imaging.pixels import lm_grid
            self.grid = lm_grid(pix["size"], cell=pix["cell"])
        self.int_ticks = int(hdr["imager"]["integration_ticks"])
        from .nonfinite import get_tally
        from .rfi_flag import get_flag_tally
        self.tally = get_tally(hdr)
        self.flag_tally = get_flag_tally(hdr)
        self.acc = int(hdr["imager"].get("accumulate_frames", 1))
        self.seq_index = getattr(self, "seq_index", -1) + 1
        self.frames_in_seq = 0

    def _time(self, j):
        from ..io.tbf import time_tag_to_time
        return time_tag_to_time(int(self.hdr["time_tag"]) + j * self.int_ticks)

    def on_data(self, ispan):
        from ..io import fits as fits_out
        data = to_numpy(span_array(ispan))
        imager = self.hdr["imager"]
        common = dict(method=f"{imager['kind']}:{imager['method']}", precision=imager["precision"],
                      telescope=self.hdr.get("station", {}).get("name"),
                      int_time_s=self.int_ticks / FS_HZ, nantenna=imager.get("nant_used"))
        for k in range(data.shape[0]):
            j = self.frames_in_seq
            stem = os.path.join(self.outdir, f"{self.prefix}_s{self.seq_index:02d}_i{j:04d}")
            frame = data[k]
            common["nonfinite"] = self.tally.count(j * self.acc, (j + 1) * self.acc) if self.tally else 0
            if self.flag_tally is not None:
                fpi = max(1, self.int_ticks // self.flag_tally.ticks_per_frame)    # frames in this image
                frac = self.flag_tally.fraction(j * fpi, (j + 1) * fpi)
                if frac is not None:
                    common["extra_header"] = {"FLAGFRAC": (round(frac, 6), "stand-samples flagged (interference)")}
            if self.grid is not None:
                runs = _even_runs(self.freq)
                width = float(self.freq[1] - self.freq[0]) if len(self.freq) > 1 else None
                if self.run_index is not None:  # one block of a larger set: name and width as in the set
                    if len(runs) != 1:
                        raise ValueError(f"ImageWriterBlock: run_index={self.run_index} given, but the channels "
                                         f"are {len(runs)} runs of even spacing, not one")
                    if width is None:
                        width = self.hdr.get("chan_bw_hz")
                stems = [(stem if len(runs) == 1 and self.run_index is None
                          else f"{stem}_r{r if self.run_index is None else self.run_index}", a, b)
                         for r, (a, b) in enumerate(runs)]
                job = dict(frame=np.array(frame), runs=stems, grid=self.grid, freq=self.freq, products=self.products,
                           loc=self.loc, time_tag0=int(self.hdr["time_tag"]), int_ticks=self.int_ticks, j=j,
                           width=width, fits=self.do_fits, png=self.do_png, label_sources=self.label_sources,
                           station=self.hdr.get("station", {}).get("name", ""), common=dict(common))
                self._hand_over(stem, write_grid_integration, job)
            else:
                t = self._time(j)
                lm = np.asarray(self.hdr["pixels"]["lm"])
                if self.hdr["pixels"]["kind"] == "track" and self.pixels_fn is not None:
                    lm = np.asarray(self.pixels_fn(int(self.hdr["time_tag"]) + j * self.int_ticks))
                if self.do_table or self.do_fits:
                    self._record([fits_out.write_pixel_table(f"{stem}_pixels.fits", frame, lm, self.freq,
                                                             self.products, t, self.loc, **common)])
                if self.do_png:
                    self._record([_patch_png(f"{stem}.png", frame, lm, self.products, t)])
            self.frames_in_seq += 1
            self.frames += 1


#: integrations whose zenith pointings (a FITS image's WCS) are computed in one astropy transform: its
#: interpreter time hardly grows with the number of images, so one transform serves many
POINTING_BATCH = 64
_POINTINGS = {}


def integration_pointing(location, time_tag0, int_ticks, j):
    """(ra_deg, dec_deg, north_deg) of the zenith at the start of integration ``j`` of a sequence that
    starts at ``time_tag0`` (196 MHz ticks) with integrations of ``int_ticks``: from a batch of
    :data:`POINTING_BATCH` integrations computed together (:func:`~bf_epic_blocks.sky.zenith_pointings`)."""
    from ..io.tbf import time_tag_to_time
    from ..sky import as_location, zenith_pointings
    loc = as_location(location)
    key = (tuple(float(v.to_value("m")) for v in loc.to_geocentric()), int(time_tag0), int(int_ticks))
    j0, batch = _POINTINGS.get(key, (0, None))
    if batch is None or not j0 <= j < j0 + len(batch[0]):
        tags = int(time_tag0) + (j + np.arange(POINTING_BATCH)) * int(int_ticks)
        j0, batch = j, zenith_pointings(time_tag_to_time(tags), loc)
        if len(_POINTINGS) > 16:
            _POINTINGS.clear()
        _POINTINGS[key] = (j0, batch)
    return tuple(float(v[j - j0]) for v in batch)


def write_grid_integration(job):
    """One integration's grid files (FITS cube and/or PNG per run of evenly spaced channels); returns
    the paths. Runs in the writer's thread or in its helper process; ``job`` is what
    :meth:`ImageWriterBlock.on_data` puts together (the frame and everything needed to place it)."""
    from ..io import fits as fits_out, quicklook
    from ..io.tbf import time_tag_to_time
    frame, freq, grid, products, loc = job["frame"], job["freq"], job["grid"], job["products"], job["loc"]
    j = job["j"]
    t = time_tag_to_time(job["time_tag0"] + j * job["int_ticks"])
    written = []
    for rstem, a, b in job["runs"]:
        if job["fits"]:
            written += fits_out.write_fits_image(
                f"{rstem}.fits", frame[a:b], grid, freq[a:b], products, t, loc,
                chan_width_hz=job["width"] if b - a == 1 else None,
                pointing=integration_pointing(loc, job["time_tag0"], job["int_ticks"], j), **job["common"])
        if job["png"]:  # channel mean of the first product, one PNG per FITS file
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels below the horizon
                mean = np.nanmean(frame[a:b, 0], axis=0)
            title = (f"{job['station']} {products[0]}  {t.isot[:19]} UTC  "
                     f"{freq[a] / 1e6:.2f}-{freq[b - 1] / 1e6:.2f} MHz")
            written.append(quicklook.quicklook_png(f"{rstem}.png", mean, grid, title=title,
                                                   sources=_labels(t, loc) if job["label_sources"] else None))
    return written


def _labels(t, location):
    """Catalogue sources (and the Sun) above the horizon at ``t``: [(name, l, m)] for a quicklook."""
    from ..sky import KNOWN_SOURCES, as_location, icrs_to_lm
    loc = as_location(location)
    names, ra, dec = [], [], []
    for s in KNOWN_SOURCES.values():
        names.append(s.name)
        ra.append(s.ra_deg)
        dec.append(s.dec_deg)
    lm, alt = icrs_to_lm(np.array(ra), np.array(dec), t, loc)
    out = [(n, float(l), float(m)) for n, (l, m), a in zip(names, lm, alt) if np.isfinite(a) and a > 0]
    try:  # the Sun is near: go to AltAz directly (via ICRS would add a parallax of degrees)
        from astropy.coordinates import AltAz, get_body
        from ..station.offline import iers_table
        iers_table()
        sun = get_body("sun", t, loc).transform_to(AltAz(obstime=t, location=loc))
        if sun.alt.deg > 0:
            alt_r, az_r = sun.alt.rad, sun.az.rad
            out.append(("Sun", float(np.cos(alt_r) * np.sin(az_r)), float(np.cos(alt_r) * np.cos(az_r))))
    except Exception as e:  # decoration only
        log.debug("no Sun position: %s", e)
    return out


_STARTED = []   # helper processes started ahead, each taken by the next ImageWriterBlock(processes=1)


def _fits_loaded():
    """Whether this process has already imported what writing a FITS image here needs."""
    return "astropy.wcs" in sys.modules and "astropy.io.fits" in sys.modules


def _since_start(pool):
    t = getattr(pool, "_bf_started", None)
    return float("nan") if t is None else time.perf_counter() - t


def _new_helper(png):
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    # spawn, not fork: the parent has threads and a CUDA context
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_helper_init,
                               initargs=(bool(png),))
    pool._bf_started = time.perf_counter()
    try:
        return pool, pool.submit(_helper_ready)   # done when the helper has started and imported
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        raise


def start_helper(png=False):
    """Start an image writer's helper process now, for the next ``ImageWriterBlock(processes=1)``: its
    start (a Python with numpy and astropy, a second or more) then overlaps the parent's own."""
    _STARTED.append(_new_helper(png))


def stop_helpers():
    """Stop helper processes started ahead and not taken by a writer."""
    while _STARTED:
        pool, ready = _STARTED.pop()
        _stop(pool, starting=not ready.done())


def _stop(pool, starting):
    """Shut a helper pool down and wait for its process to end; one still starting (importing) is
    terminated rather than waited for."""
    if starting:
        for proc in list(getattr(pool, "_processes", {}).values()):   # (no public way to stop a worker)
            proc.terminate()
    try:
        pool.shutdown(wait=True, cancel_futures=True)
    except Exception as e:  # noqa: BLE001 - a terminated worker breaks the pool: nothing left to do
        log.debug("helper pool shutdown: %s", e)


def _helper_init(png):
    """The helper process: astropy and LSL kept offline as in the parent, and the imports its first
    image would otherwise wait for made at once (they overlap the pipeline's start)."""
    import atexit
    from ..station.offline import configure_offline
    configure_offline()
    # once told to stop, the helper ends without its interpreter's teardown (astropy's and NumPy's modules,
    # ~0.4 s): its files are closed by then, and its parent waits for it (ImageWriterBlock.close)
    atexit.register(os._exit, 0)
    import astropy.coordinates  # noqa: F401
    from ..io import fits  # noqa: F401  (astropy.io.fits, astropy.wcs)
    if png:
        from ..io import quicklook  # noqa: F401  (matplotlib)


def _helper_ready():
    return []


def _patch_png(path, frame, lm, products, t):
    """A small PNG of a square pixel patch (tracking), channel mean of the first product."""
    from matplotlib.figure import Figure
    n = int(round(np.sqrt(lm.shape[0])))
    vals = np.nanmean(frame[:, 0], axis=0)
    fig = Figure(figsize=(4.6, 4))
    ax = fig.add_subplot(1, 1, 1)
    if n * n == lm.shape[0]:
        im = ax.imshow(vals.reshape(n, n), origin="lower", cmap="inferno")
        ax.set_xlabel("patch x (towards East)")
        ax.set_ylabel("patch y (towards North / up)")
    else:
        im = ax.scatter(lm[:, 0], lm[:, 1], c=vals, cmap="inferno")
        ax.invert_xaxis()
        ax.set_xlabel("l (East)")
        ax.set_ylabel("m (North)")
    ax.set_title(f"{products[0]} {t.isot[:19]} UTC", fontsize=9)
    fig.colorbar(im, ax=ax, label="power (uncalibrated)")
    fig.savefig(path, dpi=90)
    return path


def image_writer(iring, outdir, *args, **kwargs):
    """Factory for :class:`ImageWriterBlock`."""
    return ImageWriterBlock(iring, outdir, *args, **kwargs)
