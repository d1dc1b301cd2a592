"""Pipeline configuration: a YAML file, validated completely before anything runs.

:func:`load_config` reads a YAML pipeline (``yaml.safe_load`` only), applies ``--set key=value``
overrides, checks every key against the schema below, fills the defaults and returns a plain dict.
Every problem found is reported at once in one :class:`ConfigError`, one line per problem, each
starting with the dotted path of the key and, where the key is written in the YAML, its line
(``imager.grid.size (line 23): expected an integer >= 2, got 'abc'``; values given with ``--set``
have no line). Unknown keys are errors and come with the closest valid key as a suggestion.
The generic checker (leaf checks, sections, did-you-mean, YAML line map) is :mod:`.yaml_schema`;
this module holds the pipeline's schema, its defaults and the cross-checks.

The schema is :data:`SCHEMA`: every key's check, default and description (``Key(..., doc=...)``).
Its reference page, docs/reference/pipeline-yaml.md, is generated from this schema alone
(docs/gen_yaml_reference.py), so a key's meaning is written in one place; tests/test_config.py
fails for a key without a description.

Paths of input files (``station.ssmif``, ``source.path``, ``calibration.gains_table``) are resolved
against the YAML file's directory (the working directory for inline text) and returned absolute.
A key set to ``null`` takes its default; ``imager.grid: null`` removes a grid given in the file, so
``--set imager.grid=null --set imager.track.source=CygA`` switches a pipeline to tracking.
Rules that span keys (grid or track, products against the station's pols, an image that fits in a
simulated source, a tracked source the pipeline knows, the expert modes a device can run) are
checked once every key has been, by the sections' ``post`` rules and :func:`_fill_and_cross_check`.
"""
from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Iterable

import yaml

from ..imaging.fused import FUSED as _FUSED
from ..imaging.gemm import PRECISIONS as _PRECISIONS
from ..imaging.products import PRESETS, VALID as VALID_PRODUCTS, needs_cross, resolve_products
from .yaml_schema import (INVALID, REQUIRED, BadValue, Bool, Choice, Context, File, Float, Int, Key, ListOf, Section,
                          Str, TimeStr, did_you_mean, is_valid, join_path, key_lines, run_check)

__all__ = ["ConfigError", "load_config", "apply_overrides", "parse_device", "pixel_split_problems", "resolved_split",
           "several_gpus", "schema_keys", "schema_entries",
           "STATIONS", "CATALOGUE_SOURCES", "DEFAULT_START", "NPOL"]

PRECISION_NAMES = tuple(_PRECISIONS)
STATIONS = ("lwasv", "lwana", "lwa1")
#: Source names the simulated sky and the tracker know without coordinates.
CATALOGUE_SOURCES = ("CygA", "CasA", "TauA", "VirA")
DEFAULT_START = "2024-01-01T06:00:00"
#: LWA stations have two linear polarisations (X = N-S, Y = E-W); products are checked against it.
NPOL = 2


class ConfigError(ValueError):
    """An invalid pipeline configuration.

    ``problems`` is the list of ``"dotted.path: what is wrong"`` strings (``"dotted.path (line N):
    what is wrong"`` where the key is written in the YAML); ``source`` names the file (or
    ``'<text>'``). ``str(err)`` lists every problem, one per line.
    """

    def __init__(self, problems: Iterable[str], source: str = "<text>"):
        self.problems = list(problems)
        self.source = source
        if len(self.problems) == 1:
            msg = f"{source}: {self.problems[0]}"
        else:
            msg = f"{source}: {len(self.problems)} problems in the pipeline config:\n" + "\n".join(
                f"  - {p}" for p in self.problems)
        super().__init__(msg)


# ---------------------------------------------------------------------------------------------
# Checks that know the pipeline (the generic ones are in .yaml_schema)
# ---------------------------------------------------------------------------------------------
class Device:
    def describe(self) -> str:
        return "'cpu', 'gpu' or 'gpu:N' (N >= 0 the GPU index)"

    _MULTI = "several GPUs as 'gpu:all', 'gpu:0,1' or a list of distinct indices >= 0 like [0, 1]"

    def __call__(self, v, ctx):
        if isinstance(v, list) or (isinstance(v, str) and (v.strip().lower() == "gpu:all" or "," in v)):
            items = v if isinstance(v, list) else v.strip().lower()[4:].split(",") if v.strip().lower() != "gpu:all" else None
            if items is None:
                return "gpu:all"
            try:
                idx = [int(i) for i in items]
            except (TypeError, ValueError):
                raise BadValue(f"expected {self._MULTI}, got {v!r}") from None
            if not idx or min(idx) < 0 or len(set(idx)) != len(idx) or any(isinstance(i, bool) for i in items):
                raise BadValue(f"expected {self._MULTI}, got {v!r}")
            return "gpu:" + ",".join(str(i) for i in idx) if len(idx) > 1 else f"gpu:{idx[0]}"
        try:
            kind, idx = parse_device(v)
        except ValueError:
            raise BadValue(f"expected {self.describe()}, got {v!r}") from None
        return "cpu" if kind == "cpu" else f"gpu:{idx}"


class Products:
    def describe(self) -> str:
        return f"a list of {', '.join(VALID_PRODUCTS)} or a preset ({', '.join(PRESETS)})"

    def __call__(self, v, ctx):
        if not isinstance(v, (str, list)):
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        if isinstance(v, list) and not all(isinstance(p, str) for p in v):
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        try:
            names = resolve_products(NPOL, v)
        except ValueError as e:
            raise BadValue(str(e)) from None
        if len(set(names)) != len(names):
            raise BadValue(f"products repeat a name: {list(names)}")
        return list(names)



class SourceList:
    """source.sources: catalogue names or {name, ra_deg, dec_deg, flux_jy} mappings."""

    entry = Section({
        "name": Key(Str(r"\S+", "a name without spaces"), REQUIRED,
                    doc="The source's name, unique in the list; `imager.track.source` can name it."),
        "ra_deg": Key(Float(0.0, 360.0, hi_open=True), REQUIRED, doc="Right ascension (ICRS), degrees."),
        "dec_deg": Key(Float(-90.0, 90.0), REQUIRED, doc="Declination (ICRS), degrees."),
        "flux_jy": Key(Float(0.0), REQUIRED, doc="Flux density at `ref_freq_hz`, Jy."),
        "spectral_index": Key(Float(), None,
                              doc="Spectral index α of S ∝ ν^α; null: 0 (a flat spectrum)."),
        "ref_freq_hz": Key(Float(0.0, lo_open=True), None,
                           doc="The frequency `flux_jy` is given at, Hz; null: 74 MHz."),
    }, what="a source mapping")

    def __init__(self, names=CATALOGUE_SOURCES):
        self.names = tuple(names)

    def describe(self) -> str:
        return f"a list of source names ({', '.join(self.names)}) or {{name, ra_deg, dec_deg, flux_jy}}"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return INVALID
        out = []
        for i, x in enumerate(v):
            where = f"{path}[{i}]"
            if isinstance(x, str):
                if x not in self.names:
                    close = did_you_mean(x, self.names)
                    hint = f" (did you mean {close!r}?)" if close else ""
                    ctx.error(where, f"unknown source {x!r}{hint}; catalogue names are "
                                     f"{', '.join(self.names)}, or give {{name, ra_deg, dec_deg, flux_jy}}")
                    out.append(INVALID)
                else:
                    out.append(x)
            elif isinstance(x, dict):
                e = self.entry.check(x, where, ctx)
                if e is not INVALID:  # absent optional keys stay absent (pipeline.sky has defaults)
                    e = {k: v for k, v in e.items() if v is not None}
                out.append(e)
            else:
                ctx.error(where, f"expected a source name or {{name, ra_deg, dec_deg, flux_jy}}, got {x!r}")
                out.append(INVALID)
        names = [s if isinstance(s, str) else s["name"] for s in out
                 if s is not INVALID and (isinstance(s, str) or s["name"] is not INVALID)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            ctx.error(path, f"source names must be unique; repeated: {', '.join(dup)}")
        return out


class FlagList:
    entry = Section({
        "stand": Key(Int(1), REQUIRED, doc="The stand flagged, numbered from 1 as in the SSMIF."),
        "pol": Key(Choice("X", "Y", "both"), "both",
                   doc="The polarisation flagged: X (N-S dipole), Y (E-W) or both."),
    }, what="a flag mapping {stand, pol}")

    def describe(self) -> str:
        return "a list of {stand: int, pol: X|Y|both} or stand numbers"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return INVALID
        out = []
        for i, x in enumerate(v):
            if isinstance(x, int) and not isinstance(x, bool):
                x = {"stand": x}
            out.append(self.entry.check(x, f"{path}[{i}]", ctx))
        return out


class FreqRanges:
    """Frequency ranges in MHz: a list of [lo, hi] pairs or single frequencies (+- 100 kHz, Orville's rule)."""

    def describe(self) -> str:
        return "a list of [lo_mhz, hi_mhz] pairs or frequencies in MHz"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return INVALID
        out = []
        for i, x in enumerate(v):
            pair = x if isinstance(x, list) else [x]
            ok = len(pair) in (1, 2) and all(isinstance(y, (int, float)) and not isinstance(y, bool)
                                            and y == y and 0 < y < 1e4 for y in pair)
            if ok and len(pair) == 2 and not pair[0] < pair[1]:
                ok = False
            if not ok:
                ctx.error(f"{path}[{i}]", f"expected a frequency in MHz or a pair [lo, hi] with lo < hi, got {x!r}")
                out.append(INVALID)
                continue
            out.append([float(y) for y in pair])
        return out


class OffsetPairs:
    """watch.targets[].offsets_deg: [east_deg, north_deg] pairs (checked in full by parse_targets)."""

    def describe(self) -> str:
        return "a list of [east_deg, north_deg] pairs"

    def __call__(self, v, ctx):
        if not isinstance(v, list) or not all(isinstance(p, list) and len(p) == 2 for p in v):
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        return v


class WatchTargets:
    """watch.targets: catalogue or body names, or {name, ra_deg, dec_deg} / {name, body} mappings,
    each checked by :func:`bf_epic_blocks.sky.watch.parse_targets`."""

    entry = Section({
        "name": Key(Str(r"[^/\s]+", "a name without spaces or slashes"), REQUIRED,
                    doc="The target's name, unique in the list and its group in the watch file; alone, a "
                        "catalogue name (CygA, CasA, TauA, VirA) or a body's."),
        "ra_deg": Key(Float(0.0, 360.0, hi_open=True), None, doc="Right ascension (ICRS), degrees; with `dec_deg`."),
        "dec_deg": Key(Float(-90.0, 90.0), None, doc="Declination (ICRS), degrees; with `ra_deg`."),
        "body": Key(Str(r"\S+", "a body name"), None,
                    doc="A solar-system body placed by astropy's built-in ephemeris: sun, moon, mercury, venus, "
                        "mars, jupiter, saturn, uranus or neptune."),
        "start": Key(TimeStr(), None, doc="Start of the window the target is recorded in (UTC); null: always."),
        "stop": Key(TimeStr(), None, doc="End of the window (UTC), not before `start`; null: no end."),
        "offsets_deg": Key(OffsetPairs(), None,
                           doc="Reference directions around the target: [east_deg, north_deg] great-circle offsets "
                               "along RA and Dec, moving with a body."),
    }, what="a watch target mapping")

    def describe(self) -> str:
        return "a list of catalogue or body names, or {name, ra_deg, dec_deg} / {name, body} mappings"

    def check(self, v, path, ctx):
        from ..sky.watch import parse_targets
        if not isinstance(v, list) or not v:
            ctx.error(path, f"expected {self.describe()} (at least one), got {v!r}")
            return INVALID
        out, good = [], []
        for i, x in enumerate(v):
            where = f"{path}[{i}]"
            if isinstance(x, dict):
                e = self.entry.check(x, where, ctx)
                if e is INVALID or not all(is_valid(y) for y in e.values()):
                    out.append(INVALID)
                    continue
                x = {k: y for k, y in e.items() if y is not None}
            elif not isinstance(x, str):
                ctx.error(where, f"expected a target name or a mapping {{name, ...}}, got {x!r}")
                out.append(INVALID)
                continue
            try:
                good.append(parse_targets([x])[0])
            except ValueError as err:
                ctx.error(where, str(err))
                out.append(INVALID)
                continue
            out.append(x)
        names = [t.name for t in good]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            ctx.error(path, f"watch target names must be unique; repeated: {', '.join(dup)}")
        return out


#: the top-level keys a tuning may set for itself (the station and the name are the station's)
TUNING_KEYS = ("source", "calibration", "flagging", "imager", "device", "watch", "output", "service")


class Tunings:
    """tunings: a station's tunings, each ``{name, <section>: {...}}``: the sections it sets are merged key
    by key over the pipeline's own (what it leaves out is the pipeline's). Each merged pipeline is checked
    as a pipeline of its own in :func:`load_config`; here, the list's shape and the names."""

    def describe(self) -> str:
        return ("a list of at least two mappings {name, and any of " + ", ".join(TUNING_KEYS) +
                "}, each a tuning's own settings")

    def check(self, v, path, ctx):
        if not isinstance(v, list) or len(v) < 2:
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return INVALID
        out, names = [], []
        for i, x in enumerate(v):
            where = f"{path}[{i}]"
            if not isinstance(x, dict):
                ctx.error(where, f"expected a mapping {{name, source: ..., ...}}, got {x!r}")
                out.append(INVALID)
                continue
            name = x.get("name")
            if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
                ctx.error(f"{where}.name", f"expected a name of letters, digits, '_', '.' or '-', got {name!r}")
                out.append(INVALID)
                continue
            bad = sorted(set(x) - set(TUNING_KEYS) - {"name"})
            if bad:
                ctx.error(where, f"a tuning sets only {', '.join(TUNING_KEYS)}; not {', '.join(bad)} (the "
                                 "station's own keys are set once, outside `tunings`)")
                out.append(INVALID)
                continue
            names.append(name)
            out.append(x)
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            ctx.error(path, f"tuning names must be unique; repeated: {', '.join(dup)}")
            return INVALID
        return out


def _merged(base, over):
    """``base`` with ``over`` merged in, mapping by mapping (a list or a value in ``over`` replaces)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def _paths(d, prefix=""):
    """Every dotted key path in the nested mapping ``d``."""
    for k, v in d.items():
        p = f"{prefix}{k}"
        yield p
        if isinstance(v, dict):
            yield from _paths(v, p + ".")


def _tuning_listen(listen, k):
    """The ``k``-th tuning's ``service.listen``: the station's port + k (port 0: each its own free port)."""
    from ..service.server import parse_listen
    try:
        host, port = parse_listen(listen)
    except ValueError:
        return listen                     # the tuning's own check names the problem
    host = f"[{host}]" if ":" in host else host
    return f"{host}:{port + k if port else 0}"


def _tuning_device(device, k):
    """The device of a station's ``k``-th tuning that names none itself: tuning k on the k-th of several
    GPUs (``gpu:all``: GPU k), round robin over a list; one device: every tuning on it."""
    if isinstance(device, str) and device.startswith("gpu:") and (device == "gpu:all" or "," in device):
        if device == "gpu:all":
            return f"gpu:{k}"
        idx = device[4:].split(",")
        return f"gpu:{idx[k % len(idx)]}"
    return device


def _expand_tunings(cfg, raw, lines, base, source):
    """cfg["tunings"] (a checked list of tuning mappings) replaced by each tuning's whole pipeline, checked
    as one: the station's raw mapping with the tuning's sections merged over it, named
    ``<name>_<tuning>``, writing to ``<output.dir>/<tuning>``. A simulated burst given once for the station
    (``start_s`` its arrival at the station's highest channel) is delayed in each tuning by its dispersion
    from there to the tuning's own highest channel, so every tuning sees one event. Raises ConfigError with
    every problem, each named by its tuning."""
    from ..conventions import dispersion_delay_s
    station = {k: v for k, v in raw.items() if k != "tunings"}
    errors, out = [], []
    for i, t in enumerate(cfg["tunings"]):
        over = {k: v for k, v in t.items() if k != "name"}
        merged = _merged(station, over)
        merged["name"] = f"{cfg['name']}_{t['name']}"
        sub = {k: (v if isinstance(v, dict) else {}) for k, v in over.items()}   # a tuning's sections, as given
        out_over = sub.get("output", {})
        merged.setdefault("output", {})
        if isinstance(merged["output"], dict):          # (anything else: the check below names it)
            if "dir" not in out_over:
                merged["output"]["dir"] = str(Path(cfg["output"]["dir"]) / t["name"])
            if "prefix" not in out_over:
                merged["output"]["prefix"] = merged["name"]
        if "device" not in over:
            merged["device"] = _tuning_device(cfg["device"], i)
        if cfg.get("service") and "listen" not in sub.get("service", {}):
            merged["service"] = dict(merged.get("service") or {}, listen=_tuning_listen(cfg["service"]["listen"], i))
        prefix = f"tunings[{i}]."
        mine = set(_paths(over))          # a base key's line is not where a tuning's own value came from
        tl = {p: n for p, n in lines.items() if not p.startswith("tunings") and p not in mine}
        tl.update({p[len(prefix):]: n for p, n in lines.items() if p.startswith(prefix)})
        ctx = Context(base, tl)
        tc = SCHEMA.check(merged, "", ctx)
        if not ctx.errors:
            _fill_and_cross_check(tc, merged["name"], ctx)
        errors += [f"tunings[{i}] ({t['name']}): {e}" for e in ctx.errors]
        out.append((tc, "transients" not in sub.get("source", {})))
    if errors:
        raise ConfigError(errors, source)
    live = [(tc["source"]["address"], tc["source"]["port"]) for tc, _ in out
            if tc["source"]["kind"] == "udp" and tc["source"]["port"]]
    shared = sorted({f"{a}:{p}" for a, p in live if live.count((a, p)) > 1})
    if shared:
        raise ConfigError([f"tunings: live tunings listen on one socket ({', '.join(shared)}); give each its own "
                           "source.port (each F-engine stream its own port)"], source)
    sim = [tc for tc, _ in out if tc["source"]["kind"] == "simulated"]
    if len(sim) == len(out):
        def f_hi(tc):
            ch = tc["source"]["channels"]
            return (ch["first"] + ch["count"] - 1) * ch["width_hz"]
        top = max(f_hi(tc) for tc, _ in out)
        for tc, inherited in out:
            if inherited:
                for b in tc["source"]["transients"] or []:
                    b["start_s"] = float(b["start_s"]) + float(dispersion_delay_s(b.get("dm") or 0.0, f_hi(tc), top))
    _stagger_solves([tc for tc, _ in out])
    for tc, _ in out:
        tc["tunings"] = None
    cfg["tunings"] = [tc for tc, _ in out]


def _stagger_solves(tunings):
    """``calibration.solve.stagger``: the n tunings that solve live on one device start their schedules in
    turn, tuning j of them ``j cadence_s / n`` after its ``offset_s`` (modulo the cadence), so that their
    solves' memory and time come at different moments. Written into each tuning's ``offset_s``."""
    groups = {}
    for tc in tunings:
        sv = (tc.get("calibration") or {}).get("solve")
        if sv and sv.get("stagger"):
            groups.setdefault(str(tc["device"]), []).append(sv)
    for group in groups.values():
        for j, sv in enumerate(group):
            cad = float(sv["cadence_s"])
            sv["offset_s"] = (float(sv["offset_s"]) + j * cad / len(group)) % cad


class OnOffAuto(Choice):
    """'auto', 'on' or 'off'; YAML's bare on / off / true / false (booleans to a YAML 1.1 reader) too."""

    def __init__(self):
        super().__init__("auto", "on", "off")

    def __call__(self, v, ctx):
        if isinstance(v, bool):
            return "on" if v else "off"
        return super().__call__(v, ctx)


def _flagging_post(out, given, path, ctx):
    f = out.get("bad_freq_file")
    if isinstance(f, str):
        from ..imaging.rfi import parse_bad_freq_list
        try:
            parse_bad_freq_list(Path(f))
        except (ValueError, OSError) as e:
            ctx.error(f"{path}.bad_freq_file", str(e))


FLAGGING = Section({
    "enabled": Key(OnOffAuto(), "auto",
                   doc="Detect interference and leave it out of the images: auto is on for capture files and "
                       "live streams, off for the simulated sky unless it adds interference (`source.rfi`)."),
    "far": Key(Float(0.0, 1.0, lo_open=True, hi_open=True), 1e-3,
               doc="False-alarm rate: the fraction of blocks of pure noise the spectral-kurtosis test flags."),
    "block_frames": Key(Int(64), 1024,
                        doc="Samples per spectral-kurtosis block (1024 = 41 ms of 25 kHz channels); a gulp "
                            "is tested in blocks of this many frames, a shorter last block as it is."),
    "impulse_frames": Key(Int(1), 16,
                          doc="Samples per short block of the impulse detector (16 = 0.64 ms); `block_frames` "
                              "must be a multiple of it."),
    "impulse_sigma": Key(Float(0.0, lo_open=True), 6.0,
                         doc="A short block whose power, against each channel's median and taken across the "
                             "band, exceeds the gulp's by this many robust sigmas is an impulse, flagged across "
                             "the band (every stand, or the one stand that shows it)."),
    "report_s": Key(Float(0.0, lo_open=True), 60.0,
                    doc="Seconds of data between rewrites of the occupancy table and waterfall "
                        "(`<prefix>_flags.ecsv`, `.png`) while a run goes on; the last is written at its end."),
    "bad_freq_mhz": Key(FreqRanges(), [],
                        doc="Frequencies always dropped: [lo, hi] ranges in MHz, or single frequencies "
                            "(+- 100 kHz, as Orville's list)."),
    "bad_freq_file": Key(File("bad-frequency list"), None,
                         doc="An Orville `bad_freq.txt`: one frequency in MHz per line (+- 100 kHz), "
                             "'#' comments; 'lo hi' ranges are also read."),
}, post=_flagging_post,
    what="a flagging mapping {enabled, far, block_frames, impulse_frames, impulse_sigma, report_s, bad_freq_mhz, "
         "bad_freq_file}")


def _station_post(out, given, path, ctx):
    if "name" in given and "ssmif" in given:
        ctx.error(path, "give either station.name or station.ssmif, not both")
    elif "name" not in given and "ssmif" not in given:
        out["name"] = "lwasv"


def _calibration_post(out, given, path, ctx):
    if out.get("solve") and out.get("gains_table"):
        ctx.error(join_path(path, "solve"), "give gains_table (solutions made before) or solve (solutions made as "
                                            "the data flow), not both")
    sv = out.get("solve")
    if is_valid(sv) and sv and is_valid(sv.get("cadence_s")) and is_valid(sv.get("integration_s")) \
            and sv["integration_s"] > sv["cadence_s"]:
        ctx.error(join_path(join_path(path, "solve"), "integration_s"),
                  f"must be <= cadence_s ({sv['cadence_s']}), got {sv['integration_s']}")
    if is_valid(sv) and sv and is_valid(sv.get("cadence_s")) and is_valid(sv.get("offset_s")) \
            and sv["offset_s"] >= sv["cadence_s"]:
        ctx.error(join_path(join_path(path, "solve"), "offset_s"),
                  f"must be < cadence_s ({sv['cadence_s']}), got {sv['offset_s']}")


def pixel_split_problems(cfg) -> list[str]:
    """Why ``cfg`` cannot split a grid's pixels over several GPUs (empty: it can)."""
    im, src, cal = cfg["imager"], cfg["source"], cfg.get("calibration") or {}
    return [why for why, bad in (
        ("imager.kind is not dft", im.get("kind") != "dft"),
        ("imager.track follows a source (a grid is split)", im.get("track") is not None),
        ("the source is live (udp): each GPU would need its own copy of the packets", src.get("kind") == "udp"),
        ("calibration.gains_table needs CalFoldBlock on one device", bool(cal.get("gains_table")))) if bad]


def resolved_split(cfg) -> str:
    """'pixels' or 'channels': how several GPUs share the dft imager (``imager.split``; auto: pixels
    where a search runs on a grid from a file or simulated source). Meaningful only for several GPUs."""
    im = cfg["imager"]
    split = im.get("split", "auto")
    if split != "auto":
        return split
    return "pixels" if im.get("search") and not pixel_split_problems(cfg) else "channels"


def several_gpus(device) -> bool:
    """Whether a (resolved) device string names several GPUs ('gpu:all', 'gpu:0,1')."""
    return isinstance(device, str) and (device.endswith(":all") or "," in device)


def _imager_post(out, given, path, ctx):
    if out.get("tolerance") not in (None, INVALID) and "precision" not in given:
        out["precision"] = None   # the tolerance picks it (bf_epic_blocks.imaging.plan)
    if "grid" in given and "track" in given:
        ctx.error(path, "give exactly one of imager.grid (all-sky) or imager.track (a patch that "
                        "follows a source), not both; set the other to null to remove it")
        return
    if "track" in given:
        out["grid"] = None
        if out.get("kind") not in ("dft", INVALID):
            ctx.error(join_path(path, "track"),
                      f"a tracked patch needs the dft imager (imager.kind is {out['kind']!r}); "
                      "the FFT imagers (wstack, moff) make all-sky grids only")
    else:
        out["track"] = None
        if "grid" not in given:
            out["grid"] = IMAGER_GRID.check({}, join_path(path, "grid"), ctx)


IMAGER_GRID = Section({
    "size": Key(Int(2), 64, doc="Pixels per side."),
    "cell": Key(Float(0.0, lo_open=True), None,
                doc="Pixel step in the direction cosines l and m; null: 2 / size, the whole sky."),
}, what="a grid mapping {size, cell}")

IMAGER_TRACK = Section({
    "source": Key(Str(r"\S+", "a source name"), REQUIRED,
                  doc="The source followed: a catalogue name (CygA, CasA, TauA, VirA) or the name of an "
                      "entry of `source.sources`."),
    "size": Key(Int(2), 16, doc="Pixels per side of the patch."),
    "fov_deg": Key(Float(0.0, 180.0, lo_open=True), 10.0, doc="Width of the patch, degrees."),
    "update_s": Key(Float(0.0, lo_open=True), 10.0, doc="Seconds between recomputations of the patch's centre."),
}, what="a track mapping {source, size, fov_deg, update_s}")

TRANSIENT = Section({
    "name": Key(Str(r"\S+", "a name without spaces"), None, doc="A name for the burst; null: none."),
    "ra_deg": Key(Float(0.0, 360.0, hi_open=True), REQUIRED, doc="Right ascension (ICRS), degrees."),
    "dec_deg": Key(Float(-90.0, 90.0), REQUIRED, doc="Declination (ICRS), degrees."),
    "start_s": Key(Float(0.0), REQUIRED,
                   doc="When the burst reaches the band's highest channel, seconds after `source.start`."),
    "duration_s": Key(Float(0.0, lo_open=True), REQUIRED, doc="Length of the burst in each channel, seconds."),
    "flux_jy": Key(Float(0.0), REQUIRED, doc="Flux density while the burst lasts, Jy."),
    "dm": Key(Float(0.0), 0.0,
              doc="Dispersion measure, pc cm^-3: lower channels see the burst later by the cold-plasma "
                  "delay."),
}, what="a burst mapping {ra_deg, dec_deg, start_s, duration_s, flux_jy, dm}")

IMAGER_SEARCH = Section({
    "threshold": Key(Float(0.0, lo_open=True), 6.0, doc="Detection threshold, S/N."),
    "window_s": Key(Float(0.0, lo_open=True), 1.0,
                    doc="Seconds of images in the sliding window that gives each pixel's mean and variance; "
                        "with a simulated source, shorter than `source.duration_s`."),
    "dms": Key(ListOf(Float(0.0), "DMs >= 0", min_len=1), [0.0], doc="Trial dispersion measures, pc cm^-3."),
    "widths": Key(ListOf(Int(1), "integers >= 1", min_len=1), [1, 2, 4, 8], doc="Boxcar widths, in images."),
    "average_channels": Key(Bool(), True,
                            doc="Dedisperse and average the channels into one series per DM; false searches "
                                "each channel on its own."),
    "dedisperse": Key(Choice("auto", "shifts", "tree"), "auto",
                      doc="shifts: each DM of `dms` is a sum of shifted channels; tree: the streaming FDMT "
                          "over every sweep from 0 to the largest DM's, one image apart; auto: the tree from "
                          "64 channels up, else shifts."),
    "tree_precision": Key(Choice("fp32", "fp16"), "fp32",
                          doc="What the tree stores: fp16 halves its memory traffic and rings, and rounds the "
                              "fluctuations about each channel's first image by about 1e-3 of the sums' "
                              "noise rms."),
    "product": Key(Str(r"\S+", "a product name"), None,
                   doc="The product searched, one of `imager.products`; null: the first."),
    "table": Key(Choice("ecsv", "fits"), "ecsv",
                 doc="Format of the candidate table, `<prefix>_candidates.<table>` in `output.dir`."),
    "png": Key(Bool(), True, doc="Also write a PNG of the sky with the candidates and their light curves."),
    "max_pixels": Key(Int(1), 32, doc="Threshold crossings kept per trial image, its brightest."),
    "sky_fraction": Key(Float(0.0, 1.0, lo_open=True), 0.1,
                        doc="A larger fraction of the sky over the threshold at once is one 'sky-wide' event "
                            "(lightning, RFI, a flash), not a set of candidates."),
    "sidelobe_factor": Key(Float(0.0), 2.0,
                           doc="A candidate whose S/N is at most this many times what a brighter one puts at "
                               "its pixel (through the array's beam or its DM sidelobe) is folded into it; 0 "
                               "keeps every candidate."),
}, what="a search mapping {threshold, window_s, dms, widths, ...}")

OUTPUT_INTEGRATE = Section({
    "seconds": Key(Float(0.0, lo_open=True), 1.0,
                   doc="Length of an integrated image: the mean of round(seconds / image length) images."),
    "average_channels": Key(Bool(), True, doc="Average the channels into one band-averaged image."),
}, what="an integrate mapping {seconds, average_channels}")

OUTPUT_OIMS = Section({
    "ngrid": Key(Int(2), 128,
                 doc="Pixels per side of the OIMS images (Orville's grid: 130 / ngrid degrees a pixel, the zenith "
                     "between the middle four pixels), imaged exactly at those directions."),
    "seconds": Key(Float(0.0, lo_open=True), 5.0, doc="Length of each OIMS integration (Orville's is 5 s)."),
    "products": Key(Products(), ["I", "Q", "U", "V"],
                    doc="The images' Stokes products; OIMS2fits reads I, Q, U, V (or XX, XY, YX, YY)."),
    "lwatv": Key(Bool(), True,
                 doc="Also draw each integration as the station's LWATV view (I and |V| of one channel, the "
                     "sources labelled, the band's spectrum) into lwatv/<MJD>/ under Orville's names."),
    "lwatv_mhz": Key(Float(0.0, lo_open=True), None,
                     doc="The LWATV view's channel: the one nearest this frequency; null: the band's middle."),
}, what="an oims mapping {ngrid, seconds, products, lwatv, lwatv_mhz}")

OUTPUT_CUBE = Section({
    "dtype": Key(Choice("float32", "float16"), "float32", doc="The data type the cube stores its pixels in."),
    "average_channels": Key(Bool(), False, doc="Store one band-averaged image per time, not every channel."),
    "images_per_file": Key(Int(1), None, doc="Images (times) per HDF5 file; null: one file per sequence."),
}, what="a cube mapping {dtype, average_channels, images_per_file}")

CALIBRATION_SOLVE = Section({
    "sources": Key(SourceList(CATALOGUE_SOURCES + ("Sun",)), list(CATALOGUE_SOURCES),
                   doc="The sky model: catalogue names (CygA, CasA, TauA, VirA, Sun) or source mappings. Those "
                       "below `min_alt_deg` at a solution's time are left out."),
    "cadence_s": Key(Float(0.0, lo_open=True), 10.0, doc="Seconds of data from one solution to the next."),
    "integration_s": Key(Float(0.0, lo_open=True), 1.0,
                         doc="Seconds of data each solution sums its covariances over (the first of its cadence); "
                             "it applies from the first frame after them."),
    "offset_s": Key(Float(0.0), 0.0,
                    doc="Seconds of data before the first solution's integration (less than `cadence_s`): solution k "
                        "sums from k x cadence_s + offset_s."),
    "stagger": Key(Bool(), True,
                   doc="A station's tunings that solve on one device (`tunings:` on one GPU, or the CPU) do so in "
                       "turn: of n such tunings, tuning j's schedule starts j x cadence_s / n after its `offset_s`, "
                       "so that their solves' memory (GBs at the whole band) and time come at different moments. "
                       "No effect on a single pipeline or on tunings with GPUs of their own."),
    "apply_delay_s": Key(Float(0.0), 6.0,
                         doc="A solution applies this long after the end of its data (on the first image "
                             "integration from then): the time its solve takes, so that the imager need not wait. "
                             "At the whole band on a GPU the imager shares, the last sums and the solve take "
                             "~2.2 s of wall time, and an imager running at twice real time covers 6 s of data "
                             "in 3 s."),
    "min_baseline_lambda": Key(Float(0.0), 4.0,
                               doc="Baselines shorter than this many wavelengths are not used: the diffuse Galactic "
                                   "emission, which a point-source model lacks, dominates them."),
    "diffuse": Key(Bool(), True,
                   doc="Add the analytic Galactic sky (`bf_epic_blocks.sky.diffuse`) to the model, its scale fitted per "
                       "channel and polarisation: at a compact station it correlates on every baseline and biases a "
                       "point-source-only solution by ~10%."),
    "min_alt_deg": Key(Float(0.0, 90.0), 10.0, doc="Model sources lower than this altitude are left out, degrees."),
    "pattern": Key(Choice("none", "dipole", none_is="none"), None,
                   doc="The antennas' voltage pattern the model's sources are seen through; null: "
                       "`calibration.pattern`."),
    "reference": Key(Int(1, auto=True), "auto",
                     doc="Stand id of the reference input, whose phase is zero in every channel; auto: the good "
                         "input with the largest gain."),
    "smooth_channels": Key(Int(1), 16,
                           doc="Channels in the running mean across the band once each input's delay is removed; "
                               "1 keeps every channel's own solution."),
    "max_delay_s": Key(Float(0.0), 2e-6, doc="The residual delay searched per input spans +- this, seconds."),
    "deaf_below": Key(Float(0.0, 1.0, hi_open=True), 0.3,
                      doc="An input whose gain is below this fraction of the inputs' median is flagged deaf."),
    "noisy_above": Key(Float(1.0, lo_open=True), 3.0,
                       doc="An input whose power per unit gain is above this multiple of the median is flagged noisy."),
    "residual_above": Key(Float(1.0, lo_open=True), 4.0,
                          doc="An input the model fits this many times worse than the median input is flagged."),
    "saturated_above": Key(Float(0.0, 1.0, lo_open=True), 0.1,
                           doc="A 4-bit input whose samples clip more often than this fraction (estimated from its "
                               "power) is flagged saturated: clipping loses correlation and biases its gain (an "
                               "input clipping 7% of its samples came out 19% wrong in bench_calibration)."),
    "max_iter": Key(Int(2), 200, doc="StEFCal's iteration limit."),
    "tol": Key(Float(0.0, lo_open=True), 1e-6, doc="StEFCal's convergence test: relative change of the gains."),
    "min_good_fraction": Key(Float(0.0, 1.0, lo_open=True), 0.5,
                             doc="A solution with fewer good inputs than this fraction of the station's (per pol) "
                                 "fails, and the last good one stays in force."),
    "min_samples": Key(Int(1), 1000,
                       doc="A sequence shorter than one integration is solved from what it has if that is at least "
                           "this many samples; fewer is an error (offline) or a counted failure (live)."),
    "png": Key(Bool(), True, doc="Write a PNG of the gains and flags beside the table."),
    "solutions_per_file": Key(Int(1), 60,
                              doc="Live solutions per table file: then `<prefix>_gains_p001.npz`, and so on, so a "
                                  "run of weeks keeps one file's solutions in memory. `bf-epic calibrate` writes one "
                                  "table."),
}, what="a solve mapping {sources, cadence_s, integration_s, min_baseline_lambda, ...}")
class InputChoice:
    """source.corrupt.deaf / noisy: a number of inputs the seed picks, or [stand_index, pol] pairs."""

    def describe(self) -> str:
        return "an integer >= 0 or a list of [stand_index, pol] pairs (stand_index from 0, pol 0 or 1)"

    def __call__(self, v, ctx):
        if isinstance(v, int) and not isinstance(v, bool):
            if v < 0:
                raise BadValue(f"expected {self.describe()}, got {v!r}")
            return v
        ok = isinstance(v, list) and all(
            isinstance(x, list) and len(x) == 2 and all(isinstance(i, int) and not isinstance(i, bool) for i in x)
            and x[0] >= 0 and x[1] in (0, 1) for x in v)
        if not ok:
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        pairs = [list(x) for x in v]
        if len({tuple(x) for x in pairs}) != len(pairs):
            raise BadValue(f"an input is listed twice: {v!r}")
        return pairs


SOURCE_DIFFUSE = Section({
    "scale": Key(Float(0.0), 1.0, doc="Factor on the model's brightness temperatures (1: the model as it is)."),
    "nmode": Key(Int(1), 32,
                 doc="Eigenmodes of the diffuse sky's covariance simulated, each one more column of the "
                     "simulator (on a CPU a column costs about as much as a point source). 32 keep about a "
                     "quarter of LWA-SV's diffuse power, its largest scales; the rest, spread thinly over "
                     "the other modes, is left out. On a GPU the sources, modes and noisy inputs together may be at most 96 "
                     "columns."),
}, what="a diffuse mapping {scale, nmode}")

SOURCE_CORRUPT = Section({
    "amplitude_rms": Key(Float(0.0), 0.25, doc="Fractional rms scatter of the gains' amplitudes about 1 (log-normal)."),
    "delay_ns_rms": Key(Float(0.0), 30.0, doc="Rms of each input's delay, ns (a phase slope across the band)."),
    "random_phase": Key(Bool(), True, doc="Give each input a uniform random phase; false: phase 0 before drift and delay."),
    "drift": Key(Section({
        "amplitude_frac": Key(Float(0.0), 0.0,
                              doc="Fractional change of each input's amplitude after `over_s` seconds (sign "
                                  "random per input)."),
        "phase_deg": Key(Float(), 0.0,
                         doc="Change of each input's phase after `over_s` seconds, degrees (sign random per input)."),
        "over_s": Key(Float(0.0, lo_open=True), 600.0,
                      doc="Seconds over which the drift reaches those values; it goes on at that rate."),
    }, what="a drift mapping {amplitude_frac, phase_deg, over_s}"), {},
        doc="A linear drift of the gains, applied piecewise constant over `source.refresh_s`."),
    "deaf": Key(InputChoice(), 0,
                doc="Inputs that see no sky, only receiver noise: a number the seed picks among the unflagged "
                    "inputs, or [stand_index, pol] pairs (stand_index counted from 0, pol 0 = X, 1 = Y)."),
    "noisy": Key(InputChoice(), 0,
                 doc="Inputs with extra independent noise: a number the seed picks (not deaf, unflagged), or "
                     "[stand_index, pol] pairs."),
    "noisy_power": Key(Float(0.0), 10.0,
                       doc="Extra noise power of a noisy input, in units of the median input's total power."),
    "seed": Key(Int(), None, doc="Seed of the corruptions; null: `source.seed`."),
}, what="a corrupt mapping {amplitude_rms, delay_ns_rms, random_phase, drift, deaf, noisy, noisy_power, seed}")

SOURCE_COMMON = {
    "kind": Key(Choice("simulated", "tbf", "tbx", "file", "udp"), REQUIRED,
                doc="simulated: a sky computed as the pipeline runs; tbf, tbx: a capture file of that format; "
                    "file: a TBF or TBX file, told apart by its frame id; udp: live packets."),
    "gulp_nframe": Key(Int(1, auto=True), "auto",
                       doc="Frames (time samples) per ring gulp. auto: 1024, or for a capture file imaged on "
                           "a GPU about 64 MiB of samples per gulp (`runner.gulp_frames`)."),
}
SOURCE_SIMULATED = {
    "start": Key(TimeStr(), DEFAULT_START, doc="UTC time of the first sample, an ISO string; sets where the "
                                               "sources are in the sky."),
    "duration_s": Key(Float(0.0, lo_open=True), 2.0, doc="Seconds of data simulated."),
    "channels": Key(Section({
        "first": Key(Int(1), 2960,
                     doc="Number of the first channel; its centre frequency is first × width_hz "
                         "(2960 × 25 kHz = 74.0 MHz)."),
        "count": Key(Int(1), 16, doc="Number of channels."),
        "width_hz": Key(Float(0.0, lo_open=True), 25000.0,
                        doc="Channel width, Hz; one frame (time sample) lasts 1 / width_hz seconds."),
    }, what="a channels mapping {first, count, width_hz}"), {},
        doc="The simulated band: `count` adjacent channels from channel number `first`."),
    "sources": Key(SourceList(), list(CATALOGUE_SOURCES),
                   doc="The sky's point sources: catalogue names or mappings, as "
                       "`bf_epic_blocks.sky.resolve_source` takes them. Sources below the horizon are left out."),
    "noise_power": Key(Float(0.0), 1000.0,
                       doc="Power of the receiver noise added to each antenna, polarisation, channel and "
                           "sample, in the units of flux_jy."),
    "seed": Key(Int(), 1, doc="Seed of the random signals and noise: the same seed gives the same voltages."),
    "quantize": Key(Bool(), True,
                    doc="Round the voltages to 4-bit complex integers as a station's F-engine does; false "
                        "keeps them complex floats."),
    "refresh_s": Key(Float(0.0, lo_open=True), 1.0,
                     doc="Seconds of data between recomputations of the sources' directions. The sky turns "
                         "0.004 degrees a second, and a bright source's step at each recomputation is what a "
                         "sensitive search sees."),
    "transients": Key(ListOf(TRANSIENT, "burst mappings"), [],
                      doc="Dispersed bursts added to the sky."),
    "pattern": Key(Choice("none", "dipole", none_is="none"), "none",
                   doc="Voltage pattern of the simulated antennas, applied to every source and to the diffuse "
                       "sky: a short dipole's, or none (isotropic)."),
    "diffuse": Key(SOURCE_DIFFUSE, None,
                   doc="The diffuse Galactic emission (an analytic model, `bf_epic_blocks.sky.diffuse`) as a few "
                       "eigenmodes of its covariance, recomputed every 60 s of data; `{}` turns it on with the "
                       "defaults. null: off."),
    "corrupt": Key(SOURCE_CORRUPT, None,
                   doc="Chosen corruptions of the voltages (`bf_epic_blocks.sky.corrupt`): complex gains on the "
                       "sky signal, deaf and noisy inputs, drawn from a seed; `{}` turns them on with the "
                       "defaults. null: none."),
}
SOURCE_TBF = {
    "path": Key(File("TBF file"), REQUIRED, doc="The TBF capture file."),
    "channel_block": Key(Int(0), None,
                         doc="Image only this block of the file's channels: the runs of evenly spaced channels "
                             "that `bf-epic run` writes to separate FITS files (`_r<index>`); `bf-epic batch` "
                             "sets it. null: every channel."),
}
SOURCE_UDP = {  # live capture (bf_epic_blocks.io.udp); station from station.name / ssmif
    "address": Key(Str(r"\S+", "an IP address to listen on"), "127.0.0.1", doc="IP address to listen on."),
    "port": Key(Int(0), REQUIRED, doc="UDP port to listen on; 0 picks a free (ephemeral) port."),
    "format": Key(Choice("tbf", "tbx", "chips", "snap2"), "tbf",
                  doc="Packet format: tbf, tbx, chips (the ADP F-engine's own stream, LWA-SV) or snap2 (the NDP "
                      "F-engine's), as Bifrost names them."),
    "sync_time": Key(Int(0), None,
                     doc="chips only: the whole UNIX second the F-engine counts spectra from (its utc_start); "
                         "null: recovered from the arrival clock."),
    "engine": Key(Choice("auto", "bifrost", "python"), "auto",
                  doc="The receiver: Bifrost's C packet capture or the Python one. auto: Bifrost's where "
                      "Bifrost is the runtime and decodes the format (chips, snap2), else Python's."),
    "core": Key(Int(0), None, doc="CPU core Bifrost's capture thread is bound to; null: not bound."),
    "buffer_s": Key(Float(0.0, lo_open=True), 0.05, doc="Reordering window, seconds of data."),
    "idle_timeout_s": Key(Float(0.0, lo_open=True), 2.0, doc="Seconds without a packet that end a sequence."),
    "start_timeout_s": Key(Float(0.0, lo_open=True), None,
                           doc="Seconds to wait for the first packet; null: wait forever."),
    "rcvbuf_mb": Key(Float(0.0, lo_open=True), 64.0, doc="Socket receive buffer asked for, MiB."),
    "sequences": Key(Int(0), 1, doc="Sequences (streams) to image before stopping; 0: until stopped."),
}
SOURCE_TBX = {"path": Key(File("TBX file"), REQUIRED, doc="The TBX capture file.")}
SOURCE_FILE = {"path": Key(File("TBF or TBX capture file"), REQUIRED,
                           doc="The capture file, TBF or TBX (told apart by its frame id).")}
#: source.kind -> the keys it takes besides SOURCE_COMMON
SOURCE_KINDS = {"simulated": SOURCE_SIMULATED, "tbf": SOURCE_TBF, "tbx": SOURCE_TBX, "file": SOURCE_FILE,
                "udp": SOURCE_UDP}


class SourceSection(Section):
    """source: the keys allowed depend on source.kind."""

    def __init__(self):
        super().__init__({**SOURCE_COMMON, **SOURCE_SIMULATED, **SOURCE_TBF, **SOURCE_UDP}, what="a source mapping",
                         doc="The keys allowed depend on `kind`; a key of another kind is an error that names "
                             "the kinds it belongs to.")

    def check(self, v, path, ctx, **_):
        if v is None:
            v = {}
        if not isinstance(v, dict):
            ctx.error(path, f"expected a source mapping with at least 'kind', got {v!r}")
            return INVALID
        kind = (run_check(SOURCE_COMMON["kind"].check, v["kind"], join_path(path, "kind"), ctx)
                if v.get("kind") is not None else None)
        if kind is None:
            ctx.error(join_path(path, "kind"), "missing required key (one of "
                                           + ", ".join(repr(k) for k in SOURCE_KINDS) + ")")
            return INVALID
        if kind is INVALID:
            return INVALID
        mine = SOURCE_KINDS[kind]
        users = {}
        for other_kind, keys in SOURCE_KINDS.items():
            for k in keys:
                if k not in mine:
                    users.setdefault(k, []).append(repr(other_kind))
        elsewhere = {k: f"only used when source.kind is {' or '.join(u)} (kind is {kind!r})" for k, u in users.items()}
        out = super().check(v, path, ctx, allowed={**SOURCE_COMMON, **mine}, elsewhere=elsewhere)
        if (kind == "udp" and is_valid(out) and out.get("sync_time") is not None
                and out.get("format") not in ("chips", INVALID)):
            ctx.error(join_path(path, "sync_time"), f"only used when source.format is 'chips' (its packets carry "
                                                    f"no absolute time); format is {out.get('format')!r}")
        return out


SCHEMA = Section({
    "name": Key(Str(r"[^/\\\s]+", "a name without spaces or slashes"), None,
                doc="The pipeline's name, the default of `output.dir` and `output.prefix`; null: the YAML "
                    "file's stem, or 'pipeline' for inline text."),
    "station": Key(Section({
        "name": Key(Choice(*STATIONS, "auto"), None,
                    doc="A station LSL knows. auto: the station the TBF file's frame id names (ADP: lwasv, "
                        "NDP: lwana), for TBF sources only, so that one YAML serves both in a batch."),
        "ssmif": Key(File("SSMIF file"), None, doc="An SSMIF file that describes the station, instead of `name`."),
        "flags": Key(FlagList(), [],
                     doc="Antennas left out, on top of the station's own status flags: mappings "
                         "`{stand, pol}`, or bare stand numbers (both pols)."),
    }, post=_station_post, what="a station mapping",
        doc="Give `name` or `ssmif`, not both; with neither, `name` is lwasv."), {},
        doc="The station whose antennas are imaged."),
    "source": Key(SourceSection(), REQUIRED, doc="Where the voltages come from; `kind` decides the other keys."),
    "calibration": Key(Section({
        "cable": Key(Bool(), True, doc="Remove each antenna's cable delay and gain (LSL's cable model)."),
        "gains_table": Key(File("gains table", (".npz", ".yaml", ".yml")), None,
                           doc="Time-variable gain solutions applied to the voltages, each from its exact "
                               "frame: arrays `valid_from` (time tags) and `gains` (nsol, nchan, nstand, npol). "
                               "null: none."),
        "pattern": Key(Choice("none", "dipole", none_is="none"), "dipole",
                       doc="Antenna voltage pattern folded into the imaging operator: a short dipole's, or none."),
        "solve": Key(CALIBRATION_SOLVE, None,
                     doc="Solve the antennas' gains and health from the sky as the data flow, beside the imager, "
                         "and image with each solution from the first frame after its data; the table is "
                         "written to `output.dir`. null: no solving. `bf-epic calibrate` uses these keys too."),
    }, post=_calibration_post, what="a calibration mapping"), {}, doc="What is done to the voltages before imaging."),
    "flagging": Key(FLAGGING, {}, doc="Interference: what the sky did not send, detected in the voltages and "
                                      "left out of the images, the search and the gain solutions."),
    "imager": Key(Section({
        "kind": Key(Choice("dft", "wstack", "moff"), "dft",
                    doc="dft: the exact direct Fourier transform; wstack: E-field w-stacking or covariance "
                        "w-gridding with ducc0; moff: one gridded plane that ignores the w-term (fast, and "
                        "wrong by tens of per cent of the peak across a wide field)."),
        "grid": Key(IMAGER_GRID, None,
                    doc="An all-sky grid of `size × size` pixels in the direction cosines (l, m)."),
        "track": Key(IMAGER_TRACK, None, doc="A small patch that follows a source (dft imager only)."),
        "accumulate_frames": Key(Int(1), 1024,
                                 doc="Frames (time samples) per image: an image lasts accumulate_frames / "
                                     "width_hz seconds (16 = 0.64 ms at 25 kHz channels). With a simulated "
                                     "source, at most `source.duration_s` long, or no image would be made."),
        "products": Key(Products(), ["I"],
                        doc="The polarisation products imaged: a list of names or a preset (stokes, linear, "
                            "full), returned as the resolved list; each must be possible with the station's "
                            "two pols, X and Y."),
        "remove_autocorr": Key(Bool(), False, doc="Subtract each antenna's own power from the image."),
        "method": Key(Choice("auto", "direct", "covariance"), "auto",
                      doc="Expert override of the dft imager's route: direct (F = D X, then |F|² averaged) or "
                          "covariance (R = X Xᴴ / T, then diag(D R Dᴴ)). auto: the resolver picks. Beside a "
                          "`tolerance` it restricts the resolver's choice."),
        "precision": Key(Choice(*PRECISION_NAMES), "fp32",
                         doc="Expert override of the dft imager's arithmetic. fp32 and fp64 run anywhere; the "
                             "others are tensor-core modes that need a GPU, and i8x1 / i8x2 / i8x3 4-bit voltages on "
                             "one GPU's direct route (`bf_epic_blocks.imaging.gemm`). Beside a `tolerance` it "
                             "restricts the resolver's choice; `--set imager.tolerance=...` replaces the "
                             "file's precision."),
        "tolerance": Key(Float(0.0, 1.0, lo_open=True, hi_open=True), None,
                         doc="The accuracy knob: the largest relative error of an image against its float64 "
                             "value, max |I − I_float64| / max |I_float64|. dft: the fastest route and precision "
                             "whose measured error bound is within it on the device; null: `precision` on the "
                             "cheaper route. wstack, moff: the gridder's epsilon = tolerance / 4, tolerance in "
                             "[4e-14, 0.4]; null: 4e-4 (epsilon 1e-4)."),
        "min_elevation_deg": Key(Float(0.0, 90.0, hi_open=True), 0.0,
                                 doc="Grid pixels below this elevation, degrees, are not imaged (those below "
                                     "the horizon never are)."),
        "search": Key(IMAGER_SEARCH, None, doc="A transient search on the images; null: none."),
        "split": Key(Choice("auto", "channels", "pixels"), "auto",
                     doc="How several GPUs share the dft imager's work. channels: each GPU images some "
                         "channels and the images meet on the host; pixels: each GPU reads or simulates the "
                         "whole source and images and searches its part of the grid (needs a grid and a file or "
                         "simulated source); auto: pixels where there is a search and pixels can be, else "
                         "channels."),
    }, post=_imager_post, what="an imager mapping", renamed={
        "epsilon": "epsilon is now imager.tolerance, the one accuracy knob (the largest relative image error; "
                   "for wstack / moff the gridder's epsilon = tolerance / 4): write tolerance: 4 x your epsilon"},
        doc="`tolerance` is the one accuracy knob; `method` and `precision` are expert overrides that fix the "
            "dft imager's route and arithmetic (alone) or restrict the resolver's choice (beside a "
            "tolerance). One resolver, `bf_epic_blocks.imaging.plan.resolve`, decides; `bf-epic plan` prints "
            "its pick. Give `grid` or `track`, not both; with neither, the grid's defaults; `grid: null` "
            "removes a grid given in the file."),
        {}, doc="How the images are made."),
    "tunings": Key(Tunings(), None,
                   doc="A station of several tunings run as one process (guide/station.md): a list of "
                       "`{name, source: ..., imager: ..., device: ...}`, each merged over the rest of this "
                       "file as its own pipeline, named `<name>_<tuning>`, writing to `<output.dir>/<tuning>`; "
                       "a burst seen by every tuning's search is reported once, in `<output.dir>/<name>_events."
                       "ecsv`. With several GPUs (`device: gpu:all`), tuning k runs on the k-th; with `service`, "
                       "tuning k serves at the station's port + k. null: one tuning."),
    "device": Key(Device(), "cpu",
                  doc="Where the pipeline computes: cpu, gpu (gpu:0), gpu:N, or several GPUs of the host as "
                      "gpu:all or a list [0, 1] (returned as 'gpu:all' / 'gpu:0,1'), which share the dft "
                      "imager's work as `imager.split` says. On GPUs, with no gains table and a file or "
                      "simulated source, the dft imager folds the cable terms into its operator; "
                      "`calibration.gains_table` needs a single device."),
    "gpu_memory_gb": Key(Float(0.0, lo_open=True), None,
                         doc="The most CuPy's memory pool holds on each GPU the run uses, in GB (1e9 bytes): the "
                             "pool lets go of the blocks it keeps when it reaches it (CuPy's `set_limit`, what "
                             "`CUPY_GPU_MEMORY_LIMIT` does for a whole process), and an allocation beyond it "
                             "fails the run with a clear error; `run` refuses a configuration whose plan needs "
                             "more (a station's tunings on one GPU together). CUDA's own context (~0.6 GB) "
                             "comes on top. "
                             "null: no limit (the pool keeps what it frees, up to the whole card)."),
    "watch": Key(Section({
        "targets": Key(WatchTargets(), REQUIRED,
                       doc="The watched directions: catalogue names (CygA, CasA, TauA, VirA), bodies (sun, moon, "
                           "jupiter, ...), or mappings {name, ra_deg, dec_deg} / {name, body} with an optional "
                           "window (`start`, `stop`) and `offsets_deg`."),
        "products": Key(Products(), ["I"], doc="The products recorded per target and channel."),
        "png_every_s": Key(Float(0.0, lo_open=True), 60.0,
                           doc="Seconds of data between rewrites of each target's dynamic-spectrum PNG."),
        "ring_s": Key(Float(0.0, lo_open=True), 2.0,
                      doc="Seconds of band-averaged images before a trigger that a triggered save holds."),
        "save_after_s": Key(Float(0.0), 1.0, doc="Seconds of images after a trigger that its save holds."),
        "hold_off_s": Key(Float(0.0), 10.0,
                          doc="Seconds after a saved trigger during which further triggers are counted, not saved."),
        "trigger_sigma": Key(Float(0.0, lo_open=True), None,
                             doc="A target whose band-mean light curve rises this many robust sigma above its "
                                 "last ring_s triggers a save; null: light curves do not trigger."),
        "trigger_dir": Key(Str(r"\S.*", "a directory path"), None,
                           doc="A folder watched for trigger files: each new file triggers a save (its first "
                               "line is the reason) and is moved to <trigger_dir>/done; null: none."),
        "webhook": Key(Str(r"https?://\S+", "an http(s) URL"), None,
                       doc="URL each trigger is posted to as JSON (retried with back-off, never holding the "
                           "pipeline); null: none."),
    }, what="a watch mapping {targets, products, png_every_s, ring_s, save_after_s, hold_off_s, trigger_sigma, "
            "trigger_dir, webhook}",
        doc="A second DFT imager images the targets' directions at every image the imager makes; their "
            "spectra go to <output.dir>/<prefix>_watch.h5, and search candidates, light curves and trigger "
            "files save snippets of the band-averaged images and send alerts (a webhook, VOEvent files) "
            "(guide/watch.md)."), None,
        doc="Spectra of named directions at every image, in an HDF5 file; null: off."),
    "service": Key(Section({
        "listen": Key(Str(r"\S+", "HOST:PORT"), "127.0.0.1:8080",
                      doc="Where the service listens (`bf-epic run --serve HOST:PORT` sets it): /metrics "
                          "(Prometheus), /health (JSON), / (a status page), POST /trigger (with the token)."),
        "allow_remote": Key(Bool(), False,
                            doc="Allow an address other than this machine's loopback (put it behind the "
                                "station's firewall)."),
        "token": Key(Str(r"\S{16,}", "a token of at least 16 characters"), None,
                     doc="The token a request that changes state (POST /trigger) must carry as "
                         "`Authorization: Bearer TOKEN`; null: the variable `token_env` names, else none "
                         "(such requests are refused)."),
        "token_env": Key(Str(r"[A-Za-z_][A-Za-z0-9_]*", "an environment variable name"), "BF_EPIC_SERVICE_TOKEN",
                         doc="The environment variable holding the token when `token` is null."),
        "no_data_s": Key(Float(0.0, lo_open=True), 10.0,
                         doc="Seconds without new data at the source before /health says down."),
        "min_free_gb": Key(Float(0.0), 5.0,
                           doc="Free disk in the output folder under which /health says degraded (under half "
                               "of it: down)."),
        "behind": Key(Float(0.0), 1.0,
                      doc="A live source's real-time factor over the last minute under which /health says "
                          "degraded (behind real time); 0 never. Lower it only for streams sent slower than "
                          "real time on purpose (a replayed test stream)."),
        "lost_window_s": Key(Float(0.0, lo_open=True), 600.0,
                             doc="Data lost at the source (missing or late frames, overflowed samples, kernel "
                                 "drops) within the last this many seconds makes /health say degraded; the "
                                 "totals since the start stay in /metrics."),
    }, what="a service mapping {listen, allow_remote, token, token_env, no_data_s, min_free_gb, behind, "
            "lost_window_s}",
        doc="The run's metrics and health over HTTP (guide/service.md)."), None,
        doc="Serve metrics and health while the pipeline runs; null: no service."),
    "output": Key(Section({
        "dir": Key(Str(r"\S.*", "a directory path"), None,
                   doc="Directory of the outputs, relative to the working directory; null: `output/<name>`."),
        "fits": Key(Bool(), True, doc="Write each grid image as a FITS cube."),
        "png": Key(Bool(), True, doc="Write a quicklook PNG of each image."),
        "table": Key(Bool(), False,
                     doc="Write each image as a FITS table of pixels too (a tracked patch always is)."),
        "prefix": Key(Str(r"[^/\\\s]+", "a file-name prefix without spaces or slashes"), None,
                      doc="Start of every output file's name; null: `name`."),
        "integrate": Key(OUTPUT_INTEGRATE, None,
                         doc="FITS and PNG of longer images than the imager's (a cube and the search still see "
                             "every image); null: each image as the imager makes it."),
        "cube": Key(OUTPUT_CUBE, None, doc="HDF5 image cubes with a time axis; null: none."),
        "oims": Key(OUTPUT_OIMS, None,
                    doc="The station's image database (Orville's OIMS files, one an hour, for its archive, "
                        "OIMS2fits and LWATV tools; guide/service.md); null: none."),
        "keep_gb": Key(Float(0.0, lo_open=True), None,
                       doc="Keep `dir` within this many GB while the run goes: the oldest files go first, never "
                           "one being written (guide/service.md); null: no limit."),
        "keep_days": Key(Float(0.0, lo_open=True), None,
                         doc="Delete files in `dir` older than this many days while the run goes; null: none."),
    }, what="an output mapping"), {}, doc="What is written, and where."),
}, what="a pipeline mapping",
    doc="Numbers such as `1e-3` are read as numbers, although YAML 1.1 (PyYAML) reads them as strings.")


def schema_entries() -> list[tuple[str, Key]]:
    """Every ``(dotted path, Key)`` of the schema, as the YAML reference lists them: the keys of every
    ``source.kind`` (``source.path`` once per kind that takes it) and of list items (``station.flags[].pol``)."""
    out = []

    def walk(keys, prefix):
        for k, spec in keys.items():
            p = join_path(prefix, k)
            out.append((p, spec))
            sub = spec.check
            if isinstance(sub, SourceSection):
                walk(SOURCE_COMMON, p)
                for kind_keys in SOURCE_KINDS.values():
                    walk(kind_keys, p)
            elif isinstance(sub, Section):
                walk(sub.keys, p)
            elif isinstance(getattr(sub, "entry", None), Section):  # SourceList, FlagList, WatchTargets
                walk(sub.entry.keys, p + "[]")
            elif isinstance(getattr(sub, "item", None), Section):   # ListOf a mapping
                walk(sub.item.keys, p + "[]")
    walk(SCHEMA.keys, "")
    return out


def schema_keys() -> list[str]:
    """Every dotted key path the schema knows, each once (``station.flags[].pol`` for list items)."""
    return list(dict.fromkeys(p for p, _ in schema_entries()))


# ---------------------------------------------------------------------------------------------
# Public functions
# ---------------------------------------------------------------------------------------------
def parse_device(device) -> tuple[str, int | None]:
    """'cpu' -> ('cpu', None); 'gpu' -> ('gpu', 0); 'gpu:N' -> ('gpu', N). ValueError otherwise."""
    if isinstance(device, str):
        s = device.strip().lower()
        if s == "cpu":
            return "cpu", None
        if s == "gpu":
            return "gpu", 0
        m = re.fullmatch(r"gpu:(\d+)", s)
        if m:
            return "gpu", int(m.group(1))
    raise ValueError(f"device must be 'cpu', 'gpu' or 'gpu:N' with N >= 0 the GPU index, got {device!r}")


def apply_overrides(raw: dict, overrides: Iterable[str]) -> list[str]:
    """Apply ``key.path=value`` overrides to the raw (unvalidated) mapping in place.

    Values are parsed with ``yaml.safe_load`` (``64`` is an int, ``[I, V]`` a list, ``null`` None).
    Intermediate mappings are created as needed; list elements cannot be addressed (replace the
    whole list: ``station.flags=[{stand: 3}]``). Returns the list of problems (empty if none).
    """
    problems = []
    for ov in overrides:
        if not isinstance(ov, str) or "=" not in ov:
            problems.append(f"--set {ov!r}: expected key.path=value")
            continue
        key, _, text = ov.partition("=")
        parts = key.strip().split(".")
        if not all(p.strip() for p in parts):
            problems.append(f"--set {ov!r}: {key!r} is not a dotted key path like imager.grid.size")
            continue
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError as e:
            problems.append(f"--set {ov!r}: the value is not valid YAML ({e})")
            continue
        node = raw
        for i, p in enumerate(parts[:-1]):
            nxt = node.get(p)
            if nxt is None:
                nxt = node[p] = {}
            if not isinstance(nxt, dict):
                problems.append(f"--set {ov!r}: {'.'.join(parts[:i + 1])} is {nxt!r}, not a mapping")
                break
            node = nxt
        else:
            node[parts[-1]] = value
    return problems


def _looks_like_path(x) -> bool:
    if isinstance(x, os.PathLike):
        return True
    if not isinstance(x, str) or "\n" in x:
        return False
    return x.strip().lower().endswith((".yaml", ".yml")) or os.path.isfile(x)


def load_config(path_or_text, overrides: Iterable[str] = (), *, base_dir=None) -> dict:
    """Read, override, validate and default-fill a pipeline config.

    Parameters
    ----------
    path_or_text : a path (str ending in .yaml/.yml, an existing file, or os.PathLike) or YAML text.
    overrides : ``"dotted.key=value"`` strings (the CLI's ``--set``), applied before validation.
    base_dir : directory for relative input paths; default the YAML file's directory, or the
        working directory for inline text.

    Returns the validated dict with every key of the schema present (see :data:`SCHEMA`).
    Raises :class:`ConfigError` listing every problem found, each prefixed by its key path and,
    where the key is written in the YAML (not set by an override), its line.
    """
    if _looks_like_path(path_or_text):
        path = Path(path_or_text)
        source = str(path)
        if not path.is_file():
            raise ConfigError([f"config file not found: {str(path)!r}"], source)
        text = path.read_text()
        default_name = path.stem
        base = Path(base_dir) if base_dir is not None else path.resolve().parent
    elif isinstance(path_or_text, str):
        source, text, default_name = "<text>", path_or_text, "pipeline"
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    else:
        raise TypeError(f"load_config expects a path or YAML text, got {type(path_or_text).__name__}")

    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ConfigError([f"not valid YAML: {e}"], source) from None
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError([f"the top level must be a mapping of keys (name, station, source, ...), "
                           f"got {type(raw).__name__}"], source)
    if isinstance(overrides, str):
        overrides = [overrides]
    keys = {ov.partition("=")[0].strip() for ov in overrides if isinstance(ov, str)}
    if "imager.tolerance" in keys and "imager.precision" not in keys and isinstance(raw.get("imager"), dict):
        # an accuracy target given on the command line replaces the file's mode; written beside a
        # precision in the same place, the precision restricts the choice (see _imager_post)
        raw["imager"].pop("precision", None)
    problems = apply_overrides(raw, overrides)
    if problems:
        raise ConfigError(problems, source)

    lines = key_lines(text)
    for ov in overrides:  # a value from --set has no line in the file, nor has anything below it
        key = ov.partition("=")[0].strip()
        lines = {p: n for p, n in lines.items() if p != key and not p.startswith((key + ".", key + "["))}
    ctx = Context(base, lines)
    station_raw = copy.deepcopy(raw) if isinstance(raw.get("tunings"), list) else None
    cfg = SCHEMA.check(raw, "", ctx)
    _fill_and_cross_check(cfg, default_name, ctx)
    if ctx.errors:
        raise ConfigError(ctx.errors, source)
    if cfg.get("tunings"):
        _expand_tunings(cfg, station_raw, lines, base, source)
    return cfg


def _check_fused(cfg, src, im, ctx):
    """imager.precision i8x1 / i8x2 / i8x3 (the direct route's fused integer modes) images what it can: 4-bit
    voltages reaching one GPU's DFT imager (no gains table, whose CalFoldBlock makes them complex; a
    quantised simulated sky), the pols' own powers (XX, YY, I, Q), whole 16-sample units per image."""
    if not (is_valid(im) and is_valid(im["precision"]) and im["precision"] in _FUSED):
        return
    p, why = im["precision"], []
    if is_valid(im["kind"]) and im["kind"] != "dft":
        why.append(f"imager.kind is {im['kind']!r} (the fused modes are the DFT imager's)")
    if is_valid(im["method"]) and im["method"] == "covariance":
        why.append("imager.method is 'covariance' (they are a direct-route kernel)")
    if is_valid(im["products"]) and needs_cross(im["products"]):
        why.append(f"imager.products {im['products']} need cross-pol terms (they image XX, YY, I, Q)")
    if is_valid(im["accumulate_frames"]) and im["accumulate_frames"] % 16:
        why.append(f"imager.accumulate_frames {im['accumulate_frames']} is not a multiple of 16 samples")
    cal = cfg["calibration"]
    if is_valid(cal) and is_valid(cal.get("gains_table")) and cal.get("gains_table"):
        why.append("calibration.gains_table turns the voltages complex (CalFoldBlock) before the imager")
    if is_valid(src) and src["kind"] == "simulated" and is_valid(src["quantize"]) and not src["quantize"]:
        why.append("source.quantize is false (complex voltages, not 4-bit integers)")
    if is_valid(cfg["device"]) and several_gpus(cfg["device"]) and resolved_split(cfg) != "pixels":
        why.append(f"device {cfg['device']!r} is several GPUs sharing the channels (measured on one only; "
                   "imager.split: pixels gives each GPU a whole imager)")
    if why:
        ctx.error("imager.precision", f"{p!r} images 4-bit voltages on one GPU's direct route; here "
                                      + "; ".join(why) + ": use fp16x3 or fp32, or imager.tolerance")


def _fill_and_cross_check(cfg: dict, default_name: str, ctx: Context) -> None:
    """Defaults that depend on other keys, and rules spanning sections (run on a valid tree)."""
    if cfg["name"] is None:
        cfg["name"] = re.sub(r"[^A-Za-z0-9_.-]+", "_", default_name) or "pipeline"
    out = cfg["output"]
    if is_valid(out) and is_valid(cfg["name"]):
        if out["dir"] is None:
            out["dir"] = f"output/{cfg['name']}"
        if out["prefix"] is None:
            out["prefix"] = cfg["name"]

    src, im = cfg["source"], cfg["imager"]
    st = cfg["station"]
    if is_valid(im) and is_valid(cfg["device"]) and is_valid(im["precision"]) and im["precision"] is not None \
            and cfg["device"] == "cpu" and _PRECISIONS[im["precision"]][2]:
        ctx.error("imager.precision", f"{im['precision']!r} needs tensor cores (device: gpu); on the CPU use "
                                      "fp32 or fp64, or imager.tolerance to let the imager pick")
    _check_fused(cfg, src, im, ctx)
    if is_valid(im) and is_valid(im["kind"]) and im["kind"] != "dft" and is_valid(im["tolerance"]) \
            and im["tolerance"] is not None:
        from ..imaging.plan import gridded_epsilon
        try:
            gridded_epsilon(im["tolerance"], im["kind"])
        except ValueError as e:
            ctx.error("imager.tolerance", str(e))
    if is_valid(im) and is_valid(src) and is_valid(cfg["calibration"]) and im.get("split") == "pixels":
        why = pixel_split_problems(cfg)
        if why:
            ctx.error("imager.split", "'pixels' cannot be used here: " + "; ".join(why) + "; use split: channels "
                                      "or auto")
    if is_valid(st) and is_valid(src) and st.get("name") == "auto" and src["kind"] != "tbf":
        ctx.error("station.name", "'auto' takes the station from a TBF file's frame id; with a "
                                  f"{src['kind']} source name the station (lwasv, lwana, lwa1)")
    if is_valid(src) and is_valid(im) and src["kind"] == "simulated" and is_valid(src["duration_s"]) \
            and is_valid(src["channels"]) and is_valid(src["channels"]["width_hz"]) \
            and is_valid(im["accumulate_frames"]):
        ch = src["channels"]
        nframe = src["duration_s"] * ch["width_hz"]  # one frame = one sample of 1 / width_hz s
        if im["accumulate_frames"] > nframe + 1e-9:
            ctx.error("imager.accumulate_frames",
                      f"{im['accumulate_frames']} frames ({im['accumulate_frames'] / ch['width_hz'] * 1e3:g} ms at "
                      f"{ch['width_hz']:g} Hz channels) is longer than source.duration_s = {src['duration_s']:g} s "
                      f"({int(nframe + 1e-9)} frames): no image would be produced")
    sv = cfg.get("service")
    if is_valid(sv) and sv is not None and is_valid(sv.get("listen")):
        from ..service.server import parse_listen
        try:
            parse_listen(sv["listen"])
        except ValueError as e:
            ctx.error("service.listen", str(e).removeprefix("service.listen: "))
    search = im.get("search") if is_valid(im) else None
    if is_valid(search) and search is not None:
        if is_valid(search["product"]) and search["product"] is not None and is_valid(im["products"]) \
                and search["product"] not in im["products"]:
            ctx.error("imager.search.product", f"{search['product']!r} is not one of imager.products {im['products']}")
        if is_valid(src) and src["kind"] == "simulated" and is_valid(src["duration_s"]) and is_valid(search["window_s"]) \
                and search["window_s"] >= src["duration_s"]:
            ctx.error("imager.search.window_s", f"{search['window_s']:g} s is not shorter than source.duration_s = "
                                                f"{src['duration_s']:g} s: the window would never fill, nothing would be searched")
    if is_valid(im) and is_valid(im["track"]) and im["track"] is not None and is_valid(im["track"]["source"]):
        known = set(CATALOGUE_SOURCES)
        if is_valid(src) and src["kind"] == "simulated" and is_valid(src["sources"]):
            known |= {s["name"] for s in src["sources"] if isinstance(s, dict) and is_valid(s["name"])}
        name = im["track"]["source"]
        if name not in known:
            close = did_you_mean(name, sorted(known))
            hint = f"; did you mean {close!r}?" if close else ""
            ctx.error("imager.track.source", f"unknown source {name!r}{hint} (known: {', '.join(sorted(known))})")
