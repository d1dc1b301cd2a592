"""A griffe extension that lets the package's docstrings read well as Markdown in the API reference.

The docstrings are prose with shapes, written for ``help()`` in the reStructuredText habits of the
scientific Python world: ``double backticks``, roles such as :func:`name`, ``name : description``
lines under a "Parameters" heading, and paragraphs ending in ``::`` before a literal block. They are
not strict numpydoc, so griffe's numpy parser misreads some of them; the site renders them as
Markdown instead, after this extension rewrites those habits (the source is never changed):

* roles ``:func:`x``` / ``:class:`~a.b.X``` become code spans (``x``, ``X``);
* ``double backticks`` become single ones;
* a paragraph's closing ``::`` becomes ``:`` (the indented block after it is already code in Markdown);
* lines ``name : description`` at the left margin become list items, so each parameter keeps its line.
"""
from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|obj|exc|const):`~?\.?([^`]+)`")
_DOUBLE = re.compile(r"``([^`]+)``")
_PARAM = re.compile(r"^([A-Za-z_*][\w*]*(?:, [A-Za-z_*][\w*]*)*) : (\S.*)$")


def _roles(line: str) -> str:
    def role(m):
        name = m.group(1)
        return f"`{name.split('.')[-1]}`" if "~" in m.group(0) else f"`{name}`"
    return _DOUBLE.sub(r"`\1`", _ROLE.sub(role, line))


def to_markdown(text: str) -> str:
    """The docstring ``text`` with the rewrites above; fenced code and literal blocks are left alone."""
    out: list[str] = []
    in_fence = literal = False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            in_fence = not in_fence
            out.append(line)
            continue
        if in_fence or (literal and (not line.strip() or line.startswith(" "))):
            out.append(line)
            continue
        literal = False
        line = _roles(line)
        if line.rstrip().endswith("::"):
            line, literal = line.rstrip()[:-1], True
        m = _PARAM.match(line)
        if m:
            if out and out[-1].strip() and not out[-1].startswith(("- ", " ")):
                out.append("")
            line = f"- `{m.group(1)}` : {m.group(2)}"
        out.append(line)
    return "\n".join(out)


class MarkdownDocstrings(griffe.Extension):
    """Rewrite every loaded object's docstring with :func:`to_markdown`."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value)
