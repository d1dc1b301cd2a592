"""BifrostCaptureBlock: the station's F-engine stream captured by Bifrost's C packet capture.

Real Bifrost only (``bifrost.packet_capture.UDPCapture``, the engine LWA stations run; verbs where
the machine has them, ``use_verbs=True``). The capture thread is C: it receives, orders and writes
packets straight into this block's output ring, zero-filling a source that sent less than half of
a buffer's packets, and calls back here once per sequence for its header. Formats: ``chips``
(ADP) and ``snap2`` (NDP), as :mod:`bf_epic_blocks.io.udp` decodes them in Python; Bifrost has no
TBF/TBX decoder, so those stay with :class:`~bf_epic_blocks.blocks.udp_source.UDPSourceBlock`.

Ring layout as Bifrost's processors write it: per spectrum (chans, inputs) with inputs in source
order -- chips: 16 stands x 2 pols per ROACH board; snap2: ``npol`` inputs per packet -- which is
the station's digitizer order, the (time, freq, stand, pol) ci4 frames the imager reads.

Time: chips packets count spectra from the F-engine's sync time (``sync_time``, UNIX s; None =
recovered from the arrival clock, see :class:`~bf_epic_blocks.io.udp.ChipsPackets`); snap2 packets
carry it. A stream ends after ``idle_timeout_s`` without packets; ``sequences`` streams end the
block (0 = until the pipeline stops).
"""
from __future__ import annotations

import contextlib
import json
import logging

import numpy as np

from ..conventions import FS_HZ
from ..io.udp import ADP_CHAN_BW_HZ, NDP_CHAN_BW_HZ, _sync_from_clock
from ._compat import HAVE_BIFROST, bfp
from .headers import efield_header

log = logging.getLogger(__name__)

#: formats Bifrost's capture decodes, with (channel width, stands per source for chips)
CAPTURE_FORMATS = {"chips": ADP_CHAN_BW_HZ, "snap2": NDP_CHAN_BW_HZ}


def snap2_inputs_per_packet():
    """Inputs per channel that Bifrost's snap2 processor copies from each packet: 64 in an AVX build
    (two 256-bit words per channel, placed by the packet's pol0), 32 otherwise (one word, placed by
    source number, one channel block). The F-engine's packets must have that shape."""
    from bifrost.libbifrost import _bf
    return 64 if getattr(_bf, "BF_AVX_ENABLED", 0) else 32


def bifrost_capture_available(fmt):
    """(True, '') when Bifrost's packet capture can receive ``fmt`` here, else (False, why)."""
    if fmt not in CAPTURE_FORMATS:
        return False, f"Bifrost's packet capture has no {fmt} decoder (its formats: chips, snap2, ...)"
    if not HAVE_BIFROST:
        return False, "Bifrost is not the runtime in use"
    try:
        import bifrost.packet_capture  # noqa: F401
    except Exception as e:  # pragma: no cover - depends on the Bifrost build
        return False, f"bifrost.packet_capture does not import ({e})"
    return True, ""


class BifrostCaptureBlock(bfp.SourceBlock):
    """Receive ``fmt`` ('chips' or 'snap2') packets on ``address:port`` with Bifrost's C capture.

    Parameters
    ----------
    station : a StationTable (its stand count sets the sources expected: chips nstand/16 boards;
        snap2 ``nsrc``, default 2 * nstand / :func:`snap2_inputs_per_packet`, one channel block).
    gulp_nframe : spectra per capture buffer and per ring gulp.
    sync_time : chips only, see the module docstring.
    core : CPU core to bind the capture thread to (None: not bound), as stations run it.
    ``capture_stats``: per sequence, what the capture's header callback saw (seq0, chan0, nchan, nsrc).
    """

    def __init__(self, address, port, gulp_nframe, fmt, station, sync_time=None, nsrc=None, idle_timeout_s=1.0,
                 sequences=1, max_payload_size=9000, use_verbs=False, core=None, rcvbuf_bytes=None, space="system",
                 *args, **kwargs):
        ok, why = bifrost_capture_available(fmt)
        if not ok:
            raise RuntimeError(f"BifrostCaptureBlock: {why}")
        super().__init__([], gulp_nframe, space, *args, **kwargs)
        from bifrost.address import Address
        from bifrost.udp_socket import UDPSocket
        self.fmt, self.station, self.sync_time = fmt, station, sync_time
        self.nsrc = int(nsrc) if nsrc else (station.nstand // 16 if fmt == "chips"
                                            else 2 * station.nstand // snap2_inputs_per_packet())
        self.idle_timeout_s, self.nsequences = float(idle_timeout_s), int(sequences)
        self.max_payload_size, self.use_verbs = int(max_payload_size), bool(use_verbs)
        self.capture_core = None if core is None else int(core)
        self.sock = UDPSocket()
        self.sock.bind(Address(address, int(port)))
        # Bifrost's capture ends a sequence at the first receive that times out without a whole
        # buffer (packet_capture.cpp: recv -> flush, BF_CAPTURE_ENDED): the socket's timeout *is*
        # the stream's idle timeout, and how long a shutdown may wait
        self.sock.timeout = float(idle_timeout_s)
        self.address, self.port = address, self._bound_port(int(port))
        self.rcvbuf_granted = self._set_rcvbuf(rcvbuf_bytes)
        self.capture_stats = []
        self.udp_stats = {"engine": "bifrost"}
        self._hdr_buf = None
        log.info("udp %s:%d [%s]: listening with Bifrost's packet capture (%s), %d sources; receive buffer "
                 "%.0f MiB%s", address, self.port, fmt, "verbs" if use_verbs else "sockets", self.nsrc,
                 self.rcvbuf_granted / 2**20, "" if not rcvbuf_bytes or self.rcvbuf_granted >= rcvbuf_bytes else
                 f" (asked {rcvbuf_bytes / 2**20:.0f} MiB: raise net.core.rmem_max for more)")

    def _set_rcvbuf(self, nbytes):
        """Ask the kernel for a receive buffer of ``nbytes`` if more than Bifrost's own (256 MB asked); the
        granted size (Linux caps it at net.core.rmem_max) is returned. A stream's first packet waits
        for the sequence header (built in Python: ~0.1-0.2 s for 132 channels of LWA-SV, whose cable
        terms it carries), and all that arrives meanwhile must fit here: what does not is dropped,
        and Bifrost's capture, once behind, blanks whole sources and falls further behind."""
        import socket
        with self._py_socket() as s:
            if nbytes and int(nbytes) > s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF):  # never shrink it
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(nbytes))
            return s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def _bound_port(self, port):
        if port:
            return port
        with self._py_socket() as s:
            return s.getsockname()[1]

    @contextlib.contextmanager
    def _py_socket(self):
        """A Python socket on Bifrost's socket's descriptor, let go (not closed) afterwards."""
        import socket
        s = socket.socket(fileno=self.sock.fileno())
        try:
            yield s
        finally:
            s.detach()

    # -- the C capture owns the ring's writing --------------------------------------------------------
    def begin_writing(self, exit_stack, orings):
        return orings  # bfRingBeginWriting/EndWriting are the capture's (its RingWriter)

    def _header(self, seq0, chan0, nchan, nsrc, sync_s):
        bw = CAPTURE_FORMATS[self.fmt]
        ticks = int(round(FS_HZ / bw))
        freq = (chan0 + np.arange(nchan)) * bw
        st = self.station
        name = f"udp://{self.address}:{self.port}/{self.fmt}/{len(self.capture_stats) + 1}"
        time_tag = int(sync_s) * FS_HZ + int(seq0) * ticks
        hdr = efield_header(name, time_tag, freq, 1.0 / bw, st.to_header(freq), dtype="ci4", npol=2,
                            chan_bw_hz=float(bw), udp={"address": self.address, "port": int(self.port),
                                                       "format": self.fmt, "engine": "bifrost",
                                                       "sync_time": int(sync_s), "channels": list(range(chan0, chan0 + nchan))})
        hdr["gulp_nframe"] = int(self.gulp_nframe)
        self.capture_stats.append({"seq0": int(seq0), "chan0": int(chan0), "nchan": int(nchan), "nsrc": int(nsrc),
                                   "sync_time": int(sync_s), "time_tag": time_tag})
        log.info("%s: %s, %d stands, %d channels from %d, sync time %d, seq0 %d", name, self.fmt, st.nstand, nchan,
                 chan0, sync_s, seq0)
        return time_tag, hdr

    def _set_header(self, time_tag, hdr, time_tag_ptr, hdr_ptr, hdr_size_ptr):
        import ctypes
        text = json.dumps(hdr).encode()
        self._hdr_buf = ctypes.create_string_buffer(text)  # kept alive until the next sequence
        time_tag_ptr[0] = time_tag
        hdr_ptr[0] = ctypes.cast(self._hdr_buf, ctypes.c_void_p)
        hdr_size_ptr[0] = len(text)

    def _chips_cb(self, seq0, chan0, nchan, nsrc, time_tag_ptr, hdr_ptr, hdr_size_ptr):
        try:
            ticks = int(round(FS_HZ / ADP_CHAN_BW_HZ))
            sync = self.sync_time if self.sync_time is not None else _sync_from_clock(seq0, ticks)
            if nchan * 16 * nsrc * 2 <= 0 or nsrc * 16 != self.station.nstand:
                raise ValueError(f"{nsrc} boards x 16 stands do not match station {self.station.name} "
                                 f"({self.station.nstand} stands)")
            tt, hdr = self._header(seq0, chan0, nchan, nsrc, sync)
            self._set_header(tt, hdr, time_tag_ptr, hdr_ptr, hdr_size_ptr)
            return 0
        except Exception:  # noqa: BLE001 - a C callback must not raise; Bifrost stops on non-zero
            log.exception("chips sequence header")
            return 1

    def _snap2_cb(self, seq0, chan0, nchan, nsrc, time_tag_ptr, hdr_ptr, hdr_size_ptr):
        try:
            sync = int(time_tag_ptr[0])  # Bifrost's snap2 capture passes the packets' sync_time in
            # sources = channel blocks x input blocks of INPUTS_PER_SNAP2 inputs (what Bifrost's
            # snap2 processor copies per channel); nchan is one packet's
            nchan_tot = nchan * nsrc * snap2_inputs_per_packet() // (2 * self.station.nstand)
            tt, hdr = self._header(seq0, chan0, nchan_tot, nsrc, sync)
            self._set_header(tt, hdr, time_tag_ptr, hdr_ptr, hdr_size_ptr)
            return 0
        except Exception:  # noqa: BLE001
            log.exception("snap2 sequence header")
            return 1

    def main(self, orings):
        from bifrost.libbifrost import _bf
        from bifrost.packet_capture import PacketCaptureCallback, UDPCapture
        cls = UDPCapture
        if self.use_verbs:
            from bifrost.packet_capture import UDPVerbsCapture as cls
        cb = PacketCaptureCallback()
        (cb.set_chips if self.fmt == "chips" else cb.set_snap2)(
            self._chips_cb if self.fmt == "chips" else self._snap2_cb)
        started, ended = _bf.BF_CAPTURE_STARTED, _bf.BF_CAPTURE_ENDED
        nseq = 0
        # the readers initialise on the first sequence, which only the capture can bring: report this
        # block initialised now instead of waiting with the others (bifrost.pipeline's begin_sequences)
        self.pipeline.block_init_queue.put((self, True))
        with cls(self.fmt, self.sock, orings[0], self.nsrc, 0, self.max_payload_size, self.gulp_nframe,
                 self.gulp_nframe, sequence_callback=cb, core=self.capture_core) as cap:
            while not self.shutdown_event.is_set():
                status = cap.recv()
                if status == started:
                    nseq += 1
                elif status == ended:  # idle for idle_timeout_s: the capture flushed the sequence
                    self.udp_stats.update(self._read_stats())
                    if self.nsequences and nseq >= self.nsequences:
                        break
            self.udp_stats.update(self._read_stats())
        self.sock.close()
        log.info("udp %s:%d [%s]: Bifrost's capture ended: %s", self.address, self.port, self.fmt, self.udp_stats)

    def _read_stats(self):
        """The capture's own counters (its ProcLog 'stats' entry, as of its last receive: the buffers
        committed when it ends are not in them) and the kernel's drops on the socket."""
        import os
        from ..io.udp import socket_drops
        out = {}
        try:
            from bifrost.proclog import load_by_pid
            for entries in load_by_pid(os.getpid()).values():
                st = entries.get("stats") if isinstance(entries, dict) else None
                if isinstance(st, dict) and "nvalid" in st:
                    out = {"packets": int(st["nvalid"]) + int(st["nlate"]) + int(st["ninvalid"]),
                           "packets_valid": int(st["nvalid"]), "packets_late": int(st["nlate"]),
                           "packets_invalid": int(st["ninvalid"]), "good_bytes": int(st["ngood_bytes"]),
                           "missing_bytes": int(st["nmissing_bytes"])}
        except Exception as e:  # noqa: BLE001 - counters are a report, never a failure
            log.debug("capture stats not readable: %s", e)
        with self._py_socket() as s:
            drops = socket_drops(s)
        if drops is not None:
            out["kernel_drops"] = drops
        return out
