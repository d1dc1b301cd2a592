"""Counting the non-finite voltage samples the blocks zero, and handing the counts downstream.

A sequence header is fixed when the sequence begins (Bifrost's contract), before any sample has been
seen, so the counts cannot travel in it. The block that zeroes (CalFoldBlock, or DFTImagerBlock for
float input that did not pass CalFoldBlock) keeps a :class:`NonfiniteTally` for the sequence and puts
its id in the header (``nonfinite = {"tally": id, "zeroed_by": block name}``, docs/HEADERS.md); blocks
downstream in the same process look it up with :func:`get_tally` and ask for the count of any range
of input frames (the image writer: the frames of each integration, as FITS keyword NONFINIT).
Counts are exact: per input frame (time sample) for frames that had any, and cumulative per
(station, pol) for the sequence.
"""
from __future__ import annotations

import itertools
import logging
import threading

import numpy as np

from ..imaging._xp import to_numpy
from ..imaging.sanitize import zero_nonfinite

log = logging.getLogger(__name__)

__all__ = ["NonfiniteTally", "get_tally", "is_float_dtype", "lookup_tally", "new_tally", "register_tally",
           "zero_and_count"]

_TALLIES: dict[str, "NonfiniteTally"] = {}
_LOCK = threading.Lock()
_IDS = itertools.count(1)
#: Tallies kept alive at once (oldest dropped first): a long run makes one per sequence.
MAX_TALLIES = 256


class NonfiniteTally:
    """Non-finite samples zeroed in one sequence.

    ``counts`` : int64 (nstand, npol), cumulative for the sequence;
    ``frames`` : {input frame index: samples zeroed in that frame} for frames that had any.
    """

    def __init__(self, tally_id: str, nstand: int, npol: int, owner: str):
        self.id, self.owner = tally_id, owner
        self.counts = np.zeros((nstand, npol), np.int64)
        self.frames: dict[int, int] = {}
        self.frames_seen = 0
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def add(self, frame0: int, per_time_counts) -> None:
        """Record the (ntime, nstand, npol) counts of input frames frame0, frame0 + 1, ..."""
        c = to_numpy(per_time_counts)
        with self._lock:
            self.counts += c.sum(axis=0)
            per_frame = c.reshape(c.shape[0], -1).sum(axis=1)
            for k in np.flatnonzero(per_frame):
                self.frames[int(frame0 + k)] = self.frames.get(int(frame0 + k), 0) + int(per_frame[k])
            self.frames_seen = max(self.frames_seen, frame0 + c.shape[0])

    def count(self, frame_start: int, frame_stop: int) -> int:
        """Samples zeroed in input frames [frame_start, frame_stop)."""
        with self._lock:
            return int(sum(n for f, n in self.frames.items() if frame_start <= f < frame_stop))

    def to_header(self) -> dict:
        return {"tally": self.id, "zeroed_by": self.owner}


def is_float_dtype(dtype_str: str) -> bool:
    """True for Bifrost float types ('f16', 'f32', 'cf32', 'cf64'...): the ones that can hold NaN/Inf."""
    return str(dtype_str).startswith(("f", "cf"))


def register_tally(prefix: str, make):
    """``make(tally_id)``, kept under a new id ``<prefix>-<n>`` that a sequence header carries, so that
    blocks downstream in the same process find it (:func:`lookup_tally`): any per-sequence count a block
    hands on (non-finite samples here, interference flags in :mod:`.rfi_flag`)."""
    with _LOCK:
        tid = f"{prefix}-{next(_IDS)}"
        t = make(tid)
        _TALLIES[tid] = t
        while len(_TALLIES) > MAX_TALLIES:
            _TALLIES.pop(next(iter(_TALLIES)))
        return t


def lookup_tally(tally_id):
    """The tally registered under ``tally_id``, or None (never registered, or dropped as old)."""
    with _LOCK:
        return _TALLIES.get(tally_id)


def new_tally(owner: str, nstand: int, npol: int) -> NonfiniteTally:
    return register_tally(owner, lambda tid: NonfiniteTally(tid, nstand, npol, owner))


def get_tally(header) -> NonfiniteTally | None:
    """The tally a sequence header names (``header['nonfinite']['tally']``), or None."""
    return lookup_tally(((header or {}).get("nonfinite") or {}).get("tally"))


def zero_and_count(x, tally: NonfiniteTally, frame0: int, who: str, seq_name):
    """Zero the non-finite samples of the (ntime, nchan, nstand, npol) float gulp ``x`` (a copy when there
    are any: ``x`` may be a view of the input ring), record them in ``tally``, log one warning per gulp."""
    x, per_time = zero_nonfinite(x, per_time=True)
    n = int(to_numpy(per_time.sum()))
    if n:
        tally.add(frame0, per_time)
        c = to_numpy(per_time).sum(axis=0)
        log.warning("%s %s: %d non-finite samples zeroed in frames %d-%d on %d antenna-pols (%d so far in "
                    "the sequence)", who, seq_name, n, frame0, frame0 + x.shape[0] - 1, int((c > 0).sum()),
                    tally.total)
    else:
        tally.frames_seen = max(tally.frames_seen, frame0 + x.shape[0])
    return x
