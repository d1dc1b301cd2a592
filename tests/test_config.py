"""Pipeline YAML schema: defaults, overrides, path resolution and one clear message per problem."""
from __future__ import annotations

import textwrap

import pytest

from bf_epic_blocks.pipeline import config as cfgmod
from bf_epic_blocks.pipeline.config import ConfigError, load_config, parse_device
from bf_epic_blocks.pipeline.yaml_schema import key_lines

REALISTIC = textwrap.dedent("""\
    name: lwasv_tbf_allsky
    station:
      name: lwasv
      flags:
        - {stand: 256, pol: both}   # the outrigger
        - {stand: 10, pol: X}
        - 42
    source:
      kind: tbf
      path: data/capture.tbf
      gulp_nframe: 512
    calibration:
      cable: true
      gains_table: cal/gains.npz
      pattern: dipole
    imager:
      kind: dft
      grid: {size: 128}
      accumulate_frames: 512
      products: stokes
      remove_autocorr: true
      method: covariance
      precision: fp32
    device: gpu:1
    output:
      dir: out/tbf
      fits: true
      png: true
      table: false
    """)


@pytest.fixture
def yaml_dir(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "capture.tbf").write_bytes(b"\0" * 16)
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "gains.npz").write_bytes(b"PK")
    p = tmp_path / "pipe.yaml"
    p.write_text(REALISTIC)
    return tmp_path


def _problems(text, overrides=(), **kw):
    with pytest.raises(ConfigError) as ei:
        load_config(text, overrides, **kw)
    return ei.value.problems, str(ei.value)


def test_realistic_file_validates_and_resolves_paths(yaml_dir, monkeypatch):
    monkeypatch.chdir("/")  # relative paths must follow the YAML file, not the working directory
    cfg = load_config(yaml_dir / "pipe.yaml")
    assert cfg["name"] == "lwasv_tbf_allsky"
    assert cfg["source"] == {"kind": "tbf", "path": str((yaml_dir / "data" / "capture.tbf").resolve()),
                             "gulp_nframe": 512, "channel_block": None}
    assert cfg["calibration"]["gains_table"] == str((yaml_dir / "cal" / "gains.npz").resolve())
    assert cfg["station"]["flags"] == [{"stand": 256, "pol": "both"}, {"stand": 10, "pol": "X"},
                                       {"stand": 42, "pol": "both"}]
    assert cfg["station"]["ssmif"] is None
    assert cfg["imager"]["products"] == ["I", "Q", "U", "V"]  # preset resolved
    assert cfg["imager"]["grid"] == {"size": 128, "cell": None} and cfg["imager"]["track"] is None
    from bf_epic_blocks.imaging.plan import gridded_epsilon
    assert cfg["imager"]["tolerance"] is None and gridded_epsilon(cfg["imager"]["tolerance"]) == 1e-4
    assert cfg["device"] == "gpu:1"
    assert cfg["output"] == {"dir": "out/tbf", "fits": True, "png": True, "table": False,
                             "prefix": "lwasv_tbf_allsky", "integrate": None, "cube": None, "oims": None,
                             "keep_gb": None, "keep_days": None}


def test_minimal_simulated_defaults():
    cfg = load_config("source: {kind: simulated}")
    src = cfg["source"]
    assert src["start"] == "2024-01-01T06:00:00" and src["duration_s"] == 2.0
    assert src["channels"] == {"first": 2960, "count": 16, "width_hz": 25000.0}
    assert src["channels"]["first"] * src["channels"]["width_hz"] == 74.0e6
    assert src["sources"] == ["CygA", "CasA", "TauA", "VirA"]
    assert (src["noise_power"], src["seed"], src["quantize"]) == (1000.0, 1, True)
    assert cfg["station"] == {"name": "lwasv", "ssmif": None, "flags": []}
    assert cfg["calibration"] == {"cable": True, "gains_table": None, "pattern": "dipole", "solve": None}
    im = cfg["imager"]
    assert im["kind"] == "dft" and im["grid"] == {"size": 64, "cell": None}
    assert (im["accumulate_frames"], im["products"], im["method"], im["precision"]) == (1024, ["I"], "auto", "fp32")
    assert cfg["device"] == "cpu"
    assert cfg["name"] == "pipeline" and cfg["output"]["dir"] == "output/pipeline"


def test_name_defaults_to_file_stem(tmp_path):
    p = tmp_path / "my_sky.yml"
    p.write_text("source: {kind: simulated}\n")
    cfg = load_config(str(p))
    assert cfg["name"] == "my_sky" and cfg["output"]["prefix"] == "my_sky" and cfg["output"]["dir"] == "output/my_sky"


def test_overrides_parse_yaml_values(yaml_dir):
    cfg = load_config(yaml_dir / "pipe.yaml", ["imager.grid.size=32", "imager.products=[XX, YY]",
                                                "device=cpu", "output.table=true", "imager.tolerance=4e-3"])
    assert cfg["imager"]["grid"]["size"] == 32
    assert cfg["imager"]["products"] == ["XX", "YY"]
    assert cfg["device"] == "cpu" and cfg["output"]["table"] is True
    assert cfg["imager"]["tolerance"] == 4e-3


def test_override_switches_grid_to_track(yaml_dir):
    cfg = load_config(yaml_dir / "pipe.yaml", ["imager.grid=null", "imager.track.source=CygA",
                                                "imager.track.fov_deg=5"])
    assert cfg["imager"]["grid"] is None
    assert cfg["imager"]["track"] == {"source": "CygA", "size": 16, "fov_deg": 5.0, "update_s": 10.0}


def test_bad_override_syntax():
    probs, _ = _problems("source: {kind: simulated}", ["imager.grid.size"])
    assert probs == ["--set 'imager.grid.size': expected key.path=value"]
    probs, _ = _problems("source: {kind: simulated}\ndevice: cpu", ["device.index=1"])
    assert "device is 'cpu', not a mapping" in probs[0]


def test_unknown_key_suggests_closest():
    probs, msg = _problems("source: {kind: simulated}\nimager: {grdi: {size: 32}}")
    assert len(probs) == 1
    assert probs[0].startswith("imager.grdi (line 2): unknown key; did you mean 'grid'?")
    probs, _ = _problems("source: {kind: simulated}\noutptu: {dir: x}")
    assert probs[0].startswith("outptu (line 2): unknown key; did you mean 'output'?")
    probs, _ = _problems("source: {kind: simulated, durations: 3}")
    assert probs[0].startswith("source.durations (line 1): unknown key; did you mean 'duration_s'?")


def test_key_of_the_other_source_kind_is_explained(yaml_dir):
    probs, _ = _problems("source: {kind: simulated, path: x.tbf}")
    assert probs == ["source.path (line 1): only used when source.kind is 'tbf' or 'tbx' or 'file' (kind is 'simulated')"]


def test_wrong_type_message_matches_operator_expectation():
    probs, msg = _problems("source: {kind: simulated}\nimager: {grid: {size: abc}}")
    assert probs == ["imager.grid.size (line 2): expected an integer >= 2, got 'abc'"]
    assert "imager.grid.size (line 2): expected an integer >= 2, got 'abc'" in msg
    probs, _ = _problems("source: {kind: simulated}\nimager: {remove_autocorr: 'yes'}")
    assert probs == ["imager.remove_autocorr (line 2): expected true or false, got 'yes'"]
    probs, _ = _problems("source: {kind: simulated}\nimager: {accumulate_frames: true}")
    assert probs[0].startswith("imager.accumulate_frames (line 2): expected an integer >= 1")  # bool is not an int


def test_missing_files_are_errors(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("source: {kind: tbf, path: nope.tbf}\nstation: {ssmif: ssmif.txt}\n"
                 "calibration: {gains_table: g.npz}\n")
    probs, msg = _problems(p)
    assert len(probs) == 3
    assert any(s.startswith("source.path (line 1): TBF file 'nope.tbf' not found") and str(tmp_path) in s
               for s in probs)
    assert any(s.startswith("station.ssmif (line 2): SSMIF file 'ssmif.txt' not found") for s in probs)
    assert any(s.startswith("calibration.gains_table (line 3): gains table 'g.npz' not found") for s in probs)
    assert msg.startswith(f"{p}: 3 problems")
    probs, _ = _problems("source: {kind: tbf}")
    assert probs == ["source.path: missing required key (the path of TBF file)"]
    (tmp_path / "g.txt").write_text("x")
    probs, _ = _problems("source: {kind: simulated}\ncalibration: {gains_table: g.txt}", base_dir=tmp_path)
    assert "must end in .npz or .yaml or .yml" in probs[0]


def test_missing_config_file():
    probs, _ = _problems("/nonexistent/pipe.yaml")
    assert "config file not found" in probs[0]


@pytest.mark.parametrize("text, path, expect", [
    ("imager: {accumulate_frames: 0}", "imager.accumulate_frames", "expected an integer >= 1, got 0"),
    ("imager: {grid: {size: 1}}", "imager.grid.size", "expected an integer >= 2, got 1"),
    ("imager: {grid: {cell: -0.1}}", "imager.grid.cell", "expected a number > 0, got -0.1"),
    ("imager: {kind: wstack, tolerance: 0.5}", "imager.tolerance", "tolerance must lie in [4e-14, 0.4]"),
    ("imager: {epsilon: 1e-3}", "imager.epsilon", "epsilon is now imager.tolerance"),
    ("source: {kind: simulated, channels: {count: 0}}", "source.channels.count", "expected an integer >= 1, got 0"),
    ("source: {kind: simulated, duration_s: 0}", "source.duration_s", "expected a number > 0, got 0"),
    ("source: {kind: simulated, duration_s: .nan}", "source.duration_s", "expected a number > 0, got nan"),
    ("source: {kind: simulated, noise_power: -1}", "source.noise_power", "expected a number >= 0, got -1"),
    ("device: 'gpu:-1'", "device", "expected 'cpu', 'gpu' or 'gpu:N'"),
    ("device: tpu", "device", "expected 'cpu', 'gpu' or 'gpu:N'"),
    ("device: 3", "device", "expected 'cpu', 'gpu' or 'gpu:N'"),
    ("imager: {products: [I, Z]}", "imager.products", "unknown polarisation product 'Z'"),
    ("imager: {products: [I, I]}", "imager.products", "repeat"),
    ("imager: {kind: fft}", "imager.kind", "expected one of 'dft', 'wstack', 'moff'"),
    ("imager: {precision: fp8}", "imager.precision", "expected one of 'fp64', 'fp32', 'tf32x3'"),
    ("imager: {precision: fp16}", "imager.precision", "needs tensor cores (device: gpu)"),
    ("imager: {tolerance: 0}", "imager.tolerance", "expected a number in (0, 1)"),
    ("imager: {min_elevation_deg: 90}", "imager.min_elevation_deg", "expected a number in [0, 90)"),
    ("station: {name: lwa2}", "station.name", "expected one of 'lwasv', 'lwana', 'lwa1'"),
    ("station: {flags: [{stand: 0}]}", "station.flags[0].stand", "expected an integer >= 1, got 0"),
    ("station: {flags: [{stand: 3, pol: Z}]}", "station.flags[0].pol", "expected one of 'X', 'Y', 'both'"),
    ("source: {kind: simulated, start: yesterday}", "source.start", "expected an ISO UTC time string"),
    ("source: {kind: simulated, start: '2024-13-45T99:00:00'}", "source.start", "expected an ISO UTC time string"),
    ("source: {kind: simulated, start: 12}", "source.start", "expected an ISO UTC time string"),
    ("source: {kind: sim}", "source.kind", "expected one of 'simulated', 'tbf', 'tbx', 'file', 'udp', got 'sim'"),
    ("source: {kind: simulated, sources: [cyga]}", "source.sources[0]", "unknown source 'cyga' (did you mean 'CygA'?)"),
    ("source: {kind: simulated, sources: [{name: X, ra_deg: 400, dec_deg: 0, flux_jy: 1}]}",
     "source.sources[0].ra_deg", "expected a number in [0, 360), got 400"),
    ("name: 'a b'", "name", "expected a name without spaces or slashes"),
])
def test_impossible_or_malformed_values(text, path, expect):
    if "source:" not in text:
        text = "source: {kind: simulated}\n" + text
    probs, _ = _problems(text)
    assert len(probs) == 1, probs
    assert probs[0].startswith(f"{path} (line {text.count(chr(10)) + 1}): "), probs  # the key is on the last line
    assert expect in probs[0], probs


def test_grid_and_track_are_exclusive():
    probs, _ = _problems("source: {kind: simulated}\nimager: {grid: {size: 32}, track: {source: CygA}}")
    assert len(probs) == 1 and probs[0].startswith("imager (line 2): give exactly one of imager.grid")


def test_custom_sources_match_the_sky_module():
    cfg = load_config("source: {kind: simulated, sources: [CasA, {name: S1, ra_deg: 10, dec_deg: -5, flux_jy: 50,"
                      " spectral_index: -0.7}]}")
    assert cfg["source"]["sources"] == ["CasA", {"name": "S1", "ra_deg": 10.0, "dec_deg": -5.0, "flux_jy": 50.0,
                                                 "spectral_index": -0.7}]
    sky = pytest.importorskip("bf_epic_blocks.sky")
    src = sky.resolve_sources(cfg["source"]["sources"])  # the validated entries are what sky accepts
    assert [s.name for s in src] == ["CasA", "S1"] and src[1].spectral_index == -0.7
    probs, _ = _problems("source: {kind: simulated, sources: [{name: S1, ra_deg: 1, dec_deg: 1, flux_jy: 1, "
                         "spectral_indx: 1}]}")
    assert probs[0].startswith("source.sources[0].spectral_indx (line 1): unknown key; did you mean 'spectral_index'?")


def test_track_rules():
    cfg = load_config("source: {kind: simulated, sources: [{name: Src1, ra_deg: 10, dec_deg: 20, flux_jy: 5}]}\n"
                      "imager: {track: {source: Src1, size: 8}}")
    assert cfg["imager"]["track"]["source"] == "Src1" and cfg["imager"]["grid"] is None
    probs, _ = _problems("source: {kind: simulated}\nimager: {track: {source: CygB}}")
    assert probs[0].startswith("imager.track.source (line 2): unknown source 'CygB'; did you mean 'CygA'?")
    probs, _ = _problems("source: {kind: simulated}\nimager: {kind: moff, track: {source: CygA}}")
    assert probs[0].startswith("imager.track (line 2): a tracked patch needs the dft imager")


def test_accumulation_must_fit_in_duration():
    probs, _ = _problems("source: {kind: simulated, duration_s: 0.01}")  # 250 frames < 1024
    assert probs[0].startswith("imager.accumulate_frames: 1024 frames (40.96 ms")  # the default: no line
    assert "no image would be produced" in probs[0]
    load_config("source: {kind: simulated, duration_s: 0.04096}")  # exactly one image is fine


def test_station_name_or_ssmif(tmp_path):
    (tmp_path / "s.txt").write_text("x")
    cfg = load_config("source: {kind: simulated}\nstation: {ssmif: s.txt}", base_dir=tmp_path)
    assert cfg["station"]["name"] is None and cfg["station"]["ssmif"] == str((tmp_path / "s.txt").resolve())
    probs, _ = _problems("source: {kind: simulated}\nstation: {name: lwasv, ssmif: s.txt}", base_dir=tmp_path)
    assert probs == ["station (line 2): give either station.name or station.ssmif, not both"]


def test_all_problems_reported_together(yaml_dir):
    probs, msg = _problems(yaml_dir / "pipe.yaml", ["imager.grid.size=abc", "device=gpu:x", "imager.kind=fft",
                                                     "output.pngs=false"])
    assert len(probs) == 4
    assert {p.split(":")[0] for p in probs} == {"imager.grid.size", "device", "imager.kind", "output.pngs"}
    for p in probs:
        assert f"  - {p}" in msg


def test_yaml_structure_errors():
    assert "not valid YAML" in _problems("source: [")[0][0]
    assert "top level must be a mapping" in _problems("- a\n- b\n")[0][0]
    assert _problems("")[0] == ["source: missing required key (a source mapping)"]
    assert _problems("source: {}")[0] == ["source.kind: missing required key (one of 'simulated', 'tbf', 'tbx', 'file', 'udp')"]
    with pytest.raises(ValueError):  # ConfigError is a ValueError
        load_config("source: 3")


def test_yaml_timestamps_and_null_pattern():
    cfg = load_config("source: {kind: simulated, start: 2024-03-01 12:30:00}\ncalibration: {pattern: none}")
    assert cfg["source"]["start"] == "2024-03-01T12:30:00" and cfg["calibration"]["pattern"] == "none"
    cfg = load_config("source: {kind: simulated, start: 2024-03-01T12:30:00+02:00}")
    assert cfg["source"]["start"] == "2024-03-01T10:30:00"  # converted to UTC


def test_parse_device():
    assert parse_device("cpu") == ("cpu", None)
    assert parse_device("gpu") == ("gpu", 0)
    assert parse_device("gpu:3") == ("gpu", 3)
    for bad in ("gpu:", "gpu:-1", "cuda", None, 0):
        with pytest.raises(ValueError):
            parse_device(bad)


def test_every_schema_key_has_a_description():
    """The YAML reference is generated from ``Key.doc`` alone: a key added without one fails here."""
    entries = cfgmod.schema_entries()
    paths = {p for p, _ in entries}
    # the walk reaches every kind's keys and the keys of list items, not only the top sections
    assert {"source.port", "source.channel_block", "source.channels.width_hz", "source.transients[].dm",
            "source.sources[].flux_jy", "station.flags[].pol", "imager.search.sidelobe_factor",
            "output.cube.dtype"} <= paths
    assert sum(p == "source.path" for p, _ in entries) == 3  # tbf, tbx, file
    undocumented = [p for p, key in entries if not key.doc.strip()]
    assert not undocumented, f"schema keys without a description (Key(..., doc=...)): {undocumented}"


def test_accuracy_keys_document_one_knob_and_expert_overrides():
    im = cfgmod.SCHEMA.keys["imager"].check
    tol = im.keys["tolerance"].doc
    assert "accuracy knob" in tol and "float64" in tol and "epsilon = tolerance / 4" in tol
    for name in ("method", "precision"):
        assert im.keys[name].doc.startswith("Expert override"), name
    assert "one accuracy knob" in im.doc and "expert overrides" in im.doc
    assert "imager.tolerance" in im.renamed["epsilon"]


def _render_yaml_reference(monkeypatch):
    """The page docs/gen_yaml_reference.py writes (with mkdocs-gen-files replaced by a recorder), and
    the script's ``cell``, which escapes a description for a table cell."""
    import io
    import runpy
    import sys
    import types
    from pathlib import Path

    pages = {}

    class Page(io.StringIO):
        def __init__(self, name):
            super().__init__()
            self.name = name

        def __exit__(self, *exc):
            pages[self.name] = self.getvalue()
            return super().__exit__(*exc)

    fake = types.ModuleType("mkdocs_gen_files")
    fake.open = lambda name, mode="r": Page(name)
    fake.set_edit_path = lambda *a: None
    monkeypatch.setitem(sys.modules, "mkdocs_gen_files", fake)
    script = runpy.run_path(str(Path(__file__).resolve().parents[1] / "docs" / "gen_yaml_reference.py"))
    return pages["reference/pipeline-yaml.md"], script["cell"]


def test_yaml_reference_shows_every_key_with_its_description(monkeypatch):
    page, cell = _render_yaml_reference(monkeypatch)
    rows = [line for line in page.splitlines() if line.startswith("| `")]
    assert len(rows) == len(cfgmod.schema_entries())
    for path, key in cfgmod.schema_entries():
        name = path.rsplit(".", 1)[-1]
        assert any(r.startswith(f"| `{name}` |") and r.endswith(f"| {cell(key.doc)} |") for r in rows), \
            f"{path}: no row with its description"
    assert "docstring" not in page  # descriptions come from the schema alone


LINES = textwrap.dedent("""\
    name: lines                  # line 1
    station:
      name: lwasv
      flags:
        - 3
        - {stand: 0, pol: X}     # line 6: stand < 1
    source:
      kind: simulated
      duration_s: 0.01           # line 9: too short for accumulate_frames (line 17)
      channels:
        count: 4
        widht_hz: 25000          # line 12: unknown key
    imager:
      grid:
        size: abc                # line 15
        cell: 0.05
      accumulate_frames: 1024    # line 17
      products: [I, Z]           # line 18
    device: gpu:x                # line 19
    """)


def test_messages_give_the_yaml_line_of_the_key(tmp_path):
    p = tmp_path / "lines.yaml"
    p.write_text(LINES)
    probs, msg = _problems(p)
    assert sorted(probs) == sorted([
        "station.flags[1].stand (line 6): expected an integer >= 1, got 0",
        "source.channels.widht_hz (line 12): unknown key; did you mean 'width_hz'? "
        "(valid keys here: first, count, width_hz)",
        "imager.grid.size (line 15): expected an integer >= 2, got 'abc'",
        next(s for s in probs if s.startswith("imager.products (line 18): unknown polarisation product 'Z'")),
        "device (line 19): expected 'cpu', 'gpu' or 'gpu:N' (N >= 0 the GPU index), got 'gpu:x'",
        next(s for s in probs if s.startswith("imager.accumulate_frames (line 17): 1024 frames")),  # cross-check
    ]), probs
    assert msg.startswith(f"{p}: 6 problems") and "  - imager.grid.size (line 15): " in msg


def test_overridden_keys_have_no_line():
    # --set replaces the value written on line 15 (and everything under imager.grid): no line for it
    probs, _ = _problems(LINES.replace("widht_hz", "width_hz"), ["imager.grid={size: 1}", "device=tpu"])
    assert "imager.grid.size: expected an integer >= 2, got 1" in probs
    assert "device: expected 'cpu', 'gpu' or 'gpu:N' (N >= 0 the GPU index), got 'tpu'" in probs
    assert "station.flags[1].stand (line 6): expected an integer >= 1, got 0" in probs  # untouched keys keep theirs
    # a key the file does not have, and one created by an override: no line either
    probs, _ = _problems("source: {kind: simulated}", ["imager.grdi.size=3"])
    assert probs[0].startswith("imager.grdi: unknown key")


def test_key_lines_of_block_flow_lists_and_merges():
    text = textwrap.dedent("""\
        base: &b
          x: 1
          y: 2
        top:
          <<: *b
          y: 3
          z: [a, {w: 1}]
        """)
    lines = key_lines(text)
    assert lines["base"] == 1 and lines["base.x"] == 2 and lines["top"] == 4
    assert lines["top.x"] == 2  # merged from the anchor
    assert lines["top.y"] == 6  # the mapping's own key wins over the merged one, as in loading
    assert lines["top.z"] == 7 and lines["top.z[1]"] == 7 and lines["top.z[1].w"] == 7
    assert key_lines("a: [") == {} and key_lines("") == {}


@pytest.mark.parametrize("given, resolved", [("gpu:all", "gpu:all"), ("[0, 1]", "gpu:0,1"), ("'gpu:1,0'", "gpu:1,0"),
                                             ("[2]", "gpu:2")])
def test_several_gpus(given, resolved):
    assert load_config(f"source: {{kind: simulated}}\ndevice: {given}\n")["device"] == resolved


@pytest.mark.parametrize("given", ["[0, 0]", "[-1, 1]", "[a, b]", "[]"])
def test_several_gpus_bad(given):
    with pytest.raises(ConfigError, match="several GPUs as"):
        load_config(f"source: {{kind: simulated}}\ndevice: {given}\n")


def test_calibration_folded_into_the_imager_only_where_it_should_be(yaml_dir):
    """On a GPU with static calibration the DFT imager folds it (no CalFoldBlock), live UDP included
    (its blocks read guaranteed); time-variable gains, the gridded imagers and the CPU keep
    CalFoldBlock; several GPUs always fold."""
    from bf_epic_blocks.pipeline.runner import folds_calibration
    base = load_config("source: {kind: simulated}")
    assert folds_calibration(base, "gpu") and folds_calibration(base, "gpus")
    assert not folds_calibration(base, "cpu")
    gains = dict(base, calibration=dict(base["calibration"], gains_table="gains.npz"))
    assert not folds_calibration(gains, "gpu")
    udp = dict(base, source=dict(base["source"], kind="udp"))
    assert folds_calibration(udp, "gpu") and folds_calibration(udp, "gpus") and not folds_calibration(udp, "cpu")
    ws = dict(base, imager=dict(base["imager"], kind="wstack"))
    assert not folds_calibration(ws, "gpu") and not folds_calibration(ws, "gpus")


def test_the_fused_integer_modes_are_refused_where_they_cannot_image(tmp_path):
    """imager.precision i8x2/i8x3 needs 4-bit voltages at one GPU's DFT imager, XX/YY powers and whole
    16-sample units: each way of breaking that is named up front, not met as a failed block mid-run."""
    (tmp_path / "gains.npz").write_bytes(b"PK")
    base = "source: {kind: simulated}\ndevice: gpu\nimager: {accumulate_frames: 16, precision: i8x2}\n"
    cfg = load_config(base)
    assert cfg["imager"]["precision"] == "i8x2"
    for extra, words in ((["imager.products=[I, U]"], "cross-pol"),
                         (["imager.method=covariance"], "direct-route"),
                         (["imager.accumulate_frames=24"], "multiple of 16"),
                         (["source.quantize=false"], "quantize is false"),
                         ([f"calibration.gains_table={tmp_path / 'gains.npz'}"], "turns the voltages complex"),
                         (["device=gpu:all"], "several GPUs")):
        with pytest.raises(ConfigError, match=words):
            load_config(base, extra)
    with pytest.raises(ConfigError, match="tensor cores"):
        load_config(base, ["device=cpu"])


def test_gpu_memory_gb_limits_the_pool_of_each_gpu_the_run_uses():
    """gpu_memory_gb: CuPy's default pool limited on every GPU a (station's) configuration uses, in 1e9
    bytes; nothing on the CPU or without it; a bad value is a clear error."""
    from types import SimpleNamespace

    from bf_epic_blocks.pipeline.runner import limit_gpu_pools
    limits, current = {}, [None]

    class Device:
        def __init__(self, i):
            self.i = i

        def __enter__(self):
            current[0] = self.i

        def __exit__(self, *a):
            current[0] = None

    pool = SimpleNamespace(set_limit=lambda size: limits.__setitem__(current[0], size))
    fake = SimpleNamespace(cuda=SimpleNamespace(Device=Device), get_default_memory_pool=lambda: pool)
    cfg = load_config("source: {kind: simulated}\ndevice: gpu:1\ngpu_memory_gb: 75")
    assert cfg["gpu_memory_gb"] == 75.0
    assert limit_gpu_pools(cfg, cupy=fake) == {1: 75_000_000_000} and limits == {1: 75_000_000_000}
    limits.clear()
    station = {"gpu_memory_gb": 12.5, "tunings": [{"device": "gpu:0"}, {"device": "gpu:2"}]}
    assert limit_gpu_pools(station, cupy=fake) == {0: 12_500_000_000, 2: 12_500_000_000} and len(limits) == 2
    limits.clear()
    assert limit_gpu_pools(load_config("source: {kind: simulated}\ngpu_memory_gb: 75"), cupy=fake) == {}   # the CPU
    assert limit_gpu_pools(load_config("source: {kind: simulated}\ndevice: gpu"), cupy=fake) == {} and not limits
    for bad in ("0", "-3", "lots"):
        with pytest.raises(ConfigError, match="gpu_memory_gb"):
            load_config(f"source: {{kind: simulated}}\ngpu_memory_gb: {bad}")


def test_a_station_s_tunings_on_one_device_solve_in_turn():
    """calibration.solve.stagger (on by default): of the n tunings that solve on one device, tuning j's
    schedule starts j cadence / n after its offset_s; tunings on GPUs of their own, a station that does not
    solve (solve: null, which must stay null for every tuning) and stagger: false are left alone."""
    def offsets(*sets):
        cfg = load_config("pipelines/lwasv_sim_station.yaml", list(sets))
        return [tc["calibration"]["solve"] and tc["calibration"]["solve"]["offset_s"] for tc in cfg["tunings"]]
    assert offsets("device=gpu") == [0.0, 5.0] and offsets("device=cpu") == [0.0, 5.0]
    assert offsets("device=gpu:all") == [0.0, 0.0]
    assert offsets("calibration.solve=null") == [None, None]
    assert offsets("calibration.solve.stagger=false") == [0.0, 0.0]
    assert offsets("calibration.solve.offset_s=8") == [8.0, 3.0]                # modulo the cadence
    assert offsets("calibration.solve.cadence_s=4", "calibration.solve.integration_s=0.5") == [0.0, 2.0]
    one = load_config("pipelines/lwasv_sim_allsky.yaml", ["calibration.solve={}"])
    assert one["calibration"]["solve"]["offset_s"] == 0.0                        # a single pipeline: as given


def test_a_run_refuses_what_does_not_fit_gpu_memory_gb():
    """gpu_memory_gb bounds what a GPU configuration may need, before anything is allocated: one pipeline's
    plan, and a station's tunings on one GPU together (64.8 GiB for lwasv_sim_station: 75 GB holds them,
    60 GB does not), each refused with a clear error naming the limit."""
    from bf_epic_blocks.pipeline import runner
    cfg = load_config("pipelines/lwasv_sim_station.yaml", ["device=gpu"])
    assert cfg["gpu_memory_gb"] == 75.0
    runner.check_station_fits(cfg)                                   # 69.6 GB <= 75 GB
    with pytest.raises(ValueError, match=r"gpu:0 need about 64.8 GiB together.*gpu_memory_gb: 60"):
        runner.check_station_fits(load_config("pipelines/lwasv_sim_station.yaml", ["device=gpu", "gpu_memory_gb=60"]))
    runner.check_station_fits(load_config("pipelines/lwasv_sim_station.yaml", ["device=gpu:all", "gpu_memory_gb=60"]))
    one = load_config("pipelines/lwasv_sim_wholeband.yaml", ["device=gpu", "gpu_memory_gb=10"])
    with pytest.raises(ValueError, match=r"CuPy's pool \(gpu_memory_gb: 10\)"):
        runner.check_fits(one)
    runner.check_fits(load_config("pipelines/lwasv_sim_wholeband.yaml", ["device=gpu", "gpu_memory_gb=60"]))
