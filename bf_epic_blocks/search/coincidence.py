"""One burst, several tunings: a station's candidates from each tuning's search joined into events.

A dispersed burst reaches a station's low tuning later than its high one, by the dispersion law
(:func:`bf_epic_blocks.conventions.dispersion_delay_s`). Each tuning's search reports a candidate's time
as its start at that tuning's highest channel (``f_ref``); here every detection's time is carried, at its
own DM, to the station's highest channel ``F``:

    t_F = t_ref + dispersion_delay_s(dm, F, f_ref)          (seconds; <= t_ref, as F >= f_ref)

Two detections from different tunings are one event when all of these hold (the tolerances are what the
searches themselves resolve, not free parameters):

- **DM**: they differ by at most ``dm_trials`` trial steps of the coarser tuning at that DM (one step by
  default: a tuning's tree or list of trials places a burst within half a step of its DM, either side);
- **time**: their ``t_F`` differ by at most the sum, over the two, of one image, half the boxcar width, and
  the time one DM step moves ``t_F`` (``|dispersion_delay_s(step, F, f_ref)|``), so that the DM each found
  within its own trials cannot part them;
- **place**: their directions differ by at most ``cells`` grid cells (1.5 by default) in (l, m) at the
  coarser tuning's cell; sky-wide events (impulses, lightning: the whole sky over threshold) are joined on
  DM and time alone, and only with sky-wide events.

Events are formed greedily from the brightest detection down; each event takes at most one detection from
each tuning (its brightest match). A candidate no other tuning saw is an event of one detection, so the
events table lists everything the station's searches found, and ``ntunings`` says which were seen twice.

An event seen by tunings at different frequencies measures its DM from the tunings' arrival times:
each search dedisperses to its own highest channel, so its time there hardly depends on which of its DM
trials won, and the delay between tunings spans a lever arm far longer than any one tuning's band (a
burst's arrival at 57.6 MHz and 93.6 MHz differ by 0.78 s per unit DM; across one 19.6-MHz tuning at
74 MHz, 0.28 s). A least-squares fit of ``t_k = t_F + K DM (f_k^-2 - F^-2)`` over the detections gives the
event's ``dm`` and ``time_utc`` (``dm_from`` 'tunings'); an event of one detection keeps its search's
(``dm_from`` 'trials').
"""
from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from ..conventions import dispersion_delay_s

log = logging.getLogger("bf_epic_blocks")

__all__ = ["TuningSearch", "Detection", "detection", "coincident", "fit_dm", "station_events", "StationEvents"]


@dataclass
class TuningSearch:
    """What joining needs of one tuning's search.

    name : the tuning's name; f_ref_hz : its candidates' time reference (its highest channel, Hz);
    dt_s : one image (s); dm_trials : its DM trials (pc cm^-3), any order; cell_lm : one grid cell in the
    direction cosines (nan: no grid, places not compared)."""
    name: str
    f_ref_hz: float
    dt_s: float
    dm_trials: np.ndarray
    cell_lm: float = float("nan")

    def __post_init__(self):
        self._trials = np.unique(np.asarray(self.dm_trials, dtype=np.float64))     # sorted, once
        self._gaps = np.diff(self._trials)

    def dm_step(self, dm: float) -> float:
        """The trial spacing at ``dm``: the larger of the gaps either side of the nearest trial (0 for one
        trial)."""
        d, gaps = self._trials, self._gaps
        if d.size < 2:
            return 0.0
        k = int(np.clip(np.searchsorted(d, dm), 1, d.size - 1))
        k = k if d[k] - dm < dm - d[k - 1] else k - 1                    # the nearest trial
        return float(max(gaps[max(k - 1, 0)], gaps[min(k, gaps.size - 1)]))

    @property
    def max_step(self) -> float:
        """The widest gap between its trials (0 for one trial)."""
        return float(self._gaps.max()) if self._gaps.size else 0.0


@dataclass
class Detection:
    """One tuning's candidate as joining sees it (``t_f_unix`` its start at the station's highest channel)."""
    tuning: int
    row: int
    t_f_unix: float
    dm: float
    width_s: float
    l: float
    m: float
    snr: float
    skywide: bool
    time_unix: float                   # its own time (at its tuning's f_ref)
    ra_deg: float = float("nan")
    dec_deg: float = float("nan")
    extra: dict = field(default_factory=dict)


def detection(row, k: int, i: int, search: TuningSearch, f_station_hz: float) -> Detection:
    """A :class:`Detection` from a candidate row (a table row or the search's row dict: ``time_utc`` an
    astropy Time, ``dm``, ``width_ms``, ``l``, ``m``, ``snr``, ``kind``, ``ra_deg``, ``dec_deg``)."""
    t = float(row["time_utc"].unix)
    dm = float(row["dm"])
    return Detection(tuning=k, row=i, t_f_unix=t + float(dispersion_delay_s(dm, f_station_hz, search.f_ref_hz)),
                     dm=dm, width_s=float(row["width_ms"]) * 1e-3, l=float(row["l"]), m=float(row["m"]),
                     snr=float(row["snr"]), skywide=str(row["kind"]) == "sky-wide", time_unix=t,
                     ra_deg=float(row["ra_deg"]), dec_deg=float(row["dec_deg"]))


def coincident(a: Detection, b: Detection, sa: TuningSearch, sb: TuningSearch, f_station_hz: float, *,
               dm_trials: float = 1.0, cells: float = 1.5) -> bool:
    """Whether detections ``a`` (of tuning ``sa``) and ``b`` (of ``sb``) are one burst (module docstring)."""
    if a.skywide != b.skywide:
        return False
    step_a, step_b = sa.dm_step(a.dm), sb.dm_step(b.dm)
    if abs(a.dm - b.dm) > dm_trials * max(step_a, step_b) + 1e-9:
        return False
    tol = (sa.dt_s + sb.dt_s + 0.5 * (a.width_s + b.width_s)
           + abs(float(dispersion_delay_s(step_a, f_station_hz, sa.f_ref_hz)))
           + abs(float(dispersion_delay_s(step_b, f_station_hz, sb.f_ref_hz))))
    if abs(a.t_f_unix - b.t_f_unix) > tol:
        return False
    if a.skywide:
        return True
    cell = np.nanmax([sa.cell_lm, sb.cell_lm]) if not (math.isnan(sa.cell_lm) and math.isnan(sb.cell_lm)) \
        else float("nan")
    return math.isnan(cell) or math.hypot(a.l - b.l, a.m - b.m) <= cells * cell + 1e-12


def _group(dets, searches, f_station_hz, dm_trials, cells):
    """Events (lists of detections, the first the brightest) from detections, greedily by S/N. A detection
    is compared only with the other tunings' detections within the widest time tolerance any pair can have
    (:func:`coincident`), found by bisection: a night's thousands of candidates join in n log n."""
    import bisect
    if not dets:
        return []
    reach = (2 * max(s.dt_s for s in searches) + max(d.width_s for d in dets)
             + 2 * max(abs(float(dispersion_delay_s(s.max_step, f_station_hz, s.f_ref_hz)))
                       for s in searches))
    by_tuning = []
    for k in range(len(searches)):
        mine = sorted((d.t_f_unix, i) for i, d in enumerate(dets) if d.tuning == k)
        by_tuning.append(([t for t, _ in mine], [i for _, i in mine]))
    used, events = set(), []
    for i in sorted(range(len(dets)), key=lambda i: -dets[i].snr):
        if i in used:
            continue
        a = dets[i]
        used.add(i)
        ev = [a]
        for k, (times, idx) in enumerate(by_tuning):
            if k == a.tuning:
                continue
            lo, hi = bisect.bisect_left(times, a.t_f_unix - reach), bisect.bisect_right(times, a.t_f_unix + reach)
            near = [j for j in idx[lo:hi] if j not in used and
                    coincident(a, dets[j], searches[a.tuning], searches[k], f_station_hz, dm_trials=dm_trials,
                               cells=cells)]
            if near:
                best = max(near, key=lambda j: dets[j].snr)        # its brightest match
                used.add(best)
                ev.append(dets[best])
        events.append(ev)
    return events


def fit_dm(times_s, f_ref_hz, f_station_hz):
    """(dm, t_F): the DM (pc cm^-3) and the start at ``f_station_hz`` that best fit (least squares) the
    starts ``times_s`` seen at frequencies ``f_ref_hz``; None where the frequencies do not differ."""
    f = np.asarray(f_ref_hz, np.float64)
    if f.size < 2 or np.ptp(f) == 0:
        return None
    x = np.asarray(dispersion_delay_s(1.0, f, f_station_hz))          # delay per unit DM at each
    t = np.asarray(times_s, np.float64)
    t0 = t.mean()                                                       # unix seconds: fit about their mean
    a = np.column_stack([np.ones_like(x), x])
    (c, dm), *_ = np.linalg.lstsq(a, t - t0, rcond=None)
    return float(dm), float(t0 + c)


def station_events(tables, searches, *, dm_trials: float = 1.0, cells: float = 1.5):
    """The station's events from each tuning's candidate table.

    tables : one astropy Table per tuning (:func:`bf_epic_blocks.io.candidates.candidate_table`'s
        columns), in the order of ``searches`` (:class:`TuningSearch`).
    Returns an astropy Table sorted by time, a row per event: ``event``; ``time_utc`` (its start at the
    station's highest channel) and ``dm``: fitted to the detections' times where tunings at different
    frequencies saw it (:func:`fit_dm`; ``dm_from`` 'tunings'), else from its brightest detection and the
    detections' S/N²-weighted mean DM ('trials'); ``snr`` (their S/N added in quadrature), ``l``, ``m``, ``ra_deg``, ``dec_deg`` and ``kind`` (of
    the brightest), ``ntunings``, ``tunings`` (names, comma-separated); and per tuning ``<name>_row`` (the
    row of its candidate table, -1: not seen), ``<name>_snr``, ``<name>_dm``, ``<name>_time_utc`` (ISO, at
    its own ``f_ref``; '' when not seen). ``meta`` holds the station's ``f_ref_mhz`` and the tolerances."""
    from astropy.table import Table
    from astropy.time import Time
    f_station = float(np.nanmax([s.f_ref_hz for s in searches]))
    dets = [detection(r, k, i, searches[k], f_station) for k, t in enumerate(tables) for i, r in enumerate(t)]
    events = _group(dets, searches, f_station, dm_trials, cells)
    fits = [fit_dm([d.time_unix for d in ev], [searches[d.tuning].f_ref_hz for d in ev], f_station) for ev in events]
    w = [np.array([d.snr ** 2 for d in ev]) for ev in events]
    when = [ev[0].t_f_unix if fit is None else fit[1] for ev, fit in zip(events, fits)]
    order = np.argsort(when, kind="stable")
    events, fits, w, when = ([x[i] for i in order] for x in (events, fits, w, when))
    cols = {"event": np.arange(len(events), dtype=np.int64),
            "time_utc": Time(when, format="unix", scale="utc") if events else Time([], format="unix", scale="utc")}
    cols["dm"] = np.array([float(np.sum(wi * [d.dm for d in ev]) / np.sum(wi)) if fit is None else fit[0]
                           for ev, wi, fit in zip(events, w, fits)])
    cols["dm_from"] = np.array(["trials" if fit is None else "tunings" for fit in fits], dtype="U8")
    cols["snr"] = np.array([math.sqrt(float(np.sum(wi))) for wi in w])
    for k in ("l", "m", "ra_deg", "dec_deg"):
        cols[k] = np.array([getattr(ev[0], k) for ev in events], dtype=np.float64)
    cols["kind"] = np.array(["sky-wide" if ev[0].skywide else "point" for ev in events], dtype="U8")
    cols["ntunings"] = np.array([len(ev) for ev in events], dtype=np.int64)
    cols["tunings"] = np.array([",".join(searches[d.tuning].name for d in sorted(ev, key=lambda d: d.tuning))
                                for ev in events], dtype="U64") if events else np.zeros(0, dtype="U1")
    for k, s in enumerate(searches):
        mine = [next((d for d in ev if d.tuning == k), None) for ev in events]
        cols[f"{s.name}_row"] = np.array([-1 if d is None else d.row for d in mine], dtype=np.int64)
        cols[f"{s.name}_snr"] = np.array([np.nan if d is None else d.snr for d in mine])
        cols[f"{s.name}_dm"] = np.array([np.nan if d is None else d.dm for d in mine])
        cols[f"{s.name}_time_utc"] = np.array(["" if d is None else Time(d.time_unix, format="unix").isot
                                               for d in mine], dtype="U26") if events else np.zeros(0, dtype="U1")
    t = Table(cols, meta={"f_ref_mhz": f_station / 1e6, "dm_trials": dm_trials, "cells": cells,
                          "tunings": [s.name for s in searches],
                          "time_reference": "event start at the station's highest channel frequency (f_ref_mhz)"})
    t["time_utc"].format = "isot"
    return t


class StationEvents:
    """Live joining: each tuning's search tells it of every candidate (``listener(k)`` is the search's
    ``on_candidate``); a candidate that joins one from another tuning is logged at once as a station
    event. ``joined`` counts them. Thread-safe (the searches run in their own threads). ``refresh(k)``,
    where given, returns tuning ``k``'s :class:`TuningSearch` anew at each candidate (a search learns its
    trials from its first sequence). ``on_event(alert)``, where given, is told of each join: a dict with
    ``time_utc`` (ISO, the start at the station's highest channel) and ``dm`` (:func:`fit_dm` of the two
    detections), ``ra_deg``, ``dec_deg``, ``snr`` (in quadrature), ``width_ms``, ``kind``, ``tunings``
    and ``reason`` (the alerts' form, :class:`bf_epic_blocks.io.alerts.AlertSender`)."""

    def __init__(self, searches, f_station_hz=None, *, dm_trials=1.0, cells=1.5, keep=1000, refresh=None,
                 on_event=None):
        self.searches = list(searches)
        self.refresh = refresh
        self.on_event = on_event
        self.f_station_hz = f_station_hz
        self.dm_trials, self.cells, self.keep = dm_trials, cells, int(keep)
        self.recent = [[] for _ in self.searches]
        self.joined = 0
        self._lock = threading.Lock()

    def listener(self, k, then=None):
        """The callable for tuning ``k``'s search (``then``: a listener it already had, called first)."""
        def told(row):
            if then is not None:
                then(row)
            self.add(k, row)
        return told

    def add(self, k, row):
        f = self.f_station_hz or float(np.nanmax([s.f_ref_hz for s in self.searches]))
        with self._lock:
            if self.refresh is not None:
                self.searches = [self.refresh(j) for j in range(len(self.searches))]
            d = detection(row, k, len(self.recent[k]), self.searches[k], f)
            for j, others in enumerate(self.recent):
                if j == k:
                    continue
                for o in reversed(others):
                    if coincident(d, o, self.searches[k], self.searches[j], f, dm_trials=self.dm_trials,
                                  cells=self.cells):
                        self.joined += 1
                        log.warning("station event: %s (S/N %.1f, DM %g) and %s (S/N %.1f, DM %g) saw one burst, "
                                    "l %.3f m %.3f", self.searches[k].name, d.snr, d.dm, self.searches[j].name,
                                    o.snr, o.dm, d.l, d.m)
                        if self.on_event is not None:
                            self._tell(d, o, self.searches[k], self.searches[j], f)
                        break
            self.recent[k].append(d)
            del self.recent[k][:-self.keep]

    def _tell(self, a, b, sa, sb, f_station_hz):
        from astropy.time import Time
        fit = fit_dm([a.time_unix, b.time_unix], [sa.f_ref_hz, sb.f_ref_hz], f_station_hz)
        dm, t_f = fit if fit is not None else (a.dm, a.t_f_unix)
        best = a if a.snr >= b.snr else b
        names = ",".join(sorted((sa.name, sb.name)))
        snr = math.hypot(a.snr, b.snr)
        alert = {"time_utc": Time(t_f, format="unix", scale="utc").isot, "dm": round(float(dm), 5),
                 "ra_deg": best.ra_deg, "dec_deg": best.dec_deg, "snr": round(snr, 2),
                 "width_ms": round(1e3 * best.width_s, 4), "kind": "sky-wide" if best.skywide else "point",
                 "tunings": names, "reason": f"station event S/N {snr:.1f} in {names}"}
        try:
            self.on_event(alert)
        except Exception as e:  # noqa: BLE001 - a listener must not stop a search
            log.warning("station events: the listener failed: %s", e)
