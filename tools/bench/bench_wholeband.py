"""The whole band through `bf-epic run`: real-time factor, memory over the run, and the injected burst.

One run of ``pipelines/lwasv_sim_wholeband.yaml`` (or ``--yaml``, a station of several tunings too:
``pipelines/lwasv_sim_station.yaml``) as a subprocess, timed from
outside, as an operator runs it (``--set`` overrides pass through; the default is the YAML's 60 s on
``--device gpu``). Printed and written as JSON:

* whole run: data seconds / process wall; pipeline: data seconds / the runner's own wall;
  flowing: data seconds / the time from the search's first images to its last (the search is where
  every image ends; without one, the imager; several GPUs' searches: the first's first to the last's
  last), the figure the whole-band issue asks for (>= 1.5x).
* start: seconds after the process started when the runner started, when every imager had made its
  first images (the end of its first gulp) and when the search had them (the cold start).
* memory, sampled every ``--sample-s``: the GPU's used memory (``nvidia-smi``, where there is one;
  with several GPUs the fullest one's) and
  the run's resident set (``/proc``): first, peak, and the growth from the first quarter of the
  flowing time to the last (flat means ~0).
* the CuPy kernels compiled during the run (files added to CuPy's kernel cache, less those copied from
  the kernel store that ``bf-epic compile`` fills at install; 0 when every kernel was cached or stored):
  on an empty cache and no store the first images wait for compilation, so releases are compared on
  equal caches (a run first on a fresh machine pays it, the next finds its kernels cached). On a GPU the
  run lists each of them (``$BF_EPIC_LOG_COMPILES``): when, how long, on which thread, asked by what.
* what the run imports is compiled to bytecode first, untimed, as an installation has it
  (``--no-warm-bytecode`` leaves that to the run, where the environment forbids writing it beside the sources).
* each injected burst (``source.transients``): the brightest candidate within ``--match-s`` of its
  arrival, its DM off the burst's in trials (the tree's one-image sweep step), its place off the
  burst's in grid cells (the truth's own RA/Dec against the candidate's), and whether that is within
  the issue's bounds (+-1 trial, <= 1.5 cells); and how many other candidates the run listed. A station:
  each tuning's own, and each burst's station event (how many tunings saw it, its time at the
  station's highest channel).

usage: python tools/bench/bench_wholeband.py [--device gpu] [--seconds 60] [--set KEY=VALUE ...]
                                       [--sample-s 2] [--switch-interval-s S] [--no-warm-bytecode]
                                       [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchlib import REPO, bf_epic_command, child_env, machine, warm_bytecode, write_json
from bf_epic_blocks.cuda import COMPILE_LOG_ENV


#: seconds between a burst's arrival and a candidate that may be it
MATCH_S = 0.05


def kernel_cache_names():
    """Names of the files in CuPy's on-disk kernel cache (``CUPY_CACHE_DIR``, default ``~/.cupy/kernel_cache``),
    empty where it does not exist yet; None where CuPy keeps its cache in memory (``CUPY_CACHE_IN_MEMORY=1``)."""
    if os.environ.get("CUPY_CACHE_IN_MEMORY", "0") not in ("", "0"):
        return None
    d = Path(os.environ.get("CUPY_CACHE_DIR") or Path.home() / ".cupy" / "kernel_cache")
    try:
        return {str(f.relative_to(d)) for f in d.rglob("*") if f.is_file()}
    except OSError:
        return set()


def kernel_cache_files():
    """How many files CuPy's on-disk kernel cache holds (see :func:`kernel_cache_names`; None: in memory)."""
    names = kernel_cache_names()
    return None if names is None else len(names)


def kernel_store_names():
    """Names of the files in the package's kernel store (``bf-epic compile``; empty where there is none)."""
    from bf_epic_blocks.cuda import kernel_store
    try:
        return set(os.listdir(kernel_store()))
    except OSError:
        return set()


def gpu_used_mib():
    """Used memory of the first GPU in MiB (``nvidia-smi``), or None where there is none."""
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None
    try:
        out = subprocess.run([exe, "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=10).stdout.split()
        return max(float(v) for v in out) if out else None       # several GPUs: the fullest
    except (OSError, subprocess.SubprocessError, ValueError):
        return None


def rss_mib(pid):
    """Resident set of process ``pid`` in MiB (Linux ``/proc``), or None."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def growth(samples, t0, t1):
    """(first, peak, growth) of ``samples`` [(t, value)] within [t0, t1]: growth is the peak of the last
    quarter of that span minus the peak of its first quarter (None where either quarter is empty)."""
    vals = [(t, v) for t, v in samples if v is not None and t0 <= t <= t1]
    if not vals:
        return None, None, None
    q = (t1 - t0) / 4
    first = [v for t, v in vals if t <= t0 + q]
    last = [v for t, v in vals if t >= t1 - q]
    g = (max(last) - max(first)) if first and last else None
    return vals[0][1], max(v for _, v in vals), g


def seconds_after(table, start):
    """Each row's ``time_utc`` in seconds after ``start`` (a numpy datetime64)."""
    return np.array([(np.datetime64(str(v).replace("Z", "")) - start) / np.timedelta64(1, "us") / 1e6
                     for v in table["time_utc"]])


def brightest_near(table, start, start_s):
    """(row index or None, every row's time in s after ``start``): the brightest row of ``table`` (a
    ``time_utc`` and ``snr`` column; None or empty allowed) within MATCH_S of ``start_s``."""
    if table is None or not len(table):
        return None, None
    t = seconds_after(table, start)
    near = np.flatnonzero(np.abs(t - start_s) <= MATCH_S)
    return (int(near[np.argmax(np.asarray(table["snr"])[near])]) if near.size else None), t


def candidate_rows(table, start, tuning=None, limit=100):
    """The brightest ``limit`` rows of a candidate table as plain dicts (time in s after ``start``, DM,
    S/N, width, kind, place), so that a record says what the run found besides its bursts."""
    if table is None or not len(table):
        return []
    t = seconds_after(table, start)
    order = np.argsort(-np.asarray(table["snr"], np.float64))[:limit]
    return [{**({"tuning": tuning} if tuning else {}), "time_s": round(float(t[k]), 6),
             "dm": float(table["dm"][k]), "snr": round(float(table["snr"][k]), 2), "width_ms": float(table["width_ms"][k]),
             "kind": str(table["kind"][k]), "ra_deg": round(float(table["ra_deg"][k]), 3),
             "dec_deg": round(float(table["dec_deg"][k]), 3)} for k in order]


def burst_checks(cfg, table):
    """Each injected burst against the run's candidate table (astropy Table or None)."""
    from astropy.coordinates import SkyCoord
    from bf_epic_blocks.conventions import dispersion_delay_s
    from bf_epic_blocks.pipeline.runner import channel_freqs
    src, im = cfg["source"], cfg["imager"]
    freq = np.asarray(channel_freqs(cfg))
    dt_img = int(im["accumulate_frames"]) / float(src["channels"]["width_hz"])
    per_dm = float(dispersion_delay_s(1.0, freq.min(), freq.max())) / dt_img      # sweep images per unit DM
    cell_deg = float(np.degrees(2.0 / int(im["grid"]["size"])))                  # l, m cell at the zenith
    start = np.datetime64(str(src["start"]).replace("Z", ""))
    out = []
    for tr in src.get("transients") or []:
        row = {"name": tr.get("name"), "dm": tr["dm"], "ra_deg": tr["ra_deg"], "dec_deg": tr["dec_deg"],
               "start_s": tr["start_s"], "found": False}
        k, t = brightest_near(table, start, tr["start_s"])
        if k is not None:
            sep = SkyCoord(float(table["ra_deg"][k]), float(table["dec_deg"][k]), unit="deg").separation(
                SkyCoord(tr["ra_deg"], tr["dec_deg"], unit="deg")).deg
            d_trials = (float(table["dm"][k]) - tr["dm"]) * per_dm
            row.update(found=bool(abs(d_trials) <= 1.0 + 1e-9 and sep <= 1.5 * cell_deg),
                       snr=float(table["snr"][k]), dm_found=float(table["dm"][k]), dm_off_trials=d_trials,
                       time_off_s=float(t[k] - tr["start_s"]), offset_deg=float(sep),
                       offset_cells=float(sep / cell_deg))
        out.append(row)
    return out


def station_checks(cfg, outdir):
    """A station's run: each tuning's bursts (:func:`burst_checks`, each row naming its tuning), the
    candidates that are none of them, and each injected burst's station event (the brightest event
    within MATCH_S of its arrival at the station's highest channel, and how many tunings saw it)."""
    from astropy.table import Table
    from bf_epic_blocks.io.candidates import read_candidates
    bursts, others, listed = [], 0, []
    for tc in cfg["tunings"]:
        name = tc["name"][len(cfg["name"]) + 1:]
        cands = sorted(Path(tc["output"]["dir"]).glob("*_candidates.ecsv"))
        table = read_candidates(cands[0]) if cands else None
        listed += candidate_rows(table, np.datetime64(str(tc["source"]["start"]).replace("Z", "")), name)
        rows = burst_checks(tc, table)
        bursts += [dict(b, tuning=name) for b in rows]
        others += (len(table) - len([b for b in rows if b.get("snr") is not None])) if table is not None else 0
    path = Path(cfg["output"]["dir"]) / f"{cfg['output']['prefix']}_events.ecsv"
    events = []
    ev = Table.read(path, format="ascii.ecsv") if path.exists() else None
    start = np.datetime64(str(cfg["source"]["start"]).replace("Z", ""))
    for tr in cfg["source"].get("transients") or []:
        row = {"name": tr.get("name"), "start_s": tr["start_s"], "dm": tr["dm"], "ntunings": 0}
        k, t = brightest_near(ev, start, tr["start_s"])
        if k is not None:
            row.update(ntunings=int(ev["ntunings"][k]), tunings=str(ev["tunings"][k]), snr=float(ev["snr"][k]),
                       dm_found=float(ev["dm"][k]), time_off_s=float(t[k] - tr["start_s"]))
        events.append(row)
    return bursts, others, {"events": 0 if ev is None else len(ev), "bursts": events}, listed


def run(args):
    from bf_epic_blocks.io.candidates import read_candidates
    from bf_epic_blocks.pipeline.config import load_config
    sets = [f"device={args.device}"] + ([f"source.duration_s={args.seconds}"] if args.seconds else []) + args.set
    outdir = Path(tempfile.mkdtemp(prefix="bench_wholeband_"))
    cfg = load_config(args.yaml, sets + [f"output.dir={outdir}"])
    data_s = float(cfg["source"]["duration_s"])
    summary = outdir / "summary.json"
    cmd = bf_epic_command() + ["run", str(args.yaml), "--no-progress", "-q", "--summary-json", str(summary)]
    for s in sets + [f"output.dir={outdir}"]:
        cmd += ["--set", s]
    samples_gpu, samples_rss = [], []
    stop = threading.Event()
    bytecode = warm_bytecode(args.device) if args.warm_bytecode else {"prefix": child_env().get("PYTHONPYCACHEPREFIX"),
                                                                       "seconds": None}
    cache0, store = kernel_cache_names(), kernel_store_names()
    t0, t0_unix = time.perf_counter(), time.time()
    with tempfile.TemporaryFile("w+") as err:
        env = child_env()
        if args.device.startswith("gpu"):
            env[COMPILE_LOG_ENV] = "1"      # the run lists what it compiles (a cache miss, a kernel not stored)
        if args.switch_interval_s is not None:
            env["BF_EPIC_SWITCH_INTERVAL_S"] = repr(float(args.switch_interval_s))
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True, env=env)

        def sample():
            while not stop.is_set():
                t = time.perf_counter() - t0
                if args.device.startswith("gpu"):
                    samples_gpu.append((t, gpu_used_mib()))
                samples_rss.append((t, rss_mib(p.pid)))
                stop.wait(args.sample_s)
        th = threading.Thread(target=sample, daemon=True)
        th.start()
        rc = p.wait()
        wall = time.perf_counter() - t0
        stop.set()
        th.join()
        if rc:
            err.seek(0)
            raise SystemExit(f"bf-epic run failed ({rc}): {err.read()[-3000:]}")
    cache1 = kernel_cache_names()
    # files new in the cache: compiled during the run, or copied from the kernel store at its start
    compiled = None if cache0 is None or cache1 is None else len(cache1 - cache0 - store)
    from_store = None if cache0 is None or cache1 is None else len((cache1 - cache0) & store)
    info = json.loads(summary.read_text())
    blocks = info.get("blocks", {})
    if "tunings" in info:          # a station: every tuning's blocks, named <tuning>/<block>
        blocks = {f"{t}/{n}": b for t, s in info["tunings"].items() for n, b in s["blocks"].items()}
        info["search"] = {t: s.get("search") for t, s in info["tunings"].items()}
        info["solver"] = {t: s.get("solver") for t, s in info["tunings"].items()}
    # the searches (one per GPU of a pixel split, one per tuning of a station), else the imagers: from
    # the first's first images to the last's last
    kind = (lambda n: n.rsplit("/", 1)[-1])
    parts = [b for n, b in blocks.items() if kind(n).startswith("TransientSearch")] or \
        [b for n, b in blocks.items() if kind(n).startswith(("DFTImager", "WStack"))]
    parts = [b for b in parts if b["first_data_s"] is not None and b["last_data_s"] is not None]
    sink = {"first_data_s": min(b["first_data_s"] for b in parts),
            "last_data_s": max(b["last_data_s"] for b in parts)} if parts else None
    # the runner's block times are seconds after its own start, which is this long after the process's
    lag = info["started_unix_s"] - t0_unix if "started_unix_s" in info else wall - info["wall_s"]
    flow = None
    if sink and sink["last_data_s"] > sink["first_data_s"]:
        flow = (sink["first_data_s"] + lag, sink["last_data_s"] + lag)
    # every imager's first images made (the end of its first gulp), seconds after the process started
    made = [b.get("first_done_s") for n, b in blocks.items() if kind(n).startswith(("DFTImager", "WStack"))]
    imaged_at = max(made) + lag if made and None not in made else None
    window = flow or (0.0, wall)
    gpu = growth(samples_gpu, *window)
    rss = growth(samples_rss, *window)
    if cfg.get("tunings"):
        bursts, others, events, listed = station_checks(cfg, outdir)
    else:
        cands = sorted(outdir.glob("*_candidates.ecsv"))
        table = read_candidates(cands[0]) if cands else None
        bursts, events = burst_checks(cfg, table), None
        listed = candidate_rows(table, np.datetime64(str(cfg["source"]["start"]).replace("Z", "")))
        others = (len(table) - len([b for b in bursts if b.get("snr") is not None])) if table is not None else 0
    row = {"data_s": data_s, "wall_s": wall, "pipeline_s": info["wall_s"], "rt_whole": data_s / wall,
           "rt_pipeline": data_s / info["wall_s"],
           "flowing_s": None if flow is None else flow[1] - flow[0],
           "rt_flowing": None if flow is None else data_s / (flow[1] - flow[0]),
           "first_images_at_s": None if flow is None else flow[0], "runner_started_at_s": lag,
           "imagers_first_images_at_s": imaged_at,
           "gpu_mib": dict(zip(("first", "peak", "growth"), gpu)),
           "rss_mib": dict(zip(("first", "peak", "growth"), rss)),
           "kernels_compiled": compiled, "kernels_from_store": from_store,
           "compiled_while_running": [dict(c, at_s=round(c["at_unix_s"] - t0_unix, 2))
                                      for c in info.get("kernels_compiled_while_running") or []],
           "bytecode": bytecode,
           "images": info.get("images"), "search": info.get("search"), "solver": info.get("solver"), "bursts": bursts,
           "other_candidates": others, "candidates": listed, "station_events": events, "blocks": blocks}
    out = {"benchmark": "bench_wholeband", "date": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime()),
           "yaml": str(args.yaml), "sets": sets, "switch_interval_s": args.switch_interval_s,
           "machine": machine("gpu" if args.device.startswith("gpu") else "cpu"), "run": row,
           "samples": {"gpu_mib": samples_gpu, "rss_mib": samples_rss}}
    shutil.rmtree(outdir, ignore_errors=True)
    return out


def fmt(v, spec):
    return "-" if v is None else format(v, spec)


def show(out):
    r = out["run"]
    print(f"# bench_wholeband: {out['yaml']} {' '.join('--set ' + s for s in out['sets'])} "
          f"on {out['machine']['hardware']}")
    print("data s   wall s  whole x  pipeline x  flowing x  first images s  GPU MiB first/peak/growth  "
          "RSS MiB first/peak/growth")
    g, m = r["gpu_mib"], r["rss_mib"]
    gpu = f"{fmt(g['first'], '.0f')}/{fmt(g['peak'], '.0f')}/{fmt(g['growth'], '+.0f')}"
    rss = f"{fmt(m['first'], '.0f')}/{fmt(m['peak'], '.0f')}/{fmt(m['growth'], '+.0f')}"
    print(f"{r['data_s']:6.1f}  {r['wall_s']:7.1f}  {r['rt_whole']:7.3f}  {r['rt_pipeline']:10.3f}  "
          f"{fmt(r['rt_flowing'], '9.3f')}  {fmt(r['first_images_at_s'], '14.1f')}  {gpu:>26}  {rss:>25}")
    for b in r["bursts"]:
        where = f" in {b['tuning']}" if b.get("tuning") else ""
        if b.get("snr") is None:
            print(f"burst {b['name']}{where}: DM {b['dm']} at {b['start_s']} s: NOT FOUND")
        else:
            print(f"burst {b['name']}{where}: DM {b['dm']} at {b['start_s']} s: found DM {b['dm_found']:.4f} "
                  f"({b['dm_off_trials']:+.2f} trials), {b['time_off_s'] * 1e3:+.1f} ms, {b['offset_deg']:.2f} deg "
                  f"({b['offset_cells']:.2f} cells), S/N {b['snr']:.1f}: {'within' if b['found'] else 'OUTSIDE'} "
                  "+-1 trial and 1.5 cells")
    print(f"other candidates: {r['other_candidates']}")
    if r.get("station_events"):
        for e in r["station_events"]["bursts"]:
            print(f"station event of burst {e['name']}: seen by {e['ntunings']} tuning(s)"
                  + (f" ({e['tunings']}), DM {e['dm_found']:.4f}, {e['time_off_s'] * 1e3:+.1f} ms at the station's "
                     f"top channel, S/N {e['snr']:.1f}" if e["ntunings"] else ""))
        print(f"station events: {r['station_events']['events']}")
    if r.get("imagers_first_images_at_s") is not None:
        print(f"after the process started: the runner at {r['runner_started_at_s']:.2f} s, every imager's first "
              f"images at {r['imagers_first_images_at_s']:.2f} s, the search's at {fmt(r['first_images_at_s'], '.2f')} s"
              f" ({r.get('kernels_from_store') or 0} kernels from the store)")
    if r.get("kernels_compiled"):
        print(f"CuPy kernels compiled during the run: {r['kernels_compiled']} (the kernel cache was not warm: "
              "the first images, and anything first used later, waited for them)")
    for c in r.get("compiled_while_running") or []:
        print(f"  {c['kernel']} at {c['at_s']:.1f} s ({c['seconds']:.2f} s, thread {c['thread']}, asked by "
              f"{c['caller'] or 'CuPy'})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--yaml", type=Path, default=REPO / "pipelines" / "lwasv_sim_wholeband.yaml")
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--seconds", type=float, default=None, help="source.duration_s (default: the YAML's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more overrides")
    ap.add_argument("--sample-s", type=float, default=2.0, help="seconds between memory samples")
    ap.add_argument("--switch-interval-s", type=float, default=None,
                    help="the run's interpreter switch interval (BF_EPIC_SWITCH_INTERVAL_S; default: bf-epic's)")
    ap.add_argument("--no-warm-bytecode", dest="warm_bytecode", action="store_false",
                    help="time the run without first compiling what it imports (where the environment forbids "
                         "writing bytecode beside the sources, the first run then compiles it)")
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv)
    out = run(args)
    show(out)
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
