"""Tree dedispersion (imaging/fdmt.py) against the shifted sums it stands for, and a dispersed pulse
against the dispersion law (the delay 4.149 ms DM (f^-2 - f_ref^-2), f in GHz, from transient.py)."""
import numpy as np
import pytest

from bf_epic_blocks.imaging.fdmt import FDMTPlan, effective_back, fdmt
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
