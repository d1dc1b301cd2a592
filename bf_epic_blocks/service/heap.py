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
import functools
import logging
import os
import sys

log = logging.getLogger(__name__)

#: bytes from which an allocation is a mapping of its own (glibc's M_MMAP_THRESHOLD)
MMAP_THRESHOLD = 1 << 20
_M_MMAP_THRESHOLD = -3          # glibc's malloc.h


@functools.lru_cache(maxsize=1)
def _libc():
    """The C library, loaded once (finding it runs ``ldconfig``: not on every metrics scrape)."""
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


def fix_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``nbytes`` for this process; True when set. False (nothing done) where
    the C library is not glibc, or ``MALLOC_MMAP_THRESHOLD_`` is set (the operator's choice stands)."""
    if os.environ.get("MALLOC_MMAP_THRESHOLD_"):
        return False
    try:
        mallopt = _libc().mallopt
    except (OSError, AttributeError):          # not glibc (macOS, Windows)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    done = bool(mallopt(_M_MMAP_THRESHOLD, int(nbytes)))
    if done:
        log.debug("malloc's mmap threshold fixed at %d bytes", nbytes)
    return done


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]


_STATUS = {"RssAnon:": "rss_anon", "RssFile:": "rss_file", "RssShmem:": "rss_shmem"}


def _status_figures(path: str = "/proc/self/status") -> dict:
    """The resident set by kind and the thread count from ``/proc/<pid>/status`` (Linux); {} elsewhere."""
    out = {}
    try:
        with open(path) as f:
            for line in f:
                parts = line.split()
                if parts and parts[0] in _STATUS:
                    out[_STATUS[parts[0]]] = int(parts[1]) * 1024      # kB
                elif parts and parts[0] == "Threads:":
                    out["threads"] = int(parts[1])
    except (OSError, ValueError, IndexError):
        pass
    return out


def memory_figures() -> dict:
    """This process's memory by kind, in bytes, so that a service whose resident set grows shows where:

    * ``rss``: resident (``/proc/self/statm``; Linux), and of it, from ``/proc/self/status``: ``rss_anon``
      (the process's own: malloc, the CUDA driver's host copies), ``rss_file`` (pages of files mapped:
      shared libraries as their code is first run) and ``rss_shmem`` (shared: on a GPU, CuPy's page-locked
      buffers, which the driver maps shared); ``threads`` (a count);
    * ``heap_in_use``, ``heap_free``, ``heap_mapped``: glibc malloc's arenas, all of them (``mallinfo2``,
      glibc >= 2.33): allocated, free but kept, and in blocks of their own mapping;
    * with CuPy already in use (never imported here): ``gpu_pool_used`` and ``gpu_pool_held`` (CuPy's
      device pool: in arrays, and kept from the driver), ``pinned_free_blocks`` (a count: page-locked
      host blocks CuPy's pinned pool keeps for reuse, each of one exact size).

    What cannot be told here is left out."""
    out = {}
    try:
        with open("/proc/self/statm") as f:
            out["rss"] = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    out.update(_status_figures())
    try:
        fn = _libc().mallinfo2
        fn.restype = _Mallinfo2
        m = fn()
        out.update(heap_in_use=int(m.uordblks), heap_free=int(m.fordblks), heap_mapped=int(m.hblkhd))
    except (OSError, AttributeError):          # not glibc, or older than 2.33
        pass
    cp = sys.modules.get("cupy")
    if cp is not None:
        try:
            pool = cp.get_default_memory_pool()
            out.update(gpu_pool_used=int(pool.used_bytes()), gpu_pool_held=int(pool.total_bytes()),
                       pinned_free_blocks=int(cp.get_default_pinned_memory_pool().n_free_blocks()))
        except Exception:   # noqa: BLE001 - CuPy without a device: no pool figures
            pass
    return out
