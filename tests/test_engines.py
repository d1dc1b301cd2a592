"""An imager block's engine (bf_epic_blocks.blocks.engines): made in on_sequence, made again only when the
header asks for another operator, and one image_gulp call per gulp, against the float64 definition."""
import types

import numpy as np
import pytest

from bf_epic_blocks.blocks import ArraySourceBlock, DFTImagerBlock, bfp, efield_header
from bf_epic_blocks.blocks.engines import DFTEngine
from truth import brute_image

DT = 40e-6


def scene(seed=2, nst=10, nchan=2, T=40):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 25, (nst, 3)) * [1, 1, 0.05]
    freq = 60e6 + 25e3 * np.arange(nchan)
    X = (rng.normal(size=(T, nchan, nst, 2)) + 1j * rng.normal(size=(T, nchan, nst, 2))).astype(np.complex64)
    lm = np.array([[0.0, 0.0], [0.2, 0.1], [-0.5, 0.4]])
    return xyz, freq, X, lm


def sequence(img, hdr, X, gulps):
    """One sequence through the block's own on_sequence / on_data path: the images it wrote."""
    ohdr = img.on_sequence(types.SimpleNamespace(header=hdr))
    frame = list(ohdr["_tensor"]["shape"][1:])
    out, got = np.zeros([len(X)] + frame, np.float32), 0
    for a, b in gulps:
        got += img.engine.image_gulp(X[a:b], out[got:])
    img.on_sequence_end(types.SimpleNamespace(header=hdr))
    return out[:got]


def imager_block():
    """scene()'s voltages, its header (no flags) and an fp64 DFTImagerBlock of XX, YY over 10 samples."""
    xyz, freq, X, lm = scene()
    flags = np.zeros((len(xyz), 2), bool)
    hdr = efield_header("a", 0, freq, DT, {"xyz_m": xyz, "flags": flags}, dtype="cf32")
    with bfp.Pipeline():
        src = ArraySourceBlock(X, hdr, gulp_nframe=8)
        img = DFTImagerBlock(src, lm, 10, products=("XX", "YY"), precision="fp64")
    return xyz, freq, X, lm, flags, hdr, img


def test_the_engine_is_made_again_only_when_the_header_asks_for_another_operator():
    xyz, freq, X, lm, flags, hdr, img = imager_block()
    ref = np.stack([brute_image(X[i:i + 10], xyz, freq, lm, ("XX", "YY")) for i in range(0, 40, 10)])

    first = sequence(img, hdr, X, [(0, 8), (8, 16), (16, 40)])
    engine = img.engine
    assert isinstance(engine, DFTEngine) and img.img_stats["operator_builds"] == 1
    np.testing.assert_allclose(first, ref, rtol=0, atol=1e-5 * np.abs(ref).max())

    # the next sequence, same array and channels: the same engine, the same images, whatever the gulps
    again = sequence(img, dict(hdr, name="b", time_tag=12345), X, [(0, 25), (25, 40)])
    assert img.engine is engine and img.img_stats["operator_builds"] == 1
    np.testing.assert_allclose(again, first, rtol=1e-6, atol=0)

    # an antenna flagged: another operator
    flags2 = flags.copy()
    flags2[3] = True
    hdr2 = efield_header("c", 0, freq, DT, {"xyz_m": xyz, "flags": flags2}, dtype="cf32")
    third = sequence(img, hdr2, X[:20], [(0, 20)])
    assert img.engine is not engine and img.img_stats["operator_builds"] == 2
    w = np.broadcast_to(~flags2, (len(freq), len(xyz), 2)).astype(float)
    ref2 = np.stack([brute_image(X[i:i + 10], xyz, freq, lm, ("XX", "YY"), weights=w) for i in (0, 10)])
    np.testing.assert_allclose(third, ref2, rtol=0, atol=1e-5 * np.abs(ref2).max())



def test_a_new_operator_is_made_after_the_old_one_is_let_go():
    """A rebuild (a gain solution, tracking pixels, a new sequence's array) never holds two operators:
    a whole band's is GBs on the GPU. The real build sees the old operator already gone."""
    import gc
    import weakref
    xyz, freq, X, lm, flags, hdr, img = imager_block()
    made, old_alive = [], []
    real = img._operator

    def operator(lm_):
        gc.collect()
        old_alive.append([r() is not None for r in made])
        op, route = real(lm_)
        made.append(weakref.ref(op))
        return op, route
    img._operator = operator
    sequence(img, hdr, X, [(0, 40)])
    img.engine._rebuild(lm)                        # as a gain solution does
    flags2 = flags.copy()
    flags2[3] = True                               # another operator for the next sequence
    third = sequence(img, efield_header("c", 0, freq, DT, {"xyz_m": xyz, "flags": flags2}, dtype="cf32"),
                     X[:20], [(0, 20)])
    assert old_alive == [[], [False], [False, False]]
    w = np.broadcast_to(~flags2, (len(freq), len(xyz), 2)).astype(float)
    ref = np.stack([brute_image(X[i:i + 10], xyz, freq, lm, ("XX", "YY"), weights=w) for i in (0, 10)])
    np.testing.assert_allclose(third, ref, rtol=0, atol=1e-5 * np.abs(ref).max())

def test_a_partial_integration_at_the_end_of_a_sequence_is_dropped_and_counted():
    xyz, freq, X, lm = scene()
    hdr = efield_header("a", 0, freq, DT, {"xyz_m": xyz}, dtype="cf32")
    with bfp.Pipeline():
        src = ArraySourceBlock(X, hdr, gulp_nframe=8)
        img = DFTImagerBlock(src, lm, 15, precision="fp64")
    imgs = sequence(img, hdr, X, [(0, 7), (7, 40)])
    assert imgs.shape[0] == 2 and img.img_stats["frames_dropped_partial"] == 10
    assert img.engine.ntime == 0


class _HostSharded:
    """A stand-in for multigpu.ShardedOperator on the CPU: one operator for every channel, the same calls."""

    def __init__(self, op):
        self.ops, self.npol, self.npix, self.npix_out = [op], op.npol, op.npix, op.npix

    def image(self, x, products, *, accumulate, out, remove_autocorr, method, decode):
        out[...] = self.ops[0].image(x, products, remove_autocorr=remove_autocorr, method=method,
                                     accumulate=accumulate)

    def submit(self, x, products, *, out, remove_autocorr, method, decode):
        out[...] = self.ops[0].image(x, products, remove_autocorr=remove_autocorr, method=method)
        return types.SimpleNamespace(result=lambda: out)


@pytest.mark.parametrize("method", ["direct", "covariance"])
def test_the_sharded_engine_images_whole_integrations_only(method):
    from bf_epic_blocks.blocks.engines import ImageOutput, ShardedEngine, ShardedRoute
    from bf_epic_blocks.imaging.dft import DFTOperator
    xyz, freq, X, lm = scene()
    op = DFTOperator(xyz, freq, lm, npol=2, precision="fp64")
    counted = []
    eng = ShardedEngine(lambda lm_: ShardedRoute(_HostSharded(op), ("XX", "YY"), method, False, 10, "cf32"), lm,
                        accumulate=10, dtype="cf32", name="test")
    eng.begin(ImageOutput(None, None, counted.append))
    out = np.zeros((4, 2, 2, 3), np.float64)
    assert eng.image_gulp(X[:20], out) == 2 and eng.image_gulp(X[20:40], out[2:]) == 2 and counted == [2, 2]
    ref = np.stack([brute_image(X[i:i + 10], xyz, freq, lm, ("XX", "YY")) for i in range(0, 40, 10)])
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    with pytest.raises(ValueError, match="whole integrations only"):
        eng.image_gulp(X[:15], out)


def test_a_gulp_that_crosses_a_tracking_step_is_batched_on_each_side_with_the_right_pixels():
    """Tracking pixels held for steps of 30 frames (3 integrations of 10), gulps of 40 frames: each gulp
    crosses a step. The integrations before a step are made by one batched call, and those after it by
    another with the operator moved (a lone integration, as at frame 30, one at a time: the CPU
    route batches two or more), and each image is the float64 DFT at its own pixels."""
    from bf_epic_blocks.blocks.headers import efield_layout
    xyz, freq, X, lm = scene(T=80)
    flags = np.zeros((len(xyz), 2), bool)
    hdr = efield_header("a", 0, freq, DT, {"xyz_m": xyz, "flags": flags}, dtype="cf32")
    tpf = efield_layout(hdr, "test")["ticks_per_frame"]

    def pixels_at(frame):
        return lm + 0.05 * (frame // 30)

    with bfp.Pipeline():
        src = ArraySourceBlock(X, hdr, gulp_nframe=40)
        img = DFTImagerBlock(src, lambda tag: pixels_at(int(tag // tpf)), 10, products=("XX",), precision="fp64")
    ohdr = img.on_sequence(types.SimpleNamespace(header=hdr))
    eng = img.engine
    whole, batched = eng._whole, []

    def spy_whole(pos, g, out, nout):
        batched.append((eng.frame + pos, g))
        return whole(pos, g, out, nout)
    eng._whole = spy_whole
    out = np.zeros([8] + list(ohdr["_tensor"]["shape"][1:]), np.float32)
    got = eng.image_gulp(X[:40], out)
    got += eng.image_gulp(X[40:80], out[got:])
    assert got == 8
    assert batched == [(0, 3), (40, 2), (60, 2)]
    assert img.img_stats["operator_builds"] == 1 and img.img_stats["operator_moves"] == 2
    ref = np.stack([brute_image(X[i:i + 10], xyz, freq, pixels_at(i), ("XX",)) for i in range(0, 80, 10)])
    np.testing.assert_allclose(out[:got], ref, rtol=0, atol=1e-5 * np.abs(ref).max())
