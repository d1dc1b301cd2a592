"""Write the pipeline YAML reference page at build time, from the schema the validator uses.

mkdocs-gen-files runs this script inside ``mkdocs build``; the page it writes,
``reference/pipeline-yaml.md``, exists only in the built site. Every key, its type, allowed values and
default come from ``bf_epic_blocks.pipeline.config.SCHEMA`` (the objects ``bf-epic validate`` checks
with), so the page cannot drift from the validator. A key's description is its ``Key.doc``; where
that is empty, the line that config.py's module docstring gives the key is shown instead, marked so.
"""
from __future__ import annotations

import re
import sys
import textwrap
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the build runs from a checkout; the package need not be installed
    sys.path.insert(0, str(ROOT))

from bf_epic_blocks.pipeline import config  # noqa: E402
from bf_epic_blocks.pipeline import yaml_schema as ys  # noqa: E402

PAGE = "reference/pipeline-yaml.md"


def docstring_notes(doc: str) -> dict[str, str]:
    """{dotted key: its text} from the indented schema summary in config.py's module docstring.

    The summary is the literal block after the line ending in ``::``; a key line is indented two
    spaces per level below its parent, and deeper-indented lines continue the previous key's text.
    """
    lines = doc.splitlines()
    start = next((i for i, s in enumerate(lines) if s.rstrip().endswith("::")), None)
    if start is None:
        return {}
    block = []
    for s in lines[start + 1:]:
        if s.strip() and not s.startswith(" "):
            break
        block.append(s)
    block = textwrap.dedent("\n".join(block)).splitlines()
    key_re = re.compile(r"^( *)([A-Za-z_][A-Za-z0-9_]*):(.*)$")
    notes: dict[str, str] = {}
    stack: list[str] = []
    last = None
    for s in block:
        if not s.strip() or s.lstrip().startswith("#"):
            continue
        m = key_re.match(s)
        indent = len(s) - len(s.lstrip())
        if m and indent % 2 == 0 and indent // 2 <= len(stack):
            depth = indent // 2
            stack = stack[:depth] + [m.group(2)]
            last = ".".join(stack)
            notes[last] = m.group(3).strip()
        elif last is not None:
            notes[last] += " " + s.strip()
    return {k: re.sub(r"\s+", " ", v).strip() for k, v in notes.items()}


def cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    text = str(text).replace("|", "\\|").replace("\n", " ")
    return text.replace("{", "&#123;").replace("}", "&#125;")  # attr_list would take "{...}" as attributes


def type_text(check) -> str:
    if isinstance(check, ys.Choice):
        return "one of " + ", ".join(f"`{o}`" for o in check.options)
    if isinstance(check, ys.Section):
        return "mapping (below)"
    return cell(check.describe())


def default_text(key: ys.Key) -> str:
    d = key.default
    if d is ys.REQUIRED:
        return "**required**"
    if isinstance(key.check, ys.Section):
        return "—" if d is None else "its keys' defaults"
    if d is None:
        return "`null`"
    if isinstance(d, bool):
        return f"`{str(d).lower()}`"
    if isinstance(d, list):
        return "`[" + ", ".join(str(x) for x in d) + "]`"
    return f"`{d}`"


class Writer:
    def __init__(self, notes: dict[str, str]):
        self.notes = notes
        self.out: list[str] = []
        self.keys = 0
        self.undocumented: list[str] = []

    def description(self, path: str, key: ys.Key) -> str:
        if key.doc:
            return cell(key.doc)
        self.undocumented.append(path)
        note = self.notes.get(path)
        return f"*{cell(note)}*" if note else ""

    def table(self, keys, prefix: str) -> list[tuple[str, ys.Section]]:
        """One table row per key; returns the sub-sections to describe after the table."""
        self.out += ["| key | type / allowed values | default | description |", "|---|---|---|---|"]
        subs = []
        for name, key in keys.items():
            path = ys.join_path(prefix, name)
            self.keys += 1
            self.out.append(f"| `{name}` | {type_text(key.check)} | {default_text(key)} | "
                            f"{self.description(path, key)} |")
            check = key.check
            if isinstance(check, ys.Section):
                subs.append((path, check))
            elif isinstance(getattr(check, "entry", None), ys.Section):      # lists of mappings
                subs.append((path + "[]", check.entry))
            elif isinstance(getattr(check, "item", None), ys.Section):
                subs.append((path + "[]", check.item))
        self.out.append("")
        return subs

    def section(self, path: str, sec: ys.Section, level: int) -> None:
        self.out += [f"{'#' * level} `{path}`", ""]
        if isinstance(sec, config.SourceSection):
            self.source(path, level)
            return
        for sub_path, sub in self.table(sec.keys, path.removesuffix("[]")):
            self.section(sub_path, sub, level + 1)

    def source(self, path: str, level: int) -> None:
        self.out += ["The keys allowed depend on `source.kind`; these two hold for every kind:", ""]
        subs = self.table(config.SOURCE_COMMON, path)
        for kind, keys in config.SOURCE_KINDS.items():
            self.out += [f"{'#' * (level + 1)} `source.kind: {kind}`", ""]
            subs += self.table(keys, path)
        for sub_path, sub in subs:
            self.section(sub_path, sub, level + 1)


def render() -> str:
    notes = docstring_notes(config.__doc__ or "")
    w = Writer(notes)
    w.out += ["## Top level", ""]
    for sub_path, sub in w.table(config.SCHEMA.keys, ""):
        w.section(sub_path, sub, 2)
    head = [
        "# Pipeline YAML reference",
        "",
        "This page is generated at build time from the schema that `bf-epic validate` and `bf-epic run` "
        "check every YAML against (`bf_epic_blocks.pipeline.config.SCHEMA`). "
        "For how to edit a pipeline, see [Editing a pipeline](../guide/editing-yaml.md).",
        "",
        "- A key set to `null` takes its default; **required** keys have none.",
        "- Any key can be set from the command line: `--set imager.grid.size=128`.",
        "- Paths of input files are resolved against the YAML file's directory.",
        "- Unknown keys are errors and name the closest valid key.",
        "",
    ]
    if w.undocumented:
        head += [
            f"!!! note \"Descriptions\"",
            f"    {len(w.undocumented)} of {w.keys} keys carry no description in the schema yet "
            "(`Key(..., doc=...)`); for those, the *italic* text is the key's line in the schema "
            "summary of `bf_epic_blocks/pipeline/config.py`'s docstring.",
            "",
        ]
    tail = []
    rules = (config.__doc__ or "").split("::", 1)[-1]
    paras = [p.strip() for p in re.split(r"\n\s*\n", rules)
             if p.strip() and not p.startswith(" ") and p.strip().split()[0] in ("Numbers:", "Cross-checks:")]
    if paras:
        tail += ["## Rules that span keys", ""]
        for p in paras:
            tail += [re.sub(r"``([^`]+)``", r"`\1`", re.sub(r"\s*\n\s*", " ", p)), ""]
    return "\n".join(head + w.out + tail)


with mkdocs_gen_files.open(PAGE, "w") as f:
    f.write(render())
mkdocs_gen_files.set_edit_path(PAGE, "gen_yaml_reference.py")
