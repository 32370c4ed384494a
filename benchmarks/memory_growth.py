"""Memory over a long training run: does it stay flat?

Runs ``python sota_scripts/train.py`` for ``iterations`` iterations of each ``runs`` entry
(``ENV:LOSS``, with the run's tuned file and ``env.num_envs``), one after the other, evaluations
and checkpoints at their usual spacing, and reads back the memory every training row records
(``memory/rss_mib``: the process's resident memory; ``memory/cuda_allocated_mib`` on a GPU). It
reports, per run, the memory after the first tenth of the iterations (the warm-up: allocator
pools, compiled kernels, replay buffers filling) and at the end, and the slope of a least-squares
line through the rows after the warm-up, in MiB per 1000 iterations: a leak of a tensor per
iteration shows as a positive slope::

    python benchmarks/memory_growth.py                                  # 10k iterations, CPU
    python benchmarks/memory_growth.py runs=[HalfCheetah-v5:ahac] iterations=2000 device=cuda
    python benchmarks/memory_growth.py from_metrics=[pendulum:shac=PATH]  # summarise runs' metrics.jsonl
                                                                          # (train_dir= keeps them)

Results: ``benchmarks/results/memory_growth.json`` (or ``out=``) and ``docs/data/memory_growth.json``.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

KEYS = ("memory/rss_mib", "memory/cuda_allocated_mib")


@dataclass(frozen=True)
class MemoryGrowthSettings(C.BenchmarkSettings):
    runs: list[str] = field(default_factory=lambda: ["pendulum:shac", "HalfCheetah-v5:bptt"])  # ENV:LOSS
    iterations: int = checked(10_000, checks.positive_int)  # training iterations of each run
    num_envs: int = checked(16, checks.positive_int)
    log_interval: int = checked(10, checks.positive_int)  # iterations between training rows
    device: str = "cpu"
    train_dir: str | None = None  # keep the runs' directories here (default: a temporary directory)
    from_metrics: list[str] | None = None  # ENV:LOSS=PATH of metrics.jsonl files: summarise them, train nothing


def _split(run: str) -> tuple[str, str]:
    env, sep, loss = run.partition(":")
    if not sep or not env or not loss:
        raise SystemExit(f"runs: expected ENV:LOSS, got {run!r}")
    return env, loss


def slope_per_1000(points: list[tuple[int, float]]) -> float:
    """The least-squares slope of ``(iteration, MiB)`` points, in MiB per 1000 iterations."""
    n = len(points)
    mean_x = sum(x for x, _ in points) / n
    mean_y = sum(y for _, y in points) / n
    spread = sum((x - mean_x) ** 2 for x, _ in points)
    return 1000 * sum((x - mean_x) * (y - mean_y) for x, y in points) / spread if spread else 0.0


def summarise(label: str, metrics: Path) -> dict:
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    out = {"run": label}
    for key in KEYS:
        points = [(r["time/iteration"], r[key]) for r in rows if key in r and "time/iteration" in r]
        if not points:
            continue
        last_iteration = points[-1][0]
        settled = [p for p in points if p[0] >= last_iteration / 10]  # after the warm-up
        out[key] = {"iterations": int(last_iteration), "after_warmup": settled[0][1], "end": points[-1][1],
                    "peak": max(y for _, y in points), "slope_per_1000": slope_per_1000(settled)}
    if len(out) == 1:
        out["error"] = f"no memory rows in {metrics} (a training row records them)"
    return out


def train(env: str, loss: str, args, run_dir: Path) -> Path:
    """One train.py run of ``args.iterations`` iterations: its metrics.jsonl."""
    # iterations -> the env-step budget: each env's steps per iteration are the loss's window
    # (horizon) or rollout length (AHAC's adaptive horizon starts at its configured one)
    C.load_train_script()  # registers the generated loss configs that composing needs
    cfg = C.compose([f"env={env}", f"loss={loss}", f"env.num_envs={args.num_envs}"])
    per_env = cfg.loss.get("horizon") or cfg.loss.get("rollout_len")
    if not per_env:
        raise SystemExit(f"memory_growth: loss={loss} has neither loss.horizon nor loss.rollout_len")
    command = [sys.executable, str(C.REPO_ROOT / "sota_scripts" / "train.py"), f"env={env}", f"loss={loss}",
               f"device={args.device}", "seed=0", "logger=csv", "eval.gif=false", "train.progress_bar=false",
               f"env.num_envs={args.num_envs}", f"train.total_env_steps={args.iterations * args.num_envs * per_env}",
               f"train.log_interval={args.log_interval}", f"hydra.run.dir={run_dir}"]
    env_vars = {**os.environ, "WANDB_MODE": "disabled", "OMP_NUM_THREADS": str(args.threads)}
    with open(run_dir.parent / f"{env}_{loss}.log", "w") as log:
        code = subprocess.call(command, stdout=log, stderr=subprocess.STDOUT, env=env_vars)
    if code != 0:
        raise SystemExit(f"memory_growth: train.py {env} {loss} exited with {code}: see {log.name}")
    return run_dir / "metrics.jsonl"


def main(argv=None) -> dict:
    args = parse_cli(MemoryGrowthSettings, argv, __doc__)
    C.setup_threads(args.threads)  # the runs' threads too (OMP_NUM_THREADS)
    if args.from_metrics is not None:
        metrics = {}
        for item in args.from_metrics:
            label, sep, path = str(item).partition("=")
            if not sep:
                raise SystemExit(f"from_metrics: expected ENV:LOSS=PATH items, got {item!r}")
            metrics[label] = Path(path)
    else:
        C.setup_device(args.device)
        root = Path(args.train_dir or tempfile.mkdtemp(prefix="memory_growth_"))
        root.mkdir(parents=True, exist_ok=True)
        metrics = {}
        for run in args.runs:
            env, loss = _split(run)
            metrics[run] = train(env, loss, args, root / run.replace(":", "_"))
    results = [summarise(label, path) for label, path in metrics.items()]
    headers = ["run", "memory", "iterations", "after warm-up (MiB)", "end (MiB)", "peak (MiB)",
               "slope (MiB per 1000 iterations)"]
    table = []
    for r in results:
        if "error" in r:
            table.append([r["run"], "", "", r["error"], "", "", ""])
        for key, name in zip(KEYS, ("resident (RSS)", "CUDA tensors")):
            if key in r:
                m = r[key]
                table.append([r["run"], name, f"{m['iterations']:,}", f"{m['after_warmup']:.0f}", f"{m['end']:.0f}",
                              f"{m['peak']:.0f}", f"{m['slope_per_1000']:+.2f}"])
    C.print_table(headers, table)
    payload = {"benchmark": "memory_growth", "date": C.today(), "info": C.versions(), "results": results}
    C.write_json("memory_growth", payload, args.out)
    C.write_data(args, "memory_growth", {"memory": C.data_table(
        "Memory over a training run (train.py): after the first tenth of the iterations, at the end, and the "
        "slope after it", headers, table)},
        device=args.device)
    return payload


if __name__ == "__main__":
    main()
