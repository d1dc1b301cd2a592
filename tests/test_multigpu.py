"""Channels sharded over several GPUs give the images of one device (GPU tests run where GPUs exist)."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging._xp import cupy_or_none, gpu_available
from bf_epic_blocks.imaging.multigpu import channel_blocks
from truth import brute_image, point_source_efield

NGPU = cupy_or_none().cuda.runtime.getDeviceCount() if gpu_available() else 0


def test_channel_blocks_cover_the_band_in_order():
    for nchan, n in ((16, 2), (32, 3), (5, 5), (7, 2)):
        b = channel_blocks(nchan, n)
        assert len(b) == n and b[0].start == 0 and b[-1].stop == nchan
        assert all(x.stop == y.start for x, y in zip(b, b[1:]))
        assert max(x.stop - x.start for x in b) - min(x.stop - x.start for x in b) <= 1
    with pytest.raises(ValueError, match="at least one channel each"):
        channel_blocks(3, 4)


@pytest.mark.skipif(gpu_available(), reason="checks the message on a machine without GPUs")
def test_several_gpus_without_gpus_is_a_clear_error():
    from bf_epic_blocks.imaging.multigpu import resolve_devices
    with pytest.raises(RuntimeError, match="CuPy or a CUDA GPU is not available"):
        resolve_devices("all")


@pytest.mark.gpu
@pytest.mark.skipif(NGPU < 1, reason="needs CuPy and a CUDA device")
def test_sharded_equals_one_device_and_truth():
    from bf_epic_blocks.imaging.multigpu import ShardedOperator
    rng = np.random.default_rng(2)
    xyz = rng.normal(0, 20, (24, 3)) * [1, 1, 0.1]
    freq = 60e6 + 1e6 * np.arange(6)
    X = rng.normal(size=(64, 6, 24, 2)) + 1j * rng.normal(size=(64, 6, 24, 2))
    X += point_source_efield(xyz, freq, 0.3, 0.2, 3.0, 64, npol=2, rng=rng)
    q = np.stack([np.clip(np.rint(X.real), -8, 7), np.clip(np.rint(X.imag), -8, 7)], -1).astype(np.int8)
    lm = imaging.lm_grid(10).lm
    ref = brute_image(q[..., 0] + 1j * q[..., 1], xyz, freq, lm, ("I", "V"))
    devices = list(range(NGPU)) if NGPU > 1 else [0]
    sh = ShardedOperator(xyz, freq, lm, devices, npol=2, precision="fp32")
    for method in ("direct", "covariance"):
        img = sh.image(q, ("I", "V"), method=method)
        assert img.shape == ref.shape
        assert np.max(np.abs(img - ref)) / np.max(np.abs(ref)) < 1e-6
        one = imaging.DFTOperator(*(cupy_or_none().asarray(v) for v in (xyz, freq, lm)), npol=2).image(
            cupy_or_none().asarray(q), ("I", "V"), method=method).get()
        assert np.max(np.abs(img - one)) / np.max(np.abs(one)) <= 1e-6
    imgs = sh.image(q, ("I",), accumulate=16, method="direct")
    assert imgs.shape == (4, 6, 1, len(lm))
