#!/usr/bin/env python
"""Benchmark: imaging case P with 32 channels on one GPU vs the channels sharded over several GPUs.

Case P geometry (256 antennas, 64 x 64 grid, 1,024-sample gulps, 2 pols, Stokes I), 32 channels of
4-bit voltages. Rows, all in the same run:
  * ``1 GPU``: one DFTOperator over all 32 channels on GPU 0;
  * ``N GPUs, resident``: ShardedOperator, each GPU's input already in its memory (the imaging itself);
  * ``N GPUs, peer, threads``: ShardedOperator fed from GPU 0's memory (one host thread per GPU);
  * ``N GPUs, from host``: ShardedOperator fed the gulp from (pinned) host memory as packed ci4 bytes,
    each GPU copying its channels over its own link and decoding them (what DFTImagerBlock(gpus=...) does),
    one host thread per GPU (and the same issued from one thread, for comparison).
Times are medians of wall-clock seconds per gulp (the result gathered on the host each time); the
speed-up is over the 1-GPU row of the same feeding (``1 GPU`` for resident input, ``1 GPU, from host``
for the host-fed rows; ``1 GPU, 16 channels`` shows one GPU's share alone, the bound for 2 GPUs).
Output images are checked equal (<= 1e-6 of the peak) to 1 GPU.

    python tools/bench_multigpu.py --json bench_multigpu.json [--precision fp16] [--nchan 32]
"""
import argparse
import datetime
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from cases import lwasv_like_layout, quantise4, sky_efield  # noqa: E402

from bf_epic_blocks import imaging  # noqa: E402
from bf_epic_blocks.imaging.multigpu import ShardedOperator  # noqa: E402
from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs  # noqa: E402


def wall(fn, repeat):
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nchan", type=int, default=32)
    ap.add_argument("--precision", nargs="+", default=["fp32", "fp16"])
    ap.add_argument("--method", default="covariance")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cupy as cp
    ngpu = cp.cuda.runtime.getDeviceCount()
    names = []
    for d in range(ngpu):
        p = cp.cuda.runtime.getDeviceProperties(d)["name"]
        names.append(p.decode() if isinstance(p, bytes) else p)
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    Q = quantise4(sky_efield(xyz, freq, 1024, npol=2, dtype=np.complex128))     # int8 pairs
    packed = pack_ci4(Q[..., 0] + 1j * Q[..., 1])                                  # (T, C, A, P) uint8
    pinned = cp.cuda.alloc_pinned_memory(packed.nbytes)
    host = np.frombuffer(pinned, np.uint8, packed.size).reshape(packed.shape)
    host[...] = packed
    grid = imaging.lm_grid(64)
    rows = []
    print(f"# bench_multigpu: {ngpu} GPU(s) {names}; case P geometry, {a.nchan} channels, 4-bit, Stokes I, "
          f"{a.method} route")
    print(f"{'precision':<9} {'setup':<22} {'ms/gulp':>9} {'speed-up':>9} {'max diff':>9}")
    for precision in a.precision:
        with cp.cuda.Device(0):
            op = imaging.DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2,
                                     precision=precision)
            q0 = cp.asarray(Q)

            def one():
                return op.image(q0, ("I",), method=a.method).get()
            t1 = wall(one, a.repeat)
            ref = one()
        rows.append({"precision": precision, "setup": "1 GPU", "ngpu": 1, "gulp_s": t1, "speedup": 1.0})
        print(f"{precision:<9} {'1 GPU':<22} {t1 * 1e3:9.3f} {1.0:9.2f} {'':>9}", flush=True)
        if ngpu > 1:
            # one GPU's share (nchan / ngpu channels) alone: the bound N GPUs could reach, showing how
            # much of a call does not shrink with the channels
            share = a.nchan // ngpu
            with cp.cuda.Device(0):
                op_s = imaging.DFTOperator(cp.asarray(xyz), cp.asarray(freq[:share]), cp.asarray(grid.lm), npol=2,
                                           precision=precision)
                q_s = cp.asarray(Q[:, :share])
                t_s = wall(lambda: op_s.image(q_s, ("I",), method=a.method).get(), a.repeat)
                del op_s, q_s
            label = f"1 GPU, {share} channels"
            rows.append({"precision": precision, "setup": label, "ngpu": 1, "gulp_s": t_s, "speedup": t1 / t_s})
            print(f"{precision:<9} {label:<22} {t_s * 1e3:9.3f} {t1 / t_s:9.2f} {'':>9}", flush=True)
        # the same from host memory on one GPU (what DFTImagerBlock(gpus=[0]) does): the baseline of
        # the host-fed rows
        sh1 = ShardedOperator(xyz, freq, grid.lm, [0], npol=2, precision=precision)
        th1 = wall(lambda: sh1.image(host, ("I",), method=a.method,
                                     decode=lambda b: unpack_int8_pairs(b, "ci4")), a.repeat)
        rows.append({"precision": precision, "setup": "1 GPU, from host", "ngpu": 1, "gulp_s": th1,
                     "speedup": t1 / th1})
        print(f"{precision:<9} {'1 GPU, from host':<22} {th1 * 1e3:9.3f} {t1 / th1:9.2f} {'':>9}", flush=True)
        for n in range(2, ngpu + 1):
            sh = ShardedOperator(xyz, freq, grid.lm, list(range(n)), npol=2, precision=precision)
            resident = []
            for d, cs in zip(sh.devices, sh.blocks):
                with cp.cuda.Device(d):
                    resident.append(cp.asarray(Q))

            def res():
                parts = []
                for d, cs, o, x in zip(sh.devices, sh.blocks, sh.ops, resident):
                    with cp.cuda.Device(d):
                        parts.append(o.image(x[:, cs], ("I",), method=a.method))
                out = []
                for d, p in zip(sh.devices, parts):
                    with cp.cuda.Device(d):
                        out.append(p.get())
                return np.concatenate(out, axis=0)

            def from_host():
                return sh.image(host, ("I",), method=a.method, decode=lambda b: unpack_int8_pairs(b, "ci4"))

            def res_threads():
                return sh.image(resident[0], ("I",), method=a.method)   # peer copies of each GPU's slice

            def from_host_serial():
                sh.threads = False
                try:
                    return from_host()
                finally:
                    sh.threads = True
            for label, fn in ((f"{n} GPUs, resident", res), (f"{n} GPUs, peer, threads", res_threads),
                              (f"{n} GPUs, from host", from_host), (f"{n} GPUs, host, 1 thread", from_host_serial)):
                t = wall(fn, a.repeat)
                diff = float(np.max(np.abs(fn() - ref)) / np.max(np.abs(ref)))
                base = th1 if "host" in label else t1      # host-fed rows against the host-fed 1 GPU
                rows.append({"precision": precision, "setup": label, "ngpu": n, "gulp_s": t, "speedup": base / t,
                             "max_rel_diff_vs_1gpu": diff})
                print(f"{precision:<9} {label:<22} {t * 1e3:9.3f} {base / t:9.2f} {diff:9.1e}", flush=True)
    out = {"benchmark": "bench_multigpu", "date": datetime.datetime.now(datetime.timezone.utc).isoformat(),
           "gpus": names, "case": {"nchan": a.nchan, "nant": 256, "layout": layout, "npix": grid.npix, "ntime": 1024,
                                   "method": a.method}, "rows": rows}
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
        print(f"# wrote {a.json}")
    return out


if __name__ == "__main__":
    main()
