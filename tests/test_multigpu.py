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
    # calibrated complex voltages (CalFoldBlock's output): replayed as CUDA graphs from the second call
    for call in range(3):
        Xc = (X * np.exp(0.3j * call)).astype(np.complex64)
        img = sh.image(Xc, ("I", "V"), method="covariance")
        truth = brute_image(Xc.astype(np.complex128), xyz, freq, lm, ("I", "V"))
        assert np.max(np.abs(img - truth)) / np.max(np.abs(truth)) < 1e-5, call


@pytest.mark.gpu
@pytest.mark.skipif(NGPU < 1, reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("method", ["covariance", "direct"])
def test_gulps_in_flight_each_equal_truth(method):
    """Several gulps submitted before any result is taken, from one reused pinned host buffer that is
    overwritten as soon as the GPUs have read it: each result equals the float64 truth of its own
    gulp (no gulp sees another's samples or images), for 4-bit samples decoded on the GPUs."""
    cp = cupy_or_none()
    from bf_epic_blocks.imaging.multigpu import ShardedOperator
    from bf_epic_blocks.runtime.dtypes import pack_ci4, unpack_int8_pairs
    rng = np.random.default_rng(5)
    xyz = rng.normal(0, 15, (20, 3)) * [1, 1, 0.1]
    freq = 60e6 + 1e6 * np.arange(5)
    lm = imaging.lm_grid(8).lm
    gulps = []
    for k in range(5):      # more gulps than staging buffers (depth 2)
        X = rng.normal(size=(48, 5, 20, 2)) + 1j * rng.normal(size=(48, 5, 20, 2))
        X += point_source_efield(xyz, freq, 0.1 * k - 0.2, 0.15, 4.0, 48, npol=2, rng=rng)
        q = np.stack([np.clip(np.rint(X.real), -8, 7), np.clip(np.rint(X.imag), -8, 7)], -1).astype(np.int8)
        gulps.append(q)
    devices = list(range(NGPU)) if NGPU > 1 else [0]
    sh = ShardedOperator(xyz, freq, lm, devices, npol=2, precision="fp32", depth=2)
    packed = pack_ci4(gulps[0][..., 0] + 1j * gulps[0][..., 1])
    mem = cp.cuda.alloc_pinned_memory(packed.nbytes)
    host = np.frombuffer(mem, np.uint8, packed.size).reshape(packed.shape)
    acc = 16 if method == "direct" else None
    pending = []
    for q in gulps:
        host[...] = pack_ci4(q[..., 0] + 1j * q[..., 1])
        p = sh.submit(host, ("I",), method=method, accumulate=acc, decode=lambda b: unpack_int8_pairs(b, "ci4"))
        p.release_input()          # the buffer may be refilled now
        pending.append(p)
    for q, p in zip(gulps, pending):
        img = p.result()
        if acc is None:
            ref = brute_image(q[..., 0] + 1j * q[..., 1], xyz, freq, lm, ("I",))
        else:
            ref = np.stack([brute_image(q[i:i + acc, ..., 0] + 1j * q[i:i + acc, ..., 1], xyz, freq, lm, ("I",))
                            for i in range(0, 48, acc)])
        assert img.shape == ref.shape
        assert np.max(np.abs(img - ref)) / np.max(np.abs(ref)) < 1e-6
    # device input and output (peer copies of each GPU's channels): the same images, on the first GPU
    dev = sh.submit(cp.asarray(gulps[-1]), ("I",), method=method, accumulate=acc, out="device").result()
    assert isinstance(dev, cp.ndarray) and dev.device.id == devices[0]
    assert np.max(np.abs(dev.get() - ref)) / np.max(np.abs(ref)) < 1e-6


@pytest.mark.gpu
@pytest.mark.skipif(NGPU < 1, reason="needs CuPy and a CUDA device")
def test_sharded_bad_arguments_are_clear_errors():
    from bf_epic_blocks.imaging.multigpu import ShardedOperator
    xyz = np.zeros((4, 3))
    xyz[:, 0] = np.arange(4)
    with pytest.raises(ValueError, match="depth"):
        ShardedOperator(xyz, [60e6, 61e6], imaging.lm_grid(4).lm, [0], depth=0)
    sh = ShardedOperator(xyz, [60e6, 61e6], imaging.lm_grid(4).lm, [0])
    with pytest.raises(ValueError, match="2 channels on axis 1"):
        sh.submit(np.zeros((8, 3, 4, 1), np.complex64))
    with pytest.raises(ValueError, match="out must be"):
        sh.submit(np.zeros((8, 2, 4, 1), np.complex64), out="gpu")
    with pytest.raises(ValueError, match=r"out: expected a C-contiguous float32 array of shape \(2, 1, 9\)"):
        sh.submit(np.zeros((8, 2, 4, 1), np.complex64), out=np.zeros((2, 1, 15), np.float32))
    with pytest.raises(ValueError, match="scatter must be"):
        ShardedOperator(xyz, [60e6, 61e6], imaging.lm_grid(4).lm, [0], scatter=(np.arange(3), 16))


@pytest.mark.gpu
@pytest.mark.skipif(NGPU < 1, reason="needs CuPy and a CUDA device")
def test_scatter_onto_grid_into_a_given_array():
    """scatter=(grid indices, n): images placed on the whole grid on the GPUs (NaN elsewhere), written
    into the caller's array; equal to the float64 truth at the imaged pixels."""
    from bf_epic_blocks.imaging.multigpu import ShardedOperator
    rng = np.random.default_rng(8)
    xyz = rng.normal(0, 15, (16, 3)) * [1, 1, 0.1]
    freq = 60e6 + 1e6 * np.arange(4)
    grid = imaging.lm_grid(12)
    X = rng.normal(size=(32, 4, 16, 2)) + 1j * rng.normal(size=(32, 4, 16, 2))
    X += point_source_efield(xyz, freq, -0.2, 0.3, 5.0, 32, npol=2, rng=rng)
    devices = list(range(NGPU)) if NGPU > 1 else [0]
    sh = ShardedOperator(xyz, freq, grid.lm, devices, npol=2, scatter=(np.flatnonzero(grid.mask), grid.size ** 2))
    out = np.full((4, 2, grid.size ** 2), -1.0, np.float32)
    assert sh.image(X.astype(np.complex64), ("I", "Q"), method="covariance", out=out) is out
    ref = brute_image(X, xyz, freq, grid.lm, ("I", "Q"))
    on = grid.mask.ravel()
    assert np.all(np.isnan(out[..., ~on]))
    assert np.max(np.abs(out[..., on] - ref)) / np.max(np.abs(ref)) < 1e-5



@pytest.mark.gpu
@pytest.mark.skipif(NGPU < 1, reason="needs CuPy and a CUDA device")
def test_the_first_gulp_waits_for_the_operator_to_be_built():
    """On a GPU shared with another process (here one multiplying matrices), a ShardedOperator's first
    gulp is imaged only once its operators and placements are built: its non-blocking streams wait for the
    stream they were built on. Twelve operators built and used at once, each equal to the float64 truth."""
    import subprocess
    import sys
    load = subprocess.Popen([sys.executable, "-c", "import cupy as cp, time\n"
                             "a = cp.random.rand(8192, 8192, dtype=cp.float32); t = time.time()\n"
                             "while time.time() - t < 20: (a @ a).sum().item()\n"])
    try:
        import time
        time.sleep(3)                                         # the other process is multiplying
        bad = []
        for k in range(12):
            try:
                test_scatter_onto_grid_into_a_given_array()
            except AssertionError:
                bad.append(k)
    finally:
        load.kill()
        load.wait()
    assert not bad, f"operators {bad} of 12 imaged before they were built"
