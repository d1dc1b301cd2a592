"""End to end: what a station operator gets from `bf-epic run`, beside the imaging core, in one run.

Rows (each `bf-epic run` is a subprocess, timed from outside, as a user would see it):

* recording: a TBF file written with the project's own writer (`io.tbf.write_tbf`: LWA-SV, 256
  stands, random 4-bit samples; default 10 s of 24 channels = 3.08 GB), imaged on a 64x64 all-sky
  grid with 1-s images, once per precision; the first run of the first precision is a warm-up
  (CuPy kernels compiled and cached). Whole run: data seconds / process wall; pipeline: data
  seconds / the runner's own wall (`wall_s` of `--summary-json`); steady: the imager's data after
  its first gulp / the time from that gulp to its last (the runner's per-block timing), beside each
  block's host milliseconds per gulp.
* simulated: `pipelines/lwasv_sim_allsky.yaml` (2 s, 16 channels), the same measures.
* recording from disk: the last precision again after the file's pages are dropped from the page
  cache (``posix_fadvise(DONTNEED)``), so it is read from the disk.
* memory against length: the first 20% of the file as its own recording, and (``long``) a recording
  ``--long-factor`` times as long (default 3: 30 s, 9.25 GB), with its peak resident set over the
  short one's; the long row also shows the sustained rate once start-up is spread thinner.
* every run has Python's bytecode caches, as an installation does (:func:`child_env`; an image that
  sets ``PYTHONDONTWRITEBYTECODE`` gets them under a folder of the benchmark's own), compiled before
  the first timed run; the JSON's ``bytecode`` says which.
* start-up: the first of those runs with CuPy's kernel cache pointed at an empty folder
  (`CUPY_CACHE_DIR`): seconds to the first image file, and the whole run.
* source alone: the simulated sky's generator (`sky.fastsim.make_gulp`) for 16, 24 and 784
  channels on the device asked for; and the TBF reader alone (`io.tbf.iter_tbf_gulps`).
* core: the imager's operator on the same problem (24 channels, 256 stands, 3,205 pixels, 1,024
  samples per gulp, 25,000 per image) called directly, per gulp, as a real-time factor: with the
  voltages as complex64 (the floating-point covariance route), and as packed ci4 bytes decoded and
  accumulated as integers, which is what `bf-epic run` does with a capture file on a GPU.

usage: python tools/bench/bench_e2e.py [--device gpu|cpu] [--seconds 10] [--nchan 24] [--precisions fp16,fp32]
                                 [--gulps auto,1024,5000]
                                 [--long-factor 3] [--skip recording,long,tbx,simulated,startup,source,core]
                                 [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchlib import REPO, array_module, bf_epic_command, child_env, machine, synchronize, warm_bytecode, write_json

DT = 40e-6


def write_recording(path, seconds, nchan, seed=1, fmt="tbf"):
    """A TBF (or, ``fmt="tbx"``, NDP TBX) file of ``seconds`` of LWA-SV-sized data (256 stands,
    ``nchan`` channels from 1200, random 4-bit samples), written with the project's own writers in
    pieces of 1 s so memory stays small; returns (bytes, write seconds)."""
    from bf_epic_blocks.imaging.calibration import FS_HZ
    from bf_epic_blocks.io.tbf import write_tbf
    from bf_epic_blocks.io.tbx import write_tbx
    rng = np.random.default_rng(seed)
    ntime = int(round(seconds / DT))
    step = int(round(FS_HZ * DT))
    t0 = time.perf_counter()
    with open(path, "wb") as out:
        for a in range(0, ntime, 25000):
            n = min(25000, ntime - a)
            data = rng.integers(0, 256, size=(n, nchan, 256, 2), dtype=np.uint8)
            piece = str(path) + ".piece"
            if fmt == "tbx":
                write_tbx(piece, data, 10**15 + 8192 * (a + np.arange(n)), 1200)
            else:
                write_tbf(piece, data, 1200, int(1.7e9) * FS_HZ + a * step, frame_id=1)
            with open(piece, "rb") as fh:
                shutil.copyfileobj(fh, out, 1 << 24)
            os.remove(piece)
    return os.path.getsize(path), time.perf_counter() - t0


def recording_yaml(path, tbf, outdir, device, precision, kind="tbf", gulp=1024):
    Path(path).write_text(f"""name: e2e_recording
station: {{name: lwasv}}
source: {{kind: {kind}, path: {tbf}, gulp_nframe: {gulp}}}
calibration: {{cable: true, pattern: none}}
imager: {{kind: dft, grid: {{size: 64}}, accumulate_frames: 25000, products: [I], method: auto,
         precision: {precision}}}
device: {device}
output: {{dir: {outdir}, fits: true, png: false}}
""")


def evict(path):
    """Drop the file's pages from the page cache (posix_fadvise DONTNEED); True if the call worked."""
    try:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)
        return True
    except (OSError, AttributeError):
        return False


def run_cli(yml, data_s, outdir, env_extra=None, sets=()):
    """Run bf-epic; watch the output folder for image files. Returns a row of times."""
    shutil.rmtree(outdir, ignore_errors=True)
    summary = Path(tempfile.mkdtemp()) / "summary.json"
    cmd = bf_epic_command() + ["run", str(yml), "--no-progress", "-q", "--summary-json", str(summary)]
    for s in sets:
        cmd += ["--set", s]
    env = dict(child_env(), **(env_extra or {}))
    seen = {}
    stop = threading.Event()

    def watch():
        while not stop.is_set():
            if Path(outdir).exists():
                for p in Path(outdir).rglob("*.fits"):
                    seen.setdefault(p.name, time.perf_counter())
            time.sleep(0.01)
    th = threading.Thread(target=watch, daemon=True)
    t0 = time.perf_counter()
    th.start()
    with tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True, env=env)
        _, status, usage = os.wait4(p.pid, 0)       # this child's own peak memory, not all children's
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        stop.set()
        th.join()
        if p.returncode:
            err.seek(0)
            raise RuntimeError(f"bf-epic run failed ({p.returncode}): {err.read()[-2000:]}")
    info = json.loads(summary.read_text())
    marks = sorted(seen.values())
    row = {"wall_s": wall, "pipeline_s": info["wall_s"], "images": info["images"], "data_s": data_s,
           "rt_whole": data_s / wall, "rt_pipeline": data_s / info["wall_s"],
           "first_image_s": (marks[0] - t0) if marks else None, "peak_rss_mb": usage.ru_maxrss / 1024}
    row.update(steady_rate(info.get("blocks", {}), data_s))
    return row


def steady_rate(blocks, data_s):
    """The imager's real-time factor once it runs: the data after its first gulp over the time from
    its first gulp's start to its last gulp's end (from the runner's per-block timing), and each
    block's host time per gulp. Not image-file times: a writer that starts late (a slow first FITS
    file) writes the queued images back to back, faster than the pipeline runs."""
    out = {}
    img = next((b for n, b in blocks.items() if n.startswith(("DFTImager", "WStack"))), None)
    if img and img["ngulp"] > 1 and img["last_data_s"] > img["first_data_s"]:
        out["rt_steady"] = data_s * (img["ngulp"] - 1) / img["ngulp"] / (img["last_data_s"] - img["first_data_s"])
    for n, b in blocks.items():
        if b["ngulp"]:
            out["ms_per_gulp_" + n.rsplit("_", 1)[0].replace("Block", "")] = 1e3 * b["process_s"] / b["ngulp"]
    return out


def core_rate(device, nchan, precision, gulps=20, packed=False, gulp=1024):
    """Real-time factor of the imaging core alone: ``gulp``-sample gulps accumulated into 25,000-sample
    images, on the LWA-SV layout, 64x64 all-sky grid. ``packed=False``: random ci4 integers given as
    complex64 (the covariance route in floating point); ``packed=True``: the same kind of voltages as
    packed 4-bit bytes, decoded and accumulated as integers, which is what `bf-epic run` does on a GPU
    for a capture file (the exact integer covariance)."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging.dft import DFTOperator
    from bf_epic_blocks.runtime.dtypes import int8_pairs_decoder
    from bf_epic_blocks.station import load_station
    st = load_station("lwasv")
    xp = array_module(device)
    freq = 25e3 * (1200 + np.arange(nchan))
    lm = imaging.lm_grid(64).lm
    op = DFTOperator(xp.asarray(st.xyz_m), xp.asarray(freq), xp.asarray(lm), npol=2, precision=precision)
    acc = op.accumulator(("I",), method="auto", ntime_hint=25000)
    rng = np.random.default_rng(0)
    if packed:
        x = xp.asarray(rng.integers(0, 256, (gulp, nchan, st.nstand, 2), dtype=np.uint8))
        decode = int8_pairs_decoder("ci4")

        def add():
            acc.add(decode(x))
    else:
        x = xp.asarray((rng.integers(-8, 8, (gulp, nchan, st.nstand, 2))
                        + 1j * rng.integers(-8, 8, (gulp, nchan, st.nstand, 2))).astype(np.complex64))

        def add():
            acc.add(x)
    per_image = max(1, 25000 // gulp)

    def one(i):
        add()
        if (i + 1) % per_image == 0:      # an image every 25,000 samples, as the pipeline makes
            acc.result()
            acc.reset()
    for i in range(per_image):            # a whole image first: kernels compiled, caches filled
        one(i)
    synchronize(xp)
    t0 = time.perf_counter()
    for i in range(1, gulps + 1):
        one(i)
    synchronize(xp)
    per_gulp = (time.perf_counter() - t0) / gulps
    return {"per_gulp_ms": per_gulp * 1e3, "rt": gulp * DT / per_gulp, "gulp": gulp, "input": "ci4" if packed else "complex64"}


def source_rates(device, nchans=(16, 24, 784), gulp=1024):
    from bf_epic_blocks.sky import fastsim
    rows = []
    rng = np.random.default_rng(0)
    xyz = rng.normal(0, 40, (256, 3))
    xp = array_module(device)
    for nchan in nchans:
        if device != "gpu" and nchan > 100:
            continue                     # the whole band on a CPU: hours, not a benchmark
        f = 25e3 * (2960 + np.arange(nchan))
        l, m = np.array([0.1, -0.3, 0.4, 0.0]), np.array([0.2, 0.1, -0.3, 0.6])
        w = fastsim.sky_weights(xyz, f, l, m, np.sqrt(1 - l * l - m * m), np.full((nchan, 4), 1e4))
        on0, on1 = fastsim.burst_windows(4, [], f, DT)
        wd = xp.asarray(w)
        out = xp.empty((gulp, nchan, 256, 2), np.uint8)
        keys = fastsim.stream_keys(1)
        fastsim.make_gulp(out, 0, wd, on0, on1, keys, 1000.0, 0.1)
        reps = 20 if device == "gpu" else 2
        synchronize(xp)
        t0 = time.perf_counter()
        for i in range(reps):
            fastsim.make_gulp(out, (i + 1) * gulp, wd, on0, on1, keys, 1000.0, 0.1)
        synchronize(xp)
        per = (time.perf_counter() - t0) / reps
        rows.append({"nchan": nchan, "per_gulp_ms": per * 1e3, "rt": gulp * DT / per})
    return rows


def raw_read_rates(path, data_s, gulp_bytes, threads=(1, 2, 4, 8, 16)):
    """The GPU path's file reads alone (:func:`~bf_epic_blocks.blocks.sources.pread_start`, page cache
    -> pinned memory, ``gulp_bytes`` at a time, two reads ahead) for several reader-thread counts."""
    from concurrent.futures import ThreadPoolExecutor
    from bf_epic_blocks.blocks.sources import pread_start, pread_wait
    from bf_epic_blocks.imaging._xp import pinned_empty
    size = os.path.getsize(path)
    bufs = [pinned_empty(gulp_bytes, np.uint8) for _ in range(3)]
    rows = []
    fd = os.open(path, os.O_RDONLY)
    try:
        for nt in threads:
            with ThreadPoolExecutor(nt) as pool:
                t0 = time.perf_counter()
                pending = []
                for k, off in enumerate(range(0, size - gulp_bytes + 1, gulp_bytes)):
                    pending.append(pread_start(fd, bufs[k % 3], off, pool))
                    if len(pending) > 2:
                        pread_wait(pending.pop(0))
                for p in pending:
                    pread_wait(p)
                dt = time.perf_counter() - t0
            rows.append({"threads": nt, "GB_per_s": size / dt / 1e9, "rt": data_s / dt})
    finally:
        os.close(fd)
    return rows


def reader_rate(path, data_s):
    from bf_epic_blocks.io.tbf import iter_tbf_gulps, scan_tbf
    t0 = time.perf_counter()
    info = scan_tbf(path)
    t1 = time.perf_counter()
    for _ in iter_tbf_gulps(path, 1024, info=info):
        pass
    t2 = time.perf_counter()
    return {"scan_s": t1 - t0, "read_s": t2 - t1, "rt": data_s / (t2 - t0)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="gpu", choices=("gpu", "cpu"))
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--nchan", type=int, default=24)
    ap.add_argument("--precisions", default="fp16,fp32")
    ap.add_argument("--gulps", default="auto,1024,5000",
                    help="source.gulp_nframe values for the recordings (the first is the main row: auto, the default)")
    ap.add_argument("--workdir", default=None, help="where the recording is written (default: a temp folder)")
    ap.add_argument("--long-factor", type=float, default=3.0,
                    help="the 'long' row: a recording this many times --seconds (0 or 1: none)")
    ap.add_argument("--skip", default="", help="comma list of rows to leave out")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    skip = set(a.skip.split(",")) - {""}
    work = Path(a.workdir or tempfile.mkdtemp(prefix="bf_e2e_"))
    work.mkdir(parents=True, exist_ok=True)
    res = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "device": a.device, "args": vars(a),
           "machine": machine(a.device)}
    env = child_env()
    res["bytecode"] = {"dont_write_bytecode": "PYTHONDONTWRITEBYTECODE" in env,
                       "pycache_prefix": env.get("PYTHONPYCACHEPREFIX")}
    warm_bytecode(a.device)

    def show(name, row):
        print(f"{name:<34} " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                                         for k, v in row.items()), flush=True)

    if "startup" not in skip or "simulated" not in skip:
        yml = REPO / "pipelines" / "lwasv_sim_allsky.yaml"
        sets = [f"device={a.device}", f"output.dir={work / 'sim'}", "output.png=false"]
        if "startup" not in skip:
            cold = Path(tempfile.mkdtemp(prefix="cupy_cache_"))
            res["startup_cold"] = run_cli(yml, 2.0, work / "sim", {"CUPY_CACHE_DIR": str(cold)}, sets)
            show("simulated demo, empty kernel cache", res["startup_cold"])
        if "simulated" not in skip:
            run_cli(yml, 2.0, work / "sim", None, sets)               # warm-up
            res["simulated"] = run_cli(yml, 2.0, work / "sim", None, sets)
            show("simulated demo (2 s, 16 ch)", res["simulated"])
    if "source" not in skip:
        res["source"] = source_rates(a.device)
        for r in res["source"]:
            show(f"simulated sky alone, {r['nchan']} ch", r)
    if "recording" not in skip:
        tbf = work / "recording.tbf"
        nbytes, wt = write_recording(tbf, a.seconds, a.nchan)
        print(f"wrote {tbf}: {nbytes / 1e9:.2f} GB in {wt:.1f} s", flush=True)
        res["recording_bytes"] = nbytes
        res["reader"] = reader_rate(tbf, a.seconds)
        show("TBF reader alone (host)", res["reader"])
        if a.device == "gpu":
            res["raw_reads"] = raw_read_rates(tbf, a.seconds, 1024 * (a.nchan // 12) * 6168)
            for r in res["raw_reads"]:
                show(f"file reads alone, {r['threads']} threads", r)
        res["recording"] = {}
        gulps = a.gulps.split(",")
        for i, prec in enumerate(a.precisions.split(",")):
            for gulp in gulps:
                y = work / f"rec_{prec}_{gulp}.yaml"
                recording_yaml(y, tbf, work / "rec", a.device, prec, gulp=gulp)
                if i == 0 and gulp == gulps[0]:
                    run_cli(y, a.seconds, work / "rec")                      # warm-up (kernels cached)
                key = prec if gulp == gulps[0] else f"{prec}_gulp{gulp}"
                res["recording"][key] = run_cli(y, a.seconds, work / "rec")
                show(f"recording {a.seconds:g} s x {a.nchan} ch, {prec}, gulp {gulp}", res["recording"][key])
        # the same file with its pages dropped from the page cache: read from the disk
        evicted = evict(tbf)
        res["recording_from_disk"] = run_cli(y, a.seconds, work / "rec")
        res["recording_from_disk"]["page_cache_evicted"] = evicted
        show(f"recording, {prec}, gulp {gulp}, evicted from cache", res["recording_from_disk"])
        # peak memory against the file's length: the first 20% of it as its own recording
        short = work / "short.tbf"
        with open(tbf, "rb") as fi, open(short, "wb") as fo:
            fo.write(fi.read(nbytes // 5 // 6168 * 6168))
        recording_yaml(work / "short.yaml", short, work / "rec", a.device, prec, gulp=gulp)
        res["recording_short"] = run_cli(work / "short.yaml", a.seconds / 5, work / "rec")
        show(f"recording {a.seconds / 5:g} s (peak memory)", res["recording_short"])
        short.unlink()
        tbf.unlink()
        if "long" not in skip and a.long_factor > 1:
            # a longer recording: the sustained rate once start-up is spread thinner, and peak memory
            # against length (it must not grow with the file)
            long_s = a.seconds * a.long_factor
            longf = work / "long.tbf"
            nb, wt = write_recording(longf, long_s, a.nchan, seed=2)
            print(f"wrote {longf}: {nb / 1e9:.2f} GB in {wt:.1f} s", flush=True)
            recording_yaml(work / "long.yaml", longf, work / "rec", a.device, prec, gulp=gulps[0])
            res["recording_long"] = run_cli(work / "long.yaml", long_s, work / "rec")
            res["recording_long"]["bytes"] = nb
            res["recording_long"]["peak_rss_vs_short"] = (res["recording_long"]["peak_rss_mb"]
                                                          / res["recording_short"]["peak_rss_mb"])
            show(f"recording {long_s:g} s, {prec}, gulp {gulps[0]}", res["recording_long"])
            longf.unlink()
    if "tbx" not in skip:
        tbx = work / "recording.tbx"
        nbytes, wt = write_recording(tbx, a.seconds, a.nchan, fmt="tbx")
        print(f"wrote {tbx}: {nbytes / 1e9:.2f} GB in {wt:.1f} s", flush=True)
        res["tbx"] = {"bytes": nbytes}
        prec = a.precisions.split(",")[0]
        for j, gulp in enumerate(a.gulps.split(",")):
            y = work / f"tbx_{gulp}.yaml"
            recording_yaml(y, tbx, work / "tbx", a.device, prec, kind="tbx", gulp=gulp)
            if j == 0:
                run_cli(y, a.seconds, work / "tbx")
            res["tbx"][f"gulp{gulp}"] = run_cli(y, a.seconds, work / "tbx")
            show(f"TBX recording {a.seconds:g} s x {a.nchan} ch, {prec}, gulp {gulp}", res["tbx"][f"gulp{gulp}"])
        tbx.unlink()
    if "core" not in skip:
        res["core"] = {p: core_rate(a.device, a.nchan, p) for p in a.precisions.split(",")}
        for p, r in res["core"].items():
            show(f"core, {a.nchan} ch, {p}, complex64 input", r)
        res["core_ci4"] = {p: core_rate(a.device, a.nchan, p, gulps=40, packed=True) for p in a.precisions.split(",")}
        for p, r in res["core_ci4"].items():
            show(f"core, {a.nchan} ch, {p}, ci4 as run uses", r)
    if a.json:
        write_json(a.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
