#!/usr/bin/env python
"""Benchmark: how far each imaging mode's band-averaged images are from float64 truth (GPU).

The whole-band pipelines write band-averaged products: the cube (every 16-sample image averaged over
the band's channels) and the integrations (images averaged over a second and over the band). An
integer mode rounds each channel's operator on its own, so a channel's images are off by a pattern
that changes from channel to channel, and an average over channels averages those patterns. This
measures how much, on one gulp: 256 LWA-SV-like antennas, the 64 x 64 grid's 3,205 pixels, 784
contiguous channels of 25 kHz from 74 MHz, 4-bit voltages of a sky of four bright sources over noise
(``cases.sky_efield``), one image per 16 samples. For the first C channels (C = 1, 16, 64, 256, 784):

  * ``channel``: the worst channel's 16-sample images (the per-image error bench_dft reports);
  * ``cube``: the 16-sample images averaged over the C channels;
  * ``integration``: the gulp's images averaged over time and over the C channels;

each as max |I - I_ref| / max |I_ref| over 200 random pixels plus the brightest, I = XX + YY, I_ref the
float64 evaluation of the definition (``cases.reference_image``). Prints the table and writes JSON.

    python tools/bench/bench_band_error.py [--ntime 256] [--json bench_band_error_gpu.json]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, timer, utc_now, write_json  # noqa: E402
from cases import lwasv_like_layout, quantise4, reference_image, sky_efield  # noqa: E402

COUNTS = (1, 16, 64, 256, 784)


def errors(img, ref, counts):
    """{C: {"channel", "cube", "integration"}} of images ``img`` against ``ref``, both (g, C', 2, k)."""
    I, R = img.sum(axis=2), ref.sum(axis=2)                               # (g, C', k): XX + YY
    out = {}
    for c in counts:
        per = np.abs(I[:, :c] - R[:, :c]).max(axis=(0, 2)) / np.abs(R[:, :c]).max(axis=(0, 2))
        cube_i, cube_r = I[:, :c].mean(axis=1), R[:, :c].mean(axis=1)
        int_i, int_r = cube_i.mean(axis=0), cube_r.mean(axis=0)
        out[c] = {"channel": float(per.max()),
                  "cube": float(np.abs(cube_i - cube_r).max() / np.abs(cube_r).max()),
                  "integration": float(np.abs(int_i - int_r).max() / np.abs(int_r).max())}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ntime", type=int, default=256, help="samples (a multiple of 16)")
    ap.add_argument("--nchan", type=int, default=784)
    ap.add_argument("--modes", default="fp32,i8x1,i8x2", help="comma-separated precisions")
    ap.add_argument("--nref", type=int, default=200)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import cupy as cp
    from bf_epic_blocks import imaging

    counts = tuple(c for c in COUNTS if c < a.nchan) + (a.nchan,)
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    Q = quantise4(sky_efield(xyz, freq, a.ntime, npol=2, dtype=np.complex128))     # int8 (T, C, A, P, 2)
    grid = imaging.lm_grid(64)
    rng = np.random.default_rng(0)
    Qd, xyzd, fd, lmd = cp.asarray(Q), cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm)
    run = timer("gpu")
    rows, sub = [], None
    print(f"# bench_band_error: {len(xyz)} antennas ({layout}), {grid.npix} pixels, {a.ntime} samples, "
          f"{a.nchan} channels x 2 pols, one image per 16 samples; {machine('gpu')['hardware']}")
    print(f"{'mode':<6} {'ms/gulp':>9} " + " ".join(f"{f'{k} C={c}':>17}" for k in ("channel", "cube", "integr.")
                                                   for c in (1, a.nchan)))
    ref = None
    for mode in a.modes.split(","):
        op = imaging.DFTOperator(xyzd, fd, lmd, npol=2, precision=mode)
        t, img = run(lambda: op.image(Qd, method="direct", accumulate=16), 3)
        if sub is None:                          # the pixels: random ones plus the brightest of the band
            bright = np.argsort(img.sum(axis=(0, 1, 2)).get())[-20:]
            sub = np.unique(np.concatenate([rng.choice(grid.npix, size=min(a.nref, grid.npix), replace=False),
                                            bright]))
            ref = reference_image(Q, xyz, freq, grid.lm[sub], ((0, 0), (1, 1)), accumulate=16)   # (g, C, 2, k)
        err = errors(img[..., sub].get(), ref, counts)
        rows.append({"mode": mode, "gulp_s": t, "errors": {str(c): e for c, e in err.items()}})
        print(f"{mode:<6} {t * 1e3:9.2f} " + " ".join(f"{err[c][k]:17.2e}" for k in ("channel", "cube", "integration")
                                                      for c in (1, a.nchan)), flush=True)
        op = img = None
        cp.get_default_memory_pool().free_all_blocks()
    print("# by channels averaged (C): mode  C  channel  cube  integration")
    for r in rows:
        for c, e in r["errors"].items():
            print(f"  {r['mode']:<6} {c:>4} {e['channel']:9.2e} {e['cube']:9.2e} {e['integration']:9.2e}")
    if a.json:
        write_json(a.json, {"benchmark": "bench_band_error", "date": utc_now(), "machine": machine("gpu"),
                            "case": {"nant": len(xyz), "npix": grid.npix, "ntime": a.ntime, "nchan": a.nchan,
                                     "channel_hz": 25e3, "first_hz": 74e6, "accumulate": 16,
                                     "pixels_compared": int(len(sub))},
                            "rows": rows})


if __name__ == "__main__":
    main()
