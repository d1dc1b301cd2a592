"""Transient candidates out: an astropy table (ECSV or FITS) and a PNG of the sky with light curves.

Table columns (one row per candidate, i.e. per cluster of threshold crossings; units in the table):

=============  ===========================================================================
time_utc       UTC start of the event at the reference frequency (the band's highest channel)
sequence       name of the image sequence; ``image``: index of the event's first image in it
pixel          index in the list of imaged pixels; ``grid_x``, ``grid_y``: l and m indices on
               the grid (-1 for pixel lists)
l, m           direction cosines (East, North)
ra_deg, dec_deg ICRS direction at ``time_utc`` (NaN without a station location)
snr            peak S/N (boxcar mean against the sliding window's mean and sigma)
dm             trial DM of the peak (pc cm^-3); ``channel``: -1 (channels averaged) or the channel
width          boxcar width in images; ``width_ms``: the same in milliseconds
nmembers       threshold crossings merged into the candidate (at most ``max_pixels`` per trial image)
nsidelobes     fainter candidates at the same time folded into this one as its sidelobes (the point
               source fitted to its S/N image explains them through the array's beam; their
               crossings are in ``nmembers``)
kind           'point', or 'sky-wide': more than the search's ``sky_fraction`` of the image's pixels over
               the threshold at once (lightning, RFI, a flash); ``pixel`` etc. are then its peak's
sky_fraction   the largest fraction of the image's pixels over the threshold among its crossings
lightcurve     S/N per image (width 1, the candidate's DM and pixel) from ``lc_first`` images
               before the event to after it (NaN where not held); meta ``lightcurve_first``
=============  ===========================================================================

The table's ``meta`` holds the search parameters (threshold, window, DM trials, widths, image
time, reference frequency, trials per width).

:class:`CandidateWriter` writes a search's table and PNG (``<prefix>_candidates.ecsv`` or ``.fits``,
``<prefix>_candidates.png``); the search block hands it every candidate so far at the end of each
sequence, so the files always hold the whole run's.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["CANDIDATE_COLUMNS", "CandidateWriter", "candidate_table", "write_candidates", "read_candidates",
           "candidates_png"]

CANDIDATE_COLUMNS = ("time_utc", "sequence", "image", "pixel", "grid_x", "grid_y", "l", "m", "ra_deg", "dec_deg",
                     "snr", "dm", "dm_trial", "channel", "width", "width_ms", "nmembers", "nsidelobes", "kind", "sky_fraction", "lightcurve")
_UNITS = {"ra_deg": "deg", "dec_deg": "deg", "dm": "pc / cm3", "dm_trial": "pc / cm3", "width_ms": "ms"}


def candidate_table(rows, meta=None, lc_length=0):
    """An astropy Table from a list of row dicts (keys :data:`CANDIDATE_COLUMNS`), sorted by time."""
    from astropy.table import Table
    from astropy.time import Time
    cols = {}
    for k in CANDIDATE_COLUMNS:
        vals = [r[k] for r in rows]
        if k == "time_utc":
            cols[k] = Time([v.isot for v in vals], scale="utc", format="isot") if vals else Time([], format="isot")
        elif k == "lightcurve":
            cols[k] = np.asarray(vals, dtype=np.float32).reshape(len(vals), lc_length)
        elif k in ("sequence", "kind"):
            cols[k] = np.asarray(vals, dtype=str) if vals else np.zeros(0, dtype="U1")
        else:
            cols[k] = np.asarray(vals, dtype=np.int64 if k in ("image", "pixel", "grid_x", "grid_y", "channel",
                                                               "width", "nmembers", "nsidelobes") else np.float64)
    t = Table(cols, meta=dict(meta or {}))
    for k, u in _UNITS.items():
        t[k].unit = u
    if len(t):
        t.sort("time_utc")
    return t


class CandidateWriter:
    """Writes a transient search's candidates: ``<prefix>_candidates.<table_format>`` and, with ``png``,
    ``<prefix>_candidates.png`` in ``outdir`` (made if missing), each call replacing the last.

    table_format : 'ecsv' or 'fits'. ``written`` lists the paths written so far (each once).
    """

    def __init__(self, outdir, prefix="transients", table_format="ecsv", png=True):
        if table_format not in ("ecsv", "fits"):
            raise ValueError(f"CandidateWriter: table_format must be 'ecsv' or 'fits', got {table_format!r}")
        self.outdir, self.prefix, self.table_format, self.png = str(outdir), str(prefix), table_format, bool(png)
        self.written = []

    def write(self, table, sky, *, grid=None, lm=None):
        """Write ``table`` (:func:`candidate_table`; its meta's ``threshold``, ``product`` and ``dt_s``
        title and scale the PNG) and the PNG of ``sky`` (npix,), the window mean at the searched pixels
        (on ``grid``, an LMGrid, or at ``lm`` (npix, 2); all zero if any is not finite). Returns the
        paths written by this call."""
        os.makedirs(self.outdir, exist_ok=True)
        stem = os.path.join(self.outdir, f"{self.prefix}_candidates")
        out = [write_candidates(f"{stem}.{self.table_format}", table)]
        if self.png:
            meta = table.meta
            sky = sky if np.all(np.isfinite(sky)) else np.zeros(len(sky))
            out.append(candidates_png(f"{stem}.png", table, sky, grid=grid, lm=lm, dt_s=meta["dt_s"],
                                      title=f"{len(table)} candidate(s) above {meta['threshold']:g} sigma "
                                            f"({meta['product']}); sky: window mean"))
        self.written += [p for p in out if p not in self.written]
        return out


def write_candidates(path, table):
    """Write the table as ECSV (``.ecsv``) or FITS (``.fits``); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".ecsv":
        t = table
        lc = table["lightcurve"] if "lightcurve" in table.colnames else None
        if len(table) == 0 and lc is not None and lc.ndim > 1:
            # astropy's ECSV reader cannot rebuild a 0-row column of arrays ("shape mismatch between value
            # and column specifier", astropy 7-8): store it flat and its length in the meta
            t = table.copy()
            t.replace_column("lightcurve", np.zeros(0, dtype=lc.dtype))
            t.meta["lightcurve_length"] = int(lc.shape[1])
        t.write(path, format="ascii.ecsv", overwrite=True)
    elif path.suffix.lower() in (".fits", ".fit"):
        t = table.copy()
        t.meta = {k.upper()[:8]: (str(v) if isinstance(v, (list, tuple, dict)) else v) for k, v in t.meta.items()}
        t.write(path, format="fits", overwrite=True)
    else:
        raise ValueError(f"candidate table path must end in .ecsv or .fits, got {str(path)!r}")
    return str(path)


def read_candidates(path):
    """Read a table written by :func:`write_candidates`."""
    from astropy.table import Table
    path = Path(path)
    fmt = "ascii.ecsv" if path.suffix.lower() == ".ecsv" else "fits"
    t = Table.read(path, format=fmt)
    n = t.meta.pop("lightcurve_length", None)
    if n is not None and len(t) == 0 and "lightcurve" in t.colnames:
        t.replace_column("lightcurve", np.zeros((0, int(n)), dtype=t["lightcurve"].dtype))
    return t


def candidates_png(path, table, sky, *, grid=None, lm=None, dt_s=None, title=None, max_curves=8, dpi=100):
    """Sky with the candidates marked (numbered by S/N rank) and each candidate's light curve.

    sky : (npix,) background values (e.g. the window mean) on ``grid`` (LMGrid) or at ``lm``
    (npix, 2); dt_s : seconds per image (light-curve time axis). Returns the path.
    """
    from matplotlib.figure import Figure
    from .quicklook import _draw_sky, _limits, _save
    sky = np.asarray(sky, dtype=np.float64)
    order = np.argsort(-np.asarray(table["snr"])) if len(table) else np.zeros(0, int)
    shown = order[:max_curves]
    ncur = max(1, len(shown))
    fig = Figure(figsize=(12.0, max(5.5, 1.3 * ncur + 1.0)))
    gs = fig.add_gridspec(ncur, 2, width_ratios=[1.15, 1.0])
    ax = fig.add_subplot(gs[:, 0])
    marks = [(str(i + 1), float(table["l"][k]), float(table["m"][k])) for i, k in enumerate(order)]
    if grid is not None:
        img = grid.to_image(sky)
        lo, hi = _limits([img], None, None, (1.0, 99.5))
        im = _draw_sky(ax, img, grid, cmap="inferno", lo=lo, hi=hi, sources=marks, horizon=True)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="window mean (uncalibrated)")
    else:
        p = np.asarray(lm, dtype=np.float64)
        sc = ax.scatter(p[:, 0], p[:, 1], c=sky, cmap="inferno", s=12)
        for lab, l, m in marks:
            ax.plot([l], [m], marker="o", ms=11, mfc="none", mec="cyan", mew=1.2)
            ax.annotate(lab, (l, m), xytext=(7, 7), textcoords="offset points", color="cyan", fontsize=8)
        ax.invert_xaxis()
        ax.set_aspect("equal")
        ax.set_xlabel("l (East)")
        ax.set_ylabel("m (North)")
        fig.colorbar(sc, ax=ax, fraction=0.046, pad=0.04, label="window mean (uncalibrated)")
    ax.set_title(title or f"{len(table)} candidate(s); circles numbered by S/N rank", fontsize=10)
    first = int(table.meta.get("lightcurve_first", 0))
    dt_ms = 1e3 * float(dt_s if dt_s is not None else table.meta.get("dt_s", 1.0))
    for i, k in enumerate(shown):
        a = fig.add_subplot(gs[i, 1])
        lc = np.asarray(table["lightcurve"][k], dtype=np.float64)
        x = (first + np.arange(lc.size)) * dt_ms
        a.step(x, lc, where="post", color="k", lw=0.9)
        w = int(table["width"][k])
        a.axvspan(0.0, w * dt_ms, color="tab:orange", alpha=0.3)
        a.axhline(0.0, color="0.6", lw=0.5)
        a.text(0.01, 0.95, f"#{i + 1}  S/N {float(table['snr'][k]):.1f}  DM {float(table['dm'][k]):g}  "
                           f"w {w}  {table['time_utc'][k].isot[11:23]}", transform=a.transAxes, va="top", fontsize=8)
        a.set_ylabel("S/N", fontsize=8)
        a.tick_params(labelsize=7)
        if i == len(shown) - 1:
            a.set_xlabel("time from event start (ms), dedispersed at the candidate's DM", fontsize=8)
    if not len(shown):
        a = fig.add_subplot(gs[0, 1])
        a.text(0.5, 0.5, "no candidate", ha="center", va="center")
        a.set_axis_off()
    fig.tight_layout()
    return _save(fig, path, dpi)
