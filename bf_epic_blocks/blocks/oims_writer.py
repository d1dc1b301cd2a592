"""OimsWriterBlock: an imager's images on Orville's grid written into the station's OIMS image database.

The imager before it images the directions of :func:`~bf_epic_blocks.io.oims.oims_lm` above the horizon (a
pixel list, row-major), so that each OIMS pixel holds the sky at the direction the station's tools assume
(the zenith between the four middle pixels, which this package's own grids put on a pixel). The block
places them into (nchan, nproducts, ngrid, ngrid) images, 0 below the horizon, and appends one integration
each to an hourly file named as Orville names its own::

    <output.dir>/<MJD>_<HH>0000_<first channel MHz>MHz_<last channel MHz>MHz.oims

with the integration's start (MJD UTC), length, mean LST, the zenith's RA and Dec as the phase centre,
and, per channel, the mask of channels the interference flagger left wholly flagged.

With ``lwatv``, each integration is also drawn as the station's LWATV view
(:func:`~bf_epic_blocks.io.quicklook.lwatv_png`: I and |V| of one channel, the catalogue's sources and
the Sun labelled, the band's spectrum below, as the mean of I within 45 degrees of the zenith) under
Orville's names, ``<output.dir>/lwatv/<MJD>/<MJD>_<HHMMSS>_<MHz>MHz.png``, and
``<output.dir>/lwatv/lwatv_timestamp`` holds the latest one's ``MJD:HH:MM:SS``. It is drawn in this
block's thread, once an integration.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..conventions import FS_HZ
from ..io.oims import OimsWriter, oims_lm
from ._compat import bfp, span_array, to_numpy

__all__ = ["OimsWriterBlock", "oims_pixels"]

log = logging.getLogger(__name__)


def oims_pixels(ngrid):
    """(lm (npix, 2), keep (ngrid, ngrid) bool): the directions of Orville's ngrid x ngrid grid above the
    horizon, row-major, for the imager before an :class:`OimsWriterBlock`."""
    lm = oims_lm(ngrid)
    keep = (lm ** 2).sum(axis=-1) < 1.0
    return lm[keep], keep


class OimsWriterBlock(bfp.SinkBlock):
    """Append each image of an imager on :func:`oims_pixels` (header as DFTImagerBlock's with a pixel list:
    (time, freq, pol, pixel)) to the hourly OIMS file of ``outdir`` (module docstring).

    ngrid : the grid's side (the imager's pixels are ``oims_pixels(ngrid)``). station : the name in the
    files' headers (default: the header's station name). lwatv, lwatv_mhz : draw the LWATV view of the
    channel nearest lwatv_mhz (default the band's middle) at each integration (module docstring). ``integrations`` counts the integrations, ``files``
    lists the files (in order of first use).
    """

    def __init__(self, iring, outdir, ngrid, station=None, lwatv=False, lwatv_mhz=None, **kwargs):
        super().__init__(iring, **kwargs)
        self.outdir, self.ngrid, self.station = Path(outdir), int(ngrid), station
        self.lwatv, self.lwatv_mhz, self.pngs = bool(lwatv), lwatv_mhz, []
        self.lm, self.keep = oims_pixels(self.ngrid)
        self.lm_grid = oims_lm(self.ngrid)
        self._w = self._name = None
        self.integrations, self.files = 0, []

    def define_valid_input_spaces(self):
        return ("system", "cuda")

    def on_sequence(self, iseq):
        hdr = iseq.header
        st = hdr.get("station", {})
        if "lat_deg" not in st or "lon_deg" not in st:
            raise ValueError("OimsWriterBlock: the header's station has no lat_deg/lon_deg: the phase centre and "
                             "LST cannot be written")
        pix = hdr.get("pixels", {})
        if pix.get("kind") not in ("list", "track") or len(pix.get("lm", [])) != int(self.keep.sum()):
            raise ValueError(f"OimsWriterBlock: the imager must image oims_pixels({self.ngrid}) "
                             f"({int(self.keep.sum())} pixels), got pixels of kind {pix.get('kind')!r} "
                             f"({len(pix.get('lm', []))} pixels)")
        if not np.allclose(np.asarray(pix["lm"], np.float64), self.lm, rtol=0, atol=1e-12):
            raise ValueError(f"OimsWriterBlock: the imager's pixels are not oims_pixels({self.ngrid})")
        from astropy.coordinates import EarthLocation
        import astropy.units as u
        self.loc = EarthLocation.from_geodetic(float(st["lon_deg"]) * u.deg, float(st["lat_deg"]) * u.deg,
                                               float(st.get("elev_m", 0.0)) * u.m)
        self.name = str(self.station or st.get("name") or "")
        if not self.name:
            raise ValueError("OimsWriterBlock: no station name (give station= or a header station name)")
        self.freq = np.asarray(hdr["freq_hz"], np.float64)
        self.products = list(hdr["pol_products"])
        self.hdr = hdr
        self.int_ticks = int(hdr["imager"]["integration_ticks"])
        self.j = 0
        from .rfi_flag import get_flag_tally
        self.flag_tally = get_flag_tally(hdr)

    def _file_for(self, mjd):
        hour = int(np.floor((mjd % 1.0) * 24.0 + 1e-9))
        name = f"{int(mjd)}_{hour:02d}0000_{self.freq.min() / 1e6:.3f}MHz_{self.freq.max() / 1e6:.3f}MHz.oims"
        if name != self._name:
            self.close()
            path = self.outdir / name
            self._w = OimsWriter(path, self.name, tuple(self.products), self.ngrid, len(self.freq),
                                 append=path.exists())
            self._name = name
            if str(path) not in self.files:
                self.files.append(str(path))
            log.info("OimsWriterBlock: %s integrations -> %s", "appending" if self._w.nint else "writing", path)
        return self._w

    def on_data(self, ispan):
        from astropy.coordinates import AltAz, ICRS, SkyCoord
        import astropy.units as u
        from ..io.tbf import time_tag_to_time
        data = to_numpy(span_array(ispan))                                # (n, nchan, nprod, npix)
        tag0 = int(self.hdr["time_tag"])
        for k in range(data.shape[0]):
            start = time_tag_to_time(tag0 + self.j * self.int_ticks)
            mid = start + (0.5 * self.int_ticks / FS_HZ) * u.s
            cube = np.zeros((len(self.freq), len(self.products), self.ngrid, self.ngrid), np.float32)
            cube[..., self.keep] = data[k]
            zen = SkyCoord(alt=90 * u.deg, az=0 * u.deg, frame=AltAz(obstime=mid, location=self.loc)).transform_to(ICRS())
            lst = mid.sidereal_time("mean", longitude=self.loc.lon).hour / 24.0
            mask = None
            if self.flag_tally is not None:
                fpi = max(1, self.int_ticks // self.flag_tally.ticks_per_frame)
                frac = self.flag_tally.fraction(self.j * fpi, (self.j + 1) * fpi)
                if frac is not None and frac >= 1.0:
                    mask = np.ones(len(self.freq), bool)       # nothing was imaged
            self._file_for(start.mjd).add(cube, start_mjd=start.mjd, int_len_s=self.int_ticks / FS_HZ,
                                          freq_hz=self.freq, lst_turns=lst, center_ra_deg=zen.ra.deg,
                                          center_dec_deg=zen.dec.deg, mask=mask)
            if self.lwatv:
                self._draw_lwatv(cube, start, mid)
            self.j += 1
            self.integrations += 1

    def _draw_lwatv(self, cube, start, mid):
        """The LWATV PNG of this integration and the timestamp file (module docstring); a failure is logged
        and counted, never stops the recording."""
        import os
        from ..io.quicklook import lwatv_png
        from .image_writer import _labels
        if "I" not in self.products:
            if not getattr(self, "_lwatv_warned", False):
                log.warning("OimsWriterBlock: no LWATV view: the products %s have no I", self.products)
                self._lwatv_warned = True
            return
        want = self.freq[len(self.freq) // 2] if self.lwatv_mhz is None else float(self.lwatv_mhz) * 1e6
        c = int(np.argmin(np.abs(self.freq - want)))
        i = self.products.index("I")
        v = self.products.index("V") if "V" in self.products else None
        inner = self.keep & ((self.lm_grid ** 2).sum(axis=-1) < 0.5)        # within 45 deg of the zenith
        spectrum = cube[:, i][:, inner].mean(axis=1)
        d = start.datetime
        mjd = int(np.floor(start.mjd))
        folder = self.outdir / "lwatv" / str(mjd)
        path = folder / f"{mjd}_{d.hour:02d}{d.minute:02d}{d.second:02d}_{self.freq[c] / 1e6:.3f}MHz.png"
        try:
            loc = (self.loc.lon.deg, self.loc.lat.deg, self.loc.height.to_value("m"))
            lwatv_png(path, cube[c, i], None if v is None else np.abs(cube[c, v]), 130.0 / self.ngrid,
                      when=d.strftime("%Y/%m/%d %H:%M:%S UTC"), freq_hz=self.freq[c], labels=_labels(mid, loc),
                      spectrum=spectrum, spectrum_freq_hz=self.freq,
                      spectrum_label="mean of I within 45 deg of the zenith, per channel")
            self.pngs.append(str(path))
            ts = self.outdir / "lwatv" / "lwatv_timestamp"
            tmp = ts.with_name(".lwatv_timestamp.tmp")
            tmp.write_text(f"{mjd}:{d.hour:02d}:{d.minute:02d}:{d.second:02d}")
            os.replace(tmp, ts)
        except Exception as e:  # noqa: BLE001 - a view must not stop the recording
            self.lwatv_failed = getattr(self, "lwatv_failed", 0) + 1
            log.warning("OimsWriterBlock: the LWATV view %s was not drawn: %s", path, e)

    @property
    def written(self):
        return list(self.files) + list(self.pngs)

    def close(self):
        """Close the open file (its header's start, stop and time order written)."""
        if self._w is not None:
            self._w.close()
            self._w = self._name = None

    def on_sequence_end(self, iseq):
        self.close()
