"""A station of several tunings run as one process (``tunings:`` in the pipeline YAML): what
:func:`bf_epic_blocks.pipeline.runner.run_station` runs them with.

Each tuning is a whole pipeline of its own (its configuration checked and filled by
:func:`bf_epic_blocks.pipeline.config.load_config`): its graph is built as ``bf-epic run`` builds one, and
the graphs run side by side, each block in its own thread as always. One SIGTERM drains them all, one
stall watchdog watches every block, and one failure stops every tuning. Each tuning writes what its own
pipeline would, in ``<output.dir>/<tuning>``; the station adds the events that its tunings' searches saw
together (:mod:`bf_epic_blocks.search.coincidence`), logged as they happen and written at the end to
``<output.dir>/<name>_events.ecsv``.

    tuning lo: source -> ... -> imager -> search --+
    tuning hi: source -> ... -> imager -> search --+--> station events
"""
from __future__ import annotations

import logging
import threading
from pathlib import Path

log = logging.getLogger("bf_epic_blocks")


class Together:
    """Several built pipelines run as one: ``run()`` runs each in a thread and returns when all have ended;
    the first failure shuts the others down and is raised. ``blocks`` are all of theirs; ``drain()``
    (where every pipeline has it) drains each."""

    def __init__(self, pipelines):
        self.pipelines = list(pipelines)
        self.blocks = [b for p in self.pipelines for b in p.blocks]
        if all(hasattr(p, "drain") for p in self.pipelines):
            self.drain = self._drain

    def _drain(self):
        for p in self.pipelines:
            p.drain()

    def shutdown(self, wait=True):
        for p in self.pipelines:
            p.shutdown(wait=wait)

    def run(self):
        errors = []

        def one(p):
            try:
                p.run()
            except BaseException as e:  # noqa: BLE001 - raised in the calling thread below
                errors.append(e)
                for q in self.pipelines:
                    if q is not p:
                        q.shutdown(wait=False)
        threads = [threading.Thread(target=one, args=(p,), name=f"tuning-{k}", daemon=True)
                   for k, p in enumerate(self.pipelines)]
        try:
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                for t in threads:
                    t.join(0.2)
        except BaseException:      # KeyboardInterrupt: stop every tuning, then re-raise
            self.shutdown()
            raise
        if errors:
            raise errors[0]


def tuning_search(name, tc, g):
    """The :class:`~bf_epic_blocks.search.coincidence.TuningSearch` of tuning ``name`` (its config ``tc``,
    its built graph ``g``): from its search block once it has seen a sequence (the images' frequencies and
    cadence, its DM trials), before that from the configuration (a simulated source's channels; NaN for
    a capture's or a stream's, which are known only from their data)."""
    import numpy as np

    from ..search.coincidence import TuningSearch
    s = g.search
    lay = getattr(s, "lay", None)
    trials = getattr(getattr(s, "search", None), "dms", None)
    if trials is None:
        trials = tc["imager"]["search"]["dms"]
    grid = tc["imager"].get("grid")
    cell = 2.0 / grid["size"] if grid else float("nan")
    if lay is not None:
        f_ref, dt = float(np.max(lay["freq_hz"])), float(lay["dt_s"])
    elif tc["source"]["kind"] == "simulated":
        ch = tc["source"]["channels"]
        f_ref = float((ch["first"] + ch["count"] - 1) * ch["width_hz"])
        dt = tc["imager"]["accumulate_frames"] / float(ch["width_hz"])
    else:
        f_ref = dt = float("nan")
    return TuningSearch(name, f_ref, dt, np.asarray(trials, dtype=np.float64), cell)


def write_events(cfg, searches, blocks):
    """Join the tunings' candidate tables and write ``<output.dir>/<name>_events.ecsv``; returns its path
    and ``{"events": rows, "coincident": rows seen by more than one tuning}``."""
    from ..io.candidates import candidate_table
    from ..search.coincidence import station_events
    tables = []
    for b in blocks:
        t = getattr(b, "candidates", None)
        tables.append(t if t is not None else candidate_table([], {}))
    events = station_events(tables, searches)
    out = Path(cfg["output"]["dir"])
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{cfg['output']['prefix']}_events.ecsv"
    events.write(path, format="ascii.ecsv", overwrite=True)
    return path, {"events": len(events), "coincident": int((events["ntunings"] > 1).sum()) if len(events) else 0}
