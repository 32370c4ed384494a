"""The baseline a user would otherwise run: tuned PPO trained on Gymnasium's own env, beside the
same PPO on this library's env, back to back on the same machine with the same threads.

``mode=train`` (default) trains ``loss=ppo`` through the training script's ``run`` (configurations
composed by Hydra as the command line composes them, so ``configs/tuned/<env>_ppo.yaml`` applies
to both) once per backend and seed, interleaved (seed by seed, backend by backend), and reports
per run: the final evaluation return in the env it trained on, its return in Gymnasium's own env
(``eval.gymnasium=true``: the same number for the Gymnasium backend), the wall time and the env
steps per second, overall and of the training iterations alone (the median of the iterations'
``time/steps_per_s``; evaluations excluded), and the process's CPU time (steadier than the wall
clock on a shared machine)::

    python benchmarks/gymnasium_baseline.py                                   # HalfCheetah-v5, 20k steps, seed 0
    python benchmarks/gymnasium_baseline.py steps=500000 seeds=[0,1,2]        # the race's budget
    python benchmarks/gymnasium_baseline.py envs=[Hopper-v5] backends=[gymnasium]

For a race table, run the baseline as a variant of the race's own script and summarise both
together: ``python benchmarks/time_to_solve.py envs=[HalfCheetah-v5] losses=[ppo]
variant=["gymnasium=env.backend=gymnasium"]``.

``mode=vectorization`` times random-action rollouts of Gymnasium's env batched three ways:
the training script's (TorchRL's ``GymWrapper`` over Gymnasium's in-process ``SyncVectorEnv``),
TorchRL's ``ParallelEnv`` of two such workers, and TorchRL's ``GymEnv(num_envs=N)`` (Gymnasium's
``AsyncVectorEnv``, one process per env)::

    python benchmarks/gymnasium_baseline.py mode=vectorization num_envs=64

Arguments are ``key=value`` (lists as ``[a,b]``). Results: ``benchmarks/results/gymnasium_baseline.json``
(or ``out=``).
"""
from __future__ import annotations

import functools
import json
import statistics
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402
from torchrl_diffenvs.envs.gymnasium_backend import ENV_BACKENDS  # noqa: E402

HEADERS = ["env", "backend", "seed", "env steps", "wall s", "steps/s", "train steps/s", "CPU s", "steps/CPU s",
           "eval return", "Gymnasium return"]


@dataclass(frozen=True)
class BaselineSettings(C.BenchmarkSettings):
    mode: str = checked("train", checks.one_of(("train", "vectorization")))
    envs: list[str] = field(default_factory=lambda: ["HalfCheetah-v5"])  # Gymnasium's MuJoCo tasks
    backends: list[str] = checked(list(ENV_BACKENDS), checks.each(checks.one_of(ENV_BACKENDS)))
    seeds: list[int] = field(default_factory=lambda: [0])
    steps: int = checked(20_000, checks.positive_int)  # train.total_env_steps of every run
    override: list[str] = field(default_factory=list)  # extra Hydra overrides for every run
    num_envs: int = checked(64, checks.positive_int)  # mode=vectorization: envs in the batch
    rollout_steps: int = checked(100, checks.positive_int)  # mode=vectorization: steps timed per batching
    # mode=vectorization: each batching runs in its own process, stopped (with its workers) after this long
    timeout_s: int = checked(180, checks.positive_int)
    candidate: int | None = None  # internal: the batching a child process times


def train(s: BaselineSettings) -> dict:
    """``mode=train``: every (seed, env, backend) run, back to back; returns the JSON payload."""
    train_script = C.load_train_script()
    runs, rows = [], []
    root = Path(tempfile.mkdtemp(prefix="gymnasium_baseline_"))
    print(f"# run directories (metrics, checkpoints): {root}", flush=True)
    for seed in s.seeds:
        for env in s.envs:
            for backend in s.backends:
                overrides = [f"env={env}", "loss=ppo", f"env.backend={backend}", f"seed={seed}", "logger=none",
                             "train.progress_bar=false", "eval.gif=false", "eval.gymnasium=true",
                             f"train.total_env_steps={s.steps}", *s.override]
                if s.quick:
                    overrides += ["env.num_envs=4", "loss.rollout_len=8", "eval.num_envs=2", "eval.max_steps=20",
                                  "train.total_env_steps=64"]
                run_dir = root / f"{env}_{backend}_seed{seed}"
                cfg, results = C.compose(overrides), []
                wall, cpu = C.timed(lambda: results.append(train_script.run(cfg, run_dir, overrides)))
                history = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
                result = C.portable_run(results[0], root)
                rates = [row["time/steps_per_s"] for row in history if "time/steps_per_s" in row]
                result.update(backend=backend, overrides=overrides, process_wall_s=wall, process_cpu_s=cpu,
                              train_steps_per_s=statistics.median(rates) if rates else None,
                              steps_per_cpu_s=result["env_steps"] / cpu)
                runs.append(result)
                rows.append([env, backend, str(seed), f"{result['env_steps']:,}", f"{result['wall_time_s']:.1f}",
                             C.fmt_rate(result["steps_per_s"]), C.fmt_rate(result["train_steps_per_s"]),
                             f"{cpu:.1f}", C.fmt_rate(result["steps_per_cpu_s"]),
                             f"{result['eval/return']:.4g}", f"{result.get('eval/gymnasium_return', float('nan')):.4g}"])
                print(" | ".join(rows[-1]), flush=True)
    table = C.print_table(HEADERS, rows)
    return {"benchmark": "gymnasium_baseline", "mode": "train", "runs": runs, "table": table}


def _rollout_rate(make_env, steps: int) -> float | str:
    """Env steps per second of a random-action rollout of ``steps`` steps (after a warm-up), or
    why it failed."""
    env = None
    try:
        env = make_env()
        env.set_seed(0)
        env.rollout(5, break_when_any_done=False)
        tic = time.perf_counter()
        td = env.rollout(steps, break_when_any_done=False)
        return td.numel() / (time.perf_counter() - tic)
    except Exception as err:  # noqa: BLE001 - a batching that does not run here is a result too
        return f"failed: {type(err).__name__}: {err}"
    finally:
        if env is not None:
            env.close()


def _batchings(env_id: str, n: int) -> dict:
    """``{label: env factory}`` of the batchings ``mode=vectorization`` compares."""
    from torchrl.envs import GymEnv, ParallelEnv

    from torchrl_diffenvs.envs.gymnasium_backend import GymnasiumBackedEnv

    return {
        f"GymWrapper(SyncVectorEnv({n})) [env.backend=gymnasium]": functools.partial(GymnasiumBackedEnv, env_id, n),
        f"ParallelEnv(2, SyncVectorEnv({n // 2}))": lambda: ParallelEnv(
            2, functools.partial(GymnasiumBackedEnv, env_id, max(1, n // 2))),
        f"GymEnv(num_envs={n}) (AsyncVectorEnv)": lambda: GymEnv(env_id, num_envs=n),
    }


def _in_child(s: BaselineSettings, index: int) -> float | str:
    """Times batching ``index`` in its own process (session), killed with its workers after
    ``timeout_s``: a batching that hangs is reported, not waited for."""
    import os
    import signal
    import subprocess

    command = [sys.executable, __file__, "mode=vectorization", f"candidate={index}", f"num_envs={s.num_envs}",
               f"rollout_steps={10 if s.quick else s.rollout_steps}", f"envs=[{s.envs[0]}]", f"threads={s.threads}"]
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                             start_new_session=True)
    try:
        out, _ = child.communicate(timeout=s.timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)  # the child's session: it and the env workers it started
        child.communicate()
        return f"no result in {s.timeout_s} s"
    lines = [line for line in out.splitlines() if line.startswith("RATE ")]
    if not lines:
        return f"failed (exit status {child.returncode})"
    value = lines[-1].removeprefix("RATE ")
    return float(value) if value[0].isdigit() else value


def vectorization(s: BaselineSettings) -> dict:
    """``mode=vectorization``: random-action rollouts of each batching; returns the JSON payload."""
    n, env_id = s.num_envs, s.envs[0]
    rows = []
    for index, label in enumerate(_batchings(env_id, n)):
        rate = _in_child(s, index)
        rows.append([env_id, label, rate if isinstance(rate, str) else C.fmt_rate(rate)])
        print(" | ".join(rows[-1]), flush=True)
    table = C.print_table(["env", "batching", "env steps/s (random actions)"], rows)
    return {"benchmark": "gymnasium_baseline", "mode": "vectorization", "rows": rows, "table": table}


def main(argv=None) -> dict:
    s = parse_cli(BaselineSettings, argv, __doc__)
    C.setup_threads(s.threads)
    warnings.filterwarnings("ignore")
    if s.candidate is not None:  # a child of mode=vectorization: one batching, one line
        make = list(_batchings(s.envs[0], s.num_envs).values())[s.candidate]
        print(f"RATE {_rollout_rate(make, s.rollout_steps)}", flush=True)
        return {}
    info = C.versions()
    C.print_header(f"gymnasium_baseline mode={s.mode}", info)
    payload = train(s) if s.mode == "train" else vectorization(s)
    payload["info"] = info
    C.write_json("gymnasium_baseline", payload, s.out)
    return payload


if __name__ == "__main__":
    main()
