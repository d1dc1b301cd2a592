#!/usr/bin/env python
"""Benchmark: cost per image of the transient search at case P, CPU (NumPy) or GPU (CuPy).

Case P images: 3,205 pixels (64x64 all-sky grid), 16 channels, one image per 16 samples (0.64 ms at
LWA-SV); a 1-s sliding window (1,562 images), boxcar widths 1, 2, 4, 8, and ``--dms`` trial DMs
(default 0, 0.5, 1, 2: up to 24 images of channel delay at 74 MHz). Images arrive in gulps of 64 (one
1,024-sample gulp of the imager); the clock covers whole gulps after the window has filled (steady
state), including the transfer of the crossings to the host. Rows:

* ``search`` -- :class:`bf_epic_blocks.search.TransientSearch.push` (running sums);
* ``naive`` -- the same S/N recomputed per image from the whole window (mean and std over W values,
  per series and pixel): what the running sums avoid (CPU: a few images only, it is slow);
* per DM count -- how the cost grows with the trials.

The real-time factor is 0.64 ms divided by the time per image.

    python tools/bench/bench_transient.py --device cpu --json docs/bench/transient_cpu.json
    python tools/bench/bench_transient.py --device gpu --json docs/bench/transient_gpu.json
"""
import argparse
import time

import numpy as np

from bf_epic_blocks.search import TransientSearch

from benchlib import array_module, machine, synchronize, utc_now, write_json

DT_IMG = 16 / 25e3


def time_search(xp, nchan, npix, window, dms, widths, ngulp, gulp=64, seed=0):
    rng = np.random.default_rng(seed)
    freq = 74e6 + 25e3 * np.arange(nchan)
    s = TransientSearch(freq, DT_IMG, npix, window, dms=dms, widths=widths, threshold=6.0, xp=xp)
    # a few distinct gulps on the device, cycled (the imager's output is already there)
    gulps = [xp.asarray(rng.normal(10.0, 1.0, (gulp, nchan, npix)).astype(np.float32)) for _ in range(4)]
    nfill = -(-(window + max(widths) + s.shift) // gulp) + 1
    for i in range(nfill):
        s.push(gulps[i % 4])
    synchronize(xp)
    ncross = 0
    t0 = time.perf_counter()
    for i in range(ngulp):
        ncross += len(s.push(gulps[i % 4]))
    synchronize(xp)
    el = time.perf_counter() - t0
    return el / (ngulp * gulp), ncross, s


def time_naive(xp, s, nimg, seed=1):
    """Per image: S/N from mean/std over the whole window of each series (what running sums replace)."""
    rng = np.random.default_rng(seed)
    W, wmax = s.window, s.wmax
    hist = xp.asarray(rng.normal(10.0, 1.0, (s.nser, W + wmax, s.npix)).astype(np.float32))
    synchronize(xp)
    t0 = time.perf_counter()
    for _ in range(nimg):
        win = hist[:, :W]
        mu, sd = win.mean(axis=1), win.std(axis=1, ddof=1)
        for w in s.widths:
            snr = (hist[:, W + wmax - w:].mean(axis=1) - mu) * np.sqrt(w) / sd
            hit = xp.nonzero(snr > 6.0)
            _ = [h.size for h in hit]
    synchronize(xp)
    return (time.perf_counter() - t0) / nimg


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--npix", type=int, default=3205)
    ap.add_argument("--nchan", type=int, default=16)
    ap.add_argument("--window-s", type=float, default=1.0)
    ap.add_argument("--dms", type=float, nargs="*", default=[0.0, 0.5, 1.0, 2.0])
    ap.add_argument("--ngulp", type=int, default=None, help="timed gulps of 64 images")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    xp = array_module(a.device)
    ngulp = a.ngulp or (200 if a.device == "gpu" else 20)
    window = int(round(a.window_s / DT_IMG))
    widths = [1, 2, 4, 8]
    rows = []
    dm_sets = [[0.0], a.dms[:2], a.dms] if len(a.dms) > 2 else [a.dms]
    s_main = None
    for dms in dm_sets:
        t, ncross, s = time_search(xp, a.nchan, a.npix, window, dms, widths, ngulp)
        rows.append({"row": "search", "ndm": len(dms), "dms": dms, "ms_per_image": t * 1e3,
                     "realtime_factor": DT_IMG / t, "crossings": ncross})
        s_main = s
    nnaive = 3 if a.device == "cpu" else 50
    t = time_naive(xp, s_main, nnaive)
    rows.append({"row": "naive", "ndm": len(a.dms), "dms": a.dms, "ms_per_image": t * 1e3,
                 "realtime_factor": DT_IMG / t, "crossings": None})
    info = machine(a.device)
    print(f"\nTransient search, case P: {a.npix} pixels, {a.nchan} channels, window {window} images "
          f"({a.window_s:g} s), widths {widths}, gulps of 64 images, {a.device} ({info['hardware']})")
    print(f"{'row':<8} {'DMs':>4} {'ms/image':>10} {'x real time':>12} {'crossings':>10}")
    for r in rows:
        print(f"{r['row']:<8} {r['ndm']:>4} {r['ms_per_image']:>10.3f} {r['realtime_factor']:>12.2f} "
              f"{'' if r['crossings'] is None else r['crossings']:>10}")
    if a.json:
        out = {"date": utc_now(), "device": a.device, "machine": info,
               "npix": a.npix, "nchan": a.nchan, "window_images": window, "widths": widths,
               "image_time_s": DT_IMG, "rows": rows}
        write_json(a.json, out)


if __name__ == "__main__":
    main()
