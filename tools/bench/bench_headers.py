"""A sequence's start: what copying its header costs at the whole band.

Every ring checks a new sequence's header and hands each reader a copy of its own; every block derives its
output header from a copy. A live station's E-field header carries the cable tables for each channel
(``cable_delay_s``, ``cable_gain``: 256 stands x 2 pols x nchan Python floats), so at the whole band
(792 channels, LWA-SV) one header holds ~8 x 10^5 numbers, and these copies are made while the receiver's
thread waits for the interpreter. This times, on LWA-SV's real station table and cable model:

* ``validate_header`` against the JSON round trip it did before (``json.loads(json.dumps(h))``);
* a reader's or a derived header's copy (``plain_copy``) against ``copy.deepcopy``;

and checks that each copy equals the round trip's (compared as JSON text). Prints a table and writes JSON.
usage: python tools/bench/bench_headers.py [--nchan 60 792] [--repeat 3] [--json PATH]
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import best, machine, utc_now, write_json  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nchan", type=int, nargs="+", default=[60, 792])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    from bf_epic_blocks.blocks.headers import efield_header
    from bf_epic_blocks.runtime.header import plain_copy, validate_header
    from bf_epic_blocks.station.offline import configure_offline
    from bf_epic_blocks.station.tables import load_station
    configure_offline()
    st = load_station("lwasv")
    rows = []
    for nchan in args.nchan:
        freq = (1980 + np.arange(nchan)) * 25e3
        h = efield_header("udp://bench", 1447376362 * 196000000, freq, 40e-6, st.to_header(freq))
        want = json.dumps(json.loads(json.dumps(h, allow_nan=True)), sort_keys=True)
        t_json, _ = best(lambda: json.loads(json.dumps(h, allow_nan=True)), args.repeat)
        t_val, v = best(lambda: validate_header(h), args.repeat)
        t_deep, _ = best(lambda: copy.deepcopy(v), args.repeat)
        t_plain, c = best(lambda: plain_copy(v), args.repeat)
        same = json.dumps(v, sort_keys=True) == want and json.dumps(c, sort_keys=True) == want
        numbers = sum(np.size(h["station"][k]) for k in ("cable_delay_s", "cable_gain"))
        rows.append({"nchan": nchan, "cable_numbers": int(numbers), "json_round_trip_s": t_json,
                     "validate_header_s": t_val, "deepcopy_s": t_deep, "plain_copy_s": t_plain,
                     "validate_speedup": t_json / t_val, "copy_speedup": t_deep / t_plain, "equal_to_round_trip": same})
    print(f"# {machine()['hardware']}: one E-field header (LWA-SV, cable tables per channel), best of {args.repeat}")
    print(f"{'nchan':>6} {'numbers':>9} {'JSON trip s':>12} {'validate s':>11} {'x':>6} {'deepcopy s':>11} "
          f"{'plain s':>9} {'x':>6} {'equal':>6}")
    for r in rows:
        print(f"{r['nchan']:>6} {r['cable_numbers']:>9} {r['json_round_trip_s']:>12.4f} {r['validate_header_s']:>11.4f} "
              f"{r['validate_speedup']:>6.1f} {r['deepcopy_s']:>11.4f} {r['plain_copy_s']:>9.4f} "
              f"{r['copy_speedup']:>6.1f} {str(r['equal_to_round_trip']):>6}")
    if args.json:
        write_json(args.json, {"benchmark": "bench_headers", "date": utc_now(), "machine": machine(),
                               "repeat": args.repeat, "rows": rows})
    return 0 if all(r["equal_to_round_trip"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
