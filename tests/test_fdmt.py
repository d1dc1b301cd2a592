"""Tree dedispersion (search/tree.py) against the shifted sums it stands for, and a dispersed pulse
against the dispersion law (the delay 4.149 ms DM (f^-2 - f_ref^-2), f in GHz, from bf_epic_blocks.conventions)."""
import numpy as np
import pytest

from bf_epic_blocks.search import FDMTPlan, StreamingFDMT, effective_back, fdmt
from bf_epic_blocks.conventions import dispersion_delay_s


def gathered_sums(x, back):
    """sum_c x_c(t - back[d, c]) in float64, each term fetched by its own time index (zero before a
    channel's first image): (ntrial, T, npix)."""
    C, T, _ = x.shape
    t = np.arange(T)[None, None, :] - back[:, :, None]                       # (ntrial, C, T)
    terms = x.astype(np.float64)[np.arange(C)[None, :, None], np.clip(t, 0, None)]
    return np.where((t >= 0)[..., None], terms, 0.0).sum(axis=1)


def test_the_tree_equals_the_shifted_sums_of_its_own_read_offsets():
    """Channels in descending order (as some formats give them), a band not a power of two."""
    rng = np.random.default_rng(0)
    f = (74e6 + 25e3 * np.arange(37))[::-1]
    plan = FDMTPlan(f, 40)
    x = rng.normal(size=(37, 90, 3)).astype(np.float32)
    got = fdmt(x, plan)
    back = effective_back(plan)
    assert got.shape == (41, 90, 3) and got.dtype == np.float32
    assert np.abs(got - gathered_sums(x, back)).max() < 1e-4
    assert (back[:, np.argmax(f)] == np.arange(41)).all() and (back[:, np.argmin(f)] == 0).all()


@pytest.mark.parametrize("nchan,dmax,worst", [(40, 30, 1), (784, 1875, 2)])
def test_read_offsets_follow_the_dispersion_curve(nchan, dmax, worst):
    f = 74e6 + 25e3 * np.arange(nchan)
    back = effective_back(FDMTPlan(f, dmax))
    k = f ** -2.0
    curve = np.arange(dmax + 1)[:, None] * (k[0] - k[None, :]) / (k[0] - k[-1])
    assert np.abs(back - curve).max() <= worst + 0.5


def test_a_dispersed_pulse_peaks_at_its_sweep_and_arrival():
    """A one-image pulse at DM 1.3 across 64 channels of 25 kHz at 74 MHz, 0.64-ms images: the trial
    d = rint(sweep / dt) holds all 64 channels at the arrival time at the lowest channel."""
    f = 74e6 + 25e3 * np.arange(64)
    dt, dm = 0.64e-3, 1.3
    delay = dispersion_delay_s(dm, f, f.max()) / dt           # images after the top channel's arrival
    sweep = int(np.rint(delay.max()))
    plan = FDMTPlan(f, sweep + 10)
    t_top = 20
    x = np.zeros((64, 200, 1), np.float32)
    x[np.arange(64), t_top + np.rint(delay).astype(int), 0] = 1.0
    out = fdmt(x, plan)[..., 0]
    d, t = np.unravel_index(np.argmax(out), out.shape)
    assert abs(d - sweep) <= 1 and t == t_top + sweep and out[d, t] >= 60


def test_cost_is_the_tree_s_not_the_shifted_sums():
    plan = FDMTPlan(74e6 + 25e3 * np.arange(784), 1875)
    assert plan.rows() < 0.02 * 1876 * 784


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="positive"):
        FDMTPlan([74e6, -1.0], 3)
    with pytest.raises(ValueError, match="dmax"):
        FDMTPlan([74e6, 75e6], 2.5)
    with pytest.raises(ValueError, match="nchan=2"):
        fdmt(np.zeros((3, 4, 1)), FDMTPlan([74e6, 75e6], 2))


@pytest.mark.parametrize("nchan,dmax,blocks,chunk", [(40, 30, [7, 50, 1, 92], 2), (13, 9, [60], None),
                                                     (300, 120, [64, 64, 100, 3], 4), (1, 0, [3, 7], None)])
def test_the_stream_equals_the_tree_of_the_whole_series(nchan, dmax, blocks, chunk):
    """Images pushed a block at a time (blocks shorter and longer than the largest read-back; channels in
    random order; pixels in chunks) give, time for time, the transform of the whole series at once --
    which the test above holds to the shifted sums of its read offsets."""
    rng = np.random.default_rng(nchan)
    f = rng.permutation(60e6 + 25e3 * np.arange(nchan))
    plan = FDMTPlan(f, dmax)
    T = sum(blocks)
    x = rng.normal(size=(nchan, T, 5)).astype(np.float32)
    s = StreamingFDMT(plan, 5, pixel_chunk=chunk)
    got, t = [], 0
    for b in blocks:
        got.append(s.push(x[:, t:t + b]))
        t += b
    got = np.concatenate(got, axis=1)
    assert got.shape == (dmax + 1, T, 5)
    assert np.abs(got - gathered_sums(x, effective_back(plan))).max() < 1e-4
    s.reset()                                     # a reset forgets the past: as a new series
    assert np.abs(s.push(x[:, :20]) - gathered_sums(x[:, :20], effective_back(plan))).max() < 1e-4


def test_the_working_rows_are_made_once_and_a_reset_clears_the_rings_in_place():
    """Each push works in the same rows (a whole band's are 2.9 GB on a GPU: made each push they churn
    the memory pool) and a reset (each gain solution) zeroes the rings where they are; the stream still
    equals the tree of the whole series, before and after the reset."""
    rng = np.random.default_rng(5)
    plan = FDMTPlan(60e6 + 25e3 * np.arange(40), 30)
    x = rng.normal(size=(40, 4 * 16, 3)).astype(np.float32)
    s = StreamingFDMT(plan, 3)
    got, bufs = [], set()
    for t in range(0, x.shape[1], 16):
        got.append(s.push(x[:, t:t + 16]))
        bufs.add(id(s._work._slots[0][0]))
    assert len(bufs) == 1 and len(s._work._slots) == 1       # on the host no push's rows are still read
    assert np.abs(np.concatenate(got, axis=1) - gathered_sums(x, effective_back(plan))).max() < 1e-4
    ring = s.ring
    s.reset()
    assert s.ring is ring and not ring.any()
    assert np.abs(s.push(x[:, :16]) - gathered_sums(x[:, :16], effective_back(plan))).max() < 1e-4
    assert id(s._work._slots[0][0]) in bufs


def test_the_stream_s_memory_is_fixed_by_the_band_not_the_run():
    """LWA-SV's whole tuning (784 channels from 74 MHz, 0.64-ms images, DM 3: 1,331 sweeps): the rings
    hold 444,050 row-times whatever the run's length; the tree does 12,283 rows per image."""
    f = 74e6 + 25e3 * np.arange(784)
    smax = int(np.rint(dispersion_delay_s(3.0, f.min(), f.max()) / 0.64e-3))
    plan = FDMTPlan(f, smax)
    s = StreamingFDMT(plan, 2, pixel_chunk=1)
    assert smax == 1330 and plan.rows() == 12283 and s.ring_size == 444050
    assert s.memory_bytes(64) == 4 * (444050 * 2 + s.nrow * 64)


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
def test_the_gpu_stream_equals_the_host_s():
    import cupy as cp
    rng = np.random.default_rng(3)
    f = 74e6 + 25e3 * np.arange(200)
    plan = FDMTPlan(f, 90)
    x = rng.normal(size=(200, 300, 37)).astype(np.float32)
    host, dev = StreamingFDMT(plan, 37, pixel_chunk=16), StreamingFDMT(plan, 37, xp=cp, pixel_chunk=16)
    for a, b in ((0, 64), (64, 70), (70, 300)):
        h, d = host.push(x[:, a:b]), dev.push(cp.asarray(x[:, a:b])).get()
        assert np.abs(h - d).max() <= 1e-5 * np.abs(h).max()


# ---------------------------------------------------------------- float16 storage
def _fp16_bound(x, nchan):
    """What float16 storage may cost a sum (its ~log2(nchan) + 1 roundings of 2^-11 of a partial sum no
    larger than the whole's bound), as a fraction of that bound: loose by ~3x against what is seen."""
    return (np.log2(max(nchan, 2)) + 2) * 2.0 ** -11


@pytest.mark.parametrize("nchan,dmax,blocks,chunk,npix", [(40, 30, [7, 50, 1, 92], 2, 5),
                                                          pytest.param(300, 120, [64, 64, 100, 3], 32, 67,
                                                                       marks=pytest.mark.slow),
                                                          (13, 9, [60], None, 3)])
def test_float16_storage_is_within_its_rounding_of_the_float64_sums(nchan, dmax, blocks, chunk, npix):
    """Sky-like images (a positive mean, 10% noise) at a scale float16 could not hold unscaled (1e7): once
    every channel has its past (t >= dmax), the stream in float16 equals the float64 shifted sums far
    below the sums' noise -- it stores the fluctuations about each channel's first image, so its
    rounding is of those, not of the mean -- and well inside float16's rounding of the fluctuations;
    pixel chunks with an odd last one (the even rows' spare pixel)."""
    rng = np.random.default_rng(nchan + 1)
    f = rng.permutation(60e6 + 25e3 * np.arange(nchan))
    plan = FDMTPlan(f, dmax)
    T = sum(blocks)
    x = (1e7 * rng.normal(1.0, 0.1, size=(nchan, T, npix))).astype(np.float32)
    s = StreamingFDMT(plan, npix, pixel_chunk=chunk, precision="fp16")
    got, t = [], 0
    for b in blocks:
        got.append(s.push(x[:, t:t + b], factor=0.5))
        t += b
    got = np.concatenate(got, axis=1)[:, dmax:]
    want = 0.5 * gathered_sums(x, effective_back(plan))[:, dmax:]
    assert got.dtype == np.float32 and np.isfinite(got).all()
    noise = 0.5 * 1e7 * 0.1 * np.sqrt(nchan)                        # of a sum
    fluct = 0.5 * 1e7 * 0.1 * np.sqrt(2) * 4 * nchan                # bound of a sum of fluctuations (4 sigma)
    assert np.abs(got - want).max() < _fp16_bound(x, nchan) * fluct
    # rms 1e-3 of the noise here; rounding the whole values (the first version) measured 0.055 of it
    assert np.sqrt(np.mean((got - want) ** 2)) < 0.005 * noise
    assert s.ring.dtype == np.float16 and s.rescales == 0


def test_float16_storage_rescales_before_a_flash_would_overflow():
    """A flash 1e5 times the sky in one push: the rings are rescaled first (the past's sums stay right),
    nothing overflows, and every sum is within float16's rounding of its own largest fluctuation."""
    rng = np.random.default_rng(5)
    f = 74e6 + 25e3 * np.arange(64)
    plan = FDMTPlan(f, 40)
    x = rng.normal(100.0, 10.0, size=(64, 192, 4)).astype(np.float32)
    x[:, 100:104, 2] *= 1e5
    s = StreamingFDMT(plan, 4, precision="fp16")
    got = np.concatenate([s.push(x[:, a:a + 64]) for a in (0, 64, 128)], axis=1)[:, 40:]
    want = gathered_sums(x, effective_back(plan))[:, 40:]
    assert s.rescales == 1 and np.isfinite(got).all()
    flash = np.abs(got[..., 2] - want[..., 2]).max() / np.abs(want[..., 2]).max()
    assert flash < _fp16_bound(x, 64)
    quiet = np.abs(got[..., 0] - want[..., 0]).max() / (64 * 10.0 * np.sqrt(2) * 4)
    assert quiet < _fp16_bound(x, 64)                                   # the other pixels: as before


def test_float16_storage_names_bad_input():
    plan = FDMTPlan(74e6 + 25e3 * np.arange(8), 4)
    with pytest.raises(ValueError, match="precision"):
        StreamingFDMT(plan, 3, precision="fp8")
    s = StreamingFDMT(plan, 3, precision="fp16")
    x = np.ones((8, 5, 3), np.float32)
    x[2, 1, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        s.push(x)


def test_float16_halves_the_rings():
    f = 74e6 + 25e3 * np.arange(784)
    plan = FDMTPlan(f, 1330)
    a, b = StreamingFDMT(plan, 3205, allocate=False), StreamingFDMT(plan, 3205, allocate=False, precision="fp16")
    # float16 rows: a whole number of 16-byte loads (8 values), 3,205 pixels stored as 3,208
    assert b.ld == 3208 and b._chunk(64) == 3205
    assert b.memory_bytes(64) == 2 * (444050 * 3208 + b.nrow * 64 * 3208)
    ring_a, ring_b = 4 * 444050 * 3205, 2 * 444050 * 3208                # 5.7 GB -> 2.8 GB
    assert a.memory_bytes(64) - ring_a <= StreamingFDMT.WORK_BYTES + 2 * 4 * a.nrow * 64 * 32
    assert b.memory_bytes(64) - ring_b <= StreamingFDMT.WORK_BYTES + 2 * 2 * b.nrow * 64 * 32
    assert b._chunk(64) >= 1.9 * a._chunk(64)                            # the same pass: twice the pixels


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("npix,chunk", [(37, 16), (37, None), (64, 32)])
def test_the_gpu_float16_stream_equals_the_host_s_bit_for_bit(npix, chunk):
    """The same float32 steps rounded once to float16 on both: equal bits; odd pixel counts (the spare
    pixel of a pair), a flash that rescales mid-stream."""
    import cupy as cp
    rng = np.random.default_rng(4)
    f = 74e6 + 25e3 * np.arange(200)
    plan = FDMTPlan(f, 90)
    x = rng.normal(50.0, 5.0, size=(200, 300, npix)).astype(np.float32)
    x[:, 150:152, 3] *= 1e4
    host = StreamingFDMT(plan, npix, pixel_chunk=chunk, precision="fp16")
    dev = StreamingFDMT(plan, npix, xp=cp, pixel_chunk=chunk, precision="fp16")
    for a, b in ((0, 64), (64, 70), (70, 300)):
        h, d = host.push(x[:, a:b], factor=0.25), dev.push(cp.asarray(x[:, a:b]), factor=0.25).get()
        assert np.array_equal(h, d)
    assert host.rescales == dev.rescales == 1
    want = 0.25 * gathered_sums(x[:, :300], effective_back(plan))[:, 70:]
    assert np.abs(h - want).max() / np.abs(want).max() < _fp16_bound(x, 200)


def test_float16_reference_is_the_first_image_not_a_view_of_the_caller_s_buffer():
    """A caller that pushes one image at a time from a buffer it reuses (a ring's span) must not move
    the reference: the stream equals the float64 sums as with fresh arrays."""
    rng = np.random.default_rng(8)
    plan = FDMTPlan(74e6 + 25e3 * np.arange(16), 6)
    x = rng.normal(100.0, 10.0, size=(16, 40, 3)).astype(np.float32)
    s = StreamingFDMT(plan, 3, precision="fp16")
    buf = np.empty((16, 1, 3), np.float32)
    got = []
    for t in range(40):
        buf[...] = x[:, t:t + 1]
        got.append(s.push(buf))
    got = np.concatenate(got, axis=1)[:, 6:]
    want = gathered_sums(x, effective_back(plan))[:, 6:]
    assert np.abs(got - want).max() < _fp16_bound(x, 16) * 16 * 10.0 * np.sqrt(2) * 4


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
def test_the_gpu_float16_stream_reads_the_search_s_strided_view_and_names_nan():
    """The search hands the tree a (nchan, B, npix) view of its (B, nchan, npix) images: the scale's
    maximum (one kernel over the strided view) and the sums equal the host's bit for bit, through a
    flash that rescales; a NaN anywhere is named, as on the host."""
    import cupy as cp
    rng = np.random.default_rng(14)
    f = 74e6 + 25e3 * np.arange(96)
    plan = FDMTPlan(f, 40)
    x = rng.normal(50.0, 5.0, size=(160, 96, 37)).astype(np.float32)          # (B, nchan, npix)
    x[90:92, :, 36] *= 1e4
    host = StreamingFDMT(plan, 37, precision="fp16")
    dev = StreamingFDMT(plan, 37, xp=cp, precision="fp16")
    xd = cp.asarray(x)
    for a, b in ((0, 64), (64, 160)):
        h = host.push(np.moveaxis(x[a:b], 0, 1))
        d = dev.push(cp.moveaxis(xd[a:b], 0, 1)).get()
        assert np.array_equal(h, d)
    assert host.rescales == dev.rescales == 1
    bad = xd[:5].copy()
    bad[3, 50, 36] = cp.nan
    with pytest.raises(ValueError, match="non-finite"):
        dev.push(cp.moveaxis(bad, 0, 1))
    # the refused push left nothing behind (on the GPU its levels had run before the check): the stream
    # goes on as the host's, which refused it before any level
    with pytest.raises(ValueError, match="non-finite"):
        host.push(np.moveaxis(bad.get(), 0, 1))
    more = rng.normal(50.0, 5.0, size=(40, 96, 37)).astype(np.float32)
    assert np.array_equal(host.push(np.moveaxis(more, 0, 1)), dev.push(cp.moveaxis(cp.asarray(more), 0, 1)).get())


def _grid_cells(rng, x, ncell):
    """x (nchan, B, npix) placed in cells of a (nchan, B, ncell) grid (the rest NaN, as below the horizon):
    (grid, index) with pixel p in cell index[p]."""
    index = np.sort(rng.choice(ncell, x.shape[2], replace=False)).astype(np.int32)
    grid = np.full(x.shape[:2] + (ncell,), np.nan, np.float32)
    grid[:, :, index] = x
    return grid, index


def test_the_tree_reads_pixels_out_of_cells_as_it_reads_them_gathered():
    """push(..., index): the images as an imager's grid (NaN in the cells no pixel has), pixel p in cell
    index[p]: the same sums as the gathered pixels' (the host gathers them first)."""
    rng = np.random.default_rng(31)
    plan = FDMTPlan(74e6 + 25e3 * np.arange(24), 12)
    x = rng.normal(50.0, 5.0, size=(24, 80, 9)).astype(np.float32)
    grid, index = _grid_cells(rng, x, 16)
    for precision in ("fp32", "fp16"):
        a, b = StreamingFDMT(plan, 9, precision=precision), StreamingFDMT(plan, 9, precision=precision)
        for s0, s1 in ((0, 30), (30, 80)):
            assert np.array_equal(a.push(x[:, s0:s1]), b.push(grid[:, s0:s1], index=index))
    with pytest.raises(ValueError, match="index"):
        b.push(grid[:, :4], index=index[:5])


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("chunk", [None, 16])
def test_the_gpu_float16_stream_reads_pixels_out_of_cells_bit_for_bit(chunk):
    """On the GPU the float16 tree reads each pixel out of its cell in the scale's maximum and its input
    pass (no gathered copy): the sums equal the host's of the gathered pixels bit for bit, through a flash
    that rescales, with an odd pixel count, from the search's strided (nchan, B, ncell) view; the cells no
    pixel has (NaN) are never read, and a NaN in a pixel's cell is named."""
    import cupy as cp
    rng = np.random.default_rng(32)
    plan = FDMTPlan(74e6 + 25e3 * np.arange(96), 40)
    x = rng.normal(50.0, 5.0, size=(96, 160, 37)).astype(np.float32)          # (nchan, B, npix)
    x[:, 90:92, 36] *= 1e4
    grid, index = _grid_cells(rng, x, 64)
    host = StreamingFDMT(plan, 37, pixel_chunk=chunk, precision="fp16")
    dev = StreamingFDMT(plan, 37, xp=cp, pixel_chunk=chunk, precision="fp16")
    gd = cp.asarray(np.ascontiguousarray(np.moveaxis(grid, 0, 1)))             # (B, nchan, ncell), as a ring's span
    idx = cp.asarray(index)
    for a, b in ((0, 64), (64, 160)):
        h = host.push(x[:, a:b])
        d = dev.push(cp.moveaxis(gd[a:b], 0, 1), index=idx).get()
        assert np.array_equal(h, d)
    assert host.rescales == dev.rescales == 1
    bad = gd[:5].copy()
    bad[3, 50, int(index[20])] = cp.nan
    with pytest.raises(ValueError, match="non-finite"):
        dev.push(cp.moveaxis(bad, 0, 1), index=idx)


def test_the_gpu_layout_keeps_the_memory_of_a_block_in_one_pass():
    """On a GPU the merged rows that keep a ring live only in it (ring length + block slots) and leave the
    working array: at a push of ``block`` images in one pass (the whole band's search) the same bytes."""
    f = 74e6 + 25e3 * np.arange(784)
    s = StreamingFDMT(FDMTPlan(f, 1330), 3205, allocate=False, precision="fp16", block=64)
    moved = int(s._inplace.sum())
    assert moved > 1000 and s.nwrow == s.nrow - moved and not s._inplace[:784].any()
    assert s.dev_ring_size == s.ring_size + 64 * moved
    assert s._chunk(64, gpu=True) >= 3205 and s.memory_bytes(64, gpu=True) == s.memory_bytes(64, gpu=False)
    with pytest.raises(ValueError, match="block"):
        StreamingFDMT(FDMTPlan(f[:4], 3), 2, block=0)


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("bf_epic_blocks.imaging._xp", fromlist=["x"]).gpu_available(),
                    reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("precision,chunk", [("fp32", None), ("fp32", 16), ("fp16", None), ("fp16", 16)])
def test_the_gpu_rings_hold_the_rows_through_pushes_shorter_and_longer_than_a_block(precision, chunk):
    """The merged rows written and read in their rings (block 16, read-backs to 60 images: rings longer
    and shorter than a block), pushes of 1 to 45 images (split into blocks), pixels in one pass or three:
    the host's sums (float16: bit for bit; float32: to rounding), and the shifted sums of the read offsets."""
    import cupy as cp
    rng = np.random.default_rng(41)
    plan = FDMTPlan(74e6 + 25e3 * np.arange(120), 60)
    x = rng.normal(50.0, 5.0, size=(120, 200, 37)).astype(np.float32)
    host = StreamingFDMT(plan, 37, pixel_chunk=chunk, precision=precision)
    dev = StreamingFDMT(plan, 37, xp=cp, pixel_chunk=chunk, precision=precision, block=16)
    got, t = [], 0
    for b in (16, 1, 45, 15, 17, 16, 60, 30):
        h, d = host.push(x[:, t:t + b]), dev.push(cp.asarray(x[:, t:t + b])).get()
        if precision == "fp16":
            assert np.array_equal(h, d)
        else:
            assert np.abs(h - d).max() <= 1e-5 * np.abs(h).max()
        got.append(d)
        t += b
    want = gathered_sums(x, effective_back(plan))
    assert np.abs(np.concatenate(got, axis=1)[:, 60:] - want[:, 60:]).max() / np.abs(want).max() < 3e-3


def test_the_working_array_is_sized_for_a_block_on_the_host_too():
    """Pushes longer than ``block`` are made a block at a time on the host as on a GPU, so the working
    array a push adds is a block's, not the push's, in either layout."""
    f = 74e6 + 25e3 * np.arange(40)
    s = StreamingFDMT(FDMTPlan(f, 30), 5, allocate=False, pixel_chunk=5, block=16)
    assert s.memory_bytes(64, gpu=False) == 4 * (s.ring_size * 5 + s.nrow * 16 * 5)
    assert s.memory_bytes(64, gpu=True) == 4 * (s.dev_ring_size * 5 + s.nwrow * 16 * 5)
    assert s.memory_bytes(8, gpu=False) == 4 * (s.ring_size * 5 + s.nrow * 8 * 5)
