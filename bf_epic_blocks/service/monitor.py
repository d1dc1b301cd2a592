"""What a running pipeline is doing, as plain numbers: the snapshot that ``/metrics`` and ``/health`` serve.

:class:`Monitor` reads the counters the blocks keep anyway (the runtime's per-block ``stats``, the
source's ``tbf_stats`` / ``udp_stats``, the imager's ``img_stats``, the search's, the watchlist's, the
gain solver's, the flagger's) from the service's thread; every value is a number copied out of a dict
that its own block updates, so reading needs no lock and costs the pipeline nothing.

:func:`assess` turns a snapshot into the station's go / degraded / down with the reasons, a pure
function of the snapshot and the limits.
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass

from .heap import memory_figures

__all__ = ["Monitor", "Limits", "assess"]


@dataclass(frozen=True)
class Limits:
    """When health leaves go (``service:`` keys of the same names).

    no_data_s : seconds without a new gulp at the source before the pipeline is down (no data);
    behind : a live source whose real-time factor over the last minute falls below this is degraded;
    stale_solution_s : a live solution older than this is stale (degraded); None: 3 x the cadence;
    min_free_gb : the output folder's disk with less free than this is degraded (half of it: down);
    lost_window_s : data lost (frames missing, samples overflowed, kernel drops, late frames) within the
    last this many seconds is degraded (the totals since the start stay in the metrics): a glitch weeks
    ago is not today's state.
    """
    no_data_s: float = 10.0
    behind: float = 1.0
    stale_solution_s: float | None = None
    min_free_gb: float = 5.0
    lost_window_s: float = 600.0


#: the source's counters of data lost, by name (:func:`assess`)
LOST = ("frames_missing", "samples_overflow", "kernel_drops", "frames_late")


def _num(d):
    """The numeric items of a dict (bools as 0/1), others left out."""
    out = {}
    for k, v in (d or {}).items():
        if isinstance(v, bool):
            out[k] = int(v)
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = v
    return out


#: candidates the page lists, the latest first
RECENT = 10


def recent_candidates(rows, n=RECENT):
    """The last ``n`` of a TransientSearchBlock's candidate rows, latest first, as plain values: ``time_utc``
    (ISO), ``snr``, ``dm`` (pc cm^-3), ``width_ms``, ``ra_deg``, ``dec_deg``, ``kind`` ('point' or
    'sky-wide'). The search appends to its list from its own thread; a copy of its tail is read."""
    out = []
    for r in list(rows[-n:])[::-1]:
        t = r.get("time_utc")
        out.append({"time_utc": getattr(t, "isot", str(t)), "snr": float(r["snr"]), "dm": float(r["dm"]),
                    "width_ms": float(r["width_ms"]), "ra_deg": float(r["ra_deg"]), "dec_deg": float(r["dec_deg"]),
                    "kind": str(r.get("kind", "point"))})
    return out


class Monitor:
    """A live view of a built pipeline graph (``runner.build_graph``'s result) for the service.

    ``snapshot()`` -> dict: ``uptime_s``, ``data_s`` (seconds of data the source has read), ``realtime``
    (data seconds per wall second since the first data), ``realtime_recent`` (over the last ~60 s of
    snapshots), ``last_data_age_s``, ``blocks`` {name: runtime stats}, ``source`` (its stats), ``imager``,
    ``search``, ``recent_candidates`` (:func:`recent_candidates`), ``watch``, ``solver`` (with ``solution_age_s``), ``flagging``, ``disk`` (output folder:
    total, used, free bytes), ``gpu`` (free and total bytes, where CuPy sees one), ``failed`` (the error
    that stopped the pipeline, or None), ``finished``.
    """

    def __init__(self, graph, cfg, dt_s=None, lost_window_s=Limits.lost_window_s):
        self.g, self.cfg = graph, cfg
        self.started = time.perf_counter()
        self.lost_window_s = float(lost_window_s)
        self._lost = [(self.started, {})]       # (wall, the source's loss counters) of recent snapshots
        self.failed, self.finished = None, False
        src = cfg["source"]
        ch = src.get("channels") or {}
        # seconds of data per frame: the simulated source's channel width; a capture's from its scan
        self.dt_s = dt_s if dt_s is not None else (1.0 / float(ch["width_hz"]) if ch.get("width_hz") else None)
        self._history = []          # (wall, data seconds) of recent snapshots
        self.live = src["kind"] == "udp"

    def _data_s(self):
        frames = int(self.g.source.stats.get("nframe_written", 0)) if hasattr(self.g.source, "stats") else 0
        dt = self.dt_s
        if dt is None:              # a live stream's channel width comes with its packets
            bw = getattr(getattr(getattr(self.g.source, "capture", None), "layout", None), "chan_bw_hz", None)
            dt = 1.0 / bw if bw else None
        return frames * dt if dt else None

    def snapshot(self):
        now = time.perf_counter()
        g = self.g
        blocks = {}
        for b in g.pipeline.blocks:
            st = getattr(b, "stats", None)
            if isinstance(st, dict):
                s = _num(st)
                last = st.get("last_data_at")
                s["last_data_age_s"] = None if last is None else now - last
                blocks[b.name] = s
        src_blk = blocks.get(getattr(g.source, "name", ""), {})
        first = getattr(g.source, "stats", {}).get("first_data_at") if hasattr(g.source, "stats") else None
        data_s = self._data_s()
        snap = {
            "uptime_s": now - self.started, "data_s": data_s, "blocks": blocks,
            "last_data_age_s": src_blk.get("last_data_age_s"),
            "source": _num(getattr(g.source, "udp_stats", None) or getattr(g.source, "tbf_stats", None) or {}),
            "imager": _num(getattr(g.imager, "img_stats", None)),
            "failed": self.failed, "finished": self.finished, "live": self.live,
        }
        snap["realtime"] = (data_s / (now - first)) if data_s and first and now > first else None
        # the data lost within the window: the counters now less those of the newest snapshot at least
        # lost_window_s old (or the oldest kept; the run's start counts as all zero)
        lost = {k: snap["source"].get(k, 0) for k in LOST}
        self._lost.append((now, lost))
        while len(self._lost) > 2 and now - self._lost[1][0] >= self.lost_window_s:
            self._lost.pop(0)
        base = self._lost[0][1]
        snap["source_lost_recent"] = {k: v - base.get(k, 0) for k, v in lost.items()}
        self._history.append((now, data_s or 0.0))
        while len(self._history) > 2 and now - self._history[1][0] > 60.0:
            self._history.pop(0)
        (t0, d0), (t1, d1) = self._history[0], self._history[-1]
        snap["realtime_recent"] = (d1 - d0) / (t1 - t0) if t1 - t0 > 1.0 else snap["realtime"]
        if g.search is not None:
            snap["search"] = _num(getattr(g.search, "search_stats", None))
            snap["recent_candidates"] = recent_candidates(getattr(g.search, "rows", None) or [])
        if g.watch is not None:
            w = {"rows": g.watch.rows, "inactive_rows": g.watch.inactive, "light_curve_triggers": g.watch.triggers}
            if g.snippets is not None:
                w.update({f"snippet_{k}": v for k, v in g.snippets.trig_stats.items()})
            alerts = getattr(g.watch, "alerts", None)
            if alerts is not None:
                w.update({f"alerts_{k}": v for k, v in _num(alerts.stats).items()})
            snap["watch"] = w
        if g.solver is not None:
            sv = _num(g.solver.solver_stats)
            last = getattr(g.solver, "last_solution_at", None)
            sv["solution_age_s"] = None if last is None else now - last
            snap["solver"] = sv
        flaggers = [b for b in g.pipeline.blocks if type(b).__name__ == "RFIFlagBlock"]
        if flaggers:
            fs = getattr(flaggers[0], "flag_stats", None) or {}
            snap["flagging"] = {**_num(fs), **{f"flagged_{k}": v for k, v in _num(fs.get("flagged")).items()}}
        try:
            du = shutil.disk_usage(g.outdir)
            snap["disk"] = {"total_bytes": du.total, "used_bytes": du.used, "free_bytes": du.free}
        except OSError:
            snap["disk"] = None
        snap["gpu"] = _gpu_memory() if self.cfg["device"] != "cpu" else None
        snap["memory"] = memory_figures()
        if getattr(g, "budget", None) is not None:
            snap["budget"] = dict(g.budget.stats)
        return snap


def _gpu_memory():
    try:
        from ..imaging._xp import cupy_or_none
        cp = cupy_or_none()
        free, total = cp.cuda.runtime.memGetInfo()
        return {"free_bytes": int(free), "total_bytes": int(total)}
    except Exception:  # noqa: BLE001 - no CuPy or no device: no GPU figures
        return None


def assess(snap, limits=Limits(), cadence_s=None):
    """(status, reasons) of a snapshot: 'down' (a block failed; no data for ``no_data_s``; the disk
    under half of ``min_free_gb``), 'degraded' (a live source behind real time; frames lost or missing
    within ``lost_window_s`` -- ``source_lost_recent``, else the totals of ``source``; a stale calibration; the disk under ``min_free_gb``), else 'go'. ``reasons``: one
    line each, the worst first."""
    down, degraded = [], []
    if snap.get("failed"):
        down.append(f"the pipeline stopped: {snap['failed']}")
    age = snap.get("last_data_age_s")
    if not snap.get("finished") and age is not None and age > limits.no_data_s:
        down.append(f"no data for {age:.0f} s (limit {limits.no_data_s:g} s)")
    rt = snap.get("realtime_recent")
    if snap.get("live") and rt is not None and rt < limits.behind:
        degraded.append(f"behind real time: x{rt:.2f} over the last minute")
    recent = snap.get("source_lost_recent")
    src = recent if recent is not None else (snap.get("source") or {})
    lost = {k: v for k, v in src.items() if k in LOST and v}
    if lost:
        within = "" if recent is None else f" in the last {limits.lost_window_s:g} s"
        degraded.append(f"data lost{within}: " + ", ".join(f"{k} {v}" for k, v in sorted(lost.items())))
    sv = snap.get("solver")
    if sv is not None:
        stale = limits.stale_solution_s if limits.stale_solution_s is not None else \
            (3.0 * cadence_s if cadence_s else None)
        a = sv.get("solution_age_s")
        if stale is not None and a is not None and a > stale:
            degraded.append(f"calibration stale: the last solution is {a:.0f} s old (limit {stale:g} s)")
    disk = snap.get("disk")
    if disk:
        free_gb = disk["free_bytes"] / 1e9
        if free_gb < 0.5 * limits.min_free_gb:
            down.append(f"disk nearly full: {free_gb:.1f} GB free in the output folder")
        elif free_gb < limits.min_free_gb:
            degraded.append(f"disk low: {free_gb:.1f} GB free in the output folder (limit {limits.min_free_gb:g} GB)")
    status = "down" if down else "degraded" if degraded else "go"
    return status, down + degraded
