#!/usr/bin/env python
"""Benchmark: exact DFT vs E-field w-stacking vs covariance + w-gridding vs MOFF.

Case (PHYSICS.md, case P): 256 LWA-SV-like antennas (LSL's lwasv stands when ``lsl`` imports, else
the look-alike of tools/bench/cases.py), 1024 time samples at 74 MHz, all-sky N x N grids. CPU: one channel, one polarisation.
GPU: 16 channels x 2 polarisations (XX, YY). The data are a few incoherent point sources plus noise.

Errors: max |I - I_ref| / max I_ref over a subset of pixels (200 random kept pixels plus the pixel
nearest each source), I_ref a float64 brute-force DFT on that subset (cheap). MOFF ignores the
antenna heights, so its error is the wide-field error, not a gridding error.

Timings are steady state: one warm-up call first (it builds and caches the gridding plans, as a
pipeline would once), then the median of ``--repeat`` calls; GPU timings use cupy.cuda.Event.

    python tools/bench/bench_wstack.py --device cpu --quick
    python tools/bench/bench_wstack.py --device gpu --sizes 64 128 256 --json gpu.json --plot gpu.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bf_epic_blocks.imaging.moff import moff_image
from bf_epic_blocks.imaging.pixels import lm_grid
from bf_epic_blocks.imaging.wstack import cov_wgrid_image, get_plan, work_dtype, wstack_image

from benchlib import array_module, machine, timer, utc_now, write_json
from cases import lwasv_like_layout, reference_image

C = 299792458.0
FREQ0 = 74e6
LEVELS = (1e-2, 1e-4, 1e-6)


def simulate(xyz, freqs, ntime, npol, rng, srcs):
    s = np.c_[srcs, np.sqrt(1 - (srcs ** 2).sum(1))]
    out = np.empty((ntime, len(freqs), xyz.shape[0], npol), np.complex64)
    for c, f in enumerate(freqs):
        ph = np.exp(2j * np.pi * f / C * (xyz @ s.T))
        for p in range(npol):
            amp = (rng.normal(size=(ntime, len(s))) + 1j * rng.normal(size=(ntime, len(s)))) * np.linspace(1, 0.3, len(s))
            noise = 0.3 * (rng.normal(size=(ntime, xyz.shape[0])) + 1j * rng.normal(size=(ntime, xyz.shape[0])))
            out[:, c, :, p] = amp @ ph.T + noise
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512])
    ap.add_argument("--eps", type=float, nargs="+", default=list(LEVELS))
    ap.add_argument("--ntime", type=int, default=1024)
    ap.add_argument("--nant", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["dft_direct", "dft_cov", "wstack", "cov_wgrid", "moff"])
    ap.add_argument("--quick", action="store_true", help="sizes 32 64, 128 samples, eps 1e-2 1e-4, 1 repeat")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path)
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.ntime, args.eps, args.repeat = [32, 64], 128, [1e-2, 1e-4], 1
    rng = np.random.default_rng(0)
    xyz, layout = lwasv_like_layout(args.nant)
    xp = array_module(args.device)
    nchan, npol = (16, 2) if args.device == "gpu" else (1, 1)
    freqs = FREQ0 + 25e3 * np.arange(nchan)
    srcs = np.array([[0.21, 0.33], [-0.45, 0.12], [0.05, -0.62], [0.7, -0.3]])
    efield_h = simulate(xyz, freqs, args.ntime, npol, rng, srcs)
    try:
        from bf_epic_blocks.imaging import dirty_image
    except Exception as exc:  # the DFT module may be absent in a partial checkout
        dirty_image = None
        print(f"# dirty_image unavailable ({exc}); DFT rows skipped")
    run = timer(args.device)
    print(f"# device={args.device} layout={layout} nant={xyz.shape[0]} ntime={args.ntime} nchan={nchan} npol={npol}")
    rows = []
    for N in args.sizes:
        grid = lm_grid(N)
        sub = rng.choice(grid.npix, size=min(200, grid.npix), replace=False)
        near = [int(np.argmin(np.hypot(*(grid.lm - s).T))) for s in srcs]
        sub = np.unique(np.r_[sub, near])
        ref = reference_image(efield_h, xyz, freqs, grid.lm[sub], tuple((p, p) for p in range(npol)))
        peak = ref.max()
        cases = []
        for eps in args.eps:
            ed = xp.asarray(efield_h if work_dtype(eps) == np.complex64 else efield_h.astype(np.complex128))
            if "wstack" in args.methods:
                cases.append(("wstack", eps, lambda ed=ed, eps=eps: wstack_image(ed, xyz, freqs, grid, epsilon=eps)))
            if "cov_wgrid" in args.methods:
                cases.append(("cov_wgrid", eps, lambda ed=ed, eps=eps: cov_wgrid_image(ed, xyz, freqs, grid, epsilon=eps)))
        ed32 = xp.asarray(efield_h)
        if "moff" in args.methods:
            cases.append(("moff", 1e-4, lambda: moff_image(ed32, xyz, freqs, grid, epsilon=1e-4)))
        if dirty_image is not None:
            for meth in ("direct", "covariance"):
                if f"dft_{'cov' if meth == 'covariance' else 'direct'}" in args.methods:
                    for prec in ("fp32",):
                        cases.append((f"dft_{meth}", None, lambda meth=meth, prec=prec: dirty_image(
                            ed32, xyz, freqs, grid.lm, method=meth, precision=prec)))
        for name, eps, fn in cases:
            try:
                t, img = run(fn, args.repeat)
            except Exception as exc:  # e.g. out of memory at large N: report and go on
                print(f"{name:12s} N={N:4d} eps={eps}: failed: {type(exc).__name__}: {exc}")
                continue
            img = np.asarray(img.get() if hasattr(img, "get") else img, np.float64)[:, :npol]
            err = float(np.max(np.abs(img[..., sub] - ref)) / peak)
            info = {}
            if name in ("wstack", "moff"):
                plan = get_plan(xyz * freqs[0] / C, grid, epsilon=eps, sigma=2.0, use_w=(name == "wstack"),
                                direct="auto" if name == "wstack" else None, xp=xp, dtype=work_dtype(eps))
                info = {"Ng": plan.Ng, "planes": plan.nplanes, "W": plan.kernel.W, "direct_ants": plan.ndirect}
            rows.append({"method": name, "size": N, "epsilon": eps, "time_s": t, "error": err, **info})
            print(f"{name:12s} N={N:4d} eps={'-' if eps is None else f'{eps:.0e}':>6s} time={t:9.4f} s "
                  f"err={err:.2e} {info if info else ''}", flush=True)
    print("\n# cheapest method meeting each error level (MOFF only where its wide-field error qualifies)")
    cross = {}
    for N in args.sizes:
        for lvl in LEVELS:
            ok = [r for r in rows if r["size"] == N and r["error"] <= lvl]
            best = min(ok, key=lambda r: r["time_s"]) if ok else None
            cross[f"{N}:{lvl:g}"] = best and {"method": best["method"], "epsilon": best["epsilon"], "time_s": best["time_s"]}
            print(f"N={N:4d} err<={lvl:.0e}: " + (f"{best['method']} (eps={best['epsilon']}) {best['time_s']:.4f} s"
                                                  if best else "none"))
    if args.json:
        write_json(args.json, {"date": utc_now(), "device": args.device, "machine": machine(args.device),
                               "layout": layout, "nant": int(xyz.shape[0]), "ntime": args.ntime, "nchan": nchan,
                               "npol": npol, "rows": rows, "crossover": cross})
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(7, 5))
        markers = dict(zip(sorted({r["method"] for r in rows}), "osD^vx*"))
        for N in args.sizes:
            for m, mk in markers.items():
                rs = [r for r in rows if r["size"] == N and r["method"] == m]
                if rs:
                    ax.loglog([max(r["error"], 1e-16) for r in rs], [r["time_s"] for r in rs], mk + "-",
                              label=f"{m} N={N}")
        ax.set_xlabel("max error / peak")
        ax.set_ylabel("time per gulp (s)")
        ax.set_title(f"{args.device}: {xyz.shape[0]} antennas, {args.ntime} samples, {nchan}x{npol} chan-pol")
        ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
    return rows


if __name__ == "__main__":
    main()
