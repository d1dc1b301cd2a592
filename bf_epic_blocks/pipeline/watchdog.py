"""``bf-epic run``'s stall watchdog: a run that stops moving says where each block is.

Why: a block stuck in host work shows no progress and no error until someone kills the run (a 10-s
whole-band run once spent minutes in friends-of-friends clustering over millions of crossings; only
a stack dump taken from outside showed it). The watchdog reads each block's runtime ``stats``
(``ngulp``, ``last_data_at``: the project's runtime keeps them; real Bifrost's blocks, which keep
their own ``perf`` proclog instead, are not watched) and, when no block has finished a gulp for
``stall_s`` seconds, logs a WARNING with every block's gulps, the time since its last, and where its
thread is (its innermost frames: a block waiting on a ring is waiting for another; the one that is
not is the stall). Repeated every ``stall_s`` while the stall lasts; a live source waiting for
packets reads the same way.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
import traceback

log = logging.getLogger("bf_epic_blocks")

__all__ = ["StallWatchdog", "where"]


def where(frame, depth=4):
    """The innermost ``depth`` frames of a thread's stack, innermost first, as 'file:line function'
    joined by ' <- ' ('not running' for None)."""
    if frame is None:
        return "not running"
    stack = traceback.extract_stack(frame)[-depth:]
    return " <- ".join(f"{os.path.basename(fs.filename)}:{fs.lineno} {fs.name}" for fs in reversed(stack))


class StallWatchdog:
    """Warns (log WARNING, counted in ``warnings``) when none of ``blocks`` has finished a gulp for
    ``stall_s`` seconds; looks every ``poll_s`` (default stall_s / 4, at most 5 s). A context manager:
    started on entry, stopped (its thread joined) on exit. ``stall_s <= 0`` or no watched block: off."""

    def __init__(self, blocks, stall_s=60.0, poll_s=None):
        self.blocks = [b for b in blocks if isinstance(getattr(b, "stats", None), dict) and "ngulp" in b.stats]
        self.stall_s = float(stall_s)
        self.poll_s = float(poll_s) if poll_s else min(5.0, max(self.stall_s, 1e-3) / 4)
        self.warnings = 0
        self._stop = threading.Event()
        self._thread = None

    def __enter__(self):
        if self.blocks and self.stall_s > 0:
            self._thread = threading.Thread(target=self._watch, name="bf-epic-watchdog", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        return False

    def _gulps(self):
        return sum(int(b.stats["ngulp"]) for b in self.blocks)

    def _watch(self):
        seen, since, warned = self._gulps(), time.perf_counter(), None
        while not self._stop.wait(self.poll_s):
            now, n = time.perf_counter(), self._gulps()
            if n != seen:
                seen, since, warned = n, now, None
            elif now - since >= self.stall_s and (warned is None or now - warned >= self.stall_s):
                warned = now
                self.warnings += 1
                log.warning(self.report(now - since))

    def report(self, idle_s):
        """The warning's text: how long nothing moved, then a line per block."""
        frames = sys._current_frames()
        ident = {t.name: t.ident for t in threading.enumerate()}
        now = time.perf_counter()
        lines = [f"no block has finished a gulp for {idle_s:.1f} s; where each block is (innermost first):"]
        for b in self.blocks:
            st = b.stats
            n = int(st["ngulp"])
            last = "" if st.get("last_data_at") is None else f", the last {now - st['last_data_at']:.1f} s ago"
            lines.append(f"  {b.name}: {n} gulp{'' if n == 1 else 's'} done{last}; in "
                         f"{where(frames.get(ident.get(b.name)))}")
        return "\n".join(lines)
