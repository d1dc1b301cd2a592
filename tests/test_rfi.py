"""Interference detection (imaging.rfi) against truth the tests choose: Monte Carlo noise, Gaussian noise
through the project's own 4-bit packer, carriers and pulses of known power, and Nita & Gary's published
variance; the ci4 decode against runtime.dtypes."""
import math

import numpy as np
import pytest

from bf_epic_blocks.imaging import rfi
from bf_epic_blocks.imaging._xp import to_numpy
from bf_epic_blocks.runtime.dtypes import pack_ci4, pack_complex, unpack_complex


def complex_noise(rng, shape, sigma=1.0):
    """Complex Gaussian voltages, each part of std sigma, complex64."""
    re = rng.standard_normal(shape, dtype=np.float32)
    im = rng.standard_normal(shape, dtype=np.float32)
    return (sigma * (re + 1j * im)).astype(np.complex64)


def rate(reason, code, n):
    return float(np.count_nonzero(to_numpy(reason) == code)) / n


# ------------------------------------------------------------------------------------------ power sums

def test_ci4_power_sums_match_unpack_complex():
    rng = np.random.default_rng(0)
    m = 64
    b = rng.integers(0, 256, (4 * m, 3, 5), dtype=np.uint8)
    b[:256, 0, 0] = np.arange(256)                               # every byte at least once
    S1, S2 = rfi.power_sums(b, m, ci4=True)
    v = unpack_complex(b, "ci4").astype(np.complex128)
    p = v.real ** 2 + v.imag ** 2
    want1 = p.reshape(4, m, 3, 5).sum(axis=1)
    want2 = (p ** 2).reshape(4, m, 3, 5).sum(axis=1)
    assert S1.dtype == np.float64 and S1.shape == (4, 3, 5)
    assert np.array_equal(S1, want1) and np.array_equal(S2, want2)
    # the host ring's structured form gives the same sums
    structured = pack_complex(unpack_complex(b, "ci4"), "ci4", "system")
    assert structured.dtype.names
    S1s, S2s = rfi.power_sums(structured, m, ci4=True)
    assert np.array_equal(S1s, want1) and np.array_equal(S2s, want2)


def test_ci4_power_sums_exact_at_full_scale():
    m = 65536                                                       # every sample -8 - 8j: |x|^2 = 128
    b = np.full((m, 1), 0x88, np.uint8)
    S1, S2 = rfi.power_sums(b, m, ci4=True)
    assert S1[0, 0] == 128 * m and S2[0, 0] == 128 ** 2 * m      # 2^30: float32 would round it


def test_complex_power_sums_and_partial_block():
    rng = np.random.default_rng(1)
    x = complex_noise(rng, (96, 2))
    S1, S2 = rfi.power_sums(x, 32)
    p = np.abs(x.astype(np.complex128)) ** 2
    assert np.allclose(S1, p.reshape(3, 32, 2).sum(1), rtol=1e-6)
    assert np.allclose(S2, (p ** 2).reshape(3, 32, 2).sum(1), rtol=1e-6)
    with pytest.raises(ValueError, match="not a multiple of m"):
        rfi.power_sums(x[:95], 32)
    with pytest.raises(ValueError, match="m .* integer >= 2"):
        rfi.power_sums(x, 1)


def test_spectral_kurtosis_limits():
    m = 128
    tone = np.exp(2j * np.pi * 0.1 * np.arange(m))[:, None] * 3.0        # constant |x|: SK = 0 exactly
    S1, S2 = rfi.power_sums(tone, m)
    assert abs(rfi.spectral_kurtosis(S1, S2, m)[0, 0]) < 1e-12
    spike = np.zeros((m, 1), complex)
    spike[5] = 2.0                                                        # one sample: SK = m + 1
    S1, S2 = rfi.power_sums(spike, m)
    assert rfi.spectral_kurtosis(S1, S2, m)[0, 0] == pytest.approx(m + 1)
    assert np.isnan(rfi.spectral_kurtosis(np.zeros(1), np.zeros(1), m)[0])


# ----------------------------------------------------------------------------------- noise statistics

@pytest.mark.parametrize("m", [64, 256, 1024])
def test_gaussian_variance_is_nita_gary(m):
    mean, std = rfi.expected_sk(None, m, bits=None)
    assert mean == 1.0
    assert std ** 2 == pytest.approx(4 * m ** 2 / ((m - 1) * (m + 2) * (m + 3)), rel=1e-12)


def test_quantised_moments_sheppard_and_brute_force():
    from scipy.stats import norm
    # sigma = 1: clipping (beyond 6.5 sigma) is negligible, and rounding is adding an independent
    # uniform to within ~exp(-2 pi^2 sigma^2) = 3e-9 times powers of 2 pi (Sheppard)
    s = 1.0
    mom = rfi.quantised_power_moments(np.array([s]))[0]
    ea2, ea4 = s ** 2 + 1 / 12, 3 * s ** 4 + s ** 2 / 2 + 1 / 80
    assert mom[0] == pytest.approx(2 * ea2, rel=1e-7)
    assert mom[1] == pytest.approx(2 * ea4 + 2 * ea2 ** 2, rel=1e-6)
    # sigma = 4: clipped; enumerate the 256 level pairs
    s = 4.0
    edges = np.concatenate([[-np.inf], np.arange(-7.5, 7.0), [np.inf]])
    pl = np.diff(norm.cdf(edges / s))
    lv = np.arange(-8, 8)
    P = (lv[:, None] ** 2 + lv[None, :] ** 2).astype(float)
    w = pl[:, None] * pl[None, :]
    want = [(w * P ** k).sum() for k in (1, 2, 3, 4)]
    assert np.allclose(rfi.quantised_power_moments(s), want, rtol=1e-10)


@pytest.mark.parametrize("m", [256, 1024])
def test_gaussian_false_alarm_rate(m):
    rng = np.random.default_rng(10 + m)
    nblk = 12_000_000 // m
    x = complex_noise(rng, (nblk * m, 1))
    S1, S2 = rfi.power_sums(x, m)
    sk = rfi.spectral_kurtosis(S1, S2, m)
    assert abs(sk.mean() - 1) < 3 * math.sqrt(4 / m / nblk)
    assert sk.std() == pytest.approx(rfi.expected_sk(None, m, bits=None)[1], rel=0.03)
    for far in (1e-2, 1e-3):
        flag, reason = rfi.sk_flags(S1, S2, m, far, bits=None)
        measured = flag.mean()
        print(f"gaussian m={m} far={far}: {measured:.2e} (low {rate(reason, 1, flag.size):.1e}, "
              f"high {rate(reason, 2, flag.size):.1e})")
        assert far / 2 < measured < 2 * far
        assert rate(reason, 1, flag.size) > 0 and rate(reason, 2, flag.size) > 0   # both tails used


@pytest.fixture(scope="module")
def quantised_noise():
    """(m, nblock, {sigma: (S1, S2)}) of 4-bit noise, m = 256, 100000 blocks each, through the project's
    packer (round, clip to -8..7) and the ci4 path of power_sums."""
    rng = np.random.default_rng(20)
    m, nblk, chunk = 256, 100_000, 20_000
    out = {}
    for s in (0.7, 1.5, 3.0, 5.0):
        sums = [rfi.power_sums(pack_ci4(complex_noise(rng, (chunk * m, 1), s)), m, ci4=True)
                for _ in range(nblk // chunk)]
        out[s] = tuple(np.concatenate(part) for part in zip(*sums))
    return m, nblk, out


@pytest.mark.parametrize("sigma", [0.7, 1.5, 3.0, 5.0])
def test_quantised_false_alarm_rate(quantised_noise, sigma):
    m, nblk, data = quantised_noise
    S1, S2 = data[sigma]
    for far in (1e-2, 1e-3):
        flag, reason = rfi.sk_flags(S1, S2, m, far, bits=4)
        measured = flag.mean()
        uncorrected = rfi.sk_flags(S1, S2, m, far, bits=None)[0].mean()
        print(f"4-bit sigma={sigma} m={m} far={far}: {measured:.2e} (low {rate(reason, 1, nblk):.1e}, "
              f"high {rate(reason, 2, nblk):.1e}); Gaussian thresholds: {uncorrected:.2e}")
        assert far / 2 < measured < 2 * far
        assert not np.any(reason == 3)


@pytest.mark.parametrize("sigma", [3.0, 5.0])
def test_quantisation_correction_matters(quantised_noise, sigma):
    """Clipping moves the SK of noise below 1: the Gaussian thresholds flag far more than asked, the
    corrected mean matches the data."""
    m, nblk, data = quantised_noise
    S1, S2 = data[sigma]
    sk = rfi.spectral_kurtosis(S1, S2, m)
    far = 1e-2
    assert rfi.sk_flags(S1, S2, m, far, bits=None)[0].mean() > 2.5 * far
    mean_power = S1.sum() / S1.size / m                              # the data's own E[|x|^2]
    mean, std = rfi.expected_sk(np.array(mean_power), m, bits=4, measured=False)
    assert abs(sk.mean() - 1) > 50 * std / math.sqrt(nblk)             # far from the Gaussian value
    assert sk.mean() == pytest.approx(float(mean), abs=0.1 * float(std))
    assert sk.std() == pytest.approx(float(std), rel=0.05)
    # given each block's own power the spread is smaller (the SK and the power are correlated once the
    # quantiser clips), as expected_sk(measured=True) says
    mc, sc = rfi.expected_sk(S1 / m, m, bits=4)
    assert (sk - mc).std() == pytest.approx(float(np.median(sc)), rel=0.05)
    assert float(np.median(sc)) < (0.99 if sigma < 4 else 0.9) * float(std)


def test_low_power_blocks_are_no_power():
    rng = np.random.default_rng(5)
    m = 256
    b = pack_ci4(complex_noise(rng, (8 * m, 2), 0.2))          # mostly zeros
    b[:, 1] = 0                                                 # all zeros
    S1, S2 = rfi.power_sums(b, m, ci4=True)
    flag, reason = rfi.sk_flags(S1, S2, m, 1e-3, bits=4)
    assert np.all(reason == 3) and np.all(flag)
    assert np.all(S1[:, 0] / m < rfi.min_mean_power(4))


def test_thresholds_validate_their_arguments():
    with pytest.raises(ValueError, match="far"):
        rfi.sk_thresholds(0.0, 256, bits=None)
    with pytest.raises(ValueError, match="mean power"):
        rfi.sk_thresholds(1e-3, 256, None, bits=4)
    lo, hi = rfi.sk_thresholds(1e-3, 1024, bits=None)
    assert lo < 1 < hi and hi - 1 > 1 - lo                          # skewed: the high side is further


# ----------------------------------------------------------------------------------------- interference

@pytest.mark.parametrize("bits", [None, 4])
def test_carrier_flagged_low(bits):
    """A steady tone as strong as the noise (INR 1) in every block of m = 4096 samples."""
    rng = np.random.default_rng(30)
    m, nblk, s = 4096, 64, 1.5
    n = m * nblk
    tone = math.sqrt(2 * s * s) * np.exp(2j * np.pi * (0.1234 * np.arange(n) + 0.3))
    x = complex_noise(rng, (n, 1), s) + tone[:, None].astype(np.complex64)
    S1, S2 = rfi.power_sums(pack_ci4(x), m, ci4=True) if bits else rfi.power_sums(x, m)
    _, reason = rfi.sk_flags(S1, S2, m, 1e-3, bits=bits)
    print(f"carrier INR 1, bits={bits}: low in {rate(reason, 1, nblk):.3f} of blocks")
    assert rate(reason, 1, nblk) >= 0.95


@pytest.mark.parametrize("bits", [None, 4])
def test_pulse_flagged_high(bits):
    """Noise of 10x the power for 10% of each block of m = 1024."""
    rng = np.random.default_rng(31)
    m, nblk, s = 1024, 64, 1.0
    x = complex_noise(rng, (nblk, m, 1), s)
    on = rng.integers(0, m - m // 10, nblk)
    for k in range(nblk):
        x[k, on[k]:on[k] + m // 10] *= math.sqrt(10)
    x = x.reshape(nblk * m, 1)
    S1, S2 = rfi.power_sums(pack_ci4(x), m, ci4=True) if bits else rfi.power_sums(x, m)
    _, reason = rfi.sk_flags(S1, S2, m, 1e-3, bits=bits)
    print(f"pulse 10x for 10%, bits={bits}: high in {rate(reason, 2, nblk):.3f} of blocks")
    assert rate(reason, 2, nblk) >= 0.95


def test_broadband_impulse():
    rng = np.random.default_rng(40)
    m, nblk, nchan, ninput = 16, 256, 16, 8
    x = complex_noise(rng, (m * nblk, nchan, ninput))
    t0, width = 1000, 25                                            # samples 1000..1024: blocks 62, 63, 64
    x[t0:t0 + width] += complex_noise(rng, (width, nchan, ninput))  # as strong as the noise, everywhere
    S1, _ = rfi.power_sums(x, m)
    flags = rfi.broadband_flags(S1)
    hit = [k for k in range(nblk) if (k + 1) * m > t0 and k * m < t0 + width]
    assert hit == [62, 63, 64]
    # 62 holds 8 impulse samples, 63 all 16, 64 one (1/16 of its power: not asked to be found)
    assert flags[62] and flags[63]
    assert not np.any(np.delete(flags, hit))


def test_broadband_impulse_on_one_input_flags_that_input():
    rng = np.random.default_rng(41)
    m, nblk, nchan, ninput = 16, 256, 16, 8
    x = complex_noise(rng, (m * nblk, nchan, ninput))
    x[2000:2025, :, 3] += 2 * complex_noise(rng, (25, nchan))         # 4x the noise power, input 3 only
    S1, _ = rfi.power_sums(x, m)
    flags = rfi.broadband_flags(S1, per_input=True)
    assert flags.shape == (nblk, ninput)
    assert flags[125, 3] and flags[126, 3]                          # samples 2000..2015, 2016..2031
    others = np.delete(flags, 3, axis=1)
    assert not others.any()
    assert not np.delete(flags[:, 3], [125, 126]).any()


def test_device_and_host_agree(xp):
    """The same numbers from the array namespace under test as from NumPy."""
    rng = np.random.default_rng(50)
    m = 256
    b = pack_ci4(complex_noise(rng, (32 * m, 4, 2), 2.0))
    b[3 * m:4 * m, 1, 0] = pack_ci4(np.full(m, 3 + 0j))                # a constant block: low SK
    S1, S2 = rfi.power_sums(xp.asarray(b), m, ci4=True)
    S1h, S2h = rfi.power_sums(b, m, ci4=True)
    assert np.array_equal(to_numpy(S1), S1h) and np.array_equal(to_numpy(S2), S2h)
    _, r = rfi.sk_flags(S1, S2, m, 1e-2, bits=4)
    _, rh = rfi.sk_flags(S1h, S2h, m, 1e-2, bits=4)
    assert np.array_equal(to_numpy(r), rh) and rh.dtype == np.int8 and rh[3, 1, 0] == 1
    assert np.array_equal(to_numpy(rfi.broadband_flags(S1)), rfi.broadband_flags(S1h))


def test_impulse_detectors_on_the_device_are_their_array_form(xp):
    """broadband_flags (both forms) and band_power at a whole band's shapes (channels in groups of 3, 65
    groups; 64 short blocks): the GPU's kernels give the NumPy array form's flags and powers, with sparks
    on the whole band, on one stand, on half the stands at once, and dead stands."""
    rng = np.random.default_rng(52)
    nb, nchan, nst = 64, 195, 40
    P = rng.poisson(32.0, (nb, nchan, nst)).astype(np.float32)          # integer short-block powers
    P[10] += 40.0                                                       # a broadband spark
    P[20, :, 5] *= 6.0                                                  # one stand's own
    P[30, :, :22] *= 5.0                                                # over half the live stands at once
    P[:, 7, 3] = 0.0                                                    # a channel with no power on one stand
    live = np.ones(nst, bool)
    live[[1, 2]] = False
    for per_input in (True, False):
        want = rfi.broadband_flags(P, 6.0, per_input=per_input)
        got = to_numpy(rfi.broadband_flags(xp.asarray(P), 6.0, per_input=per_input))
        assert np.array_equal(got, want), per_input
    per = rfi.broadband_flags(P, 6.0, per_input=True)
    assert per[20, 5] and per[30, :22].all() and not per[20, 6]
    want = rfi.band_power(P, per, live)
    got = to_numpy(rfi.band_power(xp.asarray(P), xp.asarray(per), xp.asarray(live)))
    assert got.shape == want.shape == (nb, nchan, 1) and np.array_equal(got, want)
    assert want[20, 0, 0] == pytest.approx(P[20, 0, live & (np.arange(nst) != 5)].sum() * 38 / 37)
    assert want[30, 0, 0] == P[30, 0, live].sum()                       # most sparked: the sky's, kept
    band = rfi.broadband_flags(want, 6.0)
    assert band[10] and band[30] and not band[20]


@pytest.mark.parametrize("bits", [4, None])
def test_sk_code_is_sk_flags_per_stand(xp, bits):
    """sk_code's bits are sk_flags' low and high reasons, any pol of a stand (on a GPU: the kernel and its
    table of thresholds per integer block power, against the interpolated thresholds)."""
    rng = np.random.default_rng(63)
    m = 256
    v = complex_noise(rng, (4 * m, 5, 6, 2), 2.0)
    v[:m, 1, 2, 0] = 3.0                                               # a constant: low SK
    v[m:m + 20, 3, 4, 1] *= 12.0                                       # a burst: high SK
    v[2 * m:3 * m, 4, 0, :] = 0.0                                      # no power: no flag
    if bits:
        S1, S2 = rfi.power_sums(pack_ci4(v), m, ci4=True)
    else:
        S1, S2 = rfi.power_sums(v, m)
    _, r = rfi.sk_flags(S1, S2, m, 1e-2, bits=bits)
    want = ((r == 1).any(axis=3) | ((r == 2).any(axis=3) << 1)).astype(np.uint8)
    got = to_numpy(rfi.sk_code(xp.asarray(S1), xp.asarray(S2), m, 1e-2, bits=bits))
    assert got[0, 1, 2] & 1 and got[1, 3, 4] & 2 and got[2, 4, 0] == 0
    assert np.array_equal(got, want)


def test_median_over_the_middle_axis_is_numpys(xp):
    rng = np.random.default_rng(64)
    for L in (1, 2, 7, 64, 65, 130):
        x = rng.standard_normal((3, L, 9)).astype(np.float32)
        got = to_numpy(rfi._median_axis1(xp.asarray(x)))
        assert np.allclose(got, np.median(x, axis=1), rtol=1e-6, atol=1e-7), L


def test_block_power_is_its_definition(xp):
    """S1, S2 per block of m (short blocks in ``skip`` left out) and the power per short block of a summed
    over each pair of inputs, from the decoded 4-bit samples by plain sums (on a GPU: the kernel)."""
    rng = np.random.default_rng(62)
    m, a, T = 64, 16, 200                          # 3 whole blocks, 12 whole short blocks, a ragged tail
    b = rng.integers(0, 256, (T, 3, 6), dtype=np.uint8)
    v = unpack_complex(b.reshape(T, 3, 6), "ci4").astype(np.complex128)
    p = v.real ** 2 + v.imag ** 2                  # integers, exact
    skip = np.zeros(T // a, bool)
    skip[[1, 6]] = True
    keep = np.ones(T, bool)
    keep[:(T // a) * a] = ~np.repeat(skip, a)
    S1, S2, Sa = rfi.block_power(xp.asarray(b), m, a, ci4=True, group=2, skip=skip)
    pk = p * keep[:, None, None]
    want1 = pk[:3 * m].reshape(3, m, 3, 6).sum(1)
    want2 = (pk ** 2)[:3 * m].reshape(3, m, 3, 6).sum(1)
    wanta = p[:12 * a].reshape(12, a, 3, 3, 2).sum(axis=(1, 4))
    assert np.array_equal(to_numpy(S1), want1) and np.array_equal(to_numpy(S2), want2)
    assert Sa.shape == (12, 3, 3) and np.array_equal(to_numpy(Sa), wanta)
    S1, S2, Sa = rfi.block_power(xp.asarray(b[:5]), m, a, ci4=True, group=2)   # shorter than a short block
    assert S1.shape == (0, 3, 6) and Sa.shape == (0, 3, 3)


@pytest.mark.parametrize("B", [2, 3])
def test_apply_flags_zeroes_and_counts_by_the_rules(xp, B):
    """apply_flags against its rules written out as loops over (short block, channel, stand): which stands
    are zeroed in which frames, and what each reason counts (B = 2: 4-byte rows, copied by words on a GPU;
    B = 3: rows of odd length, by bytes)."""
    rng = np.random.default_rng(60)
    n, nchan, nstand, a = 40, 5, 7, 16                                   # ns = 3, the last of 8 frames
    x = rng.integers(1, 256, (n, nchan, nstand, B), dtype=np.uint8)     # no zero byte: a zero is a flag
    sk = rng.integers(0, 4, (2, nchan, nstand)).astype(np.uint8)
    sk[1, 2] = 1                                                         # every stand low in (block 1, chan 2)
    which = np.array([0, 1, -1], np.int32)
    imp = np.array([False, False, True])
    imp_st = rng.random((3, nstand)) < 0.3
    static = np.array([False, True, False, False, False])
    live = np.ones(nstand, bool)
    live[4] = False
    spread_max = 3.5
    out = xp.zeros((n, nchan, nstand, B), xp.uint8)
    cnt = to_numpy(rfi.apply_flags(xp.asarray(x), out, xp.asarray(sk), which, xp.asarray(imp),
                                   xp.asarray(imp_st), xp.asarray(static), xp.asarray(live), a, spread_max))
    want_out = x.copy()
    want_cnt = np.zeros((3, nchan, 7), np.int64)
    for j in range(3):
        for c in range(nchan):
            code = sk[which[j], c] if which[j] >= 0 else np.zeros(nstand, np.uint8)
            own = [bool(live[s] and (code[s] & 3 or imp_st[j, s])) for s in range(nstand)]
            wide = sum(own) > spread_max
            for s in range(nstand):
                sp = wide and not own[s]
                bad = static[c] or own[s] or imp[j] or sp
                if bad:
                    want_out[j * a:(j + 1) * a, c, s] = 0
                if live[s]:
                    want_cnt[j, c] += [static[c], code[s] & 1, code[s] >> 1 & 1, imp[j], imp_st[j, s], sp, bad]
    assert want_cnt[1, 2, 5] == 0 and want_cnt[1, 2, 1] == 6             # all own: nothing left to spread to
    assert want_cnt[:, :, 5].sum() > 0                                   # the spread rule is exercised
    assert np.array_equal(to_numpy(out), want_out)
    assert np.array_equal(cnt, want_cnt)
    # a gulp too short for any SK block (one frame, as a TBX capture gives): the other flags only
    one = xp.zeros((1, nchan, nstand, B), xp.uint8)
    cnt1 = to_numpy(rfi.apply_flags(xp.asarray(x[:1]), one, xp.zeros((0, nchan, nstand), xp.uint8),
                                    np.array([-1], np.int32), xp.asarray(imp[:1]), xp.asarray(imp_st[:1]),
                                    xp.asarray(static), xp.asarray(live), a, spread_max))
    assert np.array_equal(cnt1[0, :, 0], static * live.sum())


def test_per_input_impulses_ignore_a_carrier_switching_on_in_a_few_channels():
    """One stand's broadband spike is flagged on that stand; a carrier that switches on in 3 of 64 channels
    of every stand is not an impulse (the SK's to flag)."""
    rng = np.random.default_rng(61)
    m, nblk, nchan, ninput = 16, 64, 64, 8
    x = complex_noise(rng, (m * nblk, nchan, ninput))
    x[320:480, 10:13] += 3 * complex_noise(rng, (160, 3, ninput))        # 10 blocks, 3 channels, all inputs
    x[800:816, :, 5] += 2 * complex_noise(rng, (16, nchan))             # block 50, every channel, input 5
    S1, _ = rfi.power_sums(x, m)
    flags = rfi.broadband_flags(S1, per_input=True)
    assert flags[50, 5]
    assert flags.sum() == 1


# ----------------------------------------------------------------------------------- frequency lists

GOOD_LIST = """# channels to flag (MHz)
38.100
  45.000   # a comment after the frequency

50.0 50.5
60.1, 60.2
"""


def test_parse_bad_freq_list(tmp_path):
    ranges = rfi.parse_bad_freq_list(GOOD_LIST)
    want = [(38.0e6, 38.2e6), (44.9e6, 45.1e6), (50.0e6, 50.5e6), (60.1e6, 60.2e6)]
    assert np.allclose(ranges, want, rtol=0, atol=1e-3)
    path = tmp_path / "bad_freq.txt"
    path.write_text(GOOD_LIST)
    assert rfi.parse_bad_freq_list(path) == ranges
    assert rfi.parse_bad_freq_list(str(path)) == ranges


@pytest.mark.parametrize("text,match", [
    ("38.1\n38.1 MHz\n", "line 2"),
    ("# c\n\n1 2 3\n", "line 3"),
    ("40.5 40.0\n", "line 1.*low end"),
    ("-5\n", "line 1"),
    ("nan\n", "line 1"),
    ("", "no ranges"),
    ("# only a comment\n\n", "no ranges"),
])
def test_parse_bad_freq_list_malformed(text, match):
    with pytest.raises(ValueError, match=match):
        rfi.parse_bad_freq_list(text)


def test_parse_bad_freq_list_names_the_file(tmp_path):
    path = tmp_path / "flags.txt"
    path.write_text("38.1\nthirty\n")
    with pytest.raises(ValueError, match=r"flags\.txt, line 2: 'thirty'"):
        rfi.parse_bad_freq_list(path)


def test_channel_mask():
    bw = 25e3
    freq = 38.0e6 + bw * np.arange(16)                               # 38.000 .. 38.375 MHz
    ranges = rfi.parse_bad_freq_list("38.1\n")                       # (38.0, 38.2) MHz
    # channels overlapping (38.0, 38.2): centres within 112.5 kHz of 38.1 (38.000 .. 38.200 MHz)
    mask = rfi.channel_mask(freq, ranges, bw)
    assert list(np.flatnonzero(mask)) == list(range(9))
    # chan_bw_hz = 0 is Orville's own rule, |centre - 38.1 MHz| < 100 kHz
    orville = np.abs(freq - 38.1e6) < 100e3
    assert np.array_equal(rfi.channel_mask(freq, ranges, 0.0), orville)
    # touching is not overlapping: a range ending at a channel's lower edge leaves it alone
    mask = rfi.channel_mask(freq, [(38.2125e6, 38.2375e6)], bw)
    assert list(np.flatnonzero(mask)) == [9]
    assert not rfi.channel_mask(freq, [], bw).any()


def test_quantised_needs_long_blocks():
    with pytest.raises(ValueError, match="m >= 64"):
        rfi.sk_thresholds(1e-3, 32, np.ones(3), bits=4)
    lo, hi = rfi.sk_thresholds(1e-3, 32, bits=None)                  # Gaussian: any m >= 2
    assert 0 < lo < 1 < hi
