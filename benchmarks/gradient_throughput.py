"""Gradient throughput: forward + backward of a differentiable window, and its memory.

For each task, window length H in {32, 1000} and N in {1, 64, 1024} (and 16384 for H = 32),
timed interleaved in one process, each candidate computes ``loss = -mean(reward)`` over a
window of H steps from the same start states and calls ``loss.backward()``:

* ``ours``: ``env.rollout(H, policy, auto_reset=False, tensordict=start,
  break_when_any_done=False)`` (the lean path; what :class:`DiffWindowCollector` calls);
* ``EnvBase.rollout``: TorchRL's generic rollout on the same env;
* ``raw``: a plain torch loop over the same physics functions and the same policy network on
  tensors (actions via ``unbind(0)`` in open-loop mode: indexing ``acts[t]`` would make the
  backward quadratic in H).

Two modes: ``policy`` (a tanh MLP 64-64 maps observations to actions: BPTT) and ``open-loop``
(the actions themselves are the leaf tensors, ``actions=acts.unbind(0)``: trajectory
optimisation, physics only). Episodes are not cut inside a window (``max_episode_steps`` is
set above H), so every candidate differentiates the same function.

Memory, per env-step (bytes / (N H)), counted once per candidate outside the timed rounds:

* ``saved``: bytes of the distinct tensor storages that autograd saves for backward during the
  forward (``torch.autograd.graph.saved_tensors_hooks``; a storage shared by several saved
  tensors, e.g. a parameter used at every step, counts once);
* ``held``: ``saved`` plus the storages of the forward's result that are not already counted:
  the rollout TensorDict (TorchRL's layout keeps observation, state, params, episode step and
  flags at both the root and under "next") or, for ``raw``, the stacked rewards. This is the
  memory the window holds until ``backward``;
* ``must keep``: the ``saved`` bytes of ``raw``: what eager autograd needs to differentiate
  this physics and policy. The target compares ours' ``held`` with it.

    python benchmarks/gradient_throughput.py           # full run, several minutes
    python benchmarks/gradient_throughput.py quick=true   # smoke run, seconds
"""
from __future__ import annotations

import gc
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402


def make_policy(env, hidden: int = 64, seed: int = 0):
    """A deterministic tanh MLP (Ivy Gym's policy) as a plain module and a TensorDictModule."""
    import torch
    from tensordict.nn import TensorDictModule
    from torch import nn

    torch.manual_seed(seed)
    net = nn.Sequential(
        nn.Linear(env.observation_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
        nn.Linear(hidden, env.action_dim), nn.Tanh(),
    ).to(env.float_dtype)
    return net, TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def raw_window(env, net, start, horizon: int, actions=None):
    """The window in plain torch: returns ``-mean(reward)`` (a scalar with a graph)."""
    import torch

    params = dict(start["params"].items())
    state = dict(start["state"].items())
    obs = start["observation"]
    steps = actions.unbind(0) if actions is not None else range(horizon)
    rewards = []
    for step in steps:
        action = step if actions is not None else net(obs)
        state, reward, _ = env.transition(state, action, params)
        obs = env.observation(state, params)
        rewards.append(reward)
    return -torch.stack(rewards, dim=1).mean()


def count_memory(forward):
    """(saved bytes, held bytes) of one ``forward()`` returning (loss, result tensors)."""

    with C.saved_for_backward() as saved:
        loss, result = forward()
    held = dict(saved)
    C.storage_bytes(result, held)
    loss.backward()  # frees the graph
    return sum(saved.values()), sum(held.values())


@dataclass(frozen=True)
class GradientThroughputSettings(C.BenchmarkSettings):
    tasks: list[str] | None = None  # tasks (default: pendulum cartpole)
    horizons: list[int] | None = None  # window lengths (default 32 1000)
    sizes: list[int] | None = None  # N (default 1 64 1024, +16384 for H <= 32)
    modes: list[str] = checked(["policy", "open-loop"], checks.each(checks.one_of(("policy", "open-loop"))))


def main(argv=None) -> dict:
    args = parse_cli(GradientThroughputSettings, argv, __doc__)
    printed = {}  # headers and rows of the printed tables: the docs' data file holds them too
    C.setup_threads(args.threads)

    import torch
    from torchrl.envs import EnvBase

    from torchrl_diffenvs import make_env

    quick = args.quick
    tasks = args.tasks or (["pendulum"] if quick else ["pendulum", "cartpole"])
    horizons = args.horizons or ([4] if quick else [32, 1000])
    rounds = args.repeats or (2 if quick else 5)
    info = C.versions()
    C.print_header("gradient throughput: forward + backward of a window (env-steps/s from CPU time)", info)

    results = []
    for task in tasks:
        for horizon in horizons:
            sizes = args.sizes or ([2] if quick else [1, 64, 1024] + ([16384] if horizon <= 32 else []))
            for n in sizes:
                env = make_env(task, num_envs=n, seed=0, max_episode_steps=horizon + 1)
                net, policy = make_policy(env)
                start = env.reset().detach()
                acts0 = (torch.rand(horizon, n, env.action_dim, generator=torch.Generator().manual_seed(0),
                                    dtype=env.float_dtype) * 2 - 1)
                for mode in args.modes:
                    def rollout_loss(path, mode=mode, env=env, policy=policy, start=start, acts0=acts0):
                        if mode == "policy":
                            td = path(env, horizon, policy, auto_reset=False, tensordict=start.clone(),
                                      break_when_any_done=False)
                        else:
                            acts = acts0.clone().requires_grad_(True)
                            td = path(env, horizon, actions=acts.unbind(0), auto_reset=False,
                                      tensordict=start.clone(), break_when_any_done=False)
                        return -td["next", "reward"].mean(), list(td.values(True, True))

                    def raw_loss(mode=mode, env=env, net=net, start=start, acts0=acts0):
                        acts = acts0.clone().requires_grad_(True) if mode == "open-loop" else None
                        loss = raw_window(env, net, start, horizon, acts)
                        return loss, [loss]

                    forwards = {
                        "ours": lambda f=rollout_loss: f(type(env).rollout),
                        "EnvBase.rollout": lambda f=rollout_loss: f(EnvBase.rollout),
                        "raw": raw_loss,
                    }
                    candidates = {name: (lambda fw=fw: fw()[0].backward()) for name, fw in forwards.items()}
                    timings = C.interleaved(candidates, rounds)
                    memory = {}
                    for name, fw in forwards.items():
                        gc.collect()
                        saved, held = count_memory(fw)
                        memory[name] = {"saved_bytes_per_env_step": saved / (n * horizon),
                                        "held_bytes_per_env_step": held / (n * horizon)}
                    row = {"task": task, "mode": mode, "H": horizon, "N": n, "candidates": {}, "memory": memory}
                    rates = {}
                    for name, t in timings.items():
                        rates[name] = [n * horizon / s for s in t["cpu"]]
                        row["candidates"][name] = {
                            "env_steps_per_s_cpu": C.spread(rates[name]),
                            "env_steps_per_s_wall": C.spread([n * horizon / s for s in t["wall"]]),
                        }
                    row["ratios_cpu"] = {f"ours / {o}": C.median_ratio(rates["ours"], rates[o])
                                         for o in rates if o != "ours"}
                    must_keep = memory["raw"]["saved_bytes_per_env_step"]
                    row["memory"]["ours_held_over_must_keep"] = memory["ours"]["held_bytes_per_env_step"] / must_keep
                    results.append(row)
                    print(f"# {task} {mode} H={horizon} N={n}: " + "  ".join(
                        f"{k}={C.fmt_rate(v['env_steps_per_s_cpu']['median'])}" for k, v in row["candidates"].items()))

    print("\n## forward + backward, env-steps/s (median over rounds, CPU time) and ratios")
    printed["throughput"] = (
        ["task", "mode", "H", "N", "ours", "EnvBase.rollout", "raw", "ours/EnvBase", "ours/raw"],
        [[r["task"], r["mode"], r["H"], r["N"],
          *[C.fmt_rate(r["candidates"][k]["env_steps_per_s_cpu"]["median"]) for k in ("ours", "EnvBase.rollout", "raw")],
          C.fmt_ratio(r["ratios_cpu"]["ours / EnvBase.rollout"]), C.fmt_ratio(r["ratios_cpu"]["ours / raw"])]
         for r in results],
    )
    table = C.print_table(*printed["throughput"])
    print("\n## memory per env-step (bytes): saved for backward / held until backward")
    printed["memory"] = (
        ["task", "mode", "H", "N", "must keep (raw saved)", "ours saved", "ours held", "EnvBase held",
         "ours held / must keep"],
        [[r["task"], r["mode"], r["H"], r["N"], f"{r['memory']['raw']['saved_bytes_per_env_step']:.0f}",
          f"{r['memory']['ours']['saved_bytes_per_env_step']:.0f}", f"{r['memory']['ours']['held_bytes_per_env_step']:.0f}",
          f"{r['memory']['EnvBase.rollout']['held_bytes_per_env_step']:.0f}",
          C.fmt_ratio(r["memory"]["ours_held_over_must_keep"])] for r in results],
    )
    memory_table = C.print_table(*printed["memory"])
    payload = {"benchmark": "gradient_throughput", "info": info, "rounds": rounds, "results": results,
               "table": table, "memory_table": memory_table}
    C.write_json("gradient_throughput" + ("_quick" if quick else ""), payload, args.out)
    C.write_data(args, "gradient_throughput", {
        "throughput": C.data_table("Forward + backward through a window of H steps, env-steps/s", *printed["throughput"]),
        "memory": C.data_table("Memory per env-step (bytes) kept for backward", *printed["memory"]),
    })
    return payload


if __name__ == "__main__":
    main()
