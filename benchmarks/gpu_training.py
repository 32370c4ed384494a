"""train.py on a GPU against the CPU race: how long each learner takes to reach tuned PPO's final
return in MuJoCo.

Each learner of ``learners`` trains HalfCheetah-v5 (``env=``) with ``python sota_scripts/train.py
device=cuda`` for its seconds (``seconds=[LOSS=S]``, default ``default_s``; then SIGTERM, which
ends a run cleanly with a checkpoint), one run after the other so that neither slows the other.
PPO runs with massively parallel settings (4096 envs, 20-step rollouts, Brax's discount and
entropy, constant learning rate), a gradient learner with its tuned file and 1024 envs. Every
evaluation is played in Gymnasium's own env alone (``eval.gymnasium=true eval.only_gymnasium=true``:
MuJoCo's C step on the CPU; this library's own evaluation, 32 envs stepped a thousand times in a
row, is bound by kernel launches on a GPU).

The report, per learner: the env steps and wall-clock seconds (training and evaluations) at
which its MuJoCo return first reaches the target, the median final MuJoCo return of tuned PPO in
the CPU race (``race=``, its raw results: ``docs/data/runs/race_mujoco/<env>_s*_ppo.json``), its
best and last MuJoCo return, and its env steps per second::

    python benchmarks/gpu_training.py seconds=[ppo=215,ahac=80]          # on a GPU: trains, then reports
    python benchmarks/gpu_training.py from_metrics=[ppo=a.jsonl,ahac=b.jsonl] gpu="NVIDIA H200"

``from_metrics`` summarises earlier runs' ``metrics.jsonl`` (``train_dir`` keeps each run's
directory, ``<train_dir>/<loss>/metrics.jsonl``). Results: ``benchmarks/results/gpu_training.json``
(or ``out=``) and ``docs/data/gpu_training.json``.
"""
from __future__ import annotations

import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402

# what each learner's run sets beyond its tuned file (PPO: Brax-style massively parallel settings)
LEARNER_OVERRIDES = {
    "ppo": ["env.num_envs=4096", "loss.rollout_len=20", "loss.minibatch_size=10240", "loss.epochs=8",
            "loss.lr_schedule=constant", "loss.gamma=0.95", "loss.entropy_coeff=1e-3", "eval.interval=500000"],
    "ahac": ["env.num_envs=1024", "eval.interval=200000"],
    "shac": ["env.num_envs=1024", "eval.interval=200000"],
    "sapo": ["env.num_envs=1024", "eval.interval=200000"],
}


def _label_values(values: list[str], what: str, valid: list[str]) -> dict[str, str]:
    out = {}
    for item in values:
        label, sep, value = str(item).partition("=")
        if not sep or not label:
            raise SystemExit(f"{what}: expected LOSS=VALUE items, got {item!r}")
        if label not in valid:
            raise SystemExit(f"{what}: {label!r} is not a learner of this run; valid: {valid}")
        out[label] = value
    return out


@dataclass(frozen=True)
class GPUTrainingSettings(C.BenchmarkSettings):
    env: str = "HalfCheetah-v5"
    learners: list[str] = checked(["ppo", "ahac"], checks.each(checks.one_of(tuple(LEARNER_OVERRIDES))))
    seconds: list[str] = checked([], checks.each(lambda v: None if "=" in str(v) else "expected LOSS=SECONDS"))
    default_s: int = checked(100, checks.positive_int)  # seconds of a learner not named in seconds=
    seed: int = checked(0, checks.nonnegative_int)
    device: str = "cuda"
    train_dir: str | None = None  # keep the runs' directories here (default: a temporary directory)
    from_metrics: list[str] | None = None  # LOSS=PATH of metrics.jsonl files: summarise them, train nothing
    gpu: str | None = None  # with from_metrics: the GPU they ran on, for the data file's machine
    race: str = "docs/data/runs/race_mujoco"  # the CPU race's raw results (the target: PPO's final median)


def cpu_ppo_target(race: Path, env: str) -> tuple[float, list[str]]:
    """The median over seeds of tuned PPO's final MuJoCo return in the CPU race, and its files."""
    files = sorted(race.glob(f"{env}_s*_ppo.json"))
    finals = []
    for path in files:
        summary = json.loads(path.read_text())["summary"][0]
        finals.append(summary["mujoco_return"]["median"])
    if not finals:
        raise SystemExit(f"race={race}: no {env}_s*_ppo.json results there (the CPU race's raw results)")
    return statistics.median(finals), [str(p.relative_to(C.REPO_ROOT) if p.is_relative_to(C.REPO_ROOT) else p)
                                       for p in files]


def curve(metrics: Path) -> tuple[list[tuple[int, float, float]], float | None]:
    """``(env steps, wall s, MuJoCo return)`` of each evaluation, and the training env-steps/s
    (median of the logged iterations'). A last line cut off by the run's end is skipped."""
    points, rates, wall = [], [], 0.0
    for line in metrics.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        wall = row.get("time/wall_s", wall)
        if "time/steps_per_s" in row:
            rates.append(row["time/steps_per_s"])
        if "eval/gymnasium_return" in row:
            points.append((row["env_steps"], wall, row["eval/gymnasium_return"]))
    return points, (statistics.median(rates) if rates else None)


def summarise(label: str, metrics: Path, target: float, exit_code: int | None = None) -> dict:
    if exit_code not in (None, 0, -signal.SIGTERM, 128 + signal.SIGTERM):
        return {"learner": label, "error": f"train.py exited with {exit_code}: see {metrics.parent.parent / label}.log"}
    if not metrics.is_file():
        return {"learner": label, "error": f"no {metrics}: the run wrote no metrics"}
    points, rate = curve(metrics)
    if not points:
        return {"learner": label, "error": f"no eval/gymnasium_return in {metrics}"}
    reached = next(((steps, wall) for steps, wall, ret in points if ret >= target), None)
    return {"learner": label, "evaluations": points, "training_env_steps_per_s": rate,
            "reached_steps": None if reached is None else reached[0],
            "reached_wall_s": None if reached is None else reached[1],
            "evaluated_every": (statistics.median(b[0] - a[0] for a, b in zip(points, points[1:]))
                                if len(points) > 1 else None),
            "best_return": max(ret for _, _, ret in points), "last_return": points[-1][2],
            "last_env_steps": points[-1][0], "last_wall_s": points[-1][1]}


def train(label: str, seconds: int, args, run_dir: Path) -> tuple[Path, int]:
    """One train.py run on the GPU, stopped by SIGTERM after ``seconds``; its metrics.jsonl and
    exit code."""
    command = [sys.executable, str(C.REPO_ROOT / "sota_scripts" / "train.py"), f"env={args.env}", f"loss={label}",
               f"device={args.device}", f"seed={args.seed}", "logger=csv", "eval.gif=false",
               "train.progress_bar=false", "eval.gymnasium=true", "eval.only_gymnasium=true",
               "train.checkpoint_interval=100000000", "train.total_env_steps=100000000",
               *LEARNER_OVERRIDES[label], f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONUNBUFFERED": "1"}
    with open(run_dir.parent / f"{label}.log", "w") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            process.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            process.terminate()  # SIGTERM: the run ends after its iteration, with a checkpoint
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    return run_dir / "metrics.jsonl", process.returncode


def main(argv=None) -> dict:
    args = parse_cli(GPUTrainingSettings, argv, __doc__)
    target, race_files = cpu_ppo_target(Path(args.race) if Path(args.race).is_absolute()
                                        else C.REPO_ROOT / args.race, args.env)
    print(f"# target: tuned PPO's final MuJoCo return in the CPU race, median of {len(race_files)} seeds: "
          f"{target:.1f}", flush=True)
    if args.from_metrics is not None:
        given = _label_values(args.from_metrics, "from_metrics", list(LEARNER_OVERRIDES))
        metrics = {label: (Path(path), None) for label, path in given.items()}
        machine, info = args.gpu or "a GPU", {"from_metrics": given}
    else:
        C.setup_device(args.device)
        seconds = {}
        for label, value in _label_values(args.seconds, "seconds", args.learners).items():
            if not value.isdigit() or int(value) < 1:
                raise SystemExit(f"seconds: {label}={value!r}: expected a whole number of seconds >= 1")
            seconds[label] = int(value)
        root = Path(args.train_dir or tempfile.mkdtemp(prefix="gpu_training_"))
        root.mkdir(parents=True, exist_ok=True)
        metrics = {}
        for label in args.learners:
            tic = time.perf_counter()
            metrics[label] = train(label, seconds.get(label, args.default_s), args, root / label)
            print(f"# {label}: {time.perf_counter() - tic:.0f} s", flush=True)
        machine, info = C.machine_name(args.device), C.versions()
    rows = [summarise(label, path, target, code) for label, (path, code) in metrics.items()]
    headers = ["learner", "envs", f"time to {target:.0f} in MuJoCo", "env steps then", "evaluated every (env steps)",
               "best MuJoCo return", "last (env steps, s)", "training env-steps/s"]
    table = []
    for row in rows:
        if "error" in row:
            table.append([row["learner"], "", row["error"], "", "", "", "", ""])
            continue
        reached = "not reached" if row["reached_wall_s"] is None else f"{row['reached_wall_s']:.0f} s"
        envs = [o.split("=")[1] for o in LEARNER_OVERRIDES.get(row["learner"], []) if o.startswith("env.num_envs=")]
        table.append([row["learner"], envs[0] if envs else "tuned file",
                      reached, "-" if row["reached_steps"] is None else f"{row['reached_steps']:,}",
                      "-" if row["evaluated_every"] is None else f"{row['evaluated_every']:,.0f}",
                      f"{row['best_return']:.0f}",
                      f"{row['last_return']:.0f} ({row['last_env_steps']:,}, {row['last_wall_s']:.0f} s)",
                      C.fmt_rate(row["training_env_steps_per_s"])])
    C.print_table(headers, table)
    payload = {"benchmark": "gpu_training", "date": C.today(), "env": args.env, "target": target,
               "race_files": race_files, "machine": machine, "info": info, "results": rows}
    C.write_json("gpu_training", payload, args.out)
    C.write_data(args, "gpu_training", {"time_to_ppo": C.data_table(
        f"{args.env}, train.py on one GPU, scored in Gymnasium's own env: time to tuned PPO's final MuJoCo "
        f"return in the CPU race ({target:.0f}, median of {len(race_files)} seeds)", headers, table)},
        device=args.device, measured=None if args.from_metrics is None else {
            "machine": machine, "command": shlex.join(["python", "benchmarks/gpu_training.py",
                                    *(a for a in (sys.argv[1:] if argv is None else argv)
                                      if not a.startswith(("out=", "data=")))])})
    return payload


if __name__ == "__main__":
    main()
