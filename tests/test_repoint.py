"""DFTOperator.repoint: an operator's pixels moved in place (a tracking imager, the watchlist) images the
new directions as the float64 definition does, through the routes made before the move, the CUDA graphs
captured before it, and the fused modes' int8 pieces and grid factors; an operator refuses what it cannot
move to."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging.dft import DFTOperator
from conftest import HAVE_GPU
from truth import brute_image

GPU = [pytest.mark.gpu, pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")]
#: error bounds against float64 on these small scenes (each mode's own, as the other tests use)
BOUND = {"fp64": 1e-12, "fp32": 1e-5, "fp16x3": 1e-5, "i8x2": 4e-5}


def _scene(seed=0, nant=24, nchan=3, T=64):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 40, (nant, 3)) * [1, 1, 0.05]
    freq = 50e6 + 7e6 * np.arange(nchan)
    q = rng.integers(-8, 8, (T, nchan, nant, 2, 2)).astype(np.int8)
    return xyz, freq, q, rng


def _pixels(rng, k):
    """k directions well above the horizon."""
    r = np.sqrt(rng.uniform(0, 0.8, k))
    a = rng.uniform(0, 2 * np.pi, k)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def _pattern(kind, lm, nchan, nant, rng):
    """A voltage pattern for pixels ``lm``: None, one per pixel (antenna-independent) or per pixel and
    antenna; a smooth function of direction, so that moving the pixels changes it."""
    if kind is None:
        return None
    l, m = lm[:, 0], lm[:, 1]
    pix = (1.0 - 0.3 * l * l - 0.2 * m * m)[None, :, None, None] * np.array([1.0, 0.9])[None, None, None, :]
    pix = pix * (1.0 + 0.01 * np.arange(nchan))[:, None, None, None]
    if kind == "pixel":
        return pix                                                              # (C, K, 1, P)
    per_ant = 1.0 + 0.05 * np.exp(1j * np.arange(nant))[None, None, :, None] * l[None, :, None, None]
    return pix * per_ant                                                        # (C, K, A, P)


def _cplx(q):
    return q[..., 0].astype(np.float64) + 1j * q[..., 1]


@pytest.mark.parametrize("precision", ["fp64", "fp32"])
@pytest.mark.parametrize("kind", [None, "pixel", "antenna"])
@pytest.mark.parametrize("method", ["direct", "covariance"])
def test_repointed_operator_images_the_new_pixels_as_the_float64_definition(precision, kind, method):
    """Routes made before the move (and images made with them, so every derived form exists) give the new
    pixels' images: against the float64 sum, and equal to an operator built for them."""
    xyz, freq, q, rng = _scene(1)
    w = np.where(np.arange(24) == 3, 0.0, 1.0)[None, :, None] * np.ones((3, 1, 2))
    w[1, 7, 0] = 0.0                                        # a partial flag: one channel-pol of one antenna
    lm_a, lm_b = _pixels(rng, 5), _pixels(rng, 5)
    X = _cplx(q)
    prods = ("I", "V") if method == "covariance" else ("I",)
    op = DFTOperator(xyz, freq, lm_a, npol=2, weights=w, pattern=_pattern(kind, lm_a, 3, 24, rng),
                     precision=precision)
    route = op.accumulator(prods, method=method)
    route.add(X)
    before = route.result()
    truth_a = brute_image(X, xyz, freq, lm_a, prods, weights=w, pattern=_pattern(kind, lm_a, 3, 24, rng))
    assert np.abs(before - truth_a).max() / np.abs(truth_a).max() < BOUND[precision]
    op.repoint(lm_b, pattern=_pattern(kind, lm_b, 3, 24, rng))
    route.reset()
    route.add(X)
    after = route.result()
    truth_b = brute_image(X, xyz, freq, lm_b, prods, weights=w, pattern=_pattern(kind, lm_b, 3, 24, rng))
    err = np.abs(after - truth_b).max() / np.abs(truth_b).max()
    assert err < BOUND[precision], err
    assert np.abs(truth_b - truth_a).max() > 100 * BOUND[precision] * np.abs(truth_b).max()   # they moved
    fresh = DFTOperator(xyz, freq, lm_b, npol=2, weights=w, pattern=_pattern(kind, lm_b, 3, 24, rng),
                        precision=precision).image(X, prods, method=method)
    np.testing.assert_allclose(after, fresh, rtol=1e-6 if precision == "fp32" else 1e-13, atol=0)
    np.testing.assert_array_equal(op.pixels_lm, lm_b)


def test_repoint_refuses_another_pixel_count_or_pattern_kind():
    xyz, freq, _, rng = _scene(2)
    lm = _pixels(rng, 4)
    op = DFTOperator(xyz, freq, lm, npol=2)
    with pytest.raises(ValueError, match="5 pixels given to an operator of 4"):
        op.repoint(_pixels(rng, 5))
    with pytest.raises(ValueError, match="not of the kind"):
        op.repoint(lm, pattern=_pattern("antenna", lm, 3, 24, rng))
    with pytest.raises(ValueError):
        op.repoint(np.array([[0.9, 0.9]] * 4))                 # below the horizon: check_lm's error
    # a refused move leaves the operator as it was
    np.testing.assert_array_equal(op.pixels_lm, lm)


@pytest.mark.parametrize("precision, method", [("fp32", "direct"), ("fp16x3", "covariance"), ("i8x2", "direct")],
                         ids=["fp32", "fp16x3", "i8x2"])
@pytest.mark.parametrize("kind", [None, "pixel"])
@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_gpu_replayed_graphs_see_the_moved_operator(precision, method, kind):
    """On the GPU, images replayed from CUDA graphs captured before the move (op.image, ci4 bytes decoded
    inside the graph as the whole-band imager replays them) and batched route images (the fused modes'
    int8 pieces) equal the float64 definition at the new pixels."""
    import cupy as cp
    from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs
    xyz, freq, q, rng = _scene(3, nant=48, T=64)
    lm_a, lm_b = _pixels(rng, 10), _pixels(rng, 10)
    X = _cplx(q)
    packed = cp.asarray(pack_ci4(X))

    def decode(b):
        return unpack_int8_pairs(b, "ci4")

    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm_a), npol=2, precision=precision,
                     pattern=None if kind is None else cp.asarray(_pattern(kind, lm_a, 3, 48, rng)))
    acc = op.accumulator(("I",), method=method)
    for _ in range(3):                                         # eager, capture, replay
        op.image(packed[:16], ("I",), method=method, decode=decode, static_out=True)
    acc.images(cp.asarray(q), 16)
    op.repoint(cp.asarray(lm_b), pattern=None if kind is None else cp.asarray(_pattern(kind, lm_b, 3, 48, rng)))
    pb = _pattern(kind, lm_b, 3, 48, rng)
    truth = np.stack([brute_image(X[i * 16:(i + 1) * 16], xyz, freq, lm_b, ("I",), pattern=pb) for i in range(4)])
    replayed = np.stack([op.image(packed[i * 16:(i + 1) * 16], ("I",), method=method, decode=decode,
                                  static_out=True).get() for i in range(4)])
    assert op.graphs is not None and op.graphs.replays >= 4
    batched = acc.images(cp.asarray(q), 16).get()
    for got in (replayed, batched):
        err = np.abs(got - truth).max() / np.abs(truth).max()
        assert err < BOUND[precision], err


@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_gpu_fused_images_on_the_grid_after_a_move_use_the_new_factors():
    """The fused kernel's images placed on a grid multiply by factors made from the int8 pieces' scales and
    the pattern: a move forms them again in place (an operator on 'grid' pixels moved to another set of
    as many directions, placed onto the same cells)."""
    import cupy as cp
    from bf_epic_blocks.imaging.pixels import GridPlacement
    xyz, freq, q, rng = _scene(4, nant=48, T=64)
    grid = imaging.lm_grid(12)
    lm_a = grid.lm
    lm_b = lm_a * 0.9 + 0.02                                   # as many directions, elsewhere
    X = _cplx(q)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm_a), npol=2, precision="i8x2",
                     pattern=cp.asarray(_pattern("pixel", lm_a, 3, 48, rng)))
    acc = op.accumulator(("I",), method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, cp)
    out = cp.zeros((4, 3, 1, grid.size ** 2), cp.float32)
    acc.images(cp.asarray(q), 16, place=place, out=out)
    op.repoint(cp.asarray(lm_b), pattern=cp.asarray(_pattern("pixel", lm_b, 3, 48, rng)))
    out[...] = -1
    acc.images(cp.asarray(q), 16, place=place, out=out)
    pb = _pattern("pixel", lm_b, 3, 48, rng)
    truth = np.stack([brute_image(X[i * 16:(i + 1) * 16], xyz, freq, lm_b, ("I",), pattern=pb) for i in range(4)])
    got = out.get()[..., grid.mask.ravel()]
    err = np.abs(got - truth).max() / np.abs(truth).max()
    assert err < BOUND["i8x2"], err


@pytest.mark.parametrize("device, precision", [("cpu", "fp64"), pytest.param("gpu", "fp32", marks=GPU),
                                               pytest.param("gpu", "i8x2", marks=GPU)])
def test_directions_beside_a_grid_are_imaged_and_moved_alone_as_the_float64_definition(device, precision):
    """A watchlist's directions after a grid's pixels in one operator (GridPlacement's ``extra``): the grid's
    cells and the directions' own images (``xout``) equal the float64 sum, before and after only the
    directions move (repoint from the first of them): on the GPU through the fused kernel's grid output with
    its second destination (i8x2) and the products kernel's placement (fp32)."""
    from bf_epic_blocks.imaging.pixels import GridPlacement
    xp = np
    if device == "gpu":
        import cupy as xp
    xyz, freq, q, rng = _scene(5, nant=48, T=64)
    grid = imaging.lm_grid(12)
    ng = grid.lm.shape[0]
    dirs_a = np.array([[0.31, -0.22], [0.0, 0.0], [-0.55, 0.4]])            # between cells, the zenith, ...
    dirs_b = dirs_a * 0.8 + [0.013, 0.007]
    X = _cplx(q)
    op = DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(np.concatenate([grid.lm, dirs_a])), npol=2,
                     precision=precision)
    acc = op.accumulator(("I",), method="direct")
    place = GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, xp, extra=len(dirs_a))
    for dirs in (dirs_a, dirs_b):
        if dirs is dirs_b:
            op.repoint(xp.asarray(dirs_b), first=ng)
        out = xp.full((4, 3, 1, grid.size ** 2), -1.0, xp.float32)
        xout = xp.full((4, 3, 1, len(dirs)), -1.0, xp.float32)
        acc.images(xp.asarray(q), 16, place=place.beside(xout), out=out)
        truth = np.stack([brute_image(X[i * 16:(i + 1) * 16], xyz, freq, np.concatenate([grid.lm, dirs]), ("I",))
                          for i in range(4)])
        got_grid = to_host(out)[..., grid.mask.ravel()]
        bound = max(BOUND[precision], 3e-7) * np.abs(truth).max()            # (float32 images)
        assert np.abs(got_grid - truth[..., :ng]).max() < bound
        assert np.abs(to_host(xout) - truth[..., ng:]).max() < bound
        assert np.all(np.isnan(to_host(out)[..., ~grid.mask.ravel()]))
    np.testing.assert_array_equal(to_host(op.pixels_lm), np.concatenate([grid.lm, dirs_b]))
    truth_a = brute_image(X[:16], xyz, freq, dirs_a, ("I",))
    assert np.abs(truth[0, ..., ng:] - truth_a).max() > 100 * bound                          # they moved


def to_host(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_a_placement_beside_the_grid_reads_nothing_back_from_the_device(monkeypatch):
    """Each gulp's placement beside the grid (``beside``: a copy for one call) clears its images and gives
    each pixel's cell without reading the index back from the device: a read-back waits for every image
    queued before it (on a station of two tunings it held the imager's thread 40 ms a gulp), and the forms
    the kernels read are the placement's own, shared by its copies, not made again for each."""
    import cupy as cp

    from bf_epic_blocks.imaging import pixels
    from bf_epic_blocks.imaging.pixels import GridPlacement
    grid = imaging.lm_grid(12)
    index = np.flatnonzero(grid.mask)
    place = GridPlacement(index, grid.size ** 2, cp, extra=3)

    def no_read_back(a):
        raise AssertionError("the placement read an array back from the device")
    monkeypatch.setattr(pixels, "to_numpy", no_read_back, raising=False)
    out = cp.full((2, grid.size ** 2), -1.0, cp.float32)
    bound = [place.beside(cp.zeros((2, 3), cp.float32)) for _ in range(2)]
    bound[0].clear(out)
    assert bound[0].cells is bound[1].cells is place.cells
    np.testing.assert_array_equal(place.cells.get(), np.r_[index, grid.size ** 2 + np.arange(3)])
    host = out.get()
    assert np.all(host[:, index] == 0) and np.all(np.isnan(np.delete(host, index, axis=1)))
