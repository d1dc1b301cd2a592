"""Which LWA F-engine frame format a capture (file or packet) holds: TBF or TBX, told by the frame id.

Both formats start every frame with the Mark 5C sync word 0xDEC0DE5C (big-endian bytes DE C0 DE 5C)
followed by one byte of frame id: 1 (ADP TBF, LWA-SV before NDP), 5 (NDP TBF) or 8 (NDP TBX, as LSL's
``lsl.reader.tbx`` defines it). Nothing else is needed to tell them apart.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["detect_format", "FrameFormatError", "SYNC_WORD", "FRAME_ID_FORMAT"]

SYNC_WORD = 0xDEC0DE5C
#: frame id byte -> format name
FRAME_ID_FORMAT = {1: "tbf", 5: "tbf", 8: "tbx"}


class FrameFormatError(ValueError):
    """The bytes are not a TBF or TBX frame (bad sync word, unknown frame id, too short)."""


def detect_format(path_or_bytes) -> str:
    """``'tbf'`` or ``'tbx'`` for a capture file (str / PathLike) or the bytes of its first frame.

    Reads the first 5 bytes only: the sync word and the frame id. Raises :class:`FrameFormatError`
    (a ValueError) naming what was found when the sync word is wrong or the frame id is neither
    (1 or 5 = TBF, 8 = TBX); FileNotFoundError for a missing file.
    """
    if isinstance(path_or_bytes, (str, os.PathLike)):
        where = str(path_or_bytes)
        p = Path(path_or_bytes)
        if not p.is_file():
            raise FileNotFoundError(f"capture file not found: {p}")
        with open(p, "rb") as fh:
            head = fh.read(5)
    else:
        where = "buffer"
        head = bytes(memoryview(path_or_bytes).cast("B")[:5])
    if len(head) < 5:
        raise FrameFormatError(f"{where}: {len(head)} bytes is too short to hold a frame's sync word and id")
    sync = int.from_bytes(head[:4], "big")
    if sync != SYNC_WORD:
        raise FrameFormatError(f"{where}: bad sync word 0x{sync:08X} at byte offset 0 (expected 0x{SYNC_WORD:08X}): "
                               "not an LWA TBF/TBX capture")
    fid = head[4]
    try:
        return FRAME_ID_FORMAT[fid]
    except KeyError:
        raise FrameFormatError(f"{where}: frame id {fid} is neither TBF (1 = ADP, 5 = NDP) nor TBX (8)") from None


@dataclass
class CaptureGrid:
    """The (time tag, channel) grid of a TBF or TBX header scan, shared by their ``*Info`` classes.

    ``time_tags`` (ntime,) sorted distinct; ``blocks`` (nblock,) sorted distinct first channels;
    ``frame_time_index``/``frame_block_index`` (nframe,) the grid cell of each complete frame.
    Subclasses add ``nchan_frame`` and ``chan_bw_hz`` (fields or properties)."""
    path: Path
    nstand: int
    frame_bytes: int
    nframe: int
    truncated_bytes: int
    time_tags: np.ndarray
    blocks: np.ndarray
    frame_time_index: np.ndarray
    frame_block_index: np.ndarray

    @property
    def channels(self) -> np.ndarray:
        return (self.blocks[:, None] + np.arange(self.nchan_frame)).ravel()

    @property
    def freq_hz(self) -> np.ndarray:
        return self.channels * self.chan_bw_hz

    @property
    def ntime(self) -> int:
        return len(self.time_tags)

    @property
    def nchan(self) -> int:
        return len(self.blocks) * self.nchan_frame
