#!/usr/bin/env python
"""Benchmark: run time against error (vs a float64 evaluation of the definition) for the DFT imager.

Cases (see tools/cases.py): case P on the GPU (16 channels x 2 pols, 1,024 samples, 3,205 pixels,
256 antennas) and one channel-pol of case P on the CPU. For each method and precision it prints
the time per 1,024-sample gulp with the operator already built (the pipeline's steady state), the
time of a cold ``dirty_image`` call that also builds the operator, and the error: max |I - I_ref| /
max |I_ref| over a random subset of pixels (the reference is float64 and independent of the package).

    python tools/bench_dft.py --device cpu --json bench_dft_cpu.json
    python tools/bench_dft.py --device gpu --json bench_dft_gpu.json
"""
import argparse
import datetime
import json
import os
import platform
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from cases import lwasv_like_layout, reference_image, sky_efield, timer  # noqa: E402

from bf_epic_blocks import imaging  # noqa: E402


def machine(xp):
    info = {"host": platform.node(), "cpu": platform.processor() or platform.machine(),
            "ncpu": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__}
    if xp.__name__ == "cupy":
        import cupy as cp
        props = cp.cuda.runtime.getDeviceProperties(0)
        info["gpu"] = props["name"].decode() if isinstance(props["name"], bytes) else props["name"]
        info["cupy"] = cp.__version__
    return info


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, default=None, help="channels (default: 1 on cpu, 16 on gpu)")
    ap.add_argument("--npol", type=int, default=None, help="pols (default: 1 on cpu, 2 on gpu)")
    ap.add_argument("--ntime", type=int, default=1024)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=None)
    ap.add_argument("--nref", type=int, default=200, help="pixels in the float64 reference subset")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.device == "gpu":
        import cupy as xp
    else:
        xp = np
    nchan = a.nchan or (16 if a.device == "gpu" else 1)
    npol = a.npol or (2 if a.device == "gpu" else 1)
    repeat = a.repeat or (20 if a.device == "gpu" else 5)
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(nchan)
    grid = imaging.lm_grid(a.grid)
    X = sky_efield(xyz, freq, a.ntime, npol=npol)
    rng = np.random.default_rng(0)
    sub = rng.choice(grid.npix, size=min(a.nref, grid.npix), replace=False)
    blocks = ((0, 0), (1, 1)) if npol == 2 else ((0, 0),)
    ref = reference_image(X, xyz, freq, grid.lm[sub], blocks)
    Xd, xyzd, fd, lmd = (xp.asarray(v) for v in (X, xyz, freq, grid.lm))
    run = timer(a.device)
    rows = []
    print(f"# bench_dft: device={a.device} nant={len(xyz)} ({layout}) npix={grid.npix} ntime={a.ntime} "
          f"nchan={nchan} npol={npol}")
    print(f"{'method':<11} {'precision':<9} {'gulp ms':>9} {'cold ms':>9} {'rel err':>10} {'rt factor':>9}")
    for precision in ("fp32", "fp64"):
        op = imaging.DFTOperator(xyzd, fd, lmd, npol=npol, precision=precision)
        for method in ("auto", "direct", "covariance"):
            img = op.image(Xd, method=method)
            got = imaging._xp.to_numpy(img)[:, :, sub]
            err = float(np.max(np.abs(got - ref)) / np.max(np.abs(ref)))
            t_gulp, _ = run(lambda: op.image(Xd, method=method), repeat)
            t_cold, _ = run(lambda: imaging.dirty_image(Xd, xyzd, fd, lmd, method=method, precision=precision),
                         max(2, repeat // 4))
            chosen = op.accumulator(method=method, ntime_hint=a.ntime).method
            rt = (a.ntime * 40e-6) / t_gulp  # LWA-SV: 25 kHz channels, 40 us per sample
            rows.append({"method": method, "resolved_method": chosen, "precision": precision,
                         "gulp_s": t_gulp, "cold_s": t_cold, "rel_err": err, "realtime_factor": rt})
            label = method if method != "auto" else f"auto->{chosen[:3]}"
            print(f"{label:<11} {precision:<9} {t_gulp * 1e3:9.2f} {t_cold * 1e3:9.2f} {err:10.2e} {rt:9.1f}")
    out = {"benchmark": "bench_dft", "date": datetime.datetime.now(datetime.timezone.utc).isoformat(),
           "machine": machine(xp), "device": a.device, "case": {"nant": len(xyz), "layout": layout,
           "npix": grid.npix, "grid": a.grid, "ntime": a.ntime, "nchan": nchan, "npol": npol}, "rows": rows}
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
        print(f"# wrote {a.json}")
    return out


if __name__ == "__main__":
    main()
