#!/usr/bin/env python
"""Benchmark: how far from its true DM the transient search places a burst, in DM trials.

Simulated image series, searched by ``TransientSearchBlock`` as a pipeline runs it (the tree, every
sweep to DM 1.6 one image apart, boxcars of 1, 2, 4 and 8 images, a 0.2-s window): 96 channels over
19.2 MHz from 74 MHz, one image per 0.64 ms, Gaussian noise, and per run four bursts at four pixels
far apart, each at a DM drawn from 0.3-1.5 and arriving between two images (a box of ``width``
images, each channel's share of an image its overlap with the box). For each burst the row at its
pixel gives two DMs:

* ``dm_trial`` -- the DM trial of the highest S/N (what the search alone reports);
* ``dm`` -- the vertex of the S/N across the trials around it
  (:meth:`bf_epic_blocks.search.TransientSearch.refine_dm`).

Each case prints the error of both in trials (one trial: one image of sweep across the band): rms
and largest over its bursts, and the share within one trial. Cases: a 4-ms burst (6.25 images, the
station pipeline's) bright and faint, a 1-ms one (1.5 images), and the station pipeline's high
tuning (784 channels of 25 kHz) with its burst (4 ms, DM 0.35-0.45, S/N ~300).

    python tools/bench/bench_dm_accuracy.py [--seeds 6] [--case NAME ...] [--json bench_dm_accuracy_cpu.json]
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402

NCHAN, CHAN_HZ, F0, DT = 96, 200e3, 74e6, 16 * 40e-6
NIMG, ARRIVAL = 2600, 1500
#: (name, burst width in images, amplitude per channel-image in units of the noise sigma, channels, channel
#: width (Hz), DMs drawn from); the last: the station pipeline's high tuning and burst (784 channels of
#: 25 kHz, DM 0.4, S/N ~300)
CASES = (("4 ms, S/N ~135", 6.25, 6.0, NCHAN, CHAN_HZ, (0.3, 1.5)),
         ("4 ms, S/N ~29", 6.25, 1.3, NCHAN, CHAN_HZ, (0.3, 1.5)),
         ("1 ms, S/N ~55", 1.5, 6.0, NCHAN, CHAN_HZ, (0.3, 1.5)),
         ("station, S/N ~300", 6.25, 4.8, 784, 25e3, (0.35, 0.45)))


def run_case(width, amp, seed, nchan=NCHAN, chan_hz=CHAN_HZ, dm_range=(0.3, 1.5)):
    """One pipeline run of four bursts; returns [(true DM, dm_trial, dm, snr)] and the trial step."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.blocks import ArraySourceBlock, TransientSearchBlock, bfp, headers
    from bf_epic_blocks.conventions import dispersion_delay_s
    from bf_epic_blocks.io.candidates import CandidateWriter, read_candidates
    from bf_epic_blocks.search import SearchSettings
    rng = np.random.default_rng(seed)
    freq = F0 + chan_hz * np.arange(nchan)
    grid = imaging.lm_grid(8)
    N = grid.size
    valid = np.flatnonzero(grid.mask.ravel())
    x = rng.normal(10.0, 1.0, (NIMG, nchan, 1, N * N)).astype(np.float32)
    bursts = [(valid[i], rng.uniform(*dm_range)) for i in (0, 4, 26, 38)]     # cells 4 or more apart
    for cell, dm in bursts:
        t0 = ARRIVAL + rng.random()
        for c in range(nchan):
            a = t0 + dispersion_delay_s(dm, freq[c], freq.max()) / DT
            for i in range(int(a), int(np.ceil(a + width))):
                x[i, c, 0, cell] += amp * (min(a + width, i + 1) - max(a, i))
    from bf_epic_blocks.conventions import FS_HZ
    station = {"name": "lwasv", "lat_deg": 34.3484, "lon_deg": -106.8858, "elev_m": 1477.0}
    hdr = headers.image_header("dm", int(1717236000 * FS_HZ), freq, DT, grid, station, ("I",))
    with tempfile.TemporaryDirectory() as d:
        with bfp.Pipeline() as pl:
            src = ArraySourceBlock(x.reshape(NIMG, nchan, 1, N, N), hdr, gulp_nframe=64)
            srch = TransientSearchBlock(src, SearchSettings(threshold=7.5, window_s=0.2, dms=[1.6], dedisperse="tree",
                                                             widths=[1, 2, 4, 8], sidelobe_factor=0.0),
                                        writer=CandidateWriter(d, png=False))
            pl.run()
        t = read_candidates(Path(d) / "transients_candidates.ecsv")
    out = []
    for cell, dm in bursts:
        rows = t[valid[t["pixel"]] == cell]
        if not len(rows):
            out.append((dm, float("nan"), float("nan"), 0.0))
            continue
        r = rows[int(np.argmax(rows["snr"]))]
        out.append((dm, float(r["dm_trial"]), float(r["dm"]), float(r["snr"])))
    return out, float(srch.search.dms[1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=6, help="runs per case (four bursts each)")
    ap.add_argument("--case", action="append", help="only the cases whose name starts so (repeatable)")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'case':18s} {'bursts':>6s} {'found':>5s} {'S/N':>6s} | {'best trial: rms':>15s} {'max':>5s} {'<=1':>5s} | "
          f"{'fitted: rms':>11s} {'max':>5s} {'<=1':>5s}  {'s':>5s}")
    for name, width, amp, nchan, chan_hz, dm_range in CASES:
        if args.case and not any(name.startswith(c) for c in args.case):
            continue
        t0 = time.perf_counter()
        got = []
        for seed in range(args.seeds):
            res, step = run_case(width, amp, 3000 + seed, nchan, chan_hz, dm_range)
            got += [(dm, (a - dm) / step, (b - dm) / step, snr) for dm, a, b, snr in res]
        g = np.array(got)
        found = np.isfinite(g[:, 1])
        et, ef = g[found, 1], g[found, 2]
        row = {"case": name, "width_images": width, "amplitude": amp, "nchan": nchan, "chan_hz": chan_hz,
               "dm_range": list(dm_range), "bursts": len(g), "found": int(found.sum()),
               "snr_median": float(np.median(g[found, 3])),
               "trial_rms": float(np.sqrt(np.mean(et ** 2))), "trial_max": float(np.abs(et).max()),
               "trial_within_1": float(np.mean(np.abs(et) <= 1)),
               "fit_rms": float(np.sqrt(np.mean(ef ** 2))), "fit_max": float(np.abs(ef).max()),
               "fit_within_1": float(np.mean(np.abs(ef) <= 1)), "seconds": time.perf_counter() - t0,
               "errors_trial": et.tolist(), "errors_fit": ef.tolist(), "dm_true": g[:, 0].tolist()}
        rows.append(row)
        print(f"{name:18s} {row['bursts']:6d} {row['found']:5d} {row['snr_median']:6.0f} | {row['trial_rms']:15.2f} "
              f"{row['trial_max']:5.2f} {row['trial_within_1']:5.0%} | {row['fit_rms']:11.2f} {row['fit_max']:5.2f} "
              f"{row['fit_within_1']:5.0%}  {row['seconds']:5.0f}")
    if args.json:
        write_json(args.json, {"benchmark": "bench_dm_accuracy", "date": utc_now(), "machine": machine("cpu"),
                               "setup": {"nchan": NCHAN, "chan_hz": CHAN_HZ, "f0_hz": F0, "dt_s": DT, "dms": "tree to 1.6",
                                         "widths": [1, 2, 4, 8], "window_s": 0.2, "seeds": args.seeds},
                               "rows": rows})


if __name__ == "__main__":
    main()
