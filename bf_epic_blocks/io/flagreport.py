"""The interference flags of a run, for people: an occupancy table and a waterfall PNG.

``<prefix>_flags.ecsv`` (astropy's ECSV): one row per channel, its frequency (MHz) and the fraction of its
stand-samples flagged (a stand-sample: one stand, both pols, one frame), with the run's fractions by
reason in the table's metadata. ``<prefix>_flags.png``: flagged fraction against time (rows of gulps) and
frequency, beside the occupancy per channel.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_flag_report"]


def write_flag_report(outdir, prefix, freq_hz, summary, waterfall, row_s, title=""):
    """Write ``<prefix>_flags.ecsv`` and ``<prefix>_flags.png`` to ``outdir``; returns their paths.

    freq_hz : (nchan,); summary : :meth:`~bf_epic_blocks.blocks.rfi_flag.RFIFlagBlock.summary`;
    waterfall : (nrow, nchan) flagged fraction; row_s : seconds of data per row."""
    from astropy.table import Table
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    f = np.asarray(freq_hz, np.float64) / 1e6
    occ = np.asarray(summary["channel_fraction"], np.float64)
    t = Table({"freq_mhz": f, "flagged_fraction": occ})
    t["freq_mhz"].unit = "MHz"
    t.meta = {"fraction_flagged": float(summary["fraction_flagged"]),
              "by_reason": {k: float(v) for k, v in summary["by_reason"].items()},
              "stand_samples_seen": int(summary["stand_samples_seen"]),
              "static_channels": int(summary["static_channels"])}
    table = out / f"{prefix}_flags.ecsv"
    t.write(table, format="ascii.ecsv", overwrite=True)

    fig = Figure(figsize=(10, 6), dpi=100)
    FigureCanvasAgg(fig)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    w = np.asarray(waterfall, np.float64)
    if w.size:
        df = (f[1] - f[0]) if len(f) > 1 else 0.025
        im = ax.imshow(100 * w, aspect="auto", origin="lower", interpolation="nearest", vmin=0, vmax=100,
                       extent=(f[0] - df / 2, f[-1] + df / 2, 0, w.shape[0] * row_s), cmap="magma")
        fig.colorbar(im, ax=ax, label="flagged (%)")
    ax.set_ylabel("time (s of data)")
    ax.set_title(title or f"interference flags: {100 * summary['fraction_flagged']:.3f}% of the stand-samples")
    ax2.plot(f, 100 * occ, lw=1)
    ax2.set_xlabel("frequency (MHz)")
    ax2.set_ylabel("flagged (%)")
    fig.tight_layout()
    png = out / f"{prefix}_flags.png"
    from .quicklook import save_figure
    save_figure(fig, png)
    return [str(table), str(png)]
