"""Interference flagging in a pipeline, against interference the test chose.

A simulated sky (a point source and noise, 64 stands, 12 channels, 4-bit) with: steady carriers from a
direction near the horizon in two channels, an intermittent carrier in a third, two broadband impulses
of 1 ms, and one stand's own carrier. The flagger must find the contaminated stand-samples (>= 95%),
leave the clean blocks alone (<= 0.5% flagged, also on pure noise), and the image of the flagged data
must equal the clean data's image to 1% of the peak, where the unflagged image is wrong by order unity.
"""
from pathlib import Path

import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, ImageIntegratorBlock, bfp, \
    efield_header
from bf_epic_blocks.blocks.rfi_flag import FlagWeights, RFIFlagBlock
from bf_epic_blocks.runtime.dtypes import ci4_bytes, pack_ci4

C = 299792458.0
DT = 40e-6
T, NCHAN, NST, GULP, ACC, M = 8192, 12, 64, 2048, 16, 1024


def _phase(xyz, freq, l, m):
    n = np.sqrt(1.0 - l * l - m * m)
    return np.exp(2j * np.pi * freq[:, None] / C * (l * xyz[:, 0] + m * xyz[:, 1] + n * xyz[:, 2])[None, :])


def _gauss(rng, shape, power):
    return np.sqrt(power / 2) * (rng.normal(size=shape) + 1j * rng.normal(size=shape))


@pytest.fixture(scope="module")
def sky():
    rng = np.random.default_rng(11)
    r = 60 * np.sqrt(rng.random(NST))
    a = 2 * np.pi * rng.random(NST)
    xyz = np.stack([r * np.cos(a), r * np.sin(a), rng.normal(0, 0.3, NST)], axis=1)
    freq = 74e6 + 25e3 * np.arange(NCHAN)
    noise = 8.0                                           # complex power per sample (sigma 2 per part)
    # the source: constant power (a constant-modulus signal, random phase per sample), so that images of
    # different channel sets or image counts differ by the noise alone; 0.1 of the noise per stand keeps
    # its own kurtosis deficit (1%) far below the test's thresholds
    src = np.sqrt(0.1 * noise) * np.exp(2j * np.pi * rng.random((T, NCHAN, 1, 2))) \
        * _phase(xyz, freq, 0.2, 0.1)[None, :, :, None]
    clean = src + _gauss(rng, (T, NCHAN, NST, 2), noise)
    rfi = np.zeros_like(clean)
    truth = np.zeros((T, NCHAN, NST), bool)
    t = np.arange(T)[:, None, None, None]
    horizon = _phase(xyz, freq, 0.9, -0.35)[None, :, :, None]        # a transmitter near the horizon
    for c in (3, 7):                                                 # steady carriers, INR 2
        rfi[:, c:c + 1] += np.sqrt(2 * noise) * np.exp(2j * np.pi * 0.013 * c * t[:, 0:1]) * horizon[:, c:c + 1]
        truth[:, c] = True
    on = slice(2000, 3100)                                           # an intermittent carrier, INR 3
    rfi[on, 9:10] += np.sqrt(3 * noise) * np.exp(2j * np.pi * 0.021 * t[on, 0:1]) * horizon[:, 9:10]
    truth[on, 9] = True
    for t0 in (5003, 7011):                                          # 1-ms broadband sparks, 10x the noise
        sl = slice(t0, t0 + 25)
        rfi[sl] += _gauss(rng, (25, NCHAN, 1, 2), 10 * noise) * _phase(xyz, freq, -0.5, 0.6)[None, :, :, None]
        truth[sl] = True
    rfi[:, 1, 5] += np.sqrt(4 * noise) * np.exp(2j * np.pi * 0.031 * np.arange(T))[:, None]   # stand 5's own
    truth[:, 1, 5] = True

    def ci4(x):
        return pack_ci4(np.clip(np.round(x.real), -8, 7) + 1j * np.clip(np.round(x.imag), -8, 7))

    hdr = efield_header("rfi", 0, freq, DT, {"name": "test", "xyz_m": xyz, "flags": np.zeros((NST, 2), bool)})
    noise_only = _gauss(rng, (T, NCHAN, NST, 2), noise)
    return dict(clean=ci4(clean), dirty=ci4(clean + rfi), noise=ci4(noise_only), truth=truth, hdr=hdr)


def _flag(X, hdr, space="system", **kw):
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=GULP, space=space)
        fb = RFIFlagBlock(src, far=1e-3, block_frames=M, impulse_frames=ACC, **kw)
        sink = ArraySinkBlock(fb)
        p.run()
    out = sink.result(0)
    out = ci4_bytes(out.get() if hasattr(out, "get") else np.asarray(out))
    flagged = (out == 0).all(axis=3) & (np.asarray(X) != 0).any(axis=3)       # zeroed by the flagger
    return flagged, fb


def _clean_blocks_flagged(flagged, truth):
    """Fraction of (block of M, channel, stand) units without interference that hold any flag."""
    f = flagged.reshape(T // M, M, NCHAN, NST).any(axis=1)
    c = truth.reshape(T // M, M, NCHAN, NST).any(axis=1)
    return f[~c].mean()


def test_the_flagger_finds_the_interference_the_test_chose(sky, xp):
    flagged, fb = _flag(sky["dirty"], sky["hdr"], "system" if xp is np else "cuda")
    truth = sky["truth"]
    found = flagged[truth].mean()
    assert found >= 0.95, found
    assert _clean_blocks_flagged(flagged, truth) <= 0.005
    # each kind on its own
    assert flagged[:, 3].mean() > 0.99 and flagged[:, 7].mean() > 0.99
    assert flagged[5003:5028].mean() > 0.99 and flagged[7011:7036].mean() > 0.99
    assert flagged[:, 1, 5].mean() > 0.99
    others = np.arange(NST) != 5                                     # that stand's carrier flags that stand only
    assert flagged[:, 1, others][~truth[:, 1, others]].mean() < 0.01
    st = fb.summary()
    assert st["by_reason"]["sk-low"] > 0 and st["by_reason"]["impulse"] > 0 and st["by_reason"]["impulse-stand"] >= 0
    assert st["fraction_flagged"] == pytest.approx(flagged.mean(), rel=0.02)


def test_pure_4bit_noise_is_left_alone(sky):
    seen = []                                    # the interval reports: every 0.1 s of data (2,500 frames)
    flagged, fb = _flag(sky["noise"], sky["hdr"], report=lambda b: seen.append(b.summary()["stand_samples_seen"]),
                        report_every_s=0.1)
    assert len(seen) == 2 and seen[0] < seen[1] == fb.summary()["stand_samples_seen"]   # at 4,096 and 8,192 frames
    assert _clean_blocks_flagged(flagged, np.zeros_like(sky["truth"])) <= 0.005
    assert fb.summary()["fraction_flagged"] <= 0.005


def test_a_gulp_without_impulses_waits_once_and_copies_nothing_to_the_device(sky, xp, monkeypatch):
    """The flagger's gulp on noise: one copy to the host (its counts), and on a GPU no copy of a host array
    to the device after the first gulp: such a copy waits for the queued kernels inside the CUDA driver,
    holding up the imager's thread; the same gulp with an impulse takes the impulses' path as well."""
    import bf_epic_blocks.blocks.rfi_flag as rf
    host_copies, device_copies = [], []
    real_to_numpy = rf.to_numpy

    def counted(a):
        host_copies.append(a.shape)
        return real_to_numpy(a)
    monkeypatch.setattr(rf, "to_numpy", counted)
    if xp is not np:
        real_asarray = xp.asarray

        def asarray(a, *args, **kw):
            if isinstance(a, np.ndarray) and len(host_copies) > 1:        # after the first gulp
                device_copies.append(a.shape)
            return real_asarray(a, *args, **kw)
        monkeypatch.setattr(xp, "asarray", asarray)
    _, fb = _flag(sky["noise"], sky["hdr"], "system" if xp is np else "cuda")
    assert fb.flag_stats["flagged"]["impulse"] == fb.flag_stats["flagged"]["impulse-stand"] == 0
    assert len(host_copies) == fb.flag_stats["gulps"] == T // GULP
    assert device_copies == []
    host_copies.clear()
    _, fb = _flag(sky["dirty"], sky["hdr"], "system" if xp is np else "cuda")
    assert fb.flag_stats["flagged"]["impulse"] > 0
    assert fb.flag_stats["gulps"] < len(host_copies) <= 3 * fb.flag_stats["gulps"]


def _image(X, hdr, flag):
    lm = np.concatenate([imaging.lm_grid(24).lm, [[0.2, 0.1], [0.9, -0.35]]])   # the source, the transmitter
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=GULP)
        w = FlagWeights(ACC) if flag else None
        feed = RFIFlagBlock(src, far=1e-3, block_frames=M, impulse_frames=ACC, weights=w) if flag else src
        img = DFTImagerBlock(feed, lm, ACC, flag_weights=w)
        it = ImageIntegratorBlock(img, T // ACC, average_channels=True)
        sink = ArraySinkBlock(it)
        p.run()
    return np.asarray(sink.result(0))[0, 0].sum(axis=0), lm       # XX + YY, band and time mean


def test_the_flagged_image_is_the_clean_image(sky):
    clean, lm = _image(sky["clean"], sky["hdr"], False)
    flagged, _ = _image(sky["dirty"], sky["hdr"], True)
    dirty, _ = _image(sky["dirty"], sky["hdr"], False)
    peak = np.nanmax(clean)
    assert np.nanargmax(clean) == len(lm) - 2                          # the source
    err = np.nanmax(np.abs(flagged - clean)) / peak
    bad = np.nanmax(np.abs(dirty - clean)) / peak
    assert err <= 0.01, err
    assert bad > 0.3, bad


def test_images_of_part_of_the_array_are_rescaled_to_the_whole(sky):
    """A stand flagged for its own carrier leaves its channel's images (63/64)^2 of the whole array's for a
    point source; with the flagger's weights the imager returns them to the whole's units."""
    lm = np.array([[0.2, 0.1]])

    def per_channel(X, flag, weights):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(X, sky["hdr"], gulp_nframe=GULP)
            w = FlagWeights(ACC) if weights else None
            feed = RFIFlagBlock(src, far=1e-3, block_frames=M, impulse_frames=ACC, weights=w) if flag else src
            img = DFTImagerBlock(feed, lm, ACC, flag_weights=w)
            it = ImageIntegratorBlock(img, T // ACC, average_channels=False)
            sink = ArraySinkBlock(it)
            p.run()
        return np.asarray(sink.result(0))[0, :, :, 0].sum(axis=1), w     # (nchan,) XX + YY at the source

    clean, _ = per_channel(sky["clean"], False, False)
    plain, _ = per_channel(sky["dirty"], True, False)
    fixed, w = per_channel(sky["dirty"], True, True)
    assert plain[1] / clean[1] == pytest.approx((63 / 64) ** 2, abs=0.01)
    assert fixed[1] / clean[1] == pytest.approx(1.0, abs=0.005)
    assert w.stats["images_rescaled"] >= T // ACC
    ok = np.isin(np.arange(NCHAN), [0, 1, 2, 4, 5, 6, 8, 9, 10, 11])
    assert np.allclose(fixed[ok] / clean[ok], 1.0, atol=0.01)


def test_the_search_ignores_sparks_and_a_carrier_and_still_finds_the_burst(tmp_path):
    """A dispersed burst on the sky with two 1-ms sparks and a carrier added: searched without flagging,
    the sparks are candidates; with flagging (the flagged channel images treated as missing), none is,
    and the burst is found at its pixel, time and DM."""
    from bf_epic_blocks.blocks import TransientSearchBlock
    from bf_epic_blocks.conventions import FS_HZ
    from bf_epic_blocks.io.candidates import CandidateWriter
    from bf_epic_blocks.search import SearchSettings
    from bf_epic_blocks.sky import simulate_efield

    rng = np.random.default_rng(5)
    xyz = np.c_[rng.uniform(-30, 30, (24, 2)), rng.normal(0, 0.3, 24)]
    acc, nchan = 16, 8
    freq = 74e6 + 25e3 * np.arange(nchan)
    grid = imaging.lm_grid(16)
    gx, gy = 10, 5
    dt_img = acc * DT
    burst = {"l": (gx - 8) * grid.cell, "m": (gy - 8) * grid.cell, "start_s": 0.30 + 0.3 * dt_img,
             "duration_s": 4 * dt_img, "flux_jy": 0.1, "dm": 0.9}
    T = int(0.45 / DT) // acc * acc
    X = simulate_efield(xyz, freq, T, sources=[], noise_power=1.0, seed=3, transients=[burst]).astype(np.complex64)
    sparks = (3003, 5511)                                       # 1 ms each, 30x the noise, from one direction
    for t0 in sparks:
        X[t0:t0 + 25] += (_gauss(rng, (25, nchan, 1, 2), 30.0) * _phase(xyz, freq, -0.4, 0.3)[None, :, :, None])
    t = np.arange(T)[:, None, None]
    X[:, 2] += (np.sqrt(2.0) * np.exp(2j * np.pi * 0.017 * t) * _phase(xyz, freq[2:3], 0.85, -0.4)[0][None, :, None])
    st = {"name": "lwasv", "xyz_m": xyz, "lat_deg": 34.3484, "lon_deg": -106.8858, "elev_m": 1477.0}
    hdr = efield_header("burst", int(1717236000 * FS_HZ), freq, DT, st, dtype="cf32")
    dms = [0.0, 0.5, 1.0, 1.5, 2.0]

    def search(flag):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(X, hdr, gulp_nframe=1024)
            w = FlagWeights(acc, track_empty=True) if flag else None
            feed = RFIFlagBlock(src, far=1e-3, block_frames=1024, impulse_frames=acc, weights=w) if flag else src
            img = DFTImagerBlock(feed, grid, acc, products=["I"], pattern=False, flag_weights=w)
            srch = TransientSearchBlock(img, SearchSettings(threshold=6.0, window_s=0.1, dms=dms),
                                        writer=CandidateWriter(tmp_path / str(flag)), flag_weights=w)
            p.run()
        return srch.candidates, w

    def near_sparks(tab):
        return [int(r["image"]) for r in tab if any(abs(int(r["image"]) - t0 / acc) <= 16 for t0 in sparks)]

    plain, _ = search(False)
    assert near_sparks(plain), "the sparks should fool a search without flagging"
    tab, w = search(True)
    assert not near_sparks(tab), near_sparks(tab)
    assert w.stats["channel_images_filled"] > 0
    best = tab[int(np.argmax(tab["snr"]))]
    assert abs(best["grid_x"] - gx) <= 1 and abs(best["grid_y"] - gy) <= 1
    assert abs(best["image"] - burst["start_s"] / dt_img) <= 1.0
    assert best["dm"] == 1.0


def test_a_stand_s_own_spark_near_a_bright_source_is_no_candidate(tmp_path):
    """One stand's 1-image spark under a bright source. The flagger takes that stand out of that image only
    (not the whole band's stands, as a detector of the summed power would; not the stand for the whole
    kurtosis block, as a spark's high kurtosis would), which still changes the array's beam for one image
    across the band: the source's sidelobes jump as a burst at DM 0 would. The search takes that image as
    missing: no candidate near it, and the image is counted."""
    from bf_epic_blocks.blocks import TransientSearchBlock
    from bf_epic_blocks.conventions import FS_HZ
    from bf_epic_blocks.io.candidates import CandidateWriter
    from bf_epic_blocks.search import SearchSettings

    rng = np.random.default_rng(8)
    nst, acc, nchan = 24, 16, 16
    xyz = np.c_[rng.uniform(-30, 30, (nst, 2)), rng.normal(0, 0.3, nst)]
    freq = 74e6 + 25e3 * np.arange(nchan)
    T = int(0.3 / DT) // acc * acc
    noise = 1.0
    # a source as the sky's are, Gaussian noise from one direction (its kurtosis is noise's), twice the
    # receiver noise per stand
    src = _gauss(rng, (T, nchan, 1, 2), 2 * noise) * _phase(xyz, freq, 0.1, 0.2)[None, :, :, None]
    X = (src + _gauss(rng, (T, nchan, nst, 2), noise)).astype(np.complex64)
    spark = 230 * acc                                                   # one image, stand 7, 40x the noise
    X[spark:spark + acc, :, 7] += _gauss(rng, (acc, nchan, 2), 40 * noise)
    st = {"name": "lwasv", "xyz_m": xyz, "lat_deg": 34.3484, "lon_deg": -106.8858, "elev_m": 1477.0}
    hdr = efield_header("spark", int(1717236000 * FS_HZ), freq, DT, st, dtype="cf32")
    with bfp.Pipeline() as p:
        src_b = ArraySourceBlock(X, hdr, gulp_nframe=1024)
        w = FlagWeights(acc, track_empty=True)
        fb = RFIFlagBlock(src_b, far=1e-3, block_frames=1024, impulse_frames=acc, weights=w)
        img = DFTImagerBlock(fb, imaging.lm_grid(16), acc, products=["I"], pattern=False, flag_weights=w)
        srch = TransientSearchBlock(img, SearchSettings(threshold=6.0, window_s=0.1, dms=[0.0, 0.5, 1.0]),
                                    writer=CandidateWriter(tmp_path / "c"), flag_weights=w)
        p.run()
    assert fb.flag_stats["flagged"]["impulse-stand"] == acc * nchan          # the spark, on stand 7 only
    assert fb.flag_stats["flagged"]["impulse"] == 0
    assert w.stats["images_missing_stand_spark"] == 1
    # nothing near the spark's image, nor at the edges of its SK block (images 192 and 256): the spark's
    # samples are left out of stand 7's kurtosis, which would otherwise flag the stand for the whole block
    near = [(int(r["image"]), round(float(r["snr"]), 1)) for r in srch.candidates if 188 <= int(r["image"]) <= 260]
    assert not near, near


def test_bad_flagging_input_is_a_clear_error(tmp_path):
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    from bf_epic_blocks.pipeline.runner import build_graph, run
    base = ("name: f\nstation: {name: lwasv}\n"
            "source: {kind: simulated, start: '2024-06-01T10:00:00', duration_s: 0.03, gulp_nframe: 256,\n"
            "         channels: {first: 2960, count: 4, width_hz: 25000.0}, sources: [CygA], quantize: true}\n"
            "imager: {kind: dft, grid: {size: 8}, accumulate_frames: 256}\n"
            f"output: {{dir: {tmp_path / 'o'}, fits: false, png: false}}\n")
    for far in ("0", "1.5", "-1e-3"):
        with pytest.raises(ConfigError, match="flagging.far"):
            load_config(base + f"flagging: {{far: {far}}}\n")
    assert load_config(base + "flagging: {enabled: off}\n")["flagging"]["enabled"] == "off"   # YAML's bare off
    with pytest.raises(ConfigError, match=r"flagging.bad_freq_mhz\[0\]"):
        load_config(base + "flagging: {bad_freq_mhz: [[75, 74]]}\n")
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing here\n\n")
    with pytest.raises(ValueError, match="no ranges"):
        build_graph(load_config(base + f"flagging: {{bad_freq_file: {empty}}}\n"))
    bad = tmp_path / "bad.txt"
    bad.write_text("60.1\nsixty\n")
    with pytest.raises(ValueError, match="line 2"):
        build_graph(load_config(base + f"flagging: {{bad_freq_file: {bad}}}\n"))
    with pytest.raises(Exception, match="covers every channel"):
        run(load_config(base + "flagging: {enabled: on, bad_freq_mhz: [[10, 100]]}\n"), show_progress=False)
    # a simulated sky with flagging on: the run's summary and files say what was flagged
    summ = run(load_config(base + "flagging: {enabled: on, report_s: 0.01, bad_freq_mhz: [[74.02, 74.03]]}\n"),
               show_progress=False)
    assert summ["flagging"]["static_channels"] == 1 and summ["flagging"]["by_reason"]["static"] == 0.25
    assert any(f.endswith("f_flags.ecsv") for f in summ["files"]) and any(f.endswith("f_flags.png") for f in summ["files"])
    # each FITS image records the fraction of its stand-samples flagged: the listed channel, 1 of 4
    summ = run(load_config(base.replace("fits: false", "fits: true")
                           + "flagging: {enabled: on, bad_freq_mhz: [[74.02, 74.03]]}\n"), show_progress=False)
    from astropy.io import fits
    images = [f for f in summ["files"] if f.endswith(".fits")]
    assert images and all(fits.getheader(f)["FLAGFRAC"] == pytest.approx(0.25, abs=0.01) for f in images)


@pytest.mark.slow
@pytest.mark.parametrize("device", ["cpu", pytest.param("gpu", marks=[
    pytest.mark.gpu, pytest.mark.skipif(not imaging._xp.gpu_available(), reason="needs CuPy and a CUDA device")])])
def test_flagging_a_clean_sky_leaves_every_image_as_it_was(tmp_path, device):
    """The whole-band demo's sky (no interference) through `bf-epic run` with the detector off and on: it
    flags ~0.2% of blocks (its false alarms), so each 0.64-ms image made with it is the unflagged image
    less the few stand-blocks it dropped: within 5% of the sky's peak, the median within 0.5%. (On a GPU the flagger handed the imager its rescaling factors as device arrays
    from its own CUDA stream; the imager read some before they were written and divided images by up to
    1,000.)"""
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_wholeband.yaml"
    # on the CPU half a second of 32 channels: ~100 false-alarm flags (far 1e-3), enough to test the rescaling
    small = ["source.channels.count=256", "imager.grid.size=16", "imager.precision=fp32", "source.duration_s=1.0"] \
        if device == "gpu" else ["source.channels.count=32", "imager.grid.size=16", "imager.precision=fp32",
                                 "source.duration_s=0.5"]
    images = {}
    for on in ("off", "on"):
        d = tmp_path / on
        cfg = load_config(yaml, small + [f"device={device}", "imager.search=null",
                                         "output.fits=false", "output.png=false", "output.integrate=null", "watch=null",
                                         f"flagging.enabled={on}", f"output.dir={d}",
                                         "output.cube={dtype: float32, average_channels: true}"])
        summary = run(cfg, show_progress=False)
        images[on] = np.asarray(read_image_cube(next(d.glob("*_cube_*.h5")))["images"], np.float64)
    assert 0 < summary["flagging"]["fraction_flagged"] < 0.01
    off, on = images["off"], images["on"]
    err = np.nanmax(np.abs(on - off), axis=tuple(range(1, off.ndim))) / np.nanmax(off)
    print(f"{device}: worst image off by {err.max():.2e} of the peak")
    assert off.shape == on.shape and err.max() < 0.05 and np.median(err) < 0.005
