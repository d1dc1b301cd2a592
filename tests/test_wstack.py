"""w-stacking, covariance w-gridding and MOFF imagers against a float64 brute-force DFT.

The truth here is this file's own DFT (:func:`brute_image`), written from PHYSICS.md:
F_k(t) = sum_a w_a x_a(t) exp(-2 pi i nu (l x + m y + n z)/c) / N_A, I = mean_t |F|^2,
XY = mean_t F_X F_Y^*, Stokes I = XX + YY, Q = XX - YY, U = 2 Re XY, V = -2 Im XY.
"""
import numpy as np
import pytest

from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.imaging.kernels import es_fourier, es_kernel, es_params, good_fft_size
from bf_epic_blocks.imaging.moff import moff_image
from bf_epic_blocks.imaging.pixels import lm_grid
from bf_epic_blocks.imaging.wstack import FieldPlan, cov_wgrid_image, wstack_image

C = 299792458.0
# Stated bound (module docstring of wstack): max |I - I_DFT| / max I_DFT <= BOUND * epsilon at sigma = 2.
BOUND = 4.0


# ----------------------------------------------------------------------------- truth
def brute_fields(efield, xyz, freq, lm, weights=None, zero_z=False):
    """(nchan, npol, npix, ntime) complex128 fields, plain float64 DFT."""
    T, nc, A, npol = efield.shape
    l, m = lm[:, 0], lm[:, 1]
    n = np.sqrt(1.0 - l ** 2 - m ** 2)
    z = np.zeros(A) if zero_z else xyz[:, 2]
    w = np.ones((nc, A, npol)) if weights is None else np.broadcast_to(weights, (nc, A, npol))
    out = np.zeros((nc, npol, lm.shape[0], T), np.complex128)
    for c in range(nc):
        k = freq[c] / C
        ph = np.exp(-2j * np.pi * k * (np.outer(l, xyz[:, 0]) + np.outer(m, xyz[:, 1]) + np.outer(n, z)))
        for p in range(npol):
            act = w[c, :, p] != 0
            D = ph[:, act] * w[c, act, p] / act.sum()
            out[c, p] = D @ efield[:, c, act, p].astype(np.complex128).T
    return out


def brute_image(efield, xyz, freq, lm, weights=None, zero_z=False, products="XX", remove_autocorr=False):
    F = brute_fields(efield, xyz, freq, lm, weights, zero_z)
    T, nc, A, npol = efield.shape
    xx = (np.abs(F[:, 0]) ** 2).mean(-1)
    yy = (np.abs(F[:, 1]) ** 2).mean(-1) if npol == 2 else None
    xy = (F[:, 0] * F[:, 1].conj()).mean(-1) if npol == 2 else None
    if remove_autocorr:
        w = np.ones((nc, A, npol)) if weights is None else np.broadcast_to(weights, (nc, A, npol))
        nact = (w != 0).sum(1)                                           # (nc, npol)
        y = efield.astype(np.complex128) * (w / nact[:, None, :])[None]  # (T, nc, A, npol)
        xx = xx - (np.abs(y[..., 0]) ** 2).sum(-1).mean(0)[:, None]
        if npol == 2:
            yy = yy - (np.abs(y[..., 1]) ** 2).sum(-1).mean(0)[:, None]
            xy = xy - (y[..., 0] * y[..., 1].conj()).sum(-1).mean(0)[:, None]
    table = {"XX": lambda: xx, "YY": lambda: yy, "I": lambda: xx + yy, "Q": lambda: xx - yy,
             "U": lambda: 2 * xy.real, "V": lambda: -2 * xy.imag}
    names = ("I", "Q", "U", "V") if products == "stokes" else tuple(products.split(","))
    return np.stack([table[p]() for p in names], axis=1)


def point_sky(xyz, freq, ntime, rng, srcs=None, npol=1, noise=0.05):
    """Incoherent point sources (l, m) seen with the sigma = +1 convention, plus a little noise."""
    if srcs is None:
        srcs = np.array([[0.3, 0.2], [-0.5, 0.1], [0.1, -0.6], [0.6, 0.55], [-0.2, -0.3]])
    s = np.c_[srcs, np.sqrt(1 - (srcs ** 2).sum(1))]
    amp = rng.normal(size=(ntime, len(s), npol)) + 1j * rng.normal(size=(ntime, len(s), npol))
    if npol == 2:  # partially polarised: mix the pols so XY is non-zero
        amp[..., 1] = 0.6 * amp[..., 1] + 0.5 * amp[..., 0]
    out = np.zeros((ntime, len(freq), xyz.shape[0], npol), np.complex128)
    for c, f in enumerate(freq):
        ph = np.exp(+2j * np.pi * f / C * (xyz @ s.T))                 # (A, S)
        out[:, c] = np.einsum("as,tsp->tap", ph, amp)
    out += noise * (rng.normal(size=out.shape) + 1j * rng.normal(size=out.shape))
    return out


def cloud(rng, nant=32):
    return rng.normal(size=(nant, 3)) * 20.0             # strongly non-coplanar: sigma 20 m in z too


def lwasv_like(rng, ncore=64):
    r = 50.0 * np.sqrt(rng.uniform(size=ncore))
    th = rng.uniform(0, 2 * np.pi, ncore)
    core = np.c_[r * np.cos(th), r * np.sin(th), rng.uniform(-0.5, 0.5, ncore)]
    return np.vstack([core, [-300.0, 0.0, 10.0]])          # outrigger: 300 m West, 10 m up


def relerr(img, ref):
    return float(np.max(np.abs(np.asarray(img, np.float64) - ref)) / np.max(np.abs(ref)))


# ----------------------------------------------------------------------------- kernels
def test_es_fourier_matches_dense_quadrature():
    kern = es_params(1e-6)
    z = np.linspace(-kern.W / 2, kern.W / 2, 400001)
    phi = es_kernel(z, kern.W, kern.beta)
    for f in (0.0, 0.1, 0.25):
        dense = np.trapezoid(phi * np.cos(2 * np.pi * z * f), z)
        assert abs(es_fourier(f, kern.W, kern.beta) - dense) < 1e-9 * dense


def test_es_params_formulas_and_errors():
    assert [es_params(e).W for e in (1e-2, 1e-4, 1e-6)] == [3, 5, 7]
    assert es_params(1e-4).beta == pytest.approx(2.30 * 5)
    assert es_params(1e-4, sigma=1.5).W == 6
    with pytest.raises(ValueError, match="epsilon"):
        es_params(0.0)
    with pytest.raises(ValueError, match="sigma"):
        es_params(1e-3, sigma=1.0)
    assert good_fft_size(129) == 144 and good_fft_size(121) == 128 and good_fft_size(128) == 128 and good_fft_size(7) == 8


# ----------------------------------------------------------------------------- E-field w-stacking
@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-6])
@pytest.mark.parametrize("direct", ["auto", None])
def test_wstack_gaussian_cloud(eps, direct):
    rng = np.random.default_rng(1)
    xyz = cloud(rng)
    freq = np.array([60e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 4, rng)
    ref = brute_image(e, xyz, freq, grid.lm)
    img = wstack_image(e, xyz, freq, grid, epsilon=eps, direct=direct)
    assert img.shape == (1, 1, grid.npix)
    assert img.dtype == (np.float32 if eps >= 1e-5 else np.float64)
    assert relerr(img, ref) <= BOUND * eps
    # the w term matters here: ignoring it is wrong by far more than epsilon
    assert relerr(moff_image(e, xyz, freq, grid, epsilon=1e-4), ref) > 0.05


@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-6])
def test_wstack_lwasv_core_plus_outrigger(eps):
    rng = np.random.default_rng(2)
    xyz = lwasv_like(rng)
    freq = np.array([74e6])
    grid = lm_grid(32)                        # outrigger: 74 wavelengths, far beyond the +-8 of the grid
    e = point_sky(xyz, freq, 3, rng)
    ref = brute_image(e, xyz, freq, grid.lm)
    for direct in ("auto", None):             # None: the outrigger is gridded by periodic wrapping
        img = wstack_image(e, xyz, freq, grid, epsilon=eps, direct=direct)
        assert relerr(img, ref) <= BOUND * eps, direct
    plan = FieldPlan(xyz * freq[0] / C, grid, epsilon=eps, direct="auto")
    assert plan.ndirect == 1 and plan.direct_mask[-1]   # auto peels exactly the outrigger off in w


def test_wrapping_is_exact_for_one_far_antenna():
    """A lone antenna at u = 74 wavelengths (wrapped many times) reproduces its exact phase ramp."""
    grid = lm_grid(32)
    uvw = np.array([[-74.0, 13.3, 2.5]])
    plan = FieldPlan(uvw, grid, epsilon=1e-10, direct=None)
    F = plan.apply(np.ones((1, 1), np.complex128))[:, 0]
    l, m = grid.lm[:, 0], grid.lm[:, 1]
    n = np.sqrt(1 - l ** 2 - m ** 2)
    exact = np.exp(-2j * np.pi * (uvw[0, 0] * l + uvw[0, 1] * m + uvw[0, 2] * n))
    assert np.max(np.abs(F - exact)) < 1e-8


@pytest.mark.parametrize("fn", ["wstack", "moff", "cov_xp", "cov_ducc0"])
def test_point_source_orientation(fn):
    """A source East of zenith (l = +0.5) peaks at +l; one North (m = +0.4) at +m."""
    if fn == "cov_ducc0":
        pytest.importorskip("ducc0")
    rng = np.random.default_rng(3)
    xyz = lwasv_like(rng, 48)
    freq = np.array([50e6])
    grid = lm_grid(32)
    f = {"wstack": lambda e: wstack_image(e, xyz, freq, grid),
         "moff": lambda e: moff_image(e, xyz, freq, grid),
         "cov_xp": lambda e: cov_wgrid_image(e, xyz, freq, grid, backend="xp"),
         "cov_ducc0": lambda e: cov_wgrid_image(e, xyz, freq, grid, backend="ducc0")}[fn]
    for src in ([0.5, 0.0], [0.0, 0.375]):
        e = point_sky(xyz, freq, 2, rng, srcs=np.array([src]), noise=0.0)
        k = int(np.argmax(f(e)[0, 0]))
        assert np.allclose(grid.lm[k], src, atol=grid.cell / 2 + 1e-12), (src, grid.lm[k])


def test_moff_equals_dft_with_z_zero():
    rng = np.random.default_rng(4)
    xyz = lwasv_like(rng, 40)
    freq = np.array([40e6, 74e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 3, rng)
    for eps in (1e-2, 1e-6):
        img = moff_image(e, xyz, freq, grid, epsilon=eps)
        assert relerr(img, brute_image(e, xyz, freq, grid.lm, zero_z=True)) <= BOUND * eps


def test_wstack_stokes_weights_flags_autocorr():
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(24, 3)) * np.array([20.0, 20.0, 3.0])
    freq = np.array([40e6, 65e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 4, rng, npol=2)
    w = np.exp(1j * rng.uniform(0, 6, (2, 24, 2))) * rng.uniform(0.5, 1.5, (2, 24, 2))
    w[0, 3, 0] = 0
    w[1, 5, 1] = 0
    w[:, 7, :] = 0
    for ra in (False, True):
        ref = brute_image(e, xyz, freq, grid.lm, weights=w, products="stokes", remove_autocorr=ra)
        img = wstack_image(e, xyz, freq, grid, epsilon=1e-6, products="stokes", weights=w, remove_autocorr=ra)
        assert img.shape == (2, 4, grid.npix)
        assert relerr(img, ref) <= BOUND * 1e-6
        img = cov_wgrid_image(e, xyz, freq, grid, epsilon=1e-6, products="stokes", weights=w,
                              remove_autocorr=ra, backend="xp")
        assert relerr(img, ref) <= BOUND * 1e-6


# ----------------------------------------------------------------------------- covariance route
@pytest.mark.parametrize("backend", ["xp", "ducc0"])
@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-6])
def test_cov_wgrid_equals_dft(backend, eps):
    if backend == "ducc0":
        pytest.importorskip("ducc0")
    rng = np.random.default_rng(6)
    xyz = lwasv_like(rng, 40)
    freq = np.array([74e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 6, rng, npol=2)
    ref = brute_image(e, xyz, freq, grid.lm, products="XX,YY,U,V")
    img = cov_wgrid_image(e, xyz, freq, grid, epsilon=eps, products=("XX", "YY", "U", "V"), backend=backend)
    assert relerr(img, ref) <= BOUND * eps


def test_cov_wgrid_cloud():
    rng = np.random.default_rng(7)
    xyz = cloud(rng, 24)
    freq = np.array([60e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 4, rng)
    ref = brute_image(e, xyz, freq, grid.lm)
    assert relerr(cov_wgrid_image(e, xyz, freq, grid, epsilon=1e-4, backend="xp"), ref) <= BOUND * 1e-4


def test_agrees_with_package_dirty_image():
    dft = pytest.importorskip("bf_epic_blocks.imaging.dft")
    rng = np.random.default_rng(8)
    xyz = cloud(rng, 20)
    freq = np.array([55e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 3, rng)
    ref = dft.dirty_image(e, xyz, freq, grid.lm, precision="fp64", method="direct")
    assert relerr(ref, brute_image(e, xyz, freq, grid.lm)) < 1e-12
    assert relerr(wstack_image(e, xyz, freq, grid, epsilon=1e-6), ref) <= BOUND * 1e-6


# ----------------------------------------------------------------------------- bad input
def test_bad_inputs_raise():
    grid = lm_grid(32)
    xyz = np.zeros((4, 3))
    e = np.ones((2, 1, 4, 1), np.complex64)
    f = np.array([50e6])
    with pytest.raises(TypeError, match="complex"):
        wstack_image(e.real, xyz, f, grid)
    with pytest.raises(ValueError, match="ntime, nchan, nant, npol"):
        wstack_image(e[0], xyz, f, grid)
    with pytest.raises(ValueError, match="xyz_m"):
        wstack_image(e, xyz[:3], f, grid)
    with pytest.raises(ValueError, match="freq_hz"):
        wstack_image(e, xyz, np.array([50e6, 60e6]), grid)
    with pytest.raises(ValueError, match="flagged"):
        wstack_image(e, xyz, f, grid, weights=np.zeros(4))
    with pytest.raises(ValueError, match="weights"):
        moff_image(e, xyz, f, grid, weights=np.ones(5))
    with pytest.raises(TypeError, match="LMGrid"):
        cov_wgrid_image(e, xyz, f, grid.lm)
    with pytest.raises(ValueError, match="epsilon"):
        wstack_image(e, xyz, f, grid, epsilon=0.7)
    with pytest.raises(ValueError, match="backend"):
        cov_wgrid_image(e, xyz, f, grid, backend="fftw")
    with pytest.raises(ValueError, match="ducc0"):
        cov_wgrid_image(e, xyz, f, lm_grid(16), backend="ducc0")


# ----------------------------------------------------------------------------- GPU (CuPy)
gpu = pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")


@pytest.mark.gpu
@gpu
@pytest.mark.parametrize("eps", [1e-2, 1e-4, 1e-6])
def test_gpu_wstack_moff_cov(eps):
    import cupy as cp
    rng = np.random.default_rng(9)
    xyz = lwasv_like(rng)
    freq = np.array([60e6, 74e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 4, rng, npol=2)
    ref = brute_image(e, xyz, freq, grid.lm, products="stokes")
    ref0 = brute_image(e, xyz, freq, grid.lm, products="stokes", zero_z=True)
    ed = cp.asarray(e.astype(np.complex64 if eps >= 1e-5 else np.complex128))
    img = wstack_image(ed, xyz, freq, grid, epsilon=eps, products="stokes")
    assert isinstance(img, cp.ndarray)
    assert relerr(img.get(), ref) <= BOUND * eps
    img = cov_wgrid_image(ed, xyz, freq, grid, epsilon=eps, products="stokes")
    assert isinstance(img, cp.ndarray)
    assert relerr(img.get(), ref) <= BOUND * eps
    img = moff_image(ed, xyz, freq, grid, epsilon=eps, products="stokes")
    assert relerr(img.get(), ref0) <= BOUND * eps


@pytest.mark.gpu
@gpu
def test_gpu_cloud_direct_none():
    import cupy as cp
    rng = np.random.default_rng(10)
    xyz = cloud(rng)
    freq = np.array([60e6])
    grid = lm_grid(32)
    e = point_sky(xyz, freq, 4, rng)
    ref = brute_image(e, xyz, freq, grid.lm)
    img = wstack_image(cp.asarray(e), xyz, freq, grid, epsilon=1e-4, direct=None)
    assert relerr(img.get(), ref) <= BOUND * 1e-4
