"""Where the watchlist's time goes in the whole-band pipeline: host time per function and thread.

Runs `pipelines/lwasv_sim_wholeband.yaml` in this process with ``--targets`` ICRS watch targets (as
bench_cost.py places them), with the watch path's functions wrapped by timers: the imagers' gulps,
their operator rebuilds and pixel checks, the watch file's writes, the PNG rounds, the snippet block.
Prints each block's time per gulp (the run summary's) and each wrapped function's calls, total and mean
host seconds by thread, and writes them as JSON. Host time is what the other threads wait for while a
function holds Python's lock; GPU work shows only where the function waits for it.

    python tools/bench/profile_watch.py [--targets 10] [--seconds 6] [--device gpu] [--set KEY=VALUE ...]
                                        [--json PATH] [--cprofile N]

``--cprofile N`` also prints the N functions with the most cumulative time inside the operator rebuilds
(``DFTEngine._rebuild``), from Python's cProfile.
"""
from __future__ import annotations

import argparse
import collections
import cProfile
import io
import pstats
import functools
import importlib
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cost import targets  # noqa: E402
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402

#: (module, class, methods) timed
TIMED = (("bf_epic_blocks.blocks.engines", "Engine", ("image_gulp", "_track", "_held_count")),
         ("bf_epic_blocks.blocks.engines", "DFTEngine", ("_rebuild", "_whole")),
         ("bf_epic_blocks.blocks.dft_imager", "DFTImagerBlock", ("_operator", "on_data")),
         ("bf_epic_blocks.blocks.watch", "WatchPixels", ("state",)),
         ("bf_epic_blocks.blocks.watch", "WatchWriterBlock", ("on_data", "write_pngs")),
         ("bf_epic_blocks.io.watchfile", "WatchWriter", ("append", "flush")),
         ("bf_epic_blocks.blocks.snippets", "SnippetBlock", ("on_data",)))


def wrap_all(table):
    for mod, cls_name, names in TIMED:
        cls = getattr(importlib.import_module(mod), cls_name)
        for name in names:
            f = getattr(cls, name)

            def timed(*a, _f=f, _key=f"{cls_name}.{name}", **k):
                t0 = time.perf_counter()
                try:
                    return _f(*a, **k)
                finally:
                    r = table[(threading.current_thread().name, _key)]
                    r[0] += 1
                    r[1] += time.perf_counter() - t0
            setattr(cls, name, functools.wraps(f)(timed))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--targets", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more overrides")
    ap.add_argument("--json")
    ap.add_argument("--cprofile", type=int, default=0, metavar="N",
                    help="print the N costliest functions inside the operator rebuilds")
    args = ap.parse_args(argv)
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    table = collections.defaultdict(lambda: [0, 0.0])
    wrap_all(table)
    prof = cProfile.Profile() if args.cprofile else None
    if prof is not None:
        from bf_epic_blocks.blocks.engines import DFTEngine
        rebuild = DFTEngine._rebuild

        def profiled(self, lm, _f=rebuild):
            if self.pixels_fn is None:          # the main imager's one build
                return _f(self, lm)
            prof.enable()
            try:
                return _f(self, lm)
            finally:
                prof.disable()
        DFTEngine._rebuild = profiled
    sets = [f"device={args.device}", f"source.duration_s={args.seconds}", "output.dir=/tmp/profile_watch"]
    if args.targets:
        sets.append(f"watch.targets={targets(args.targets)}")
    sets += args.set
    cfg = load_config(REPO / "pipelines" / "lwasv_sim_wholeband.yaml", sets)
    s = runner.run(cfg, show_progress=False)
    print(f"# {args.targets} targets, {args.seconds:g} s of data: pipeline {s['wall_s']:.1f} s")
    for name, b in s["blocks"].items():
        print(f"  {name:32s} {b['ngulp']:5d} gulps {1e3 * b['process_s'] / max(1, b['ngulp']):8.2f} ms/gulp")
    rows = sorted(((th, fn, n, t) for (th, fn), (n, t) in table.items()), key=lambda r: -r[3])
    for th, fn, n, t in rows:
        print(f"  {th[:24]:24s} {fn:34s} {n:6d} calls {t:8.3f} s {1e3 * t / max(n, 1):9.3f} ms/call")
    if prof is not None:
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(args.cprofile)
        print(buf.getvalue())
    if args.json:
        write_json(args.json, {"benchmark": "profile_watch", "date": utc_now(), "machine": machine(args.device),
                               "targets": args.targets, "seconds": args.seconds, "blocks": s["blocks"],
                               "functions": [{"thread": th, "function": fn, "calls": n, "seconds": t}
                                             for th, fn, n, t in rows]})


if __name__ == "__main__":
    main()
