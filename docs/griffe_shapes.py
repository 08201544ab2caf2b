"""A griffe extension for the docs build: the library's "Shapes:" lines render as a box.

diffcloth's docstrings are Google style with one extra convention (docs/architecture.md): a
paragraph that starts with "Shapes:" names the shape and unit of each array argument and result,
often right under the summary line without a blank line between. Markdown would run it into the
summary's paragraph. This extension rewrites each such top-level paragraph, in the docstring that
griffe parses (not in the source), into a Google admonition block

    Shapes:
        x (n, 3) m -> () J.

which griffe turns into a "Shapes" section and mkdocstrings into an admonition box. Lines inside
Args:/Returns:/... sections (indented) are left alone.
"""

from __future__ import annotations

import re

import griffe

_SHAPES = re.compile(r"^Shapes:\s+(?P<rest>\S.*)$")
_SECTION = re.compile(r"^[A-Z][\w ]*:\s*$")  # "Args:", "Returns:", ...


def rewrite_shapes(text: str) -> str:
    """The docstring `text` with each top-level "Shapes: ..." paragraph as an indented block."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = _SHAPES.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        if out and out[-1].strip():
            out.append("")
        out += ["Shapes:", "    " + m["rest"]]
        i += 1
        # continuation lines: the rest of the paragraph (not indented, not a section header)
        while i < len(lines) and lines[i].strip() and not lines[i].startswith(" "):
            if _SECTION.match(lines[i]) or _SHAPES.match(lines[i]):
                break
            out.append("    " + lines[i])
            i += 1
        out.append("")
    return "\n".join(out).rstrip("\n")


class ShapesSection(griffe.Extension):
    """Rewrite "Shapes:" paragraphs of every loaded object's docstring (see the module)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and "Shapes:" in obj.docstring.value:
            obj.docstring.value = rewrite_shapes(obj.docstring.value)
