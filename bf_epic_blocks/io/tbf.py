"""Reader for LWA TBF files (frequency-domain transient-buffer F-engine captures), pure NumPy.

Format (all header fields big-endian; see ``data/lwa/README.md``)::

    offset  size  field
    0       u32   sync word 0xDEC0DE5C
    4       u8    frame id (1 = ADP TBF, LWA-SV; 5 = NDP TBF, LWA-NA)
    5       u24   frame count
    8       u32   second count
    12      i16   first channel (index of the first of the frame's 12 channels)
    14      i16   number of stands (0 in old ADP frames means 256)
    16      i64   time tag: ticks of the 196 MHz sampling clock since the Unix epoch
    24      ...   payload: 12 channels x nstand x 2 pols, one byte per complex sample
                  (high nibble = real, low nibble = imaginary, each 4-bit two's complement)

Frame size = 24 + 12 * nstand * 2 bytes. Channel k is centred on k * channel width (ADP 25 kHz,
NDP 196 MHz / 8192). The stand axis is LSL's digitizer order: LSL ``station.antennas[k]`` is stand
index ``k // 2``, polarisation ``k % 2`` (0 = X = N-S dipole, 1 = Y = E-W), so
``data.reshape(ntime, nchan, 2 * nstand)[..., k]`` is antenna k.

Output layout (:class:`TBFData`): ``data`` uint8 ``(ntime, nchan, nstand, 2)`` in the packed ci4 form
(call :meth:`TBFData.unpack` or :func:`unpack_ci4` for complex values); ``time_tags`` int64
``(ntime,)``, the sorted distinct time tags found; ``channels`` ``(nchan,)`` sorted channel indices,
the union of all the 12-channel blocks found in the file.

Robustness:

* A file interleaves frames of different first channels sharing a time tag; frames need not be in
  time order. Frames are grouped by (time tag, first channel).
* A (time tag, channel block) combination absent from the file is zero-filled (byte 0 = 0+0j) and
  counted in ``stats['frames_missing']``. A time tag absent altogether is NOT inserted (the time
  axis holds the time tags present); steps larger than one sample are counted in
  ``stats['time_gaps']``.
* A repeated (time tag, block) frame keeps the first copy and is counted in ``stats['frames_duplicate']``.
* Trailing bytes shorter than one frame (a truncated last frame) are ignored, counted in
  ``stats['truncated_bytes']`` and reported once with a :class:`TBFWarning`.
* A bad sync word, a frame id or stand count differing from the first frame's, or a first channel
  that is negative or not aligned to the first frame's 12-channel blocks raises :class:`TBFError`
  (a ``ValueError``) naming the byte offset of the offending frame.

Files are memory-mapped: :func:`iter_tbf_gulps` reads one header pass and then only the frames of
each gulp, so files larger than memory stream in bounded memory.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ..conventions import FS_HZ
from .formats import CaptureGrid

__all__ = ["TBFData", "TBFInfo", "TBFError", "TBFWarning", "read_tbf", "iter_tbf_gulps", "scan_tbf",
           "unpack_ci4", "pack_ci4", "time_tag_to_time", "SYNC_WORD", "FS_HZ", "CHANNELS_PER_FRAME",
           "HEADER_BYTES", "FRAME_KINDS", "write_tbf"]

SYNC_WORD = 0xDEC0DE5C
#: Sampling clock of the LWA digitisers; time tags count its ticks since the Unix epoch.
CHANNELS_PER_FRAME = 12
HEADER_BYTES = 24
#: frame id -> (F-engine, station whose TBF uses it, channel width in Hz)
FRAME_KINDS = {
    1: ("ADP", "lwasv", 25_000.0),
    5: ("NDP", "lwana", FS_HZ / 8192),
}

_HEADER_DTYPE = np.dtype([("sync", ">u4"), ("id_count", ">u4"), ("second", ">u4"),
                          ("first_chan", ">i2"), ("nstand", ">i2"), ("time_tag", ">i8")])
assert _HEADER_DTYPE.itemsize == HEADER_BYTES

# Lookup table byte -> (re, im) int8 for the integer unpack.
_NIB = np.arange(16, dtype=np.int16)
_NIB = np.where(_NIB >= 8, _NIB - 16, _NIB)
_B = np.arange(256)
_LUT_I8 = np.stack([_NIB[_B >> 4], _NIB[_B & 0xF]], axis=-1).astype(np.int8)  # (256, 2) re, im


class TBFError(ValueError):
    """A malformed TBF file; ``offset`` is the byte offset of the offending frame (or None)."""

    def __init__(self, message: str, offset: int | None = None):
        super().__init__(message)
        self.offset = offset


class TBFWarning(UserWarning):
    """A recoverable irregularity in a TBF file (truncated tail)."""


def unpack_ci4(packed, dtype=np.complex64):
    """Decode packed ci4 bytes to complex values of the same shape.

    High nibble = real, low nibble = imaginary, both 4-bit two's complement (-8..7).
    ``dtype``: a complex dtype (complex64/complex128), or ``'int8'`` to get int8 ``(..., 2)`` (re, im).
    The complex decoding is the ring runtime's (:func:`bf_epic_blocks.runtime.dtypes.unpack_complex`).
    """
    from ..runtime.dtypes import unpack_complex
    packed = np.asarray(packed)
    if packed.dtype != np.uint8:
        raise TypeError(f"unpack_ci4 expects uint8 packed ci4 bytes, got dtype {packed.dtype}")
    if np.dtype(dtype) == np.int8:
        return _LUT_I8[packed]
    if np.dtype(dtype).kind != "c":
        raise TypeError(f"unpack_ci4: dtype must be complex64, complex128 or int8, got {dtype}")
    return unpack_complex(packed, "ci4").astype(dtype, copy=False)


def pack_ci4(values) -> np.ndarray:
    """Pack complex values with integer real/imag parts in -8..7 into ci4 bytes (uint8, same shape).

    Raises ValueError for non-integer or out-of-range parts (round and clip first; see
    :func:`bf_epic_blocks.sky.quantize_ci4`).
    """
    v = np.asarray(values)
    re = np.real(v)
    im = np.imag(v) if np.iscomplexobj(v) else np.zeros_like(re)
    for name, part in (("real", re), ("imaginary", im)):
        if part.size and (np.any(part != np.round(part)) or part.min() < -8 or part.max() > 7):
            raise ValueError(f"pack_ci4: {name} parts must be integers in -8..7 "
                             f"(got range {part.min()}..{part.max()})")
    from ..runtime.dtypes import pack_ci4 as _pack  # the one packer; this wrapper only refuses to round
    return _pack(re + 1j * im)


def time_tag_to_time(time_tag):
    """astropy ``Time`` (UTC) for time tag(s) in 196 MHz ticks since the Unix epoch.

    Split into integer seconds + fraction so that no precision is lost to a float64 of ~1e17 ticks.
    """
    from astropy.time import Time
    tt = np.asarray(time_tag, dtype=np.int64)
    sec, frac = np.divmod(tt, FS_HZ)
    return Time(sec.astype(np.float64), frac / FS_HZ, format="unix", scale="utc")


@dataclass
class TBFInfo(CaptureGrid):
    """What one header pass over a TBF file finds (no payload read): the grid (:class:`CaptureGrid`)
    and the frame id (1 = ADP, 5 = NDP)."""
    frame_id: int

    @property
    def engine(self) -> str:
        return FRAME_KINDS[self.frame_id][0]

    @property
    def station_hint(self) -> str:
        return FRAME_KINDS[self.frame_id][1]

    @property
    def chan_bw_hz(self) -> float:
        return FRAME_KINDS[self.frame_id][2]

    @property
    def nchan_frame(self) -> int:
        return CHANNELS_PER_FRAME


@dataclass
class TBFData:
    """A stretch of TBF data on a regular (time tag, channel) grid.

    Attributes
    ----------
    data : uint8 (ntime, nchan, nstand, 2), packed ci4 (high nibble real); zero where missing.
    time_tags : int64 (ntime,), 196 MHz ticks since the Unix epoch, sorted.
    channels : int64 (nchan,), channel indices, sorted; frequency = channel * chan_bw_hz.
    chan_bw_hz : channel width, Hz (ADP 25e3, NDP 196e6/8192).
    frame_id : 1 (ADP) or 5 (NDP).
    stats : counts, additive over the gulps of :func:`iter_tbf_gulps`: ``frames_read``,
        ``frames_expected`` (ntime * nblock), ``frames_missing`` (zero-filled), ``frames_duplicate``,
        ``time_gaps`` (time-tag steps larger than one sample), ``truncated_bytes`` (the file's
        truncated tail; in the last gulp only).
    """
    data: np.ndarray
    time_tags: np.ndarray
    channels: np.ndarray
    chan_bw_hz: float
    frame_id: int
    stats: dict = field(default_factory=dict)

    @property
    def nstand(self) -> int:
        return self.data.shape[2]

    @property
    def ntime(self) -> int:
        return self.data.shape[0]

    @property
    def nchan(self) -> int:
        return self.data.shape[1]

    @property
    def freq_hz(self) -> np.ndarray:
        """Channel centre frequencies, float64 Hz (nchan,)."""
        return self.channels.astype(np.float64) * self.chan_bw_hz

    @property
    def station_hint(self) -> str:
        """'lwasv' for ADP frames (id 1), 'lwana' for NDP frames (id 5)."""
        return FRAME_KINDS[self.frame_id][1]

    @property
    def sample_ticks(self) -> int:
        """Time-tag step of one sample (FS_HZ / channel width): 7840 (ADP), 8192 (NDP)."""
        return int(round(FS_HZ / self.chan_bw_hz))

    @property
    def times(self):
        """astropy Time (UTC) of each time tag."""
        return time_tag_to_time(self.time_tags)

    def unpack(self, dtype=np.complex64) -> np.ndarray:
        """Complex voltages (ntime, nchan, nstand, 2) in 4-bit units; see :func:`unpack_ci4`."""
        return unpack_ci4(self.data, dtype)


def _open_frames(path) -> tuple[np.memmap | np.ndarray, dict]:
    """Memory-map the file and read the first header: (uint8 map of whole frames, first-frame facts)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"TBF file not found: {path}")
    size = os.path.getsize(path)
    if size < HEADER_BYTES:
        raise TBFError(f"{path}: {size} bytes is shorter than one TBF header ({HEADER_BYTES} bytes)", 0)
    with open(path, "rb") as fh:
        h = np.frombuffer(fh.read(HEADER_BYTES), dtype=_HEADER_DTYPE)[0]
    if int(h["sync"]) != SYNC_WORD:
        raise TBFError(f"{path}: at byte offset 0 (frame 0): bad sync word 0x{int(h['sync']):08X} "
                       f"(expected 0x{SYNC_WORD:08X}): not a TBF file?", 0)
    frame_id = int(h["id_count"]) >> 24
    if frame_id not in FRAME_KINDS:
        raise TBFError(f"{path}: at byte offset 0 (frame 0): frame id {frame_id} is not a TBF frame id "
                       f"(expected 1 = ADP or 5 = NDP)" + ("; it is a TBX frame id: read it with "
                       "bf_epic_blocks.io.tbx (source.kind: tbx or file)" if frame_id == 8 else ""), 0)
    nstand = int(h["nstand"])
    if nstand == 0 and frame_id == 1:
        nstand = 256  # old ADP firmware left the field at 0
    if nstand <= 0:
        raise TBFError(f"{path}: at byte offset 0 (frame 0): invalid stand count {int(h['nstand'])}", 0)
    frame_bytes = HEADER_BYTES + CHANNELS_PER_FRAME * nstand * 2
    nframe = size // frame_bytes
    truncated = size - nframe * frame_bytes
    if nframe == 0:
        raise TBFError(f"{path}: {size} bytes holds no complete frame ({frame_bytes} bytes each "
                       f"for {nstand} stands)", 0)
    mm = np.memmap(path, dtype=np.uint8, mode="r", shape=(nframe, frame_bytes))
    return mm, dict(path=path, frame_id=frame_id, nstand=nstand, nstand_field=int(h["nstand"]),
                    frame_bytes=frame_bytes, nframe=nframe, truncated=truncated,
                    first_chan0=int(h["first_chan"]))


def release_rows(mm, i0, i1):
    """Unmap rows [i0, i1) of a file memory map from this process (``madvise(MADV_DONTNEED)``; the
    kernel keeps them in its page cache): without it every page a pass touched would stay in the
    process's resident set, so a run's memory would grow with the file's length (a 30-s, 9.3-GB TBF
    recording held 9.3 GB resident after the header pass). No-op where the call is missing."""
    import mmap as _mmap
    m = getattr(mm, "_mmap", None)
    advice = getattr(_mmap, "MADV_DONTNEED", None)
    if m is None or advice is None or i1 <= i0:
        return
    fb = mm.shape[1] if mm.ndim == 2 else 1
    page = _mmap.PAGESIZE
    # where the array starts in the mapping (NumPy maps from the offset rounded down to the granularity)
    base = int(getattr(mm, "offset", 0)) % _mmap.ALLOCATIONGRANULARITY
    a = (base + i0 * fb) // page * page          # whole pages (a page shared with the next row goes too:
    b = min(len(m), base + i1 * fb)              # it is mapped again, from the page cache, if read again)
    try:
        m.madvise(advice, a, b - a)
    except (OSError, ValueError):
        pass


def scan_tbf(path, *, chunk_frames: int = 8192, warn: bool = True) -> TBFInfo:
    """Header pass: validate every complete frame and find the (time tag, channel block) grid.

    Raises TBFError (with the byte offset) for a bad sync word, a frame id or stand count unlike
    the first frame's, or a misaligned/negative first channel. A truncated tail gives a TBFWarning.
    """
    mm, f = _open_frames(path)
    fb, nframe = f["frame_bytes"], f["nframe"]
    tts, fcs = [], []
    for i0 in range(0, nframe, chunk_frames):
        i1 = min(nframe, i0 + chunk_frames)
        h = np.ascontiguousarray(mm[i0:i1, :HEADER_BYTES]).view(_HEADER_DTYPE).ravel()
        release_rows(mm, i0, i1)
        problems = []
        bad = np.flatnonzero(h["sync"] != SYNC_WORD)
        if bad.size:
            problems.append((bad[0], f"bad sync word 0x{int(h['sync'][bad[0]]):08X} (expected 0x{SYNC_WORD:08X})"))
        fid = h["id_count"] >> 24
        bad = np.flatnonzero(fid != f["frame_id"])
        if bad.size:
            problems.append((bad[0], f"frame id {int(fid[bad[0]])} differs from the first frame's {f['frame_id']}"))
        bad = np.flatnonzero(h["nstand"] != f["nstand_field"])
        if bad.size:
            problems.append((bad[0], f"stand count field {int(h['nstand'][bad[0]])} differs from the "
                                     f"first frame's {f['nstand_field']}"))
        fc = h["first_chan"].astype(np.int64)
        bad = np.flatnonzero((fc < 0) | ((fc - f["first_chan0"]) % CHANNELS_PER_FRAME != 0))
        if bad.size:
            problems.append((bad[0], f"first channel {int(fc[bad[0]])} is negative or not aligned to the "
                                     f"{CHANNELS_PER_FRAME}-channel blocks of the first frame (first channel "
                                     f"{f['first_chan0']})"))
        if problems:
            k, what = min(problems, key=lambda p: p[0])
            idx = i0 + int(k)
            raise TBFError(f"{f['path']}: at byte offset {idx * fb} (frame {idx}): {what}", idx * fb)
        tts.append(h["time_tag"].astype(np.int64))
        fcs.append(fc)
    tt = np.concatenate(tts)
    fc = np.concatenate(fcs)
    time_tags, t_idx = np.unique(tt, return_inverse=True)
    blocks, b_idx = np.unique(fc, return_inverse=True)
    if f["truncated"] and warn:
        warnings.warn(f"{f['path']}: {f['truncated']} trailing bytes (a truncated frame) ignored after "
                      f"{nframe} complete frames", TBFWarning, stacklevel=2)
    return TBFInfo(path=f["path"], frame_id=f["frame_id"], nstand=f["nstand"], frame_bytes=fb,
                   nframe=nframe, truncated_bytes=f["truncated"], time_tags=time_tags, blocks=blocks,
                   frame_time_index=t_idx.ravel().astype(np.int64),
                   frame_block_index=b_idx.ravel().astype(np.int64))


@dataclass
class RawGulp:
    """A gulp whose frames lie in the file as one unbroken run in (time, channel block) order, each
    (time, block) once: bytes ``[offset, offset + nframe * frame_bytes)`` of the file are its frames,
    and their payloads, headers (``header_bytes``) stripped, are its samples, packed ci4
    (ntime, nblock * nchan_frame, nstand, 2). Readers copy those bytes wherever they are needed
    (a GPU strips the headers) instead of gathering frames on the host. ``time_tags``, ``stats``: as
    :class:`TBFData`."""
    offset: int
    nframe: int
    ntime: int
    nblock: int
    frame_bytes: int
    header_bytes: int
    time_tags: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        return self.nframe * self.frame_bytes


def _gulp_stats(info, t0, t1, prev_tag, nread, nexpected, nduplicate):
    tags = info.time_tags[t0:t1]
    step = int(round(FS_HZ / info.chan_bw_hz))
    steps = np.diff(tags if prev_tag is None else np.concatenate([[prev_tag], tags]))
    return tags, dict(frames_read=int(nread), frames_expected=int(nexpected), frames_missing=int(nexpected - nread),
                      frames_duplicate=int(nduplicate), time_gaps=int(np.count_nonzero(steps > step)),
                      truncated_bytes=0)


def _as_raw(info, frames, t0, t1, prev_tag, header_bytes):
    """A :class:`RawGulp` when ``frames`` (file order within a time) are one run of the file in
    (time, block) order covering every cell of [t0, t1) once; else None."""
    nt, nb = t1 - t0, len(info.blocks)
    n = nt * nb
    if len(frames) != n or n == 0 or frames[-1] - frames[0] != n - 1:
        return None
    if not (np.all(np.diff(frames) == 1)
            and np.array_equal(info.frame_time_index[frames], np.repeat(np.arange(t0, t1), nb))
            and np.array_equal(info.frame_block_index[frames], np.tile(np.arange(nb), nt))):
        return None
    tags, stats = _gulp_stats(info, t0, t1, prev_tag, n, n, 0)
    return RawGulp(offset=int(frames[0]) * info.frame_bytes, nframe=n, ntime=nt, nblock=nb,
                   frame_bytes=info.frame_bytes, header_bytes=header_bytes, time_tags=tags.copy(), stats=stats)


def _gather(mm, info, frames: np.ndarray, t0: int, t1: int, prev_tag, header_bytes: int, data_cls):
    """Assemble time indices [t0, t1) from the given frame indices (all inside that range) into a
    ``data_cls`` (TBFData, or TBX's subclass): shared by the TBF and TBX readers, whose grids differ
    only in header size and channels per frame (``info.nchan_frame``)."""
    nt, nb, nc, ns = t1 - t0, len(info.blocks), info.nchan_frame, info.nstand
    out = np.zeros((nt, nb, nc, ns, 2), dtype=np.uint8)
    ti = info.frame_time_index[frames] - t0
    bi = info.frame_block_index[frames]
    cell = ti * nb + bi
    # keep the first copy of a repeated (time, block) frame
    _, first = np.unique(cell, return_index=True)
    keep = np.sort(first)
    frames, ti, bi = frames[keep], ti[keep], bi[keep]
    if frames.size:
        payload = np.asarray(mm[frames, header_bytes:])  # fancy index: reads only these frames
        release_rows(mm, int(frames.min()), int(frames.max()) + 1)
        out[ti, bi] = payload.reshape(len(frames), nc, ns, 2)
    tags, stats = _gulp_stats(info, t0, t1, prev_tag, len(frames), nt * nb, len(cell) - len(keep))
    return data_cls(data=out.reshape(nt, nb * nc, ns, 2), time_tags=tags.copy(),
                    channels=info.channels.astype(np.int64), chan_bw_hz=info.chan_bw_hz,
                    frame_id=info.frame_id, stats=stats)


def _check_gulp(gulp_ntime):
    if isinstance(gulp_ntime, bool) or not isinstance(gulp_ntime, (int, np.integer)) or gulp_ntime < 1:
        raise ValueError(f"gulp_ntime must be an integer >= 1, got {gulp_ntime!r}")


def _iter_gulps(mm, info, gulp_ntime: int, header_bytes: int, data_cls, raw=False):
    """Chunks of ``gulp_ntime`` time tags of a scanned capture (TBF or TBX), in time order; with
    ``raw``, a :class:`RawGulp` for each chunk whose frames lie in the file in order."""
    order = np.argsort(info.frame_time_index, kind="stable")  # file order within a time tag
    sorted_t = info.frame_time_index[order]
    prev = None
    for t0 in range(0, info.ntime, int(gulp_ntime)):
        t1 = min(info.ntime, t0 + int(gulp_ntime))
        lo, hi = np.searchsorted(sorted_t, [t0, t1])
        chunk = _as_raw(info, order[lo:hi], t0, t1, prev, header_bytes) if raw else None
        if chunk is None:
            chunk = _gather(mm, info, order[lo:hi], t0, t1, prev, header_bytes, data_cls)
        prev = int(info.time_tags[t1 - 1])
        if t1 == info.ntime:
            chunk.stats["truncated_bytes"] = int(info.truncated_bytes)
        yield chunk


def iter_tbf_gulps(path, gulp_ntime: int, *, info: TBFInfo | None = None, raw=False) -> Iterator[TBFData]:
    """Stream a TBF file as :class:`TBFData` chunks of ``gulp_ntime`` time tags (the last may be shorter).

    Every chunk has the full channel axis of the file (all blocks found by the header pass), so
    chunks concatenate along time into :func:`read_tbf`'s result; their ``stats`` add up to it.
    ``info``: a :func:`scan_tbf` result to reuse (skips the header pass). ``raw``: yield a
    :class:`RawGulp` (the file's byte range) instead for chunks whose frames lie in the file in order.
    """
    _check_gulp(gulp_ntime)
    if info is None:
        info = scan_tbf(path, warn=True)
    mm, _ = _open_frames(path)
    yield from _iter_gulps(mm, info, gulp_ntime, HEADER_BYTES, TBFData, raw=raw)


def read_tbf(path) -> TBFData:
    """Read a whole TBF file into one :class:`TBFData` (see the module docstring for the layout)."""
    info = scan_tbf(path, warn=True)
    return next(iter_tbf_gulps(path, max(info.ntime, 1), info=info))


def write_tbf(path, data, first_channel, time_tag0, *, frame_id=5, time_step=None, order=None) -> int:
    """Write packed ci4 samples as a TBF file (for tests, demos and the replayer); returns frames written.

    data : uint8 (ntime, nchan, nstand, 2) packed ci4 (see :func:`pack_ci4`); nchan a multiple of 12.
    first_channel : channel index of data[:, 0]; the file holds blocks first_channel + 12 k.
    time_tag0 : time tag of sample 0; sample t has time_tag0 + t * time_step (default one sample:
        FS_HZ / channel width of ``frame_id``).
    frame_id : 1 (ADP) or 5 (NDP). ``order`` : optional permutation of the ntime * nblock frames
        (time-major: frame i is sample i // nblock, block i % nblock), to write them out of order.
    The header's frame count and second count are filled as the F-engine would (count = frame
    index mod 2^24, second = time tag // FS_HZ); :func:`read_tbf` reads the file back exactly.
    """
    data = np.asarray(data)
    if data.dtype != np.uint8 or data.ndim != 4 or data.shape[3] != 2 or data.shape[1] % CHANNELS_PER_FRAME:
        raise ValueError(f"write_tbf: data must be uint8 (ntime, 12*k, nstand, 2), got {data.dtype} {data.shape}")
    if frame_id not in FRAME_KINDS:
        raise ValueError(f"write_tbf: frame_id must be one of {sorted(FRAME_KINDS)}, got {frame_id!r}")
    ntime, nchan, nstand, _ = data.shape
    nblock = nchan // CHANNELS_PER_FRAME
    step = int(round(FS_HZ / FRAME_KINDS[frame_id][2])) if time_step is None else int(time_step)
    n = ntime * nblock
    hdr = np.zeros(n, _HEADER_DTYPE)
    t = np.repeat(np.arange(ntime), nblock)
    b = np.tile(np.arange(nblock), ntime)
    tags = int(time_tag0) + t.astype(np.int64) * step
    hdr["sync"] = SYNC_WORD
    hdr["id_count"] = (frame_id << 24) | (np.arange(n) % (1 << 24))
    hdr["second"] = tags // FS_HZ
    hdr["first_chan"] = int(first_channel) + b * CHANNELS_PER_FRAME
    hdr["nstand"] = nstand
    hdr["time_tag"] = tags
    frames = np.empty((n, HEADER_BYTES + CHANNELS_PER_FRAME * nstand * 2), np.uint8)
    frames[:, :HEADER_BYTES] = hdr.view(np.uint8).reshape(n, HEADER_BYTES)
    frames[:, HEADER_BYTES:] = data.reshape(ntime, nblock, -1).reshape(n, -1)
    if order is not None:
        frames = frames[np.asarray(order)]
    with open(path, "wb") as fh:
        fh.write(frames.tobytes())
    return n
