"""Griffe extension: render the package's Sphinx roles and math directives as Markdown.

The docstrings are Google style with a few reST pieces that mkdocstrings would print
verbatim: roles such as ``:func:`~closedchain.load` `` and ``:math:`M a` ``, and
``.. math::`` blocks. This extension (listed in mkdocs.yml) rewrites them, in the
loaded object tree only, as inline code and indented code blocks. The sources are not
changed.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

#: A role: ``:func:`~a.b` `` (a ``~`` shows the last component only).
ROLE = re.compile(r":(?:py:)?(?:attr|class|data|exc|func|meth|mod|obj|const|math):`(~?)([^`]+)`")
#: A math directive on its own line (its indented body follows).
MATH_DIRECTIVE = re.compile(r"^([ \t]*)\.\. math::[ \t]*$", re.M)


def _role(match: re.Match) -> str:
    text = match[2].rsplit(".", 1)[-1] if match[1] else match[2]
    return f"`{text}`"


def markdown(text: str) -> str:
    """Return ``text`` with roles as inline code and math directives dropped (their
    indented body then reads as a code block)."""
    return MATH_DIRECTIVE.sub("", ROLE.sub(_role, text))


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
