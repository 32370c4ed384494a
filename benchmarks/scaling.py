"""Data-parallel scaling: the same training run with 1 and 2 ranks under torchrun.

Each configuration is ``torchrun --standalone --nproc_per_node=K sota_scripts/train.py ...`` with
one torch thread per rank. ``scaling=strong`` (default) keeps the *global* batch: ``env.num_envs``
and PPO's ``loss.minibatch_size`` (SAC's ``loss.batch_size``) are divided by ``K``, so that ``K``
ranks run the algorithm of the 1-rank run (tests/training/test_distributed.py checks that equivalence) and
only the wall time may change. ``scaling=weak`` keeps the per-rank batch (``num_envs`` envs on
every rank): ``K`` times the env steps per iteration, a larger batch for the learner.

Reported per loss and rank count, over seeds (median, min-max): training env-steps/s (median of
the logged per-iteration rates: collection and updates, evaluations excluded), the whole run's
env-steps/s (evaluations on rank 0 included), the final evaluation return, and the wall time to
reach ``level`` (default 74.2: PPO's final pendulum return in docs/performance.md).
Scaling efficiency: ``rate(K) / (K x rate(1))``.

    python benchmarks/scaling.py                                  # shac and ppo, 1 and 2 ranks, seeds 0 1 2
    python benchmarks/scaling.py losses=[shac] seeds=[0] ranks=[1,2]
    python benchmarks/scaling.py scaling=weak env=HalfCheetah-v5 losses=[shac] seeds=[0] eval_interval=1000000 \
        override=[train.total_env_steps=32768]
    python benchmarks/scaling.py quick=true                       # tiny runs: a smoke test
"""
from __future__ import annotations

import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from time_to_solve import eval_curve, first_time_at  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "sota_scripts" / "train.py"
LOSSES = ("shac", "ppo", "bptt", "sac")
PER_RANK_BATCH = {"ppo": ("loss.minibatch_size", 512), "sac": ("loss.batch_size", 256)}  # global value, split
QUICK = ["env.max_episode_steps=12", "eval.num_envs=2", "eval.interval=64", "train.total_env_steps=256",
         "loss.actor.hidden=[16]"]


@dataclass(frozen=True)
class ScalingSettings(C.BenchmarkSettings):
    env: str = "pendulum"
    losses: list[str] = checked(["shac", "ppo"], checks.each(checks.one_of(LOSSES)))
    ranks: list[int] = checked([1, 2], checks.each(checks.positive_int))
    seeds: list[int] | None = None  # default 0 1 2 (quick: 0)
    num_envs: int = checked(64, checks.positive_int)  # strong: global, each of K ranks num_envs / K; weak: per rank
    scaling: str = checked("strong", checks.one_of(("strong", "weak")))
    level: float = 74.2  # the return whose time to reach is reported
    eval_interval: int = checked(20_000, checks.positive_int)
    override: list[str] = checked([], checks.each(lambda v: None if "=" in str(v) else "expected KEY=VALUE"))
    keep_runs: str | None = None  # keep the run directories here


def launch(run_dir: Path, ranks: int, overrides: list[str]) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}",
               str(SCRIPT), *overrides, f"hydra.run.dir={run_dir}"]
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"scaling: {' '.join(command)} failed:\n{done.stderr[-3000:]}")
    result = json.loads((run_dir / "final_metrics.json").read_text())
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    rates = [row["time/steps_per_s"] for row in rows if "time/steps_per_s" in row]
    result["train_steps_per_s"] = statistics.median(rates[1:] or rates)  # the first iteration warms up
    result["curve"] = eval_curve(run_dir)
    return result


def main(argv=None) -> dict:
    args = parse_cli(ScalingSettings, argv, __doc__)
    bad = [k for k in args.ranks if args.num_envs % k and args.scaling == "strong"]
    if bad:
        raise SystemExit(f"scaling: num_envs={args.num_envs} must split evenly over ranks={bad}")
    seeds = args.seeds if args.seeds is not None else ([0] if args.quick else [0, 1, 2])
    info = C.versions() | {"cpus": os.cpu_count()}
    C.print_header(f"data-parallel {args.scaling} scaling (torchrun, one thread per rank)", info)
    runs_root = Path(args.keep_runs) if args.keep_runs else Path(tempfile.mkdtemp(prefix="scaling_"))

    runs = []
    for seed in seeds:
        for loss in args.losses:
            for k in args.ranks:  # interleaved, so that load from other processes spreads over all
                split = k if args.scaling == "strong" else 1
                overrides = [f"env={args.env}", f"loss={loss}", f"seed={seed}", f"env.num_envs={args.num_envs // split}",
                             "logger=none", "train.progress_bar=false", "eval.gif=false",
                             f"eval.interval={args.eval_interval}"]
                if loss in PER_RANK_BATCH:
                    key, default = PER_RANK_BATCH[loss]
                    overrides.append(f"{key}={max(1, default // split)}")
                overrides += QUICK if args.quick else []
                result = launch(runs_root / f"{loss}_ranks{k}_seed{seed}", k, overrides + args.override)
                result.update({"ranks": k, "overrides": overrides,
                               "time_to_level_s": first_time_at(result["curve"], args.level)})
                runs.append(result)
                print(f"# {loss} ranks={k} seed={seed}: {result['train_steps_per_s']:,.0f} env-steps/s training, "
                      f"eval return {result['eval/return']:.4g}, {result['wall_time_s']:.1f} s, "
                      f"{args.level} reached at {result['time_to_level_s']:.1f} s")

    rows, summary = [], []
    for loss in args.losses:
        base = None
        for k in args.ranks:
            group = [r for r in runs if r["loss"] == loss and r["ranks"] == k]
            rate = statistics.median(r["train_steps_per_s"] for r in group)
            whole = statistics.median(r["steps_per_s"] for r in group)
            times = [r["time_to_level_s"] for r in group]
            to_level = statistics.median(times)
            base = base or (k, rate, whole, to_level)
            efficiency = rate / (k / base[0] * base[1])
            speedup = base[3] / to_level if math.isfinite(to_level) and math.isfinite(base[3]) else None
            row = {"loss": loss, "ranks": k, "train_steps_per_s": C.spread([r["train_steps_per_s"] for r in group]),
                   "run_steps_per_s": whole, "efficiency": efficiency,
                   "final_return": C.spread([r["eval/return"] for r in group]),
                   "time_to_level_s": times, "speedup_to_level": speedup}
            summary.append(row)
            reached = sum(math.isfinite(t) for t in times)
            rows.append([
                loss, k, f"{C.fmt_rate(rate)} [{C.fmt_rate(row['train_steps_per_s']['min'])}, "
                         f"{C.fmt_rate(row['train_steps_per_s']['max'])}]",
                C.fmt_rate(whole), f"{efficiency:.0%}",
                f"{row['final_return']['median']:.4g} [{row['final_return']['min']:.4g}, {row['final_return']['max']:.4g}]",
                ("never" if not math.isfinite(to_level) else f"{to_level:.1f} s") + f" ({reached}/{len(times)})",
                C.fmt_ratio(speedup),
            ])
    batch = f"global batch {args.num_envs} envs" if args.scaling == "strong" else f"{args.num_envs} envs per rank"
    print(f"\n## {args.env}, {args.scaling} scaling: {batch}, one thread per rank (median over seeds {seeds})")
    table = C.print_table(["loss", "ranks", "training env-steps/s", "run env-steps/s", "scaling efficiency",
                           "final eval return", f"time to {args.level}", "speed-up"], rows)
    for r in runs:
        r["curve"] = [list(p) for p in r["curve"]]
    payload = {"benchmark": "scaling", "info": info, "settings": vars(args) if hasattr(args, "__dict__") else {},
               "summary": summary, "runs": runs, "table": table}
    C.write_json(f"scaling_{args.scaling}" + ("_quick" if args.quick else ""), payload, args.out)
    data_name = f"scaling_{args.scaling}" + ("" if args.env == "pendulum" else f"_{args.env}")
    C.write_data(args, data_name, {"scaling": C.data_table(
        f"Data parallel, {args.env}, {args.scaling} scaling ({batch}), one torch thread per rank "
        "(medians [min, max] over seeds)", *C.table_cells(table))}, source="scaling")
    if args.keep_runs is None:
        shutil.rmtree(runs_root, ignore_errors=True)
    return payload


if __name__ == "__main__":
    main()
