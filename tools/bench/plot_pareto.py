#!/usr/bin/env python
"""One Pareto picture of run time against error: the DFT precision ladder and the w-gridding ladder.

Reads a ``bench_dft.py`` JSON (every route x precision x grid of the exact DFT imager) and optionally a
``bench_wstack.py`` JSON of the same machine (covariance + w-gridding at several epsilon), and plots
time per 1,024-sample gulp against max |I - I_ref| / peak, one panel per grid size, the naive CuPy
baseline as a grey star.

    python tools/bench/plot_pareto.py docs/bench/bench_dft_gpu.json --wstack docs/bench/bench_wstack_gpu.json \\
        --out docs/images/pareto_gpu.png
"""
import argparse
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COLOURS = {"fp64": "tab:gray", "fp32": "tab:blue", "tf32x3": "tab:cyan", "fp16x3": "tab:purple", "tf32": "tab:green",
           "fp16": "tab:orange", "bf16": "tab:red"}
MARKERS = {("covariance", "ci4"): "o", ("covariance", "cf32"): "s", ("direct", "ci4"): "^"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dft_json")
    ap.add_argument("--wstack", default=None)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    d = json.load(open(a.dft_json))
    ws = json.load(open(a.wstack)) if a.wstack else None
    grids = sorted({r["grid"] for r in d["rows"] if r["regime"] == "gulp"})
    fig, axes = plt.subplots(1, len(grids), figsize=(5.2 * len(grids), 4.6), squeeze=False)
    for ax, g in zip(axes[0], grids):
        for r in d["rows"]:
            if r["grid"] != g or r["regime"] != "gulp":
                continue
            err = max(r["rel_err"], 1e-16)
            if r["route"].startswith("naive"):
                ax.scatter(err, r["gulp_s"] * 1e3, marker="*", s=140, c="0.6", edgecolors="k", zorder=3)
                continue
            if r["route"] == "previous":
                ax.scatter(err, r["gulp_s"] * 1e3, marker="P", s=90, c="0.3", edgecolors="k", zorder=3)
                continue
            ax.scatter(err, r["gulp_s"] * 1e3, c=COLOURS.get(r["precision"], "k"),
                       marker=MARKERS.get((r["route"], r["input"]), "x"), s=55, edgecolors="k", linewidths=0.5,
                       zorder=4)
        if ws:
            pts = sorted((r["error"], r["time_s"] * 1e3) for r in ws["rows"]
                         if r["method"] == "cov_wgrid" and r["size"] == g)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], "-D", c="tab:purple", ms=5,
                        label="covariance + w-gridding (epsilon ladder)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("max |I - I_ref(float64)| / peak")
        ax.set_ylabel("ms per 1,024-sample gulp (16 chan x 2 pol)")
        ax.set_title(f"{g} x {g} grid", fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
    ax0 = axes[0][0]
    for name, c in COLOURS.items():
        ax0.scatter([], [], c=c, label=name, edgecolors="k", linewidths=0.5)
    for (route, inp), mk in MARKERS.items():
        ax0.scatter([], [], c="w", marker=mk, edgecolors="k", label=f"{route}, {inp} input")
    ax0.scatter([], [], marker="*", s=140, c="0.6", edgecolors="k", label="naive CuPy (same run)")
    ax0.scatter([], [], marker="P", s=90, c="0.3", edgecolors="k", label="previous release (same run)")
    ax0.legend(fontsize=7, loc="upper right", ncol=2)
    gpu = d["machine"].get("gpu", d["machine"].get("cpu"))
    fig.suptitle(f"DFT imager, case P: run time against error, {gpu}, {d['date'][:10]}", fontsize=11)
    fig.tight_layout()
    fig.savefig(a.out, dpi=100)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
