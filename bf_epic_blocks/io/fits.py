"""FITS outputs: all-sky image cubes with a celestial WCS, and per-pixel tables.

Image cubes (:func:`write_fits_image`)
--------------------------------------
The imager gives float32 cubes ``(nchan, nprod, N, N)`` indexed ``[chan, prod, m_index, l_index]``
on an :class:`~bf_epic_blocks.imaging.pixels.LMGrid` (l East along columns, m North along rows,
pixel centres ``(i - N//2) * cell``, NaN below the horizon). They are written as a 4-axis FITS
image, NumPy order ``(nprod, nchan, N, N)``, i.e. FITS axes

    NAXIS1 = l -> RA---SIN,  NAXIS2 = m -> DEC--SIN,  NAXIS3 = FREQ,  NAXIS4 = STOKES.

Why this WCS is exact: the SIN (orthographic) projection maps a direction to intermediate
coordinates that are its direction cosines about the reference point, so with the reference point
at the zenith, the projection plane's (x, y) are (l, m) up to a rotation. CRVAL1/2 is the ICRS
RA/Dec of the zenith for the station at the observation time (astropy AltAz -> ICRS, no refraction),
CRPIX1/2 = N//2 + 1 (FITS is 1-based), CDELT1 = CDELT2 = +degrees(cell): x grows toward East
(increasing RA), as l does, so neither axis is flipped. The remaining rotation is the angle between
local North (the meridian, along +m) and ICRS North at the zenith (precession/nutation since J2000,
a fraction of a degree); it goes into the PC matrix, ``[[cos t, sin t], [-sin t, cos t]]`` with t
the position angle (East of North) of local North. What is left is aberration (~20 arcsec),
which is not a rotation; the tests check the round trip AltAz -> (l, m) -> pixel -> WCS -> ICRS ->
AltAz to well under a pixel.

STOKES axis codes (FITS convention): I=1, Q=2, U=3, V=4, XX=-5, YY=-6, XY=-7, YX=-8. The STOKES
axis must be linear (CRVAL4 + CDELT4 * k); if the products as given are not such a run but can be
reordered into one (e.g. the "full" preset XX, XY, YX, YY -> XX, YY, XY, YX) the planes are written
in that order (the header says so in PRODUCTS; a reader should always use the WCS). Otherwise one
file is written per product, named ``<stem>_<PRODUCT>.fits``. Products with no FITS code (XYi, YXi:
imaginary parts of the cross products) always get their own 3-axis file (no STOKES axis) with the
header key PRODUCT naming them.

The FREQ axis must be uniformly spaced (CRVAL3 = first channel centre in Hz, CDELT3 = spacing);
non-uniform channel sets raise ValueError (write them channel by channel instead). For a single
channel CDELT3 is ``chan_width_hz`` if given, else 1 Hz.

Image values are power in arbitrary (uncalibrated) units: BUNIT = 'UNCALIB'.

Pixel tables (:func:`write_pixel_table`)
----------------------------------------
For arbitrary pixel lists (tracked patches, selected directions): one row per pixel with L, M,
AZ_DEG, ALT_DEG, RA_DEG, DEC_DEG and one vector column (nchan values) per product, in a FITS binary
table (HDU 'PIXELS', channel frequencies in HDU 'CHANNELS'), or an ``.npz`` archive when the path
ends in ``.npz``. :func:`read_pixel_table` reads either back.

Time and location: ``time`` is an astropy Time or anything Time accepts as UTC (ISO string,
datetime); ``location`` an astropy EarthLocation or a tuple (lon_deg, lat_deg, height_m).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..imaging._xp import to_numpy
from ..imaging.products import VALID as VALID_PRODUCTS
from ..imaging.pixels import azalt_from_lm
from ..sky.catalogue import as_location, as_time, lm_to_icrs, zenith_pointings

__all__ = ["STOKES_CODES", "image_wcs", "write_fits_image", "write_pixel_table", "read_pixel_table"]

#: FITS STOKES axis codes (Greisen & Calabretta 2002).
STOKES_CODES = {"I": 1, "Q": 2, "U": 3, "V": 4, "XX": -5, "YY": -6, "XY": -7, "YX": -8}


# ---------------------------------------------------------------------------------------------
# WCS and image cubes
# ---------------------------------------------------------------------------------------------
def _freq_axis(freq_hz, chan_width_hz):
    f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
    if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"freq_hz must be a non-empty 1-D array of positive frequencies in Hz, got {freq_hz!r}")
    if f.size == 1:
        return f[0], float(chan_width_hz) if chan_width_hz else 1.0
    d = np.diff(f)
    if not np.allclose(d, d[0], rtol=1e-6, atol=1e-3) or d[0] == 0:
        raise ValueError("freq_hz must be uniformly spaced to make a FITS FREQ axis (CRVAL3 + CDELT3 * k); "
                         f"got spacings from {d.min():g} to {d.max():g} Hz: write the channels separately")
    return f[0], float(d[0])


def _stokes_run(codes):
    """(crval, cdelt) if ``codes`` is an arithmetic run with non-zero step, else None."""
    if len(codes) == 1:
        return codes[0], 1
    d = codes[1] - codes[0]
    if d != 0 and all(b - a == d for a, b in zip(codes, codes[1:])):
        return codes[0], d
    return None


def _product_groups(products):
    """Split products into files: list of (suffix or None, [indices], (crval4, cdelt4) or None)."""
    products = list(products)
    for p in products:
        if p not in VALID_PRODUCTS:
            raise ValueError(f"unknown product {p!r}; expected one of {VALID_PRODUCTS}")
    if len(set(products)) != len(products):
        raise ValueError(f"products repeat a name: {products}")
    coded = [i for i, p in enumerate(products) if p in STOKES_CODES]
    uncoded = [i for i, p in enumerate(products) if p not in STOKES_CODES]
    groups = []
    if coded:
        codes = [STOKES_CODES[products[i]] for i in coded]
        run = _stokes_run(codes)
        if run is not None:
            groups.append((None, coded, run))
        else:
            order = sorted(coded, key=lambda i: abs(STOKES_CODES[products[i]]))  # I..V, then XX..YX
            run = _stokes_run([STOKES_CODES[products[i]] for i in order])
            if run is not None:
                groups.append((None, order, run))
            else:
                groups += [(products[i], [i], (STOKES_CODES[products[i]], 1)) for i in coded]
    groups += [(products[i], [i], None) for i in uncoded]
    return groups


def image_wcs(grid, freq_hz, products, time, location, *, chan_width_hz=None, pointing=None):
    """The 4-axis celestial WCS (RA---SIN, DEC--SIN, FREQ, STOKES) of an all-sky cube.

    grid : LMGrid (uses ``size`` and ``cell``); freq_hz : (nchan,) uniformly spaced channel centres;
    products : names with FITS STOKES codes, forming a linear run in the given order
    (:func:`write_fits_image` reorders or splits other sets before calling this).
    A 3-axis WCS (no STOKES) is returned when ``products`` is None. ``pointing``: the zenith's
    (ra_deg, dec_deg, north_deg) at ``time`` if already known (:func:`~bf_epic_blocks.sky.zenith_pointings`
    for a series of images in one call), else computed here.
    """
    from astropy.wcs import WCS
    N, cell = int(grid.size), float(grid.cell)
    f0, df = _freq_axis(freq_hz, chan_width_hz)
    t, loc = as_time(time), as_location(location)
    ra0, dec0, north = zenith_pointings(t, loc) if pointing is None else (float(v) for v in pointing)
    theta = np.deg2rad(north)
    naxis = 3 if products is None else 4
    w = WCS(naxis=naxis)
    ctype = ["RA---SIN", "DEC--SIN", "FREQ"]
    crval = [ra0, dec0, f0]
    cdelt = [np.rad2deg(cell), np.rad2deg(cell), df]
    cunit = ["deg", "deg", "Hz"]
    if products is not None:
        codes = [STOKES_CODES.get(p) for p in products]
        if None in codes:
            raise ValueError(f"products {list(products)} include names without a FITS STOKES code "
                             f"({', '.join(STOKES_CODES)}); write those without a STOKES axis")
        run = _stokes_run(codes)
        if run is None:
            raise ValueError(f"products {list(products)} (codes {codes}) are not a linear run; "
                             "reorder them or write one file per product")
        ctype.append("STOKES")
        crval.append(float(run[0]))
        cdelt.append(float(run[1]))
        cunit.append("")
    w.wcs.ctype = ctype
    w.wcs.crval = crval
    w.wcs.crpix = [N // 2 + 1, N // 2 + 1] + [1.0] * (naxis - 2)
    w.wcs.cdelt = cdelt
    w.wcs.cunit = cunit
    pc = np.eye(naxis)
    # (x, y) = R (l, m): local North sits at position angle theta East of ICRS North.
    pc[:2, :2] = [[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]]
    w.wcs.pc = pc
    w.wcs.radesys = "ICRS"
    w.wcs.specsys = "TOPOCENT"
    w.wcs.dateobs = t.utc.isot
    w.wcs.mjdobs = float(t.utc.mjd)
    w.wcs.set()
    return w


#: The IAU 1976 ellipsoid of FITS WCS Paper VII: equatorial radius (m) and flattening.
IAU1976_A_M, IAU1976_F = 6378140.0, 1.0 / 298.2577


def _geodetic_iau1976(x, y, z):
    """Geocentric X, Y, Z (m) -> longitude, latitude (deg), height (m) on the IAU 1976 ellipsoid (erfa)."""
    import erfa
    elong, phi, h = erfa.gc2gde(IAU1976_A_M, IAU1976_F, np.array([x, y, z], dtype=np.float64))
    return float(np.degrees(elong)), float(np.degrees(phi)), float(h)


def _common_header(hdr, time, location, *, method, precision, telescope, int_time_s, nantenna, extra_header,
                   nonfinite=None):
    t, loc = as_time(time), as_location(location)
    hdr["DATE-OBS"] = (t.utc.isot, "UTC start of the integration")
    hdr["MJD-OBS"] = (float(t.utc.mjd), "MJD (UTC) of DATE-OBS")
    hdr["TIMESYS"] = ("UTC", "")
    if telescope is not None:
        hdr["TELESCOP"] = (str(telescope), "station")
    x, y, z = (float(v.to_value("m")) for v in loc.to_geocentric())
    hdr["OBSGEO-X"] = (x, "[m] station geocentric X")
    hdr["OBSGEO-Y"] = (y, "[m] station geocentric Y")
    hdr["OBSGEO-Z"] = (z, "[m] station geocentric Z")
    # L/B/H beside X/Y/Z, so that astropy.wcs has nothing to fill in (it would say so with a
    # FITSFixedWarning). WCS Paper VII (and wcslib's consistency check, 1 m) puts them on the IAU 1976
    # ellipsoid, not WGS84: on WGS84 the same point is 3 m higher and wcslib calls the pair inconsistent.
    lon, lat, h = _geodetic_iau1976(x, y, z)
    hdr["OBSGEO-L"] = (lon, "[deg] station longitude (IAU 1976 ellipsoid)")
    hdr["OBSGEO-B"] = (lat, "[deg] station latitude (IAU 1976 ellipsoid)")
    hdr["OBSGEO-H"] = (h, "[m] station height (IAU 1976 ellipsoid)")
    hdr["ORIGIN"] = ("bf_epic_blocks", "E-field DFT imaging blocks")
    if method is not None:
        hdr["IMAGER"] = (str(method), "imaging method")
    if precision is not None:
        hdr["PRECISN"] = (str(precision), "imager arithmetic precision (fp32/fp64)")
    if int_time_s is not None:
        hdr["INTTIME"] = (float(int_time_s), "[s] integration time per image")
    if nantenna is not None:
        hdr["NANTENNA"] = (int(nantenna), "antennas used (unflagged)")
    if nonfinite is not None:
        hdr["NONFINIT"] = (int(nonfinite), "non-finite voltage samples zeroed in this image")
    for k, v in (extra_header or {}).items():
        hdr[k] = v  # value or (value, comment)


def _with_suffix(path: Path, suffix: str) -> Path:
    name = path.name
    for ext in (".fits.gz", ".fits", ".fit", ".fts"):
        if name.lower().endswith(ext):
            return path.with_name(f"{name[:-len(ext)]}_{suffix}{name[-len(ext):]}")
    return path.with_name(f"{name}_{suffix}")


def write_fits_image(path, cube, grid, freq_hz, products, time, location, *, method, precision,
                     telescope=None, int_time_s=None, nantenna=None, chan_width_hz=None,
                     extra_header=None, nonfinite=None, overwrite=True, pointing=None) -> list[str]:
    """Write an all-sky image cube as FITS; returns the list of paths written.

    cube : (nchan, nprod, N, N) [m, l] real array (NumPy or CuPy), NaN below the horizon; cast
        to float32 and stored as (nprod, nchan, N, N) = FITS (l, m, FREQ, STOKES).
    grid : LMGrid of the images; freq_hz : (nchan,) uniform channel centres in Hz;
    products : the nprod product names; time : UTC start of the integration; location : station.
    method, precision : recorded as IMAGER and PRECISN (FITS keys have <= 8 characters); telescope, int_time_s, nantenna : TELESCOP,
        INTTIME (s) and NANTENNA when given; extra_header : {key: value or (value, comment)};
    nonfinite : the number of non-finite (NaN/Inf) voltage samples zeroed in this integration, as NONFINIT.
    pointing : the zenith's (ra_deg, dec_deg, north_deg) at ``time`` if known (see :func:`image_wcs`).
    Usually one file at ``path``; see the module docstring for the product sets that need several.
    """
    from astropy.io import fits
    cube = to_numpy(cube)
    if cube.ndim != 4:
        raise ValueError(f"cube must be shaped (nchan, nprod, N, N) [m, l]; got shape {cube.shape}")
    nchan, nprod, ny, nx = cube.shape
    N = int(grid.size)
    f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
    products = list(products)
    if (ny, nx) != (N, N):
        raise ValueError(f"cube images are {ny} x {nx} but the grid is {N} x {N}")
    if f.size != nchan:
        raise ValueError(f"cube has {nchan} channels but freq_hz has {f.size}")
    if len(products) != nprod:
        raise ValueError(f"cube has {nprod} products but {len(products)} names were given: {products}")
    if not np.isrealobj(cube):
        raise TypeError(f"cube must be real (images), got dtype {cube.dtype}")
    path = Path(path)
    written = []
    for suffix, idx, run in _product_groups(products):
        names = [products[i] for i in idx]
        w = image_wcs(grid, f, names if run is not None else None, time, location, chan_width_hz=chan_width_hz,
                      pointing=pointing)
        data = np.ascontiguousarray(np.transpose(cube[:, idx], (1, 0, 2, 3)).astype(np.float32))
        if run is None:
            data = data[0]  # (nchan, N, N): no STOKES axis for products without a code
        hdu = fits.PrimaryHDU(data=data, header=w.to_header())
        hdr = hdu.header
        hdr["EQUINOX"] = (2000.0, "ICRS is aligned with J2000")
        hdr["BUNIT"] = ("UNCALIB", "arbitrary (uncalibrated) power units")
        hdr["BTYPE"] = ("Intensity", "")
        hdr["PRODUCTS"] = (",".join(names), "planes along the STOKES axis, in file order")
        if run is None:
            hdr["PRODUCT"] = (names[0], "imag. part of a cross product; no FITS code")
        if chan_width_hz is not None:
            hdr["CHANWID"] = (float(chan_width_hz), "[Hz] channel width")
        hdr["GRIDN"] = (N, "pixels per side of the (l, m) grid")
        hdr["GRIDCELL"] = (float(grid.cell), "grid step in direction cosines")
        _common_header(hdr, time, location, method=method, precision=precision, telescope=telescope,
                       int_time_s=int_time_s, nantenna=nantenna, extra_header=extra_header, nonfinite=nonfinite)
        hdr.add_comment("Pixels at or below the horizon (l^2 + m^2 >= 1) are NaN.")
        hdr.add_comment("Projection centred on the zenith: pixel (l, m) = direction cosines East, North.")
        out = path if suffix is None else _with_suffix(path, suffix)
        out.parent.mkdir(parents=True, exist_ok=True)
        hdu.writeto(out, overwrite=overwrite)
        written.append(str(out))
    return written


# ---------------------------------------------------------------------------------------------
# Pixel tables
# ---------------------------------------------------------------------------------------------
def write_pixel_table(path, values, pixels_lm, freq_hz, products, time, location, *, method=None,
                      precision=None, telescope=None, int_time_s=None, nantenna=None, extra_header=None,
                      nonfinite=None, overwrite=True) -> str:
    """Write per-pixel values as a FITS binary table (or ``.npz``); returns the path.

    values : (nchan, nprod, npix) real array; pixels_lm : (npix, 2) l East, m North;
    freq_hz : (nchan,) channel centres (any spacing); products : the nprod names.
    FITS: HDU 'PIXELS' has one row per pixel with L, M, AZ_DEG, ALT_DEG, RA_DEG, DEC_DEG (float64)
    and one float32 column per product holding the nchan values; HDU 'CHANNELS' has FREQ_HZ.
    ``.npz``: arrays l, m, az_deg, alt_deg, ra_deg, dec_deg, freq_hz, products, values
    (nchan, nprod, npix), time_isot and location_xyz_m.
    """
    values = to_numpy(values)
    lm = np.asarray(to_numpy(pixels_lm), dtype=np.float64)
    f = np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
    products = list(products)
    if lm.ndim != 2 or lm.shape[1] != 2:
        raise ValueError(f"pixels_lm must be shaped (npix, 2); got {lm.shape}")
    if values.ndim != 3 or values.shape != (f.size, len(products), lm.shape[0]):
        raise ValueError(f"values must be shaped (nchan, nprod, npix) = ({f.size}, {len(products)}, "
                         f"{lm.shape[0]}); got {values.shape}")
    if not np.isrealobj(values):
        raise TypeError(f"values must be real, got dtype {values.dtype}")
    for p in products:
        if p not in VALID_PRODUCTS:
            raise ValueError(f"unknown product {p!r}; expected one of {VALID_PRODUCTS}")
    if np.any(np.hypot(lm[:, 0], lm[:, 1]) > 1.0 + 1e-12):
        raise ValueError("pixels_lm has directions below the horizon (l^2 + m^2 > 1)")
    az, alt = azalt_from_lm(lm)
    ra, dec = lm_to_icrs(lm, time, location)
    t, loc = as_time(time), as_location(location)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".npz":
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists and overwrite is False")
        np.savez(path, l=lm[:, 0], m=lm[:, 1], az_deg=az, alt_deg=alt, ra_deg=ra, dec_deg=dec, freq_hz=f,
                 products=np.array(products), values=values, time_isot=np.array(t.utc.isot),
                 location_xyz_m=np.array([float(v.to_value("m")) for v in loc.to_geocentric()]),
                 method=np.array("" if method is None else str(method)),
                 precision=np.array("" if precision is None else str(precision)))
        return str(path)
    from astropy.io import fits
    nchan = f.size
    cols = [fits.Column(name=n, format="D", array=a, unit=u) for n, a, u in
            (("L", lm[:, 0], ""), ("M", lm[:, 1], ""), ("AZ_DEG", az, "deg"), ("ALT_DEG", alt, "deg"),
             ("RA_DEG", ra, "deg"), ("DEC_DEG", dec, "deg"))]
    for k, p in enumerate(products):
        cols.append(fits.Column(name=p, format=f"{nchan}E", unit="UNCALIB",
                                array=np.ascontiguousarray(values[:, k, :].T.astype(np.float32))))
    pix = fits.BinTableHDU.from_columns(cols, name="PIXELS")
    chans = fits.BinTableHDU.from_columns([fits.Column(name="FREQ_HZ", format="D", unit="Hz", array=f)],
                                          name="CHANNELS")
    primary = fits.PrimaryHDU()
    for hdr in (primary.header, pix.header):
        _common_header(hdr, t, loc, method=method, precision=precision, telescope=telescope,
                       int_time_s=int_time_s, nantenna=nantenna, extra_header=extra_header, nonfinite=nonfinite)
    pix.header["BUNIT"] = ("UNCALIB", "arbitrary (uncalibrated) power units")
    pix.header["PRODUCTS"] = (",".join(products), "product columns")
    pix.header.add_comment("RA_DEG/DEC_DEG: ICRS; AZ_DEG from North through East; L East, M North.")
    fits.HDUList([primary, pix, chans]).writeto(path, overwrite=overwrite)
    return str(path)


def read_pixel_table(path) -> dict:
    """Read :func:`write_pixel_table` output (FITS or .npz) into a dict of arrays.

    Keys: l, m, az_deg, alt_deg, ra_deg, dec_deg (npix,), freq_hz (nchan,), products (list),
    values (nchan, nprod, npix) float, time_isot (str).
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in ("l", "m", "az_deg", "alt_deg", "ra_deg", "dec_deg", "freq_hz", "values")}
            out["products"] = [str(p) for p in z["products"]]
            out["time_isot"] = str(z["time_isot"])
        return out
    from astropy.io import fits
    with fits.open(path) as hl:
        pix, chans = hl["PIXELS"], hl["CHANNELS"]
        products = pix.header["PRODUCTS"].split(",")
        d = pix.data
        out = {k.lower(): np.asarray(d[k], dtype=np.float64) for k in ("L", "M", "AZ_DEG", "ALT_DEG", "RA_DEG", "DEC_DEG")}
        out["freq_hz"] = np.asarray(chans.data["FREQ_HZ"], dtype=np.float64)
        nchan = out["freq_hz"].size
        out["values"] = np.stack([np.asarray(d[p], dtype=np.float32).reshape(-1, nchan).T for p in products], axis=1)
        out["products"] = products
        out["time_isot"] = hl[0].header["DATE-OBS"]
    return out
