"""What a feature adds to the whole band: `bf-epic run pipelines/lwasv_sim_wholeband.yaml` with it off and on.

Each variant is one run of the whole-band pipeline as an operator runs it (bench_wholeband's run: a
subprocess, the search on, the YAML's outputs), ``--seconds`` of data; its time is the *flowing* time,
from the search's first images to its last, so that start-up (kernel compiles, a solver's warm-up) is
left out. The variants run interleaved (off, on, ..., off, on, ...) ``--repeat`` times so that a drift of
the machine falls on all alike; the median of each variant's repeats is set against the case's first
variant (its baseline), and the spread of the repeats is printed beside it.

Cases:

* ``watch``: no watchlist; 10 targets; 100 targets (ICRS directions around the burst's field, all
  above the horizon; each adds one DFT direction per image and its spectra to the watch file).
* ``flagging``: the interference detector off and on (``flagging.enabled``).
* ``solver``: the live gain solver off and on (a solution every 10 s from 1 s of data).

usage: python tools/bench/bench_cost.py [--case watch flagging solver] [--seconds 30] [--repeat 2]
                                        [--json PATH]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import REPO, machine, utc_now, write_json  # noqa: E402


def targets(n, ra0=310.0, dec0=30.0, span_deg=30.0):
    """``n`` ICRS targets on a square patch of ``span_deg`` around (ra0, dec0), as a ``watch.targets`` value."""
    import math
    k = math.ceil(math.sqrt(n))
    step = span_deg / max(k - 1, 1)
    out = []
    for i in range(n):
        ra = ra0 - span_deg / 2 + step * (i % k)
        dec = dec0 - span_deg / 2 + step * (i // k)
        out.append(f"{{name: T{i:03d}, ra_deg: {ra:.3f}, dec_deg: {dec:.3f}}}")
    return "[" + ", ".join(out) + "]"


#: case -> [(variant name, overrides)]; the first variant is the case's baseline
CASES = {
    "watch": [("no watchlist", []),
              ("10 targets", [f"watch.targets={targets(10)}"]),
              ("100 targets", [f"watch.targets={targets(100)}"])],
    "flagging": [("flagging off", ["flagging.enabled=off"]),
                 ("flagging on", ["flagging.enabled=on"])],
    "solver": [("no solver", []),
               ("solver", ["calibration.solve.cadence_s=10.0", "calibration.solve.integration_s=1.0"])],
}


def run_variant(sets, seconds, device="gpu"):
    """One whole-band run (bench_wholeband.run) with ``sets``: its row."""
    import bench_wholeband as bw
    args = argparse.Namespace(yaml=REPO / "pipelines" / "lwasv_sim_wholeband.yaml", device=device,
                              seconds=seconds, set=list(sets), sample_s=5.0)
    return bw.run(args)["run"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", nargs="+", choices=sorted(CASES), default=["watch", "flagging", "solver"])
    ap.add_argument("--seconds", type=float, default=30.0, help="seconds of data a run")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each variant, interleaved")
    ap.add_argument("--device", default="gpu")
    ap.add_argument("--json")
    ap.add_argument("--no-warmup", action="store_true", help="skip the first, thrown-away run (kernels cached)")
    args = ap.parse_args(argv)
    if not args.no_warmup:
        # a first short run compiles every kernel (each case's last variant has the most) and is thrown away
        run_variant(sum((CASES[c][-1][1] for c in args.case), []), min(args.seconds, 5.0), args.device)
    out = {}
    print(f"{'case':<10} {'variant':<16} {'flowing s per s of data (each run)':<38} {'median':>8} {'added':>8}",
          flush=True)
    for case in args.case:
        runs = {name: [] for name, _ in CASES[case]}
        for _ in range(args.repeat):
            for name, sets in CASES[case]:
                row = run_variant(sets, args.seconds, args.device)
                print(f"  {case}, {name}: flowing {row['flowing_s']:.2f} s for {row['data_s']:g} s of data, "
                      f"whole run {row['wall_s']:.1f} s", flush=True)
                runs[name].append({"flowing_s_per_data_s": row["flowing_s"] / row["data_s"],
                                   "wall_s": row["wall_s"], "gpu_mib_peak": row["gpu_mib"]["peak"],
                                   "candidates": (row.get("search") or {}).get("candidates"),
                                   "bursts_found": sum(b.get("snr") is not None for b in row["bursts"])})
        base = None
        res = {}
        for name, _ in CASES[case]:
            per = [r["flowing_s_per_data_s"] for r in runs[name]]
            med = statistics.median(per)
            base = med if base is None else base
            res[name] = {"runs": runs[name], "median_s_per_data_s": med, "added_fraction": med / base - 1.0,
                         "spread_fraction": (max(per) - min(per)) / med}
            print(f"{case:<10} {name:<16} {' '.join(f'{p:.4f}' for p in per):<38} {med:8.4f} "
                  f"{100 * (med / base - 1):7.1f}%", flush=True)
        out[case] = {"variants": res, "overrides": {n: s for n, s in CASES[case]}}
        if args.json:        # after each case, so that a run cut short keeps the cases it finished
            write_json(args.json, {"benchmark": "bench_cost", "date": utc_now(), "machine": machine(args.device),
                                   "seconds": args.seconds, "repeat": args.repeat, "cases": out})
            print(f"wrote {args.json}", flush=True)
    return out


if __name__ == "__main__":
    main()
