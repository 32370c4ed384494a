"""MkDocs hook: the docstrings' formulas as MathML, written into the pages at build time.

``pymdownx.arithmatex`` (generic mode) leaves ``$...$`` as ``<span class="arithmatex">\\(...\\)</span>``
and ``$$...$$`` as ``<div class="arithmatex">\\[...\\]</div>``. This hook replaces each with the
``<math>`` element ``latex2mathml`` writes for it, which browsers draw natively: the site renders
its formulas offline, with no script and no CDN. A formula ``latex2mathml`` cannot read fails the
build, naming the page and the formula; so does a command it does not know (which it would
otherwise print as text).
"""
from __future__ import annotations

import html
import re

from latex2mathml.converter import convert

ARITHMATEX = re.compile(r'<(span|div) class="arithmatex">\s*\\[(\[](.*?)\\[)\]]\s*</\1>', re.S)
UNKNOWN_COMMAND = re.compile(r">(\\[A-Za-z]+)<")  # latex2mathml writes a command it does not know as text


def to_mathml(tex: str, display: bool) -> str:
    """A TeX formula (without its delimiters) as a ``<math>`` element, inline or as a block."""
    mathml = convert(tex.strip(), display="block" if display else "inline")
    if unknown := UNKNOWN_COMMAND.search(mathml):
        raise ValueError(f"unknown TeX command {unknown.group(1)}")
    return mathml


def on_post_page(output: str, page, config) -> str:
    def replace(match: re.Match) -> str:
        tex = html.unescape(match.group(2))
        try:
            return to_mathml(tex, display=match.group(1) == "div")
        except Exception as error:  # latex2mathml's own errors name the token, not the page
            raise ValueError(f"{page.file.src_uri}: cannot write the formula {tex!r} as MathML: {error}") from error

    return ARITHMATEX.sub(replace, output)
