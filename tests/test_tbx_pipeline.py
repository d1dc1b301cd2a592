"""TBX through the pipeline: the real LWA-NA TBX capture imaged via the CLI (kind tbx and kind file)."""
import warnings
from pathlib import Path

import numpy as np
import pytest

from bf_epic_blocks.station.offline import configure_offline

configure_offline()
pytest.importorskip("lsl")

from bf_epic_blocks.pipeline import cli  # noqa: E402
from bf_epic_blocks.pipeline.config import ConfigError, load_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
YAML = REPO / "pipelines" / "lwana_tbx_allsky.yaml"
TBX = REPO / "tests" / "data" / "lwana-ndp-tbx.dat"

# every test here images, plans or names the real capture in tests/data
pytestmark = pytest.mark.real_data


def _fits(out):
    from astropy.io import fits
    from astropy.wcs import WCS
    (path,) = sorted(out.glob("*.fits"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # no FITSFixedWarning: OBSGEO-L/B/H are written too
        with fits.open(path) as h:
            return h[0].data.copy(), WCS(h[0].header), dict(h[0].header)


def _peaks(img, wcs, n, exclude_deg=12.0):
    """The n brightest pixels of a 2-D image, each at least exclude_deg from the brighter ones (SkyCoords)."""
    a = img.copy()
    yy, xx = np.mgrid[:a.shape[0], :a.shape[1]]
    ok = np.isfinite(a.ravel())
    pts = wcs.celestial.pixel_to_world(xx.ravel()[ok], yy.ravel()[ok])
    out = []
    for _ in range(n):
        k = int(np.nanargmax(a.ravel()[ok]))
        out.append((pts[k], float(a.ravel()[ok][k])))
        sep = pts.separation(pts[k]).deg
        flat = a.ravel()
        idx = np.flatnonzero(ok)[sep < exclude_deg]
        flat[idx] = np.nan
    return out


def test_real_tbx_images_the_sun_then_cas_a(tmp_path):
    """The one-sample, 312-channel capture (2024-06-27 17:32:27 UTC): brightest peak on the Sun,
    the next on Cas A, both within 2 pixels (cell 1.8 deg at the zenith)."""
    from astropy.coordinates import AltAz, EarthLocation, SkyCoord, get_body
    from astropy.time import Time
    out = tmp_path / "tbx"
    assert cli.main(["run", str(YAML), "--set", f"output.dir={out}", "--set", "output.png=false",
                     "--no-progress", "-q"]) == 0
    data, wcs, hdr = _fits(out)
    assert data.shape == (1, 312, 64, 64) and hdr["DATE-OBS"].startswith("2024-06-27T17:32:27")
    assert hdr["CRVAL3"] == pytest.approx(2176 * 196e6 / 8192)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        img = np.nanmean(data[0], axis=0)
    assert np.isfinite(img).sum() == 3205
    (p1, v1), (p2, v2), (p3, v3) = _peaks(img, wcs, 3)
    t = Time(hdr["DATE-OBS"], scale="utc")
    loc = EarthLocation.from_geocentric(hdr["OBSGEO-X"], hdr["OBSGEO-Y"], hdr["OBSGEO-Z"], unit="m")
    frame = AltAz(obstime=t, location=loc)
    sun = get_body("sun", t, loc).transform_to(frame)   # direct to AltAz: no parallax through ICRS
    cas = SkyCoord(350.8584, 58.8117, unit="deg").transform_to(frame)
    assert p1.transform_to(frame).separation(sun).deg < 3.6
    assert p2.transform_to(frame).separation(cas).deg < 3.6
    # both stand out of the rest of the sky: the third peak is well below them
    rest = img[np.isfinite(img)]
    assert (v2 - np.median(rest)) > 1.15 * (v3 - np.median(rest))


def test_kind_file_detects_tbx_and_gives_the_same_image(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    small = ["--set", "imager.grid.size=16", "--set", "output.png=false", "--no-progress", "-q"]
    assert cli.main(["run", str(YAML), "--set", f"output.dir={a}", *small]) == 0
    assert cli.main(["run", str(YAML), "--set", f"output.dir={b}", "--set", "source.kind=file", *small]) == 0
    da, _, _ = _fits(a)
    db, _, _ = _fits(b)
    np.testing.assert_array_equal(da, db)


def test_tbx_file_given_as_tbf_is_a_clear_error(tmp_path, capsys):
    rc = cli.main(["run", str(YAML), "--set", "source.kind=tbf", "--set", f"output.dir={tmp_path}",
                   "--no-progress", "-q"])
    assert rc != 0
    err = capsys.readouterr().err
    assert "frame id 8 is not a TBF frame id" in err and "TBX" in err


def test_config_source_kinds():
    cfg = load_config(f"source: {{kind: file, path: {TBX}}}")
    assert cfg["source"]["kind"] == "file" and cfg["source"]["path"] == str(TBX.resolve())
    cfg = load_config(f"source: {{kind: tbx, path: {TBX}, gulp_nframe: 4}}")
    assert cfg["source"]["gulp_nframe"] == 4
    with pytest.raises(ConfigError) as e:
        load_config("source: {kind: tbx, path: nowhere.tbx}")
    assert e.value.problems == ["source.path (line 1): TBX file 'nowhere.tbx' not found (looked for "
                                f"{Path.cwd() / 'nowhere.tbx'})"]
    with pytest.raises(ConfigError) as e:
        load_config(f"source: {{kind: tbx, path: {TBX}, seed: 3}}")
    assert e.value.problems == ["source.seed (line 1): only used when source.kind is 'simulated' (kind is 'tbx')"]
    with pytest.raises(ConfigError) as e:
        load_config("source: {kind: simulated, path: x.tbx}")
    assert e.value.problems == ["source.path (line 1): only used when source.kind is 'tbf' or 'tbx' or 'file' "
                                "(kind is 'simulated')"]


def test_plan_reads_the_tbx_file(capsys):
    assert cli.main(["plan", str(YAML), "--set", "source.kind=file"]) == 0
    out = capsys.readouterr().out
    assert "312 (52.062-59.503 MHz)" in out and "1 frames" in out
