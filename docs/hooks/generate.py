"""MkDocs hook: fills the pages' generated parts at build time.

* ``{{ table NAME }}`` becomes the Markdown table of ``docs/data/NAME.json`` (written by the
  benchmark that measured it), followed by its date, machine and command. Numbers are never
  pasted into the pages: re-running the benchmark rewrites the data file and the next build
  shows the new measurement. ``{{ table NAME:KEY without=PREFIX,PREFIX }}`` leaves out the
  columns of those names, or whose names start with them (a page-wide table; the data file keeps
  them all).
* ``{{ curves DIR }}`` (or ``{{ curves DIR:FILTER }}``, only the result files whose name holds
  ``FILTER``) becomes a figure per env of the evaluation returns against env steps of every run
  in the result files of ``docs/data/runs/DIR/`` (``time_to_solve.py out=``), one line per run,
  one colour per learner: an inline SVG, drawn here from the runs' curves.
* ``{{ scaling NAME:TABLE:COLUMNS }}`` (or ``{{ scaling NAME:TABLE:COLUMNS:TASKS }}``, only those
  tasks) becomes a log-log figure of the rate columns ``COLUMNS`` (comma-separated) of table
  ``TABLE`` of ``docs/data/NAME.json`` against its ``N`` column (the number of envs), one line per
  task and column: an inline SVG, drawn from the data file.
* ``{{ value NAME:TABLE[ROW][COLUMN] }}`` (or ``{{ value NAME[ROW][COLUMN] }}`` for a file with one
  table) becomes one cell of a data file's table, inline: the row whose leading cells are
  ``ROW``'s comma-separated values (``[Ant-v5,sapo]``; ``\\,`` for a comma inside a cell), in the
  column named ``COLUMN``. Prose
  cites measurements this way, so a re-run updates the sentence with the table.
* ``{{ config_reference }}`` becomes the reference of every learner's settings, read from the
  settings dataclasses themselves (field, default, accepted values, description).

A missing data file or learner raises, so ``mkdocs build --strict`` (CI) fails loudly.
"""
from __future__ import annotations

import dataclasses
import inspect
import json
import math
import re
import warnings
from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
TABLE = re.compile(r"\{\{\s*table\s+([A-Za-z0-9_.-]+)(?::([A-Za-z0-9_.-]+))?(?:\s+without=([^}]+?))?\s*\}\}")
CURVES = re.compile(r"\{\{\s*curves\s+([A-Za-z0-9_.-]+)(?::([A-Za-z0-9_.-]+))?\s*\}\}")
SCALING = re.compile(r"\{\{\s*scaling\s+([A-Za-z0-9_.-]+):([A-Za-z0-9_.-]+):([^}]+?)\s*\}\}")
VALUE = re.compile(r"\{\{\s*value\s+([A-Za-z0-9_.-]+)(?::([A-Za-z0-9_.-]+))?\[([^\]]+)\]\[([^\]]+)\]\s*\}\}")
CONFIG_REFERENCE = re.compile(r"\{\{\s*config_reference\s*\}\}")
DATA_FIELDS = ("measured", "machine", "command", "tables")
TABLE_FIELDS = ("title", "columns", "rows")


def _plain(text: str) -> str:
    """reStructuredText roles and literals of a docstring as Markdown code: ``:class:`X` `` -> `` `X` ``."""
    text = re.sub(r":[\w:]+:`~?([^`]+)`", r"`\1`", text)
    return re.sub(r"``([^`]+)``", r"`\1`", text)


SCIENTIFIC = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?e[+-]\d\d\b")
CODE_SPAN = re.compile(r"(`+)(.+?)\1")
SKIPPED = "skipped (budget)"


def _plain_number(match: re.Match) -> str:
    """Numbers as people read them: ``2.23e+03`` -> ``2230`` (thousands written out), ``1.3e+09`` ->
    ``1.3e9`` and ``4.2e-05`` -> ``4.2e-5`` (no plus sign, no leading zero in the exponent)."""
    mantissa, _, exponent = match.group(0).partition("e")
    if exponent in ("+03", "+04"):
        return f"{float(match.group(0)):.0f}"
    return f"{mantissa}e{int(exponent)}"


def _cell(value) -> str:
    """A table cell: pipes escaped outside code spans (inside them Markdown keeps them), one line,
    thousands written out."""
    text = "-" if value is None else str(value)
    parts, last = [], 0
    for match in CODE_SPAN.finditer(text):
        parts.append(SCIENTIFIC.sub(_plain_number, text[last:match.start()]).replace("\\|", "|").replace("|", "\\|"))
        parts.append(match.group(0))
        last = match.end()
    parts.append(SCIENTIFIC.sub(_plain_number, text[last:]).replace("\\|", "|").replace("|", "\\|"))
    return "".join(parts).replace("\n", " ")


def _skipped(row: list) -> bool:
    """A row the benchmark did not measure (its time budget ran out): no cell beyond the first two
    holds a measurement."""
    cells = [str(c) for c in row[2:]]
    return any(c == SKIPPED for c in cells) and all(c in ("-", "n/a", SKIPPED) for c in cells)


def load_data(name: str) -> dict:
    """The data file ``docs/data/<name>.json``, checked for the fields every data file needs."""
    path = DATA_DIR / f"{name}.json"
    if not path.is_file():
        valid = ", ".join(sorted(p.stem for p in DATA_DIR.glob("*.json")))
        raise ValueError(f"data file {name!r}: no {path}; valid: {valid}")
    data = json.loads(path.read_text())
    missing = [key for key in DATA_FIELDS if key not in data]
    if missing:
        raise ValueError(f"{path}: missing field(s) {', '.join(missing)}; every data file needs {', '.join(DATA_FIELDS)}")
    for key, table in data["tables"].items():
        missing = [field for field in TABLE_FIELDS if field not in table]
        if missing:
            raise ValueError(f"{path}: table {key!r} lacks {', '.join(missing)}")
        for i, row in enumerate(table["rows"]):
            if len(row) != len(table["columns"]):
                raise ValueError(f"{path}: table {key!r}, row {i} has {len(row)} cells for {len(table['columns'])} columns")
    return data


def _kept_columns(table: dict, without: str | None, tag: str) -> list[int]:
    """The columns' positions without those ``without`` names (comma-separated): a column of that
    name, or else the columns whose names start with it."""
    columns = [str(c) for c in table["columns"]]
    if not without:
        return list(range(len(columns)))
    dropped: set[int] = set()
    for name in (p.strip() for p in without.split(",") if p.strip()):
        named = [i for i, c in enumerate(columns) if c == name] or [i for i, c in enumerate(columns) if c.startswith(name)]
        if not named:
            raise ValueError(f"{tag}: without= {name} names no column; valid columns: {', '.join(columns)}")
        dropped.update(named)
    return [i for i in range(len(columns)) if i not in dropped]


def render_table(name: str, key: str | None, data_link: str, without: str | None = None) -> str:
    """``{{ table name }}`` (a data file with one table) or ``{{ table name:key }}``, as Markdown;
    ``without``: comma-separated prefixes of the names of columns to leave out."""
    data = load_data(name)
    tables = data["tables"]
    if key is None and len(tables) != 1:
        raise ValueError(f"{{{{ table {name} }}}}: the file holds {len(tables)} tables; name one: "
                         + ", ".join(f"{name}:{k}" for k in tables))
    if key is not None and key not in tables:
        raise ValueError(f"{{{{ table {name}:{key} }}}}: no table {key!r}; valid: {', '.join(tables)}")
    table = tables[key] if key is not None else next(iter(tables.values()))
    kept = _kept_columns(table, without, f"{{{{ table {name}{':' + key if key else ''} }}}}")
    lines = ["| " + " | ".join(_cell(table["columns"][i]) for i in kept) + " |", "|" + "|".join("---" for _ in kept) + "|"]
    rows = [row for row in table["rows"] if not _skipped(row)]
    lines += ["| " + " | ".join(_cell(row[i]) for i in kept) + " |" for row in rows]
    skipped: dict[str, list[str]] = {}
    for row in table["rows"]:
        if _skipped(row):
            skipped.setdefault(str(row[0]), []).append(str(row[1]))
    note = ""
    if skipped:
        note = ("Not measured (the run's time budget ran out): "
                + "; ".join(f"{key} ({table['columns'][1]} = {', '.join(values)})" for key, values in skipped.items())
                + ".\n\n")
    command = data["command"]
    left_out = [_cell(c) for i, c in enumerate(table["columns"]) if i not in kept]
    caption = (f"*{table['title']}. Measured {data['measured']} on {data['machine']}"
               + (f" with `{command}`" if command else "") + f" ([data]({data_link}{name}.json)"
               + (f"; also there: {', '.join(left_out)}" if left_out else "") + ").*")
    return note + "\n".join(lines) + "\n\n" + caption + "\n"


def render_value(name: str, key: str | None, row_key: str, column: str) -> str:
    """``{{ value name:key[row][column] }}``: the cell of table ``key`` (the file's only table when
    ``key`` is None) in the row whose leading cells are ``row``'s comma-separated values (``\\,``
    for a comma inside a cell) and the column named ``column``, as the table shows it."""
    tag = f"{{{{ value {name}{':' + key if key else ''}[{row_key}][{column}] }}}}"
    tables = load_data(name)["tables"]
    if key is None and len(tables) != 1:
        raise ValueError(f"{tag}: the file holds {len(tables)} tables; name one: " + ", ".join(f"{name}:{k}" for k in tables))
    if key is not None and key not in tables:
        raise ValueError(f"{tag}: no table {key!r}; valid: {', '.join(tables)}")
    table = tables[key] if key is not None else next(iter(tables.values()))
    columns = [str(c) for c in table["columns"]]
    if column.strip() not in columns:
        raise ValueError(f"{tag}: no column {column.strip()!r}; valid: {', '.join(columns)}")
    wanted = [cell.replace("\\,", ",").strip() for cell in re.split(r"(?<!\\),", row_key)]
    rows = [row for row in table["rows"] if [str(c) for c in row[:len(wanted)]] == wanted]
    if len(rows) != 1:
        leading = ", ".join(f"[{','.join(str(c) for c in row[:len(wanted)])}]" for row in table["rows"])
        raise ValueError(f"{tag}: {len(rows)} rows start with [{','.join(wanted)}], not one; the rows start with: {leading}")
    return _cell(rows[0][columns.index(column.strip())])


# --------------------------------------------------------------------------- learning curves

COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")
WIDTH, HEIGHT, LEFT, RIGHT, TOP, BOTTOM = 640, 300, 60, 130, 28, 40


def load_runs(directory: str, only: str | None) -> list[dict]:
    """The runs of the result files in ``docs/data/runs/<directory>/`` (whose name holds ``only``)."""
    folder = DATA_DIR / "runs" / directory
    files = sorted(p for p in folder.glob("*.json") if only is None or only in p.name) if folder.is_dir() else []
    if not files:
        valid = ", ".join(sorted(p.name for p in (DATA_DIR / "runs").iterdir() if p.is_dir()))
        raise ValueError(f"{{{{ curves {directory} }}}}: no result files in {folder}"
                         + (f" holding {only!r}" if only else "") + f"; valid folders: {valid}")
    runs = []
    for path in files:
        for run in json.loads(path.read_text()).get("runs", []):
            if not run.get("curve"):
                raise ValueError(f"{path}: run {run.get('loss')} seed {run.get('seed')} has no evaluation curve")
            runs.append(run)
    return runs


def _run_label(run: dict) -> str:
    """A run's learner as the tables name it: ``loss`` or ``loss:variant``."""
    return f"{run['loss']}:{run['variant']}" if run.get("variant") else run["loss"]


def _seed_counts(runs: list[dict]) -> str:
    """``3 seeds per learner``, or per learner where they differ: ``seeds: ppo 3, shac 2``."""
    seeds: dict[str, set] = {}
    for run in runs:
        seeds.setdefault(_run_label(run), set()).add(run["seed"])
    counts = {label: len(s) for label, s in seeds.items()}
    if len(set(counts.values())) == 1:
        n = next(iter(counts.values()))
        return f"{n} seed{'s' if n > 1 else ''} per learner"
    return "seeds: " + ", ".join(f"{label} {n}" for label, n in counts.items())


def _ticks(low: float, high: float, count: int = 5) -> list[float]:
    """About ``count`` round values spanning ``[low, high]``."""
    raw = (high - low) / max(count - 1, 1) or 1.0
    magnitude = 10 ** int(f"{raw:e}".split("e")[1])
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw)
    first = step * -(-low // step)
    return [first + i * step for i in range(int((high - first) // step) + 1)]


def _label(value: float) -> str:
    return f"{value / 1000:g}k" if abs(value) >= 1000 else f"{value:g}"


def render_curves(directory: str, only: str | None) -> str:
    """``{{ curves DIR }}``: per env, an SVG of every run's evaluation return against env steps."""
    runs = load_runs(directory, only)
    figures = []
    for env in dict.fromkeys(r["env"] for r in runs):
        group = [r for r in runs if r["env"] == env]
        labels = list(dict.fromkeys(_run_label(r) for r in group))
        colour = {label: COLOURS[i % len(COLOURS)] for i, label in enumerate(labels)}
        xs = [p[0] for r in group for p in r["curve"]]
        ys = [p[2] for r in group for p in r["curve"]]
        x_ticks, y_ticks = _ticks(0, max(xs)), _ticks(min(ys), max(ys))
        x_low, x_high = 0, max(max(xs), x_ticks[-1])
        y_low, y_high = min(min(ys), y_ticks[0]), max(max(ys), y_ticks[-1])
        width, height = WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM

        def x(value):
            return LEFT + width * (value - x_low) / ((x_high - x_low) or 1)

        def y(value):
            return TOP + height * (1 - (value - y_low) / ((y_high - y_low) or 1))

        parts = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {WIDTH} {HEIGHT}" role="img" '
                 f'style="max-width:{WIDTH}px;width:100%;font:11px sans-serif">',
                 f'<title>{env}: evaluation return against env steps, every run</title>',
                 f'<text x="{LEFT}" y="16" font-weight="bold">{env}</text>']
        for tick in y_ticks:
            parts.append(f'<line x1="{LEFT}" x2="{LEFT + width}" y1="{y(tick):.1f}" y2="{y(tick):.1f}" stroke="#ddd"/>'
                         f'<text x="{LEFT - 6}" y="{y(tick) + 4:.1f}" text-anchor="end">{_label(tick)}</text>')
        for tick in x_ticks:
            parts.append(f'<text x="{x(tick):.1f}" y="{TOP + height + 16}" text-anchor="middle">{_label(tick)}</text>')
        parts.append(f'<text x="{LEFT + width / 2}" y="{HEIGHT - 6}" text-anchor="middle">env steps</text>')
        parts.append(f'<text transform="translate(14 {TOP + height / 2}) rotate(-90)" text-anchor="middle">'
                     'evaluation return</text>')
        for run in group:
            label = _run_label(run)
            points = " ".join(f"{x(p[0]):.1f},{y(p[2]):.1f}" for p in run["curve"])
            parts.append(f'<polyline points="{points}" fill="none" stroke="{colour[label]}" stroke-width="1.5" '
                         f'stroke-opacity="0.8"><title>{label}, seed {run["seed"]}</title></polyline>')
        for i, label in enumerate(labels):
            top = TOP + 14 * i
            parts.append(f'<line x1="{LEFT + width + 12}" x2="{LEFT + width + 30}" y1="{top + 6}" y2="{top + 6}" '
                         f'stroke="{colour[label]}" stroke-width="2"/>'
                         f'<text x="{LEFT + width + 34}" y="{top + 10}">{label}</text>')
        parts.append("</svg>")
        figures.append("".join(parts) + f"\n\n*{env}: the evaluation return of every run against its env steps "
                       f"(one line per run; {_seed_counts(group)}).*\n")
    return "\n".join(figures)


# --------------------------------------------------------------------------- throughput against N

RATE = re.compile(r"^(\d+(?:\.\d+)?)([kM]?)$")


def _rate(cell) -> float | None:
    """``"3.27k"`` -> 3270.0, ``"1.2M"`` -> 1.2e6; ``None`` for a cell without a measurement (``-``)."""
    match = RATE.match(str(cell).strip())
    if match is None:
        return None
    return float(match.group(1)) * {"": 1, "k": 1e3, "M": 1e6}[match.group(2)]


def _decades(low: float, high: float) -> list[float]:
    """The powers of ten spanning ``[low, high]``."""
    first, last = math.floor(math.log10(low)), math.ceil(math.log10(high))
    return [10.0 ** k for k in range(first, last + 1)]


def render_scaling(name: str, key: str, columns: str, data_link: str) -> str:
    """``{{ scaling NAME:TABLE:COLUMNS[:TASKS] }}``: a log-log SVG of rate columns against ``N``, per task."""
    columns, _, tasks = columns.partition(":")
    only = {t.strip() for t in tasks.split(",")} if tasks else None
    data = load_data(name)
    if key not in data["tables"]:
        raise ValueError(f"{{{{ scaling {name}:{key} }}}}: no table {key!r}; valid: {', '.join(data['tables'])}")
    table = data["tables"][key]
    wanted = [c.strip() for c in columns.split(",")]
    missing = [c for c in ["task", "N", *wanted] if c not in table["columns"]]
    if missing:
        raise ValueError(f"{{{{ scaling {name}:{key} }}}}: no column(s) {', '.join(map(repr, missing))}; "
                         f"valid: {', '.join(table['columns'])}")
    at = {c: table["columns"].index(c) for c in ["task", "N", *wanted]}
    lines: dict[str, list[tuple[float, float]]] = {}
    for row in table["rows"]:
        if only is not None and row[at["task"]] not in only:
            continue
        n = _rate(row[at["N"]])
        for column in wanted:
            rate = _rate(row[at[column]])
            if n is not None and rate is not None:
                task = row[at["task"]]
                if only is not None and len(only) == 1:  # one task: the columns name the lines
                    label = column
                else:
                    label = f"{task} ({column})" if len(wanted) > 1 else task
                lines.setdefault(label, []).append((n, rate))
    if not lines:
        raise ValueError(f"{{{{ scaling {name}:{key}:{columns} }}}}: no measured rates to draw")
    xs = [p[0] for points in lines.values() for p in points]
    ys = [p[1] for points in lines.values() for p in points]
    x_ticks, y_ticks = _decades(min(xs), max(xs)), _decades(min(ys), max(ys))
    width, height = WIDTH - LEFT - RIGHT - 60, HEIGHT - TOP - BOTTOM
    log_x = (math.log10(x_ticks[0]), math.log10(x_ticks[-1]))
    log_y = (math.log10(y_ticks[0]), math.log10(y_ticks[-1]))

    def x(value):
        return LEFT + width * (math.log10(value) - log_x[0]) / ((log_x[1] - log_x[0]) or 1)

    def y(value):
        return TOP + height * (1 - (math.log10(value) - log_y[0]) / ((log_y[1] - log_y[0]) or 1))

    title = f"{table['title']}: env steps per second against N"
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {WIDTH} {HEIGHT}" role="img" '
             f'style="max-width:{WIDTH}px;width:100%;font:11px sans-serif"><title>{title}</title>']
    for tick in y_ticks:
        parts.append(f'<line x1="{LEFT}" x2="{LEFT + width}" y1="{y(tick):.1f}" y2="{y(tick):.1f}" stroke="#ddd"/>'
                     f'<text x="{LEFT - 6}" y="{y(tick) + 4:.1f}" text-anchor="end">{_si(tick)}</text>')
    for tick in x_ticks:
        parts.append(f'<line x1="{x(tick):.1f}" x2="{x(tick):.1f}" y1="{TOP}" y2="{TOP + height}" stroke="#eee"/>'
                     f'<text x="{x(tick):.1f}" y="{TOP + height + 16}" text-anchor="middle">{_si(tick)}</text>')
    parts.append(f'<text x="{LEFT + width / 2}" y="{HEIGHT - 6}" text-anchor="middle">N (envs in the batch)</text>')
    parts.append(f'<text transform="translate(14 {TOP + height / 2}) rotate(-90)" text-anchor="middle">'
                 'env steps / s</text>')
    for i, (label, points) in enumerate(lines.items()):
        colour = COLOURS[i % len(COLOURS)]
        path = " ".join(f"{x(n):.1f},{y(rate):.1f}" for n, rate in sorted(points))
        parts.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="1.8">'
                     f'<title>{label}</title></polyline>')
        parts.extend(f'<circle cx="{x(n):.1f}" cy="{y(rate):.1f}" r="2.5" fill="{colour}"/>' for n, rate in points)
        top = TOP + 14 * i
        parts.append(f'<line x1="{LEFT + width + 12}" x2="{LEFT + width + 30}" y1="{top + 6}" y2="{top + 6}" '
                     f'stroke="{colour}" stroke-width="2"/><text x="{LEFT + width + 34}" y="{top + 10}">{label}</text>')
    parts.append("</svg>")
    which = ", ".join(wanted) + (f"; {', '.join(sorted(only))}" if only else "")
    return ("".join(parts) + f"\n\n*{table['title']}: env steps per second against the number of envs "
            f"({which}; log-log). Measured {data['measured']} on {data['machine']} "
            f"([data]({data_link}{name}.json)).*\n")


def _si(value: float) -> str:
    for unit, scale in (("M", 1e6), ("k", 1e3)):
        if value >= scale:
            return f"{value / scale:g}{unit}"
    return f"{value:g}"


# --------------------------------------------------------------------------- config reference

def _field_comments(cls) -> dict[str, str]:
    """``name -> trailing comment`` of the field lines in the class bodies along the MRO."""
    comments: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        for match in re.finditer(r"^\s+(\w+)\s*:[^=\n]*=.*?#\s*(.+)$", source, flags=re.MULTILINE):
            comments[match.group(1)] = match.group(2).strip()
    return comments


def _accepted(field: dataclasses.Field) -> str:
    """What a field accepts, in the words of its check's error message."""
    check = field.metadata.get("check")
    if check is None:
        return ""
    for probe in (object(), "?", -1, 0, None):
        try:
            message = check(probe)
        except Exception:  # a check that cannot even look at the probe says nothing
            continue
        if message:
            return message.removeprefix("expected ").replace("valid: ", "one of ")
    return ""


def _default(field: dataclasses.Field):
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return field.default


def _type_name(field: dataclasses.Field) -> str:
    return field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type))


def _settings_rows(cls, prefix: str, instance=None) -> list[list[str]]:
    """One row per field of the settings dataclass ``cls``; the defaults are ``instance``'s values
    when given (a learner's network section: its own defaults, not the section class's)."""
    rows, comments = [], _field_comments(cls)
    for field in dataclasses.fields(cls):
        default = getattr(instance, field.name) if instance is not None else _default(field)
        if dataclasses.is_dataclass(default):  # nested settings (e.g. the networks): their own rows
            rows += _settings_rows(type(default), f"{prefix}{field.name}.")
            continue
        if isinstance(default, tuple):
            default = list(default)
        doc = _plain(field.metadata.get("doc") or comments.get(field.name, ""))
        rows.append([f"`{prefix}{field.name}`", f"`{_yaml_value(default)}`", _cell(_type_name(field)),
                     _cell(_accepted(field)), _cell(doc)])
    return rows


def _yaml_value(value) -> str:
    """A default as a Hydra command line or a YAML file writes it: ``true``, ``null``, ``1e6``,
    ``.inf``."""
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    if isinstance(value, float):
        if not math.isfinite(value):
            return ".nan" if math.isnan(value) else (".inf" if value > 0 else "-.inf")
        if value.is_integer() and abs(value) >= 1e5:  # 1e6, not 1000000.0 (an int to the reader)
            mantissa, exponent = f"{value:.15e}".split("e")
            return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"
        return repr(value).replace("e+", "e")
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    return repr(value).replace("'", "")


def _learners() -> dict:
    with warnings.catch_warnings():  # TorchRL's import-time deprecation notices are not the docs' warnings
        warnings.simplefilter("ignore")
        from torchrl_diffenvs import learners

    registry = getattr(learners, "LEARNERS", None)
    if not registry:
        raise ValueError("torchrl_diffenvs.learners.LEARNERS is missing or empty: the config reference "
                         "lists the learners registered there")
    return dict(registry)


def render_config_reference() -> str:
    parts = []
    for name, learner in _learners().items():
        settings = getattr(learner, "config_class", None)
        if settings is None or not dataclasses.is_dataclass(settings):
            raise ValueError(f"learner {name!r} ({learner.__name__}) has no settings dataclass in config_class")
        summary = _plain((inspect.getdoc(settings) or "").split("\n\n")[0].replace("\n", " "))
        parts.append(f"### `loss={name}`: `{settings.__name__}`\n\n{summary}\n")
        parts.append("| key | default | type | accepts | what |\n|---|---|---|---|---|")
        parts += ["| " + " | ".join(row) + " |" for row in _settings_rows(settings, "loss.")]
        for key, network in getattr(learner, "networks", {}).items():  # loss.actor.*, loss.critic.*
            parts += ["| " + " | ".join(row) + " |" for row in _settings_rows(type(network), f"loss.{key}.", network)]
        parts.append("")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    data_link = "../" * page.file.src_uri.count("/") + "data/"
    markdown = TABLE.sub(lambda m: render_table(m.group(1), m.group(2), data_link, m.group(3)), markdown)
    markdown = CURVES.sub(lambda m: render_curves(m.group(1), m.group(2)), markdown)
    markdown = VALUE.sub(lambda m: render_value(m.group(1), m.group(2), m.group(3), m.group(4)), markdown)
    markdown = SCALING.sub(lambda m: render_scaling(m.group(1), m.group(2), m.group(3), data_link), markdown)
    if CONFIG_REFERENCE.search(markdown):
        markdown = CONFIG_REFERENCE.sub(lambda m: render_config_reference(), markdown)
    return markdown
