#!/usr/bin/env python
"""Benchmark: Gauss's three-product fused kernel against the four-product one, regime B, case P (GPU).

Case P as ``bench_dft.py`` builds it (256 LWA-SV-like antennas, 16 channels x 2 pols, 1,024 4-bit samples,
the 64 x 64 all-sky grid's 3,205 pixels), one image per 16 samples (64 a gulp). Rows, all in one run:

  * ``naive-dir``: plain CuPy (F = G X batched, |F|^2 averaged per 16 samples) -- the baseline;
  * ``floor-i8x2``: cuBLAS' int8 GEMM with the four-product mode's MACs (batch C, m = 2 Kpad, k = 4 Apad:
    two pieces of the four real products), int32 output written -- bench_dft's floor row;
  * ``floor-i8x3m``: cuBLAS' int8 GEMMs with the three-product form's MACs (batch 3 C, m = Kpad,
    k = 2 Apad) -- the floor Gauss's form moves to (3/4 of the MACs);
  * ``i8x2 image``: the package's regime-B call (``DFTOperator.image(ci4, accumulate=16)``: layout, kernel,
    products), what bench_dft's regime-B row times;
  * ``floor-i8x1``: the same with one piece's MACs (k = 2 Apad), the floor of the one-piece mode;
  * ``i8x1 kernel`` / ``i8x2 kernel`` / ``i8x3 kernel``: the four-product fused kernel alone on the operator's
    own operands (``i8x1 image``: the one-piece mode's regime-B call);
  * ``gauss2 kernel`` / ``gauss3 kernel``: the three-product kernel alone (two and three pieces);
  * ``gauss2 image (pred.)``: the image call's time with its kernel's replaced by Gauss's (a prediction:
    the layout and products are the same work).

Errors: max |I - I_ref| / max |I_ref| over all 64 images on 200 random pixels plus the brightest, against
a float64 evaluation of the definition (cases.reference_image). Prints the table and writes JSON.

    python tools/bench/bench_gauss.py [--repeat 20] [--json bench_gauss_gpu.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, timer, utc_now, write_json  # noqa: E402
from cases import lwasv_like_layout, pairs_to_complex, quantise4, reference_image, sky_efield  # noqa: E402


def profile(cp, a, xyzd, fd, lmd, Qd, nant, npix):
    """One call of each kernel (i8x2's four-product, Gauss's with two pieces, i8x1's), warmed up, between
    cudaProfilerStart and Stop: run under Nsight Compute with ``--profile-from-start off``."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging import fused, gauss
    op = imaging.DFTOperator(xyzd, fd, lmd, npol=2, precision="i8x2")
    fo = op.fused
    T = fused.padded_ntime(a.ntime)
    Bv = fo._layout(Qd, [0, 1], False)
    Gd = imaging.geometric_operator(xyzd, fd, lmd, "fp64")
    Aq, osc, b, xmax = gauss.quantise_gauss(Gd, cp.ones((a.nchan, nant, 2), cp.complex128), np.arange(nant), nant, 2,
                                            tiled=True)
    Bg = gauss.layout_gauss(fused.layout_voltages(Qd, None, cp.asarray([0, 1], dtype=cp.int32),
                                                  2 * fused._pad(nant, 64), 8), fused._pad(nant, 128), tiled=True)
    flag = cp.zeros(1, cp.int32)
    f1 = imaging.DFTOperator(xyzd, fd, lmd, npol=2, precision="i8x1").fused
    calls = [lambda: fused.fused_power(fo.Aq, fo.osc, Bv, T, 2, fo.flag, fo.npix, fo.config),
             lambda: gauss.gauss_power(Aq, osc, Bg, T, 2, flag, npix),
             lambda: fused.fused_power(f1.Aq, f1.osc, f1._layout(Qd, [0, 1], False), T, 2, f1.flag, f1.npix,
                                       f1.config)]
    calls += [lambda cfg=dict(fused.HOPPER_CONFIG, **c): fused.fused_power(fo.Aq, fo.osc, Bv, T, 2, fo.flag, fo.npix, cfg)
              for c in a.hopper_configs]               # the four-product kernel's other shapes (i8x2), if asked
    for f in calls:
        f()
    cp.cuda.Device().synchronize()
    cp.cuda.runtime.profilerStart()
    for f in calls:
        f()
    cp.cuda.Device().synchronize()
    cp.cuda.runtime.profilerStop()
    print("# profiled one call each of bf_fused_power (i8x2), bf_fused_gauss (two pieces), bf_fused_power (i8x1)"
          + "".join(f", bf_fused_power (i8x2, {c})" for c in a.hopper_configs))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nchan", type=int, default=16)
    ap.add_argument("--ntime", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--nref", type=int, default=200)
    ap.add_argument("--configs", default='[{"ST": 7}, {"MT": 8}]',
                    help="JSON list of kernel shapes (gauss.GAUSS_CONFIG keys) timed beside the default, two pieces")
    ap.add_argument("--hopper-configs", default='[{"ST": 6}, {"ST": 7}]',
                    help="JSON list of the four-product Hopper kernel's shapes (fused.HOPPER_CONFIG keys) timed beside it")
    ap.add_argument("--hopper-configs-1", default='[{"MT": 8}, {"MT": 2}, {"ST": 4}]',
                    help="the same for the one-piece mode (i8x1)")
    ap.add_argument("--profile", action="store_true",
                    help="only one call of each kernel between cudaProfilerStart/Stop (for Nsight Compute)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    a.configs, a.hopper_configs = json.loads(a.configs), json.loads(a.hopper_configs)
    a.hopper_configs_1 = json.loads(a.hopper_configs_1)
    import cupy as cp
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging import fused, gauss

    if cp.cuda.Device().compute_capability != "90":
        sys.exit("bench_gauss: the three-product kernel needs a Hopper GPU (compute capability 9.0)")
    npol, n = 2, 16
    xyz, layout = lwasv_like_layout(256)
    nant = len(xyz)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    Q = quantise4(sky_efield(xyz, freq, a.ntime, npol=npol, dtype=np.complex128))     # int8 (T, C, A, P, 2)
    grid = imaging.lm_grid(64)
    rng = np.random.default_rng(0)
    sub = rng.choice(grid.npix, size=min(a.nref, grid.npix), replace=False)
    Qd, xyzd, fd, lmd = cp.asarray(Q), cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm)
    quick = imaging.DFTOperator(xyzd, fd, lmd, npol=npol).image(cp.asarray(pairs_to_complex(Q))[:128]).get()
    sub = np.unique(np.concatenate([sub, np.argsort(quick.max(axis=(0, 1)))[-20:]]))
    refn = reference_image(Q, xyz, freq, grid.lm[sub], ((0, 0), (1, 1)), accumulate=n)  # (64, C, 2, nsub)
    run = timer("gpu")
    rows = []
    print(f"# bench_gauss: {nant} antennas ({layout}), {grid.npix} pixels, {a.ntime} samples, {a.nchan} channels "
          f"x {npol} pols, one image per {n} samples; {machine('gpu')['hardware']}")
    print(f"{'row':<22} {'ms/gulp':>9} {'rel err':>9} {'vs naive':>8} {'int8 MACs':>10}")

    def row(name, t, err=float("nan"), base=None, macs=None, **kw):
        r = {"row": name, "gulp_s": t, "rel_err": err, "speedup_vs_naive": (base / t) if base else None,
             "int8_macs": macs, **kw}
        rows.append(r)
        sn = f"{base / t:8.2f}" if base else f"{'':8}"
        mc = f"{macs:10.3g}" if macs else f"{'':10}"
        print(f"{name:<22} {t * 1e3:9.3f} {err:9.1e} {sn} {mc}", flush=True)
        return t

    def rel(img):
        img = np.asarray(img)
        return float(np.max(np.abs(img - refn)) / np.max(np.abs(refn)))

    if a.profile:
        return profile(cp, a, xyzd, fd, lmd, Qd, nant, grid.npix)
    # the naive CuPy baseline
    G = imaging.geometric_operator(xyzd, fd, lmd, "fp32") / nant
    X = cp.asarray(pairs_to_complex(Q))
    from bench_dft import int8_floor, naive_direct
    t_naive, img = run(lambda: naive_direct(cp, G, X, n), a.repeat)
    row("naive-dir", t_naive, rel(img[..., sub].get()))
    G = X = img = None
    # the floors
    Kp64, Ap64, Kp128, Ap128 = (fused._pad(grid.npix, 64), fused._pad(nant, 64), fused._pad(grid.npix, 128),
                                fused._pad(nant, 128))
    ncol = npol * a.ntime
    m4 = a.nchan * 2 * Kp64 * 4 * Ap64 * ncol
    row("floor-i8x2", int8_floor(cp, a.nchan, 2 * Kp64, 4 * Ap64, ncol, run, a.repeat), base=t_naive, macs=m4)
    row("floor-i8x1", int8_floor(cp, a.nchan, 2 * Kp64, 2 * Ap64, ncol, run, a.repeat), base=t_naive, macs=m4 // 2)
    m3 = 3 * a.nchan * Kp64 * 2 * Ap64 * ncol
    row("floor-i8x3m", int8_floor(cp, 3 * a.nchan, Kp64, 2 * Ap64, ncol, run, a.repeat), base=t_naive, macs=m3)
    cp.get_default_memory_pool().free_all_blocks()

    def images_of(sums):
        """(T/16, C, P, npix) kernel sums -> the 64 images' XX, YY on the reference pixels (means, 1/nant^2)."""
        return (sums[..., sub] / (n * nant ** 2)).get()

    out = {}
    for precision in ("i8x1", "i8x2", "i8x3"):
        pieces = fused.PIECES[precision]
        op = imaging.DFTOperator(xyzd, fd, lmd, npol=npol, precision=precision)
        t_img, img = run(lambda: op.image(Qd, method="direct", accumulate=n), a.repeat)
        row(f"{precision} image", t_img, rel(img[..., sub].get()), base=t_naive)
        fo = op.fused
        T = fused.padded_ntime(a.ntime)
        Bv = fo._layout(Qd, [0, 1], False)
        t_k, sums = run(lambda: fused.fused_power(fo.Aq, fo.osc, Bv, T, npol, fo.flag, fo.npix, fo.config), a.repeat)
        row(f"{precision} kernel", t_k, rel(images_of(sums)), base=t_naive, macs=a.nchan * 4 * pieces * Kp64 * Ap64 * ncol)
        for cfg in {1: a.hopper_configs_1, 2: a.hopper_configs}.get(pieces, []):   # the four-product kernel's shapes
            cfg = dict(fused.HOPPER_CONFIG, **cfg)
            t_c, got = run(lambda: fused.fused_power(fo.Aq, fo.osc, Bv, T, npol, fo.flag, fo.npix, cfg), a.repeat)
            name = f"{precision} " + " ".join(f"{k}={v}" for k, v in cfg.items() if k != "kernel")
            row(name, t_c, rel(images_of(got)), base=t_naive, config=cfg, equal_to_default=bool(cp.array_equal(got, sums)))
            got = None
        op = fo = Bv = sums = img = None
        cp.get_default_memory_pool().free_all_blocks()
        if pieces == 1:                  # Gauss's kernel takes two or three pieces
            continue
        # the same operator in Gauss's form (its quantisation here in array code: the kernel is what is timed)
        Gd = imaging.geometric_operator(xyzd, fd, lmd, "fp64")
        w = cp.ones((a.nchan, nant, npol), cp.complex128)
        Aq, osc, b, xmax = gauss.quantise_gauss(Gd, w, np.arange(nant), nant, pieces, tiled=True)
        Gd = None
        Bl = fused.layout_voltages(Qd, None, cp.asarray([0, 1], dtype=cp.int32), 2 * Ap64, 8)
        Bg = gauss.layout_gauss(Bl, Ap128, tiled=True)
        flag = cp.zeros(1, cp.int32)
        t_g, sums = run(lambda: gauss.gauss_power(Aq, osc, Bg, T, npol, flag, grid.npix), a.repeat)
        row(f"gauss{pieces} kernel", t_g, rel(images_of(sums)), base=t_naive,
            macs=a.nchan * 3 * pieces * Kp128 * Ap128 * ncol, flag=int(flag.get()[0]))
        row(f"gauss{pieces} image (pred.)", t_img - t_k + t_g, float("nan"), base=t_naive, predicted=True)
        best = sums
        for cfg in (a.configs if pieces == 2 else []):          # the kernel's shapes: the same images, timed
            t_c, got = run(lambda: gauss.gauss_power(Aq, osc, Bg, T, npol, flag, grid.npix, config=cfg), a.repeat)
            same = bool(cp.array_equal(got, best))
            name = "gauss2 " + " ".join(f"{k}={v}" for k, v in cfg.items())
            row(name, t_c, rel(images_of(got)), base=t_naive, config=cfg, equal_to_default=same)
            if t_c < t_g:
                t_g = t_c
            got = None
        if a.configs and pieces == 2:
            row("gauss2 image (pred., best)", t_img - t_k + t_g, float("nan"), base=t_naive, predicted=True)
        out[precision] = {"image": t_img, "kernel": t_k, "gauss_kernel": t_g}     # the best shape's
        Aq = osc = Bl = Bg = sums = None
        cp.get_default_memory_pool().free_all_blocks()
    for precision, v in out.items():
        print(f"# {precision}: Gauss's kernel {v['gauss_kernel'] / v['kernel']:.3f}x the four-product kernel's time "
              f"(predicted 0.75 at the same efficiency)")
    result = {"benchmark": "bench_gauss", "date": utc_now(), "machine": machine("gpu"),
              "case": {"nant": nant, "layout": layout, "npix": grid.npix, "ntime": a.ntime, "nchan": a.nchan,
                       "npol": npol, "accumulate": n, "data": "sky + noise, 4-bit"},
              "rows": rows, "ratios": {p: v["gauss_kernel"] / v["kernel"] for p, v in out.items()}}
    if a.json:
        write_json(a.json, result)
    return result


if __name__ == "__main__":
    main()
