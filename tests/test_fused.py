"""The fused integer modes (i8x1, i8x2, i8x3): the operator in int8 pieces, the GEMM exact in int32, |F|^2
summed in the kernel's epilogue. Truth: a float64 sum over antennas by the definition (truth.py),
written without the package; the GPU kernel is also held to an int64 emulation of itself."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging import dft, fused, plan
from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.imaging.dft import DFTOperator
from bf_epic_blocks.imaging.gemm import PrecisionUnavailable
from truth import brute_fields

GPU = pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
#: per-mode error limits on the small scenes below (measured 3.4e-3, 1.5e-5 and 8.7e-7 with 37 antennas, where
#: fewer antennas average the operator's rounding less than case P's 256); i8x1's is its measured bound
LIMIT = {"i8x1": 1e-2, "i8x2": 4e-5, "i8x3": 3e-6}


def scene(nant=40, T=128, nchan=2, npix_grid=16, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 30, (nant, 3)) * [1, 1, 0.05]
    freq = 60e6 + 10e6 * np.arange(nchan)
    lm = imaging.lm_grid(npix_grid).lm
    Q = rng.integers(-8, 8, (T, nchan, nant, 2, 2)).astype(np.int8)
    return xyz, freq, lm, Q


def truth_powers(Q, xyz, freq, lm, weights, n):
    """float64 sums over groups of n samples of |F_p|^2, F = sum_a w_a exp(-2 pi i nu s.r / c) x_a
    (no 1/N_A): (g, C, P, K)."""
    X = Q[..., 0].astype(np.float64) + 1j * Q[..., 1]
    F = brute_fields(X, xyz, freq, lm, weights=weights)                 # (T, C, K, P), with 1/N_A
    live = (np.broadcast_to(weights, (len(freq), len(xyz), 2)) != 0).sum(axis=1)   # (C, P)
    F = F * live[None, :, None, :]
    T = X.shape[0]
    g = T // n
    return (np.abs(F[:g * n]) ** 2).reshape(g, n, *F.shape[1:]).sum(1).transpose(0, 1, 3, 2)


def test_bases_keep_int32_sums_exact():
    for pieces in (1, 2, 3):
        for kd in (64, 512, 1024, 2048):
            b, xmax = fused.bases(pieces, kd)
            cmax = 127 * sum(b ** i for i in range(pieces))
            assert cmax * kd * xmax < 2 ** 31 and xmax >= 8, (pieces, kd, b, xmax)
    assert fused.bases(2, 512) == (254, 128)      # any int8 sample is exact with two pieces, 256 antennas
    assert fused.bases(3, 512) == (63, 8)         # three pieces: 4-bit samples
    assert fused.bases(1, 512) == (1, 128)        # one piece: no base


@pytest.mark.parametrize("precision", ["i8x1", "i8x2", "i8x3"])
def test_integer_pieces_image_within_limit_of_float64_truth(precision):
    """The quantised operator and the int64 emulation of the kernel against a float64 sum, with complex
    gains that differ by pol, flagged antennas, antennas not a multiple of 32, pixels not of 64."""
    xyz, freq, lm, Q = scene(nant=37)
    rng = np.random.default_rng(1)
    w = np.exp(2j * np.pi * rng.random((2, 37, 2))) * rng.uniform(0.5, 2.0, (2, 37, 2))
    w[:, 3, :] = 0          # a flagged antenna
    w[1, 5, 1] = 0          # one flagged channel-pol
    keep = np.flatnonzero((w != 0).any(axis=(0, 2)))
    G = imaging.geometric_operator(xyz[keep], freq, lm, "fp64")
    Aq, osc, b, xmax = fused.quantise_operator(G, w[:, keep], keep, len(xyz), fused.PIECES[precision])
    assert Aq.shape[1] == 2 and Aq.shape[-1] % 64 == 0 and Aq.dtype == np.int8
    assert np.abs(Aq).max() <= 127
    Bv = fused.layout_voltages(Q, None, [0, 1], Aq.shape[-1], xmax)
    got = fused.reference_power(Aq, osc, Bv, Q.shape[0])[..., :len(lm)]        # (C, P, T/16, K)
    ref = truth_powers(Q, xyz, freq, lm, w, 16).transpose(1, 2, 0, 3)
    err = np.abs(got - ref).max() / np.abs(ref).max()
    assert err <= LIMIT[precision], err


def test_layout_puts_each_sample_where_the_kernel_reads_it():
    rng = np.random.default_rng(2)
    Q = rng.integers(-8, 8, (64, 3, 5, 2, 2)).astype(np.int8)
    B = fused.layout_voltages(Q, np.array([2, 0]), [1], 64, 8)
    assert B.shape == (2, 128, 64)       # 64 samples padded to a whole block of 128 columns with zeros
    for ci, c in enumerate((2, 0)):
        for t in (0, 17, 63):
            for a in range(5):
                assert list(B[ci, t, 2 * a:2 * a + 2]) == list(Q[t, c, a, 1])
            assert not B[ci, t, 10:].any()
        assert not B[ci, 64:].any()


def test_tiles_put_each_byte_where_the_swizzled_kernel_reads_it():
    """The Hopper kernel's tiles against the swizzle written out byte by byte: byte k of row m sits in
    tile (m // 128, k // 128) at (r // 8) 1024 + (r % 8) 128 + 16 (j ^ r % 8) + k % 16, r = m % 128,
    j = (k % 128) // 16 -- and quantise_operator(tiled=True) is the tiled logical operator."""
    rng = np.random.default_rng(16)
    A = rng.integers(-127, 128, (2, 1, 2, 256, 384)).astype(np.int8)            # (C, PA, pieces, M, KD)
    At = fused.tile_operator(A)
    assert At.shape == (2, 1, 2, 2, 3, fused.TILE)
    Bv = rng.integers(-8, 8, (2, 256, 384)).astype(np.int8)
    Bt = fused.tile_voltages(Bv)
    assert Bt.shape == (2, 2, 3, fused.TILE)
    for c, piece, m, k in zip(rng.integers(0, 2, 800), rng.integers(0, 2, 800), rng.integers(0, 256, 800),
                              rng.integers(0, 384, 800)):
        r, j = m % 128, (k % 128) // 16
        off = (r // 8) * 1024 + (r % 8) * 128 + 16 * (j ^ (r % 8)) + k % 16
        assert At[c, 0, m // 128, piece, k // 128, off] == A[c, 0, piece, m, k]
        assert Bt[c, m // 128, k // 128, off] == Bv[c, m, k]
    xyz, freq, lm, Q = scene(nant=37)
    G = imaging.geometric_operator(xyz, freq, lm, "fp64")
    w = np.ones((2, 37, 2))
    plain = fused.quantise_operator(G, w, np.arange(37), 37, 2)
    tiled = fused.quantise_operator(G, w, np.arange(37), 37, 2, tiled=True)
    assert np.array_equal(tiled[0], fused.tile_operator(plain[0])) and np.array_equal(tiled[1], plain[1])
    assert np.array_equal(fused.layout_voltages(Q, None, [0, 1], 128, 8, tiled=True),
                          fused.tile_voltages(fused.layout_voltages(Q, None, [0, 1], 128, 8)))


def test_the_planner_offers_integer_modes_only_for_4bit_voltages():
    table = {"rows": [
        {"device": "gpu", "method": "direct", "precision": "fp16", "bound": 9e-4, "rate_cmac_s": 2e13},
        {"device": "gpu", "method": "direct", "precision": "i8x2", "input": "ci4", "bound": 2e-5, "rate_cmac_s": 4e13}]}
    assert plan.choose(1e-3, "gpu", table=table).precision == "fp16"
    assert plan.choose(1e-3, "gpu", table=table, sample_bits=4).precision == "i8x2"
    assert plan.choose(1e-3, "gpu", table=table, sample_bits=8).precision == "fp16"
    assert plan.choose(1e-3, "gpu", table=table, sample_bits=4, products=("I", "U")).precision == "fp16"


def test_integer_modes_need_a_gpu():
    xyz, freq, lm, Q = scene()
    with pytest.raises(PrecisionUnavailable, match="tensor cores"):
        DFTOperator(xyz, freq, lm, npol=2, precision="i8x2")


# ----------------------------------------------------------------------------------------- GPU
@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("tiled", [False, True])
@pytest.mark.parametrize("case", ["pols-differ", "pols-share", "cast-in-chunks"])
def test_gpu_quantising_kernel_equals_the_numpy_pieces(case, tiled, monkeypatch):
    """The one-launch quantising kernel (quantise.cu) against the NumPy arithmetic it mirrors, which the
    tests above hold to float64 truth: the same int8 pieces byte for byte and the same row scales, with
    flagged antennas, antennas and pixels not multiples of 64, a channel-pol flagged, and refilled in place
    over garbage (every byte is written)."""
    import cupy as cp
    xyz, freq, lm, _ = scene(nant=77, nchan=5, npix_grid=22, seed=8)
    rng = np.random.default_rng(9)
    w = np.exp(2j * np.pi * rng.random((5, 77, 2))) * rng.uniform(0.3, 3.0, (5, 77, 2))
    if case == "pols-share":
        w[..., 1] = w[..., 0]
    w[:, [4, 40], :] = 0
    w[2, 7, :] = 0
    keep = np.flatnonzero((w != 0).any(axis=(0, 2)))
    G = imaging.geometric_operator(xyz[keep], freq, lm, "fp64" if case == "cast-in-chunks" else "fp32")
    want = fused.quantise_operator(G, w[:, keep], keep, 80, 2, tiled=tiled)
    if case == "cast-in-chunks":                     # a complex128 G is cast 2 channels a launch: 3 launches
        monkeypatch.setattr(fused, "_CHUNK_BYTES_GPU", 1)
    Gd = cp.asarray(G)
    got = fused.quantise_operator(Gd, cp.asarray(w[:, keep]), keep, 80, 2, tiled=tiled, chunk=2,
                                  weights_host=w[:, keep])
    assert got[0].shape == want[0].shape and got[2:] == want[2:]
    diff = got[0].get() != want[0]
    assert not diff.any(), f"{int(diff.sum())} of {diff.size} bytes differ"
    assert np.array_equal(got[1].get(), want[1])
    junk = (cp.full(got[0].shape, 99, cp.int8), cp.full(got[1].shape, 7.0, cp.float32))
    fused.quantise_operator(Gd, cp.asarray(w[:, keep]), cp.asarray(keep), 80, 2, tiled=tiled, out=junk)
    assert np.array_equal(junk[0].get(), want[0]) and np.array_equal(junk[1].get(), want[1])


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("kernel", ["device", "portable", "portable-staged", "hopper", "hopper-st4"])
@pytest.mark.parametrize("precision", ["i8x1", "i8x2", "i8x3"])
def test_gpu_kernel_equals_its_int64_emulation(precision, kernel):
    """The device's kernel, the portable mma.sync one (B whole in shared memory, and B staged with A, the
    form for arrays too large) and (on Hopper) the warpgroup one, each against the int64 emulation: the
    integer sums are exact, so only float32's squares and sums differ."""
    import cupy as cp
    xyz, freq, lm, Q = scene(nant=70, T=256, nchan=3, npix_grid=24, seed=3)
    rng = np.random.default_rng(4)
    w = np.exp(2j * np.pi * rng.random((3, 70, 2)))
    G = imaging.geometric_operator(xyz, freq, lm, "fp32")
    Aq, osc, b, xmax = fused.quantise_operator(cp.asarray(G), cp.asarray(w), np.arange(70), 70,
                                               fused.PIECES[precision])
    flag = cp.zeros(1, cp.int32)
    Bv = fused.layout_voltages(cp.asarray(Q), None, cp.asarray([0, 1], dtype=cp.int32), int(Aq.shape[-1]), xmax, flag)
    assert np.array_equal(Bv.get(), fused.layout_voltages(Q, None, [0, 1], int(Aq.shape[-1]), xmax))
    npix = len(lm)
    cc = cp.cuda.Device().compute_capability
    if kernel.startswith("hopper") and cc != "90":
        pytest.skip("the warpgroup kernel needs compute capability 9.0")
    config = {"device": None, "portable": {}, "portable-staged": {"BFULL": 0}, "hopper": dict(fused.HOPPER_CONFIG),
              "hopper-st4": dict(fused.HOPPER_CONFIG, ST=4)}[kernel]
    got = fused.fused_power(Aq, osc, Bv, 256, 2, flag, npix, config).get()   # (16, C, P, K)
    got = got.transpose(1, 2, 0, 3)
    ref = fused.reference_power(Aq.get(), osc.get(), Bv.get(), 256, base=b)[..., :npix]
    assert np.abs(got - ref).max() <= 1e-6 * np.abs(ref).max()
    assert int(flag.get()[0]) == 0


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("precision,T", [("i8x1", 256), ("i8x2", 256), ("i8x2", 384)])
def test_gpu_the_kernel_places_the_int64_emulation_s_images_on_the_grid(precision, T):
    """The Hopper kernel onto a grid, per-pol gains (PA = 2), against the int64 emulation: each pol's
    16-sample sum times its own factor, added to the pixel's cell (three pixels beside the grid, in
    xout; cells no pixel has left at zero; 13 of the gulp's T / 16 images written)."""
    import cupy as cp
    if cp.cuda.Device().compute_capability != "90":
        pytest.skip("the grid's images need the warpgroup kernel (compute capability 9.0)")
    C, nant = 3, 70
    xyz, freq, lm, Q = scene(nant=nant, T=T, nchan=C, npix_grid=24, seed=5)
    rng = np.random.default_rng(6)
    w = np.exp(2j * np.pi * rng.random((C, nant, 2)))                       # the pols' own gains: PA = 2
    G = imaging.geometric_operator(xyz, freq, lm, "fp32")
    Aq, osc, b, xmax = fused.quantise_operator(cp.asarray(G), cp.asarray(w), np.arange(nant), nant,
                                               fused.PIECES[precision])
    assert int(osc.shape[1]) == 2
    flag = cp.zeros(1, cp.int32)
    Bv = fused.layout_voltages(cp.asarray(Q), None, cp.asarray([0, 1], dtype=cp.int32), int(Aq.shape[-1]), xmax, flag)
    npix, kpad, g_out, nx = len(lm), int(osc.shape[-1]), 13, 3
    ncell = npix + 5
    cell = np.empty(npix, np.int32)
    cell[:-nx] = rng.permutation(ncell)[:npix - nx]
    cell[-nx:] = ncell + np.arange(nx)                                      # directions beside the grid
    fac = rng.uniform(0.5, 2.0, (C, 2, kpad)).astype(np.float32)
    sums = fused.reference_power(Aq.get(), np.ones((C, 2, kpad)), Bv.get(), T, base=b)   # (C, P, T / 16, Kpad)
    per = (fac[:, :, None, :] * sums).sum(axis=1)[:, :g_out, :npix]          # (C, g, npix)
    want = np.zeros((g_out, C, ncell + nx))
    want[:, :, cell] = per.transpose(1, 0, 2)
    out, xout = cp.zeros((g_out, C, ncell), cp.float32), cp.zeros((g_out, C, nx), cp.float32)
    fused.fused_power(Aq, osc, Bv, T, 2, flag, npix, dict(fused.HOPPER_CONFIG),
                      grid=(out, cp.asarray(fac), cp.asarray(cell), xout))
    got = np.concatenate([out.get(), xout.get()], axis=-1)
    assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()
    assert (got[..., np.setdiff1d(np.arange(ncell), cell)] == 0).all()


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("precision,n,T", [("i8x2", 16, 256), ("i8x3", 16, 256), ("i8x1", 16, 256), ("i8x2", 64, 256),
                                             ("i8x2", 16, 208)])
def test_gpu_operator_images_within_limit_of_float64_truth(precision, n, T):
    """DFTOperator in a fused mode, through image(accumulate=n), with a dead channel and flags: the
    images (1/N_A^2 and 1/n applied) against the float64 definition; NaN where a channel is dead.
    208 samples: a sequence's last gulp, which is not a whole block of the kernel's columns."""
    import cupy as cp
    xyz, freq, lm, Q = scene(nant=48, T=T, nchan=3, seed=5)
    w = np.ones((3, 48, 2))
    w[:, 7] = 0
    w[2] = 0                                                 # a dead channel
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, weights=cp.asarray(w),
                     precision=precision)
    img = op.image(cp.asarray(Q), ("XX", "YY", "I"), accumulate=n).get()          # (g, C, 3, K)
    again = op.image(cp.asarray(Q), ("XX", "YY", "I"), accumulate=n).get()        # a graph replay
    assert np.array_equal(np.isnan(img), np.isnan(again)) and np.allclose(img, again, rtol=1e-6, equal_nan=True)
    live = (w != 0).sum(axis=1)
    ref = truth_powers(Q, xyz, freq, lm, w, n)[:, :2] / n / (live[None, :2, :, None] ** 2)   # (g, 2, P, K)
    ref = np.concatenate([ref, ref.sum(axis=2, keepdims=True)], axis=2)
    err = np.abs(img[:, :2] - ref).max() / np.abs(ref).max()
    assert err <= LIMIT[precision], err
    assert np.isnan(img[:, 2]).all()


@GPU
@pytest.mark.gpu
def test_gpu_samples_beyond_what_int32_holds_give_nan_not_a_wrong_image():
    import cupy as cp
    xyz, freq, lm, Q = scene(nant=40, T=128, seed=6)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x3")
    ok = op.image(cp.asarray(Q), accumulate=16, method="direct").get()
    assert np.isfinite(ok).all()
    Q8 = Q.copy()
    Q8[3, 0, 0, 0, 0] = 100                      # an 8-bit sample: three pieces hold 4-bit sums only
    bad = op.image(cp.asarray(Q8), accumulate=16, method="direct").get()
    assert np.isnan(bad).all()


@GPU
@pytest.mark.gpu
def test_gpu_integer_modes_refuse_what_they_do_not_image():
    import cupy as cp
    xyz, freq, lm, Q = scene(nant=40, T=128, seed=7)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2")
    X = cp.asarray(Q[..., 0] + 1j * Q[..., 1], dtype=cp.complex64)
    with pytest.raises(ValueError, match="integer"):
        op.image(X, accumulate=16)
    with pytest.raises(ValueError, match="cross-pol|covariance"):
        op.image(cp.asarray(Q), ("I", "U"), accumulate=16)
    with pytest.raises(ValueError, match="multiple of 16"):
        op.image(cp.asarray(Q), accumulate=8)


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("nant,pols", [(70, [0, 1]), (72, [0, 1]), (72, [1]), (64, [0])])
def test_gpu_layout_equals_numpy_and_flags_what_int32_cannot_hold(nant, pols):
    """Both layout kernels (antennas a multiple of 8 with two pols take the vector one) against the
    NumPy layout; a sample beyond xmax sets the flag, -128 included."""
    import cupy as cp
    rng = np.random.default_rng(8)
    Q = rng.integers(-8, 8, (64, 3, nant, 2, 2)).astype(np.int8)
    kd = 2 * (-(-nant // 64) * 64)
    chan = np.array([2, 0])
    for xmax, bad in ((8, None), (8, 100), (8, -128), (128, -128)):
        q = Q.copy()
        if bad is not None:
            q[5, 2, nant - 1, pols[-1], 1] = bad
        flag = cp.zeros(1, cp.int32)
        got = fused.layout_voltages(cp.asarray(q), cp.asarray(chan, dtype=cp.int32), cp.asarray(pols, dtype=cp.int32),
                                    kd, xmax, flag)
        assert np.array_equal(got.get(), fused.layout_voltages(q, chan, pols, kd, xmax))
        if kd % 128 == 0:
            tiled = fused.layout_voltages(cp.asarray(q), cp.asarray(chan, dtype=cp.int32),
                                          cp.asarray(pols, dtype=cp.int32), kd, xmax, tiled=True)
            assert np.array_equal(tiled.get(), fused.layout_voltages(q, chan, pols, kd, xmax, tiled=True))
        assert int(flag.get()[0]) == (1 if bad is not None and abs(bad) > xmax else 0), (xmax, bad)


@GPU
@pytest.mark.gpu
def test_gpu_an_integration_split_across_gulps_in_any_lengths_equals_truth():
    """A pipeline's integration that a gulp boundary splits arrives in pieces of any length (the
    sequence's last 4 samples, say): accumulated with add(), the image equals the float64 one."""
    import cupy as cp
    xyz, freq, lm, Q = scene(nant=40, T=132, nchan=2, seed=9)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2")
    acc = op.accumulator(("XX", "YY"), method="direct")
    for a, b in ((0, 100), (100, 128), (128, 132)):
        acc.add(cp.asarray(Q[a:b]))
    img = acc.result().get()                                            # (C, 2, K)
    ref = truth_powers(Q, xyz, freq, lm, np.ones((2, 40, 2)), 132)[0] / 132 / 40 ** 2     # (C, P, K)
    assert np.abs(img - ref).max() / np.abs(ref).max() <= LIMIT["i8x2"]


def test_kernel_shape_falls_back_where_the_hopper_kernel_or_shared_memory_does_not_fit():
    assert fused.kernel_config(512, "90")["kernel"] == "wgmma"       # Hopper, 256 antennas: warpgroup kernel
    assert fused.kernel_config(512, "80")["kernel"] == "mma.sync"    # compute capability 8.0: the portable kernel
    assert fused.kernel_config(512, "80")["BFULL"] == 1
    assert fused.kernel_config(512, "90")["ST"] == fused.HOPPER_CONFIG["ST"]
    for kd, st in ((1152, 5), (1280, 4)):                            # 576 and 640 antennas: fewer stages fit beside B
        few = fused.kernel_config(kd, "90")
        assert few["kernel"] == "wgmma" and few["ST"] == st and fused._smem(few, kd) <= fused._SMEM_MAX
    mid = fused.kernel_config(1408, "90")                            # 704 antennas: B too large for the Hopper kernel
    assert mid["kernel"] == "mma.sync" and mid["BFULL"] == 1
    big = fused.kernel_config(4096, "90")                            # 2048 antennas: B no longer fits whole
    assert big["kernel"] == "mma.sync" and big["BFULL"] == 0
    with pytest.raises(ValueError, match="too many"):
        fused.bases(3, 2 ** 20)


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("nant,pols", [(72, [0, 1]), (72, [1]), (70, [0, 1])])
def test_gpu_ci4_bytes_lay_out_as_their_unpacked_pairs(nant, pols):
    """ci4 bytes laid out for the kernel as they are read (the stations' case, antennas a multiple of 8
    and two pols, decoded in the layout kernel; others unpacked first) equal the NumPy layout of the
    same voltages as int8 pairs, every 4-bit value (-8 included) and the zero padding."""
    import cupy as cp
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    rng = np.random.default_rng(12)
    Q = rng.integers(-8, 8, (50, 3, nant, 2, 2)).astype(np.int8)
    Q[0, 0, 0, 0] = (-8, 7)
    b = pack_ci4(Q[..., 0] + 1j * Q[..., 1].astype(np.float64))
    kd = 2 * (-(-nant // 64) * 64)
    chan = np.array([2, 0])
    got = fused.layout_voltages(cp.asarray(b), cp.asarray(chan, dtype=cp.int32), cp.asarray(pols, dtype=cp.int32),
                                kd, 8, ci4=True)
    assert np.array_equal(got.get(), fused.layout_voltages(Q, chan, pols, kd, 8))
    tiled = fused.layout_voltages(cp.asarray(b), cp.asarray(chan, dtype=cp.int32), cp.asarray(pols, dtype=cp.int32),
                                  kd, 8, ci4=True, tiled=True)
    assert np.array_equal(tiled.get(), fused.layout_voltages(Q, chan, pols, kd, 8, tiled=True))


@GPU
@pytest.mark.gpu
def test_gpu_images_from_ci4_bytes_on_the_grid_equal_float64_truth():
    """The whole-band imager's path: ci4 bytes straight into the fused kernel, the products placed on
    the grid in one pass (ImageAccumulator.images(ci4=True, place=, out=)), against the float64
    definition, and equal to the same images from unpacked pairs placed afterwards."""
    import cupy as cp
    from bf_epic_blocks.imaging.pixels import GridPlacement
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    xyz, freq, _, Q = scene(nant=48, T=256, nchan=3, seed=13)
    grid = imaging.lm_grid(16)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2, precision="i8x2")
    acc = op.accumulator(("I",), method="direct")
    assert acc.takes_ci4
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    b = cp.asarray(pack_ci4(Q[..., 0] + 1j * Q[..., 1].astype(np.float64)))
    out = cp.full((16, 3, 1, grid.size ** 2), -7.0, cp.float32)
    acc.images(b, 16, ci4=True, place=place, out=out)
    got = out.get()
    ref = truth_powers(Q, xyz, freq, grid.lm, np.ones((3, 48, 2)), 16).sum(axis=2) / 16 / 48 ** 2   # (g, C, K)
    on = grid.mask.ravel()
    assert np.isnan(got[..., ~on]).all() and np.isfinite(got[..., on]).all()
    err = np.abs(got[:, :, 0][..., on] - ref).max() / np.abs(ref).max()
    assert err <= LIMIT["i8x2"], err
    # the same images by the per-pol sums and the products pass, placed afterwards: on a Hopper GPU the
    # kernel wrote the cells itself, its factor (scale, 1/N_A^2, 1/n) multiplied in another order
    pairs = place(acc.images(cp.asarray(Q), 16)).get()
    assert np.array_equal(np.isnan(got), np.isnan(pairs))
    assert np.allclose(got, pairs, rtol=2e-6, atol=0, equal_nan=True)


@GPU
@pytest.mark.gpu
def test_gpu_gulps_in_a_row_share_one_layout_and_each_equals_float64_truth():
    """The voltages' layout is kept from gulp to gulp (one Workspace): the next gulp is laid out while the
    last one's kernel may still be queued, on the same stream, so it overwrites nothing that kernel
    reads. Each gulp's images, read after both ran, equal the float64 definition."""
    import cupy as cp
    from bf_epic_blocks.imaging.pixels import GridPlacement
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    xyz, freq, _, Q1 = scene(nant=48, T=256, nchan=3, seed=21)
    Q2 = scene(nant=48, T=256, nchan=3, seed=22)[3]
    grid = imaging.lm_grid(16)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(grid.lm), npol=2, precision="i8x2")
    acc = op.accumulator(("I",), method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    outs, ptrs = [], []
    for Q in (Q1, Q2):
        out = cp.full((16, 3, 1, grid.size ** 2), -7.0, cp.float32)
        acc.images(cp.asarray(pack_ci4(Q[..., 0] + 1j * Q[..., 1].astype(np.float64))), 16, ci4=True,
                   place=place, out=out)
        outs.append(out)
        ptrs.append(op.fused._b_work._slots[0][0].data.ptr)
    assert ptrs[0] == ptrs[1]
    on = grid.mask.ravel()
    for Q, out in zip((Q1, Q2), outs):
        ref = truth_powers(Q, xyz, freq, grid.lm, np.ones((3, 48, 2)), 16).sum(axis=2) / 16 / 48 ** 2
        err = np.abs(out.get()[:, :, 0][..., on] - ref).max() / np.abs(ref).max()
        assert err <= LIMIT["i8x2"], err


@GPU
@pytest.mark.gpu
@pytest.mark.parametrize("products,T,precision", [(("I",), 256, "i8x2"), (("I",), 176, "i8x2"), (("XX",), 256, "i8x2"),
                                                  (("Q",), 256, "i8x3")])
def test_gpu_images_made_on_the_grid_by_the_kernel_equal_float64_truth(products, T, precision):
    """The fused kernel's images written straight onto the grid (each pol's share, the second added to
    the first; every factor in the kernel): per-pol flags (one operator a pol), an antenna-independent
    pattern, a dead channel-pol, a gulp that is not whole kernel blocks (176 samples: 11 images, the
    kernel's padded units not written), against the float64 definition; the cells no pixel has NaN, and
    (three pieces) an 8-bit sample, beyond what the int32 sums hold, makes the gulp's images NaN."""
    import cupy as cp
    from bf_epic_blocks.imaging.pixels import GridPlacement
    xyz, freq, _, Q = scene(nant=48, T=T, nchan=3, seed=17)
    grid = imaging.lm_grid(16)
    lm = grid.lm
    w = np.ones((3, 48, 2))
    w[:, 5, 1] = 0                                         # pol Y of one antenna flagged: PA = 2
    w[1, :, 0] = 0                                         # channel 1's X: dead
    pat = np.cos(np.linspace(0, 1.2, lm.shape[0]))[None, :, None, None] * np.ones((3, 1, 1, 2))
    pat[..., 1] *= 0.8                                     # (C, K, 1, P): the pols' own patterns
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, weights=cp.asarray(w),
                     pattern=cp.asarray(pat), precision=precision)
    acc = op.accumulator(products, method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    g = T // 16
    out = cp.full((g, 3, 1, grid.size ** 2), -7.0, cp.float32)
    acc.images(cp.asarray(Q), 16, place=place, out=out)
    got = out.get()
    live = (w != 0).sum(axis=1)                                              # (C, P)
    P = truth_powers(Q, xyz, freq, lm, w, 16) / 16 / np.maximum(live, 1)[None, :, :, None] ** 2   # (g, C, P, K)
    P = P * pat[None, :, :, 0, :].transpose(0, 1, 3, 2) ** 2
    ref = {"I": P[:, :, 0] + P[:, :, 1], "XX": P[:, :, 0], "Q": P[:, :, 0] - P[:, :, 1]}[products[0]]
    on = grid.mask.ravel()
    assert np.isnan(got[..., ~on]).all() and np.isnan(got[:, 1]).all()       # (every product here reads X)
    assert np.isfinite(got[:, [0, 2]][..., on]).all()
    err = np.abs(got[:, [0, 2], 0][..., on] - ref[:, [0, 2]]).max() / np.abs(ref[:, [0, 2]]).max()
    assert err <= LIMIT[precision], err
    if precision == "i8x3":
        Q8 = Q.copy()
        Q8[3, 0, 0, 0, 0] = 100
        acc.images(cp.asarray(Q8), 16, place=place, out=out)
        assert np.isnan(out.get()).all()


def test_ci4_bytes_decode_to_their_pairs():
    """The layout's own ci4 decoding (for shapes the GPU's ci4 layout kernel does not take) against the
    runtime's unpacking, every byte value."""
    from bf_epic_blocks.runtime.dtypes import unpack_int8_pairs
    b = np.arange(256, dtype=np.uint8).reshape(4, 2, 8, 4)
    assert np.array_equal(fused._ci4_pairs(b), unpack_int8_pairs(b, "ci4"))
    Q = unpack_int8_pairs(b, "ci4")                                       # (T, C, A, P, 2)
    assert np.array_equal(fused.layout_voltages(b[..., :2], None, [0, 1], 128, 8, ci4=True),
                          fused.layout_voltages(Q[..., :2, :], None, [0, 1], 128, 8))


@pytest.mark.parametrize("pols_differ", [False, True])
def test_the_plan_counts_the_operator_the_imager_holds(pols_differ):
    """cost.operator_bytes (what `bf-epic plan` adds to the memory it checks) against the arrays the code
    makes: G of a real DFTOperator, and the fused pieces quantise_operator makes (on the host; the same
    shapes on a GPU). The whole LWA-SV band's (784 channels, 3,205 pixels, 254 of 256 stands, i8x2, the
    pols' weights differing) is 9.781 GiB of pieces, what CuPy allocated on an H200, and no phases (on a
    GPU formed 256 MiB at a time while the pieces are made)."""
    from bf_epic_blocks.imaging.cost import operator_bytes
    rng = np.random.default_rng(0)
    C, K, A, A_in = 3, 130, 70, 72
    lm = rng.uniform(-0.5, 0.5, (K, 2))
    op = DFTOperator(rng.normal(0, 20, (A, 3)), 60e6 + 25e3 * np.arange(C), lm, npol=2, precision="fp32")
    got = operator_bytes(C, K, A, "fp32", gpu=False)
    assert got["phases"] == op.G.nbytes and got["operands"] == 0
    w = np.ones((C, A, 2), np.float32)
    if pols_differ:
        w[:, 5, 1] = 0.0
    Aq, osc, _, _ = fused.quantise_operator(op.G[:, 0], w, np.arange(A), A_in, fused.PIECES["i8x2"], tiled=True)
    got = operator_bytes(C, K, A, "i8x2", gpu=True, nant_in=A_in, pols_differ=pols_differ)
    assert got["operands"] == Aq.nbytes + osc.nbytes and got["phases"] == 0
    assert got["building"] == op.G[:, 0].nbytes          # every channel's phases at once (complex64)
    band = operator_bytes(784, 3205, 254, "i8x2", gpu=True, nant_in=256)
    assert (band["phases"], round(band["operands"] / 2**30, 3)) == (0, 9.781)
    assert 0.24 * 2**30 < band["building"] <= 2**28


def test_the_plan_counts_the_voltage_layout_the_fused_imager_keeps():
    """cost.voltage_bytes against the array layout_voltages makes (plain and tiled: the same bytes), for a
    gulp not a multiple of 128 samples and antennas not of 64; the whole LWA-SV band's (784 channels, 1,024
    samples, 256 stands, two pols) is 784 MiB, what CuPy's pool held for it on an H200; nothing for the other
    modes or on the CPU."""
    from bf_epic_blocks.imaging.cost import voltage_bytes
    rng = np.random.default_rng(2)
    T, C, A = 200, 3, 70
    Q = rng.integers(-8, 8, (T, C, A, 2, 2)).astype(np.int8)
    KD = 2 * (-(-A // 64) * 64)
    for tiled in (False, True):
        B = fused.layout_voltages(Q, None, [0, 1], KD, 8, tiled=tiled)
        assert voltage_bytes(C, T, A, "i8x2", gpu=True) == B.nbytes
    assert voltage_bytes(784, 1024, 256, "i8x3", gpu=True) == 784 * 2**20
    assert voltage_bytes(784, 1024, 256, "fp16", gpu=True) == 0 == voltage_bytes(784, 1024, 256, "i8x2", gpu=False)


def test_phases_formed_again_by_chunks_quantise_into_the_same_pieces():
    """Where an operator does not hold its phases (the fused modes on a GPU), :meth:`DFTOperator.phases`
    forms them from the host geometry a chunk of channels at a time: bit-equal to the held ones, and
    quantised chunk by chunk into the arrays of the whole (the pols' weights differing in one channel
    only, so that other chunks alone would make one pol set) they give the same int8 pieces and scales."""
    rng = np.random.default_rng(3)
    C, K, A = 7, 90, 40
    op = DFTOperator(rng.normal(0, 20, (A, 3)), 60e6 + 25e3 * np.arange(C), rng.uniform(-0.5, 0.5, (K, 2)), npol=2,
                     precision="fp32")
    G = op.live_G(0).copy()
    w = np.ones((C, A, 2), np.complex64) * np.exp(1j * rng.uniform(0, 6, (C, A, 1)))
    w[2, 5, 1] = 0.5
    pieces = fused.PIECES["i8x2"]
    Aq, osc, _, _ = fused.quantise_operator(G, w, np.arange(A), A, pieces, tiled=True)
    op.G = None
    op._derived.clear()
    out = (np.zeros_like(Aq), np.zeros_like(osc))
    for c0 in range(0, C, 3):
        cs = slice(c0, min(C, c0 + 3))
        assert np.array_equal(op.phases(cs), G[cs])
        fused.quantise_operator(op.phases(cs), w[cs], np.arange(A), A, pieces, tiled=True, out=(out[0][cs], out[1][cs]),
                                weights_host=w[cs])
    assert np.array_equal(out[0], Aq) and np.array_equal(out[1], osc)
    assert np.array_equal(op.live_G(0), G) and op.G is not None      # a route asking for them: formed whole


@pytest.mark.gpu
@GPU
def test_gpu_a_fused_operator_holds_no_phases_and_its_pieces_equal_the_whole_operator_s():
    """A fused-mode operator on a GPU lets its phases go (4.8 GB at the whole band): its int8 pieces, made
    a chunk of channels at a time (the chunk made small here), equal those quantised from the whole
    operator, when built, after a new gain solution (reweight) and after its last pixels moved (repoint);
    it still holds no phases after both."""
    import cupy as cp
    rng = np.random.default_rng(4)
    C, K, A = 9, 200, 48
    xyz, freq, lm = rng.normal(0, 20, (A, 3)), 60e6 + 25e3 * np.arange(C), rng.uniform(-0.5, 0.5, (K, 2))
    # gains, not unit weights: a solution folds in place only where both are (the routes chose by that)
    w = (0.8 * np.exp(1j * rng.uniform(0, 6, (C, A, 1))) * np.ones((1, 1, 2))).astype(np.complex64)
    old = fused._REFORM_BYTES_GPU
    fused._REFORM_BYTES_GPU = 2 * K * A * 8          # two channels a chunk: five chunks, the last one short
    try:
        op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, weights=cp.asarray(w),
                         precision="i8x2")
        assert op.G is None

        def whole(weights):
            G = op.phases()                          # every channel at once
            return fused.quantise_operator(G, cp.asarray(weights), op.keep_index, op.nant_in, op.fused.pieces,
                                           tiled=op.fused.tiled, weights_host=weights)
        ref = whole(w)
        assert cp.array_equal(op.fused.Aq, ref[0]) and cp.array_equal(op.fused.osc, ref[1])
        w2 = (w * np.exp(1j * rng.uniform(0, 6, (C, A, 1)))).astype(np.complex64)
        w2[:, 3] *= 0.25
        assert op.reweight(w2)
        ref = whole(w2)
        assert cp.array_equal(op.fused.Aq, ref[0]) and cp.array_equal(op.fused.osc, ref[1]) and op.G is None
        moved = rng.uniform(-0.3, 0.3, (10, 2))
        formed = []
        form = dft._geometric_from_path

        def spy(xp, path, f, precision):
            formed.append(int(path.shape[0]))
            return form(xp, path, f, precision)
        dft._geometric_from_path = spy
        try:
            op.repoint(moved, first=K - 10)
        finally:
            dft._geometric_from_path = form
        assert formed and set(formed) == {10}          # only the moved pixels' phases were formed
        ref = whole(w2)
        assert cp.array_equal(op.fused.Aq, ref[0]) and cp.array_equal(op.fused.osc, ref[1]) and op.G is None
        # the phases it forms are the moved pixels' (not those it formed before the move), bit for bit
        lm2 = np.concatenate([lm[:K - 10], moved])
        assert cp.array_equal(op.phases(), imaging.geometric_operator(cp.asarray(xyz), cp.asarray(freq),
                                                                      cp.asarray(lm2)))
    finally:
        fused._REFORM_BYTES_GPU = old


def test_quantise_operator_refuses_moved_rows_alone_where_it_cannot_place_them():
    """Phases of the moved pixels alone (``g_first``) are placed only into given arrays, on a GPU, from a
    first pixel at or after them: elsewhere a clear error, not pieces written at the wrong rows."""
    rng = np.random.default_rng(5)
    G = np.exp(1j * rng.uniform(0, 6, (2, 6, 8))).astype(np.complex64)
    w = np.ones((2, 8, 1), np.complex64)
    with pytest.raises(ValueError, match="need a GPU, out and first >= g_first"):
        fused.quantise_operator(G, w, np.arange(8), 8, 2, g_first=4, first=4)


def test_the_shipped_table_offers_one_piece_at_a_search_s_tolerance_and_two_below_it():
    """measured.json's integer rows: i8x1 (bound 1e-2) for 4-bit voltages at a tolerance of 1e-2, i8x2 at 1e-4,
    neither for complex voltages; the one-piece mode's bound is looser and its rate faster than i8x2's."""
    rows = {r["precision"]: r for r in plan.candidates("gpu") if r["precision"] in fused.FUSED}
    assert rows["i8x1"]["bound"] > rows["i8x2"]["bound"] and rows["i8x1"]["rate_cmac_s"] > rows["i8x2"]["rate_cmac_s"]
    assert plan.choose(1e-2, "gpu", sample_bits=4).precision == "i8x1"
    assert plan.choose(1e-4, "gpu", sample_bits=4).precision == "i8x2"
    assert plan.choose(1e-2, "gpu").precision not in fused.FUSED
