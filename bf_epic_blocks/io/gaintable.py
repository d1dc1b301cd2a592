"""Solved gain tables on disk: the ``GainTable`` .npz the pipeline reads, with flags, quality and provenance,
and a PNG a person can read.

The .npz holds, for ``nsol`` solutions of ``nchan`` channels, ``nstand`` stands and ``npol`` pols:

* ``valid_from`` int64 (nsol,) time tags (196 MHz ticks since the Unix epoch) from which each applies;
  ``gains`` complex128 (nsol, nchan, nstand, npol): CORRECTIONS (1 / g) multiplied onto the
  cable-corrected voltages, 0 = flagged. These two are all that ``calibration.gains_table`` reads.
* ``flags`` bool and ``flag_reason`` str (nsol, nstand, npol) (reasons as
  :data:`bf_epic_blocks.imaging.skycal.REASONS`; '' for good inputs).
* quality, float64 (nsol, nstand, npol): ``gain_amp`` |g|, ``residual`` (relative model residual),
  ``power`` (autocorrelation), ``power_per_gain``, ``delay_s`` (the smoothing fit's delay);
  ``converged`` bool (nsol, nchan, npol).
* ``freq_hz`` (nchan,), ``stand_ids`` (nstand,), ``time_unix`` (nsol,) the middle of each solution's data,
  ``provenance`` a JSON string: the station, the model (sources, altitudes, apparent fluxes, pattern),
  the solver's settings, the integration, the software version.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["TablePart", "write_gain_table", "gain_table_png", "read_solved_table"]

_QUALITY = ("gain_amp", "residual", "power", "power_per_gain", "delay_s")


class TablePart:
    """The solutions of one table file as the file holds them (complex64 corrections, flags, reasons,
    quality), in arrays made once for ``capacity`` solutions at the first and filled in place: a solver
    that runs for weeks holds one part, and its memory does not grow while the part fills (the arrays'
    pages are written when made). ``capacity`` None: no limit (the arrays double when full).

    At the whole band (784 channels, 256 stands, 2 pols) a solution is 3.1 MB of corrections (the
    solver's own complex128 gains and corrections, 12 MB, are not kept)."""

    def __init__(self, capacity=None):
        self.capacity = None if capacity is None else int(capacity)
        self.n = 0
        self._a = None

    def __len__(self):
        return self.n

    def _make(self, sol, cap):
        nchan, nant, npol = sol.corrections.shape
        shapes = {"gains": ((nchan, nant, npol), np.complex64), "flags": ((nant, npol), bool),
                  "flag_reason": ((nant, npol), "U16"), "converged": ((nchan, npol), bool)}
        for k in _QUALITY:
            shapes[k] = ((nant, npol), np.float64 if k == "delay_s" else np.float32)
        a = {}
        for k, (shp, dt) in shapes.items():
            a[k] = np.empty((cap,) + shp, dt)
            a[k].fill(0 if a[k].dtype.kind != "U" else "")          # the pages now, not as the part fills
            if self._a is not None:
                a[k][:self.n] = self._a[k][:self.n]
        self._a = a

    def add(self, sol):
        """Append a :class:`~bf_epic_blocks.imaging.skycal.Solution`'s table entries (a full part refuses)."""
        if self.capacity is not None and self.n >= self.capacity:
            raise ValueError(f"TablePart: the part holds {self.capacity} solutions already")
        if self._a is None:
            self._make(sol, self.capacity or 16)
        elif self.n == len(self._a["gains"]):
            self._make(sol, 2 * self.n)
        i, a = self.n, self._a
        a["gains"][i] = sol.corrections
        a["flags"][i] = sol.flags
        a["flag_reason"][i] = sol.reasons
        a["converged"][i] = sol.quality["converged"]
        for k in _QUALITY:
            a[k][i] = sol.quality[k]
        self.n += 1

    def arrays(self) -> dict:
        """The filled entries: {name: (n, ...) array} (views, not copies)."""
        return {} if self._a is None else {k: v[:self.n] for k, v in self._a.items()}

    def entry(self, i=-1) -> dict:
        """Solution ``i``'s corrections, flags and reasons: {'gains': (nchan, nstand, npol), ...}."""
        i = range(self.n)[i]
        return {k: self._a[k][i] for k in ("gains", "flags", "flag_reason")}


def write_gain_table(path, valid_from, solutions, *, freq_hz, stand_ids, time_unix, provenance):
    """Write the solutions (a list of :class:`~bf_epic_blocks.imaging.skycal.Solution`, or a
    :class:`TablePart`) to ``path`` (.npz), atomically (a temporary file renamed over the old one, so a
    reader never sees half a table)."""
    from .. import __version__
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not isinstance(solutions, TablePart):
        part = TablePart(len(solutions))
        for s in solutions:
            part.add(s)
        solutions = part
    arrays = {
        "valid_from": np.asarray(valid_from, np.int64),
        # complex64: a solution is good to ~1e-3, and a live table is rewritten at every solution
        **solutions.arrays(),
        "freq_hz": np.asarray(freq_hz, np.float64),
        "stand_ids": np.asarray(stand_ids, np.int64),
        "time_unix": np.asarray(time_unix, np.float64),
        "provenance": np.array(json.dumps({**provenance, "software": f"bf_epic_blocks {__version__}"})),
    }
    tmp = path.with_name(path.name + ".tmp.npz")
    # uncompressed: gains are noise-like to zlib, and compressing a part of 60 whole-band solutions costs
    # seconds of a CPU the pipeline needs
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return path


def read_solved_table(path) -> dict:
    """Every array of a solved table as a dict (``provenance`` parsed from JSON)."""
    with np.load(path, allow_pickle=False) as z:
        out = {k: z[k] for k in z.files}
    if "provenance" in out:
        out["provenance"] = json.loads(str(out["provenance"]))
    return out


def gain_table_png(path, table_path=None, *, table=None, solution=-1, title=None):
    """A PNG of one solution: amplitude and phase of every input's correction across the band, per pol,
    good inputs as thin lines, and a strip per pol marking each flagged input with its reason.

    Give ``table_path`` (an .npz :func:`write_gain_table` wrote) or ``table`` (its dict)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    t = table if table is not None else read_solved_table(table_path)
    g = np.asarray(t["gains"])[solution]                                   # (c, a, p) corrections
    flags = np.asarray(t["flags"])[solution]
    reasons = np.asarray(t["flag_reason"])[solution]
    f = np.asarray(t["freq_hz"]) / 1e6
    nchan, nant, npol = g.shape
    fig = Figure(figsize=(11, 8), dpi=100)
    FigureCanvasAgg(fig)
    axs = fig.subplots(3, npol, squeeze=False, gridspec_kw={"height_ratios": [3, 3, 1.2]})
    names = "XY"
    colours = {"station": "0.6", "no-power": "k", "deaf": "tab:blue", "noisy": "tab:red", "residual": "tab:orange",
               "few-baselines": "tab:purple"}
    x = f if nchan > 1 else np.array([0.0, 1.0]) + f[0]
    for p in range(npol):
        good = ~flags[:, p]
        gg = g[:, good, p]
        amp = np.abs(gg)
        med = np.median(amp, axis=1, keepdims=True) if gg.size else 1.0
        ax = axs[0, p]
        y = amp / np.where(med > 0, med, 1)
        ax.plot(x, y if nchan > 1 else np.repeat(y, 2, axis=0), lw=0.5, alpha=0.5)
        ax.set_ylabel("|correction| / median")
        ax.set_title(f"pol {names[p] if p < 2 else p}: {int(good.sum())} good, {int((~good).sum())} flagged")
        ax = axs[1, p]
        ph = np.degrees(np.angle(gg))
        ax.plot(x, ph if nchan > 1 else np.repeat(ph, 2, axis=0), lw=0.5, alpha=0.5)
        ax.set_ylabel("phase (deg)")
        ax.set_xlabel("frequency (MHz)")
        ax.set_ylim(-185, 185)
        ax = axs[2, p]
        for r, c in colours.items():
            idx = np.flatnonzero(reasons[:, p] == r)
            if idx.size:
                ax.scatter(idx, np.zeros(idx.size), marker="|", s=200, color=c, label=f"{r} ({idx.size})")
        ax.set_xlim(-1, nant)
        ax.set_yticks([])
        ax.set_xlabel("input (stand index)")
        if (~good).any():
            ax.legend(loc="upper right", fontsize=7, ncol=3, frameon=False)
    prov = t.get("provenance") or {}
    model = prov.get("model", {})
    fig.suptitle(title or f"gain solution {solution % len(t['valid_from'])} of {len(t['valid_from'])}: "
                 f"{prov.get('station', '')}, model {', '.join(model.get('sources', []))}")
    fig.tight_layout()
    from .quicklook import save_figure
    save_figure(fig, path)
    return path
