"""Where a `bf-epic run` spends its start-up: every CUDA kernel compile, and the time line of a run.

Runs `bf-epic run YAML --set device=gpu` in this process (so CuPy's compiler can be watched) with
CuPy's kernel cache pointed at an empty folder (``--cold``, the default) or at the user's cache
(``--warm``), and prints:

* each kernel CuPy compiled into the (empty) cache, in order: when its file appeared, the gap to the
  one before (compiles run one after another, so about its compile time), and its first line;
* totals: kernels compiled, the run's wall, and seconds from this script's start to the first image
  file.

usage: python tools/bench/cold_start.py YAML [--warm] [--set KEY=VALUE ...] [--json PATH]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchlib import machine, utc_now, write_json

T0 = time.perf_counter()


def cache_listing(folder, t_start_wall):
    """Every kernel CuPy compiled into ``folder`` (``CUPY_CACHE_SAVE_CUDA_SOURCE=1`` keeps its source
    beside it): [(seconds since the run started, seconds since the previous file, first line)] by time.
    Compiles run one after another, so the gap to the previous file is about the compile's time."""
    rows = []
    for p in Path(folder).rglob("*"):
        if p.suffix in (".cu", ".tmp") or not p.is_file():
            continue
        src = p.with_name(p.name + ".cu")
        first = ""
        if src.exists():
            first = next((ln for ln in src.read_text(errors="replace").splitlines() if "__global__" in ln), "")
        rows.append([p.stat().st_mtime - t_start_wall, first.strip()[:140]])
    rows.sort()
    prev = 0.0
    out = []
    for at, first in rows:
        out.append({"at": at, "gap_s": at - prev, "kernel": first})
        prev = at
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("yaml")
    ap.add_argument("--warm", action="store_true", help="use the user's kernel cache (default: an empty one)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json")
    args = ap.parse_args()
    if not args.warm:
        os.environ["CUPY_CACHE_DIR"] = tempfile.mkdtemp(prefix="cupy_cold_")
        os.environ["CUPY_CACHE_SAVE_CUDA_SOURCE"] = "1"
    wall0 = time.time() - (time.perf_counter() - T0)
    t_imp = time.perf_counter()
    import cupy  # noqa: F401
    t_cupy = time.perf_counter() - t_imp
    out = Path(tempfile.mkdtemp(prefix="cold_out_"))
    seen = []
    stop = threading.Event()

    def watch():
        while not stop.is_set() and not seen:
            if any(out.rglob("*.fits")):
                seen.append(time.perf_counter() - T0)
            time.sleep(0.01)
    threading.Thread(target=watch, daemon=True).start()
    from bf_epic_blocks.pipeline.cli import main as cli_main
    sets = ["device=gpu", f"output.dir={out}"] + args.set
    argv = ["run", args.yaml, "--no-progress", "-q"] + [x for s in sets for x in ("--set", s)]
    t_run = time.perf_counter()
    rc = cli_main(argv)
    wall = time.perf_counter() - t_run
    stop.set()
    listing = cache_listing(os.environ["CUPY_CACHE_DIR"], wall0) if not args.warm else []
    for r in listing:
        print(f"file at {r['at']:6.2f} s (+{r['gap_s']:5.2f})  {r['kernel'][:110]}")
    summary = {"date": utc_now(), "machine": machine("gpu"), "yaml": args.yaml, "cold": not args.warm, "rc": rc, "import_cupy_s": t_cupy,
               "run_wall_s": wall, "first_image_s": seen[0] if seen else None,
               "compiles": len(listing), "cache_files": listing}
    print(f"rc {rc}; cupy import {t_cupy:.2f} s; run {wall:.2f} s; first image at {summary['first_image_s']} s "
          f"from script start; {len(listing)} kernels compiled")
    if args.json:
        write_json(args.json, summary)
    return rc


if __name__ == "__main__":
    sys.exit(main())
