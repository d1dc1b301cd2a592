"""Station metadata from LSL: positions, order, flags, cable terms, header round trip, offline config."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bf_epic_blocks.station.offline import configure_offline

configure_offline()          # before lsl is imported anywhere in this module
lsl = pytest.importorskip("lsl", reason="LSL not installed (pip install lsl; see tools/install_system_deps.sh)")
from lsl.common import stations as lsl_stations  # noqa: E402

from bf_epic_blocks.station import StationTable, load_station  # noqa: E402

FREQS = np.array([38e6, 58.7e6, 74e6])


@pytest.fixture(scope="module")
def sv():
    return load_station("lwasv")


def test_lwasv_facts(sv):
    assert sv.name == "lwasv" and sv.nstand == 256 and sv.nant == 512
    np.testing.assert_array_equal(sv.stand_ids, np.arange(1, 257))
    # stand 256 is the outrigger ~293 m West and ~10 m up; all others within 70 m of the centre
    x, y, z = sv.xyz_m[sv.stand_index(256)]
    assert -300 < x < -285 and abs(y) < 20 and 9 < z < 11
    assert np.hypot(sv.xyz_m[:255, 0], sv.xyz_m[:255, 1]).max() < 71
    assert sv.location.lat.deg == pytest.approx(34.348358, abs=1e-5)
    assert sv.location.lon.deg == pytest.approx(-106.885783, abs=1e-5)
    assert sv.location.height.to_value("m") == pytest.approx(1477.8, abs=1e-3)


def test_order_positions_flags_match_lsl_antenna_by_antenna(sv):
    ants = lsl_stations.lwasv.antennas
    for k, a in enumerate(ants):
        s, p = k // 2, k % 2
        assert a.pol == p and a.stand.id == sv.stand_ids[s]
        assert tuple(sv.xyz_m[s]) == (a.stand.x, a.stand.y, a.stand.z)
        assert sv.flags[s, p] == (a.combined_status != 33)
    assert 0 < sv.flags.sum() < 100   # LSL 4.0.1 marks 24 LWA-SV antennas not 33


def test_cable_terms_match_lsl(sv):
    ants = lsl_stations.lwasv.antennas
    d, g = sv.cable_delay_s(FREQS), sv.cable_gain(FREQS)
    assert d.shape == g.shape == (256, 2, 3)
    for k in (0, 1, 77, 300, 511):
        np.testing.assert_array_equal(d[k // 2, k % 2], ants[k].cable.delay(FREQS))
        np.testing.assert_array_equal(g[k // 2, k % 2], ants[k].cable.gain(FREQS))
    assert 0.1e-6 < d.min() and d.max() < 3e-6       # tens to hundreds of metres of coax
    assert np.all((g > 0) & (g < 1))                 # power gain: a loss
    assert np.all(np.diff(g, axis=-1) < 0)           # more loss at higher frequency


def test_cable_weights_undo_the_data_model(sv):
    w = sv.cable_weights(FREQS)
    assert w.shape == (3, 256, 2) and w.dtype == np.complex128
    d, g = sv.cable_delay_s(FREQS), sv.cable_gain(FREQS)
    # the raw voltage carries sqrt(G) exp(-2 pi i nu tau) (PHYSICS.md); calibration must give 1
    raw = np.moveaxis(np.sqrt(g) * np.exp(-2j * np.pi * FREQS * d), -1, 0)
    good = ~sv.flags
    np.testing.assert_allclose((w * raw)[:, good], 1.0, atol=1e-12)
    assert np.all(w[:, sv.flags] == 0)
    # one antenna by hand: stand 10 pol Y = antenna 19
    a = lsl_stations.lwasv.antennas[19]
    if a.combined_status == 33:
        ref = np.exp(2j * np.pi * FREQS * a.cable.delay(FREQS)) / np.sqrt(a.cable.gain(FREQS))
        np.testing.assert_allclose(w[:, 9, 1], ref, rtol=1e-13)


def test_extra_flags(sv):
    t = load_station("lwasv", extra_flags=[{"stand": 5, "pol": "X"}, {"stand": 7, "pol": "both"},
                                           {"stand": 9, "pol": "y"}, 11])
    new = t.flags & ~sv.flags
    assert set(zip(*np.nonzero(new))) <= {(4, 0), (6, 0), (6, 1), (8, 1), (10, 0), (10, 1)}
    assert t.flags[4, 0] and t.flags[6].all() and t.flags[8, 1] and t.flags[10].all()
    assert t.flags[4, 1] == sv.flags[4, 1]
    assert np.all(t.cable_weights(FREQS)[:, 6, :] == 0)
    with pytest.raises(ValueError, match="no stand 999"):
        load_station("lwasv", extra_flags=[{"stand": 999, "pol": "X"}])
    with pytest.raises(ValueError, match="pol: expected 'X', 'Y' or 'both'"):
        sv.with_flags([{"stand": 3, "pol": "Z"}])
    with pytest.raises(ValueError, match="unknown key"):
        sv.with_flags([{"stand": 3, "polarisation": "X"}])
    with pytest.raises(ValueError, match="integer stand id"):
        sv.with_flags([{"stand": "3"}])


def test_other_stations_and_names():
    na = load_station("LWA-NA")
    assert na.name == "lwana" and na.nstand == 64
    np.testing.assert_array_equal(na.stand_ids, np.arange(1, 65))
    one = load_station("lwa1")
    assert one.nstand == 256 and sorted(one.stand_ids) == list(range(1, 257))
    assert not np.array_equal(one.stand_ids, np.arange(1, 257))   # digitizer order, not stand order
    assert load_station("lwavl").name == "lwa1"
    with pytest.raises(ValueError, match="not a known station name"):
        load_station("lwaxx")
    with pytest.raises(TypeError):
        load_station(42)


def test_ssmif_path_gives_same_table(sv, tmp_path):
    src = Path(lsl_stations.DATA_PATH) / "lwasv-ssmif.txt"
    if not src.is_file():
        pytest.skip(f"LSL's SSMIF not found at {src}")
    t = load_station(src)
    np.testing.assert_array_equal(t.xyz_m, sv.xyz_m)
    np.testing.assert_array_equal(t.flags, sv.flags)
    np.testing.assert_array_equal(t.cable_delay_s(FREQS), sv.cable_delay_s(FREQS))
    bad = tmp_path / "station.yaml"
    bad.write_text("x")
    with pytest.raises(ValueError, match="SSMIF"):
        load_station(bad)


def test_header_round_trip(sv):
    t = sv.with_flags([{"stand": 3, "pol": "X"}])
    h = json.loads(json.dumps(t.to_header()))
    back = StationTable.from_header(h)
    assert back.name == "lwasv" and (back.lat_deg, back.lon_deg, back.elev_m) == (t.lat_deg, t.lon_deg, t.elev_m)
    np.testing.assert_array_equal(back.xyz_m, t.xyz_m)
    np.testing.assert_array_equal(back.flags, t.flags)
    np.testing.assert_array_equal(back.stand_ids, t.stand_ids)
    with pytest.raises(ValueError, match="no cable model"):
        back.cable_delay_s(FREQS)
    h = json.loads(json.dumps(t.to_header(freq_hz=FREQS)))
    back = StationTable.from_header(h)
    np.testing.assert_array_equal(back.cable_weights(FREQS), t.cable_weights(FREQS))
    np.testing.assert_array_equal(back.cable_gain(FREQS[[2, 0]]), t.cable_gain(FREQS[[2, 0]]))
    with pytest.raises(ValueError, match="only for its stored"):
        back.cable_delay_s([50e6])
    with pytest.raises(ValueError, match="lacks key"):
        StationTable.from_header({"name": "x"})
    assert set(h) >= {"name", "lat_deg", "lon_deg", "elev_m", "stand_ids", "xyz_m", "flags",
                      "cable_delay_s", "cable_gain", "cable_freq_hz"}   # docs/HEADERS.md keys
    assert np.shape(h["cable_delay_s"]) == (256, 2, 3)


def test_bad_frequencies(sv):
    for bad in ([], [-1.0], [[1e6, 2e6]], [np.nan]):
        with pytest.raises(ValueError, match="freq_hz"):
            sv.cable_delay_s(bad)


def _fresh_env(home):
    """The environment of a fresh interpreter whose home and cache folder are ``home`` (no LSLCONFIGDIR)."""
    env = {k: v for k, v in os.environ.items() if k != "LSLCONFIGDIR"}
    env.update(XDG_CACHE_HOME=str(home), HOME=str(home))
    return env


def _in_fresh_python(home, code, *args):
    """stdout of ``code`` (with ``args`` as sys.argv[1:]) run by a fresh interpreter whose home and cache
    folder are ``home``."""
    out = subprocess.run([sys.executable, "-c", code, *args], env=_fresh_env(home), capture_output=True, text=True,
                         timeout=180, cwd=str(Path(__file__).resolve().parents[1]))
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_configure_offline_in_fresh_process(tmp_path):
    """A fresh interpreter: LSL must read our lsl.cfg (telemetry off, long refresh age)."""
    code = ("from bf_epic_blocks.station.offline import configure_offline as c\n"
            "d = c(); assert c() == d\n"
            "from lsl.config import LSL_CONFIG as L\n"
            "from astropy.utils import iers\n"
            "print(L.dirname, L.get('telemetry.enabled'), L.get('download.refresh_age'), iers.conf.auto_download)\n")
    dirname, enabled, age, auto = _in_fresh_python(tmp_path, code).split()
    assert Path(dirname) == tmp_path / "bf_epic_blocks" / "lslcfg"
    assert (enabled, age, auto) == ("False", "36500", "False")
    assert "enabled = False" in (tmp_path / "bf_epic_blocks" / "lslcfg" / "lsl.cfg").read_text()


def test_capture_station_is_checked_against_the_stand_count():
    """A capture's station: its own hint when none is named; a named one with a different stand count
    is a clear error naming both counts (file and UDP sources share this check)."""
    from bf_epic_blocks.station.tables import station_for_capture
    st = station_for_capture(None, "lwana", 64, "TBF file's frames", "name the right station")
    assert st.nstand == 64
    assert station_for_capture(st, "lwasv", 64, "x", "y") is st
    with pytest.raises(ValueError, match=r"TBF file's frames carry 256 stands but station 'lwana' has 64; name"):
        station_for_capture("lwana", "lwasv", 256, "TBF file's frames", "name the right station")


def test_station_cache_gives_lsl_s_table_without_lsl(tmp_path, monkeypatch):
    """load_station(name, freq_hz=f) caches the table with LSL's cable terms at f; the next call reads
    the file (no LSL objects in it) and answers the same positions, flags and cable terms; other
    frequencies or a damaged file go back to LSL."""
    from bf_epic_blocks.station import tables
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    f = 25e3 * (2960 + np.arange(6))
    ref = tables.load_station("lwasv")                       # straight from LSL, no cache
    first = tables.load_station("lwasv", freq_hz=f)
    files = list((tmp_path / "bf_epic_blocks" / "stations").glob("lwasv-*.npz"))
    assert len(files) == 1 and first.cables is not None
    again = tables.load_station("lwasv", freq_hz=f, extra_flags=[{"stand": int(ref.stand_ids[3]), "pol": "X"}])
    assert again.cables is None and again.cable_table is not None
    np.testing.assert_array_equal(again.xyz_m, ref.xyz_m)
    np.testing.assert_array_equal(again.stand_ids, ref.stand_ids)
    assert again.flags[3, 0] and (again.flags ^ ref.flags).sum() == (0 if ref.flags[3, 0] else 1)
    np.testing.assert_array_equal(again.cable_delay_s(f), ref.cable_delay_s(f))
    np.testing.assert_array_equal(again.cable_gain(f[2:4]), ref.cable_gain(f[2:4]))
    assert (again.lat_deg, again.lon_deg, again.elev_m) == (ref.lat_deg, ref.lon_deg, ref.elev_m)
    with pytest.raises(ValueError, match="cable terms only for its stored"):
        again.cable_delay_s(f + 12.5e3)
    assert tables.load_station("lwasv", freq_hz=f + 25e3).cables is not None    # other channels: LSL
    files[0].write_bytes(b"not a cache")
    assert tables.load_station("lwasv", freq_hz=f).cables is not None            # damaged: rebuilt
    assert tables.load_station("lwasv", freq_hz=f).cables is None


def test_the_iers_cache_gives_astropy_s_own_earth_orientation(tmp_path):
    """iers_table(): the first process parses astropy's bundled IERS-A file and keeps the columns; a
    second one reads them instead of parsing (astropy's reader is made to fail there) and answers
    UT1-UTC, polar motion and a zenith's ICRS position value for value as astropy's parse does."""
    code = ("import sys\n"
            "from bf_epic_blocks.station.offline import configure_offline, iers_table\n"
            "configure_offline()\n"
            "from astropy.utils import iers\n"
            "if sys.argv[1] == 'cached':\n"
            "    def no(*a, **k): raise AssertionError('parsed the IERS file again')\n"
            "    iers.IERS_A.read = classmethod(no)\n"
            "if sys.argv[1] != 'astropy':\n"
            "    iers_table()\n"
            "from astropy.time import Time\n"
            "from bf_epic_blocks.sky.catalogue import zenith_icrs\n"
            "t = Time(['2019-03-01T00:00:00', '2026-11-25T04:00:00', '2027-06-01T12:00:00'])\n"
            "tab = iers.earth_orientation_table.get()\n"
            "print(type(tab).__name__, list(t.ut1.jd2), [list(v.value) for v in tab.pm_xy(t.jd1, t.jd2)],\n"
            "      zenith_icrs('2026-11-25T04:00:00', (-106.9, 34.3, 1477.0)))\n")
    outs = {mode: _in_fresh_python(tmp_path, code, mode).strip() for mode in ("astropy", "first", "cached")}
    assert len(list((tmp_path / "bf_epic_blocks" / "iers").glob("iers_a-*.npz"))) == 1
    assert outs["first"] == outs["cached"] == outs["astropy"]
    assert outs["cached"].startswith("IERS_Auto ")


def test_configure_offline_does_not_import_astropy_but_configures_it_when_it_loads(tmp_path):
    """The offline settings cost no astropy import (~1 s on a GPU host, and a recording imaged on a GPU
    needs none in the process that runs the blocks), yet whatever imports astropy later gets them,
    IERS downloads off and internet access forbidden, before any code can use the modules."""
    code = ("import sys\n"
            "from bf_epic_blocks.station.offline import configure_offline as c\n"
            "c()\n"
            "print('astropy' in sys.modules)\n"
            "from astropy.time import Time\n"
            "from astropy.utils import iers\n"
            "from astropy.utils.data import conf\n"
            "print(iers.conf.auto_download, iers.conf.auto_max_age, iers.conf.iers_degraded_accuracy, "
            "conf.allow_internet)\n")
    loaded, settings = _in_fresh_python(tmp_path, code).strip().splitlines()
    assert loaded == "False"
    assert settings.split() == ["False", "None", "warn", "False"]


def test_planning_reads_the_station_cache_and_never_writes_it(tmp_path):
    """`bf-epic plan` (and the check before every run) needs the stand count, not the cable terms: with
    no cached table it takes LSL's and writes nothing; once a run has cached the table for its channels,
    planning reads that file and does not import LSL's station module (seconds of every start)."""
    code = ("import sys\n"
            "from bf_epic_blocks.pipeline import runner\n"
            "from bf_epic_blocks.pipeline.config import load_config\n"
            "cfg = load_config('pipelines/lwasv_sim_transient.yaml', ['imager.grid.size=16'])\n"
            "if sys.argv[1] == 'run':\n"
            "    runner.load_station_for(cfg)\n"
            "else:\n"
            "    runner.plan(cfg)\n"
            "print('lsl.common.stations' in sys.modules)\n")
    cached = lambda: sorted((tmp_path / "bf_epic_blocks" / "stations").glob("lwasv-*.npz"))  # noqa: E731
    assert _in_fresh_python(tmp_path, code, "plan").strip() == "True" and cached() == []
    assert _in_fresh_python(tmp_path, code, "run").strip() == "True" and len(cached()) == 1
    assert _in_fresh_python(tmp_path, code, "plan").strip() == "False" and len(cached()) == 1
