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
@pytest.mark.parametrize("epsilon", [1e-2, 1e-4])
def test_wstack_block_matches_exact_dft(xp, scene, route, epsilon):
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    hdr = efield_header("w", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="cf32")
    sink, blk = run(xp, X, hdr, grid, 24, epsilon=epsilon, route=route, products=("I", "Q"))
    out = sink.result(0)  # (2, nchan, nprod, N, N)
    assert out.shape == (2, 2, 2, 32, 32)
    assert np.all(np.isnan(out[..., ~grid.mask]))
    for j in range(2):
        ref = brute_image(X[j * 24:(j + 1) * 24], xyz, freq, grid.lm, ("I", "Q"))
        got = out[j][..., grid.mask]
        assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= 4 * epsilon
    assert sink.headers[0]["imager"]["method"] == route


def test_moff_mode_equals_dft_without_z(scene):
    xyz, freq, X = scene
    grid = imaging.lm_grid(32)
    hdr = efield_header("m", 0, freq, 40e-6, {"xyz_m": xyz}, dtype="cf32")
    sink, _ = run(np, X, hdr, grid, 48, epsilon=1e-5, moff=True, products=("I",))
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
        with pytest.raises(ValueError, match="epsilon"):
            WStackBlock(src, imaging.lm_grid(16), 4, epsilon=0.5)
    with pytest.raises(Exception, match="cannot fold an antenna pattern"):
        with bfp.Pipeline() as p:
            s2 = ArraySourceBlock(X.astype(np.complex64), hdr, 16)
            WStackBlock(CalFoldBlock(s2, cable=False, pattern="dipole"), imaging.lm_grid(16), 4)
            p.run()
