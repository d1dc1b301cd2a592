"""The GPU check: what a station operator runs, on a machine with a GPU, compared with the CPU.

1. The GPU tests (``pytest -m gpu``).
2. Every shipped pipeline (``pipelines/*.yaml``) whose input exists here, run by ``bf-epic run`` twice:
   ``--set device=gpu`` and ``--set device=cpu``. Their outputs are compared file by file:
   FITS images and pixel tables by max |GPU - CPU| / max |CPU| (<= 1e-5 at fp32), NaN masks equal;
   HDF5 cubes the same, or, stored narrower than float32 (a float16 cube), within one unit in the
   last place of each stored value or, beyond that unit, within one unit at the cube's largest
   value (2^-11 of it: a simulated sky's GPU and CPU voltages differ by ~1e-5 of their rms, and a
   0.64-ms image of 16 samples moves by ~1e-4 when one 4-bit sample lands a step over);
   candidate tables by their candidates (sequence, image, pixel, DM, width) and S/N; PNGs must exist
   on both sides. A UDP pipeline is fed by ``bf-epic replay`` of an LWA-SV TBF capture.
3. ``bf-epic plan pipelines/lwasv_sim_allsky.yaml --set device=gpu`` at tolerances 1e-3, 1e-4, 1e-6.

A table is printed at the end; ``--json`` writes it. Exit status 0 only when every step passed.

usage: python tools/gpu_check.py [--data DIR] [--out DIR] [--json PATH] [--skip-tests]
                                 [--only NAME ...] [--set KEY=VALUE ...] [--pytest-args "..."]

Input files: a YAML's ``source.path`` as written (relative to the YAML), else the same file name in
``--data`` (default ``$BF_EPIC_DATA``, else ``../shared/data/lwa`` beside the repository).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from bench.benchlib import bf_epic_command, write_json

REPO = Path(__file__).resolve().parents[1]
TOL_FP32 = 1e-5
#: images made with gains solved on each side: the GPU solves in complex64 (the CPU in complex128) from
#: voltages ~1e-5 of their rms apart, to StEFCal's 1e-6 convergence test; solutions agree to ~1e-4
TOL_SOLVED = 1e-3
TOLERANCES = ("1e-3", "1e-4", "1e-6")
#: a simulated sky quantised to 4 bits: the GPU's and the CPU's voltages are ~1e-5 of their rms apart
#: before the quantiser, so a sample near a level's edge rounds to neighbouring levels on the two; the
#: (image, channel) values it feeds differ by ~1e-4 to 1e-3 of their scale. A float32 output passes
#: when at most this fraction of its values differ beyond the tolerance, none by more than FLIP_TOL.
FLIP_FRACTION, FLIP_TOL = 0.01, 1e-2
#: fitted DMs (pc cm^-3) of one candidate on the GPU and the CPU: the vertex of a parabola through three
#: S/N values that differ by ~1e-4 on the two
DM_TOL = 1e-3


def data_dir(arg):
    if arg:
        return Path(arg)
    if os.environ.get("BF_EPIC_DATA"):
        return Path(os.environ["BF_EPIC_DATA"])
    return REPO.parent / "shared" / "data" / "lwa"


def gpu_name():
    try:
        import cupy
        return cupy.cuda.runtime.getDeviceProperties(0)["name"].decode()
    except Exception as e:  # noqa: BLE001 - reported, not raised: the check says what is missing
        return f"no GPU ({type(e).__name__}: {e})"


# ------------------------------------------------------------------ comparisons
def _rel(got, ref, dtype):
    """(max |got - ref| / max |ref|, ulps, beyond, problem or None) for two numeric arrays stored as ``dtype``.

    ulps: the largest difference in units in the last place of ``dtype`` at the CPU's value -- the
    measure for outputs stored narrower than float32 (a float16 cube), where one rounding apart is
    all two correct imagers can promise when their inputs are the same. beyond: the largest
    difference less that one unit, over max |ref|: a simulated sky's GPU and CPU voltages differ
    by ~1e-5 of their rms (sky.fastsim), which moves a value near zero by many of its own tiny
    units but the cube by less than one unit at its largest value (``narrow_scale_tol``)."""
    dtype = np.dtype(dtype)
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    if got.shape != ref.shape:
        return float("inf"), float("inf"), float("inf"), f"shapes differ: GPU {got.shape}, CPU {ref.shape}"
    if not np.array_equal(np.isnan(got), np.isnan(ref)):
        return float("inf"), float("inf"), float("inf"), (f"NaN masks differ ({int(np.isnan(got).sum())} vs "
                                            f"{int(np.isnan(ref).sum())})")
    if not np.isfinite(ref).any():
        return 0.0, 0.0, 0.0, None
    diff = np.abs(got - ref)
    scale = np.nanmax(np.abs(ref))
    rel = float(np.nanmax(diff) / scale) if scale > 0 else float(np.nanmax(diff))
    with np.errstate(invalid="ignore"):       # NaN below the horizon: equal masks were checked above
        spacing = np.spacing(np.abs(ref).astype(dtype)).astype(np.float64)
        ulps = float(np.nanmax(diff / np.maximum(spacing, np.finfo(dtype).tiny)))
        beyond = float(np.nanmax(np.maximum(diff - spacing, 0.0)) / scale) if scale > 0 else rel
    return rel, ulps, beyond, None


def _beyond_fraction(got, ref, tol):
    """The fraction of the finite values of ``ref`` that ``got`` misses by more than ``tol`` of max |ref|."""
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    ok = np.isfinite(ref)
    scale = np.max(np.abs(ref[ok]), initial=0.0)
    return float(np.mean(np.abs(got[ok] - ref[ok]) > tol * scale)) if ok.any() and scale > 0 else 0.0


def narrow_scale_tol(dtype):
    """One unit in the last place at a value's own scale, relative to it (2^-11 for float16): what a
    narrow cube cannot resolve in its largest values."""
    return float(np.finfo(np.dtype(dtype)).eps) / 2


def _narrow(dtype):
    """Stored narrower than float32: compared in units in the last place, not to 1e-5."""
    return np.dtype(dtype).kind == "f" and np.dtype(dtype).itemsize < 4


def _fits_arrays(path):
    """{name: (array, dtype)} of a FITS file's images and numeric table columns."""
    from astropy.io import fits
    out = {}
    with fits.open(path) as h:
        for i, hdu in enumerate(h):
            if hdu.data is None:
                continue
            if isinstance(hdu, (fits.BinTableHDU, fits.TableHDU)):
                for name in hdu.columns.names:
                    col = np.asarray(hdu.data[name])
                    if col.dtype.kind in "fiu":
                        out[f"hdu{i}.{name}"] = (col, col.dtype)
            else:
                out[f"hdu{i}"] = (np.asarray(hdu.data), hdu.data.dtype)
    return out


def _h5_arrays(path):
    import h5py
    out = {}

    def take(name, d):           # every numeric dataset, in groups too (the watch file's targets)
        if isinstance(d, h5py.Dataset) and d.dtype.kind in "fiu":
            out[name] = (d[()], d.dtype)

    with h5py.File(path, "r") as f:
        f.visititems(take)
    return out


def _candidates(path):
    """The candidate table (lightcurve left out when the file cannot be read whole)."""
    from astropy.table import Table
    fmt = "ascii.ecsv" if path.suffix == ".ecsv" else "fits"
    try:
        return Table.read(path, format=fmt), None
    except Exception as e:  # noqa: BLE001 - a table that does not read back is reported
        cols = ["sequence", "image", "pixel", "dm", "width", "snr"]
        return Table.read(path, format=fmt, include_names=cols), f"reads back only without lightcurve ({e})"


def compare_candidates(gpu, cpu):
    """Two candidate tables: the same candidates (sequence, image, pixel, DM trial, width), their S/N within
    1e-3, and their fitted DMs within DM_TOL. A table with ``dm_trial`` has ``dm`` fitted between the
    trials (the vertex of the S/N across three of them), which moves with the S/N's last digits; one
    without has the trial as ``dm``."""
    tg, note_g = _candidates(gpu)
    tc, note_c = _candidates(cpu)
    trial = "dm_trial" if "dm_trial" in tg.colnames and "dm_trial" in tc.colnames else "dm"
    key = ("sequence", "image", "pixel", trial, "width")
    kg = {tuple(str(r[k]) for k in key): (float(r["snr"]), float(r["dm"])) for r in tg}
    kc = {tuple(str(r[k]) for k in key): (float(r["snr"]), float(r["dm"])) for r in tc}
    if set(kg) != set(kc):
        return {"ok": False, "rows": [len(tg), len(tc)],
                "problem": f"candidates differ: {len(set(kg) - set(kc))} only on the GPU, "
                           f"{len(set(kc) - set(kg))} only on the CPU ({', '.join(key)}: GPU "
                           f"{sorted(set(kg) - set(kc))[:3]}, CPU {sorted(set(kc) - set(kg))[:3]})"}
    dsnr = max((abs(kg[k][0] - kc[k][0]) / max(abs(kc[k][0]), 1e-30) for k in kc), default=0.0)
    ddm = max((abs(kg[k][1] - kc[k][1]) for k in kc), default=0.0)
    res = {"ok": dsnr <= 1e-3 and ddm <= DM_TOL, "rows": [len(tg), len(tc)], "snr_rel_diff": dsnr,
           "dm_abs_diff": ddm}
    if note_g or note_c:
        res["note"] = note_g or note_c
    return res


def compare_flags(g, c, tol=1e-3):
    """Interference flag tables (``<prefix>_flags.ecsv``): the flagged fraction of each channel within
    ``tol`` (the GPU's and the CPU's thresholds are the same tables; a block at a threshold may fall
    either side of it by a rounding)."""
    from astropy.table import Table
    tg, tc = Table.read(g, format="ascii.ecsv"), Table.read(c, format="ascii.ecsv")
    if len(tg) != len(tc):
        return {"ok": False, "problem": f"{len(tg)} channels on the GPU, {len(tc)} on the CPU"}
    d = float(np.max(np.abs(np.asarray(tg["flagged_fraction"]) - np.asarray(tc["flagged_fraction"])), initial=0.0))
    return {"ok": d <= tol, "kind": "flag table", "max_fraction_diff": d, "allowed": tol}


def compare_dirs(gdir, cdir, tol=TOL_FP32, flips=False):
    """Per-file comparison of two output folders: {relative path: result dict}; images to ``tol``.
    ``flips``: the runs read a quantised simulated sky (FLIP_FRACTION)."""
    files = sorted({p.relative_to(cdir) for p in cdir.rglob("*") if p.is_file()} |
                   {p.relative_to(gdir) for p in gdir.rglob("*") if p.is_file()})
    out = {}
    for rel in files:
        g, c = gdir / rel, cdir / rel
        if not g.exists() or not c.exists():
            out[str(rel)] = {"ok": False, "problem": f"only on the {'CPU' if c.exists() else 'GPU'}"}
            continue
        name = rel.name
        if "candidates" in name and name.endswith((".ecsv", ".fits")):
            out[str(rel)] = compare_candidates(g, c)
            continue
        if name.endswith("_flags.ecsv"):
            out[str(rel)] = compare_flags(g, c)
            continue
        if name.endswith(".fits"):
            ga, ca = _fits_arrays(g), _fits_arrays(c)
        elif name.endswith((".h5", ".hdf5")):
            ga, ca = _h5_arrays(g), _h5_arrays(c)
        else:
            out[str(rel)] = {"ok": True, "kind": "present on both"}
            continue
        worst, ulps, beyond, problem, worst_key, flipped = 0.0, 0.0, 0.0, None, None, 0.0
        narrow = any(_narrow(v[1]) for v in ca.values())
        if set(ga) != set(ca):
            problem = f"different contents: {sorted(set(ga) ^ set(ca))}"
        for k in ca:
            if k not in ga or problem:
                continue
            if ca[k][0].dtype.kind in "iu":   # indices, time tags, pixel numbers: exactly equal
                if not np.array_equal(ga[k][0], ca[k][0]):
                    problem = f"{k}: integer values differ"
                continue
            d, u, b, prob = _rel(ga[k][0], ca[k][0], ca[k][1])
            problem = problem or (f"{k}: {prob}" if prob else None)
            if not _narrow(ca[k][1]) and d >= worst:
                worst, worst_key = d, k
            if flips and not _narrow(ca[k][1]) and d > tol and not prob:
                flipped = max(flipped, _beyond_fraction(ga[k][0], ca[k][0], tol))
            ulps = max(ulps, u) if _narrow(ca[k][1]) else ulps
            beyond = max(beyond, b) if _narrow(ca[k][1]) else beyond
        res = {"rel_diff": worst, "allowed": tol, "worst": worst_key}
        if narrow:
            # one stored rounding apart, or beyond that by less than one stored unit at the cube's scale
            ntol = min(narrow_scale_tol(v[1]) for v in ca.values() if _narrow(v[1]))
            res.update(ulp_diff=ulps, allowed_ulps=1.0, rel_diff_beyond_ulp=beyond, allowed_beyond_ulp=ntol)
        within = worst <= res["allowed"]
        if flips and not within:
            res.update(flipped_fraction=flipped, allowed_flipped=FLIP_FRACTION, allowed_flip=FLIP_TOL)
            within = flipped <= FLIP_FRACTION and worst <= FLIP_TOL
        res["ok"] = problem is None and within and (not narrow or ulps <= 1.0 or beyond <= res["allowed_beyond_ulp"])
        if problem:
            res["problem"] = problem
        out[str(rel)] = res
    return out


# ------------------------------------------------------------------ running pipelines
def free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: pipelines made small enough for the CPU run they are compared with: those made for a GPU alone (in fp32
#: on both: the fused integer modes are GPU-only and have their own GPU tests), and the calibration story
SMALL = {"lwasv_sim_wholeband": [
    "source.duration_s=0.5", "source.channels.count=64", "imager.grid.size=32", "imager.precision=fp32",
    "imager.search.window_s=0.06", "imager.search.dms=[1.0]", "output.integrate.seconds=0.1",
    "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, duration_s: 0.0015, flux_jy: 1500.0, dm: 0.6}]"],
    # both tunings, 8 channels each; a burst of DM 0.05 reaches the low tuning 0.1 s after the high one
    "lwasv_sim_station": [
        "source.duration_s=0.5", "source.channels.count=8", "imager.grid.size=16", "imager.tolerance=null",
        "imager.precision=fp32", "imager.search.window_s=0.06", "imager.search.dms=[0.2]",
        "imager.search.threshold=6.5", "output.integrate.seconds=0.1", "source.refresh_s=0.1",
        "calibration.solve.cadence_s=0.2", "calibration.solve.integration_s=0.1", "calibration.solve.apply_delay_s=0.05",
        "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.15, duration_s: 0.002, flux_jy: 1500.0, dm: 0.05}]"],
    "lwasv_sim_calibrate": ["source.duration_s=2.0", "calibration.solve.cadence_s=1.0",
                            "calibration.solve.integration_s=0.5", "calibration.solve.apply_delay_s=0.0"]}


def resolve_input(yml, cfg, data):
    """(overrides, sender file or None, reason it cannot run or None) for one pipeline YAML."""
    src = cfg.get("source", {})
    kind = src.get("kind")
    if kind == "simulated":
        return list(SMALL.get(yml.stem, [])), None, None
    if kind in ("tbf", "tbx"):
        p = (yml.parent / src["path"]).resolve()
        if p.exists():
            return [], None, None
        alt = data / Path(src["path"]).name
        if alt.exists():
            return [f"source.path={alt.resolve()}"], None, None
        return [], None, f"input {src['path']} not found (nor in {data})"
    if kind == "udp":
        fmt = src.get("format", "tbf")
        sender = data / ("lwasv-adp-tbf.dat" if fmt == "tbf" else "lwana-ndp-tbx.dat")
        if not sender.exists() and fmt == "tbx":
            sender = REPO / "tests" / "data" / "lwana-ndp-tbx.dat"
        if not sender.exists():
            return [], None, f"no {fmt.upper()} capture to replay ({sender})"
        return [], sender, None
    return [], None, f"source kind {kind!r} has no input the check knows how to give"


def run_one(yml, device, outdir, overrides, sender, log):
    """Run ``bf-epic run`` on one device; (ok, wall seconds, summary dict or None, tail of its output)."""
    summary = outdir.with_suffix(".json")
    cmd = bf_epic_command() + ["run", str(yml), "--set", f"device={device}", "--set", f"output.dir={outdir}",
                       "--no-progress", "--summary-json", str(summary)]
    for ov in overrides:
        cmd += ["--set", ov]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    if sender is None:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        text, rc = proc.stdout + proc.stderr, proc.returncode
    else:
        port = free_port()
        cmd += ["--set", f"source.port={port}"]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        lines = []
        for line in proc.stdout:           # send once the receiver says it listens
            lines.append(line)
            if "listening" in line:
                break
        rep = subprocess.run(bf_epic_command() + ["replay", str(sender), "--to", f"127.0.0.1:{port}", "--rate", "1", "-q"],
                             capture_output=True, text=True)
        lines.append(rep.stdout + rep.stderr)
        rest, _ = proc.communicate(timeout=600)
        text, rc = "".join(lines) + rest, proc.returncode
    wall = time.perf_counter() - t0
    log(f"    {device}: rc {rc}, {wall:.1f} s")
    info = json.loads(summary.read_text()) if summary.exists() else None
    return rc == 0, wall, info, text[-3000:]


def check_pipeline(yml, args, data, out, log):
    cfg = yaml.safe_load(yml.read_text())
    name = yml.stem
    row = {"pipeline": name, "source": cfg.get("source", {}).get("kind")}
    overrides, sender, why = resolve_input(yml, cfg, data)
    if why:
        row.update(status="skipped", reason=why)
        log(f"  {name}: skipped ({why})")
        return row
    overrides = overrides + list(args.set)
    log(f"  {name}: {row['source']} source{' (replayed ' + sender.name + ')' if sender else ''}")
    runs = {}
    for device in ("gpu", "cpu"):
        d = out / device / name
        shutil.rmtree(d, ignore_errors=True)
        ok, wall, info, tail = run_one(yml, device, d, overrides, sender, log)
        runs[device] = {"ok": ok, "wall_s": wall, "images": (info or {}).get("images")}
        if not ok:
            log(tail)
    row["runs"] = runs
    if not all(r["ok"] for r in runs.values()):
        row.update(status="FAIL", reason="a run failed")
        return row
    solved = bool(((cfg or {}).get("calibration") or {}).get("solve"))
    src = (cfg or {}).get("source") or {}
    flips = src.get("kind") == "simulated" and bool(src.get("quantize"))
    files = compare_dirs(out / "gpu" / name, out / "cpu" / name, TOL_SOLVED if solved else TOL_FP32, flips=flips)
    row["files"] = files
    bad = {k: v for k, v in files.items() if not v["ok"]}
    diffs = [v["rel_diff"] for v in files.values() if "rel_diff" in v and "ulp_diff" not in v]
    ulps = [v["ulp_diff"] for v in files.values() if "ulp_diff" in v]
    row["max_ulp_diff_narrow"] = max(ulps) if ulps else None
    beyond = [v["rel_diff_beyond_ulp"] for v in files.values() if "rel_diff_beyond_ulp" in v]
    row["max_rel_diff_beyond_ulp_narrow"] = max(beyond) if beyond else None
    cands = [v for v in files.values() if "rows" in v]
    row["max_rel_diff"] = max(diffs) if diffs else None
    row["candidates"] = [v["rows"][1] for v in cands] or None
    same_images = runs["gpu"]["images"] == runs["cpu"]["images"]
    row["status"] = "ok" if not bad and same_images and files else "FAIL"
    if bad or not same_images or not files:
        row["reason"] = "; ".join([f"{k}: {v.get('problem', v)}" for k, v in bad.items()] +
                                  ([] if same_images else ["image counts differ"]) + ([] if files else ["no outputs"]))
    for k, v in bad.items():
        log(f"    {k}: {v}")
    return row


def plan_picks(log):
    rows = []
    for tol in TOLERANCES:
        cmd = bf_epic_command() + ["plan", str(REPO / "pipelines" / "lwasv_sim_allsky.yaml"), "--set", "device=gpu",
                           "--set", f"imager.tolerance={tol}", "--json", "-q"]
        p = subprocess.run(cmd, capture_output=True, text=True)
        try:
            pick = json.loads(p.stdout)["tolerance_pick"]
            rows.append({"tolerance": float(tol), **pick, "ok": pick["bound"] <= float(tol),
                         "predicted_gulp_ms": json.loads(p.stdout)["predicted_gulp_s"] * 1e3})
        except Exception:  # noqa: BLE001 - reported in the table
            rows.append({"tolerance": float(tol), "ok": False, "problem": (p.stdout + p.stderr)[-500:]})
        log(f"  tolerance {tol}: {rows[-1]}")
    return rows


def run_tests(pytest_args, log):
    cmd = [sys.executable, "-m", "pytest", "-q", "-m", "gpu", "-p", "no:cacheprovider", *pytest_args.split()]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    last = [ln for ln in p.stdout.strip().splitlines() if ln.strip()][-1:] or ["(no output)"]
    log(p.stdout[-4000:] + p.stderr[-2000:])
    ok = p.returncode == 0 and " passed" in last[0] and "failed" not in last[0]
    return {"ok": ok, "summary": last[0], "wall_s": time.perf_counter() - t0, "rc": p.returncode}


def table(result):
    lines = [f"GPU check, {result['date']}: {result['gpu']}; {result['host']}", ""]
    if result.get("tests"):
        t = result["tests"]
        lines.append(f"GPU tests (pytest -m gpu): {t['summary']} [{'ok' if t['ok'] else 'FAIL'}]")
        lines.append("")
    lines.append(f"{'pipeline':<22} {'source':<10} {'GPU s':>7} {'CPU s':>7} {'images':>7} {'files':>5} "
                 f"{'max |G-C|/max|C|':>17} {'f16 cube':>9} {'candidates':>10}  status")
    for r in result["pipelines"]:
        if r["status"] == "skipped":
            lines.append(f"{r['pipeline']:<22} {r['source'] or '?':<10} {'':>7} {'':>7} {'':>7} {'':>5} {'':>17} "
                         f"{'':>9} {'':>10}  skipped: {r['reason']}")
            continue
        g, c = r["runs"]["gpu"], r["runs"]["cpu"]
        diff = "-" if r.get("max_rel_diff") is None else f"{r['max_rel_diff']:.1e}"
        cand = "-" if not r.get("candidates") else "same " + "/".join(map(str, r["candidates"]))
        cube = "-" if r.get("max_ulp_diff_narrow") is None else f"{r['max_ulp_diff_narrow']:.2g} ulp"
        if r.get("max_ulp_diff_narrow") and r["max_ulp_diff_narrow"] > 1:
            cube += f"/{r['max_rel_diff_beyond_ulp_narrow']:.0e}"
        lines.append(f"{r['pipeline']:<22} {r['source']:<10} {g['wall_s']:>7.1f} {c['wall_s']:>7.1f} "
                     f"{str(g['images']):>7} {len(r.get('files', {})):>5} {diff:>17} {cube:>9} {cand:>10}  "
                     f"{r['status']}"
                     + (f": {r['reason']}" if r.get("reason") else ""))
    lines += ["", "bf-epic plan pipelines/lwasv_sim_allsky.yaml --set device=gpu --set imager.tolerance=T:"]
    for p in result["plan"]:
        if "precision" in p:
            lines.append(f"  T = {p['tolerance']:.0e}: {p['method']} route, {p['precision']}, bound {p['bound']:.1e}, "
                         f"predicted {p['predicted_gulp_ms']:.2f} ms per gulp  [{'ok' if p['ok'] else 'FAIL'}]")
        else:
            lines.append(f"  T = {p['tolerance']:.0e}: FAIL {p['problem']}")
    lines.append("")
    lines.append("ALL OK" if result["ok"] else "SOME CHECKS FAILED")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="folder of the LWA captures the YAMLs name (default $BF_EPIC_DATA or "
                                   "../shared/data/lwa)")
    ap.add_argument("--out", default="output/gpu_check", help="where both runs write (default output/gpu_check)")
    ap.add_argument("--json", help="write the results as JSON here")
    ap.add_argument("--skip-tests", action="store_true", help="do not run the GPU tests")
    ap.add_argument("--pytest-args", default="", help="extra pytest arguments, e.g. '-x tests/test_blocks.py'")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="only these pipelines (YAML stems)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an override for every run of every pipeline (e.g. source.duration_s=0.5)")
    args = ap.parse_args(argv)
    data, out = data_dir(args.data), Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(msg, flush=True)

    result = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "gpu": gpu_name(),
              "host": f"{platform.node()}, {os.cpu_count()} CPU cores, Python {platform.python_version()}",
              "overrides": args.set}
    log(f"GPU: {result['gpu']}")
    if not args.skip_tests:
        log("GPU tests:")
        result["tests"] = run_tests(args.pytest_args, log)
    log("pipelines (bf-epic run, device=gpu then device=cpu):")
    ymls = sorted((REPO / "pipelines").glob("*.yaml"))
    if args.only:
        ymls = [y for y in ymls if y.stem in args.only]
    result["pipelines"] = [check_pipeline(y, args, data, out, log) for y in ymls]
    log("planner picks:")
    result["plan"] = plan_picks(log)
    result["ok"] = (result.get("tests", {"ok": True})["ok"] and all(p["ok"] for p in result["plan"])
                    and all(r["status"] != "FAIL" for r in result["pipelines"]))
    text = table(result)
    log("\n" + text)
    if args.json:
        write_json(args.json, result)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
