"""Interference flagging in a pipeline, against interference the test chose.

A simulated sky (a point source and noise, 64 stands, 12 channels, 4-bit) with: steady carriers from a
direction near the horizon in two channels, an intermittent carrier in a third, two broadband impulses
of 1 ms, and one stand's own carrier. The flagger must find the contaminated stand-samples (>= 95%),
leave the clean blocks alone (<= 0.5% flagged, also on pure noise), and the image of the flagged data
must equal the clean data's image to 1% of the peak, where the unflagged image is wrong by order unity.
"""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, ImageIntegratorBlock, bfp, \
    efield_header
from bf_epic_blocks.blocks.rfi_flag import RFIFlagBlock
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


def _flag(X, hdr):
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=GULP)
        fb = RFIFlagBlock(src, far=1e-3, block_frames=M, impulse_frames=ACC)
        sink = ArraySinkBlock(fb)
        p.run()
    out = ci4_bytes(np.asarray(sink.result(0)))
    flagged = (out == 0).all(axis=3) & (np.asarray(X) != 0).any(axis=3)       # zeroed by the flagger
    return flagged, fb


def _clean_blocks_flagged(flagged, truth):
    """Fraction of (block of M, channel, stand) units without interference that hold any flag."""
    f = flagged.reshape(T // M, M, NCHAN, NST).any(axis=1)
    c = truth.reshape(T // M, M, NCHAN, NST).any(axis=1)
    return f[~c].mean()


def test_the_flagger_finds_the_interference_the_test_chose(sky):
    flagged, fb = _flag(sky["dirty"], sky["hdr"])
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
    flagged, fb = _flag(sky["noise"], sky["hdr"])
    assert _clean_blocks_flagged(flagged, np.zeros_like(sky["truth"])) <= 0.005
    assert fb.summary()["fraction_flagged"] <= 0.005


def _image(X, hdr, flag):
    lm = np.concatenate([imaging.lm_grid(24).lm, [[0.2, 0.1], [0.9, -0.35]]])   # the source, the transmitter
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=GULP)
        feed = RFIFlagBlock(src, far=1e-3, block_frames=M, impulse_frames=ACC) if flag else src
        img = DFTImagerBlock(feed, lm, ACC)
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
