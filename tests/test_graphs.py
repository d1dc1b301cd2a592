"""CUDA-graph replay of DFTOperator.image (GPU only): replays equal eager calls bitwise and the float64
truth within the mode's bound, for new data on every call, across streams, with other allocations in
between; calls that cannot be captured run eagerly and stay correct."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging.dft import DFTOperator
from conftest import HAVE_GPU
from truth import brute_image

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")]


def _scene(seed, T=128):
    rng = np.random.default_rng(seed)
    xyz = np.stack([rng.normal(0, 40, 24), rng.normal(0, 40, 24), rng.normal(0, 0.5, 24)], axis=1)
    freq = np.array([50e6, 70e6])
    lm = imaging.lm_grid(12).lm
    return xyz, freq, lm, rng


def _ints(rng, T, nchan=2, nant=24, npol=2):
    return rng.integers(-8, 8, size=(T, nchan, nant, npol, 2)).astype(np.int8)


def _cplx(q):
    return q[..., 0].astype(np.float64) + 1j * q[..., 1]


@pytest.mark.parametrize("method, precision, accumulate", [
    ("covariance", "fp32", None), ("covariance", "fp16", None), ("covariance", "fp16x3", None),
    ("direct", "fp16", 16), ("direct", "fp32", None)])
def test_replays_equal_eager_calls_and_the_float64_truth(method, precision, accumulate):
    import cupy as cp
    xyz, freq, lm, rng = _scene(1)
    args = (cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm))
    w = cp.asarray(np.where(np.arange(24) == 5, 0.0, 1.0))           # one flagged antenna
    g_op = DFTOperator(*args, npol=2, weights=w, precision=precision)
    e_op = DFTOperator(*args, npol=2, weights=w, precision=precision, graphs=False)
    prods = ("I", "Q", "U", "V")
    bound = {"fp32": 1e-5, "fp16": 2e-3, "fp16x3": 1e-5}[precision]
    for call in range(4):                      # eager, capture + first replay, two more replays
        q = _ints(rng, 128)
        got = g_op.image(cp.asarray(q), prods, method=method, accumulate=accumulate)
        ref = e_op.image(cp.asarray(q), prods, method=method, accumulate=accumulate)
        assert cp.array_equal(got, ref), (call, float(cp.max(cp.abs(got - ref))))
        qc, wt = _cplx(q), np.where(np.arange(24) == 5, 0.0, 1.0)[None, :, None]
        if accumulate is None:
            truth = brute_image(qc, xyz, freq, lm, prods, weights=wt)
        else:
            truth = np.stack([brute_image(qc[i * accumulate:(i + 1) * accumulate], xyz, freq, lm, prods, weights=wt)
                              for i in range(128 // accumulate)])
        err = np.max(np.abs(got.get() - truth)) / np.max(np.abs(truth))
        assert err < bound, (call, err)
    assert g_op.graphs.captured == 1 and g_op.graphs.replays == 3


@pytest.mark.parametrize("precision", ["fp32", "fp16x3"])
def test_complex_voltages_replayed_on_the_covariance_route(precision):
    """Complex voltages (a calibration block's output): replays equal eager calls bitwise and the float64
    truth, a NaN sample is zeroed on every replay, and the non-finite counts keep accumulating."""
    import cupy as cp
    xyz, freq, lm, rng = _scene(4)
    args = (cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm))
    g_op = DFTOperator(*args, npol=2, precision=precision)
    e_op = DFTOperator(*args, npol=2, precision=precision, graphs=False)
    prods = ("I", "Q", "U", "V")
    bound = {"fp32": 1e-5, "fp16x3": 1e-5}[precision]
    for call in range(4):
        x = (rng.standard_normal((128, 2, 24, 2)) + 1j * rng.standard_normal((128, 2, 24, 2))).astype(np.complex64)
        x[call, 1, 7, 0] = np.nan                   # one bad sample per call, antenna 7 pol X
        got = g_op.image(cp.asarray(x), prods, method="covariance")
        ref = e_op.image(cp.asarray(x), prods, method="covariance")
        assert cp.array_equal(got, ref), (call, float(cp.max(cp.abs(got - ref))))
        x[call, 1, 7, 0] = 0
        truth = brute_image(x.astype(np.complex128), xyz, freq, lm, prods)
        err = np.max(np.abs(got.get() - truth)) / np.max(np.abs(truth))
        assert err < bound, (call, err)
        counts = g_op.nonfinite_counts.get()
        assert counts[7, 0] == call + 1 and counts.sum() == call + 1, (call, counts)
    assert g_op.graphs.captured == 1 and g_op.graphs.replays == 3


def test_replays_are_safe_across_streams_and_other_allocations():
    import cupy as cp
    xyz, freq, lm, rng = _scene(2)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="fp16")
    ref_op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="fp16", graphs=False)
    qs = [cp.asarray(_ints(rng, 128)) for _ in range(6)]
    op.image(qs[0])
    op.image(qs[1])                                            # captured
    keep = []
    for i, s in enumerate([cp.cuda.Stream(non_blocking=True), cp.cuda.Stream(), cp.cuda.Stream.null] * 2):
        with s:
            filler = cp.full(1 << 20, i, dtype=cp.float32)      # memory the pool hands out meanwhile
            got = op.image(qs[i % 6])
            keep.append((filler, i))
        s.synchronize()
        assert cp.array_equal(got, ref_op.image(qs[i % 6])), i
    for filler, i in keep:
        assert bool(cp.all(filler == i)), "a replay wrote into memory it does not own"
    assert op.graphs.replays == 7


def test_uncapturable_calls_run_eagerly_and_stay_correct():
    import cupy as cp
    xyz, freq, lm, rng = _scene(3)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="fp32")
    ref = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="fp32", graphs=False)
    for _ in range(3):
        q = cp.asarray(_ints(rng, 96))
        # one covariance image per 32 samples builds accumulators on every call: not captured
        got = op.image(q, method="covariance", accumulate=32)
        assert cp.array_equal(got, ref.image(q, method="covariance", accumulate=32))
        # complex voltages on the direct route are not captured (replays were seen to differ from eager
        # calls in the last bits there)
        z = q[..., 0].astype(cp.complex64) + 1j * q[..., 1].astype(cp.complex64)
        assert cp.array_equal(op.image(z, method="direct"), ref.image(z, method="direct"))
    assert op.graphs.captured == 0


@pytest.mark.parametrize("T, flagged", [(100, False), (1024, False), (70, True)])
def test_gram_rows_word_transpose_equals_numpy(T, flagged):
    """The GPU's gram_rows (word-wide transpose when nothing is selected, the general kernel when
    something is) against NumPy's, bitwise, for times that do not fill a tile."""
    import cupy as cp
    from bf_epic_blocks.imaging.layout import gram_rows
    xyz, freq, lm, rng = _scene(4)
    freq = np.array([50e6, 60e6, 70e6])
    w = np.ones(24)
    if flagged:
        w[3] = 0
    q = rng.integers(-8, 8, size=(T, 3, 24, 2, 2)).astype(np.int8)
    op_g = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, weights=cp.asarray(w))
    op_c = DFTOperator(xyz, freq, lm, npol=2, weights=w)
    got = gram_rows(cp.asarray(q), op_g.sel).get()
    ref = gram_rows(q, op_c.sel)
    assert np.array_equal(got[..., :T], ref) and not got[..., T:].any()


def test_replays_read_channel_slices_and_strided_inputs():
    """The static input is filled by one 2-D copy from a channel slice (rows at a pitch), and by
    CuPy's copy from other strides: both replays equal eager calls on the same view."""
    import cupy as cp
    xyz, freq, lm, rng = _scene(5)
    freq4 = np.array([40e6, 50e6, 60e6, 70e6])
    big = cp.asarray(rng.integers(-8, 8, size=(128, 4, 24, 2, 2)).astype(np.int8))
    for view in (big[:, 1:3], big[::2, 0:2], big[:, 2:4]):
        op = DFTOperator(cp.asarray(xyz), cp.asarray(freq4[:2]), cp.asarray(lm), npol=2, precision="fp32")
        ref = DFTOperator(cp.asarray(xyz), cp.asarray(freq4[:2]), cp.asarray(lm), npol=2, precision="fp32",
                          graphs=False)
        for _ in range(3):
            big[...] = cp.asarray(rng.integers(-8, 8, size=big.shape).astype(np.int8))   # new data, same view
            assert cp.array_equal(op.image(view), ref.image(view))
        assert op.graphs.replays == 2


def test_ci4_unpack_kernel_equals_numpy():
    """The one-pass GPU decodes of ci4 bytes give NumPy's (re, im) int8 pairs and complex64 values,
    for strided device views too (NumPy's decode is checked against hand-decoded bytes in test_tbf)."""
    import cupy as cp
    from bf_epic_blocks.runtime.dtypes import unpack_complex, unpack_int8_pairs
    rng = np.random.default_rng(6)
    b = rng.integers(0, 256, size=(37, 5, 24, 2)).astype(np.uint8)
    bd = cp.asarray(b)
    for sl in (np.s_[:], np.s_[:, 1:4], np.s_[::3]):
        got = unpack_int8_pairs(bd[sl], "ci4")
        assert got.shape == b[sl].shape + (2,)
        assert np.array_equal(got.get(), unpack_int8_pairs(b[sl], "ci4"))
        assert np.array_equal(unpack_complex(bd[sl], "ci4").get(), unpack_complex(b[sl], "ci4"))


def test_packed_input_decoded_inside_the_graph_and_static_output():
    """decode=: the graph copies in the packed ci4 bytes and decodes them itself; static_out=True
    hands back the graph's own output, overwritten by the next call (so used at once). Both equal
    eager calls on the decoded pairs bitwise, and the float64 truth."""
    import cupy as cp
    from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs

    def decode(b):
        return unpack_int8_pairs(b, "ci4")

    xyz, freq, lm, rng = _scene(4)
    args = (cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm))
    g_op = DFTOperator(*args, npol=2, precision="fp32")
    e_op = DFTOperator(*args, npol=2, precision="fp32", graphs=False)
    outs = []
    for call in range(4):
        q = _ints(rng, 96)
        packed = cp.asarray(pack_ci4(q[..., 0] + 1j * q[..., 1]))           # (T, C, A, P) uint8
        got = g_op.image(packed, ("I",), decode=decode, static_out=True)
        ref = e_op.image(cp.asarray(q), ("I",))
        assert cp.array_equal(got, ref), call
        truth = brute_image(_cplx(q), xyz, freq, lm, ("I",))
        assert np.max(np.abs(got.get() - truth)) / np.max(np.abs(truth)) < 1e-5
        outs.append(got)
    assert g_op.graphs.captured == 1 and g_op.graphs.replays == 3
    assert outs[1] is outs[2] is outs[3]            # the static output: one array, reused
    with pytest.raises(TypeError, match="decode must give"):
        g_op.image(packed, ("I",), decode=lambda b: b)


def test_copy_rows_copies_rows_at_a_pitch_and_declines_the_rest():
    """_xp.copy_rows: a channel slice of a gulp (rows of contiguous bytes at a pitch) into a contiguous array
    and back into a strided destination, each one 2-D memcpy equal to NumPy's copy; a view whose rows are
    not contiguous, or another shape or dtype, is declined with nothing written."""
    import cupy as cp
    from bf_epic_blocks.imaging._xp import copy_rows
    rng = np.random.default_rng(7)
    g = cp.asarray(rng.integers(-8, 8, size=(6, 5, 4, 2), dtype=np.int8))
    stream = cp.cuda.get_current_stream()
    dst = cp.zeros((6, 2, 4, 2), cp.int8)
    assert copy_rows(dst, g[:, 1:3], stream)
    back = cp.zeros_like(g)
    assert copy_rows(back[:, 3:5], dst, stream)
    stream.synchronize()
    assert np.array_equal(dst.get(), g[:, 1:3].get())
    assert np.array_equal(back.get()[:, 3:5], g[:, 1:3].get()) and not back.get()[:, :3].any()
    one = cp.zeros((1, 2, 4, 2), cp.int8)
    assert copy_rows(one, g[2:3, 1:3], stream)
    assert np.array_equal(one.get(), g[2:3, 1:3].get())
    keep = cp.full((6, 2, 2, 4), 9, cp.int8)
    assert not copy_rows(keep, g[:, 1:3].transpose(0, 1, 3, 2), stream)            # rows not contiguous
    assert not copy_rows(dst, g[:, 1:3].astype(cp.int16), stream)                   # another dtype
    assert not copy_rows(dst[:, :1], g[:, 1:3], stream)                             # another shape
    assert (keep == 9).all()
