"""Collects the final metrics of training runs into a markdown table (one row per env x loss).

    python sota_scripts/train.py -m env=cartpole,pendulum loss=bptt,shac,ppo,sac hydra.sweep.dir=results/table
    python sota_scripts/results_table.py dirs=[results/table] [output=results/table.md] [only_run=true]

Every ``final_metrics.json`` found under the given directories is one run (sota_scripts/train.py
writes it at the end of training). Runs of the same env and loss (different seeds) are grouped:
the table shows the mean final evaluation return (+- standard deviation over seeds when there are
several), the random policy's return on the same start states, and the mean wall time. Pairs of the
full grid (every registered env x every loss) with no run are listed as "not run".
"""
from __future__ import annotations

import json
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

from torchrl_diffenvs import checks, list_envs
from torchrl_diffenvs.checks import Settings, checked, parse_cli
from torchrl_diffenvs.training.config import LOSSES


def collect(directories: list[Path]) -> list[dict]:
    """Every run's ``final_metrics.json`` under ``directories`` (the path recorded as ``"_path"``)."""
    runs = []
    for directory in directories:
        if not directory.exists():
            raise FileNotFoundError(f"no such directory: {directory}")
        for path in sorted(directory.rglob("final_metrics.json")):
            run = json.loads(path.read_text())
            run["_path"] = str(path)
            runs.append(run)
    return runs


def _mean_std(values: list[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.4g}"
    return f"{statistics.mean(values):.4g} +- {statistics.stdev(values):.2g}"


def markdown_table(runs: list[dict], full_grid: bool = True) -> str:
    """The table: rows ordered by env (Ivy-style tasks, then Gymnasium ids), then loss (bptt, shac, ppo, sac)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for run in runs:
        groups.setdefault((run["env"], run["loss"]), []).append(run)
    # Ivy-style tasks (lower case) first, then the Gymnasium-compatible ids, then anything else found
    registered = sorted(list_envs(), key=lambda name: (name[:1].isupper(), name))
    envs = registered + sorted({e for e, _ in groups} - set(registered))
    keys = [(e, l) for e in envs for l in LOSSES] if full_grid else sorted(groups)
    lines = [
        "| env | loss | seeds | env steps | final eval return | random policy | wall time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for env, loss in keys:
        group = groups.get((env, loss))
        if not group:
            if full_grid:
                lines.append(f"| {env} | {loss} | 0 | | not run | | |")
            continue
        returns = [run_score(r) for r in group]
        randoms = [r["eval/random_return"] for r in group if r.get("eval/random_return") is not None]
        steps = sorted({r["env_steps"] for r in group})
        wall = statistics.mean(r["wall_time_s"] for r in group)
        random_cell = f"{statistics.mean(randoms):.4g}" if randoms else ""
        lines.append(
            f"| {env} | {loss} | {len(group)} | {'/'.join(f'{s:,}' for s in steps)} | {_mean_std(returns)} | "
            f"{random_cell} | {wall:.0f} |"
        )
    return "\n".join(lines) + "\n"


def run_score(result: dict) -> float:
    """A run's final evaluation return: this library's, or Gymnasium's where only that was played
    (``eval.only_gymnasium=true``: ``eval/return`` is null)."""
    ours = result.get("eval/return")
    return result["eval/gymnasium_return"] if ours is None and "eval/gymnasium_return" in result else ours


@dataclass(frozen=True)
class TableSettings(Settings):
    """The script's arguments (``key=value``)."""

    dirs: list[str] = checked([], lambda v: None if v else "give the run or sweep directories: dirs=[path,...]")
    output: str | None = None  # also write the table to this file
    only_run: bool = checked(False, checks.boolean)  # leave out the pairs that have no run


def main(argv: list[str] | None = None) -> str:
    args = parse_cli(TableSettings, argv, __doc__)
    directories = [Path(d) for d in args.dirs]
    runs = collect(directories)
    if not runs:
        raise SystemExit(f"error: no final_metrics.json under {', '.join(map(str, directories))}")
    table = markdown_table(runs, full_grid=not args.only_run)
    if args.output is not None:
        output = Path(args.output)
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(table)
    sys.stdout.write(table)
    return table


if __name__ == "__main__":
    main()
