"""The watchlist's spectra of each target at each image: a streaming HDF5 file, and a dynamic-spectrum PNG.

File layout (docs/guide/watch.md)
---------------------------------
Root attributes: ``format`` ('bf_epic_blocks watchlist'), ``targets`` (group names, in order),
``products``. Root dataset ``complete`` (bool scalar): True once the writer closed cleanly.
One group per target, named by the target:

``data``         (ntime, nchan, nprod) float32, the target's direction; resizable along time;
``offset_data``  (ntime, noff, nchan, nprod) float32, its offsets' directions (targets with offsets);
``time_unix``    (ntime,) float64, seconds since 1970-01-01 UTC (Unix time);
``freq_hz``      (nchan,) float64, channel centres;
``ra_deg``, ``dec_deg`` (ntime,) float64, the ICRS direction used at each time (bodies only).
Attributes: ``kind``, ``products``, ``offsets_deg`` ((noff, 2) [east_deg, north_deg]), ``start``/``stop``
(ISO UTC, '' without a window), ``ra_deg``/``dec_deg`` (fixed targets), ``body`` (bodies).

The writer opens the file in HDF5's single-writer/multiple-reader mode (SWMR; ``libver='latest'``)
and flushes after every write, so a reader (``h5py.File(path, 'r', libver='latest', swmr=True)``,
then ``dataset.refresh()``) sees each write as it lands. Everything is created before SWMR starts:
the writer adds no groups or attributes later, only rows. A writer given ``flush_s`` holds the rows of
up to that many seconds of data (and at most ``max_pending_bytes``) and writes them together: each
HDF5 write and resize costs the same for 64 rows as for 1,000, so a pipeline's writer makes one a
second, not one a gulp. The file has no chunk cache (``rdcc_nbytes=0``): the writer only appends, so a
cache saves nothing, and under HDF5's default cache (1 MiB a dataset) the library's memory in use grows
with every chunk appended, for minutes of data, in a file that stays open for a whole run.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..sky.watch import parse_targets

__all__ = ["WatchWriter", "read_watch", "dynamic_spectrum_png", "FORMAT"]

FORMAT = "bf_epic_blocks watchlist"
_CHUNK_BYTES = 1 << 20    # a chunk of a target's rows: large enough that a second of 0.64-ms images is a
                          # few chunks, small enough that a short run wastes little


def _iso(t) -> str:
    return "" if t is None else t.utc.isot


class WatchWriter:
    """Append the watch targets' spectra to an HDF5 file as images are made (layout: module doc).

    path : the file (overwritten). targets : :class:`~bf_epic_blocks.sky.watch.WatchTarget` list or
    entries for :func:`~bf_epic_blocks.sky.watch.parse_targets`. freq_hz : (nchan,) channel centres.
    products : product names (``['I']``), the last axis of the data. chunk_rows : rows per HDF5 chunk
    (default: about 1 MiB of a target's data). flush_s : hold rows until they span this many seconds
    of data, then write them (None: write at every :meth:`append`); max_pending_bytes bounds what is
    held. :attr:`nrows` counts the rows in the file, :attr:`rows` those appended. Use as a context
    manager, or call :meth:`close` (which writes what is held).
    """

    def __init__(self, path, targets, freq_hz, products, *, chunk_rows: int | None = None,
                 flush_s: float | None = None, max_pending_bytes: int = 64 << 20):
        import h5py
        self.targets = parse_targets(targets)
        self.freq_hz = np.asarray(freq_hz, np.float64).reshape(-1)
        self.products = [str(p) for p in products]
        self.nchan, self.nprod = self.freq_hz.size, len(self.products)
        self.ndir = sum(t.ndir for t in self.targets)
        self.nrows = 0
        self.flush_s = None if flush_s is None else float(flush_s)
        self._cap = max(1, int(max_pending_bytes) // max(1, self.ndir * self.nchan * self.nprod * 4))
        self._npend = 0
        self._pend = None          # (data (ndir, cap, nchan, nprod), time (cap,), ra_dec (cap, ntarget, 2))
        row = self.nchan * self.nprod * 4
        rows = int(chunk_rows) if chunk_rows is not None else max(1, min(4096, _CHUNK_BYTES // max(row, 1)))
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = f = h5py.File(self.path, "w", libver="latest", rdcc_nbytes=0)
        f.attrs["format"] = FORMAT
        f.attrs["targets"] = [t.name for t in self.targets]
        f.attrs["products"] = self.products
        self._complete = f.create_dataset("complete", data=False)
        self._groups = []
        for t in self.targets:
            g = f.create_group(t.name)
            g.attrs["kind"] = t.kind
            g.attrs["products"] = self.products
            g.attrs["offsets_deg"] = np.asarray(t.offsets_deg, np.float64).reshape(-1, 2)
            g.attrs["start"], g.attrs["stop"] = _iso(t.start), _iso(t.stop)
            if t.moving:
                g.attrs["body"] = t.body
            else:
                g.attrs["ra_deg"], g.attrs["dec_deg"] = t.ra_deg, t.dec_deg
            g.create_dataset("freq_hz", data=self.freq_hz)
            ds = {"data": g.create_dataset("data", (0, self.nchan, self.nprod), "f4", chunks=(rows, self.nchan, self.nprod),
                                           maxshape=(None, self.nchan, self.nprod)),
                  "time_unix": g.create_dataset("time_unix", (0,), "f8", chunks=(max(rows, 512),), maxshape=(None,))}
            if t.offsets_deg:
                noff = len(t.offsets_deg)
                ds["offset_data"] = g.create_dataset("offset_data", (0, noff, self.nchan, self.nprod), "f4",
                                                     chunks=(max(1, rows // noff), noff, self.nchan, self.nprod),
                                                     maxshape=(None, noff, self.nchan, self.nprod))
            if t.moving:
                for k in ("ra_deg", "dec_deg"):
                    ds[k] = g.create_dataset(k, (0,), "f8", chunks=(max(rows, 512),), maxshape=(None,))
            self._groups.append(ds)
        f.swmr_mode = True   # readers may open the file from here on
        f.flush()

    def append(self, time_unix, data, ra_dec=None) -> None:
        """Add ``n`` rows to every target: written and flushed now, or held until ``flush_s`` of data are.

        time_unix : (n,) float64 Unix seconds (UTC). data : (n, ndir, nchan, nprod), directions ordered
        as :func:`~bf_epic_blocks.sky.watch.target_lm` orders them (a target, then its offsets; ndir is
        ntarget without offsets). ra_dec : (n, ntarget, 2) ICRS degrees of each target at each time,
        required when a target is a body (only the bodies' values are stored).
        """
        t = np.asarray(time_unix, np.float64).reshape(-1)
        n = t.size
        d = np.asarray(data, np.float32)
        want = (n, self.ndir, self.nchan, self.nprod)
        if d.shape != want:
            raise ValueError(f"data must have shape (n, ndir, nchan, nprod) = {want}, got {d.shape}")
        moving = any(tg.moving for tg in self.targets)
        if moving:
            if ra_dec is None:
                raise ValueError(f"ra_dec (n, ntarget, 2) is needed: targets "
                                 f"{[tg.name for tg in self.targets if tg.moving]} are bodies")
            rd = np.asarray(ra_dec, np.float64)
            if rd.shape != (n, len(self.targets), 2):
                raise ValueError(f"ra_dec must have shape (n, ntarget, 2) = {(n, len(self.targets), 2)}, got {rd.shape}")
        if self.flush_s is None:
            self._write(t, np.moveaxis(d, 1, 0), rd if moving else None)
            return
        if self._pend is None:
            self._pend = (np.empty((self.ndir, self._cap, self.nchan, self.nprod), np.float32),
                          np.empty(self._cap), np.empty((self._cap, len(self.targets), 2)))
        pd, pt, pr = self._pend
        i = 0
        while i < n:
            k = min(n - i, self._cap - self._npend)
            a, b = self._npend, self._npend + k
            pd[:, a:b] = np.moveaxis(d[i:i + k], 1, 0)
            pt[a:b] = t[i:i + k]
            if moving:
                pr[a:b] = rd[i:i + k]
            self._npend, i = b, i + k
            if self._npend == self._cap or pt[self._npend - 1] - pt[0] >= self.flush_s:
                self.flush()

    @property
    def rows(self) -> int:
        """Rows appended: those in the file and those held for the next write."""
        return self.nrows + self._npend

    def flush(self) -> None:
        """Write the rows held (nothing when none are)."""
        if self._npend:
            pd, pt, pr = self._pend
            m, self._npend = self._npend, 0
            self._write(pt[:m], pd[:, :m], pr[:m])

    def _write(self, t, d, rd):
        """Write rows: t (n,), d (ndir, n, nchan, nprod), rd (n, ntarget, 2) or None; resize, write, flush."""
        n = t.size
        lo, hi = self.nrows, self.nrows + n
        col = 0
        for i, (tg, ds) in enumerate(zip(self.targets, self._groups)):
            for v in ds.values():
                v.resize(hi, axis=0)
            ds["data"][lo:hi] = d[col]
            if tg.offsets_deg:
                ds["offset_data"][lo:hi] = np.moveaxis(d[col + 1:col + tg.ndir], 0, 1)
            ds["time_unix"][lo:hi] = t
            if tg.moving:
                ds["ra_deg"][lo:hi], ds["dec_deg"][lo:hi] = rd[:, i, 0], rd[:, i, 1]
            col += tg.ndir
        self.nrows = hi
        self._f.flush()

    @property
    def groups(self):
        """Per target, its datasets by name (``data``, ``time_unix``, ...), in target order."""
        return self._groups

    def close(self) -> None:
        """Mark the file complete and close it (again: nothing)."""
        if self._f is None:
            return
        self.flush()
        self._complete[()] = True
        self._f.close()
        self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_watch(path) -> dict:
    """{target name: dict} of a watchlist file, in the file's target order; readable while a writer
    has it open (SWMR). Each dict: ``time`` (astropy Time, UTC), ``time_unix``, ``freq_hz``, ``data``
    (ntime, nchan, nprod), ``products``, ``kind``, ``offsets_deg`` (noff, 2), ``start``/``stop``
    (Time or None), and as present ``offset_data``, ``ra_deg``/``dec_deg`` (float for fixed targets,
    (ntime,) arrays for bodies), ``body``. Rows are those whose time was written (a reader may
    catch an append between its datasets)."""
    import h5py
    from astropy.time import Time
    out = {}
    with h5py.File(path, "r", libver="latest", swmr=True) as f:
        for name in [str(n) for n in f.attrs["targets"]]:
            g = f[name]
            for ds in g.values():
                ds.refresh()
            n = min(g[k].shape[0] for k in g if k != "freq_hz")
            t = g["time_unix"][:n]
            e = {"time": Time(t, format="unix", scale="utc"), "time_unix": t, "freq_hz": g["freq_hz"][:],
                 "data": g["data"][:n], "products": [str(p) for p in g.attrs["products"]],
                 "kind": str(g.attrs["kind"]), "offsets_deg": np.asarray(g.attrs["offsets_deg"])}
            for k in ("start", "stop"):
                e[k] = Time(str(g.attrs[k]), scale="utc") if g.attrs[k] else None
            if "offset_data" in g:
                e["offset_data"] = g["offset_data"][:n]
            if "body" in g.attrs:
                e["body"] = str(g.attrs["body"])
                e["ra_deg"], e["dec_deg"] = g["ra_deg"][:n], g["dec_deg"][:n]
            else:
                e["ra_deg"], e["dec_deg"] = float(g.attrs["ra_deg"]), float(g.attrs["dec_deg"])
            out[name] = e
    return out


class BinnedSpectra:
    """The last ``nbins`` time bins of ``bin_n`` images each of several targets' spectra, as NaN-aware
    means, kept in memory for the quicklook PNGs: a minute of 0.64-ms images is ~94,000 rows a target,
    more than a PNG shows and more than it should re-read from the file each time.

    ``add(t (n,), data (n, ntarget, nchan))`` in time order; ``rows()`` -> (t (nb,), means (nb, ntarget,
    nchan)) of the bins completed so far and the one being filled, oldest first.
    """

    def __init__(self, ntarget, nchan, bin_n, nbins):
        import collections
        self.bin_n = max(1, int(bin_n))
        self._done = collections.deque(maxlen=max(1, int(nbins)))
        self._sum = np.zeros((ntarget, nchan))
        self._cnt = np.zeros((ntarget, nchan))
        self._tsum, self._n = 0.0, 0

    def add(self, t, data):
        t = np.asarray(t, np.float64)
        data = np.asarray(data)
        i = 0
        while i < t.size:
            k = min(t.size - i, self.bin_n - self._n)
            part = data[i:i + k]
            # summed in float64 as they are; a non-finite sum means a NaN row (a target down, a dead
            # channel): only then the NaN-aware sum (a gulp of 100 targets' spectra is 20 MB)
            s = part.sum(axis=0, dtype=np.float64)
            if np.isfinite(s).all():
                self._sum += s
                self._cnt += k
            else:
                ok = np.isfinite(part)
                self._sum += np.where(ok, part, 0.0).sum(axis=0, dtype=np.float64)
                self._cnt += ok.sum(axis=0)
            self._tsum += float(t[i:i + k].sum())
            self._n += k
            i += k
            if self._n == self.bin_n:
                self._done.append(self._current())
                self._sum[:] = 0.0
                self._cnt[:] = 0.0
                self._tsum, self._n = 0.0, 0

    def _current(self):
        with np.errstate(invalid="ignore", divide="ignore"):
            return self._tsum / self._n, np.where(self._cnt > 0, self._sum / np.maximum(self._cnt, 1), np.nan)

    def rows(self):
        done = list(self._done) + ([self._current()] if self._n else [])
        if not done:
            return np.zeros(0), np.zeros((0,) + self._sum.shape)
        return np.array([d[0] for d in done]), np.stack([d[1] for d in done])


def dynamic_spectrum_png(path_png, time_unix, freq_hz, data, title="") -> str:
    """Write a PNG: the dynamic spectrum (UTC on x, MHz on y) above its band-averaged light curve.

    time_unix : (ntime,) Unix seconds (UTC); freq_hz : (nchan,); data : (ntime, nchan), one product
    (NaN where nothing was recorded). The colour scale spans the 1st to 99th percentiles. Returns the path.
    """
    import matplotlib.dates as mdates
    from astropy.time import Time
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t = np.asarray(time_unix, np.float64).reshape(-1)
    f = np.asarray(freq_hz, np.float64).reshape(-1) / 1e6
    d = np.asarray(data, np.float64)
    if d.shape != (t.size, f.size):
        raise ValueError(f"data must have shape (ntime, nchan) = {(t.size, f.size)}, got {d.shape}")
    x = mdates.date2num(Time(t, format="unix", scale="utc").datetime) if t.size else np.zeros(0)
    fig = Figure(figsize=(10, 6), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax, ax2 = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    finite = d[np.isfinite(d)]
    if t.size and f.size:
        dx = np.median(np.diff(x)) if t.size > 1 else 1.0 / 86400
        df = np.median(np.diff(f)) if f.size > 1 else 0.025
        lo, hi = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
        im = ax.imshow(d.T, aspect="auto", origin="lower", interpolation="nearest", cmap="viridis",
                       vmin=lo, vmax=hi if hi > lo else lo + 1,
                       extent=(x[0] - dx / 2, x[-1] + dx / 2, f[0] - df / 2, f[-1] + df / 2))
        fig.colorbar(im, ax=[ax, ax2], label="power")   # on both rows: keeps their time axes aligned
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(d).any(axis=1)
            curve = np.full(t.size, np.nan)
            curve[ok] = np.nanmean(d[ok], axis=1)
        ax2.plot(x, curve, lw=1)
    ax.set_ylabel("frequency (MHz)")
    ax.set_title(title)
    ax2.set_ylabel("band mean")
    day = Time(t[0], format="unix", scale="utc").isot[:10] if t.size else ""
    ax2.set_xlabel(f"UTC ({day})")
    if t.size > 1 and t[-1] - t[0] < 20:      # under ~20 s the ticks need the milliseconds
        from matplotlib.ticker import FuncFormatter
        ax2.xaxis.set_major_formatter(FuncFormatter(lambda v, _: mdates.num2date(v).strftime("%H:%M:%S.%f")[:-3]))
    else:
        ax2.xaxis.set_major_formatter(mdates.DateFormatter("%H:%M:%S"))
    from .quicklook import save_figure
    save_figure(fig, path_png)
    return str(path_png)
