"""Image cubes with a time axis, written as fast as the imager makes them: HDF5 (h5py).

Why HDF5 and not FITS
---------------------
At one image per 16 samples (0.64 ms at LWA-SV) a 64x64 all-sky imager makes ~1,560 images a
second, ~320 MB/s of float32 at 16 channels (case P). What such a stream needs:

* appending without knowing the length: HDF5 datasets are chunked and resizable along time; a
  FITS image's size sits in its header (NAXISn), so a FITS stream must be split into fixed-size
  files or have its header patched when it ends;
* float16 (half the bytes; enough for a dynamic range of ~1e3 per image): HDF5 has it natively,
  FITS has no 16-bit float BITPIX at all (only scaled integers);
* no conversion on the way out: HDF5 stores the host's little-endian floats as they are; FITS is
  big-endian, so every byte would be swapped on the CPU first;
* readers: h5py (and anything built on HDF5: CARTA, pandas, MATLAB, IDL) read it with the same
  metadata; astronomers' FITS viewers (DS9, CARTA) get a FITS cube from :func:`cube_to_fits`,
  with the same celestial + spectral + time WCS.

So the stream is HDF5 and FITS is one function away. The header's WCS is kept as FITS header text
(attribute ``wcs_header``), so ``astropy.wcs.WCS(read_image_cube(path)['wcs_header'])`` is the WCS
of the gridded cube.

File layout (one file per sequence, or per ``images_per_file`` images)
----------------------------------------------------------------------
``images``       (ntime, nchan, nprod, npix) float32 or float16, chunked along time (about 4 MiB
                 a chunk), imaged pixels only (the horizon's corners are never written);
``time_tag``     (ntime,) int64: start of each image in LWA ticks (196 MHz since the Unix epoch);
``freq_hz``      (nchan,) channel centres (one, the mean, when channels are averaged);
``lm``           (npix, 2) direction cosines (l East, m North) of the pixels;
``pixel_index``  (npix,) flat index ``m_index * N + l_index`` on the N x N grid (grids only).
Attributes: ``products``, ``grid_size``/``grid_cell`` (grids), ``dt_s`` (seconds per image),
``integration_ticks``, ``date_obs`` (UTC of the first image), ``chan_width_hz``,
``averaged_channels``, ``telescope``, ``wcs_header`` (grids: the WCS of the gridded cube
``(time, prod, freq, m, l)``, i.e. FITS axes RA---SIN, DEC--SIN, FREQ, STOKES, TIME; the celestial
part is exact for the first image: the sky turns 0.25 deg a minute, and each image's own time is
in ``time_tag``), ``nimages`` and ``complete`` (True once closed cleanly; a crashed writer
leaves ``complete`` False and ``nimages`` at the last flush).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..imaging._xp import to_numpy

__all__ = ["ImageCubeWriter", "read_image_cube", "cube_to_fits", "cube_wcs_header"]

log = logging.getLogger(__name__)

FLOAT16_MAX = 65504.0
_CHUNK_BYTES = 4 << 20


def cube_wcs_header(grid, freq_hz, products, time, location, dt_s, *, chan_width_hz=None):
    """FITS header text of the 5-axis WCS (l, m, FREQ, STOKES, TIME) of a gridded image cube; TIME
    in seconds from ``time`` (MJDREF, UTC) at the start of each image. '' when the products have
    no linear STOKES run (e.g. XX, XY, YX, YY): write those cubes per product."""
    from astropy.wcs import WCS
    from ..sky.catalogue import as_time
    from .fits import image_wcs
    try:
        w4 = image_wcs(grid, freq_hz, products, time, location, chan_width_hz=chan_width_hz)
    except ValueError as e:
        log.warning("image cube: no WCS written (%s)", e)
        return ""
    h = w4.to_header()
    h["WCSAXES"] = 5
    t = as_time(time)
    for k, v in (("CTYPE5", "TIME"), ("CUNIT5", "s"), ("CRPIX5", 1.0), ("CRVAL5", 0.0), ("CDELT5", float(dt_s)),
                 ("MJDREF", float(t.utc.mjd)), ("DATEREF", t.utc.isot), ("TIMESYS", "UTC")):
        h[k] = v
    return WCS(h).to_header().tostring(sep="\n")


class ImageCubeWriter:
    """Append images to an HDF5 cube (module docstring for the layout).

    Parameters
    ----------
    path : file to create (overwritten).
    freq_hz : (nchan,) channel centres of the images given to :meth:`append`.
    products : product names along the images' pol axis.
    lm : (npix, 2) pixel directions; pixel_index : (npix,) flat grid indices (grids), or None.
    time_tag0 : time tag (ticks) of the first image; integration_ticks : ticks per image.
    grid : the LMGrid (grids) or None; location : EarthLocation (for the WCS) or None.
    dtype : 'float32' or 'float16'; average_channels : store the channel mean only.
    images_per_chunk : images per HDF5 chunk (default: about 4 MiB per chunk).
    flush_every : chunks between HDF5 flushes (what a crash can lose at most).
    attrs : extra attributes (JSON-able scalars or strings).

    :meth:`append` takes ``(n, nchan, nprod, npix)`` float arrays (NumPy; CuPy is copied) and keeps
    a chunk's worth in memory, so every write to HDF5 is one whole, aligned chunk.
    """

    def __init__(self, path, freq_hz, products, lm, time_tag0, integration_ticks, *, pixel_index=None, grid=None,
                 location=None, dtype="float32", average_channels=False, images_per_chunk=None, flush_every=16,
                 telescope=None, attrs=None):
        import h5py
        from ..conventions import FS_HZ
        if dtype not in ("float32", "float16"):
            raise ValueError(f"dtype must be 'float32' or 'float16', got {dtype!r}")
        self.freq_in = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        self.products = [str(p) for p in products]
        self.lm = np.asarray(lm, dtype=np.float64)
        if self.lm.ndim != 2 or self.lm.shape[1] != 2:
            raise ValueError(f"lm must be (npix, 2), got {self.lm.shape}")
        self.average = bool(average_channels)
        self.dtype = np.dtype(dtype)
        nchan_in = self.freq_in.size
        nchan = 1 if self.average else nchan_in
        self.shape = (nchan_in, len(self.products), self.lm.shape[0])
        self.frame = (nchan, len(self.products), self.lm.shape[0])
        per_image = int(np.prod(self.frame)) * self.dtype.itemsize
        self.k = int(images_per_chunk) if images_per_chunk else max(1, _CHUNK_BYTES // per_image)
        self.flush_every = int(flush_every)
        self.time_tag0, self.ticks = int(time_tag0), int(integration_ticks)
        self.path = str(path)
        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        self.f = h5py.File(self.path, "w", libver="latest")
        self.dset = self.f.create_dataset("images", shape=(0,) + self.frame, maxshape=(None,) + self.frame,
                                          chunks=(self.k,) + self.frame, dtype=self.dtype)
        self.tags = self.f.create_dataset("time_tag", shape=(0,), maxshape=(None,), chunks=(max(self.k, 1024),),
                                          dtype=np.int64)
        df = float(self.freq_in[1] - self.freq_in[0]) if nchan_in > 1 else None
        freq_out = np.array([self.freq_in.mean()]) if self.average else self.freq_in
        width = (df * nchan_in if df else None) if self.average else df
        self.f.create_dataset("freq_hz", data=freq_out)
        self.f.create_dataset("lm", data=self.lm)
        a = self.f.attrs
        if pixel_index is not None:
            self.f.create_dataset("pixel_index", data=np.asarray(pixel_index, dtype=np.int64))
        if grid is not None:
            a["grid_size"], a["grid_cell"] = int(grid.size), float(grid.cell)
        from .tbf import time_tag_to_time
        t0 = time_tag_to_time(self.time_tag0)
        a["products"] = self.products
        a["dt_s"] = self.ticks / FS_HZ
        a["integration_ticks"] = self.ticks
        a["date_obs"] = t0.isot
        a["chan_width_hz"] = float(width) if width else float("nan")
        a["averaged_channels"] = int(nchan_in) if self.average else 0
        a["telescope"] = str(telescope or "")
        a["layout"] = "images[time, freq, product, pixel]; pixel_index -> grid[m, l]"
        a["wcs_header"] = (cube_wcs_header(grid, freq_out, self.products, t0, location, self.ticks / FS_HZ,
                                           chan_width_hz=width) if grid is not None and location is not None else "")
        for key, val in (attrs or {}).items():
            a[key] = val
        a["complete"] = False
        a["nimages"] = 0
        self._buf = np.empty((self.k,) + self.frame, dtype=self.dtype)
        self._nbuf = 0
        self.nimages = 0          # appended (buffered or written)
        self.nwritten = 0         # in the file
        self.overflow = 0         # float16 values beyond +-65504 (stored as inf)
        self._chunks = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def append(self, images):
        """Append ``(n, nchan, nprod, npix)`` images (the next ones in time); when channels are averaged,
        also ``(n, 1, nprod, npix)``: their channel mean, already taken."""
        x = to_numpy(images)
        mean_given = self.average and x.ndim == 4 and x.shape[1] == 1 and x.shape[2:] == self.shape[1:]
        if not mean_given and (x.ndim != 4 or x.shape[1:] != self.shape):
            raise ValueError(f"images: expected (n, nchan, nprod, npix) = (n,) + {self.shape}, got {x.shape}")
        if self.average and not mean_given:
            x = x.mean(axis=1, keepdims=True, dtype=np.float32)
        if self.dtype == np.float16:
            big = np.abs(x) > FLOAT16_MAX
            if big.any():
                nbig = int(np.count_nonzero(big & np.isfinite(x)))
                if nbig and not self.overflow:
                    log.warning("%s: %d image values beyond the float16 range (+-65504) stored as inf", self.path, nbig)
                self.overflow += nbig
        with np.errstate(over="ignore"):         # counted and logged above: no warning a gulp
            x = np.ascontiguousarray(x, dtype=self.dtype)
        pos, n = 0, x.shape[0]
        while pos < n:
            if self._nbuf == 0 and n - pos >= self.k and self.nwritten % self.k == 0:
                self._write(x[pos:pos + self.k])          # whole aligned chunk: no copy into the buffer
                pos += self.k
                continue
            take = min(self.k - self._nbuf, n - pos)
            self._buf[self._nbuf:self._nbuf + take] = x[pos:pos + take]
            self._nbuf += take
            pos += take
            if self._nbuf == self.k:
                self._write_buffer()
        self.nimages += n

    def _write_buffer(self):
        if self._nbuf:
            self._write(self._buf[:self._nbuf])
            self._nbuf = 0

    def _write(self, block):
        """Write ``block`` (n <= k images, C-contiguous, the file's dtype) after the last image."""
        n, a = block.shape[0], self.nwritten
        self.dset.resize(a + n, axis=0)
        if n == self.k and a % self.k == 0:   # a whole aligned chunk: straight to the file, no filter pipeline
            self.dset.id.write_direct_chunk((a, 0, 0, 0), memoryview(block))
        else:
            self.dset[a:a + n] = block
        self.tags.resize(a + n, axis=0)
        self.tags[a:a + n] = self.time_tag0 + self.ticks * np.arange(a, a + n, dtype=np.int64)
        self.nwritten += n
        self._chunks += 1
        if self._chunks % self.flush_every == 0:
            self.f.attrs["nimages"] = self.nwritten
            self.f.flush()

    def skip(self, n):
        """Record that ``n`` images were lost: the time tags of later images jump over them."""
        self._write_buffer()
        self.time_tag0 += int(n) * self.ticks
        self.f.attrs["images_lost"] = int(self.f.attrs.get("images_lost", 0)) + int(n)

    def close(self):
        """Write what is buffered, mark the file complete and close it (idempotent)."""
        if self.f is None:
            return
        self._write_buffer()
        self.f.attrs["nimages"] = self.nwritten
        self.f.attrs["float16_overflow"] = self.overflow
        self.f.attrs["complete"] = True
        self.f.close()
        self.f = None


def read_image_cube(path, grid=False, start=0, stop=None):
    """Read a cube: dict with ``images`` ((ntime, nchan, nprod, npix), or (ntime, nprod, nchan, N, N)
    with NaN off the imaged pixels when ``grid=True``), ``time_tag``, ``time`` (astropy Time),
    ``freq_hz``, ``lm``, ``pixel_index`` (or None), and every attribute (``products``, ``wcs_header``...)."""
    import h5py
    from .tbf import time_tag_to_time
    with h5py.File(path, "r") as f:
        out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        n = int(f["images"].shape[0]) if stop is None else min(int(stop), int(f["images"].shape[0]))
        out["images"] = f["images"][start:n]
        out["time_tag"] = f["time_tag"][start:n]
        out["freq_hz"], out["lm"] = f["freq_hz"][...], f["lm"][...]
        out["pixel_index"] = f["pixel_index"][...] if "pixel_index" in f else None
    out["products"] = [str(p) for p in out["products"]]
    out["time"] = time_tag_to_time(out["time_tag"]) if len(out["time_tag"]) else None
    if grid:
        if out["pixel_index"] is None:
            raise ValueError(f"{path}: a pixel-list cube has no grid")
        N = int(out["grid_size"])
        img = out["images"]
        g = np.full(img.shape[:3] + (N * N,), np.nan, dtype=img.dtype)
        g[..., out["pixel_index"]] = img
        out["images"] = np.swapaxes(g.reshape(img.shape[:3] + (N, N)), 1, 2)
    return out


def cube_to_fits(h5_path, fits_path, start=0, stop=None):
    """Write (part of) an HDF5 cube as a 5-axis FITS image (l, m, FREQ, STOKES, TIME) for FITS
    viewers; float16 cubes become float32. Returns the path."""
    from astropy.io import fits
    c = read_image_cube(h5_path, grid=True, start=start, stop=stop)
    if not c.get("wcs_header"):
        raise ValueError(f"{h5_path}: no celestial WCS in this cube (pixel list, no station location, or "
                         "products without a linear STOKES axis); read it with read_image_cube instead")
    hdr = fits.Header.fromstring(c["wcs_header"], sep="\n")
    hdr["CRVAL5"] = float(start * c["dt_s"])   # seconds after the cube's first image (MJDREF)
    hdr["BUNIT"] = "UNCALIB"
    hdr["DATE-OBS"] = str(c["date_obs"])
    hdr["PRODUCTS"] = ",".join(c["products"])
    fits.PrimaryHDU(np.asarray(c["images"], dtype=np.float32), header=hdr).writeto(fits_path, overwrite=True)
    return str(fits_path)
