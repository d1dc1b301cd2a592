"""The benchmark scripts' own helpers (tools/bench/, on the path through setup.cfg's pytest
``pythonpath``): what they measure must mean what their tables say. Timing itself is never asserted."""
import os
import time

import numpy as np
import pytest

pytest.importorskip("astropy")
pytest.importorskip("h5py")


def test_benchlib_names_the_machine_by_its_hardware_and_refuses_unknown_devices():
    import benchlib
    m = benchlib.machine("cpu")
    assert m["ncpu"] == os.cpu_count() and m["hardware"] == f"{m['cpu']}, {os.cpu_count()} cores"
    assert "gpu" not in m
    assert benchlib.array_module("cpu") is np
    with pytest.raises(ValueError, match=r"device 'tpu': expected one of \('cpu', 'gpu'\)"):
        benchlib.array_module("tpu")


def test_benchlib_imports_a_package_from_a_folder_without_touching_sys_path(tmp_path):
    """bench_dft.py --previous: a release copied aside as a package is imported, its submodules with it."""
    import sys
    import benchlib
    pkg = tmp_path / "bf_epic_prev_probe"
    (pkg / "imaging").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from . import imaging\n")
    (pkg / "imaging" / "__init__.py").write_text("VALUE = 42\n")
    before = list(sys.path)
    try:
        mod = benchlib.import_package(tmp_path, "bf_epic_prev_probe")
        import bf_epic_prev_probe.imaging as sub
        assert mod.imaging.VALUE == 42 and sub is mod.imaging and sys.path == before
    finally:
        for name in [n for n in sys.modules if n.startswith("bf_epic_prev_probe")]:
            del sys.modules[name]
    with pytest.raises(FileNotFoundError, match="nowhere"):
        benchlib.import_package(tmp_path, "nowhere")


def test_bench_e2e_steady_rate_is_the_imager_s_own_pace():
    """tools/bench/bench_e2e.py: the steady real-time factor comes from the imager's first and last gulps,
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
    """tools/bench/bench_wholeband.py: memory 'growth' is the last quarter's peak over the first quarter's,
    within the flowing span only (start-up allocations before it do not count)."""
    import bench_wholeband as bw
    flat = [(0.5, 100.0)] + [(t, 5000.0 + (t % 3)) for t in np.arange(2.0, 22.0, 1.0)]
    assert bw.growth(flat, 2.0, 21.0) == (5000.0 + 2 % 3, 5002.0, 0.0)
    grows = [(t, 5000.0 + 10 * t) for t in np.arange(2.0, 22.0, 1.0)]
    first, peak, g = bw.growth(grows, 2.0, 21.0)
    assert peak == 5210.0 and g == pytest.approx(5210.0 - 5060.0)
    assert bw.growth([(1.0, None)], 0.0, 2.0) == (None, None, None)



def test_bench_wholeband_lists_the_brightest_candidates_with_their_times():
    """The record lists what the run found: the brightest rows first, each with its time after the
    source's start (from the row's UTC time), DM, S/N, width, kind and place; none for no table."""
    import astropy.units as u
    import bench_wholeband as bw
    from astropy.table import Table
    from astropy.time import Time
    start = "2026-11-28T00:00:00"
    rows = [{"time_utc": (Time(start) + dt * u.s).isot, "snr": snr, "dm": dm, "width_ms": 0.64, "kind": "point",
             "ra_deg": 10.0, "dec_deg": -5.0} for dt, snr, dm in ((1.5, 8.0, 0.1), (3.25, 30.0, 0.4), (0.5, 7.0, 0.0))]
    got = bw.candidate_rows(Table(rows=rows), np.datetime64(start), "low", limit=2)
    assert [(r["tuning"], r["time_s"], r["snr"], r["dm"]) for r in got] == [("low", 3.25, 30.0, 0.4),
                                                                              ("low", 1.5, 8.0, 0.1)]
    assert got[0]["kind"] == "point" and got[0]["ra_deg"] == 10.0
    assert bw.candidate_rows(None, np.datetime64(start)) == []

@pytest.mark.slow
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
    assert r["solver"] is None                     # the whole-band YAML solves no gains
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
    """tools/bench/bench_scrunch.py (a prediction, not a search mode): with no trial at half rate the split
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


def test_profile_memory_samples_the_host_and_reports_a_failure_rather_than_raising(tmp_path, monkeypatch):
    """tools/bench/profile_memory.py on the demo made small (CPU): the host's samples (resident set,
    glibc's heap where glibc has mallinfo2) and their slopes in the JSON; a run that fails (what the tool
    is for: out of memory) is reported with its error and exit 1, its samples kept."""
    import json
    import profile_memory as pm
    small = ["--yaml", "pipelines/lwasv_sim_allsky.yaml", "--device", "cpu", "--seconds", "0.5", "--host-every", "0.05",
             "--set", "source.channels.count=2", "--set", "imager.grid.size=16", "--set", "output.fits=false",
             "--set", "output.png=false", "--set", f"output.dir={tmp_path / 'o'}"]
    assert pm.main(small + ["--snap", "0.05", "0.1", "--json", str(tmp_path / "m.json")]) == 0
    d = json.loads((tmp_path / "m.json").read_text())
    host = d["host"]["samples"]
    largest = d["host"]["largest_containers"]
    assert len(largest) == 2 and all(len(v["containers"]) == 10 and " held as " in v["containers"][0] for v in largest)
    assert d["error"] is None and d["gpu"] is None and len(host) >= 3
    assert all(s["rss"] > 50 for s in host)
    if pm._libc() is not None:
        assert all(s["malloc_in_use"] > 1 for s in host) and "malloc_in_use" in d["host"]["slopes_mib_per_s"]
    from bf_epic_blocks.pipeline import runner

    def out_of_memory(cfg, **kw):
        raise MemoryError("Out of memory allocating 822,083,584 bytes")
    monkeypatch.setattr(runner, "run", out_of_memory)
    assert pm.main(small + ["--json", str(tmp_path / "bad.json")]) == 1
    bad = json.loads((tmp_path / "bad.json").read_text())
    assert bad["error"].startswith("MemoryError: Out of memory") and len(bad["host"]["samples"]) >= 1

    def stopped(cfg, **kw):               # a time limit's SIGTERM: the runner drains, then raises this
        time.sleep(0.6)                   # (the sampler's last sample, after this, is past --trace-from)
        raise KeyboardInterrupt
    monkeypatch.setattr(runner, "run", stopped)
    assert pm.main(small + ["--snap", "0.05", "0.1", "--tracemalloc", "--trace-from", "0.3",
                            "--json", str(tmp_path / "stop.json")]) == 1
    stop = json.loads((tmp_path / "stop.json").read_text())
    assert stop["error"].startswith("KeyboardInterrupt") and len(stop["host"]["samples"]) >= 3
    s = stop["host"]["samples"]
    assert "traced" not in s[0] and "traced" in s[-1]             # traced from --trace-from on


def test_profile_memory_refuses_a_bad_setting_with_its_message(capsys):
    """A mistyped --set (or a YAML that is not there) is the config's message and exit 2, not a traceback."""
    import profile_memory as pm
    assert pm.main(["--device", "cpu", "--set", "imager.no_such_key=1"]) == 2
    assert "no_such_key" in capsys.readouterr().err
    assert pm.main(["--device", "cpu", "--yaml", "pipelines/no_such.yaml"]) == 2
    assert "config file not found" in capsys.readouterr().err


def test_profile_memory_counts_what_was_alive_at_a_time_by_site():
    """--lifetimes' summary: an allocation is alive from when it was made until it was freed (or the end);
    a Workspace's allocations are named with their caller."""
    import profile_memory as pm
    logs = [[1.0, 2**30, "a", ["x.py:1:f"], 3.0],                     # freed before t = 4
            [2.0, 2**29, "a", ["x.py:1:f"], None],                    # never freed
            [3.5, 2**30, "b", ["tree.py:9:push", "_xp.py:169:take"], 4.5],
            [4.0, 2**28, "b", ["y.py:2:g"], 4.0],                     # freed at t = 4: not alive then
            [5.0, 2**30, "b", ["y.py:2:g"], None]]                    # made after t = 4
    live = pm.live_by_site(logs, 4.0)
    assert live == [{"site": "_xp.py:169:take < tree.py:9:push", "count": 1, "gib": 1.0},
                    {"site": "x.py:1:f", "count": 1, "gib": 0.5}]
    assert pm.live_by_site(logs, 0.5) == [] and pm.site_of([]) == "?"


def _grow(store, n):
    store.extend(bytearray(2**16) for _ in range(n))     # n blocks of 64 KiB from one line


def test_profile_memory_names_the_python_allocations_that_grew():
    """--tracemalloc's summary: the traceback whose bytes grew most between two snapshots is the line that
    allocated them, with its size and block count; a line that allocated and let go does not show."""
    import tracemalloc

    import profile_memory as pm
    keep = []
    tracemalloc.start(12)
    try:
        s0 = tracemalloc.take_snapshot()
        _grow(keep, 64)                  # 4 MiB kept
        _grow([], 64)                    # 4 MiB made and dropped
        s1 = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    top = pm.traced_growth_by_site(s0, s1)[0]
    assert top["frames"][0].startswith("test_bench.py:") and len(top["frames"]) <= 4
    assert 4.0 <= top["mib"] < 4.2 and top["blocks"] >= 64
    assert sum(x["mib"] for x in pm.traced_growth_by_site(s0, s1)) < 4.5


def test_profile_memory_tracemalloc_needs_two_snapshot_times():
    import profile_memory as pm
    with pytest.raises(SystemExit) as e:
        pm.main(["--device", "cpu", "--tracemalloc"])
    assert e.value.code == 2


def test_predict_gauss_reproduces_the_package_and_bounds_the_three_product_forms():
    """tools/bench/predict_gauss.py: its four-product arithmetic gives the package's fused-mode images (the
    package's quantisation and int64 emulation of the kernel) to float32's rounding of the epilogue; the
    three-product forms' errors against the float64 definition are of the four-product mode's order (a
    wrong combination of the three products would be off by the image itself)."""
    import predict_gauss as pg
    from cases import lwasv_like_layout, quantise4, reference_image, sky_efield
    from bf_epic_blocks import imaging
    xyz, _ = lwasv_like_layout(64)
    freq = 74e6 + 25e3 * np.arange(2)
    Q = quantise4(sky_efield(xyz, freq, 64, npol=2, dtype=np.complex128))
    lm = imaging.lm_grid(16).lm
    ref = reference_image(Q, xyz, freq, lm, ((0, 0), (1, 1)), accumulate=16)
    D = pg.operator(xyz, freq, lm)
    scale = np.abs(ref).max()
    for pieces in (2, 3):
        pkg = pg.package_images(xyz, freq, lm, Q, pieces)
        err_pkg = np.abs(pkg - ref).max() / scale                     # 5.9e-6 (i8x2), 2.9e-7 (i8x3) here
        assert np.abs(pg.images(D, Q, pieces, "four") - pkg).max() / scale < 3e-7    # float32's epilogue
        for form in ("shared", "own"):
            assert np.abs(pg.images(D, Q, pieces, form) - ref).max() / scale < 3 * err_pkg


def test_profile_writers_prints_and_writes_each_writer_s_samples(tmp_path, capsys):
    """tools/bench/profile_writers.py at tiny sizes: a row a writer (the watch writer at each channel count,
    the cube writer), samples of glibc's bytes in use every --every s of data, the growth and wall time,
    written as JSON."""
    import json

    import profile_writers as pw
    if pw.in_use_mib() is None:
        pytest.skip("needs glibc's mallinfo2")
    out = tmp_path / "w.json"
    assert pw.main(["--seconds", "6", "--every", "2", "--watch-channels", "4", "--npix", "50",
                    "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert [r["writer"] for r in rec["rows"]] == ["watch", "cube"]
    for r in rec["rows"]:
        assert [s[0] for s in r["samples"]][:3] == [0.0, 2.0, 4.0] and r["wall_s"] > 0
        assert r["growth_mib"] == round(r["samples"][-1][1] - r["samples"][0][1], 2)
    assert "watch" in capsys.readouterr().out


def test_bench_dft_table_replaces_only_the_precisions_it_timed(tmp_path, monkeypatch):
    """`bench_dft.py --precisions i8x1 --table` writes i8x1's row and keeps every other precision's, the
    GPU's fp16 among them; a run of every precision replaces them all."""
    import json
    import bench_dft
    from bf_epic_blocks.imaging import plan
    path = tmp_path / "measured.json"
    old = [{"device": "gpu", "method": "direct", "precision": p, "bound": 1e-3, "rate_cmac_s": 1e13} for p in
           ("fp16", "i8x1")] + [{"device": "cpu", "method": "direct", "precision": "fp32", "bound": 1e-6,
                                 "rate_cmac_s": 1e10}]
    path.write_text(json.dumps({"rows": old}))
    monkeypatch.setattr(plan, "TABLE_PATH", path)
    row = {"grid": 64, "regime": "gulp", "route": "direct", "precision": "i8x1", "gulp_s": 1e-3, "cmacs": 1e11,
           "rel_err": 2e-3}
    result = {"precisions": ["i8x1"], "rows": [row], "hard_scenes": [{"route": "direct", "precision": "i8x1",
                                                                      "rel_err": 3.05e-3}],
              "machine": {"gpu": "a GPU", "cpu": "a CPU"}, "date": "2026-12-02T00:00:00"}
    bench_dft.write_table(result, "gpu")
    rows = {(r["device"], r["precision"]): r for r in json.loads(path.read_text())["rows"]}
    assert set(rows) == {("gpu", "fp16"), ("gpu", "i8x1"), ("cpu", "fp32")}
    assert rows[("gpu", "fp16")] == old[0]
    assert rows[("gpu", "i8x1")]["bound"] == 1e-2 and rows[("gpu", "i8x1")]["rate_cmac_s"] == 1e14
    assert rows[("gpu", "i8x1")]["input"] == "ci4"


def test_profile_station_busy_fraction_idle_gaps_and_the_threads_that_waited():
    """profile_station.summarise on a trace written here: two kernels overlapping on two streams and a copy,
    a gap in which one thread sat in cudaStreamSynchronize; the union, the gap, the stages and the
    per-thread figures are the arithmetic of those intervals."""
    import profile_station as ps
    us = 1e-6
    ev = [{"ph": "X", "cat": "kernel", "name": "bf_fused_power", "ts": 0, "dur": 500,
           "args": {"stream": 7, "correlation": 5}},
          {"ph": "X", "cat": "kernel", "name": "bf_fdmt_level", "ts": 400, "dur": 300, "args": {"stream": 8}},
          {"ph": "X", "cat": "gpu_memcpy", "name": "Memcpy DtoH", "ts": 900, "dur": 100, "args": {"stream": 7}},
          {"ph": "X", "cat": "cuda_runtime", "name": "cudaStreamSynchronize", "ts": 650, "dur": 300, "tid": 11},
          {"ph": "X", "cat": "cuda_driver", "name": "cuLaunchKernel", "ts": 10, "dur": 5, "tid": 12,
           "args": {"correlation": 5}},
          {"ph": "X", "cat": "cpu_op", "name": "not GPU work", "ts": 0, "dur": 2000, "tid": 12}]
    r = ps.summarise({"traceEvents": ev}, 1.0, cpu={11: 0.25, 12: 0.5}, names={11: "search", 12: "imager"})
    assert r["traced_span_s"] == pytest.approx(1000 * us)
    assert r["busy"] == pytest.approx(0.8)                     # 0-700 and 900-1000 of 0-1000
    assert r["kernel_s_per_s"] == pytest.approx(0.9)           # each counted in full
    assert r["stages"]["imaging: fused integer kernel"] == pytest.approx(0.5)
    assert r["stages"]["search: tree"] == pytest.approx(0.3) and r["stages"]["copies"] == pytest.approx(0.1)
    assert r["idle"]["gaps"] == 1 and r["idle"]["s_per_s"] == pytest.approx(0.2)
    assert r["idle"]["threads_waiting_s_per_s"] == {"search": pytest.approx(0.2)}   # 700-900 of its 650-950
    t = {x["thread"]: x for x in r["threads"]}
    assert t["search"]["wait_s_per_s"] == pytest.approx(0.3) and t["imager"]["wait_s_per_s"] == 0
    assert t["imager"]["cuda_calls"] == 1 and t["imager"]["cpu_s_per_s"] == 0.5
    assert t["imager"]["streams"] == {"7": 1} and t["search"]["streams"] == {}   # joined by correlation id
    assert r["streams"] == {"7": pytest.approx(0.6), "8": pytest.approx(0.3)}
    assert ps.union_seconds([(0, 2), (1, 3), (5, 6)]) == 4
    assert ps.stage_of("sim_gulp_few") == "other" and ps.stage_of("bf_layout_ci4_p2").startswith("imaging")
    with pytest.raises(SystemExit, match="no GPU activity"):
        ps.summarise({"traceEvents": ev[3:]}, 1.0)
    names = ps.thread_names()       # CUPTI's thread ids (pthread_t's low 32 bits) name Python's threads too
    import threading
    assert names[threading.get_ident() & 0xFFFFFFFF] == threading.current_thread().name


def test_profile_station_gil_probe_sees_a_thread_that_holds_the_interpreter():
    """The probe's 0.5-ms sleeps wake about a switch interval late while another thread runs Python, and
    about on time when none does."""
    import sys
    import threading
    import profile_station as ps

    def probe(seconds):
        stop, out = threading.Event(), {}
        th = threading.Thread(target=ps.gil_probe, args=(stop, out))
        th.start()
        time.sleep(seconds)
        stop.set()
        th.join()
        return out["gil_wait_ms"]

    quiet = probe(0.3)
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.02)
    busy = threading.Event()

    def spin():
        while not busy.is_set():
            sum(range(200))
    th = threading.Thread(target=spin)
    th.start()
    try:
        loaded = probe(0.6)
    finally:
        busy.set()
        th.join()
        sys.setswitchinterval(old)
    assert loaded["median"] > 10.0 > quiet["median"]


def test_bench_wholeband_passes_the_switch_interval_to_the_run(monkeypatch):
    """--switch-interval-s reaches the bf-epic run it times as BF_EPIC_SWITCH_INTERVAL_S; without it the run
    inherits the environment's (here: none)."""
    import argparse
    import bench_wholeband as bw
    seen = []

    class Run:
        pid = os.getpid()

        def __init__(self, cmd, env=None, **kw):
            seen.append(env)

        def wait(self):
            return 3
    monkeypatch.setattr(bw.subprocess, "Popen", Run)
    monkeypatch.delenv("BF_EPIC_SWITCH_INTERVAL_S", raising=False)
    base = dict(yaml=bw.REPO / "pipelines" / "lwasv_sim_allsky.yaml", device="cpu", seconds=1.0, set=[], sample_s=0.01,
                warm_bytecode=False)
    for si in (0.0005, None):
        with pytest.raises(SystemExit, match=r"bf-epic run failed \(3\)"):
            bw.run(argparse.Namespace(switch_interval_s=si, **base))
    assert seen[0]["BF_EPIC_SWITCH_INTERVAL_S"] == "0.0005" and "BF_EPIC_SWITCH_INTERVAL_S" not in seen[1]
    assert bw.COMPILE_LOG_ENV not in seen[0]
    # on a GPU the run lists the kernels it compiles, and what it imports is compiled to bytecode first
    warmed = []
    monkeypatch.setattr(bw, "warm_bytecode", lambda device: warmed.append(device) or {"prefix": None, "seconds": 0.0})
    with pytest.raises(SystemExit, match=r"bf-epic run failed \(3\)"):
        bw.run(argparse.Namespace(switch_interval_s=None, **dict(base, device="gpu", warm_bytecode=True)))
    assert seen[2][bw.COMPILE_LOG_ENV] == "1" and warmed == ["gpu"]


def test_warm_bytecode_compiles_what_a_run_imports_where_it_may_not_be_written_beside_the_sources(
        tmp_path, monkeypatch):
    """Where the environment forbids bytecode beside the sources, the timed runs keep it in a folder of their own,
    which warm_bytecode fills first (as an installation's pip does); elsewhere it does nothing."""
    import benchlib
    monkeypatch.setattr(benchlib, "_PYCACHE", tmp_path / "pyc")
    monkeypatch.setattr(benchlib, "RUN_IMPORTS", ("yaml", "no_such_module_here"))
    monkeypatch.delenv("PYTHONPYCACHEPREFIX", raising=False)
    monkeypatch.delenv("PYTHONDONTWRITEBYTECODE", raising=False)
    assert benchlib.warm_bytecode("cpu") == {"prefix": None, "seconds": 0.0}
    assert not (tmp_path / "pyc").exists()
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    got = benchlib.warm_bytecode("cpu")
    assert got["prefix"] == str(tmp_path / "pyc") and got["seconds"] > 0
    assert any("yaml" in str(p) for p in (tmp_path / "pyc").rglob("*.pyc"))


def test_clock_fused_reads_the_samples_taken_while_a_mode_ran_and_names_the_reasons():
    """tools/bench/clock_fused.py: only nvidia-smi's samples inside a mode's span count, malformed lines
    (a driver message, a missing field) are passed over, and the reason bits decode to their names."""
    import clock_fused as cf
    lines = ["2026/12/02 20:15:30.151, 1980, 1980, 89.86, 700.00, 0x0000000000000000",
             "2026/12/02 20:15:32.724, 1755, 1980, 704.40, 700.00, 0x0000000000000004",
             "Failed to initialize NVML: Unknown Error",
             "2026/12/02 20:15:33.479, 1680, 1980, [N/A], 700.00, 0x0000000000000004",
             "2026/12/02 20:15:33.731, 1770, 1980, 693.65, 700.00, 0x0000000000000005",
             "2026/12/02 20:15:40.540, 1980, 1980, 197.26, 700.00, 0x0000000000000000"]
    t = lambda s: time.mktime(time.strptime(s, "%Y/%m/%d %H:%M:%S"))   # noqa: E731
    got = cf.parse(lines, t("2026/12/02 20:15:32"), t("2026/12/02 20:15:34"))
    assert [v[0] for v in got] == [1755.0, 1770.0] and got[0][2] == 704.4 and got[1][4] == 5
    bits = got[0][4] | got[1][4]
    assert [n for b, n in cf.REASONS.items() if bits & b] == ["idle", "power cap (software)"]
