"""DFTOperator.reweight: a new gain solution folded into an operator in place (the live solver's each
solution) images as the float64 definition with the new weights does, through the routes made before it,
the CUDA graphs captured before it and the fused modes' int8 pieces; weights that flag or unflag an input
are refused, the operator left as it was."""
import numpy as np
import pytest

from bf_epic_blocks.imaging.dft import DFTOperator
from conftest import HAVE_GPU
from test_repoint import BOUND, _cplx, _pixels, _scene
from truth import brute_image


def _gains(rng, nchan, nant, flag=((3, 0), (7, 1))):
    """Complex per-input gains (nchan, nant, 2) with ~25% amplitude scatter and random phases, zero where
    ``flag`` says (antenna, pol), and a channel-pol partial flag."""
    g = np.exp(0.25 * rng.standard_normal((nchan, nant, 2)) + 1j * rng.uniform(0, 2 * np.pi, (nchan, nant, 2)))
    for a, p in flag:
        g[:, a, p] = 0
    g[1, 9, 0] = 0
    return g


@pytest.mark.parametrize("precision", ["fp64", "fp32"])
@pytest.mark.parametrize("method", ["direct", "covariance"])
@pytest.mark.parametrize("ints", [True, False], ids=["int-voltages", "complex-voltages"])
def test_reweighted_operator_images_as_the_float64_definition_with_the_new_gains(precision, method, ints):
    xyz, freq, q, rng = _scene(5)
    lm = _pixels(rng, 6)
    w_a, w_b = _gains(rng, 3, 24), _gains(rng, 3, 24)
    X = _cplx(q)
    data = q if ints else X
    prods = ("I", "V") if method == "covariance" else ("I",)
    op = DFTOperator(xyz, freq, lm, npol=2, weights=w_a, precision=precision)
    route = op.accumulator(prods, method=method)
    route.add(data)
    truth_a = brute_image(X, xyz, freq, lm, prods, weights=w_a)
    assert np.abs(route.result() - truth_a).max() / np.abs(truth_a).max() < BOUND[precision]
    assert op.reweight(w_b) is True
    route.reset()
    route.add(data)
    after = route.result()
    truth_b = brute_image(X, xyz, freq, lm, prods, weights=w_b)
    err = np.abs(after - truth_b).max() / np.abs(truth_b).max()
    assert err < BOUND[precision], err
    assert np.abs(truth_b - truth_a).max() > 0.1 * np.abs(truth_b).max()       # the gains changed the images
    fresh = DFTOperator(xyz, freq, lm, npol=2, weights=w_b, precision=precision).image(data, prods, method=method)
    np.testing.assert_allclose(after, fresh, rtol=1e-6 if precision == "fp32" else 1e-13, atol=0)


def test_reweight_refuses_other_flags_and_leaves_the_operator_as_it_was():
    xyz, freq, q, rng = _scene(6)
    lm = _pixels(rng, 4)
    w = _gains(rng, 3, 24)
    op = DFTOperator(xyz, freq, lm, npol=2, weights=w)
    X = _cplx(q)
    before = op.image(X, ("I",))
    newly_flagged = w.copy()
    newly_flagged[:, 5, 1] = 0                                   # an input the solver found deaf
    unflagged = w.copy()
    unflagged[:, 3, 0] = 1.0                                     # an input that came back
    back_all = w.copy()
    back_all[:, 3, :] = 0.5                                      # an antenna the operator dropped, back
    for bad in (newly_flagged, unflagged, back_all, (w != 0).astype(float)):   # the last: unit weights
        assert op.reweight(bad) is False
        np.testing.assert_array_equal(op.image(X, ("I",)), before)
    unit = DFTOperator(xyz, freq, lm, npol=2, weights=(w != 0).astype(float))
    assert unit.reweight(w) is False                             # the routes chose exact integer paths
    with pytest.raises(ValueError, match="NaN or inf"):
        op.reweight(np.where(w != 0, np.nan, 0))


@pytest.mark.parametrize("precision, method", [("fp32", "direct"), ("fp16x3", "covariance"), ("i8x2", "direct")],
                         ids=["fp32", "fp16x3", "i8x2"])
@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_gpu_replayed_graphs_and_fused_pieces_see_the_new_gains(precision, method):
    """On the GPU: images replayed from CUDA graphs captured before the new gains (ci4 bytes decoded inside
    the graph, where the route captures) and batched route images (the fused mode's int8 pieces, one set per pol) equal the float64
    definition with the new gains; the fused mode's images placed on a grid use the new scales."""
    import cupy as cp
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging.pixels import GridPlacement
    from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs
    xyz, freq, q, rng = _scene(7, nant=48, T=64)
    grid = imaging.lm_grid(10)
    lm = grid.lm
    w_a, w_b = _gains(rng, 3, 48), _gains(rng, 3, 48)
    w_b *= np.abs(w_a).max() / np.abs(w_b).max()          # the same fp16 range scale (fp16x3's covariances)
    X = _cplx(q)
    packed = cp.asarray(pack_ci4(X))

    def decode(b):
        return unpack_int8_pairs(b, "ci4")

    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision=precision,
                     weights=cp.asarray(w_a))
    acc = op.accumulator(("I",), method=method)
    for _ in range(3):                                           # eager, capture, replay
        op.image(packed[:16], ("I",), method=method, decode=decode, static_out=True)
    acc.images(cp.asarray(q), 16)
    place = out = None
    if precision == "i8x2":
        place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
        out = cp.zeros((4, 3, 1, grid.size ** 2), cp.float32)
        acc.images(cp.asarray(q), 16, place=place, out=out)
    captured = op.graphs.replays                              # > 0 where these calls replay a graph
    assert op.reweight(cp.asarray(w_b)) is True
    truth = np.stack([brute_image(X[i * 16:(i + 1) * 16], xyz, freq, lm, ("I",), weights=w_b) for i in range(4)])
    replayed = np.stack([op.image(packed[i * 16:(i + 1) * 16], ("I",), method=method, decode=decode,
                                  static_out=True).get() for i in range(4)])
    assert op.graphs.replays >= captured + 4 if captured else op.graphs.replays == 0
    got = [replayed, acc.images(cp.asarray(q), 16).get()]
    if place is not None:
        out[...] = -1
        acc.images(cp.asarray(q), 16, place=place, out=out)
        got.append(out.get()[..., grid.mask.ravel()])
    for g in got:
        err = np.abs(g - truth).max() / np.abs(truth).max()
        assert err < BOUND[precision], err


def test_an_imager_folds_each_new_solution_in_place(xp):
    """DFTImagerBlock with a gain table folded into its operator (as the live solver's table is): the
    operator is built once, with the cable terms, and each solution (the same inputs flagged) goes into it
    in place; every integration's image is the float64 definition with its own solution and the cable
    terms (ci4 voltages, on the CPU and a GPU)."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, bfp
    from bf_epic_blocks.imaging.calibration import GainTable, cable_weights
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    from test_blocks import DT, TPF, efield_header, station
    rng = np.random.default_rng(8)
    nst, nchan, T, acc = 12, 3, 240, 40
    xyz = rng.normal(0, 20, (nst, 3)) * [1, 1, 0.05]
    freq = 60e6 + 25e3 * np.arange(nchan)
    X = rng.integers(-8, 8, (T, nchan, nst, 2)) + 1j * rng.integers(-8, 8, (T, nchan, nst, 2))
    flags = np.zeros((nst, 2), bool)
    flags[4, 1] = True
    s = dict(xyz=xyz, flags=flags, delay=rng.uniform(100e-9, 600e-9, (nst, 2, nchan)),
             gain=rng.uniform(0.5, 2.0, (nst, 2, nchan)))
    lm = imaging.lm_grid(8).lm
    t0 = 10**12
    g = rng.uniform(0.5, 1.5, (3, nchan, nst, 2)) * np.exp(2j * np.pi * rng.random((3, nchan, nst, 2)))
    starts = [0, 2, 4]                                                   # integrations where each begins
    table = GainTable([t0 + k * acc * TPF for k in starts], g)
    hdr = efield_header("fold", t0, freq, DT, station(s), dtype="ci4")
    gpu = xp.__name__ == "cupy"
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=80, space="cuda" if gpu else "system")
        img = DFTImagerBlock(src, lm, acc, products=["I"], gains=table, cable=True, pattern=False,
                             precision="fp32")
        sink = ArraySinkBlock(img)
        p.run()
    got = sink.result(0)[:, :, 0]
    wc = cable_weights(s["delay"], s["gain"], freq) * ~flags[None]
    for j in range(T // acc):
        i = max(k for k, st in enumerate(starts) if st <= j)
        want = brute_image(X[j * acc:(j + 1) * acc], xyz, freq, lm, ("I",), weights=wc * g[i])[:, 0]
        err = np.abs(got[j] - want).max() / np.abs(want).max()
        assert err < 1e-5, (j, err)
    assert img.img_stats["solutions_applied"] == 3
    assert img.img_stats["operator_builds"] == 1 and img.img_stats["operator_reweights"] == 3


def test_a_solution_that_flags_another_input_lets_the_old_operator_go_before_the_new_is_built(monkeypatch):
    """A solution that flags another input needs a new operator (N_A and the kept antennas change): the old
    one is let go before the new is built, so that a whole band's (15 GB on a GPU) is not held twice at
    each such solution; the images are the float64 definition with each solution (as above)."""
    import gc
    import weakref

    from bf_epic_blocks import imaging
    from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, bfp
    from bf_epic_blocks.imaging import dft
    from bf_epic_blocks.imaging.calibration import GainTable
    from bf_epic_blocks.runtime.dtypes import pack_ci4
    from test_blocks import DT, TPF, efield_header, station
    rng = np.random.default_rng(9)
    nst, nchan, T, acc = 12, 3, 160, 40
    xyz = rng.normal(0, 20, (nst, 3)) * [1, 1, 0.05]
    freq = 60e6 + 25e3 * np.arange(nchan)
    X = rng.integers(-8, 8, (T, nchan, nst, 2)) + 1j * rng.integers(-8, 8, (T, nchan, nst, 2))
    lm = imaging.lm_grid(8).lm
    t0 = 10**12
    g = rng.uniform(0.5, 1.5, (2, nchan, nst, 2)) * np.exp(2j * np.pi * rng.random((2, nchan, nst, 2)))
    g[1, :, 5, 0] = 0                                                    # the second solution flags an input
    table = GainTable([t0, t0 + 2 * acc * TPF], g)
    hdr = efield_header("fold", t0, freq, DT, station(dict(xyz=xyz, flags=np.zeros((nst, 2), bool)), False),
                        dtype="ci4")
    built, alive_at_build = [], []
    init = dft.DFTOperator.__init__

    def recording(self, *a, **k):
        gc.collect()
        alive_at_build.append(sum(r() is not None for r in built))
        init(self, *a, **k)
        built.append(weakref.ref(self))
    monkeypatch.setattr(dft.DFTOperator, "__init__", recording)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=80)
        img = DFTImagerBlock(src, lm, acc, products=["I"], gains=table, pattern=False, precision="fp64")
        sink = ArraySinkBlock(img)
        p.run()
    got = sink.result(0)[:, :, 0]
    for j in range(T // acc):
        want = brute_image(X[j * acc:(j + 1) * acc], xyz, freq, lm, ("I",), weights=g[j // 2])[:, 0]
        assert np.abs(got[j] - want).max() < 1e-6 * np.abs(want).max(), j          # (float32 images)
    assert img.img_stats["solutions_applied"] == 2 and len(built) == img.img_stats["operator_builds"] >= 2
    assert alive_at_build == [0] * len(built)


@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_gpu_a_new_solution_does_not_wait_for_the_queued_images():
    """Folding a solution in is queued behind the images already asked for, never waited on: the imager's
    thread runs ahead of its GPU work by up to the rings' depth, and a wait at each solution drains that
    queue and leaves the GPU idle while the host forms the new operator (the live solver's cost at the
    whole band). A kernel that spins ~0.5 s stands for the queued images; reweight returns while it
    still runs, and the images after it see the new gains."""
    import cupy as cp
    xyz, freq, q, rng = _scene(9, nant=48, T=64)
    lm = _pixels(rng, 8)
    w_a, w_b = _gains(rng, 3, 48), _gains(rng, 3, 48)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2",
                     weights=cp.asarray(w_a))
    acc = op.accumulator(("I",), method="direct")
    acc.images(cp.asarray(q), 16)
    spin = cp.RawKernel(r"""extern "C" __global__ void spin(long long n) {
        long long t0 = clock64(); while (clock64() - t0 < n) { } }""", "spin")
    rate = cp.cuda.Device().attributes["ClockRate"] * 1e3                      # cycles per second
    stream = cp.cuda.Stream(non_blocking=True)
    with stream:
        cp.cuda.get_current_stream().synchronize()
        spin((1,), (1,), (np.int64(0.5 * rate),))
        assert op.reweight(w_b) is True                  # host weights, as the imager's solution hook hands
        assert not stream.done, "reweight waited for the queued work"
        got = acc.images(cp.asarray(q), 16).get()
    truth = np.stack([brute_image(_cplx(q)[i * 16:(i + 1) * 16], xyz, freq, lm, ("I",), weights=w_b) for i in range(4)])
    err = np.abs(got - truth).max() / np.abs(truth).max()
    assert err < BOUND["i8x2"], err
