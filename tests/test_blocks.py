"""Blocks in a pipeline against the core called directly, and against point-source truth."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import (ArraySinkBlock, ArraySourceBlock, CalFoldBlock, DFTImagerBlock, bfp,
                                   efield_header)
from bf_epic_blocks.imaging.calibration import FS_HZ, GainTable, apply_direction_independent, cable_weights
from bf_epic_blocks.blocks import _compat
from bf_epic_blocks.runtime.dtypes import pack_ci4
from conftest import HAVE_GPU
from truth import brute_image, point_source_efield

C_LIGHT = 299792458.0
DT = 40e-6
TPF = int(round(DT * FS_HZ))


def to_np(a):
    return a.get() if hasattr(a, "get") else np.asarray(a)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(1)
    nst, nchan, T = 12, 3, 360
    xyz = np.concatenate([rng.normal(0, 20, (nst - 1, 3)) * [1, 1, 0.05], [[-290.0, 3.0, 10.0]]])
    freq = 60e6 + 25e3 * np.arange(nchan)
    ints = rng.integers(-8, 8, size=(T, nchan, nst, 2)) + 1j * rng.integers(-8, 8, size=(T, nchan, nst, 2))
    delay = rng.uniform(100e-9, 600e-9, (nst, 2, nchan))
    gain = rng.uniform(0.5, 2.0, (nst, 2, nchan))
    flags = np.zeros((nst, 2), bool)
    flags[4, 1] = True
    lm = np.concatenate([imaging.lm_grid(10).lm, [[0.3, 0.4]]])
    return dict(xyz=xyz, freq=freq, ints=ints, delay=delay, gain=gain, flags=flags, lm=lm, T=T)


def station(s, with_cable=True):
    st = {"name": "test", "xyz_m": s["xyz"], "flags": s["flags"]}
    if with_cable:
        st["cable_delay_s"], st["cable_gain"] = s["delay"], s["gain"]
    return st


def run_pipeline(X, hdr, gulp, accumulate, pixels, space="system", **kw):
    cal_kw = {k: kw.pop(k) for k in ("cable", "gains", "flags", "pattern") if k in kw}
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(X, hdr, gulp_nframe=gulp, space=space)
        cal = CalFoldBlock(src, **cal_kw)
        img = DFTImagerBlock(cal, pixels, accumulate, **kw)
        sink = ArraySinkBlock(img)
        p.run()
    return sink, img


def expected(s, X, accumulate, weights_for_frame, **kw):
    """Core calls per integration: for each run of frames with one weight set, image and time-weight."""
    out = []
    n = X.shape[0] // accumulate
    for j in range(n):
        frames = np.arange(j * accumulate, (j + 1) * accumulate)
        keys = [weights_for_frame(f)[0] for f in frames]
        acc = 0
        for key in dict.fromkeys(keys):
            sel = frames[np.array(keys) == key]
            w = weights_for_frame(sel[0])[1]
            img = imaging.dirty_image(X[sel], s["xyz"], s["freq"], s["lm"], weights=w, precision="fp64", **kw)
            acc = acc + img * len(sel)
        out.append(acc / accumulate)
    return np.stack(out)


@pytest.mark.parametrize("dtype", ["ci4", "cf32"])
@pytest.mark.parametrize("gulp,accumulate", [(64, 40), (64, 64), (64, 150), (100, 30)])
def test_calfold_imager_equals_core_with_folded_weights(xp, scene, dtype, gulp, accumulate):
    s = scene
    X = s["ints"]
    data = pack_ci4(X) if dtype == "ci4" else X.astype(np.complex64)
    t0 = 10**12
    # a calibration table whose second solution starts inside a gulp (frame 77)
    rng = np.random.default_rng(3)
    g = rng.uniform(0.5, 1.5, (2, 3, 12, 2)) * np.exp(2j * np.pi * rng.random((2, 3, 12, 2)))
    table = GainTable([t0 - 5 * TPF, t0 + 77 * TPF], g)
    hdr = efield_header("obs", t0, s["freq"], DT, station(s), dtype=dtype)
    sink, blk = run_pipeline(data, hdr, gulp, accumulate, s["lm"], space="cuda" if xp.__name__ == "cupy" else "system",
                             gains=table, products="stokes", remove_autocorr=True)
    got = sink.result(0)
    wc = cable_weights(s["delay"], s["gain"], s["freq"]) * ~s["flags"][None]

    def wff(f):
        i = 0 if f < 77 else 1
        return i, wc * g[i]

    ref = expected(s, X.astype(np.complex128), accumulate, wff, products="stokes", remove_autocorr=True)
    assert got.shape == ref.shape == (s["T"] // accumulate, 3, 4, len(s["lm"]))
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= 1e-6
    assert blk.img_stats["frames_dropped_partial"] == s["T"] % accumulate
    hdr_out = sink.headers[0]
    assert hdr_out["_tensor"]["labels"] == ["time", "freq", "pol", "pixel"]
    assert hdr_out["imager"]["accumulate_frames"] == accumulate
    assert hdr_out["calibration"]["gain_table"]["nsol"] == 2


@pytest.mark.parametrize("tol", [1e-3, 1e-5, 1e-6])
def test_imager_with_a_tolerance_picks_for_its_device(xp, scene, tol):
    """DFTImagerBlock(tolerance=) as `imager.tolerance` in a YAML: the fastest mode whose measured bound
    meets it on the device the block images on (on a GPU a tensor-core mode down to fp16x3's bound of
    2e-6, then fp32; never on the CPU), and images within the tolerance of float64 truth; the pick
    is in the header."""
    s = scene
    gpu = xp.__name__ == "cupy"
    hdr = efield_header("tol", 0, s["freq"], DT, station(s, with_cable=False), dtype="ci4")
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(pack_ci4(s["ints"]), hdr, gulp_nframe=120, space="cuda" if gpu else "system")
        img = DFTImagerBlock(src, s["lm"], 120, products="stokes", tolerance=tol)
        sink = ArraySinkBlock(img)
        p.run()
    assert img.plan is not None and img.plan.device == ("gpu" if gpu else "cpu")
    assert img.plan.bound <= tol and img.precision == img.plan.precision
    tensor_core = img.precision not in ("fp32", "fp64")
    assert tensor_core == (gpu and tol > 1e-6), img.plan
    assert sink.headers[0]["imager"]["precision"] == img.precision
    assert sink.headers[0]["imager"]["tolerance"] == tol
    ref = expected(s, s["ints"].astype(np.complex128), 120, lambda f: (0, ~s["flags"][None]), products="stokes")
    got = sink.result(0)
    assert got.shape == ref.shape
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= tol
    with bfp.Pipeline():
        with pytest.raises(ValueError, match="tolerance must be a positive number"):
            DFTImagerBlock(ArraySourceBlock(pack_ci4(s["ints"]), hdr, 8), s["lm"], 4, tolerance=0)


@pytest.mark.parametrize("gain", [False, True])
def test_apply_direction_independent_against_float64(xp, gain):
    """The calibration product, fused on a GPU and written into a given array, against float64: x * w * g,
    and exact zeros for a dead antenna-pol even where its gain is NaN."""
    rng = np.random.default_rng(11)
    x = (rng.standard_normal((7, 3, 5, 2)) + 1j * rng.standard_normal((7, 3, 5, 2))).astype(np.complex64)
    w = (rng.uniform(0.5, 2, (3, 5, 2)) * np.exp(2j * np.pi * rng.random((3, 5, 2)))).astype(np.complex64)
    g = (rng.uniform(0.5, 2, (3, 5, 2)) * np.exp(2j * np.pi * rng.random((3, 5, 2)))).astype(np.complex64)
    live = np.ones((5, 2), bool)
    live[2, 1] = False
    g[:, 2, 1] = np.nan
    ref = x.astype(np.complex128) * w.astype(np.complex128) * (g.astype(np.complex128) if gain else 1)
    ref[:, :, 2, 1] = 0
    out = xp.full(x.shape, np.nan, np.complex64)
    got = apply_direction_independent(xp.asarray(x), xp.asarray(w), xp.asarray(live),
                                      xp.asarray(g) if gain else None, out=out)
    assert got is out
    got = got.get() if xp.__name__ == "cupy" else got
    assert np.all(got[:, :, 2, 1] == 0)
    np.testing.assert_allclose(got, ref, rtol=3e-7, atol=0)
    plain = apply_direction_independent(xp.asarray(x), xp.asarray(w))   # no flags, a new array
    plain = plain.get() if xp.__name__ == "cupy" else plain
    np.testing.assert_allclose(plain, x.astype(np.complex128) * w, rtol=3e-7, atol=0)


def test_cable_terms_recover_a_point_source(scene):
    """Independent truth: voltages corrupted by known cables; after CalFold the source has its power."""
    s = scene
    rng = np.random.default_rng(8)
    l0, m0 = 0.3, 0.4
    X = point_source_efield(s["xyz"], s["freq"], l0, m0, 2.0, 64, npol=2, rng=rng)
    corrupt = np.sqrt(s["gain"]) * np.exp(-2j * np.pi * s["freq"][None, None, :] * s["delay"])  # (nst, 2, nchan)
    Xr = X * np.moveaxis(corrupt, 2, 0)[None]
    hdr = efield_header("pt", 0, s["freq"], DT, station(s), dtype="cf32")
    sink, _ = run_pipeline(Xr.astype(np.complex64), hdr, 32, 64, s["lm"], products=("XX", "YY", "I"))
    got = sink.result(0)[0]
    assert np.argmax(got[0, 2]) == len(s["lm"]) - 1
    np.testing.assert_allclose(got[:, :, -1], [[2.0, 2.0, 4.0]] * 3, rtol=1e-5)
    # and without the cable correction the source is lost
    sink2, _ = run_pipeline(Xr.astype(np.complex64), hdr, 32, 64, s["lm"], cable=False, products=("I",))
    assert sink2.result(0)[0, 0, 0, -1] < 2.0


def test_dipole_pattern_carried_to_imager(scene):
    s = scene
    l0, m0 = 0.3, 0.4
    X = point_source_efield(s["xyz"], s["freq"], l0, m0, 1.0, 32, npol=2)
    hdr = efield_header("pt", 0, s["freq"], DT, {"xyz_m": s["xyz"]}, dtype="cf32")
    sink, _ = run_pipeline(X.astype(np.complex64), hdr, 32, 32, s["lm"], cable=False, pattern="dipole",
                           products=("XX", "YY"))
    got = sink.result(0)[0, 0, :, -1]
    np.testing.assert_allclose(got, [1 - m0 ** 2, 1 - l0 ** 2], rtol=1e-5)  # |B|^2 of a short dipole
    assert sink.headers[0]["calibration"]["pattern"] == "dipole"

    def flat(lm, f, npol):
        return np.full((len(lm), npol), 0.5)
    sink, _ = run_pipeline(X.astype(np.complex64), hdr, 32, 32, s["lm"], cable=False, pattern=flat,
                           products=("XX",))
    np.testing.assert_allclose(sink.result(0)[0, 0, 0, -1], 0.25, rtol=1e-5)


def test_grid_output_layout_and_nan_outside(scene):
    s = scene
    grid = imaging.lm_grid(16)
    X = point_source_efield(s["xyz"], s["freq"], 0.5, 0.0, 1.0, 20, npol=2)
    hdr = efield_header("g", 0, s["freq"], DT, {"xyz_m": s["xyz"]}, dtype="cf32")
    sink, _ = run_pipeline(X.astype(np.complex64), hdr, 20, 10, grid, cable=False, products=("I",))
    out = sink.result(0)
    assert out.shape == (2, 3, 1, 16, 16)
    assert sink.headers[0]["_tensor"]["labels"] == ["time", "freq", "pol", "m", "l"]
    assert np.all(np.isnan(out[..., ~grid.mask])) and np.all(np.isfinite(out[..., grid.mask]))
    peak = np.unravel_index(np.nanargmax(out[0, 0, 0]), (16, 16))
    assert peak == (8, 8 + 4), "a source East of the zenith (l = 0.5) is 4 columns right of the centre"


def test_tracking_pixels_move_the_operator(scene):
    """A pixel that moves at each integration: one operator built, moved three times in place, each
    integration's image the float64 definition's at that integration's direction."""
    s = scene

    def track(tag):
        frame = (tag - 0) // TPF
        return [[0.1 + 0.01 * (frame // 10), 0.0]]

    X = point_source_efield(s["xyz"], s["freq"], 0.1, 0.0, 1.0, 40, npol=2)
    hdr = efield_header("t", 0, s["freq"], DT, {"xyz_m": s["xyz"]}, dtype="cf32")
    sink, blk = run_pipeline(X.astype(np.complex64), hdr, 16, 10, track, cable=False, products=("XX",))
    got = sink.result(0)
    assert got.shape == (4, 3, 1, 1)
    assert blk.img_stats["operator_builds"] == 1 and blk.img_stats["operator_moves"] == 3
    np.testing.assert_allclose(got[0, :, 0, 0], 1.0, rtol=1e-5)  # first integration on the source
    for i in range(4):
        truth = brute_image(X[10 * i:10 * (i + 1)].astype(np.complex64), s["xyz"], s["freq"],
                            np.array([[0.1 + 0.01 * i, 0.0]]), ("XX",))
        np.testing.assert_allclose(got[i], truth, rtol=1e-5, atol=1e-6)
    assert got[3, 0, 0, 0] < 0.9                                  # the pixel left the source


def stepping_dirs(step):
    """Two watch directions that move every ``step`` frames: tag -> [[l, m], [l, m]]."""
    def dirs(tag):
        k = (tag // TPF) // step
        return [[0.31 - 0.05 * k, -0.22], [-0.4, 0.1 + 0.02 * k]]
    return dirs


def assert_watch_images(got, s, X, dirs, bound):
    """Each 16-frame Stokes I watch image (n, nchan, 1, 2) against the float64 definition at that image's
    directions, to ``bound`` of its peak (the scene's flagged inputs left out)."""
    w = np.where(s["flags"], 0.0, 1.0)[None]
    for i in range(len(got)):
        truth = brute_image(X[16 * i:16 * (i + 1)], s["xyz"], s["freq"], np.array(dirs(16 * i * TPF)), ("I",),
                            weights=w)
        assert np.abs(got[i] - truth).max() < bound * np.abs(truth).max(), i


@pytest.mark.parametrize("precision", ["fp32", "i8x2"])
def test_watch_directions_ride_beside_the_grid_on_a_second_ring(xp, scene, precision):
    """DFTImagerBlock(watch=): two directions imaged with a grid's pixels by one operator, moved each 32
    frames (in place: one build), written to the second output ring: each 16-frame image the float64
    definition's at that image's directions, the grid's images those of an imager without them, and the
    watch ring's header a tracking pixel list. On a GPU from ci4 bytes in i8x2 the grid and the
    directions come out of the fused kernel together."""
    s = scene
    if precision == "i8x2" and xp.__name__ != "cupy":
        pytest.skip("the fused integer modes run on a GPU")
    gpu = xp.__name__ == "cupy"
    grid = imaging.lm_grid(12)
    dirs = stepping_dirs(32)
    X = s["ints"][:128]
    hdr = efield_header("w", 0, s["freq"], DT, station(s, with_cable=False), dtype="ci4")

    class HalfKept:
        """FlagWeights' interface: every image kept half a point source's power."""
        def take(self, seq, first, n):
            return np.full((n, 3), 0.5)                  # (images, channels)

    def run(watch, flag_weights=None):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=64, space="cuda" if gpu else "system")
            img = DFTImagerBlock(src, grid, 16, products=("I",), precision=precision, method="direct", watch=watch,
                                 flag_weights=flag_weights)
            sink = ArraySinkBlock(img)
            wsink = ArraySinkBlock(img.watch_ring) if watch is not None else None
            p.run()
        return img, sink, wsink

    img, sink, wsink = run(dirs)
    got = wsink.result(0)
    assert got.shape == (8, 3, 1, 2)
    assert img.img_stats["operator_builds"] == 1 and img.img_stats["operator_moves"] == 3
    assert_watch_images(got, s, X, dirs, {"fp32": 1e-5, "i8x2": 4e-5}[precision])
    whdr = wsink.headers[0]
    assert whdr["_tensor"]["labels"] == ["time", "freq", "pol", "pixel"] and whdr["pixels"]["kind"] == "track"
    assert whdr["_tensor"]["scales"][0] == sink.headers[0]["_tensor"]["scales"][0]
    _, alone, _ = run(None)
    np.testing.assert_allclose(sink.result(0), alone.result(0), rtol=1e-6, atol=1e-7 * np.nanmax(alone.result(0)))
    _, half, whalf = run(dirs, HalfKept())             # images rescaled to the whole array's units: both rings
    np.testing.assert_allclose(whalf.result(0), 2 * got, rtol=1e-6)
    np.testing.assert_allclose(half.result(0), 2 * sink.result(0), rtol=1e-6)
    with pytest.raises(ValueError, match="ride beside a grid"):
        DFTImagerBlock(ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=64), s["lm"], 16, watch=dirs)


@pytest.mark.gpu
@pytest.mark.skipif(not HAVE_GPU, reason="needs CuPy and a CUDA device")
def test_a_lone_integration_of_a_longer_gulp_is_imaged_by_the_batched_call(scene, monkeypatch):
    """Watch directions that step every 48 frames, gulps of 64, images of 16: the integrations at frames 48
    and 128 are each alone between a step and a gulp's edge. They go through the same batched call as
    their neighbours, not the operator's graph-replayed image() (whose eager first call decodes the bytes
    and places the images with kernels nothing else uses, compiled while a station's data flow); every
    image is the float64 definition's at its own directions."""
    from bf_epic_blocks.imaging.dft import DFTOperator
    s = scene
    grid = imaging.lm_grid(12)
    dirs = stepping_dirs(48)
    X = s["ints"][:192]
    hdr = efield_header("lone", 0, s["freq"], DT, station(s, with_cable=False), dtype="ci4")
    calls = []
    image = DFTOperator.image

    def spy(self, *a, **kw):
        calls.append(kw.get("decode"))
        return image(self, *a, **kw)
    monkeypatch.setattr(DFTOperator, "image", spy)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=64, space="cuda")
        img = DFTImagerBlock(src, grid, 16, products=("I",), precision="i8x2", method="direct", watch=dirs)
        wsink = ArraySinkBlock(img.watch_ring)
        p.run()
    assert img.img_stats["operator_moves"] == 3 and calls == []
    got = wsink.result(0)
    assert got.shape == (12, 3, 1, 2)
    assert_watch_images(got, s, X, dirs, 4e-5)


def test_tracking_rebuilds_log_the_plan_once(scene, caplog):
    """An operator built once and moved three times in one sequence: its plan is logged once."""
    s = scene
    X = point_source_efield(s["xyz"], s["freq"], 0.1, 0.0, 1.0, 40, npol=2)
    hdr = efield_header("t", 0, s["freq"], DT, {"xyz_m": s["xyz"]}, dtype="cf32")
    with caplog.at_level("INFO", logger="bf_epic_blocks.blocks.dft_imager"):
        _, blk = run_pipeline(X.astype(np.complex64), hdr, 16, 10,
                              lambda tag: [[0.1 + 0.01 * ((tag // TPF) // 10), 0.0]], cable=False, products=("XX",))
    assert blk.img_stats["operator_builds"] == 1 and blk.img_stats["operator_moves"] == 3
    plans = [r for r in caplog.records if r.getMessage().startswith("DFTImagerBlock: dft imager")]
    assert len(plans) == 1, [r.getMessage() for r in plans]


def test_flagged_station_garbage_never_reaches_the_image(scene):
    s = scene
    X = s["ints"][:64].astype(np.complex64)
    X[:, :, 4, 1] = np.nan
    hdr = efield_header("f", 0, s["freq"], DT, station(s, with_cable=False), dtype="cf32")
    sink, _ = run_pipeline(X, hdr, 64, 64, s["lm"], cable=False, products="stokes")
    assert np.all(np.isfinite(sink.result(0)))


def test_bad_headers_name_the_problem(scene):
    s = scene
    X = s["ints"][:8].astype(np.complex64)
    hdr = efield_header("b", 0, s["freq"], DT, {"xyz_m": s["xyz"]}, dtype="cf32")
    bad = dict(hdr, _tensor=dict(hdr["_tensor"], labels=["time", "chan", "station", "pol"]))
    with pytest.raises(Exception, match=r"CalFoldBlock.*expected E-field axes labelled"):
        run_pipeline(X, bad, 8, 8, s["lm"], cable=False)
    nost = {k: v for k, v in hdr.items() if k != "station"}
    with pytest.raises(Exception, match=r"station"):
        run_pipeline(X, nost, 8, 8, s["lm"], cable=False)
    with pytest.raises(Exception, match=r"cable_delay_s"):
        run_pipeline(X, hdr, 8, 8, s["lm"], cable=True)
    with bfp.Pipeline():
        with pytest.raises(ValueError, match="accumulate must be a positive integer"):
            DFTImagerBlock(ArraySourceBlock(X, hdr, 8), s["lm"], 0)
        with pytest.raises(ValueError, match="below the horizon"):
            DFTImagerBlock(ArraySourceBlock(X, hdr, 8), [[0.9, 0.9]], 4)


@pytest.mark.bifrost
@pytest.mark.skipif(not _compat.HAVE_BIFROST, reason="needs real Bifrost (import bifrost) as the runtime")
def test_real_bifrost_pipeline_matches_core(scene):
    """Inside real Bifrost: ArraySource -> CalFold -> DFTImager -> ArraySink equals dirty_image."""
    import bifrost.pipeline
    assert _compat.HAVE_BIFROST and _compat.RUNTIME == "bifrost"
    assert issubclass(bfp.Pipeline, bifrost.pipeline.Pipeline)
    assert issubclass(DFTImagerBlock, bifrost.pipeline.TransformBlock)
    s = scene
    X = s["ints"][:96]
    hdr = efield_header("rb", 0, s["freq"], DT, station(s), dtype="ci4")
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(pack_ci4(X), hdr, gulp_nframe=40)  # short last gulp of 16
        cal = CalFoldBlock(src, cable=True)
        img = DFTImagerBlock(cal, s["lm"], 48, products="stokes")
        sink = ArraySinkBlock(img)
        assert isinstance(p, bifrost.pipeline.Pipeline)
        p.run()
    w = cable_weights(s["delay"], s["gain"], s["freq"]) * ~s["flags"][None]
    ref = np.stack([imaging.dirty_image(X[j * 48:(j + 1) * 48].astype(np.complex128), s["xyz"], s["freq"],
                                        s["lm"], weights=w, precision="fp64", products="stokes")
                    for j in range(2)])
    got = sink.result(0)
    assert got.shape == ref.shape == (2, 3, 4, len(s["lm"]))
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= 1e-6
    assert sink.headers[0]["_tensor"]["labels"] == ["time", "freq", "pol", "pixel"]


@pytest.mark.parametrize("gulp,accumulate", [(60, 60), (120, 30), (64, 40)])
def test_imager_folding_static_calibration_equals_calfold(xp, scene, gulp, accumulate):
    """What bf-epic run builds on a GPU for static calibration: no CalFoldBlock, the cable terms and
    flags folded into the imager's operator, the 4-bit samples imaged as integers (one CUDA-graph
    replay per whole integration in a gulp, the accumulator otherwise). Same images as the float64
    core with those weights, and as CalFoldBlock -> DFTImagerBlock; on a grid, NaN below the horizon."""
    s = scene
    space = "cuda" if xp.__name__ == "cupy" else "system"
    data = pack_ci4(s["ints"])
    hdr = efield_header("obs", 10**12, s["freq"], DT, station(s), dtype="ci4")
    grid = imaging.lm_grid(10)
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(data, hdr, gulp_nframe=gulp, space=space)
        img = DFTImagerBlock(src, grid, accumulate, products="stokes", cable=True)
        sink = ArraySinkBlock(img)
        p.run()
    got = sink.result(0)
    ref_sink, _ = run_pipeline(data, hdr, gulp, accumulate, grid, space=space, cable=True, products="stokes")
    wc = cable_weights(s["delay"], s["gain"], s["freq"]) * ~s["flags"][None]
    core = expected(dict(s, lm=grid.lm), s["ints"].astype(np.complex128), accumulate, lambda f: (0, wc),
                    products="stokes")
    core = grid.to_image(core)
    nimg = s["T"] // accumulate
    assert got.shape == ref_sink.result(0).shape == core.shape == (nimg, 3, 4, 10, 10)
    assert img.img_stats["images"] == nimg and img.img_stats["frames_dropped_partial"] == s["T"] % accumulate
    np.testing.assert_array_equal(np.isnan(got), ~np.broadcast_to(grid.mask, got.shape))
    scale = np.nanmax(np.abs(core))
    assert np.nanmax(np.abs(got - core)) / scale <= 1e-6
    assert np.nanmax(np.abs(got - ref_sink.result(0))) / scale <= 1e-6
    # the cable terms were folded in: the image header leaves them behind (they are nstand x npol x
    # nchan, 16 MB of JSON per ring at 784 channels) and keeps the rest of the station
    st = sink.headers[0]["station"]
    assert "cable_delay_s" not in st and "cable_gain" not in st
    np.testing.assert_array_equal(st["xyz_m"], s["xyz"])


def _ngpu():
    from bf_epic_blocks.imaging._xp import cupy_or_none, gpu_available
    return cupy_or_none().cuda.runtime.getDeviceCount() if gpu_available() else 0


@pytest.mark.gpu
@pytest.mark.skipif(_ngpu() < 1, reason="needs CuPy and a CUDA device")
@pytest.mark.parametrize("method", ["auto", "covariance"])
@pytest.mark.parametrize("pixels", ["list", "grid"])
def test_imager_on_several_gpus_equals_calfold_then_one_device(scene, method, pixels):
    """DFTImagerBlock(gpus=...) with the cable terms folded into its operators (no CalFoldBlock) equals
    CalFoldBlock -> DFTImagerBlock on the CPU: same images, channels gathered in order (the covariance
    route submits each of a gulp's two integrations before taking the first's images). On a grid the
    GPUs place the pixels (NaN below the horizon) and write straight into the pinned output span."""
    s = scene
    pix = s["lm"] if pixels == "list" else imaging.lm_grid(10)
    data = pack_ci4(s["ints"])
    hdr = efield_header("obs", 10**12, s["freq"], DT, station(s), dtype="ci4")
    ref_sink, _ = run_pipeline(data, hdr, 60, 30, pix, cable=True, products="stokes")
    with bfp.Pipeline() as p:
        src = ArraySourceBlock(data, hdr, gulp_nframe=60, space="cuda_host")
        img = DFTImagerBlock(src, pix, 30, products="stokes", gpus=list(range(max(1, min(_ngpu(), 3)))),
                             cable=True, method=method)
        sink = ArraySinkBlock(img)
        p.run()
    got, ref = sink.result(0), ref_sink.result(0)
    npix = (len(s["lm"]),) if pixels == "list" else (10, 10)
    assert got.shape == ref.shape == (s["T"] // 30, 3, 4) + npix
    assert img.img_stats["images"] == s["T"] // 30
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) / np.nanmax(np.abs(ref)) <= 1e-6


@pytest.mark.gpu
@pytest.mark.parametrize("fold", [True, False])
def test_warm_up_before_a_stream_changes_no_image(scene, fold):
    """DFTImagerBlock.warm_up (the runner calls it before a live source starts) runs a small
    integration through the block's own route and forgets it: the stream's images are those of a
    block never warmed (bit for bit) and within 1e-6 of float64 truth, its counters untouched."""
    pytest.importorskip("cupy")
    s = scene
    hdr = efield_header("warm", 0, s["freq"], DT, station(s, with_cable=fold), dtype="ci4")
    got = []
    for warm in (False, True):
        with bfp.Pipeline() as p:
            src = ArraySourceBlock(pack_ci4(s["ints"]), hdr, gulp_nframe=120, space="cuda")
            feed = src if fold else CalFoldBlock(src, cable=False)
            img = DFTImagerBlock(feed, s["lm"], 120, products="stokes", precision="fp32", cable=fold)
            sink = ArraySinkBlock(img)
        took = img.warm_up("ci4" if fold else "cf32") if warm else None
        p.run()
        assert took is None or took > 0
        assert img.img_stats["images"] == s["T"] // 120 and img.img_stats["operator_builds"] == 1
        got.append(sink.result(0))
    assert np.array_equal(got[0], got[1])
    w = (lambda f: (0, ~s["flags"][None])) if not fold else None
    if w is not None:
        ref = expected(s, s["ints"].astype(np.complex128), 120, w, products="stokes")
        assert np.max(np.abs(got[1] - ref)) / np.max(np.abs(ref)) <= 1e-6


def test_warm_up_on_the_cpu_does_nothing(scene):
    s = scene
    hdr = efield_header("warm", 0, s["freq"], DT, station(s, with_cable=False), dtype="ci4")
    with bfp.Pipeline():
        src = ArraySourceBlock(pack_ci4(s["ints"]), hdr, gulp_nframe=120)
        img = DFTImagerBlock(src, s["lm"], 120)
    assert img.warm_up() == 0.0 and img.img_stats["operator_builds"] == 0


@pytest.mark.gpu
@pytest.mark.parametrize("sets", [[], ["calibration.cable=false", "imager.precision=fp16", "imager.method=covariance"]])
def test_the_runner_warms_a_live_imager_before_its_socket_opens(sets):
    """bf-epic run of a live YAML on a GPU compiles the imager's route in a scratch graph first."""
    pytest.importorskip("cupy")
    from pathlib import Path
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import warm_live_imager
    from bf_epic_blocks.station import load_station
    yml = Path(__file__).resolve().parents[1] / "pipelines" / "lwasv_udp_live.yaml"
    cfg = load_config(yml, ["device=gpu", "imager.grid.size=16", "imager.accumulate_frames=64", *sets])
    assert warm_live_imager(cfg, load_station("lwasv")) > 0


def test_header_values_become_plain_json():
    """efield_header turns NumPy arrays and scalars (at any depth, in lists and tuples too) into the
    Python values JSON writes, and leaves plain values as they are (the fast path for lists of them)."""
    import json
    from bf_epic_blocks.blocks.headers import efield_header
    station = {"xyz_m": np.arange(6.0).reshape(2, 3), "flags": [[False, np.bool_(True)], (True, False)],
               "cable_delay_s": [[[1e-9, 2e-9], [np.float32(3e-9), 4e-9]], [[5e-9, 6e-9], [7e-9, 8e-9]]],
               "stand_ids": np.array([7, 9], np.int16), "name": "x", "lat_deg": np.float64(34.1)}
    hdr = efield_header("h", 0, [60e6, 60.025e6], 4e-5, station, extra=(np.int64(3), [np.float32(0.5)]))
    st = hdr["station"]
    assert st["xyz_m"] == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]] and type(st["xyz_m"][1][2]) is float
    assert st["flags"] == [[False, True], [True, False]] and type(st["flags"][0][1]) is bool
    assert type(st["flags"][1]) is list
    assert st["cable_delay_s"][0][1][0] == float(np.float32(3e-9)) and type(st["cable_delay_s"][0][1][0]) is float
    assert st["stand_ids"] == [7, 9] and type(st["stand_ids"][0]) is int
    assert type(st["lat_deg"]) is float and st["lat_deg"] == 34.1
    assert hdr["extra"] == [3, [0.5]] and type(hdr["extra"][0]) is int
    assert json.loads(json.dumps(hdr)) == hdr
