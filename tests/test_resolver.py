"""One accuracy knob, one resolver: the YAML (config -> runner), the imaging blocks and
``imaging.dirty_image`` get their route and precision from :func:`bf_epic_blocks.imaging.plan.resolve`,
and give the same Plan for the same tolerance and problem; w-stacking included. Planning needs no GPU."""
import numpy as np
import pytest

from bf_epic_blocks import imaging
from bf_epic_blocks.blocks import ArraySinkBlock, ArraySourceBlock, DFTImagerBlock, WStackBlock, bfp, efield_header
from bf_epic_blocks.imaging import plan as planner
from bf_epic_blocks.imaging.plan import Plan, Problem, resolve
from bf_epic_blocks.pipeline import runner
from bf_epic_blocks.pipeline.config import ConfigError, load_config

YAML = """
source: {{kind: simulated, duration_s: 0.01, quantize: {quantize}, channels: {{count: 2}}}}
imager: {{kind: {kind}, grid: {{size: 8}}, accumulate_frames: 32, products: [I]{tolerance}}}
calibration: {{pattern: none}}
device: {device}
"""

TOLERANCES = [1e-2, 1e-4, 1e-6, None]


def config(tol, device, kind="dft", quantize=True, extra=()):
    text = YAML.format(quantize=str(quantize).lower(), kind=kind, device=device,
                       tolerance="" if tol is None else f", tolerance: {tol}")
    return load_config(text, list(extra))


def yaml_plan(cfg):
    """The plan the runner hands the imager block it builds for ``cfg`` (build_graph's own call)."""
    station = runner.load_station_for(cfg)
    dev = "cpu" if cfg["device"] == "cpu" else "gpu"
    return runner.imager_plan_for(cfg, runner._pixels(cfg, station), station, dev), station


def efield_hdr(cfg, station, dtype):
    freq = runner.channel_freqs(cfg)
    return efield_header("r", 0, freq, 1.0 / cfg["source"]["channels"]["width_hz"], station.to_header(freq),
                         dtype=dtype, npol=2)


def block_plan(cfg, station, dtype, device, block=DFTImagerBlock, **kw):
    """The plan a block constructed with the YAML's tolerance resolves for the same sequence, on
    ``device`` (a GPU block's device is the one thing set by hand here: a CUDA ring needs a GPU)."""
    im = cfg["imager"]
    hdr = efield_hdr(cfg, station, dtype)
    pixels = runner._pixels(cfg, station)
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((32, 2, station.nstand, 2), np.complex64), efield_hdr(cfg, station, "cf32"), 32)
        blk = block(src, pixels, im["accumulate_frames"], products=im["products"], tolerance=im["tolerance"], **kw)
    blk._device = lambda: device
    return blk.plan_for(hdr)


@pytest.mark.parametrize("device", ["cpu", "gpu"])
@pytest.mark.parametrize("tol", TOLERANCES)
@pytest.mark.parametrize("quantize", [True, False])
def test_yaml_and_block_give_the_same_plan(device, tol, quantize):
    """The runner's plan for a YAML (what build_graph hands the block) is the plan a block built with
    the same tolerance resolves itself, for the input that reaches it: 4-bit integers on one GPU that
    folds the calibration (a quantised sky), complex voltages from CalFoldBlock otherwise."""
    cfg = config(tol, device, quantize=quantize)
    want, station = yaml_plan(cfg)
    assert isinstance(want, Plan) and want.tolerance == tol and want.imager == "dft"
    dtype = "ci4" if runner.imager_sample_bits(cfg, device) == 4 else "cf32"
    assert (want.input_kind == "ci4") == (device == "gpu" and quantize)
    got = block_plan(cfg, station, dtype, device)
    assert got == want
    if tol is not None:
        assert want.bound <= tol
    else:
        assert want.precision == "fp32" and want.overrides == ()


@pytest.mark.parametrize("tol", TOLERANCES)
def test_dirty_image_uses_the_same_plan(tol):
    """``dirty_image`` on the same problem (the YAML's pixels, antennas, samples, channels) resolves the
    same plan, and images with it: the image is within the plan's bound of float64 truth."""
    cfg = config(tol, "cpu", quantize=False)
    want, station = yaml_plan(cfg)
    lm = runner._pixels(cfg, station).lm
    freq = runner.channel_freqs(cfg)
    rng = np.random.default_rng(3)
    X = rng.normal(size=(32, 2, station.nstand, 2)) + 1j * rng.normal(size=(32, 2, station.nstand, 2))
    weights = (~station.flags)[None].astype(np.complex128)
    img, got = imaging.dirty_image(X, station.xyz_m, freq, lm, products=["I"], weights=weights, tolerance=tol,
                                   return_plan=True)
    assert got == want
    ref = imaging.dirty_image(X, station.xyz_m, freq, lm, products=["I"], weights=weights, precision="fp64")
    assert np.max(np.abs(img - ref)) / np.max(np.abs(ref)) <= (want.bound or 1e-5)


def test_dirty_image_calls_the_resolver(monkeypatch):
    """The API picks nothing itself: the plan it images with is the resolver's answer."""
    seen = []
    real = planner.resolve

    def spy(*a, **kw):
        seen.append(real(*a, **kw))
        return seen[-1]
    monkeypatch.setattr(planner, "resolve", spy)
    rng = np.random.default_rng(0)
    X = rng.normal(size=(8, 1, 5, 2)) + 1j * rng.normal(size=(8, 1, 5, 2))
    _, got = imaging.dirty_image(X, rng.normal(0, 10, (5, 3)), [70e6], [[0.0, 0.0]], tolerance=1e-3,
                                 return_plan=True)
    assert seen and got is seen[0]


@pytest.mark.parametrize("kind", ["wstack", "moff"])
@pytest.mark.parametrize("tol", [4e-2, 4e-4, 4e-6, None])
def test_wstack_yaml_and_block_give_the_same_plan(kind, tol):
    """imager.tolerance is the w-stacking and MOFF imagers' knob too: epsilon = tolerance / 4 (their
    tested bound is 4 epsilon), the default tolerance 4e-4 keeps epsilon 1e-4, the work precision
    follows epsilon."""
    cfg = config(tol, "cpu", kind=kind)
    want, station = yaml_plan(cfg)
    asked = planner.GRIDDED_DEFAULT_TOLERANCE if tol is None else tol
    assert want.imager == kind and want.tolerance == tol and want.epsilon == pytest.approx(asked / 4)
    assert want.precision == ("fp32" if asked / 4 >= 1e-5 else "fp64")
    assert want.bound == (None if kind == "moff" else pytest.approx(asked))
    got = block_plan(cfg, station, "cf32", "cpu", block=WStackBlock, moff=(kind == "moff"))
    assert got == want


def test_gridded_route_follows_the_problem():
    """auto: covariance w-gridding when the integration is at least as long as the array has antennas."""
    for ntime, route in ((16, "efield"), (64, "covariance")):
        p = resolve(1e-3, device="cpu", problem=Problem(100, 32, ntime), imager="wstack")
        assert p.method == route and p.overrides == ()
    p = resolve(1e-3, device="gpu", problem=Problem(100, 32, 64), imager="wstack", method="efield")
    assert p.method == "efield" and p.overrides == ("method",)


def test_old_epsilon_is_an_error_naming_tolerance():
    with pytest.raises(ConfigError, match=r"imager\.epsilon.*imager\.tolerance"):
        config(None, "cpu", kind="wstack", extra=["imager.epsilon=1e-3"])
    with pytest.raises(ConfigError, match=r"imager\.epsilon.*imager\.tolerance"):
        load_config("source: {kind: simulated}\nimager: {kind: wstack, epsilon: 1.0e-4}")
    with pytest.raises(ConfigError, match=r"imager\.tolerance.*\[4e-14, 0\.4\]"):
        config(0.5, "cpu", kind="wstack")
    hdr = efield_header("e", 0, [70e6], 4e-5, {"xyz_m": np.zeros((4, 3))}, dtype="cf32")
    with bfp.Pipeline():
        src = ArraySourceBlock(np.zeros((8, 1, 4, 2), np.complex64), hdr, 8)
        with pytest.raises(TypeError, match="tolerance"):
            WStackBlock(src, imaging.lm_grid(8), 4, epsilon=1e-4)
        with pytest.raises(ValueError, match="tolerance"):
            WStackBlock(src, imaging.lm_grid(8), 4, tolerance=0.9)


def test_overrides_are_validated_and_recorded():
    """precision / method are expert overrides: their names are checked against what is allowed
    (the fused integer modes included), and a plan says which restricted its choice."""
    prob = Problem(3205, 256, 1024)
    with pytest.raises(ValueError, match=r"precision must be one of .*'i8x2', 'i8x3'"):
        resolve(1e-3, device="gpu", problem=prob, precision="fp8")
    with pytest.raises(ValueError, match=r"method must be one of \('auto', 'direct', 'covariance'\)"):
        resolve(1e-3, device="gpu", problem=prob, method="fast")
    with pytest.raises(ValueError, match="input kind must be one of"):
        resolve(1e-3, device="gpu", problem=prob, input_kind="ci3")
    with pytest.raises(ValueError, match="tensor cores"):
        resolve(None, device="cpu", problem=prob, precision="fp16")
    with pytest.raises(ValueError, match="direct route's XX/YY powers"):
        resolve(None, device="gpu", problem=prob, precision="i8x2", method="covariance", input_kind="ci4")
    p = resolve(1e-3, device="gpu", problem=prob, precision="fp32")
    assert p.precision == "fp32" and p.overrides == ("precision",) and p.bound <= 1e-3
    free = resolve(1e-3, device="gpu", problem=prob)
    assert free.overrides == () and free.predicted_s <= p.predicted_s


def test_an_override_is_recorded_in_the_header():
    """The header says what was picked, whoever asked: tolerance, bound, overrides, for a block run
    with a tolerance and an expert precision, on the CPU."""
    rng = np.random.default_rng(2)
    xyz = rng.normal(0, 15, (6, 3))
    freq = np.array([70e6])
    hdr = efield_header("h", 0, freq, 4e-5, {"xyz_m": xyz}, dtype="cf32")
    X = (rng.normal(size=(16, 1, 6, 2)) + 1j * rng.normal(size=(16, 1, 6, 2))).astype(np.complex64)
    with bfp.Pipeline() as p:
        img = DFTImagerBlock(ArraySourceBlock(X, hdr, 16), [[0.0, 0.0], [0.2, 0.1]], 16, products=["I"],
                             tolerance=1e-4, precision="fp64")
        sink = ArraySinkBlock(img)
        p.run()
    im = sink.headers[0]["imager"]
    assert im["precision"] == "fp64" and im["tolerance"] == 1e-4 and im["overrides"] == ["precision"]
    assert im["error_bound"] == img.plan.bound <= 1e-4 and im["method"] == img.plan.method
    # and with no tolerance the mode is still the resolver's, and said so
    with bfp.Pipeline() as p:
        img = DFTImagerBlock(ArraySourceBlock(X, hdr, 16), [[0.0, 0.0]], 16, products=["I"])
        sink = ArraySinkBlock(img)
        p.run()
    im = sink.headers[0]["imager"]
    assert im["tolerance"] is None and im["precision"] == "fp32" and im["overrides"] == []
    assert im["method"] == resolve(None, device="cpu", problem=Problem(1, 6, 16, 1, 2, ["I"])).method


def test_cli_tolerance_reaches_the_block(tmp_path):
    """`--set imager.tolerance=...` reaches the block the runner builds: its plan and its header."""
    cfg = config(None, "cpu", extra=["imager.tolerance=1e-3", f"output.dir={tmp_path}"])
    g = runner.build_graph(cfg)
    assert g.imager.plan.tolerance == 1e-3 and g.imager.tolerance == 1e-3
    assert g.imager.plan == yaml_plan(cfg)[0]


def test_choose_is_the_resolver_for_a_dft_problem():
    """plan.choose (sizes as keywords, sample bits) answers what resolve answers for that Problem."""
    for dev in ("cpu", "gpu"):
        for bits, kind in ((None, "complex"), (4, "ci4")):
            a = planner.choose(1e-4, dev, ntime=64, nant=100, npix=500, nchan=3, products="stokes", sample_bits=bits)
            b = resolve(1e-4, device=dev, problem=Problem(500, 100, 64, 3, 2, "stokes"), input_kind=kind)
            assert a == b


def test_gridded_precision_is_the_gridders_work_precision():
    from bf_epic_blocks.imaging.fieldgrid import work_dtype
    for tol in (0.4, 4e-3, 4.4e-5, 4e-5, 3.9e-5, 4e-8, 4e-14):
        p = resolve(tol, device="cpu", problem=Problem(10, 4, 8), imager="wstack")
        assert p.precision == {np.complex64: "fp32", np.complex128: "fp64"}[work_dtype(p.epsilon)], tol
