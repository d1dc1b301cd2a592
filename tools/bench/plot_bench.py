#!/usr/bin/env python
"""Plot run time against error from bench_wstack.py JSON files (one panel per file).

Colour = method, marker = image size. Used for the README's figure:

    python tools/bench/plot_bench.py docs/bench/bench_wstack_cpu.json docs/bench/bench_wstack_gpu.json \\
        --out docs/images/time_vs_error.png
"""
import argparse
import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COLOURS = {"dft_direct": "tab:blue", "dft_covariance": "tab:orange", "wstack": "tab:purple",
           "cov_wgrid": "tab:green", "moff": "tab:red"}
LABELS = {"dft_direct": "DFT direct", "dft_covariance": "DFT covariance", "wstack": "E-field w-stacking",
          "cov_wgrid": "covariance + w-gridding", "moff": "MOFF (z ignored)"}
MARKERS = {64: "o", 128: "s", 256: "^", 512: "D"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json", nargs="+")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    fig, axes = plt.subplots(1, len(a.json), figsize=(6.5 * len(a.json), 5), squeeze=False)
    for ax, path in zip(axes[0], a.json):
        d = json.load(open(path))
        for r in d["rows"]:
            ax.scatter(max(r["error"], 1e-9), r["time_s"], c=COLOURS.get(r["method"], "k"),
                       marker=MARKERS.get(r["size"], "x"), s=45, edgecolors="k", linewidths=0.4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("max |I - I_DFT(float64)| / peak")
        ax.set_ylabel("time per 1024-sample image (s)")
        ax.set_title(f"{d['device'].upper()}: {d['nant']} antennas, {d['ntime']} samples, "
                     f"{d['nchan']} chan x {d['npol']} pol", fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
    for m, c in COLOURS.items():
        axes[0][0].scatter([], [], c=c, label=LABELS[m], edgecolors="k", linewidths=0.4)
    for n, mk in MARKERS.items():
        axes[0][0].scatter([], [], c="w", marker=mk, edgecolors="k", label=f"{n}x{n}")
    axes[0][0].legend(fontsize=8, loc="upper right", ncol=2)
    fig.tight_layout()
    fig.savefig(a.out, dpi=100)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
