"""Non-finite (NaN/Inf) voltage samples: zeroed, counted per antenna, logged, recorded; images stay finite."""
import logging
import warnings

import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import (ArraySinkBlock, ArraySourceBlock, CalFoldBlock, DFTImagerBlock, bfp,
                                   efield_header)
from bf_epic_blocks.blocks.nonfinite import get_tally
from bf_epic_blocks.imaging.sanitize import zero_nonfinite

NST, NCHAN, T, ACC, GULP = 10, 2, 96, 32, 24


def to_np(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


# -------------------------------------------------------------------------------- the pure function
def planted(seed=0):
    """cf32 voltages (T, nchan, nstand, 2), the positions of the planted non-finite samples, their counts."""
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(T, NCHAN, NST, 2)) + 1j * rng.normal(size=(T, NCHAN, NST, 2))).astype(np.complex64)
    bad_values = [complex(np.nan, 1.0), complex(1.0, np.inf), complex(-np.inf, 0.0), complex(np.nan, np.nan),
                  complex(np.inf, -np.inf), complex(0.0, np.nan)]
    where = [(3, 0, 2, 0), (3, 1, 2, 0), (40, 0, 7, 1), (41, 1, 7, 1), (41, 0, 9, 0), (90, 1, 0, 1),
             (90, 0, 0, 1), (5, 1, 2, 0)]
    for k, idx in enumerate(where):
        x[idx] = bad_values[k % len(bad_values)]
    counts = np.zeros((NST, 2), np.int64)
    per_time = np.zeros((T, NST, 2), np.int64)
    for t, c, s, p in where:
        counts[s, p] += 1
        per_time[t, s, p] += 1
    zeroed = x.copy()
    for idx in where:
        zeroed[idx] = 0
    return x, zeroed, counts, per_time, where


def test_zero_nonfinite_zeroes_and_counts_exactly(xp):
    x, zeroed, counts, per_time, where = planted()
    clean, c = zero_nonfinite(xp.asarray(x))
    assert c.shape == (NST, 2) and c.dtype == np.int64
    np.testing.assert_array_equal(to_np(c), counts)
    np.testing.assert_array_equal(to_np(clean), zeroed)
    assert np.isfinite(to_np(clean)).all()
    assert np.isnan(x[where[0]])          # the input is untouched (not inplace)
    _, c2 = zero_nonfinite(xp.asarray(x), per_time=True)
    assert c2.shape == (T, NST, 2)
    np.testing.assert_array_equal(to_np(c2), per_time)
    y = xp.asarray(x)
    out, _ = zero_nonfinite(y, inplace=True)
    assert out is y
    np.testing.assert_array_equal(to_np(y), zeroed)


def test_zero_nonfinite_clean_input_is_returned_as_is(xp):
    x = xp.asarray(planted()[1])
    clean, c = zero_nonfinite(x)
    assert clean is x and int(c.sum()) == 0
    r = xp.asarray(np.array([[1.0, np.inf], [np.nan, 2.0]], np.float32))   # real float voltages (nant, npol)
    clean, c = zero_nonfinite(r)
    np.testing.assert_array_equal(to_np(clean), [[1, 0], [0, 2]])
    np.testing.assert_array_equal(to_np(c), [[0, 1], [1, 0]])
    with pytest.raises(TypeError, match="integer samples cannot be non-finite"):
        zero_nonfinite(np.zeros((2, 3, 2), np.int8))
    with pytest.raises(ValueError, match="per_time"):
        zero_nonfinite(np.zeros((3, 2), np.complex64), per_time=True)


# -------------------------------------------------------------------------------- through the blocks
@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    xyz = rng.normal(0, 15, (NST, 3)) * [1, 1, 0.05]
    freq = 60e6 + 25e3 * np.arange(NCHAN)
    lm = np.concatenate([imaging.lm_grid(8).lm, [[0.3, 0.4]]])
    return dict(xyz=xyz, freq=freq, lm=lm)


def header(s, dtype="cf32"):
    return efield_header("nan-test", 337023871211995136, s["freq"], 40e-6, {"name": "test", "xyz_m": s["xyz"]}, dtype=dtype)


def run(X, hdr, lm, calfold=True, writer_dir=None):
    from bf_epic_blocks.blocks.image_writer import ImageWriterBlock
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=GULP)
        cal = CalFoldBlock(src, cable=False) if calfold else None
        img = DFTImagerBlock(cal if calfold else src, lm, ACC, products=["I"], precision="fp64")
        sink = ArraySinkBlock(img)
        writer = None
        if writer_dir is not None:
            from astropy.coordinates import EarthLocation
            writer = ImageWriterBlock(img, writer_dir, prefix="nan", png=False, table=True,
                                      location=EarthLocation.from_geodetic(-107.64, 34.247, 2133.6))
        p.run()
    return sink, cal, img, writer


@pytest.mark.parametrize("through_calfold", [True, False], ids=["calfold", "imager-only"])
def test_blocks_zero_count_and_log(scene, caplog, through_calfold):
    x, zeroed, counts, per_time, where = planted()
    with caplog.at_level(logging.WARNING, logger="bf_epic_blocks"):
        sink, cal, img, _ = run(x, header(scene), scene["lm"], calfold=through_calfold)
    ref_sink, *_ = run(zeroed, header(scene), scene["lm"], calfold=through_calfold)
    out, ref = to_np(sink.result()), to_np(ref_sink.result())
    assert out.shape == (T // ACC, NCHAN, 1, len(scene["lm"]))
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(out, ref)   # exactly the image of the voltages with those samples zeroed
    # and that image is the definition's (float64 core) on the zeroed voltages
    for j in range(T // ACC):
        truth = imaging.dirty_image(zeroed[j * ACC:(j + 1) * ACC].astype(np.complex128), scene["xyz"], scene["freq"],
                                    scene["lm"], precision="fp64", products=["I"])
        np.testing.assert_allclose(out[j], truth, rtol=1e-6)   # images are f32 on the ring
    owner = cal if through_calfold else img
    np.testing.assert_array_equal(owner.tally.counts, counts)
    assert owner.tally.total == len(where)
    assert owner.tally.frames == {t: int(per_time[t].sum()) for t in np.flatnonzero(per_time.sum(axis=(1, 2)))}
    hdr_out = sink.headers[0]
    assert hdr_out["nonfinite"] == {"tally": owner.tally.id, "zeroed_by": type(owner).__name__}
    assert get_tally(hdr_out) is owner.tally
    if through_calfold:
        assert cal.cal_stats["nonfinite"] == len(where)
        np.testing.assert_array_equal(cal.nonfinite_counts, counts)
        assert img.tally is None          # CalFoldBlock cleaned the data; the imager does not count again
    # one warning per gulp that had any (frames 3-5 in gulp 0, 40-41 in gulp 1, 90 in gulp 3), plus a summary
    per_gulp = [r for r in caplog.records if "non-finite samples zeroed in frames" in r.getMessage()]
    assert [r.getMessage().split(" in frames ")[1].split(" on ")[0] for r in per_gulp] == ["0-23", "24-47", "72-95"]
    assert "3 non-finite samples zeroed" in per_gulp[0].getMessage()


def test_integer_input_is_not_checked(scene):
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    rng = np.random.default_rng(0)
    ints = rng.integers(-8, 8, (T, NCHAN, NST, 2)) + 1j * rng.integers(-8, 8, (T, NCHAN, NST, 2))
    sink, cal, img, _ = run(pack_ci4(ints), header(scene, "ci4"), scene["lm"])
    # CalFoldBlock does not look at integer samples, but its tally (all zeros) tells the imager the data are clean
    assert cal.tally.total == 0 and not cal.tally.frames and img.tally is None
    assert sink.headers[0]["nonfinite"]["zeroed_by"] == "CalFoldBlock"


def test_fits_and_tables_record_nonfinit_per_integration(scene, tmp_path):
    """NONFINIT of integration j = the samples zeroed in its frames [j*ACC, (j+1)*ACC)."""
    from astropy.io import fits
    from astropy.wcs import WCS
    x, _, _, per_time, _ = planted()
    expect = per_time.reshape(T // ACC, ACC, -1).sum(axis=(1, 2))
    assert list(expect) == [3, 3, 2]
    # pixel tables (a list of pixels)
    _, _, _, writer = run(x, header(scene), scene["lm"], writer_dir=tmp_path / "tab")
    tables = sorted(p for p in writer.written if p.endswith("_pixels.fits"))
    assert len(tables) == T // ACC
    for j, path in enumerate(tables):
        with fits.open(path) as h:
            assert h[0].header["NONFINIT"] == expect[j] and h["PIXELS"].header["NONFINIT"] == expect[j]
            assert np.isfinite(h["PIXELS"].data["I"]).all()
    # FITS cubes (an all-sky grid): NONFINIT, and the header reads back without fix-up warnings
    _, _, _, writer = run(x, header(scene), imaging.lm_grid(8), writer_dir=tmp_path / "cube")
    cubes = sorted(p for p in writer.written if p.endswith(".fits"))
    assert len(cubes) == T // ACC
    for j, path in enumerate(cubes):
        with fits.open(path) as h:
            assert h[0].header["NONFINIT"] == expect[j]
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                WCS(h[0].header)
            data = h[0].data
            inside = imaging.lm_grid(8).mask
            assert np.isfinite(data[..., inside]).all()


def test_nonfinite_cable_weight_flags_the_antenna(scene):
    x = planted()[1]
    w = np.ones((1, NST, 2), np.complex64)
    w[0, 6, 1] = np.nan
    with bfp.Pipeline() as p:
        cal = CalFoldBlock(ArraySourceBlock(x, header(scene), gulp_nframe=GULP), cable=w)
        sink = ArraySinkBlock(cal)
        p.run()
    flags = np.array(sink.headers[0]["station"]["flags"])
    assert flags[6, 1] and flags.sum() == 1
    assert np.isfinite(to_np(sink.result())).all()
