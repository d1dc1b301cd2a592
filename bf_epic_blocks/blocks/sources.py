"""Source blocks that put LWA E-fields on a ring: TBF and TBX file readers and a simulated sky.

Both write E-field sequences as docs/HEADERS.md defines them (labels time, freq, station, pol; the
station table, with its cable terms for the channels, in ``station``), so CalFoldBlock and the
imagers read them without knowing where they came from. Optional ``progress`` (a callable taking
the number of frames just written) lets a CLI drive a progress bar.
"""
from __future__ import annotations

import contextlib
import logging
import os
import warnings
from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..conventions import FS_HZ
from . import _compat
from ._compat import HostToDevice, assign_storage, bfp, span_array
from .headers import efield_header

log = logging.getLogger(__name__)


class _Reader(contextlib.AbstractContextManager):
    """A plain state holder; SourceBlock wants a context manager per source name."""

    def __init__(self, **state):
        self.__dict__.update(state)

    def __exit__(self, *exc):
        # reads started ahead (TBFSourceBlock._next_chunk) finish or are cancelled before their file
        # descriptor closes: a read of a closed (or reused) descriptor would be wrong, not just lost
        for _, job in getattr(self, "ahead", ()):
            for f in (job[2] if job is not None else ()):
                f.cancel()
        pool = getattr(self, "pool", None)
        if pool is not None:
            pool.shutdown(wait=True)
            self.pool = None
        if getattr(self, "fd", None) is not None:
            os.close(self.fd)
            self.fd = None
        return False


class TBFSourceBlock(bfp.SourceBlock):
    """Read LWA TBF files (ADP or NDP), one sequence per file, 'ci4' gulps (time, freq, station, pol).

    station : a :class:`~bf_epic_blocks.station.StationTable`, a station name, or None
              (the station the file's frame id names: ADP -> lwasv, NDP -> lwana).
    channels : None (all) or an index range ``(start, stop)`` into the file's channels (frequency
               order): only those channels go on the ring (a channel block, as ``bf-epic batch`` uses).
    scanned : header passes already made (``{path: scan result}``, as the runner has for planning), so a
               file's frame headers are not read twice; other files are scanned when opened.
    Missing frames are zero-filled and counted (``tbf_stats``); a truncated last frame ends the
    file cleanly with a warning; a bad sync word raises TBFError with its byte offset.
    """

    fmt = "tbf"  # the header key and name prefix; subclasses for other capture formats change it

    @staticmethod
    def _scan(path):
        from ..io.tbf import scan_tbf
        return scan_tbf(path)

    @staticmethod
    def _iter(path, gulp_nframe, info, raw=False):
        from ..io.tbf import iter_tbf_gulps
        return iter_tbf_gulps(path, gulp_nframe, info=info, raw=raw)

    def __init__(self, paths, gulp_nframe, station=None, progress=None, space="system", *args, channels=None,
                 scanned=None, **kwargs):
        paths = [paths] if isinstance(paths, (str, bytes)) or hasattr(paths, "__fspath__") else list(paths)
        super().__init__([str(p) for p in paths], gulp_nframe, space, *args, **kwargs)
        self.station, self.progress = station, progress
        self.channels = None if channels is None else slice(int(channels[0]), int(channels[1]))
        self._scanned = {os.path.abspath(str(k)): v for k, v in (scanned or {}).items()}
        self.tbf_stats = {"frames_read": 0, "frames_missing": 0, "time_gaps": 0, "truncated_bytes": 0, "samples": 0}
        self._h2d = HostToDevice()
        # raw gulps' reads fill their own staging buffers: a gathered gulp's copy must never take a
        # buffer that a read started ahead is still filling
        self._h2d_reads = HostToDevice(nstage=READ_AHEAD + 1)

    def create_reader(self, sourcename):
        info = self._scanned.pop(os.path.abspath(sourcename), None)
        if info is None:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                info = self._scan(sourcename)
            for w in caught:
                log.warning("%s", w.message)
        # on a GPU, gulps whose frames lie in the file in order are read straight into pinned memory,
        # copied down whole and stripped of their headers there (_read_raw)
        raw = _compat.space_of(self.orings[0]) == "cuda" and self.channels is None
        return _Reader(info=info, it=self._iter(sourcename, self.gulp_nframe, info, raw=raw), path=sourcename,
                       fd=os.open(sourcename, os.O_RDONLY) if raw else None)

    def _station(self, info):
        from ..station.tables import station_for_capture
        return station_for_capture(self.station, info.station_hint, info.nstand, f"{self.fmt.upper()} file's frames",
                                   f"name the right station (a {self.fmt.upper()} file from this station?)")

    def on_sequence(self, reader, sourcename):
        info = reader.info
        st = self._station(info)
        sel = reader.sel = self.channels if self.channels is not None else slice(None)
        freq = np.asarray(info.freq_hz, dtype=np.float64)[sel]
        if freq.size == 0 or (self.channels is not None and self.channels.stop > info.nchan):
            raise ValueError(f"channels {self.channels.start}:{self.channels.stop} asked for, but {self.fmt.upper()} "
                             f"file {sourcename} has {info.nchan} channels (0:{info.nchan})")
        hdr = efield_header(f"{self.fmt}:{sourcename}", int(info.time_tags[0]), freq, 1.0 / info.chan_bw_hz,
                            st.to_header(freq), dtype="ci4", npol=2, chan_bw_hz=float(info.chan_bw_hz),
                            **{self.fmt: {"path": sourcename, "engine": info.engine,
                                          "channels": [int(c) for c in info.channels[sel]]}})
        reader.expected_tag = int(info.time_tags[0])
        reader.sample_ticks = int(round(FS_HZ / info.chan_bw_hz))
        log.info(self.fmt.upper() + " %s: %s, %d stands, %d channels (%.3f-%.3f MHz), %d time samples", sourcename, info.engine,
                 info.nstand, len(freq), freq.min() / 1e6, freq.max() / 1e6, info.ntime)
        return [hdr]

    def on_data(self, reader, ospans):
        chunk, job = self._next_chunk(reader)
        if chunk is None:
            return [0]
        if job is not None:
            return [self._read_raw(reader, chunk, job, span_array(ospans[0]))]
        n = chunk.data.shape[0]
        self._count(chunk.stats, n)
        if self.tbf_stats["frames_missing"]:
            log.debug("%s: %d frames missing so far (zero-filled)", self.fmt.upper(), self.tbf_stats["frames_missing"])
        dst = span_array(ospans[0])
        _write_span(dst[:n], chunk.data[:, reader.sel], self._h2d)
        if self.progress:
            self.progress(n)
        return [n]

    def _count(self, stats, ntime):
        for k in ("frames_read", "frames_missing", "time_gaps", "truncated_bytes"):
            self.tbf_stats[k] += int(stats.get(k, 0))
        self.tbf_stats["samples"] += ntime

    def _next_chunk(self, reader):
        """The next chunk of the capture and, for a :class:`~bf_epic_blocks.io.tbf.RawGulp`, its read
        (already under way); the reads of the following ``READ_AHEAD`` raw gulps are started
        before returning, so the file is read while this gulp goes to the GPU and the imager runs."""
        from ..io.tbf import RawGulp
        ahead = reader.__dict__.setdefault("ahead", deque())
        first = ahead.popleft() if ahead else None
        while len(ahead) < READ_AHEAD and not getattr(reader, "done", False):
            try:
                chunk = next(reader.it)
            except StopIteration:
                reader.done = True
                break
            job = None
            if isinstance(chunk, RawGulp):
                buf, slot = self._h2d_reads.staging(chunk.nbytes)
                # one piece per reader thread (at least 2 MB): each piece's end takes the GIL back
                # in a reader thread, so 2-MB pieces of a 60-MB gulp cost 30 hand-offs per gulp
                piece = max(2 << 20, -(-chunk.nbytes // READ_THREADS))
                job = (buf, slot, pread_start(reader.fd, buf, chunk.offset, self._pool(reader), piece=piece))
            ahead.append((chunk, job))
        if first is None:
            first = ahead.popleft() if ahead else (None, None)
        return first

    def _read_raw(self, reader, g, job, dst):
        """A :class:`~bf_epic_blocks.io.tbf.RawGulp` into the 'cuda' span ``dst``: its bytes, read by
        threads (``os.preadv``) into a pinned staging buffer, copied to the GPU whole, headers
        stripped by one strided copy on the GPU. One host copy (the kernel's, page cache to pinned)."""
        import cupy as cp
        buf, slot, pieces = job
        pread_wait(pieces)
        self._count(g.stats, g.ntime)
        frames = getattr(self, "_raw_dev", None)
        if frames is None or frames.nbytes < g.nbytes:
            frames = self._raw_dev = cp.empty(g.nbytes, cp.uint8)
        raw = frames[:g.nbytes]
        self._h2d_reads.copy_staged(raw, buf, slot)
        with _compat.stream_context():
            out = dst[:g.ntime].reshape(g.ntime, g.nblock, -1)
            out[...] = raw.reshape(g.ntime, g.nblock, g.frame_bytes)[:, :, g.header_bytes:]
            if _compat.HAVE_BIFROST:  # pragma: no cover - Bifrost's commit does not wait for CuPy work
                cp.cuda.get_current_stream().synchronize()
        if self.progress:
            self.progress(g.ntime)
        return g.ntime

    @staticmethod
    def _pool(reader):
        if getattr(reader, "pool", None) is None:
            reader.pool = ThreadPoolExecutor(max_workers=READ_THREADS, thread_name_prefix="bf-epic-read")
        return reader.pool



#: threads reading a capture's bytes at once: one thread's copy from the page cache into pinned
#: memory is several times slower than a GPU images a wide gulp, so a gulp's parts are read in parallel
READ_THREADS = max(2, min(8, os.cpu_count() or 2))
#: raw gulps whose reads are under way ahead of the one being copied to the GPU (staging buffers:
#: READ_AHEAD + 1, each a gulp's bytes of pinned memory)
READ_AHEAD = 2


def pread_start(fd, buf, offset, pool, piece=2 << 20):
    """Start filling the uint8 array ``buf`` with the file's bytes from ``offset`` on ``pool``
    (``os.preadv``, pieces of ``piece`` bytes in parallel); returns what :func:`pread_wait` takes."""
    view = memoryview(buf).cast("B")
    n = len(view)
    return [pool.submit(_pread_piece, fd, view, offset, a, min(n, a + piece)) for a in range(0, n, piece)]


def pread_wait(pieces):
    """Wait for the reads :func:`pread_start` began; the first error (a short read) is raised."""
    for f in pieces:
        f.result()


def _pread_piece(fd, view, offset, a, b):
    got = a
    while got < b:
        k = os.preadv(fd, [view[got:b]], offset + got)
        if k <= 0:
            raise OSError(f"short read at byte {offset + got} of the capture: the file ended early")
        got += k


class TBXSourceBlock(TBFSourceBlock):
    """Read LWA TBX files (NDP transient buffer, frame id 8), one sequence per file, 'ci4' gulps.

    Same parameters, header layout and counting as :class:`TBFSourceBlock` (the counts are in
    ``tbf_stats``, also reachable as ``tbx_stats``); the header carries ``tbx`` = {path, engine,
    channels} instead of ``tbf``. With ``station=None`` the station is the NDP station with the
    file's stand count (64 -> lwana, 256 -> lwasv). Reader: :mod:`bf_epic_blocks.io.tbx`.
    """

    fmt = "tbx"

    @staticmethod
    def _scan(path):
        from ..io.tbx import scan_tbx
        return scan_tbx(path)

    @staticmethod
    def _iter(path, gulp_nframe, info, raw=False):
        from ..io.tbx import iter_tbx_gulps
        return iter_tbx_gulps(path, gulp_nframe, info=info, raw=raw)

    @property
    def tbx_stats(self):
        return self.tbf_stats


def capture_source_class(path):
    """The source block class for a capture file, by its first frame id: TBFSourceBlock or TBXSourceBlock."""
    from ..io.formats import detect_format
    return {"tbf": TBFSourceBlock, "tbx": TBXSourceBlock}[detect_format(path)]


def _write_span(dst, host, h2d, room=None):
    """Host samples (in the ring's storage form: packed ci4 bytes, ...) into span array ``dst``:
    on a GPU an asynchronous copy of the packed bytes through pinned memory (``h2d``; ``room``: bytes
    its staging buffers are made for, see :class:`~._compat.HostToDevice`)."""
    if type(dst).__module__.startswith("cupy"):
        h2d.copy(dst, host, room=room)
    else:
        assign_storage(dst, _as_storage(host, dst.dtype))


def _as_storage(packed_u8, dtype):
    """Packed ci4 bytes in the ring's storage form (structured 're_im' on the host, plain uint8 on GPU)."""
    a = np.ascontiguousarray(packed_u8)
    return a.view(dtype) if np.dtype(dtype) != a.dtype and np.dtype(dtype).itemsize == 1 else a


class SimSkySourceBlock(bfp.SourceBlock):
    """Simulated LWA voltages for a sky of point sources plus receiver noise (one sequence).

    station : StationTable (positions, cable terms and flags come from it; the simulated cables
              delay and scale the voltages exactly as the data model says).
    freq_hz : channel centres; ``start`` : astropy Time (or ISO string); ``duration_s`` : length.
    sources, noise_power, seed : as :func:`bf_epic_blocks.sky.simulate_efield`. The samples are made
              by :mod:`bf_epic_blocks.sky.fastsim` where the ring lives (one CUDA kernel per gulp
              on a GPU, its NumPy twin on the host): every sample is a function of the seed, its
              place and the number of sky columns, so runs repeat exactly whatever the gulp size, and
              GPU and CPU give the same data. (A source's counter counts the columns: adding a burst,
              even one that starts later, gives the steady sources other signals; the noise stays.)
    quantize : True writes 'ci4' scaled like an F-engine (rms 2 units, from the model's expected
              power), False writes 'cf32'.
    transients : dispersed bursts, ``[{ra_deg, dec_deg, start_s, duration_s, flux_jy, dm}]`` with
              ``start_s`` seconds after ``start`` (at the highest channel; see sky.efield).
    refresh_s : seconds of data between recomputations of the source directions (the sky turns
              0.004 deg in a second); the true gains' drift is applied piecewise constant over it.
    pattern : None (isotropic antennas) or a voltage pattern name of :mod:`..imaging.patterns`
              ("dipole"): B_p(l, m) multiplies every source's and burst's amplitude per pol, and
              weights the diffuse sky.
    diffuse : None (off) or a mapping ``{scale, nmode}`` (defaults 1.0, 32): the diffuse Galactic
              emission as ``nmode`` eigenmode columns (:func:`bf_epic_blocks.sky.diffuse.diffuse_weights`),
              recomputed every ``diffuse_refresh_s`` seconds of data (60: the sky turns 0.25 deg in
              a minute, under a quarter of the grid's cell; each computation costs ~1 s of CPU).
    corrupt : None or a :class:`~bf_epic_blocks.sky.corrupt.GainCorruption` (or its YAML mapping):
              true gains on the sky columns, deaf and noisy inputs (the deaf and noisy ones picked
              among the station's unflagged inputs). :meth:`true_gains` and :meth:`truth` give what
              was applied.

    The weights at each refresh: the steady sources (x pattern), then the diffuse modes, both times
    the true gains at that time and the cable factor, then one column per noisy input, then the
    bursts. The 4-bit scale comes from the expected rms of all of them at the start. With none of
    pattern, diffuse and corrupt the samples are those of a block without them, bit for bit.
    """

    def __init__(self, station, freq_hz, start, duration_s, sources, gulp_nframe, noise_power=1000.0, seed=1,
                 quantize=True, cable=True, progress=None, space="system", transients=None, *args, refresh_s=1.0,
                 pattern=None, diffuse=None, corrupt=None, diffuse_refresh_s=60.0, **kwargs):
        super().__init__(["simulated-sky"], gulp_nframe, space, *args, **kwargs)
        from astropy.time import Time

        from ..sky.efield import check_transient
        self.station, self.freq_hz = station, np.asarray(freq_hz, dtype=np.float64)
        self.start = Time(start, scale="utc")
        width = abs(self.freq_hz[1] - self.freq_hz[0]) if len(self.freq_hz) > 1 else 25e3
        self.dt_s = 1.0 / width
        self.nframe = int(round(duration_s / self.dt_s))
        if self.nframe < 1:
            raise ValueError(f"duration_s={duration_s} is shorter than one sample ({self.dt_s} s)")
        self.sources, self.noise_power, self.seed = sources, float(noise_power), int(seed)
        self.quantize, self.cable, self.progress = quantize, cable, progress
        self.scale = None
        self.transients = list(transients or [])
        self._bursts = [check_transient(i, tr) for i, tr in enumerate(self.transients)]
        self.refresh_frames = max(1, int(round(float(refresh_s) / self.dt_s)))
        self.pattern = None if pattern in (None, "none") else pattern
        if self.pattern is not None and isinstance(self.pattern, str):
            from ..imaging.patterns import get_pattern
            get_pattern(self.pattern)   # an unknown name fails here, not at the first gulp
        self.diffuse = _diffuse_settings(diffuse)
        self.diffuse_refresh_s = float(diffuse_refresh_s)
        if corrupt is not None and not hasattr(corrupt, "gains"):
            from ..sky.corrupt import GainCorruption
            corrupt = GainCorruption.from_config(corrupt, seed=self.seed)
        self.corrupt = corrupt
        self._refreshes = []
        self._noisy_w = self._diffuse_w = self.diffuse_fraction = self.median_power = None
        self._h2d = HostToDevice()

    def create_reader(self, sourcename):
        return _Reader(pos=0)

    def on_sequence(self, reader, sourcename):
        from ..sky import fastsim
        st = self.station
        self.time_tag0 = int(round(self.start.unix * FS_HZ))
        hdr = efield_header("simulated-sky", self.time_tag0, self.freq_hz, self.dt_s, st.to_header(self.freq_hz),
                            dtype="ci4" if self.quantize else "cf32", npol=2, t0_s=float(self.start.unix),
                            simulation={"sources": [str(s) if not isinstance(s, dict) else s.get("name", "custom")
                                                    for s in self.sources],
                                        "noise_power": self.noise_power, "seed": self.seed, "start": self.start.isot,
                                        "transients": self.transients, "generator": "counter (sky.fastsim)",
                                        "pattern": self.pattern if isinstance(self.pattern, str) or self.pattern is None
                                        else getattr(self.pattern, "__name__", "custom"),
                                        "diffuse": None if self.diffuse is None else
                                        {**self.diffuse, "refresh_s": self.diffuse_refresh_s},
                                        "corrupt": None if self.corrupt is None else self.corrupt.to_dict()})
        self._dir_cache = {}
        d = self._directions(0)[0]          # the first refresh's, at the start
        log.info("simulated sky at %s UTC: %s above the horizon%s", self.start.isot[:19],
                 ", ".join(f"{n} (alt {np.degrees(a):.1f} deg)" for n, a in zip(d.names, d.alt)) or "no source",
                 f"; below: {', '.join(d.dropped)}" if d.dropped else "")
        self._cable = None
        if self.cable:
            from ..sky.efield import cable_factor
            self._cable = cable_factor(np.moveaxis(st.cable_delay_s(self.freq_hz), -1, 0),
                                       np.moveaxis(st.cable_gain(self.freq_hz), -1, 0), self.freq_hz,
                                       len(self.freq_hz), st.nstand, 2)
        self._keys = fastsim.stream_keys(self.seed)
        self._xp = self._gen_namespace()
        self._w_at = None
        self._refreshes = []
        self._diffuse_w, self._diffuse_at, self.diffuse_fraction = None, None, None
        usable = ~np.asarray(st.flags, bool)
        self._usable = usable
        self._noisy_w = None
        if self.corrupt is not None:
            nd = self.corrupt.deaf_mask(st.nstand, 2, usable=usable)
            nn = self.corrupt.noisy_mask(st.nstand, 2, usable=usable)
            log.info("simulated corruptions: gains (amplitude rms %.2f, delay rms %.1f ns%s), %d deaf and %d noisy "
                     "inputs", self.corrupt.amplitude_rms, self.corrupt.delay_ns_rms,
                     ", random phases" if self.corrupt.random_phase else "", nd.sum(), nn.sum())
            if nn.any():
                # the median input's total power (sky through gains and cables, plus receiver noise)
                # over the unflagged inputs that are neither deaf nor noisy, at the start
                self._weights(0)
                p = self.noise_power + 2.0 * np.sum(np.abs(self._w_steady.astype(np.complex128)) ** 2, axis=1)
                sel = usable & ~nd & ~nn
                self.median_power = np.median(p[:, sel], axis=1) if sel.any() else np.full(len(self.freq_hz),
                                                                                             self.noise_power)
                self._noisy_w = self.corrupt.noisy_weights(st.nstand, 2, len(self.freq_hz), self.median_power,
                                                           usable=usable)
                self._w_at, self._refreshes = None, []
        self._weights(0)
        if self.quantize:
            self.scale = 2.0 / fastsim.expected_rms(self._w_steady, self.noise_power)
        return [hdr]

    def true_gains(self, t_s: float) -> np.ndarray:
        """The gains g (complex128 (nchan, nstand, npol)) on the sky columns of the samples at ``t_s``
        seconds after ``start``: those of the refresh in force there (evaluated at its first sample;
        refreshes fall on gulp starts, every ``refresh_s`` or at the next gulp). Ones without
        ``corrupt``; 0 for deaf inputs. Cable terms not included."""
        st = self.station
        if self.corrupt is None:
            return np.ones((len(self.freq_hz), st.nstand, 2), np.complex128)
        pos = self._refresh_start(int(np.floor(float(t_s) / self.dt_s + 1e-9)))
        return self.corrupt.gains(st.nstand, 2, self.freq_hz, pos * self.dt_s, usable=~np.asarray(st.flags, bool))

    def _refresh_start(self, sample: int) -> int:
        """The first sample of the weights' refresh that makes ``sample``: gulps start every
        ``gulp_nframe`` samples and a refresh happens at the first gulp start ``refresh_frames`` or
        more after the last (as :meth:`_weights` does)."""
        g, last = int(self.gulp_nframe), 0
        while True:
            nxt = -(-(last + self.refresh_frames) // g) * g
            if nxt > sample:
                return last
            last = nxt

    def truth(self) -> dict:
        """What a test needs to know of the simulated corruptions and sky, after ``on_sequence``:

        * ``deaf``, ``noisy``: bool (nstand, npol) masks (all False without ``corrupt``);
        * ``flags``: the station's flags (bool (nstand, npol)), the inputs the choice avoided;
        * ``median_power``: (nchan,) the median input's total power the noisy ones are scaled to
          (None without noisy inputs); ``noisy_power``: its multiple;
        * ``noise_power``: the receiver noise power; ``diffuse_fraction``: (nchan, npol) of the
          diffuse power the modes keep (None without ``diffuse``);
        * ``diffuse_weights``: complex128 (nchan, nmode, nstand, npol) last computed modes before
          gains and cables (None without diffuse): the simulated diffuse covariance is
          ``2 sum_k W W^H``;
        * ``refreshes``: [(first sample, t_s)] of the weights' refreshes made so far;
        * ``true_gains``: :meth:`true_gains`.
        """
        st = self.station
        usable = ~np.asarray(st.flags, bool)
        none = np.zeros((st.nstand, 2), bool)
        c = self.corrupt
        return {"deaf": c.deaf_mask(st.nstand, 2, usable=usable) if c else none,
                "noisy": c.noisy_mask(st.nstand, 2, usable=usable) if c else none.copy(),
                "flags": np.asarray(st.flags, bool).copy(),
                "median_power": self.median_power,
                "noisy_power": c.noisy_power if c else None, "noise_power": self.noise_power,
                "diffuse_fraction": self.diffuse_fraction, "diffuse_weights": self._diffuse_w,
                "refreshes": list(self._refreshes), "true_gains": self.true_gains}

    def _gen_namespace(self):
        """Where the samples are made: on the GPU for 'cuda' rings and for pinned 'cuda_host' rings
        (copied down), on the host otherwise."""
        if _compat.space_of(self.orings[0]) in ("cuda", "cuda_host"):
            from ..imaging._xp import cupy_or_none, gpu_available
            if gpu_available():
                return cupy_or_none()
        return np

    #: weights' refreshes whose source directions one astropy call computes: this one and those after it
    #: (a call's cost is mostly its fixed part, and it holds the interpreter the other blocks need)
    DIRECTION_BATCH = 64

    def _directions(self, pos):
        """(the sources' SourceDirections, [each burst's]) at sample ``pos``, as ``source_directions`` gives
        them: from a batch for this refresh and the next ones (every gulp-rounded ``refresh_frames``)."""
        hit = self._dir_cache.get(pos)
        if hit is None:
            from astropy.time import TimeDelta

            from ..sky.catalogue import source_directions_at
            g = int(self.gulp_nframe)
            ps = pos + (-(-self.refresh_frames // g) * g) * np.arange(self.DIRECTION_BATCH)
            t = self.start + TimeDelta(ps * self.dt_s, format="sec")
            loc = self.station.location
            steady = source_directions_at(self.sources, t, loc)
            bursts = [source_directions_at([src], t, loc) for _, _, src in self._bursts]
            self._dir_cache = {int(p): (steady[k], [b[k] for b in bursts]) for k, p in enumerate(ps)}
            hit = self._dir_cache[pos]
        return hit

    def _weights(self, pos):
        """The sky's weights and burst windows for the data from sample ``pos`` (recomputed each
        ``refresh_frames``)."""
        if self._w_at is not None and pos - self._w_at < self.refresh_frames:
            return
        from astropy.time import TimeDelta

        from ..sky import fastsim
        t = self.start + TimeDelta(pos * self.dt_s, format="sec")
        loc, f = self.station.location, self.freq_hz
        d, burst_dirs = self._directions(pos)
        flux = [s.flux_at(f) for s in d.sources]
        l, m, n = list(d.l), list(d.m), list(d.n)
        bursts = []
        for i, ((dm, dur, src), b) in enumerate(zip(self._bursts, burst_dirs)):
            if not len(b.sources):
                if self._w_at is None:
                    log.warning("transient %s is below the horizon: not simulated", src["name"])
                continue
            flux.append(b.sources[0].flux_at(f))
            l, m, n = l + [b.l[0]], m + [b.m[0]], n + [b.n[0]]
            bursts.append({"start_s": self.transients[i]["start_s"], "duration_s": dur, "dm": dm})
        flux = np.stack(flux, axis=1) if flux else np.zeros((len(f), 0))
        cable = self._cable
        t_s = pos * self.dt_s
        if self.corrupt is not None:
            g = self.corrupt.gains(self.station.nstand, 2, f, t_s, usable=self._usable)
            cable = g if cable is None else cable * g
        beam = None
        if self.pattern is not None and len(l):
            from ..imaging.patterns import pattern_array
            b = pattern_array(self.pattern, np.stack([np.array(l), np.array(m)], axis=1), f, 2)
            beam = np.broadcast_to(np.asarray(b)[:, :, 0, :], (len(f), len(l), 2))
        w = fastsim.sky_weights(self.station.xyz_m, f, np.array(l), np.array(m), np.array(n), flux, cable,
                                pattern=beam)
        nsteady = len(d.sources)
        extra = []
        if self.diffuse is not None:
            if self._diffuse_at is None or t_s - self._diffuse_at >= self.diffuse_refresh_s:
                from ..sky.diffuse import diffuse_weights
                self._diffuse_w, self.diffuse_fraction = diffuse_weights(
                    self.station.xyz_m, f, t, loc, pattern=self.pattern, scale=self.diffuse["scale"],
                    nmode=self.diffuse["nmode"], return_fraction=True)
                self._diffuse_at = t_s
            wd = self._diffuse_w if cable is None else self._diffuse_w * cable[:, None]
            extra.append(wd.astype(np.complex64))
        if self._noisy_w is not None:
            extra.append(self._noisy_w.astype(np.complex64))
        if extra:
            w = np.concatenate([w[:, :nsteady], *extra, w[:, nsteady:]], axis=1)
            nsteady += sum(e.shape[1] for e in extra)
        self._w_steady = w[:, :nsteady]
        on0, on1 = fastsim.burst_windows(nsteady, bursts, f, self.dt_s)
        xp = self._xp
        self._w, self._on0, self._on1 = xp.asarray(w), xp.asarray(on0), xp.asarray(on1)
        self._w_at = pos
        self._refreshes.append((pos, t_s))

    def on_data(self, reader, ospans):
        from ..sky import fastsim
        dst = span_array(ospans[0])
        n = min(dst.shape[0], self.nframe - reader.pos)
        if n <= 0:
            return [0]
        self._weights(reader.pos)
        xp = self._xp
        shape = (n, len(self.freq_hz), self.station.nstand, 2)
        dtype = np.uint8 if self.quantize else np.complex64
        direct = type(dst).__module__.startswith("cupy") and dst.dtype == dtype and dst[:n].flags.c_contiguous
        out = dst[:n] if direct else xp.empty(shape, dtype)
        fastsim.make_gulp(out, reader.pos, self._w, self._on0, self._on1, self._keys, self.noise_power, self.scale)
        if not direct:
            host = out.get() if xp is not np else out
            _write_span(dst[:n], host, self._h2d)
        reader.pos += n
        if self.progress:
            self.progress(n)
        return [n]


def _diffuse_settings(diffuse):
    """None (off) or {scale, nmode} from None / False / True / a mapping (defaults 1.0, 32)."""
    if diffuse is None or diffuse is False:
        return None
    d = {} if diffuse is True else dict(diffuse)
    unknown = set(d) - {"scale", "nmode"}
    if unknown:
        raise ValueError(f"diffuse: unknown key(s) {sorted(unknown)}; allowed: scale, nmode")
    scale = 1.0 if d.get("scale") is None else float(d["scale"])
    nmode = 32 if d.get("nmode") is None else d["nmode"]
    if not (np.isfinite(scale) and scale >= 0):
        raise ValueError(f"diffuse.scale: expected a number >= 0, got {d['scale']!r}")
    if isinstance(nmode, bool) or int(nmode) != nmode or nmode < 1:
        raise ValueError(f"diffuse.nmode: expected an integer >= 1, got {nmode!r}")
    return {"scale": scale, "nmode": int(nmode)}


def tbf_source(paths, gulp_nframe, *args, **kwargs):
    """Factory for :class:`TBFSourceBlock`."""
    return TBFSourceBlock(paths, gulp_nframe, *args, **kwargs)


def tbx_source(paths, gulp_nframe, *args, **kwargs):
    """Factory for :class:`TBXSourceBlock`."""
    return TBXSourceBlock(paths, gulp_nframe, *args, **kwargs)


def file_source(paths, gulp_nframe, *args, **kwargs):
    """A TBF or TBX source block, chosen by the frame id of the (first) file; all files must share it."""
    paths = [paths] if isinstance(paths, (str, bytes)) or hasattr(paths, "__fspath__") else list(paths)
    classes = {capture_source_class(p) for p in paths}
    if len(classes) != 1:
        raise ValueError(f"file_source: the files mix capture formats ({sorted(c.fmt for c in classes)}); "
                         "give one source per format")
    return classes.pop()(paths, gulp_nframe, *args, **kwargs)


def sim_sky_source(station, freq_hz, start, duration_s, sources, gulp_nframe, *args, **kwargs):
    """Factory for :class:`SimSkySourceBlock`."""
    return SimSkySourceBlock(station, freq_hz, start, duration_s, sources, gulp_nframe, *args, **kwargs)
