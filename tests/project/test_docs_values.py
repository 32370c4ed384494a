"""The docs hook's inline values (``{{ value NAME:TABLE[ROW][COLUMN] }}``): the one cell the row's
leading cells and the column name pick, rendered as the table renders it, and errors that name
what is valid."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace

import pytest

HOOK = Path(__file__).resolve().parents[2] / "docs" / "hooks" / "generate.py"


@pytest.fixture
def hook(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("docs_generate", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "DATA_DIR", tmp_path)
    race = {"title": "race", "columns": ["env", "loss", "in Gymnasium's env", "wall s"],
            "rows": [["Ant-v5", "ppo", "378 [218, 473]", 2.23e3], ["Ant-v5", "sapo", "1194 [1173, 1299]", "a|b"]]}
    data = {"measured": "2026-01-01", "machine": "m", "command": "c", "tables": {"Ant-v5": race, "levels": race}}
    (tmp_path / "race.json").write_text(json.dumps(data))
    single = dict(data, tables={"speed": {"title": "t", "columns": ["task", "ratio"], "rows": [["Ant-v5", "0.351x"]]}})
    (tmp_path / "speed.json").write_text(json.dumps(single))
    return module


def _page(text):
    return SimpleNamespace(file=SimpleNamespace(src_uri="results.md")), text


def test_a_value_is_the_cell_of_its_row_and_column(hook):
    page, text = _page("SAPO ends at {{ value race:Ant-v5[Ant-v5, sapo][in Gymnasium's env] }}, PPO at "
                       "{{ value race:Ant-v5[Ant-v5,ppo][in Gymnasium's env] }}; the Ant runs at "
                       "{{ value speed[Ant-v5][ratio] }}.")
    assert hook.on_page_markdown(text, page, None, None) == (
        "SAPO ends at 1194 [1173, 1299], PPO at 378 [218, 473]; the Ant runs at 0.351x.")
    # as the table shows it: thousands written out, pipes escaped
    assert hook.render_value("race", "Ant-v5", "Ant-v5,ppo", "wall s") == "2230.0"
    assert hook.render_value("race", "Ant-v5", "Ant-v5,sapo", "wall s") == "a\\|b"


def test_value_errors_name_what_is_valid(hook):
    with pytest.raises(ValueError, match="holds 2 tables; name one: race:Ant-v5, race:levels"):
        hook.render_value("race", None, "Ant-v5,ppo", "wall s")
    with pytest.raises(ValueError, match="no table 'Hopper-v5'; valid: Ant-v5, levels"):
        hook.render_value("race", "Hopper-v5", "Ant-v5,ppo", "wall s")
    with pytest.raises(ValueError, match="no column 'wall'; valid: env, loss, in Gymnasium's env, wall s"):
        hook.render_value("race", "Ant-v5", "Ant-v5,ppo", "wall")
    with pytest.raises(ValueError, match=r"2 rows start with \[Ant-v5\], not one; the rows start with: \[Ant-v5\], \[Ant-v5\]"):
        hook.render_value("race", "Ant-v5", "Ant-v5", "wall s")
    with pytest.raises(ValueError, match=r"0 rows start with \[Ant-v5,shac\]"):
        hook.render_value("race", "Ant-v5", "Ant-v5,shac", "wall s")
    with pytest.raises(ValueError, match="data file .missing.: no .*missing.json; valid: race, speed"):
        hook.render_value("missing", None, "Ant-v5", "ratio")
