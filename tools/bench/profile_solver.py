"""Where the live gain solver's cost goes in the whole-band pipeline: a time line of the imager's gulps and
of each solution's steps.

Runs `pipelines/lwasv_sim_wholeband.yaml` (search and outputs off, as ``bench_calibration.py --case cost``)
in this process with `calibration.solve` (a solution every 10 s from ``--integration`` s of data), with the
solution's steps wrapped by timers: the imager's gulps, its solution hook and the operator's new gains
(``DFTOperator.reweight``, the fused pieces' ``requantise``), the solver's sums hand-over, solve and file
writes, and the live table's waits. Prints each step's calls, total and longest host seconds by thread, the
imager's gulp-to-gulp gaps (the longest ones with the steps running beside them), and writes them as JSON.
Host time is what a thread waits for, including a wait for the GPU work it queued.

    python tools/bench/profile_solver.py [--seconds 40] [--integration 1] [--device gpu] [--set KEY=VALUE ...]
                                         [--sample] [--json PATH]
"""
from __future__ import annotations

import argparse
import collections
import functools
import importlib
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402

#: (module, class or None, function) timed
TIMED = (("bf_epic_blocks.blocks.engines", "Engine", "image_gulp"),
         ("bf_epic_blocks.blocks.dft_imager", "DFTImagerBlock", "_solution_hook"),
         ("bf_epic_blocks.blocks.dft_imager", "DFTImagerBlock", "_weights"),
         ("bf_epic_blocks.imaging.dft", "DFTOperator", "reweight"),
         ("bf_epic_blocks.imaging.fused", "FusedOperator", "requantise"),
         ("bf_epic_blocks.blocks.gain_solver", "GainSolverBlock", "_hand_over"),
         ("bf_epic_blocks.blocks.gain_solver", "GainSolverBlock", "_solve"),
         ("bf_epic_blocks.blocks.gain_solver", "GainSolverBlock", "write"),
         ("bf_epic_blocks.blocks.gain_solver", "LiveGainTable", "wait_through"),
         ("bf_epic_blocks.blocks.gain_solver", "LiveGainTable", "post"),
         ("bf_epic_blocks.sky.model", None, "sky_model"))

#: the steps of a solution listed in the time line
STEPS = ("GainSolverBlock._hand_over", "GainSolverBlock._solve", "GainSolverBlock.write", "DFTOperator.reweight",
         "FusedOperator.requantise")


def wrap_all(events, t0):
    """Wrap each of :data:`TIMED`; every call appends (thread, name, start, end), seconds after ``t0``."""
    for mod, cls, name in TIMED:
        owner = getattr(importlib.import_module(mod), cls) if cls else importlib.import_module(mod)
        f = getattr(owner, name)

        def timed(*a, _f=f, _key=f"{cls}.{name}" if cls else name, **k):
            start = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                events.append((threading.current_thread().name, _key, start - t0, time.perf_counter() - t0))
        setattr(owner, name, functools.wraps(f)(timed))


class StackSampler:
    """Where a thread's host time goes inside the steps named: every ``every_s`` while a thread is in one
    of them, its innermost frame and its innermost frame in this package are counted (a sampling
    profile: a line that waits on the GPU collects samples as much as one that computes)."""

    def __init__(self, steps, every_s=0.005):
        self.steps, self.every_s = set(steps), every_s
        self.inside = {}                       # thread ident -> step name
        self.counts = collections.Counter()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stack-sampler", daemon=True)

    def wrap(self, owner, name, key):
        f = getattr(owner, name)

        def entered(*a, _f=f, **k):
            me = threading.get_ident()
            outer = me in self.inside
            if not outer:
                self.inside[me] = key
            try:
                return _f(*a, **k)
            finally:
                if not outer:
                    self.inside.pop(me, None)
        setattr(owner, name, functools.wraps(f)(entered))

    def _run(self):
        pkg = str(Path(REPO, "bf_epic_blocks"))
        while not self._stop.wait(self.every_s):
            frames = sys._current_frames()
            for ident, step in list(self.inside.items()):
                fr = frames.get(ident)
                if fr is None:
                    continue
                inner, ours = f"{Path(fr.f_code.co_filename).name}:{fr.f_lineno} {fr.f_code.co_name}", None
                while fr is not None and ours is None:
                    if fr.f_code.co_filename.startswith(pkg):
                        ours = f"{Path(fr.f_code.co_filename).name}:{fr.f_lineno} {fr.f_code.co_name}"
                    fr = fr.f_back
                self.counts[(step, ours, inner)] += 1

    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._thread.join()

    def table(self, top=15):
        """The most-sampled (step, our line, innermost line) with their seconds."""
        return [{"step": s, "line": o, "innermost": i, "seconds": n * self.every_s}
                for (s, o, i), n in self.counts.most_common(top)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=40.0, help="seconds of data")
    ap.add_argument("--integration", type=float, default=1.0, help="seconds of data each solution is summed from")
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more overrides")
    ap.add_argument("--gaps", type=int, default=12, help="the longest gulp-to-gulp gaps listed")
    ap.add_argument("--sample", action="store_true",
                    help="also sample the lines the imager's thread spends its time on while it folds in a solution")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    events = []
    wrap_all(events, time.perf_counter())
    sampler = None
    if args.sample:
        from bf_epic_blocks.imaging.dft import DFTOperator
        sampler = StackSampler(["DFTOperator.reweight"])
        sampler.wrap(DFTOperator, "reweight", "DFTOperator.reweight")
        sampler.start()
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    sets = [f"device={args.device}", "imager.search=null", "output.cube=null", "output.fits=false",
            "output.png=false", "output.integrate=null", f"source.duration_s={args.seconds}",
            "output.dir=/tmp/profile_solver", "calibration.solve.cadence_s=10",
            f"calibration.solve.integration_s={args.integration}", *args.set]
    cfg = load_config(REPO / "pipelines" / "lwasv_sim_wholeband.yaml", sets)
    s = runner.run(cfg, show_progress=False)
    samples = []
    if sampler is not None:
        sampler.stop()
        samples = sampler.table()
    print(f"# {args.seconds:g} s of data, a solution every 10 s from {args.integration:g} s: pipeline "
          f"{s['wall_s']:.1f} s; operator {s.get('operator')}")
    agg = collections.defaultdict(lambda: [0, 0.0, 0.0])
    for th, k, a, b in events:
        r = agg[(th, k)]
        r[0] += 1
        r[1] += b - a
        r[2] = max(r[2], b - a)
    rows = sorted(((th, k, n, t, mx) for (th, k), (n, t, mx) in agg.items()), key=lambda r: -r[3])
    for th, k, n, t, mx in rows:
        print(f"  {th[:20]:20s} {k:30s} {n:6d} calls {t:8.3f} s  longest {mx:7.3f} s")
    starts = np.array(sorted(a for th, k, a, b in events if k == "Engine.image_gulp"))
    gaps = np.diff(starts) if starts.size > 1 else np.zeros(0)
    longest = []
    if gaps.size:
        print(f"  the imager's gulps start {1e3 * np.median(gaps):.2f} ms apart (median), "
              f"{1e3 * np.percentile(gaps, 99):.1f} ms (99%), {gaps.max():.3f} s at most")
        for i in sorted(np.argsort(gaps)[-args.gaps:]):
            t, g = float(starts[i]), float(gaps[i])
            beside = [(k, round(a, 2), round(b - a, 3)) for th, k, a, b in events
                      if k in STEPS and a <= t + g and b >= t]
            longest.append({"after_s": t, "gap_s": g, "beside": beside})
            print(f"  gap {g:6.3f} s at {t:7.2f} s: {beside}")
    timeline = sorted((round(a, 3), round(b - a, 4), k, th) for th, k, a, b in events if k in STEPS)
    print("  the solutions' steps (start s, seconds, step):")
    for a, d, k, th in timeline:
        print(f"    {a:8.2f} {d:7.3f}  {k}")
    if samples:
        print("  where the imager's thread spent a solution's fold-in (sampled every "
              f"{1e3 * sampler.every_s:g} ms: seconds, our line, innermost line):")
        for r in samples:
            print(f"    {r['seconds']:7.3f}  {r['line']}  <-  {r['innermost']}")
    if args.json:
        write_json(args.json, {"benchmark": "profile_solver", "date": utc_now(), "machine": machine(args.device),
                               "seconds": args.seconds, "integration_s": args.integration, "wall_s": s["wall_s"],
                               "operator": s.get("operator"), "blocks": s["blocks"],
                               "functions": [{"thread": th, "function": k, "calls": n, "seconds": t, "longest_s": mx}
                                             for th, k, n, t, mx in rows],
                               "longest_gaps": longest, "samples": samples,
                               "steps": [{"start_s": a, "seconds": d, "step": k, "thread": th}
                                         for a, d, k, th in timeline]})


if __name__ == "__main__":
    main()
