#!/usr/bin/env python
"""Benchmark: throughput of a case-P pipeline through the blocks vs calling the core directly.

Pipeline: ArraySourceBlock ('ci4', 1,024-frame gulps of 16 channels x 256 stands x 2 pols) ->
CalFoldBlock (explicit complex weights) -> DFTImagerBlock (64 x 64 all-sky grid, 1,024 frames per
image, Stokes I) -> ArraySinkBlock. The core baseline does the same work per gulp without rings:
unpack ci4, apply the weights, ``DFTOperator.image``. The ratio is the runtime's overhead.
Real time for LWA-SV is 25,000 frames/s (40 us per sample).

    python tools/bench_pipeline.py --device cpu --nchan 1 --json out.json
    python tools/bench_pipeline.py --device gpu --json out.json
"""
import argparse
import datetime
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from cases import lwasv_like_layout  # noqa: E402

from bf_epic_blocks import imaging  # noqa: E402
from bf_epic_blocks.blocks import (ArraySinkBlock, ArraySourceBlock, CalFoldBlock, DFTImagerBlock, bfp,  # noqa: E402
                                   efield_header)
from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_complex  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, default=16)
    ap.add_argument("--ngulp", type=int, default=20)
    ap.add_argument("--gulp", type=int, default=1024)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    xp = np
    if a.device == "gpu":
        import cupy as xp
    space = "cuda" if a.device == "gpu" else "system"
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    grid = imaging.lm_grid(64)
    rng = np.random.default_rng(0)
    nframe = a.ngulp * a.gulp
    ints = rng.integers(-8, 8, (nframe, a.nchan, 256, 2)) + 1j * rng.integers(-8, 8, (nframe, a.nchan, 256, 2))
    packed = pack_ci4(ints)
    w = np.exp(2j * np.pi * rng.random((a.nchan, 256, 2))).astype(np.complex64)
    hdr = efield_header("bench", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="ci4")

    def sync():
        if a.device == "gpu":
            xp.cuda.Device().synchronize()

    # core, data on the host (the pipeline's source is host memory too), one gulp at a time
    op = imaging.DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(grid.lm), npol=2)
    wd = xp.asarray(w)

    def core():
        sync()
        t = time.perf_counter()
        for g in range(a.ngulp):
            x = unpack_complex(xp.asarray(packed[g * a.gulp:(g + 1) * a.gulp]), "ci4") * wd[None]
            img = op.image(x, ("I",))
            _ = grid.to_image(img)
        sync()
        return time.perf_counter() - t

    core()  # warm-up (kernel compilation, allocator)
    t_core = core()

    def pipeline():
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(packed, hdr, gulp_nframe=a.gulp, space=space)
            cal = CalFoldBlock(src, cable=w)
            img = DFTImagerBlock(cal, grid, a.gulp, products=("I",))
            sink = ArraySinkBlock(img)
            t0 = time.perf_counter()
            p.run()
            sync()
            return time.perf_counter() - t0, sink

    pipeline()  # warm-up (plans, kernels)
    t_pipe, sink = pipeline()
    n_img = sink.result(0).shape[0]
    rows = {"core_s": t_core, "pipeline_s": t_pipe, "frames": nframe, "images": int(n_img),
            "core_fps": nframe / t_core, "pipeline_fps": nframe / t_pipe, "overhead": t_pipe / t_core - 1,
            "realtime_fps": 25000.0}
    print(f"# bench_pipeline device={a.device} nchan={a.nchan} gulps={a.ngulp}x{a.gulp} ({layout}) runtime={bfp.__name__}")
    print(f"{'path':<10} {'seconds':>9} {'frames/s':>10} {'x real time':>11}")
    print(f"{'core':<10} {t_core:9.3f} {nframe / t_core:10.0f} {nframe / t_core / 25000:11.2f}")
    print(f"{'pipeline':<10} {t_pipe:9.3f} {nframe / t_pipe:10.0f} {nframe / t_pipe / 25000:11.2f}")
    print(f"# runtime overhead: {100 * rows['overhead']:.1f}% ({n_img} images)")
    if a.json:
        out = {"benchmark": "bench_pipeline", "date": datetime.datetime.now(datetime.timezone.utc).isoformat(),
               "device": a.device, "nchan": a.nchan, "layout": layout, **rows}
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
