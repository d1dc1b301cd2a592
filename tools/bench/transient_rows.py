#!/usr/bin/env python
"""The transient issue's table, run as a user runs it: `bf-epic run pipelines/lwasv_sim_transient.yaml`
with ``--set source.transients=[...]``, one run per row, and what each gives.

Rows (all at RA 310, Dec 20, 0.33 s into the 0.5-s demo, 4 ms long):

* ``quiet``     -- nothing injected (the table must still read back);
* ``burst2k``   -- 2,000 Jy at DM 0.5 (a bright point burst, which lands between pixels);
* ``flash30k``  -- 30 kJy at DM 0 (fills much of the sky);
* ``flash3M``   -- 3 MJy at DM 0 (fills the whole sky: memory and time must stay bounded);
* ``demo``      -- the YAML's own burst, unchanged.

For each: wall time and the child's peak resident memory (``wait4``), the rows written (read back
with astropy), their kind, S/N, folded sidelobes and image index; the bounds the issue sets are
checked (3 MJy flash: peak memory <= 2x and wall <= 2.5x the quiet run's; the burst: <= 3 rows within
50 ms; a flash: one ``sky-wide`` row, <= 5 rows within 50 ms). Prints a table, writes JSON.

    python tools/bench/transient_rows.py --device cpu --json transient_rows_cpu.json
    python tools/bench/transient_rows.py --device gpu --json transient_rows_gpu.json
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench_e2e import run_cli
from benchlib import REPO, machine, utc_now, write_json

_AT = "ra_deg: 310.0, dec_deg: 20.0, start_s: 0.33, duration_s: 0.004"
ROWS = {
    "quiet": "[]",
    "burst2k": f"[{{name: B, {_AT}, flux_jy: 2000.0, dm: 0.5}}]",
    "flash30k": f"[{{name: F, {_AT}, flux_jy: 30000.0, dm: 0.0}}]",
    "flash3M": f"[{{name: F, {_AT}, flux_jy: 3000000.0, dm: 0.0}}]",
    "demo": None,
}


def run_row(name, transients, device, work):
    out = work / name
    sets = [f"device={device}", f"output.dir={out}", "output.cube=null"]
    if transients is not None:
        sets.append(f"source.transients={transients}")
    # the end-to-end benchmark's runner: wall time and this child's own peak memory (wait4)
    row = run_cli(REPO / "pipelines" / "lwasv_sim_transient.yaml", 0.5, out, sets=sets)
    wall, peak_mb = row["wall_s"], row["peak_rss_mb"]
    from bf_epic_blocks.io.candidates import read_candidates
    t = read_candidates(out / "lwasv_sim_transient_candidates.ecsv")
    dt_img = 16 / 25e3
    within = np.abs(np.asarray(t["image"]) * dt_img - 0.33) <= 0.05 if len(t) else np.zeros(0, bool)
    return {"wall_s": round(wall, 2), "peak_rss_mb": round(peak_mb), "rows": len(t),
            "rows_within_50ms": int(within.sum()), "kinds": [str(k) for k in t["kind"]],
            "snr": [round(float(v), 1) for v in t["snr"]], "nsidelobes": [int(v) for v in t["nsidelobes"]],
            "image": [int(v) for v in t["image"]], "grid_xy": [[int(x), int(y)] for x, y in zip(t["grid_x"], t["grid_y"])],
            "sky_fraction": [round(float(v), 3) for v in t["sky_fraction"]]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rows", nargs="*", default=list(ROWS))
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    work = Path(a.workdir or tempfile.mkdtemp(prefix="bf_epic_rows_"))
    work.mkdir(parents=True, exist_ok=True)
    res = {"date": utc_now(), "device": a.device, "machine": machine("gpu" if a.device.startswith("gpu") else "cpu")}
    print(f"{'row':<9} {'wall s':>7} {'peak MB':>8} {'rows':>5} {'<=50ms':>7}  kinds / S/N / sidelobes folded")
    for name in a.rows:
        r = run_row(name, ROWS[name], a.device, work)
        res[name] = r
        desc = ", ".join(f"{k} {s:g} ({n})" for k, s, n in zip(r["kinds"], r["snr"], r["nsidelobes"]))
        print(f"{name:<9} {r['wall_s']:7.2f} {r['peak_rss_mb']:8d} {r['rows']:5d} {r['rows_within_50ms']:7d}  {desc}")
    checks = {}
    if "quiet" in res and "flash3M" in res:
        q, f = res["quiet"], res["flash3M"]
        checks["flash3M_memory_ratio"] = round(f["peak_rss_mb"] / q["peak_rss_mb"], 3)
        checks["flash3M_wall_ratio"] = round(f["wall_s"] / q["wall_s"], 3)
        checks["flash3M_bounded"] = checks["flash3M_memory_ratio"] <= 2.0 and checks["flash3M_wall_ratio"] <= 2.5
    if "burst2k" in res:
        checks["burst_at_most_3_rows"] = 1 <= res["burst2k"]["rows_within_50ms"] <= 3
    for name in ("flash30k", "flash3M"):
        if name in res:
            checks[f"{name}_named"] = "sky-wide" in res[name]["kinds"] and res[name]["rows_within_50ms"] <= 5
    res["checks"] = checks
    print("checks:", ", ".join(f"{k} {v}" for k, v in checks.items()))
    if a.json:
        write_json(a.json, res)
    return 0 if all(v for k, v in checks.items() if not k.endswith("ratio")) else 1


if __name__ == "__main__":
    sys.exit(main())
