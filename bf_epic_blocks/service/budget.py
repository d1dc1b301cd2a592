"""The output budget (``output.keep_gb``, ``output.keep_days``): a run left going for weeks keeps its
output folder within a size and an age by deleting its oldest products.

:func:`choose_deletions` is the rule, a pure function of the folder's listing; :class:`OutputBudget`
applies it every ``every_s`` seconds in a thread of its own. A file this process has open (read from
``/proc/self/fd``: a cube, the watch file, a table being written) or modified in the last
``settle_s`` seconds is never deleted; each deletion is counted and logged.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path

__all__ = ["choose_deletions", "open_files", "OutputBudget"]

log = logging.getLogger(__name__)


def choose_deletions(files, keep_bytes=None, keep_s=None, now=None, protected=()):
    """The files to delete, oldest first.

    files : iterable of (path, size bytes, mtime Unix s); keep_bytes : the folder's size to stay within
    (None: no size limit); keep_s : the oldest age kept (None: no age limit); now : Unix s (default the
    clock); protected : paths never deleted (open, or too new). Every file older than ``keep_s`` goes,
    then the oldest of the rest until the total is within ``keep_bytes``; protected files count toward
    the total but are skipped, so a budget smaller than the open files deletes every other file and
    stops there.
    """
    now = time.time() if now is None else float(now)
    protected = {str(p) for p in protected}
    files = sorted(((str(p), int(s), float(m)) for p, s, m in files), key=lambda f: (f[2], f[0]))
    total = sum(f[1] for f in files)
    out = []
    for path, size, mtime in files:
        if path in protected:
            continue
        too_old = keep_s is not None and now - mtime > keep_s
        too_big = keep_bytes is not None and total > keep_bytes
        if too_old or too_big:
            out.append(path)
            total -= size
    return out


def open_files():
    """The regular files this process has open (Linux's /proc/self/fd; empty elsewhere)."""
    out = set()
    try:
        for fd in os.listdir("/proc/self/fd"):
            try:
                target = os.readlink(f"/proc/self/fd/{fd}")
            except OSError:
                continue
            if target.startswith("/"):
                out.add(target)
    except OSError:
        pass
    return out


class OutputBudget:
    """Keep ``folder`` within ``keep_gb`` and ``keep_days`` (either None: no such limit), checking every
    ``every_s`` seconds; ``start()`` / ``stop()`` (a last sweep). ``stats``: sweeps, files and bytes deleted,
    failures."""

    def __init__(self, folder, keep_gb=None, keep_days=None, every_s=30.0, settle_s=60.0):
        self.folder = Path(folder)
        self.keep_bytes = None if keep_gb is None else int(float(keep_gb) * 1e9)
        self.keep_s = None if keep_days is None else float(keep_days) * 86400.0
        self.every_s, self.settle_s = float(every_s), float(settle_s)
        self.stats = {"sweeps": 0, "deleted_files": 0, "deleted_bytes": 0, "failed": 0, "folder_bytes": 0}
        self._stop = threading.Event()
        self._thread = None

    def _listing(self):
        out = []
        for root, _, names in os.walk(self.folder):
            for n in names:
                p = os.path.join(root, n)
                try:
                    st = os.stat(p)
                except OSError:
                    continue
                out.append((os.path.realpath(p), st.st_size, st.st_mtime))
        return out

    def sweep(self, now=None):
        """One pass: delete what :func:`choose_deletions` picks; returns the paths deleted."""
        now = time.time() if now is None else now
        files = self._listing()
        protected = open_files() | {p for p, _, m in files if now - m < self.settle_s}
        sizes = {p: s for p, s, _ in files}
        gone = []
        for p in choose_deletions(files, self.keep_bytes, self.keep_s, now, protected):
            try:
                os.remove(p)
            except OSError as e:
                self.stats["failed"] += 1
                log.warning("output budget: %s not deleted: %s", p, e)
                continue
            gone.append(p)
            self.stats["deleted_files"] += 1
            self.stats["deleted_bytes"] += sizes[p]
        self.stats["sweeps"] += 1
        self.stats["folder_bytes"] = sum(sizes.values()) - sum(sizes[p] for p in gone)
        if gone:
            log.info("output budget: deleted %d oldest files (%.1f MB) from %s; %d deleted in all", len(gone),
                     sum(sizes[p] for p in gone) / 1e6, self.folder, self.stats["deleted_files"])
        return gone

    def _run(self):
        while not self._stop.wait(self.every_s):
            try:
                self.sweep()
            except Exception as e:  # noqa: BLE001 - the budget must never stop the run
                self.stats["failed"] += 1
                log.warning("output budget: sweep failed: %s", e)

    def start(self):
        self._thread = threading.Thread(target=self._run, name="bf-epic-output-budget", daemon=True)
        self._thread.start()
        return self

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)
            self._thread = None
        try:
            self.sweep()
        except Exception as e:  # noqa: BLE001
            log.warning("output budget: last sweep failed: %s", e)
