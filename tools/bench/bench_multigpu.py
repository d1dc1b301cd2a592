#!/usr/bin/env python
"""Benchmark: imaging case P with 32 channels on one GPU vs the channels sharded over several GPUs.

Case P geometry (256 antennas, 64 x 64 grid, 1,024-sample gulps, 2 pols, Stokes I), 32 channels of
4-bit voltages. Rows, all in the same run:
  * ``1 GPU``: one DFTOperator over all 32 channels on GPU 0;
  * ``N GPUs, resident``: ShardedOperator, each GPU's input already in its memory (the imaging itself);
  * ``N GPUs, peer``: ShardedOperator fed from GPU 0's memory (peer copies of each GPU's channels);
  * ``N GPUs, from host``: ShardedOperator fed the gulp from (pinned) host memory as packed ci4 bytes,
    each GPU copying its channels over its own link and decoding them (what DFTImagerBlock(gpus=...) does);
  * ``1 GPU / N GPUs, in flight``: the host-fed form as a stream of gulps, each submitted before the
    previous one's images are taken (``ShardedOperator.submit``, two gulps in flight): the throughput
    a pipeline that keeps gulps flowing gets, with the transfers, the host's issue work and the gather
    hidden behind the imaging. Its time is the wall-clock time of ``--stream`` gulps divided by their
    number; its speed-up is over ``1 GPU, in flight``.
  * ``block, K/gulp``: DFTImagerBlock(gpus=...) in a pipeline (ci4 source into a pinned 'cuda_host'
    ring -> imager -> sink), one image per 1,024 frames and K images per gulp (K > 1: the block submits a gulp's
    integrations before taking the first's images); the imager's own time per image (median
    on_data / K); the pipeline's steady time per image is printed too (the source's host copy
    into the ring can bound it).
Times are medians of wall-clock seconds per gulp (the result gathered on the host each time); the
speed-up is over the 1-GPU row of the same feeding (``1 GPU`` for resident input, ``1 GPU, from host``
for the host-fed rows; ``1 GPU, 16 channels`` shows one GPU's share alone, the bound for 2 GPUs).
Output images are checked equal (<= 1e-6 of the peak) to 1 GPU.

    python tools/bench/bench_multigpu.py --json bench_multigpu.json [--precision fp16] [--nchan 32]
"""
import argparse
import time

import numpy as np

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging.multigpu import ShardedOperator
from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs

from benchlib import gpu_names, machine, timer, utc_now, write_json
from cases import lwasv_like_layout, quantise4, reference_image, sky_efield


def wall(fn, repeat):
    """Median wall-clock seconds of ``fn()`` after one warm-up call (the host waits for each result)."""
    return timer("cpu")(fn, repeat)[0]


def bench_block(xyz, freq, grid, Q, packed, ngpu, k, precision, method, nimage=48):
    """DFTImagerBlock(gpus=range(ngpu)) over ``nimage`` integrations of 1,024 frames, ``k`` per gulp,
    from pinned host ci4; returns (the imager's on_data seconds per image (median), the pipeline's
    steady seconds per image, the first image's error against the float64 definition on a sample
    of pixels). The pipeline's figure includes the array source copying each gulp into the ring
    (a host memcpy of 16.8 MB per image here), which can bound it."""
    import cupy as cp

    from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, bfp, efield_header
    T = packed.shape[0]
    raw = np.concatenate([packed] * nimage)
    mem = cp.cuda.alloc_pinned_memory(raw.nbytes)
    host = np.frombuffer(mem, np.uint8, raw.size).reshape(raw.shape)
    host[...] = raw
    stamps = []

    class Stamp(ArraySinkBlock):
        def on_data(self, ispan):
            super().on_data(ispan)
            stamps.append(time.perf_counter())
    hdr = efield_header("bench", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="ci4")
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(host, hdr, gulp_nframe=k * T, space="cuda_host")
        img = DFTImagerBlock(src, grid, T, products=("I",), gpus=list(range(ngpu)), precision=precision,
                             method=method)
        sink = Stamp(img)
        calls = []
        on_data = img.on_data

        def timed(*args):
            t0 = time.perf_counter()
            r = on_data(*args)       # returns with the gulp's images on the host
            calls.append(time.perf_counter() - t0)
            return r
        img.on_data = timed
        p.run()
    out = sink.result(0)
    if out.shape[0] != nimage:
        raise RuntimeError(f"the block made {out.shape[0]} images, expected {nimage}")
    # the first image against the float64 definition on a sample of pixels (every gulp is the same sky)
    sel = np.flatnonzero(grid.mask)[::97]
    ref = reference_image(Q, xyz, freq, grid.lm[::97], blocks=((0, 0), (1, 1)))    # (C, 2, n)
    ref_i = ref[:, 0] + ref[:, 1]                                                   # Stokes I = XX + YY
    got = out[0, :, 0].reshape(out.shape[1], -1)[:, sel]
    diff = float(np.max(np.abs(got - ref_i)) / np.max(np.abs(ref_i)))
    t_block = float(np.median(calls[1:])) / k
    return t_block, (stamps[-1] - stamps[0]) / ((len(stamps) - 1) * k), diff


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nchan", type=int, default=32)
    ap.add_argument("--precision", nargs="+", default=["fp32", "fp16"])
    ap.add_argument("--method", default="covariance")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--stream", type=int, default=60, help="gulps in the in-flight rows")
    ap.add_argument("--block", type=int, nargs="*", default=[1, 4, 8],
                    help="images per gulp for the block rows (none: skip them)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cupy as cp
    ngpu = cp.cuda.runtime.getDeviceCount()
    names = gpu_names()
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
        decode = lambda b: unpack_int8_pairs(b, "ci4")  # noqa: E731

        def in_flight(sh, depth=2):
            """Seconds per gulp over a stream of gulps, ``depth`` of them in flight; and the last images."""
            from collections import deque
            for _ in range(2 * depth):                      # warm-up: graphs captured
                sh.submit(host, ("I",), method=a.method, decode=decode).result()
            pend = deque()
            t0 = time.perf_counter()
            for _ in range(a.stream):
                pend.append(sh.submit(host, ("I",), method=a.method, decode=decode))
                if len(pend) >= depth:
                    last = pend.popleft().result()
            while pend:
                last = pend.popleft().result()
            return (time.perf_counter() - t0) / a.stream, last
        tf1, img = in_flight(sh1)
        rows.append({"precision": precision, "setup": "1 GPU, in flight", "ngpu": 1, "gulp_s": tf1,
                     "speedup": 1.0, "vs_1gpu_sync": t1 / tf1,
                     "max_rel_diff_vs_1gpu": float(np.max(np.abs(img - ref)) / np.max(np.abs(ref)))})
        print(f"{precision:<9} {'1 GPU, in flight':<22} {tf1 * 1e3:9.3f} {1.0:9.2f} {rows[-1]['max_rel_diff_vs_1gpu']:9.1e}",
              flush=True)
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
                return sh.image(host, ("I",), method=a.method, decode=decode)

            def peer():
                return sh.image(resident[0], ("I",), method=a.method)   # peer copies of each GPU's slice

            for label, fn in ((f"{n} GPUs, resident", res), (f"{n} GPUs, peer", peer),
                              (f"{n} GPUs, from host", from_host)):
                t = wall(fn, a.repeat)
                diff = float(np.max(np.abs(fn() - ref)) / np.max(np.abs(ref)))
                base = th1 if "host" in label else t1      # host-fed rows against the host-fed 1 GPU
                rows.append({"precision": precision, "setup": label, "ngpu": n, "gulp_s": t, "speedup": base / t,
                             "max_rel_diff_vs_1gpu": diff})
                print(f"{precision:<9} {label:<22} {t * 1e3:9.3f} {base / t:9.2f} {diff:9.1e}", flush=True)
            tf, img = in_flight(sh)
            diff = float(np.max(np.abs(img - ref)) / np.max(np.abs(ref)))
            label = f"{n} GPUs, in flight"
            rows.append({"precision": precision, "setup": label, "ngpu": n, "gulp_s": tf, "speedup": tf1 / tf,
                         "vs_1gpu_sync": t1 / tf, "max_rel_diff_vs_1gpu": diff})
            print(f"{precision:<9} {label:<22} {tf * 1e3:9.3f} {tf1 / tf:9.2f} {diff:9.1e}", flush=True)
    for precision in a.precision if a.block else ():
        for k in a.block:
            base = None
            for n in sorted({1, ngpu}):
                t, t_pipe, diff = bench_block(xyz, freq, grid, Q, packed, n, k, precision, a.method)
                base = base or t
                label = f"{n} GPU{'s' if n > 1 else ''}, block, {k}/gulp"
                rows.append({"precision": precision, "setup": label, "ngpu": n, "gulp_s": t, "speedup": base / t,
                             "images_per_gulp": k, "pipeline_s_per_image": t_pipe,
                             "max_rel_diff_vs_truth_sample": diff})
                print(f"{precision:<9} {label:<22} {t * 1e3:9.3f} {base / t:9.2f} {diff:9.1e}  "
                      f"(pipeline {t_pipe * 1e3:.3f} ms/image)", flush=True)
    out = {"benchmark": "bench_multigpu", "date": utc_now(), "machine": machine("gpu"), "gpus": names, "case": {"nchan": a.nchan, "nant": 256, "layout": layout, "npix": grid.npix, "ntime": 1024,
                                   "method": a.method}, "rows": rows}
    if a.json:
        write_json(a.json, out)
    return out


if __name__ == "__main__":
    main()
