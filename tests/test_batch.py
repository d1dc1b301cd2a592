"""``bf-epic batch``: many TBF files x channel blocks on a Dask distributed cluster.

One LocalCluster per module: 2 workers, **processes** (one thread each), on 127.0.0.1. Processes,
not threads, because that is what ``bf-epic batch`` starts by default and what a remote cluster
does: task configs and results are pickled and the package is imported in fresh worker
interpreters (the workers inherit the parent's sys.path, so PYTHONPATH checkouts work). It costs
about two seconds once. The batch is run through ``--scheduler`` at that cluster's address; the
default path (a LocalCluster the CLI starts itself) has its own small test.
"""
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("astropy")
from bf_epic_blocks.station.offline import configure_offline  # noqa: E402

configure_offline()
pytest.importorskip("lsl")
distributed = pytest.importorskip("distributed")

from bf_epic_blocks.pipeline import cli  # noqa: E402


from lwa_data import DATA, NA, SV  # noqa: E402
NA_FRAME = 1560
pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(not (SV.is_file() and NA.is_file()),
                                 reason=f"real LWA TBF files not found in {DATA} (set BF_EPIC_DATA)")]

# One YAML for both stations (station.name: auto); small grid, the files hold one sample each.
YAML = """
name: batch
station: {name: auto}
source: {kind: tbf, path: %s, gulp_nframe: 1}
calibration: {cable: true, pattern: none}
imager: {kind: dft, grid: {size: 32}, accumulate_frames: 1, products: [I], method: direct}
device: cpu
"""
QUIET = ["--no-progress", "-q"]


@pytest.fixture(scope="module")
def cluster():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=":0") as c:
            yield c


@pytest.fixture
def pipeline(tmp_path):
    p = tmp_path / "batch.yaml"
    p.write_text(YAML % NA)
    return p


def _corrupt_copy(tmp_path) -> Path:
    raw = bytearray(NA.read_bytes())
    raw[2 * NA_FRAME:2 * NA_FRAME + 4] = b"\x00\x00\x00\x00"  # bad sync word in frame 2
    bad = tmp_path / "lwana-corrupt.dat"
    bad.write_bytes(bytes(raw))
    return bad


def _fits_data(path):
    from astropy.io import fits
    with fits.open(path) as h:
        return h[0].data.copy(), h[0].header


def test_batch_equals_run_per_file_and_reports_the_corrupt_one(cluster, pipeline, tmp_path, capsys):
    bad = _corrupt_copy(tmp_path)
    out, js = tmp_path / "batch", tmp_path / "summary.json"
    rc = cli.main(["batch", str(pipeline), "--inputs", str(SV), str(NA), str(bad),
                   "--scheduler", cluster.scheduler_address, "--set", f"output.dir={out}",
                   "--summary-json", str(js), *QUIET])
    table = capsys.readouterr().out
    print(table)  # the summary as printed (pytest -s shows it)
    assert rc == 1, "one task failed: the exit status must say so"
    rows = {line.split()[0] + " " + line.split()[1]: line for line in table.splitlines()[1:-2]}
    assert set(rows) == {f"{SV} 1/1", f"{NA} 1/2", f"{NA} 2/2", f"{bad} -"}, table
    assert "TBFError" in rows[f"{bad} -"] and "byte offset 3120" in rows[f"{bad} -"]
    assert "3 of 4 tasks succeeded" in table
    summary = json.loads(js.read_text())
    assert summary["ok"] is False and len(summary["tasks"]) == 4
    for t in summary["tasks"]:
        if t["file"] != str(bad):
            assert t["error"] is None and t["images"] == 1 and t["frames"] == 1 and t["skipped"] == 0, t
    assert not (out / bad.stem).exists() or not any((out / bad.stem).iterdir())

    # each good file: the same files as `bf-epic run` writes, with the same images
    for f in (SV, NA):
        ref = tmp_path / "ref" / f.stem
        assert cli.main(["run", str(pipeline), "--set", f"source.path={f}", "--set", f"output.dir={ref}", *QUIET]) == 0
        got = sorted(p.name for p in (out / f.stem).iterdir())
        assert got == sorted(p.name for p in ref.iterdir()), (got, f)
        fits_files = [n for n in got if n.endswith(".fits")]
        assert len(fits_files) == (2 if f == NA else 1)  # NA: two channel blocks (15 and 52 MHz)
        for name in fits_files:
            a, ha = _fits_data(out / f.stem / name)
            b, hb = _fits_data(ref / name)
            assert a.shape == b.shape and np.isfinite(a).any()
            assert np.array_equal(np.isnan(a), np.isnan(b))
            # same code on the same data; dask's workers run BLAS single-threaded (OPENBLAS_NUM_THREADS=1),
            # which changes fp32 sums at ~1e-7 of the peak (bit-identical when the run does the same)
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * np.nanmax(np.abs(b)), equal_nan=True)
            for k in ("CRVAL3", "CDELT3", "NAXIS3", "DATE-OBS", "TELESCOP"):
                assert ha.get(k) == hb.get(k), (name, k)


def test_batch_all_good_exits_zero(cluster, pipeline, tmp_path, capsys):
    rc = cli.main(["batch", str(pipeline), "--inputs", str(SV), "--scheduler", cluster.scheduler_address,
                   "--set", f"output.dir={tmp_path / 'o'}", *QUIET])
    assert rc == 0, capsys.readouterr()
    assert "1 of 1 tasks succeeded" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "o" / SV.stem).iterdir()) == ["batch_flags.ecsv", "batch_flags.png",
                                                                             "batch_s00_i0000.fits",
                                                                             "batch_s00_i0000.png"]


def test_batch_starts_its_own_local_cluster(pipeline, tmp_path, capsys):
    bad = _corrupt_copy(tmp_path)
    rc = cli.main(["batch", str(pipeline), "--inputs", str(bad), "--workers", "1",
                   "--set", f"output.dir={tmp_path / 'o'}", *QUIET])
    out = capsys.readouterr().out
    assert rc == 1 and "0 of 1 tasks succeeded" in out and "bad sync word" in out, out


def test_batch_yaml_path_need_not_exist(cluster, tmp_path, capsys):
    p = tmp_path / "nopath.yaml"
    p.write_text(YAML % "not-here.dat")  # source.path is replaced by the inputs
    rc = cli.main(["batch", str(p), "--inputs", str(tmp_path / "missing.dat"), str(NA), "--scheduler",
                   cluster.scheduler_address, "--set", f"output.dir={tmp_path / 'o'}", *QUIET])
    out = capsys.readouterr().out
    assert rc == 1 and "2 of 3 tasks succeeded" in out and "FileNotFoundError" in out, out


def test_batch_argument_errors(pipeline, tmp_path, capsys):
    twin = tmp_path / "twin"
    twin.mkdir()
    (twin / NA.name).write_bytes(NA.read_bytes())
    assert cli.main(["batch", str(pipeline), "--inputs", str(NA), str(twin / NA.name), *QUIET]) == 2
    assert "share the stem" in capsys.readouterr().err
    sim = tmp_path / "sim.yaml"
    sim.write_text("source: {kind: simulated}\n")
    assert cli.main(["batch", str(sim), "--inputs", str(NA), *QUIET]) == 2
    assert "source.kind must be 'tbf'" in capsys.readouterr().err
    assert cli.main(["batch", str(pipeline), "--inputs", str(NA), "--workers", "0", *QUIET]) == 2


def test_station_auto_needs_a_tbf_source(tmp_path, capsys):
    sim = tmp_path / "sim.yaml"
    sim.write_text("station: {name: auto}\nsource: {kind: simulated}\n")
    assert cli.main(["validate", str(sim), "-q"]) == 2
    assert "station.name" in capsys.readouterr().err


def test_channel_block_out_of_range_is_a_clear_error(pipeline, tmp_path, capsys):
    assert cli.main(["run", str(pipeline), "--set", "source.channel_block=2", "--set",
                     f"output.dir={tmp_path / 'o'}", *QUIET]) == 1
    err = capsys.readouterr().err
    assert "source.channel_block: 2" in err and "2 channel block(s)" in err, err
