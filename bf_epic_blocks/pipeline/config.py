"""Pipeline configuration: a YAML file, validated completely before anything runs.

:func:`load_config` reads a YAML pipeline (``yaml.safe_load`` only), applies ``--set key=value``
overrides, checks every key against the schema below, fills the defaults and returns a plain dict.
Every problem found is reported at once in one :class:`ConfigError`, one line per problem, each
starting with the dotted path of the key and, where the key is written in the YAML, its line
(``imager.grid.size (line 23): expected an integer >= 2, got 'abc'``; values given with ``--set``
have no line). Unknown keys are errors and come with the closest valid key as a suggestion.
The generic checker (leaf checks, sections, did-you-mean, YAML line map) is :mod:`.yaml_schema`;
this module holds the pipeline's schema, its defaults and the cross-checks.

Schema (``(default ...)`` marks optional keys; keys without a default are required)::

    name: str                        (default: the YAML file's stem, or 'pipeline' for inline text)
    station:                         exactly one of name / ssmif (default name: lwasv)
      name: lwasv | lwana | lwa1 | auto (auto: the station the TBF file's frame id names, ADP -> lwasv,
                                     NDP -> lwana; TBF sources only; lets one YAML serve both in a batch)
      ssmif: path to an SSMIF file   (must exist)
      flags: list of {stand: int >= 1, pol: X | Y | both (default both)}, or bare stand numbers
                                     (default [])
    source:
      kind: simulated | tbf | tbx | file | udp (required; file = TBF or TBX, told by the frame id)
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
      refresh_s: float > 0           (default 1.0; seconds of data between recomputations of the
                                     sources' directions: the sky turns 0.004 deg a second, and a bright
                                     source's step at each recomputation is what a sensitive search sees)
      transients: list of dispersed bursts {ra_deg, dec_deg, start_s: float >= 0 (s after start, at the
               band's highest channel), duration_s: float > 0, flux_jy: float >= 0, dm: float >= 0
               (default 0), name: str (optional)}   (default [])
      # kind: tbf, tbx or file
      path: path to a TBF / TBX file (required, must exist)
      channel_block: int >= 0        (tbf only; default null = all channels; image only this block of the
                                     file's channels: the runs of evenly spaced channels that bf-epic run
                                     writes to separate FITS files, ``_r<index>``; ``bf-epic batch`` sets it)
      # kind: udp (live packets; the station is station.name / ssmif and must match the packets)
      address: IP address to listen on (default 127.0.0.1)
      port: int >= 0                 (required; 0 = an ephemeral port)
      format: tbf | tbx | chips | snap2  (default tbf; chips = the ADP F-engine's own stream (LWA-SV),
                                     snap2 = the NDP F-engine's (Bifrost's formats of those names))
      engine: auto | bifrost | python  (default auto: Bifrost's C packet capture where Bifrost is the
                                     runtime and decodes the format (chips, snap2), else the Python receiver)
      core: int >= 0                 (default null; the CPU core Bifrost's capture thread is bound to)
      sync_time: int >= 0            (chips only; default null = recovered from the arrival clock: the
                                     whole UNIX second the F-engine counts spectra from, its utc_start)
      buffer_s: float > 0            (default 0.05; reordering window, seconds of data)
      idle_timeout_s: float > 0      (default 2.0; no packet for this long ends the sequence)
      start_timeout_s: float > 0     (default null = wait for the first packet forever)
      rcvbuf_mb: float > 0           (default 64; socket receive buffer asked for, MiB)
      sequences: int >= 0            (default 1; streams to image before stopping, 0 = until stopped)
      # either kind
      gulp_nframe: int >= 1 | auto   (default auto; frames (time samples) per ring gulp. auto: 1024,
                                     but a capture file imaged on a GPU gets ~64 MiB of samples per
                                     gulp, 5,376 frames for 24 LWA-SV channels: see runner.gulp_frames)
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
      tolerance: float in (0, 1)     (default null; the accuracy knob: the largest relative error of an
                                     image against its float64 value, max |I - I_exact| / max I_exact.
                                     dft: the fastest route x precision whose measured error bound is
                                     <= tolerance on the device; null: precision (fp32) on the cheaper
                                     route. wstack / moff: the gridder's epsilon = tolerance / 4, in
                                     [4e-14, 0.4]; null: 4e-4 (epsilon 1e-4). One resolver decides
                                     (bf_epic_blocks.imaging.plan.resolve); --set imager.tolerance=...
                                     replaces the file's precision. The old key epsilon is an error
                                     naming this one)
      method: auto | direct | covariance (default auto; expert override of the dft imager's route)
      precision: fp32 | fp64 | tf32x3 | fp16x3 | tf32 | fp16 | bf16 | i8x2 | i8x3  (default fp32; expert
                                     override of the dft imager's GEMM precision; all but fp32 and fp64
                                     need a GPU (tensor-core modes, see bf_epic_blocks.imaging.gemm), and
                                     i8x2 / i8x3 4-bit voltages on one GPU's direct route; written beside
                                     a tolerance it restricts the choice)
      min_elevation_deg: float in [0, 90) (default 0; grid pixels below this elevation are not imaged)
      split: auto | channels | pixels (default auto; how several GPUs share the dft imager's work.
                                     channels: each GPU images some channels, the images meet on the
                                     host. pixels: each GPU reads or simulates the whole source, images
                                     every channel for its part of the grid and searches it; only the
                                     band-averaged images and the candidates meet (a grid, and a file
                                     or simulated source). auto: pixels where there is a search and
                                     pixels can be, else channels)
      search:                        transient search on the images (default null = none)
        threshold: float > 0         (default 6.0; S/N)
        window_s: float > 0          (default 1.0; sliding mean/variance window)
        dms: list of float >= 0      (default [0.0]; trial DMs, pc cm^-3)
        widths: list of int >= 1     (default [1, 2, 4, 8]; boxcar widths in images)
        average_channels: bool       (default true; dedisperse and average, else per channel)
        dedisperse: auto | shifts | tree (default auto: the tree from 64 channels; shifts: each DM of
                                     `dms` a sum of shifted channels; tree: the streaming FDMT over
                                     every sweep from 0 to max(dms)'s, one image apart)
        tree_precision: fp32 | fp16  (default fp32; what the tree stores: fp16 halves its memory traffic
                                     and rings; it rounds the fluctuations about each channel's first
                                     image, ~1e-3 of the sums' noise rms)
        product: str                 (default null = the first product)
        table: ecsv | fits           (default ecsv; <prefix>_candidates.<table> in output.dir)
        png: bool                    (default true; sky with the candidates and their light curves)
        max_pixels: int >= 1         (default 32; crossings kept per trial image, its brightest)
        sky_fraction: float in (0, 1] (default 0.1; more of the sky over the threshold at once is one
                                     'sky-wide' event: lightning, RFI, a flash)
        sidelobe_factor: float >= 0  (default 2.0; fold a candidate a brighter one explains through the
                                     array's beam; 0 keeps every candidate)
    device: cpu | gpu | 'gpu:N'      (default cpu; returned as 'cpu' or 'gpu:N', 'gpu' = 'gpu:0');
            on one GPU with static calibration (no gains_table) and a file or simulated source, the
            dft imager folds the cable terms into its operator and no CalFoldBlock runs;
            or several GPUs of the host: 'gpu:all' or a list [0, 1] (returned as 'gpu:all' / 'gpu:0,1'):
            the dft imager splits the work across them as imager.split says (no CalFoldBlock then:
            cable terms are folded into the operators; calibration.gains_table needs a single device)
    output:
      dir: path                      (default 'output/<name>'; relative to the working directory)
      fits: bool                     (default true)
      png: bool                      (default true)
      table: bool                    (default false)
      prefix: str                    (default: name)
      integrate:                     FITS / PNG of longer images than the imager's (default null = each
                                     image as the imager makes it)
        seconds: float > 0           (default 1.0; the mean of round(seconds / image length) images)
        average_channels: bool       (default true; one band-averaged image)
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

Why a hand-written checker, not pydantic v2 or jsonschema (prototypes of the imager and source
sections with pydantic 2.14 and jsonschema 4.26): pydantic gives dotted paths and every problem at
once, but no "did you mean" for unknown keys ("Extra inputs are not permitted"), tag-inserted paths
for kind-dependent sections (``source.simulated.durations``), one error per union branch (a bad
``source.sources[0]`` fails twice), messages without the allowed range ("Input should be a valid
integer" for ``size: abc``), a lax mode that takes ``'yes'`` for true while strict mode rejects
YAML 1.1's ``1e-3`` string, a model-wide rule (grid or track) silenced by any field error, and
``null`` is not "the default". Rewriting its errors into today's messages took 70 non-blank lines
of formatter and 15 of set-up besides 56 of models; here the same sections are 74 lines of schema on
a 144-line generic engine. The file, time, device, product and source-list checks, overrides,
defaults and cross-checks (about 280 lines) would stay as they are: a saving of about 80 of 640
non-blank lines, for a compiled dependency whose error types and locations the formatter must
track. jsonschema (34 lines for the same sections) fills no defaults, normalises nothing, puts an
unknown key's error on its parent, reports ``grid: {size: abc}`` as "{'size': 'abc'} is not valid
under any of the given schemas", prints the schema for the grid-or-track rule and accepts ``.nan``.
So the checker stays, split by concern. Lines (total / non-blank): before, config.py 760 / 639;
after, config.py 522 / 458 + yaml_schema.py 330 / 261 = 852 / 719 (new: YAML line map, this note).
"""
from __future__ import annotations

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
           "several_gpus", "schema_keys",
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
            return INVALID
        out = []
        for i, x in enumerate(v):
            where = f"{path}[{i}]"
            if isinstance(x, str):
                if x not in CATALOGUE_SOURCES:
                    close = did_you_mean(x, CATALOGUE_SOURCES)
                    hint = f" (did you mean {close!r}?)" if close else ""
                    ctx.error(where, f"unknown source {x!r}{hint}; catalogue names are "
                                     f"{', '.join(CATALOGUE_SOURCES)}, or give {{name, ra_deg, dec_deg, flux_jy}}")
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
        "stand": Key(Int(1), REQUIRED),
        "pol": Key(Choice("X", "Y", "both"), "both"),
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


def _station_post(out, given, path, ctx):
    if "name" in given and "ssmif" in given:
        ctx.error(path, "give either station.name or station.ssmif, not both")
    elif "name" not in given and "ssmif" not in given:
        out["name"] = "lwasv"


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
    "dedisperse": Key(Choice("auto", "shifts", "tree"), "auto"),
    "tree_precision": Key(Choice("fp32", "fp16"), "fp32"),
    "product": Key(Str(r"\S+", "a product name"), None),
    "table": Key(Choice("ecsv", "fits"), "ecsv"),
    "png": Key(Bool(), True),
    "max_pixels": Key(Int(1), 32),
    "sky_fraction": Key(Float(0.0, 1.0, lo_open=True), 0.1),
    "sidelobe_factor": Key(Float(0.0), 2.0),
}, what="a search mapping {threshold, window_s, dms, widths, ...}")

OUTPUT_INTEGRATE = Section({
    "seconds": Key(Float(0.0, lo_open=True), 1.0),
    "average_channels": Key(Bool(), True),
}, what="an integrate mapping {seconds, average_channels}")

OUTPUT_CUBE = Section({
    "dtype": Key(Choice("float32", "float16"), "float32"),
    "average_channels": Key(Bool(), False),
    "images_per_file": Key(Int(1), None),
}, what="a cube mapping {dtype, average_channels, images_per_file}")

SOURCE_COMMON = {"kind": Key(Choice("simulated", "tbf", "tbx", "file", "udp"), REQUIRED),
                 "gulp_nframe": Key(Int(1, auto=True), "auto")}
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
    "refresh_s": Key(Float(0.0, lo_open=True), 1.0),
    "transients": Key(ListOf(TRANSIENT, "burst mappings"), []),
}
SOURCE_TBF = {
    "path": Key(File("TBF file"), REQUIRED),
    "channel_block": Key(Int(0), None),
}
SOURCE_UDP = {  # live capture (bf_epic_blocks.io.udp); station from station.name / ssmif
    "address": Key(Str(r"\S+", "an IP address to listen on"), "127.0.0.1"),
    "port": Key(Int(0), REQUIRED),
    "format": Key(Choice("tbf", "tbx", "chips", "snap2"), "tbf"),
    "sync_time": Key(Int(0), None),
    "engine": Key(Choice("auto", "bifrost", "python"), "auto"),
    "core": Key(Int(0), None),
    "buffer_s": Key(Float(0.0, lo_open=True), 0.05),
    "idle_timeout_s": Key(Float(0.0, lo_open=True), 2.0),
    "start_timeout_s": Key(Float(0.0, lo_open=True), None),
    "rcvbuf_mb": Key(Float(0.0, lo_open=True), 64.0),
    "sequences": Key(Int(0), 1),
}
SOURCE_TBX = {"path": Key(File("TBX file"), REQUIRED)}
SOURCE_FILE = {"path": Key(File("TBF or TBX capture file"), REQUIRED)}
#: source.kind -> the keys it takes besides SOURCE_COMMON
SOURCE_KINDS = {"simulated": SOURCE_SIMULATED, "tbf": SOURCE_TBF, "tbx": SOURCE_TBX, "file": SOURCE_FILE,
                "udp": SOURCE_UDP}


class SourceSection(Section):
    """source: the keys allowed depend on source.kind."""

    def __init__(self):
        super().__init__({**SOURCE_COMMON, **SOURCE_SIMULATED, **SOURCE_TBF, **SOURCE_UDP}, what="a source mapping")

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
    "name": Key(Str(r"[^/\\\s]+", "a name without spaces or slashes"), None),
    "station": Key(Section({
        "name": Key(Choice(*STATIONS, "auto"), None),
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
        "precision": Key(Choice(*PRECISION_NAMES), "fp32"),
        "tolerance": Key(Float(0.0, 1.0, lo_open=True, hi_open=True), None),
        "min_elevation_deg": Key(Float(0.0, 90.0, hi_open=True), 0.0),
        "search": Key(IMAGER_SEARCH, None),
        "split": Key(Choice("auto", "channels", "pixels"), "auto"),
    }, post=_imager_post, what="an imager mapping", renamed={
        "epsilon": "epsilon is now imager.tolerance, the one accuracy knob (the largest relative image error; "
                   "for wstack / moff the gridder's epsilon = tolerance / 4): write tolerance: 4 x your epsilon"}),
        {}),
    "device": Key(Device(), "cpu"),
    "output": Key(Section({
        "dir": Key(Str(r"\S.*", "a directory path"), None),
        "fits": Key(Bool(), True),
        "png": Key(Bool(), True),
        "table": Key(Bool(), False),
        "prefix": Key(Str(r"[^/\\\s]+", "a file-name prefix without spaces or slashes"), None),
        "integrate": Key(OUTPUT_INTEGRATE, None),
        "cube": Key(OUTPUT_CUBE, None),
    }, what="an output mapping"), {}),
}, what="a pipeline mapping")


def schema_keys() -> list[str]:
    """Every dotted key path the schema knows (for docs and tests)."""
    out = []

    def walk(sec, prefix):
        for k, spec in sec.keys.items():
            p = join_path(prefix, k)
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
    cfg = SCHEMA.check(raw, "", ctx)
    _fill_and_cross_check(cfg, default_name, ctx)
    if ctx.errors:
        raise ConfigError(ctx.errors, source)
    return cfg


def _check_fused(cfg, src, im, ctx):
    """imager.precision i8x2 / i8x3 (the direct route's fused integer modes) images what it can: 4-bit
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
