#!/usr/bin/env python
"""Profile one DFT imaging call of case P on the GPU: run under Nsight Compute to see each kernel.

    ncu --profile-from-start off --clock-control none --metrics gpu__time_duration.sum --csv \\
        python tools/bench/profile_dft.py --route covariance --precision fp16 --input ci4

The script warms up, then brackets ONE ``DFTOperator.image`` call with cudaProfilerStart/Stop, so
the report lists exactly the kernels of one gulp (GEMMs, reductions, conversions) with their times.
Without ncu it prints the call's median time (CUDA events).
"""
import argparse
import time

import numpy as np

from bf_epic_blocks import imaging

from benchlib import timer
from cases import lwasv_like_layout, pairs_to_complex, quantise4, sky_efield


def summarise(path):
    """Print kernel, time (us) and share from an ``ncu --csv`` report of gpu__time_duration.sum."""
    import csv
    rows = []
    with open(path) as fh:
        lines = [ln for ln in fh if ln.startswith('"')]
    for r in csv.DictReader(lines):
        if r.get("Metric Name") == "gpu__time_duration.sum":
            rows.append((r["Kernel Name"][:70], float(r["Metric Value"].replace(",", "")) / 1e3))
    total = sum(t for _, t in rows)
    for name, us in rows:
        print(f"  {us:9.1f} us {100 * us / total:5.1f}%  {name}")
    print(f"  {total:9.1f} us total over {len(rows)} kernels")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--summarise", default=None, help="print an ncu --csv report and exit")
    ap.add_argument("--route", default="covariance")
    ap.add_argument("--precision", default="fp16")
    ap.add_argument("--input", choices=["ci4", "cf32"], default="ci4")
    ap.add_argument("--accumulate", type=int, default=None)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--nchan", type=int, default=16)
    ap.add_argument("--products", nargs="+", default=None, help="e.g. I (default: the operator's default)")
    a = ap.parse_args(argv)
    if a.summarise:
        return summarise(a.summarise)
    import cupy as cp
    xyz, _ = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    Q = quantise4(sky_efield(xyz, freq, 1024, npol=2, dtype=np.complex128))
    X = cp.asarray(Q if a.input == "ci4" else pairs_to_complex(Q))
    grid = imaging.lm_grid(a.grid)
    op = imaging.DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2, precision=a.precision)

    def call():
        return op.image(X, a.products, method=a.route, accumulate=a.accumulate)
    t, _ = timer("gpu")(call, 10)
    cp.cuda.Device().synchronize()
    t0 = time.perf_counter()
    for _ in range(10):
        call()
    t_host = (time.perf_counter() - t0) / 10          # host time to issue one call (launch-bound if ~ t)
    cp.cuda.Device().synchronize()
    print(f"# {a.route} {a.precision} {a.input} accumulate={a.accumulate} grid={a.grid} nchan={a.nchan}: {t * 1e3:.3f} ms "
          f"(host issue time {t_host * 1e3:.3f} ms)")
    cp.cuda.Device().synchronize()
    cp.cuda.profiler.start()
    call()
    cp.cuda.Device().synchronize()
    cp.cuda.profiler.stop()


if __name__ == "__main__":
    main()
