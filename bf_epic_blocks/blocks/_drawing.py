"""DrawingHelper: a block's quicklooks (matplotlib PNGs) drawn in a helper process, one job at a time.

matplotlib's drawing is interpreter time: drawn in a block's thread it holds the lock the pipeline's
other threads need (seconds a PNG at the whole band), and a stalled block stalls the imagers through
the rings. The helper is spawned at the first job (spawn, not fork: the parent has threads and a CUDA
context); a job asked while the last is still drawing is skipped and counted (the next one comes a
cadence later); a helper that cannot start or breaks is logged and the jobs are drawn in the caller's
thread from then on.
"""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


class DrawingHelper:
    """Run ``fn(*args)`` jobs in one spawned process. ``owner`` names the block in the log; ``enabled``
    False draws every job in the caller's thread. ``skipped`` counts the jobs skipped."""

    def __init__(self, owner, enabled=True):
        self.owner, self.enabled, self.skipped = owner, bool(enabled), 0
        self._pool = self._future = self._collect_fn = None

    def run(self, fn, args, collect, wait=False):
        """Run ``fn(*args)`` (picklable) and hand its result to ``collect`` once it is done (when the next
        job is asked, at ``wait`` or at :meth:`close`). Returns False, counted in ``skipped``, where the
        last job is still drawing and ``wait`` is False. ``wait``: return once this job is collected."""
        fut = self._future
        if fut is not None and not (wait or fut.done()):
            self.skipped += 1
            return False
        if self.enabled:
            try:
                if fut is not None:
                    self._collect(fut)
                if self._pool is None:
                    import multiprocessing
                    from concurrent.futures import ProcessPoolExecutor
                    self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
                self._future, self._collect_fn = self._pool.submit(fn, *args), collect
                if wait:
                    self._collect(self._future)
                return True
            except Exception as e:  # noqa: BLE001 - a helper that cannot start or broke: draw here
                log.warning("%s: the drawing helper process failed (%s); drawing in this thread", self.owner, e)
                self.enabled, self._future = False, None
        collect(fn(*args))
        return True

    def _collect(self, fut):
        self._future = None
        self._collect_fn(fut.result())

    def wait(self):
        """Collect the job being drawn, if any (a failure is logged: a quicklook must not stop a pipeline)."""
        if self._future is not None:
            try:
                self._collect(self._future)
            except Exception as e:  # noqa: BLE001
                log.warning("%s: the last drawing was not made: %s", self.owner, e)

    def close(self):
        """Collect the job being drawn and stop the helper process (it starts again at the next job)."""
        self.wait()
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
