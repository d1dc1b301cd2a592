"""The station service (`bf-epic run --serve`): health judged from chosen snapshots, the HTTP surface
(what it serves, what it refuses), and a real run scraped while it goes."""
import threading
import time
import urllib.error
import urllib.request

import pytest

pytest.importorskip("aiohttp")
pytest.importorskip("prometheus_client")

from bf_epic_blocks.service.monitor import Limits, assess  # noqa: E402
from bf_epic_blocks.service.server import Service, parse_listen  # noqa: E402


def _snap(**kw):
    s = {"uptime_s": 100.0, "data_s": 90.0, "realtime": 1.2, "realtime_recent": 1.2, "last_data_age_s": 0.1,
         "blocks": {"Src_0": {"ngulp": 10, "process_s": 0.5, "nframe_written": 10240}}, "source": {},
         "imager": {"images": 5}, "flagging": {"seen": 10, "flagged_sk-high": 2}, "failed": None, "finished": False, "live": True,
         "disk": {"total_bytes": 1e12, "used_bytes": 1e11, "free_bytes": 9e11}, "gpu": None}
    s.update(kw)
    return s


@pytest.mark.parametrize("change, status, words", [
    ({}, "go", None),
    ({"failed": "block 'X' failed: boom"}, "down", "stopped"),
    ({"last_data_age_s": 30.0}, "down", "no data for 30 s"),
    ({"last_data_age_s": 30.0, "finished": True}, "go", None),          # a capture that ended is not a stall
    ({"realtime_recent": 0.8}, "degraded", "behind real time"),
    ({"realtime_recent": 0.8, "live": False}, "go", None),              # a file may be read at any pace
    ({"source": {"frames_missing": 12, "packets": 100}}, "degraded", "frames_missing 12"),
    ({"solver": {"solutions": 3, "solution_age_s": 40.0}}, "degraded", "calibration stale"),
    ({"solver": {"solutions": 3, "solution_age_s": 20.0}}, "go", None),
    ({"disk": {"total_bytes": 1e12, "used_bytes": 1e12, "free_bytes": 4e9}}, "degraded", "disk low"),
    ({"disk": {"total_bytes": 1e12, "used_bytes": 1e12, "free_bytes": 1e9}}, "down", "disk nearly full"),
])
def test_health_from_chosen_snapshots(change, status, words):
    got, reasons = assess(_snap(**change), Limits(no_data_s=10.0, min_free_gb=5.0), cadence_s=10.0)
    assert got == status, reasons
    assert (words is None and not reasons) or any(words in r for r in reasons), reasons


def test_service_behind_sets_when_a_slow_stream_is_degraded():
    """service.behind: the real-time factor under which a live stream is degraded (0: never, for a stream
    replayed slower than real time on purpose), read from the YAML."""
    from bf_epic_blocks.pipeline.config import load_config
    slow = _snap(realtime_recent=0.004)
    assert assess(slow, Limits(behind=1.0))[0] == "degraded"
    assert assess(slow, Limits(behind=0.0))[0] == "go"
    assert assess(slow, Limits(behind=0.001))[0] == "go"
    on = "service={listen: '127.0.0.1:8080'}"
    assert load_config("pipelines/lwasv_udp_live.yaml", [on])["service"]["behind"] == 1.0
    assert load_config("pipelines/lwasv_udp_live.yaml", [on, "service.behind=0"])["service"]["behind"] == 0.0


def test_data_lost_is_degraded_within_the_window_then_go_again(tmp_path):
    """A live source that lost frames is degraded while the loss lies within service.lost_window_s, then go
    again (a glitch long ago is not the state now); the totals since the start stay in the snapshot. The
    Monitor over a stand-in graph whose source counters change between snapshots."""
    import time
    from types import SimpleNamespace

    from bf_epic_blocks.service.monitor import Monitor
    src = SimpleNamespace(name="Src", udp_stats={"packets": 10, "frames_missing": 0}, stats={})
    g = SimpleNamespace(pipeline=SimpleNamespace(blocks=[]), source=src, imager=None, search=None, watch=None,
                        solver=None, outdir=str(tmp_path), snippets=None)
    cfg = {"source": {"kind": "udp"}, "device": "cpu"}
    mon = Monitor(g, cfg, dt_s=1e-3, lost_window_s=0.3)
    lim = Limits(lost_window_s=0.3, min_free_gb=0.0)
    assert assess(mon.snapshot(), lim)[0] == "go"
    src.udp_stats = {"packets": 20, "frames_missing": 12}          # frames lost
    snap = mon.snapshot()
    status, reasons = assess(snap, lim)
    assert status == "degraded" and any("frames_missing 12" in r and "0.3 s" in r for r in reasons), reasons
    time.sleep(0.35)
    mon.snapshot()
    time.sleep(0.35)
    snap = mon.snapshot()
    assert assess(snap, lim)[0] == "go" and snap["source"]["frames_missing"] == 12
    assert snap["source_lost_recent"]["frames_missing"] == 0


class FakeMonitor:
    def __init__(self):
        self.snap = _snap()

    def snapshot(self):
        return dict(self.snap)


class FakeBus:
    def __init__(self):
        self.requests = []

    def request(self, reason):
        self.requests.append(reason)


def _get(url, data=None, headers=None, method=None):
    req = urllib.request.Request(url, data=data, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.read().decode(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(), e.headers.get("Content-Type", "")


@pytest.fixture
def served():
    mon, bus = FakeMonitor(), FakeBus()
    srv = Service(mon, "127.0.0.1:0", token="a-token-of-sixteen-chars", bus=bus, name="test").start()
    yield srv, mon, bus
    srv.stop()


def test_metrics_health_and_page(served):
    from prometheus_client.parser import text_string_to_metric_families
    srv, mon, _ = served
    code, body, ctype = _get(srv.url + "/metrics")
    assert code == 200 and ctype.startswith("text/plain")
    fams = {f.name: f for f in text_string_to_metric_families(body)}
    assert fams["bf_epic_up"].samples[0].value == 1.0
    assert fams["bf_epic_realtime_factor"].samples[0].value == pytest.approx(1.2)
    assert fams["bf_epic_imager_images"].samples[0].value == 5
    gulps = {s.labels["block"]: s.value for s in fams["bf_epic_block_ngulp"].samples}
    assert gulps == {"Src_0": 10.0}
    assert fams["bf_epic_health"].samples[0].value == 0
    assert fams["bf_epic_flagging_flagged_sk_high"].samples[0].value == 2        # a metric's name from 'sk-high'
    code, body, _ = _get(srv.url + "/health")
    assert code == 200 and '"status": "go"' in body
    mon.snap = _snap(last_data_age_s=60.0)
    time.sleep(0.6)                                          # past the shared snapshot's 0.5 s
    code, body, _ = _get(srv.url + "/health")
    assert code == 503 and '"status": "down"' in body and "no data for 60 s" in body
    code, body, ctype = _get(srv.url + "/")
    assert code == 200 and ctype.startswith("text/html") and "down" in body and "no data" in body



def test_memory_by_kind_follows_what_is_allocated_and_is_served(served):
    """memory_figures: 20 MB of 2-kB buffers (malloc, not Python's small-object arenas) show in malloc's
    figures (the resident set need not grow: freed heap pages are reused); the service serves each
    figure as bf_epic_memory_*."""
    from prometheus_client.parser import text_string_to_metric_families
    from bf_epic_blocks.service.heap import memory_figures
    before = memory_figures()
    if "heap_in_use" not in before:
        pytest.skip("not glibc >= 2.33 (no mallinfo2)")
    keep = [bytearray(b"x" * 2000) for _ in range(10_000)]
    after = memory_figures()
    assert 19e6 <= after["heap_in_use"] - before["heap_in_use"] < 30e6
    assert after["rss"] > after["heap_in_use"] - before["heap_in_use"]
    # the resident set by kind: the heap's pages are the process's own (anonymous), not a file's
    assert after["rss_anon"] + after["rss_file"] <= after["rss"] * 1.01 + 1e6
    assert after["rss_anon"] >= after["heap_in_use"] - before["heap_in_use"]
    assert after["threads"] >= 1
    del keep
    srv, mon, _ = served
    mon.snap = _snap(memory={"rss": 5e8, "heap_free": 1e6, "pinned_free_blocks": 3, "threads": 12})
    time.sleep(0.6)                                          # past the shared snapshot's 0.5 s
    fams = {f.name: f.samples[0].value for f in text_string_to_metric_families(_get(srv.url + "/metrics")[1])
            if f.samples}
    assert fams["bf_epic_memory_rss_bytes"] == 5e8 and fams["bf_epic_memory_heap_free_bytes"] == 1e6
    assert fams["bf_epic_memory_pinned_free_blocks"] == 3 and fams["bf_epic_memory_threads"] == 12

def test_the_page_lists_the_latest_candidates_first():
    """recent_candidates from a search's rows (an astropy Time each, as TransientSearchBlock keeps them):
    the last ten, latest first; the page shows them as a table, its text escaped."""
    from astropy.time import Time
    from bf_epic_blocks.service.monitor import recent_candidates
    rows = [{"time_utc": Time(1.7e9 + i, format="unix"), "snr": 7.0 + i, "dm": 0.1 * i, "width_ms": 0.64,
             "ra_deg": 300.0, "dec_deg": 40.0, "kind": "point"} for i in range(12)]
    rows[-1]["kind"] = "<b>sky-wide</b>"
    got = recent_candidates(rows)
    assert [c["snr"] for c in got] == [18.0 - i for i in range(10)]
    assert got[0]["time_utc"] == Time(1.7e9 + 11, format="unix").isot and got[0]["dm"] == pytest.approx(1.1)
    body = _page_of(_snap(recent_candidates=got))
    assert "<h2>Recent candidates</h2>" in body and body.count("<tr><td>20") == 10
    assert body.index("<td>18.0</td>") < body.index("<td>9.0</td>")
    assert "&lt;b&gt;sky-wide&lt;/b&gt;" in body and "<b>sky-wide</b>" not in body
    assert "Recent candidates" not in _page_of(_snap())


def _page_of(snap):
    mon = FakeMonitor()
    mon.snap = snap
    srv = Service(mon, "127.0.0.1:0", name="test").start()
    try:
        return _get(srv.url + "/")[1]
    finally:
        srv.stop()


def test_refusals(served):
    srv, _, bus = served
    assert _get(srv.url + "/../../etc/passwd")[0] == 404
    assert _get(srv.url + "/output/x.fits")[0] == 404                       # no files are served
    assert _get(srv.url + "/png/image")[0] == 404 and _get(srv.url + "/png/..%2f..%2fetc%2fpasswd")[0] == 404
    assert _get(srv.url + "/metrics", data=b"x", method="PUT")[0] == 405
    assert _get(srv.url + "/trigger", data=b"GRB")[0] == 401                 # no token
    assert _get(srv.url + "/trigger", data=b"GRB", headers={"Authorization": "Bearer wrong-token-xxxxxxxx"})[0] == 401
    big = b"x" * (65 * 1024)
    assert _get(srv.url + "/trigger", data=big,
                headers={"Authorization": "Bearer a-token-of-sixteen-chars"})[0] == 413
    assert bus.requests == []
    code, body, _ = _get(srv.url + "/trigger", data=b"GRB 261128A\nmore",
                         headers={"Authorization": "Bearer a-token-of-sixteen-chars"})
    assert code == 202 and bus.requests == ["http: GRB 261128A"]
    assert srv.stats["refused"] >= 6 and srv.stats["triggers"] == 1


def test_no_token_configured_means_nothing_changes():
    bus = FakeBus()
    srv = Service(FakeMonitor(), "127.0.0.1:0", token=None, bus=bus).start()
    try:
        assert _get(srv.url + "/trigger", data=b"x", headers={"Authorization": "Bearer anything-at-all-xx"})[0] == 403
        assert bus.requests == []
    finally:
        srv.stop()


def test_listen_addresses():
    assert parse_listen("8080") == ("127.0.0.1", 8080) and parse_listen("localhost:9") == ("localhost", 9)
    with pytest.raises(ValueError, match="HOST:PORT"):
        parse_listen("127.0.0.1:http")
    with pytest.raises(ValueError, match="allow_remote"):
        Service(FakeMonitor(), "0.0.0.0:0")
    srv = Service(FakeMonitor(), "0.0.0.0:0", allow_remote=True).start()
    srv.stop()


def test_a_run_scraped_while_it_goes(tmp_path):
    """`bf-epic run` with the service on: /metrics and /health answer while the pipeline runs (frames
    grow between scrapes), a trigger with the token saves a snippet, and the run's summary counts the
    requests."""
    from prometheus_client.parser import text_string_to_metric_families
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    token = "tok-" + "x" * 20
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
        "source.duration_s=0.45", "output.cube=null", "imager.grid.size=16", "imager.search=null",
        f"output.dir={tmp_path}", "watch.png_every_s=0.05", f"service={{listen: '127.0.0.1:0', token: {token}}}"])
    seen, pics, got, page = [], {}, {}, []

    def scrape(srv):
        def once():
            code, body, _ = _get(srv.url + "/metrics")
            fams = {f.name: f for f in text_string_to_metric_families(body)}
            seen.append(fams["bf_epic_data_seconds"].samples[0].value if "bf_epic_data_seconds" in fams else 0.0)
            if len(seen) == 1:
                _get(srv.url + "/trigger", data=b"operator", headers={"Authorization": f"Bearer {token}"})
                seen.append(_get(srv.url + "/health")[0])
            pics.update(srv.pictures())
            for k in srv.pictures():
                req = urllib.request.Request(srv.url + f"/png/{k}")
                with urllib.request.urlopen(req, timeout=10) as r:
                    got[k] = (r.status, r.read()[:8])
            page.append(_get(srv.url + "/")[1])

        def loop():
            while srv._thread is not None:
                try:
                    once()
                except OSError:       # the run ended and its server closed between two requests
                    break
                time.sleep(0.6)
        threading.Thread(target=loop, daemon=True).start()

    summary = runner.run(cfg, show_progress=False, service_ready=scrape)
    assert len(seen) >= 3 and seen[1] == 200
    data_s = [v for i, v in enumerate(seen) if i != 1]
    assert data_s == sorted(data_s) and data_s[-1] > 0          # the data read, growing as the run goes
    assert summary["service"]["requests"] >= 3 and summary["service"]["triggers"] == 1
    assert summary["watch"]["triggers"]["from_requests"] == 1
    assert len(list(tmp_path.glob("*_snippet_*http-operator*.h5"))) == 1
    # the page shows the watch targets' PNGs once drawn, each served by its key and nothing by a path
    assert any(k.startswith("watch-") for k in got), pics
    assert all(v == (200, b"\x89PNG\r\n\x1a\n") for v in got.values()), got
    assert any('src="/png/watch-' in p for p in page)

def test_sigterm_finishes_the_images_and_closes_every_file(tmp_path):
    """systemd stops a service with SIGTERM: `bf-epic run` ends the data, the blocks finish the images
    in their rings and close their files (the watch file marked complete, the candidate table
    written), and the process exits 0 well within the stop timeout, saying it was stopped."""
    import signal
    import subprocess

    import h5py
    from benchlib import bf_epic_command, child_env
    cmd = bf_epic_command() + ["run", "pipelines/lwasv_sim_transient.yaml", "--no-progress",
                               "--set", "source.duration_s=60", "--set", "output.cube=null",
                               "--set", "imager.grid.size=16", "--set", f"output.dir={tmp_path}",
                               "--set", "watch.png_every_s=100", "--summary-json", str(tmp_path / "s.json")]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env())
    watch = tmp_path / "lwasv_sim_transient_watch.h5"
    t0 = time.monotonic()
    while not watch.exists() and time.monotonic() - t0 < 120 and p.poll() is None:
        time.sleep(0.2)
    time.sleep(3.0)                                   # some images made
    assert p.poll() is None, p.communicate()
    p.send_signal(signal.SIGTERM)
    t1 = time.monotonic()
    out, err = p.communicate(timeout=60)
    print(err[-2000:])
    assert p.returncode == 0 and time.monotonic() - t1 < 30, (p.returncode, err[-3000:])
    assert "SIGTERM" in err and "stopped by SIGTERM" in out
    import json
    summ = json.loads((tmp_path / "s.json").read_text())
    # every frame the source wrote was imaged (or was the last partial integration): nothing in the rings lost
    assert summ["stopped_by"] == "SIGTERM" and 0 < summ["frames_read"] < 60 * 25000
    assert summ["frames_imaged"] + summ["frames_dropped_partial"] == summ["frames_read"], summ
    with h5py.File(watch, "r") as f:
        assert bool(f["complete"][()]) and f["FRB1/data"].shape[0] > 0
    assert (tmp_path / "lwasv_sim_transient_candidates.ecsv").exists()


def test_the_budget_deletes_the_oldest_first_and_never_a_protected_file():
    from bf_epic_blocks.service.budget import choose_deletions
    day = 86400.0
    files = [("/o/a.fits", 400, 1.0 * day), ("/o/b.fits", 300, 2.0 * day), ("/o/c.h5", 500, 3.0 * day),
             ("/o/d.fits", 200, 4.0 * day), ("/o/e.png", 100, 5.0 * day)]           # 1,500 bytes in all
    now = 5.5 * day
    assert choose_deletions(files, keep_bytes=2000, now=now) == []
    assert choose_deletions(files, keep_bytes=1000, now=now) == ["/o/a.fits", "/o/b.fits"]     # 1,500 -> 800
    assert choose_deletions(files, keep_bytes=1000, now=now, protected={"/o/a.fits"}) == \
        ["/o/b.fits", "/o/c.h5"]                                     # a is open: b and c go instead (1,500 -> 700)
    assert choose_deletions(files, keep_s=3.0 * day, now=now) == ["/o/a.fits", "/o/b.fits"]   # older than 3 days
    assert choose_deletions(files, keep_bytes=50, now=now, protected={"/o/c.h5"}) == \
        ["/o/a.fits", "/o/b.fits", "/o/d.fits", "/o/e.png"]          # all but the protected one


def test_a_run_keeps_its_folder_within_the_budget(tmp_path, monkeypatch):
    """A run with output.keep_days and keep_gb: last week's products in its folder are deleted while it
    runs (counted in the summary), its own files and files it has open are not."""
    import os

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    monkeypatch.setattr(runner, "BUDGET_EVERY_S", 0.2)
    old = []
    for k in range(5):
        p = tmp_path / f"lwasv_sim_transient_old{k}.fits"
        p.write_bytes(b"x" * 1000)
        t = time.time() - (8 - k) * 86400
        os.utime(p, (t, t))
        old.append(p)
    held = tmp_path / "held_open_by_this_process.dat"
    fh = open(held, "wb")
    fh.write(b"y" * 1000)
    fh.flush()
    os.utime(held, (time.time() - 9 * 86400,) * 2)
    try:
        cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
            "source.duration_s=0.45", "output.cube=null", "imager.grid.size=16", f"output.dir={tmp_path}",
            "watch=null", "output.keep_days=7"])
        summary = runner.run(cfg, show_progress=False)
    finally:
        fh.close()
    assert [p.exists() for p in old] == [False, False, True, True, True]      # 8 and 7+ days old: gone
    assert held.exists()                                                     # open: kept however old
    assert summary["output_budget"]["deleted_files"] == 2
    assert (tmp_path / "lwasv_sim_transient_candidates.ecsv").exists()


def test_the_systemd_unit_restarts_on_failure_and_stops_gracefully():
    """tools/systemd/bf-epic@.service: restarted on failure, journald logging, SIGTERM to stop with
    more time than the run takes to close its files, and `bf-epic run` of the instance's YAML."""
    import configparser
    from pathlib import Path

    from bf_epic_blocks.pipeline import runner
    unit = Path(__file__).resolve().parent.parent / "tools" / "systemd" / "bf-epic@.service"
    cp = configparser.ConfigParser(interpolation=None, strict=False)
    cp.optionxform = str
    cp.read_string(unit.read_text())
    svc = cp["Service"]
    assert svc["Restart"] == "on-failure" and svc["KillSignal"] == "SIGTERM"
    assert float(svc["TimeoutStopSec"]) > runner.STOP_TIMEOUT_S
    assert svc["StandardOutput"] == "journal" and svc["StandardError"] == "journal"
    assert " run /etc/bf-epic/%i.yaml" in svc["ExecStart"] and svc["ExecStart"].split()[0].endswith("/bf-epic")
    assert cp["Install"]["WantedBy"] == "multi-user.target"


def test_systemd_accepts_the_unit(tmp_path):
    """`systemd-analyze verify` on the unit (where systemd is installed): its only complaint here is
    that /opt/bf-epic is not installed on this machine."""
    import shutil
    import subprocess
    from pathlib import Path
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze is not installed")
    unit = Path(__file__).resolve().parent.parent / "tools" / "systemd" / "bf-epic@.service"
    (tmp_path / "bf-epic@test.service").write_text(unit.read_text())
    r = subprocess.run([exe, "verify", "--man=no", str(tmp_path / "bf-epic@test.service")],
                       capture_output=True, text=True, timeout=60)
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    assert all("/opt/bf-epic/.venv/bin/bf-epic is not executable" in ln for ln in lines), lines


def _browser():
    """A headless Chromium from the distribution's packages, driven by Selenium (None where absent)."""
    import shutil
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service as DriverService
    chrome = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chrome or not driver:
        pytest.skip("the distribution's chromium and chromium-driver are not installed "
                    "(tools/install_system_deps.sh --browser)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chrome
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=900,1400"):
        opts.add_argument(a)
    return webdriver.Chrome(service=DriverService(executable_path=driver), options=opts)


def _png(path, value):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    fig, ax = plt.subplots(figsize=(3, 3))
    ax.imshow(np.full((8, 8), value), vmin=0, vmax=1)
    ax.set_title(f"sky {value}")
    fig.savefig(path)
    plt.close(fig)


def test_the_page_in_a_real_browser(tmp_path):
    """The status page in headless Chromium: it shows the health, the figures and the run's latest
    image, and updates by itself (a new image, a new count and a candidate in the candidate list appear
    without a reload by the test)."""
    from types import SimpleNamespace
    a, b = tmp_path / "run_i0000.png", tmp_path / "run_i0001.png"
    _png(a, 0.2)
    mon = FakeMonitor()
    mon.g = SimpleNamespace(writer=SimpleNamespace(written=[str(a)]), outdir=str(tmp_path), watch=None)
    srv = Service(mon, "127.0.0.1:0", name="lwasv_live").start()
    drv = _browser()
    try:
        drv.get(srv.url + "/")
        assert "lwasv_live" in drv.title and "go" in drv.page_source
        img = drv.find_element("css selector", 'img[alt="image"]')
        assert drv.execute_script("return arguments[0].complete && arguments[0].naturalWidth", img) > 100
        assert not drv.find_elements("xpath", "//h2[text()='Recent candidates']")
        # the run goes on: a new image, more images counted and a candidate; the page refreshes itself
        _png(b, 0.8)
        mon.g.writer.written.append(str(b))
        cand = {"time_utc": "2026-11-28T10:00:02.999", "snr": 371.0, "dm": 1.5017, "width_ms": 5.12,
                "ra_deg": 310.68, "dec_deg": 20.19, "kind": "point"}
        mon.snap = _snap(imager={"images": 77}, uptime_s=160.0, recent_candidates=[cand])
        t0 = time.monotonic()
        while "77" not in drv.page_source and time.monotonic() - t0 < 15:
            time.sleep(0.5)
        assert "77" in drv.page_source
        cells = [td.text for td in drv.find_elements("xpath", "//h2[text()='Recent candidates']"
                                                             "/following-sibling::table[1]//td")]
        assert cells[:4] == ["2026-11-28T10:00:02.999", "371.0", "1.502", "5.12"], cells
        img = drv.find_element("css selector", 'img[alt="image"]')
        assert drv.execute_script("return arguments[0].naturalWidth", img) > 100
        assert "t=160" in img.get_attribute("src")
        drv.save_screenshot(str(tmp_path / "page.png"))
        assert (tmp_path / "page.png").stat().st_size > 5000
    finally:
        drv.quit()
        srv.stop()


def test_slow_and_many_clients_do_not_hold_the_others(served):
    """A client that sends half a request and stalls, and 200 clients at once: every other request is
    still answered, each within a few seconds."""
    import socket
    from concurrent.futures import ThreadPoolExecutor
    srv = served[0]
    slow = [socket.create_connection((srv.host, srv.port)) for _ in range(20)]
    for s in slow:
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")          # never finished
    try:
        t0 = time.monotonic()
        with ThreadPoolExecutor(200) as ex:
            codes = list(ex.map(lambda i: _get(srv.url + ("/metrics" if i % 2 else "/"))[0], range(400)))
        assert codes == [200] * 400 and time.monotonic() - t0 < 30
    finally:
        for s in slow:
            s.close()


_HEAP_PROBE = r"""
import ctypes, sys
import numpy as np
from bf_epic_blocks.service.heap import fix_mmap_threshold
class MI(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MI
if sys.argv[2] == "raised":       # where glibc has already raised its threshold (as a freed 20-MB block does)
    libc.mallopt(-3, 32 << 20)
fixed = fix_mmap_threshold() if sys.argv[1] == "fix" else False
a = np.ones(20 << 20, np.uint8)     # mapped, or not where the threshold was raised; freeing it may raise it
del a
before = libc.mallinfo2().hblkhd
b = np.ones(8 << 20, np.uint8)      # mapped (handed back when freed) under a fixed threshold
print(int(fixed), (libc.mallinfo2().hblkhd - before) >> 20)
"""


def test_a_fixed_mmap_threshold_hands_large_arrays_back(tmp_path):
    """A service's heap: with the threshold fixed, an 8-MB array is its own mapping (given back to the system
    when freed) even after glibc has raised its threshold; without, it comes from the heap (the control: what
    kept tens of MB a reset in the soak). The raised threshold is set explicitly, so the test does not rest on
    glibc's dynamic rise, which a host's malloc settings (``GLIBC_TUNABLES``, ``MALLOC_*_``) switch off."""
    import ctypes.util
    import os
    import subprocess
    import sys
    if "glibc" not in (os.confstr("CS_GNU_LIBC_VERSION") if hasattr(os, "confstr") else "") \
            or not ctypes.util.find_library("c") or not hasattr(ctypes.CDLL("libc.so.6"), "mallinfo2"):
        pytest.skip("glibc's malloc only (2.33 or later, for mallinfo2)")
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}

    def probe(mode, start="raised"):
        out = subprocess.run([sys.executable, "-c", _HEAP_PROBE, mode, start], capture_output=True, text=True,
                             env=env, timeout=60, check=True).stdout.split()
        return int(out[0]), int(out[1])
    assert probe("fix") == (1, 8)
    assert probe("nofix") == (0, 0)
    assert probe("fix", "default") == (1, 8)        # after glibc's own rise, where the host's malloc has one
    env["MALLOC_MMAP_THRESHOLD_"] = "4194304"          # the operator's own setting is left as it is
    assert probe("fix")[0] == 0
