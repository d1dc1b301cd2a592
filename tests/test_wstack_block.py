"""WStackBlock in a pipeline against the exact DFT (independent float64 brute force) and MOFF."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, CalFoldBlock, WStackBlock, bfp, efield_header
from truth import brute_image, point_source_efield


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(4)
    xyz = np.concatenate([rng.normal(0, 20, (15, 3)) * [1, 1, 0.1], [[-293.0, 5.0, 10.0]]])
    freq = np.array([74e6, 74.025e6])
    X = point_source_efield(xyz, freq, 0.45, 0.3, 6.0, 48, npol=2, rng=rng)
    X += point_source_efield(xyz, freq, -0.2, -0.6, 3.0, 48, npol=2, rng=rng)
    X += 0.3 * (rng.normal(size=X.shape) + 1j * rng.normal(size=X.shape))
    return xyz, freq, X


def run(xp, X, hdr, grid, acc, **kw):
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X.astype(np.complex64), hdr, gulp_nframe=16,
                               space="cuda" if xp.__name__ == "cupy" else "system")
        blk = WStackBlock(CalFoldBlock(src, cable=False), grid, acc, **kw)
        sink = ArraySinkBlock(blk)
        p.run()
    return sink, blk


@pytest.mark.parametrize("route", ["efield", "covariance"])
@pytest.mark.parametrize("tolerance", [4e-2, 4e-4])
def test_wstack_block_matches_exact_dft(xp, scene, route, tolerance):
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    hdr = efield_header("w", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="cf32")
    sink, blk = run(xp, X, hdr, grid, 24, tolerance=tolerance, route=route, products=("I", "Q"))
    out = sink.result(0)  # (2, nchan, nprod, N, N)
    assert out.shape == (2, 2, 2, 32, 32)
    assert np.all(np.isnan(out[..., ~grid.mask]))
    for j in range(2):
        ref = brute_image(X[j * 24:(j + 1) * 24], xyz, freq, grid.lm, ("I", "Q"))
        got = out[j][..., grid.mask]
        assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= tolerance
    im = sink.headers[0]["imager"]
    assert im["method"] == route and im["tolerance"] == tolerance and im["epsilon"] == tolerance / 4
    assert im["overrides"] == ["method"] and im["error_bound"] == pytest.approx(tolerance)


def test_moff_mode_equals_dft_without_z(scene):
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    hdr = efield_header("m", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="cf32")
    sink, _ = run(np, X, hdr, grid, 48, tolerance=4e-5, moff=True, products=("I",))
    flat = xyz * [1, 1, 0]
    ref = brute_image(X, flat, freq, grid.lm, ("I",))
    got = sink.result(0)[0][..., grid.mask]
    assert np.max(np.abs(got - ref)) / ref.max() <= 4e-5
    assert sink.headers[0]["imager"]["kind"] == "moff"
    truth = brute_image(X, xyz, freq, grid.lm, ("I",))
    assert np.max(np.abs(got - truth)) / truth.max() > 1e-3, "MOFF must show the wide-field error here"


def test_wstack_block_rejects_what_it_cannot_do(scene):
    xyz, freq, X = scene
    hdr = efield_header("e", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="cf32")
    with bfp.Pipeline():
        src = ArraySourceBlock(X.astype(np.complex64), hdr, 16)
        with pytest.raises(TypeError, match="LMGrid"):
            WStackBlock(src, [[0.0, 0.0]], 4)
        with pytest.raises(ValueError, match="tolerance"):
            WStackBlock(src, imaging.lm_grid(16), 4, tolerance=2.0)
        with pytest.raises(TypeError, match="tolerance"):
            WStackBlock(src, imaging.lm_grid(16), 4, epsilon=1e-3)
    with pytest.raises(Exception, match="cannot fold an antenna pattern"):
        with bfp.Pipeline() as p:
            s2 = ArraySourceBlock(X.astype(np.complex64), hdr, 16)
            WStackBlock(CalFoldBlock(s2, cable=False, pattern="dipole"), imaging.lm_grid(16), 4)
            p.run()


def test_zenith_phased_moff_drops_only_w_n_minus_1(scene):
    """MOFF on zenith-phased voltages = the DFT with the w (n - 1) term dropped: exact at the zenith,
    wrong away from it (the seed paper's wide-field error)."""
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    got = imaging.moff_image(X, xyz, freq, grid, epsilon=1e-6, products=("I",), phase_zenith=True)
    C = 299792458.0
    Xz = X * np.exp(-2j * np.pi * freq[None, :, None, None] / C * xyz[None, None, :, 2:3])
    ref = brute_image(Xz, xyz * [1, 1, 0], freq, grid.lm, ("I",))
    assert np.max(np.abs(got - ref)) / ref.max() <= 4e-6
    # a source at the zenith keeps its exact peak; one 60 deg out does not
    g = imaging.lm_grid(64)
    for az, alt, exact_expected in ((0.0, 90.0, True), (90.0, 30.0, False)):
        (l, m), = imaging.lm_from_azalt([az], [alt])
        Xs = point_source_efield(xyz, freq, l, m, 1.0, 8, npol=2)
        approx = imaging.moff_image(Xs, xyz, freq, g, epsilon=1e-6, products=("XX",), phase_zenith=True)
        exact = imaging.dirty_image(Xs, xyz, freq, g.lm, products=("XX",), precision="fp64")
        k = int(np.argmin(np.hypot(g.lm[:, 0] - l, g.lm[:, 1] - m)))
        err = abs(approx[0, 0, k] - exact[0, 0, k]) / exact[0, 0, k]
        assert (err < 1e-5) if exact_expected else (err > 1e-2), (az, alt, err)


def test_covariance_gridder_accumulates_across_calls(scene):
    """R summed over several calls and gridded once = one call on all samples (and = the DFT)."""
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    g = imaging.CovarianceGridder(xyz, freq, grid, 2, epsilon=1e-6, products="stokes", remove_autocorr=True)
    for chunk in np.array_split(X, 5):
        g.add(chunk)
    assert g.ntime == X.shape[0]
    whole = imaging.cov_wgrid_image(X, xyz, freq, grid, epsilon=1e-6, products="stokes", remove_autocorr=True)
    ref = brute_image(X, xyz, freq, grid.lm, ("I", "Q", "U", "V"), remove_autocorr=True)
    assert np.max(np.abs(g.image() - whole)) / np.abs(ref).max() <= 1e-6
    assert np.max(np.abs(g.image() - ref)) / np.abs(ref).max() <= 4e-6
