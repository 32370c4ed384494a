"""The docs hook's learning-curve figures (``{{ curves DIR }}``): one polyline per run, at the
coordinates its evaluations map to (hand-computed), one colour per learner, clear errors."""
from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

HOOK = Path(__file__).resolve().parents[2] / "docs" / "hooks" / "generate.py"


@pytest.fixture
def hook(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("docs_generate", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "DATA_DIR", tmp_path)
    folder = tmp_path / "runs" / "race"
    folder.mkdir(parents=True)
    runs = [{"env": "Hopper-v5", "loss": "ppo", "variant": "", "seed": 0,
             "curve": [[0, 0.0, 0.0], [100000, 50.0, 1000.0], [200000, 90.0, 2000.0]]},
            {"env": "Hopper-v5", "loss": "ahac", "variant": "", "seed": 0,
             "curve": [[0, 0.0, 0.0], [200000, 80.0, 1000.0]]}]
    (folder / "Hopper-v5_s0.json").write_text(json.dumps({"runs": runs}))
    return module


def test_each_run_is_a_polyline_at_its_evaluations(hook):
    svg = hook.render_curves("race", None)
    lines = re.findall(r'<polyline points="([^"]+)" fill="none" stroke="([^"]+)"', svg)
    assert len(lines) == 2 and lines[0][1] != lines[1][1]  # one colour per learner
    # the plot area spans x 60..510 (0..200k env steps) and y 28..260 (return 2000..0)
    assert lines[0][0] == "60.0,260.0 285.0,144.0 510.0,28.0"
    assert lines[1][0] == "60.0,260.0 510.0,144.0"
    assert ">ppo</text>" in svg and ">ahac</text>" in svg and "Hopper-v5" in svg


def test_curves_errors_name_what_is_valid(hook):
    with pytest.raises(ValueError, match="no result files .* valid folders: race"):
        hook.render_curves("missing", None)
    with pytest.raises(ValueError, match="holding 'Ant'"):
        hook.render_curves("race", "Ant")
