#!/usr/bin/env python
"""Benchmark: run time against error for every route x precision x regime x grid of the DFT imager.

Case P (tools/bench/cases.py): 256 antennas, 16 channels x 2 pols (GPU; one channel-pol on the CPU),
1,024 samples of sky + noise quantised to 4 bits (int8 (re, im) pairs, as ci4 unpacks), all-sky
grids of 64 (3,205 pixels), 128 and 256. Regimes: one image per 1,024-sample gulp, and one image
per 16 samples (64 images per gulp, ``accumulate=16``). Products XX, YY (Stokes I needs both).

Each row: median time per gulp with the operator built (the pipeline's steady state) and the error
max |I - I_ref| / max |I_ref| against a float64 evaluation of the definition on 200 random pixels
(all 64 images in the high-cadence regime). Rows in the same run, for speed-up ratios:
  * ``naive``: plain CuPy written naively (R = Y Y^H and (G R * conj G).sum(-1); batched F = G X and
    |F|^2 summed per group) -- the issue's "naive CuPy" baseline;
  * ``previous``: another release's DFTOperator, when ``--previous DIR`` points at a folder holding
    a copy of that package named ``bf_epic_prev``;
  * ``floor-f32`` / ``floor-f16`` (GPU, high-cadence regime): cuBLAS' fp16 GEMM alone on the direct
    route's stacked shapes with fp32 / fp16 output -- what the regime would cost if |F|^2 were free;
  * ``floor-i8x2`` (GPU, high-cadence regime): cuBLAS' int8 GEMM (int32 sums and output) with the MACs
    of the i8x2 mode: the stacked shapes (pixels and antennas padded to 64, as the fused kernel's) with K
    doubled for the two pieces -- the integer floor. Its int32 field (0.86 GB a gulp) is written, which
    the fused kernel never does.
The fused integer modes (i8x2, i8x3: 4-bit voltages, direct route) have no covariance or cf32 rows;
their hard scenes are the same scenes quantised to 4 bits.

``--table`` also images two hard scenes (a 5 km baseline at 88 MHz with pixels at n ~ 1e-4; a
60 dB point source) with every mode and rewrites the package's measured.json: per (device, route,
precision) the bound = 3 x the worst error seen (rounded up) and the rate in CMAC/s on case P.

    python tools/bench/bench_dft.py --device gpu --json bench_dft_gpu.json --table
    python tools/bench/bench_dft.py --device cpu --json bench_dft_cpu.json
"""
import argparse
import gc
import json
import math

import numpy as np

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging import cost, plan
from bf_epic_blocks.imaging.fused import FUSED
from bf_epic_blocks.imaging.gemm import PRECISIONS, precision_available

from benchlib import array_module, import_package, machine, timer, utc_now, write_json
from cases import lwasv_like_layout, pairs_to_complex, quantise4, reference_image, sky_efield

C = 299792458.0


def release(xp):
    """Free a deleted operator's device memory now: its cached accumulators refer back to it (a cycle
    only the collector breaks) and each CUDA graph it captured holds one gulp's working memory."""
    gc.collect()
    if xp.__name__ == "cupy":
        xp.get_default_memory_pool().free_all_blocks()


def naive_covariance(xp, G, X):
    """Plain CuPy/NumPy: R = Y Y^H of the pol-stacked voltages, then Re sum_ab G R G^H per block."""
    T, Cn, A, P = X.shape
    Y = X.transpose(1, 3, 2, 0).reshape(Cn, P * A, T)
    R = xp.matmul(Y, xp.conj(Y).transpose(0, 2, 1)) / T
    out = []
    for p in range(P):
        Rp = R[:, p * A:(p + 1) * A, p * A:(p + 1) * A]
        out.append((xp.matmul(G, Rp) * xp.conj(G)).sum(-1).real)
    return xp.stack(out, 1)


def naive_direct(xp, G, X, n):
    """Plain CuPy/NumPy: F = G X for the whole gulp, |F|^2 averaged over groups of n samples."""
    T, Cn, A, P = X.shape
    Y = X.transpose(1, 2, 3, 0).reshape(Cn, A, P * T)
    F = xp.matmul(G, Y).reshape(Cn, G.shape[1], P, T // n, n)
    return (F.real ** 2 + F.imag ** 2).mean(-1).transpose(3, 0, 2, 1)


def gemm_floor(xp, nchan, npix, nant, ncol, run, repeat):
    """[(name, precision, seconds)]: cuBLAS' batched fp16 GEMM alone on the direct route's stacked shapes,
    (nchan, 2 npix, 2 nant) . (nchan, 2 nant, ncol), fp32 accumulation, with fp32 and fp16 output --
    what regime B would cost if the |F|^2 sums were free (the issue's floor row); and cuBLAS' int8 GEMM
    with the i8x2 mode's MACs, (nchan, 2 npix, 4 nant) . (nchan, 4 nant, ncol), int32 sums and output."""
    from bf_epic_blocks.imaging import gemm as G
    # operands like the real ones (unit-modulus phases, 4-bit integers): all-ones operands run the
    # tensor cores at a higher clock and flatter the floor
    rng = xp.random.default_rng(0)
    a = xp.cos(rng.uniform(0, 6.3, (nchan, 2 * npix, 2 * nant), dtype=xp.float32)).astype(xp.float16)
    b = rng.integers(-8, 8, (nchan, 2 * nant, ncol)).astype(xp.float16)
    out = []
    for name, dt, ot in (("floor-f32", xp.float32, G._CUDA_R_32F), ("floor-f16", xp.float16, G._CUDA_R_16F)):
        c = xp.empty((nchan, 2 * npix, ncol), dt)
        t, _ = run(lambda: G._gemm_ex(a, b, c, G._CUDA_R_16F, ot, G._COMPUTE["fp32"], np.float32, 0), repeat)
        out.append((name, "fp16", t))
        del c
    # pixels and antennas padded to 64 as the fused kernel pads them (cuBLAS' int8 kernels want m a multiple
    # of 16: 2 x 3,205 rows take a slower one, 3.1x the time on an H200)
    m, k = 2 * (-(-npix // 64) * 64), 4 * (-(-nant // 64) * 64)
    out.append(("floor-i8x2", "i8", int8_floor(xp, nchan, m, k, ncol, run, repeat)))
    return out


def int8_floor(xp, batch, m, k, ncol, run, repeat):
    """Seconds of cuBLAS' batched int8 GEMM, row-major (batch, m, k) . (batch, ncol, k)^T -> int32 (batch, ncol,
    m), as cuBLAS' column-major C (m x n) = A^T B with both operands K-contiguous (the layout its int8 kernels
    take); operands like the real ones (an operator in -127..127, 4-bit samples)."""
    from bf_epic_blocks.imaging import gemm as G
    rng = xp.random.default_rng(0)
    a8 = rng.integers(-127, 128, (batch, m, k), dtype=xp.int8)
    b8 = rng.integers(-8, 8, (batch, ncol, k), dtype=xp.int8)
    c8 = xp.empty((batch, ncol, m), xp.int32)
    one, zero = np.array(1, np.int32), np.array(0, np.int32)
    args = (G._OP_T, G._OP_N, m, ncol, k, one.ctypes.data, a8.data.ptr, G._CUDA_R_8I, k, m * k, b8.data.ptr,
            G._CUDA_R_8I, k, ncol * k, zero.ctypes.data, c8.data.ptr, G._CUDA_R_32I, m, m * ncol, batch,
            G._COMPUTE_32I, G._GEMM_DEFAULT)
    t, _ = run(lambda: G._call_gemm(args), repeat)
    return t


def hard_scenes():
    """Two small scenes that stress precision: (name, xyz, freq, X complex, lm)."""
    rng = np.random.default_rng(11)
    xyz = np.concatenate([rng.normal(0, 30, (63, 3)) * [1, 1, 0.05], [[4000.0, -3000.0, 12.0]]])
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    r = math.sqrt(1 - 1e-8)                                           # n = 1e-4
    lm = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang)], 1), imaging.lm_grid(16).lm])
    T = 256
    noise = (rng.normal(size=(T, 1, 64, 2)) + 1j * rng.normal(size=(T, 1, 64, 2))) / math.sqrt(2)
    out = []
    for name, l, m, amp in (("5 km, 88 MHz, n=1e-4 pixels", 0.7, -0.7141, 3.0), ("60 dB point source", 0.2, 0.3, 1e3)):
        nn = math.sqrt(1 - l * l - m * m)
        ph = np.exp(2j * np.pi * 88e6 / C * (xyz @ [l, m, nn]))
        s = amp * np.exp(2j * np.pi * rng.random((T, 1, 1, 2)))
        out.append((name, xyz, np.array([88e6]), (noise + s * ph[None, None, :, None]).astype(np.complex64), lm))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "gpu"], default="cpu")
    ap.add_argument("--nchan", type=int, default=None, help="channels (default: 1 on cpu, 16 on gpu)")
    ap.add_argument("--npol", type=int, default=None, help="pols (default: 1 on cpu, 2 on gpu)")
    ap.add_argument("--ntime", type=int, default=1024)
    ap.add_argument("--grids", type=int, nargs="+", default=None, help="grid sizes (default 64 128 256 on gpu)")
    ap.add_argument("--repeat", type=int, default=None)
    ap.add_argument("--precisions", nargs="+", default=None, help="precisions to time (default: every one available)")
    ap.add_argument("--nref", type=int, default=200, help="pixels in the float64 reference subset")
    ap.add_argument("--previous", default=None, help="folder holding the previous release as package bf_epic_prev")
    ap.add_argument("--table", action="store_true", help="rewrite the package's measured.json from this run")
    ap.add_argument("--ducc", action="store_true", help="CPU: add ducc0's covariance w-gridding route")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    xp = array_module(a.device)
    gpu = a.device == "gpu"
    nchan = a.nchan or (16 if gpu else 1)
    npol = a.npol or (2 if gpu else 1)
    repeat = a.repeat or (20 if gpu else 5)
    grids = a.grids or ([64, 128, 256] if gpu else [64])
    precisions = [p for p in PRECISIONS if precision_available(p, xp) and (a.precisions is None or p in a.precisions)]
    prev = None
    if a.previous:
        import_package(a.previous, "bf_epic_prev")
        import bf_epic_prev.imaging as prev
    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(nchan)
    Q = quantise4(sky_efield(xyz, freq, a.ntime, npol=npol, dtype=np.complex128))   # int8 (T, C, A, P, 2)
    Xc = pairs_to_complex(Q)
    run = timer(a.device)
    rows = []
    rng = np.random.default_rng(0)
    Qd, Xd, xyzd, fd = xp.asarray(Q), xp.asarray(Xc), xp.asarray(xyz), xp.asarray(freq)
    print(f"# bench_dft: device={a.device} nant={len(xyz)} ({layout}) ntime={a.ntime} nchan={nchan} npol={npol} "
          f"4-bit sky+noise; {machine(a.device)['hardware']}")
    print(f"{'grid':>4} {'regime':<8} {'route':<10} {'precision':<8} {'input':<5} {'ms/gulp':>9} {'rel err':>9} "
          f"{'vs naive':>8} {'vs prev':>8} calls")

    def row(grid, regime, route, precision, inp, t, err, base=None, prevt=None, **kw):
        r = {"grid": grid, "regime": regime, "route": route, "precision": precision, "input": inp,
             "gulp_s": t, "rel_err": err, "realtime_factor": a.ntime * 40e-6 / t, **kw}
        r["speedup_vs_naive"] = base / t if base else None
        r["speedup_vs_previous"] = prevt / t if prevt else None
        rows.append(r)
        sn = f"{base / t:8.2f}" if base else f"{'':8}"
        sp = f"{prevt / t:8.2f}" if prevt else f"{'':8}"
        mode = {True: "graph", False: "eager"}.get(kw.get("graphs"), "")
        print(f"{grid:>4} {regime:<8} {route:<10} {precision:<8} {inp:<5} {t * 1e3:9.3f} {err:9.1e} {sn} {sp} {mode}",
              flush=True)

    def rel(got, ref):
        got = imaging._xp.to_numpy(got)
        return float(np.max(np.abs(got - ref)) / np.max(np.abs(ref)))

    def graph_kw(op, inp, route):
        # replayed as CUDA graphs: integer voltages on either route, complex ones on the covariance route
        return {"graphs": True} if gpu and op.graphs is not None and (inp == "ci4" or route == "covariance") else {}

    eager_ops = {}

    def op_eager(precision):
        """The same operator with CUDA graphs off (one per precision and grid, made once)."""
        key = (precision, int(lmd.shape[0]))
        if key not in eager_ops:
            eager_ops.clear()
            eager_ops[key] = imaging.DFTOperator(xyzd, fd, lmd, npol=npol, precision=precision, graphs=False)
        return eager_ops[key]

    for grid_n in grids:
        grid = imaging.lm_grid(grid_n)
        # reference pixels: random ones plus the brightest (found with a quick fp32 image; only the
        # choice of where to look uses the package, the reference values are independent), so the
        # error is relative to the true image peak on every grid
        sub = rng.choice(grid.npix, size=min(a.nref, grid.npix), replace=False)
        quick = imaging._xp.to_numpy(imaging.DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(grid.lm),
                                                         npol=npol).image(Xd[:128]))
        sub = np.unique(np.concatenate([sub, np.argsort(quick.max(axis=(0, 1)))[-20:]]))
        blocks = ((0, 0), (1, 1)) if npol == 2 else ((0, 0),)
        ref1 = reference_image(Q, xyz, freq, grid.lm[sub], blocks)
        lmd = xp.asarray(grid.lm)
        subd = xp.asarray(sub)
        big = grid_n >= 256
        # -------- baselines in the same run
        G = imaging.geometric_operator(xyzd, fd, lmd, "fp32") / len(xyz)
        t_naive_cov, img = run(lambda: naive_covariance(xp, G, Xd), repeat)
        row(grid_n, "gulp", "naive-cov", "fp32", "cf32", t_naive_cov, rel(img[:, :, sub], ref1))
        t_prev = None
        if prev is not None:
            pop = prev.DFTOperator(xyzd, fd, lmd, npol=npol, precision="fp32")
            t_prev, img = run(lambda: pop.image(Xd, method="auto"), repeat)
            row(grid_n, "gulp", "previous", "fp32", "cf32", t_prev, rel(img[:, :, sub], ref1), base=t_naive_cov)
        # -------- one image per gulp
        for precision in precisions:
            if big and precision in ("fp64",):
                continue
            op = imaging.DFTOperator(xyzd, fd, lmd, npol=npol, precision=precision)
            for route in ("covariance", "direct"):
                if (big and route == "direct") or (precision in FUSED and route == "covariance"):
                    continue
                for inp, X in (("ci4", Qd), ("cf32", Xd)):
                    if route == "direct" and inp == "cf32":
                        continue
                    cm = nchan * cost.route_cmacs(a.ntime, len(xyz), grid.npix, npol, npol)[route]
                    t, img = run(lambda: op.image(X, method=route), repeat)
                    row(grid_n, "gulp", route, precision, inp, t, rel(img[:, :, subd], ref1),
                        base=t_naive_cov, prevt=t_prev, cmacs=cm, **graph_kw(op, inp, route))
                    if graph_kw(op, inp, route) and not big:    # the same without CUDA graphs (host-bound?)
                        t, img = run(lambda: op_eager(precision).image(X, method=route), repeat)
                        row(grid_n, "gulp", route, precision, inp, t, rel(img[:, :, subd], ref1),
                            base=t_naive_cov, prevt=t_prev, cmacs=cm, graphs=False)
            del op
            release(xp)
        if grid_n != 64:
            continue
        # -------- one image per 16 samples (64 per gulp)
        n = 16
        refn = reference_image(Q, xyz, freq, grid.lm[sub], blocks, accumulate=n)
        t_naive_dir, img = run(lambda: naive_direct(xp, G, Xd, n), repeat)
        row(grid_n, "x64", "naive-dir", "fp32", "cf32", t_naive_dir, rel(img[..., sub], refn))
        if gpu:   # the floor: cuBLAS' fp16 GEMM alone for the same shapes, the field written and nothing else
            for name, prec, t in gemm_floor(xp, nchan, grid.npix, len(xyz), npol * a.ntime, run, repeat):
                row(grid_n, "x64", name, prec, "ci4", t, float("nan"), base=t_naive_dir)
        t_prev64 = None
        if prev is not None:
            pop = prev.DFTOperator(xyzd, fd, lmd, npol=npol, precision="fp32")

            def prev64():
                return [pop.image(Xd[i * n:(i + 1) * n], method="auto") for i in range(a.ntime // n)]
            t_prev64, imgs = run(prev64, max(3, repeat // 4))
            img = xp.stack(imgs)
            row(grid_n, "x64", "previous", "fp32", "cf32", t_prev64, rel(img[..., sub], refn), base=t_naive_dir)
        for precision in precisions:
            op = imaging.DFTOperator(xyzd, fd, lmd, npol=npol, precision=precision)
            cm = nchan * cost.route_cmacs(a.ntime, len(xyz), grid.npix, npol, npol)["direct"]
            t, img = run(lambda: op.image(Qd, method="direct", accumulate=n), repeat)
            row(grid_n, "x64", "direct", precision, "ci4", t, rel(img[..., subd], refn), base=t_naive_dir,
                prevt=t_prev64, cmacs=cm, **graph_kw(op, "ci4", "direct"))
            if gpu:
                t, img = run(lambda: op_eager(precision).image(Qd, method="direct", accumulate=n), repeat)
                row(grid_n, "x64", "direct", precision, "ci4", t, rel(img[..., subd], refn), base=t_naive_dir,
                    prevt=t_prev64, cmacs=cm, graphs=False)
            del op
            release(xp)
        del G
    if a.ducc and not gpu:
        from bf_epic_blocks.imaging.wstack import cov_wgrid_image
        grid = imaging.lm_grid(64)
        sub = rng.choice(grid.npix, size=min(a.nref, grid.npix), replace=False)
        ref1 = reference_image(Q, xyz, freq, grid.lm[sub], ((0, 0),))
        for eps in (1e-4, 1e-6):
            t, img = run(lambda: cov_wgrid_image(Xc, xyz, freq, grid, epsilon=eps, backend="ducc0"), repeat)
            row(64, "gulp", f"ducc0 {eps:.0e}", "fp64" if eps < 1e-5 else "fp32", "cf32", t, rel(img[:, :, sub], ref1))

    # -------- hard scenes, for the bounds
    hard = []
    for name, hxyz, hf, hX, hlm in hard_scenes():
        href = reference_image(hX, hxyz, hf, hlm, ((0, 0), (1, 1)))
        # the integer modes take 4-bit voltages only: the same scene quantised, against its own reference
        hQ = quantise4(hX)
        qref = reference_image(hQ, hxyz, hf, hlm, ((0, 0), (1, 1)))
        for precision in precisions:
            op = imaging.DFTOperator(xp.asarray(hxyz), xp.asarray(hf), xp.asarray(hlm), npol=2, precision=precision)
            for route in ("direct", "covariance"):
                if precision in FUSED:
                    if route == "direct":
                        hard.append({"scene": name + " (4-bit)", "route": route, "precision": precision,
                                     "rel_err": rel(op.image(xp.asarray(hQ), method=route), qref)})
                    continue
                err = rel(op.image(xp.asarray(hX), method=route), href)
                hard.append({"scene": name, "route": route, "precision": precision, "rel_err": err})
    print("# hard scenes: worst error per route x precision")
    for precision in precisions:
        for route in ("direct", "covariance"):
            es = [h["rel_err"] for h in hard if h["route"] == route and h["precision"] == precision]
            if es:
                print(f"#   {route:<10} {precision:<8} {max(es):.1e}")

    out = {"benchmark": "bench_dft", "date": utc_now(), "machine": machine(a.device), "device": a.device,
           "precisions": precisions,
           "case": {"nant": len(xyz), "layout": layout, "ntime": a.ntime, "nchan": nchan, "npol": npol,
                    "grids": grids, "data": "sky + noise, 4-bit"}, "rows": rows, "hard_scenes": hard}
    if a.json:
        write_json(a.json, out)
    if a.table:
        write_table(out, a.device)
    return out


def _round_up(x):
    """x rounded up to one significant digit (3.2e-5 -> 4e-5)."""
    if x <= 0:
        return 1e-16
    e = math.floor(math.log10(x))
    return float(f"{math.ceil(x / 10 ** e)}e{e}")


def write_table(result, device):
    """Replace ``device``'s rows of the package's measured.json with this run's bounds and rates: the rows of
    the precisions it timed (``--precisions``; all of them by default), the others kept as they are."""
    table = json.loads(plan.TABLE_PATH.read_text())
    timed = result.get("precisions", PRECISIONS)
    keep = [r for r in table["rows"] if r["device"] != device or r["precision"] not in timed]
    new = []
    for precision in timed:
        for route in ("direct", "covariance"):
            case = [r for r in result["rows"] if r["route"] == route and r["precision"] == precision
                    and r["grid"] == 64 and r["regime"] == "gulp"]
            if not case:
                continue
            errs = [r["rel_err"] for r in result["rows"] if r["route"] == route and r["precision"] == precision]
            errs += [h["rel_err"] for h in result["hard_scenes"] if h["route"] == route and h["precision"] == precision]
            best = min(case, key=lambda r: r["gulp_s"])
            new.append({"device": device, "method": route, "precision": precision,
                        **({"input": "ci4"} if precision in FUSED else {}),
                        "bound": max(_round_up(3 * max(errs)), 1e-11),
                        "rate_cmac_s": float(f"{best['cmacs'] / best['gulp_s']:.3g}"),
                        "measured": f"{result['machine'].get('gpu', result['machine']['cpu'])}, "
                                    f"{result['date'][:10]}"})
    table["rows"] = keep + new
    table["note"] = ("bounds = 3 x worst error measured (case P 4-bit sky, 5 km horizon, 60 dB; the integer modes: "
                     "those scenes quantised to 4 bits); rates on case P")
    plan.TABLE_PATH.write_text(json.dumps(table, indent=1) + "\n")
    print(f"# rewrote {plan.TABLE_PATH} ({len(new)} {device} rows)")


if __name__ == "__main__":
    main()
