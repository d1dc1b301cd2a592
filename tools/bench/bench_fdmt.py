#!/usr/bin/env python
"""Benchmark: tree dedispersion (search/tree.py) against shifted sums, time and error, CPU or GPU.

For ``--nchan`` channels of 25 kHz from 74 MHz at 0.64-ms images and DMs 0 .. ``--dm-max``, every sweep
0 .. S images is a trial (S = the sweep at the largest DM). A block of ``--ntime`` images of
``--npix`` pixels (noise, plus a dispersed pulse) is dedispersed two ways:

* ``shifts`` -- one shifted add per (trial, channel): what the streaming search does today;
* ``fdmt`` -- :func:`bf_epic_blocks.search.fdmt`.

Error: max |fdmt - shifts| / max |shifts| with the shifted sums taken at the tree's own read offsets
(:func:`effective_back`), so the two compute the same sums; and how far those offsets are from the
rounded dispersion curve (images). Rows per channel count; JSON with ``--json``.

    python tools/bench/bench_fdmt.py --device cpu --json docs/bench/bench_fdmt_cpu_2cores.json
"""
import argparse
import time

import numpy as np

from bf_epic_blocks.conventions import dispersion_delay_s
from bf_epic_blocks.search import FDMTPlan, effective_back, fdmt

from benchlib import array_module, machine, synchronize, utc_now, write_json

DT = 16 / 25e3


def shifted_sums(xp, x, back):
    """sum_c x_c(t - back[d, c]): one slice add per (trial, channel)."""
    nd, (C, T, P) = back.shape[0], x.shape
    out = xp.zeros((nd, T, P), x.dtype)
    for d in range(nd):
        for c in range(C):
            b = int(back[d, c])
            if b < T:
                out[d, b:] += x[c, :T - b]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, nargs="+", default=[16, 64, 256])
    ap.add_argument("--dm-max", type=float, default=3.0)
    ap.add_argument("--ntime", type=int, default=None, help="images per block (default: 2 x the sweep)")
    ap.add_argument("--npix", type=int, default=16)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    xp = array_module(a.device)

    def clock(fn):
        fn()
        synchronize(xp)
        t0 = time.perf_counter()
        out = fn()
        synchronize(xp)
        return time.perf_counter() - t0, out

    rows = []
    rng = np.random.default_rng(0)
    print(f"{'nchan':>6} {'sweep':>6} {'ntime':>6} {'rows fdmt':>10} {'rows shifts':>11} {'fdmt s':>8} "
          f"{'shifts s':>9} {'speed-up':>8} {'rel err':>8} {'curve dev':>9}")
    for nchan in a.nchan:
        f = 74e6 + 25e3 * np.arange(nchan)
        delay = dispersion_delay_s(a.dm_max, f, f.max()) / DT
        sweep = int(np.ceil(delay.max()))
        T = a.ntime or 2 * sweep + 64
        plan = FDMTPlan(f, sweep)
        back = effective_back(plan)
        k = f ** -2.0
        dev = float(np.abs(back - np.rint(np.arange(sweep + 1)[:, None] * (k[0] - k) / (k[0] - k[-1]))).max())
        x = xp.asarray(rng.normal(size=(nchan, T, a.npix)).astype(np.float32))
        tf, got = clock(lambda: fdmt(x, plan))
        ts, ref = clock(lambda: shifted_sums(xp, x, back))
        err = float(xp.abs(got - ref).max() / xp.abs(ref).max())
        r = {"nchan": nchan, "sweep": sweep, "ntime": T, "npix": a.npix, "rows_fdmt": plan.rows(),
             "rows_shifts": (sweep + 1) * nchan, "fdmt_s": tf, "shifts_s": ts, "speedup": ts / tf,
             "rel_err": err, "curve_dev_images": dev}
        rows.append(r)
        print(f"{nchan:>6} {sweep:>6} {T:>6} {r['rows_fdmt']:>10} {r['rows_shifts']:>11} {tf:>8.3f} {ts:>9.3f} "
              f"{ts / tf:>8.1f} {err:>8.1e} {dev:>9.0f}", flush=True)
    out = {"benchmark": "bench_fdmt", "date": utc_now(), "device": a.device, "machine": machine(a.device),
           "case": {"dm_max": a.dm_max, "dt_s": DT, "chan_width_hz": 25e3, "f0_hz": 74e6}, "rows": rows}
    if a.json:
        write_json(a.json, out)
    return out


if __name__ == "__main__":
    main()
