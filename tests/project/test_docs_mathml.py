"""The docs hook that writes the docstrings' formulas as MathML: arithmatex's inline and block
wrappers become ``<math>`` elements (structure checked by hand), HTML entities are read back as
TeX, and a formula it cannot write fails the build naming the page."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import pytest

HOOK = Path(__file__).resolve().parents[2] / "docs" / "hooks" / "mathml.py"
PAGE = SimpleNamespace(file=SimpleNamespace(src_uri="api/objectives.md"))


@pytest.fixture(scope="module")
def hook():
    spec = importlib.util.spec_from_file_location("docs_mathml", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_inline_and_block_formulas_become_mathml(hook):
    page = ('<p>the horizon <span class="arithmatex">\\(H\\)</span> and</p>\n'
            '<div class="arithmatex">\\[\n-\\frac{1}{N} \\sum_{k&lt;K} r_k\n\\]</div>')
    out = hook.on_post_page(page, PAGE, None)
    assert "arithmatex" not in out and "\\(" not in out and "\\[" not in out
    inline, block = out.split("and</p>")
    assert '<math xmlns="http://www.w3.org/1998/Math/MathML" display="inline"><mrow><mi>H</mi></mrow></math>' in inline
    assert 'display="block"' in block
    assert "<mfrac><mrow><mn>1</mn></mrow><mrow><mi>N</mi></mrow></mfrac>" in block
    # the escaped "<" of the page is TeX's "<" again: an operator under the sum, not the text "&lt;"
    assert "<munder><mo>&#x02211;</mo><mrow><mi>k</mi><mo>&#x0003C;</mo><mi>K</mi></mrow></munder>" in block
    assert "<p>the horizon " in inline  # the text around the formulas is left alone


def test_a_formula_it_cannot_write_fails_naming_the_page(hook):
    with pytest.raises(ValueError, match=r"api/objectives\.md: .*\\\\notacommand.*unknown TeX command"):
        hook.on_post_page('<span class="arithmatex">\\(\\notacommand x\\)</span>', PAGE, None)
    with pytest.raises(ValueError, match=r"api/objectives\.md: cannot write the formula 'x_\{'"):
        hook.on_post_page('<span class="arithmatex">\\(x_{\\)</span>', PAGE, None)
