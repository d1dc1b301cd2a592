#!/usr/bin/env python
"""Benchmark: the streaming transient search over a band, time per second of data, memory, and the
injected burst found (or not).

Images of ``--npix`` pixels in ``--nchan`` channels of 25 kHz from 74 MHz, one per 0.64 ms, are
pushed a gulp (``--gulp`` images) at a time into :class:`bf_epic_blocks.search.TransientSearch`
for ``--seconds`` of data: Gaussian noise (a pool of gulps cycled, made before the clock starts)
plus one dispersed burst of ``--burst-snr`` per channel-image sigma x sqrt(nchan) ... at DM
``--burst-dm``, 2 images wide, at a chosen pixel and time. Rows:

* ``tree`` -- every sweep from DM 0 to ``--dm-max``, the streaming FDMT (``dedisperse='tree'``);
* ``tree-array`` -- (``--array-stats``) the same with the statistics as array code (CPU's path);
* ``shifts`` -- (``--shifts-dms N``, off by default) N trial DMs spread over the same range, each a
  sum of shifted channels: the naive baseline, on the same data.

``--tree-precision fp32 fp16`` runs the tree row once per storage precision, on the same data. Before
the clock starts, a small search with a burst and a flash runs once per row (``warm_up``), so that
every kernel the timed run meets -- the statistics kernel, the crossings' reductions -- is compiled
before the clock starts, not inside the timed run.

Per row: seconds of search per second of data (and its inverse, the real-time factor), the tree's
share (timed with CUDA events around the dedispersion), GPU memory the search holds (CuPy's pool
after the run; peak of the pool), trials, and the brightest candidate's DM, sweep, image and pixel
against the burst's. JSON with ``--json``.

    python tools/bench/bench_search.py --device gpu --nchan 784 --npix 3205 --seconds 10 --json out.json
"""
import argparse
import time

import numpy as np

from bf_epic_blocks.conventions import dispersion_delay_s
from bf_epic_blocks.search import Crossings, TransientSearch

from benchlib import array_module, machine, synchronize, utc_now, write_json

DT = 16 / 25e3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, default=784)
    ap.add_argument("--npix", type=int, default=3205)
    ap.add_argument("--dm-max", type=float, default=3.0)
    ap.add_argument("--window-s", type=float, default=0.2)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--gulp", type=int, default=64)
    ap.add_argument("--threshold", type=float, default=7.5)
    ap.add_argument("--burst-dm", type=float, default=1.5)
    ap.add_argument("--burst-snr", type=float, default=1.0, help="burst per channel-image, in units of the noise sigma")
    ap.add_argument("--shifts-dms", type=int, default=0, help="also run the shifted-sum search with this many DMs")
    ap.add_argument("--array-stats", action="store_true",
                    help="also run the tree with the statistics as array code (the GPU kernel's baseline)")
    ap.add_argument("--tree-precision", nargs="+", choices=["fp32", "fp16"], default=["fp32"],
                    help="what the tree stores: a tree row for each")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    xp = array_module(a.device)
    f = 74e6 + 25e3 * np.arange(a.nchan)
    window = int(round(a.window_s / DT))
    ngulp = int(np.ceil(a.seconds / (a.gulp * DT)))
    rng = np.random.default_rng(0)
    pool = [xp.asarray(rng.normal(10.0, 1.0, (a.gulp, a.nchan, a.npix)).astype(np.float32)) for _ in range(4)]
    # the burst: 2 images wide, arriving at the band top at image e0, at pixel pix
    delays = np.rint(dispersion_delay_s(a.burst_dm, f, f.max()) / DT).astype(int)
    e0 = int(0.6 * ngulp * a.gulp)
    pix = a.npix // 3
    hits = {}
    for c, d in enumerate(delays):
        for k in range(2):
            j = e0 + d + k
            hits.setdefault(j // a.gulp, []).append((j % a.gulp, c))

    def gulp(g):
        x = pool[g % len(pool)]
        if g in hits:
            x = x.copy()
            jj, cc = (np.asarray(v) for v in zip(*hits[g]))
            x[xp.asarray(jj), xp.asarray(cc), pix] += a.burst_snr
        return x

    rows = []
    modes = [("tree" if prec == "fp32" else f"tree-{prec}", dict(dms=[a.dm_max], dedisperse="tree", tree_precision=prec))
             for prec in a.tree_precision]
    if a.array_stats:
        modes.append(("tree-array", dict(dms=[a.dm_max], dedisperse="tree")))
    if a.shifts_dms:
        modes.append(("shifts", dict(dms=list(np.linspace(0, a.dm_max, a.shifts_dms)), dedisperse="shifts")))
    print(f"# bench_search: device={a.device} nchan={a.nchan} npix={a.npix} DM 0-{a.dm_max} window {window} images, "
          f"{a.seconds} s of data in gulps of {a.gulp} images; burst DM {a.burst_dm} at image {e0}, pixel {pix}")
    print(f"{'mode':<10} {'trials':>6} {'s/s':>7} {'x real':>7} {'tree s/s':>8} {'GB held':>8} {'GB peak':>8} "
          f"{'best DM':>8} {'image':>6} {'pixel':>6} {'S/N':>6}")
    for name, kw in modes:
        if xp is not np:
            xp.get_default_memory_pool().free_all_blocks()
        TransientSearch.FUSED_STATS = name != "tree-array"
        warm_up(xp, kw)
        s = TransientSearch(f, DT, a.npix, window, widths=(1, 2, 4, 8), threshold=a.threshold, xp=xp,
                            max_batch=a.gulp, **kw)
        tree_t = [0.0]
        inner = s._dedisperse

        def timed(x, index=None, inner=inner):
            if xp is np:
                t0 = time.perf_counter()
                out = inner(x, index)
                tree_t[0] += time.perf_counter() - t0
                return out
            e0_, e1_ = xp.cuda.Event(), xp.cuda.Event()
            e0_.record()
            out = inner(x, index)
            e1_.record()
            e1_.synchronize()
            tree_t[0] += xp.cuda.get_elapsed_time(e0_, e1_) / 1e3
            return out
        s._dedisperse = timed
        found = [s.push(gulp(0))]                     # the first gulp compiles kernels: not timed
        synchronize(xp)
        tree_t[0] = 0.0
        t0 = time.perf_counter()
        for g in range(1, ngulp):
            found.append(s.push(gulp(g)))
        synchronize(xp)
        wall = time.perf_counter() - t0
        data_s = (ngulp - 1) * a.gulp * DT
        c = Crossings.concat(found)
        held = peak = None
        if xp is not np:
            pool_ = xp.get_default_memory_pool()
            held, peak = pool_.used_bytes() / 1e9, pool_.total_bytes() / 1e9
        r = {"mode": name, "trials": s.nser, "seconds_per_second": wall / data_s, "realtime_factor": data_s / wall,
             "tree_seconds_per_second": tree_t[0] / data_s, "gb_held": held, "gb_pool": peak,
             "data_s": data_s, "crossings": len(c)}
        if len(c):
            k = int(np.argmax(c.snr))
            r.update(best_dm=s.dms[c.series[k]], best_sweep=int(s.delay_max[c.series[k]]), best_image=int(c.image[k]),
                     best_pixel=int(c.pixel[k]), best_snr=float(c.snr[k]),
                     found=bool(c.pixel[k] == pix and abs(int(c.image[k]) - e0) <= 1))
        rows.append(r)
        print(f"{name:<10} {s.nser:>6} {r['seconds_per_second']:>7.3f} {r['realtime_factor']:>7.2f} "
              f"{r['tree_seconds_per_second']:>8.3f} {held or 0:>8.2f} {peak or 0:>8.2f} "
              f"{r.get('best_dm', float('nan')):>8.3f} {r.get('best_image', -1):>6} {r.get('best_pixel', -1):>6} "
              f"{r.get('best_snr', float('nan')):>6.1f}", flush=True)
        # the timing wrapper and the search hold each other: both go, or the next row's pool starts
        # with this one's arrays and its peak counts them
        s.__dict__.pop("_dedisperse", None)
        del s, found, timed, inner
    truth_sweep = int(np.rint(dispersion_delay_s(a.burst_dm, f.min(), f.max()) / DT))
    print(f"# truth: DM {a.burst_dm} (sweep {truth_sweep}), image {e0}, pixel {pix}")
    out = {"benchmark": "bench_search", "date": utc_now(), "device": a.device, "machine": machine(a.device),
           "case": {**vars(a), "json": None, "window_images": window, "burst_image": e0, "burst_pixel": pix,
                    "burst_sweep": truth_sweep}, "rows": rows}
    if a.json:
        write_json(a.json, out)
    return out


def warm_up(xp, kw):
    """One small search of this row's kind with a burst and a sky-wide flash: compiles the kernels the
    timed run uses (they are cached by source and type, not by size)."""
    f = 74e6 + 25e3 * np.arange(64)
    s = TransientSearch(f, DT, 64, 20, widths=(1, 2, 4, 8), threshold=5.0, xp=xp, max_batch=64, max_pixels=4,
                        **{**kw, "dms": [0.2]})
    x = np.random.default_rng(1).normal(10.0, 1.0, (64 * 6, 64, 64)).astype(np.float32)
    x[300:302, :, 5] += 20.0
    x[320:322] += 20.0
    for g in range(6):
        s.push(xp.asarray(x[64 * g:64 * (g + 1)]))
    if xp is not np:
        xp.cuda.Device().synchronize()


if __name__ == "__main__":
    main()
