"""Calibration from the sky, measured as an operator runs it: `bf-epic calibrate` and `bf-epic run` with
`calibration.solve`, against truth the simulator chose.

Cases (``--case``, repeatable; default all but ``cost`` on a CPU):

* ``accuracy`` -- simulated LWA-SV (``pipelines/lwasv_sim_calibrate.yaml``): per-input gains with
  25% amplitude scatter, delays of tens of ns and random phases, deaf and noisy inputs, the Galactic
  plane the model lacks. ``bf-epic calibrate`` solves from ``--seconds`` (<= 2) of 12 channels. Printed:
  the residual gain error against the simulator's gains (the unobservable per-channel phase and
  scale removed), deaf/noisy inputs flagged, good inputs flagged, and the image error (max over
  pixels and channels of |image - truth| / peak of truth) of the corrupted data imaged with the table
  and without it. Truth: the same sky with unit gains, not quantised (so in Jy), imaged with the same
  flags.
* ``drift`` -- the gains drift by 10% and 20 degrees over ``--drift-s`` (600) seconds; live solving
  every 10 s from 1 s (`calibration.solve`) against one solution from the first second applied
  throughout. Printed: the image error of each run, worst and mean over the images after the first
  solution.
* ``cost`` -- (GPU) the whole band (784 channels), `pipelines/lwasv_sim_wholeband.yaml` without its
  search and cube: the solver's seconds (summing covariances + solving) against the imager's, a
  solution every 10 s from 1 s of data; and the same run without solving (the imager's own route).
* ``png`` -- the gain table's whole-band PNG: how long the solver's thread is held drawing it, and
  handing it to the helper process instead.
* ``real`` -- the real LWA-NA TBX and TBF captures (one time sample each) calibrated against the Sun
  and the A-team: the images' peak-to-rms (and peak over the median absolute deviation) before and after.

usage: python tools/bench/bench_calibration.py [--device cpu|gpu] [--case accuracy ...] [--json PATH]
"""
from __future__ import annotations

import argparse
import glob
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchlib import REPO, bf_epic_command, child_env, machine, utc_now, write_json

YAML = REPO / "pipelines" / "lwasv_sim_calibrate.yaml"


def cli(*args, check=True):
    """Run ``bf-epic ARGS`` as a user would; returns (seconds, the summary JSON or None)."""
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as fh:
        summ = fh.name
    cmd = bf_epic_command() + list(args) + ["--no-progress", "--summary-json", summ, "-q"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=child_env(), capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if check and r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}")
    try:
        return dt, json.loads(Path(summ).read_text())
    except (OSError, ValueError):
        return dt, None


def sets(d):
    out = []
    for k, v in d.items():
        out += ["--set", f"{k}={json.dumps(v) if not isinstance(v, str) else v}"]
    return out


def fits_images(folder):
    """(nimage, nchan, N, N) float64 of a run's FITS images, in time order (NaN below the horizon)."""
    from astropy.io import fits
    files = sorted(glob.glob(str(Path(folder) / "*_i[0-9][0-9][0-9][0-9].fits")))
    if not files:
        raise RuntimeError(f"no FITS images in {folder}")
    return np.stack([np.asarray(fits.getdata(f), np.float64).reshape((-1,) + fits.getdata(f).shape[-2:])
                     for f in files])


def image_errors(img, ref):
    """Per image: max over channels and pixels of |img - ref| / max |ref| (finite pixels)."""
    out = []
    for a, b in zip(img, ref):
        ok = np.isfinite(a) & np.isfinite(b)
        out.append(float(np.max(np.abs(a[ok] - b[ok])) / np.max(np.abs(b[ok]))))
    return np.array(out)


def flags_override(flags, stand_ids):
    """station.flags entries for the inputs flagged (bool (nstand, npol))."""
    return [{"stand": int(stand_ids[a]), "pol": "XY"[p]} for a, p in zip(*np.nonzero(flags))]


def truth_of(yaml, overrides):
    """(GainCorruption, config) of a simulated pipeline."""
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.sky.corrupt import GainCorruption
    cfg = load_config(str(yaml), overrides)
    return GainCorruption.from_config(cfg["source"]["corrupt"], seed=cfg["source"]["seed"]), cfg


NEUTRAL = {"source.corrupt.amplitude_rms": 0.0, "source.corrupt.delay_ns_rms": 0.0,
           "source.corrupt.random_phase": False, "source.corrupt.drift.amplitude_frac": 0.0,
           "source.corrupt.drift.phase_deg": 0.0}


def case_accuracy(args, work):
    from bf_epic_blocks.imaging.skycal import gain_error
    from bf_epic_blocks.io.gaintable import read_solved_table
    from bf_epic_blocks.pipeline.runner import channel_freqs
    from bf_epic_blocks.station.tables import load_station
    # the exact diffuse sky needs a column per antenna (nmode 256), past the GPU simulator's 96: the
    # simulated source runs on the CPU
    base = {"device": args.acc_device, "source.duration_s": args.seconds, "source.diffuse.nmode": args.nmode,
            "imager.accumulate_frames": int(round(args.seconds * 25000))}
    table = work / "acc_table.npz"
    t_cal, s_cal = cli("calibrate", str(YAML), "-o", str(table), *sets(base),
                       *sets({"calibration.solve.integration_s": args.seconds,
                              "calibration.solve.cadence_s": args.seconds}))
    t = read_solved_table(table)
    corr, flags, reasons = t["gains"][0], t["flags"][0], t["flag_reason"][0]
    gc, cfg = truth_of(YAML, sets(base)[1::2])
    st = load_station(cfg["station"]["name"])
    f = channel_freqs(cfg)
    u = ~st.flags
    g_true = gc.gains(st.nstand, 2, f, 0.5 * args.seconds, usable=u)
    deaf, noisy = gc.deaf_mask(st.nstand, 2, usable=u), gc.noisy_mask(st.nstand, 2, usable=u)
    good_true = ~st.flags & ~deaf & ~noisy
    err, per = gain_error(corr, g_true, ~flags)
    row = {"seconds": args.seconds, "nchan": int(f.size), "calibrate_wall_s": t_cal,
           "gain_error_rms": err, "gain_error_max": float(per[~flags].max()),
           "deaf": int(deaf.sum()), "deaf_flagged": int((flags & deaf).sum()),
           "noisy": int(noisy.sum()), "noisy_flagged": int((flags & noisy).sum()),
           "good_inputs": int(good_true.sum()), "good_flagged": int((flags & good_true).sum()),
           "reasons": {r: int((reasons == r).sum()) for r in set(reasons.ravel()) if r}}
    fl = flags_override(flags & ~st.flags, st.stand_ids)
    out = {}
    for name, extra in (("calibrated", {"calibration.gains_table": str(table), "calibration.solve": None}),
                        ("uncalibrated", {"source.quantize": False, "calibration.solve": None}),
                        ("truth", {**NEUTRAL, "source.quantize": False, "calibration.solve": None})):
        d = work / f"acc_{name}"
        cli("run", str(YAML), *sets({**base, **extra, "output.dir": str(d), "output.png": name != "truth",
                                     "station.flags": fl}))
        out[name] = fits_images(d)
    row["image_error_calibrated"] = float(image_errors(out["calibrated"], out["truth"]).max())
    row["image_error_uncalibrated"] = float(image_errors(out["uncalibrated"], out["truth"]).max())
    print(f"accuracy: {args.seconds:g} s of {f.size} channels; gain error {err:.4f} rms (worst input "
          f"{row['gain_error_max']:.4f}); deaf {row['deaf_flagged']}/{row['deaf']} and noisy "
          f"{row['noisy_flagged']}/{row['noisy']} flagged, good inputs flagged {row['good_flagged']}/"
          f"{row['good_inputs']}; image error with the table {row['image_error_calibrated']:.4f} of the peak, "
          f"without {row['image_error_uncalibrated']:.3f}; calibrate {t_cal:.1f} s")
    return row


def case_drift(args, work):
    dur = args.drift_s
    # no diffuse sky here: the GPU simulator holds 96 columns, too few for it exactly (see accuracy)
    base = {"device": args.device, "source.duration_s": dur, "imager.accumulate_frames": 25000,
            "source.corrupt.drift.amplitude_frac": 0.10, "source.corrupt.drift.phase_deg": 20.0,
            "source.corrupt.drift.over_s": dur, "output.png": False, "source.diffuse": None,
            "calibration.solve.diffuse": False}
    live = work / "drift_live"
    t_live, s_live = cli("run", str(YAML), *sets({**base, "output.dir": str(live),
                                                   "calibration.solve.cadence_s": 10.0,
                                                   "calibration.solve.integration_s": 1.0}))
    from bf_epic_blocks.io.gaintable import read_solved_table
    from bf_epic_blocks.station.tables import load_station
    tl = read_solved_table(next(live.glob("*_gains.npz")))
    one = work / "drift_one.npz"
    cli("calibrate", str(YAML), "-o", str(one), *sets({**base, "source.duration_s": 1.0,
                                                         "imager.accumulate_frames": 25000,
                                                         "calibration.solve.integration_s": 1.0}))
    t1 = read_solved_table(one)
    st = load_station("lwasv")
    flags = np.any(tl["flags"], axis=0) | t1["flags"][0]
    fl = flags_override(flags & ~st.flags, st.stand_ids)
    single, truth = work / "drift_single", work / "drift_truth"
    cli("run", str(YAML), *sets({**base, "output.dir": str(single), "calibration.gains_table": str(one),
                                 "station.flags": fl, "calibration.solve": None}))
    cli("run", str(YAML), *sets({**base, **NEUTRAL, "source.quantize": False, "output.dir": str(truth),
                                 "station.flags": fl, "calibration.solve": None}))
    ref = fits_images(truth)
    # the images before the first live solution applies are uncalibrated: left out of both series
    from bf_epic_blocks.conventions import FS_HZ
    from bf_epic_blocks.sky.catalogue import as_time
    tag0 = int(round(as_time(str(truth_of(YAML, [])[1]["source"]["start"])).unix * FS_HZ))
    first = int(np.ceil((int(tl["valid_from"][0]) - tag0) / (FS_HZ / 25000) / 25000))
    e_live = image_errors(fits_images(live), ref)[first:]
    e_one = image_errors(fits_images(single), ref)[first:]
    row = {"seconds": dur, "solutions": int(len(tl["valid_from"])), "live_wall_s": t_live, "images_left_out": first,
           "live_error_max": float(e_live.max()), "live_error_mean": float(e_live.mean()),
           "single_error_max": float(e_one.max()), "single_error_last": float(e_one[-1]),
           "live_error_series": np.round(e_live, 5).tolist(), "single_error_series": np.round(e_one, 5).tolist(),
           "solver": (s_live or {}).get("solver")}
    print(f"drift over {dur:g} s: live ({row['solutions']} solutions) image error max {row['live_error_max']:.4f} "
          f"(mean {row['live_error_mean']:.4f}); one solution at the start: max {row['single_error_max']:.4f}, "
          f"at the end {row['single_error_last']:.4f}")
    return row


def case_cost(args, work):
    """The solver beside the whole-band imager. Each configuration runs for ``--cost-short-s`` and ``--cost-s``
    seconds of data; the difference of the two pipelines' walls over the difference of data is the steady
    time per second of data, free of start-up (kernel compiles, the solver's warm-up, the first solution).
    A run with solving goes first and is thrown away, so that every measured run finds its kernels compiled."""
    yaml = REPO / "pipelines" / "lwasv_sim_wholeband.yaml"
    base = {"device": "gpu", "imager.search": None, "output.cube": None,
            "output.fits": False, "output.png": False, "output.integrate": None}
    solve = {"calibration.solve.cadence_s": 10.0, "calibration.solve.integration_s": 1.0}
    alone_name, both_name = "imager alone (folded, integer route)", "imager + solver"
    cli("run", str(yaml), *sets({**base, **solve, "source.duration_s": args.cost_short_s,
                                 "output.dir": str(work / "cost")}))          # compiles every kernel
    rows = {}
    for name, extra in ((alone_name, {}), (both_name, solve)):
        r = {}
        for tag, dur in (("short", args.cost_short_s), ("long", args.cost_s)):
            wall, summ = cli("run", str(yaml), *sets({**base, **extra, "source.duration_s": dur,
                                                      "output.dir": str(work / "cost")}))
            img = next(v for k, v in summ["blocks"].items() if "Imager" in k)
            r[tag] = {"data_s": dur, "pipeline_s": summ["wall_s"], "imager_s": img["process_s"],
                      "first_image_s": img["first_data_s"], "realtime_factor": dur / summ["wall_s"]}
            r[tag]["operator"] = summ.get("operator")
            if "solver" in summ:
                sv = summ["solver"]
                r[tag]["solver"] = {k: sv.get(k) for k in ("solutions", "failures", "sum_s", "solve_s", "wait_s",
                                                           "sum_s_each", "solve_s_each", "warm_s")}
        r["steady_s_per_data_s"] = (r["long"]["pipeline_s"] - r["short"]["pipeline_s"]) / (args.cost_s - args.cost_short_s)
        r["steady_realtime_factor"] = 1.0 / r["steady_s_per_data_s"]
        rows[name] = r
    both, alone = rows[both_name], rows[alone_name]
    both["steady_added_fraction"] = both["steady_s_per_data_s"] / alone["steady_s_per_data_s"] - 1.0
    sv = both["long"]["solver"]
    steady = [a + b for a, b in zip(sv["sum_s_each"][1:], sv["solve_s_each"][1:])]
    both["solver_s_per_solution_median"] = float(np.median(steady)) if steady else None
    for name, r in rows.items():
        print(f"cost, 784 channels, {name}: {r['short']['data_s']:g} s of data in {r['short']['pipeline_s']:.2f} s, "
              f"{r['long']['data_s']:g} s in {r['long']['pipeline_s']:.2f} s: steady {r['steady_s_per_data_s']:.4f} s "
              f"per s of data (x{r['steady_realtime_factor']:.3f} real time); first image at "
              f"{r['long']['first_image_s']:.1f} s")
    print(f"cost, steady: solving live (a solution every 10 s from 1 s of data) adds "
          f"{100 * both['steady_added_fraction']:.1f}% to the pipeline's time per second of data; the solver's "
          f"own seconds per solution (sums + solve, GPU shared with the imager): {sv['sum_s_each']} + "
          f"{sv['solve_s_each']}; warm-up {sv.get('warm_s')}; the imager's operator: {both['long'].get('operator')}")
    return rows


def _stage_timers(xp, names):
    """Wrap ``skycal``'s stage functions so each call is timed between two device synchronisations
    (a profile: the waits change the total, so the solves' walls are measured without these wrappers).
    Returns (seconds per stage, calls per stage, undo)."""
    from benchlib import synchronize
    from bf_epic_blocks.imaging import skycal
    spent, calls, saved = {n: 0.0 for n in names}, {n: 0 for n in names}, {}
    for n in names:
        fn = saved[n] = getattr(skycal, n)

        def timed(*a, _fn=fn, _n=n, **k):
            synchronize(xp)
            t0 = time.perf_counter()
            out = _fn(*a, **k)
            synchronize(xp)
            spent[_n] += time.perf_counter() - t0
            calls[_n] += 1
            return out
        setattr(skycal, n, timed)

    def undo():
        for n, fn in saved.items():
            setattr(skycal, n, fn)
    return spent, calls, undo


def case_solver(args, work):
    """The solver's two parts alone on an idle device, at the whole band: summing the covariances of 1 s of
    4-bit data (25 gulps of 1,024 frames x 784 channels x 256 stands x 2 pols) and solves: a cold one (no
    start, no diffuse term) and a live solver's steady state (the analytic Galactic sky fitted with its
    scale, each solve started from the last solution with its flags carried, the gains drifting between
    solves), with the live solve's time by stage."""
    import math

    from astropy.time import Time

    from benchlib import array_module, synchronize
    from bf_epic_blocks.imaging import skycal
    from bf_epic_blocks.sky.model import diffuse_model
    from bf_epic_blocks.station.tables import load_station
    xp = array_module(args.device)
    st = load_station("lwasv")
    nchan = args.nchan
    f = 74e6 + 25e3 * np.arange(nchan)
    rng = np.random.default_rng(0)
    gulp = xp.asarray(rng.integers(0, 256, (1024, nchan, st.nstand, 2), dtype=np.uint8))
    sums = skycal.CovarianceSums(nchan, st.nstand, 2, xp)
    sums.add(gulp[:64], ci4=True)                                         # warm-up (kernel compilation)
    sums.reset()
    synchronize(xp)
    ngulp = int(math.ceil(args.solver_frames / 1024))
    t0 = time.perf_counter()
    for _ in range(ngulp):
        sums.add(gulp, ci4=True)
    synchronize(xp)
    t_sum = time.perf_counter() - t0
    # the integer GEMMs alone, the same calls on rows already laid out: what the sums' other part (the
    # rows' layout from the 4-bit bytes) costs is the difference
    from bf_epic_blocks.imaging.gemm import int_gram
    rows = xp.asarray(rng.integers(-8, 8, (min(sums.chunk, nchan), 2 * st.nstand, 1024), dtype=np.int8))
    G = xp.zeros((rows.shape[0], 2 * st.nstand, 2 * st.nstand), xp.int32 if xp is not np else np.float64)
    ncall = ngulp * 2 * (-(-nchan // sums.chunk))
    int_gram(rows, out=G)
    synchronize(xp)
    t0 = time.perf_counter()
    for _ in range(ncall):
        int_gram(rows, out=G, accumulate=True)
    synchronize(xp)
    t_gemm = time.perf_counter() - t0
    lmn = np.array([[0.10, 0.15, math.sqrt(1 - 0.0325)], [-0.30, 0.50, math.sqrt(1 - 0.34)]])
    flux = np.full((nchan, 2, 2), 8500.0)
    cdt = np.complex128 if xp is np else xp.complex64
    M = skycal.model_covariance(st.xyz_m, f, lmn, flux, xp=xp, dtype=cdt)
    amp = np.exp(0.25 * rng.standard_normal((st.nstand, 2)))
    g = amp * np.exp(1j * rng.uniform(0, 2 * np.pi, (st.nstand, 2)))

    def corrupt(gains, model):
        G = xp.asarray(np.broadcast_to(gains.T[None], (nchan, 2, st.nstand)).astype(cdt))
        R = G[..., :, None] * xp.conj(G[..., None, :]) * model
        R[..., idx, idx] += 1000.0
        return R
    idx = xp.arange(st.nstand)
    R = corrupt(g, M)
    W = skycal.baseline_weights(st.xyz_m, f, 4.0, xp=xp)
    times = []
    for rep in range(3):
        synchronize(xp)
        t0 = time.perf_counter()
        sol = skycal.solve_gains(R, M, st.xyz_m, f, st.flags, weights=W)
        synchronize(xp)
        times.append(time.perf_counter() - t0)
    row = {"nchan": nchan, "frames": ngulp * 1024, "sum_s": t_sum, "sum_gemm_s": t_gemm, "solve_s": float(np.median(times)),
           "solve_first_s": times[0], "iterations": sol.info["iterations"], "summary": sol.summary()}
    print(f"solver, {nchan} channels: covariance sums of {ngulp * 1024} frames {t_sum:.3f} s (of which the "
          f"integer GEMMs alone {t_gemm:.3f} s, {ncall} calls); one solve "
          f"{row['solve_s']:.3f} s (first {times[0]:.3f} s, {sol.info['iterations']} iterations)")
    # the live solver's steady state
    E = diffuse_model(st.xyz_m, f, Time("2026-06-01T08:00:00", scale="utc"), st.location, pattern="dipole",
                      xp=xp, dtype=cdt)
    scale = float(to_host(xp.median(xp.abs(M[..., idx, idx])) / xp.maximum(xp.median(xp.abs(E[..., idx, idx])), 1e-30)))
    ME = M + (0.7 * scale) * E                                            # the sky: sources + 0.7 x the diffuse term
    last = skycal.solve_gains(corrupt(g, ME), M, st.xyz_m, f, st.flags, weights=W, extra=E)
    live_t, live_it, drifted = [], [], g
    stages = ("stefcal", "fit_scale", "input_health", "reference_phase", "smooth_across_channels")
    for rep in range(4):
        drifted = drifted * (1.003 * np.exp(1j * np.deg2rad(0.3) * rng.standard_normal(g.shape)))
        Rk = corrupt(drifted, ME)
        profile = rep == 3
        if profile:
            spent, calls, undo = _stage_timers(xp, stages)
        synchronize(xp)
        t0 = time.perf_counter()
        try:
            last = skycal.solve_gains(Rk, M, st.xyz_m, f, st.flags, weights=W, extra=E,
                                      g0=last.gains.transpose(0, 2, 1), extra_scale0=last.info["extra_scale"],
                                      flags0=last.reasons)
            synchronize(xp)
        finally:
            if profile:
                undo()
        dt = time.perf_counter() - t0
        if not profile:
            live_t.append(dt)
            live_it.append(last.info["iterations"])
        else:
            profiled = dt
    err = skycal.gain_error(last.corrections, drifted[None].repeat(nchan, 0), ~last.flags)[0]
    row.update(live_solve_s=float(np.median(live_t)), live_solve_each_s=[round(t, 4) for t in live_t],
               live_iterations=live_it, live_gain_error=err, live_summary=last.summary(),
               live_stages_s={n: round(spent[n], 4) for n in stages}, live_stage_calls=calls,
               live_profiled_s=round(profiled, 4))
    print(f"solver, live (diffuse term fitted, warm start, flags carried): one solve {row['live_solve_s']:.3f} s "
          f"(each {row['live_solve_each_s']}, iterations {live_it}); gain error {100 * err:.3f}% rms")
    print("  stages of one live solve, each between synchronisations (total %.3f s): " % profiled
          + ", ".join(f"{n} {spent[n]:.4f} s x{calls[n]}" for n in stages)
          + f"; the rest {profiled - sum(spent.values()):.4f} s")
    return row


def to_host(a):
    return a.get() if hasattr(a, "get") else a


def case_png(args, work):
    """The gain table's PNG at the whole band (784 channels x 256 stands x 2 pols), as the live solver
    draws it about once a minute of data: the seconds its caller (the solver's worker thread) is held,
    drawn in that thread, and handed to the helper process (the first hand-over starts the process)."""
    from bf_epic_blocks.blocks.gain_solver import GainSolverBlock, _draw_gain_png
    rng = np.random.default_rng(1)
    nchan, nant = args.nchan, 256
    g = np.exp(0.2 * rng.standard_normal((1, nchan, nant, 2)) + 1j * rng.uniform(-np.pi, np.pi, (1, nchan, nant, 2)))
    flags = np.zeros((1, nant, 2), bool)
    flags[0, :7, 0] = True
    reasons = np.where(flags, "deaf", "")
    table = {"gains": g, "flags": flags, "flag_reason": reasons, "freq_hz": 74e6 + 25e3 * np.arange(nchan),
             "valid_from": [0], "provenance": {"station": "LWA-SV", "model": {"sources": ["CygA", "CasA"]}}}
    from bf_epic_blocks.blocks._drawing import DrawingHelper
    blk = GainSolverBlock.__new__(GainSolverBlock)          # only its PNG hand-over, no pipeline
    blk.solver_stats = {"pngs": 0, "pngs_in_helper": 0, "pngs_skipped": 0}
    blk._drawing = DrawingHelper("bench")
    row = {"nchan": nchan}
    t0 = time.perf_counter()
    _draw_gain_png(str(work / "here.png"), table, "in this thread")
    row["in_thread_s"] = time.perf_counter() - t0
    held = []
    for k in range(3):
        t0 = time.perf_counter()
        blk._draw_png((str(work / f"helper{k}.png"), table, "in the helper"))
        held.append(time.perf_counter() - t0)
        blk._drawing.wait()
    blk.close()
    row.update(helper_first_s=held[0], helper_s=float(np.median(held[1:])), drawn_in_helper=blk.solver_stats["pngs_in_helper"])
    print(f"png, {nchan} channels: drawn in the caller's thread {row['in_thread_s']:.2f} s; handed to the helper "
          f"process {1e3 * row['helper_s']:.1f} ms (the first, starting the process, {row['helper_first_s']:.2f} s); "
          f"{row['drawn_in_helper']} of 3 drawn there")
    return row


def peak_stats(folder):
    from astropy.io import fits
    out = []
    for f in sorted(glob.glob(str(Path(folder) / "*.fits"))):
        im = np.asarray(fits.getdata(f), np.float64)
        im = im.reshape((-1,) + im.shape[-2:]).mean(axis=0)
        v = im[np.isfinite(im)]
        med = np.median(v)
        mad = 1.4826 * np.median(np.abs(v - med))
        out.append({"file": Path(f).name, "peak_over_rms": float(v.max() / v.std()),
                    "peak_over_mad": float((v.max() - med) / mad)})
    return out


def case_real(args, work):
    rows = {}
    model = {"calibration.solve.sources": ["Sun", "CygA", "CasA", "TauA", "VirA"],
             "calibration.solve.min_samples": 1, "calibration.solve.pattern": "dipole"}
    for name, yaml, extra in (("LWA-NA TBX (312 ch, 52-60 MHz)", "lwana_tbx_allsky.yaml",
                               {"calibration.solve.smooth_channels": 312}),
                              ("LWA-NA TBF (36 ch, 52 MHz)", "lwana_tbf_allsky.yaml",
                               {"source.channel_block": 1, "calibration.solve.smooth_channels": 36})):
        y = REPO / "pipelines" / yaml
        tab = work / f"{yaml}.npz"
        _, s = cli("calibrate", str(y), "-o", str(tab), *sets({**model, **extra}))
        before, after = work / f"{yaml}_before", work / f"{yaml}_after"
        run_extra = {k: v for k, v in extra.items() if not k.startswith("calibration.solve")}
        cli("run", str(y), *sets({**run_extra, "output.dir": str(before)}))
        cli("run", str(y), *sets({**run_extra, "output.dir": str(after), "calibration.gains_table": str(tab)}))
        rows[name] = {"before": peak_stats(before), "after": peak_stats(after), "solve": s.get("last") if s else None}
        b, a = rows[name]["before"][0], rows[name]["after"][0]
        print(f"real, {name}: peak/rms {b['peak_over_rms']:.1f} -> {a['peak_over_rms']:.1f}, peak/MAD "
              f"{b['peak_over_mad']:.1f} -> {a['peak_over_mad']:.1f}; {rows[name]['solve']}")
    return rows


CASES = {"accuracy": case_accuracy, "drift": case_drift, "cost": case_cost, "real": case_real,
         "solver": case_solver, "png": case_png}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    ap.add_argument("--case", action="append", choices=sorted(CASES))
    ap.add_argument("--seconds", type=float, default=2.0, help="accuracy: seconds of data solved from")
    ap.add_argument("--drift-s", type=float, default=600.0, help="drift: seconds simulated")
    ap.add_argument("--cost-s", type=float, default=60.0, help="cost: seconds of the whole band (the long runs)")
    ap.add_argument("--cost-short-s", type=float, default=20.0, help="cost: seconds of the whole band (the short runs)")
    ap.add_argument("--nchan", type=int, default=784, help="solver: channels")
    ap.add_argument("--acc-device", choices=("cpu", "gpu"), default="cpu", help="accuracy: the pipeline's device")
    ap.add_argument("--nmode", type=int, default=256, help="accuracy: the simulated diffuse sky's modes")
    ap.add_argument("--solver-frames", type=int, default=25000, help="solver: frames summed (1 s = 25,000)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None, help="keep the runs' outputs in this folder")
    args = ap.parse_args(argv)
    cases = args.case or [c for c in ("accuracy", "drift", "real") if c != "drift" or args.device == "gpu"]
    work = Path(args.keep or tempfile.mkdtemp(prefix="bench_cal_"))
    work.mkdir(parents=True, exist_ok=True)
    out = {"benchmark": "bench_calibration", "date": utc_now(), "machine": machine(args.device),
           "device": args.device, "cases": {}}
    for c in cases:
        out["cases"][c] = CASES[c](args, work)
    write_json(args.json or str(REPO / "docs" / "bench" / f"bench_calibration_{args.device}.json"), out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
