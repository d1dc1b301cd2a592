"""Live capture of LWA F-engine packets over UDP, and a replayer that sends a capture file as packets.

Packet formats are plug-ins (:class:`PacketFormat`): each knows how to recognise its frames, what a
stream's layout is (frame size, stands, channels per frame, channel width) and how to list the frames
of a file for the replayer. One frame per datagram: ``tbf`` (:class:`TBFPackets`, the layout of
:mod:`bf_epic_blocks.io.tbf`) and ``tbx`` (:class:`TBXPackets`, the layout of :mod:`bf_epic_blocks.io.tbx`).

:class:`UDPCapture` receives on its own thread and assembles frames into time samples:

* The first valid packet fixes the stream's layout (frame id, stands, frame size). The channel
  blocks and the first time tag are learned from the packets of the first ``buffer_s`` of data
  (the sequence starts at the earliest time tag seen then; a block first seen later is counted as
  ``frames_unknown_block`` and ignored).
* Frames are put into a window of time slots (at least ``buffer_s`` of data, up to twice that), so
  packets that arrive out of order within the window are put back in order. A slot leaves the
  window when a frame more than the window ahead arrives; its missing frames are zero-filled
  (byte 0 = 0+0j) and counted in ``frames_missing``. A frame for a slot that already left is
  ``frames_late`` (it stays lost), a repeated one ``frames_duplicate``.
* Datagrams that are not frames of the stream -- wrong size, bad sync word, another frame id or
  stand count, a misaligned channel, a time tag off the sample grid -- are counted in
  ``garbage`` (by reason) and ignored.
* A forward jump of more than ``resync_s`` of data ends the sequence and starts a new one at the
  new time (a restarted stream, whose samples need not lie on the old time grid), once
  ``UDPCapture.JUMP_CONFIRM`` frames agree on the new time base (a lone corrupted time tag is counted
  as garbage, ``time_jump``); no valid packet for ``idle_timeout_s`` ends the sequence.
* The socket is never stalled: the thread only receives and copies, and hands finished gulps to the
  consumer through a bounded queue. If the consumer falls more than ``max_queue_bytes`` behind,
  a gulp is replaced by a "gap" marker (its samples counted in ``samples_overflow``) so that the
  time axis stays exact. This queue is the one place a live pipeline loses data: the blocks behind
  :class:`~bf_epic_blocks.blocks.udp_source.UDPSourceBlock` read guaranteed (back-pressure reaches
  the block's thread, never the socket).
* Once a second the thread logs what it received, lost (missing, late, garbage) and, when the
  consumer provides it (``extra_report``), what was skipped downstream.

Why a plain socket: a large ``SO_RCVBUF`` (the kernel caps it at ``net.core.rmem_max``; the granted
size is logged) absorbs the bursts while the Python thread waits for the GIL; one ``recv_into``
per datagram keeps the code portable (Python has no ``recvmmsg``). The receiver sustains tens of
thousands of packets per second on one core (see the README's live-capture figures); at higher
rates use a C packet capture (Bifrost's ``udp_capture``) in front of the same blocks.

Loopback is the tested setting; nothing here restricts the address a capture binds to, but
:func:`replay` refuses to send anywhere but a loopback address unless ``allow_remote=True``.
"""
from __future__ import annotations

import collections
import dataclasses
import ipaddress
import logging
import math
import os
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..conventions import FS_HZ
from .tbf import CHANNELS_PER_FRAME, FRAME_KINDS, HEADER_BYTES, SYNC_WORD, _open_frames, read_tbf

__all__ = ["PacketFormat", "TBFPackets", "TBXPackets", "StreamLayout", "SequenceInfo", "UDPCapture", "ReplayResult",
           "packet_format", "replay", "parse_host_port", "PACKET_FORMATS"]

log = logging.getLogger(__name__)

#: Names accepted by :func:`packet_format`.
PACKET_FORMATS = ("tbf", "tbx", "chips", "snap2")


@dataclass(frozen=True)
class StreamLayout:
    """What the first valid packet of a stream tells: everything but the channel blocks and t0.

    ``frame_bytes`` = ``header_bytes`` + ``chans_per_frame`` * ``nstand`` * 2 (ci4, 1 byte per
    complex sample); ``sample_ticks`` = time-tag step of one sample (196 MHz ticks);
    ``nstand_field`` the raw header value (old ADP frames write 0 for 256).
    """
    format: str
    frame_id: int
    nstand: int
    nstand_field: int
    chans_per_frame: int
    header_bytes: int
    frame_bytes: int
    chan_bw_hz: float
    engine: str
    station_hint: str
    first_chan0: int
    time_tag0: int
    #: Sources per time sample, as (channel blocks, input blocks): a packet carries
    #: ``chans_per_frame`` channels x ``payload_bytes // chans_per_frame`` inputs (1 byte each,
    #: ci4). 0 channel blocks = learned from the stream (TBF/TBX: blocks of all stands, keyed by
    #: their first channel); otherwise every source is expected from the start (chips, snap2:
    #: keyed by source number; a source never heard is zero-filled and counted missing).
    nchan_blocks: int = 0
    ninput_blocks: int = 1

    @property
    def sample_ticks(self) -> int:
        return int(round(FS_HZ / self.chan_bw_hz))

    @property
    def payload_bytes(self) -> int:
        return self.frame_bytes - self.header_bytes


class PacketFormat:
    """Interface of a packet format (one frame per datagram).

    ``probe(buf, n)`` -> StreamLayout, or a garbage reason (str) when ``buf[:n]`` is not a frame.
    ``parse(buf, n, layout)`` -> (time_tag, block key) of a frame of that stream, or a reason; the
    key is the first channel (TBF/TBX) or the source number (chips, snap2; see StreamLayout).
    ``file_frames(path)`` -> (frames uint8 (nframe, frame_bytes), time_tags int64 (nframe,)) of a
    capture file, complete frames in file order (for the replayer).
    """
    name = "?"
    #: (start, stop) bytes of a frame's big-endian int64 time tag, where the replayer can rewrite it
    time_tag_bytes = None

    @staticmethod
    def to_samples(slots, layout):
        """Packet payloads (n, nsource, payload_bytes), sources in key order, as time samples
        uint8 (n, nchan, nstand, 2). Source key = input block + channel block * ninput_blocks;
        a payload is (chans_per_frame, inputs) channel-major, inputs stand-major (stand, pol)."""
        n = slots.shape[0]
        ncb = layout.nchan_blocks or slots.shape[1]
        nib = layout.ninput_blocks
        cpf = layout.chans_per_frame
        x = slots.reshape(n, ncb, nib, cpf, -1)
        if nib > 1:
            x = x.transpose(0, 1, 3, 2, 4)
        return x.reshape(n, ncb * cpf, layout.nstand, 2)

    def probe(self, buf, n):
        raise NotImplementedError

    def parse(self, buf, n, layout):
        raise NotImplementedError

    def file_frames(self, path):
        raise NotImplementedError


_TBF_HDR = struct.Struct(">IIIhhq")  # sync, id<<24|count, second, first chan, nstand, time tag


class TBFPackets(PacketFormat):
    """TBF frames (ADP id 1, NDP id 5) as UDP payloads; layout as :mod:`bf_epic_blocks.io.tbf`."""
    name = "tbf"
    time_tag_bytes = (16, 24)        # the header's big-endian int64 time tag (the replayer rewrites it)

    def probe(self, buf, n):
        if n < HEADER_BYTES:
            return "size"
        sync, idc, _, fc, ns, tt = _TBF_HDR.unpack_from(buf, 0)
        if sync != SYNC_WORD:
            return "sync"
        fid = idc >> 24
        if fid not in FRAME_KINDS:
            return "frame_id"
        nstand = 256 if (ns == 0 and fid == 1) else ns
        if nstand <= 0:
            return "nstand"
        fb = HEADER_BYTES + CHANNELS_PER_FRAME * nstand * 2
        if n != fb:
            return "size"
        if fc < 0:
            return "channel"
        eng, hint, bw = FRAME_KINDS[fid]
        return StreamLayout("tbf", fid, nstand, ns, CHANNELS_PER_FRAME, HEADER_BYTES, fb, bw, eng, hint, fc, tt)

    def parse(self, buf, n, layout):
        if n != layout.frame_bytes:
            return "size"
        sync, idc, _, fc, ns, tt = _TBF_HDR.unpack_from(buf, 0)
        if sync != SYNC_WORD:
            return "sync"
        if idc >> 24 != layout.frame_id:
            return "frame_id"
        if ns != layout.nstand_field:
            return "nstand"
        if fc < 0 or (fc - layout.first_chan0) % CHANNELS_PER_FRAME:
            return "channel"
        return tt, fc

    def file_frames(self, path):
        mm, f = _open_frames(path)
        tt = np.ascontiguousarray(mm[:, 16:24]).view(">i8").ravel().astype(np.int64)
        return mm, tt


_TBX_HDR = struct.Struct(">IIIIHHq")  # sync, id<<24|count, second, first chan, nstand, nchan, time tag


class TBXPackets(PacketFormat):
    """TBX frames (NDP, id 8) as UDP payloads; layout as :mod:`bf_epic_blocks.io.tbx`.

    The header is decoded with :mod:`struct` rather than :func:`~bf_epic_blocks.io.tbx.parse_tbx_header`
    (NumPy per packet is several times slower); the tests check both agree through the file reader.
    """
    name = "tbx"
    time_tag_bytes = (20, 28)

    def probe(self, buf, n):
        from .tbx import CHAN_BW_HZ, FRAME_ID, HEADER_BYTES as TBX_HEADER
        if n < TBX_HEADER:
            return "size"
        sync, idc, _, fc, ns, nc, tt = _TBX_HDR.unpack_from(buf, 0)
        if sync != SYNC_WORD:
            return "sync"
        if idc >> 24 != FRAME_ID:
            return "frame_id"
        if ns <= 0 or nc <= 0:
            return "nstand"
        fb = TBX_HEADER + nc * ns * 2
        if n != fb:
            return "size"
        hint = {64: "lwana", 256: "lwasv"}.get(ns, "lwana" if ns <= 64 else "lwasv")  # as io.tbx's station hint
        return StreamLayout("tbx", FRAME_ID, ns, ns, nc, TBX_HEADER, fb, CHAN_BW_HZ, "NDP", hint, fc, tt)

    def parse(self, buf, n, layout):
        if n != layout.frame_bytes:
            return "size"
        sync, idc, _, fc, ns, nc, tt = _TBX_HDR.unpack_from(buf, 0)
        if sync != SYNC_WORD:
            return "sync"
        if idc >> 24 != layout.frame_id:
            return "frame_id"
        if ns != layout.nstand or nc != layout.chans_per_frame:
            return "nstand"
        if (fc - layout.first_chan0) % layout.chans_per_frame:
            return "channel"
        return tt, fc

    def file_frames(self, path):
        from .tbx import _open_frames as open_tbx
        mm, _, _ = open_tbx(path)
        tt = np.ascontiguousarray(mm[:, 20:28]).view(">i8").ravel().astype(np.int64)
        return mm, tt


# The F-engines' own streams, as Bifrost's src/formats/chips.hpp and snap2.hpp define them.
_CHIPS_HDR = struct.Struct(">BBBBBBHQ")  # roach (1-based), gbe, nchan, nsubband, subband, nroach, chan0, seq (1-based)
_SNAP2_HDR = struct.Struct(">QIHHHHIII")  # seq, sync_time, npol, npol_tot, nchan, nchan_tot, chan_block_id, chan0, pol0
ADP_CHAN_BW_HZ = 25e3           # ADP F-engine channels (LSL: lsl.common.adp.fC)
NDP_CHAN_BW_HZ = FS_HZ / 8192   # NDP F-engine channels (LSL: lsl.common.ndp.fC)


def _spectra(ntime, time_tag0, time_step, sync_time, chan_bw_hz, name):
    """For a writer of ``name`` packets: (time tags, 0-based spectrum counts since the sync time,
    sync time) of ``ntime`` samples from ``time_tag0``; the sync time defaults to the whole second
    at or before it. ValueError when the samples are not whole spectra after it."""
    sync = int(time_tag0 // FS_HZ) if sync_time is None else int(sync_time)
    tt = int(time_tag0) + np.arange(ntime, dtype=np.int64) * int(time_step)
    seq, rem = np.divmod(tt - sync * FS_HZ, int(round(FS_HZ / chan_bw_hz)))
    if rem.any() or (seq < 0).any():
        raise ValueError(f"time tags are not whole spectra after sync time {sync}: not a {name} stream")
    return tt, seq, sync


def _sync_from_clock(seq, ticks):
    """The F-engine's sync time (whole UNIX second at which ``seq`` was 0), from the arrival time of
    a packet with spectrum count ``seq``: F-engines start on a whole second, so rounding the arrival
    time less ``seq`` samples recovers it while the network delay is well under 0.5 s."""
    return int(round(time.time() - seq * ticks / FS_HZ))


class ChipsPackets(PacketFormat):
    """ADP (LWA-SV) F-engine packets, Bifrost's ``chips`` format: one per ROACH board and spectrum.

    Header (16 bytes, big-endian): roach (1-based), gbe (tuning), nchan, nsubband, subband, nroach,
    chan0 (first channel), seq (spectrum count, 1-based). Payload: nchan channels x 32 inputs (16
    stands x 2 pols, digitizer order: board r carries stands 16 (r-1) .. 16 r - 1 of LSL's antenna
    order, the TBF payload order), 1 byte ci4 each. Every board of ``nroach`` is expected; one not
    heard is zero-filled and counted in ``frames_missing``.

    The packets carry no absolute time: a spectrum's time tag is ``sync_time`` x 196e6 + (seq - 1)
    x 7,840 ticks, ``sync_time`` the whole UNIX second the F-engine counted from (ADP's
    ``utc_start``). ``sync_time=None`` recovers it from the arrival clock (logged; exact while the
    network delay is < 0.5 s and the machine's clock is right); give it for archival streams.
    """
    name = "chips"
    INPUTS = 32

    def __init__(self, sync_time=None):
        self.sync_time = None if sync_time is None else int(sync_time)

    def probe(self, buf, n):
        if n < _CHIPS_HDR.size:
            return "size"
        roach, _, nchan, _, _, nroach, chan0, seq = _CHIPS_HDR.unpack_from(buf, 0)
        if nroach == 0 or nchan == 0 or not 1 <= roach <= nroach:
            return "source"
        if n != _CHIPS_HDR.size + nchan * self.INPUTS:
            return "size"
        if seq < 1:
            return "time_grid"
        ticks = int(round(FS_HZ / ADP_CHAN_BW_HZ))
        sync = self.sync_time
        if sync is None:
            sync = _sync_from_clock(seq - 1, ticks)
            log.info("chips: sync time %d (UNIX s) recovered from the arrival clock; set source.sync_time "
                     "to the F-engine's utc_start for archival accuracy", sync)
        self._sync_ticks = sync * FS_HZ
        return StreamLayout("chips", 0, nroach * 16, nroach, nchan, _CHIPS_HDR.size, n, ADP_CHAN_BW_HZ,
                            "ADP F-engine", "lwasv", chan0, self._sync_ticks + (seq - 1) * ticks,
                            nchan_blocks=1, ninput_blocks=nroach)

    def parse(self, buf, n, layout):
        if n != layout.frame_bytes:
            return "size"
        roach, _, nchan, _, _, nroach, chan0, seq = _CHIPS_HDR.unpack_from(buf, 0)
        if nroach != layout.ninput_blocks or not 1 <= roach <= nroach or nchan != layout.chans_per_frame:
            return "source"
        if chan0 != layout.first_chan0:
            return "channel"
        if seq < 1:
            return "time_grid"
        return self._sync_ticks + (seq - 1) * layout.sample_ticks, roach - 1

    def packets(self, data, time_tag0, chan0, time_step, sync_time=None):
        """Chips packets of time samples ``data`` uint8 (ntime, nchan, nstand, 2) (nstand a multiple
        of 16, nchan <= 255): (packets uint8 (ntime * nroach, size), time tags), per spectrum the
        boards in order. ``sync_time``: default the whole second at or before ``time_tag0``."""
        ntime, nchan, nstand, _ = data.shape
        if nstand % 16 or not 0 < nchan < 256 or not 0 <= chan0 < 65536:
            raise ValueError(f"chips packets need a multiple of 16 stands and 1-255 channels; got {nstand} stands, "
                             f"{nchan} channels from {chan0}")
        tt, seq, sync = _spectra(ntime, time_tag0, time_step, sync_time, ADP_CHAN_BW_HZ, "chips")
        nroach = nstand // 16
        hdr = np.zeros((ntime, nroach), np.dtype([("roach", "u1"), ("gbe", "u1"), ("nchan", "u1"), ("nsub", "u1"),
                                                  ("sub", "u1"), ("nroach", "u1"), ("chan0", ">u2"), ("seq", ">u8")]))
        hdr["roach"] = np.arange(1, nroach + 1)
        hdr["nchan"], hdr["nsub"], hdr["nroach"], hdr["chan0"] = nchan, 1, nroach, chan0
        hdr["seq"] = (seq + 1)[:, None]
        pay = data.reshape(ntime, nchan, nroach, 32).transpose(0, 2, 1, 3).reshape(ntime, nroach, -1)
        out = np.concatenate([hdr.view(np.uint8).reshape(ntime, nroach, -1), pay], axis=2)
        return out.reshape(ntime * nroach, -1), np.repeat(tt, nroach), sync

    def file_frames(self, path):
        return _packets_from_recording(self, path)


class Snap2Packets(PacketFormat):
    """NDP (SNAP2) F-engine packets, Bifrost's ``snap2`` format.

    Header (32 bytes, big-endian): seq (spectrum count since ``sync_time``), sync_time (UNIX s),
    npol, npol_tot, nchan, nchan_tot, chan_block_id, chan0 (this packet's first channel), pol0
    (first input). Payload: nchan x npol inputs, 1 byte ci4 each; inputs stand-major (stand, pol)
    in the station's digitizer order, as the TBF payload. Source number = pol0 / npol +
    chan_block_id x (npol_tot / npol), as Bifrost's decoder numbers them; all are expected, and
    one not heard is zero-filled and counted. Time tag = sync_time x 196e6 + seq x 8,192 ticks.
    """
    name = "snap2"

    def __init__(self, npol=64, nchan=None):
        self.npol, self.nchan = int(npol), nchan  # packet shape the replayer sends (see packets)

    def probe(self, buf, n):
        if n < _SNAP2_HDR.size:
            return "size"
        seq, sync, npol, npol_tot, nchan, nchan_tot, cb, chan0, pol0 = _SNAP2_HDR.unpack_from(buf, 0)
        if not npol or not nchan or npol_tot % npol or nchan_tot % nchan or npol_tot % 2:
            return "source"
        if n != _SNAP2_HDR.size + nchan * npol:
            return "size"
        if cb >= nchan_tot // nchan or pol0 % npol or pol0 >= npol_tot or chan0 < cb * nchan:
            return "source"
        ticks = int(round(FS_HZ / NDP_CHAN_BW_HZ))
        nstand = npol_tot // 2
        hint = "lwana" if nstand <= 64 else "lwasv"
        return StreamLayout("snap2", 0, nstand, nstand, nchan, _SNAP2_HDR.size, n, NDP_CHAN_BW_HZ, "NDP F-engine",
                            hint, chan0 - cb * nchan, sync * FS_HZ + seq * ticks,
                            nchan_blocks=nchan_tot // nchan, ninput_blocks=npol_tot // npol)

    def parse(self, buf, n, layout):
        if n != layout.frame_bytes:
            return "size"
        seq, sync, npol, npol_tot, nchan, nchan_tot, cb, chan0, pol0 = _SNAP2_HDR.unpack_from(buf, 0)
        nib = layout.ninput_blocks
        if (nchan != layout.chans_per_frame or npol_tot != 2 * layout.nstand or npol * nib != npol_tot
                or nchan_tot != nchan * layout.nchan_blocks or cb >= layout.nchan_blocks or pol0 % npol
                or pol0 >= npol_tot):
            return "source"
        if chan0 != layout.first_chan0 + cb * nchan:
            return "channel"
        return sync * FS_HZ + seq * layout.sample_ticks, pol0 // npol + cb * nib

    def packets(self, data, time_tag0, chan0, time_step, sync_time=None, npol=None, nchan=None):
        """Snap2 packets of ``data`` uint8 (ntime, nchan_tot, nstand, 2): ``npol`` inputs (default
        the format's, 64, or all) by ``nchan`` channels (default the format's, or the most,
        dividing the total, that fit 8 kB) each; per spectrum the sources in order. Returns
        (packets, time tags, sync time)."""
        npol = self.npol if npol is None else npol
        nchan = self.nchan if nchan is None else nchan
        ntime, nchan_tot, nstand, _ = data.shape
        npol_tot = 2 * nstand
        npol = min(int(npol), npol_tot)
        if npol_tot % npol:
            raise ValueError(f"snap2 packets: {npol} inputs per packet do not divide {npol_tot}")
        if nchan is None:
            nchan = max(c for c in range(1, nchan_tot + 1) if nchan_tot % c == 0 and c * npol <= 8192)
        if nchan_tot % nchan:
            raise ValueError(f"snap2 packets: {nchan} channels per packet do not divide {nchan_tot}")
        tt, seq, sync = _spectra(ntime, time_tag0, time_step, sync_time, NDP_CHAN_BW_HZ, "snap2")
        ncb, nib = nchan_tot // nchan, npol_tot // npol
        hdr = np.zeros((ntime, ncb, nib), np.dtype([("seq", ">u8"), ("sync", ">u4"), ("npol", ">u2"),
                                                    ("npol_tot", ">u2"), ("nchan", ">u2"), ("nchan_tot", ">u2"),
                                                    ("cb", ">u4"), ("chan0", ">u4"), ("pol0", ">u4")]))
        hdr["seq"] = seq[:, None, None]
        hdr["sync"], hdr["npol"], hdr["npol_tot"], hdr["nchan"], hdr["nchan_tot"] = sync, npol, npol_tot, nchan, nchan_tot
        hdr["cb"] = np.arange(ncb)[:, None]
        hdr["chan0"] = chan0 + nchan * np.arange(ncb)[:, None]
        hdr["pol0"] = npol * np.arange(nib)
        pay = data.reshape(ntime, ncb, nchan, nib, npol).transpose(0, 1, 3, 2, 4).reshape(ntime, ncb, nib, -1)
        out = np.concatenate([hdr.view(np.uint8).reshape(ntime, ncb, nib, -1), pay], axis=3)
        return out.reshape(ntime * ncb * nib, -1), np.repeat(tt, ncb * nib), sync

    def file_frames(self, path):
        return _packets_from_recording(self, path)


def _packets_from_recording(fmt, path):
    """A TBF or TBX recording's samples as ``fmt``'s packets (for the replayer): (packets, time tags)."""
    from .formats import detect_format
    kind = detect_format(path)
    if kind == "tbx":
        from .tbx import read_tbx
        d = read_tbx(path)
    else:
        d = read_tbf(path)
    if d.data.shape[0] == 0:
        return np.zeros((0, 0), np.uint8), np.zeros(0, np.int64)
    step = int(round(FS_HZ / d.chan_bw_hz))
    if np.any(np.diff(d.channels) != 1):
        raise ValueError(f"{path}: channels are not contiguous; a {fmt.name} stream carries one run of channels")
    pkts, tts, sync = fmt.packets(d.data, int(d.time_tags[0]), int(d.channels[0]), step)
    fmt.replay_sync_time = sync
    log.info("%s: %d samples x %d channels as %d %s packets (sync time %d)", path, d.data.shape[0],
             d.data.shape[1], len(pkts), fmt.name, sync)
    return pkts, tts


_FORMATS = {"tbf": TBFPackets, "tbx": TBXPackets, "chips": ChipsPackets, "snap2": Snap2Packets}


def packet_format(name: str, **options) -> PacketFormat:
    """The :class:`PacketFormat` called ``name``: 'tbf' (:class:`TBFPackets`), 'tbx'
    (:class:`TBXPackets`), 'chips' (:class:`ChipsPackets`; option ``sync_time``) or 'snap2'
    (:class:`Snap2Packets`).

    Another format plugs in as a :class:`PacketFormat` subclass added here (probe, parse, file_frames).
    """
    if name not in _FORMATS:
        raise ValueError(f"unknown packet format {name!r}; expected one of {PACKET_FORMATS}")
    return _FORMATS[name](**options)


def parse_host_port(text: str) -> tuple[str, int]:
    """'127.0.0.1:4015' -> ('127.0.0.1', 4015); ValueError naming the problem otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT (e.g. 127.0.0.1:4015), got {text!r}")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"port must be an integer, got {port!r} in {text!r}") from None
    if not 0 < p < 65536:
        raise ValueError(f"port must be in 1..65535, got {p}")
    return host.strip("[]"), p


# ------------------------------------------------------------------------------------------------
# Capture
# ------------------------------------------------------------------------------------------------
@dataclass
class SequenceInfo:
    """One sequence of a capture: the stream layout, channels learned, first time tag, index."""
    layout: StreamLayout
    blocks: np.ndarray        # (nblock,) sorted first channels
    time_tag0: int
    index: int

    @property
    def channels(self) -> np.ndarray:
        lay = self.layout
        if lay.nchan_blocks:  # sources expected by number: one run of channels from the first
            return lay.first_chan0 + np.arange(lay.nchan_blocks * lay.chans_per_frame, dtype=np.int64)
        return (self.blocks[:, None] + np.arange(lay.chans_per_frame)).ravel().astype(np.int64)

    @property
    def freq_hz(self) -> np.ndarray:
        return self.channels.astype(np.float64) * self.layout.chan_bw_hz

    @property
    def nchan(self) -> int:
        return len(self.channels)


def socket_drops(sock):
    """Datagrams the kernel dropped on this UDP socket (its receive buffer was full), from
    /proc/net/udp (Linux); None where that is not available."""
    try:
        ino = str(os.fstat(sock.fileno()).st_ino)
        for name in ("/proc/net/udp", "/proc/net/udp6"):
            with open(name) as fh:
                for line in fh.readlines()[1:]:
                    f = line.split()
                    if len(f) > 12 and f[9] == ino:
                        return int(f[12])
    except (OSError, ValueError):
        pass
    return None


def _new_stats():
    return dict(packets=0, bytes=0, kernel_drops=0, frames_used=0, frames_late=0, frames_duplicate=0,
                frames_unknown_block=0, frames_missing=0, samples=0, samples_overflow=0, sequences=0,
                garbage=collections.Counter())


class UDPCapture:
    """Receive frames of one packet format on ``(address, port)``; hand out ordered gulps.

    ``JUMP_CONFIRM``: frames that must agree on a new time base (its sample grid, within a resync's reach)
    before a jump ends the sequence: one frame with a corrupted time tag must not end a stream, and a
    restarted F-engine sends every block of every sample.

    Parameters
    ----------
    address, port : where to bind (port 0 = an ephemeral port, then read ``self.port``).
    fmt : a :class:`PacketFormat` or its name.
    gulp_nframe : time samples per handed-out gulp (the last of a sequence may be shorter).
    buffer_s : reordering window, seconds of data (>= 1 sample).
    idle_timeout_s : no valid frame for this long (wall clock) ends the sequence.
    resync_s : a forward jump of more than this (data time) ends the sequence and starts another.
    rcvbuf_bytes : SO_RCVBUF asked for (the kernel may grant less: ``self.rcvbuf_granted``).
    max_queue_bytes : how far (bytes of gulps; at least 2 gulps) the consumer may lag before gulps
        become counted gaps.
    max_learn_frames : learning ends after this many frames even if the time has not advanced buffer_s.
    extra_report : callable -> dict of extra counts for the once-a-second log line (e.g. skipped).
    log_interval_s : seconds between log lines (None: no periodic log).

    Events from :meth:`next_event`: ``("start", SequenceInfo)``, ``("data", t_index, array)`` with
    array uint8 (n, nchan, nstand, 2) packed ci4 and t_index its first sample in the sequence,
    ``("gap", t_index, n)`` (n samples the consumer was too slow to take: write zeros),
    ``("end", reason)``, and ``("closed", reason)`` once the capture has stopped.
    ``stats`` (cumulative): packets, bytes, kernel_drops (datagrams the kernel dropped because the
    socket buffer was full; Linux, updated once a second and at each sequence end), frames_used,
    frames_late, frames_duplicate,
    frames_unknown_block, frames_missing, samples, samples_overflow, sequences, garbage (by reason).
    """

    JUMP_CONFIRM = 3

    def __init__(self, address="127.0.0.1", port=0, fmt="tbf", gulp_nframe=1024, buffer_s=0.05,
                 idle_timeout_s=1.0, start_timeout_s=None, resync_s=1.0, rcvbuf_bytes=64 << 20,
                 max_queue_bytes=256 << 20, extra_report=None, log_interval_s=1.0, max_sequences=None,
                 max_learn_frames=1 << 18):
        self.fmt = packet_format(fmt) if isinstance(fmt, str) else fmt
        if int(gulp_nframe) < 1:
            raise ValueError(f"gulp_nframe must be >= 1, got {gulp_nframe!r}")
        for name, v in (("buffer_s", buffer_s), ("idle_timeout_s", idle_timeout_s), ("resync_s", resync_s)):
            if not (isinstance(v, (int, float)) and v > 0):
                raise ValueError(f"{name} must be a number > 0, got {v!r}")
        self.gulp = int(gulp_nframe)
        self.buffer_s, self.idle_timeout_s, self.resync_s = float(buffer_s), float(idle_timeout_s), float(resync_s)
        self.start_timeout_s = start_timeout_s
        self.max_queue_bytes, self.extra_report = int(max_queue_bytes), extra_report
        self.log_interval_s, self.max_learn_frames = log_interval_s, int(max_learn_frames)
        self.max_sequences = max_sequences
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
            self.sock.bind((address, int(port)))
        except OSError as e:
            self.sock.close()
            raise OSError(f"cannot receive UDP on {address}:{port}: {e}") from e
        self.address, self.port = self.sock.getsockname()[:2]
        self.rcvbuf_granted = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self.stats = _new_stats()
        self.layout = None               # the stream's StreamLayout once its first packet is read
        log.info("%s: listening; receive buffer %.1f MiB%s", self.label, self.rcvbuf_granted / 2**20,
                 "" if self.rcvbuf_granted >= int(rcvbuf_bytes) else
                 f" (asked {int(rcvbuf_bytes) / 2**20:.1f} MiB: raise net.core.rmem_max for more)")
        self.sock.settimeout(min(0.05, self.idle_timeout_s / 4))
        self._events = collections.deque()
        self._ndata_queued = 0
        self._bytes_queued = 0
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._thread = None
        self._closed_reason = None
        self._nseq = 0

    @property
    def label(self) -> str:
        return f"udp {self.address}:{self.port} [{self.fmt.name}]"

    # ---------------------------------------------------------------- consumer side
    def start(self):
        """Start the receiving thread (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._main, name=f"udp-capture-{self.port}", daemon=True)
            self._thread.start()
        return self

    def next_event(self, timeout=None):
        """The next event (see the class docstring), or None after ``timeout`` seconds."""
        with self._cv:
            if not self._events:
                self._cv.wait(timeout)
            if not self._events:
                return None
            ev = self._events.popleft()
            if ev[0] == "data":
                self._ndata_queued -= 1
                self._bytes_queued -= ev[2].nbytes
            return ev

    def close(self, timeout=5.0):
        """Stop receiving (the open sequence is flushed and ended) and close the socket."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        try:
            self.sock.close()
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---------------------------------------------------------------- receiver side
    def _emit(self, ev):
        with self._cv:
            if ev[0] == "data" and self._ndata_queued >= 2 and \
                    self._bytes_queued + ev[2].nbytes > self.max_queue_bytes:
                n = ev[2].shape[0]
                self.stats["samples_overflow"] += n
                ev = ("gap", ev[1], n)
            elif ev[0] == "data":
                self._ndata_queued += 1
                self._bytes_queued += ev[2].nbytes
            self._events.append(ev)
            self._cv.notify_all()

    def _main(self):
        reason = "stopped"
        try:
            reason = self._receive()
        except Exception as e:  # noqa: BLE001 - reported to the consumer, which raises it
            log.exception("%s: receiver failed", self.label)
            reason = f"receiver failed: {type(e).__name__}: {e}"
        finally:
            self._closed_reason = reason
            self._emit(("closed", reason))
            self._log_line(force=True)

    def _receive(self):
        buf = bytearray(65536)
        mv = memoryview(buf)
        fmt, stats = self.fmt, self.stats
        seq = None                  # _Assembly of the open sequence (after learning)
        learn = None                # list of (tt, fc, payload bytes) while learning
        jump = None                 # (time tag, frames) of a new time base not yet confirmed
        layout = None
        lo = hi = 0               # time-tag range seen while learning
        grid0 = ticks = hbytes = 0  # the stream's time grid and header size (from its layout)
        t_start = time.monotonic()
        last_valid = None
        self._next_log = time.monotonic() + (self.log_interval_s or 1e30)
        self._last_logged = dict(stats, garbage=stats["garbage"].copy())
        while True:
            if self._stop.is_set():
                self._finish(seq, learn, layout, "capture stopped")
                return "stopped"
            now = time.monotonic()
            if self.log_interval_s and now >= self._next_log:
                self._log_line()
            if last_valid is not None and now - last_valid > self.idle_timeout_s:
                self._finish(seq, learn, layout, f"no packet for {self.idle_timeout_s:g} s")
                seq = learn = layout = last_valid = jump = None
                if self.max_sequences and self._nseq >= self.max_sequences:
                    return "all sequences received"
            if (last_valid is None and self._nseq == 0 and self.start_timeout_s
                    and now - t_start > self.start_timeout_s):
                return f"no packet within {self.start_timeout_s:g} s"
            try:
                n = self.sock.recv_into(buf)
            except socket.timeout:
                continue
            except OSError:
                if self._stop.is_set():
                    continue
                raise
            stats["packets"] += 1
            stats["bytes"] += n
            if layout is None:
                got = fmt.probe(buf, n)
                if isinstance(got, str):
                    stats["garbage"][got] += 1
                    continue
                layout = self.layout = got          # what the stream is, for the service's real-time figure
                learn = []
                grid0, ticks, hbytes = layout.time_tag0, layout.sample_ticks, layout.header_bytes
            got = fmt.parse(buf, n, layout)
            if isinstance(got, str):
                stats["garbage"][got] += 1
                continue
            tt, fc = got
            off_grid = (tt - grid0) % ticks
            if off_grid and (seq is None or not seq.jumped(tt)):
                stats["garbage"]["time_grid"] += 1
                continue
            last_valid = time.monotonic()
            payload = mv[hbytes:n]
            if learn is not None:
                learn.append((tt, fc, bytes(payload)))
                lo, hi = (tt, tt) if len(learn) == 1 else (min(lo, tt), max(hi, tt))
                if (hi - lo) // ticks >= self._nwin(layout) or len(learn) >= self.max_learn_frames:
                    seq = self._begin(layout, learn)
                    learn = None
                continue
            # a frame off this sequence's time grid far ahead of it: the F-engine restarted on a new time
            # base (its samples need not fall on the old grid) -- a new sequence rather than garbage until
            # the idle timeout
            status = "resync" if off_grid else seq.insert(tt, fc, payload)
            if status == "resync":
                # taken when JUMP_CONFIRM frames agree on the new time base (its grid, within a resync's
                # reach), so that one corrupted time tag does not end the stream; the frames that agreed
                # begin the new sequence
                if jump is not None and not (tt - jump[0]) % ticks and abs(tt - jump[0]) // ticks <= seq.max_jump:
                    jump[1].append((tt, fc, bytes(payload)))
                else:                               # (an earlier candidate's frames stay garbage)
                    jump = (tt, [(tt, fc, bytes(payload))])
                garbage = stats["garbage"]
                garbage["time_jump"] += 1           # until confirmed
                if len(jump[1]) < self.JUMP_CONFIRM:
                    continue
                garbage["time_jump"] -= len(jump[1])
                if not garbage["time_jump"]:
                    del garbage["time_jump"]
                self._finish(seq, None, layout, "time jump (stream restarted?)")
                if self.max_sequences and self._nseq >= self.max_sequences:
                    return "all sequences received"
                seq, learn, jump = None, jump[1], None
                lo, hi = min(x[0] for x in learn), max(x[0] for x in learn)
                layout = dataclasses.replace(layout, time_tag0=lo)
                grid0 = lo

    def _nwin(self, layout):
        return max(1, int(math.ceil(self.buffer_s * layout.chan_bw_hz)))

    def _begin(self, layout, learn):
        tts = np.array([x[0] for x in learn], dtype=np.int64)
        if layout.nchan_blocks:  # every source of the F-engine is expected, heard or not
            blocks = np.arange(layout.nchan_blocks * layout.ninput_blocks, dtype=np.int64)
        else:
            blocks = np.unique(np.array([x[1] for x in learn], dtype=np.int64))
        info = SequenceInfo(layout, blocks, int(tts.min()), self._nseq)
        self._nseq += 1
        self.stats["sequences"] += 1
        self._emit(("start", info))
        log.info("%s: sequence %d: %s, %d stands, %d channels (%d sources, from channel %d), time tag %d",
                 self.label, info.index, layout.engine, layout.nstand, info.nchan, len(blocks),
                 int(info.channels[0]), info.time_tag0)
        seq = _Assembly(self, info, self._nwin(layout), int(math.ceil(self.resync_s * layout.chan_bw_hz)))
        for tt, fc, p in learn:
            seq.insert(tt, fc, p)
        return seq

    def _finish(self, seq, learn, layout, why):
        if seq is None and learn:
            seq = self._begin(layout, learn)
        if seq is not None:
            self.kernel_drops()
            seq.flush_all()
            self._emit(("end", why))
            log.info("%s: sequence %d ended (%s): %d samples", self.label, seq.info.index, why, seq.emitted)

    def kernel_drops(self):
        """Update and return ``stats['kernel_drops']`` (0 where the kernel does not say)."""
        n = socket_drops(self.sock)
        if n is not None:
            self.stats["kernel_drops"] = n
        return self.stats["kernel_drops"]

    def _log_line(self, force=False):
        self.kernel_drops()
        s, p = self.stats, self._last_logged
        now = time.monotonic()
        self._next_log = now + (self.log_interval_s or 1e30)
        d = {k: s[k] - p[k] for k in s if k != "garbage"}
        dg = sum(s["garbage"].values()) - sum(p["garbage"].values())
        if not force and d["packets"] == 0 and d["samples"] == 0:
            return
        extra = {}
        if self.extra_report is not None:
            try:
                extra = self.extra_report() or {}
            except Exception:  # noqa: BLE001 - a report must never stop the receiver
                extra = {}
        more = "".join(f", {k} {v}" for k, v in extra.items())
        log.info("%s: +%d packets (%.1f MB), %d dropped by the kernel, %d frames used, %d garbage, %d late, "
                 "%d duplicate; %d frames missing (zero-filled); %d samples out, %d overflowed%s | total %d packets, "
                 "%d garbage %s", self.label, d["packets"], d["bytes"] / 1e6, d["kernel_drops"], d["frames_used"], dg,
                 d["frames_late"],
                 d["frames_duplicate"], d["frames_missing"], d["samples"], d["samples_overflow"], more,
                 s["packets"], sum(s["garbage"].values()), dict(s["garbage"]) or "")
        self._last_logged = dict(s, garbage=s["garbage"].copy())


class _Assembly:
    """The window of time slots of one sequence (receiver thread only).

    Slots hold ``2 * nwin`` samples; when a frame lands ``2 * nwin`` or more samples past the oldest
    open slot, the slots older than ``nwin`` samples before it are emitted (in order, missing frames
    zero-filled and counted), so reordering up to ``nwin`` samples is always undone.
    """

    def __init__(self, cap: UDPCapture, info: SequenceInfo, nwin: int, max_jump: int):
        self.cap, self.info, self.nwin, self.max_jump = cap, info, nwin, max_jump
        lay = info.layout
        self.nslot = 2 * nwin
        self.nblock = len(info.blocks)
        self.block_index = {int(b): i for i, b in enumerate(info.blocks)}
        self.pbytes = lay.payload_bytes
        self.slots = np.zeros((self.nslot, self.nblock, self.pbytes), np.uint8)
        self._slots_mv = memoryview(self.slots.reshape(-1))  # per-frame copies without NumPy overhead
        self._have = bytearray(self.nslot * self.nblock)
        self.have = np.frombuffer(self._have, np.uint8).reshape(self.nslot, self.nblock)
        self.tt0, self.ticks = int(info.time_tag0), lay.sample_ticks
        self.base = 0           # time index of the oldest open slot
        self.hi = 0             # 1 + the largest time index seen
        self.chunk = None       # the gulp being filled
        self.chunk_t0 = 0
        self.chunk_n = 0
        self.emitted = 0
        self.frame_shape = (info.nchan, lay.nstand, 2)

    def jumped(self, tt):
        """Whether time tag ``tt`` lies further ahead of the newest sample than a resync allows."""
        return (tt - self.tt0) // self.ticks - self.hi > self.max_jump

    def insert(self, tt, fc, payload):
        """Put one frame (payload: bytes-like of payload_bytes) into its slot; 'resync' on a big jump."""
        st = self.cap.stats
        bi = self.block_index.get(fc)
        if bi is None:
            st["frames_unknown_block"] += 1
            return None
        ti = (tt - self.tt0) // self.ticks
        if ti < self.base:
            st["frames_late"] += 1
            return None
        if ti >= self.base + self.nslot:
            if ti - self.hi > self.max_jump:
                return "resync"
            self.flush_to(ti - self.nwin + 1)
        cell = (ti % self.nslot) * self.nblock + bi
        if self._have[cell]:
            st["frames_duplicate"] += 1
            return None
        off = cell * self.pbytes
        self._slots_mv[off:off + self.pbytes] = payload
        self._have[cell] = 1
        st["frames_used"] += 1
        if ti >= self.hi:
            self.hi = ti + 1
        return None

    def flush_to(self, t_end):
        """Emit samples [base, t_end) in order (missing frames zero-filled and counted)."""
        st = self.cap.stats
        while self.base < t_end:
            if self.chunk is None:
                self.chunk = np.empty((self.cap.gulp,) + self.frame_shape, np.uint8)
                self.chunk_t0, self.chunk_n = self.base, 0
            s0 = self.base % self.nslot
            n = min(t_end - self.base, self.nslot - s0, self.cap.gulp - self.chunk_n)
            sl = slice(s0, s0 + n)
            st["frames_missing"] += int(n * self.nblock - np.count_nonzero(self.have[sl]))
            self.chunk[self.chunk_n:self.chunk_n + n] = self.cap.fmt.to_samples(self.slots[sl], self.info.layout)
            self.slots[sl] = 0
            self.have[sl] = 0
            self.chunk_n += n
            self.base += n
            st["samples"] += n
            self.emitted += n
            if self.chunk_n == self.cap.gulp:
                self._hand_off()

    def _hand_off(self):
        if self.chunk is not None and self.chunk_n:
            self.cap._emit(("data", self.chunk_t0, self.chunk[:self.chunk_n]))
        self.chunk = None
        self.chunk_n = 0

    def flush_all(self):
        self.flush_to(self.hi)
        self._hand_off()


# ------------------------------------------------------------------------------------------------
# Replay
# ------------------------------------------------------------------------------------------------
@dataclass
class ReplayResult:
    """What :func:`replay` did: frames in the file, packets sent, indices (file order) dropped."""
    nframe: int
    sent: int
    dropped: list = field(default_factory=list)
    wall_s: float = 0.0
    data_s: float = 0.0
    sync_time: int | None = None  # chips/snap2: the sync time (UNIX s) the packets count from

    @property
    def rate_achieved(self) -> float:
        """Data seconds per wall second actually achieved (inf for a single-time-tag file)."""
        return self.data_s / self.wall_s if self.wall_s > 0 else float("inf")


def _is_loopback(host):
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


def choose_drops(nframe, drop, seed):
    """Indices (sorted, file order) of the round(drop * nframe) frames to drop, reproducible by seed."""
    if not 0 <= drop < 1:
        raise ValueError(f"drop must be a fraction in [0, 1), got {drop!r}")
    k = int(round(drop * nframe))
    if k == 0:
        return np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(nframe, size=k, replace=False)).astype(np.int64)


def replay(path, host, port, rate=1.0, drop=0.0, seed=None, fmt="tbf", allow_remote=False, stop=None,
           sndbuf_bytes=8 << 20, loops=1, shift_s=0.0):
    """Send the frames of a capture file as UDP datagrams, paced at ``rate`` x real time.

    Frames go out in file order; frame i leaves when the wall clock since the start reaches
    (max time tag so far - first time tag) / 196 MHz / rate (a sender that falls behind sends at once).
    ``drop``: fraction of frames not sent, exactly round(drop * nframe) of them, chosen by
    ``seed`` (:func:`choose_drops`); with ``loops`` other than 1, each frame of each pass with probability
    ``drop`` instead (a short file's passes would otherwise drop none), drawn from ``seed``. ``stop``: an Event that ends the replay
    early. ``loops``: passes over the file (0: until ``stop``), each pass's time tags after the last's by
    the file's span and one sample, so that the passes are one continuous stream (a soak from a short
    file). ``shift_s``: seconds added to every time tag -- replayed after another replay, a jump in the
    stream's time base, as an F-engine reset makes. Both rewrite the frames' time tags, which TBF and
    TBX frames carry (the chips and snap2 streams count from their sync time: refused).
    Returns a :class:`ReplayResult` (nframe: frames of one pass; sent: over all passes; dropped =
    file-order frame indices, counted over the passes: pass * nframe + index).
    """
    if not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate!r}")
    if isinstance(loops, bool) or int(loops) != loops or loops < 0:
        raise ValueError(f"loops must be an integer >= 0 (0 = until stopped), got {loops!r}")
    if not math.isfinite(float(shift_s)):
        raise ValueError(f"shift_s must be a finite number of seconds, got {shift_s!r}")
    if not allow_remote and not _is_loopback(host):
        raise ValueError(f"replay sends only to a loopback address (127.0.0.1) unless allowed; got {host!r}")
    fmt = packet_format(fmt) if isinstance(fmt, str) else fmt
    rewrite = int(loops) != 1 or float(shift_s) != 0.0
    if rewrite and fmt.time_tag_bytes is None:
        raise ValueError(f"loops and shift_s rewrite the frames' time tags, which {fmt.name} packets do not "
                         "carry (they count from a sync time); replay the file as tbf or tbx frames")
    frames, tts = fmt.file_frames(path)
    nframe = len(tts)
    per_pass = int(loops) != 1 and drop > 0
    if per_pass and not 0.0 <= float(drop) < 1.0:
        raise ValueError(f"drop must be in [0, 1), got {drop!r}")
    dropped = [] if per_pass else [int(i) for i in choose_drops(nframe, drop, seed)]
    rng = np.random.default_rng(seed) if per_pass else None
    keep = np.ones(nframe, bool)
    keep[dropped] = False
    span = 0
    if rewrite and nframe:
        lay = fmt.probe(np.ascontiguousarray(frames[0]).tobytes(), frames.shape[1])
        step = lay.sample_ticks if not isinstance(lay, str) else 1
        span = int(tts.max() - tts.min()) + step
    base = tts + int(round(float(shift_s) * FS_HZ)) if nframe else tts
    due = (np.maximum.accumulate(tts) - tts.min()) / FS_HZ / rate if nframe else tts
    pass_s = span / FS_HZ / rate
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent, passes = 0, 0
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(sndbuf_bytes))
        addr = (host, int(port))
        fb = frames.shape[1] if nframe else 0
        send, clock, sleep = sock.sendto, time.perf_counter, time.sleep
        keep_l = keep.tolist()     # plain Python: per-packet NumPy indexing is slow
        t0 = clock()
        while nframe and (loops == 0 or passes < loops) and not (stop is not None and stop.is_set()):
            if rewrite:            # this pass's frames with their time tags moved on (a copy: the file is read-only)
                buf = np.array(frames, dtype=np.uint8)
                a, b = fmt.time_tag_bytes
                buf[:, a:b] = (base + passes * span).astype(">i8").view(np.uint8).reshape(nframe, 8)
                flat = memoryview(buf.reshape(-1))
            else:
                flat = memoryview(np.ascontiguousarray(frames).reshape(-1))  # no copy for a memmap
            due_s = (due + passes * pass_s).tolist()
            if per_pass:
                miss = rng.random(nframe) < drop
                keep_l = (~miss).tolist()
                dropped.extend(int(i) + passes * nframe for i in np.flatnonzero(miss))
            for i in range(nframe):
                if stop is not None and stop.is_set():
                    break
                wait = due_s[i] - (clock() - t0)
                if wait > 1e-3:
                    sleep(wait)
                if keep_l[i]:
                    while True:
                        try:
                            send(flat[i * fb:(i + 1) * fb], addr)
                            break
                        except BlockingIOError:  # the local send buffer is full: let it drain
                            sleep(1e-4)
                    sent += 1
            passes += 1
        wall = time.perf_counter() - t0
    finally:
        sock.close()
    data_s = float((tts.max() - tts.min()) / FS_HZ) if nframe else 0.0
    if passes > 1:
        data_s = passes * span / FS_HZ
    return ReplayResult(nframe=nframe, sent=sent, dropped=dropped, wall_s=wall, data_s=data_s,
                        sync_time=getattr(fmt, "replay_sync_time", None))
