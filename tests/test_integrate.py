"""ImageIntegratorBlock: the mean of every N images (and of the channels), against NumPy means of the
same images; its header (time step, one channel at the band's mean frequency); and through
`bf-epic run`, band-averaged FITS equal to the mean of the per-channel images the cube keeps."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, ImageIntegratorBlock, bfp, image_layout
from test_transient import DT, image_header


@pytest.mark.parametrize("average,gulp", [(True, 64), (False, 7), (True, 500)])
def test_integrations_are_the_means_of_their_images(average, gulp):
    rng = np.random.default_rng(3)
    grid = imaging.lm_grid(16)
    freq = 74e6 + 25e3 * np.arange(5)
    x = rng.normal(5.0, 1.0, (230, 5, 1, 16, 16)).astype(np.float32)
    x[..., ~grid.mask.reshape(16, 16)] = np.nan                     # below the horizon, as the imager leaves it
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, 16 * DT), gulp_nframe=gulp)
        it = ImageIntegratorBlock(src, 50, average_channels=average)
        sink = ArraySinkBlock(it)
        p.run()
    got = sink.result(0)
    want = x[:200].reshape(4, 50, 5, 1, 16, 16).astype(np.float64).mean(axis=1)
    if average:
        want = want.mean(axis=1, keepdims=True)
    assert got.shape == want.shape == ((4, 1, 1, 16, 16) if average else (4, 5, 1, 16, 16))
    ok = np.isfinite(want)
    assert np.array_equal(np.isfinite(got), ok)
    assert np.allclose(got[ok], want[ok], rtol=1e-6)
    lay = image_layout(sink.headers[0])
    assert lay["dt_s"] == pytest.approx(50 * 16 * DT)
    assert np.allclose(lay["freq_hz"], [freq.mean()] if average else freq)
    assert it.int_stats == {"images_in": 230, "images_out": 4, "images_dropped_partial": 30, "channel_images_flagged": 0}


def test_an_integration_of_an_integration_counts_the_imagers_images_and_channels():
    """The band mean of each image, then the mean of every 25 of those: the images the second's mean,
    and its header's record counts the imager's images and channels (not the first's one channel)."""
    rng = np.random.default_rng(5)
    grid = imaging.lm_grid(16)
    freq = 74e6 + 25e3 * np.arange(5)
    x = rng.normal(5.0, 1.0, (100, 5, 1, 16, 16)).astype(np.float32)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, 16 * DT), gulp_nframe=32)
        band = ImageIntegratorBlock(src, 1, average_channels=True)
        it = ImageIntegratorBlock(band, 25, average_channels=True)
        sink = ArraySinkBlock(it)
        p.run()
    want = x.astype(np.float64).mean(axis=1).reshape(4, 25, 1, 16, 16).mean(axis=1)
    assert np.allclose(sink.result(0)[:, 0], want, rtol=1e-6)
    assert sink.headers[0]["integrated"] == {"images": 25, "average_channels": True, "nchan_in": 5}
    assert image_layout(sink.headers[0])["dt_s"] == pytest.approx(25 * 16 * DT)


def test_bad_lengths_are_named():
    with pytest.raises(ValueError, match="nimage"):
        ImageIntegratorBlock(None, 0)
    with pytest.raises(ValueError, match="one of them"):
        ImageIntegratorBlock(None)
    with pytest.raises(ValueError, match="seconds"):
        ImageIntegratorBlock(None, seconds=-1)


@pytest.mark.slow
def test_wholeband_pipeline_made_small(tmp_path):
    """pipelines/lwasv_sim_wholeband.yaml with 16 channels on a 16x16 grid (the CPU's share of it): the
    tree search finds the burst at its DM (+-1 sweep), arrival and place; each band-averaged FITS is
    the mean of the per-channel images the cube keeps over its second (here 0.1 s)."""
    from pathlib import Path
    from astropy.coordinates import SkyCoord
    from astropy.io import fits
    from bf_epic_blocks.conventions import dispersion_delay_s
    from bf_epic_blocks.io.candidates import read_candidates
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"
    cfg = load_config(yaml, [f"output.dir={tmp_path}", "source.duration_s=0.42", "source.channels.count=16",
                             "imager.grid.size=16", "imager.search.window_s=0.06", "imager.search.dms=[1.0]",
                             "imager.search.threshold=7", "output.integrate.seconds=0.1",
                             "output.cube.dtype=float32", "output.cube.average_channels=false",
                             "watch={targets: [{name: FRB1, ra_deg: 310.0, dec_deg: 20.0}, CygA], "
                             "save_after_s: 0.05, png_every_s: 1.0}",
                             "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, duration_s: 0.0015, "
                             "flux_jy: 2000.0, dm: 0.6}]"])
    summary = run(cfg, show_progress=False)
    dt = 16 * DT
    # the candidates save one snippet: the band-averaged images before the burst and 0.05 s after it
    import h5py
    snips = sorted(tmp_path.glob("*_snippet_*candidate*.h5"))
    assert len(snips) == 1 and summary["watch"]["triggers"]["saved"] == 1, summary["watch"]
    with h5py.File(snips[0]) as f:
        t, when = f["time_unix"][:], float(f.attrs["trigger_unix"])
        assert f.attrs["complete"] and t.min() < when - 0.2 and t.max() >= when + 0.049
    tab = read_candidates(tmp_path / "lwasv_sim_wholeband_candidates.ecsv")
    best = tab[int(np.argmax(tab["snr"]))]
    print(tab["snr", "dm", "width", "image", "ra_deg", "dec_deg"])
    freq = (2960 + np.arange(16)) * 25e3
    step = 1.0 / (dispersion_delay_s(1.0, freq.min(), freq.max()) / dt)       # DM per sweep
    assert abs(best["dm"] - 0.6) <= 1.01 * step and best["snr"] > 10
    assert abs(best["image"] - 0.3 / dt) <= 1
    sep = SkyCoord(best["ra_deg"], best["dec_deg"], unit="deg").separation(SkyCoord(310.0, 20.0, unit="deg")).deg
    assert sep < 1.5 * np.degrees(2 / 16)                       # within ~one 7-degree cell
    cube = read_image_cube(next(tmp_path.glob("*_cube_*.h5")))
    imgs = cube["images"]                                                     # (n, 16, 1, npix)
    n = int(round(0.1 / dt))
    files = sorted(tmp_path.glob("lwasv_sim_wholeband_*.fits"))
    assert len(files) == summary["images"] // n == 4
    for k, f in enumerate(files):
        with fits.open(f) as h:
            data, hdr = h[0].data, h[0].header
        assert data.shape[-3] == 1 and hdr["CRVAL3"] == pytest.approx(freq.mean())
        want = imgs[k * n:(k + 1) * n].astype(np.float64).mean(axis=(0, 1))[0]      # (npix,)
        got = data.reshape(-1)[cube["pixel_index"]]
        assert np.allclose(got, want, rtol=2e-6)


@pytest.mark.slow
def test_search_with_a_minimum_elevation(tmp_path):
    """imager.min_elevation_deg leaves the pixels below it NaN on the grid; the image header says which
    pixels were imaged (pixels.index), so the search takes only those (it had taken every pixel above the
    horizon, and the tree refused the NaN) and still finds the burst."""
    from pathlib import Path
    from bf_epic_blocks.io.candidates import read_candidates
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"
    cfg = load_config(yaml, [f"output.dir={tmp_path}", "source.duration_s=0.42", "source.channels.count=16",
                             "imager.grid.size=16", "imager.min_elevation_deg=20", "imager.search.window_s=0.06",
                             "imager.search.dms=[1.0]", "imager.search.threshold=7", "output.integrate=null",
                             "output.fits=false", "output.png=false", "output.cube=null",
                             "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, duration_s: 0.0015, "
                             "flux_jy: 2000.0, dm: 0.6}]"])
    summary = run(cfg, show_progress=False)
    tab = read_candidates(tmp_path / "lwasv_sim_wholeband_candidates.ecsv")
    best = tab[int(np.argmax(tab["snr"]))]
    assert abs(best["image"] - 0.3 / (16 * DT)) <= 1 and best["snr"] > 10
    from bf_epic_blocks.imaging.pixels import lm_grid
    assert summary["search"]["trials_per_width"][0] % lm_grid(16, min_elevation_deg=20).npix == 0


@pytest.mark.slow
@pytest.mark.parametrize("device", ["cpu", pytest.param("gpu", marks=[
    pytest.mark.gpu, pytest.mark.skipif(not imaging._xp.gpu_available(), reason="needs CuPy and a CUDA device")])])
def test_wholeband_images_equal_a_float64_evaluation(tmp_path, device):
    """The whole-band pipeline (made small: 16 channels, a 16x16 grid, 0.1 s; no antenna pattern) through
    `bf-epic run`: the per-channel 0.64-ms images it keeps, at randomly chosen channels and times, equal
    the float64 definition (tests/truth.py: an explicit sum over antennas, the cable terms as PHYSICS.md
    writes them) of the very voltages the simulator made, within the YAML's tolerance (1e-4: the mode
    the tolerance picks on that device, i8x2 on a GPU)."""
    from pathlib import Path
    from truth import brute_image, calibration_weights
    from bf_epic_blocks.blocks.sources import SimSkySourceBlock
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import _pixels, channel_freqs, load_station_for, run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"
    cfg = load_config(yaml, [f"output.dir={tmp_path}", f"device={device}", "source.duration_s=0.1",
                             "source.channels.count=16", "imager.grid.size=16", "imager.search=null",
                             "calibration.pattern=none", "output.integrate=null", "output.fits=false",
                             "output.png=false", "output.cube.dtype=float32", "output.cube.average_channels=false"])
    run(cfg, show_progress=False)
    cube = read_image_cube(next(tmp_path.glob("*_cube_*.h5")))
    imgs = cube["images"]                                                    # (n, 16, 1, npix)
    # the same voltages again (every sample is a function of the seed and its place), to the host
    src = cfg["source"]
    station = load_station_for(cfg)
    freq = channel_freqs(cfg)
    with bfp.Pipeline() as p:
        # (with the YAML's burst too, though it starts later: the generator's streams depend on the
        # sky's columns, a burst's included, so without it every sample would differ)
        sim = SimSkySourceBlock(station, freq, src["start"], src["duration_s"], src["sources"], 1024,
                                noise_power=src["noise_power"], seed=src["seed"], quantize=src["quantize"],
                                refresh_s=src["refresh_s"],
                                transients=[{k: v for k, v in t.items() if v is not None} for t in src["transients"]])
        sink = ArraySinkBlock(sim)
        p.run()
    x = sink.result(as_complex=True).astype(np.complex128)                  # (nframe, 16, nstand, 2)
    acc = cfg["imager"]["accumulate_frames"]
    assert imgs.shape[0] == x.shape[0] // acc and imgs.shape[1] == 16
    lm = _pixels(cfg, station).lm
    w = calibration_weights(np.moveaxis(station.cable_delay_s(freq), -1, 0),
                            np.moveaxis(station.cable_gain(freq), -1, 0), station.flags, freq)
    rng = np.random.default_rng(22)
    errs = []
    for j, c in zip(rng.integers(0, imgs.shape[0], 6), rng.integers(0, 16, 6)):
        want = brute_image(x[j * acc:(j + 1) * acc, c:c + 1], station.xyz_m, freq[c:c + 1], lm, ["I"],
                           weights=w[c:c + 1])[0, 0]
        got = imgs[j, c, 0]
        errs.append(np.abs(got - want).max() / np.abs(want).max())
    print(device, "max |I - I_exact| / max I_exact per image:", np.array(errs))
    assert max(errs) <= cfg["imager"]["tolerance"]
    assert max(errs) > 0                                                     # (a real comparison: float32 at best)


@pytest.mark.slow
def test_wholeband_band_mean_made_once_for_the_files_and_the_cube(tmp_path):
    """Where the files and the cube both average the channels (pipelines/lwasv_sim_wholeband.yaml), the
    band mean of each image is made once, by one block reading the imager, and both outputs read it: the
    cube's band-averaged images equal the float64 mean over channels of the per-channel images a second
    run keeps (themselves held to float64 truth in test_wholeband_images_equal_a_float64_evaluation), and
    each FITS the mean of the cube's images over its span."""
    from pathlib import Path
    from astropy.io import fits
    from bf_epic_blocks.blocks.integrate import ImageIntegratorBlock
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import build_graph, run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"
    small = ["source.duration_s=0.1", "source.channels.count=16", "imager.grid.size=16", "imager.search=null",
             "calibration.pattern=none", "output.cube.dtype=float32", "output.png=false"]
    cfg = load_config(yaml, small + [f"output.dir={tmp_path / 'mean'}", "output.integrate.seconds=0.05"])
    g = build_graph(cfg)
    readers = [b for b in g.pipeline.blocks if b.irings and b.irings[0] is g.imager.orings[0]]
    means = [b for b in readers if isinstance(b, ImageIntegratorBlock)]
    assert len(means) == 1 and means[0].nimage == 1 and means[0].average_channels
    assert g.cube not in readers and g.cube.irings[0] is means[0].orings[0]
    run(cfg, show_progress=False)
    cfg1 = load_config(yaml, small + [f"output.dir={tmp_path / 'chan'}", "output.integrate=null", "output.fits=false",
                                      "output.cube.average_channels=false"])
    run(cfg1, show_progress=False)
    band = read_image_cube(next((tmp_path / "mean").glob("*_cube_*.h5")))
    chan = read_image_cube(next((tmp_path / "chan").glob("*_cube_*.h5")))
    assert band["images"].shape[1] == 1 and chan["images"].shape[1] == 16
    want = chan["images"].astype(np.float64).mean(axis=1)                       # (n, 1, npix)
    assert np.allclose(band["images"][:, 0], want, rtol=1e-6, atol=0)
    n = int(round(0.05 / (16 * DT)))
    files = sorted((tmp_path / "mean").glob("lwasv_sim_wholeband_*.fits"))
    assert len(files) == band["images"].shape[0] // n == 2
    for k, f in enumerate(files):
        with fits.open(f) as h:
            got = h[0].data.reshape(-1)[band["pixel_index"]]
        assert np.allclose(got, band["images"][k * n:(k + 1) * n, 0, 0].astype(np.float64).mean(axis=0), rtol=2e-6)


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
def test_the_gpu_band_mean_is_the_float64_mean_of_the_channels():
    """The band mean's kernel (a thread per output value, the channels summed in float64): NumPy's float64
    mean to its rounding, NaN wherever a channel is NaN (a cell below the horizon)."""
    import cupy as cp
    from bf_epic_blocks.imaging.reduce import channel_mean
    rng = np.random.default_rng(9)
    x = rng.normal(100.0, 30.0, (5, 37, 1, 300)).astype(np.float32)
    x[:, :, :, 7] = np.nan
    x[2, 11, 0, 40] = np.nan
    got = channel_mean(cp.asarray(x)).get()
    want = x.astype(np.float64).mean(axis=1, keepdims=True)
    assert got.shape == want.shape == (5, 1, 1, 300) and got.dtype == np.float64
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.allclose(got, want, rtol=1e-14, atol=0, equal_nan=True)


def test_channel_images_that_imaged_anything(xp):
    """rows_nonzero: a channel image with any value that is neither 0 nor NaN imaged something; zeros and
    NaN (below the horizon) alone did not. Rows whose one value lies past the first 256, or is negative,
    or at the very end, count; against the expression it stands for, on the host."""
    from bf_epic_blocks.imaging.reduce import rows_nonzero
    rng = np.random.default_rng(4)
    x = rng.normal(10.0, 3.0, (6, 9, 1, 700)).astype(np.float32)
    x[:, :, :, :50] = np.nan                                         # cells below the horizon
    x[1, 2] = 0.0                                                    # a wholly flagged channel
    x[2, 3] = 0.0
    x[2, 3, 0, 699] = -1e-30                                         # one negative value, at the end
    x[3, 4] = np.nan
    x[3, 5] = 0.0
    x[3, 5, 0, 300] = 2.0                                            # one value past the first 256
    x[4, 0] = np.where(np.isnan(x[4, 0]), np.nan, 0.0)               # zeros and NaN
    want = ((x > 0) | (x < 0)).reshape(6, 9, -1).any(axis=2)
    got = rows_nonzero(xp.asarray(x))
    got = got.get() if hasattr(got, "get") else got
    assert got.dtype == bool and got.shape == (6, 9)
    assert np.array_equal(got, want)
    assert not got[1, 2] and got[2, 3] and not got[3, 4] and got[3, 5] and not got[4, 0]
