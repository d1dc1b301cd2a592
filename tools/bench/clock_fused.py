#!/usr/bin/env python
"""Benchmark: the fused integer kernel run back to back, with the GPU's clock and power sampled beside it.

Case P's regime B (as ``bench_gauss.py`` builds it: 256 LWA-SV-like antennas, 16 channels x 2 pols, 1,024
4-bit samples, the 64 x 64 all-sky grid's 3,205 pixels, one image per 16 samples): the four-product
Hopper kernel (``fused.fused_power``) of each mode called back to back for ``--seconds`` each, while
``nvidia-smi`` samples the SM clock, the power drawn and the clock-event reasons every 250 ms. A kernel's
int8 rate is limited by the clock it actually runs at, which a dense integer load pulls below the card's
maximum when it reaches the power limit; a floor computed from the peak rate at the maximum clock
overstates what the card can do by that ratio.

Rows: mode, ms a call (CUDA events over the whole loop), int8 MACs a call, the rate as a fraction of the
peak at the maximum clock and at the median clock sampled while it ran, and the clock's and power's
median, min and max, with the reasons reported. Prints the table and writes JSON.

    python tools/bench/clock_fused.py [--seconds 8] [--json clock_fused_gpu.json]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402
from cases import lwasv_like_layout, quantise4, sky_efield  # noqa: E402

#: nvidia-smi's fields, in order
FIELDS = ("clocks.sm", "clocks.max.sm", "power.draw", "power.limit", "clocks_event_reasons.active")
#: the int8 dense tensor rate a multiprocessor-cycle on compute capability 9.0 (MACs)
MACS_PER_SM_CYCLE = 4096
#: clock-event reason bits nvidia-smi reports (NVML's nvmlClocksEventReason*)
REASONS = {0x1: "idle", 0x4: "power cap (software)", 0x8: "hardware slowdown", 0x20: "thermal (software)",
           0x40: "thermal (hardware)", 0x80: "power brake (hardware)"}


def sample():
    """Start nvidia-smi sampling every 250 ms; returns the process (its stdout: CSV lines)."""
    return subprocess.Popen(["nvidia-smi", f"--query-gpu=timestamp,{','.join(FIELDS)}", "--format=csv,noheader,nounits",
                             "-lms", "250"], stdout=subprocess.PIPE, text=True)


def parse(lines, t0, t1):
    """(clock MHz, max clock MHz, power W, limit W, reasons) of the samples taken between t0 and t1 (epoch s)."""
    out = []
    for line in lines:
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 1 + len(FIELDS):
            continue
        try:
            t = time.mktime(time.strptime(parts[0].split(".")[0], "%Y/%m/%d %H:%M:%S")) + float("0." + parts[0].split(".")[1])
            vals = (float(parts[1]), float(parts[2]), float(parts[3]), float(parts[4]), int(parts[5], 16))
        except (ValueError, IndexError):
            continue
        if t0 <= t <= t1:
            out.append(vals)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds of back-to-back calls a mode")
    ap.add_argument("--modes", nargs="+", default=["i8x2", "i8x1"])
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cupy as cp
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging import fused
    xyz, _ = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(16)
    Q = cp.asarray(quantise4(sky_efield(xyz, freq, 1024, npol=2, dtype=np.complex128)))
    lm = imaging.lm_grid(64).lm
    dev = cp.cuda.Device()
    nsm = dev.attributes["MultiProcessorCount"]
    proc = sample()
    rows, spans = [], []
    try:
        for mode in a.modes:
            op = imaging.DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision=mode)
            fo = op.fused
            Bv = fo._layout(Q, [0, 1], False)
            T = fused.padded_ntime(1024)
            sh = [int(v) for v in fo.Aq.shape]           # tiled (C, PA, M/128, NP, KD/128, 16384) or (C, PA, NP, M, KD)
            M, KD = (sh[2] * 128, sh[4] * 128) if len(sh) == 6 else (sh[3], sh[4])
            macs = 16 * M * (2 * T) * KD * fused.PIECES[mode]

            def call():
                fused.fused_power(fo.Aq, fo.osc, Bv, T, 2, fo.flag, fo.npix, fo.config)
            call()
            dev.synchronize()
            time.sleep(1.0)                              # the clock settles between modes
            e0, e1 = cp.cuda.Event(), cp.cuda.Event()
            n, t0 = 0, time.time()
            e0.record()
            while time.time() - t0 < a.seconds:
                for _ in range(100):
                    call()
                n += 100
                dev.synchronize()
            e1.record()
            e1.synchronize()
            t1 = time.time()
            ms = cp.cuda.get_elapsed_time(e0, e1) / n
            rows.append(dict(mode=mode, calls=n, ms=ms, int8_macs=macs))
            spans.append((t0 + 1.0, t1))                 # the first second: the clock still moving
    finally:
        time.sleep(0.5)
        proc.terminate()
        lines = proc.communicate()[0].splitlines()
    print(f"# clock_fused: case P regime B, {machine('gpu')['hardware']}")
    print(f"{'mode':6} {'ms/call':>8} {'of peak@max':>11} {'of peak@clk':>11} {'SM MHz med (min-max)':>22} "
          f"{'W med (max)':>12}  reasons")
    for r, (t0, t1) in zip(rows, spans):
        s = parse(lines, t0, t1)
        if not s:
            print(f"{r['mode']:6} {r['ms']:8.4f}   (no clock samples: is nvidia-smi on PATH?)")
            continue
        clk = np.array([v[0] for v in s])
        pw = np.array([v[2] for v in s])
        bits = 0
        for v in s:
            bits |= v[4]
        peak = lambda mhz: MACS_PER_SM_CYCLE * nsm * mhz * 1e6        # noqa: E731
        rate = r["int8_macs"] / (r["ms"] * 1e-3)
        r.update(samples=len(s), sm_mhz_median=float(np.median(clk)), sm_mhz_min=float(clk.min()),
                 sm_mhz_max=float(clk.max()), sm_mhz_limit=s[0][1], power_w_median=float(np.median(pw)),
                 power_w_max=float(pw.max()), power_limit_w=s[0][3],
                 reasons=[name for bit, name in REASONS.items() if bits & bit],
                 of_peak_at_max_clock=rate / peak(s[0][1]), of_peak_at_median_clock=rate / peak(np.median(clk)))
        print(f"{r['mode']:6} {r['ms']:8.4f} {r['of_peak_at_max_clock']:11.2f} {r['of_peak_at_median_clock']:11.2f} "
              f"{r['sm_mhz_median']:8.0f} ({r['sm_mhz_min']:.0f}-{r['sm_mhz_max']:.0f}) / {r['sm_mhz_limit']:.0f} "
              f"{r['power_w_median']:6.0f} ({r['power_w_max']:.0f}) / {r['power_limit_w']:.0f}  {', '.join(r['reasons'])}")
    if a.json:
        write_json(a.json, dict(benchmark="clock_fused", date=utc_now(), machine=machine("gpu"),
                                case="P, regime B (16 channels x 2 pols, 1,024 samples, 64x64 grid)",
                                seconds=a.seconds, rows=rows))


if __name__ == "__main__":
    main()
