"""tools/gpu_check.py's comparison of two runs' outputs (the GPU check itself needs a GPU): it must
pass equal outputs and catch each kind of difference a GPU bug would leave."""
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("astropy")
pytest.importorskip("h5py")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import gpu_check  # noqa: E402


def _fits(path, data):
    from astropy.io import fits
    path.parent.mkdir(parents=True, exist_ok=True)
    fits.PrimaryHDU(np.asarray(data, np.float32)).writeto(path, overwrite=True)


def _cube(path, data):
    import h5py
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f.create_dataset("images", data=np.asarray(data, np.float16))
        f.create_dataset("time_tag", data=np.arange(len(data), dtype=np.int64))


def _cands(path, rows):
    from bf_epic_blocks.io.candidates import write_candidates
    from astropy.table import Table
    t = Table(rows=rows, names=("sequence", "image", "pixel", "dm", "width", "snr"))
    write_candidates(path, t)


@pytest.fixture
def sky():
    rng = np.random.default_rng(0)
    img = rng.uniform(1, 100, (2, 16, 16))
    img[:, :3] = np.nan                                  # below the horizon
    return img


def test_equal_outputs_pass_and_differences_are_caught(tmp_path, sky):
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    _fits(c / "a.fits", sky)
    _fits(g / "a.fits", sky * (1 + 1e-7))
    _cube(c / "cube.h5", sky)
    with np.errstate(invalid="ignore"):
        _cube(g / "cube.h5", np.float16(sky) + np.spacing(np.float16(sky)))   # one float16 rounding apart
    (c / "a.png").write_bytes(b"png")
    (g / "a.png").write_bytes(b"png")
    res = gpu_check.compare_dirs(g, c)
    assert all(v["ok"] for v in res.values()), res
    assert res["a.fits"]["rel_diff"] < 1e-6 and res["cube.h5"]["ulp_diff"] <= 1.0

    worse = sky.copy()
    worse[1, 8, 8] += 1e-3 * np.nanmax(sky)              # a 1e-3 error in one pixel
    _fits(g / "a.fits", worse)
    with np.errstate(invalid="ignore"):
        _cube(g / "cube.h5", np.float16(sky) + 3 * np.spacing(np.float16(sky)))
    masked = sky.copy()
    masked[0, 10, 10] = np.nan
    _fits(g / "b.fits", masked)
    _fits(c / "b.fits", sky)
    (c / "only_cpu.png").write_bytes(b"png")
    res = gpu_check.compare_dirs(g, c)
    assert not res["a.fits"]["ok"] and res["a.fits"]["rel_diff"] == pytest.approx(1e-3, rel=1e-3)
    assert not res["cube.h5"]["ok"] and res["cube.h5"]["ulp_diff"] >= 2
    assert res["cube.h5"]["rel_diff_beyond_ulp"] > 1e-3
    assert not res["b.fits"]["ok"] and "NaN masks differ" in res["b.fits"]["problem"]
    assert not res["only_cpu.png"]["ok"]


def test_a_cube_value_near_zero_may_move_many_of_its_units_but_not_the_cube_s_scale(tmp_path, sky):
    """A simulated sky's GPU and CPU voltages differ by ~1e-5 of their rms: a cube value near zero then
    moves by many of its own float16 units, yet by less than one unit at the cube's largest value."""
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    ref = sky.copy()
    ref[0, 5, 5] = 0.3                                   # float16 spacing there: 2.4e-4
    _cube(c / "cube.h5", ref)
    near = ref.copy()
    near[0, 5, 5] += 5e-6 * np.nanmax(sky)                # ~2 of its units, 5e-6 of the cube's scale
    _cube(g / "cube.h5", near)
    res = gpu_check.compare_dirs(g, c)["cube.h5"]
    assert res["ok"] and res["ulp_diff"] > 1.5 and res["rel_diff_beyond_ulp"] < 5e-6, res
    near[0, 5, 5] += 1e-3 * np.nanmax(sky)                # 1e-3 of the scale, twice float16's 2^-11: caught
    _cube(g / "cube.h5", near)
    res = gpu_check.compare_dirs(g, c)["cube.h5"]
    assert not res["ok"] and res["rel_diff_beyond_ulp"] > 5e-4 and res["allowed_beyond_ulp"] == 2.0 ** -11, res


def test_candidate_tables_compare_by_their_candidates(tmp_path):
    rows = [("s0", 10, 5, 0.4, 2, 12.0), ("s0", 90, 7, 1.2, 1, 8.0)]
    _cands(tmp_path / "cpu" / "c_candidates.ecsv", rows)
    _cands(tmp_path / "gpu" / "c_candidates.ecsv", [r[:5] + (r[5] * (1 + 1e-6),) for r in rows])
    assert gpu_check.compare_dirs(tmp_path / "gpu", tmp_path / "cpu")["c_candidates.ecsv"]["ok"]
    _cands(tmp_path / "gpu" / "c_candidates.ecsv", rows[:1] + [("s0", 91, 7, 1.2, 1, 8.0)])
    res = gpu_check.compare_dirs(tmp_path / "gpu", tmp_path / "cpu")["c_candidates.ecsv"]
    assert not res["ok"] and "1 only on the GPU, 1 only on the CPU" in res["problem"]


def test_inputs_found_or_the_pipeline_skipped_with_a_reason(tmp_path):
    yml = tmp_path / "p.yaml"
    data = tmp_path / "data"
    data.mkdir()
    cfg = {"source": {"kind": "tbf", "path": "../nowhere/x.dat"}}
    assert "not found" in gpu_check.resolve_input(yml, cfg, data)[2]
    (data / "x.dat").write_bytes(b"")
    ov, sender, why = gpu_check.resolve_input(yml, cfg, data)
    assert why is None and ov == [f"source.path={(data / 'x.dat').resolve()}"]
    assert gpu_check.resolve_input(yml, {"source": {"kind": "simulated"}}, data) == ([], None, None)


def test_bench_e2e_steady_rate_is_the_imager_s_own_pace():
    """tools/bench_e2e.py: the steady real-time factor comes from the imager's first and last gulps,
    not from image-file times (a writer that starts late writes queued images back to back)."""
    import bench_e2e
    blocks = {"TBFSourceBlock_0": {"ngulp": 11, "process_s": 0.011, "first_data_s": 0.2, "last_data_s": 1.2},
              "DFTImagerBlock_0": {"ngulp": 11, "process_s": 0.022, "first_data_s": 0.5, "last_data_s": 1.5},
              "ImageWriterBlock_0": {"ngulp": 2, "process_s": 1.0, "first_data_s": 1.4, "last_data_s": 1.51}}
    r = bench_e2e.steady_rate(blocks, 11.0)
    assert r["rt_steady"] == pytest.approx(10.0)          # 10 of 11 s of data in 1.0 s
    assert r["ms_per_gulp_DFTImager"] == pytest.approx(2.0) and r["ms_per_gulp_ImageWriter"] == pytest.approx(500.0)
    assert "rt_steady" not in bench_e2e.steady_rate({"DFTImagerBlock_0": dict(blocks["DFTImagerBlock_0"], ngulp=1)}, 1.0)


def test_bench_wholeband_growth_sees_flat_and_growing_memory():
    """tools/bench_wholeband.py: memory 'growth' is the last quarter's peak over the first quarter's,
    within the flowing span only (start-up allocations before it do not count)."""
    import bench_wholeband as bw
    flat = [(0.5, 100.0)] + [(t, 5000.0 + (t % 3)) for t in np.arange(2.0, 22.0, 1.0)]
    assert bw.growth(flat, 2.0, 21.0) == (5000.0 + 2 % 3, 5002.0, 0.0)
    grows = [(t, 5000.0 + 10 * t) for t in np.arange(2.0, 22.0, 1.0)]
    first, peak, g = bw.growth(grows, 2.0, 21.0)
    assert peak == 5210.0 and g == pytest.approx(5210.0 - 5060.0)
    assert bw.growth([(1.0, None)], 0.0, 2.0) == (None, None, None)


def test_bench_wholeband_runs_the_cli_and_finds_the_burst(tmp_path):
    """The benchmark on the whole-band YAML made small (16 channels, 16x16, the CPU): it runs `bf-epic
    run`, times it, samples the run's memory and checks the injected burst against the candidates:
    within one DM trial and 1.5 cells; a burst the YAML does not hold is reported not found."""
    import json
    import bench_wholeband as bw
    small = ["source.duration_s=0.42", "source.channels.count=16", "imager.grid.size=16",
             "imager.search.window_s=0.06", "imager.search.dms=[1.0]", "imager.search.threshold=7",
             "output.integrate.seconds=0.1"]
    bursts = ("source.transients=[{name: B1, ra_deg: 310.0, dec_deg: 20.0, start_s: 0.3, duration_s: 0.0015, "
              "flux_jy: 2000.0, dm: 0.6}, {name: faint, ra_deg: 200.0, dec_deg: 40.0, start_s: 0.2, "
              "duration_s: 0.0015, flux_jy: 0.001, dm: 0.3}]")
    argv = ["--device", "cpu", "--sample-s", "0.2", "--json", str(tmp_path / "bw.json")]
    for s in small + [bursts]:
        argv += ["--set", s]
    out = bw.main(argv)
    r = out["run"]
    assert 0 < r["rt_whole"] < r["rt_pipeline"] and r["rt_flowing"] > 0 and r["images"] > 0
    b1, faint = r["bursts"]
    assert b1["found"] and abs(b1["dm_off_trials"]) <= 1 and b1["offset_cells"] <= 1.5 and b1["snr"] > 10
    assert not faint["found"] and faint.get("snr") is None
    assert r["kernels_compiled"] is None or r["kernels_compiled"] >= 0
    assert r["rss_mib"]["peak"] > 100
    assert json.loads((tmp_path / "bw.json").read_text())["run"]["bursts"][0]["found"]


def test_bench_wholeband_counts_the_kernel_cache(tmp_path, monkeypatch):
    """What the run compiled is what CuPy's kernel cache gained: the files under CUPY_CACHE_DIR (none
    when it does not exist yet), None when CuPy keeps its cache in memory."""
    import bench_wholeband as bw
    monkeypatch.setenv("CUPY_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("CUPY_CACHE_IN_MEMORY", raising=False)
    assert bw.kernel_cache_files() == 0
    (tmp_path / "cache" / "sub").mkdir(parents=True)
    for name in ("a.cubin", "b.cubin", "sub/c.cubin"):
        (tmp_path / "cache" / name).write_bytes(b"x")
    assert bw.kernel_cache_files() == 3
    monkeypatch.setenv("CUPY_CACHE_IN_MEMORY", "1")
    assert bw.kernel_cache_files() is None


def test_bench_scrunch_costs_and_snr_make_sense():
    """tools/bench_scrunch.py (a prediction, not a search mode): with no trial at half rate the split
    costs what the full search does; lower split DMs cost less; a burst searched at half rate keeps at
    most its full-rate S/N and a narrow one loses more than a wide one; a pulse filling one full-rate
    image exactly, alone, keeps 1/sqrt(2) at half rate (twice the noise, the same signal)."""
    import bench_scrunch as bs
    assert bs.cost(3.0)["ratio"] == pytest.approx(1.0)
    r = [bs.cost(d)["ratio"] for d in (0.75, 1.5, 2.25)]
    assert r[0] < r[1] < r[2] < 1.0
    narrow, wide = bs.snr_retained(2.0, 0.32e-3), bs.snr_retained(2.0, 2.56e-3)
    assert 0.5 < narrow[0] < wide[0] <= 1.0 and narrow[1] <= narrow[0]
    one = bs.best_snr(np.array([1.0]), np.array([2.0]), 2, (1,)) / bs.best_snr(np.array([1.0]), np.array([2.0]), 1, (1,))
    assert one == pytest.approx(1 / np.sqrt(2))
