"""The docs hook that fills the pages from the data files (``docs/hooks/generate.py``): the
learning-curve figures (``{{ curves DIR }}``: one polyline per run, at the coordinates its
evaluations map to, hand-computed, one colour per learner), the scaling figures, the inline values
(``{{ value NAME:TABLE[ROW][COLUMN] }}``: the one cell a row's leading cells and a column name
pick), and errors that name what is valid."""
from __future__ import annotations

import importlib.util
import json
import re
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


def _throughput(tmp_path):
    table = {"title": "rates", "columns": ["task", "N", "ours", "theirs"],
             "rows": [["Hopper-v5", "1", "10", "-"], ["Hopper-v5", "100", "1k", "2.5k"],
                      ["Hopper-v5", "10000", "1M", "3k"]]}
    data = {"measured": "2026-01-01", "machine": "m", "command": "c", "tables": {"rates": table}}
    (tmp_path / "rates.json").write_text(json.dumps(data))


def test_scaling_figure_is_log_log_in_the_rates_of_the_table(hook, tmp_path):
    _throughput(tmp_path)
    svg = hook.render_scaling("rates", "rates", "ours", "../data/")
    (points,) = re.findall(r'<polyline points="([^"]+)"', svg)
    # x: N 1..10000 over 60..450 (four decades); y: 10..1M over 260..28 (five decades)
    assert points == "60.0,260.0 255.0,167.2 450.0,28.0"
    assert "[data](../data/rates.json)" in svg
    both = hook.render_scaling("rates", "rates", "ours,theirs", "")
    assert len(re.findall("<polyline", both)) == 2 and "Hopper-v5 (theirs)" in both  # the "-" cell is left out


def test_scaling_figure_names_what_is_valid(hook, tmp_path):
    _throughput(tmp_path)
    with pytest.raises(ValueError, match="no column.*'speed'.*valid: task, N, ours, theirs"):
        hook.render_scaling("rates", "rates", "speed", "")
    with pytest.raises(ValueError, match="no table 'other'; valid: rates"):
        hook.render_scaling("rates", "other", "ours", "")
    assert hook._rate("3.27k") == 3270.0 and hook._rate("1.2M") == 1.2e6 and hook._rate("-") is None


def test_scaling_figure_of_one_task_names_its_lines_by_column(hook, tmp_path):
    _throughput(tmp_path)
    svg = hook.render_scaling("rates", "rates", "ours,theirs:Hopper-v5", "")
    assert ">ours</text>" in svg and ">theirs</text>" in svg and "(ours, theirs; Hopper-v5; log-log)" in svg
    with pytest.raises(ValueError, match="no measured rates"):
        hook.render_scaling("rates", "rates", "ours:Ant-v5", "")


def test_a_table_leaves_out_the_columns_named_by_prefix_and_says_so(hook):
    (hook.DATA_DIR / "wide.json").write_text(json.dumps({
        "measured": "2026-01-01", "machine": "m", "command": "c",
        "tables": {"t": {"title": "T", "columns": ["env", "loss", "env steps", "PPO final = 612", "95% of PPO = 582"],
                         "rows": [["Hopper-v5", "shac", "200,704", "1964 s", "1900 s"]]}}}))
    page = hook.on_page_markdown("{{ table wide:t without=env,95% }}", _page("results.md"), None, None)
    # a column's own name leaves out that column only ("env", not "env steps"); else a prefix
    assert page.splitlines()[:3] == ["| loss | env steps | PPO final = 612 |", "|---|---|---|",
                                     "| shac | 200,704 | 1964 s |"]
    assert "also there: env, 95% of PPO = 582" in page
    with pytest.raises(ValueError, match=r"without= 80% names no column; valid columns: env, loss"):
        hook.render_table("wide", "t", "data/", "loss,80%")


def _page(src_uri: str):
    """What the hook reads of an MkDocs page: its source path."""
    return SimpleNamespace(file=SimpleNamespace(src_uri=src_uri))


def test_table_cells_write_numbers_as_people_read_them(hook):
    cell = hook._cell
    assert cell("2.23e+03") == "2230" and cell("-1.5e+04 s") == "-15000 s"  # thousands written out
    assert cell("1.3e+09") == "1.3e9" and cell("4.2e-05") == "4.2e-5" and cell("2e+19") == "2e19"
    assert cell("`x=1e+09` or 1e+05") == "`x=1e+09` or 1e5"  # code stays as written
    assert cell("ratio 0.5x | 12") == "ratio 0.5x \\| 12"


@pytest.fixture
def tables(hook, tmp_path):
    race = {"title": "race", "columns": ["env", "loss", "in Gymnasium's env", "wall s"],
            "rows": [["Ant-v5", "ppo", "378 [218, 473]", 2.23e3], ["Ant-v5", "sapo", "1194 [1173, 1299]", "a|b"]]}
    levels = dict(race, rows=race["rows"] + [["Ant-v5", "sapo, seed 1", "1173", 12]])
    data = {"measured": "2026-01-01", "machine": "m", "command": "c", "tables": {"Ant-v5": race, "levels": levels}}
    (tmp_path / "race.json").write_text(json.dumps(data))
    single = dict(data, tables={"speed": {"title": "t", "columns": ["task", "ratio"], "rows": [["Ant-v5", "0.351x"]]}})
    (tmp_path / "speed.json").write_text(json.dumps(single))
    return hook


def test_a_value_is_the_cell_of_its_row_and_column(tables):
    text = ("SAPO ends at {{ value race:Ant-v5[Ant-v5, sapo][in Gymnasium's env] }}, PPO at "
                       "{{ value race:Ant-v5[Ant-v5,ppo][in Gymnasium's env] }}; the Ant runs at "
                       "{{ value speed[Ant-v5][ratio] }}.")
    assert tables.on_page_markdown(text, _page("results.md"), None, None) == (
        "SAPO ends at 1194 [1173, 1299], PPO at 378 [218, 473]; the Ant runs at 0.351x.")
    # as the table shows it: thousands written out, pipes escaped
    assert tables.render_value("race", "Ant-v5", "Ant-v5,ppo", "wall s") == "2230.0"
    assert tables.render_value("race", "Ant-v5", "Ant-v5,sapo", "wall s") == "a\\|b"
    # a comma inside a leading cell is written \,
    assert tables.render_value("race", "levels", "Ant-v5,sapo\\, seed 1", "wall s") == "12"


def test_value_errors_name_what_is_valid(tables):
    with pytest.raises(ValueError, match="holds 2 tables; name one: race:Ant-v5, race:levels"):
        tables.render_value("race", None, "Ant-v5,ppo", "wall s")
    with pytest.raises(ValueError, match="no table 'Hopper-v5'; valid: Ant-v5, levels"):
        tables.render_value("race", "Hopper-v5", "Ant-v5,ppo", "wall s")
    with pytest.raises(ValueError, match="no column 'wall'; valid: env, loss, in Gymnasium's env, wall s"):
        tables.render_value("race", "Ant-v5", "Ant-v5,ppo", "wall")
    with pytest.raises(ValueError, match=r"2 rows start with \[Ant-v5\], not one; the rows start with: \[Ant-v5\], \[Ant-v5\]"):
        tables.render_value("race", "Ant-v5", "Ant-v5", "wall s")
    with pytest.raises(ValueError, match=r"0 rows start with \[Ant-v5,shac\]"):
        tables.render_value("race", "Ant-v5", "Ant-v5,shac", "wall s")
    with pytest.raises(ValueError, match="data file .missing.: no .*missing.json; valid: race, speed"):
        tables.render_value("missing", None, "Ant-v5", "ratio")
