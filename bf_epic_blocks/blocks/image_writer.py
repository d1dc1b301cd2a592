"""ImageWriterBlock: image sequences to FITS / pixel tables / PNG quicklooks on disk.

A sink for the imagers' output (docs/HEADERS.md): grids become FITS cubes with a zenith-centred SIN
WCS (one file per integration; channels with uneven spacing are split into runs of even spacing)
and an all-sky PNG of the channel-mean of the first product; pixel lists and tracked patches
become pixel tables (FITS binary tables) and a small PNG of the patch. The writing itself lives
in :mod:`bf_epic_blocks.io.fits` and :mod:`bf_epic_blocks.io.quicklook`.
"""
from __future__ import annotations

import logging
import os
import warnings

import numpy as np

from ..imaging.calibration import FS_HZ
from ..imaging.pixels import LMGrid
from ._compat import bfp, span_array, to_numpy

log = logging.getLogger(__name__)


def channel_runs(freq_hz):
    """Index runs [(start, stop)] over which the channel spacing is constant (a FITS FREQ axis each).

    These are the channel blocks the writer puts in separate files (``_r<index>`` when more than one).
    """
    f = np.asarray(freq_hz, dtype=np.float64)
    runs, start = [], 0
    while start < len(f):
        stop = start + 1
        if stop < len(f):
            step = f[stop] - f[start]
            while stop < len(f) and np.isclose(f[stop] - f[stop - 1], step, rtol=1e-9, atol=1e-3):
                stop += 1
        runs.append((start, stop))
        start = stop
    return runs


_even_runs = channel_runs


class ImageWriterBlock(bfp.SinkBlock):
    """Write each output frame (one integration) of an imager.

    outdir, prefix : where and under which name; fits / png / table : what to write.
    location : astropy EarthLocation of the station (default: from the header's station lat/lon).
    label_sources : catalogue sources (plus the Sun) drawn on the PNGs when above the horizon.
    pixels_fn : for tracked patches, the imager's ``pixels(time_tag)`` function, so each pixel
                table carries the directions of its own integration (the header has the first).
    run_index : when the input holds only channel block ``run_index`` of a larger channel set (see
                :func:`channel_runs`), name its files ``_r<run_index>`` as the whole set's would be.
    ``written`` lists the files written. Each file records, as NONFINIT, the non-finite voltage samples
    zeroed upstream in its integration (from the tally the header's ``nonfinite`` names; 0 without one).
    """

    def __init__(self, iring, outdir, prefix="image", fits=True, png=True, table=False, location=None,
                 label_sources=True, pixels_fn=None, *args, run_index=None, **kwargs):
        super().__init__(iring, *args, **kwargs)
        self.outdir, self.prefix = str(outdir), prefix
        self.do_fits, self.do_png, self.do_table = fits, png, table
        self.location, self.label_sources, self.pixels_fn = location, label_sources, pixels_fn
        self.run_index = run_index
        self.written = []
        self.frames = 0

    def on_sequence(self, iseq):
        from astropy.coordinates import EarthLocation
        hdr = iseq.header
        self.hdr = hdr
        os.makedirs(self.outdir, exist_ok=True)
        st = hdr.get("station", {})
        loc = self.location
        if loc is None and "lat_deg" in st:
            loc = EarthLocation.from_geodetic(st["lon_deg"], st["lat_deg"], st.get("elev_m", 0.0))
        if loc is None:
            raise ValueError("ImageWriterBlock: no station location: give location= or a header station with lat/lon")
        self.loc = loc
        self.freq = np.asarray(hdr.get("freq_hz"), dtype=np.float64)
        self.products = list(hdr["pol_products"])
        pix = hdr["pixels"]
        self.grid = None
        if pix["kind"] == "grid":
            from ..imaging.pixels import lm_grid
            self.grid = lm_grid(pix["size"], cell=pix["cell"])
        self.int_ticks = int(hdr["imager"]["integration_ticks"])
        from .nonfinite import get_tally
        self.tally = get_tally(hdr)
        self.acc = int(hdr["imager"].get("accumulate_frames", 1))
        self.seq_index = getattr(self, "seq_index", -1) + 1
        self.frames_in_seq = 0
        self._pointings = (0, None)

    def _time(self, j):
        from ..io.tbf import time_tag_to_time
        return time_tag_to_time(int(self.hdr["time_tag"]) + j * self.int_ticks)

    #: images whose zenith pointings (a FITS image's WCS) are computed in one astropy transform: one
    #: image's transform costs ~15 ms of interpreter time, 64 images' ~20 ms (this thread holds the
    #: GIL throughout, so a per-image transform slowed the source and imager threads)
    POINTING_BATCH = 64

    def _pointing(self, j):
        """(ra_deg, dec_deg, north_deg) of the zenith at the start of integration ``j``."""
        from ..sky import zenith_pointings
        from ..io.tbf import time_tag_to_time
        j0, batch = self._pointings
        if batch is None or not j0 <= j < j0 + len(batch[0]):
            tags = int(self.hdr["time_tag"]) + (j + np.arange(self.POINTING_BATCH)) * self.int_ticks
            j0, batch = j, zenith_pointings(time_tag_to_time(tags), self.loc)
            self._pointings = (j0, batch)
        return tuple(float(v[j - j0]) for v in batch)

    def _labels(self, t):
        if not self.label_sources:
            return None
        from ..sky import KNOWN_SOURCES, icrs_to_lm
        names, ra, dec = [], [], []
        for s in KNOWN_SOURCES.values():
            names.append(s.name)
            ra.append(s.ra_deg)
            dec.append(s.dec_deg)
        lm, alt = icrs_to_lm(np.array(ra), np.array(dec), t, self.loc)
        out = [(n, float(l), float(m)) for n, (l, m), a in zip(names, lm, alt) if np.isfinite(a) and a > 0]
        try:  # the Sun is near: go to AltAz directly (via ICRS would add a parallax of degrees)
            from astropy.coordinates import AltAz, get_body
            from ..station.offline import iers_table
            iers_table()
            sun = get_body("sun", t, self.loc).transform_to(AltAz(obstime=t, location=self.loc))
            if sun.alt.deg > 0:
                alt_r, az_r = sun.alt.rad, sun.az.rad
                out.append(("Sun", float(np.cos(alt_r) * np.sin(az_r)), float(np.cos(alt_r) * np.cos(az_r))))
        except Exception as e:  # decoration only
            log.debug("no Sun position: %s", e)
        return out

    def on_data(self, ispan):
        from ..io import fits as fits_out, quicklook
        data = to_numpy(span_array(ispan))
        imager = self.hdr["imager"]
        common = dict(method=f"{imager['kind']}:{imager['method']}", precision=imager["precision"],
                      telescope=self.hdr.get("station", {}).get("name"),
                      int_time_s=self.int_ticks / FS_HZ, nantenna=imager.get("nant_used"))
        for k in range(data.shape[0]):
            j = self.frames_in_seq
            t = self._time(j)
            stem = os.path.join(self.outdir, f"{self.prefix}_s{self.seq_index:02d}_i{j:04d}")
            frame = data[k]
            common["nonfinite"] = self.tally.count(j * self.acc, (j + 1) * self.acc) if self.tally else 0
            if self.grid is not None:
                runs = _even_runs(self.freq)
                width = float(self.freq[1] - self.freq[0]) if len(self.freq) > 1 else None
                if self.run_index is not None:  # one block of a larger set: name and width as in the set
                    if len(runs) != 1:
                        raise ValueError(f"ImageWriterBlock: run_index={self.run_index} given, but the channels "
                                         f"are {len(runs)} runs of even spacing, not one")
                    if width is None:
                        width = self.hdr.get("chan_bw_hz")
                for r, (a, b) in enumerate(runs):
                    rstem = (stem if len(runs) == 1 and self.run_index is None
                             else f"{stem}_r{r if self.run_index is None else self.run_index}")
                    if self.do_fits:
                        self.written += fits_out.write_fits_image(
                            f"{rstem}.fits", frame[a:b], self.grid, self.freq[a:b], self.products, t, self.loc,
                            chan_width_hz=width if b - a == 1 else None, pointing=self._pointing(j), **common)
                    if self.do_png:  # channel mean of the first product, one PNG per FITS file
                        with np.errstate(all="ignore"), warnings.catch_warnings():
                            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels below the horizon
                            mean = np.nanmean(frame[a:b, 0], axis=0)
                        title = (f"{self.hdr.get('station', {}).get('name', '')} {self.products[0]}  {t.isot[:19]} UTC  "
                                 f"{self.freq[a] / 1e6:.2f}-{self.freq[b - 1] / 1e6:.2f} MHz")
                        self.written.append(quicklook.quicklook_png(f"{rstem}.png", mean, self.grid, title=title,
                                                                    sources=self._labels(t)))
            else:
                lm = np.asarray(self.hdr["pixels"]["lm"])
                if self.hdr["pixels"]["kind"] == "track" and self.pixels_fn is not None:
                    lm = np.asarray(self.pixels_fn(int(self.hdr["time_tag"]) + j * self.int_ticks))
                if self.do_table or self.do_fits:
                    self.written.append(fits_out.write_pixel_table(f"{stem}_pixels.fits", frame, lm, self.freq,
                                                                   self.products, t, self.loc, **common))
                if self.do_png:
                    self.written.append(_patch_png(f"{stem}.png", frame, lm, self.products, t))
            self.frames_in_seq += 1
            self.frames += 1


def _patch_png(path, frame, lm, products, t):
    """A small PNG of a square pixel patch (tracking), channel mean of the first product."""
    from matplotlib.figure import Figure
    n = int(round(np.sqrt(lm.shape[0])))
    vals = np.nanmean(frame[:, 0], axis=0)
    fig = Figure(figsize=(4.6, 4))
    ax = fig.add_subplot(1, 1, 1)
    if n * n == lm.shape[0]:
        im = ax.imshow(vals.reshape(n, n), origin="lower", cmap="inferno")
        ax.set_xlabel("patch x (towards East)")
        ax.set_ylabel("patch y (towards North / up)")
    else:
        im = ax.scatter(lm[:, 0], lm[:, 1], c=vals, cmap="inferno")
        ax.invert_xaxis()
        ax.set_xlabel("l (East)")
        ax.set_ylabel("m (North)")
    ax.set_title(f"{products[0]} {t.isot[:19]} UTC", fontsize=9)
    fig.colorbar(im, ax=ax, label="power (uncalibrated)")
    fig.savefig(path, dpi=90)
    return path


def image_writer(iring, outdir, *args, **kwargs):
    """Factory for :class:`ImageWriterBlock`."""
    return ImageWriterBlock(iring, outdir, *args, **kwargs)
