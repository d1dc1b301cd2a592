"""Transient search: injected bursts found where, when and as bright as they were put; noise-only
crossings as many as the Gaussian tail predicts; resets at gaps; dispersed bursts in the simulator."""
import time
from types import SimpleNamespace

import numpy as np
import pytest

from bf_epic_blocks import conventions, imaging
from bf_epic_blocks.blocks import ArraySourceBlock, DFTImagerBlock, TransientSearchBlock, bfp, efield_header
from bf_epic_blocks.blocks import headers
from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.conventions import FS_HZ
from bf_epic_blocks.search import Crossings, SearchSettings, TransientSearch, dm_delays, expected_false_rate, refine_peak
from bf_epic_blocks.io.candidates import CandidateWriter, read_candidates
from bf_epic_blocks.sky import simulate_efield
from bf_epic_blocks.sky.catalogue import icrs_to_lm

LWASV = {"lat_deg": 34.3484, "lon_deg": -106.8858, "elev_m": 1477.0}
TIME_TAG = int(1717236000 * FS_HZ)      # 2024-06-01 10:00 UTC
DT = 40e-6                              # one sample at 25 kHz channels


def image_header(grid, freq, dt_img, time_tag=TIME_TAG, products=("I",), name="img"):
    """An image sequence header as DFTImagerBlock writes it, at LWA-SV (:func:`headers.image_header`)."""
    return headers.image_header(name, time_tag, freq, dt_img, grid, {"name": "lwasv", **LWASV}, products)


def to_np(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


# ------------------------------------------------------------------------------ dispersion
def test_dispersion_delay_and_simulated_burst_arrival():
    # 4.149 ms * DM * (f^-2 - f_ref^-2), f in GHz: DM 2 between 74.0 and 74.375 MHz
    d = conventions.dispersion_delay_s(2.0, 74.0e6, 74.375e6)
    assert d == pytest.approx(4.149e-3 * 2.0 * (0.074 ** -2 - 0.074375 ** -2), rel=1e-12)
    assert 0.015 < d < 0.016                              # ~7.6 ms per unit DM here
    # the simulator: a burst, no noise, no steady sky; power per channel vs time
    freq = 74e6 + 25e3 * np.arange(16)
    xyz = np.array([[0.0, 0.0, 0.0], [5.0, 3.0, 0.1]])
    start, dur, dm = 3e-3, 1.2e-3, 1.5
    x = simulate_efield(xyz, freq, 1000, sources=[], noise_power=0.0, seed=1,
                        transients=[{"l": 0.1, "m": 0.2, "start_s": start, "duration_s": dur, "flux_jy": 4.0, "dm": dm}],
                        t0_s=1e-3)
    on = np.abs(x[:, :, 0, 0]) > 0                                    # (ntime, nchan)
    t = 1e-3 + DT * np.arange(1000)
    for c, f in enumerate(freq):
        delay = 4.149e-3 * dm * ((f / 1e9) ** -2 - (freq.max() / 1e9) ** -2)
        expect = (t >= start + delay) & (t < start + delay + dur)
        np.testing.assert_array_equal(on[:, c], expect)
    assert on[:, 0].argmax() > on[:, -1].argmax()                      # lower frequency: later
    # power: flux/2 per pol, on average
    p = np.mean(np.abs(x[np.broadcast_to(on[:, :, None, None], x.shape)]) ** 2)
    assert p == pytest.approx(2.0, rel=0.1)


# ------------------------------------------------------------------------------ the math alone
def _inject(x, pix, first_image, nimg, amp, delays):
    for c, d in enumerate(delays):
        x[first_image + d:first_image + d + nimg, c, pix] += amp


@pytest.mark.parametrize("dedisperse", ["tree", "shifts"])
def test_memory_bytes_is_what_the_search_allocates(dedisperse):
    """TransientSearch.memory_bytes (what `bf-epic plan` prints) against the arrays a search really
    holds after pushes (NumPy nbytes), and its working part against the largest push's peak; sizing
    without allocating (allocate=False) gives the same numbers."""
    import tracemalloc
    rng = np.random.default_rng(1)
    f = 74e6 + 25e3 * np.arange(80)
    kw = dict(window=40, dms=[0.3], widths=[1, 4], dedisperse=dedisperse, max_batch=32, hold=10)
    s = TransientSearch(f, 16 * DT, 50, **kw)
    x = rng.normal(5, 1, (96, 80, 50)).astype(np.float32)
    s.push(x[:64])
    tracemalloc.start()
    s.push(x[64:])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    mem = s.memory_bytes()
    held = s._hist.nbytes + s._s1.nbytes + s._s2.nbytes + s._ref.nbytes
    held += s._tree.ring.nbytes if dedisperse == "tree" else s._chan.nbytes
    assert sum(v for k, v in mem.items() if k != "working") == held
    assert 0.5 * peak <= mem["working"] <= 3 * peak
    assert TransientSearch(f, 16 * DT, 50, allocate=False, **kw).memory_bytes() == mem


def test_a_flash_over_a_few_pixels_is_one_sky_wide_crossing(xp):
    """Fewer pixels than max_pixels (a pixel list, a tracked source or a small grid) and a flash over
    all of them: one sky-wide crossing per trial image at the brightest pixel (the old code raised
    'assignment destination is read-only' writing that peak into a broadcast index array)."""
    rng = np.random.default_rng(3)
    freq = 74e6 + 25e3 * np.arange(4)
    s = TransientSearch(freq, 16 * DT, 12, 60, widths=[1], threshold=6.0, xp=xp)
    assert s.max_pixels >= 12
    x = rng.normal(5.0, 1.0, (200, 4, 12)).astype(np.float32)
    x[150] += 20.0
    x[150, :, 7] += 20.0                                  # the brightest pixel of the flash
    c = Crossings.concat([s.push(xp.asarray(x[a:a + 50])) for a in range(0, 200, 50)])
    sky = c.skywide.astype(bool)
    assert sky.sum() == 1 and c.end_image[sky][0] == 150 and c.pixel[sky][0] == 7
    assert np.all(c.end_image[~sky] != 150)


def test_search_finds_dispersed_burst_at_expected_snr(xp):
    rng = np.random.default_rng(11)
    freq = 74e6 + 25e3 * np.arange(16)
    dt_img, W, npix, nimg = 16 * DT, 150, 300, 600
    dms = [0.0, 0.5, 1.0, 1.5, 2.0]
    s = TransientSearch(freq, dt_img, npix, W, dms=dms, widths=[1, 2, 4, 8], threshold=6.0, xp=xp)
    sigma = 2.0
    x = rng.normal(50.0, sigma, (nimg, 16, npix)).astype(np.float32)
    amp, width, e0, pix = 2.5, 4, 400, 77
    _inject(x, pix, e0, width, amp, s.delays[dms.index(1.0)])
    found = Crossings.concat([s.push(xp.asarray(x[a:a + 50])) for a in range(0, nimg, 50)])
    k = int(np.argmax(found.snr))
    assert found.pixel[k] == pix and found.image[k] == e0
    assert dms[found.series[k]] == 1.0 and s.widths[found.width_index[k]] == width
    expect = amp * np.sqrt(width) / (sigma / np.sqrt(16))    # mean excess / sigma of a w-image, 16-channel mean
    print(f"pure search S/N {found.snr[k]:.2f}, expected {expect:.2f}")
    assert found.snr[k] == pytest.approx(expect, rel=0.2)


def _dispersed_burst(seed, nchan, npix, chan_hz, nimg, dm, pix, e0, amp):
    """Noise images (mean 10, sigma 1) over ``nchan`` channels of ``chan_hz`` from 74 MHz, one per 16
    samples, with a width-2 burst of ``amp`` at DM ``dm`` arriving at the band top at image ``e0``:
    (f, dt, x (nimg, nchan, npix))."""
    from bf_epic_blocks.conventions import dispersion_delay_s
    rng = np.random.default_rng(seed)
    dt = 16 * DT
    f = 74e6 + chan_hz * np.arange(nchan)
    x = rng.normal(10, 1, (nimg, nchan, npix)).astype(np.float32)
    _inject(x, pix, e0, 2, amp, np.rint(dispersion_delay_s(dm, f, f.max()) / dt).astype(int))
    return f, dt, x


@pytest.mark.slow
def test_the_tree_search_finds_a_burst_at_its_dm_across_a_wide_band(xp):
    """96 channels over 19 MHz from 74 MHz (a band the shifted sums would need ~1,300 trials for): the
    tree searches every sweep, and a width-2 burst at DM 0.9 is found at its pixel, its arrival at
    the band top and its sweep (+-1: the tree's channels sit within 1-2 images of the curve)."""
    from bf_epic_blocks.conventions import dispersion_delay_s
    nchan, npix, dm, pix, e0 = 96, 50, 0.9, 17, 2000
    f, dt, x = _dispersed_burst(1, nchan, npix, 200e3, 3000, dm, pix, e0, 3.0)
    s = TransientSearch(f, dt, npix, 300, dms=[3.0], widths=(1, 2, 4), threshold=7, dedisperse="auto",
                        max_batch=64, xp=xp)
    per_dm = dispersion_delay_s(1.0, f.min(), f.max()) / dt              # images of sweep per unit DM
    assert s.dedisperse == "tree" and s.nser == round(3.0 * per_dm) + 1 == 1304
    assert s.dms[1] == pytest.approx(1 / per_dm)
    found = Crossings.concat([s.push(xp.asarray(x[a:a + 64])) for a in range(0, 3000, 64)])
    k = int(np.argmax(found.snr))
    assert found.pixel[k] == pix and found.image[k] == e0
    assert abs(found.series[k] - round(dm * per_dm)) <= 1
    assert found.snr[k] > 0.8 * 3.0 * np.sqrt(2) * np.sqrt(nchan)     # most of the exact sums' S/N


def test_a_float16_tree_finds_the_burst_the_float32_tree_finds_at_its_s_n(xp):
    """The tree storing float16 (the whole band's setting): the same brightest candidate -- pixel, arrival,
    sweep, width -- as float32 storage, its S/N within 1%, and the window statistics within 1% of the
    noise (float16 rounds the fluctuations about each channel's first image, not the sums)."""
    npix, pix, e0 = 20, 7, 1300
    f, dt, x = _dispersed_burst(11, 64, npix, 300e3, 1600, 0.6, pix, e0, 2.5)
    best, stats = [], []
    for prec in ("fp32", "fp16"):
        s = TransientSearch(f, dt, npix, 200, dms=[1.0], widths=(1, 2, 4), threshold=7, dedisperse="tree",
                            max_batch=64, xp=xp, tree_precision=prec)
        found = Crossings.concat([s.push(xp.asarray(x[a:a + 64])) for a in range(0, 1600, 64)])
        k = int(np.argmax(found.snr))
        best.append((found.pixel[k], found.image[k], found.series[k], found.width_index[k], found.snr[k]))
        stats.append([to_np(a) for a in s.statistics()])
    (p32, i32, s32, w32, z32), (p16, i16, s16, w16, z16) = best
    assert (p16, i16, s16, w16) == (p32, i32, s32, w32) and p32 == pix and abs(i32 - e0) <= 1
    assert z16 == pytest.approx(z32, rel=0.01) and z32 > 20
    (m32, sg32), (m16, sg16) = stats
    assert np.abs(m16 - m32).max() < 0.01 * sg32.mean() and np.abs(sg16 / sg32 - 1).max() < 0.01


@pytest.mark.parametrize("dedisperse,prec", [("tree", "fp16"), ("tree", "fp32"), ("shifts", "fp32")])
def test_the_search_reads_pixels_out_of_an_imager_s_cells(xp, dedisperse, prec):
    """push(images, index): the images as an imager's grid, NaN in the cells no pixel has, pixel p in
    cell index[p] -- the same crossings, S/N and window statistics as the gathered pixels (the float16
    tree on a GPU reads the cells itself, the rest gather them)."""
    npix, pix, e0 = 20, 7, 1300
    f, dt, x = _dispersed_burst(12, 64, npix, 300e3, 1600, 0.6, pix, e0, 2.5)
    rng = np.random.default_rng(13)
    index = np.sort(rng.choice(32, npix, replace=False)).astype(np.int32)
    grid = np.full(x.shape[:2] + (32,), np.nan, np.float32)
    grid[:, :, index] = x
    got = []
    for imgs, idx in ((x, None), (grid, xp.asarray(index))):
        s = TransientSearch(f, dt, npix, 200, dms=[1.0] if dedisperse == "tree" else [0.3, 0.6], widths=(1, 2, 4),
                            threshold=7, dedisperse=dedisperse, max_batch=64, xp=xp, tree_precision=prec)
        found = Crossings.concat([s.push(xp.asarray(imgs[a:a + 64]), idx) for a in range(0, 1600, 64)])
        got.append((found, [to_np(a) for a in s.statistics()]))
    (a, sa), (b, sb) = got
    assert len(a) == len(b) > 0 and np.array_equal(a.snr, b.snr) and np.array_equal(a.pixel, b.pixel)
    assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(sa, sb))


def test_many_series_are_searched_in_chunks_with_the_same_result(monkeypatch):
    """The statistics of many trials run a chunk of series at a time (bounded temporaries): the same
    crossings, S/N and state as all at once."""
    rng = np.random.default_rng(2)
    f = 74e6 + 25e3 * np.arange(8)
    x = rng.normal(5, 1, (400, 8, 30)).astype(np.float32)
    _inject(x, 3, 300, 2, 2.5, np.zeros(8, int))
    runs = []
    for chunk in (TransientSearch.CHUNK_BYTES, 64 * 30 * 8 * 2):       # all at once; two series per chunk
        monkeypatch.setattr(TransientSearch, "CHUNK_BYTES", chunk)
        s = TransientSearch(f, 16 * DT, 30, 50, dms=[0, 0.2, 0.4, 0.6, 0.8], threshold=4, max_batch=64)
        c = Crossings.concat([s.push(x[a:a + 64]) for a in range(0, 400, 64)])
        order = np.lexsort((c.pixel, c.width_index, c.series, c.end_image))
        runs.append((c.take(order), s.statistics()))
    (a, sa), (b, sb) = runs
    assert len(a) > 0 and len(a) == len(b)
    for k in Crossings.FIELDS:
        assert np.allclose(getattr(a, k), getattr(b, k), rtol=1e-12), k
    assert np.allclose(sa[1], sb[1], rtol=1e-12)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("dedisperse,widths,one_series_per_chunk", [("shifts", (1, 2, 4, 8), False),
                                                                    ("shifts", (1, 2, 4, 8), True),
                                                                    ("tree", (1, 3, 16), False),
                                                                    ("tree-fp16", (1, 2, 4, 8), False)])
def test_the_gpu_statistics_kernel_equals_the_array_code(monkeypatch, dedisperse, widths, one_series_per_chunk):
    """On the GPU the statistics run in one kernel: the same crossings (S/N to float32), the same
    window statistics and history as the array code, over pushes that straddle the window's filling,
    a bright flash (sky-wide rows, the brightest-pixels cap) and a burst. A chunk of trials is run a
    second time, from its saved window sums, only where it has a crossing: with one series per chunk
    some chunks of a push have crossings (the burst's DM) and some have none."""
    import cupy as cp
    rng = np.random.default_rng(4)
    f = 74e6 + 100e3 * np.arange(24)
    x = rng.normal(5, 1, (700, 24, 300)).astype(np.float32)
    _inject(x, 17, 500, 2, 2.0, np.zeros(24, int))
    x[600:602] += 30.0
    runs = []
    if one_series_per_chunk:
        monkeypatch.setattr(TransientSearch, "CHUNK_BYTES", 1)
    for fused in (True, False):
        monkeypatch.setattr(TransientSearch, "FUSED_STATS", fused)
        s = TransientSearch(f, 16 * DT, 300, 60, dms=[0.0, 0.5, 1.0] if dedisperse == "shifts" else [1.0],
                            widths=widths, threshold=5, dedisperse=dedisperse.split("-")[0], max_batch=64, xp=cp,
                            tree_precision="fp16" if dedisperse.endswith("fp16") else "fp32")
        c = Crossings.concat([s.push(cp.asarray(x[a:a + b])) for a, b in ((0, 37), (37, 100), (137, 400), (537, 163))])
        order = np.lexsort((c.pixel, c.width_index, c.series, c.end_image))
        mean, sig = s.statistics()
        runs.append((c.take(order), mean.get(), sig.get(), s._hist.get()))
    (a, ma, sa, ha), (b, mb, sb, hb) = runs
    assert len(a) > 10 and len(a) == len(b)
    for k in Crossings.FIELDS:
        tol = dict(rtol=2e-6) if k in ("snr", "frac") else dict(rtol=0, atol=0)
        assert np.allclose(getattr(a, k), getattr(b, k), **tol), k
    assert a.skywide.any()
    assert np.array_equal(ha, hb) and np.allclose(ma, mb, rtol=1e-12) and np.allclose(sa, sb, rtol=1e-7)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
def test_the_gpu_float16_tree_hands_the_statistics_its_rows():
    """On the GPU the float16 tree's rows go to the statistics kernel where the tree left them (no float32
    copy): the rows it hands over are, made float32, the tree's own float32 output bit for bit (the
    equality of the statistics themselves: test_the_gpu_statistics_kernel_equals_the_array_code)."""
    import cupy as cp
    from bf_epic_blocks.search import HalfRows
    rng = np.random.default_rng(9)
    f = 74e6 + 100e3 * np.arange(24)
    x = cp.asarray(rng.normal(5, 1, (192, 24, 31)).astype(np.float32))
    got = []
    for fused in (True, False):
        s = TransientSearch(f, 16 * DT, 31, 60, dms=[1.0], widths=(1, 2, 4, 8), threshold=5, dedisperse="tree",
                            max_batch=64, xp=cp, tree_precision="fp16")
        s.FUSED_STATS = fused
        v = []
        for a in (0, 64, 128):
            v.append(s._dedisperse(x[a:a + 64]))
            s.nimages += 64                     # (what push counts: the values before the band's sweep are dropped)
        assert all(isinstance(u, HalfRows) == fused for u in v)
        got.append([(u.array() if fused else u).get() for u in v])
    assert all(np.array_equal(a, b) for a, b in zip(*got))
    assert 0 < got[0][1].shape[1] < 64 and got[0][2].shape[1] == 64        # from a time inside the push, then all


# ------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def array24():
    rng = np.random.default_rng(5)
    return np.c_[rng.uniform(-30, 30, (24, 2)), rng.normal(0, 0.3, 24)]


def _expected_snr(freq, dt_img, acc, burst, dm_trial, width, nant, noise_power):
    """Peak S/N from the data model alone: the burst adds flux x (fraction of the image's samples it
    is on) to the pixel's I in each channel; the noise of an image of T samples is the radiometer
    sigma of |F|^2 (a complex Gaussian beam of power P = noise_power / nant per pol):
    var(I) = 2 P^2 / T per channel, /nchan after the channel mean."""
    nchan = len(freq)
    fmax = freq.max()
    delay_true = 4.149e-3 * burst["dm"] * ((freq / 1e9) ** -2 - (fmax / 1e9) ** -2)
    shift = np.rint(4.149e-3 * dm_trial * ((freq / 1e9) ** -2 - (fmax / 1e9) ** -2) / dt_img).astype(int)
    nimg = int(1 + (burst["start_s"] + delay_true.max() + burst["duration_s"]) / dt_img) + 16
    excess = np.zeros((nchan, nimg))
    ts = DT * np.arange(nimg * acc)                            # sample start times
    for c in range(nchan):
        on = (ts >= burst["start_s"] + delay_true[c]) & (ts < burst["start_s"] + delay_true[c] + burst["duration_s"])
        excess[c] = burst["flux_jy"] * on.reshape(nimg, acc).mean(axis=1)
    dd = np.zeros(nimg)
    for c in range(nchan):                                     # align on the band top, as the search does
        dd[:nimg - shift[c]] += excess[c, shift[c]:] / nchan
    box = np.convolve(dd, np.ones(width), "valid") / width
    P = noise_power / nant
    sigma = np.sqrt(2 * P ** 2 / acc / nchan)
    return box.max() * np.sqrt(width) / sigma


@pytest.mark.parametrize("dm_true", [0.0, 0.9])
def test_burst_found_on_the_sky_through_the_imager(array24, tmp_path, dm_true):
    xyz, acc, nchan = array24, 16, 8
    freq = 74e6 + 25e3 * np.arange(nchan)
    grid = imaging.lm_grid(16)
    gx, gy = 10, 5                                              # a pixel East and South of the zenith
    l0, m0 = (gx - 8) * grid.cell, (gy - 8) * grid.cell
    dt_img = acc * DT
    burst = {"l": l0, "m": m0, "start_s": 0.30 + 0.3 * dt_img, "duration_s": 4 * dt_img, "flux_jy": 0.1, "dm": dm_true}
    T = int(0.45 / DT) // acc * acc
    X = simulate_efield(xyz, freq, T, sources=[], noise_power=1.0, seed=3, transients=[burst]).astype(np.complex64)
    st = {"name": "lwasv", "xyz_m": xyz, **LWASV}
    hdr = efield_header("burst", TIME_TAG, freq, DT, st, dtype="cf32")
    dms = [0.0, 0.5, 1.0, 1.5, 2.0]
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=1024)
        img = DFTImagerBlock(src, grid, acc, products=["I"], pattern=False)
        srch = TransientSearchBlock(img, SearchSettings(threshold=6.0, window_s=0.1, dms=dms),
                                    writer=CandidateWriter(tmp_path))
        p.run()
    tab = srch.candidates
    assert len(tab) >= 1
    best = tab[int(np.argmax(tab["snr"]))]
    assert abs(best["grid_x"] - gx) <= 1 and abs(best["grid_y"] - gy) <= 1
    e_true = burst["start_s"] / dt_img
    assert abs(best["image"] - e_true) <= 1.0
    assert best["dm_trial"] == dms[int(np.argmin(np.abs(np.asarray(dms) - dm_true)))]
    assert abs(best["dm"] - dm_true) <= 0.5                      # between trials: within one trial step
    expect = _expected_snr(freq, dt_img, acc, burst, best["dm"], int(best["width"]), len(xyz), 1.0)
    print(f"DM {dm_true}: S/N {best['snr']:.2f} expected {expect:.2f}, image {best['image']} vs {e_true:.2f}")
    assert best["snr"] == pytest.approx(expect, rel=0.2)
    # time and sky position in the table agree with where the burst was put
    t_true = TIME_TAG / FS_HZ + burst["start_s"]
    assert abs(best["time_utc"].unix - t_true) <= 1.5 * dt_img
    lm, _ = icrs_to_lm(best["ra_deg"], best["dec_deg"], best["time_utc"], srch.loc)
    assert np.hypot(lm[0, 0] - best["l"], lm[0, 1] - best["m"]) < 1e-3
    # files: the table reads back, the PNG exists
    back = read_candidates(tmp_path / "transients_candidates.ecsv")
    assert len(back) == len(tab) and back["lightcurve"].shape[1] == 65
    assert (tmp_path / "transients_candidates.png").stat().st_size > 10_000


# ------------------------------------------------------------------------------ noise statistics
def test_noise_only_crossings_match_the_gaussian_tail():
    """Single width, DM 0: trials are independent but for the shared window statistics, so the count
    is Poisson about the exact expectation P(t_{W-1} > thr / sqrt(1 + 1/W)) per trial."""
    rng = np.random.default_rng(2024)
    W, npix, nimg, thr = 200, 2000, 700, 3.5
    s = TransientSearch([74e6], 16 * DT, npix, W, dms=[0.0], widths=[1], threshold=thr)
    n = 0
    for a in range(0, nimg, 100):
        n += len(s.push(rng.normal(10.0, 1.0, (100, 1, npix)).astype(np.float32)))
    trials = (nimg - (W + 1 - 1)) * npix
    expect = trials * expected_false_rate(thr, W, [1])[0]
    print(f"noise-only crossings {n}, expected {expect:.1f}")
    assert abs(n - expect) < 4 * np.sqrt(expect), (n, expect)
    # and not the Gaussian tail alone without the window's estimation error (a test that can fail)
    from scipy.stats import norm
    assert expect > 1.05 * trials * norm.sf(thr)


def test_a_sky_filling_flash_is_one_crossing_per_trial_not_one_per_pixel(xp):
    """A flash over the whole image (every pixel far over the threshold) gives one sky-wide crossing
    per trial image (series, value, width) at its peak pixel, whatever the number of pixels; an event
    over fewer pixels than sky_fraction keeps at most max_pixels (its brightest) per trial image, and
    a lone burst keeps its own crossing. Bounded crossings mean bounded memory and time downstream
    (a 3-MJy flash once made 24 GB of crossings)."""
    rng = np.random.default_rng(7)
    npix, W = 4000, 20
    s = TransientSearch([74e6], 16 * DT, npix, W, dms=[0.0], widths=[1, 2], threshold=8.0, xp=xp,
                        max_pixels=16, sky_fraction=0.1)
    noise = lambda n: xp.asarray(rng.normal(10.0, 1.0, (n, 1, npix)).astype(np.float32))  # noqa: E731
    assert len(s.push(noise(W + 4))) == 0
    flash = noise(1)
    flash += 1e4
    flash[0, 0, 1234] += 5e4                                    # its peak
    cr = s.push(flash)
    assert len(cr) == 2 and set(cr.width_index) == {0, 1}       # one per width, not 2 x 4000
    assert np.all(cr.skywide == 1) and np.all(cr.pixel == 1234) and np.all(cr.frac == 1.0)
    s.reset(0)
    assert len(s.push(noise(W + 4))) == 0
    part = noise(1)
    part[0, 0, :300] += 1e3                                     # 7.5% of the sky: not sky-wide
    part[0, 0, 7] += 1e4
    cr = s.push(part)
    assert 0 < len(cr) <= 2 * 16 and np.all(cr.skywide == 0)
    assert 7 in cr.pixel and np.all(cr.pixel < 300) and np.allclose(cr.frac, 300 / npix)
    s.reset(0)
    s.push(noise(W + 4))
    one = noise(1)
    one[0, 0, 99] += 100.0
    cr = s.push(one)
    assert list(cr.pixel[cr.width_index == 0]) == [99] and np.all(cr.skywide == 0)


def test_noise_only_block_count_all_widths_and_dms():
    """Through the block, 4 widths x 3 DMs: the count of crossings matches the sum of the tails over
    the trials the block reports (loose bound: trials of one event are correlated)."""
    rng = np.random.default_rng(7)
    grid = imaging.lm_grid(24)
    freq = 74e6 + 25e3 * np.arange(8)
    dt_img, nimg = 16 * DT, 500
    x = rng.normal(5.0, 0.5, (nimg, 8, 1, 24, 24)).astype(np.float32)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, dt_img), gulp_nframe=64)
        srch = TransientSearchBlock(src, SearchSettings(threshold=3.5, window_s=150 * dt_img, dms=[0.0, 1.0, 2.0]))
        p.run()
    st = srch.search_stats
    rate = expected_false_rate(3.5, srch.search.window, srch.widths)
    expect = float(np.dot(st["trials_per_width"], rate))
    assert st["images_searched"] == nimg - (srch.search.window + 8 - 1) - srch.search.shift
    print(f"block crossings {st['crossings']}, expected {expect:.1f}, candidates {len(srch.candidates)}")
    assert abs(st["crossings"] - expect) < 5 * np.sqrt(12 * expect), (st["crossings"], expect)
    assert len(srch.candidates) <= st["crossings"]


def test_a_flash_is_one_sky_wide_row_and_a_burst_elsewhere_stays_a_point(tmp_path):
    """Through the block, with DM trials: a flash over the whole sky (DM 0, seen smeared by the other
    trials) is ONE row of kind 'sky-wide' with its sky fraction; a point burst well after it is its own
    'point' row at its pixel; the table reads back with both kinds."""
    rng = np.random.default_rng(5)
    grid = imaging.lm_grid(24)
    freq = 74e6 + 25e3 * np.arange(8)
    dt_img, nimg = 16 * DT, 700
    x = rng.normal(5.0, 0.5, (nimg, 8, 1, 24, 24)).astype(np.float32)
    x[400:402] += 500.0                                            # the flash: every pixel, every channel
    pix = divmod(int(np.flatnonzero(grid.mask)[40]), 24)          # (row = m index, column = l index)
    x[600, :, 0, pix[0], pix[1]] += 20.0                           # the burst: one pixel, S/N ~ 40
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, dt_img), gulp_nframe=64)
        srch = TransientSearchBlock(src, SearchSettings(threshold=8.0, window_s=150 * dt_img, dms=[0.0, 1.0, 2.0]),
                                    writer=CandidateWriter(tmp_path, png=False))
        p.run()
    t = read_candidates(tmp_path / "transients_candidates.ecsv")
    sky = t[t["kind"] == "sky-wide"]
    assert len(sky) == 1 and sky["image"][0] in (399, 400, 401) and sky["sky_fraction"][0] > 0.9
    pts = t[t["kind"] == "point"]
    assert len(pts) == 1 and pts["image"][0] == 600 and (pts["grid_y"][0], pts["grid_x"][0]) == pix
    assert srch.search_stats["sky_wide"] == 1


def test_dm_sidelobe_snr_counts_the_channel_images_two_sweeps_share():
    """Analytic cases: the burst's own trial gets its S/N back; a trial whose sweep never meets it, 0;
    two sweeps that cross get the channel-images they share (counted by brute force here)."""
    from bf_epic_blocks.search import dm_delays, dm_sidelobe_snr
    f = 74e6 + 25e3 * np.arange(256)
    dt = 16 * DT
    assert dm_sidelobe_snr(f, dt, (1000, 1.5, 8, 300.0), (1000, 1.5, 8), slack=0) == pytest.approx(300.0)
    assert dm_sidelobe_snr(f, dt, (1000, 1.5, 4, 300.0), (1000, 1.5, 8), slack=0) == pytest.approx(300.0 * 4 / np.sqrt(32))
    assert dm_sidelobe_snr(f, dt, (1000, 1.5, 8, 300.0), (1200, 1.5, 8)) == 0.0
    db, df = dm_delays([1.5, 2.0], f, dt)
    ef = 1000 - (df - db)[-1] + 3                           # the sweeps cross near the band's foot
    shared = sum(len(set(range(1000 + db[c], 1000 + db[c] + 8)) & set(range(ef + df[c], ef + df[c] + 8)))
                 for c in range(len(f)))
    assert shared > 0
    assert dm_sidelobe_snr(f, dt, (1000, 1.5, 8, 300.0), (ef, 2.0, 8), slack=0) == pytest.approx(300.0 * shared / (256 * 8))


@pytest.mark.slow
@pytest.mark.parametrize("factor,defer", [(2.0, False), (0.0, False), (2.0, True), (0.0, True)])
def test_a_bright_dispersed_burst_s_dm_sidelobes_fold_into_it(tmp_path, monkeypatch, factor, defer):
    """The tree search over a wide band sees a bright burst (S/N ~260) in trials of other DMs whose
    sweeps cross its own near the band's foot: S/N ~7.5-8 at DM ~2.0, 0.14 s before it (the whole-band
    run on the H100: S/N 9.4 at DM 2.38, 0.24 s before its S/N-370 burst). They fold into the burst's
    row (one row, nsidelobes counts them; the old code: three rows); sidelobe_factor 0 keeps them. The
    same with each gulp's statistics run at the next (what a GPU does): the crossings of a staged gulp
    still reach the clusters they belong to (no candidate is closed before they are in)."""
    monkeypatch.setattr(TransientSearchBlock, "DEFER_STATS", defer)
    rng = np.random.default_rng(2)
    nchan, nimg, width = 256, 3400, 6
    freq = 74e6 + 19.6e6 / nchan * np.arange(nchan)
    grid = imaging.lm_grid(6)
    N = grid.size
    valid = np.flatnonzero(grid.mask.ravel())
    x = rng.normal(0.0, 1.0, (nimg, nchan, 1, N * N)).astype(np.float32)
    d = dm_delays([1.5], freq, 16 * DT)[0]
    amp = 300.0 / np.sqrt(nchan * width)                  # band-mean S/N 300 over its 6 images
    for c in range(nchan):
        x[1500 + d[c]:1500 + d[c] + width, c, 0, valid[2]] += amp
    with bfp.Pipeline() as pl:
        src = ArraySourceBlock(x.reshape(nimg, nchan, 1, N, N), image_header(grid, freq, 16 * DT), gulp_nframe=64)
        srch = TransientSearchBlock(src, SearchSettings(threshold=7.5, window_s=0.2, dms=[2.2], dedisperse="tree",
                                                         widths=[1, 2, 4, 8], sidelobe_factor=factor),
                                    writer=CandidateWriter(tmp_path, png=False))
        pl.run()
    t = read_candidates(tmp_path / "transients_candidates.ecsv")
    t.sort("snr", reverse=True)
    assert t["pixel"][0] == 2 and abs(t["image"][0] - 1500) <= 2 and abs(t["dm"][0] - 1.5) < 0.01
    if factor == 0:
        assert len(t) >= 2 and np.all(t["nsidelobes"] == 0) and np.all(t["dm"][1:] > 1.8)
        return
    assert len(t) == 1, t["image", "pixel", "snr", "dm", "nsidelobes"]
    assert t["nsidelobes"][0] >= 1 and srch.search_stats["sidelobes_folded"] == t["nsidelobes"][0]


@pytest.mark.parametrize("factor", [2.0, 0.0])
def test_a_bright_burst_s_sidelobes_fold_into_it_and_a_second_burst_stays(tmp_path, factor):
    """Images of a bright burst (S/N ~200) drawn with the array's own beam (24 antennas in the
    header's station: sidelobes of 4-30% over a few per cent of the sky) and a second, unrelated burst at the same
    time: the sidelobes fold into the burst's row (nsidelobes counts them), the burst keeps its
    pixel, the second burst keeps its own row; sidelobe_factor 0 keeps every row (the old output)."""
    from bf_epic_blocks.search import beam_power
    rng = np.random.default_rng(11)
    grid = imaging.lm_grid(24)
    lm = grid.lm
    freq = 74e6 + 25e3 * np.arange(4)
    xyz = np.column_stack([rng.uniform(-40, 40, (64, 2)), np.zeros(64)])
    hdr = image_header(grid, freq, 16 * DT)
    hdr["station"].update(xyz_m=xyz.tolist(), flags=np.zeros((64, 2), bool).tolist())
    nimg, N = 500, grid.size
    x = rng.normal(5.0, 1.0, (nimg, 4, 1, N * N)).astype(np.float32)
    valid = np.flatnonzero(grid.mask.ravel())
    p, q = 150, 400                                       # indices into the imaged pixels
    beam = beam_power(xyz, freq, lm[p], lm)
    x[420, :, 0, valid] += (100.0 * beam)[:, None]        # one image: S/N ~200 at p, its sidelobes elsewhere
    assert 10 < np.sum(200.0 * beam > 8.0) < 0.1 * len(lm)   # sidelobes over the threshold, not sky-wide
    x[420, :, 0, valid[q]] += 60.0                        # an unrelated burst, far above p's sidelobe there
    with bfp.Pipeline() as pl:
        src = ArraySourceBlock(x.reshape(nimg, 4, 1, N, N), hdr, gulp_nframe=50)
        srch = TransientSearchBlock(src, SearchSettings(threshold=8.0, window_s=150 * 16 * DT, widths=[1],
                                                         sidelobe_factor=factor),
                                    writer=CandidateWriter(tmp_path, png=False))
        pl.run()
    t = read_candidates(tmp_path / "transients_candidates.ecsv")
    t.sort("snr", reverse=True)
    if factor == 0:
        assert len(t) > 10 and np.all(t["nsidelobes"] == 0)
        return
    assert len(t) <= 3, t["pixel", "snr", "nsidelobes"]
    assert t["pixel"][0] == p and t["nsidelobes"][0] > 10
    assert q in list(t["pixel"])


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.34, 0.41), (-0.5, 0.2)])
def test_locate_point_source_finds_a_source_between_pixels(offset):
    """An S/N image drawn from beam_power (float64, every channel) at a known position between pixels,
    plus unit noise and pixels of differing noise: the fitted position is within 0.05 cells of it, and
    the fitted S/N at every pixel is the drawn one within the noise."""
    from bf_epic_blocks.search import ArrayBeam, beam_power, locate_point_source
    rng = np.random.default_rng(7)
    xyz = np.column_stack([rng.uniform(-50, 50, (96, 2)), rng.normal(0, 0.5, 96)])
    grid = imaging.lm_grid(32)
    lm = grid.lm
    freq = 74e6 + 25e3 * np.arange(8)
    p = int(np.argmin(np.hypot(lm[:, 0] + 0.2, lm[:, 1] - 0.1)))
    true = lm[p] + np.array(offset) * grid.cell
    sigma = rng.uniform(0.5, 2.0, len(lm))
    beam = ArrayBeam([xyz, xyz[:90]], [1.0, 1.0], freq, lm)
    # two pols, one with 6 antennas flagged: the beam is their mean
    want = 0.5 * (beam_power(xyz, freq, true, lm) + beam_power(xyz[:90], freq, true, lm))
    every = ArrayBeam([xyz, xyz[:90]], [1.0, 1.0], freq, lm, max_channels=8)
    np.testing.assert_allclose(every.at(true[None])[0], want, atol=2e-6)
    np.testing.assert_allclose(beam.at(true[None])[0], want, atol=1e-4)     # 4 channels stand for 8
    y = 500.0 * want / sigma + rng.normal(size=len(lm))
    fit, model, explained = locate_point_source(y, sigma, beam, lm[p], grid.cell)
    assert np.hypot(*(fit - true)) < 0.05 * grid.cell, (fit, true)
    assert np.max(np.abs(model - 500.0 * want / sigma)) < 1.0 and explained > 0.9


@pytest.mark.parametrize("tail", [False, True])
def test_a_burst_between_pixels_is_one_row_though_its_pixel_sees_a_tenth_of_it(tmp_path, tail):
    """A grid coarser than the beam (LWA-SV's 256 stands, a 32x32 all-sky grid: the beam is half a
    cell wide) sees a burst between pixels in its nearest pixel at a small fraction of its peak, and
    its sidelobes elsewhere at many times that fraction, so the beam from the pixel's centre explains
    none of them. The images are drawn from the array's beam at the true position; the search fits
    that position and folds the sidelobes: one row at the burst's pixel (the old code: one per
    sidelobe, 10 or more). With ``tail`` the burst's cluster goes on 20 images after its peak (the
    next pixel, linked by a longer time link) and gulps are short, so its sidelobes' clusters are complete gulps before its own: they
    wait for it (they were rows of their own)."""
    from bf_epic_blocks.search import beam_power
    from bf_epic_blocks.station.tables import load_station
    st = load_station("lwasv")
    xyz = np.asarray(st.xyz_m)[st.good.all(axis=1)]
    rng = np.random.default_rng(2)
    grid = imaging.lm_grid(32)
    lm = grid.lm
    freq = 74e6 + 25e3 * np.arange(4)
    hdr = image_header(grid, freq, 16 * DT)
    hdr["station"].update(xyz_m=xyz.tolist(), flags=np.zeros((len(xyz), 2), bool).tolist())
    nimg, N = 500, grid.size
    x = rng.normal(5.0, 1.0, (nimg, 4, 1, N * N)).astype(np.float32)
    valid = np.flatnonzero(grid.mask.ravel())
    p = int(np.argmin(np.hypot(lm[:, 0] - 0.25, lm[:, 1] + 0.25)))
    true = lm[p] + np.array([0.34, 0.41]) * grid.cell           # off the pixel as the demo's burst is
    beam = beam_power(xyz, freq, true, lm)
    assert beam[p] < 0.2 and np.sum(60.0 * beam / beam[p] > 8.0) > 10   # the pixel sees a fraction; sidelobes cross
    x[420, :, 0, valid] += (30.0 / beam[p] * beam)[:, None]     # S/N ~60 at p (noise 0.5 in the channel mean)
    if tail:                                                    # the next pixel East, S/N ~20, 20 images later
        e = int(np.argmin(np.hypot(lm[:, 0] - lm[p, 0] - grid.cell, lm[:, 1] - lm[p, 1])))
        x[440, :, 0, valid[e]] += 10.0
    with bfp.Pipeline() as pl:
        src = ArraySourceBlock(x.reshape(nimg, 4, 1, N, N), hdr, gulp_nframe=10 if tail else 50)
        srch = TransientSearchBlock(src, SearchSettings(threshold=6.0, window_s=150 * 16 * DT, widths=[1],
                                                         time_link=24 if tail else None),
                                    writer=CandidateWriter(tmp_path, png=False))
        pl.run()
    t = read_candidates(tmp_path / "transients_candidates.ecsv")
    assert len(t) == 1, t["pixel", "snr", "nsidelobes"]
    assert t["pixel"][0] == p and t["nsidelobes"][0] >= 10 and t["snr"][0] == pytest.approx(60, rel=0.05)
    # the light curve is the search's own S/N, against the window the burst was found with
    assert t["lightcurve"][0][32] == pytest.approx(t["snr"][0], rel=1e-3)


@pytest.mark.slow
def test_a_bright_burst_in_the_demo_is_at_most_three_rows(tmp_path):
    """The issue's case, as a user runs it: pipelines/lwasv_sim_transient.yaml (LWA-SV, Cyg A, Cas A,
    4-bit voltages, a 32x32 grid) with a 2 kJy, 4-ms burst at DM 0.5, which lands between pixels:
    at most 3 rows within 50 ms of it (the old code: 11), the brightest within 1.5 cells of where it
    was put, the rest of its crossings folded into it."""
    from pathlib import Path
    from astropy.coordinates import SkyCoord
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_transient.yaml"
    cfg = load_config(yaml, [f"output.dir={tmp_path}", "source.duration_s=0.36", "output.cube=null",
                             "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, duration_s: 0.004, "
                             "flux_jy: 2000.0, dm: 0.5}]"])
    run(cfg, show_progress=False)
    t = read_candidates(tmp_path / "lwasv_sim_transient_candidates.ecsv")
    near = t[np.abs(t["image"] * 16 * DT - 0.3) < 0.05]
    print(near["pixel", "grid_x", "grid_y", "snr", "dm", "width", "nsidelobes"])
    assert 1 <= len(near) <= 3
    best = near[int(np.argmax(near["snr"]))]
    assert best["snr"] > 40 and best["nsidelobes"] >= 5
    sep = SkyCoord(best["ra_deg"], best["dec_deg"], unit="deg").separation(SkyCoord(310.0, 20.0, unit="deg")).deg
    assert sep < 1.5 * np.degrees(2 / 32)                       # within 1.5 cells of 3.6 degrees


# ------------------------------------------------------------------------------ resets
def _fake(data):
    return SimpleNamespace(data=data, space="system")


def test_skipped_gulp_and_new_sequence_reset_the_window(tmp_path):
    """A level jump hidden in a gap would be a huge 'burst' without the reset. After the gap the search
    waits for a full window, and image indices still count the lost images."""
    rng = np.random.default_rng(3)
    grid = imaging.lm_grid(12)
    freq = 74e6 + 25e3 * np.arange(4)
    dt_img = 16 * DT
    hdr = image_header(grid, freq, dt_img)
    N, W = grid.size, 60
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((1, 4, 1, N, N), np.float32), hdr, gulp_nframe=8)
        blk = TransientSearchBlock(src, SearchSettings(threshold=6.0, window_s=W * dt_img, dms=[0.0]))

    def noise(n, level):
        return rng.normal(level, 1.0, (n, 4, 1, N, N)).astype(np.float32)

    blk.on_sequence(SimpleNamespace(header=hdr))
    for _ in range(10):
        blk.on_data(_fake(noise(20, 10.0)))                 # images 0..199
    blk.on_skip([slice(200, 232)], [])                      # 32 images lost
    after = noise(200, 40.0)                                # the level jumped during the gap
    k = int(np.flatnonzero(grid.mask)[40])
    early, late = 232 + 20, 232 + 150                       # inside / after the window's refill
    after[early - 232, :, 0].reshape(4, -1)[:, k] += 10.0
    after[late - 232, :, 0].reshape(4, -1)[:, k] += 10.0
    for a in range(0, 200, 25):
        blk.on_data(_fake(after[a:a + 25]))
    blk.on_sequence_end(None)
    tab = blk.candidates
    assert blk.search_stats["resets"] == 1 and blk.search_stats["images_lost"] == 32
    assert list(tab["image"]) == [late]                      # no jump candidate, no early one
    # a new sequence at yet another level: reset again, nothing found in pure noise
    hdr2 = dict(hdr, name="img2")
    blk.on_sequence(SimpleNamespace(header=hdr2))
    for _ in range(5):
        blk.on_data(_fake(noise(40, 90.0)))
    blk.on_sequence_end(None)
    assert len(blk.candidates) == 1


def test_a_search_out_of_memory_loses_that_gulp_s_search_not_the_run(monkeypatch):
    """A push that finds too little memory (on a GPU, CuPy's OutOfMemoryError: a MemoryError; the station's
    search once ended its run so) is counted and logged, its images left unsearched and the window begun
    again after them; a burst after the refill is still found, at its image."""
    from bf_epic_blocks.search import TransientSearch
    rng = np.random.default_rng(4)
    grid = imaging.lm_grid(12)
    freq = 74e6 + 25e3 * np.arange(4)
    hdr = image_header(grid, freq, 16 * DT)
    N, W = grid.size, 40
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((1, 4, 1, N, N), np.float32), hdr, gulp_nframe=8)
        blk = TransientSearchBlock(src, SearchSettings(threshold=6.0, window_s=W * 16 * DT, dms=[0.0]))
    real, calls = TransientSearch.push, []

    def push(self, *args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise MemoryError("Out of memory allocating 534,952,960 bytes")
        return real(self, *args, **kw)
    monkeypatch.setattr(TransientSearch, "push", push)
    imgs = rng.normal(10.0, 1.0, (300, 4, 1, N, N)).astype(np.float32)
    k = int(np.flatnonzero(grid.mask)[40])
    imgs[250, :, 0].reshape(4, -1)[:, k] += 10.0
    blk.on_sequence(SimpleNamespace(header=hdr))
    for a in range(0, 300, 25):
        blk.on_data(_fake(imgs[a:a + 25]))
    blk.on_sequence_end(None)
    st = blk.search_stats
    assert st["out_of_memory"] == 1 and st["images_lost"] == 25 and st["resets"] == 1 and st["images"] == 275
    assert list(blk.candidates["image"]) == [250]


def _peak_rise(fn):
    """Bytes by which the traced peak rose above what was held when ``fn`` started (NumPy's arrays are
    traced by tracemalloc)."""
    import tracemalloc
    tracemalloc.start()
    try:
        fn(start=True)
        held = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        fn(start=False)
        return tracemalloc.get_traced_memory()[1] - held
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("dedisperse", ["shifts", "tree"])
def test_a_reset_clears_the_history_in_place_and_searches_as_a_new_search(dedisperse):
    """A reset (each gain solution) zeroes the history where it is -- tens of GB for a whole band on a
    GPU, taken from the pool once -- and the search then finds what a new search given the same images
    finds (a burst after the reset: same crossings, same S/N)."""
    rng = np.random.default_rng(3)
    freq = 74e6 + 25e3 * np.arange(16)
    make = lambda: TransientSearch(freq, 16 * DT, 50, 40, dms=[0.0, 1.0], dedisperse=dedisperse,  # noqa: E731
                                   threshold=6.0)
    imgs = rng.normal(10.0, 1.0, (120, 16, 50)).astype(np.float32)
    imgs[90, :, 17] += 30.0                                     # a DM-0 flash at pixel 17
    old = make()
    old.push(rng.normal(10.0, 1.0, (70, 16, 50)).astype(np.float32) * 3)   # another past, then forgotten
    hist = old._hist
    old.reset(0)
    assert old._hist is hist and not hist.any()
    a, b = old.push(imgs), make().push(imgs)
    assert len(a) > 0 and 17 in a.pixel
    assert np.array_equal(a.pixel, b.pixel) and np.array_equal(a.image, b.image)
    assert np.allclose(a.snr, b.snr, rtol=1e-5)


@pytest.mark.parametrize("dedisperse", ["shifts", "tree"])
def test_a_reset_holds_the_history_once(dedisperse):
    """A reset (every new sequence, every gain solution) holds the search's arrays once: cleared in
    place, never made again beside the old ones (the history is tens of GB for a whole band on a GPU)."""
    freq = 74e6 + 25e3 * np.arange(64)
    box = {}

    def fn(start):
        if start:
            box["s"] = TransientSearch(freq, 16 * DT, 1024, 200, dms=[0.0, 1.0], dedisperse=dedisperse)
        else:
            box["s"].reset(17)
    rise = _peak_rise(fn)
    s = box["s"]
    hist = s._hist.nbytes + (s._tree.ring.nbytes if s._tree is not None else s._chan.nbytes)
    assert hist > 8e6 and s.next_image == 17
    assert rise < 0.25 * hist, (rise, hist)


def test_a_new_sequence_lets_the_last_search_go_first():
    """The block's search for a new sequence is made after the last sequence's is let go."""
    grid = imaging.lm_grid(64)
    freq = 74e6 + 25e3 * np.arange(8)
    hdr = image_header(grid, freq, 16 * DT)
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((1, 8, 1, 64, 64), np.float32), hdr, gulp_nframe=8)
        blk = TransientSearchBlock(src, SearchSettings(threshold=6.0, window_s=300 * 16 * DT, dms=[0.0, 1.0]))

    def fn(start):
        blk.on_sequence(SimpleNamespace(header=hdr if start else dict(hdr, name="img2")))
    rise = _peak_rise(fn)
    hist = blk.search._hist.nbytes
    assert hist > 8e6
    assert rise < 0.5 * hist, (rise, hist)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
def test_cpu_and_gpu_find_the_same_candidates():
    import cupy
    rng = np.random.default_rng(8)
    grid = imaging.lm_grid(32)
    freq = 74e6 + 25e3 * np.arange(16)
    dt_img, nimg = 16 * DT, 400
    x = rng.normal(5.0, 0.5, (nimg, 16, 1, 32, 32)).astype(np.float32)
    flat = x.reshape(nimg, 16, 1, -1)
    s = TransientSearch(freq, dt_img, 1, 100, dms=[0.0, 1.0])
    for j, c in enumerate(np.flatnonzero(grid.mask)[[5, 300, 700]]):
        for ch, d in enumerate(s.delays[1]):
            flat[250 + 30 * j + d:250 + 30 * j + d + 2, ch, 0, c] += 1.5
    out = []
    for space in ("system", "cuda"):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(x, image_header(grid, freq, dt_img), gulp_nframe=64, space=space)
            srch = TransientSearchBlock(src, SearchSettings(threshold=4.5, window_s=100 * dt_img, dms=[0.0, 0.5, 1.0]))
            p.run()
        out.append(srch)
    assert out[1].xp is cupy
    a, b = out[0].candidates, out[1].candidates
    assert len(a) >= 3 and len(a) == len(b)
    for col in ("image", "pixel", "dm", "width"):
        np.testing.assert_array_equal(a[col], b[col])
    np.testing.assert_allclose(a["snr"], b["snr"], rtol=1e-4)
    assert out[0].search_stats["crossings"] == out[1].search_stats["crossings"]


def test_a_flood_of_crossings_is_bounded_counted_and_the_brightest_kept(monkeypatch, caplog):
    """A bright source that steps (as a simulator's refreshed sky did) puts every trial of its pixels over
    the threshold for a whole window: the block clusters at most MAX_PENDING crossings (the brightest),
    counts the rest and says so once, and still reports the brightest event where it is."""
    monkeypatch.setattr(TransientSearchBlock, "MAX_PENDING", 200)
    rng = np.random.default_rng(6)
    grid = imaging.lm_grid(24)
    freq = 74e6 + 25e3 * np.arange(8)
    x = rng.normal(5.0, 0.5, (500, 8, 1, 24, 24)).astype(np.float32)
    flat = x.reshape(500, 8, 1, -1)
    pix = np.flatnonzero(grid.mask)
    flat[300:, :, 0, pix[:40]] += 3.0                   # a step on 40 pixels (under the sky-wide fraction)
    flat[420:422, :, 0, pix[200]] += 40.0               # and a brighter burst elsewhere
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, image_header(grid, freq, 16 * DT), gulp_nframe=64)
        srch = TransientSearchBlock(src, SearchSettings(threshold=6, window_s=100 * 16 * DT, dms=[0.0, 0.5]))
        p.run()
    st = srch.search_stats
    assert st["crossings_dropped"] > 0 and st["crossings"] > 200
    assert sum("crossings pending" in r.message for r in caplog.records) == 1
    best = srch.candidates[int(np.argmax(srch.candidates["snr"]))]
    assert best["pixel"] == 200 and best["image"] == 420          # the imaged pixels are numbered in order


# ------------------------------------------------------------------------------ the YAML pipeline
def test_transient_pipeline_yaml_end_to_end(tmp_path):
    """pipelines/lwasv_sim_transient.yaml, made small: the burst is the brightest candidate, on the sky
    where it was put; every image is in the HDF5 cube."""
    from pathlib import Path
    from astropy.coordinates import SkyCoord
    from bf_epic_blocks.io.cube import read_image_cube
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_transient.yaml"
    cfg = load_config(yaml, [f"output.dir={tmp_path}", "source.duration_s=0.2", "source.channels.count=8",
                             "imager.grid.size=16", "imager.search.window_s=0.06", "imager.search.dms=[0, 1.0, 2.0, 3.0]",
                             "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.14, duration_s: 0.0015, "
                             "flux_jy: 1500.0, dm: 2.0}]"])
    summary = run(cfg, show_progress=False)
    tab = read_candidates(tmp_path / "lwasv_sim_transient_candidates.ecsv")
    best = tab[int(np.argmax(tab["snr"]))]
    print(tab["snr", "dm", "width", "image", "ra_deg", "dec_deg"])
    assert best["dm"] == 2.0 and best["snr"] > 8
    assert abs(best["image"] - 0.14 / (16 * DT)) <= 1
    sep = SkyCoord(best["ra_deg"], best["dec_deg"], unit="deg").separation(SkyCoord(310.0, 20.0, unit="deg")).deg
    assert sep < 1.5 * np.degrees(2 / 16)                       # within ~one 7-degree cell
    cube = read_image_cube(next(tmp_path.glob("*_cube_*.h5")))
    assert cube["nimages"] == summary["images"] == int(0.2 / DT) // 16 and cube["images"].dtype == np.float16
    assert summary["search"]["candidates"] == len(tab)


@pytest.mark.parametrize("suffix", [".ecsv", ".fits"])
@pytest.mark.parametrize("nrow", [0, 1, 7])
def test_candidate_tables_read_back_for_any_number_of_rows(tmp_path, suffix, nrow):
    """The written candidate table reads back with astropy for 0, 1 and many rows, light curves
    (NaN where not held) included: a quiet night's empty ECSV once could not be read at all."""
    import astropy.units as u
    from astropy.table import Table
    from astropy.time import Time
    from bf_epic_blocks.io.candidates import CANDIDATE_COLUMNS, candidate_table, write_candidates
    rng = np.random.default_rng(nrow)
    rows = []
    for k in range(nrow):
        r = {c: float(rng.normal()) for c in CANDIDATE_COLUMNS}
        r.update(time_utc=Time("2026-11-25T04:00:00") + k * 0.01 * u.s,
                 sequence=f"seq{k}", image=k, pixel=3 * k, grid_x=k, grid_y=-1, channel=-1, width=1 + k,
                 nmembers=k + 2, nsidelobes=k, kind="sky-wide" if k == 1 else "point", sky_fraction=0.01 * k, lightcurve=np.where(np.arange(9) < 2, np.nan, rng.normal(size=9)))
        rows.append(r)
    tab = candidate_table(rows, {"threshold": 6.0, "lightcurve_first": -4}, lc_length=9)
    path = write_candidates(tmp_path / f"c{suffix}", tab)
    back = Table.read(path) if suffix == ".ecsv" else Table.read(path, format="fits")
    assert len(back) == nrow
    from bf_epic_blocks.io.candidates import read_candidates
    back = read_candidates(path)
    assert len(back) == nrow and back["lightcurve"].shape == (nrow, 9)
    np.testing.assert_array_equal(np.asarray(back["lightcurve"]), np.asarray(tab["lightcurve"]))
    np.testing.assert_array_equal(np.asarray(back["snr"]), np.asarray(tab["snr"]))
    assert list(back["sequence"]) == list(tab["sequence"]) and back["dm"].unit == tab["dm"].unit
    assert list(back["kind"]) == list(tab["kind"])


def test_beam_power_is_what_the_imager_makes_of_a_point_source():
    """beam_power(p -> q) against the DFT imager itself: one noise-free sample of a point source at a
    pixel p, imaged on the grid and divided by its peak, is the beam at every pixel (float64),
    with and without the self terms."""
    from bf_epic_blocks.imaging.dft import dirty_image
    from bf_epic_blocks.search import beam_power
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-50, 50, (40, 2)), rng.normal(0, 1, 40)])
    freq = np.array([60e6, 70e6])
    grid = imaging.lm_grid(24)
    lm = grid.lm
    p = 77
    s = np.append(lm[p], np.sqrt(1 - (lm[p] ** 2).sum()))
    for sign in (1, -1):
        x = np.exp(sign * 2j * np.pi * freq[:, None] / 299792458.0 * (xyz @ s)[None])[None, :, :, None]
        for rm in (False, True):
            img = dirty_image(x, xyz, freq, lm, remove_autocorr=rm, precision="fp64").sum(axis=0)[0]
            if not rm and int(np.argmax(img)) != p:
                break                                       # the other sign is the model's
            got = img / img[p]
            np.testing.assert_allclose(got, beam_power(xyz, freq, lm[p], lm, remove_autocorr=rm), atol=1e-9)
            assert beam_power(xyz, freq, lm[p], lm[p:p + 1], remove_autocorr=rm)[0] == pytest.approx(1.0)
        else:
            return
    raise AssertionError("the imager's image of the point source peaks at neither sign's pixel")


def test_the_search_s_bounds_are_pipeline_settings():
    """imager.search.max_pixels / sky_fraction / sidelobe_factor reach the search block from the YAML;
    a fraction outside (0, 1] is an error naming the key."""
    from pathlib import Path
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    from bf_epic_blocks.pipeline.runner import build_graph
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_transient.yaml"
    cfg = load_config(yaml, ["imager.search.max_pixels=4", "imager.search.sky_fraction=0.3",
                             "imager.search.sidelobe_factor=0"])
    g = build_graph(cfg)
    st = g.search.settings
    assert (st.max_pixels, st.sky_fraction, st.sidelobe_factor) == (4, 0.3, 0.0)
    assert load_config(yaml, [])["imager"]["search"]["sky_fraction"] == 0.1
    with pytest.raises(ConfigError, match="imager.search.sky_fraction"):
        load_config(yaml, ["imager.search.sky_fraction=1.5"])


class _SlowSearch(TransientSearchBlock):
    def on_data(self, ispan):
        time.sleep(0.004)
        super().on_data(ispan)


def test_an_overrun_search_counts_every_image_searched_or_lost(tmp_path):
    """guarantee=False behind a fast source: each image is searched or counted lost (both runtimes;
    real Bifrost reports its overruns differently, see TransientSearchBlock.on_data)."""
    rng = np.random.default_rng(5)
    grid = imaging.lm_grid(8)
    freq = 74e6 + 25e3 * np.arange(2)
    hdr = image_header(grid, freq, 16 * DT)
    n = 600
    x = rng.normal(10.0, 1.0, (n, 2, 1, grid.size, grid.size)).astype(np.float32)
    x[:, :, :, ~grid.mask] = np.nan
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(x, hdr, gulp_nframe=4)
        blk = _SlowSearch(src, SearchSettings(threshold=8.0, window_s=40 * 16 * DT, dms=[0.0]), guarantee=False)
        p.run()
    st = blk.search_stats
    assert st["images_lost"] > 0 and st["resets"] >= 1
    assert st["images"] + st["images_lost"] == n, st


@pytest.mark.parametrize("kw, name", [({"max_pixels": 0}, "max_pixels"), ({"sky_fraction": 1.5}, "sky_fraction"),
                                      ({"hold": -1}, "hold"), ({"hold": 2.5}, "hold"), ({"window": 2}, "window"),
                                      ({"dedisperse": "fft"}, "dedisperse"), ({"tree_precision": "fp8"}, "tree_precision"),
                                      ({"dedisperse": "tree", "average_channels": False}, "dedisperse")])
def test_bad_search_settings_are_named(kw, name):
    args = {"window": 10, **kw}
    with pytest.raises(ValueError, match=name):
        TransientSearch([74e6], 0.64e-3, 5, args.pop("window"), **args)


@pytest.mark.parametrize("kw, name", [({"threshold": float("nan")}, "threshold"), ({"window_s": 0}, "window_s"),
                                      ({"dms": [-1.0]}, "dms"), ({"dms": []}, "dms"), ({"widths": [1, 1]}, "widths"),
                                      ({"widths": [0]}, "widths"), ({"widths": [1.5]}, "widths"),
                                      ({"average_channels": "yes"}, "average_channels"), ({"product": 1}, "product"),
                                      ({"dedisperse": "fft"}, "dedisperse"), ({"tree_precision": "fp8"}, "tree_precision"),
                                      ({"max_pixels": 0}, "max_pixels"), ({"sky_fraction": 0.0}, "sky_fraction"),
                                      ({"space_link": 0}, "space_link"), ({"time_link": -1}, "time_link"),
                                      ({"lc_before": 2.5}, "lc_before"), ({"lc_after": -1}, "lc_after"),
                                      ({"sidelobe_factor": -1}, "sidelobe_factor")])
def test_bad_block_settings_are_named(kw, name):
    with pytest.raises(ValueError, match=name):
        SearchSettings(**kw)


def test_block_settings_are_one_object_and_files_the_writer_s():
    """The settings normalise to plain values (lists in, tuples of floats and ints out) and are frozen;
    the block refuses the keywords that moved to the settings or to the writer, naming where they went;
    the writer refuses a table format it cannot write."""
    import dataclasses
    st = SearchSettings(threshold=7, dms=[0, 1], widths=np.array([1, 2]))
    assert st.threshold == 7.0 and st.dms == (0.0, 1.0) and st.widths == (1, 2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        st.threshold = 5.0
    with pytest.raises(TypeError, match="threshold"):
        TransientSearchBlock(None, threshold=6.0)
    with pytest.raises(TypeError, match="writer"):
        TransientSearchBlock(None, outdir="x")
    with pytest.raises(TypeError, match="SearchSettings"):
        TransientSearchBlock(None, {"threshold": 6.0})
    with pytest.raises(ValueError, match="table_format"):
        CandidateWriter("x", table_format="csv")


@pytest.mark.parametrize("dedisperse,nchan", [("tree", 784), ("shifts", 24)])
def test_the_warm_up_twin_takes_every_crossing_path_and_leaves_the_search_alone(dedisperse, nchan):
    """The warm-up's small twin (same widths, threshold, dedispersion, precision) crosses through both
    of the crossing paths (points, and a flash's sky-wide rows) and asks for an event's window, boxcar
    and light curve; the search itself stays as it was. On the CPU the warm-up does nothing."""
    f = 74e6 + 25e3 * np.arange(nchan)
    s = TransientSearch(f, 16 * DT, 50, 312, dms=[3.0] if dedisperse == "tree" else [0.0, 1.0], threshold=7.5,
                        dedisperse=dedisperse, tree_precision="fp16" if dedisperse == "tree" else "fp32")
    hist = s._hist.copy()
    found = s._warm_twin()
    assert found.skywide.any() and (found.skywide == 0).any() and found.snr.max() > 50
    assert s.nvalues == 0 and s.nimages == 0 and np.array_equal(s._hist, hist)
    assert s.warm_up() == 0.0


_WARM_SCRIPT = r"""
import os, sys, numpy as np, cupy as cp
from bf_epic_blocks.search import Crossings, TransientSearch
f = 74e6 + 25e3 * np.arange(64)
s = TransientSearch(f, 6.4e-4, 300, 40, dms=[0.5], threshold=7.0, dedisperse="tree", tree_precision="fp16",
                    max_batch=64, xp=cp)
if sys.argv[1] == "warm":
    s.warm_up()
cache = os.environ["CUPY_CACHE_DIR"]
import re, cupy.cuda.compiler as cc                 # (names of what compiles, for a failure's message)
_init = cc._NVRTCProgram.__init__
def _named(self, src, *a, **k):
    sys.stderr.write("compiling " + " ".join(re.findall(r"__global__\s+void\s+(\w+)", src)[:3]) + "\n")
    return _init(self, src, *a, **k)
cc._NVRTCProgram.__init__ = _named
rng = np.random.default_rng(1)
x = rng.normal(10.0, 1.0, (228, 64, 300)).astype(np.float32)
s.push(cp.asarray(x[:100]))                       # the stream's own kernels (compiled by any first gulp)
cp.cuda.get_current_stream().synchronize()
before = len(os.listdir(cache))
sys.stderr.write("BURST\n")
x[150, :, 7] += 40.0                              # a burst (DM ~0 at this resolution) and a flash
x[200] += 60.0
found = Crossings.concat([s.push(cp.asarray(x[a:a + 64])) for a in (100, 164)])   # gulps of max_batch
k = int(np.argmax(found.snr)); ser = int(found.series[k]); n = int(found.end_image[k]) - s.first_image - s.shift
s.window_statistics(ser, n); s.box_image(ser, n, 1); s.series_values(ser, int(found.pixel[k]), n - 4, n + 2)
s.statistics()
cp.cuda.get_current_stream().synchronize()
print("crossings", len(found), "compiled at the burst", len(os.listdir(cache)) - before)
"""


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
def test_gpu_after_the_warm_up_the_first_burst_compiles_little(tmp_path):
    """With an empty kernel cache (a fresh machine), the first burst compiled the crossing path's
    kernels in the middle of the stream (~3 s at the whole band; 33 kernels here); after warm_up() at
    most a quarter of them (H100: one, a reduction CuPy shapes by the number of trials, which the
    small twin does not have; the names are in the message)."""
    import os
    import subprocess
    import sys
    out = {}
    for mode in ("cold", "warm"):
        env = dict(os.environ, CUPY_CACHE_DIR=str(tmp_path / mode), CUPY_CACHE_IN_MEMORY="0")
        r = subprocess.run([sys.executable, "-c", _WARM_SCRIPT, mode], env=env, capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        words = r.stdout.split()
        out[mode] = (int(words[1]), int(words[-1]), r.stderr.split("BURST")[-1][-600:])
    assert out["cold"][0] > 0 and out["warm"][0] > 0
    assert out["cold"][1] > 0, out            # the test can fail: without the warm-up the burst compiles
    assert out["warm"][1] <= out["cold"][1] // 4, out


@pytest.mark.parametrize("dedisperse", ["tree", "shifts"])
def test_a_deferred_push_finds_what_a_push_finds(xp, dedisperse):
    """push(defer=True) leaves its last batch's statistics for the next push or flush(): over a stream
    the same crossings as plain pushes, each batch's a push later, and the same statistics at the end."""
    npix, pix, e0 = 20, 7, 1300
    f, dt, x = _dispersed_burst(14, 64, npix, 300e3, 1600, 0.6, pix, e0, 2.5)
    got = []
    for defer in (False, True):
        s = TransientSearch(f, dt, npix, 200, dms=[1.0] if dedisperse == "tree" else [0.3, 0.6], widths=(1, 2, 4),
                            threshold=7, dedisperse=dedisperse, max_batch=64, xp=xp, tree_precision="fp16")
        found = [s.push(xp.asarray(x[a:a + 96]), defer=defer) for a in range(0, 1600, 96)]
        assert s.staged_images == (min(64, 1600 - 96 * 16) if defer else 0) or not defer
        found.append(s.flush())
        assert s.staged_images == 0
        c = Crossings.concat(found)
        order = np.lexsort((c.pixel, c.width_index, c.series, c.end_image))
        got.append((c.take(order), [to_np(a) for a in s.statistics()]))
    (a, sa), (b, sb) = got
    assert len(a) == len(b) > 0
    for k in Crossings.FIELDS:
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(sa, sb))


@pytest.mark.parametrize("restart", [True, False])
def test_a_new_gain_solution_restarts_the_search_instead_of_being_a_burst(tmp_path, monkeypatch, restart):
    """Gains that change mid-sequence (a table of two solutions, the second 1.5x in amplitude from 0.1 s,
    inside image 156) step the whole sky's brightness by 2.25x. The search restarts its window there and
    leaves the straddling image out: no candidate, and the burst after the step is still found. Without
    the restart (the control: the search not told of the table), the step is a sky-wide candidate."""
    from pathlib import Path
    from astropy.time import Time
    from bf_epic_blocks.io.candidates import read_candidates
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    yaml = Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_transient.yaml"
    tag0 = int(round(Time("2024-06-01T10:00:00", scale="utc").unix * FS_HZ))
    step = tag0 + int(round(0.1 * FS_HZ))
    gains = np.ones((2, 1, 256, 1), np.complex64)
    gains[1] *= 1.5
    np.savez(tmp_path / "gains.npz", valid_from=np.array([tag0, step], np.int64), gains=gains)
    cfg = load_config(yaml, [f"output.dir={tmp_path}", "source.duration_s=0.3", "source.channels.count=8",
                             "imager.grid.size=16", "imager.search.window_s=0.06", "imager.search.dms=[0, 1.0, 2.0]",
                             f"calibration.gains_table={tmp_path / 'gains.npz'}", "watch=null", "output.cube=null",
                             "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.22, duration_s: 0.0015, "
                             "flux_jy: 1500.0, dm: 1.0}]"])
    if not restart:                      # the images calibrated as before, the search not told of the table
        search_stage = runner._search_stage
        monkeypatch.setattr(runner, "_search_stage",
                            lambda cfg, imager, outdir, flag_weights=None, gains=None:
                            search_stage(cfg, imager, outdir, flag_weights))
    summary = runner.run(cfg, show_progress=False)
    tab = read_candidates(tmp_path / "lwasv_sim_transient_candidates.ecsv")
    print(tab["time_utc", "snr", "dm", "kind", "image"])
    burst = [r for r in tab if r["kind"] == "point" and abs(r["image"] - 0.22 / (16 * DT)) <= 2]
    assert burst and burst[0]["dm"] == 1.0                    # found either way
    steps = [r for r in tab if abs(r["image"] - 156) <= 8]
    if restart:
        assert not steps and len(tab) == 1
        assert summary["search"]["gain_resets"] == 1 and summary["search"]["images_straddling_gains"] == 1
    else:
        assert steps and steps[0]["kind"] == "sky-wide"
        assert summary["search"]["gain_resets"] == 0


# ------------------------------------------------------------------------------ DM between trials
def test_refine_peak_finds_the_vertex_of_a_hump_between_trials():
    """Analytic humps sampled at whole trials: the vertex of a parabola (exactly), of a Gaussian and of a
    flat-topped hump (the boxcar plateau of a wide burst) to a tenth of a trial; a run of fewer than three
    keeps the best trial; NaN (the caller keeps its trial) for a hump that reaches the trials' end, no
    finite S/N, or a candidate's trial outside the highest hump (a brighter event's)."""
    x = np.arange(20.0)
    assert refine_peak(x, 100 - (x - 7.3) ** 2) == pytest.approx(7.3, abs=1e-9)
    assert refine_peak(x, 50 * np.exp(-0.5 * ((x - 11.6) / 2.5) ** 2)) == pytest.approx(11.6, abs=0.1)
    flat = 80 * np.clip(1.0 - np.maximum(np.abs(x - 9.4) - 2.0, 0.0) / 5.0, 0, None)
    flat[9] += 0.5                                    # noise puts the best trial off the plateau's middle
    assert refine_peak(x, flat) == pytest.approx(9.4, abs=0.1)
    assert np.isnan(refine_peak(x, 100 - x))          # falls only one way
    assert np.isnan(refine_peak(x, np.full(20, 8.0) + 0.1 * np.sin(x)))     # noise: no hump stands out
    assert refine_peak(x, np.where(x == 5, 10.0, 1.0)) == 5.0
    assert np.isnan(refine_peak(x, np.full(20, np.nan)))
    two = np.where(np.abs(x - 4) <= 1, 9.0, 1.0) + np.where(np.abs(x - 14) <= 2, 90 - (x - 14) ** 2, 0.0)
    assert refine_peak(x, two) == pytest.approx(14.0) and np.isnan(refine_peak(x, two, at=4))
    assert refine_peak(2.0 * x, 100 - (x - 7.3) ** 2) == pytest.approx(14.6, abs=1e-9)   # in x's units


def test_a_wide_burst_s_dm_is_found_between_the_trials_to_within_one(tmp_path):
    """Bursts of 6.25 images (4 ms, as the station case's) arriving between images, at DMs between the
    tree's trials, in 96 channels over 19.2 MHz from 74 MHz: in the 8-image boxcar each fills a plateau of
    trials, on which the best trial is decided by noise (here off by more than one trial: the row's
    dm_trial); the row's dm, the vertex of the S/N across the trials, is within one trial of the truth."""
    from bf_epic_blocks.conventions import dispersion_delay_s
    rng = np.random.default_rng(5)
    nchan, nimg, width, dt = 96, 2600, 6.25, 16 * DT
    freq = 74e6 + 200e3 * np.arange(nchan)
    grid = imaging.lm_grid(8)
    N = grid.size
    valid = np.flatnonzero(grid.mask.ravel())
    x = rng.normal(10.0, 1.0, (nimg, nchan, 1, N * N)).astype(np.float32)
    bursts = [(valid[0], 0.52), (valid[4], 0.77), (valid[26], 1.06), (valid[38], 1.31)]    # (cell, DM), 4+ apart
    for cell, dm in bursts:
        t0 = 1500 + rng.random()
        for c in range(nchan):
            a = t0 + dispersion_delay_s(dm, freq[c], freq.max()) / dt
            for i in range(int(a), int(np.ceil(a + width))):
                x[i, c, 0, cell] += 6.0 * (min(a + width, i + 1) - max(a, i))          # S/N ~150
    with bfp.Pipeline() as pl:
        src = ArraySourceBlock(x.reshape(nimg, nchan, 1, N, N), image_header(grid, freq, dt), gulp_nframe=64)
        srch = TransientSearchBlock(src, SearchSettings(threshold=7.5, window_s=0.2, dms=[1.6], dedisperse="tree",
                                                         widths=[1, 2, 4, 8], sidelobe_factor=0.0),
                                    writer=CandidateWriter(tmp_path, png=False))
        pl.run()
    t = read_candidates(tmp_path / "transients_candidates.ecsv")
    step = srch.search.dms[1]                          # one trial: one image of sweep across the band
    off_trial, off_fit = [], []
    for cell, dm in bursts:
        rows = t[valid[t["pixel"]] == cell]
        assert len(rows) >= 1, (cell, t["pixel", "snr", "dm"])
        r = rows[int(np.argmax(rows["snr"]))]
        off_trial.append((r["dm_trial"] - dm) / step)
        off_fit.append((r["dm"] - dm) / step)
    print("trials off, best trial:", np.round(off_trial, 2), "fitted:", np.round(off_fit, 2))
    assert np.abs(off_fit).max() <= 1.0
    assert np.abs(off_trial).max() > 1.0               # what the search's best trial alone reports


def test_a_row_reads_the_history_once_its_values_are_there_not_when_its_cluster_closes(tmp_path, monkeypatch):
    """A burst's crossings in the trials far from its DM are found up to the largest sweep after it, so its
    cluster (and row) closes that much later; the row's look-back (light curve, window, boxcar image on
    every pixel, DM between the trials) is read once the values after the event are searched, so the
    history holds the window, a batch and the look-back's few values, not the largest sweep more (for
    the station's whole band: 28 GiB of its 36 GiB search). The rows equal those of a search that holds
    every value until its clusters close and reads them then."""
    import importlib
    ts = importlib.import_module("bf_epic_blocks.blocks.transient_search")
    rng = np.random.default_rng(11)
    nchan, nimg, dt = 64, 1800, 16 * DT
    freq = 74e6 + 300e3 * np.arange(nchan)
    grid = imaging.lm_grid(8)
    N = grid.size
    valid = np.flatnonzero(grid.mask.ravel())
    x = rng.normal(10.0, 1.0, (nimg, nchan, 1, N * N)).astype(np.float32)
    for cell, dm, t0 in [(valid[3], 0.3, 1150.4), (valid[30], 0.9, 1210.7)]:
        for c in range(nchan):
            a = t0 + conventions.dispersion_delay_s(dm, freq[c], freq.max()) / dt
            x[int(a):int(a) + 4, c, 0, cell] += 5.0
    settings = SearchSettings(threshold=7.5, window_s=0.2, dms=[1.6], dedisperse="tree", widths=[1, 2, 4, 8])

    def run(out):
        with bfp.Pipeline() as pl:
            src = ArraySourceBlock(x.reshape(nimg, nchan, 1, N, N), image_header(grid, freq, dt), gulp_nframe=64)
            srch = TransientSearchBlock(src, settings, writer=CandidateWriter(out, png=False))
            pl.run()
        return srch, [dict(r) for r in srch.rows]

    srch, rows = run(tmp_path / "now")
    s = srch.search
    assert s.shift > 300
    assert s.capacity < s.window + s.wmax + s.max_batch + 60                 # not + the largest sweep
    monkeypatch.setattr(ts.TransientSearchBlock, "_take_look", lambda self, cr, k: None)    # read when closed
    real = ts.TransientSearch
    monkeypatch.setattr(ts, "TransientSearch", lambda *a, hold=0, **k: real(*a, hold=hold + 2 * s.shift, **k))
    _, closed = run(tmp_path / "closed")
    point = [r for r in rows if r["kind"] == "point"]
    assert len(point) >= 2 and len(rows) == len(closed)
    for r, c in zip(rows, closed):
        assert (r["image"], r["pixel"], r["width"]) == (c["image"], c["pixel"], c["width"])
        assert np.isfinite(r["lightcurve"]).all()
        np.testing.assert_allclose(r["lightcurve"], c["lightcurve"], rtol=1e-9)
        np.testing.assert_allclose([r["snr"], r["dm"]], [c["snr"], c["dm"]], rtol=1e-9)
    assert {valid[r["pixel"]] for r in point} >= {valid[3], valid[30]}
    assert srch._recent and all(r["snr_image"] is not None for r in srch._recent)     # the boxcar images held


def test_an_event_s_window_statistics_read_its_one_series_not_the_whole_history():
    """window_statistics (and box_image) of a window the circular history wraps: the one series' values,
    as read from the whole history, with at most a few copies of that series' window allocated (a wrapped
    read of every series first copied the whole history: ~5 GB a look on a station's GPU, the station's
    out-of-memory under a pool limit)."""
    import tracemalloc
    rng = np.random.default_rng(3)
    npix, W = 400, 24
    s = TransientSearch(np.linspace(74e6, 80e6, 16), 1e-3, npix, W, dms=list(np.linspace(0, 0.3, 16)), max_batch=32)
    assert s.nser >= 16
    for _ in range(3 * s.capacity // 32 + 1):
        s.push(rng.normal(10.0, 1.0, (32, 16, npix)).astype(np.float32))
    ser = s.nser // 2

    def wrapped():                                   # the latest window that wraps the history, if one is held
        for n in range(s.nvalues - 1, 0, -1):
            a = n - s.wmax - W + 1
            if not s._held(a, n - s.wmax):
                return None
            if a % s.capacity + W > s.capacity:
                return n, a
    for _ in range(s.capacity):
        if wrapped():
            break
        s.push(rng.normal(10.0, 1.0, (1, 16, npix)).astype(np.float32))
    n, a = wrapped()
    whole = s._ring_read(a, W)[ser].astype(np.float64)                        # every series read, then one
    tracemalloc.start()
    try:
        mean, sigma = s.window_statistics(ser, n)
        box = s.box_image(ser, n - s.wmax, W)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    ref = s._ref[ser].astype(np.float64)
    assert np.allclose(mean, whole.mean(axis=0) + ref) and np.allclose(sigma, whole.std(axis=0, ddof=1))
    assert np.allclose(box, whole.mean(axis=0) + ref)
    assert peak <= 4 * W * npix * 8 + 200_000, (peak, s.nser * W * npix * s._hist.itemsize)
