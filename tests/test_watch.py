"""The watchlist: targets placed against independent astropy transforms, parse errors, the HDF5 file
(round trip, a second reader while it is written, growth), the dynamic-spectrum PNG, the YAML section."""
import h5py
import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import AltAz, EarthLocation, SkyCoord, get_body
from astropy.time import Time

from bf_epic_blocks.io.watchfile import WatchWriter, dynamic_spectrum_png, read_watch
from bf_epic_blocks.sky.catalogue import KNOWN_SOURCES, icrs_to_lm
from bf_epic_blocks.sky.watch import WATCH_BODIES, parse_targets, target_lm

LWASV = EarthLocation.from_geodetic(lon=-106.885783 * u.deg, lat=34.348358 * u.deg, height=1477.8 * u.m)
T0 = Time("2024-07-01T00:00:00", scale="utc")
TIMES = T0 + np.arange(0, 24 * 3600, 1800) * u.s   # a day, half-hourly: sources rise and set


def _lm_truth(aa):
    """l = cos(alt) sin(az), m = cos(alt) cos(az) (PHYSICS.md), written out here; NaN below the horizon."""
    alt, az = aa.alt.rad, aa.az.rad
    lm = np.stack([np.cos(alt) * np.sin(az), np.cos(alt) * np.cos(az)], axis=-1)
    lm[alt <= 0] = np.nan
    return lm


def test_catalogue_target_matches_icrs_to_lm():
    d = target_lm(["CygA"], TIMES, LWASV)
    src = KNOWN_SOURCES["CygA"]
    assert d.lm.shape == (TIMES.size, 1, 2) and d.names == ["CygA"]
    for k, t in enumerate(TIMES):
        lm, alt = icrs_to_lm(src.ra_deg, src.dec_deg, t, LWASV)
        assert d.alt_deg[k, 0] == pytest.approx(alt[0], abs=1e-9)
        if alt[0] > 0:
            np.testing.assert_allclose(d.lm[k, 0], lm[0], atol=1e-12)
        else:
            assert np.all(np.isnan(d.lm[k, 0]))
    assert np.all(d.ra_deg == src.ra_deg) and np.all(d.dec_deg == src.dec_deg)


def test_sun_matches_get_body_per_time():
    d = target_lm([{"name": "Sun", "body": "sun"}], TIMES, LWASV)
    truth = np.array([_lm_truth(get_body("sun", t, LWASV).transform_to(AltAz(obstime=t, location=LWASV)))
                      for t in TIMES])
    np.testing.assert_allclose(d.lm[:, 0], truth, atol=1e-9)
    assert d.up[:, 0].any() and not d.up[:, 0].all()
    # the recorded (ra, dec) moves (~1 deg a day) and places the Sun where it is seen
    assert 0.5 < abs(d.ra_deg[-1, 0] - d.ra_deg[0, 0]) < 1.5
    seen = SkyCoord(ra=d.ra_deg[:, 0] * u.deg, dec=d.dec_deg[:, 0] * u.deg).transform_to(
        AltAz(obstime=TIMES, location=LWASV))
    np.testing.assert_allclose(_lm_truth(seen), truth, atol=1e-7)


def test_moon_is_topocentric():
    """The Moon's parallax (~1 deg) is in its direction: a geocentric position would be off by it."""
    d = target_lm(["moon"], TIMES, LWASV)
    k = int(np.argmax(d.alt_deg[:, 0]))
    geo = get_body("moon", TIMES[k])   # no location: seen from the Earth's centre
    geo_aa = SkyCoord(ra=geo.ra, dec=geo.dec).transform_to(AltAz(obstime=TIMES[k], location=LWASV))
    assert abs(geo_aa.alt.deg - d.alt_deg[k, 0]) > 0.2


def test_watch_pixels_give_each_step_its_middle_and_compute_a_batch_at_once(monkeypatch):
    """WatchPixels (the imager's tracking pixels): each step's directions are the Sun's and CygA's at the
    step's middle (get_body and icrs_to_lm, per time), below-horizon ones at the zenith; a run's steps
    cost one astropy call per BATCH_STEPS, not one per step (the imager's thread makes that call)."""
    from bf_epic_blocks.blocks import watch as watch_block
    from bf_epic_blocks.conventions import FS_HZ
    calls = []
    real = watch_block.target_lm
    monkeypatch.setattr(watch_block, "target_lm", lambda *a, **k: calls.append(1) or real(*a, **k))
    px = watch_block.WatchPixels(["CygA", {"name": "Sun", "body": "sun"}], LWASV, step_s=1.0)
    n = px.BATCH_STEPS
    t0 = float(np.ceil(T0.unix))
    steps = [0, 1, n - 1, n, n + 1, 2 * n + 3]
    for k in steps:
        lm = px(int(round((t0 + k + 0.25) * FS_HZ)))
        t = Time(t0 + k + 0.5, format="unix", scale="utc")
        sun = _lm_truth(get_body("sun", t, LWASV).transform_to(AltAz(obstime=t, location=LWASV)))
        cyg, alt = icrs_to_lm(KNOWN_SOURCES["CygA"].ra_deg, KNOWN_SOURCES["CygA"].dec_deg, t, LWASV)
        np.testing.assert_allclose(lm[1], np.nan_to_num(sun, nan=0.0), atol=1e-9)
        np.testing.assert_allclose(lm[0], cyg[0] if alt[0] > 0 else [0.0, 0.0], atol=1e-12)
    assert len(calls) == 3          # steps 0 .. n-1, n .. 2n-1, 2n+3 ..
    # a gulp crossing into a new batch asks for its last step first, then earlier ones: the batch before is
    # kept, so no new call
    px(int(round((t0 + 2 * n + 5 + 0.25) * FS_HZ)))
    px(int(round((t0 + n + 3 + 0.25) * FS_HZ)))
    assert len(calls) == 3


def test_icrs_target_and_offsets():
    ra, dec = 150.0, 30.0
    d = target_lm([{"name": "X", "ra_deg": ra, "dec_deg": dec, "offsets_deg": [[2.0, 0.0], [0.0, -3.0]]}],
                  TIMES, LWASV)
    assert d.names == ["X", "X+off1", "X+off2"] and list(d.target_index) == [0, 0, 0]
    frame = AltAz(obstime=TIMES[:, None], location=LWASV)
    truth = _lm_truth(SkyCoord(ra=[[ra]] * u.deg, dec=[[dec]] * u.deg).transform_to(frame))
    np.testing.assert_allclose(d.lm[:, :1], truth, atol=1e-12, equal_nan=True)
    # the offsets: 2 deg East along the great circle, 3 deg South along the meridian
    c = SkyCoord(ra=ra * u.deg, dec=dec * u.deg)
    east = SkyCoord(ra=d.ra_deg[0, 1] * u.deg, dec=d.dec_deg[0, 1] * u.deg)
    assert c.separation(east).deg == pytest.approx(2.0, abs=1e-9)
    assert c.position_angle(east).deg == pytest.approx(90.0, abs=0.1)
    assert d.ra_deg[0, 2] == pytest.approx(ra) and d.dec_deg[0, 2] == pytest.approx(dec - 3.0)
    up = ~np.isnan(d.lm[:, 1, 0])
    assert not np.allclose(d.lm[up, 1], d.lm[up, 0], atol=1e-3)


def test_horizon_mask_for_a_setting_source():
    d = target_lm(["VirA"], TIMES, LWASV)
    src = KNOWN_SOURCES["VirA"]
    aa = SkyCoord(ra=src.ra_deg * u.deg, dec=src.dec_deg * u.deg).transform_to(AltAz(obstime=TIMES, location=LWASV))
    want = aa.alt.deg > 0
    assert want.any() and not want.all()     # it sets within the day
    np.testing.assert_array_equal(d.up[:, 0], want)
    assert np.all(np.isnan(d.lm[~want, 0])) and np.all(np.isfinite(d.lm[want, 0]))
    assert np.all(np.hypot(d.lm[want, 0, 0], d.lm[want, 0, 1]) <= 1)


def test_window_masks_times():
    d = target_lm([{"name": "CasA", "start": "2024-07-01T06:00:00", "stop": "2024-07-01T08:00:00"}], TIMES, LWASV)
    hours = (TIMES - T0).to_value(u.h)
    np.testing.assert_array_equal(d.in_window[:, 0], (hours >= 6) & (hours <= 8))
    np.testing.assert_array_equal(d.active, d.up & d.in_window)


def test_parse_kinds():
    tg = parse_targets(["CygA", "Cyg A", "jupiter"][::2] + [{"name": "P", "ra_deg": 1, "dec_deg": -2},
                                                           {"name": "S", "body": "Sun"}])
    assert [(t.name, t.kind) for t in tg] == [("CygA", "catalogue"), ("jupiter", "body"), ("P", "icrs"), ("S", "body")]
    assert tg[0].ra_deg == KNOWN_SOURCES["CygA"].ra_deg and tg[3].body == "sun"
    assert parse_targets("Cyg A")[0].kind == "catalogue"


def test_parse_unknown_name_lists_known_ones():
    with pytest.raises(ValueError) as e:
        parse_targets(["CygX"])
    for name in list(KNOWN_SOURCES) + list(WATCH_BODIES):
        assert name in str(e.value)
    with pytest.raises(ValueError, match="unknown body 'pluto'.*jupiter"):
        parse_targets([{"name": "p", "body": "pluto"}])


def test_parse_duplicate_and_bad_window():
    with pytest.raises(ValueError, match="repeated: CygA"):
        parse_targets(["CygA", {"name": "CygA", "ra_deg": 1, "dec_deg": 1}])
    with pytest.raises(ValueError, match="stop .* before start"):
        parse_targets([{"name": "CygA", "start": "2024-07-02T00:00:00", "stop": "2024-07-01T00:00:00"}])
    with pytest.raises(ValueError, match="ra_deg/dec_deg or body"):
        parse_targets([{"name": "x", "ra_deg": 1, "dec_deg": 1, "body": "sun"}])
    with pytest.raises(ValueError, match="dec_deg must be in"):
        parse_targets([{"name": "x", "ra_deg": 1, "dec_deg": 91}])
    with pytest.raises(ValueError, match="unknown key"):
        parse_targets([{"name": "x", "ra": 1}])


def _file_rows(path, name):
    with h5py.File(path, "r", libver="latest", swmr=True) as f:
        return f[name]["data"].shape[0]


def test_watchfile_round_trip_and_reading_while_written(tmp_path):
    path = tmp_path / "watch.h5"
    freq = np.linspace(40e6, 60e6, 8)
    entries = ["CygA", {"name": "Sun", "body": "sun", "offsets_deg": [[5, 0]]}]
    rng = np.random.default_rng(1)
    n, ndir = 10, 3
    times = 1.7e9 + np.arange(4 * n) * 0.5
    data = rng.normal(size=(4 * n, ndir, 8, 2)).astype(np.float32)
    radec = np.stack([np.full((4 * n, 2), [299.87, 40.73]), np.c_[100 + times * 1e-6, 23 + 0 * times]], axis=1)
    sizes = []
    with WatchWriter(path, entries, freq, ["I", "V"], chunk_rows=4) as w:
        w.append(times[:n], data[:n], radec[:n])
        sizes.append(path.stat().st_size)
        # a second reader while the writer is open
        with h5py.File(path, "r", libver="latest", swmr=True) as r:
            assert r["CygA"]["data"].shape == (n, 8, 2)
            np.testing.assert_array_equal(r["CygA"]["data"][:], data[:n, 0])
            w.append(times[n:2 * n], data[n:2 * n], radec[n:2 * n])
            r["CygA"]["data"].refresh()
            assert r["CygA"]["data"].shape == (2 * n, 8, 2)
            np.testing.assert_array_equal(r["CygA"]["data"][n:], data[n:2 * n, 0])
        mid = read_watch(path)
        assert mid["Sun"]["data"].shape[0] == 2 * n
        for k in (2, 3):
            w.append(times[k * n:(k + 1) * n], data[k * n:(k + 1) * n], radec[k * n:(k + 1) * n])
            sizes.append(path.stat().st_size)
        assert _file_rows(path, "Sun") == 4 * n
    assert sizes[0] < sizes[1] < sizes[2]

    got = read_watch(path)
    assert list(got) == ["CygA", "Sun"]
    c, s = got["CygA"], got["Sun"]
    np.testing.assert_array_equal(c["data"], data[:, 0])
    np.testing.assert_array_equal(s["data"], data[:, 1])
    np.testing.assert_array_equal(s["offset_data"], data[:, 2:3])
    assert isinstance(c["time"], Time) and c["time"].scale == "utc"
    np.testing.assert_allclose(c["time"].unix, times, rtol=0, atol=1e-6)
    assert c["time"][0].isot == Time(times[0], format="unix").isot
    np.testing.assert_array_equal(c["freq_hz"], freq)
    assert c["products"] == ["I", "V"] and c["kind"] == "catalogue" and "offset_data" not in c
    assert c["ra_deg"] == KNOWN_SOURCES["CygA"].ra_deg and c["dec_deg"] == KNOWN_SOURCES["CygA"].dec_deg
    assert s["kind"] == "body" and s["body"] == "sun"
    np.testing.assert_array_equal(s["ra_deg"], radec[:, 1, 0])
    np.testing.assert_array_equal(s["dec_deg"], radec[:, 1, 1])
    np.testing.assert_array_equal(s["offsets_deg"], [[5.0, 0.0]])
    assert c["start"] is None and c["stop"] is None
    with h5py.File(path, "r") as f:
        assert bool(f["complete"][()])


def test_a_writer_that_holds_rows_writes_them_once_they_span_flush_s(tmp_path):
    """flush_s: rows are held until they span that much data (or fill max_pending_bytes), then written
    in order with their times and the bodies' positions; close() writes what is left."""
    path = tmp_path / "held.h5"
    rng = np.random.default_rng(3)
    entries = ["CygA", {"name": "B1", "ra_deg": 310.0, "dec_deg": 20.0, "offsets_deg": [[1.0, 0.0]]},
               {"name": "Sun", "body": "sun"}]
    ndir, n = 4, 25                               # CygA, B1 and its offset, Sun; 25 rows an append
    times = 1.7e9 + np.arange(8 * n) * 0.01       # 0.25 s of data an append
    data = rng.normal(size=(8 * n, ndir, 5, 2)).astype(np.float32)
    radec = np.stack([np.full((8 * n, 2), [299.87, 40.73]), np.full((8 * n, 2), [310.0, 20.0]),
                      np.c_[100 + times * 1e-6, 23 + 0 * times]], axis=1)
    with WatchWriter(path, entries, np.linspace(40e6, 50e6, 5), ["I", "V"], flush_s=0.6) as w:
        in_file = []
        for k in range(7):
            w.append(times[k * n:(k + 1) * n], data[k * n:(k + 1) * n], radec[k * n:(k + 1) * n])
            in_file.append(_file_rows(path, "B1"))
            assert w.rows == (k + 1) * n
        # rows 0..74 span 0.74 s >= 0.6 after the third append; the next three appends the same again
        assert in_file == [0, 0, 3 * n, 3 * n, 3 * n, 6 * n, 6 * n]
        assert w.nrows == 6 * n
    got = read_watch(path)
    m = 7 * n
    np.testing.assert_array_equal(got["CygA"]["data"], data[:m, 0])
    np.testing.assert_array_equal(got["B1"]["data"], data[:m, 1])
    np.testing.assert_array_equal(got["B1"]["offset_data"], data[:m, 2:3])
    np.testing.assert_array_equal(got["Sun"]["data"], data[:m, 3])
    np.testing.assert_array_equal(got["Sun"]["time_unix"], times[:m])
    np.testing.assert_array_equal(got["Sun"]["ra_deg"], radec[:m, 2, 0])
    # a small max_pending_bytes writes as often as it fills, whatever flush_s says
    row_bytes = ndir * 5 * 2 * 4
    with WatchWriter(tmp_path / "small.h5", entries, np.linspace(40e6, 50e6, 5), ["I", "V"], flush_s=100.0,
                     max_pending_bytes=10 * row_bytes) as w:
        w.append(times[:n], data[:n], radec[:n])
        assert (w.nrows, w.rows) == (20, n)
    np.testing.assert_array_equal(read_watch(tmp_path / "small.h5")["B1"]["offset_data"], data[:n, 2:3])


def test_a_writer_open_for_a_whole_run_holds_no_more_memory_as_its_file_grows(tmp_path):
    """A pipeline's watch file stays open for the whole run. Appending ten targets' rows, a second of
    0.64-ms images a write (8 channels, so that it runs in seconds), the native memory in use (glibc's
    figure: HDF5's allocations are not Python's) is the same after 600 s of data as after 100 s: within 2
    MiB, where HDF5's default chunk cache added ~100 MiB over those 500 s."""
    from profile_memory import malloc_in_use_mib as _malloc_in_use_mib   # tools/bench (setup.cfg's pythonpath)
    if _malloc_in_use_mib() is None:
        pytest.skip("needs glibc's mallinfo2 (Linux, glibc >= 2.33)")
    targets = [{"name": f"T{i}", "ra_deg": 10.0 * i, "dec_deg": 20.0} for i in range(10)]
    rows, nchan = 1562, 8
    d = np.ones((64, 10, nchan, 1), np.float32)
    marks = {}
    with WatchWriter(tmp_path / "long.h5", targets, 38e6 + 25e3 * np.arange(nchan), ["I"], chunk_rows=334,
                     flush_s=1.0) as w:
        n = 0
        while n < 600 * rows:
            w.append(1.7e9 + (n + np.arange(64)) * 0.00064, d)
            n += 64
            for s in (100, 600):
                if s not in marks and n >= s * rows:
                    marks[s] = _malloc_in_use_mib()
    assert marks[600] - marks[100] < 2.0, marks


def test_watchfile_checks_shapes(tmp_path):
    with WatchWriter(tmp_path / "w.h5", ["CygA", "sun"], [50e6], ["I"]) as w:
        with pytest.raises(ValueError, match="shape"):
            w.append([0.0], np.zeros((1, 1, 1, 1)), np.zeros((1, 2, 2)))
        with pytest.raises(ValueError, match="ra_dec"):
            w.append([0.0], np.zeros((1, 2, 1, 1)))


def test_window_is_kept(tmp_path):
    with WatchWriter(tmp_path / "w.h5", [{"name": "TauA", "start": "2024-07-01T06:00:00"}], [50e6], ["I"]):
        pass
    got = read_watch(tmp_path / "w.h5")["TauA"]
    assert got["start"].isot == "2024-07-01T06:00:00.000" and got["stop"] is None and got["data"].shape == (0, 1, 1)


def test_dynamic_spectrum_png(tmp_path):
    rng = np.random.default_rng(2)
    t = 1.7e9 + np.arange(300) * 1.0
    f = np.linspace(30e6, 80e6, 64)
    d = rng.normal(size=(300, 64)) + np.exp(-0.5 * ((t - t[150]) / 10) ** 2)[:, None] * 5
    p = dynamic_spectrum_png(tmp_path / "ds.png", t, f, d, title="CygA I")
    data = (tmp_path / "ds.png").read_bytes()
    assert p.endswith("ds.png") and data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def _yaml_with(watch_text):
    from pathlib import Path
    base = (Path(__file__).resolve().parent.parent / "pipelines" / "lwasv_sim_allsky.yaml").read_text()
    return base + "\n" + watch_text


def test_config_watch_section():
    from bf_epic_blocks.pipeline.config import load_config
    assert load_config("pipelines/lwasv_sim_allsky.yaml")["watch"] is None
    cfg = load_config(_yaml_with("watch:\n  targets: [CygA, {name: S, body: sun, offsets_deg: [[5, 0]]}]\n"))["watch"]
    assert cfg["targets"][0] == "CygA" and cfg["targets"][1]["body"] == "sun"
    assert (cfg["products"], cfg["png_every_s"], cfg["ring_s"], cfg["hold_off_s"], cfg["webhook"]) == \
        (["I"], 60.0, 2.0, 10.0, None)
    assert [t.name for t in parse_targets(cfg["targets"])] == ["CygA", "S"]


def test_config_watch_errors_name_the_entry():
    from bf_epic_blocks.pipeline.config import ConfigError, load_config
    text = _yaml_with("watch:\n  targets:\n    - CygA\n    - CygX\n    - {name: W, ra_deg: 1, dec_deg: 2, "
                      "start: '2024-01-03T00:00:00', stop: '2024-01-02T00:00:00'}\n    - {name: CygA, body: moon}\n")
    with pytest.raises(ConfigError) as e:
        load_config(text)
    probs = e.value.problems
    assert any(p.startswith("watch.targets[1] (line") and "CasA" in p and "jupiter" in p for p in probs), probs
    assert any(p.startswith("watch.targets[2] (line") and "before start" in p for p in probs), probs
    assert any(p.startswith("watch.targets (line") and "repeated: CygA" in p for p in probs), probs


# ------------------------------------------------------------------------------- in a pipeline

K_DM_S = 4.148808e3   # dispersion delay, s MHz^2 / (pc cm^-3)


@pytest.fixture(scope="module")
def watched(tmp_path_factory):
    """The transient demo's dispersed burst (FRB1, 700 Jy, DM 1.2, 4 ms from 0.33 s at the top channel)
    watched at its position, with an off-source direction 12 deg East, CygA, and the Sun (below the
    horizon at 10:00 UTC)."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    out = tmp_path_factory.mktemp("watch")
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
        "source.duration_s=0.36", "imager.search=null", "output.cube=null", "imager.grid.size=8",
        "output.png=false", "output.fits=false", f"output.dir={out}",
        "watch={targets: [{name: FRB1, ra_deg: 310.0, dec_deg: 20.0, offsets_deg: [[12.0, 0.0]]}, CygA, "
        "{name: Sun, body: sun}], png_every_s: 0.1}"])
    summary = runner.run(cfg, show_progress=False)
    return out, cfg, summary


def test_the_watched_burst_drifts_as_its_dispersion_says_and_only_on_source(watched):
    out, cfg, summary = watched
    w = read_watch(out / "lwasv_sim_transient_watch.h5")
    f = w["FRB1"]
    d, off = f["data"][..., 0], f["offset_data"][:, 0, :, 0]
    t = f["time_unix"] - f["time_unix"][0]                  # image centres from the first image's
    dt = t[1] - t[0]
    fmhz = f["freq_hz"] / 1e6
    quiet = slice(0, int(0.3 / dt))
    base, sd = np.median(d[quiet], axis=0), 1.4826 * np.median(np.abs(d[quiet] - np.median(d[quiet], 0)), axis=0)
    # the radiometer equation: a 0.64-ms image of 25 kHz in 2 pols has a mean over std of sqrt(16 x 2)
    assert np.median(base / sd) == pytest.approx(np.sqrt(32), rel=0.15)
    arrive = 0.33 + K_DM_S * 1.2 * (fmhz ** -2 - fmhz.max() ** -2)      # s after the start, per channel
    for c in range(fmhz.size):
        inside = (t >= arrive[c] - dt) & (t <= arrive[c] + 0.004 + dt)
        snr = (d[:, c] - base[c]) / sd[c]
        assert snr[inside].max() > 10, (c, snr[inside].max())
        assert np.abs(snr[~inside & (t > 0.3)]).max() < 6, c             # nowhere else
        ob, os_ = np.median(off[quiet, c]), 1.4826 * np.median(np.abs(off[quiet, c] - np.median(off[quiet, c])))
        assert np.abs((off[inside, c] - ob) / os_).max() < 6, c          # not off-source
    assert np.all(np.isnan(w["Sun"]["data"])) and np.all(np.isfinite(w["CygA"]["data"]))
    assert summary["watch"]["images"] == d.shape[0] and summary["watch"]["inactive_rows"] == d.shape[0]
    assert isinstance(f["time"], Time) and f["time"][0].isot.startswith("2024-06-01T10:00:00")
    pngs = sorted(p.name for p in out.glob("*_watch_*.png"))
    assert pngs == ["lwasv_sim_transient_watch_CygA.png", "lwasv_sim_transient_watch_FRB1.png",
                    "lwasv_sim_transient_watch_Sun.png"]
    assert str(out / "lwasv_sim_transient_watch.h5") in summary["files"]


def test_a_window_before_the_data_is_a_warning_and_nan_rows(tmp_path, caplog):
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config("pipelines/lwasv_sim_allsky.yaml", [
        "source.duration_s=0.02", "imager.accumulate_frames=250", "source.channels.count=2", "source.diffuse=null",
        "output.png=false", "output.fits=false", f"output.dir={tmp_path}",
        "watch={targets: [{name: Old, ra_deg: 300.0, dec_deg: 35.0, start: '2020-01-01T00:00:00', "
        "stop: '2020-01-02T00:00:00'}, CygA]}"])
    with caplog.at_level("WARNING"):
        summary = runner.run(cfg, show_progress=False)
    assert any("Old's window ended" in r.getMessage() for r in caplog.records)
    w = read_watch(tmp_path / "lwasv_sim_allsky_watch.h5")
    assert np.all(np.isnan(w["Old"]["data"])) and np.all(np.isfinite(w["CygA"]["data"]))
    assert summary["watch"]["inactive_rows"] == 2


def test_a_window_that_opens_inside_a_gulp_starts_its_rows_at_the_step(tmp_path):
    """A target whose window opens 1 s into the data is recorded from the image that starts in that step on:
    images of 0.1 s, gulps of 7 of them (the step's boundary inside the second gulp), the first 10 rows NaN
    and counted, the rest finite, like CygA's all through."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config("pipelines/lwasv_sim_allsky.yaml", [
        "source.duration_s=2.2", "imager.accumulate_frames=2500", "source.gulp_nframe=17500",
        "source.channels.count=2", "source.diffuse=null", "imager.grid.size=16", "output.png=false",
        "output.fits=false", f"output.dir={tmp_path}",
        "watch={targets: [{name: Win, ra_deg: 300.0, dec_deg: 35.0, start: '2024-06-01T10:00:01'}, CygA]}"])
    summary = runner.run(cfg, show_progress=False)
    w = read_watch(tmp_path / "lwasv_sim_allsky_watch.h5")
    rows = w["Win"]["data"].reshape(len(w["Win"]["data"]), -1)
    assert len(rows) == 22
    assert np.all(np.isnan(rows[:10])) and np.all(np.isfinite(rows[10:]))
    assert np.all(np.isfinite(w["CygA"]["data"])) and summary["watch"]["inactive_rows"] == 10


def test_a_target_between_grid_cells_gets_its_whole_flux(tmp_path):
    """A 1,000 Jy point source at a chosen position (noise-free, unquantised, isotropic antennas): the
    watch direction placed on it records 1,000 Jy (to the sampling scatter of 5,000 samples, 1.4%), where
    the all-sky grid's brightest cell, the nearest to it, holds much less."""
    from astropy.io import fits

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    src = "{name: P, ra_deg: 300.0, dec_deg: 35.0"
    cfg = load_config("pipelines/lwasv_sim_allsky.yaml", [
        "source.duration_s=0.1", "imager.accumulate_frames=2500", "source.channels.count=2",
        f"source.sources=[{src}, flux_jy: 1000.0}}]", "source.noise_power=0", "source.quantize=false",
        "source.diffuse=null", "calibration.pattern=none", "output.png=false", f"output.dir={tmp_path}",
        f"watch={{targets: [{src}}}]}}"])
    runner.run(cfg, show_progress=False)
    w = read_watch(tmp_path / "lwasv_sim_allsky_watch.h5")["P"]["data"][0, :, 0]
    grid = fits.getdata(next(tmp_path.glob("*_i0000.fits")))[0]
    nearest = np.nanmax(grid, axis=(1, 2))
    print(f"watch {w}, nearest grid cell {nearest}")
    np.testing.assert_allclose(w, 1000.0, rtol=0.05)
    assert np.all(nearest < 0.8 * w)


@pytest.mark.parametrize("outputs", [["output.cube=null"],
                                     ["output.cube.average_channels=true", "output.png=true",
                                      "output.integrate={seconds: 0.1, average_channels: true}"]],
                         ids=["imager", "band-means"])
def test_a_candidate_saves_one_snippet_with_the_images_around_it(tmp_path, outputs):
    """The transient demo's burst, searched: its candidates (the burst and its neighbours in DM and
    width) save one snippet holding the band-averaged images from ring_s before the trigger to
    save_after_s after it, the burst's images inside; the others are held off and counted. A trigger file
    dropped in trigger_dir saves its own snippet, named for its reason, and is moved to done/. The same
    where the snippets read the band means the outputs make (the whole-band pipeline's case) rather than
    the imager's images."""
    import h5py

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    trig = tmp_path / "triggers"
    trig.mkdir()
    (trig / "gcn.txt").write_text("GRB 240601A\n")
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", outputs + [
        "source.duration_s=0.45", "imager.grid.size=16",
        "imager.search.png=false", f"output.dir={tmp_path}",
        f"watch={{targets: [{{name: FRB1, ra_deg: 310.0, dec_deg: 20.0}}], ring_s: 0.3, save_after_s: 0.05, "
        f"hold_off_s: 0.2, trigger_dir: {trig}}}"])
    summary = runner.run(cfg, show_progress=False)
    st = summary["watch"]["triggers"]
    assert summary["search"]["candidates"] >= 1 and st["from_files"] == 1, (summary["search"], st)
    snips = sorted(tmp_path.glob("*_snippet_*.h5"))
    cands = [p for p in snips if "candidate" in p.name]
    files = [p for p in snips if "GRB-240601A" in p.name]
    assert len(cands) == 1 and len(files) == 1, [p.name for p in snips]
    assert st["saved"] == 2 and st["held"] == st["triggers"] - 2
    with h5py.File(cands[0]) as f:
        t, img, when = f["time_unix"][:], f["images"][:], float(f.attrs["trigger_unix"])
        assert f.attrs["complete"] and img.shape[1:] == (16, 16)
    t0 = t - t[0]
    assert t.min() <= when - 0.09 and t.max() >= when + 0.04           # the ring before, the seconds after
    assert np.all(np.diff(t) > 0) and np.allclose(np.diff(t), 0.00064, atol=1e-6)   # every image, once
    assert not list(trig.glob("*.txt")) and (trig / "done" / "gcn.txt").exists()
    assert t0.size == img.shape[0]
    # each trigger as a VOEvent (the FRB community's fields), the candidate's where the search put it
    import voeventparse as vp
    al = summary["watch"]["alerts"]
    assert al["voevents"] == st["triggers"] and al["voevents_skipped"] == 0
    events = [vp.load(open(p, "rb")) for p in sorted((tmp_path / "voevents").glob("*.xml"))]
    assert all(vp.valid_as_v2_0(v) for v in events)
    cand = [v for v in events if "candidate" in str(v.Why.Inference.Name)]
    pos = vp.get_event_position(cand[0])
    assert abs(pos.ra - 310.0) < 5 and abs(pos.dec - 20.0) < 5
    ev = vp.get_grouped_params(cand[0])
    assert float(ev["event parameters"]["snr"]["value"]) > 10
    assert float(ev["observatory parameters"]["sampling_time"]["value"]) == pytest.approx(0.64)


def test_alerts_are_posted_retried_and_never_wait_for_a_hung_webhook():
    """A local webhook that fails twice then accepts: the alert arrives, two retries counted. One that
    hangs: send() returns at once, the tries time out and the alert is counted as failed."""
    import json
    import threading
    import time
    from http.server import BaseHTTPRequestHandler, HTTPServer

    from bf_epic_blocks.io.alerts import AlertSender
    got, state = [], {"fail": 2, "hang": False}

    class Hook(BaseHTTPRequestHandler):
        def do_POST(self):
            body = self.rfile.read(int(self.headers["Content-Length"]))
            if state["hang"]:
                time.sleep(1.0)
            if state["fail"] > 0:
                state["fail"] -= 1
                self.send_response(500)
                self.end_headers()
                return
            got.append(json.loads(body))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *a):
            pass
    srv = HTTPServer(("127.0.0.1", 0), Hook)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{srv.server_port}/hook"
    try:
        s = AlertSender(url, None, timeout_s=2.0, tries=4, backoff_s=0.05)
        s.send({"time_utc": "2024-06-01T10:00:00.33", "reason": "candidate S/N 20", "snr": 20.0})
        s.close(wait_s=10)
        assert got == [{"time_utc": "2024-06-01T10:00:00.33", "reason": "candidate S/N 20", "snr": 20.0}]
        assert s.stats["posted"] == 1 and s.stats["retries"] == 2 and s.stats["failed"] == 0
        state["hang"] = True
        h = AlertSender(url, None, timeout_s=0.2, tries=2, backoff_s=0.05)
        t0 = time.perf_counter()
        h.send({"time_utc": "2024-06-01T10:00:01", "reason": "x"})
        assert time.perf_counter() - t0 < 0.05
        h.close(wait_s=5)
        assert h.stats["failed"] == 1 and h.stats["posted"] == 0
    finally:
        srv.shutdown()


def test_voevents_that_cannot_be_made_say_why_once(tmp_path, monkeypatch, caplog):
    """A machine whose voevent-parse cannot be imported (one of its own imports is missing: lxml on a bare
    image): the sender says so once, naming the module that failed (not "not installed"), counts each
    alert's VOEvent as skipped, and does not try a half-imported package again."""
    import logging
    import sys

    from bf_epic_blocks.io.alerts import AlertSender
    pkg = tmp_path / "site" / "voeventparse"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("import lxml_not_on_this_machine\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, "voeventparse", raising=False)
    s = AlertSender(None, tmp_path / "out")
    try:
        with caplog.at_level(logging.WARNING, logger="bf_epic_blocks.io.alerts"):
            for k in range(3):
                s._voevent({"time_utc": f"2024-06-01T10:00:0{k}", "reason": "candidate S/N 20", "snr": 20.0})
    finally:
        s.close(wait_s=5)
    said = [r.getMessage() for r in caplog.records if "VOEvent" in r.getMessage()]
    assert len(said) == 1 and "lxml_not_on_this_machine" in said[0] and "not installed" not in said[0], said
    assert s.stats["voevents_skipped"] == 3 and s.stats["voevents"] == 0


def test_a_flash_saves_once_and_counts_the_rest(tmp_path):
    """A 3 MJy, 2-ms flash: the search's candidate (one sky-wide event: its sidelobes, DM and width trials
    are clustered into it) and the target's light curve both trigger; one snippet is written, the other
    trigger is held off and counted."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
        "source.duration_s=0.3", "output.cube=null", "imager.grid.size=16", "output.png=false",
        "imager.search.png=false", f"output.dir={tmp_path}",
        "source.transients=[{name: Flash, ra_deg: 300.0, dec_deg: 30.0, start_s: 0.22, duration_s: 0.002, "
        "flux_jy: 3.0e6, dm: 0.0}]",
        "watch={targets: [{name: F, ra_deg: 300.0, dec_deg: 30.0}], trigger_sigma: 8.0, ring_s: 0.1, "
        "hold_off_s: 10.0}"])
    summary = runner.run(cfg, show_progress=False)
    st = summary["watch"]["triggers"]
    print(summary["search"]["candidates"], summary["watch"]["light_curve_triggers"], st)
    assert summary["search"]["candidates"] >= 1 and summary["watch"]["light_curve_triggers"] >= 1
    assert st["triggers"] >= 2 and st["saved"] == 1 and st["held"] == st["triggers"] - 1
    assert len(list(tmp_path.glob("*_snippet_*.h5"))) == 1


def _snippets_ran(tmp_path, dt=0.01, n=50):
    """A SnippetBlock (ring 0.2 s, 0.1 s after a trigger) that has seen n images of 2x2 pixels, dt apart
    from unix time 1000: (block, its bus, the images (time, freq, product, pixels), dt)."""
    from bf_epic_blocks.blocks.array_io import ArraySourceBlock
    from bf_epic_blocks.blocks.snippets import SnippetBlock, TriggerBus
    from bf_epic_blocks.blocks import bfp
    imgs = np.arange(n * 4, dtype=np.float32).reshape(n, 1, 1, 2, 2)
    hdr = {"name": "x", "time_tag": 0, "pol_products": ["I"],
           "_tensor": {"dtype": "f32", "shape": [-1, 1, 1, 2, 2], "labels": ["time", "freq", "pol", "l", "m"],
                       "scales": [[1000.0, dt], None, None, None, None]}}
    bus = TriggerBus()
    with bfp.Pipeline() as p:
        snip = SnippetBlock(ArraySourceBlock(imgs, hdr, gulp_nframe=10), tmp_path, "t", bus, ring_s=0.2,
                            after_s=0.1)
        p.run()
    return snip, bus, imgs, dt


def test_a_trigger_that_arrives_after_the_last_images_is_still_saved(tmp_path):
    """A search lags its images: its candidate can reach the bus after the snippet block has seen its
    last gulp. ``finish()`` (the runner calls it once every block is done) saves it from the ring, the
    images up to the end of the data, marked incomplete when its after-window ran past the data."""
    import h5py
    snip, bus, imgs, dt = _snippets_ran(tmp_path)
    bus.post(1000.0 + 0.46, "candidate S/N 9.0")          # late: the block has had all 50 images
    snip.finish()
    files = sorted(tmp_path.glob("t_snippet_*.h5"))
    assert len(files) == 1 and snip.trig_stats["saved"] == 1
    with h5py.File(files[0]) as f:
        t = f["time_unix"][:]
        assert not f.attrs["complete"]                    # the after-window (to 0.56 s) passed the data's end
        # from ring_s (0.2 s) before the trigger's own time, however late it came: images 26 .. 49
        np.testing.assert_allclose(t - 1000.0, (np.arange(26, 50) + 0.5) * dt)
        np.testing.assert_array_equal(f["images"][:], imgs[26:, 0, 0])


def test_a_trigger_soon_after_the_start_is_not_called_late(tmp_path, caplog):
    """A burst 0.05 s into the data: the snippet holds what there is (from the first image), and the log
    says so at INFO; it is not a trigger that came late (which is a warning: the ring lost images)."""
    import logging

    import h5py
    snip, bus, _, dt = _snippets_ran(tmp_path)
    bus.post(1000.0 + 0.05, "candidate S/N 9.0")
    with caplog.at_level(logging.INFO, logger="bf_epic_blocks.blocks.snippets"):
        snip.finish()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert "after the sequence's first image" in caplog.text
    with h5py.File(next(tmp_path.glob("t_snippet_*.h5"))) as f:
        np.testing.assert_allclose(f["time_unix"][:][0] - 1000.0, 0.5 * dt)


def test_the_png_bins_are_block_means_of_the_last_window():
    """The quicklook keeps NaN-aware means of bin_n images (across gulps of any length), the last nbins
    of them and the bin being filled: what a PNG of a minute of 0.64-ms images shows, without re-reading
    the file."""
    from bf_epic_blocks.io.watchfile import BinnedSpectra
    rng = np.random.default_rng(5)
    n, bin_n, nbins = 1000, 16, 20
    t = np.arange(n) * 0.00064
    d = rng.normal(size=(n, 3, 8))
    d[100:140, 1] = np.nan                                     # a target below the horizon for a while
    d[800:816, 2, 3] = np.nan                                  # one whole bin (the 50th) of one channel
    b = BinnedSpectra(3, 8, bin_n, nbins)
    i = 0
    for g in rng.integers(1, 70, 100):                       # gulps of any length
        b.add(t[i:i + g], d[i:i + g])
        i += g
        if i >= n:
            break
    tb, mb = b.rows()
    full = n // bin_n                                          # 62 bins completed, then 8 images more
    want_t = [t[k * bin_n:(k + 1) * bin_n].mean() for k in range(full - nbins, full)] + [t[full * bin_n:].mean()]
    with np.errstate(invalid="ignore"), __import__("warnings").catch_warnings():
        __import__("warnings").simplefilter("ignore", RuntimeWarning)
        want = [np.nanmean(d[k * bin_n:(k + 1) * bin_n], axis=0) for k in range(full - nbins, full)] + \
            [np.nanmean(d[full * bin_n:], axis=0)]
    np.testing.assert_allclose(tb, want_t)
    np.testing.assert_allclose(mb, np.stack(want), equal_nan=True)
    assert np.isnan(mb[50 - (full - nbins), 2, 3]) and np.isfinite(mb[49 - (full - nbins), 2, 3])


def test_pngs_drawn_by_a_helper_process(tmp_path, monkeypatch):
    """On a GPU `bf-epic run` draws the watch PNGs in a helper process (png_process): the same PNGs
    appear, the last round is waited for, and the helper is stopped when the run ends."""
    from bf_epic_blocks.blocks import watch as watch_mod
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    orig = watch_mod.WatchWriterBlock.__init__
    made = []

    def init(self, *a, **k):
        k["png_process"] = True
        orig(self, *a, **k)
        made.append(self)
    monkeypatch.setattr(watch_mod.WatchWriterBlock, "__init__", init)
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
        "source.duration_s=0.45", "output.cube=null", "imager.grid.size=16", "imager.search=null",
        f"output.dir={tmp_path}", "watch.png_every_s=0.1"])
    summary = runner.run(cfg, show_progress=False)
    pngs = sorted(p.name for p in tmp_path.glob("*_watch_*.png"))
    assert pngs == ["lwasv_sim_transient_watch_CygA.png", "lwasv_sim_transient_watch_FRB1.png",
                    "lwasv_sim_transient_watch_Sun.png"]
    assert all((tmp_path / p).read_bytes()[:4] == b"\x89PNG" for p in pngs)
    assert made[0].png_process and made[0]._drawing._pool is None and summary["watch"]["png_skipped"] >= 0


def test_a_png_is_replaced_whole_never_seen_half_written(tmp_path, monkeypatch):
    """A PNG being redrawn (the watchlist's, every png_every_s) is drawn beside its path and renamed over
    it: while matplotlib writes, the path still holds the last complete picture (the service serves it
    meanwhile)."""
    from matplotlib.figure import Figure
    path = tmp_path / "ds.png"
    t, f = 1.7e9 + np.arange(20.0), np.linspace(30e6, 80e6, 8)
    dynamic_spectrum_png(path, t, f, np.ones((20, 8)))
    first = path.read_bytes()
    seen = []
    real = Figure.savefig

    def watching(self, fname, *a, **k):
        out = real(self, fname, *a, **k)
        seen.append(path.read_bytes())          # what a reader gets while the new picture is being written
        return out
    monkeypatch.setattr(Figure, "savefig", watching)
    dynamic_spectrum_png(path, t, f, np.arange(160.0).reshape(20, 8))
    assert seen == [first]
    assert path.read_bytes() != first and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["ds.png"]


def test_the_light_curve_baseline_is_the_nan_aware_median_and_mad():
    """The light curves' baseline (median, 1.4826 MAD per target) by the plain median where a history has
    no NaN and the NaN-aware one where a target was down: both equal NumPy's nanmedian by definition."""
    from bf_epic_blocks.blocks.watch import WatchWriterBlock
    rng = np.random.default_rng(7)
    h = rng.normal(5.0, 2.0, (3125, 4))
    for hist in (h, np.where(np.arange(3125)[:, None] % 7 == 0, np.nan, h)):
        med, sd = WatchWriterBlock._robust_baseline(hist)
        want = np.nanmedian(hist, axis=0)
        np.testing.assert_allclose(med, want)
        np.testing.assert_allclose(sd, 1.4826 * np.nanmedian(np.abs(hist - want), axis=0))
        assert np.all(np.abs(sd - 2.0) < 0.15)


@pytest.mark.parametrize("products, rides", [(["I"], True), (["XX", "YY"], False)])
def test_the_watch_directions_ride_in_the_main_imager_when_it_makes_their_products(tmp_path, products, rides):
    """The watch directions are imaged by the main imager, beside its grid (one DFTImagerBlock, the watch
    file written from its second ring), when it makes the products the watchlist asks; otherwise by a
    watch imager of their own on the same voltages."""
    from bf_epic_blocks.blocks import DFTImagerBlock
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
        "source.duration_s=0.02", "imager.search=null", "output.cube=null", f"output.dir={tmp_path}",
        f"watch={{targets: [CygA, {{name: Sun, body: sun}}], products: {products}}}"])
    g = runner.build_graph(cfg)
    imagers = [b for b in g.pipeline.blocks if isinstance(b, DFTImagerBlock)]
    assert len(imagers) == (1 if rides else 2)
    assert (g.watch.irings[0] is g.imager.watch_ring) == rides
    assert (g.imager.watch is g.watch.pixels) == rides


def test_a_watch_imager_of_their_own_records_what_the_directions_beside_the_grid_do(tmp_path):
    """The two routes of the watchlist on one recording: I from the directions beside the grid equals XX + YY
    from a watch imager of their own (each route is tested against the float64 definition elsewhere), and
    the Sun, below the horizon, is NaN in both."""
    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    got = {}
    for products in (["I"], ["XX", "YY"]):
        out = tmp_path / "_".join(products)
        cfg = load_config("pipelines/lwasv_sim_transient.yaml", [
            "source.duration_s=0.03", "imager.search=null", "output.cube=null", "output.png=false",
            "output.fits=false", f"output.dir={out}",
            f"watch={{targets: [CygA, {{name: FRB1, ra_deg: 310.0, dec_deg: 20.0}}, {{name: Sun, body: sun}}], "
            f"products: {products}}}"])
        runner.run(cfg, show_progress=False)
        got[products[0]] = read_watch(out / "lwasv_sim_transient_watch.h5")
    for name in ("CygA", "FRB1"):
        i, lin = got["I"][name], got["XX"][name]
        assert list(i["products"]) == ["I"] and list(lin["products"]) == ["XX", "YY"]
        assert i["data"].shape[0] == lin["data"].shape[0] > 10
        np.testing.assert_allclose(i["data"][..., 0], lin["data"].sum(axis=-1), rtol=1e-5)
    assert np.all(np.isnan(got["I"]["Sun"]["data"])) and np.all(np.isnan(got["XX"]["Sun"]["data"]))
