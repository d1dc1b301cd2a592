"""The station-to-FITS path through the bf-epic CLI: YAMLs, real TBF files, WCS placement, tracking."""
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("astropy")
from bf_epic_blocks.station.offline import configure_offline  # noqa: E402

configure_offline()
pytest.importorskip("lsl")

from bf_epic_blocks.pipeline import cli  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PIPES = REPO / "pipelines"
DATA = REPO.parent / "shared" / "data" / "lwa"
need_data = pytest.mark.skipif(not (DATA / "lwasv-adp-tbf.dat").exists(), reason=f"real LWA data not found at {DATA}")
FAST = ["--set", "source.duration_s=0.1", "--set", "imager.accumulate_frames=2500", "--set",
        "source.channels.count=4", "--no-progress", "-q"]


def read_fits(path):
    from astropy.io import fits
    from astropy.wcs import WCS
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no FITSFixedWarning: OBSGEO-L/B/H are written beside X/Y/Z
        with fits.open(path) as h:
            return h[0].data.copy(), WCS(h[0].header), dict(h[0].header)


def test_every_pipeline_yaml_validates(capsys):
    for f in sorted(PIPES.glob("*.yaml")):
        if "tbf" in f.name and not DATA.exists():
            continue
        assert cli.main(["validate", str(f)]) == 0, f
    assert "valid" in capsys.readouterr().out


def test_validation_errors_name_the_key(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("source: {kind: tbf, path: nowhere.dat}\nimager: {grid: {size: abc}, acumulate_frames: 3}\n"
                   "device: gpu:x\n")
    assert cli.main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "source.path" in err and "imager.grid.size" in err and "acumulate_frames" in err
    assert "accumulate_frames" in err  # the suggestion
    assert "device" in err


def test_plan_reports_the_scene(capsys):
    assert cli.main(["plan", str(PIPES / "lwasv_sim_allsky.yaml")]) == 0
    out = capsys.readouterr().out
    assert "3205 pixels above the horizon" in out and "method: covariance" in out
    assert "real-time factor" in out and "254 used" in out


def test_plan_reports_the_whole_band_search_and_what_it_costs(capsys):
    """`bf-epic plan` of the whole band on a GPU: the imaging's real-time factor alone, then the
    search (1,331 tree trials to DM 3), the memory it holds -- the history of every trial, 312 window
    + 8 widest boxcar + 64 batch + 50 look-back values of 3,205 float32 pixels (32 after an event, 18
    trials either side: not the largest sweep of 1,330), the float16 tree's
    rings as a GPU holds them -- and imaging and
    search together from the measured rates, below the imaging's own factor."""
    from bf_epic_blocks.pipeline import config, runner
    cfg = config.load_config(PIPES / "lwasv_sim_wholeband.yaml", ["device=gpu"])
    d, text = runner.plan(cfg)
    sd = d["search"]
    assert sd["dedisperse"] == "tree" and sd["trials"] == 1331 and sd["tree_rows"] == 12283
    assert sd["history_values"] == 312 + 8 + 64 + (32 + 18)
    assert sd["memory_bytes"]["history"] == 1331 * sd["history_values"] * 3205 * 4
    # the YAML's float16 tree (rows of 3,208: 16-byte loads) on a GPU: the rings, and the 5,591 merged rows kept in them with a
    # push's 64 slots each (rows the working array then does not hold: the same total, 15.1 GiB below)
    assert sd["memory_bytes"]["tree"] == 2 * (444050 + 64 * 5591) * 3208
    assert sd["tree_precision"] == "fp16" and "12283 tree rows stored as fp16" in text
    assert 0 < sd["imaging_and_search_realtime_factor"] < d["realtime_factor"]
    assert "transient search: tree dedispersion, 1331 trials" in text and "imaging and search together" in text
    assert cli.main(["plan", str(PIPES / "lwasv_sim_wholeband.yaml"), "--set", "device=gpu"]) == 0
    assert "holds 15.1 GiB where it runs" in capsys.readouterr().out      # (one pass of the tree on a GPU)


@pytest.mark.slow
def test_simulated_demo_puts_cyg_a_on_its_pixel(tmp_path):
    """Stokes I's brightest pixel more than 30 deg above the horizon, read back with astropy.wcs, is
    within one pixel of Cyg A. (The demo's diffuse sky puts the Galactic Centre, ~20 deg up in the
    South, above Cyg A in a dirty image: a beam of fixed size in (l, m) covers 1/n times more sky
    near the horizon.)"""
    from astropy.coordinates import SkyCoord
    out = tmp_path / "demo"
    assert cli.main(["run", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", f"output.dir={out}", *FAST]) == 0
    fits_files = sorted(out.glob("*.fits"))
    pngs = sorted(out.glob("*.png"))
    assert len(fits_files) == 1 and len(pngs) == 1 and pngs[0].stat().st_size > 20000
    data, wcs, hdr = read_fits(fits_files[0])
    assert data.shape == (1, 4, 64, 64) and hdr["CTYPE1"] == "RA---SIN" and hdr["CTYPE3"] == "FREQ"
    assert hdr["CTYPE4"] == "STOKES" and hdr["CRVAL4"] == 1 and "DATE-OBS" in hdr and hdr["TELESCOP"]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN corners below the horizon
        img = np.nanmean(data[0], axis=0)
    ii, jj = np.meshgrid(np.arange(img.shape[1]), np.arange(img.shape[0]))
    zenith = SkyCoord(*wcs.celestial.wcs.crval, unit="deg")                # the SIN projection's centre
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                                     # NaN world coordinates off the sky
        high = wcs.celestial.pixel_to_world(ii, jj).separation(zenith).deg < 60
    j, i = np.unravel_index(np.nanargmax(np.where(high, img, np.nan)), img.shape)
    sky = wcs.celestial.pixel_to_world(i, j)
    cyg = SkyCoord(299.8681525, 40.7339156, unit="deg")
    assert sky.separation(cyg).deg < abs(hdr["CDELT1"]) * 1.5


@pytest.mark.real_data
@need_data
@pytest.mark.parametrize("yaml_name,expect_runs", [("lwasv_tbf_allsky.yaml", 1), ("lwana_tbf_allsky.yaml", 2)])
def test_real_tbf_files_image(tmp_path, yaml_name, expect_runs):
    out = tmp_path / "tbf"
    assert cli.main(["run", str(PIPES / yaml_name), "--set", f"output.dir={out}", "--no-progress", "-q"]) == 0
    fits_files = sorted(out.glob("*.fits"))
    assert len(fits_files) == expect_runs  # LWA-NA's two channel blocks: one FITS per even-spaced run
    for f in fits_files:
        data, wcs, hdr = read_fits(f)
        assert np.isfinite(data[..., 32, 32]).all() and np.isnan(data[..., 0, 0]).all()


@pytest.mark.real_data
@need_data
def test_lwana_tbf_shows_cas_a_at_52_mhz(tmp_path):
    """Real data pin the sign: the 52 MHz block of the LWA-NA capture peaks within 10 deg of Cas A."""
    from astropy.coordinates import SkyCoord
    out = tmp_path / "na"
    assert cli.main(["run", str(PIPES / "lwana_tbf_allsky.yaml"), "--set", f"output.dir={out}",
                     "--set", "imager.remove_autocorr=true", "--no-progress", "-q"]) == 0
    data, wcs, hdr = read_fits(sorted(out.glob("*_r1.fits"))[0])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        img = np.nanmean(data[0], axis=0)
    j, i = np.unravel_index(np.nanargmax(img), img.shape)
    sep = wcs.celestial.pixel_to_world(i, j).separation(SkyCoord(350.85, 58.815, unit="deg")).deg
    assert sep < 10, sep


@pytest.mark.real_data
@need_data
def test_corrupt_tbf_is_a_clear_error(tmp_path, capsys):
    raw = bytearray((DATA / "lwana-ndp-tbf.dat").read_bytes())
    raw[2 * 1560:2 * 1560 + 4] = b"\x00\x00\x00\x00"
    bad = tmp_path / "bad.dat"
    bad.write_bytes(bytes(raw))
    assert cli.main(["run", str(PIPES / "lwana_tbf_allsky.yaml"), "--set", f"source.path={bad}",
                     "--set", f"output.dir={tmp_path / 'o'}", "--no-progress", "-q"]) == 1
    err = capsys.readouterr().err
    assert "offset 3120" in err


def test_tracking_follows_cyg_a(tmp_path):
    from bf_epic_blocks.io.fits import read_pixel_table
    out = tmp_path / "track"
    args = ["run", str(PIPES / "lwasv_track_cyga.yaml"), "--set", f"output.dir={out}",
            "--set", "source.duration_s=0.2", "--set", "imager.accumulate_frames=2500",
            "--set", "source.channels.count=2", "--set", "imager.track.update_s=0.1",
            "--set", "imager.track.size=12", "--no-progress", "-q"]
    assert cli.main(args) == 0
    tables = sorted(out.glob("*_pixels.fits"))
    assert len(tables) == 2
    t0, t1 = (read_pixel_table(t) for t in tables)
    lm0, lm1 = (np.column_stack([t["l"], t["m"]]) for t in (t0, t1))
    assert not np.allclose(lm0, lm1), "the patch must move with the source"
    centre = 6 * 12 + 6
    for t, lm in ((t0, lm0), (t1, lm1)):
        vals = t["values"][:, 0].mean(axis=0)  # Stokes I, channel mean, (npix,)
        k = int(np.argmax(vals))
        assert k == centre or np.hypot(*(lm[k] - lm[centre])) < 0.02, "Cyg A stays at the patch centre"
    assert sorted(out.glob("*.png"))


@pytest.mark.parametrize("tol", ["1e-3", "1e-4", "1e-6"])
def test_plan_for_a_gpu_picks_from_the_gpu_rows(tol, capsys):
    """`bf-epic plan --set device=gpu` with a tolerance plans for the GPU on any machine (no CuPy
    needed): at 1e-3 and 1e-4 a tensor-core mode, faster than fp32; at 1e-6 a mode whose bound meets it.
    The plan's --json names the pick; the measured table says what the GPU offers."""
    from bf_epic_blocks.imaging import plan
    import json
    argv = ["plan", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", "device=gpu", "--set", f"imager.tolerance={tol}"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert cli.main(argv + ["--json"]) == 0
    pick = json.loads(capsys.readouterr().out)["tolerance_pick"]
    assert f"picked {pick['method']} route, {pick['precision']}," in out, out
    assert "predicted on gpu" in out
    assert pick["bound"] <= float(tol)
    gpu_rows = {(r["method"], r["precision"]) for r in plan.candidates("gpu")}
    assert (pick["method"], pick["precision"]) in gpu_rows
    if float(tol) >= 1e-4:
        assert pick["precision"] not in ("fp32", "fp64"), out
        fp32 = min(r["bound"] for r in plan.candidates("gpu") if r["precision"] == "fp32")
        assert fp32 <= float(tol)   # fp32 also met it: the tensor-core mode was picked for speed


def test_plan_says_when_no_rate_was_measured_for_its_mode(monkeypatch, capsys):
    """A mode the measured table has no row for (an expert's precision) is predicted from the route's generic
    rate, and the plan says so rather than naming measured rates."""
    from bf_epic_blocks.imaging import plan
    rows = [r for r in plan.load_table()["rows"] if r["precision"] != "fp16"]
    monkeypatch.setattr(plan, "load_table", lambda *a, **k: {"rows": rows})
    argv = ["plan", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", "device=gpu", "--set", "imager.precision=fp16"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert "no rate measured for" in out and "x fp16" in out and "rates measured for" not in out, out
    monkeypatch.undo()
    assert cli.main(argv) == 0
    assert "rates measured for" in capsys.readouterr().out


def test_gpu_request_without_gpu_is_clear(tmp_path, capsys):
    from bf_epic_blocks.imaging._xp import gpu_available
    if gpu_available():
        pytest.skip("this machine has a GPU")
    assert cli.main(["run", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", "device=gpu",
                     "--set", f"output.dir={tmp_path}", *FAST]) == 1
    assert "CuPy or a CUDA GPU is not available" in capsys.readouterr().err


def test_plan_with_a_tolerance_names_the_pick(capsys):
    """imager.tolerance instead of a mode: plan prints the route x precision picked, with its bound."""
    assert cli.main(["plan", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", "imager.tolerance=1e-4",
                     "--set", "imager.min_elevation_deg=10"]) == 0
    out = capsys.readouterr().out
    assert "tolerance 1.0e-04: picked" in out and "fp32" in out, out
    assert "error bound 1.0e-06" in out or "error bound" in out
    # min_elevation_deg drops the pixels near the horizon: fewer than the 3205 of the full grid
    kept = int(out.split("grid, ")[1].split(" pixels")[0])
    assert kept < 3205
    assert cli.main(["plan", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", "imager.tolerance=1e-30"]) != 0
    assert "no route x precision" in capsys.readouterr().err


def _small_tbf(path, ntime=600, nchan=12):
    """An LWA-SV (ADP, 256 stands) TBF file of random 4-bit samples."""
    from bf_epic_blocks.imaging.calibration import FS_HZ
    from bf_epic_blocks.io.tbf import write_tbf
    data = np.random.default_rng(5).integers(0, 256, (ntime, nchan, 256, 2), dtype=np.uint8)
    write_tbf(path, data, 1200, int(1.7e9) * FS_HZ, frame_id=1)
    return path


def _recording_yaml(tmp_path, tbf, extra=""):
    y = tmp_path / "rec.yaml"
    y.write_text(f"name: rec\nstation: {{name: lwasv}}\nsource: {{kind: tbf, path: {tbf}{extra}}}\n"
                 f"calibration: {{cable: true, pattern: none}}\n"
                 f"imager: {{kind: dft, grid: {{size: 16}}, accumulate_frames: 300, products: [I]}}\n"
                 f"output: {{dir: {tmp_path / 'out'}, fits: true, png: false}}\n"
                 # random bytes, not a sky: the interference flagger would rightly flag them all
                 f"flagging: {{enabled: 'off'}}\n")
    return y


def test_auto_gulp_gives_a_recording_on_a_gpu_64_mib_gulps(tmp_path, capsys):
    """source.gulp_nframe defaults to auto: a capture file imaged on a GPU gets ~64 MiB of samples per
    gulp (its block threads' per-gulp host work, not the GPU, sets the pace there); a CPU, a simulated
    sky or a number given in the YAML keep theirs. Planned on any machine (no GPU needed)."""
    import json
    from bf_epic_blocks.pipeline.runner import gulp_frames
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf"))

    def planned(*sets):
        argv = ["plan", str(y), "--json"] + [a for s in sets for a in ("--set", s)]
        assert cli.main(argv) == 0
        return json.loads(capsys.readouterr().out)["gulp_nframe"]
    assert planned("device=gpu") == (64 << 20) // (2 * 12 * 256) // 256 * 256 == 10752
    assert planned("device=cpu") == 1024
    assert planned("device=gpu", "source.gulp_nframe=2000") == 2000
    sim = ["plan", str(PIPES / "lwasv_sim_allsky.yaml"), "--json", "--set", "device=gpu",
           "--set", "source.gulp_nframe=auto"]
    assert cli.main(sim) == 0 and json.loads(capsys.readouterr().out)["gulp_nframe"] == 1024
    # channels sharded over several GPUs: whole integrations per gulp
    cfg = {"source": {"gulp_nframe": "auto", "kind": "tbf"}, "imager": {"accumulate_frames": 25000}}
    assert gulp_frames(cfg, "gpus", 24, 256) == 25000
    assert gulp_frames(dict(cfg, imager={"accumulate_frames": 100}), "gpus", 24, 256) == 5400
    # a bad value names the key and what it may be
    assert cli.main(["validate", str(y), "--set", "source.gulp_nframe=fast"]) == 2
    err = capsys.readouterr().err
    assert "source.gulp_nframe" in err and "'auto'" in err


def test_a_recording_is_scanned_once(tmp_path, monkeypatch):
    """The runner scans a capture file's headers to plan the pipeline and hands the result to the
    source block, which does not read every frame header a second time."""
    import bf_epic_blocks.io.tbf as tbf
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    calls = []
    real = tbf.scan_tbf
    monkeypatch.setattr(tbf, "scan_tbf", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    cfg = load_config(_recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=300)), ["device=cpu"])
    summary = runner.run(cfg, show_progress=False)
    assert summary["images"] == 1 and summary["frames_imaged"] == 300
    assert len(calls) == 1, calls


def test_the_console_script_exits_with_mains_status(tmp_path):
    """`bf-epic` (cli.entry) ends the process as soon as main returns -- its output flushed, its exit
    status main's -- without the interpreter's teardown."""
    import subprocess
    import sys
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=300))
    code = "import sys; from bf_epic_blocks.pipeline.cli import entry; sys.argv = ['bf-epic'] + sys.argv[1:]; entry()"
    ok = subprocess.run([sys.executable, "-c", code, "validate", str(y)], capture_output=True, text=True, timeout=300)
    assert ok.returncode == 0 and "valid" in ok.stdout, ok.stderr
    bad = subprocess.run([sys.executable, "-c", code, "validate", str(tmp_path / "none.yaml")], capture_output=True,
                         text=True, timeout=300)
    assert bad.returncode == 2 and "none.yaml" in bad.stderr


def _writer_in_a_helper(monkeypatch):
    """Make the runner's image writer use a helper process (as it does on a GPU) on this CPU; returns
    the list the writers made are put in."""
    from bf_epic_blocks.blocks import image_writer
    made = []

    class Helped(image_writer.ImageWriterBlock):
        def __init__(self, *a, **k):
            k["processes"] = 1
            super().__init__(*a, **k)
            made.append(self)
    monkeypatch.setattr(image_writer, "ImageWriterBlock", Helped)
    return made


@pytest.mark.slow
def test_a_helper_process_writes_the_same_files(tmp_path, monkeypatch):
    """The image writer's helper process (bf-epic run on a GPU) writes byte for byte the FITS files the
    writer's own thread writes, all of them by the time the run returns, in the same order."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    tbf = _small_tbf(tmp_path / "rec.tbf", ntime=1200)
    y = _recording_yaml(tmp_path, tbf)
    own = runner.run(load_config(y, ["device=cpu", f"output.dir={tmp_path / 'own'}"]), show_progress=False)
    made = _writer_in_a_helper(monkeypatch)
    from bf_epic_blocks.blocks import image_writer
    image_writer.start_helper()               # started ahead, as bf-epic run does: the writer takes it
    image_writer._STARTED[0][1].result()      # and up (until then the writer writes in its own thread)
    helped = runner.run(load_config(y, ["device=cpu", f"output.dir={tmp_path / 'helped'}"]), show_progress=False)
    assert not image_writer._STARTED
    assert made[0].helper_files == 4          # every file came from the helper process
    import multiprocessing
    assert not multiprocessing.active_children()      # the helper has ended: none left holding our streams
    assert own["images"] == helped["images"] == 4
    names = [Path(f).name for f in own["files"]]
    assert names == [Path(f).name for f in helped["files"]] and len(names) == 4
    for n in names:
        assert (tmp_path / "own" / n).read_bytes() == (tmp_path / "helped" / n).read_bytes(), n


def test_a_failure_in_the_helper_process_fails_the_run_by_name(tmp_path, monkeypatch):
    """A file the helper process cannot write is an error naming the image, not a run that ends
    'successfully' with files missing."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=600))
    out = tmp_path / "out"
    (out / "rec_s00_i0001.fits").mkdir(parents=True)      # a folder where a FITS file must go
    _writer_in_a_helper(monkeypatch)
    from bf_epic_blocks.blocks import image_writer
    image_writer.start_helper()
    image_writer._STARTED[0][1].result()
    with pytest.raises(Exception, match=r"writing \S*rec_s00_i0001 failed in the helper process"):
        runner.run(load_config(y, ["device=cpu", f"output.dir={out}"]), show_progress=False)


@pytest.mark.slow
def test_a_helper_that_cannot_start_is_not_a_lost_image(tmp_path):
    """A script without a ``__main__`` guard cannot spawn the writer's helper process (Python's spawn
    re-runs the script in the child, which refuses): the images are then written in the writer's own
    thread, every one, with a warning -- not a failed run."""
    import subprocess
    import sys
    _small_tbf(tmp_path / "rec.tbf", ntime=900)
    y = _recording_yaml(tmp_path, tmp_path / "rec.tbf")
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from bf_epic_blocks.blocks import image_writer\n"
        "from bf_epic_blocks.pipeline import runner\n"
        "from bf_epic_blocks.pipeline.config import load_config\n"
        "class Helped(image_writer.ImageWriterBlock):\n"
        "    def __init__(self, *a, **k):\n"
        "        k['processes'] = 1\n"
        "        super().__init__(*a, **k)\n"
        "image_writer.ImageWriterBlock = Helped\n"
        f"s = runner.run(load_config({str(y)!r}, ['device=cpu']), show_progress=False)\n"
        "print('files', len(s['files']), 'images', s['images'])\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600, cwd=str(tmp_path))
    assert out.returncode == 0, out.stderr[-3000:]
    assert "files 3 images 3" in out.stdout, (out.stdout, out.stderr[-2000:])
    assert sorted(p.name for p in (tmp_path / "out").glob("*.fits")) == [f"rec_s00_i000{i}.fits" for i in range(3)]


def _slow_helper(png):
    """A helper process whose start takes 30 s."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor
    from bf_epic_blocks.blocks import image_writer
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=time.sleep,
                               initargs=(30,))
    return pool, pool.submit(image_writer._helper_ready)


def test_a_short_run_does_not_wait_for_the_helper(tmp_path, monkeypatch):
    """A run whose images all come before the helper process is up writes them in the writer's thread
    at the sequence's end, waiting for a helper still starting at most ``HELPER_WAIT_S`` (not its 30-s
    start), and leaves no process."""
    import multiprocessing
    import time
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.blocks import image_writer
    made = _writer_in_a_helper(monkeypatch)
    monkeypatch.setattr(image_writer, "_new_helper", _slow_helper)
    monkeypatch.setattr(image_writer.ImageWriterBlock, "HELPER_WAIT_S", 1.0)
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=600))
    t0 = time.perf_counter()
    s = runner.run(load_config(y, ["device=cpu"]), show_progress=False)
    assert time.perf_counter() - t0 < 20
    assert s["images"] == 2 and len(s["files"]) == 2 and made[0].helper_files == 0
    assert not multiprocessing.active_children()


def test_no_image_is_written_in_the_pipelines_interpreter_while_the_helper_starts(tmp_path, monkeypatch):
    """Integrations that arrive while the helper is still starting are held, not written in the writer's
    thread while the source and imager still run (astropy's work there holds the interpreter lock they
    need between CUDA calls): the writer writes them only once the sequence's data is done (or hands
    them to the helper when it is up), and no image is lost."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.blocks import image_writer
    made = _writer_in_a_helper(monkeypatch)
    monkeypatch.setattr(image_writer, "_new_helper", _slow_helper)
    monkeypatch.setattr(image_writer.ImageWriterBlock, "HELPER_WAIT_S", 0.5)
    where = []
    real_write, real_flush = image_writer.ImageWriterBlock._write_here, image_writer.ImageWriterBlock.flush

    def flush(self):
        where.append("end")
        return real_flush(self)

    def write_here(self, stem, fn, job):
        where.append("write")
        return real_write(self, stem, fn, job)
    monkeypatch.setattr(image_writer.ImageWriterBlock, "flush", flush)
    monkeypatch.setattr(image_writer.ImageWriterBlock, "_write_here", write_here)
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=1200))
    s = runner.run(load_config(y, ["device=cpu"]), show_progress=False)
    assert s["images"] == 4 and len(s["files"]) == 4 and made[0].helper_files == 0
    assert where[0] == "end" and where.count("write") == 4, where


@pytest.mark.slow
def test_a_process_without_astropy_waits_for_a_starting_helper_rather_than_import_it(tmp_path, monkeypatch):
    """Where writing here would first import astropy (a recording's run on a GPU), images held at the
    sequence's end wait for a helper that is still starting, and all of them come from it, byte for byte
    the files the writer's own thread writes."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.blocks import image_writer
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=1200))
    own = runner.run(load_config(y, ["device=cpu", f"output.dir={tmp_path / 'own'}"]), show_progress=False)
    made = _writer_in_a_helper(monkeypatch)

    def late_helper(png):          # a helper whose start takes 3 s: the run's images all come before
        pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_late_init,
                                   initargs=(png,))
        return pool, pool.submit(image_writer._helper_ready)
    monkeypatch.setattr(image_writer, "_new_helper", late_helper)
    monkeypatch.setattr(image_writer, "_fits_loaded", lambda: False)
    helped = runner.run(load_config(y, ["device=cpu", f"output.dir={tmp_path / 'helped'}"]), show_progress=False)
    assert made[0].helper_files == 4 == helped["images"]
    assert [Path(f).name for f in own["files"]] == [Path(f).name for f in helped["files"]]
    for n in (Path(f).name for f in own["files"]):
        assert (tmp_path / "own" / n).read_bytes() == (tmp_path / "helped" / n).read_bytes(), n
    assert not multiprocessing.active_children()


def _late_init(png):
    import time
    from bf_epic_blocks.blocks import image_writer
    time.sleep(3)
    image_writer._helper_init(png)


@pytest.mark.parametrize("bad", [2, -1, "1", True])
def test_image_writer_processes_is_checked(bad):
    from bf_epic_blocks.blocks.image_writer import ImageWriterBlock
    with pytest.raises(ValueError, match="processes must be 0 or 1"):
        ImageWriterBlock(None, "/tmp/unused", processes=bad)


def test_a_writer_that_cannot_have_a_helper_writes_itself(tmp_path, monkeypatch, caplog):
    """Where no process can be started (a daemonic Dask worker may not have children) the writer says so
    and writes every image in its own thread."""
    from bf_epic_blocks.blocks import image_writer
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    made = _writer_in_a_helper(monkeypatch)

    def no_children(png):
        raise AssertionError("daemonic processes are not allowed to have children")
    monkeypatch.setattr(image_writer, "_new_helper", no_children)
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=600))
    with caplog.at_level("WARNING"):
        s = runner.run(load_config(y, ["device=cpu"]), show_progress=False)
    assert s["images"] == 2 and len(s["files"]) == 2 and made[0].helper_files == 0
    assert "no helper process (AssertionError" in caplog.text


@pytest.mark.parametrize("no_bytecode", [True, False])
def test_a_run_without_bytecode_caches_says_so(tmp_path, no_bytecode):
    """A Python told not to write bytecode (PYTHONDONTWRITEBYTECODE) recompiles every module it imports on
    every run (~1 s of a GPU run's start): `bf-epic run` says so, with what to do, and only then."""
    import os
    import subprocess
    import sys
    y = _recording_yaml(tmp_path, _small_tbf(tmp_path / "rec.tbf", ntime=300))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    if no_bytecode:
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    out = subprocess.run([sys.executable, "-m", "bf_epic_blocks.pipeline.cli", "run", str(y), "--no-progress"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    said = "Python writes no bytecode caches here (PYTHONDONTWRITEBYTECODE)" in out.stderr
    assert said == no_bytecode, out.stderr


def test_plan_offers_the_integer_modes_only_when_4bit_voltages_reach_the_imager(capsys):
    """The transient pipeline at 16 samples per image: on one GPU with the calibration folded and a
    quantised sky, the tolerance may pick a fused integer mode; with an unquantised sky (complex
    voltages), on the CPU, or with a gains table (a CalFoldBlock makes the voltages complex), it may not."""
    import json
    from bf_epic_blocks.imaging.fused import FUSED
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import imager_sample_bits
    base = ["plan", str(PIPES / "lwasv_sim_transient.yaml"), "--set", "imager.tolerance=1e-4", "--json"]
    assert cli.main(base + ["--set", "device=gpu"]) == 0
    assert json.loads(capsys.readouterr().out)["tolerance_pick"]["precision"] in FUSED
    assert cli.main(base + ["--set", "device=gpu", "--set", "source.quantize=false"]) == 0
    assert json.loads(capsys.readouterr().out)["tolerance_pick"]["precision"] not in FUSED
    cfg = load_config(PIPES / "lwasv_sim_transient.yaml", ["device=gpu"])
    assert imager_sample_bits(cfg, "gpu") == 4
    assert imager_sample_bits(cfg, "cpu") is None and imager_sample_bits(cfg, "gpus") is None
    cfg["calibration"]["gains_table"] = "gains.csv"
    assert imager_sample_bits(cfg, "gpu") is None


@pytest.mark.parametrize("setting, part", [
    ("source.channels.count=1000000", "input rings"),
    ("imager.grid.size=4096", "image rings"),
    ("imager.search.widths=[100000000]", "search"),
    ("imager.search.dms=[1.0e6]", "search"),
    ("source.gulp_nframe=1000000000", "input rings"),
])
def test_a_configuration_that_cannot_fit_is_refused_before_it_allocates(setting, part, capsys):
    """plan and run refuse it with the memory it needs, its largest part and what the machine has, before
    anything large is allocated (each used to fail allocating GiB to TiB, or to take minutes)."""
    import time
    yaml = str(PIPES / "lwasv_sim_transient.yaml")
    for cmd in ("plan", "run"):
        t0 = time.perf_counter()
        rc = cli.main([cmd, yaml, "--set", setting, "--set", "output.dir=/nonexistent/never-written"])
        err = capsys.readouterr().err
        assert rc != 0 and "needs about" in err and part in err and "available" in err, (cmd, err)
        assert time.perf_counter() - t0 < 30, cmd


def test_planning_a_refused_configuration_caches_no_station_terms(monkeypatch, capsys):
    """plan (and run's check before it builds) needs no per-channel station terms: a million channels
    are refused without computing or caching 256 x 2 x 1e6 of them (which wrote GBs to the station
    cache and took more than the refusal's 30 s to read back)."""
    from bf_epic_blocks.station import tables
    saved = []
    monkeypatch.setattr(tables, "_save_cached", lambda path, table, freqs: saved.append(np.size(freqs)))
    monkeypatch.setattr(tables, "_load_cached", lambda path: None)       # as on a machine with no cache yet
    rc = cli.main(["plan", str(PIPES / "lwasv_sim_transient.yaml"), "--set", "source.channels.count=1000000"])
    assert rc != 0 and "needs about" in capsys.readouterr().err
    assert all(n < 1000 for n in saved), saved


def test_an_empty_search_list_is_refused_by_the_schema(capsys):
    assert cli.main(["validate", str(PIPES / "lwasv_sim_transient.yaml"), "--set", "imager.search.dms=[]"]) == 2
    assert "imager.search.dms: expected a list of DMs >= 0 (at least 1), got []" in capsys.readouterr().err


def test_a_long_run_keeps_the_newest_paths_and_counts_every_file(tmp_path, monkeypatch):
    """A service writes an image every few seconds for weeks: the writer keeps the newest paths (not every one
    since it started) and the summary counts every file written."""
    from bf_epic_blocks.blocks import image_writer
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    monkeypatch.setattr(image_writer.ImageWriterBlock, "KEEP_PATHS", 1)
    tbf = _small_tbf(tmp_path / "rec.tbf", ntime=1200)
    y = _recording_yaml(tmp_path, tbf)
    s = runner.run(load_config(y, ["device=cpu", f"output.dir={tmp_path / 'out'}"]), show_progress=False)
    on_disk = sorted(p.name for p in (tmp_path / "out").glob("*.fits"))
    assert s["images"] == 4 and len(on_disk) == 4
    assert s["files_written"] == 4
    kept = [Path(f).name for f in s["files"]]
    assert 1 <= len(kept) <= 2 and kept == on_disk[-len(kept):]


def test_the_kernel_store_fills_cupy_s_cache_with_what_it_lacks(tmp_path, monkeypatch):
    """A GPU run copies the store's compiled kernels that CuPy's cache lacks into it, whole, and leaves
    those it has alone; a CPU run copies nothing; a cache that cannot be written is counted, not raised."""
    from bf_epic_blocks.cuda import seed_cupy_cache
    from bf_epic_blocks.pipeline.runner import seed_kernels
    store, cache = tmp_path / "store", tmp_path / "cache"
    store.mkdir()
    for k in range(3):
        (store / f"k{k}_2.cubin").write_bytes(bytes([k]) * (1000 + k))
    cache.mkdir()
    (cache / "k1_2.cubin").write_bytes(b"the cache's own")
    monkeypatch.setenv("BF_EPIC_KERNELS", str(store))
    monkeypatch.setenv("CUPY_CACHE_DIR", str(cache))
    assert seed_kernels({"device": "cpu"}) is None and sorted(p.name for p in cache.iterdir()) == ["k1_2.cubin"]
    got = seed_kernels({"device": "gpu:0"})
    assert (got["copied"], got["present"], got["failed"]) == (2, 1, 0)
    assert sorted(p.name for p in cache.iterdir()) == ["k0_2.cubin", "k1_2.cubin", "k2_2.cubin"]
    assert (cache / "k2_2.cubin").read_bytes() == (store / "k2_2.cubin").read_bytes()
    assert (cache / "k1_2.cubin").read_bytes() == b"the cache's own"
    st = seed_kernels({"device": "cpu", "tunings": [{"device": "cpu"}, {"device": "gpu:1"}]})
    assert (st["copied"], st["present"]) == (0, 3)
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    assert seed_cupy_cache(store, blocked)["failed"] == 3
    assert seed_cupy_cache(tmp_path / "no-store", cache) == {"store": str(tmp_path / "no-store"), "cache": str(cache),
                                                              "copied": 0, "linked": 0, "present": 0, "failed": 0}


def test_the_kernel_store_links_its_files_where_it_can_and_copies_where_not(tmp_path, monkeypatch):
    """On one file system the cache's file is the store's (one inode, no bytes copied); where a link is refused
    (another file system) it is a copy; and CuPy's way of writing a cache file (a new file renamed over the
    name) leaves the store's file as it was."""
    import os
    from bf_epic_blocks import cuda
    store, cache, other = tmp_path / "store", tmp_path / "cache", tmp_path / "other"
    store.mkdir()
    for k in range(2):
        (store / f"k{k}_2.cubin").write_bytes(bytes([k + 1]) * 4096)
    got = cuda.seed_cupy_cache(store, cache)
    assert (got["copied"], got["linked"], got["present"], got["failed"]) == (2, 2, 0, 0)
    assert os.stat(cache / "k0_2.cubin").st_ino == os.stat(store / "k0_2.cubin").st_ino
    new = cache / "tmpXYZ"
    new.write_bytes(b"recompiled")
    os.replace(new, cache / "k0_2.cubin")                     # as CuPy's compiler rewrites a cache file
    assert (store / "k0_2.cubin").read_bytes() == bytes([1]) * 4096

    def refuse(src, dst):
        raise OSError(18, "Invalid cross-device link")
    monkeypatch.setattr(cuda.os, "link", refuse)
    got = cuda.seed_cupy_cache(store, other)
    assert (got["copied"], got["linked"], got["failed"]) == (2, 0, 0)
    assert os.stat(other / "k1_2.cubin").st_ino != os.stat(store / "k1_2.cubin").st_ino
    assert (other / "k1_2.cubin").read_bytes() == (store / "k1_2.cubin").read_bytes()
    assert sorted(p.name for p in other.iterdir()) == ["k0_2.cubin", "k1_2.cubin"]     # no temporaries left


def test_compile_refuses_what_it_cannot_run(tmp_path, capsys):
    """`bf-epic compile` runs simulated pipelines on a GPU: a capture's pipeline, or no GPU, is a clear
    error (exit 2) before anything runs."""
    from conftest import HAVE_GPU
    assert cli.main(["compile", str(PIPES / "lwasv_udp_live.yaml"), "--store", str(tmp_path / "s")]) == 2
    assert "reads a udp source; compile runs simulated pipelines only" in capsys.readouterr().err
    if not HAVE_GPU:
        assert cli.main(["compile", str(PIPES / "lwasv_sim_allsky.yaml"), "--store", str(tmp_path / "s")]) == 2
        assert "compile needs CuPy and a CUDA GPU" in capsys.readouterr().err
        # a CPU YAML given a GPU-only mode is read as the GPU pipeline it compiles, not refused as a CPU one
        assert cli.main(["compile", str(PIPES / "lwasv_sim_station.yaml"), "--store", str(tmp_path / "s"),
                         "--set", "imager.tolerance=null", "--set", "imager.precision=i8x1"]) == 2
        assert "compile needs CuPy and a CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_compile_reads_a_pipeline_as_it_runs_on_a_gpu(tmp_path):
    from bf_epic_blocks.pipeline.cli import _names_gpu
    cpu, gpu = tmp_path / "cpu.yaml", tmp_path / "gpu.yaml"
    cpu.write_text("device: cpu\n")
    gpu.write_text("device: 'gpu:all'\n")
    assert not _names_gpu(cpu, []) and not _names_gpu(tmp_path / "none.yaml", [])
    assert _names_gpu(gpu, []) and _names_gpu(cpu, ["device=gpu:1"]) and not _names_gpu(gpu, ["device=cpu"])
    assert _names_gpu(cpu, ["device=cpu", "device=gpu"])     # the last --set wins, as load_config reads them


@pytest.mark.gpu
@pytest.mark.slow
def test_a_run_after_compile_compiles_nothing_on_an_empty_cache(tmp_path):
    """The install step's promise: `bf-epic compile` of a pipeline fills the store; a run of it with CuPy's
    cache empty then finds every kernel there (no file added to the cache beyond the store's)."""
    import os
    import subprocess
    import sys

    from conftest import HAVE_GPU
    if not HAVE_GPU:
        pytest.skip("needs CuPy and a CUDA device")
    from benchlib import bf_epic_command, child_env
    yaml, sets = str(PIPES / "lwasv_sim_transient.yaml"), ["--set", "imager.grid.size=16", "--set",
                                                           "source.channels.count=32"]
    env = dict(child_env(), BF_EPIC_KERNELS=str(tmp_path / "store"), CUPY_CACHE_DIR=str(tmp_path / "cache"))
    out = subprocess.run([sys.executable, "-m", "bf_epic_blocks.pipeline.cli", "compile", yaml, "--seconds", "1.5",
                          *sets], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    stored = set(os.listdir(tmp_path / "store"))
    cache = tmp_path / "cache"
    before = set(os.listdir(cache)) if cache.exists() else set()
    assert len(stored) > 10 and not stored & before
    run = subprocess.run(bf_epic_command() + ["run", yaml, "--no-progress", *sets, "--set", "source.duration_s=1.5",
                                              "--set", f"output.dir={tmp_path / 'out'}", "--set", "device=gpu"],
                         env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert f"{len(stored)} compiled kernels copied into CuPy's cache" in run.stderr
    assert set(os.listdir(cache)) - before == stored       # every file new in the cache came from the store


def test_compile_runs_each_pipeline_long_enough_for_its_periodic_steps_twice():
    from bf_epic_blocks.pipeline.cli import compile_seconds
    from bf_epic_blocks.pipeline.config import load_config
    assert compile_seconds(load_config(str(PIPES / "lwasv_sim_allsky.yaml"))) == 3.0
    # a solution every 10 s from 1 s of data, applied 1 s later, the high tuning's 5 s after the low's: its
    # second solution is made by 17 s
    assert compile_seconds(load_config(str(PIPES / "lwasv_sim_station.yaml"))) == 18.0
    assert compile_seconds(load_config(str(PIPES / "lwasv_sim_allsky.yaml"), ["output.integrate.seconds=4"])) == 9.0


def test_plan_counts_the_live_solver_once_and_the_station_fits_its_gpu_pool():
    """The station's plan on one GPU: each tuning's live solver counted as what it holds plus the most it
    adds (not every figure solver_bytes reports), and both tunings within the pool limit its YAML sets
    (gpu_memory_gb), which `run` enforces before anything is allocated."""
    from bf_epic_blocks.imaging import cost
    from bf_epic_blocks.pipeline import config, runner
    cfg = config.load_config(PIPES / "lwasv_sim_station.yaml", ["device=gpu"])
    d, text = runner.plan(cfg)
    sb = cost.solver_bytes(784, 256, 2, gpu=True, diffuse=cfg["calibration"]["solve"]["diffuse"])
    for t in ("low", "high"):
        assert d["tunings"][t]["memory_bytes"]["live gain solver"] == sb["held"] + sb["working"]
    (dev, need), = d["memory_bytes_per_device"].items()
    assert need <= cfg["gpu_memory_gb"] * 1e9 and "ABOVE IT" not in text, (dev, need)


def test_the_switch_interval_comes_from_the_environment_and_a_bad_one_is_a_clear_error(tmp_path, monkeypatch,
                                                                                         capsys):
    """BF_EPIC_SWITCH_INTERVAL_S sets the interpreter's switch interval for the run (the default where unset);
    a value that is not seconds in (0, 0.1] stops `bf-epic run` with one line naming the variable."""
    import sys
    seen = []
    monkeypatch.setattr(sys, "setswitchinterval", seen.append)
    monkeypatch.delenv(cli.SWITCH_INTERVAL_ENV, raising=False)
    assert cli.switch_interval() == cli.SWITCH_INTERVAL_S == 0.001
    monkeypatch.setenv(cli.SWITCH_INTERVAL_ENV, "0.00025")
    assert cli.switch_interval() == 0.00025
    for bad in ("fast", "0", "-1e-3", "0.5", "nan"):
        monkeypatch.setenv(cli.SWITCH_INTERVAL_ENV, bad)
        with pytest.raises(ValueError, match=r"BF_EPIC_SWITCH_INTERVAL_S must be seconds in \(0, 0.1\]"):
            cli.switch_interval()
    assert cli.main(["run", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", f"output.dir={tmp_path}", *FAST]) == 1
    assert "BF_EPIC_SWITCH_INTERVAL_S must be seconds" in capsys.readouterr().err and seen == []
    monkeypatch.setenv(cli.SWITCH_INTERVAL_ENV, "0.0005")
    assert cli.main(["run", str(PIPES / "lwasv_sim_allsky.yaml"), "--set", f"output.dir={tmp_path}", *FAST]) == 0
    assert seen == [0.0005]


def test_a_run_asked_to_lists_the_kernels_cupy_compiles_while_it_runs(monkeypatch, caplog):
    """With $BF_EPIC_LOG_COMPILES a GPU run wraps CuPy's compiler (its cache misses) and lists each kernel compiled,
    the thread and the package's frame that asked, in its summary and the log; unset, or on the CPU, nothing is
    wrapped. A CuPy is faked here: what is checked is the recording, not CuPy."""
    import logging
    import sys
    import types

    from bf_epic_blocks import cuda
    from bf_epic_blocks.pipeline import runner

    calls = []

    def nvrtc(source, options=(), *args, **kwargs):
        calls.append(source)
        return b"cubin"
    compiler = types.SimpleNamespace(_compile_using_nvrtc_no_warning=nvrtc)
    fake = types.ModuleType("cupy")
    fake.cuda = types.SimpleNamespace(compiler=compiler)
    monkeypatch.setitem(sys.modules, "cupy", fake)
    monkeypatch.setitem(sys.modules, "cupy.cuda", fake.cuda)
    monkeypatch.setitem(sys.modules, "cupy.cuda.compiler", compiler)

    monkeypatch.delenv(cuda.COMPILE_LOG_ENV, raising=False)
    assert runner.watch_compiles({"device": "gpu"}) is None and compiler._compile_using_nvrtc_no_warning is nvrtc
    monkeypatch.setenv(cuda.COMPILE_LOG_ENV, "1")
    assert runner.watch_compiles({"device": "cpu"}) is None
    watched = runner.watch_compiles({"tunings": [{"device": "gpu"}, {"device": "gpu"}]})
    assert watched is not None and compiler._compile_using_nvrtc_no_warning is not nvrtc
    assert runner.watch_compiles({"device": "gpu"})[0] is watched[0]       # wrapped once

    src = 'extern "C" __global__ void bf_probe(const float* x) { }'
    # asked from a frame of the package (a file name under it), and from outside it
    code = compile("def ask(c, s):\n    return c._compile_using_nvrtc_no_warning(s, ('-DX=1',))\n",
                   str(cuda.PACKAGE_DIR / "imaging" / "asker.py"), "exec")
    space = {}
    exec(code, space)
    with caplog.at_level(logging.INFO, logger=runner.log.name):
        assert space["ask"](compiler, src) == b"cubin"
        assert compiler._compile_using_nvrtc_no_warning("", ()) == b"cubin"      # CuPy's empty-file probe
        compiler._compile_using_nvrtc_no_warning('__global__ void other() {}', ())
        summary = runner._with_compiles({"name": "t"}, watched)
    assert calls == [src, "", "__global__ void other() {}"]
    got = summary["kernels_compiled_while_running"]
    assert [(r["kernel"], r["caller"]) for r in got] == [("bf_probe", "imaging/asker.py:2:ask"), ("other", "")]
    assert all(r["seconds"] >= 0 and r["thread"] for r in got)
    assert "kernel bf_probe compiled while running" in caplog.text
    assert "2 kernels compiled while running (not in the kernel store): bf_probe, other" in caplog.text
    assert runner._with_compiles({"name": "t"}, None) == {"name": "t"}
