"""A station of several tunings: the configuration's expansion, the events joined across tunings (against
the dispersion law written out here), the tunings run together, and the search's restart at a new gain
solution."""
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
STATION = ROOT / "pipelines" / "lwasv_sim_station.yaml"
K_DM_S = 4.149e-3             # s GHz^2 / (pc cm^-3): the project's dispersion constant (PHYSICS.md), written out


def delay_s(dm, f_hz, f_ref_hz):
    """Arrival at f after f_ref (the cold-plasma law, independent of the package's)."""
    return K_DM_S * dm * ((f_hz / 1e9) ** -2 - (f_ref_hz / 1e9) ** -2)


# ----------------------------------------------------------------------------- joining
def _row(t_unix, dm, l=0.25, m=-0.25, snr=10.0, kind="point", width_ms=0.64):
    from astropy.time import Time
    return {"time_utc": Time(t_unix, format="unix", scale="utc"), "dm": dm, "width_ms": width_ms, "l": l, "m": m,
            "snr": snr, "kind": kind, "ra_deg": 310.0, "dec_deg": 20.0}


def _as_table(rows):
    from astropy.table import Table
    from astropy.time import Time
    cols = {k: [r[k] for r in rows] for k in rows[0]}
    cols["time_utc"] = Time([r["time_utc"].unix for r in rows], format="unix", scale="utc")
    return Table(cols)


LO = dict(name="lo", f_ref_hz=57.575e6, dt_s=0.64e-3, dm_trials=np.arange(0, 3.0001, 0.002), cell_lm=2 / 64)
HI = dict(name="hi", f_ref_hz=93.575e6, dt_s=0.64e-3, dm_trials=np.arange(0, 3.0001, 0.01), cell_lm=2 / 64)
T0 = 1717236000.0             # a burst's start at the station's highest channel (unix s)


def _searches():
    from bf_epic_blocks.search.coincidence import TuningSearch
    return [TuningSearch(**LO), TuningSearch(**HI)]


def _burst_rows(dm=1.5, t0=T0, **kw):
    """The same burst as each tuning's search reports it: its start at the tuning's own highest channel."""
    lo = _row(t0 + delay_s(dm, LO["f_ref_hz"], HI["f_ref_hz"]), dm, **kw)
    hi = _row(t0, dm, **kw)
    return lo, hi


def test_one_burst_in_two_tunings_is_one_event_at_its_time_and_dm():
    """The low tuning sees a DM-1.5 burst 1.165 s after the high one; joined, the event is at the burst's
    start at the station's highest channel, with both detections."""
    from bf_epic_blocks.search.coincidence import station_events
    lo, hi = _burst_rows()
    assert 1.16 < lo["time_utc"].unix - T0 < 1.17
    ev = station_events([_as_table([lo]), _as_table([hi])], _searches())
    assert len(ev) == 1 and ev["ntunings"][0] == 2 and ev["tunings"][0] == "lo,hi"
    assert abs(ev["time_utc"][0].unix - T0) < 1e-5
    assert ev["lo_row"][0] == 0 and ev["hi_row"][0] == 0 and ev["dm"][0] == pytest.approx(1.5)
    assert ev["snr"][0] == pytest.approx(np.hypot(10.0, 10.0))
    assert ev.meta["f_ref_mhz"] == pytest.approx(93.575)


def test_the_tunings_arrival_times_measure_the_dm_better_than_any_one_search():
    """Each search's DM off by half a trial (+0.001 low, -0.005 high), its start at its own top channel right:
    the event's DM, fitted to the two starts, is the burst's to 1e-6 and its time at the station's top
    channel to a microsecond; an event of one detection keeps its search's DM."""
    from bf_epic_blocks.search.coincidence import station_events
    lo, hi = _burst_rows(dm=1.5)
    lo["dm"], hi["dm"] = 1.501, 1.495
    lone = _row(T0 + 5.0, 2.0, snr=8.0)
    ev = station_events([_as_table([lo, lone]), _as_table([hi])], _searches())
    assert list(ev["dm_from"]) == ["tunings", "trials"]
    assert abs(ev["dm"][0] - 1.5) < 1e-6 and abs(ev["time_utc"][0].unix - T0) < 1e-6
    assert ev["dm"][1] == 2.0 and abs(ev["time_utc"][1].unix - (T0 + 5.0 + delay_s(2.0, HI["f_ref_hz"], LO["f_ref_hz"]))) < 1e-5


@pytest.mark.parametrize("change, joined", [
    ({}, True),
    ({"dt": 0.002}, True),          # 2 ms: within the time one high-tuning DM step (0.01) moves its start
    ({"dt": 0.010}, False),         # 10 ms apart at the station's top: two bursts
    ({"ddm": 0.01}, True),          # one trial of the coarser (high) tuning
    ({"ddm": 0.03}, False),         # three
    ({"dl": 1.0 * 2 / 64}, True),   # one cell apart
    ({"dl": 2.0 * 2 / 64}, False),  # two cells
    ({"kind": "sky-wide"}, False),  # an impulse over the whole sky is not this point source
])
def test_what_joins_and_what_does_not(change, joined):
    from bf_epic_blocks.search.coincidence import station_events
    lo, _ = _burst_rows()
    dm = 1.5 + change.get("ddm", 0.0)
    hi = _row(T0 + change.get("dt", 0.0), dm, l=0.25 + change.get("dl", 0.0), kind=change.get("kind", "point"))
    ev = station_events([_as_table([lo]), _as_table([hi])], _searches())
    assert len(ev) == (1 if joined else 2)
    assert list(ev["ntunings"]) == ([2] if joined else [1, 1])


def test_two_bursts_each_join_their_own_and_a_lone_candidate_stays_alone():
    from bf_epic_blocks.search.coincidence import station_events
    a_lo, a_hi = _burst_rows(dm=1.5, t0=T0, snr=30.0)
    b_lo, b_hi = _burst_rows(dm=0.5, t0=T0 + 0.3, snr=12.0)
    lone = _row(T0 + 5.0, 2.0, snr=8.0)
    ev = station_events([_as_table([b_lo, a_lo, lone]), _as_table([a_hi, b_hi])], _searches())
    assert len(ev) == 3 and list(ev["ntunings"]) == [2, 2, 1]
    assert list(ev["lo_row"]) == [1, 0, 2] and list(ev["hi_row"]) == [0, 1, -1]
    assert np.isnan(ev["hi_snr"][2]) and ev["hi_time_utc"][2] == ""


def test_live_joining_logs_the_event_once_both_are_seen_and_tells_its_listener(caplog):
    from bf_epic_blocks.search.coincidence import StationEvents
    lo, hi = _burst_rows()
    told = []
    live = StationEvents(_searches(), on_event=told.append)
    live.listener(1)(hi)
    assert live.joined == 0 and not told
    seen = []
    live.listener(0, then=seen.append)(lo)
    assert live.joined == 1 and seen == [lo]
    assert "station event: lo" in caplog.text
    from astropy.time import Time
    (a,) = told
    assert a["tunings"] == "hi,lo" and a["dm"] == pytest.approx(1.5, abs=1e-5) and a["snr"] == pytest.approx(np.hypot(10, 10), abs=0.01)
    assert abs(Time(a["time_utc"], scale="utc").unix - T0) < 1e-3 and a["reason"].startswith("station event S/N 14.1")


# ----------------------------------------------------------------------------- configuration
def test_a_station_yaml_becomes_one_pipeline_per_tuning():
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config(STATION)
    low, high = cfg["tunings"]
    assert [t["name"] for t in cfg["tunings"]] == ["lwasv_sim_station_low", "lwasv_sim_station_high"]
    assert low["output"]["dir"] == "output/lwasv_sim_station/low" and low["output"]["prefix"] == low["name"]
    assert low["source"]["channels"] == {"first": 1520, "count": 784, "width_hz": 25000.0}
    assert high["source"]["channels"]["first"] == 2960 and low["imager"]["grid"] == high["imager"]["grid"]
    assert low["tunings"] is None and len(low["watch"]["targets"]) == 10 and low["calibration"]["solve"]
    # one burst for the station: the low tuning's copy starts later by its dispersion from 93.575 MHz (0.31 s)
    top = (2960 + 783) * 25e3
    assert high["source"]["transients"][0]["start_s"] == 3.0
    assert low["source"]["transients"][0]["start_s"] == pytest.approx(3.0 + delay_s(0.4, (1520 + 783) * 25e3, top))
    assert low["imager"]["search"]["dms"] == [0.5] and high["imager"]["search"]["dms"] == [3.0]
    assert [t["device"] for t in load_config(STATION, ["device=gpu:all"])["tunings"]] == ["gpu:0", "gpu:1"]
    assert [t["device"] for t in load_config(STATION, ["device=[3, 1]"])["tunings"]] == ["gpu:3", "gpu:1"]
    assert [t["device"] for t in load_config(STATION, ["device=gpu"])["tunings"]] == ["gpu:0", "gpu:0"]


@pytest.mark.parametrize("sets, message", [
    (["tunings=[{name: a}]"], "at least two"),
    (["tunings=[{name: a}, {name: a}]"], "repeated: a"),
    (["tunings=[{name: a, source: 3}, {name: b, output: x}]"], "tunings[1] (b): output: expected"),
    (["tunings=[{name: a, station: {name: lwana}}, {name: b}]"], "not station"),
    (["tunings=[{name: a}, {name: 'b c'}]"], "tunings[1].name"),
    (["tunings=[{name: a}, {name: b, source: {channels: {count: 0}}}]"], "tunings[1] (b): source.channels.count"),
    (["tunings=[{name: a}, {name: b, service: {listen: '127.0.0.1:1', lisen: 2}}]"], "tunings[1] (b): service.lisen"),
    (["tunings=[{name: a}, {name: b, service: {listen: '127.0.0.1:http'}}]"], "tunings[1] (b): service.listen"),
    (["service={listen: '127.0.0.1:70000'}"], "service.listen: port 70000 is outside"),
])
def test_a_bad_station_says_which_tuning_and_what(sets, message):
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    with pytest.raises(ConfigError) as e:
        load_config(STATION, sets)
    assert message in str(e.value)


# ----------------------------------------------------------------------------- running together
class _FakePipeline:
    def __init__(self, fail_after=None):
        self.blocks, self.fail_after, self.stop = [], fail_after, threading.Event()
        self.drained = False

    def run(self):
        if self.fail_after is not None:
            time.sleep(self.fail_after)
            raise RuntimeError("tuning broke")
        self.stop.wait(30)

    def shutdown(self, wait=True):
        self.stop.set()

    def drain(self):
        self.drained = True
        self.stop.set()


def test_one_tuning_failing_stops_the_others_and_is_raised():
    from bf_epic_blocks.pipeline.station import Together
    ok, bad = _FakePipeline(), _FakePipeline(fail_after=0.2)
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="tuning broke"):
        Together([ok, bad]).run()
    assert ok.stop.is_set() and time.monotonic() - t0 < 10


def test_draining_the_station_drains_every_tuning():
    from bf_epic_blocks.pipeline.station import Together
    a, b = _FakePipeline(), _FakePipeline()
    both = Together([a, b])
    threading.Timer(0.2, both.drain).start()
    both.run()
    assert a.drained and b.drained


def test_the_station_yaml_made_small_reports_its_burst_once(tmp_path):
    """pipelines/lwasv_sim_station.yaml with 8 channels a tuning at 74 and 84 MHz, a 16x16 grid and 0.3 s:
    a DM-0.5 burst that reaches 84.175 MHz at 0.1 s (and 74.175 MHz 84 ms later) is found by both
    searches at its DM (one trial) and place (1.5 cells), and is one station event at 0.1 s."""
    from astropy.coordinates import SkyCoord
    from astropy.table import Table
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    cfg = load_config(STATION, [
        f"output.dir={tmp_path}", "source.duration_s=0.3", "source.channels.count=8", "imager.grid.size=16",
        "tunings=[{name: low, source: {channels: {first: 2960}}}, {name: high, source: {channels: {first: 3360}}}]",
        "imager.search={threshold: 6.0, window_s: 0.06, dms: [0, 0.5, 1.0, 1.5], widths: [1, 2, 4, 8]}",
        "imager.tolerance=null", "imager.precision=fp32", "calibration.solve=null",
        "watch={targets: [CygA], png_every_s: 10.0}",
        "output.integrate=null", "output.cube=null", "output.fits=false", "output.png=false",
        "source.transients=[{ra_deg: 310.0, dec_deg: 20.0, start_s: 0.1, duration_s: 0.002, flux_jy: 1500.0, dm: 0.5}]"])
    summary = run(cfg, show_progress=False)
    assert set(summary["tunings"]) == {"low", "high"} and summary["events"]["coincident"] >= 1
    assert summary["images"] == 2 * summary["tunings"]["low"]["images"] > 0
    ev = Table.read(tmp_path / "lwasv_sim_station_events.ecsv")
    best = ev[int(np.argmax(ev["snr"]))]
    assert best["ntunings"] == 2 and best["tunings"] == "low,high"
    from astropy.time import Time
    assert abs(best["time_utc"].unix - Time("2024-06-01T10:00:00", scale="utc").unix - 0.1) < 0.004
    for name, step in (("low", 0.5), ("high", 0.5)):
        assert abs(best[f"{name}_dm"] - 0.5) <= step + 1e-9
    print(best["dm"], best["low_dm"], best["high_dm"])
    assert best["dm_from"] == "tunings" and abs(best["dm"] - 0.5) < 0.02     # finer than either search's trials
    sep = SkyCoord(best["ra_deg"], best["dec_deg"], unit="deg").separation(SkyCoord(310.0, 20.0, unit="deg")).deg
    assert sep < 1.5 * np.degrees(2 / 16)
    # the station event went out as an alert (a VOEvent in output.dir/voevents) beside each tuning's own
    assert summary["events"]["alerts"]["queued"] >= 1
    votes = list((tmp_path / "voevents").glob("*.xml"))
    assert len(votes) == summary["events"]["alerts"]["voevents"] >= 1
    assert "station event" in votes[0].read_text()
    assert (tmp_path / "low" / "lwasv_sim_station_low_candidates.ecsv").is_file()
    assert (tmp_path / "high" / "lwasv_sim_station_high_candidates.ecsv").is_file()


def test_plan_prints_each_tuning_and_what_each_device_holds(capsys):
    """The two tunings on one GPU need ~65 GiB (each: its search ~15 GiB, its operator's int8 pieces 10.0
    GiB and voltage layout 0.8 GiB, its live solver 2.9 GiB while it solves, its rings): plan says so per
    device (one NVIDIA H200 measured 67.2 GiB in use at the station's peak)."""
    from bf_epic_blocks.pipeline import cli
    assert cli.main(["plan", str(STATION), "--set", "device=gpu", "-q"]) == 0
    out = capsys.readouterr().out
    assert "tuning low (lwasv_sim_station_low)" in out and "tuning high (lwasv_sim_station_high)" in out
    assert "memory on gpu:0: about 64.8 GiB" in out
    assert cli.main(["plan", str(STATION), "--set", "device=gpu:all", "-q"]) == 0
    out = capsys.readouterr().out
    assert "memory on gpu:0: about 32.0 GiB" in out and "memory on gpu:1: about 32.8 GiB" in out


def test_calibrate_and_batch_ask_for_one_tuning(capsys, tmp_path):
    from bf_epic_blocks.pipeline import cli
    assert cli.main(["calibrate", str(STATION), "-q"]) == 1
    assert "one tuning at a time" in capsys.readouterr().err
    from bf_epic_blocks.pipeline.batch import task_configs
    from bf_epic_blocks.pipeline.config import load_config
    with pytest.raises(ValueError, match="tunings=null"):
        task_configs(load_config(STATION), [str(tmp_path / "a.tbf")])


def test_live_tunings_need_their_own_ports():
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    live = ROOT / "pipelines" / "lwasv_udp_live.yaml"
    with pytest.raises(ConfigError, match="one socket"):
        load_config(live, ["source.port=4015", "tunings=[{name: a}, {name: b}]"])
    cfg = load_config(live, ["source.port=4015", "tunings=[{name: a}, {name: b, source: {port: 4016}}]"])
    assert [t["source"]["port"] for t in cfg["tunings"]] == [4015, 4016]


def test_each_tuning_serves_at_the_stations_port_plus_its_index():
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config(STATION, ["service={listen: '127.0.0.1:8080'}"])
    assert [t["service"]["listen"] for t in cfg["tunings"]] == ["127.0.0.1:8080", "127.0.0.1:8081"]
    cfg = load_config(STATION, ["service={listen: '127.0.0.1:0'}"])
    assert [t["service"]["listen"] for t in cfg["tunings"]] == ["127.0.0.1:0", "127.0.0.1:0"]
    cfg = load_config(STATION, ["service={listen: '127.0.0.1:8080'}",
                                "tunings=[{name: a}, {name: b, service: {listen: '127.0.0.1:9000'}}]"])
    assert [t["service"]["listen"] for t in cfg["tunings"]] == ["127.0.0.1:8080", "127.0.0.1:9000"]
    assert load_config(STATION)["tunings"][0]["service"] is None


def test_a_served_station_serves_each_tuning_under_its_name(tmp_path):
    """`bf-epic run --serve` of a station: each tuning's own /health and page while it runs, named."""
    import json
    import urllib.request
    from bf_epic_blocks.pipeline.config import load_config
    from bf_epic_blocks.pipeline.runner import run
    cfg = load_config(STATION, [
        f"output.dir={tmp_path}", "source.duration_s=0.1", "source.channels.count=4", "imager.grid.size=8",
        "imager.tolerance=null", "imager.precision=fp32", "imager.search=null", "calibration.solve=null",
        "watch=null", "output.integrate=null", "output.cube=null", "output.fits=false", "output.png=false",
        "source.transients=null", "service={listen: '127.0.0.1:0', min_free_gb: 0}",
        "tunings=[{name: low, source: {channels: {first: 2960}}}, {name: high, source: {channels: {first: 3360}}}]"])
    seen = []

    def ready(service):
        with urllib.request.urlopen(service.url + "/health", timeout=10) as r:
            seen.append((r.status, json.loads(r.read())["status"]))
        with urllib.request.urlopen(service.url + "/", timeout=10) as r:
            seen.append(r.read().decode())
    summary = run(cfg, show_progress=False, service_ready=ready)
    assert [x[0] for x in seen[0::2]] == [200, 200]
    assert "lwasv_sim_station_low" in seen[1] and "lwasv_sim_station_high" in seen[3]
    urls = [summary["tunings"][k]["service"]["url"] for k in ("low", "high")]
    assert urls[0] != urls[1] and all(summary["tunings"][k]["service"]["requests"] >= 2 for k in ("low", "high"))
