"""HDF5 image cubes: every image arrives (guaranteed reader), values, times and WCS are right."""
import time

import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySourceBlock, ImageCubeWriterBlock, bfp
from bf_epic_blocks.imaging.calibration import FS_HZ
from bf_epic_blocks.io.cube import cube_to_fits, read_image_cube
from test_transient import DT, TIME_TAG, image_header

pytest.importorskip("h5py")


class SlowCubeWriter(ImageCubeWriterBlock):
    def on_data(self, ispan):
        time.sleep(0.004)
        super().on_data(ispan)


def _images(n, grid, nchan, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(10.0, 1.0, (n, nchan, 1, grid.size, grid.size)).astype(np.float32)
    x[:, :, :, ~grid.mask] = np.nan                       # as the imager leaves them
    return x


def test_guaranteed_writer_loses_no_image_and_keeps_values_and_times(tmp_path):
    grid = imaging.lm_grid(16)
    freq = 74e6 + 25e3 * np.arange(4)
    dt_img = 16 * DT
    x = _images(300, grid, 4)
    hdr = image_header(grid, freq, dt_img)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr, gulp_nframe=4, buffer_factor=2)   # small rings: back-pressure
        w = SlowCubeWriter(src, tmp_path, prefix="c", images_per_file=128)
        p.run()
    assert w.cube_stats == {"images": 300, "images_lost": 0, "files": 3}
    parts = [read_image_cube(f) for f in w.written]
    assert [c["nimages"] for c in parts] == [128, 128, 44] and all(c["complete"] for c in parts)
    got = np.concatenate([c["images"] for c in parts])
    np.testing.assert_array_equal(got, x.reshape(300, 4, 1, -1)[..., np.flatnonzero(grid.mask)])
    tags = np.concatenate([c["time_tag"] for c in parts])
    np.testing.assert_array_equal(tags, TIME_TAG + np.arange(300) * int(round(dt_img * FS_HZ)))
    g = read_image_cube(w.written[1], grid=True)["images"]                # (time, prod, chan, N, N)
    np.testing.assert_array_equal(g, np.swapaxes(x[128:256], 1, 2))


def test_float16_and_channel_average(tmp_path):
    grid = imaging.lm_grid(8)
    freq = 74e6 + 25e3 * np.arange(6)
    x = _images(50, grid, 6, seed=1)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, 16 * DT), gulp_nframe=16)
        w = ImageCubeWriterBlock(src, tmp_path, dtype="float16", average_channels=True)
        p.run()
    c = read_image_cube(w.written[0])
    assert c["images"].dtype == np.float16 and c["images"].shape == (50, 1, 1, grid.npix)
    expect = x.reshape(50, 6, 1, -1)[..., np.flatnonzero(grid.mask)].mean(axis=1, keepdims=True)
    np.testing.assert_allclose(c["images"].astype(np.float32), expect, rtol=1e-3)   # float16: 11 bits
    assert c["freq_hz"] == pytest.approx([freq.mean()]) and c["chan_width_hz"] == pytest.approx(150e3)


def test_unguaranteed_writer_counts_lost_images_and_time_tags_jump(tmp_path):
    grid = imaging.lm_grid(8)
    freq = 74e6 + 25e3 * np.arange(2)
    n = 400
    x = _images(n, grid, 2, seed=2)
    x[:, :, :, grid.mask] += np.arange(n, dtype=np.float32)[:, None, None, None]   # image j holds ~10 + j
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, 16 * DT), gulp_nframe=4)
        w = SlowCubeWriter(src, tmp_path, guarantee=False)
        p.run()
    c = read_image_cube(w.written[0])
    lost = w.cube_stats["images_lost"]
    assert lost > 0 and c["nimages"] + lost == n and c["images_lost"] == lost
    j = (c["time_tag"] - TIME_TAG) // int(round(16 * DT * FS_HZ))      # which input image each one is
    np.testing.assert_array_equal(c["images"], x.reshape(n, 2, 1, -1)[j][..., np.flatnonzero(grid.mask)])


def test_fits_export_carries_the_sky_and_time_wcs(tmp_path):
    from astropy.io import fits
    from astropy.wcs import WCS
    from bf_epic_blocks.sky.catalogue import lm_to_icrs
    from bf_epic_blocks.io.tbf import time_tag_to_time
    grid = imaging.lm_grid(32)
    freq = 74e6 + 25e3 * np.arange(3)
    dt_img = 16 * DT
    x = _images(20, grid, 3, seed=3)
    hdr = image_header(grid, freq, dt_img)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr, gulp_nframe=8)
        w = ImageCubeWriterBlock(src, tmp_path)
        p.run()
    path = cube_to_fits(w.written[0], tmp_path / "c.fits", start=5, stop=15)
    with fits.open(path) as h:
        data, header = h[0].data, h[0].header
    assert data.shape == (10, 1, 3, 32, 32)
    np.testing.assert_array_equal(data, np.swapaxes(x[5:15], 1, 2))
    wcs = WCS(header)
    ix, iy = 22, 9                                                   # some pixel above the horizon
    l, m = grid.axis[ix], grid.axis[iy]
    ra, dec, f, s, t = wcs.all_pix2world([[ix, iy, 2, 0, 3]], 0)[0]
    ra0, dec0 = lm_to_icrs([[l, m]], time_tag_to_time(TIME_TAG), w.loc)
    assert np.hypot((ra - ra0[0]) * np.cos(np.radians(dec)), dec - dec0[0]) < 0.05 * np.degrees(grid.cell)
    assert f == pytest.approx(freq[2]) and s == 1.0
    assert t == pytest.approx((5 + 3) * dt_img)                     # seconds after the first image


def test_float16_overflow_is_counted_and_logged_once_not_warned_each_gulp(tmp_path, caplog):
    """Values beyond float16's range are stored as inf, counted (``overflow``) and logged once; numpy's
    cast warning, which would repeat every gulp of a week's run, is not raised."""
    import logging
    import warnings

    from bf_epic_blocks.io.cube import ImageCubeWriter
    lm = np.zeros((3, 2))
    with ImageCubeWriter(tmp_path / "c.h5", [74e6], ["I"], lm, 0, 1, dtype="float16") as w:
        x = np.ones((4, 1, 1, 3), np.float32)
        x[1, 0, 0, 2] = 1e6
        with warnings.catch_warnings(), caplog.at_level(logging.WARNING):
            warnings.simplefilter("error")
            w.append(x)
            w.append(x)
        assert w.overflow == 2
    assert sum("beyond the float16 range" in r.getMessage() for r in caplog.records) == 1
    c = read_image_cube(tmp_path / "c.h5")
    assert np.isinf(c["images"][1, 0, 0, 2]) and np.isinf(c["images"][5, 0, 0, 2])
    assert np.count_nonzero(np.isinf(c["images"])) == 2
