"""Tree dedispersion (imaging/fdmt.py) against the shifted sums it stands for, and a dispersed pulse
against the dispersion law (the delay 4.149 ms DM (f^-2 - f_ref^-2), f in GHz, from transient.py)."""
import numpy as np
import pytest

from bf_epic_blocks.imaging.fdmt import FDMTPlan, StreamingFDMT, effective_back, fdmt
from bf_epic_blocks.imaging.transient import dispersion_delay_s


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
