"""What the watchlist's directions cost the imager's GPU at the whole band, imaged beside the grid and on their own.

One LWA-SV tuning's gulp (784 channels x 1,024 samples x 256 stands x 2 pols, ci4 bytes) imaged as the
whole-band pipeline images it: the main imager's 64 x 64 grid (3,205 directions, i8x2, 16-sample images
placed on the grid by the fused kernel), timed on the GPU with ``cupyx.profiler.benchmark``:

* alone, and with ``--targets`` directions beside its pixels in the same operator and kernel (what the
  pipeline runs: ``DFTImagerBlock(watch=)``), their images written to their own array;
* the directions imaged by an imager of their own instead (the route the pipeline takes when the main
  imager cannot carry them), and its share spent laying the voltages out again;
* the host time of moving the directions (once a second of data): only their rows of the grid's operator
  (``DFTOperator.repoint(first=)``), against the watch imager's own operator moved whole.

The directions' images beside the grid are checked against the watch imager's (the same numbers to
float32 rounding: the same int8 pieces of the same operator rows).

Prints a table and writes JSON. usage:
    python tools/bench/bench_watch_imager.py [--targets 10 100] [--json PATH]
"""
from __future__ import annotations

import argparse
import sys
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
    ng = grid.lm.shape[0]

    def gpu_ms(f, n=10):
        return benchmark(f, n_repeat=n, n_warmup=2).gpu_times.mean() * 1e3

    def grid_imager(dirs):
        lm = np.concatenate([grid.lm, dirs])
        op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2")
        place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp, extra=len(dirs))
        out = cp.zeros((T // 16, C, 1, grid.size ** 2), cp.float32)
        xout = cp.zeros((T // 16, C, 1, len(dirs)), cp.float32)
        acc = op.accumulator(("I",), method="direct")
        bound = place.beside(xout) if len(dirs) else place
        return op, xout, lambda: acc.images(b, 16, ci4=True, place=bound, out=out)

    _, _, run = grid_imager(np.zeros((0, 2)))
    main_ms = gpu_ms(run)
    cp.get_default_memory_pool().free_all_blocks()
    rows = []
    for k in args.targets:
        r = np.sqrt(rng.uniform(0, 0.8, k))
        a = rng.uniform(0, 2 * np.pi, k)
        lm = np.stack([r * np.cos(a), r * np.sin(a)], 1)
        op, xout, run = grid_imager(lm)
        ride_ms = gpu_ms(run)
        moved = lm * 0.99
        ride_move_s = benchmark(lambda: op.repoint(cp.asarray(moved), first=ng), n_repeat=5,
                                n_warmup=1).cpu_times.mean()
        run()
        beside = xout.get()[:, :, 0]
        op = xout = run = None
        cp.get_default_memory_pool().free_all_blocks()
        w = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(moved), npol=2, precision="i8x2")
        wacc = w.accumulator(("I",), method="direct")
        own_ms = gpu_ms(lambda: wacc.images(b, 16, ci4=True), 20)
        lay_ms = gpu_ms(lambda: w.fused._layout(b, [0, 1], True), 20)
        own_move_s = benchmark(lambda: w.repoint(cp.asarray(moved)), n_repeat=5, n_warmup=1).cpu_times.mean()
        own = wacc.images(b, 16, ci4=True).get()[:, :, 0]
        err = float(np.abs(beside - own).max() / np.abs(own).max())
        w = wacc = None
        cp.get_default_memory_pool().free_all_blocks()
        rows.append({"targets": k, "beside_grid_ms_per_gulp": ride_ms, "added_beside_grid": ride_ms / main_ms - 1,
                     "own_imager_ms_per_gulp": own_ms, "own_layout_ms": lay_ms, "own_share_of_main": own_ms / main_ms,
                     "move_beside_grid_host_ms": 1e3 * ride_move_s, "move_own_host_ms": 1e3 * own_move_s,
                     "beside_vs_own_rel_err": err})
    print(f"# one whole-band gulp (784 ch x 1,024 samples x 256 stands x 2 pols): main imager {main_ms:.2f} ms GPU")
    print(f"{'targets':>8} {'grid+dirs ms':>13} {'added':>7} {'own imager ms':>14} {'of it layout':>13} {'share':>7} "
          f"{'move beside ms':>15} {'move own ms':>12} {'beside vs own':>14}")
    for r in rows:
        print(f"{r['targets']:8d} {r['beside_grid_ms_per_gulp']:13.3f} {100 * r['added_beside_grid']:6.1f}% "
              f"{r['own_imager_ms_per_gulp']:14.3f} {r['own_layout_ms']:13.3f} {100 * r['own_share_of_main']:6.1f}% "
              f"{r['move_beside_grid_host_ms']:15.2f} {r['move_own_host_ms']:12.2f} {r['beside_vs_own_rel_err']:14.1e}")
    if args.json:
        write_json(args.json, {"benchmark": "bench_watch_imager", "date": utc_now(), "machine": machine("gpu"),
                               "main_ms_per_gulp": main_ms, "rows": rows})
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
