"""Griffe extension: render the package's Sphinx roles, maths and lists as Markdown.

The docstrings are Google style with a few reST pieces that mkdocstrings would print
verbatim. This extension (listed in mkdocs.yml) rewrites them, in the loaded object tree
only (the sources are not changed):

- roles such as ``:func:`~closedchain.load` `` become inline code (a ``~`` keeps the last
  component);
- ``:math:`M a` `` becomes ``$M a$`` and a ``.. math::`` block one ``$$ ... $$`` block per
  paragraph of its body: pymdownx.arithmatex marks them and docs/_ext/mathml.py renders
  them as MathML;
- a reST definition list (a term in inline code on a line of its own, its definition
  indented below) becomes a Markdown one (``:   definition``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

#: A role: ``:func:`~a.b` `` (a ``~`` shows the last component only).
ROLE = re.compile(r":(?:py:)?(?:attr|class|data|exc|func|meth|mod|obj|const):`(~?)([^`]+)`")
#: An inline maths role.
MATH_ROLE = re.compile(r":math:`([^`]+)`")
#: A math directive on its own line (its indented body follows).
MATH_DIRECTIVE = re.compile(r"^([ \t]*)\.\. math::[ \t]*$")
#: A definition-list term: inline code alone on its line.
TERM = re.compile(r"^([ \t]*)``[^`]+``[ \t]*$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def _role(match: re.Match) -> str:
    text = match[2].rsplit(".", 1)[-1] if match[1] else match[2]
    return f"`{text}`"


def _math_role(match: re.Match) -> str:
    return "$" + " ".join(match[1].split()) + "$"


def _blocks(lines: list[str]) -> list[str]:
    """Return ``lines`` with each ``.. math::`` directive and its indented body as
    ``$$`` blocks (one per paragraph of the body) at the directive's indentation."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        directive = MATH_DIRECTIVE.match(lines[i])
        if not directive:
            out.append(lines[i])
            i += 1
            continue
        pad, base = directive[1], _indent(lines[i])
        i += 1
        body: list[str] = []
        while i < len(lines) and (not lines[i].strip() or _indent(lines[i]) > base):
            body.append(lines[i].strip())
            i += 1
        while body and not body[-1]:  # blank lines after the body belong to the text
            body.pop()
            i -= 1
        for paragraph in re.split(r"\n\s*\n", "\n".join(body).strip()):
            out += ["", f"{pad}$$", *(f"{pad}{ln}" for ln in paragraph.splitlines()), f"{pad}$$"]
        out.append("")
    return out


def _definitions(lines: list[str]) -> list[str]:
    """Return ``lines`` with reST definition lists as Markdown ones."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        term = TERM.match(lines[i])
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if not (term and nxt.strip() and _indent(nxt) > _indent(lines[i])):
            out.append(lines[i])
            i += 1
            continue
        pad, base = term[1], _indent(lines[i])
        if out and out[-1].strip():
            out.append("")
        out.append(lines[i])
        i += 1
        first = True
        while i < len(lines) and lines[i].strip() and _indent(lines[i]) > base:
            out.append(f"{pad}{':   ' if first else '    '}{lines[i].strip()}")
            first = False
            i += 1
        out.append("")
    return out


def markdown(text: str) -> str:
    """Return ``text`` (a docstring) with its roles, maths and definition lists as
    Markdown (see the module docstring)."""
    text = MATH_ROLE.sub(_math_role, ROLE.sub(_role, text))
    return "\n".join(_definitions(_blocks(text.splitlines())))


class SphinxRoles(griffe.Extension):
    """Rewrite every docstring of a loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        seen: set[int] = set()
        stack: list[griffe.Object] = [pkg]
        while stack:
            obj = stack.pop()
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = markdown(obj.docstring.value)
            stack.extend(m for m in obj.members.values() if not m.is_alias)
