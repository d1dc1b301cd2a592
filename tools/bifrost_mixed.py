"""Our blocks inside real Bifrost on a GPU, between Bifrost's own blocks, against our runtime.

The mixed graph (real Bifrost, ``import bifrost`` works and BF_EPIC_RUNTIME is not ``builtin``):

    ArraySourceBlock (host ring)
      -> bifrost.blocks.copy(space='cuda')                 Bifrost copies the voltages to the GPU
      -> bifrost.blocks.transpose(['time', 'freq', 'station', 'pol'])   (cf32 only: the source is
         station-major; Bifrost's transpose does not take 4-bit samples)
      -> CalFoldBlock -> DFTImagerBlock                    ours, on Bifrost's 'cuda' ring
      -> bifrost.blocks.copy(space='system')               Bifrost copies the images back
      -> ArraySinkBlock

Our runtime's graph for the same images (``BF_EPIC_RUNTIME=builtin``): the source's voltages in
(time, freq, station, pol) order on a 'cuda' ring -> CalFoldBlock -> DFTImagerBlock -> ArraySinkBlock.

``python tools/bifrost_mixed.py --compare`` runs the graph in this process's runtime and our
runtime's in a subprocess, for ci4 and cf32, prints images compared (max |Bifrost - ours| / peak,
and each against a float64 sum by the definition on a subset of pixels) and the time per gulp of
each (steady state: the first run of each graph is a warm-up), and writes ``--json``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

C = 299792458.0
DT = 40e-6


def scene(nstand=256, nchan=8, ntime=8192, seed=3):
    """Deterministic voltages: 4-bit integers (noise + a point source), an LWA-like layout, cable terms."""
    rng = np.random.default_rng(seed)
    r = 50 * np.sqrt(rng.random(nstand))
    th = 2 * np.pi * rng.random(nstand)
    xyz = np.stack([r * np.cos(th), 1.1 * r * np.sin(th), rng.normal(0, 0.3, nstand)], axis=1)
    freq = 60e6 + 25e3 * np.arange(nchan)
    l0, m0 = 0.2, 0.3
    n0 = np.sqrt(1 - l0 * l0 - m0 * m0)
    ph = np.exp(2j * np.pi * freq[:, None] / C * (xyz @ [l0, m0, n0])[None])
    s = 1.5 * (rng.normal(size=(ntime, 1, 1, 2)) + 1j * rng.normal(size=(ntime, 1, 1, 2)))
    x = 1.5 * (rng.normal(size=(ntime, nchan, nstand, 2)) + 1j * rng.normal(size=(ntime, nchan, nstand, 2)))
    x = x + s * ph[None, :, :, None]
    ints = np.clip(np.rint(x.real), -8, 7) + 1j * np.clip(np.rint(x.imag), -8, 7)
    delay = rng.uniform(100e-9, 600e-9, (nstand, 2, nchan))
    gain = rng.uniform(0.5, 2.0, (nstand, 2, nchan))
    flags = np.zeros((nstand, 2), bool)
    flags[5, 1] = True
    return dict(xyz=xyz, freq=freq, ints=ints, delay=delay, gain=gain, flags=flags)


def header(s, dtype, station_major=False):
    from bf_epic_blocks.blocks import efield_header
    st = {"name": "mixed", "xyz_m": s["xyz"], "flags": s["flags"], "cable_delay_s": s["delay"], "cable_gain": s["gain"]}
    hdr = efield_header("mixed", 10**12, s["freq"], DT, st, dtype=dtype)
    if station_major:   # (time, station, freq, pol): what Bifrost's transpose puts right
        t = hdr["_tensor"]
        for k in ("shape", "labels", "scales", "units"):
            t[k] = [t[k][i] for i in (0, 2, 1, 3)]
    return hdr


def run_graph(s, dtype, gulp, accumulate, grid_size, precision):
    """Images (nimg, nchan, nprod, N, N) and seconds per gulp of the graph this process's runtime runs."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, CalFoldBlock, DFTImagerBlock, _compat, bfp
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    grid = imaging.lm_grid(grid_size)
    bifrost = _compat.HAVE_BIFROST
    station_major = bifrost and dtype == "cf32"
    x = s["ints"]
    if station_major:
        x = np.ascontiguousarray(x.transpose(0, 2, 1, 3))
    data = pack_ci4(x) if dtype == "ci4" else x.astype(np.complex64)
    hdr = header(s, dtype, station_major)
    with bfp.Pipeline() as p:
        if bifrost:
            import bifrost.blocks as bfb
            src = ArraySourceBlock(data, hdr, gulp_nframe=gulp, space="system")
            v = bfb.copy(src, space="cuda")
            if station_major:
                v = bfb.transpose(v, ["time", "freq", "station", "pol"])
            img = DFTImagerBlock(CalFoldBlock(v, cable=True), grid, accumulate, products="stokes",
                                 precision=precision)
            sink = ArraySinkBlock(bfb.copy(img, space="system"))
        else:
            from bf_epic_blocks.imaging._xp import gpu_available
            src = ArraySourceBlock(data, hdr, gulp_nframe=gulp, space="cuda" if gpu_available() else "system")
            img = DFTImagerBlock(CalFoldBlock(src, cable=True), grid, accumulate, products="stokes",
                                 precision=precision)
            sink = ArraySinkBlock(img)
        t0 = time.perf_counter()
        p.run()
        wall = time.perf_counter() - t0
    return np.asarray(sink.result(0)), wall / (len(s["ints"]) / gulp)


def truth(s, accumulate, grid_size, npix=64):
    """float64 Stokes I on every 50th pixel of the grid, by the definition (cable terms, flags folded in)."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging.calibration import cable_weights
    grid = imaging.lm_grid(grid_size)
    k = np.arange(grid.npix)[::50][:npix]                  # kept pixels, and their cells on the grid
    idx = np.flatnonzero(grid.mask)[k]
    l, m = grid.lm[k, 0], grid.lm[k, 1]
    n = np.sqrt(1 - l * l - m * m)
    w = cable_weights(s["delay"], s["gain"], s["freq"]) * ~s["flags"][None]     # (nchan, nstand, 2)
    X = s["ints"].astype(np.complex128)
    nimg = len(X) // accumulate
    out = np.zeros((nimg, len(s["freq"]), len(idx)))
    for c, nu in enumerate(s["freq"]):
        ph = np.exp(-2j * np.pi * nu / C * (np.outer(l, s["xyz"][:, 0]) + np.outer(m, s["xyz"][:, 1])
                                            + np.outer(n, s["xyz"][:, 2])))
        for p in range(2):
            live = w[c, :, p] != 0
            D = ph[:, live] * w[c, live, p] / live.sum()
            F = (D @ X[:nimg * accumulate, c, live, p].T).reshape(len(idx), nimg, accumulate)
            out[:, c] += (np.abs(F) ** 2).mean(axis=2).T
    return out, idx


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--compare", action="store_true", help="also run our runtime's graph (subprocess) and compare")
    ap.add_argument("--dtypes", default="ci4,cf32")
    ap.add_argument("--nstand", type=int, default=256)
    ap.add_argument("--nchan", type=int, default=8)
    ap.add_argument("--ntime", type=int, default=8192)
    ap.add_argument("--gulp", type=int, default=1024)
    ap.add_argument("--accumulate", type=int, default=1024)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--save", help="(internal) write this process's images and timings to this .npz")
    ap.add_argument("--json", help="write the comparison as JSON")
    a = ap.parse_args(argv)
    from bf_epic_blocks.blocks import _compat
    s = scene(a.nstand, a.nchan, a.ntime)
    runtime = "bifrost " + _compat.bf.__version__ if _compat.HAVE_BIFROST else "ours"
    res = {}
    for dt in a.dtypes.split(","):
        run_graph(s, dt, a.gulp, a.accumulate, a.grid, a.precision)          # warm-up: kernels, pools
        img, per_gulp = run_graph(s, dt, a.gulp, a.accumulate, a.grid, a.precision)
        res[dt] = (img, per_gulp)
        print(f"{runtime}: {dt}: {img.shape[0]} images, {per_gulp * 1e3:.3f} ms per gulp of {a.gulp} frames", flush=True)
    if a.save:
        np.savez(a.save, **{f"{k}_img": v[0] for k, v in res.items()}, **{f"{k}_t": v[1] for k, v in res.items()})
    if not a.compare:
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ours.npz"
        env = dict(os.environ, BF_EPIC_RUNTIME="builtin")
        cmd = [sys.executable, __file__, "--save", str(out)] + [f"--{k}={v}" for k, v in
               (("dtypes", a.dtypes), ("nstand", a.nstand), ("nchan", a.nchan), ("ntime", a.ntime), ("gulp", a.gulp),
                ("accumulate", a.accumulate), ("grid", a.grid), ("precision", a.precision))]
        subprocess.run(cmd, env=env, check=True)
        ours = dict(np.load(out))
    ref, idx = truth(s, a.accumulate, a.grid)
    rows, ok = [], True
    for dt, (img, per_gulp) in res.items():
        o = ours[f"{dt}_img"]
        peak = np.nanmax(np.abs(o))
        same_nan = bool(np.array_equal(np.isnan(img), np.isnan(o)))
        d = float(np.nanmax(np.abs(img - o)) / peak) if img.shape == o.shape else float("inf")
        flat = img[:, :, 0].reshape(img.shape[0], img.shape[1], -1)[..., idx]          # Stokes I
        e = float(np.max(np.abs(flat - ref)) / np.max(np.abs(ref)))
        row = {"dtype": dt, "images": int(img.shape[0]), "rel_diff_vs_ours": d, "nan_masks_equal": same_nan,
               "err_vs_float64": e, "ms_per_gulp_bifrost": per_gulp * 1e3,
               "ms_per_gulp_ours": float(ours[f"{dt}_t"]) * 1e3}
        row["ok"] = same_nan and d <= 1e-6 and e <= 1e-5
        ok &= row["ok"]
        rows.append(row)
    print(f"\n{runtime} vs ours, {a.nstand} stands x {a.nchan} channels x {a.ntime} samples, gulp {a.gulp}, "
          f"{a.accumulate} per image, {a.grid}x{a.grid} grid, {a.precision}")
    print(f"{'dtype':<6} {'images':>6} {'|bf-ours|/peak':>15} {'err vs f64':>11} {'bifrost ms/gulp':>16} "
          f"{'ours ms/gulp':>13}  ok")
    for r in rows:
        print(f"{r['dtype']:<6} {r['images']:>6} {r['rel_diff_vs_ours']:>15.1e} {r['err_vs_float64']:>11.1e} "
              f"{r['ms_per_gulp_bifrost']:>16.3f} {r['ms_per_gulp_ours']:>13.3f}  {r['ok']}")
    if a.json:
        Path(a.json).write_text(json.dumps({"runtime": runtime, "args": vars(a), "rows": rows}, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
