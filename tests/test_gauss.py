"""Gauss's form of the fused integer imaging (three int8 products a complex multiply-add): the operator's three
rows in int8 pieces, the voltages' three sections, the int32 sums' range. Truth: the float64 definition
(truth.py, through test_fused's truth_powers); the Hopper kernel is also held to an int64 emulation of itself."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging import fused, gauss
from bf_epic_blocks.imaging._xp import gpu_available
from test_fused import LIMIT, scene, truth_powers

GPU = pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")


def _weights(nant, seed=1, per_pol=True):
    rng = np.random.default_rng(seed)
    w = np.exp(2j * np.pi * rng.random((2, nant, 2))) * rng.uniform(0.5, 2.0, (2, nant, 2))
    if not per_pol:
        w[..., 1] = w[..., 0]
    w[:, 3, :] = 0          # a flagged antenna
    return w


def _images(Q, xyz, freq, lm, w, pieces, xp=np):
    keep = np.flatnonzero((w != 0).any(axis=(0, 2)))
    G = imaging.geometric_operator(xp.asarray(xyz[keep]), xp.asarray(freq), xp.asarray(lm), "fp64")
    Aq, osc, b, xmax = gauss.quantise_gauss(G, xp.asarray(w[:, keep]), keep, len(xyz), pieces)
    Bv = fused.layout_voltages(Q, None, [0, 1], 2 * fused._pad(len(xyz), 64), xmax)
    Bg = gauss.layout_gauss(Bv, int(Aq.shape[-1]))
    return Aq, osc, b, xmax, Bg


def test_bases_keep_the_three_products_int32_sums_exact():
    for pieces in (2, 3):
        for ka in (128, 256, 512, 1024):
            b, xmax = gauss.gauss_bases(pieces, ka)
            cmax = 127 * sum(b ** i for i in range(pieces))
            assert cmax * 3 * ka * xmax < 2 ** 31 and 8 <= xmax <= 63, (pieces, ka, b, xmax)
    assert gauss.gauss_bases(2, 256) == (254, 63)
    # the worst case the bound allows: every piece +-127 against every sample at xmax, signs aligned
    ka, pieces = 256, 2
    b, xmax = gauss.gauss_bases(pieces, ka)
    Aq = np.full((1, 1, 3, pieces, 128, ka), 127, np.int8)
    Bv = np.full((1, 128, 2 * ka), xmax, np.int8)
    Bg = gauss.layout_gauss(Bv, ka)
    osc = np.ones((1, 1, 128), np.float32)
    got = gauss.reference_gauss(Aq, osc, Bg, 128)        # asserts |Re F|, |Im F| <= 2^31 - 1
    assert got.max() > 0
    with pytest.raises(ValueError, match="too many"):
        gauss.gauss_bases(3, 2 ** 20)


@pytest.mark.parametrize("per_pol", [True, False])
@pytest.mark.parametrize("precision", ["i8x2", "i8x3"])
def test_three_products_image_within_limit_of_float64_truth(precision, per_pol):
    """The three rows and the voltages' sections through the int64 emulation against a float64 sum: gains
    that differ by pol (two sets of pieces) or not (one), a flagged antenna, 37 antennas (not of 128)."""
    xyz, freq, lm, Q = scene(nant=37)
    w = _weights(37, per_pol=per_pol)
    pieces = fused.PIECES[precision]
    Aq, osc, b, xmax, Bg = _images(Q, xyz, freq, lm, w, pieces)
    assert Aq.shape[1] == (2 if per_pol else 1) and Aq.shape[2:4] == (3, pieces) and Aq.shape[-1] == 128
    assert Aq.dtype == np.int8 and np.abs(Aq.astype(int)).max() <= 127
    got = gauss.reference_gauss(Aq, osc, Bg, Q.shape[0], base=b)[..., :len(lm)]       # (C, P, T/16, K)
    ref = truth_powers(Q, xyz, freq, lm, w, 16).transpose(1, 2, 0, 3)
    err = np.abs(got - ref).max() / np.abs(ref).max()
    assert err <= LIMIT[precision], err


def test_voltage_sections_are_re_plus_im_then_im_then_re():
    rng = np.random.default_rng(2)
    Bv = rng.integers(-8, 8, (2, 256, 2 * 70)).astype(np.int8)      # 70 antennas, laid out by .fused
    Bg = gauss.layout_gauss(Bv, 128)
    xr, xi = Bv[..., 0::2].astype(int), Bv[..., 1::2].astype(int)
    assert Bg.shape == (2, 256, 384)
    assert np.array_equal(Bg[..., :70], xr + xi) and np.array_equal(Bg[..., 128:198], xi)
    assert np.array_equal(Bg[..., 256:326], xr)
    assert not Bg[..., 70:128].any() and not Bg[..., 198:256].any() and not Bg[..., 326:].any()
    with pytest.raises(ValueError, match="do not fit"):
        gauss.layout_gauss(np.zeros((1, 128, 2 * 130), np.int8), 128)


def test_tiles_hold_each_stage_of_a_row_tile_in_order():
    """tile_gauss: tile (c, pa, mt, j, i, kb) holds rows mt*128.. and bytes kb*128.. of product j's piece i,
    in the swizzled order (chunk j' of row r at 16 (j' ^ r % 8))."""
    rng = np.random.default_rng(3)
    A = rng.integers(-127, 128, (1, 2, 3, 2, 256, 256)).astype(np.int8)
    t = gauss.tile_gauss(A)
    assert t.shape == (1, 2, 2, 3, 2, 2, 16384)
    for (pa, mt, j, i, kb, r, ch) in [(0, 0, 0, 0, 0, 0, 0), (1, 1, 2, 1, 1, 77, 5), (0, 1, 1, 0, 1, 127, 7)]:
        r8, rl = r // 8, r % 8
        off = r8 * 1024 + rl * 128 + 16 * (ch ^ rl)
        assert np.array_equal(t[0, pa, mt, j, i, kb, off:off + 16],
                              A[0, pa, j, i, mt * 128 + r, kb * 128 + 16 * ch:kb * 128 + 16 * ch + 16])


def test_shared_memory_decides_where_the_kernel_fits():
    assert gauss.gauss_fits(256) and gauss.gauss_fits(100)
    assert not gauss.gauss_fits(512)


def _hopper():
    import cupy as cp
    if cp.cuda.Device().compute_capability != "90":
        pytest.skip("the Gauss kernel needs compute capability 9.0")
    return cp


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("nant,npix_grid,per_pol,config", [(70, 24, True, None), (256, 40, False, None),
                                                            (37, 16, True, None), (70, 24, True, {"ST": 7}),
                                                            (256, 40, False, {"MT": 8})])
@pytest.mark.parametrize("precision", ["i8x2", "i8x3"])
def test_gpu_gauss_kernel_equals_its_int64_emulation(precision, nant, npix_grid, per_pol, config):
    """The Hopper kernel against the int64 emulation (the integer sums are exact: only float32's squares
    and sums differ): row tiles fewer than a block's (a block past the last tile), one or two gain sets,
    a whole LWA-SV station's 256 antennas, pixels not a multiple of 128; the kernel's other shapes."""
    cp = _hopper()
    xyz, freq, lm, Q = scene(nant=nant, T=256, nchan=3, npix_grid=npix_grid, seed=3)
    w = _weights(nant, per_pol=per_pol)
    w = np.concatenate([w, w[:1]])                                   # three channels
    Aq, osc, b, xmax, Bg = _images(Q, xyz, freq, lm, w, fused.PIECES[precision])
    flag = cp.zeros(1, cp.int32)
    npix = len(lm)
    got = gauss.gauss_power(cp.asarray(Aq), cp.asarray(osc), cp.asarray(Bg), 256, 2, flag, npix, config).get()
    got = got.transpose(1, 2, 0, 3)                                  # (C, P, 16, K)
    ref = gauss.reference_gauss(Aq, osc, Bg, 256, base=b)[..., :npix]
    assert np.abs(got - ref).max() <= 1e-6 * np.abs(ref).max()
    keep = np.flatnonzero((w != 0).any(axis=(0, 2)))
    truth = truth_powers(Q, xyz, freq, lm, w, 16).transpose(1, 2, 0, 3)
    assert np.abs(got - truth).max() <= LIMIT[precision] * np.abs(truth).max()
    assert len(keep) == nant - 1
    flag.fill(1)                                                     # a sample beyond range: NaN, never wrong
    assert np.isnan(gauss.gauss_power(cp.asarray(Aq), cp.asarray(osc), cp.asarray(Bg), 256, 2, flag, npix).get()).all()


@GPU
@pytest.mark.gpu
def test_gpu_gauss_kernel_places_images_on_a_grid():
    """GRID: sum_p fac[c, p, k] x (pol p's 16-sample sum) added to cell[k], pixels beside the grid to xout."""
    cp = _hopper()
    xyz, freq, lm, Q = scene(nant=70, T=256, nchan=2, npix_grid=24, seed=7)
    w = _weights(70, per_pol=False)
    Aq, osc, b, xmax, Bg = _images(Q, xyz, freq, lm, w, 2)
    npix, M = len(lm), int(Aq.shape[-2])
    rng = np.random.default_rng(8)
    ncell = 600
    cell = rng.permutation(ncell + 4)[:npix].astype(np.int32)      # a few pixels beside the grid
    fac = (rng.uniform(0.5, 1.5, (2, 2, M)) * osc[:, :1]).astype(np.float32)
    out = cp.zeros((16, 2, ncell), cp.float32)
    xout = cp.zeros((16, 2, 4), cp.float32)
    flag = cp.zeros(1, cp.int32)
    gauss.gauss_power(cp.asarray(Aq), cp.asarray(osc), cp.asarray(Bg), 256, 2, flag, npix,
                      grid=(out, cp.asarray(fac), cp.asarray(cell), xout))
    raw = gauss.reference_gauss(Aq, np.ones_like(osc), Bg, 256, base=b)[..., :npix]   # (C, P, 16, K) unscaled
    img = np.einsum("cpgk,cpk->gck", raw, fac[..., :npix].astype(np.float64))
    want = np.zeros((16, 2, ncell + 4))
    want[..., cell] = img
    got = np.concatenate([out.get(), xout.get()], axis=-1)
    assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()
