"""UDPSourceBlock: live LWA F-engine packets (TBF, TBX) onto a ring, in time order, in real time.

The receiving is done by :class:`bf_epic_blocks.io.udp.UDPCapture` on its own thread; this block
only turns its ordered gulps into ring spans (one sequence per stream: a stream ends after the
capture's idle timeout or a restart of the sender). Headers are the E-field headers of
docs/HEADERS.md, as :class:`~bf_epic_blocks.blocks.sources.TBFSourceBlock` writes them, plus
``udp`` (address, port, format, engine, channels, buffer_s).

Never stalling, never losing the start: the capture keeps receiving on its own thread whatever the
block does, and hands the block whole gulps through a bounded queue. The pipeline runner has the
blocks behind this source read *guaranteed*, so every gulp the queue holds reaches the imager --
including the reordering window's worth (``buffer_s``) that arrives at once when a stream starts,
which an unguaranteed reader lost. A pipeline that cannot keep up fills the queue, and the capture
then replaces whole gulps by counted zeros (``udp_stats['samples_overflow']``). A reader given
``guarantee=False`` still works (its skips are counted in its ``stats['nframe_skipped']`` and in
the capture's log line as ``skipped downstream``, builtin runtime), but it is overrun at the start
of a stream.
"""
from __future__ import annotations

import itertools
import logging

import numpy as np

from ..io.udp import UDPCapture
from ..imaging._xp import release_free_pinned
from ._compat import HostToDevice, bfp, span_array
from .headers import efield_header
from .sources import _Reader, _write_span

log = logging.getLogger(__name__)


class _UDPReader(_Reader):
    """Per-sequence state; a failure or shutdown inside the sequence stops the capture."""

    def __exit__(self, exc_type, *exc):
        if exc_type is not None:
            self.capture.close()
        return False


class UDPSourceBlock(bfp.SourceBlock):
    """Receive F-engine packets on ``address:port``; 'ci4' gulps (time, freq, station, pol).

    Parameters
    ----------
    address, port : where to listen (port 0 = an ephemeral port; read ``block.port``). The socket
        is bound and the capture thread started when the block is built, so packets sent before the
        pipeline runs are kept (ordered and queued, up to the capture's queue of gulps).
    gulp_nframe : time samples per gulp.
    fmt : 'tbf' or 'tbx' (see :func:`bf_epic_blocks.io.udp.packet_format`).
    station : a StationTable, a station name, or None (the one the frame id names).
    buffer_s, idle_timeout_s, start_timeout_s, rcvbuf_bytes, max_queue_bytes : as :class:`UDPCapture`
        (gulps this block was too slow to take become zeros, counted in ``udp_stats['samples_overflow']``).
    sequences : streams to receive before the block ends (0 = until the pipeline is stopped).
    ``udp_stats``: the capture's counters (packets, frames_missing, garbage, ...), kept current.
    """

    def __init__(self, address, port, gulp_nframe, fmt="tbf", station=None, buffer_s=0.05, idle_timeout_s=1.0,
                 start_timeout_s=None, rcvbuf_bytes=64 << 20, sequences=1, max_queue_bytes=256 << 20, progress=None,
                 space="system", *args, **kwargs):
        if isinstance(sequences, bool) or int(sequences) != sequences or sequences < 0:
            raise ValueError(f"sequences must be an integer >= 0 (0 = until stopped), got {sequences!r}")
        super().__init__(self._names(), gulp_nframe, space, *args, **kwargs)
        self.capture = UDPCapture(address, port, fmt, gulp_nframe=self.gulp_nframe, buffer_s=buffer_s,
                                  idle_timeout_s=idle_timeout_s, start_timeout_s=start_timeout_s,
                                  rcvbuf_bytes=rcvbuf_bytes, max_queue_bytes=max_queue_bytes,
                                  extra_report=self._skip_report,
                                  max_sequences=int(sequences) or None)
        self.address, self.port = self.capture.address, self.capture.port
        # receive from now on: packets sent while the rest of the pipeline starts are ordered and
        # queued (up to the capture's queue), not left to overflow the socket buffer
        self.capture.start()
        self.station, self.progress, self.nsequences = station, progress, int(sequences)
        self.udp_stats = self.capture.stats
        self._info = None
        # gulps go to a GPU ring through staging buffers made once for a whole gulp: a page-locked block
        # per chunk size (cupy.asarray's way) stays in CuPy's pinned pool for the life of the process
        self._h2d = HostToDevice()

    # -- sequences come from the capture, not from a list of names -------------------------------
    def _names(self):
        """Yields one name per stream the capture starts; ends when the capture closes."""
        count = itertools.count(1) if not getattr(self, "nsequences", 0) else range(1, self.nsequences + 1)
        try:
            for i in count:
                ev = self._wait(("start",))
                if ev is None:
                    return
                self._info = ev[1]
                yield f"udp://{self.address}:{self.port}/{self.capture.fmt.name}/{i}"
        finally:
            self.capture.close()

    def _wait(self, kinds):
        """Next capture event of one of ``kinds`` (None when the capture closed or the block stops)."""
        self.capture.start()
        stop = getattr(self, "shutdown_event", None)
        drain = getattr(self, "drain_event", None)          # our runtime's graceful end (Pipeline.drain)
        while True:
            if (stop is not None and stop.is_set()) or (drain is not None and drain.is_set()):
                return None
            ev = self.capture.next_event(0.2)
            if ev is None:
                continue
            if ev[0] == "closed":
                if str(ev[1]).startswith("receiver failed"):
                    raise RuntimeError(f"{self.capture.label}: {ev[1]}")
                return None
            if ev[0] in kinds:
                return ev
            log.debug("%s: ignoring %s event between sequences", self.capture.label, ev[0])

    def _skip_report(self):
        """Frames skipped by the unguaranteed readers of this block's ring (builtin runtime)."""
        ring = self.orings[0]
        blocks = getattr(getattr(self, "pipeline", None), "blocks", [])
        n = [b.stats.get("nframe_skipped", 0) for b in blocks
             if isinstance(getattr(b, "stats", None), dict) and any(r is ring for r in getattr(b, "irings", []))]
        return {"skipped downstream": int(sum(n))} if n else {}

    # -- SourceBlock hooks -------------------------------------------------------------------------
    def create_reader(self, sourcename):
        return _UDPReader(info=self._info, next_t=0, pending=None, name=sourcename, capture=self.capture)

    def _station(self, info):
        from ..station.tables import station_for_capture
        return station_for_capture(self.station, info.layout.station_hint, info.layout.nstand,
                                   f"{self.capture.label}: the packets", "name the station that sends them")

    def on_sequence(self, reader, sourcename):
        release_free_pinned()     # what the last stream's sizes left free, before this one's are made
        info = reader.info
        st = self._station(info)
        lay = info.layout
        freq = info.freq_hz
        hdr = efield_header(sourcename, int(info.time_tag0), freq, 1.0 / lay.chan_bw_hz, st.to_header(freq),
                            dtype="ci4", npol=2, chan_bw_hz=float(lay.chan_bw_hz),
                            udp={"address": self.address, "port": int(self.port), "format": lay.format,
                                 "engine": lay.engine, "buffer_s": self.capture.buffer_s,
                                 "channels": [int(c) for c in info.channels]})
        log.info("%s: %s, %d stands, %d channels (%.3f-%.3f MHz), station %s", sourcename, lay.engine, lay.nstand,
                 len(freq), freq.min() / 1e6, freq.max() / 1e6, st.name)
        return [hdr]

    def on_data(self, reader, ospans):
        dst = span_array(ospans[0])
        room = dst.shape[0]
        if reader.pending is None:
            ev = self._wait(("data", "gap", "end"))
            if ev is None or ev[0] == "end":
                return [0]
            reader.pending = ev
        kind, t0, what = reader.pending
        if t0 != reader.next_t:
            raise RuntimeError(f"{self.capture.label}: gulp at sample {t0}, expected {reader.next_t} (internal error)")
        if kind == "data":
            n = min(room, what.shape[0])
            _write_span(dst[:n], what[:n], self._h2d, room=dst.nbytes)
            rest = what[n:]
            reader.pending = (kind, t0 + n, rest) if rest.shape[0] else None
        else:  # samples the block was too slow to take from the capture: zeros, counted there
            n = min(room, what)
            _write_span(dst[:n], np.zeros((n,) + tuple(dst.shape[1:]), np.uint8), self._h2d, room=dst.nbytes)
            reader.pending = (kind, t0 + n, what - n) if what > n else None
        reader.next_t += n
        if self.progress:
            self.progress(n)
        return [n]


def udp_source(address, port, gulp_nframe, *args, **kwargs):
    """Factory for :class:`UDPSourceBlock`."""
    return UDPSourceBlock(address, port, gulp_nframe, *args, **kwargs)
