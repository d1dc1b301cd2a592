"""The exact DFT imager against independent float64 truth (tests/truth.py) and point sources."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging import pixels as px
from truth import brute_image, point_source_efield

C = 299792458.0


def to_np(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


def rel_err(got, ref):
    return float(np.nanmax(np.abs(to_np(got) - ref)) / np.nanmax(np.abs(ref)))


@pytest.fixture(scope="module")
def scene():
    """Non-coplanar array: 24 antennas within ~60 m, z spread of metres, plus one 400 m out, 8 m up."""
    rng = np.random.default_rng(42)
    xyz = np.concatenate([rng.normal(0, 25, (23, 3)) * [1, 1, 0.08], [[-400.0, 35.0, 8.0]]])
    freq = np.array([38e6, 74e6, 87.5e6])
    T = 40
    X = rng.normal(size=(T, 3, 24, 2)) + 1j * rng.normal(size=(T, 3, 24, 2))
    # a couple of sources so the image has structure as well as noise
    X += point_source_efield(xyz, freq, 0.3, -0.2, 4.0, T, npol=2, rng=rng)
    lm = np.concatenate([imaging.lm_grid(12).lm, [[0.0, 0.0], [0.999, 0.01]]])
    return xyz, freq, X, lm


@pytest.mark.parametrize("method", ["direct", "covariance"])
@pytest.mark.parametrize("npol", [1, 2])
@pytest.mark.parametrize("remove_autocorr", [False, True])
def test_against_float64_bruteforce(xp, scene, method, npol, remove_autocorr):
    xyz, freq, X, lm = scene
    X = X[..., :npol]
    prods = ("XX",) if npol == 1 else ("XX", "YY", "I", "Q", "U", "V", "XY")
    ref = brute_image(X, xyz, freq, lm, prods, remove_autocorr)
    for precision, tol in (("fp64", 1e-12), ("fp32", 1e-6)):
        img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                  method=method, precision=precision, products=prods,
                                  remove_autocorr=remove_autocorr)
        assert type(img) is type(xp.asarray(X)), "result must stay in the input's namespace"
        assert img.shape == (3, len(prods), len(lm))
        assert img.dtype == (np.float64 if precision == "fp64" else np.float32)
        assert rel_err(img, ref) <= tol, (precision, rel_err(img, ref))


def test_default_products(scene):
    xyz, freq, X, lm = scene
    assert imaging.dirty_image(X[..., :1], xyz, freq, lm).shape == (3, 1, len(lm))
    img = imaging.dirty_image(X, xyz, freq, lm)
    ref = brute_image(X, xyz, freq, lm, ("XX", "YY"))
    assert img.shape == (3, 2, len(lm)) and rel_err(img, ref) < 1e-6


@pytest.mark.parametrize("az,alt", [(0.0, 90.0), (90.0, 60.0), (0.0, 45.0), (200.0, 30.0), (300.0, 2.0)])
def test_point_source_lands_with_known_power(xp, az, alt):
    """A point source of known power lands on its pixel with that power; East is +l, North is +m."""
    rng = np.random.default_rng(7)
    xyz = np.concatenate([rng.uniform(-50, 50, (60, 2)), rng.uniform(-1, 1, (60, 1))], axis=1)
    freq = np.array([74e6])
    (l0, m0), = imaging.lm_from_azalt([az], [alt])
    X = point_source_efield(xyz, freq, l0, m0, power=3.5, ntime=16, npol=2, rng=rng)
    grid = imaging.lm_grid(48)
    lm = np.concatenate([[[l0, m0]], grid.lm])
    img = to_np(imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                    products=("XX", "YY", "I")))
    assert np.argmax(img[0, 2]) == 0, "the brightest pixel must be the source's direction"
    np.testing.assert_allclose(img[0, :, 0], [3.5, 3.5, 7.0], rtol=1e-5)
    # orientation on the grid alone: the brightest grid pixel is the nearest one to (l0, m0)
    k = np.argmax(img[0, 2, 1:])
    if alt < 10:  # at the horizon the nearest kept grid pixel can sit off the stretched main lobe
        return
    assert np.hypot(*(grid.lm[k] - [l0, m0])) < 2.5 * grid.cell
    if az == 90.0:
        assert grid.lm[k, 0] > 0.4 and abs(grid.lm[k, 1]) < 2 * grid.cell, "East must be +l"
    if (az, alt) == (0.0, 45.0):
        assert grid.lm[k, 1] > 0.6 and abs(grid.lm[k, 0]) < 2 * grid.cell, "North must be +m"


def test_wrong_sign_would_fail():
    """Guard that the point-source test can fail: a mirrored source (opposite sigma) is not found."""
    rng = np.random.default_rng(3)
    xyz = np.concatenate([rng.uniform(-50, 50, (60, 2)), np.zeros((60, 1))], axis=1)
    freq = np.array([74e6])
    X = np.conj(point_source_efield(xyz, freq, 0.5, 0.0, 1.0, 8, rng=rng))  # sigma = -1 data
    img = imaging.dirty_image(X, xyz, freq, [[0.5, 0.0], [-0.5, 0.0]])
    assert img[0, 0, 1] > 0.99 and img[0, 0, 0] < 0.2


def test_near_horizon_fp32_stability(xp):
    """n ~ 1e-4 pixels, 5 km baselines, 88 MHz: fp32 within 1e-5 of float64 truth (peak-relative)."""
    rng = np.random.default_rng(11)
    xyz = np.concatenate([rng.uniform(-2500, 2500, (20, 2)), rng.uniform(-5, 5, (20, 1))], axis=1)
    freq = np.array([88e6])
    n = 1e-4
    r = np.sqrt(1 - n * n)
    ang = np.linspace(0, 2 * np.pi, 25, endpoint=False)
    lm = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=-1)
    lm = lm[(lm ** 2).sum(1) <= 1]
    assert np.allclose(px.n_from_lm(lm[:, 0], lm[:, 1]), n, rtol=1e-3)
    X = rng.normal(size=(6, 1, 20, 1)) + 1j * rng.normal(size=(6, 1, 20, 1))
    X += point_source_efield(xyz, freq, lm[3, 0], lm[3, 1], 5.0, 6, rng=rng)
    ref = brute_image(X, xyz, freq, lm, ("XX",))
    for method in ("direct", "covariance"):
        img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                  precision="fp32", method=method)
        assert rel_err(img, ref) <= 1e-5


def test_direct_equals_covariance_fp32(xp, scene):
    xyz, freq, X, lm = scene
    args = (xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm))
    for rm in (False, True):
        d = to_np(imaging.dirty_image(*args, method="direct", products="stokes", remove_autocorr=rm))
        c = to_np(imaging.dirty_image(*args, method="covariance", products="stokes", remove_autocorr=rm))
        assert np.max(np.abs(d - c)) / np.max(np.abs(d)) <= 1e-6


def test_flagged_antenna_is_dropped(xp, scene):
    xyz, freq, X, lm = scene
    X = X.copy()
    X[:, :, 5, :] = np.nan  # a flagged antenna's garbage must not reach the image
    w = np.ones(24)
    w[5] = 0
    keep = np.arange(24) != 5
    for method in ("direct", "covariance"):
        flagged = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                      weights=xp.asarray(w), method=method, products="stokes",
                                      precision="fp64", remove_autocorr=True)
        without = imaging.dirty_image(xp.asarray(X[:, :, keep]), xp.asarray(xyz[keep]), xp.asarray(freq),
                                      xp.asarray(lm), method=method, products="stokes", precision="fp64",
                                      remove_autocorr=True)
        assert np.all(np.isfinite(to_np(flagged)))
        np.testing.assert_allclose(to_np(flagged), to_np(without), rtol=0, atol=1e-12 * float(np.abs(to_np(without)).max()))


def test_partial_flags_and_complex_weights(scene):
    """Per-channel, per-pol flags and complex gains: N_A counts the live antennas of each channel-pol."""
    xyz, freq, X, lm = scene
    rng = np.random.default_rng(5)
    w = (rng.uniform(0.5, 2, (3, 24, 2)) * np.exp(2j * np.pi * rng.random((3, 24, 2))))
    w[1, 3, 0] = 0
    w[:, 7, 1] = 0
    X = X.copy()
    X[:, 1, 3, 0] = np.inf
    prods = ("XX", "YY", "I", "U", "V")
    ref = brute_image(np.where(w[None] == 0, 0, X), xyz, freq, lm, prods, True, weights=w)
    for method in ("direct", "covariance"):
        img = imaging.dirty_image(X, xyz, freq, lm, weights=w, products=prods, method=method,
                                  precision="fp64", remove_autocorr=True)
        assert rel_err(img, ref) <= 1e-12


@pytest.mark.parametrize("per_antenna", [False, True])
def test_voltage_pattern(xp, scene, per_antenna):
    xyz, freq, X, lm = scene
    rng = np.random.default_rng(9)
    shape = (1, len(lm), 24 if per_antenna else 1, 2)
    B = rng.uniform(0.2, 1.0, shape) * np.exp(1j * rng.uniform(0, 1, shape))
    prods = ("XX", "YY", "I", "U", "V")
    ref = brute_image(X, xyz, freq, lm, prods, True, pattern=B)
    for method in ("direct", "covariance"):
        img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                  pattern=xp.asarray(B), products=prods, method=method, precision="fp64",
                                  remove_autocorr=True)
        assert rel_err(img, ref) <= 1e-12


def test_accumulator_spanning_calls_equals_one_call(scene):
    xyz, freq, X, lm = scene
    op = imaging.DFTOperator(xyz, freq, lm, npol=2, precision="fp64")
    whole = op.image(X, "stokes")
    for method in ("direct", "covariance"):
        acc = op.accumulator("stokes", method=method)
        for chunk in np.array_split(X, 3):
            acc.add(chunk)
        assert acc.ntime == X.shape[0]
        np.testing.assert_allclose(acc.result(), whole, rtol=1e-12, atol=1e-12 * np.abs(whole).max())


def test_auto_picks_the_cheaper_route():
    assert imaging.cost.choose_method(1024, 256, 3205, 2) == "covariance"
    assert imaging.cost.choose_method(4, 256, 3205, 2) == "direct"
    op = imaging.DFTOperator(np.zeros((8, 3)), [74e6], [[0, 0]], npol=1)
    assert op.accumulator(method="auto", ntime_hint=1).method == "direct"


def test_errors_name_the_problem(scene):
    xyz, freq, X, lm = scene
    with pytest.raises(ValueError, match=r"pixel 1 .*below the horizon"):
        imaging.dirty_image(X, xyz, freq, [[0, 0], [0.9, 0.9]])
    with pytest.raises(ValueError, match="xyz_m must be shaped"):
        imaging.dirty_image(X, xyz[:, :2], freq, lm)
    with pytest.raises(ValueError, match="does not match the operator"):
        imaging.dirty_image(X, xyz[:5], freq, lm)
    with pytest.raises(ValueError, match="every antenna is flagged"):
        imaging.dirty_image(X, xyz, freq, lm, weights=np.zeros(24))
    with pytest.raises(ValueError, match="method must be one of"):
        imaging.dirty_image(X, xyz, freq, lm, method="fast")
    with pytest.raises(ValueError, match="precision must be one of"):
        imaging.dirty_image(X, xyz, freq, lm, precision="fp8")
    if isinstance(X, np.ndarray):   # the CPU has no tensor cores: a clear error, not a silent fp32
        with pytest.raises(ValueError, match="needs tensor cores"):
            imaging.dirty_image(X, xyz, freq, lm, precision="fp16")
    with pytest.raises(ValueError, match="needs two polarisations"):
        imaging.dirty_image(X[..., :1], xyz, freq, lm, products="stokes")
    with pytest.raises(TypeError, match="must be complex"):
        imaging.dirty_image(np.abs(X), xyz, freq, lm)
    with pytest.raises(ValueError, match="freq_hz must be finite and positive"):
        imaging.dirty_image(X, xyz, -freq, lm)


def test_all_flagged_channel_is_nan_not_zero(scene):
    xyz, freq, X, lm = scene
    w = np.ones((3, 24, 2))
    w[2] = 0
    img = imaging.dirty_image(X, xyz, freq, lm, weights=w, products="stokes")
    assert np.all(np.isnan(img[2])) and np.all(np.isfinite(img[:2]))


def test_pixel_helpers():
    g = imaging.lm_grid(64)
    assert 3150 < g.npix < 3260 and g.mask.shape == (64, 64)
    assert np.all((g.lm ** 2).sum(1) < 1)
    img = g.to_image(np.arange(g.npix, dtype=float))
    assert img.shape == (64, 64) and np.isnan(img[0, 0])
    # the zenith is at [N//2, N//2] and l grows along columns, m along rows
    k = int(np.flatnonzero((g.lm == 0).all(1))[0])
    assert img[32, 32] == k
    k_e = int(np.flatnonzero(np.isclose(g.lm[:, 0], 10 * g.cell) & np.isclose(g.lm[:, 1], 0))[0])
    assert img[32, 42] == k_e
    lm = imaging.lm_from_azalt([90.0, 0.0, 0.0], [0.0, 0.0, 90.0])
    np.testing.assert_allclose(lm, [[1, 0], [0, 1], [0, 0]], atol=1e-15)
    az, alt = imaging.azalt_from_lm(imaging.lm_from_azalt([123.0], [34.0]))
    np.testing.assert_allclose([az[0], alt[0]], [123.0, 34.0])
    with pytest.raises(ValueError, match="outside"):
        imaging.lm_from_azalt([0.0], [-1.0])
    # n stays accurate next to the horizon
    r = 1 - 1e-12
    d = 1.0 - r  # exact in float64 (Sterbenz)
    assert abs(imaging.n_from_lm(r, 0.0) - np.sqrt(d * (2 - d))) < 1e-20


@pytest.mark.parametrize("dtype", ["float32", "float64", "complex64"])
def test_grid_placement_puts_each_pixel_in_its_cell(xp, dtype):
    from bf_epic_blocks.imaging.pixels import GridPlacement
    g = imaging.lm_grid(24)
    index = np.flatnonzero(g.mask)
    rng = np.random.default_rng(3)
    vals = rng.standard_normal((3, 2, g.npix)).astype(dtype)
    place = GridPlacement(index, g.size * g.size, xp)
    # into every other frame of a larger array (strided), and into a new array
    big = xp.zeros((5, 2, g.size * g.size), dtype)
    got = place(xp.asarray(vals), out=big[::2])
    got2 = place(xp.asarray(vals))
    for a in (got, got2, big[::2]):
        a = a.get() if hasattr(a, "get") else a
        for b, c in np.ndindex(3, 2):           # cell by cell from the definition
            cell = np.full(g.size * g.size, np.nan, dtype)
            for k, j in enumerate(index):
                cell[j] = vals[b, c, k]
            np.testing.assert_array_equal(a[b, c], cell)
    assert not np.any(np.asarray(big[1::2].get() if hasattr(big, "get") else big[1::2]))   # untouched
    # values cast to out's dtype (fp64 images into a float32 span)
    if dtype == "float64":
        o32 = place(xp.asarray(vals), out=xp.empty((3, 2, g.size * g.size), np.float32))
        o32 = o32.get() if hasattr(o32, "get") else o32
        np.testing.assert_array_equal(o32, np.asarray(got.get() if hasattr(got, "get") else got, np.float32))
    with pytest.raises(ValueError, match="last axis"):
        place(xp.asarray(vals[..., 1:]))
    with pytest.raises(ValueError, match="distinct integers"):
        GridPlacement([0, 0, 3], 8, xp)
    with pytest.raises(ValueError, match="distinct integers"):
        GridPlacement([0, 9], 8, xp)


@pytest.mark.parametrize("precision, tol", [("fp32", 5e-7), ("fp64", 1e-12)])
def test_geometric_operator_against_float64_phases(xp, precision, tol):
    """G = exp(-2 pi i nu/c (l x + m y + n z)) element by element (on a GPU: the one-kernel form), with
    km baselines and pixels near the horizon, against phases formed here in float64 and reduced
    modulo one cycle before the exponential."""
    rng = np.random.default_rng(5)
    xyz = np.concatenate([rng.uniform(-1500, 1500, (40, 2)), rng.uniform(-4, 4, (40, 1))], axis=1)
    freq = np.array([20e6, 59.3e6, 88e6])
    lm = np.concatenate([imaging.lm_grid(16).lm, [[0.99995, 0.0], [0.0, -0.9999]]])
    G = imaging.dft.geometric_operator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), precision)
    assert G.dtype == (np.complex64 if precision == "fp32" else np.complex128)
    n = np.sqrt(1.0 - lm[:, 0] ** 2 - lm[:, 1] ** 2)
    path = lm[:, :1] * xyz[None, :, 0] + lm[:, 1:] * xyz[None, :, 1] + n[:, None] * xyz[None, :, 2]
    cyc = freq[:, None, None] / C * path[None]
    ref = np.exp(-2j * np.pi * (cyc - np.round(cyc)))
    assert np.abs(to_np(G) - ref).max() <= tol


@pytest.mark.parametrize("precision,tol", [("fp64", 1e-12), ("fp32", 2e-6)])
def test_images_placed_on_the_grid_in_the_products_pass_equal_the_definition(xp, scene, precision, tol):
    """images(place=, out=) -- on the GPU the products kernel writes the grid's cells itself, the
    pattern's |B_p|^2 and the pols' sum in the same pass -- against the float64 definition placed on
    the grid by hand: a voltage pattern, one group per 8 samples, a dead channel (NaN), NaN off the grid."""
    xyz, freq, X, _ = scene
    grid = imaging.lm_grid(12)
    lm = grid.lm
    rng = np.random.default_rng(11)
    B = rng.uniform(0.2, 1.0, (1, len(lm), 1, 2)) * np.exp(1j * rng.uniform(0, 1, (1, len(lm), 1, 2)))
    w = np.ones((3, 24, 2))
    w[1] = 0                                                    # a dead channel
    prods = ("I", "XX", "Q")
    op = imaging.DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), npol=2, weights=xp.asarray(w),
                             pattern=xp.asarray(B), precision=precision)
    acc = op.accumulator(prods, method="direct")
    place = px.GridPlacement(np.flatnonzero(grid.mask), grid.size ** 2, xp)
    out = xp.full((5, 3, len(prods), grid.size ** 2), -7.0, dtype=op.rdtype)
    got = acc.images(xp.asarray(X), 8, place=place, out=out)
    assert got is out
    got = to_np(out)
    for g in range(5):
        ref = brute_image(X[8 * g:8 * (g + 1)], xyz, freq, lm, prods, weights=w, pattern=B)   # (C, nprod, K)
        cells = np.full((3, len(prods), grid.size ** 2), np.nan)
        cells[..., grid.mask.ravel()] = ref
        cells[1] = np.nan
        assert np.array_equal(np.isnan(got[g]), np.isnan(cells))
        assert rel_err(got[g], cells) <= tol, g


def test_take_pixels_of_a_ring_span_s_product_equals_take(xp):
    """The search's pixels off the grid (one kernel on the GPU) from a strided view, as a ring span's
    product slice gives it, equal NumPy's take."""
    rng = np.random.default_rng(15)
    span = rng.normal(size=(7, 5, 3, 8, 8)).astype(np.float32)          # (time, chan, product, m, l)
    index = np.sort(rng.choice(64, 41, replace=False))
    view = xp.asarray(span)[:, :, 1].reshape(7, 5, -1)
    got = px.take_pixels(view, xp.asarray(index, dtype=np.int32))
    assert to_np(got).shape == (7, 5, 41)
    assert np.array_equal(to_np(got), span[:, :, 1].reshape(7, 5, -1)[..., index])
