"""One gulp's imaging replayed as a CUDA graph: the host's cost per image falls to one launch.

Why: at case P (256 antennas, 3,205 pixels, 1,024 samples, 16 channels x 2 pols, fp16) the GPU runs
a gulp's dozen kernels -- transpose, integer covariance, layout, the image GEMM, the fused
reduction -- in about 0.45 ms, and Python and CuPy take about as long to issue them. With a graph
the host's part falls to about 0.04 ms: the GPU alone sets the pace, and the host
is free for the pipeline's other blocks and for the other GPUs one process drives.

How (:class:`GraphCache`), for a call keyed by everything that shapes the work (input shape and
dtype, products, route, accumulation):

1. The first call runs eagerly: it compiles kernels and fills the operator's caches.
2. The second call is captured on a private stream into a graph. Every block of memory it allocates
   is held by the graph's entry for as long as the graph exists (none is reused inside the capture
   or handed to another array), so the addresses baked into the graph stay valid; all of it goes
   back to CuPy's pool when the operator is dropped. Its input is a static buffer the graph reads.
   Operator cache entries first made during the capture are dropped (only the graph computed them).
3. Later calls copy the input into the static buffer, launch the graph on the current stream and
   return a copy of its output (the static output is overwritten by the next launch), or, for a
   caller that uses it at once on the same stream (DFTImagerBlock), the static output itself.

A call that cannot be captured -- one that needs the host mid-way, such as a sample count read back
from the device -- is run eagerly for good, with a log line saying why. A replay on another stream
than the last one first waits for the work issued on that one (the same stream needs no call: fewer
driver calls, each of which hands the interpreter lock to a pipeline's other threads), so changing
the current stream between calls is safe; one operator must not
be used from two threads at once (as before: it keeps cached accumulators).
"""
from __future__ import annotations

import logging

from ._xp import copy_rows

log = logging.getLogger(__name__)

__all__ = ["GraphCache"]

_WARM, _EAGER = "warm", "eager"


class _Captured:
    """A captured call: the graph, its static input and output, and the memory blocks it uses."""

    def __init__(self, graph, xin, out, memory, stream):
        self.graph, self.xin, self.out, self.memory, self.stream = graph, xin, out, memory, stream
        self.last = None   # the stream of the last replay

    def replay(self, x, static_out=False):
        import cupy as cp
        cur = cp.cuda.get_current_stream()
        if self.last is not None and self.last.ptr != cur.ptr:
            # the previous replay was on another stream: wait for everything issued there so far, which
            # includes the caller's use of a static output; on the same stream, stream order does it
            cur.wait_event(self.last.record())
        _copy_in(self.xin, x, cur)
        self.graph.launch(cur)
        if static_out:
            out = self.out                  # the caller uses it on this stream before the next call
        elif self.out.flags.c_contiguous:   # a memcpy: CuPy's copy() is a kernel, 3x the host time
            out = cp.empty_like(self.out)
            out.data.copy_from_device_async(self.out.data, self.out.nbytes, cur)
        else:
            out = self.out.copy()
        self.last = cur
        return out


def _copy_in(dst, x, stream):
    """dst[...] = x on ``stream``: one 2-D memcpy where x is rows of contiguous bytes at a fixed pitch (a
    whole gulp, or a channel slice of one as several GPUs take it; :func:`._xp.copy_rows`), else CuPy's copy."""
    if not copy_rows(dst, x, stream):
        dst[...] = x


class GraphCache:
    """Per-operator cache of captured calls, keyed by the call's shape-determining arguments.

    ``max_entries`` bounds the graphs kept (each holds the memory of one call's temporaries: about
    0.3 GB at case P); further keys run eagerly.
    """

    def __init__(self, max_entries: int = 8):
        self.max_entries = int(max_entries)
        self._entries = {}
        self.captured = 0    # graphs made
        self.replays = 0     # calls served by a graph

    def call(self, key, fn, x, caches=None, static_out=False):
        """``fn(x)`` -- eagerly the first time, captured the second, replayed after.

        x : the CuPy input array (copied into the graph's static buffer on replays).
        caches : dicts the call may fill (the operator's derived arrays): entries first made during a
        capture are removed again, since only the graph has computed them.
        static_out : on a replay, return the graph's own output array instead of a copy; the next
        call overwrites it, so the caller must have used it (on the same stream) by then.
        """
        entry = self._entries.get(key)
        if entry is None:
            if len(self._entries) >= self.max_entries:
                return fn(x)
            self._entries[key] = _WARM
            return fn(x)
        if entry == _EAGER:
            return fn(x)
        if entry == _WARM:
            entry = self._capture(key, fn, x, caches or ())
            if entry is None:
                return fn(x)
        self.replays += 1
        return entry.replay(x, static_out)

    def _capture(self, key, fn, x, caches):
        import cupy as cp
        before = [set(c) for c in caches]
        stream = cp.cuda.Stream(non_blocking=True)
        cur = cp.cuda.get_current_stream()
        alloc = cp.cuda.get_allocator()          # CuPy's (the default memory pool's malloc, normally)
        memory = []

        def malloc(size):
            # from CuPy's allocator, in the caller's stream arena, and held for the graph's lifetime: no
            # block the graph uses is handed to another array while the graph exists (nor reused
            # inside the capture), and all of it returns to the pool when the graph is dropped
            with cur:
                mp = alloc(size)
            memory.append(mp)
            return mp

        try:
            with cp.cuda.using_allocator(malloc):
                xin = cp.empty(x.shape, x.dtype)
                stream.wait_event(cur.record())      # x is ready on the caller's stream
                with stream:
                    xin[...] = x
                    stream.begin_capture()
                    try:
                        out = fn(xin)
                    except BaseException:
                        try:
                            stream.end_capture()
                        except Exception:  # noqa: BLE001 -- an invalidated capture ends with an error
                            pass
                        raise
                    graph = stream.end_capture()
                stream.synchronize()
        except Exception as err:  # noqa: BLE001 -- any failure to capture means: run eagerly
            self._entries[key] = _EAGER
            log.info("imaging call not captured as a CUDA graph (%s: %s); it runs eagerly", type(err).__name__, err)
            self._drop_new(caches, before)
            try:
                stream.synchronize()
            except Exception:  # noqa: BLE001
                pass
            return None
        self._drop_new(caches, before)
        cur.wait_event(stream.record())
        entry = _Captured(graph, xin, out, memory, stream)
        self._entries[key] = entry
        self.captured += 1
        log.debug("imaging call captured as a CUDA graph: %s", key)
        return entry

    @staticmethod
    def _drop_new(caches, before):
        for c, keys in zip(caches, before):
            for k in set(c) - keys:
                del c[k]
