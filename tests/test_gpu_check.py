"""tools/gpu_check.py's comparison of two runs' outputs (the GPU check itself needs a GPU): it must
pass equal outputs and catch each kind of difference a GPU bug would leave. (setup.cfg's pytest
``pythonpath`` puts tools/ on the path.)"""
import numpy as np
import pytest

pytest.importorskip("astropy")
pytest.importorskip("h5py")
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


def test_fitted_dms_compare_by_their_trial_and_within_a_tolerance(tmp_path):
    """A table with dm_trial: a candidate is the same on both when its trial is; its fitted DM (which moves
    with the S/N's last digits) within DM_TOL, not bit for bit."""
    from astropy.table import Table
    from bf_epic_blocks.io.candidates import write_candidates

    def cands(side, dm, trial=1.2):
        t = Table(rows=[("s0", 10, 5, dm, trial, 2, 12.0)],
                  names=("sequence", "image", "pixel", "dm", "dm_trial", "width", "snr"))
        write_candidates(tmp_path / side / "c_candidates.ecsv", t)

    cands("cpu", 1.23456)
    cands("gpu", 1.23456 + 0.2 * gpu_check.DM_TOL)
    res = gpu_check.compare_dirs(tmp_path / "gpu", tmp_path / "cpu")["c_candidates.ecsv"]
    assert res["ok"] and res["dm_abs_diff"] > 0, res
    cands("gpu", 1.23456 + 5 * gpu_check.DM_TOL)
    assert not gpu_check.compare_dirs(tmp_path / "gpu", tmp_path / "cpu")["c_candidates.ecsv"]["ok"]
    cands("gpu", 1.23456, trial=1.3)
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


def test_flag_tables_compare_by_each_channels_fraction(tmp_path):
    from astropy.table import Table
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    g.mkdir()
    c.mkdir()
    f = 74.0 + 0.025 * np.arange(4)
    Table({"freq_mhz": f, "flagged_fraction": [0.0, 0.25, 0.001, 0.0]}).write(c / "x_flags.ecsv", format="ascii.ecsv")
    Table({"freq_mhz": f, "flagged_fraction": [0.0, 0.25, 0.0012, 0.0]}).write(g / "x_flags.ecsv", format="ascii.ecsv")
    assert gpu_check.compare_dirs(g, c)["x_flags.ecsv"]["ok"]
    Table({"freq_mhz": f, "flagged_fraction": [0.0, 0.20, 0.001, 0.0]}).write(g / "x_flags.ecsv", format="ascii.ecsv",
                                                                             overwrite=True)
    res = gpu_check.compare_dirs(g, c)["x_flags.ecsv"]
    assert not res["ok"] and res["max_fraction_diff"] == pytest.approx(0.05)


def test_datasets_inside_groups_are_compared(tmp_path):
    """The watch file keeps each target's spectra in its own group: a difference there is caught."""
    import h5py
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    rng = np.random.default_rng(1)
    spec = rng.uniform(1, 10, (20, 8, 1)).astype(np.float32)
    for d, x in ((c, spec), (g, spec * np.float32(1 + 1e-3))):
        d.mkdir(parents=True)
        with h5py.File(d / "w_watch.h5", "w") as f:
            f.create_dataset("complete", data=True)
            f.create_group("targets/FRB1").create_dataset("data", data=x)
    res = gpu_check.compare_dirs(g, c)["w_watch.h5"]
    assert not res["ok"] and res["rel_diff"] == pytest.approx(1e-3, rel=1e-2), res


def test_a_float16_cube_does_not_loosen_the_next_file_s_tolerance(tmp_path, sky):
    """The cube's one-float16-unit allowance is the cube's alone: a float32 file compared after it is
    held to the float32 tolerance, and the result names the dataset that differs most."""
    import h5py
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    _cube(c / "a_cube.h5", sky)
    _cube(g / "a_cube.h5", sky)
    for d, x in ((c, sky), (g, sky * (1 + 1e-4))):
        with h5py.File(d / "b_watch.h5", "w") as f:
            f.create_dataset("time_unix", data=np.arange(3.0))
            f.create_group("T").create_dataset("data", data=np.asarray(x, np.float32))
    res = gpu_check.compare_dirs(g, c)
    assert res["a_cube.h5"]["ok"]
    assert not res["b_watch.h5"]["ok"] and res["b_watch.h5"]["allowed"] == gpu_check.TOL_FP32, res["b_watch.h5"]
    assert res["b_watch.h5"]["worst"] == "T/data"


def test_a_quantised_sky_allows_a_few_flipped_values_and_no_more(tmp_path):
    """Runs of a 4-bit simulated sky: a few (image, channel) values fed by a sample that rounded to the
    next level on one side differ by ~1e-3; that passes when they are under 1% of the values, and
    fails when more values differ (a bug) or one differs by more than 1e-2."""
    g, c = tmp_path / "gpu", tmp_path / "cpu"
    rng = np.random.default_rng(2)
    ref = rng.uniform(1, 10, (200, 16, 1)).astype(np.float32)
    cases = {"few": (0.004, 1e-3, True), "many": (0.05, 1e-3, False), "big": (0.004, 5e-2, False)}
    for name, (frac, size, ok) in cases.items():
        got = ref.copy()
        idx = rng.choice(ref.size, int(frac * ref.size), replace=False)
        got.flat[idx] += np.float32(size * ref.max())
        _fits(c / f"{name}.fits", ref)
        _fits(g / f"{name}.fits", got)
    res = gpu_check.compare_dirs(g, c, flips=True)
    assert res["few"+".fits"]["ok"] and not res["many.fits"]["ok"] and not res["big.fits"]["ok"], res
    assert not gpu_check.compare_dirs(g, c)["few.fits"]["ok"]           # without a quantiser: caught
