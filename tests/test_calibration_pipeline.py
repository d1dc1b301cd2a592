"""Calibration from the sky in pipelines: `bf-epic calibrate`, `calibration.solve` live beside the
imager, and their tables, against corruption the test chooses.

The corruption here is the station's own cable model: the simulator delays and scales every input by
LSL's cable terms, and the pipeline is told not to remove them (``calibration.cable: false``), so the
solver must find them (delays of hundreds of ns, gains scattered by tens of per cent). Truth: the
simulator's cable factor, and the same sky with the cables removed exactly, unquantised (in Jy).
"""
import numpy as np
import pytest
from astropy.io import fits

from bf_epic_blocks.conventions import FS_HZ
from bf_epic_blocks.imaging.skycal import gain_error
from bf_epic_blocks.io.gaintable import read_solved_table
from bf_epic_blocks.pipeline import runner
from bf_epic_blocks.pipeline.config import load_config

SIM = "pipelines/lwasv_sim_allsky.yaml"
QUARTER = 6250       # frames in 0.25 s


def _cfg(tmp, name, *extra):
    return load_config(SIM, ["source.duration_s=1.0", "source.channels.count=4", f"imager.accumulate_frames={QUARTER}",
                             "source.diffuse=null",
                             "calibration.pattern=none", "device=cpu", f"output.dir={tmp / name}", "output.png=false",
                             *extra])


def _images(folder):
    files = sorted(folder.glob("*_i[0-9][0-9][0-9][0-9].fits"))
    return np.stack([np.asarray(fits.getdata(f), np.float64)[0] for f in files])     # (nimg, nchan, N, N)


def _err(a, b):
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.max(np.abs(a[ok] - b[ok])) / np.max(np.abs(b[ok])))


def _cable_truth(cfg):
    from bf_epic_blocks.sky.efield import cable_factor
    from bf_epic_blocks.station.tables import load_station
    st = load_station("lwasv")
    f = runner.channel_freqs(cfg)
    g = cable_factor(np.moveaxis(st.cable_delay_s(f), -1, 0), np.moveaxis(st.cable_gain(f), -1, 0), f, f.size,
                     st.nstand, 2)
    return g, st


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cal")
    solve = ("calibration.solve={cadence_s: 0.5, integration_s: 0.25, apply_delay_s: 0, pattern: none, "
             "smooth_channels: 4, diffuse: false}")
    live = _cfg(tmp, "live", "calibration.cable=false", solve)
    s_live = runner.run(live, show_progress=False)
    truth = _cfg(tmp, "truth", "source.quantize=false")
    runner.run(truth, show_progress=False)
    raw = _cfg(tmp, "raw", "calibration.cable=false", "source.quantize=false")
    runner.run(raw, show_progress=False)
    return tmp, live, s_live


def test_live_solutions_follow_their_schedule_and_undo_the_cables(runs):
    tmp, cfg, summary = runs
    assert summary["solver"]["solutions"] == 2 and summary["solver"]["failures"] == 0
    t = read_solved_table(tmp / "live" / "lwasv_sim_allsky_gains.npz")
    tag0 = int(round(__import__("astropy.time", fromlist=["Time"]).Time(cfg["source"]["start"]).unix * FS_HZ))
    tpf = int(round(FS_HZ / 25000))
    # solution k sums frames [k 0.5 s, k 0.5 s + 0.25 s) and applies from the frame after them (no delay asked)
    assert t["valid_from"].tolist() == [tag0 + QUARTER * tpf, tag0 + 3 * QUARTER * tpf]
    g, st = _cable_truth(cfg)
    for k in range(2):
        flags = t["flags"][k]
        # at most 1% of the good inputs flagged (the outrigger's long cable leaves its Y input the weakest)
        assert (flags & ~st.flags).sum() <= 0.01 * (~st.flags).sum(), t["flag_reason"][k][flags & ~st.flags]
        err, per = gain_error(t["gains"][k], g, ~flags)
        assert err < 0.02, err
    assert (tmp / "live" / "lwasv_sim_allsky_gains.png").stat().st_size > 10_000
    # drawn by the helper process, not by the pipeline's own threads (matplotlib holds the interpreter)
    assert summary["solver"]["pngs"] >= 1 and summary["solver"]["pngs_in_helper"] == summary["solver"]["pngs"]


def test_an_offset_schedule_sums_and_applies_later_by_the_offset(tmp_path):
    """solve.offset_s (tunings on one GPU solve in turn): solution k sums [k C + offset, k C + offset + I)
    and applies from the frame after; the gains still undo the cables."""
    solve = ("calibration.solve={cadence_s: 0.5, integration_s: 0.25, offset_s: 0.25, apply_delay_s: 0, "
             "pattern: none, smooth_channels: 4, diffuse: false}")
    cfg = _cfg(tmp_path, "offset", "calibration.cable=false", solve)
    summary = runner.run(cfg, show_progress=False)
    assert summary["solver"]["solutions"] == 2 and summary["solver"]["failures"] == 0
    t = read_solved_table(tmp_path / "offset" / "lwasv_sim_allsky_gains.npz")
    tag0 = int(round(__import__("astropy.time", fromlist=["Time"]).Time(cfg["source"]["start"]).unix * FS_HZ))
    tpf = int(round(FS_HZ / 25000))
    assert t["valid_from"].tolist() == [tag0 + 2 * QUARTER * tpf, tag0 + 4 * QUARTER * tpf]
    g, st = _cable_truth(cfg)
    for k in range(2):
        err, _ = gain_error(t["gains"][k], g, ~t["flags"][k])
        assert err < 0.02, err


def test_a_solve_out_of_memory_is_skipped_and_counted_not_the_run(tmp_path, monkeypatch):
    """A live solve that finds too little memory (on a GPU, CuPy's OutOfMemoryError: a MemoryError) is a
    counted, logged failure: the run goes on, the next solve is posted."""
    from bf_epic_blocks.blocks.gain_solver import GainSolverBlock
    real, calls = GainSolverBlock._solve, []

    def solve(self, k, *args, **kw):
        calls.append(k)
        if len(calls) == 1:
            raise MemoryError("Out of memory allocating 822,083,584 bytes")
        return real(self, k, *args, **kw)
    monkeypatch.setattr(GainSolverBlock, "_solve", solve)
    solve_cfg = ("calibration.solve={cadence_s: 0.5, integration_s: 0.25, apply_delay_s: 0, pattern: none, "
                 "smooth_channels: 4, diffuse: false}")
    summary = runner.run(_cfg(tmp_path, "oom", "calibration.cable=false", solve_cfg), show_progress=False)
    s = summary["solver"]
    assert calls == [0, 1]
    assert s["out_of_memory"] == 1 and s["failures"] == 1 and s["solutions"] == 1
    assert "out of memory" in s["failure_reasons"][0]


@pytest.mark.parametrize("where", ["add", "mean"])
def test_summing_out_of_memory_drops_that_integration_not_the_run(tmp_path, monkeypatch, where):
    """An integration whose sums (part-way through) or whose hand-over (the sums' mean) find too little
    memory, as the station's did on one GPU under its pool's limit, is a counted, logged failure: the run
    goes on with the images it was making, and the next integration is summed afresh and solved -- its
    gains as good as an undisturbed run's."""
    from bf_epic_blocks.imaging.skycal import CovarianceSums
    real, calls = getattr(CovarianceSums, where), []

    def failing(self, *args, **kw):
        calls.append(1)
        if len(calls) == (2 if where == "add" else 1):      # in the first integration
            raise MemoryError("Out of memory allocating 268,435,456 bytes")
        return real(self, *args, **kw)
    monkeypatch.setattr(CovarianceSums, where, failing)
    solve_cfg = ("calibration.solve={cadence_s: 0.5, integration_s: 0.25, apply_delay_s: 0, pattern: none, "
                 "smooth_channels: 4, diffuse: false}")
    cfg = _cfg(tmp_path, "oom", "calibration.cable=false", solve_cfg)
    summary = runner.run(cfg, show_progress=False)
    s = summary["solver"]
    assert s["out_of_memory"] == 1 and s["failures"] == 1 and s["solutions"] == 1, s
    assert "out of memory while summing" in s["failure_reasons"][0]
    assert summary["images"] == 4 and summary["frames_imaged"] == summary["frames_read"] == 4 * QUARTER   # none lost
    t = read_solved_table(tmp_path / "oom" / "lwasv_sim_allsky_gains.npz")
    tpf = int(round(FS_HZ / 25000))
    tag0 = int(round(__import__("astropy.time", fromlist=["Time"]).Time(cfg["source"]["start"]).unix * FS_HZ))
    assert t["valid_from"].tolist() == [tag0 + 3 * QUARTER * tpf]      # solution 1's alone
    g, _ = _cable_truth(cfg)
    err, _ = gain_error(t["gains"][0], g, ~t["flags"][0])
    assert err < 0.02, err


def test_images_after_a_solution_are_the_truth_and_before_it_are_not(runs):
    tmp, _, _ = runs
    live, truth, raw = (_images(tmp / n) for n in ("live", "truth", "raw"))
    assert live.shape == truth.shape and len(live) == 4
    # image 0 holds the frames before solution 0: uncalibrated; images 1-3 are made with the solutions
    assert _err(raw[0], truth[0]) > 0.3                       # the cables, uncorrected, spoil the sky
    for i in (1, 2, 3):
        assert _err(live[i], truth[i]) < 0.03, (i, _err(live[i], truth[i]))


def test_offline_calibrate_writes_a_table_the_pipeline_takes(tmp_path):
    from bf_epic_blocks.pipeline import cli
    out = tmp_path / "t.npz"
    code = cli.main([ "calibrate", SIM, "-o", str(out), "--no-progress", "-q",
                      "--set", "source.duration_s=0.3", "--set", "source.channels.count=4", "--set", "source.diffuse=null",
                      "--set", "imager.accumulate_frames=7500", "--set", "calibration.cable=false",
                      "--set", "calibration.solve={integration_s: 0.25, pattern: none, diffuse: false}"])
    assert code == 0
    t = read_solved_table(out)
    cfg = load_config(SIM, ["source.channels.count=4"])
    g, st = _cable_truth(cfg)
    err, _ = gain_error(t["gains"][0], g, ~t["flags"][0])
    assert err < 0.02
    # offline: valid from the first frame of its data, and the provenance names the model and settings
    tag0 = int(round(__import__("astropy.time", fromlist=["Time"]).Time(cfg["source"]["start"]).unix * FS_HZ))
    assert t["valid_from"].tolist() == [tag0]
    assert t["provenance"]["model"]["sources"] == ["CygA", "CasA"]
    assert t["provenance"]["settings"]["min_baseline_lambda"] == 4.0
    # calibration.gains_table takes it as it is
    from bf_epic_blocks.imaging.calibration import GainTable
    tab = GainTable.load(out)
    tab.check_shape(4, 256, 2)


def test_calibrate_refuses_what_it_cannot_do(tmp_path, capsys):
    from bf_epic_blocks.pipeline import cli
    base = ["calibrate", SIM, "-o", str(tmp_path / "t.npz"), "--no-progress", "-q",
            "--set", "source.channels.count=2", "--set", "imager.accumulate_frames=100"]
    # data too short: fewer samples than min_samples
    assert cli.main(base + ["--set", "source.duration_s=0.004"]) == 1
    assert "data too short to solve: 100 samples" in capsys.readouterr().err
    # no model source above the horizon limit
    assert cli.main(base + ["--set", "source.duration_s=0.05",
                            "--set", "calibration.solve={sources: [VirA], integration_s: 0.04}"]) == 1
    assert "no model source above 10 deg" in capsys.readouterr().err
    # a table name that is not .npz
    assert cli.main(base[:3] + [str(tmp_path / "t.txt")] + base[4:] + ["--set", "source.duration_s=0.05"]) == 1
    assert "is an .npz file" in capsys.readouterr().err


def test_solve_keys_are_checked():
    from bf_epic_blocks.pipeline.config import ConfigError
    with pytest.raises(ConfigError, match="not both"):
        load_config(SIM, ["calibration.gains_table=pipelines/lwasv_sim_allsky.yaml", "calibration.solve={}"])
    with pytest.raises(ConfigError, match="must be <= cadence_s"):
        load_config(SIM, ["calibration.solve={cadence_s: 1, integration_s: 2}"])
    with pytest.raises(ConfigError, match="offset_s: must be < cadence_s"):
        load_config(SIM, ["calibration.solve={cadence_s: 1, integration_s: 0.5, offset_s: 1}"])
    with pytest.raises(ConfigError, match="unknown source 'Sun'"):
        load_config(SIM, ["source.sources=[Sun]"])          # the simulator has no Sun
    cfg = load_config(SIM, ["calibration.solve={sources: [Sun, CygA]}"])
    assert cfg["calibration"]["solve"]["sources"] == ["Sun", "CygA"]


def test_solutions_folded_into_the_operator_give_the_voltages_calibrated(runs):
    """The GPU pipeline folds live solutions into the imager's operator (no CalFoldBlock); the CPU one
    applies them to the voltages. Both take effect at the same integration: the images agree."""
    from bf_epic_blocks.blocks import ArraySinkBlock, DFTImagerBlock, LiveGainTable, bfp
    tmp, cfg, _ = runs
    station = runner.load_station_for(cfg)
    pixels = runner._pixels(cfg, station)
    with bfp.Pipeline() as p:
        src, _, _ = runner._recorded_source(cfg, None, None, station, 1024, "system", None)
        table = LiveGainTable()
        runner.gain_solver_block(cfg, src, table, None)
        img = DFTImagerBlock(src, pixels, QUARTER, plan=runner.imager_plan_for(cfg, pixels, station, "cpu"),
                             products=["I"], remove_autocorr=True, cable=False, pattern=False, gains=table)
        sink = ArraySinkBlock(img)
    p.run()
    folded = sink.result()                                             # (nimg, nchan, nprod, N, N)
    assert img.img_stats["solutions_applied"] == 2
    # each solution went in once: in place, or by a new operator where it flagged other inputs
    assert img.img_stats["operator_builds"] - 1 + img.img_stats.get("operator_reweights", 0) == 2
    live = _images(tmp / "live")
    assert folded.shape[0] == live.shape[0] == 4
    for i in range(4):
        assert _err(folded[i, :, 0], live[i]) < 1e-5, (i, _err(folded[i, :, 0], live[i]))


def test_a_live_table_holds_a_bounded_history_with_absolute_indices():
    """A pipeline solves for weeks: the live table keeps its last KEEP solutions, and the indices the
    consumers hold (CalFoldBlock, the imager's folded operator) stay those of the whole run."""
    from bf_epic_blocks.blocks import LiveGainTable
    t = LiveGainTable()
    assert t.index([5]).tolist() == [-1] and t.segments(0, 1, 3) == [(0, 3, -1)]
    n = LiveGainTable.KEEP + 5
    for k in range(n):
        t.post(100 * (k + 1), np.full((1, 2, 1), k + 1.0))
    assert len(t.valid_from) == LiveGainTable.KEEP
    last = n - 1
    assert t.index([100 * n, 100 * n + 50]).tolist() == [last, last]
    assert t.corrections(last)[0, 0, 0] == n and t.corrections(5)[0, 0, 0] == 6
    assert t.segments(100 * (n - 1), 10, 20) == [(0, 10, last - 1), (10, 20, last)]
    sol = t.solution(last)
    assert np.all(sol == n)


def _solution(rng, nchan=4, nant=5, npol=2):
    from bf_epic_blocks.imaging.skycal import Solution
    corr = rng.normal(size=(nchan, nant, npol)) + 1j * rng.normal(size=(nchan, nant, npol))
    flags = rng.random((nant, npol)) < 0.3
    reasons = np.where(flags, "dead", "")
    q = {k: rng.random((nant, npol)) for k in ("gain_amp", "residual", "power", "power_per_gain", "delay_s")}
    q["converged"] = rng.random((nchan, npol)) < 0.9
    return Solution(gains=1 / corr, corrections=corr, flags=flags, reasons=reasons, quality=q)


def test_a_table_part_holds_its_solutions_in_arrays_made_once(tmp_path):
    """TablePart: a file's entries (complex64 corrections, flags, reasons, quality) in arrays made at the
    part's first solution for the whole part and filled in place, so a solver's memory does not grow while a
    part fills; the solver's own complex128 gains are not kept. The file equals one written from the list."""
    from bf_epic_blocks.io.gaintable import TablePart, write_gain_table
    rng = np.random.default_rng(0)
    sols = [_solution(rng) for _ in range(20)]
    part = TablePart(3)
    part.add(sols[0])
    made = {k: (a.ctypes.data, a.nbytes) for k, a in part._a.items()}
    part.add(sols[1])
    part.add(sols[2])
    assert {k: (a.ctypes.data, a.nbytes) for k, a in part._a.items()} == made
    assert not any(a.dtype == np.complex128 for a in part._a.values())
    with pytest.raises(ValueError, match="holds 3"):
        part.add(sols[3])
    a = part.arrays()
    assert a["gains"].dtype == np.complex64 and a["gains"].shape == (3, 4, 5, 2)
    assert np.array_equal(a["gains"], np.stack([s.corrections for s in sols[:3]]).astype(np.complex64))
    assert np.array_equal(part.entry(-1)["flag_reason"], sols[2].reasons)
    grown = TablePart()                                          # no limit: the arrays double, nothing lost
    for s in sols:
        grown.add(s)
    assert len(grown) == 20 and np.array_equal(grown.arrays()["flags"], np.stack([s.flags for s in sols]))
    kw = dict(freq_hz=np.arange(4.0), stand_ids=np.arange(5), time_unix=np.arange(20.0), provenance={})
    t1 = read_solved_table(write_gain_table(tmp_path / "a.npz", np.arange(20), grown, **kw))
    t2 = read_solved_table(write_gain_table(tmp_path / "b.npz", np.arange(20), sols, **kw))
    assert t1.keys() == t2.keys()
    for k in t1:
        if k != "provenance":
            assert np.array_equal(t1[k], t2[k]), k
    assert np.array_equal(t1["delay_s"], np.stack([s.quality["delay_s"] for s in sols]))


def test_live_tables_are_written_in_parts(tmp_path):
    """calibration.solve.solutions_per_file: a run of weeks keeps one part in memory and on each write."""
    cfg = _cfg(tmp_path, "parts", "calibration.cable=false", "source.duration_s=0.6", "source.channels.count=2",
               "calibration.solve={cadence_s: 0.1, integration_s: 0.04, apply_delay_s: 0, pattern: none, "
               "diffuse: false, solutions_per_file: 2, png: false, min_samples: 500}",
               "imager.accumulate_frames=1000")
    s = runner.run(cfg, show_progress=False)
    assert s["solver"]["solutions"] == 6
    names = sorted(p.name for p in (tmp_path / "parts").glob("*_gains*.npz"))
    assert names == ["lwasv_sim_allsky_gains.npz", "lwasv_sim_allsky_gains_p001.npz", "lwasv_sim_allsky_gains_p002.npz"]
    tabs = [read_solved_table(tmp_path / "parts" / n) for n in names]
    vf = np.concatenate([t["valid_from"] for t in tabs])
    assert len(vf) == 6 and np.all(np.diff(vf) > 0)          # nothing lost, in time order
    assert all(str(tmp_path / "parts" / n) in s["files"] for n in names)


def test_a_simulated_sky_without_galactic_emission_is_not_fitted_a_diffuse_term():
    """A live solver's fitted diffuse term needs a sky that has one: every shipped simulated pipeline
    (each tuning of a station) either simulates the Galactic sky or solves without the term, and the
    mismatch, set by hand, is named (and logged when the solver is built)."""
    from pathlib import Path

    import yaml

    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import diffuse_mismatch
    pipes = sorted((Path(__file__).resolve().parents[1] / "pipelines").glob("*.yaml"))
    solving = 0
    for p in pipes:
        if (yaml.safe_load(p.read_text()).get("source") or {}).get("kind") != "simulated":
            continue                         # a file or live source: its input need not be here
        cfg = load_config(p)
        for tc in cfg.get("tunings") or [cfg]:
            if tc["source"]["kind"] == "simulated" and tc["calibration"].get("solve"):
                solving += 1
                assert diffuse_mismatch(tc) is None, (p.name, tc["name"])
    assert solving >= 3                      # the calibration story and the station's two tunings
    cfg = load_config(Path(__file__).resolve().parents[1] / "pipelines" / "lwasv_sim_station.yaml",
                      ["calibration.solve.diffuse=true"])
    why = diffuse_mismatch(cfg["tunings"][0])
    assert why and "source.diffuse" in why and "calibration.solve.diffuse: false" in why
