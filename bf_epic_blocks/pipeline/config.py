"""Pipeline configuration: a YAML file, validated completely before anything runs.

:func:`load_config` reads a YAML pipeline (``yaml.safe_load`` only), applies ``--set key=value``
overrides, checks every key against the schema below, fills the defaults and returns a plain dict.
Every problem found is reported at once in one :class:`ConfigError`, one line per problem, each
starting with the dotted path of the key (``imager.grid.size: expected an integer >= 2, got 'abc'``).
Unknown keys are errors and come with the closest valid key as a suggestion.

Schema (``(default ...)`` marks optional keys; keys without a default are required)::

    name: str                        (default: the YAML file's stem, or 'pipeline' for inline text)
    station:                         exactly one of name / ssmif (default name: lwasv)
      name: lwasv | lwana | lwa1
      ssmif: path to an SSMIF file   (must exist)
      flags: list of {stand: int >= 1, pol: X | Y | both (default both)}, or bare stand numbers
                                     (default [])
    source:
      kind: simulated | tbf          (required)
      # kind: simulated
      start: ISO UTC time string     (default '2024-01-01T06:00:00'; checked with astropy Time)
      duration_s: float > 0          (default 2.0)
      channels:
        first: int >= 1              (default 2960 -> 74.0 MHz at 25 kHz; frequency = first * width_hz)
        count: int >= 1              (default 16)
        width_hz: float > 0          (default 25000.0)
      sources: list of catalogue names (CygA, CasA, TauA, VirA) or
               {name: str, ra_deg: float in [0, 360), dec_deg: float in [-90, 90], flux_jy: float >= 0,
                spectral_index: float (optional), ref_freq_hz: float > 0 (optional)}
                                     (as bf_epic_blocks.sky.resolve_source takes them)
                                     (default [CygA, CasA, TauA, VirA])
      noise_power: float >= 0        (default 1000.0)
      seed: int                      (default 1)
      quantize: bool                 (default true)
      transients: list of dispersed bursts {ra_deg, dec_deg, start_s: float >= 0 (s after start, at the
               band's highest channel), duration_s: float > 0, flux_jy: float >= 0, dm: float >= 0
               (default 0), name: str (optional)}   (default [])
      # kind: tbf
      path: path to a TBF file       (required, must exist)
      # either kind
      gulp_nframe: int >= 1          (default 1024; frames (time samples) per ring gulp)
    calibration:
      cable: bool                    (default true)
      gains_table: path to a .npz / .yaml / .yml table (default null = none; must exist)
      pattern: none | dipole         (default dipole)
    imager:
      kind: dft | wstack | moff      (default dft)
      grid:                          all-sky grid; exactly one of grid / track (default: grid)
        size: int >= 2               (default 64)
        cell: float > 0              (default null = 2 / size, the whole sky)
      track:                         a small patch that follows a source (dft imager only)
        source: a catalogue name or the name of an entry of source.sources (required)
        size: int >= 2               (default 16)
        fov_deg: float in (0, 180]   (default 10.0)
        update_s: float > 0          (default 10.0; how often the patch centre is recomputed)
      accumulate_frames: int >= 1    (default 1024; frames (time samples) per image)
      products: list of XX YY XY YX XYi YXi I Q U V, or a preset stokes | linear | full
                                     (default [I]; returned as the resolved list of names)
      remove_autocorr: bool          (default false)
      method: auto | direct | covariance (default auto)
      precision: fp32 | fp64         (default fp32)
      epsilon: float in (0, 0.1]     (default 1e-4; accuracy target of wstack / moff)
      search:                        transient search on the images (default null = none)
        threshold: float > 0         (default 6.0; S/N)
        window_s: float > 0          (default 1.0; sliding mean/variance window)
        dms: list of float >= 0      (default [0.0]; trial DMs, pc cm^-3)
        widths: list of int >= 1     (default [1, 2, 4, 8]; boxcar widths in images)
        average_channels: bool       (default true; dedisperse and average, else per channel)
        product: str                 (default null = the first product)
        table: ecsv | fits           (default ecsv; <prefix>_candidates.<table> in output.dir)
        png: bool                    (default true; sky with the candidates and their light curves)
    device: cpu | gpu | 'gpu:N'      (default cpu; returned as 'cpu' or 'gpu:N', 'gpu' = 'gpu:0')
    output:
      dir: path                      (default 'output/<name>'; relative to the working directory)
      fits: bool                     (default true)
      png: bool                      (default true)
      table: bool                    (default false)
      prefix: str                    (default: name)
      cube:                          HDF5 image cubes with a time axis (default null = none)
        dtype: float32 | float16     (default float32)
        average_channels: bool       (default false)
        images_per_file: int >= 1    (default null = one file per sequence)

Numbers: ``1e-3`` is accepted for a float although YAML 1.1 (PyYAML) reads it as a string.
Paths of input files (``station.ssmif``, ``source.path``, ``calibration.gains_table``) are resolved
against the YAML file's directory (the working directory for inline text) and returned absolute.
A key set to ``null`` takes its default; ``imager.grid: null`` removes a grid given in the file, so
``--set imager.grid=null --set imager.track.source=CygA`` switches a pipeline to tracking.

Cross-checks: the products must be possible with the station's two polarisations (X, Y); with a
simulated source, ``accumulate_frames`` must fit in ``duration_s`` (one frame = 1 / width_hz s) or
no image would ever be produced; a tracked source must be one the pipeline knows.
"""
from __future__ import annotations

import copy
import datetime as _dt
import difflib
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import yaml

from ..imaging.products import PRESETS, VALID as VALID_PRODUCTS, resolve_products

__all__ = ["ConfigError", "load_config", "apply_overrides", "parse_device", "schema_keys",
           "STATIONS", "CATALOGUE_SOURCES", "DEFAULT_START", "NPOL"]

STATIONS = ("lwasv", "lwana", "lwa1")
#: Source names the simulated sky and the tracker know without coordinates.
CATALOGUE_SOURCES = ("CygA", "CasA", "TauA", "VirA")
DEFAULT_START = "2024-01-01T06:00:00"
#: LWA stations have two linear polarisations (X = N-S, Y = E-W); products are checked against it.
NPOL = 2


class ConfigError(ValueError):
    """An invalid pipeline configuration.

    ``problems`` is the list of ``"dotted.path: what is wrong"`` strings; ``source`` names the file
    (or ``'<text>'``). ``str(err)`` lists every problem, one per line.
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
# Leaf checks. Each is a callable (value, ctx) -> normalised value that raises _Bad(message);
# ``describe`` is the short type text used in messages.
# ---------------------------------------------------------------------------------------------
class _Bad(Exception):
    pass


class _Ctx:
    """What checks need besides the value: where relative paths start, and the error list."""

    def __init__(self, base_dir: Path):
        self.base_dir = base_dir
        self.errors: list[str] = []

    def error(self, path: str, msg: str) -> None:
        self.errors.append(f"{path}: {msg}" if path else msg)


_INVALID = object()  # placeholder for a value that failed its check (cross-checks skip it)


def _fmt_num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


class Int:
    def __init__(self, min: int | None = None):
        self.min = min

    def describe(self) -> str:
        return "an integer" + (f" >= {self.min}" if self.min is not None else "")

    def __call__(self, v, ctx):
        if isinstance(v, bool) or not isinstance(v, int) or (self.min is not None and v < self.min):
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        return int(v)


class Float:
    """A finite real number in an interval; integers are accepted and converted."""

    def __init__(self, lo=None, hi=None, lo_open=False, hi_open=False):
        self.lo, self.hi, self.lo_open, self.hi_open = lo, hi, lo_open, hi_open

    def describe(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            return (f"a number in {'(' if self.lo_open else '['}{_fmt_num(lo)}, "
                    f"{_fmt_num(hi)}{')' if self.hi_open else ']'}")
        if lo is not None:
            return f"a number {'>' if self.lo_open else '>='} {_fmt_num(lo)}"
        if hi is not None:
            return f"a number {'<' if self.hi_open else '<='} {_fmt_num(hi)}"
        return "a number"

    # PyYAML follows YAML 1.1, where 1e-3 (no dot) is a string; accept such plain numerals.
    _NUMERAL = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")

    def __call__(self, v, ctx):
        if isinstance(v, str) and self._NUMERAL.fullmatch(v.strip()):
            v = float(v)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        x = float(v)
        ok = x == x and abs(x) != float("inf")
        if ok and self.lo is not None:
            ok = x > self.lo if self.lo_open else x >= self.lo
        if ok and self.hi is not None:
            ok = x < self.hi if self.hi_open else x <= self.hi
        if not ok:
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        return x


class Bool:
    def describe(self) -> str:
        return "true or false"

    def __call__(self, v, ctx):
        if not isinstance(v, bool):
            raise _Bad(f"expected true or false, got {v!r}")
        return v


class Str:
    def __init__(self, pattern: str | None = None, what: str = "a string"):
        self.pattern, self.what = pattern, what

    def describe(self) -> str:
        return self.what

    def __call__(self, v, ctx):
        if not isinstance(v, str) or (self.pattern and not re.fullmatch(self.pattern, v)):
            raise _Bad(f"expected {self.what}, got {v!r}")
        return v


class Choice:
    def __init__(self, *options: str, none_is: str | None = None):
        self.options = options
        self.none_is = none_is  # YAML ``none`` is a string, ``null`` is None: accept both when asked

    def describe(self) -> str:
        return "one of " + ", ".join(repr(o) for o in self.options)

    def __call__(self, v, ctx):
        if v is None and self.none_is is not None:
            return self.none_is
        if not isinstance(v, str) or v not in self.options:
            hint = ""
            if isinstance(v, str):
                close = difflib.get_close_matches(v, self.options, n=1, cutoff=0.5) or [
                    o for o in self.options if o.lower() == v.lower()]
                if close:
                    hint = f" (did you mean {close[0]!r}?)"
            raise _Bad(f"expected {self.describe()}, got {v!r}{hint}")
        return v


class File:
    """An existing file; relative paths are resolved against the YAML file's directory."""

    def __init__(self, what: str, suffixes: tuple[str, ...] = ()):
        self.what, self.suffixes = what, suffixes

    def describe(self) -> str:
        return f"the path of {self.what}"

    def __call__(self, v, ctx):
        if isinstance(v, Path):
            v = str(v)
        if not isinstance(v, str) or not v.strip():
            raise _Bad(f"expected {self.describe()} (a string), got {v!r}")
        p = Path(os.path.expanduser(v))
        if not p.is_absolute():
            p = ctx.base_dir / p
        if self.suffixes and p.suffix.lower() not in self.suffixes:
            raise _Bad(f"{self.what} must end in {' or '.join(self.suffixes)}, got {v!r}")
        if not p.exists():
            raise _Bad(f"{self.what} {v!r} not found (looked for {p})")
        if not p.is_file():
            raise _Bad(f"{self.what} {v!r} is not a regular file ({p})")
        return str(p.resolve())


class TimeStr:
    """An ISO UTC time; YAML's own timestamps (unquoted) are accepted too. Returns astropy isot."""

    def describe(self) -> str:
        return "an ISO UTC time string like '2024-01-01T06:00:00'"

    def __call__(self, v, ctx):
        if isinstance(v, _dt.datetime):
            if v.tzinfo is not None:  # YAML timestamps with an offset: convert to naive UTC
                v = v.astimezone(_dt.timezone.utc).replace(tzinfo=None)
            v = v.isoformat()
        elif isinstance(v, _dt.date):
            v = v.isoformat()
        if not isinstance(v, str):
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        from astropy.time import Time
        try:
            t = Time(v.strip().rstrip("Z"), scale="utc")
            if t.format not in ("isot", "iso", "fits"):
                raise ValueError(f"parsed as format {t.format!r}, not an ISO date-time")
        except Exception as e:  # astropy raises ValueError and others for unparseable strings
            why = str(e).splitlines()[0][:120] if str(e).strip() else type(e).__name__
            if "did not match any of the formats" in why:
                why = "not a recognised date-time"
            raise _Bad(f"expected {self.describe()}, got {v!r} ({why})") from None
        iso = t.isot
        return iso[:-4] if iso.endswith(".000") else iso


class Device:
    def describe(self) -> str:
        return "'cpu', 'gpu' or 'gpu:N' (N >= 0 the GPU index)"

    def __call__(self, v, ctx):
        try:
            kind, idx = parse_device(v)
        except ValueError:
            raise _Bad(f"expected {self.describe()}, got {v!r}") from None
        return "cpu" if kind == "cpu" else f"gpu:{idx}"


class Products:
    def describe(self) -> str:
        return f"a list of {', '.join(VALID_PRODUCTS)} or a preset ({', '.join(PRESETS)})"

    def __call__(self, v, ctx):
        if not isinstance(v, (str, list)):
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        if isinstance(v, list) and not all(isinstance(p, str) for p in v):
            raise _Bad(f"expected {self.describe()}, got {v!r}")
        try:
            names = resolve_products(NPOL, v)
        except ValueError as e:
            raise _Bad(str(e)) from None
        if len(set(names)) != len(names):
            raise _Bad(f"products repeat a name: {list(names)}")
        return list(names)


class ListOf:
    def __init__(self, item: Callable, what: str):
        self.item, self.what = item, what

    def describe(self) -> str:
        return f"a list of {self.what}"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return _INVALID
        return [_run(self.item, x, f"{path}[{i}]", ctx) for i, x in enumerate(v)]


def _run(check, value, path, ctx):
    """Apply a leaf check or a structured check, recording errors under ``path``."""
    if hasattr(check, "check"):
        return check.check(value, path, ctx)
    try:
        return check(value, ctx)
    except _Bad as e:
        ctx.error(path, str(e))
        return _INVALID


# ---------------------------------------------------------------------------------------------
# Sections: the declarative schema. Key(check, default); REQUIRED marks keys without a default.
# ---------------------------------------------------------------------------------------------
REQUIRED = object()


@dataclass(frozen=True)
class Key:
    check: Any
    default: Any = None  # None = optional, returned as None when absent
    doc: str = ""


class Section:
    """A mapping with a fixed set of keys. ``post(out, given, path, ctx)`` adds cross-key rules."""

    def __init__(self, keys: Mapping[str, Key], post: Callable | None = None, what: str = "a mapping"):
        self.keys = dict(keys)
        self.post = post
        self.what = what

    def describe(self) -> str:
        return self.what

    def check(self, v, path, ctx, *, allowed: Mapping[str, Key] | None = None,
              elsewhere: Mapping[str, str] | None = None):
        keys = self.keys if allowed is None else allowed
        if v is None:
            v = {}
        if not isinstance(v, dict):
            ctx.error(path, f"expected {self.what} with keys {', '.join(keys)}, got {v!r}")
            return _INVALID
        out = {}
        for k in v:
            if k in keys:
                continue
            where = _join(path, str(k))
            if elsewhere and k in elsewhere:
                ctx.error(where, elsewhere[k])
                continue
            close = difflib.get_close_matches(str(k), list(keys), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            ctx.error(where, f"unknown key{hint} (valid keys here: {', '.join(keys)})")
        given = {k for k in keys if v.get(k) is not None}
        for k, spec in keys.items():
            where = _join(path, k)
            if k in given:
                out[k] = _run(spec.check, v[k], where, ctx)
            elif spec.default is REQUIRED:
                ctx.error(where, f"missing required key ({spec.check.describe()})")
                out[k] = _INVALID
            elif isinstance(spec.check, Section) and spec.default is not None:
                out[k] = spec.check.check({}, where, ctx)  # fill a sub-section's defaults
            else:
                out[k] = copy.deepcopy(spec.default)
        if self.post is not None:
            self.post(out, given, path, ctx)
        return out


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


class SourceList:
    """source.sources: catalogue names or {name, ra_deg, dec_deg, flux_jy} mappings."""

    entry = Section({
        "name": Key(Str(r"\S+", "a name without spaces"), REQUIRED),
        "ra_deg": Key(Float(0.0, 360.0, hi_open=True), REQUIRED),
        "dec_deg": Key(Float(-90.0, 90.0), REQUIRED),
        "flux_jy": Key(Float(0.0), REQUIRED),
        "spectral_index": Key(Float(), None),
        "ref_freq_hz": Key(Float(0.0, lo_open=True), None),
    }, what="a source mapping")

    def describe(self) -> str:
        return f"a list of source names ({', '.join(CATALOGUE_SOURCES)}) or {{name, ra_deg, dec_deg, flux_jy}}"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return _INVALID
        out = []
        for i, x in enumerate(v):
            where = f"{path}[{i}]"
            if isinstance(x, str):
                if x not in CATALOGUE_SOURCES:
                    close = difflib.get_close_matches(x, CATALOGUE_SOURCES, n=1, cutoff=0.5) or [
                        s for s in CATALOGUE_SOURCES if s.lower() == x.lower()]
                    hint = f" (did you mean {close[0]!r}?)" if close else ""
                    ctx.error(where, f"unknown source {x!r}{hint}; catalogue names are "
                                     f"{', '.join(CATALOGUE_SOURCES)}, or give {{name, ra_deg, dec_deg, flux_jy}}")
                    out.append(_INVALID)
                else:
                    out.append(x)
            elif isinstance(x, dict):
                e = self.entry.check(x, where, ctx)
                if e is not _INVALID:  # absent optional keys stay absent (pipeline.sky has defaults)
                    e = {k: v for k, v in e.items() if v is not None}
                out.append(e)
            else:
                ctx.error(where, f"expected a source name or {{name, ra_deg, dec_deg, flux_jy}}, got {x!r}")
                out.append(_INVALID)
        names = [s if isinstance(s, str) else s["name"] for s in out
                 if s is not _INVALID and (isinstance(s, str) or s["name"] is not _INVALID)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            ctx.error(path, f"source names must be unique; repeated: {', '.join(dup)}")
        return out


class FlagList:
    entry = Section({
        "stand": Key(Int(1), REQUIRED),
        "pol": Key(Choice("X", "Y", "both"), "both"),
    }, what="a flag mapping {stand, pol}")

    def describe(self) -> str:
        return "a list of {stand: int, pol: X|Y|both} or stand numbers"

    def check(self, v, path, ctx):
        if not isinstance(v, list):
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return _INVALID
        out = []
        for i, x in enumerate(v):
            if isinstance(x, int) and not isinstance(x, bool):
                x = {"stand": x}
            out.append(self.entry.check(x, f"{path}[{i}]", ctx))
        return out


def _station_post(out, given, path, ctx):
    if "name" in given and "ssmif" in given:
        ctx.error(path, "give either station.name or station.ssmif, not both")
    elif "name" not in given and "ssmif" not in given:
        out["name"] = "lwasv"


def _imager_post(out, given, path, ctx):
    if "grid" in given and "track" in given:
        ctx.error(path, "give exactly one of imager.grid (all-sky) or imager.track (a patch that "
                        "follows a source), not both; set the other to null to remove it")
        return
    if "track" in given:
        out["grid"] = None
        if out.get("kind") not in ("dft", _INVALID):
            ctx.error(_join(path, "track"), f"a tracked patch needs the dft imager (imager.kind is {out['kind']!r}); "
                                            "the FFT imagers (wstack, moff) make all-sky grids only")
    else:
        out["track"] = None
        if "grid" not in given:
            out["grid"] = IMAGER_GRID.check({}, _join(path, "grid"), ctx)


IMAGER_GRID = Section({
    "size": Key(Int(2), 64, "pixels per side"),
    "cell": Key(Float(0.0, lo_open=True), None, "step in l and m; null = 2 / size"),
}, what="a grid mapping {size, cell}")

IMAGER_TRACK = Section({
    "source": Key(Str(r"\S+", "a source name"), REQUIRED),
    "size": Key(Int(2), 16),
    "fov_deg": Key(Float(0.0, 180.0, lo_open=True), 10.0),
    "update_s": Key(Float(0.0, lo_open=True), 10.0),
}, what="a track mapping {source, size, fov_deg, update_s}")

TRANSIENT = Section({
    "name": Key(Str(r"\S+", "a name without spaces"), None),
    "ra_deg": Key(Float(0.0, 360.0, hi_open=True), REQUIRED),
    "dec_deg": Key(Float(-90.0, 90.0), REQUIRED),
    "start_s": Key(Float(0.0), REQUIRED),
    "duration_s": Key(Float(0.0, lo_open=True), REQUIRED),
    "flux_jy": Key(Float(0.0), REQUIRED),
    "dm": Key(Float(0.0), 0.0),
}, what="a burst mapping {ra_deg, dec_deg, start_s, duration_s, flux_jy, dm}")

IMAGER_SEARCH = Section({
    "threshold": Key(Float(0.0, lo_open=True), 6.0),
    "window_s": Key(Float(0.0, lo_open=True), 1.0),
    "dms": Key(ListOf(Float(0.0), "DMs >= 0"), [0.0]),
    "widths": Key(ListOf(Int(1), "integers >= 1"), [1, 2, 4, 8]),
    "average_channels": Key(Bool(), True),
    "product": Key(Str(r"\S+", "a product name"), None),
    "table": Key(Choice("ecsv", "fits"), "ecsv"),
    "png": Key(Bool(), True),
}, what="a search mapping {threshold, window_s, dms, widths, ...}")

OUTPUT_CUBE = Section({
    "dtype": Key(Choice("float32", "float16"), "float32"),
    "average_channels": Key(Bool(), False),
    "images_per_file": Key(Int(1), None),
}, what="a cube mapping {dtype, average_channels, images_per_file}")

SOURCE_COMMON = {"kind": Key(Choice("simulated", "tbf"), REQUIRED),
                 "gulp_nframe": Key(Int(1), 1024)}
SOURCE_SIMULATED = {
    "start": Key(TimeStr(), DEFAULT_START),
    "duration_s": Key(Float(0.0, lo_open=True), 2.0),
    "channels": Key(Section({
        "first": Key(Int(1), 2960),
        "count": Key(Int(1), 16),
        "width_hz": Key(Float(0.0, lo_open=True), 25000.0),
    }, what="a channels mapping {first, count, width_hz}"), {}),
    "sources": Key(SourceList(), list(CATALOGUE_SOURCES)),
    "noise_power": Key(Float(0.0), 1000.0),
    "seed": Key(Int(), 1),
    "quantize": Key(Bool(), True),
    "transients": Key(ListOf(TRANSIENT, "burst mappings"), []),
}
SOURCE_TBF = {
    "path": Key(File("TBF file"), REQUIRED),
}


class SourceSection(Section):
    """source: the keys allowed depend on source.kind."""

    def __init__(self):
        super().__init__({**SOURCE_COMMON, **SOURCE_SIMULATED, **SOURCE_TBF}, what="a source mapping")

    def check(self, v, path, ctx, **_):
        if v is None:
            v = {}
        if not isinstance(v, dict):
            ctx.error(path, f"expected a source mapping with at least 'kind', got {v!r}")
            return _INVALID
        kind = _run(SOURCE_COMMON["kind"].check, v["kind"], _join(path, "kind"), ctx) if v.get("kind") is not None else None
        if kind is None:
            ctx.error(_join(path, "kind"), "missing required key (one of 'simulated', 'tbf')")
            return _INVALID
        if kind is _INVALID:
            return _INVALID
        mine, other, other_kind = ((SOURCE_SIMULATED, SOURCE_TBF, "tbf") if kind == "simulated"
                                   else (SOURCE_TBF, SOURCE_SIMULATED, "simulated"))
        elsewhere = {k: f"only used when source.kind is {other_kind!r} (kind is {kind!r})" for k in other}
        return super().check(v, path, ctx, allowed={**SOURCE_COMMON, **mine}, elsewhere=elsewhere)


SCHEMA = Section({
    "name": Key(Str(r"[^/\\\s]+", "a name without spaces or slashes"), None),
    "station": Key(Section({
        "name": Key(Choice(*STATIONS), None),
        "ssmif": Key(File("SSMIF file"), None),
        "flags": Key(FlagList(), []),
    }, post=_station_post, what="a station mapping"), {}),
    "source": Key(SourceSection(), REQUIRED),
    "calibration": Key(Section({
        "cable": Key(Bool(), True),
        "gains_table": Key(File("gains table", (".npz", ".yaml", ".yml")), None),
        "pattern": Key(Choice("none", "dipole", none_is="none"), "dipole"),
    }, what="a calibration mapping"), {}),
    "imager": Key(Section({
        "kind": Key(Choice("dft", "wstack", "moff"), "dft"),
        "grid": Key(IMAGER_GRID, None),
        "track": Key(IMAGER_TRACK, None),
        "accumulate_frames": Key(Int(1), 1024),
        "products": Key(Products(), ["I"]),
        "remove_autocorr": Key(Bool(), False),
        "method": Key(Choice("auto", "direct", "covariance"), "auto"),
        "precision": Key(Choice("fp32", "fp64"), "fp32"),
        "epsilon": Key(Float(0.0, 0.1, lo_open=True), 1e-4),
        "search": Key(IMAGER_SEARCH, None),
    }, post=_imager_post, what="an imager mapping"), {}),
    "device": Key(Device(), "cpu"),
    "output": Key(Section({
        "dir": Key(Str(r"\S.*", "a directory path"), None),
        "fits": Key(Bool(), True),
        "png": Key(Bool(), True),
        "table": Key(Bool(), False),
        "prefix": Key(Str(r"[^/\\\s]+", "a file-name prefix without spaces or slashes"), None),
        "cube": Key(OUTPUT_CUBE, None),
    }, what="an output mapping"), {}),
}, what="a pipeline mapping")


def schema_keys() -> list[str]:
    """Every dotted key path the schema knows (for docs and tests)."""
    out = []

    def walk(sec, prefix):
        for k, spec in sec.keys.items():
            p = _join(prefix, k)
            out.append(p)
            sub = spec.check
            if isinstance(sub, Section):
                walk(sub, p)
            elif isinstance(sub, (SourceList, FlagList)):
                walk(sub.entry, p)
    walk(SCHEMA, "")
    return out


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

    Returns the validated dict with every key of the schema present (see the module docstring).
    Raises :class:`ConfigError` listing every problem found, each prefixed by its key path.
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
    problems = apply_overrides(raw, overrides)
    if problems:
        raise ConfigError(problems, source)

    ctx = _Ctx(base)
    cfg = SCHEMA.check(raw, "", ctx)
    _fill_and_cross_check(cfg, default_name, ctx)
    if ctx.errors:
        raise ConfigError(ctx.errors, source)
    return cfg


def _fill_and_cross_check(cfg: dict, default_name: str, ctx: _Ctx) -> None:
    """Defaults that depend on other keys, and rules spanning sections (run on a valid tree)."""
    if cfg["name"] is None:
        cfg["name"] = re.sub(r"[^A-Za-z0-9_.-]+", "_", default_name) or "pipeline"
    out = cfg["output"]
    if _ok(out) and _ok(cfg["name"]):
        if out["dir"] is None:
            out["dir"] = f"output/{cfg['name']}"
        if out["prefix"] is None:
            out["prefix"] = cfg["name"]

    src, im = cfg["source"], cfg["imager"]
    if _ok(src) and _ok(im) and src["kind"] == "simulated" and _ok(src["duration_s"]) \
            and _ok(src["channels"]) and _ok(src["channels"]["width_hz"]) and _ok(im["accumulate_frames"]):
        ch = src["channels"]
        nframe = src["duration_s"] * ch["width_hz"]  # one frame = one sample of 1 / width_hz s
        if im["accumulate_frames"] > nframe + 1e-9:
            ctx.error("imager.accumulate_frames",
                      f"{im['accumulate_frames']} frames ({im['accumulate_frames'] / ch['width_hz'] * 1e3:g} ms at "
                      f"{ch['width_hz']:g} Hz channels) is longer than source.duration_s = {src['duration_s']:g} s "
                      f"({int(nframe + 1e-9)} frames): no image would be produced")
    search = im.get("search") if _ok(im) else None
    if _ok(search) and search is not None:
        if _ok(search["product"]) and search["product"] is not None and _ok(im["products"]) \
                and search["product"] not in im["products"]:
            ctx.error("imager.search.product", f"{search['product']!r} is not one of imager.products {im['products']}")
        if _ok(src) and src["kind"] == "simulated" and _ok(src["duration_s"]) and _ok(search["window_s"]) \
                and search["window_s"] >= src["duration_s"]:
            ctx.error("imager.search.window_s", f"{search['window_s']:g} s is not shorter than source.duration_s = "
                                                f"{src['duration_s']:g} s: the window would never fill, nothing would be searched")
    if _ok(im) and _ok(im["track"]) and im["track"] is not None and _ok(im["track"]["source"]):
        known = set(CATALOGUE_SOURCES)
        if _ok(src) and src["kind"] == "simulated" and _ok(src["sources"]):
            known |= {s["name"] for s in src["sources"] if isinstance(s, dict) and _ok(s["name"])}
        name = im["track"]["source"]
        if name not in known:
            close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            ctx.error("imager.track.source", f"unknown source {name!r}{hint} (known: {', '.join(sorted(known))})")


def _ok(v) -> bool:
    """False for a value (or section) that failed validation; cross-checks skip those."""
    return v is not _INVALID
