#!/usr/bin/env python
"""Stress test of numerical stability: fp32 against fp64 (and fp64 against an independent float64
evaluation) as integrations get long, baselines long, pixels close to the horizon, and the dynamic
range high. Prints a table, writes JSON. CPU by default (``--device gpu`` for CuPy).

    python tools/bench/stress_precision.py --json stress.json
"""
import argparse

import numpy as np

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging._xp import to_numpy

from benchlib import array_module, machine, utc_now, write_json
from cases import C, reference_image


def source(xyz, freq, l, m, amp, ntime, rng):
    n = np.sqrt(1 - l * l - m * m)
    ph = np.exp(2j * np.pi * freq / C * (xyz @ [l, m, n]))
    s = amp * (rng.normal(size=(ntime, 1)) + 1j * rng.normal(size=(ntime, 1))) / np.sqrt(2)
    return (s * ph[None])[:, None, :, None]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    xp = array_module(a.device)
    rng = np.random.default_rng(5)
    rows = []

    def report(case, value, err, note=""):
        rows.append({"case": case, "value": value, "error": err, "note": note})
        print(f"{case:<34} {str(value):>12} {err:10.2e}  {note}")

    print(f"{'case':<34} {'value':>12} {'error':>10}")
    # 1. long integrations: fp32 accumulation over many 1024-sample gulps (both routes)
    xyz = np.concatenate([rng.uniform(-50, 50, (63, 2)), rng.normal(0, 0.5, (63, 1))], axis=1)
    freq = np.array([74e6])
    lm = imaging.lm_grid(32).lm
    for ngulp in (1, 10, 100):
        ops = {p: imaging.DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), precision=p)
               for p in ("fp32", "fp64")}
        accs = {(p, m): ops[p].accumulator(method=m) for p in ops for m in ("direct", "covariance")}
        g = np.random.default_rng(ngulp)
        for _ in range(ngulp):
            x = source(xyz, 74e6, 0.3, 0.2, 10.0, 1024, g) + (g.normal(size=(1024, 1, 63, 1)) + 1j * g.normal(size=(1024, 1, 63, 1)))
            xd = xp.asarray(x)
            for acc in accs.values():
                acc.add(xd)
        for m in ("direct", "covariance"):
            r64 = to_numpy(accs[("fp64", m)].result())
            r32 = to_numpy(accs[("fp32", m)].result())
            report(f"long integration, {m}", f"T={1024 * ngulp}", float(np.abs(r32 - r64).max() / r64.max()),
                   "fp32 vs fp64, peak-relative")
    # 2. long baselines and pixels at the horizon (n = 1e-4), 88 MHz
    for span in (100.0, 1e3, 1e4, 1e5):
        xyzb = np.concatenate([rng.uniform(-span / 2, span / 2, (32, 2)), rng.uniform(-5, 5, (32, 1))], axis=1)
        r = np.sqrt(1 - 1e-8)
        ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
        lmh = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=-1)
        x = source(xyzb, 88e6, *lmh[5], 3.0, 64, rng) + 0.1 * rng.normal(size=(64, 1, 32, 1))
        ref = reference_image(x, xyzb, [88e6], lmh, ((0, 0),))
        got = to_numpy(imaging.dirty_image(xp.asarray(x), xp.asarray(xyzb), xp.asarray([88e6]), xp.asarray(lmh),
                                           precision="fp32"))
        report("horizon pixels n=1e-4, fp32", f"{span:g} m", float(np.abs(got - ref).max() / ref.max()),
               "vs float64 definition")
    # 3. dynamic range: a source 1e4 times fainter than another, fp32 and fp64
    xyzd = np.concatenate([rng.uniform(-60, 60, (128, 2)), rng.normal(0, 0.5, (128, 1))], axis=1)
    x = source(xyzd, 74e6, 0.0, 0.1, 100.0, 2048, rng) + source(xyzd, 74e6, -0.5, -0.4, 1.0, 2048, rng)
    pix = np.array([[-0.5, -0.4]])
    # reference without the autocorrelation term: sum over a != b only, float64, by definition
    n = np.sqrt(1 - (pix ** 2).sum(1))
    D = np.exp(-2j * np.pi * 74e6 / C * (xyzd @ np.array([pix[0, 0], pix[0, 1], n[0]]))) / len(xyzd)
    F = x[:, 0, :, 0] @ D
    ref = float((np.abs(F) ** 2).mean() - (np.abs(D) ** 2 * (np.abs(x[:, 0, :, 0]) ** 2).mean(0)).sum())
    for p in ("fp32", "fp64"):
        got = float(to_numpy(imaging.dirty_image(xp.asarray(x), xp.asarray(xyzd), xp.asarray(freq), xp.asarray(pix),
                                                 precision=p, method="covariance", remove_autocorr=True))[0, 0, 0])
        report(f"faint source beside a 1e4x one, {p}", "1e-4", abs(got - ref) / abs(ref),
               "autocorr removed; relative to that pixel's exact value")
    if a.json:
        write_json(a.json, {"date": utc_now(), "device": a.device, "machine": machine(a.device), "rows": rows})


if __name__ == "__main__":
    main()
