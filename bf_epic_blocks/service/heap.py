"""A long-running process's heap: large arrays handed back to the system when freed.

glibc's malloc serves a request of at least its mmap threshold with a mapping of its own, returned to the
system when freed; below it, from a heap that is seldom given back. The threshold starts at 128 KiB and
rises to the size of each mapped block freed (up to 32 MiB), so after a pipeline frees a 20-MB operator,
its later 1-20 MB arrays (ring buffers, packet chunks, operators rebuilt at a new sequence) come from the
heap, and a service that starts a sequence at every F-engine reset kept tens of MB more with each (the
soak in docs/benchmarks/soak_service.md). Fixing the threshold with ``mallopt`` ends its rise: what is
larger than it is always mapped and always returned. This is glibc's own documented setting (also
``MALLOC_MMAP_THRESHOLD_`` in the environment, which, when set, is left as it is).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

#: bytes from which an allocation is a mapping of its own (glibc's M_MMAP_THRESHOLD)
MMAP_THRESHOLD = 1 << 20
_M_MMAP_THRESHOLD = -3          # glibc's malloc.h


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``nbytes`` for this process; True when set. False (nothing done) where
    the C library is not glibc, or ``MALLOC_MMAP_THRESHOLD_`` is set (the operator's choice stands)."""
    if os.environ.get("MALLOC_MMAP_THRESHOLD_"):
        return False
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):          # not glibc (macOS, Windows)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    done = bool(mallopt(_M_MMAP_THRESHOLD, int(nbytes)))
    if done:
        log.debug("malloc's mmap threshold fixed at %d bytes", nbytes)
    return done
