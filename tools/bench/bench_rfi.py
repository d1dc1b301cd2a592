"""The interference flagger's cost at the whole band, beside the imager's.

One LWA-SV tuning's gulp (1,024 frames x 784 channels x 256 stands x 2 pols, 4-bit noise) is flagged
(RFIFlagBlock's detection and zeroing, outside a pipeline) ``--repeat`` times on the device; the median
time per gulp is set against the imager's time for the same 1,024 frames, from the whole-band pipeline
run in the same call (``bf-epic run pipelines/lwasv_sim_wholeband.yaml`` with flagging off and on; the
runs' steady time per second of data from two run lengths, as bench_calibration's cost case does).

usage: python tools/bench/bench_rfi.py [--device gpu|cpu] [--nchan 784] [--repeat 20] [--pipeline]
       [--short-s 10] [--long-s 30] [--json PATH]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402

def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=("cpu", "gpu"), default="gpu")
    ap.add_argument("--nchan", type=int, default=784)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--pipeline", action="store_true",
                    help="also run the whole-band pipeline with flagging off and on (GPU; two run lengths each)")
    ap.add_argument("--short-s", type=float, default=10.0)
    ap.add_argument("--long-s", type=float, default=30.0)
    args = ap.parse_args()
    rows = {"flagger": time_flagger(args)}
    if args.device == "gpu":
        rows["gpu_parts"] = gpu_parts(args)
    r = rows["flagger"]
    print(f"flagger, {args.nchan} channels x 256 stands x 2 pols, 1,024 frames ({args.device}): "
          f"{1e3 * r['median_s']:.3f} ms a gulp (min {1e3 * r['min_s']:.3f}), "
          f"{r['median_s'] / 0.04096:.4f} s per s of data; a plain copy of the gulp (the floor) "
          f"{1e3 * r['copy_median_s']:.3f} ms")
    if args.pipeline:
        rows["pipeline"] = pipeline_cost(args)
    if args.json:
        write_json(args.json, {"benchmark": "bench_rfi", "date": utc_now(), "machine": machine(args.device),
                               "device": args.device, "cases": rows})
        print(f"wrote {args.json}")


def pipeline_cost(args):
    """`bf-epic run pipelines/lwasv_sim_wholeband.yaml` (no search, no files) with flagging off and on, each
    for ``--short-s`` and ``--long-s`` seconds of data: the steady time per second of data is the
    difference of the walls over the difference of data (start-up left out). A first short run with
    flagging compiles every kernel and is thrown away."""
    from bench_calibration import cli, sets
    yaml = Path(__file__).resolve().parents[2] / "pipelines" / "lwasv_sim_wholeband.yaml"
    base = {"device": "gpu", "imager.search": None, "output.cube": None, "output.fits": False,
            "output.png": False, "output.integrate": None, "output.dir": "/tmp/bench_rfi_out"}
    cli("run", str(yaml), *sets({**base, "flagging.enabled": "on", "source.duration_s": args.short_s}))
    out = {}
    for name, on in (("flagging off", "off"), ("flagging on", "on")):
        walls = {}
        for dur in (args.short_s, args.long_s):
            _, summ = cli("run", str(yaml), *sets({**base, "flagging.enabled": on, "source.duration_s": dur}))
            walls[dur] = summ["wall_s"]
        steady = (walls[args.long_s] - walls[args.short_s]) / (args.long_s - args.short_s)
        out[name] = {"walls": {str(k): v for k, v in walls.items()}, "steady_s_per_data_s": steady}
        print(f"pipeline, whole band, {name}: {args.short_s:g} s of data in {walls[args.short_s]:.2f} s, "
              f"{args.long_s:g} s in {walls[args.long_s]:.2f} s: steady {steady:.4f} s per s of data")
    out["added_fraction"] = out["flagging on"]["steady_s_per_data_s"] / out["flagging off"]["steady_s_per_data_s"] - 1
    print(f"pipeline: flagging adds {100 * out['added_fraction']:.1f}% to the whole-band pipeline's steady time")
    return out


def time_flagger(args):
    """Median and least seconds of one gulp's detection, zeroing and counts (RFIFlagBlock.process), driving
    the block's method on a gulp held in memory; and the floor: a plain copy of the gulp (what any block
    that writes the voltages to a ring of its own costs)."""
    from bf_epic_blocks.blocks.rfi_flag import RFIFlagBlock
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    xp = np
    if args.device == "gpu":
        import cupy as xp
    rng = np.random.default_rng(1)
    n, nchan, nst = 1024, args.nchan, 256
    shape = (n, nchan, nst, 2)
    raw = xp.asarray(pack_ci4(rng.normal(0, 2.5, shape).astype(np.float32)
                              + 1j * rng.normal(0, 2.5, shape).astype(np.float32)))
    out = xp.empty_like(raw)
    fb = _standalone_flagger(RFIFlagBlock, xp, nchan, nst)
    times = []
    for _ in range(args.repeat + 2):
        t0 = time.perf_counter()
        cnt, frames, _ = fb.process(raw, out)
        if xp is not np:
            xp.cuda.get_current_stream().synchronize()
        times.append(time.perf_counter() - t0)
    t = np.array(times[2:])
    copies = []
    for _ in range(args.repeat + 2):
        t0 = time.perf_counter()
        out[...] = raw
        if xp is not np:
            xp.cuda.get_current_stream().synchronize()
        copies.append(time.perf_counter() - t0)
    flagged = cnt[..., -1].astype(xp.int64) * int(frames[0])
    frac = float(flagged.sum()) / (n * nchan * nst)
    return {"median_s": float(np.median(t)), "min_s": float(t.min()), "copy_median_s": float(np.median(copies[2:])),
            "frames": n, "nchan": nchan,
            "flagged_fraction_noise": frac}


def gpu_parts(args):
    """GPU milliseconds (cupyx.profiler.benchmark) of one gulp's detection (power sums, both impulse detectors,
    spectral kurtosis), its zeroing and counting (apply_flags), and the whole-band imager's images of the same
    gulp (i8x2 on the 64 x 64 grid, as the whole-band pipeline makes them): the detector's share of the
    imager's time is the issue's measure."""
    import cupy as cp
    from cupyx.profiler import benchmark

    from bf_epic_blocks import imaging
    from bf_epic_blocks.blocks.rfi_flag import RFIFlagBlock
    from bf_epic_blocks.imaging import rfi
    from bf_epic_blocks.imaging.dft import DFTOperator
    from bf_epic_blocks.imaging.pixels import GridPlacement
    from bf_epic_blocks.runtime.dtypes import ci4_bytes, pack_ci4
    rng = np.random.default_rng(1)
    n, nchan, nst, a, m = 1024, args.nchan, 256, 16, 1024
    shape = (n, nchan, nst, 2)
    raw = cp.asarray(pack_ci4(rng.normal(0, 2.5, shape).astype(np.float32)
                              + 1j * rng.normal(0, 2.5, shape).astype(np.float32)))
    out = cp.empty_like(raw)
    fb = _standalone_flagger(RFIFlagBlock, cp, nchan, nst)
    x = ci4_bytes(raw).reshape(shape)

    def detect():
        S1, S2, Sa = rfi.block_power(x, m, a, ci4=True, group=2)
        P = Sa.reshape(Sa.shape[:3])
        per = rfi.broadband_flags(P, fb.impulse_sigma, per_input=True)
        allf = rfi.broadband_flags(rfi.band_power(P, per, fb._live), fb.impulse_sigma)
        return rfi.sk_code(S1, S2, m, fb.far, bits=4), allf, per

    code, allf, per = detect()
    ns = n // a
    which = fb._which(ns, a, m, [(0, m)])
    imp_st = per & ~allf[:, None]

    def zero():
        return rfi.apply_flags(x, ci4_bytes(out).reshape(shape), code, which, allf, imp_st, fb._static, fb._live, a,
                               fb.spread * nst)

    def gpu_ms(f, k=20):
        return float(np.median(benchmark(f, n_repeat=k, n_warmup=3).gpu_times[0])) * 1e3

    xyz = rng.normal(0, 40, (nst, 3)) * [1, 1, 0.05]
    freq = 74e6 + 25e3 * np.arange(nchan)
    grid = imaging.lm_grid(64)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2, precision="i8x2")
    acc = op.accumulator(("I",), method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    img = cp.zeros((n // a, nchan, 1, grid.size ** 2), cp.float32)
    res = {"detector_ms": gpu_ms(detect), "zeroing_ms": gpu_ms(zero),
           "copy_ms": gpu_ms(lambda: cp.copyto(out, raw)),
           "imager_ms": gpu_ms(lambda: acc.images(raw, a, ci4=True, place=place, out=img), 10)}
    res["detector_share"] = res["detector_ms"] / res["imager_ms"]
    res["zeroing_share"] = res["zeroing_ms"] / res["imager_ms"]
    print(f"GPU, one gulp: the whole-band imager {res['imager_ms']:.2f} ms; the detector {res['detector_ms']:.3f} ms "
          f"({100 * res['detector_share']:.1f}%); zeroing and counts {res['zeroing_ms']:.3f} ms "
          f"({100 * res['zeroing_share']:.1f}%); a plain copy {res['copy_ms']:.3f} ms")
    return res


def _standalone_flagger(cls, xp, nchan, nst):
    """An RFIFlagBlock's detection state without a pipeline (its on_sequence's fields, for noise data)."""
    fb = object.__new__(cls)
    fb.far, fb.block_frames, fb.impulse_frames, fb.impulse_sigma, fb.spread = 1e-3, 1024, 16, 6.0, 0.1
    fb.flag_stats = {"untested": 0}
    fb._xp = xp
    fb._lay = {"dtype": "ci4", "nchan": nchan}
    fb._static = xp.zeros(nchan, bool)
    fb._static_host = np.zeros(nchan, bool)
    fb._bits = 4
    fb._flagged_stands = np.zeros(nst, bool)
    fb._live = xp.ones(nst, bool)
    fb._nlive = nst
    fb._which_cache = (None, None)
    return fb


if __name__ == "__main__":
    main()
