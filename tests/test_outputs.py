"""FITS cubes, pixel tables and PNG quicklooks: orientation checked against astropy, not assumed."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

astropy = pytest.importorskip("astropy")
import astropy.units as u  # noqa: E402
from astropy.coordinates import AltAz, EarthLocation, SkyCoord  # noqa: E402
from astropy.io import fits  # noqa: E402
from astropy.time import Time  # noqa: E402
from astropy.utils import iers  # noqa: E402
from astropy.wcs import WCS  # noqa: E402

from bf_epic_blocks.imaging.pixels import azalt_from_lm, lm_from_azalt, lm_grid  # noqa: E402
from bf_epic_blocks.io import fits as fits_out  # noqa: E402
from bf_epic_blocks.io.fits import image_wcs, read_pixel_table, write_fits_image, write_pixel_table  # noqa: E402
from bf_epic_blocks.sky import icrs_to_lm, zenith_icrs  # noqa: E402

# LWA-SV (approximately) and a time when Cyg A is high in the sky there.
LOC = EarthLocation.from_geodetic(-106.885783 * u.deg, 34.348358 * u.deg, 1477.8 * u.m)
TIME = Time("2024-01-01T20:00:00", scale="utc")
CYGA = SkyCoord(ra=299.868152 * u.deg, dec=40.733916 * u.deg, frame="icrs")


@pytest.fixture(autouse=True)
def _offline_iers():
    with iers.conf.set_temp("auto_download", False):
        yield


def _altaz():
    return AltAz(obstime=TIME, location=LOC)


def _pixel_of_lm(grid, lm):
    """Fractional 0-based (x = l index, y = m index) pixel coordinates of direction cosines."""
    lm = np.atleast_2d(lm)
    return lm[:, 0] / grid.cell + grid.size // 2, lm[:, 1] / grid.cell + grid.size // 2


def test_wcs_round_trip_altaz():
    """AltAz -> (l, m) -> pixel -> WCS world (ICRS) -> AltAz returns the same direction."""
    grid = lm_grid(64)
    w = image_wcs(grid, [74e6, 74.025e6], ["I"], TIME, LOC).celestial
    az = np.array([0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0, 10.0, 100.0, 200.0, 300.0])
    alt = np.array([30.0, 60.0, 20.0, 5.0, 45.0, 75.0, 10.0, 2.0, 85.0, 50.0, 15.0, 1.0])
    x, y = _pixel_of_lm(grid, lm_from_azalt(az, alt))
    aa = w.pixel_to_world(x, y).transform_to(_altaz())
    sep = aa.separation(SkyCoord(az=az * u.deg, alt=alt * u.deg, frame=_altaz())).deg
    # Only aberration (~20 arcsec) is not a rotation; a 64-grid pixel is 1.8 deg at the zenith.
    assert np.max(sep) < 0.02, sep
    # and conversely: a mirrored East axis (CDELT1 < 0) would put az 90 at az 270
    w_bad = w.deepcopy()
    w_bad.wcs.cdelt[0] *= -1
    aa_bad = w_bad.pixel_to_world(x, y).transform_to(_altaz())
    assert np.max(aa_bad.separation(SkyCoord(az=az * u.deg, alt=alt * u.deg, frame=_altaz())).deg) > 10


def test_zenith_and_east_pixels():
    grid = lm_grid(32)
    w = image_wcs(grid, [60e6], ["XX", "YY"], TIME, LOC).celestial
    c0 = w.pixel_to_world(grid.size // 2, grid.size // 2).transform_to(_altaz())
    assert c0.alt.deg > 89.99
    ra0, dec0 = zenith_icrs(TIME, LOC)
    assert abs(w.wcs.crval[0] - ra0) < 1e-9 and abs(w.wcs.crval[1] - dec0) < 1e-9
    assert abs(dec0 - 34.35) < 0.5  # the zenith's declination is about the station latitude
    # Column index increasing = l increasing = East: 8 cells East of zenith, m = 0.
    east = w.pixel_to_world(grid.size // 2 + 8, grid.size // 2).transform_to(_altaz())
    assert abs(east.az.deg - 90.0) < 0.05
    assert abs(east.alt.deg - np.rad2deg(np.arccos(8 * grid.cell))) < 0.05
    north = w.pixel_to_world(grid.size // 2, grid.size // 2 + 8).transform_to(_altaz())
    assert min(north.az.deg, 360 - north.az.deg) < 0.05


def test_zenith_pointings_of_a_series_put_each_image_on_its_own_sky():
    """One vectorised transform for many times: each time's WCS still puts its centre pixel at the
    zenith and +m on local North *at that time* (astropy AltAz per time, the independent truth), and
    the numbers equal a transform of that time alone."""
    from bf_epic_blocks.sky import north_angle_deg, zenith_pointings
    grid = lm_grid(32)
    times = TIME + np.array([0.0, 1.0, 3600.0, 6 * 3600.0, 13 * 3600.0]) * u.s
    ra, dec, north = zenith_pointings(times, LOC)
    assert ra.shape == dec.shape == north.shape == (5,)
    assert np.ptp(ra) > 90  # the zenith moves through RA over the day: a series, not one pointing
    for k, t in enumerate(times):
        assert (ra[k], dec[k]) == zenith_icrs(t, LOC) and north[k] == north_angle_deg(t, LOC)
        w = image_wcs(grid, [60e6], ["I"], t, LOC, pointing=(ra[k], dec[k], north[k])).celestial
        frame = AltAz(obstime=t, location=LOC)
        assert w.pixel_to_world(grid.size // 2, grid.size // 2).transform_to(frame).alt.deg > 89.99
        up = w.pixel_to_world(grid.size // 2, grid.size // 2 + 8).transform_to(frame)
        assert min(up.az.deg, 360 - up.az.deg) < 0.05, (k, up.az.deg)


def test_image_writer_pointing_batches_match_each_images_time():
    """The image writer computes its FITS pointings for a batch of integrations at once: the
    pointing it gives integration j (across batch boundaries, and going back) is that of j's own time."""
    from bf_epic_blocks.blocks.image_writer import POINTING_BATCH, integration_pointing
    from bf_epic_blocks.io.tbf import time_tag_to_time
    from bf_epic_blocks.sky import zenith_pointings
    tag0, ticks = int(TIME.unix) * 196_000_000, 196_000_000 * 60
    for j in (0, 5, POINTING_BATCH + 3, 2):
        want = zenith_pointings(time_tag_to_time(tag0 + j * ticks), LOC)
        assert integration_pointing(LOC, tag0, ticks, j) == want, j
        assert integration_pointing((LOC.lon.deg, LOC.lat.deg, LOC.height.to_value(u.m)), tag0, ticks, j) == want


def _cyga_cube(grid, nchan=3, products=("I", "Q")):
    lm, alt = icrs_to_lm(CYGA.ra.deg, CYGA.dec.deg, TIME, LOC)
    assert alt[0] > 30, "test time chosen so that Cyg A is well above the horizon"
    x, y = _pixel_of_lm(grid, lm)
    ix, iy = int(round(x[0])), int(round(y[0]))
    rng = np.random.default_rng(3)
    cube = rng.uniform(0.0, 1.0, (nchan, len(products), grid.size, grid.size)).astype(np.float32)
    cube[:, :, iy, ix] = 100.0 + np.arange(nchan)[:, None]
    cube[:, :, ~grid.mask] = np.nan
    return cube, lm[0], (iy, ix)


def test_fits_cube_brightest_pixel_is_cyga(tmp_path):
    grid = lm_grid(64)
    freq = 74e6 + 25e3 * np.arange(3)
    cube, lm_cyg, (iy, ix) = _cyga_cube(grid)
    out = write_fits_image(tmp_path / "sky.fits", cube, grid, freq, ["I", "Q"], TIME, LOC, method="dft-direct",
                           precision="fp32", telescope="LWA-SV", int_time_s=0.04096, nantenna=510,
                           chan_width_hz=25e3)
    assert out == [str(tmp_path / "sky.fits")]
    with fits.open(out[0]) as hl:
        hdr, data = hl[0].header, hl[0].data
        assert data.shape == (2, 3, 64, 64) and data.dtype == np.dtype(">f4")
        np.testing.assert_array_equal(data, np.transpose(cube, (1, 0, 2, 3)))  # NaN-safe compare
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the header reads back without fix-up warnings (FITSFixedWarning)
            w = WCS(hdr)
    assert w.wcs.ctype[0] == "RA---SIN" and w.wcs.ctype[1] == "DEC--SIN"
    assert list(w.wcs.ctype) == ["RA---SIN", "DEC--SIN", "FREQ", "STOKES"]
    # brightest pixel of the I plane, channel 0 -> ICRS, within one pixel of Cyg A
    plane = data[0, 0]
    jy, jx = np.unravel_index(np.nanargmax(plane), plane.shape)
    assert (jy, jx) == (iy, ix)
    sky = w.celestial.pixel_to_world(jx, jy)
    # one pixel at Cyg A's position: cell / sin(alt) radians along the radial direction (foreshortening)
    alt = np.rad2deg(np.arccos(np.hypot(*lm_cyg)))
    pix_deg = np.rad2deg(grid.cell) / np.sin(np.deg2rad(alt))
    assert sky.separation(CYGA).deg < pix_deg
    # sub-pixel: Cyg A's exact fractional pixel maps onto Cyg A to aberration accuracy
    x, y = _pixel_of_lm(grid, lm_cyg)
    assert w.celestial.pixel_to_world(x[0], y[0]).separation(CYGA).deg < 0.02
    # spectral and polarisation axes
    world = w.pixel_to_world(jx, jy, 2, 1)
    assert abs(world[1].to_value(u.Hz) - freq[2]) < 1e-3
    assert w.wcs.crval[3] == 1 and w.wcs.cdelt[3] == 1  # I, Q
    for key, val in (("BUNIT", "UNCALIB"), ("ORIGIN", "bf_epic_blocks"), ("TELESCOP", "LWA-SV"),
                     ("IMAGER", "dft-direct"), ("PRECISN", "fp32"), ("NANTENNA", 510), ("RADESYS", "ICRS"),
                     ("PRODUCTS", "I,Q"), ("CHANWID", 25e3), ("EQUINOX", 2000.0)):
        assert hdr[key] == val, key
    assert hdr["INTTIME"] == pytest.approx(0.04096)
    assert Time(hdr["DATE-OBS"], scale="utc") == TIME
    assert hdr["MJD-OBS"] == pytest.approx(TIME.mjd)
    assert hdr["CRPIX1"] == 33 and hdr["CRPIX2"] == 33
    assert hdr["CDELT1"] == pytest.approx(np.rad2deg(grid.cell)) and hdr["CDELT2"] == pytest.approx(np.rad2deg(grid.cell))
    assert hdr["CRVAL3"] == 74e6 and hdr["CDELT3"] == 25e3
    geo = np.array([hdr["OBSGEO-X"], hdr["OBSGEO-Y"], hdr["OBSGEO-Z"]])
    np.testing.assert_allclose(geo, [v.to_value(u.m) for v in LOC.to_geocentric()], atol=1e-3)
    # L/B/H on the IAU 1976 ellipsoid (WCS Paper VII): the same place as WGS84's to 1e-6 deg, 3 m lower;
    # going back to X/Y/Z with that ellipsoid's closed form gives the written X/Y/Z to 1 mm
    assert hdr["OBSGEO-L"] == pytest.approx(LOC.lon.deg, abs=1e-9)
    assert hdr["OBSGEO-B"] == pytest.approx(LOC.lat.deg, abs=1e-6)
    assert -4 < hdr["OBSGEO-H"] - LOC.height.to_value(u.m) < -2
    a, f = 6378140.0, 1 / 298.2577
    e2 = (2 - f) * f
    lon, lat, h = np.deg2rad(hdr["OBSGEO-L"]), np.deg2rad(hdr["OBSGEO-B"]), hdr["OBSGEO-H"]
    n = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    xyz = [(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon), (n * (1 - e2) + h) * np.sin(lat)]
    np.testing.assert_allclose(xyz, geo, atol=1e-3)
    np.testing.assert_allclose(w.wcs.obsgeo, [*geo, hdr["OBSGEO-L"], hdr["OBSGEO-B"], hdr["OBSGEO-H"]], atol=1e-6)
    assert np.isnan(data[0, 0, 0, 0])  # corner is below the horizon


def test_full_preset_is_reordered_into_a_stokes_run(tmp_path):
    grid = lm_grid(16)
    products = ["XX", "XY", "YX", "YY"]  # codes -5, -7, -8, -6: not linear as given
    cube = np.zeros((1, 4, 16, 16), np.float32)
    for k in range(4):
        cube[0, k] = k + 1.0
    out = write_fits_image(tmp_path / "f.fits", cube, grid, [74e6], products, TIME, LOC, method="dft",
                           precision="fp64")
    assert len(out) == 1
    with fits.open(out[0]) as hl:
        w, data = WCS(hl[0].header), hl[0].data
        assert hl[0].header["PRODUCTS"] == "XX,YY,XY,YX"
    codes = {-5: "XX", -6: "YY", -7: "XY", -8: "YX"}
    for s in range(4):  # each plane's STOKES world value names the product it holds
        code = int(round(w.wcs_pix2world([[0, 0, 0, s]], 0)[0][3]))
        assert data[s, 0, 0, 0] == products.index(codes[code]) + 1.0


def test_irregular_products_split_into_files(tmp_path):
    grid = lm_grid(8)
    products = ["I", "V", "XX", "XYi"]
    cube = np.arange(4, dtype=np.float32)[None, :, None, None] * np.ones((2, 4, 8, 8), np.float32)
    out = write_fits_image(tmp_path / "s.fits", cube, grid, [74e6, 74.1e6], products, TIME, LOC, method="dft",
                           precision="fp32")
    assert [p.split("/")[-1] for p in out] == ["s_I.fits", "s_V.fits", "s_XX.fits", "s_XYi.fits"]
    for k, p in enumerate(out):
        with fits.open(p) as hl:
            h, d = hl[0].header, hl[0].data
            assert np.all(d == k)
            if products[k] == "XYi":
                assert d.shape == (2, 8, 8) and h["NAXIS"] == 3 and h["PRODUCT"] == "XYi"
            else:
                assert d.shape == (1, 2, 8, 8) and h["CRVAL4"] == fits_out.STOKES_CODES[products[k]]


def test_bad_inputs_raise():
    grid = lm_grid(8)
    cube = np.zeros((2, 1, 8, 8), np.float32)
    with pytest.raises(ValueError, match="uniformly spaced"):
        write_fits_image("/tmp/x.fits", np.zeros((3, 1, 8, 8)), grid, [74e6, 74.1e6, 74.3e6], ["I"], TIME, LOC,
                         method="dft", precision="fp32")
    with pytest.raises(ValueError, match="channels"):
        write_fits_image("/tmp/x.fits", cube, grid, [74e6], ["I"], TIME, LOC, method="dft", precision="fp32")
    with pytest.raises(ValueError, match="grid is 16 x 16"):
        write_fits_image("/tmp/x.fits", cube, lm_grid(16), [74e6, 75e6], ["I"], TIME, LOC, method="dft",
                         precision="fp32")
    with pytest.raises(ValueError, match="unknown product"):
        write_fits_image("/tmp/x.fits", cube, grid, [74e6, 75e6], ["P"], TIME, LOC, method="dft", precision="fp32")


@pytest.mark.parametrize("suffix", [".fits", ".npz"])
def test_pixel_table_round_trip(tmp_path, suffix):
    lm_cyg, _ = icrs_to_lm(CYGA.ra.deg, CYGA.dec.deg, TIME, LOC)
    lm = np.vstack([lm_cyg, [[0.0, 0.0], [0.5, 0.0], [0.0, -0.99]]])
    freq = np.array([60e6, 70e6, 74e6])  # table channels need not be uniform
    values = np.random.default_rng(1).normal(size=(3, 2, 4)).astype(np.float32)
    path = write_pixel_table(tmp_path / f"t{suffix}", values, lm, freq, ["I", "XYi"], TIME, (-106.885783, 34.348358, 1477.8),
                             method="dft", precision="fp32", telescope="LWA-SV")
    t = read_pixel_table(path)
    np.testing.assert_array_equal(t["values"], values)
    np.testing.assert_allclose(t["l"], lm[:, 0]) and np.testing.assert_allclose(t["m"], lm[:, 1])
    np.testing.assert_allclose(t["freq_hz"], freq)
    assert t["products"] == ["I", "XYi"]
    assert Time(t["time_isot"]) == TIME
    # independent truth: astropy's own transforms
    sky = SkyCoord(ra=t["ra_deg"] * u.deg, dec=t["dec_deg"] * u.deg)
    assert sky[0].separation(CYGA).deg < 1e-6  # the Cyg A pixel reads back as Cyg A
    aa = sky.transform_to(_altaz())
    np.testing.assert_allclose(aa.alt.deg[1], 90.0, atol=1e-6)
    np.testing.assert_allclose([aa.az.deg[2], aa.alt.deg[2]], [90.0, 60.0], atol=1e-6)  # l = 0.5 East
    az, alt = azalt_from_lm(lm)
    np.testing.assert_allclose(t["az_deg"][[0, 2, 3]], az[[0, 2, 3]])
    np.testing.assert_allclose(t["alt_deg"], alt)
    if suffix == ".fits":
        with fits.open(path) as hl:
            assert hl["PIXELS"].header["TELESCOP"] == "LWA-SV" and hl[0].header["ORIGIN"] == "bf_epic_blocks"
            assert hl["PIXELS"].columns["I"].format == "3E"


# ---------------------------------------------------------------------------------------------
# PNG quicklooks
# ---------------------------------------------------------------------------------------------
def _read_png(path):
    from matplotlib.image import imread
    with open(path, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    return imread(path)


def _bright_centroid(rgba):
    """Centroid (x, y) in image pixels of the inferno-yellow (brightest) colour."""
    r, g, b = rgba[..., 0], rgba[..., 1], rgba[..., 2]
    sel = (r > 0.9) & (g > 0.8) & (b < 0.7)
    ys, xs = np.nonzero(sel)
    assert xs.size > 0, "no bright pixel rendered"
    return xs.mean(), ys.mean()


def test_quicklook_east_left_north_up(tmp_path):
    from bf_epic_blocks.io.quicklook import quicklook_png
    grid = lm_grid(32)
    img = np.zeros((32, 32), np.float32)
    ax = grid.axis
    il, im = int(np.argmin(abs(ax - 0.5))), int(np.argmin(abs(ax - 0.25)))  # East and a bit North
    img[im - 1:im + 2, il - 1:il + 2] = 10.0
    img[~grid.mask] = np.nan
    path = quicklook_png(tmp_path / "q.png", img, grid, colorbar=False, horizon=False, sources=None)
    rgba = _read_png(path)
    h, w = rgba.shape[:2]
    x, y = _bright_centroid(rgba)
    assert x < 0.45 * w, "East must be drawn on the LEFT"
    assert y < 0.45 * h, "North must be drawn at the top"


def test_quicklook_full_render(tmp_path):
    from bf_epic_blocks.io.quicklook import quicklook_grid_png, quicklook_png
    grid = lm_grid(64)
    cube, lm_cyg, (iy, ix) = _cyga_cube(grid, nchan=6, products=("I",))
    lm_z = (0.0, 0.0)
    cube[:, 0, grid.size // 2, grid.size // 2] = 60.0
    srcs = [("Cyg A", float(lm_cyg[0]), float(lm_cyg[1])), ("zenith", *lm_z), ("below", np.nan, np.nan)]
    p1 = quicklook_png(tmp_path / "cyg.png", cube[0, 0], grid, title="Cyg A test 74.000 MHz", sources=srcs)
    p2 = quicklook_grid_png(tmp_path / "grid.png", cube[:, 0], grid, 74e6 + 25e3 * np.arange(6), title="grid",
                            sources=srcs, max_panels=4)
    for p in (p1, p2):
        rgba = _read_png(p)
        assert rgba.shape[0] > 300 and rgba.shape[1] > 300
        assert (tmp_path / p).stat().st_size > 10_000
        assert rgba[..., :3].std() > 0.05  # not a blank canvas
    with pytest.raises(ValueError, match=r"\(N, N\)"):
        quicklook_png(tmp_path / "bad.png", cube[0], grid)
