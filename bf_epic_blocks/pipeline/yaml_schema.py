"""A small declarative checker for YAML configurations, with messages written for operators.

A schema is a tree of :class:`Section` objects whose :class:`Key` entries hold a check and a default.
Leaf checks are callables ``check(value, ctx) -> normalised value`` that raise :class:`BadValue` with
a sentence; structured checks (sections, lists) have ``check(value, path, ctx)`` and record their
own problems. Every problem is collected in a :class:`Context` under the key's dotted path
(``imager.grid.size``, ``station.flags[0].pol``), with the YAML line of that key when the text
gave it (:func:`key_lines`), so that one run reports everything at once. Unknown keys are errors
that name the closest valid key (:func:`did_you_mean`).

Every :class:`Key` and :class:`Section` carries its description in ``doc``; the pipeline YAML
reference (docs/reference/pipeline-yaml.md) is generated from those alone.

Nothing here knows the pipeline: its schema, defaults and cross-checks are in :mod:`.config`.

Why hand-written rather than pydantic or jsonschema: the operator's messages need the dotted path and
YAML line of every problem at once, a "did you mean" for unknown keys, the allowed range in each
message, key sets that depend on another key (``source.kind``), ``null`` meaning "the default", and
YAML 1.1's ``1e-3`` read as a number. pydantic gives the paths and every problem at once, but the
rest would take a formatter that rewrites its errors; jsonschema fills no
defaults, normalises nothing and puts an unknown key's error on its parent.
"""
from __future__ import annotations

import copy
import datetime as _dt
import difflib
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import yaml

__all__ = ["BadValue", "Context", "INVALID", "REQUIRED", "Key", "Section", "Int", "Float", "Bool", "Str",
           "Choice", "File", "TimeStr", "run_check", "join_path", "is_valid", "did_you_mean", "key_lines"]


class BadValue(Exception):
    """Raised by a leaf check with the sentence that explains what was expected."""


class Context:
    """What checks need besides the value: where relative paths start, the YAML line of each key,
    and the list of problems found so far."""

    def __init__(self, base_dir: Path, lines: Mapping[str, int] | None = None):
        self.base_dir = base_dir
        self.lines = dict(lines or {})
        self.errors: list[str] = []

    def error(self, path: str, msg: str) -> None:
        """Record ``"path (line N): msg"``; the line only when the key was written in the YAML."""
        if not path:
            self.errors.append(msg)
            return
        line = self.lines.get(path)
        self.errors.append(f"{path} (line {line}): {msg}" if line is not None else f"{path}: {msg}")


INVALID = object()  # placeholder for a value that failed its check (cross-checks skip it)


def is_valid(v) -> bool:
    """False for a value (or section) that failed its check; cross-checks skip those."""
    return v is not INVALID


def did_you_mean(word: str, options, cutoff: float = 0.5) -> str | None:
    """The option closest to ``word`` (difflib ratio >= cutoff, else a case-insensitive match), or None."""
    options = list(options)
    close = difflib.get_close_matches(word, options, n=1, cutoff=cutoff) or [
        o for o in options if o.lower() == word.lower()]
    return close[0] if close else None


def join_path(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def key_lines(text: str) -> dict[str, int]:
    """{dotted key path: 1-based line} of every mapping key and list item in a YAML text.

    Built from PyYAML's safe composer (nodes keep their marks; nothing is constructed). Paths follow
    the checker's spelling (``a.b``, ``a.list[0].c``); merged keys (``<<: *anchor``) take the line of
    the anchor's key unless the mapping sets them itself. Empty for text that is not valid YAML.
    """
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    lines: dict[str, int] = {}

    def walk(node, path):
        if isinstance(node, yaml.MappingNode):
            merges = [v for k, v in node.value if k.tag == "tag:yaml.org,2002:merge"]
            for m in merges:  # first, so that the mapping's own keys override them (as in loading)
                for sub in (m.value if isinstance(m, yaml.SequenceNode) else [m]):
                    walk(sub, path)
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.tag != "tag:yaml.org,2002:merge":
                    p = join_path(path, str(k.value))
                    lines[p] = k.start_mark.line + 1
                    walk(v, p)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                p = f"{path}[{i}]"
                lines[p] = item.start_mark.line + 1
                walk(item, p)

    if root is not None:
        walk(root, "")
    return lines


# ---------------------------------------------------------------------------------------------
# Leaf checks. Each is a callable (value, ctx) -> normalised value that raises BadValue(message);
# ``describe`` is the short type text used in messages.
# ---------------------------------------------------------------------------------------------
def _fmt_num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


class Int:
    """An integer (>= ``min``); with ``auto``, the string 'auto' too (resolved where the value is used)."""

    def __init__(self, min: int | None = None, auto: bool = False):
        self.min, self.auto = min, auto

    def describe(self) -> str:
        return "an integer" + (f" >= {self.min}" if self.min is not None else "") + (" or 'auto'" if self.auto else "")

    def __call__(self, v, ctx):
        if self.auto and v == "auto":
            return v
        if isinstance(v, bool) or not isinstance(v, int) or (self.min is not None and v < self.min):
            raise BadValue(f"expected {self.describe()}, got {v!r}")
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
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        x = float(v)
        ok = x == x and abs(x) != float("inf")
        if ok and self.lo is not None:
            ok = x > self.lo if self.lo_open else x >= self.lo
        if ok and self.hi is not None:
            ok = x < self.hi if self.hi_open else x <= self.hi
        if not ok:
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        return x


class Bool:
    def describe(self) -> str:
        return "true or false"

    def __call__(self, v, ctx):
        if not isinstance(v, bool):
            raise BadValue(f"expected true or false, got {v!r}")
        return v


class Str:
    def __init__(self, pattern: str | None = None, what: str = "a string"):
        self.pattern, self.what = pattern, what

    def describe(self) -> str:
        return self.what

    def __call__(self, v, ctx):
        if not isinstance(v, str) or (self.pattern and not re.fullmatch(self.pattern, v)):
            raise BadValue(f"expected {self.what}, got {v!r}")
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
            close = did_you_mean(v, self.options) if isinstance(v, str) else None
            hint = f" (did you mean {close!r}?)" if close else ""
            raise BadValue(f"expected {self.describe()}, got {v!r}{hint}")
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
            raise BadValue(f"expected {self.describe()} (a string), got {v!r}")
        p = Path(os.path.expanduser(v))
        if not p.is_absolute():
            p = ctx.base_dir / p
        if self.suffixes and p.suffix.lower() not in self.suffixes:
            raise BadValue(f"{self.what} must end in {' or '.join(self.suffixes)}, got {v!r}")
        if not p.exists():
            raise BadValue(f"{self.what} {v!r} not found (looked for {p})")
        if not p.is_file():
            raise BadValue(f"{self.what} {v!r} is not a regular file ({p})")
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
            raise BadValue(f"expected {self.describe()}, got {v!r}")
        from astropy.time import Time
        try:
            t = Time(v.strip().rstrip("Z"), scale="utc")
            if t.format not in ("isot", "iso", "fits"):
                raise ValueError(f"parsed as format {t.format!r}, not an ISO date-time")
        except Exception as e:  # astropy raises ValueError and others for unparseable strings
            why = str(e).splitlines()[0][:120] if str(e).strip() else type(e).__name__
            if "did not match any of the formats" in why:
                why = "not a recognised date-time"
            raise BadValue(f"expected {self.describe()}, got {v!r} ({why})") from None
        iso = t.isot
        return iso[:-4] if iso.endswith(".000") else iso




class ListOf:
    """A list whose every item passes ``item`` (a leaf check or a Section), with at least ``min_len`` items."""

    def __init__(self, item, what: str, min_len: int = 0):
        self.item, self.what, self.min_len = item, what, int(min_len)

    def describe(self) -> str:
        return f"a list of {self.what}" + (f" (at least {self.min_len})" if self.min_len else "")

    def check(self, v, path, ctx):
        if not isinstance(v, list) or len(v) < self.min_len:
            ctx.error(path, f"expected {self.describe()}, got {v!r}")
            return INVALID
        return [run_check(self.item, x, f"{path}[{i}]", ctx) for i, x in enumerate(v)]


def run_check(check, value, path, ctx):
    """Apply a leaf check or a structured check, recording errors under ``path``."""
    if hasattr(check, "check"):
        return check.check(value, path, ctx)
    try:
        return check(value, ctx)
    except BadValue as e:
        ctx.error(path, str(e))
        return INVALID


# ---------------------------------------------------------------------------------------------
# Sections: Key(check, default); REQUIRED marks keys without a default.
# ---------------------------------------------------------------------------------------------
REQUIRED = object()


@dataclass(frozen=True)
class Key:
    """One key of a :class:`Section`: its ``check``, its ``default`` (None: optional and None when
    absent; :data:`REQUIRED`: no default) and ``doc``, the description the YAML reference shows (units,
    meaning, what ``null`` or ``auto`` stands for)."""
    check: Any
    default: Any = None
    doc: str = ""


class Section:
    """A mapping with a fixed set of keys. ``post(out, given, path, ctx)`` adds cross-key rules;
    ``renamed`` maps a key that is no longer read to the error that says what replaced it; ``doc`` is
    the paragraph the YAML reference shows under the section's heading (rules that span its keys)."""

    def __init__(self, keys: Mapping[str, Key], post: Callable | None = None, what: str = "a mapping",
                 renamed: Mapping[str, str] | None = None, doc: str = ""):
        self.keys = dict(keys)
        self.post = post
        self.what = what
        self.renamed = dict(renamed or {})
        self.doc = doc

    def describe(self) -> str:
        return self.what

    def check(self, v, path, ctx, *, allowed: Mapping[str, Key] | None = None,
              elsewhere: Mapping[str, str] | None = None):
        keys = self.keys if allowed is None else allowed
        if v is None:
            v = {}
        if not isinstance(v, dict):
            ctx.error(path, f"expected {self.what} with keys {', '.join(keys)}, got {v!r}")
            return INVALID
        out = {}
        for k in v:
            if k in keys:
                continue
            where = join_path(path, str(k))
            if elsewhere and k in elsewhere:
                ctx.error(where, elsewhere[k])
                continue
            if k in self.renamed:
                ctx.error(where, self.renamed[k])
                continue
            close = did_you_mean(str(k), keys, cutoff=0.6)
            hint = f"; did you mean {close!r}?" if close else ""
            ctx.error(where, f"unknown key{hint} (valid keys here: {', '.join(keys)})")
        given = {k for k in keys if v.get(k) is not None}
        for k, spec in keys.items():
            where = join_path(path, k)
            if k in given:
                out[k] = run_check(spec.check, v[k], where, ctx)
            elif spec.default is REQUIRED:
                ctx.error(where, f"missing required key ({spec.check.describe()})")
                out[k] = INVALID
            elif isinstance(spec.check, Section) and spec.default is not None:
                out[k] = spec.check.check({}, where, ctx)  # fill a sub-section's defaults
            else:
                out[k] = copy.deepcopy(spec.default)
        if self.post is not None:
            self.post(out, given, path, ctx)
        return out
