"""Each imaging route alone (bf_epic_blocks.imaging.routes) against the float64 image from the definition,
I = mean_t |D x|^2 (tests/truth.py), through the one interface every route has: add, result, images, reset."""
import numpy as np
import pytest

from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.imaging.dft import DFTOperator
from bf_epic_blocks.imaging.routes import (CovarianceRoute, DirectRoute, FusedIntegerRoute, ImageAccumulator,
                                           make_route)
from truth import brute_image

GPU = pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")


def scene(nant=12, T=24, nchan=2, seed=3):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 40, (nant, 3)) * [1, 1, 0.1]
    freq = 50e6 + 7e6 * np.arange(nchan)
    lm = np.array([[0.0, 0.0], [0.3, -0.2], [-0.6, 0.5], [0.05, 0.9], [0.7, 0.7]])
    Q = rng.integers(-8, 8, (T, nchan, nant, 2, 2)).astype(np.int8)    # 4-bit (re, im) pairs
    w = np.ones((nchan, nant, 2))
    w[:, 3, :] = 0                  # one antenna flagged everywhere
    w[1, 5, 1] = 0                  # one antenna-pol flagged in one channel
    return xyz, freq, lm, Q, w


def as_complex(Q):
    return Q[..., 0].astype(np.float64) + 1j * Q[..., 1]


@pytest.mark.parametrize("cls,method", [(DirectRoute, "direct"), (CovarianceRoute, "covariance")])
@pytest.mark.parametrize("ints", [False, True])
@pytest.mark.parametrize("products,remove_autocorr", [(("XX", "YY"), False), ("stokes", False), ("full", True)])
def test_each_route_alone_equals_the_definition(cls, method, ints, products, remove_autocorr):
    xyz, freq, lm, Q, w = scene()
    X = as_complex(Q)
    data = Q if ints else X.astype(np.complex128)
    op = DFTOperator(xyz, freq, lm, npol=2, weights=w, precision="fp64")
    route = make_route(op, products, method=method, remove_autocorr=remove_autocorr)
    assert type(route) is cls and route.method == method
    ref = brute_image(X, xyz, freq, lm, route.products, remove_autocorr=remove_autocorr, weights=w)
    tol = 1e-10 * np.abs(ref).max()
    # one integration added in uneven pieces
    for a, b in ((0, 5), (5, 6), (6, 24)):
        route.add(data[a:b])
    assert route.ntime == 24
    np.testing.assert_allclose(route.result(), ref, rtol=0, atol=tol)
    # one image per 8 samples in one call, the integration in progress left as it was
    route.reset()
    route.add(data[:3])
    imgs = route.images(data, 8)
    assert imgs.shape == (3, 2, len(route.products), len(lm)) and route.ntime == 3
    for g in range(3):
        sl = slice(8 * g, 8 * (g + 1))
        ref_g = brute_image(X[sl], xyz, freq, lm, route.products, remove_autocorr=remove_autocorr, weights=w)
        np.testing.assert_allclose(imgs[g], ref_g, rtol=0, atol=1e-10 * np.abs(ref_g).max())


def test_factory_resolves_auto_and_keeps_the_public_name():
    xyz, freq, lm, Q, w = scene()
    op = DFTOperator(xyz, freq, lm, npol=2, weights=w, precision="fp64")
    assert type(ImageAccumulator(op, method="covariance")) is CovarianceRoute
    assert type(op.accumulator(method="auto", ntime_hint=1)) is DirectRoute
    assert make_route(op, method="auto", ntime_hint=10**6).method in ("direct", "covariance")
    with pytest.raises(ValueError, match="method must be one of"):
        make_route(op, method="gridded")


def test_a_route_without_samples_says_so_and_takes_no_ci4_bytes():
    xyz, freq, lm, Q, w = scene()
    op = DFTOperator(xyz, freq, lm, npol=2, weights=w, precision="fp64")
    for method in ("direct", "covariance"):
        route = make_route(op, method=method)
        assert not route.takes_ci4
        with pytest.raises(ValueError, match="zero time samples"):
            route.result()
        with pytest.raises(ValueError, match="ci4 bytes"):
            route.images(np.zeros((16, 2, 12, 2), np.uint8), 16, ci4=True)


@GPU
@pytest.mark.gpu
def test_gpu_fused_integer_route_alone_equals_the_definition():
    import cupy as cp
    xyz, freq, lm, Q, w = scene(nant=40, T=64)
    w[...] = 1
    X = as_complex(Q)
    op = DFTOperator(cp.asarray(xyz), cp.asarray(freq), cp.asarray(lm), npol=2, precision="i8x2")
    route = make_route(op, ("XX", "YY"))
    assert type(route) is FusedIntegerRoute and route.method == "direct" and route.takes_ci4
    for a, b in ((0, 48), (48, 64)):
        route.add(cp.asarray(Q[a:b]))
    ref = brute_image(X, xyz, freq, lm, route.products)
    assert np.abs(route.result().get() - ref).max() / np.abs(ref).max() <= 4e-5
    imgs = route.images(cp.asarray(Q), 16).get()
    for g in range(4):
        ref_g = brute_image(X[16 * g:16 * (g + 1)], xyz, freq, lm, route.products)
        assert np.abs(imgs[g] - ref_g).max() / np.abs(ref_g).max() <= 4e-5
    with pytest.raises(ValueError, match="covariance route"):
        make_route(op, method="covariance")
