"""The counter-based simulated sky (sky.fastsim) against the data model's own statistics, the
burst windows, its 4-bit packing, gulp-size independence, and on a GPU the CUDA kernel against
its NumPy twin."""
import numpy as np
import pytest

from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.conventions import dispersion_delay_s
from bf_epic_blocks.cuda import get_kernel
from bf_epic_blocks.io.tbf import unpack_ci4
from bf_epic_blocks.sky import fastsim

C = 299792458.0


def scene(nant=8, nchan=2, seed=4):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 30, (nant, 3)) * [1, 1, 0.05]
    freq = 60e6 + 25e3 * np.arange(nchan)
    l, m = np.array([0.3, -0.2]), np.array([0.1, 0.5])
    n = np.sqrt(1 - l * l - m * m)
    flux = np.array([[400.0, 100.0]] * nchan)
    cable = np.exp(-2j * np.pi * rng.uniform(0, 1, (nchan, nant, 2))) * rng.uniform(0.8, 1.2, (nchan, nant, 2))
    w = fastsim.sky_weights(xyz, freq, l, m, n, flux, cable)
    on0, on1 = fastsim.burst_windows(2, [], freq, 40e-6)
    return dict(xyz=xyz, freq=freq, l=l, m=m, n=n, flux=flux, cable=cable, w=w, on0=on0, on1=on1)


def test_complex_normals_are_standard_and_independent():
    re, im = fastsim.complex_normals(np.arange(2_000_000, dtype=np.uint64), fastsim.stream_keys(7)[1])
    for x in (re, im):
        assert abs(x.mean()) < 5e-3 and abs(x.var() - 1) < 5e-3
        assert abs(np.mean(x.astype(np.float64) ** 4) - 3) < 0.03          # Gaussian kurtosis
    assert abs(np.corrcoef(re, im)[0, 1]) < 3e-3
    assert abs(np.corrcoef(re[:-1], re[1:])[0, 1]) < 3e-3                   # neighbouring counters
    other = fastsim.complex_normals(np.arange(200_000, dtype=np.uint64), fastsim.stream_keys(8)[1])[0]
    assert abs(np.corrcoef(re[:200_000], other)[0, 1]) < 1e-2              # another seed: another sky


def test_box_muller_pieces_against_library_float64():
    """The float32 log and sin/cos the generator builds from IEEE operations (so NumPy and CUDA agree
    bit for bit) against NumPy's float64 library functions, on every 7th of their 2^24 inputs
    (all eight octants, both ends): Cephes' accuracy, about 1e-7."""
    k = np.arange(1, (1 << 24) + 1, 7, dtype=np.int32)
    ref = np.log(k / 2.0 ** 24)
    assert np.max(np.abs(fastsim._log_u1(k) - ref)) < 1e-6
    k = np.r_[np.arange(0, 1 << 24, 7), (1 << 24) - 1].astype(np.int32)
    c, s = fastsim._sincos_2pi(k)
    th = 2 * np.pi * k / 2.0 ** 24
    assert np.max(np.abs(c - np.cos(th))) < 2e-7 and np.max(np.abs(s - np.sin(th))) < 2e-7


@pytest.mark.parametrize("where", ["cpu", pytest.param("gpu", marks=[
    pytest.mark.gpu, pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")])])
def test_voltage_covariance_is_the_data_model(where):
    """Sample covariance of the voltages against the model's: sum_s S_s/2 g_a g_b* e^{...} + noise
    delta_ab, computed here from positions, fluxes and cables, not from sky_weights; the NumPy twin
    and the CUDA kernel (its own log, sqrt and sin/cos) each."""
    s = scene()
    T, noise = 40000, 300.0
    if where == "gpu":
        import cupy
        x = cupy.empty((T, 2, 8, 2), np.complex64)
        fastsim.make_gulp(x, 0, cupy.asarray(s["w"]), s["on0"], s["on1"], fastsim.stream_keys(1), noise)
        x = x.get()
    else:
        x = np.empty((T, 2, 8, 2), np.complex64)
        fastsim.make_gulp(x, 0, s["w"], s["on0"], s["on1"], fastsim.stream_keys(1), noise)
    for c in range(2):
        for p in range(2):
            v = x[:, c, :, p].astype(np.complex128)
            R = v.T @ v.conj() / T
            g = s["cable"][c, :, p]
            ref = noise * np.eye(8, dtype=complex)
            for k in range(2):
                a = np.exp(2j * np.pi * s["freq"][c] / C * (s["xyz"] @ [s["l"][k], s["m"][k], s["n"][k]])) * g
                ref += s["flux"][c, k] / 2 * np.outer(a, a.conj())
            scale = np.sqrt(np.outer(np.diag(ref.real), np.diag(ref.real)) / T)   # one sigma of each entry
            assert np.max(np.abs(R - ref) / scale) < 5.5


def test_ci4_is_the_quantised_voltage_and_gulps_do_not_matter():
    s = scene()
    keys, noise = fastsim.stream_keys(3), 50.0
    scale = 2.0 / fastsim.expected_rms(s["w"], noise)
    v = np.empty((100, 2, 8, 2), np.complex64)
    fastsim.make_gulp(v, 1000, s["w"], s["on0"], s["on1"], keys, noise)
    q = np.empty(v.shape, np.uint8)
    fastsim.make_gulp(q, 1000, s["w"], s["on0"], s["on1"], keys, noise, scale)
    ref = np.clip(np.rint(v.real * np.float32(scale)), -8, 7) + 1j * np.clip(np.rint(v.imag * np.float32(scale)), -8, 7)
    np.testing.assert_array_equal(unpack_ci4(q), ref)
    # the rms the scale was set from is the data's (the sources' signals are common to all antennas:
    # 20,000 samples hold 40,000 independent values of each)
    long = np.empty((20000, 2, 8, 2), np.complex64)
    fastsim.make_gulp(long, 0, s["w"], s["on0"], s["on1"], keys, noise)
    rms = np.sqrt(np.mean(np.abs(long.astype(np.complex128)) ** 2) / 2)
    assert abs(rms * scale - 2.0) < 0.02
    # made in two pieces of other sizes: the same samples
    parts = [np.empty((37, 2, 8, 2), np.uint8), np.empty((63, 2, 8, 2), np.uint8)]
    fastsim.make_gulp(parts[0], 1000, s["w"], s["on0"], s["on1"], keys, noise, scale)
    fastsim.make_gulp(parts[1], 1037, s["w"], s["on0"], s["on1"], keys, noise, scale)
    np.testing.assert_array_equal(np.concatenate(parts), q)


def test_a_burst_shines_only_in_its_dispersed_window():
    s = scene(nchan=4)
    f, dt = s["freq"], 40e-6
    burst = {"start_s": 0.004, "duration_s": 0.0008, "dm": 30.0}
    on0, on1 = fastsim.burst_windows(0, [burst], f, dt)
    w = s["w"][:, :1]
    x = np.empty((400, 4, 8, 2), np.complex64)
    fastsim.make_gulp(x, 0, w, on0, on1, fastsim.stream_keys(2), 0.0)
    delay = dispersion_delay_s(30.0, f, f.max())
    t = np.arange(400) * dt
    for c in range(4):
        lit = np.abs(x[:, c]).max(axis=(1, 2)) > 0
        expect = (t >= 0.004 + delay[c] - 1e-12) & (t < 0.004 + delay[c] + 0.0008 - 1e-12)
        np.testing.assert_array_equal(lit, expect)
    assert delay[0] > 2 * dt                                               # the window moves with channel


def test_bad_output_is_refused():
    s = scene()
    with pytest.raises(ValueError, match="needs a positive scale"):
        fastsim.make_gulp(np.empty((4, 2, 8, 2), np.uint8), 0, s["w"], s["on0"], s["on1"], (1, 2), 1.0)
    with pytest.raises(ValueError, match="uint8 \\(ci4\\) or complex64"):
        fastsim.make_gulp(np.empty((4, 2, 8, 2), np.float32), 0, s["w"], s["on0"], s["on1"], (1, 2), 1.0)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("nsteady, nant", [(2, 256), (0, 256), (fastsim.MAX_REG_SRC + 2, 100)])
def test_the_gpu_kernel_makes_the_numpy_twin_s_samples(nsteady, nant):
    """Both CUDA kernels (sources in registers up to MAX_REG_SRC, the generic one beyond) against the
    NumPy twin: the same counters and uniforms, the GPU's own log, sqrt and sin/cos, so voltages
    equal to ~1e-5 of their rms and 4-bit samples equal but for a rare one a rounding edge apart."""
    import cupy
    s = scene(nant=nant, nchan=3)
    bursts = [{"start_s": 0.002, "duration_s": 0.001, "dm": 5.0}]
    w = np.concatenate([s["w"][:, np.arange(nsteady) % 2], s["w"][:, :1]], axis=1)
    on0, on1 = fastsim.burst_windows(nsteady, bursts, s["freq"], 40e-6)
    keys, noise = fastsim.stream_keys(11), 200.0
    scale = 2.0 / fastsim.expected_rms(s["w"], noise)
    for dtype in (np.uint8, np.complex64):
        ref = np.empty((512, 3, nant, 2), dtype)
        fastsim.make_gulp(ref, 4096, w, on0, on1, keys, noise, scale)
        got = cupy.empty(ref.shape, dtype)
        # in two gulps, neither a whole number of the kernel's 32-sample tiles
        fastsim.make_gulp(got[:37], 4096, cupy.asarray(w), on0, on1, keys, noise, scale)
        fastsim.make_gulp(got[37:], 4096 + 37, cupy.asarray(w), on0, on1, keys, noise, scale)
        got = got.get()
        if dtype == np.uint8:
            d = unpack_ci4(got) - unpack_ci4(ref)
            step = np.maximum(np.abs(d.real), np.abs(d.imag))
            assert step.max() <= 1 and np.mean(step > 0) < 2e-5, (step.max(), np.mean(step > 0))
        else:
            rms = np.sqrt(np.mean(np.abs(ref.astype(np.complex128)) ** 2))
            err = np.abs(got.astype(np.complex128) - ref)
            assert np.isfinite(got).all() and err.max() < 1e-3 * rms and err.mean() < 1e-5 * rms, \
                (err.max() / rms, err.mean() / rms)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("nsrc", [0, 3])
def test_the_few_source_kernel_is_the_generic_kernel_bit_for_bit(nsrc):
    """sim_gulp_few (weights in registers, counters stepped) does the generic kernel's float
    operations in its order: the same bits, ci4 and complex64, over tiles and a partial tile."""
    import cupy
    s = scene(nant=200, nchan=5)
    w = cupy.asarray(s["w"][:, np.arange(nsrc) % 2], cupy.complex64)
    on0, on1 = (cupy.asarray(a, cupy.int64) for a in fastsim.burst_windows(nsrc, [], s["freq"], 40e-6))
    keys, n, nchan = fastsim.stream_keys(5), 70, 5
    generic = get_kernel("sky/fastsim.cu", "sim_gulp", options=("--use_fast_math",))
    few = get_kernel("sky/fastsim.cu", "sim_gulp_few", defines={"NSRC": nsrc}, options=("--use_fast_math",))
    for ci4, dtype in ((1, np.uint8), (0, np.complex64)):
        outs = []
        for k in (generic, few):
            out = cupy.zeros((n, nchan, 200, 2), dtype)
            head = (out, np.int32(ci4), w, on0, on1, np.int64(999), np.int32(n), np.int32(nchan))
            tail = (np.int32(200), np.uint64(keys[0]), np.uint64(keys[1]), np.float32(9.0), np.float32(0.2))
            grid = (-(-n // 32) * nchan,)
            if k is generic:
                k(grid, (256,), head + (np.int32(nsrc),) + tail, shared_mem=max(8, 32 * 16 * nsrc))
            else:
                k(grid, (256,), head + tail)
            outs.append(out.get())
        np.testing.assert_array_equal(outs[1], outs[0])
