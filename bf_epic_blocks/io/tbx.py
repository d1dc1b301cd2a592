"""Reader and writer for LWA TBX files (NDP transient buffer, frequency domain), pure NumPy.

TBX is what NDP stations (LWA-NA, and LWA-SV since its NDP upgrade) record as the transient buffer;
LSL 4 reads it with ``lsl.reader.tbx`` (the reference the tests compare this reader against, byte
for byte). Format (all fields big-endian; from LSL 4.0.1 ``lsl/reader/tbx.cpp``)::

    offset  size  field
    0       u32   sync word 0xDEC0DE5C
    4       u8    frame id (8 = TBX)
    5       u24   frame count
    8       u32   second count
    12      u32   first channel (index of the frame's first channel)
    16      u16   number of stands
    18      u16   number of channels in the frame (LSL reads 4, 8, 12 or 16)
    20      i64   time tag: ticks of the 196 MHz sampling clock since the Unix epoch
    28      ...   payload: nchan x nstand x 2 pols, one byte per complex sample
                  (high nibble = real, low nibble = imaginary, each 4-bit two's complement)

Frame size = 28 + nchan * nstand * 2 bytes (LWA-NA: 64 stands, 12 channels -> 1,564 bytes).
Channel k is centred on k * 196 MHz / 8192 (23,925.78125 Hz), one time sample is 8,192 ticks.
The stand axis is LSL's digitizer order, as for TBF: ``station.antennas[k]`` is stand index
``k // 2``, polarisation ``k % 2``.

Same semantics and error style as :mod:`bf_epic_blocks.io.tbf` (whose docstring lists them): frames
grouped by (time tag, first channel); a missing (time tag, block) frame zero-filled and counted in
``stats['frames_missing']``; repeated frames keep the first copy (``frames_duplicate``); time-tag steps
larger than one sample counted (``time_gaps``); a truncated tail ignored, counted
(``truncated_bytes``) and reported with a :class:`TBXWarning`; a bad sync word, a frame id other
than 8, a stand or channel count unlike the first frame's, or a first channel not aligned to the
first frame's blocks raises :class:`TBXError` naming the byte offset. Files are memory-mapped and
the payloads gathered with NumPy fancy indexing, one gulp at a time.

Public pieces shared with the live (UDP) source: :func:`parse_tbx_frame` (one frame's bytes ->
time tag, first channel, payload view), :func:`parse_tbx_header`, :func:`tbx_frame_bytes`,
:data:`HEADER_BYTES`, :data:`FRAME_ID`, :data:`LWANA_FRAME_BYTES` and the writer
:func:`pack_tbx_frame` / :func:`write_tbx`.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

from .formats import SYNC_WORD, CaptureGrid
from ..conventions import FS_HZ
from .tbf import TBFData, _check_gulp, _iter_gulps, release_rows

__all__ = ["TBXData", "TBXInfo", "TBXError", "TBXWarning", "TBXFrame", "TBXHeader", "read_tbx", "iter_tbx_gulps",
           "scan_tbx", "parse_tbx_frame", "parse_tbx_header", "tbx_frame_bytes", "pack_tbx_frame", "write_tbx",
           "FRAME_ID", "HEADER_BYTES", "CHAN_BW_HZ", "SAMPLE_TICKS", "LWANA_FRAME_BYTES", "LSL_NSTAND",
           "LSL_NCHAN", "HEADER_DTYPE"]

#: Frame id of TBX frames (byte 4).
FRAME_ID = 8
#: Header bytes before the payload: 20 bytes of header plus the 8-byte time tag.
HEADER_BYTES = 28
#: NDP channel width, Hz (196 MHz / 8192).
CHAN_BW_HZ = FS_HZ / 8192
#: Time-tag ticks per time sample.
SAMPLE_TICKS = 8192
#: Stand and per-frame channel counts LSL 4.0.1's reader accepts (others it calls a sync error).
LSL_NSTAND = (64, 128, 256)
LSL_NCHAN = (4, 8, 12, 16)
#: Structured dtype of the 28 header bytes.
HEADER_DTYPE = np.dtype([("sync", ">u4"), ("id_count", ">u4"), ("second", ">u4"), ("first_chan", ">u4"),
                         ("nstand", ">u2"), ("nchan", ">u2"), ("time_tag", ">i8")])
assert HEADER_DTYPE.itemsize == HEADER_BYTES


def tbx_frame_bytes(nchan: int, nstand: int) -> int:
    """Bytes of one TBX frame holding ``nchan`` channels of ``nstand`` dual-pol stands."""
    return HEADER_BYTES + int(nchan) * int(nstand) * 2


#: Frame size of LWA-NA's TBX (64 stands, 12 channels per frame): 1,564 bytes.
LWANA_FRAME_BYTES = tbx_frame_bytes(12, 64)


class TBXError(ValueError):
    """A malformed TBX file or frame; ``offset`` is the byte offset of the offending frame (or None)."""

    def __init__(self, message: str, offset: int | None = None):
        super().__init__(message)
        self.offset = offset


class TBXWarning(UserWarning):
    """A recoverable irregularity in a TBX file (truncated tail)."""


class TBXHeader(NamedTuple):
    """The decoded 28 header bytes of one frame."""
    frame_id: int
    frame_count: int
    second_count: int
    first_chan: int
    nstand: int
    nchan: int
    time_tag: int

    @property
    def frame_bytes(self) -> int:
        return tbx_frame_bytes(self.nchan, self.nstand)


class TBXFrame(NamedTuple):
    """One parsed frame: ``time_tag`` (int, 196 MHz ticks since the Unix epoch), ``first_chan``
    (int, channel index of payload row 0) and ``payload`` (uint8 ``(nchan, nstand, 2)`` packed ci4:
    high nibble real, low nibble imaginary; pol 0 = X, 1 = Y)."""
    time_tag: int
    first_chan: int
    payload: np.ndarray


def _as_u8(buf) -> np.ndarray:
    if isinstance(buf, np.ndarray):
        if buf.dtype != np.uint8:
            raise TypeError(f"TBX frame buffer must hold uint8 bytes, got dtype {buf.dtype}")
        return buf.reshape(-1)
    return np.frombuffer(buf, dtype=np.uint8)


def parse_tbx_header(buf, offset: int = 0) -> TBXHeader:
    """Decode and check the header of the frame starting at byte ``offset`` of ``buf``.

    ``buf``: bytes, bytearray, memoryview or a uint8 array. Raises :class:`TBXError` (with
    ``offset``) for fewer than 28 bytes, a bad sync word, a frame id other than 8, or a zero stand
    or channel count.
    """
    u8 = _as_u8(buf)
    if u8.size - offset < HEADER_BYTES:
        raise TBXError(f"at byte offset {offset}: {max(0, u8.size - offset)} bytes is shorter than a TBX "
                       f"header ({HEADER_BYTES} bytes)", offset)
    h = u8[offset:offset + HEADER_BYTES].copy().view(HEADER_DTYPE)[0]
    if int(h["sync"]) != SYNC_WORD:
        raise TBXError(f"at byte offset {offset}: bad sync word 0x{int(h['sync']):08X} "
                       f"(expected 0x{SYNC_WORD:08X})", offset)
    fid = int(h["id_count"]) >> 24
    if fid != FRAME_ID:
        raise TBXError(f"at byte offset {offset}: frame id {fid} is not the TBX frame id {FRAME_ID}"
                       + (" (it is a TBF frame id)" if fid in (1, 5) else ""), offset)
    nstand, nchan = int(h["nstand"]), int(h["nchan"])
    if nstand <= 0 or nchan <= 0:
        raise TBXError(f"at byte offset {offset}: invalid stand/channel counts {nstand}/{nchan}", offset)
    return TBXHeader(frame_id=fid, frame_count=int(h["id_count"]) & 0xFFFFFF, second_count=int(h["second"]),
                     first_chan=int(h["first_chan"]), nstand=nstand, nchan=nchan, time_tag=int(h["time_tag"]))


def parse_tbx_frame(buf, offset: int = 0, *, copy: bool = False) -> TBXFrame:
    """Parse one TBX frame: ``(time_tag, first_chan, payload)``.

    ``buf``: bytes / bytearray / memoryview / uint8 array holding a whole frame from byte
    ``offset`` (a UDP datagram is one frame). ``payload`` is uint8 ``(nchan, nstand, 2)`` packed
    ci4, a zero-copy view into ``buf`` (read-only for bytes) unless ``copy=True``; unpack it with
    :func:`bf_epic_blocks.io.tbf.unpack_ci4`. Raises :class:`TBXError` for a bad header (see
    :func:`parse_tbx_header`) or a buffer shorter than the frame its header announces.
    """
    h = parse_tbx_header(buf, offset)
    u8 = _as_u8(buf)
    need = h.frame_bytes
    if u8.size - offset < need:
        raise TBXError(f"at byte offset {offset}: truncated TBX frame: {u8.size - offset} bytes, the header "
                       f"announces {need} ({h.nchan} channels x {h.nstand} stands)", offset)
    payload = u8[offset + HEADER_BYTES:offset + need].reshape(h.nchan, h.nstand, 2)
    return TBXFrame(h.time_tag, h.first_chan, payload.copy() if copy else payload)


def pack_tbx_frame(time_tag: int, first_chan: int, payload, *, frame_count: int = 0, second_count: int = 0) -> bytes:
    """The bytes of one TBX frame (the inverse of :func:`parse_tbx_frame`).

    payload : uint8 ``(nchan, nstand, 2)`` packed ci4 (see :func:`bf_epic_blocks.io.tbf.pack_ci4`).
    """
    p = np.asarray(payload)
    if p.dtype != np.uint8 or p.ndim != 3 or p.shape[2] != 2:
        raise ValueError(f"pack_tbx_frame: payload must be uint8 (nchan, nstand, 2), got {p.dtype} {p.shape}")
    h = np.zeros(1, HEADER_DTYPE)
    h["sync"] = SYNC_WORD
    h["id_count"] = (FRAME_ID << 24) | (int(frame_count) & 0xFFFFFF)
    h["second"], h["first_chan"] = int(second_count), int(first_chan)
    h["nstand"], h["nchan"], h["time_tag"] = p.shape[1], p.shape[0], int(time_tag)
    return h.tobytes() + np.ascontiguousarray(p).tobytes()


def write_tbx(path, data, time_tags, first_chan: int, *, nchan_frame: int = 12, order=None) -> int:
    """Write packed ci4 voltages as a TBX file; returns the number of frames written.

    data : uint8 ``(ntime, nchan, nstand, 2)``, nchan a multiple of ``nchan_frame``;
    time_tags : ``(ntime,)`` ints; channel index of ``data[:, c]`` is ``first_chan + c``.
    Frames go out time by time, blocks in increasing channel order (as NDP writes them), or in
    ``order`` (a permutation of the frame indices t * nblock + b) to test readers.
    """
    d = np.asarray(data)
    if d.dtype != np.uint8 or d.ndim != 4 or d.shape[3] != 2:
        raise ValueError(f"write_tbx: data must be uint8 (ntime, nchan, nstand, 2), got {d.dtype} {d.shape}")
    ntime, nchan = d.shape[:2]
    if nchan % nchan_frame:
        raise ValueError(f"write_tbx: {nchan} channels is not a multiple of nchan_frame={nchan_frame}")
    tags = np.asarray(time_tags, dtype=np.int64)
    if tags.shape != (ntime,):
        raise ValueError(f"write_tbx: time_tags must be ({ntime},), got {tags.shape}")
    nblock = nchan // nchan_frame
    frames = [pack_tbx_frame(int(tags[t]), first_chan + b * nchan_frame, d[t, b * nchan_frame:(b + 1) * nchan_frame],
                             frame_count=t, second_count=int(tags[t] // FS_HZ))
              for t in range(ntime) for b in range(nblock)]
    if order is not None:
        frames = [frames[i] for i in order]
    with open(path, "wb") as fh:
        fh.write(b"".join(frames))
    return len(frames)


@dataclass
class TBXInfo(CaptureGrid):
    """What one header pass over a TBX file finds (no payload read): the grid (:class:`CaptureGrid`)
    and the channels per frame, as :class:`~.tbf.TBFInfo`."""
    nchan_frame: int
    frame_id: int = FRAME_ID
    engine: str = "NDP"
    chan_bw_hz: float = CHAN_BW_HZ

    @property
    def station_hint(self) -> str:
        """The NDP station with this many stands: 64 -> 'lwana', 256 -> 'lwasv' (after its NDP upgrade)."""
        return _station_hint(self.nstand)


def _station_hint(nstand: int) -> str:
    return {64: "lwana", 256: "lwasv"}.get(int(nstand), "lwana" if nstand <= 64 else "lwasv")


@dataclass
class TBXData(TBFData):
    """A stretch of TBX data on a regular (time tag, channel) grid: the same attributes, methods and
    ``stats`` as :class:`~.tbf.TBFData` (``data`` uint8 (ntime, nchan, nstand, 2) packed ci4,
    ``time_tags``, ``channels``, ``chan_bw_hz`` = 196 MHz / 8192, ``frame_id`` = 8)."""

    @property
    def station_hint(self) -> str:
        return _station_hint(self.nstand)


def _open_frames(path):
    """Memory-map the file by the first frame's size: (uint8 (nframe, frame_bytes) map, first header, facts)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"TBX file not found: {path}")
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        head = fh.read(HEADER_BYTES)
    try:
        h0 = parse_tbx_header(head)
    except TBXError as e:
        raise TBXError(f"{path}: {e} (frame 0): not a TBX file?", 0) from None
    fb = h0.frame_bytes
    nframe = size // fb
    if nframe == 0:
        raise TBXError(f"{path}: {size} bytes holds no complete frame ({fb} bytes each for {h0.nchan} channels "
                       f"x {h0.nstand} stands)", 0)
    mm = np.memmap(path, dtype=np.uint8, mode="r", shape=(nframe, fb))
    return mm, h0, dict(path=path, frame_bytes=fb, nframe=nframe, truncated=size - nframe * fb)


def scan_tbx(path, *, chunk_frames: int = 8192, warn: bool = True) -> TBXInfo:
    """Header pass: validate every complete frame and find the (time tag, channel block) grid.

    Raises TBXError (with the byte offset) for a bad sync word, a frame id other than 8, a stand or
    channel count unlike the first frame's, or a first channel not aligned to the first frame's
    blocks. A truncated tail gives a TBXWarning.
    """
    mm, h0, f = _open_frames(path)
    fb, nframe = f["frame_bytes"], f["nframe"]
    tts, fcs = [], []
    for i0 in range(0, nframe, chunk_frames):
        i1 = min(nframe, i0 + chunk_frames)
        h = np.ascontiguousarray(mm[i0:i1, :HEADER_BYTES]).view(HEADER_DTYPE).ravel()
        release_rows(mm, i0, i1)
        problems = []
        bad = np.flatnonzero(h["sync"] != SYNC_WORD)
        if bad.size:
            problems.append((bad[0], f"bad sync word 0x{int(h['sync'][bad[0]]):08X} (expected 0x{SYNC_WORD:08X})"))
        fid = h["id_count"] >> 24
        bad = np.flatnonzero(fid != FRAME_ID)
        if bad.size:
            problems.append((bad[0], f"frame id {int(fid[bad[0]])} is not the TBX frame id {FRAME_ID}"))
        bad = np.flatnonzero(h["nstand"] != h0.nstand)
        if bad.size:
            problems.append((bad[0], f"stand count {int(h['nstand'][bad[0]])} differs from the first frame's "
                                     f"{h0.nstand}"))
        bad = np.flatnonzero(h["nchan"] != h0.nchan)
        if bad.size:
            problems.append((bad[0], f"channel count {int(h['nchan'][bad[0]])} differs from the first frame's "
                                     f"{h0.nchan}"))
        fc = h["first_chan"].astype(np.int64)
        bad = np.flatnonzero((fc - h0.first_chan) % h0.nchan != 0)
        if bad.size:
            problems.append((bad[0], f"first channel {int(fc[bad[0]])} is not aligned to the {h0.nchan}-channel "
                                     f"blocks of the first frame (first channel {h0.first_chan})"))
        if problems:
            k, what = min(problems, key=lambda p: p[0])
            idx = i0 + int(k)
            raise TBXError(f"{f['path']}: at byte offset {idx * fb} (frame {idx}): {what}", idx * fb)
        tts.append(h["time_tag"].astype(np.int64))
        fcs.append(fc)
    tt, fc = np.concatenate(tts), np.concatenate(fcs)
    time_tags, t_idx = np.unique(tt, return_inverse=True)
    blocks, b_idx = np.unique(fc, return_inverse=True)
    if f["truncated"] and warn:
        warnings.warn(f"{f['path']}: {f['truncated']} trailing bytes (a truncated frame) ignored after "
                      f"{nframe} complete frames", TBXWarning, stacklevel=2)
    return TBXInfo(path=f["path"], nstand=h0.nstand, nchan_frame=h0.nchan, frame_bytes=fb, nframe=nframe,
                   truncated_bytes=f["truncated"], time_tags=time_tags, blocks=blocks,
                   frame_time_index=t_idx.ravel().astype(np.int64), frame_block_index=b_idx.ravel().astype(np.int64))


def iter_tbx_gulps(path, gulp_ntime: int, *, info: TBXInfo | None = None, raw=False) -> Iterator[TBXData]:
    """Stream a TBX file as :class:`TBXData` chunks of ``gulp_ntime`` time tags (the last may be shorter).

    Every chunk has the file's full channel axis, so chunks concatenate along time into
    :func:`read_tbx`'s result and their ``stats`` add up to it. ``info``: a :func:`scan_tbx` result to reuse.
    ``raw``: as :func:`bf_epic_blocks.io.tbf.iter_tbf_gulps`.
    """
    _check_gulp(gulp_ntime)
    if info is None:
        info = scan_tbx(path, warn=True)
    mm, _, _ = _open_frames(path)
    yield from _iter_gulps(mm, info, gulp_ntime, HEADER_BYTES, TBXData, raw=raw)


def read_tbx(path) -> TBXData:
    """Read a whole TBX file into one :class:`TBXData`."""
    info = scan_tbx(path, warn=True)
    return next(iter_tbx_gulps(path, max(info.ntime, 1), info=info))
