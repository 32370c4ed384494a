"""Env throughput without gradients: env-steps per second, ours vs the tools users would pick.

For every registered task and N in {1, 64, 1024, 4096, 16384}, timed interleaved in one process:

* ``ours``: ``env.rollout(T, break_when_any_done=False)`` under ``torch.no_grad`` (the lean
  path of ``DiffEnv.rollout``; random actions, auto-resets included);
* ``EnvBase.rollout``: TorchRL's generic rollout on the same env (what ``ours`` replaces);
* ``raw``: a plain torch loop over the same task's pure physics (``transition`` +
  ``observation`` with random actions on plain tensors; no resets, no TensorDicts, nothing
  kept): the speed limit of eager torch for this physics;
* ``raw + resets``: the same loop with the episode bookkeeping of an RL env (step counter,
  time limit, termination, auto-reset of done envs), still nothing kept;
* ``ours compiled`` (``compile=true``): ``compile_physics(env, steps_per_chunk=8)``; its
  compile time is reported separately;
* for the Gymnasium ids: gymnasium's ``SyncVectorEnv`` of the same task and, for CartPole-v1,
  gymnasium's own numpy-vectorised CartPole (``make_vec(vectorization_mode=
  "vector_entry_point")``), stepping with ``action_space.sample()``;
* per N, TorchRL's own ``PendulumEnv`` (batch ``[N]``) rollout, for reference;
* with a policy (``policy=true``): ``ours + policy`` is ``env.rollout(T, actor)`` with
  :func:`~torchrl_diffenvs.modules.make_actor`'s default actor (64-64 MLP, sampled tanh-normal
  actions) and ``raw + policy`` a plain torch loop calling the same network on tensors, sampling
  the same way, stepping the same physics and stacking the observations and rewards: what the
  policy-call overhead and the output writing of a rollout cost (the speed issue's target is
  ``ours + policy`` >= 0.5x ``raw + policy`` at N = 4096).

Unit: env-steps/s = batched steps/s x N, from CPU time (see benchmarks/_common.py); wall-clock
rates are in the JSON. ``T`` is the same for ours / EnvBase / raw (1000 steps, fewer at large N
to bound memory: the rollout output is 100-300 bytes per env-step); gymnasium and TorchRL's
PendulumEnv run as many steps as fit in about a quarter of a second.

    python benchmarks/env_throughput.py            # full run, several minutes
    python benchmarks/env_throughput.py quick=true    # smoke run, seconds
    python benchmarks/env_throughput.py tasks=[pendulum,CartPole-v1] sizes=[64,1024] compile=true gym=false
    python benchmarks/env_throughput.py sizes=[4096] policy=true gym=false
"""
from __future__ import annotations

import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs.checks import parse_cli  # noqa: E402

GYM_IDS = ("CartPole-v1", "Pendulum-v1", "MountainCarContinuous-v0")


def raw_loop(env, steps: int):
    """The task's physics in a plain torch loop: random actions, transition, observation."""
    import torch

    params = dict(env.params.items())
    state = env.initial_state(env.params, env.num_envs)
    low, span = env.action_low, env.action_high - env.action_low
    shape = (env.num_envs, env.action_dim)
    for _ in range(steps):
        action = torch.rand(shape, dtype=env.float_dtype, device=env.device) * span + low
        state, reward, terminated = env.transition(state, action, params)
        observation = env.observation(state, params)
    return observation, reward


def raw_policy_loop(env, actor, steps: int):
    """``raw_loop`` with the actor's network on plain tensors choosing the actions (sampled as
    ``TanhNormal`` does), observations and rewards stacked along time."""
    import torch

    network = actor.module[0].module  # observation -> (loc, scale)
    low, high = env.action_low, env.action_high
    params = dict(env.params.items())
    state = env.initial_state(env.params, env.num_envs)
    observation = env.observation(state, params)
    observations, rewards = [], []
    for _ in range(steps):
        loc, scale = network(observation)
        action = torch.tanh(loc + torch.randn_like(loc) * scale) * (high - low) / 2 + (high + low) / 2
        state, reward, terminated = env.transition(state, action, params)
        observation = env.observation(state, params)
        observations.append(observation)
        rewards.append(reward)
    return torch.stack(observations, 1), torch.stack(rewards, 1)


def raw_loop_with_resets(env, steps: int):
    """``raw_loop`` plus what an RL env loop adds: a time limit, termination, auto-resets."""
    import torch

    n = env.num_envs
    params = dict(env.params.items())
    state = env.initial_state(env.params, n)
    episode_step = torch.zeros(n, dtype=torch.int64, device=env.device)
    low, span = env.action_low, env.action_high - env.action_low
    for _ in range(steps):
        action = torch.rand((n, env.action_dim), dtype=env.float_dtype, device=env.device) * span + low
        state, reward, terminated = env.transition(state, action, params)
        observation = env.observation(state, params)
        episode_step = episode_step + 1
        done = episode_step >= (env.max_episode_steps or steps + 1)
        if terminated is not None:
            done = done | terminated
        if done.any():
            fresh = env.initial_state(env.params, n)
            state = {k: torch.where(done.view(n, *[1] * (v.ndim - 1)), fresh[k], v) for k, v in state.items()}
            episode_step = torch.where(done, 0, episode_step)
    return observation, reward


def raw_pendulum_by_hand(num_envs: int, steps: int):
    """The Ivy pendulum written out by hand with scalar parameters (a sanity check of ``raw``)."""
    import torch

    th = torch.rand(num_envs) * 2 * math.pi - math.pi
    thd = torch.rand(num_envs) * 2 - 1
    g, m, length, dt, max_torque = 9.8, 1.0, 1.0, 0.05, 1.0
    for _ in range(steps):
        torque = max_torque * (torch.rand(num_envs, 1) * 2 - 1)[..., 0]
        thd = thd + dt * (3 * g / (2 * length) * torch.sin(th) + 3 / (m * length**2) * torque)
        th = th + dt * thd
        reward = (torch.cos(th) + 1) / 2
        observation = torch.stack([torch.cos(th), torch.sin(th), thd], dim=-1)
    return observation, reward


def gym_loop(vec_env, steps: int):
    for _ in range(steps):
        vec_env.step(vec_env.action_space.sample())


def calibrated_steps(fn_of_steps, target_seconds: float, max_steps: int) -> int:
    """Steps for one timed call of about ``target_seconds`` (from a 2-step trial)."""
    start = time.perf_counter()
    fn_of_steps(2)
    per_step = (time.perf_counter() - start) / 2
    return int(max(2, min(max_steps, target_seconds / max(per_step, 1e-9))))


@dataclass(frozen=True)
class EnvThroughputSettings(C.BenchmarkSettings):
    tasks: list[str] | None = None  # task names (default: every registered env)
    sizes: list[int] | None = None  # batch sizes N (default 1 64 1024 4096 16384)
    compile: bool = False  # also time compile_physics (compiles per task and N)
    gym: bool = True  # false: skip gymnasium and TorchRL's PendulumEnv
    policy: bool = False  # also time rollouts with make_actor's actor against a raw loop with the same network
    # where our envs run: cpu | cuda | cuda:<k> (gymnasium and JAX stay on the CPU). On CUDA the timings
    # synchronise the device; read the wall-clock rates (JSON, *_wall), not the CPU-time ones
    device: str = "cpu"


def docs_tables(results: list[dict], args) -> dict:
    """The tables the documentation shows (docs/performance.md), from the same medians as the printout."""
    def rate(r, name):
        c = r["candidates"].get(name)
        return C.fmt_rate(c["env_steps_per_s_cpu"]["median"]) if c else "-"

    def ratio(r, a, b):  # median over rounds of a / b
        c = r["candidates"]
        return C.fmt_ratio(C.median_ratio(c[a]["cpu_rates"], c[b]["cpu_rates"])) if a in c and b in c else "-"

    tables = {"rates": C.data_table(
        "Env throughput without gradient, env-steps/s from CPU time",
        ["task", "N", "ours", "EnvBase.rollout", "raw", "raw + resets", "ours / EnvBase", "ours / raw",
         "ours / raw + resets"],
        [[r["task"], r["N"], rate(r, "ours"), rate(r, "EnvBase.rollout"), rate(r, "raw"), rate(r, "raw + resets"),
          ratio(r, "ours", "EnvBase.rollout"), ratio(r, "ours", "raw"), ratio(r, "ours", "raw + resets")]
         for r in results])}
    peers = ("gymnasium SyncVectorEnv", "gymnasium vectorised CartPole", "torchrl PendulumEnv")
    peer_rows = [r for r in results if any(p in r["candidates"] for p in peers)]
    if peer_rows:
        tables["peers"] = C.data_table(
            "Against Gymnasium's vector envs and TorchRL's PendulumEnv, env-steps/s",
            ["task", "N", "ours", "gymnasium SyncVectorEnv", "ours / Sync", "gymnasium vectorised CartPole",
             "ours / vectorised", "TorchRL PendulumEnv", "ours / TorchRL"],
            [[r["task"], r["N"], rate(r, "ours"), *[cell for p in peers for cell in (rate(r, p), ratio(r, "ours", p))]]
             for r in peer_rows])
    if args.compile:
        tables["compile"] = C.data_table(
            "compile_physics(env, steps_per_chunk=8) against eager, env-steps/s",
            ["task", "N", "ours (eager)", "ours compiled", "raw (eager)", "first rollout s", "compiled/eager",
             "compiled/raw"],
            [[r["task"], r["N"], rate(r, "ours"), rate(r, "ours compiled"), rate(r, "raw"),
              f"{r['compile_seconds']:.1f}", ratio(r, "ours compiled", "ours"), ratio(r, "ours compiled", "raw")]
             for r in results])
    if args.policy:
        tables["policy"] = C.data_table(
            "With make_actor's policy: ours against a raw loop with the same network, env-steps/s",
            ["task", "N", "ours + policy", "raw + policy", "ratio"],
            [[r["task"], r["N"], rate(r, "ours + policy"), rate(r, "raw + policy"),
              ratio(r, "ours + policy", "raw + policy")] for r in results])
    return tables


def main(argv=None) -> dict:
    args = parse_cli(EnvThroughputSettings, argv, __doc__)
    C.setup_threads(args.threads)
    device = C.setup_device(args.device)

    import gymnasium
    import torch
    from torchrl.envs import EnvBase
    from torchrl.envs import PendulumEnv as TorchRLPendulum

    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_diffenvs import list_envs, make_env
    from torchrl_diffenvs.envs.rollout import compile_physics
    from torchrl_diffenvs.modules import make_actor

    quick = args.quick
    tasks = args.tasks or (["pendulum", "Pendulum-v1", "CartPole-v1"] if quick else list_envs())
    sizes = args.sizes or ([4] if quick else [1, 64, 1024, 4096, 16384])
    rounds = args.repeats or (2 if quick else 5)
    target_seconds = 0.01 if quick else 0.25
    info = C.versions()
    info["device"] = device
    C.print_header("env throughput, no grad (env-steps/s from CPU time)", info)

    results = []  # one dict per (task, N)
    for n in sizes:
        steps = 5 if quick else max(10, min(1000, 1_000_000 // n))
        reference = {}  # TorchRL's PendulumEnv for this N
        if args.gym:
            trl = TorchRLPendulum()
            start = trl.reset(trl.gen_params(batch_size=[n]), set_state=False)
            trl_steps = calibrated_steps(
                lambda k: trl.rollout(k, tensordict=start.clone(), auto_reset=False, break_when_any_done=False),
                target_seconds, steps)
            reference["torchrl PendulumEnv"] = (
                lambda: trl.rollout(trl_steps, tensordict=start.clone(), auto_reset=False, break_when_any_done=False),
                trl_steps)
        for task in tasks:
            env = make_env(task, num_envs=n, seed=0, device=device)
            candidates = {
                "ours": (lambda env=env: env.rollout(steps, break_when_any_done=False), steps),
                "EnvBase.rollout": (lambda env=env: EnvBase.rollout(env, steps, break_when_any_done=False), steps),
                "raw": (lambda env=env: raw_loop(env, steps), steps),
                "raw + resets": (lambda env=env: raw_loop_with_resets(env, steps), steps),
            }
            if task == "pendulum" and device == "cpu":
                candidates["raw by hand"] = (lambda: raw_pendulum_by_hand(n, steps), steps)
            if args.policy:
                torch.manual_seed(0)
                actor = make_actor(env).to(env.device)
                candidates["ours + policy"] = (
                    lambda env=env, actor=actor: env.rollout(steps, actor, break_when_any_done=False), steps)
                candidates["raw + policy"] = (lambda env=env, actor=actor: raw_policy_loop(env, actor, steps), steps)
            compile_seconds = None
            if args.compile:
                cenv = compile_physics(make_env(task, num_envs=n, seed=0, device=device), steps_per_chunk=8)
                with torch.no_grad():
                    t0 = time.perf_counter()
                    cenv.rollout(16, break_when_any_done=False)  # compiles the 8-step chunk
                    compile_seconds = time.perf_counter() - t0
                candidates["ours compiled"] = (lambda cenv=cenv: cenv.rollout(steps, break_when_any_done=False), steps)
            gym_envs = []
            if args.gym and task in GYM_IDS:
                modes = [("gymnasium SyncVectorEnv", "sync")]
                if task == "CartPole-v1":
                    modes.append(("gymnasium vectorised CartPole", "vector_entry_point"))
                for label, mode in modes:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        vec = gymnasium.make_vec(task, num_envs=n, vectorization_mode=mode)
                    vec.reset(seed=0)
                    vec.action_space.seed(0)
                    gym_envs.append(vec)
                    k = calibrated_steps(lambda k, vec=vec: gym_loop(vec, k), target_seconds, 1000)
                    candidates[label] = (lambda vec=vec, k=k: gym_loop(vec, k), k)
            if task in ("pendulum", "Pendulum-v1"):
                candidates.update(reference)
            with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                timings = C.interleaved({name: fn for name, (fn, _) in candidates.items()}, rounds)
            for vec in gym_envs:
                vec.close()
            row = {"task": task, "N": n, "compile_seconds": compile_seconds, "candidates": {}}
            for name, (_, k) in candidates.items():
                t = timings[name]
                row["candidates"][name] = {
                    "steps": k,
                    "env_steps_per_s_cpu": C.spread([n * k / s for s in t["cpu"]]),
                    "env_steps_per_s_wall": C.spread([n * k / s for s in t["wall"]]),
                    "cpu_rates": [n * k / s for s in t["cpu"]],
                }
            rates = {name: c["cpu_rates"] for name, c in row["candidates"].items()}
            row["ratios_cpu"] = {
                f"ours / {other}": C.median_ratio(rates["ours"], rates[other]) for other in rates if other != "ours"
            }
            wall_rates = {name: [n * k / s for s in timings[name]["wall"]] for name, (_, k) in candidates.items()}
            row["ratios_wall"] = {
                f"ours / {other}": C.median_ratio(wall_rates["ours"], wall_rates[other])
                for other in wall_rates if other != "ours"
            }
            if args.policy:
                row["ratios_cpu"]["ours + policy / raw + policy"] = C.median_ratio(rates["ours + policy"],
                                                                                   rates["raw + policy"])
            results.append(row)
            print(f"# {task:>26s} N={n:<6d} " + "  ".join(
                f"{name}={C.fmt_rate(c['env_steps_per_s_cpu']['median'])}" for name, c in row["candidates"].items()))

    print("\n## env-steps/s (median over rounds, CPU time; min-max in the JSON)")
    names = []
    for row in results:
        names += [name for name in row["candidates"] if name not in names]
    table = C.print_table(
        ["task", "N", *names],
        [[r["task"], r["N"], *[C.fmt_rate(r["candidates"][nm]["env_steps_per_s_cpu"]["median"])
                               if nm in r["candidates"] else "-" for nm in names]] for r in results],
    )
    print("\n## ratios: ours / other (median of per-round ratios; CPU time | wall clock)")
    others = [nm for nm in names if nm != "ours"]
    ratio_table = C.print_table(
        ["task", "N", *others],
        [[r["task"], r["N"], *[
            f"{C.fmt_ratio(r['ratios_cpu'][f'ours / {nm}'])} | {C.fmt_ratio(r['ratios_wall'][f'ours / {nm}'])}"
            if f"ours / {nm}" in r["ratios_cpu"] else "-" for nm in others]] for r in results],
    )
    if args.compile:
        print("\n## compile_physics: compile time of the 8-step chunk (first rollout)")
        C.print_table(["task", "N", "compile s", "ours compiled / ours"],
                      [[r["task"], r["N"], f"{r['compile_seconds']:.1f}",
                        C.fmt_ratio(1 / r["ratios_cpu"]["ours / ours compiled"])] for r in results])
    if args.policy:
        print("\n## with a policy: ours + policy / raw + policy (CPU time)")
        C.print_table(["task", "N", "ours + policy", "raw + policy", "ratio"],
                      [[r["task"], r["N"], C.fmt_rate(r["candidates"]["ours + policy"]["env_steps_per_s_cpu"]["median"]),
                        C.fmt_rate(r["candidates"]["raw + policy"]["env_steps_per_s_cpu"]["median"]),
                        C.fmt_ratio(r["ratios_cpu"]["ours + policy / raw + policy"])] for r in results])
    C.write_data(args, "env_throughput", docs_tables(results, args), device)
    for row in results:
        for c in row["candidates"].values():
            c.pop("cpu_rates")
    payload = {"benchmark": "env_throughput", "info": info, "rounds": rounds, "results": results,
               "table": table, "ratio_table": ratio_table}
    C.write_json("env_throughput" + ("_quick" if quick else ""), payload, args.out)
    return payload


if __name__ == "__main__":
    main()
