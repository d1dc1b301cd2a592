"""The watch imager's GPU work a gulp at the whole band, beside the main imager's (GPU only).

One LWA-SV tuning's gulp (784 channels x 1,024 samples x 256 stands x 2 pols, ci4 bytes) imaged as the
whole-band pipeline images it: the main imager's 64 x 64 grid (3,205 directions, i8x2, 16-sample images
placed on the grid by the fused kernel) and a watchlist's ``--targets`` directions (i8x2, 16-sample images
of each direction), timed on the GPU with ``cupyx.profiler.benchmark``; the watch imager's share of it
laying the voltages out for the fused kernel; and the host time of moving the watch operator's directions
(:meth:`~bf_epic_blocks.imaging.dft.DFTOperator.repoint`, once a second of data) against building a new
operator and route for them. The images of the moved operator are checked against a new one's (equal to
float32 rounding).

Prints a table and writes JSON. usage:
    python tools/bench/bench_watch_imager.py [--targets 10 100] [--json PATH]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", type=int, nargs="+", default=[10, 100])
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    import cupy as cp
    from cupyx.profiler import benchmark

    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging.dft import DFTOperator
    from bf_epic_blocks.imaging.pixels import GridPlacement
    rng = np.random.default_rng(0)
    nant, C, T = 256, 784, 1024
    xyz = rng.normal(0, 40, (nant, 3)) * [1, 1, 0.05]
    freq = 74e6 + 25e3 * np.arange(C)
    b = cp.asarray(rng.integers(0, 256, (T, C, nant, 2), dtype=np.uint8))
    grid = imaging.lm_grid(64)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2, precision="i8x2")
    acc = op.accumulator(("I",), method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    out = cp.zeros((T // 16, C, 1, grid.size ** 2), cp.float32)
    main_ms = benchmark(lambda: acc.images(b, 16, ci4=True, place=place, out=out), n_repeat=10,
                        n_warmup=2).gpu_times.mean() * 1e3
    rows = []
    for k in args.targets:
        r = np.sqrt(rng.uniform(0, 0.8, k))
        a = rng.uniform(0, 2 * np.pi, k)
        lm = np.stack([r * np.cos(a), r * np.sin(a)], 1)
        t0 = time.perf_counter()
        w = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2")
        wacc = w.accumulator(("I",), method="direct")
        wacc.images(b, 16, ci4=True)
        cp.cuda.Device().synchronize()
        build_s = time.perf_counter() - t0
        img_ms = benchmark(lambda: wacc.images(b, 16, ci4=True), n_repeat=20, n_warmup=3).gpu_times.mean() * 1e3
        lay_ms = benchmark(lambda: w.fused._layout(b, [0, 1], True), n_repeat=20, n_warmup=3).gpu_times.mean() * 1e3
        moved = lm * 0.99
        move_s = benchmark(lambda: w.repoint(cp.asarray(moved)), n_repeat=5, n_warmup=1).cpu_times.mean()
        got = wacc.images(b, 16, ci4=True).get()
        fresh = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(moved), npol=2, precision="i8x2")
        want = fresh.accumulator(("I",), method="direct").images(b, 16, ci4=True).get()
        err = float(np.abs(got - want).max() / np.abs(want).max())
        rows.append({"targets": k, "watch_ms_per_gulp": img_ms, "layout_ms": lay_ms,
                     "share_of_main": img_ms / main_ms, "repoint_host_ms": 1e3 * move_s,
                     "new_operator_s": build_s, "moved_vs_new_rel_err": err})
    print(f"# one whole-band gulp (784 ch x 1,024 samples x 256 stands x 2 pols): main imager {main_ms:.2f} ms GPU")
    print(f"{'targets':>8} {'watch ms':>9} {'layout ms':>10} {'share':>7} {'repoint ms':>11} {'new op s':>9} "
          f"{'moved vs new':>13}")
    for r in rows:
        print(f"{r['targets']:8d} {r['watch_ms_per_gulp']:9.3f} {r['layout_ms']:10.3f} {100 * r['share_of_main']:6.1f}% "
              f"{r['repoint_host_ms']:11.2f} {r['new_operator_s']:9.3f} {r['moved_vs_new_rel_err']:13.1e}")
    if args.json:
        write_json(args.json, {"benchmark": "bench_watch_imager", "date": utc_now(), "machine": machine("gpu"),
                               "main_ms_per_gulp": main_ms, "rows": rows})
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
