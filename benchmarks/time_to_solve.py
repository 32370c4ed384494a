"""Time to solve: SHAC vs BPTT vs PPO vs SAC (and AHAC, SAPO) on any task, in one run, same seeds.

Drives the project's public training entry point, ``sota_scripts/train.py`` (its ``run``
function, on configurations composed by Hydra exactly as the command line composes them: the
defaults of configs/ (loss settings and budgets), the per-pair files of configs/tuned/, then the overrides below).
Runs are interleaved (seed by seed, loss by loss) so that load from other processes spreads
over all learners. Each run logs deterministic evaluations (``eval/return``, the mean return of
``eval.num_envs`` fixed start states) against env steps; the wall time of an evaluation is the
run's ``time/wall_s`` at that env step (training time, earlier evaluations included); the
column "of which evaluating s" says how much of a run's wall time its evaluations took (for runs
that logged it, ``eval_time_s``), the same protocol for every learner of a table.

Reported per env and loss, over seeds (median, min-max): the final evaluation return, the wall
time and env steps of the run, and the wall time at which the evaluation return first reached
PPO's final return (the median over seeds of PPO's last evaluation): ``speed-up vs PPO`` is
PPO's time to its own final level divided by that time. The issue's target: SHAC >= 10x on
the pendulum.

    python benchmarks/time_to_solve.py                          # pendulum + cartpole, seeds 0 1 2
    python benchmarks/time_to_solve.py envs=[pendulum] seeds=[0] steps=[ppo=500000]
    python benchmarks/time_to_solve.py quick=true               # a few iterations each: smoke run
    # a sweep: variants of one learner against fixed return levels (no PPO needed)
    python benchmarks/time_to_solve.py envs=[pendulum] losses=[shac] seeds=[0,1] eval_interval=20000 \
        'variant=["default=","H8=loss.horizon=8 loss.actor_lr=2e-2"]' levels=[74.2,72.3,70.4]

Runs side by side (one process per core, e.g. one per task and seed, each with ``out=``) are
summarised together afterwards, PPO-relative levels across all of them::

    python benchmarks/time_to_solve.py summarise=[hc_s0.json,hc_s1.json,hc_s2.json] data=race_halfcheetah
    python benchmarks/time_to_solve.py "summarise=[docs/data/runs/race_mujoco/*.json]" data=race_mujoco  # a pattern

Arguments are ``key=value`` (lists as ``[a,b]``), as for the training script. A variant
(``variant=["LABEL=OVERRIDES", ...]``) runs every loss again with those Hydra overrides and is
reported as ``loss:LABEL``; ``levels`` adds columns with the time to reach fixed returns, and
``env_levels=[ENV=RETURN, ...]`` a level of one env only (in that env's table), e.g. the PPO final
median of a race whose PPO runs are not among the summarised files::

    python benchmarks/time_to_solve.py summarise=[hc_s0_sapo.json,hc_s1_sapo.json] env_levels=[HalfCheetah-v5=2230]

A run longer than one sitting (the Ant's, hours on one thread) is kept in ``keep_runs=DIR`` with
periodic checkpoints and continued later with the same command and ``resume=true``: each run whose
directory holds a checkpoint resumes from it (train.py's exact resume), its wall time counting on
from the checkpoint's, so that with the same budget its curve reads as one uninterrupted run (a
larger budget continues it too, with the learning-rate schedule of the new budget; a finished run
only repeats its final evaluation). Without ``resume=true`` a kept run is never overwritten::

    python benchmarks/time_to_solve.py envs=[Ant-v5] losses=[ppo] seeds=[0] keep_runs=runs/ant \
        "override=[train.checkpoint_interval=20000]" out=ant_s0_ppo.json              # stopped part-way
    python benchmarks/time_to_solve.py envs=[Ant-v5] losses=[ppo] seeds=[0] keep_runs=runs/ant \
        "override=[train.checkpoint_interval=20000]" out=ant_s0_ppo.json resume=true  # continues it
"""
from __future__ import annotations

import glob
import itertools
import json
import math
import shutil
import statistics
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

SCRIPT = C.TRAIN_SCRIPT
LOSSES = ("shac", "bptt", "ppo", "sac", "ahac", "sapo")
DEFAULT_LOSSES = ("shac", "bptt", "ppo", "sac")  # the swing-up race; AHAC and SAPO need contact or time

# quick=true: tiny networks and batches, a few iterations per learner (mirrors tests/training/test_train.py)
QUICK = {
    "common": ["env.num_envs=4", "env.max_episode_steps=12", "eval.num_envs=2", "eval.interval=16"],
    "bptt": ["loss.horizon=4", "loss.actor.hidden=[16]", "train.total_env_steps=32"],
    "shac": ["loss.horizon=4", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]", "loss.critic_passes=2",
             "loss.critic_minibatches=2", "train.total_env_steps=32"],
    "ppo": ["loss.rollout_len=4", "loss.epochs=2", "loss.minibatch_size=8", "loss.actor.hidden=[16]",
            "loss.critic.hidden=[16]", "train.total_env_steps=32"],
    "sac": ["loss.rollout_len=2", "loss.init_random_frames=8", "loss.batch_size=8", "loss.buffer_size=256",
            "loss.actor.hidden=[16]", "loss.qvalue.hidden=[16]", "train.total_env_steps=32"],
    "ahac": ["loss.min_horizon=4", "loss.max_horizon=5", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]",
             "loss.critic_passes=2", "loss.critic_minibatches=2", "train.total_env_steps=32"],
    "sapo": ["loss.horizon=4", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]", "loss.critic_passes=2",
             "loss.critic_minibatches=2", "train.total_env_steps=32"],
}


def load_train_script():
    if not SCRIPT.exists():
        raise SystemExit(f"time_to_solve: waiting on the training script: {SCRIPT} does not exist yet")
    return C.load_train_script()


def eval_curve(run_dir: Path) -> list[tuple[int, float, float]]:
    """``(env_steps, wall_s, eval_return)`` of every evaluation in ``metrics.jsonl``."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    wall_at = {0: 0.0}
    for row in rows:
        if "time/wall_s" in row:
            wall_at[row["env_steps"]] = row["time/wall_s"]
    curve = []
    for row in rows:
        if "eval/return" in row:
            steps = row["env_steps"]
            known = [s for s in wall_at if s <= steps]
            curve.append((steps, wall_at[max(known)], row["eval/return"]))
    return curve


def kept_run_checkpoint(run_dir: Path, overrides: list[str], resume: bool) -> int | None:
    """The env step at which the kept run in ``run_dir`` resumes (``resume=true``), or ``None`` for a
    fresh run. Refuses, before any run starts, to overwrite a kept run (without ``resume=true``) and
    to continue one that another command started (other overrides than these; the budget,
    ``train.total_env_steps``, may differ)."""
    from torchrl_diffenvs.training import load_checkpoint

    path = run_dir / "checkpoints" / "last.pt"
    if not path.exists():
        return None
    if not resume:
        raise SystemExit(f"time_to_solve: {run_dir} holds a run with checkpoints ({path}): resume=true continues "
                         "it; remove the directory to start it over")
    checkpoint = load_checkpoint(path)
    budget = lambda items: [o for o in items if not o.startswith("train.total_env_steps=")]  # noqa: E731
    if budget(checkpoint.get("overrides", [])) != budget(overrides):
        raise SystemExit(f"time_to_solve: the kept run {run_dir} was started with other overrides "
                         f"({' '.join(checkpoint.get('overrides', []))}) than this command's ({' '.join(overrides)}); "
                         "resume it with its own command, or give another keep_runs")
    return int(checkpoint["progress"]["env_steps"])


def first_time_at(curve, threshold: float) -> float:
    """Wall time of the first evaluation at or above ``threshold`` (inf if never)."""
    for _, wall, value in curve:
        if value >= threshold:
            return wall
    return math.inf


def first_steps_at(curve, threshold: float) -> float:
    """Env steps of the first evaluation at or above ``threshold`` (inf if never)."""
    for steps, _, value in curve:
        if value >= threshold:
            return steps
    return math.inf


def speedup(reference_s: float, time_s: float) -> float | None:
    """``reference_s / time_s``; ``None`` when ``time_s`` never came (inf) or both are 0."""
    if not math.isfinite(time_s) or not math.isfinite(reference_s):
        return None
    if time_s == 0:
        return None if reference_s == 0 else math.inf
    return reference_s / time_s


def gradient_health(run_dir: Path) -> dict | None:
    """The actor's gradient over a whole run, from ``metrics.jsonl``: the median and largest pre-clip
    norm of the logged updates and the updates the gradient guard skipped (its cumulative count at
    the end); None for a learner that logs no actor gradient norm (PPO, SAC)."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    norms = [row["train/grad_norm_actor"] for row in rows if "train/grad_norm_actor" in row]
    if not norms:
        return None
    skipped = [row["train/skipped_actor"] for row in rows if "train/skipped_actor" in row]
    return {"actor_grad_norm_median": statistics.median(norms), "actor_grad_norm_max": max(norms),
            "logged_updates": len(norms), "skipped_actor_updates": int(skipped[-1]) if skipped else 0}


GYMNASIUM_RETURN = "eval/gymnasium_return"  # eval.gymnasium=true: the final policy's return in Gymnasium's env
LEVELS = (1.0, 0.95, 0.9)  # fractions of PPO's final improvement over the random policy


def reached(times: list[float]) -> str:
    """``"k/n"``: how many of the runs reached a level (a finite time)."""
    return f"{sum(math.isfinite(t) for t in times)}/{len(times)}"


# the runs whose final return sets an env's levels: PPO on this library's env, else on Gymnasium's
REFERENCES = ("ppo", "ppo:gymnasium")


def run_label(run: dict) -> str:
    """``loss`` or ``loss:variant``: the rows of the summary."""
    return f"{run['loss']}:{run['variant']}" if run.get("variant") else run["loss"]


def parse_variants(items: list[str]) -> list[tuple[str, list[str]]]:
    """``["H8=loss.horizon=8 loss.actor_lr=2e-2", ...]`` -> ``[("H8", [overrides]), ...]``."""
    variants = []
    for item in items:
        label, sep, overrides = item.partition("=")
        if not sep or not label or ":" in label:
            raise SystemExit(f"time_to_solve: variant expects LABEL=OVERRIDES (LABEL without ':'), got {item!r}")
        variants.append((label, overrides.split()))
    if len({label for label, _ in variants}) != len(variants):
        raise SystemExit(f"time_to_solve: variant labels must be distinct, got {[v[0] for v in variants]}")
    return variants


def summarise(runs: list[dict], envs: list[str], losses: list[str],
              fixed_levels: list[float] = ()) -> tuple[list[dict], str]:
    """Per env and loss over seeds: final return, wall time, and times to PPO's final level.

    Levels: PPO's final return itself (the median over seeds of its last evaluation), and 95 % /
    90 % of PPO's final improvement over the random policy (``random + f (ppo_final - random)``):
    near a task's ceiling, learners that all "solve" it end a fraction of a point apart, and the
    exact final level alone would call that "never". PPO is the ``ppo`` runs of the env, or where
    it has none its ``ppo:gymnasium`` runs (PPO on Gymnasium's own env); each row names it under
    ``reference``.
    """
    summary = []
    labels = list(dict.fromkeys(run_label(r) for r in runs if r["loss"] in losses))
    for env in envs:
        by_loss = {label: [r for r in runs if r["env"] == env and run_label(r) == label] for label in labels}
        by_loss = {label: group for label, group in by_loss.items() if group}
        levels = {}
        reference = next((label for label in REFERENCES if by_loss.get(label)), None)
        if reference is not None:
            ppo_final = statistics.median(r["eval/return"] for r in by_loss[reference])
            random_return = statistics.median(r["eval/random_return"] for r in by_loss[reference])
            for fraction in LEVELS:
                level = random_return + fraction * (ppo_final - random_return)
                ppo_time = statistics.median(first_time_at(r["curve"], level) for r in by_loss[reference])
                levels[fraction] = (level, ppo_time)
        for loss, group in by_loss.items():
            row = {"env": env, "loss": loss, "seeds": [r["seed"] for r in group], "reference": reference,
                   "final_return": C.spread([r["eval/return"] for r in group]),
                   "wall_s": C.spread([r["wall_time_s"] for r in group]),
                   "env_steps": C.spread([r["env_steps"] for r in group]),
                   "random_return": statistics.median(r["eval/random_return"] for r in group), "levels": {}}
            evaluating = [r.get("eval_time_s") for r in group]
            if all(t is not None and math.isfinite(t) for t in evaluating):  # runs that counted their evaluations
                row["eval_s"] = C.spread(evaluating)
            if all(r.get("gradient_health") for r in group):  # the gradient learners' whole runs
                row["gradient_health"] = {
                    key: C.spread([r["gradient_health"][key] for r in group])
                    for key in ("actor_grad_norm_median", "actor_grad_norm_max", "skipped_actor_updates")}
            if all(GYMNASIUM_RETURN in r for r in group):  # eval.gymnasium=true: the same policy scored in MuJoCo
                row["mujoco_return"] = C.spread([r[GYMNASIUM_RETURN] for r in group])
                row["transfer"] = C.spread([r[GYMNASIUM_RETURN] / r["eval/return"] if r["eval/return"] else math.nan
                                            for r in group])
            for fraction, (level, ppo_time) in levels.items():
                times = [first_time_at(r["curve"], level) for r in group]
                row["levels"][fraction] = {
                    "return": level, "time_s": statistics.median(times),
                    "env_steps": statistics.median(first_steps_at(r["curve"], level) for r in group),
                    "reached": reached(times),
                    "seeds_reached": [r["seed"] for r, t in zip(group, times) if math.isfinite(t)],
                    # PPO's median run met it at its first evaluation (the untrained policy): no race to it
                    "speedup_vs_ppo": None if ppo_time == 0 else speedup(ppo_time, statistics.median(times)),
                    "ppo_at_start": ppo_time == 0,
                }
            row["fixed_levels"] = {}
            for level in fixed_levels:
                times = [first_time_at(r["curve"], level) for r in group]
                row["fixed_levels"][level] = {
                    "time_s": statistics.median(times), "reached": reached(times), "times_s": times,
                    "env_steps": statistics.median(first_steps_at(r["curve"], level) for r in group)}
            summary.append(row)

    print("\n## time to solve (median over seeds; min-max in brackets; t: wall s to reach the level, "
          "seeds that reached it, speed-up vs PPO)")

    def rng(d, fmt):
        show = fmt if callable(fmt) else fmt.format
        return f"{show(d['median'])} [{show(d['min'])}, {show(d['max'])}]"

    def level_cell(row, fraction):
        cell = row["levels"].get(fraction)
        if cell is None:
            return "-"
        if not math.isfinite(cell["time_s"]):
            return f"never ({cell['reached']})"
        return (f"{cell['time_s']:.0f} s, {cell['env_steps'] / 1e3:,.0f}k steps ({cell['reached']}, "
                f"{against_ppo(cell)})")

    def fixed_cell(row, level):
        cell = row["fixed_levels"][level]
        times = ", ".join("never" if not math.isfinite(t) else f"{t:.1f}" for t in cell["times_s"])
        if not math.isfinite(cell["time_s"]):
            return f"never ({cell['reached']}: {times})"
        return f"{cell['time_s']:.1f} s, {cell['env_steps'] / 1e3:,.0f}k steps ({cell['reached']}: {times})"

    first = next((r for r in summary if r["levels"]), None)
    ppo_levels = LEVELS if first else ()  # PPO-relative levels need a PPO run
    # one env: the levels' values in the header; several: each env has its own (see each row's env's table)
    # several envs: each names its own PPO in ``own``; one env: the header says which PPO
    ppo = "PPO on Gymnasium's env" if len(envs) == 1 and first and first["reference"] != "ppo" else "PPO"
    own = " (the env's own" + ("; on Gymnasium's env where it has no PPO run here)"
                               if any(r["reference"] == "ppo:gymnasium" for r in summary) else ")")
    level_names = [f"{f'{ppo} final' if f == 1.0 else f'{f:.0%} of {ppo}'}"
                   + (f" = {C.fmt_return(first['levels'][f]['return'])}" if len(envs) == 1 else own)
                   for f in ppo_levels]
    in_mujoco = any("mujoco_return" in r for r in summary)
    with_health = any("gradient_health" in r for r in summary)
    with_eval_time = any("eval_s" in r for r in summary)

    def health_cells(row):
        if not with_health:
            return []
        health = row.get("gradient_health")
        if health is None:
            return ["-", "-"]
        return [rng(health["actor_grad_norm_median"], C.fmt_error), rng(health["skipped_actor_updates"], "{:.0f}")]

    def mujoco_cells(row):
        if not in_mujoco:
            return []
        if "mujoco_return" not in row:
            return ["-", "-"]
        return [rng(row["mujoco_return"], C.fmt_return), rng(row["transfer"], "{:.2f}")]

    table = C.print_table(
        ["env", "loss", "final eval return", *(["in Gymnasium's env", "kept there"] if in_mujoco else []),
         "random policy", "wall s", *(["of which evaluating s"] if with_eval_time else []), "env steps",
         *(["actor grad norm (median)", "skipped actor updates"] if with_health else []),
         *level_names, *[f"return >= {level:g}" for level in fixed_levels]],
        [[r["env"], r["loss"], rng(r["final_return"], C.fmt_return), *mujoco_cells(r), C.fmt_return(r["random_return"]),
          rng(r["wall_s"], "{:.0f}"), *([rng(r["eval_s"], "{:.0f}") if "eval_s" in r else "-"] if with_eval_time else []),
          f"{r['env_steps']['median']:,.0f}", *health_cells(r),
          *[level_cell(r, f) for f in ppo_levels], *[fixed_cell(r, lv) for lv in fixed_levels]]
         for r in summary],
    )
    return summary, table


def against_ppo(cell: dict) -> str:
    """A level cell's speed-up against PPO, or why there is none: PPO's untrained policy (its
    first evaluation) already scores the level, so PPO's final return is below its start."""
    return "PPO's start is above it" if cell.get("ppo_at_start") else C.fmt_ratio(cell["speedup_vs_ppo"])


def seed_counts(runs: list[dict]) -> str:
    """``3 seeds``, or per row where the rows differ: ``seeds: ppo 1, shac 3``."""
    seeds: dict[str, set] = {}
    for r in runs:
        seeds.setdefault(run_label(r), set()).add(r["seed"])
    counts = {label: len(s) for label, s in seeds.items()}
    if len(set(counts.values())) == 1:
        n = next(iter(counts.values()))
        return f"{n} seed{'s' if n > 1 else ''}"
    return "seeds: " + ", ".join(f"{label} {n}" for label, n in counts.items())


def overview_table(summary: list[dict]) -> dict:
    """One row per env and learner: the final return here and in Gymnasium's own env, and the time
    to PPO's final median with its speed-up: the race at a glance."""
    def rng(d):
        return f"{C.fmt_return(d['median'])} [{C.fmt_return(d['min'])}, {C.fmt_return(d['max'])}]"

    def to_ppo(row):
        cell = row["levels"].get(1.0)
        if cell is None:
            return "-"
        if cell.get("ppo_at_start"):  # no race to PPO's final: its untrained policy already scores it
            return "- (PPO ends below its start)"
        if not math.isfinite(cell["time_s"]):
            return f"never ({cell['reached']})"
        t = cell["time_s"]
        when = f"{t:.0f} s" if t < 120 else f"{t / 60:.0f} min"
        return f"{when} ({cell['reached']}, {against_ppo(cell)})"

    rows = [[r["env"], f"{r['loss']} ({len(r['seeds'])})", rng(r["final_return"]),
             rng(r["mujoco_return"]) if "mujoco_return" in r else "-", to_ppo(r)] for r in summary]
    return C.data_table("The race at a glance: median [min, max] over seeds (their count in brackets); time to PPO's "
                        "final median (seeds that reached it, speed-up against PPO)",
                        ["task", "learner (seeds)", "final return", "in Gymnasium's env", "time to PPO's final"], rows)


def write_summary_data(args, envs, runs, table, per_env_tables=None, threads: int | None = None,
                       cpu_models: Sequence[str] = (), summary: list[dict] | None = None) -> None:
    """The docs' data file of a summary table (``data=``; see ``_common.write_data``): the table
    under ``levels``, and with several envs one table per env too (under the env's name), whose
    PPO-relative columns name that env's own levels, and (``summary``) the `overview_table`
    under ``overview``. Each title counts the seeds of its rows; ``threads``: the torch threads
    of the runs, ``cpu_models`` their CPUs (summarising earlier result files)."""
    cells = "t, env steps (seeds that reached it, speed-up against PPO)"
    tables = {"levels": C.data_table(
        f"Time to solve: {', '.join(envs)} ({seed_counts(runs)}; median [min, max]; {cells})", *C.table_cells(table))}
    for env, env_table in (per_env_tables or {}).items():
        env_runs = [r for r in runs if r["env"] == env]
        tables[env] = C.data_table(f"{env} ({seed_counts(env_runs)}; median [min, max]; {cells})",
                                   *C.table_cells(env_table))
    if summary is not None:
        tables["overview"] = overview_table(summary)
    measured = {"machine": C.machine_name(threads=threads, models=cpu_models)} if threads is not None else None
    C.write_data(args, "time_to_solve_" + "_".join(envs), tables, source="time_to_solve", measured=measured)


def env_levels(items: list[str], envs: list[str]) -> dict[str, list[float]]:
    """``["Hopper-v5=547", ...]`` -> ``{env: [levels]}`` for every env of ``envs``."""
    levels = {env: [] for env in envs}
    for item in items:
        env, _, value = item.partition("=")
        if env not in levels:
            raise SystemExit(f"time_to_solve: env_levels names {env!r}, which no summarised run has; "
                             f"valid: {', '.join(envs)}")
        try:
            levels[env].append(float(value))
        except ValueError:
            raise SystemExit(f"time_to_solve: env_levels expects ENV=RETURN (a number), got {item!r}") from None
    return levels


def summarised_files(patterns: Sequence[str]) -> list[str]:
    """The result files of ``summarise=[...]``: each item a file, or a pattern with ``*`` that
    stands for the files it matches (sorted), e.g. ``docs/data/runs/race_mujoco/*.json``."""
    files = []
    for pattern in patterns:
        if "*" not in pattern:
            files.append(pattern)
            continue
        matched = sorted(glob.glob(pattern))
        if not matched:
            raise SystemExit(f"time_to_solve: summarise: no result file matches {pattern!r}")
        files += matched
    return files


def summarise_files(args) -> dict:
    """``summarise=[a.json, ...]``: the runs of earlier result files merged and summarised again.

    Runs of the same env, loss, variant and seed in two files are refused (one would silently
    replace the other); PPO-relative levels need PPO's runs of each env among the files."""
    runs, infos = [], []
    for name in summarised_files(args.summarise):
        path = Path(name)
        if not path.is_file():
            raise SystemExit(f"time_to_solve: summarise: no result file {name!r}")
        payload = json.loads(path.read_text())
        if payload.get("benchmark") != "time_to_solve" or "runs" not in payload:
            raise SystemExit(f"time_to_solve: summarise: {name!r} is not a time_to_solve result file (out=)")
        runs += payload["runs"]
        infos.append(payload.get("info"))
    keys = [(r["env"], run_label(r), r["seed"]) for r in runs]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise SystemExit(f"time_to_solve: summarise: these runs appear more than once: {repeated}")
    envs = list(dict.fromkeys(r["env"] for r in runs))
    losses = list(dict.fromkeys(r["loss"] for r in runs))
    own_levels = env_levels(args.env_levels, envs)
    summary, table = summarise(runs, envs, losses, [*args.levels, *(own_levels[envs[0]] if len(envs) == 1 else [])])
    files = summarised_files(args.summarise)
    payload = {"benchmark": "time_to_solve", "info": infos[0], "summary": summary, "runs": runs, "table": table,
               "merged_from": [C.portable_path(f) for f in files]}
    C.write_json("time_to_solve", payload, args.out or (files[0] if len(files) == 1 else None))
    if args.data:  # re-summarising alone never replaces a page's data
        per_env = {env: summarise([r for r in runs if r["env"] == env], [env], losses,
                                  [*args.levels, *own_levels[env]])[1]
                   for env in envs} if len(envs) > 1 else None
        threads = {(info or {}).get("torch_threads") for info in infos}
        # the CPU models the runs recorded (result files written before benchmarks recorded it have none)
        models = [(info or {}).get("cpu_model") for info in infos]
        write_summary_data(args, envs, runs, table, per_env, threads=threads.pop() if len(threads) == 1 else None,
                           cpu_models=[m for m in models if m] or ["CPU not recorded"], summary=summary)
    return payload


@dataclass(frozen=True)
class TimeToSolveSettings(C.BenchmarkSettings):
    envs: list[str] | None = None  # envs (default: pendulum cartpole)
    losses: list[str] = checked(list(DEFAULT_LOSSES), checks.each(checks.one_of(LOSSES)))
    seeds: list[int] | None = None  # seeds (default 0 1 2)
    steps: list[str] = checked([], checks.each(lambda v: None if "=" in str(v) else "expected LOSS=N"))  # budgets
    eval_interval: int | None = None  # env steps between evaluations
    override: list[str] = field(default_factory=list)  # extra Hydra overrides for every run
    # LABEL=OVERRIDES: run every loss once per variant, with these space-separated Hydra overrides
    variant: list[str] = field(default_factory=list)
    levels: list[float] = field(default_factory=list)  # also report the wall time to reach these returns
    # ENV=RETURN: a level of that env only (its own table), e.g. another race's PPO final median when the
    # PPO runs are not among the summarised files
    env_levels: list[str] = checked([], checks.each(lambda v: None if "=" in str(v) else "expected ENV=RETURN"))
    keep_runs: str | None = None  # keep the run directories here
    # continue each run whose directory under keep_runs holds a checkpoint (checkpoints/last.pt) from it
    resume: bool = False
    # only summarise earlier result files (JSON, out= of earlier runs): their runs merged, e.g. one file per task
    # and seed from runs side by side; with data= the summary is also the docs' data file
    summarise: list[str] | None = None


def main(argv=None) -> dict:
    args = parse_cli(TimeToSolveSettings, argv, __doc__)
    if args.summarise is not None:
        return summarise_files(args)
    C.setup_threads(args.threads)
    train_script = load_train_script()

    quick = args.quick
    envs = args.envs or (["pendulum"] if quick else ["pendulum", "cartpole"])
    seeds = args.seeds if args.seeds is not None else ([0] if quick else [0, 1, 2])
    budgets = dict(item.split("=", 1) for item in args.steps)
    variants = parse_variants(args.variant) or [("", [])]
    info = C.versions()
    C.print_header("time to solve (sota_scripts/train.py, interleaved runs)", info)
    if args.resume and not args.keep_runs:
        raise SystemExit("time_to_solve: resume=true continues the runs kept in keep_runs=DIR; give the directory "
                         "of the runs to continue")
    runs_root = Path(args.keep_runs) if args.keep_runs else Path(tempfile.mkdtemp(prefix="time_to_solve_"))

    # every run's configuration is composed before the first run starts: a mistyped override fails
    # at once, not after hours of the runs before it
    plan = []
    for seed in seeds:
        for env in envs:
            for loss, (variant, variant_overrides) in itertools.product(args.losses, variants):
                overrides = [f"env={env}", f"loss={loss}", f"seed={seed}", "logger=none",
                             "train.progress_bar=false", "eval.gif=false"]
                if quick:
                    overrides += QUICK["common"] + QUICK[loss]
                if args.eval_interval:
                    overrides.append(f"eval.interval={args.eval_interval}")
                if loss in budgets:
                    overrides.append(f"train.total_env_steps={budgets[loss]}")
                overrides += args.override + variant_overrides
                run_dir = runs_root / f"{env}_{loss}{'_' + variant if variant else ''}_seed{seed}"
                resumed_at = kept_run_checkpoint(run_dir, overrides, args.resume)
                try:
                    cfg = C.compose(overrides)
                except Exception as error:  # Hydra's composition errors name the override
                    raise SystemExit(f"time_to_solve: the run {env} {loss} {variant or ''} seed {seed} does not "
                                     f"compose ({' '.join(overrides)}): {error}") from None
                if resumed_at is not None:
                    cfg.resume = str(run_dir / "checkpoints" / "last.pt")  # train.py's resume=
                if cfg.eval.get("only_gymnasium"):
                    raise SystemExit("time_to_solve: eval.only_gymnasium=true leaves the runs without this library's "
                                     "evaluation returns, which the race reads (eval.gymnasium=true puts Gymnasium's "
                                     "beside them): drop eval.only_gymnasium")
                plan.append((seed, env, variant, overrides, run_dir, cfg, resumed_at))
    runs = []
    for seed, env, variant, overrides, run_dir, cfg, resumed_at in plan:
        if resumed_at is not None:
            print(f"# {run_dir.name}: resuming {cfg.resume} at env step {resumed_at:,}")
        wall, cpu = C.timed(lambda: runs.append(train_script.run(cfg, run_dir, overrides)))
        result = C.portable_run(runs[-1], runs_root)
        # process_*_s: this process's part of the run (wall_time_s, the run's, counts on across resumes)
        result.update({"overrides": overrides, "variant": variant, "curve": eval_curve(run_dir),
                       "gradient_health": gradient_health(run_dir),
                       "process_wall_s": wall, "process_cpu_s": cpu,
                       "total_env_steps": int(cfg.train.total_env_steps),
                       "resumed_from_env_steps": resumed_at})
        print(f"# {env} {run_label(result)} seed {seed}: eval return {result['eval/return']:.4g} after "
              f"{result['env_steps']:,} env steps, {result['wall_time_s']:.1f} s")

    summary, table = summarise(runs, envs, args.losses, args.levels)
    for r in runs:
        r["curve"] = [list(p) for p in r["curve"]]
    payload = {"benchmark": "time_to_solve", "info": info, "summary": summary, "runs": runs, "table": table}
    C.write_json("time_to_solve" + ("_quick" if quick else ""), payload, args.out)
    write_summary_data(args, envs, runs, table, summary=summary)
    if args.keep_runs is None:
        shutil.rmtree(runs_root, ignore_errors=True)
    return payload


if __name__ == "__main__":
    main()
