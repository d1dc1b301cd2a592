"""The precision ladder, batched short integrations, exact integer covariances and the tolerance
planner, against independent float64 truth (tests/truth.py)."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.imaging import plan
from bf_epic_blocks.imaging._xp import gpu_available
from bf_epic_blocks.imaging.dft import DFTOperator
from bf_epic_blocks.imaging.fused import FUSED
from bf_epic_blocks.imaging.gemm import PRECISIONS, precision_available
from truth import brute_fields, brute_image, point_source_efield

C = 299792458.0


def to_np(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


def rel_err(got, ref):
    return float(np.nanmax(np.abs(to_np(got) - ref)) / np.nanmax(np.abs(ref)))


def quantise4(x, rms=2.0):
    """4-bit (re, im) integer pairs (int8, values -8..7) of complex voltages, as an F-engine gives."""
    s = rms / np.sqrt(np.mean(np.abs(x) ** 2) / 2)
    q = np.stack([np.clip(np.rint(x.real * s), -8, 7), np.clip(np.rint(x.imag * s), -8, 7)], axis=-1)
    return q.astype(np.int8)


def as_complex(q):
    return q[..., 0].astype(np.float64) + 1j * q[..., 1]


@pytest.fixture(scope="module")
def sky_scene():
    """Realistic data: an LWA-like 48-antenna layout (z scatter, one outrigger), noise plus three
    sources, quantised to 4 bits; 2 channels, 2 pols, 192 samples; an all-sky 20x20 grid."""
    rng = np.random.default_rng(7)
    r = 50 * np.sqrt(rng.random(48))
    th = 2 * np.pi * rng.random(48)
    xyz = np.stack([r * np.cos(th), 1.1 * r * np.sin(th), rng.normal(0, 0.4, 48)], axis=1)
    xyz[-1] = [-293.0, 5.0, 10.0]
    freq = np.array([60e6, 74e6])
    T = 192
    X = (rng.normal(size=(T, 2, 48, 2)) + 1j * rng.normal(size=(T, 2, 48, 2))) / np.sqrt(2)
    for l, m, p in ((0.3, -0.2, 3.0), (-0.5, 0.4, 2.0), (0.05, 0.7, 1.0)):
        X = X + point_source_efield(xyz, freq, l, m, p, T, npol=2, rng=rng)
    lm = imaging.lm_grid(20).lm
    return xyz, freq, quantise4(X), lm


@pytest.fixture(scope="module")
def hard_scene():
    """A 5 km baseline at 88 MHz, pixels at n ~ 1e-4 (the horizon), and a point source 60 dB above
    the noise (4-bit quantisation cannot hold 60 dB, so these voltages stay complex)."""
    rng = np.random.default_rng(11)
    xyz = np.concatenate([rng.normal(0, 30, (15, 3)) * [1, 1, 0.05], [[4000.0, -3000.0, 12.0]]])
    freq = np.array([88e6])
    T = 64
    X = 1e-3 * (rng.normal(size=(T, 1, 16, 2)) + 1j * rng.normal(size=(T, 1, 16, 2)))
    X = X + point_source_efield(xyz, freq, 0.6, 0.8 * np.sqrt(1 - 1e-8) * 0.9999, 1.0, T, npol=2, rng=rng)
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    r = np.sqrt(1 - 1e-8)                       # n = 1e-4
    lm = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang)], 1), imaging.lm_grid(8).lm])
    return xyz, freq, X, lm


def _bound(xp, method, precision):
    dev = "gpu" if xp.__name__ == "cupy" else "cpu"
    rows = [r for r in plan.load_table()["rows"] if (r["device"], r["method"], r["precision"]) ==
            (dev, method, precision)]
    assert rows, f"the shipped table has no bound for {(dev, method, precision)}"
    return rows[0]["bound"]


@pytest.mark.parametrize("method", ["direct", "covariance"])
def test_every_precision_within_its_stated_bound(xp, sky_scene, hard_scene, method):
    prods = ("I", "Q", "U", "V")
    for name, (xyz, freq, X, lm) in (("sky 4-bit", sky_scene), ("5 km horizon 60 dB", hard_scene)):
        Xc = as_complex(X) if X.dtype == np.int8 else X
        ref = brute_image(Xc, xyz, freq, lm, prods)
        inputs = [xp.asarray(X)] if X.dtype != np.int8 else [xp.asarray(X), xp.asarray(Xc.astype(np.complex64))]
        for precision in PRECISIONS:
            # (the fused integer modes image 4-bit voltages' XX/YY only: tests/test_fused.py)
            if not precision_available(precision, xp) or precision in FUSED:
                continue
            for x in inputs:
                img = imaging.dirty_image(x, xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), method=method,
                                          precision=precision, products=prods)
                err = rel_err(img, ref)
                assert err <= _bound(xp, method, precision), (name, precision, str(x.dtype), err)
                assert np.all(np.isfinite(to_np(img)))


def test_integer_covariance_is_exact(xp, sky_scene):
    """X X^H from 4-bit integers equals the float64 X X^H exactly (bitwise after conversion)."""
    xyz, freq, X, lm = sky_scene
    op = DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), npol=2, precision="fp64")
    acc = op.accumulator(("I", "U"), method="covariance")
    acc.add(xp.asarray(X[:100]))
    acc.add(xp.asarray(X[100:]))       # two calls: the integer sums carry over exactly
    R = to_np(acc._covariance_blocks())   # (nchan, nblk, A, A) for blocks XX, YY, XY
    Xc = as_complex(X)
    for i, (p, q) in enumerate(acc.blocks):
        for c in range(2):
            ref = Xc[:, c, :, p].T @ np.conj(Xc[:, c, :, q])
            assert np.array_equal(R[c, i], ref), (p, q, c)


@pytest.mark.parametrize("n", [1, 16, 1000, 7])
def test_accumulate_n_equals_n_sample_images(xp, n):
    """One batched call with accumulate=N equals N-sample images of the float64 sum; trailing
    samples that do not fill an integration are not imaged."""
    rng = np.random.default_rng(3)
    xyz = rng.normal(0, 20, (10, 3)) * [1, 1, 0.1]
    freq = np.array([50e6, 70e6])
    T = 2000 if n == 1000 else 100 + 3   # 103 samples: 7 does not divide it, nor does 16
    X = rng.normal(size=(T, 2, 10, 2)) + 1j * rng.normal(size=(T, 2, 10, 2))
    X += point_source_efield(xyz, freq, 0.2, 0.1, 2.0, T, npol=2, rng=rng)
    lm = imaging.lm_grid(6).lm
    prods = ("XX", "YY", "U", "V")
    F = brute_fields(X, xyz, freq, lm)                   # (T, C, K, P) float64
    g = T // n
    Fg = F[:g * n].reshape(g, n, *F.shape[1:])
    xx = (np.abs(Fg[..., 0]) ** 2).mean(1)
    yy = (np.abs(Fg[..., 1]) ** 2).mean(1)
    xy = (Fg[..., 0] * np.conj(Fg[..., 1])).mean(1)
    ref = np.stack([xx, yy, 2 * xy.real, -2 * xy.imag], axis=2)       # (g, C, nprod, K)
    for method in ("direct", "covariance") if n >= 16 else ("direct",):
        img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm),
                                  products=prods, method=method, precision="fp64", accumulate=n)
        assert img.shape == (g, 2, 4, len(lm))
        assert rel_err(img, ref) < 1e-12, (method, rel_err(img, ref))
    op = DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), npol=2, precision="fp32")
    img32 = op.image(xp.asarray(X.astype(np.complex64)), prods, accumulate=n)
    assert rel_err(img32, ref) < 1e-5


def test_accumulate_with_autocorr_removed_and_flags(xp):
    rng = np.random.default_rng(5)
    xyz = rng.normal(0, 20, (9, 3)) * [1, 1, 0.1]
    freq = np.array([50e6, 60e6, 70e6])
    X = rng.normal(size=(64, 3, 9, 2)) + 1j * rng.normal(size=(64, 3, 9, 2))
    lm = imaging.lm_grid(6).lm
    w = np.ones((3, 9, 2), complex) * np.exp(1j * rng.random((3, 9, 2)))
    w[:, 2, 0] = 0                 # one antenna-pol flagged
    w[1] = 0                       # a whole channel flagged: it costs nothing and images as NaN
    op = DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), npol=2, weights=xp.asarray(w),
                     precision="fp64")
    assert op.chan_index is not None and to_np(op.chan_index).tolist() == [0, 2]
    img = to_np(op.image(xp.asarray(X), ("XX", "YY", "U"), remove_autocorr=True, accumulate=16))
    assert img.shape == (4, 3, 3, len(lm)) and np.all(np.isnan(img[:, 1]))
    for j in range(4):
        ref = brute_image(X[16 * j:16 * (j + 1)], xyz, freq, lm, ("XX", "YY", "U"), remove_autocorr=True,
                          weights=w)
        live = [0, 2]
        assert np.allclose(img[j][live], ref[live], rtol=0, atol=1e-12 * np.max(np.abs(ref[live])))


def test_remove_autocorr_does_not_touch_the_covariance(xp, sky_scene):
    xyz, freq, X, lm = sky_scene
    Xc = xp.asarray(as_complex(X).astype(np.complex64))
    op = DFTOperator(xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), npol=2)
    acc = op.accumulator(("I",), method="covariance", remove_autocorr=True)
    acc.add(Xc)
    before = to_np(acc._R).copy()
    img = acc.result()
    assert np.array_equal(to_np(acc._R), before)
    ref = brute_image(as_complex(X), xyz, freq, lm, ("I",), remove_autocorr=True)
    assert rel_err(img, ref) < 1e-5


def test_tolerance_never_picks_a_mode_whose_bound_exceeds_it():
    for device in ("cpu", "gpu", np):
        for tol in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-9, 1e-12):
            for ntime in (16, 1024, 25000):
                try:
                    p = plan.choose(tol, device, ntime=ntime)
                except ValueError as e:
                    assert "no route x precision" in str(e)
                    continue
                assert p.bound <= tol and p.predicted_s > 0
                assert precision_available(p.precision, device)
        # explicit choices are honoured
        assert plan.choose(1e-3, device, method="direct").method == "direct"
        assert plan.choose(1e-3, device, precision="fp64").precision == "fp64"
    with pytest.raises(ValueError, match="no route x precision"):
        plan.choose(1e-30)
    with pytest.raises(ValueError, match="tolerance must be a positive number"):
        plan.choose(-1)
    # the CPU never gets a tensor-core mode
    assert plan.choose(1e-1, "cpu").precision in ("fp32", "fp64")
    assert plan.choose(1e-1, np).precision in ("fp32", "fp64")


TENSOR_CORE = tuple(p for p, (_, _, tc) in PRECISIONS.items() if tc)


def _fastest_fp32(device, **problem):
    return min(plan.choose(1e-3, device, precision="fp32", method=m, **problem).predicted_s
               for m in ("direct", "covariance"))


@pytest.mark.parametrize("device", ["gpu", "gpu:1", "gpu:all"])
@pytest.mark.parametrize("tol", [1e-3, 1e-4])
def test_a_gpu_plan_is_a_tensor_core_mode_that_beats_fp32(device, tol):
    """The point of a tolerance on a GPU: at 1e-3 and 1e-4 the measured table has tensor-core modes
    whose bounds meet it and which are faster than fp32, so one of them is picked (case P problem).
    Needs no CuPy: a station plans for its GPU anywhere."""
    p = plan.choose(tol, device)
    assert p.device == "gpu" and p.precision in TENSOR_CORE, p
    assert p.bound <= tol
    assert p.predicted_s < _fastest_fp32(device)
    # the pick is the fastest row meeting the tolerance, by the table's own rates and cost's counts
    from bf_epic_blocks.imaging import cost
    counts = cost.route_cmacs(1024, 256, 3205, 2, 2)
    # (rows measured for one input only -- the fused integer modes, 4-bit voltages -- are not
    # candidates when the input is not said)
    rows = [r for r in plan.load_table()["rows"] if r["device"] == "gpu" and r["bound"] <= tol]
    best = min([r for r in rows if r.get("input") is None], key=lambda r: counts[r["method"]] / r["rate_cmac_s"])
    assert (p.method, p.precision) == (best["method"], best["precision"])
    # said 4-bit voltages, the fastest of all rows, integer modes included
    p4 = plan.choose(tol, device, sample_bits=4)
    best4 = min(rows, key=lambda r: counts[r["method"]] / r["rate_cmac_s"])
    assert (p4.method, p4.precision) == (best4["method"], best4["precision"])


def test_a_stand_in_namespace_is_refused_not_taken_for_the_cpu():
    """The old bug: a class with ``__name__ = 'cupy'`` in its body answers its own class name, so
    it planned for the CPU. A namespace must be the real module, a kind a string."""
    class FakeCupy:
        __name__ = "cupy"
    assert FakeCupy.__name__ == "FakeCupy"
    with pytest.raises(TypeError, match="device must be"):
        plan.choose(1e-4, FakeCupy)
    with pytest.raises(ValueError, match="device must be"):
        plan.choose(1e-4, "tpu")
    assert plan.device_kind("GPU:0,1") == "gpu" and plan.device_kind(np) == "cpu"
    assert precision_available("fp16", "gpu") and not precision_available("fp16", "cpu")


def test_tolerance_through_the_api(sky_scene):
    xyz, freq, X, lm = sky_scene
    ref = brute_image(as_complex(X), xyz, freq, lm, ("I",))
    img = imaging.dirty_image(as_complex(X), xyz, freq, lm, products=("I",), tolerance=1e-4)
    assert rel_err(img, ref) <= 1e-4
    with pytest.raises(ValueError, match="meets tolerance"):
        imaging.dirty_image(as_complex(X), xyz, freq, lm, tolerance=1e-9, precision="fp32")


def test_array_likes_are_accepted():
    rng = np.random.default_rng(1)
    xyz = rng.normal(0, 10, (5, 3))
    X = rng.normal(size=(4, 1, 5, 1)) + 1j * rng.normal(size=(4, 1, 5, 1))
    lm = [[0.0, 0.0], [0.1, 0.2]]
    got = imaging.dirty_image(X.tolist(), xyz.tolist(), [70e6], lm)
    assert np.allclose(got, imaging.dirty_image(X, xyz, np.array([70e6]), np.array(lm)))


def test_min_elevation_drops_pixels_near_the_horizon():
    full = imaging.lm_grid(32)
    cut = imaging.lm_grid(32, min_elevation_deg=20)
    n = np.sqrt(1 - (cut.lm ** 2).sum(1))
    assert cut.npix < full.npix and np.all(n >= np.sin(np.radians(20)) - 1e-12)
    kept_n = np.sqrt(1 - (full.lm ** 2).sum(1))
    assert cut.npix == int(np.sum(kept_n >= np.sin(np.radians(20))))
    with pytest.raises(ValueError, match="min_elevation_deg"):
        imaging.lm_grid(32, min_elevation_deg=95)


@pytest.mark.parametrize("precision, tol", [("tf32x3", 1e-6), ("fp16x3", 1e-6), ("tf32", 2e-3), ("fp16", 2e-3), ("bf16", 2e-2)])
def test_stacked_real_form_equals_the_complex_product(xp, precision, tol):
    """[[Dr, -Di], [Di, Dr]] @ [Br; Bi] = [Re DB; Im DB] at the mode's rounding (NumPy: emulated)."""
    from bf_epic_blocks.imaging.gemm import stack_operator, stack_rhs, stacked_matmul
    rng = np.random.default_rng(8)
    d = (rng.normal(size=(3, 20, 12)) + 1j * rng.normal(size=(3, 20, 12))).astype(np.complex64)
    b = (rng.normal(size=(3, 12, 9)) + 1j * rng.normal(size=(3, 12, 9))).astype(np.complex64)
    out = to_np(stacked_matmul(stack_operator(xp.asarray(d), precision), stack_rhs(xp.asarray(b), precision),
                               precision))
    ref = d.astype(np.complex128) @ b.astype(np.complex128)
    got = out[:, :20] + 1j * out[:, 20:]
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) < tol


def test_reductions_read_both_layouts(xp):
    """block_corr and row_dot give the same sums from complex and stacked GEMM outputs."""
    from bf_epic_blocks.imaging.reduce import block_corr, row_dot
    rng = np.random.default_rng(9)
    F = (rng.normal(size=(2, 7, 2 * 48)) + 1j * rng.normal(size=(2, 7, 2 * 48))).astype(np.complex64)
    S = np.stack([F.real, F.imag], axis=1).astype(np.float32)          # (c, 2, K, n)
    blocks = [(0, 0), (1, 1), (0, 1)]
    Fr = F.reshape(2, 7, 2, 48).astype(np.complex128)
    ref = np.stack([(Fr[:, :, p].reshape(2, 7, 3, 16) * np.conj(Fr[:, :, q].reshape(2, 7, 3, 16))).sum(-1)
                    for p, q in blocks], axis=1)                         # (c, nblk, K, g)
    ref = np.moveaxis(ref, -1, 0)                                        # (g, c, nblk, K)
    for arr, stacked in ((F, False), (S, True)):
        got = to_np(block_corr(xp.asarray(arr), blocks, 16, npol=2, stacked=stacked, scale=2.0))
        assert got.shape == (3, 2, 3, 7) and np.allclose(got, 2 * ref, rtol=1e-5, atol=1e-4)
    D = (rng.normal(size=(2, 7, 40)) + 1j * rng.normal(size=(2, 7, 40))).astype(np.complex64)
    M = (rng.normal(size=(2, 7, 80)) + 1j * rng.normal(size=(2, 7, 80))).astype(np.complex64)
    ref = np.stack([(M[:, :, b * 40:(b + 1) * 40] * np.conj(D)).sum(-1) for b in range(2)], axis=1)
    Ms = np.stack([M.real, M.imag], axis=1).astype(np.float32)
    for arr, stacked in ((M, False), (Ms, True)):
        got = to_np(row_dot(xp.asarray(arr), xp.asarray(D), 2, stacked=stacked, scale=0.5))
        assert got.shape == (2, 2, 7) and np.allclose(got, 0.5 * ref, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("method", ["direct", "covariance"])
def test_integer_input_with_weights_flags_and_autocorr_removed(xp, sky_scene, method):
    """Integer voltages with complex weights, a flagged antenna-pol and a flagged channel, the
    autocorrelations removed, every product: against the float64 sum (both the fast layout kernels
    and the weighted covariance are exercised)."""
    xyz, freq, X, lm = sky_scene
    xyz, X = xyz[-20:], X[:96, :, -20:]      # a smaller array (outrigger kept): the brute autocorrelation is slow
    rng = np.random.default_rng(12)
    w = np.exp(1j * rng.random((2, 20, 2))) * rng.uniform(0.5, 1.5, (2, 20, 2))
    w[:, 5, 1] = 0
    prods = ("XX", "YY", "XY", "V")
    ref = brute_image(as_complex(X), xyz, freq, lm, prods, remove_autocorr=True, weights=w)
    for precision in ("fp64", "fp32"):
        img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), method=method,
                                  precision=precision, products=prods, remove_autocorr=True, weights=xp.asarray(w))
        assert rel_err(img, ref) < (1e-11 if precision == "fp64" else 2e-6), (precision, rel_err(img, ref))
    unit = np.ones((2, 20, 2))
    unit[:, 7, 0] = 0
    ref = brute_image(as_complex(X), xyz, freq, lm, prods, weights=unit)
    img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray(freq), xp.asarray(lm), method=method,
                              precision="fp64", products=prods, weights=xp.asarray(unit))
    assert rel_err(img, ref) < 1e-11


def test_nonfinite_samples_are_zeroed_and_reported(xp, caplog):
    """A NaN or Inf voltage is treated as flagged for that sample: the image stays finite and equals
    the image of the data with those samples zeroed; the API logs how many were zeroed."""
    rng = np.random.default_rng(4)
    xyz = rng.normal(0, 20, (8, 3))
    X = rng.normal(size=(32, 2, 8, 2)) + 1j * rng.normal(size=(32, 2, 8, 2))
    X[3, 0, 2, 1] = np.nan
    X[7, 1, 5, 0] = np.inf + 0j
    X[9, 1, 5, 0] = complex(1.0, np.nan)
    clean = X.copy()
    clean[~np.isfinite(clean)] = 0
    lm = imaging.lm_grid(6).lm
    ref = brute_image(clean, xyz, [50e6, 60e6], lm, ("I", "V"))
    for method in ("direct", "covariance"):
        with caplog.at_level("WARNING"):
            img = imaging.dirty_image(xp.asarray(X), xp.asarray(xyz), xp.asarray([50e6, 60e6]), xp.asarray(lm),
                                      products=("I", "V"), method=method, precision="fp64")
        assert np.all(np.isfinite(to_np(img))) and rel_err(img, ref) < 1e-12
        assert "3 non-finite (NaN/Inf) voltage samples were zeroed" in caplog.text
        caplog.clear()


def _case_p(xp, nchan=2, seed=5):
    """Case P on a GPU: 256 antennas (an LWA-SV-like ellipse with z scatter and a 293 m outrigger), the
    64x64 all-sky grid's 3,205 pixels, 1,024 samples of a 4-bit sky (noise + four sources)."""
    rng = np.random.default_rng(seed)
    nant, T = 256, 1024
    r = 50 * np.sqrt(rng.random(nant))
    th = 2 * np.pi * rng.random(nant)
    xyz = np.stack([r * np.cos(th), 1.1 * r * np.sin(th), rng.normal(0, 0.3, nant)], axis=1)
    xyz[-1] = [-293.0, 0.0, 10.0]
    freq = np.linspace(60e6, 80e6, nchan)
    lm = imaging.lm_grid(64).lm
    X = (rng.normal(size=(T, nchan, nant, 2)) + 1j * rng.normal(size=(T, nchan, nant, 2))) / np.sqrt(2)
    for k, (l, m) in enumerate(((0.1, 0.3), (-0.4, 0.2), (0.5, -0.5), (0.0, 0.05))):
        X = X + point_source_efield(xyz, freq, l, m, 2.0 * (k + 1), T, npol=2, rng=rng)
    return xyz, freq, lm, as_complex(quantise4(X))


def _oracle_xx_yy(xp, X, xyz, freq, lm):
    """float64 XX, YY (nchan, 2, npix) on the device by the definition, D written out per channel."""
    l, m = xp.asarray(lm[:, 0]), xp.asarray(lm[:, 1])
    n = xp.sqrt(1 - l * l - m * m)
    x, y, z = (xp.asarray(xyz[:, i]) for i in range(3))
    Xd = xp.asarray(X, dtype=xp.complex128)
    out = []
    for c, nu in enumerate(freq):
        D = xp.exp(-2j * np.pi * nu / C * (l[:, None] * x + m[:, None] * y + n[:, None] * z)) / len(xyz)
        out.append(xp.stack([(xp.abs(D @ Xd[:, c, :, p].T) ** 2).mean(axis=1) for p in range(2)]))
    return to_np(xp.stack(out))


@pytest.mark.gpu
@pytest.mark.parametrize("tol", [1e-3, 1e-4, 1e-6])
def test_the_gpu_pick_meets_its_bound_on_case_p(tol):
    """On a GPU, the tolerance's pick for case P images case P within the pick's measured bound (and so
    within the tolerance), against a float64 sum by the definition."""
    from bf_epic_blocks.imaging._xp import gpu_available
    if not gpu_available():
        pytest.skip("needs CuPy and a CUDA device")
    import cupy
    xyz, freq, lm, X = _case_p(cupy)
    pick = plan.choose(tol, cupy, ntime=X.shape[0], nant=len(xyz), npix=len(lm), npol=2, nchan=len(freq))
    if tol >= 1e-4:
        assert pick.precision not in ("fp32", "fp64"), pick
    img = imaging.dirty_image(cupy.asarray(X.astype(np.complex64)), xyz, freq, lm, products=("XX", "YY"),
                              tolerance=tol)
    err = rel_err(img, _oracle_xx_yy(cupy, X, xyz, freq, lm))
    print(f"tolerance {tol:.0e}: {pick.method} {pick.precision}, bound {pick.bound:.1e}, measured {err:.2e}")
    assert err <= pick.bound <= tol


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("real,lead,weighted,placed", [(True, (70000,), False, False), (False, (3, 5), False, False),
                                                        (True, (2,), False, False), (True, (70000,), True, True),
                                                        (True, (4,), "per channel", True),
                                                        (False, (3, 5), "per channel", False)])
def test_products_kernel_equals_the_definition(real, lead, weighted, placed):
    """The products kernel against its definition written out in NumPy: out[..., c, p, k] =
    sum_b scale[c, b] (a[p, b] Re w corr + i[p, b] Im w corr), with more (g, c) rows than one grid row
    holds (70,000), complex and real (the fused modes') correlations, a per-pixel weight w (the
    pattern's B_p conj(B_q), shared by the channels or per channel) and the products placed on a grid
    in the same pass (cells with no pixel NaN)."""
    import cupy as cp
    from bf_epic_blocks.imaging.reduce import product_coefficients, products_from_blocks
    rng = np.random.default_rng(7)
    blocks = [(0, 0), (1, 1)] if real else [(0, 0), (1, 1), (0, 1)]
    products = ("I", "Q", "XX") if real else ("I", "Q", "U", "V")
    C, K = 2, 37
    shape = lead + (C, len(blocks), K)
    corr = rng.normal(size=shape).astype(np.float32)
    if not real:
        corr = (corr + 1j * rng.normal(size=shape)).astype(np.complex64)
    scale = rng.uniform(0.5, 2, (C, len(blocks))).astype(np.float32)
    coef = np.asarray(product_coefficients(products, blocks), np.float64)        # (nprod, nblk, 2)
    w = None
    if weighted:
        w = (rng.uniform(0.2, 1, (C if weighted == "per channel" else 1, len(blocks), K))
             * np.exp(1j * rng.uniform(0, 6, (1, len(blocks), K)))).astype(np.complex64)
    gather = None
    if placed:
        gather = np.full(50, -1, np.int32)
        gather[rng.choice(50, K, replace=False)] = np.arange(K)
    got = products_from_blocks(cp.asarray(corr), cp.asarray(scale), cp.asarray(coef, np.float32),
                               weight=None if w is None else cp.asarray(w),
                               gather=None if gather is None else cp.asarray(gather)).get()
    z = corr.astype(np.complex128) * scale[..., None]
    if w is not None:
        z = z * w
    want = np.zeros(lead + (C, len(products), K))
    for p in range(len(products)):
        for b in range(len(blocks)):
            want[..., :, p, :] += coef[p, b, 0] * z[..., :, b, :].real + coef[p, b, 1] * z[..., :, b, :].imag
    if gather is not None:
        cells = np.full(want.shape[:-1] + (gather.size,), np.nan)
        cells[..., gather >= 0] = want[..., gather[gather >= 0]]
        want = cells
        assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.allclose(got, want, rtol=1e-5, atol=1e-5, equal_nan=True)
