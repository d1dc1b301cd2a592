"""Soak: a long simulated night through imager and transient search, flashes and bursts injected,
the process's resident memory sampled as it runs.

The shipped demo (`pipelines/lwasv_sim_transient.yaml`: LWA-SV, 16 channels, one image per 16
samples = 0.64 ms, 6 DM trials, boxcars of 1-8 images) is run for ``--minutes`` of data with no image
cube, ``--bursts`` dispersed point bursts (S/N ~20-60) and ``--flashes`` sky-filling flashes (DM 0)
spread over the run. `bf-epic run` is a subprocess; every ``--every`` seconds its resident set is
read twice from ``/proc/PID/status``: VmRSS (now) and VmHWM (the peak since the last sample: the
peak is reset after each reading by writing 5 to ``/proc/PID/clear_refs``), so a sample is the
interval's peak, not wherever in its gulp cycle the process happened to be (NumPy's temporaries
come and go by hundreds of MB a gulp on a CPU). Afterwards the candidate table is read back and:

* every burst must be a ``point`` row within 10 ms of its arrival (at the band's highest channel)
  and within 1.5 grid cells of its catalogue position, with at most 3 rows within 50 ms of it;
* every flash must be a ``sky-wide`` row within 50 ms of it, with at most 5 rows within 50 ms;
* memory must not grow: the last interval peak while data flow (before the final table and PNG are
  written) <= 1.1x the first one after the warm-up (the first 20% of those samples). The
  instantaneous samples are in the JSON too.

Prints a table and writes JSON (``--json``). usage:
    python tools/bench/soak_transient.py [--device gpu|cpu] [--minutes 10] [--bursts 6] [--flashes 3] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from benchlib import REPO, bf_epic_command, machine, utc_now, write_json


def injections(seconds, nburst, nflash, seed=3):
    """(bursts, flashes): lists of transient mappings for the simulated source, spread over the run
    (none in its first 2 s, where the search's window fills), bursts at RA 300-320, Dec 10-30."""
    rng = np.random.default_rng(seed)
    slots = np.linspace(2.0, seconds - 0.5, nburst + nflash + 1)[:-1]
    slots = slots + rng.uniform(0, 0.2, slots.size)
    order = rng.permutation(slots.size)
    bursts, flashes = [], []
    for i, k in enumerate(order):
        t = float(round(slots[k], 4))
        if i < nburst:
            bursts.append({"name": f"B{i}", "ra_deg": float(rng.uniform(300, 320)), "dec_deg": float(rng.uniform(10, 30)),
                           "start_s": t, "duration_s": 0.004, "flux_jy": float(rng.uniform(1200, 2500)),
                           "dm": float(rng.choice([0.4, 0.8, 1.2, 1.6]))})
        else:
            flashes.append({"name": f"F{i - nburst}", "ra_deg": 310.0, "dec_deg": 20.0, "start_s": t,
                            "duration_s": 0.004, "flux_jy": 3.0e5, "dm": 0.0})
    return bursts, flashes


def rss_mb(pid):
    """(resident now, peak resident since the last call) in MB, or (None, None); the peak is reset
    after reading (None for it where the kernel does not allow that)."""
    now = peak = None
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    now = int(line.split()[1]) / 1024
                elif line.startswith("VmHWM:"):
                    peak = int(line.split()[1]) / 1024
        with open(f"/proc/{pid}/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        return now, None
    return now, peak


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--minutes", type=float, default=10.0, help="minutes of simulated data")
    ap.add_argument("--bursts", type=int, default=6)
    ap.add_argument("--flashes", type=int, default=3)
    ap.add_argument("--every", type=float, default=2.0, help="seconds between memory samples")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    seconds = 60.0 * a.minutes
    work = Path(a.workdir or tempfile.mkdtemp(prefix="bf_epic_soak_"))
    work.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load((REPO / "pipelines" / "lwasv_sim_transient.yaml").read_text())
    bursts, flashes = injections(seconds, a.bursts, a.flashes)
    cfg["name"] = "soak"
    cfg["source"]["duration_s"] = seconds
    cfg["source"]["transients"] = bursts + flashes
    cfg["device"] = a.device
    cfg["output"] = {"dir": str(work / "out"), "fits": False, "png": False}
    yml = work / "soak.yaml"
    yml.write_text(yaml.safe_dump(cfg, sort_keys=False))
    summary = work / "summary.json"
    cmd = bf_epic_command() + ["run", str(yml), "--no-progress", "-q", "--summary-json", str(summary)]
    samples = []
    t0 = time.perf_counter()
    with open(work / "stderr.log", "w") as err:
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err)
        while p.poll() is None:
            r, peak = rss_mb(p.pid)
            if r is not None:
                samples.append((round(time.perf_counter() - t0, 2), round(r, 1), round(peak or r, 1), time.time()))
            time.sleep(a.every)
    wall = time.perf_counter() - t0
    if p.returncode:
        print((work / "stderr.log").read_text()[-3000:], file=sys.stderr)
        raise SystemExit(f"bf-epic run failed ({p.returncode})")
    from bf_epic_blocks.io.candidates import read_candidates
    tab = read_candidates(work / "out" / "soak_candidates.ecsv")
    import astropy.units as u
    from astropy.time import Time
    start = Time(cfg["source"]["start"], scale="utc")
    t_rel = np.asarray((tab["time_utc"] - start).sec) if len(tab) else np.zeros(0)
    kind = np.asarray(tab["kind"]).astype(str) if len(tab) else np.zeros(0, str)
    from bf_epic_blocks import imaging
    cell = imaging.lm_grid(cfg["imager"]["grid"]["size"]).cell
    found = []
    from bf_epic_blocks.sky.catalogue import icrs_to_lm
    from bf_epic_blocks.station import load_station
    st = load_station(cfg["station"]["name"])
    for b in bursts:
        near = np.flatnonzero((kind == "point") & (np.abs(t_rel - b["start_s"]) <= 0.010))
        within = int(np.sum(np.abs(t_rel - b["start_s"]) <= 0.050))
        lm, _ = icrs_to_lm(np.array([b["ra_deg"]]), np.array([b["dec_deg"]]), start + b["start_s"] * u.s, st.location)
        off = [float(np.hypot(tab["l"][i] - lm[0, 0], tab["m"][i] - lm[0, 1]) / cell) for i in near]
        found.append({"name": b["name"], "start_s": b["start_s"], "flux_jy": round(b["flux_jy"]), "dm": b["dm"],
                      "rows": int(near.size), "rows_within_50ms": within, "found": bool(off and min(off) <= 1.5),
                      "offset_cells": round(min(off), 2) if off else None,
                      "snr": round(float(max(tab["snr"][i] for i in near)), 1) if near.size else None})
    named = []
    for f in flashes:
        near = np.flatnonzero(np.abs(t_rel - f["start_s"]) <= 0.050)
        named.append({"name": f["name"], "start_s": f["start_s"], "rows_within_50ms": int(near.size),
                      "named": bool(np.any(kind[near] == "sky-wide"))})
    # while data flow: up to the search block's last gulp (the runner's per-block timing), not the
    # end-of-run table and PNG (matplotlib's import alone is ~50 MB)
    info = json.loads(summary.read_text())
    blk = next((b for n, b in info.get("blocks", {}).items() if n.startswith("TransientSearch")), None)
    end = info["started_unix_s"] + blk["last_data_s"] if blk and blk.get("last_data_s") is not None else float("inf")
    flowing = [s for s in samples if s[3] <= end] or samples
    mem, now = [s[2] for s in flowing], [s[1] for s in flowing]
    end = next((s[0] for s in reversed(samples) if s[3] <= end), wall)
    samples = [(t, m, pk) for t, m, pk, _ in samples]
    first = mem[max(1, len(mem) // 5)] if len(mem) > 2 else None
    first_now = now[max(1, len(now) // 5)] if len(now) > 2 else None
    res = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "device": a.device, "data_s": seconds, "wall_s": round(wall, 1),
           "real_time_factor": round(seconds / wall, 3), "rows": len(tab),
           "rows_point": int(np.sum(kind == "point")), "rows_sky_wide": int(np.sum(kind == "sky-wide")),
           "streaming_ends_s": round(end, 2), "rss_end_of_run_mb": samples[-1][1] if samples else None, "bursts": found, "flashes": named,
           "rss_mb_now_and_interval_peak": samples, "rss_first_after_warmup_mb": first,
           "rss_last_mb": mem[-1] if mem else None, "rss_growth": round(mem[-1] / first, 3) if first else None,
           "rss_peak_mb": max(mem) if mem else None,
           "rss_now_growth": round(now[-1] / first_now, 3) if first_now else None}
    res["ok"] = bool(all(b["found"] and b["rows_within_50ms"] <= 3 for b in found)
                     and all(f["named"] and f["rows_within_50ms"] <= 5 for f in named)
                     and res["rss_growth"] is not None and res["rss_growth"] <= 1.1)
    res.update(date=utc_now(), machine=machine("gpu" if a.device.startswith("gpu") else "cpu"))
    print(f"{seconds:.0f} s of data in {wall:.1f} s ({seconds / wall:.2f}x real time) on {a.device}; {len(tab)} rows")
    print(f"{'burst':<6} {'t (s)':>8} {'Jy':>6} {'DM':>4} {'rows50':>6} {'found':>6} {'cells':>6} {'S/N':>6}")
    for b in found:
        print(f"{b['name']:<6} {b['start_s']:8.3f} {b['flux_jy']:6d} {b['dm']:4.1f} {b['rows_within_50ms']:6d} {str(b['found']):>6} "
              f"{b['offset_cells'] if b['offset_cells'] is not None else '-':>6} {b['snr'] if b['snr'] else '-':>6}")
    for f in named:
        print(f"flash {f['name']} at {f['start_s']:.3f} s: {f['rows_within_50ms']} rows within 50 ms, named {f['named']}")
    print(f"resident memory, interval peaks: {res['rss_first_after_warmup_mb']} MB after warm-up, {res['rss_last_mb']} MB "
          f"last (x{res['rss_growth']}), peak {res['rss_peak_mb']} MB; instantaneous x{res['rss_now_growth']}; "
          f"{len(samples)} samples; ok {res['ok']}")
    if a.json:
        write_json(a.json, res)
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
