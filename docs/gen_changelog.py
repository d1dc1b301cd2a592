"""Write the changelog page at build time from the top-level CHANGELOG.md (one source, not a copy).

Links into docs/ become site links; links to other repository files become their path as code.
Without a CHANGELOG.md the page says so, so that the site still builds.
"""
from __future__ import annotations

import re
from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[1]
PAGE = "changelog.md"


def relink(text: str) -> str:
    """Links into docs/ become site links; links to other repository files become their path as code."""
    def one(m):
        label, target = m.group(1), m.group(2)
        if re.match(r"[a-z]+:|#", target):
            return m.group(0)
        if target.startswith("docs/"):
            return f"[{label}]({target[len('docs/'):]})"
        return f"{label} (`{target}`)"
    return re.sub(r"(?<!!)\[([^\]]+)\]\(([^)\s]+)\)", one, text)


src = ROOT / "CHANGELOG.md"
if src.is_file():
    text = src.read_text(encoding="utf-8")
    text = relink(text)
else:
    text = "# Changelog\n\nThis checkout has no CHANGELOG.md yet.\n"

with mkdocs_gen_files.open(PAGE, "w") as f:
    f.write(text)
