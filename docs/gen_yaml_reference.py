"""Write the pipeline YAML reference page at build time, from the schema the validator uses.

mkdocs-gen-files runs this script inside ``mkdocs build``; the page it writes,
``reference/pipeline-yaml.md``, exists only in the built site. Every key, its type, allowed values,
default and description come from ``bf_epic_blocks.pipeline.config.SCHEMA`` (the objects
``bf-epic validate`` checks with): a key's description is its ``Key.doc``, a section's paragraph its
``Section.doc``. So the page cannot drift from the validator, and a key without a description fails
tests/test_config.py rather than reaching this page blank.
"""
from __future__ import annotations

import sys
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the build runs from a checkout; the package need not be installed
    sys.path.insert(0, str(ROOT))

from bf_epic_blocks.pipeline import config  # noqa: E402
from bf_epic_blocks.pipeline import yaml_schema as ys  # noqa: E402

PAGE = "reference/pipeline-yaml.md"


def _escape_braces(text: str) -> str:
    """Braces outside code spans as HTML entities: attr_list would take "{...}" as attributes. Inside
    a code span they stay as they are (an entity there would be shown literally)."""
    parts = str(text).split("`")
    return "`".join(part if i % 2 else part.replace("{", "&#123;").replace("}", "&#125;")
                    for i, part in enumerate(parts))


def cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return _escape_braces(str(text).replace("|", "\\|").replace("\n", " "))


def prose(text: str) -> str:
    """Text safe as a Markdown paragraph."""
    return _escape_braces(text)


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
    def __init__(self):
        self.out: list[str] = []

    def paragraph(self, sec: ys.Section) -> None:
        if sec.doc:
            self.out += [prose(sec.doc), ""]

    def table(self, keys, prefix: str) -> list[tuple[str, ys.Section]]:
        """One table row per key; returns the sub-sections to describe after the table."""
        self.out += ["| key | type / allowed values | default | description |", "|---|---|---|---|"]
        subs = []
        for name, key in keys.items():
            path = ys.join_path(prefix, name)
            self.out.append(f"| `{name}` | {type_text(key.check)} | {default_text(key)} | {cell(key.doc)} |")
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
        self.paragraph(sec)
        if isinstance(sec, config.SourceSection):
            self.source(path, level)
            return
        for sub_path, sub in self.table(sec.keys, path.removesuffix("[]")):
            self.section(sub_path, sub, level + 1)

    def source(self, path: str, level: int) -> None:
        self.out += ["These keys hold for every kind:", ""]
        subs = self.table(config.SOURCE_COMMON, path)
        for kind, keys in config.SOURCE_KINDS.items():
            self.out += [f"{'#' * (level + 1)} `source.kind: {kind}`", ""]
            subs += self.table(keys, path)
        for sub_path, sub in subs:
            self.section(sub_path, sub, level + 1)


def render() -> str:
    w = Writer()
    w.out += ["## Top level", ""]
    w.paragraph(config.SCHEMA)
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
        "- Accuracy: `imager.tolerance` is the one knob; `imager.method` and `imager.precision` are expert "
        "overrides (see [Accuracy](../concepts/accuracy.md)).",
        "",
    ]
    return "\n".join(head + w.out)


with mkdocs_gen_files.open(PAGE, "w") as f:
    f.write(render())
mkdocs_gen_files.set_edit_path(PAGE, "gen_yaml_reference.py")
