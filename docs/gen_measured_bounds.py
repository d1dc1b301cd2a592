"""Append the accuracy planner's table of measured bounds to the accuracy page at build time.

The rows come from ``bf_epic_blocks/imaging/measured.json``, the file the planner itself reads, so the
page shows what ``tolerance`` plans with in this checkout.
"""
from __future__ import annotations

import json
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
PAGE = "concepts/accuracy.md"
TABLE = ROOT / "bf_epic_blocks" / "imaging" / "measured.json"

rows = json.loads(TABLE.read_text())["rows"]
out = ["", "| device | route | precision | error bound | input |", "|---|---|---|---|---|"]
for r in sorted(rows, key=lambda r: (r["device"], -r["bound"], r["method"])):
    out.append(f"| {r['device']} | {r['method']} | `{r['precision']}` | {r['bound']:.0e} | "
               f"{r.get('input') or 'any'} |")
out += ["", "(Generated from `bf_epic_blocks/imaging/measured.json` when this site was built.)", ""]

with mkdocs_gen_files.open(PAGE, "a") as f:
    f.write("\n".join(out))
