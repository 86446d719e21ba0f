"""MkDocs hook: render the site's maths as MathML at build time (no script, no network).

``pymdownx.arithmatex`` (``generic: true``, in mkdocs.yml) marks ``$...$`` and ``$$...$$``
in the pages, and in the docstrings once docs/_ext/sphinx_roles.py has turned their
``:math:`` roles and ``.. math::`` blocks into those delimiters, as

    <span class="arithmatex">\\(...\\)</span>   and   <div class="arithmatex">\\[...\\]</div>

This hook (listed under ``hooks:`` in mkdocs.yml) replaces each with the MathML that
``latex2mathml`` makes of its LaTeX, which the browser typesets itself: the built site reads
without JavaScript or a network. A fragment latex2mathml cannot convert stops the build
with the page and the fragment.
"""

from __future__ import annotations

import html
import re
from typing import Any

from latex2mathml.converter import convert
from mkdocs.exceptions import PluginError

#: arithmatex's generic output: the inline and the display forms.
INLINE = re.compile(r'<span class="arithmatex">\\\((.*?)\\\)</span>', re.S)
DISPLAY = re.compile(r'<div class="arithmatex">\\\[(.*?)\\\]</div>', re.S)
#: LaTeX commands latex2mathml does not know, written with ones it does.
MACROS = {r"\arg": r"\operatorname{arg}"}
#: Matrix brackets: latex2mathml writes them as plain operators, which browsers do not
#: stretch unless told (MathML Core's operator dictionary knows them as fences only first
#: and last in a row).
OPEN_BRACKET = re.compile(r"<mo>(&#x0005B;|&#x00028;|&#x0007C;|&#x02016;)</mo>(?=<mtable)")
CLOSE_BRACKET = re.compile(r"(?<=</mtable>)<mo>(&#x0005D;|&#x00029;|&#x0007C;|&#x02016;)</mo>")
#: A command left as text in the MathML: latex2mathml did not know it.
LEFTOVER = re.compile(r">[^<]*\\[A-Za-z]+[^<]*<")


def to_mathml(latex: str, *, display: bool) -> str:
    """Return the MathML element of one LaTeX fragment (HTML-escaped, as arithmatex
    writes it)."""
    source = html.unescape(latex).strip()
    known = re.sub(
        "|".join(re.escape(m) + r"(?![A-Za-z])" for m in MACROS), lambda m: MACROS[m[0]], source
    )
    mathml = convert(known, display="block" if display else "inline")
    if leftover := LEFTOVER.search(mathml):
        raise ValueError(f"latex2mathml left {leftover[0][1:-1]!r} as text")
    mathml = OPEN_BRACKET.sub(r'<mo stretchy="true" form="prefix">\1</mo>', mathml)
    mathml = CLOSE_BRACKET.sub(r'<mo stretchy="true" form="postfix">\1</mo>', mathml)
    # Keep the LaTeX beside the MathML (its own annotation element) for copy and search.
    opening, _, inner = mathml.partition(">")
    inner = inner.removesuffix("</math>")
    annotation = f'<annotation encoding="application/x-tex">{html.escape(source)}</annotation>'
    return f"{opening}><semantics><mrow>{inner}</mrow>{annotation}</semantics></math>"


def render(text: str, where: str) -> str:
    """Return ``text`` (a page's HTML) with every arithmatex fragment as MathML."""

    def replace(display: bool):
        def one(match: re.Match) -> str:
            try:
                mathml = to_mathml(match[1], display=display)
            except Exception as exc:  # latex2mathml raises several kinds
                raise PluginError(f"{where}: cannot render the maths {match[1]!r}: {exc}") from exc
            return f'<div class="math-display">{mathml}</div>' if display else mathml

        return one

    return INLINE.sub(replace(False), DISPLAY.sub(replace(True), text))


def on_page_content(html_text: str, page: Any, **kwargs: Any) -> str:
    """MkDocs event: a page's Markdown (docstrings included) has become HTML."""
    return render(html_text, page.file.src_uri)
