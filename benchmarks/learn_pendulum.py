"""Time to swing up the Ivy-style Pendulum with SHAC and BPTT (N=64 envs, default physics).

Every ``eval_every`` iterations the deterministic policy runs one episode (``episode_steps``,
default 100 as in Ivy Gym) in 256 envs from fresh random starts (a fixed evaluation seed); the clock
counts training time only (collection, losses, updates), not evaluation. For each run the script
reports the training time and iterations until the evaluation's mean per-step reward first reaches
each of ``thresholds``, and until its last-20-step reward (the pendulum held upright at the end of
the episode) reaches 0.9.

Reference points printed alongside: uniformly random actions, and a hand-written energy-pumping +
PD swing-up controller (the motor is weak: thdd = 14.7 sin th + 3 u, so swinging up from the bottom
takes several seconds and no policy's 100-step mean per-step reward gets near 1; the controller
scores 0.74 with 100-step episodes, 0.87 with 200, 0.935 with 400). ``episode_steps`` sets the
episode length of the evaluation envs, and of the training envs unless ``train_episode_steps``
is given.

Usage (one thread; the machine is shared, so wall times carry noise)::

    OMP_NUM_THREADS=1 python benchmarks/learn_pendulum.py configs=[shac,bptt] seeds=[0,1,2]
    # mean per-step reward 0.9 is reachable only with longer episodes: evaluate on 400-step
    # episodes, train on 100-step ones (training on 400-step episodes stays on the spinning plateau)
    OMP_NUM_THREADS=1 python benchmarks/learn_pendulum.py configs=[shac,bptt] seeds=[0,1] \
        episode_steps=400 train_episode_steps=100 thresholds=[0.6,0.7,0.8,0.9] \
        max_seconds=150 max_iterations=1000 out=benchmarks/results/learn_pendulum_400.json

Writes a JSON with every evaluation point to ``out`` (default benchmarks/results/learn_pendulum.json).
"""
from __future__ import annotations

import json
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_diffenvs import checks, make_env
from torchrl_diffenvs.checks import Settings, checked, parse_cli
from torchrl_diffenvs.evaluation import evaluate
from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner, SHACConfig, SHACLearner
from torchrl_diffenvs.modules import ObservationNormalizer, make_actor, make_critic

# name -> settings; everything not listed is the learner's (BPTTConfig / SHACConfig) or the builders' default
CONFIGS = {
    # SHAC tuned for this CPU: 16-step windows (0.8 s of pendulum time), light critic fitting
    "shac": dict(loss="shac", horizon=16, actor_lr=1e-2, critic_passes=2, critic_minibatches=2),
    # SHAC with the reference's CartPole settings: 32-step windows, 16 x 4 critic minibatches
    "shac_reference": dict(loss="shac", horizon=32, actor_lr=1e-2, critic_passes=16, critic_minibatches=4),
    # BPTT (Brax APG style) over 16-step windows with carried state, same stochastic actor
    "bptt": dict(loss="bptt", horizon=16, actor_lr=1e-2),
    # full-episode BPTT (the TorchRL tutorial / Ivy demo style): windows as long as an episode
    "bptt_full_episode": dict(loss="bptt", horizon="episode", actor_lr=1e-2),
}
DEFAULT_REWARD_THRESHOLDS = (0.6, 0.7)
TAIL_THRESHOLD = 0.9


class UniformRandomPolicy(TensorDictModuleBase):
    def __init__(self, env):
        super().__init__()
        self.in_keys, self.out_keys, self.env = ["observation"], ["action"], env

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", torch.rand(self.env.num_envs, self.env.action_dim) * 2 - 1)
        return td


class EnergyPumpingController(TensorDictModuleBase):
    """Reference swing-up controller: pump energy ``sign(thd (E* - E))`` until near the top,
    then a saturated PD on the wrapped angle. Gains picked by a small grid search."""

    def __init__(self, k_angle=20.0, k_rate=3.0, switch_angle=0.3):
        super().__init__()
        self.in_keys, self.out_keys = [("state", "th"), ("state", "thd")], ["action"]
        self.k_angle, self.k_rate, self.cos_switch = k_angle, k_rate, math.cos(switch_angle)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        th, thd = td.get(("state", "th")), td.get(("state", "thd"))
        energy = 0.5 * thd**2 + 14.7 * torch.cos(th)  # 14.7 = 3 g / (2 l): upright at rest is 14.7
        pump = torch.sign(thd * (14.7 - energy) + 1e-9)
        wrapped = torch.remainder(th + math.pi, 2 * math.pi) - math.pi
        pd = torch.clamp(-(self.k_angle * wrapped + self.k_rate * thd) / 3.0, -1.0, 1.0)
        td.set("action", torch.where(torch.cos(th) > self.cos_switch, pd, pump).unsqueeze(-1))
        return td


def run(config: dict, seed: int, max_iterations: int, max_seconds: float, eval_every: int, num_envs: int,
        episode_steps: int = 100, reward_thresholds=DEFAULT_REWARD_THRESHOLDS,
        train_episode_steps: int | None = None) -> dict:
    """One training run; ``episode_steps`` is the evaluation's episode length and, unless
    ``train_episode_steps`` is given, the training envs' too."""
    torch.manual_seed(seed)
    train_episode_steps = train_episode_steps or episode_steps
    env = make_env("pendulum", num_envs=num_envs, seed=seed, max_episode_steps=train_episode_steps)
    eval_env = make_env("pendulum", num_envs=256, seed=10_000, max_episode_steps=episode_steps)
    normalizer = ObservationNormalizer(env.observation_dim)
    actor = make_actor(env, normalizer=normalizer)
    settings = {k: v for k, v in config.items() if k != "loss"}
    if settings["horizon"] == "episode":
        settings["horizon"] = train_episode_steps
    budget = max_iterations * num_envs * settings["horizon"]
    if config["loss"] == "shac":
        learner = SHACLearner(env, actor, make_critic(env, normalizer=normalizer), SHACConfig(**settings), budget,
                              normalizer=normalizer)
    else:
        learner = BPTTLearner(env, actor, BPTTConfig(**settings), budget, normalizer=normalizer)
    train_time, points = 0.0, []
    reached: dict[str, dict | None] = {f"reward>={t}": None for t in reward_thresholds}
    reached[f"tail>={TAIL_THRESHOLD}"] = None

    def record_evaluation(iteration):
        result = evaluate(eval_env, actor)
        points.append({"iteration": iteration, "train_seconds": train_time, "env_steps": learner.collector.frames,
                       **result})
        for t in reward_thresholds:
            if reached[f"reward>={t}"] is None and result["reward_mean"] >= t:
                reached[f"reward>={t}"] = {"seconds": train_time, "iteration": iteration}
        if reached[f"tail>={TAIL_THRESHOLD}"] is None and result["tail_reward_mean"] >= TAIL_THRESHOLD:
            reached[f"tail>={TAIL_THRESHOLD}"] = {"seconds": train_time, "iteration": iteration}

    record_evaluation(0)
    for iteration in range(1, max_iterations + 1):
        start = time.perf_counter()
        learner.train_iteration()
        train_time += time.perf_counter() - start
        if iteration % eval_every == 0:
            record_evaluation(iteration)
            if all(v is not None for v in reached.values()) or train_time > max_seconds:
                break
    return {
        "seed": seed, "reached": reached, "iterations": learner.iteration, "train_seconds": train_time,
        "seconds_per_iteration": train_time / max(1, learner.iteration),
        "final_eval": points[-1], "best_reward_mean": max(p["reward_mean"] for p in points),
        "skipped_steps": learner.actor_guard.skipped, "points": points,
    }


@dataclass(frozen=True)
class LearnPendulumSettings(Settings):
    """The benchmark's arguments (``key=value``)."""

    configs: list[str] = checked(["shac", "bptt"], checks.each(checks.one_of(sorted(CONFIGS))))
    seeds: list[int] = checked([0, 1, 2], checks.each(checks.nonnegative_int))
    num_envs: int = checked(64, checks.positive_int)
    max_iterations: int = checked(400, checks.positive_int)
    max_seconds: float = checked(180.0, checks.positive)  # training-time budget per run
    eval_every: int = checked(10, checks.positive_int)
    # episode length of the evaluation envs (and of the training envs unless train_episode_steps is
    # given); at least 20: the last-20-step reward
    episode_steps: int = checked(100, lambda v: None if checks.is_int(v) and v >= 20 else "expected an integer >= 20")
    train_episode_steps: int | None = checked(None, lambda v: None if v is None else checks.positive_int(v))
    thresholds: list[float] = checked(list(DEFAULT_REWARD_THRESHOLDS), checks.each(lambda v: None if checks.is_number(v) else "expected a number"))
    out: str = "benchmarks/results/learn_pendulum.json"


def main(argv=None) -> None:
    args = parse_cli(LearnPendulumSettings, argv, __doc__)

    ref_env = make_env("pendulum", num_envs=256, seed=10_000, max_episode_steps=args.episode_steps)
    references = {
        "uniform_random": evaluate(ref_env, UniformRandomPolicy(ref_env)),
        "energy_pumping_controller": evaluate(ref_env, EnergyPumpingController()),
    }
    print(f"reference policies, {args.episode_steps}-step episodes (mean per-step reward, last-20-step reward):")
    for name, r in references.items():
        print(f"  {name:28s} {r['reward_mean']:.3f}  {r['tail_reward_mean']:.3f}")

    results = {}
    for name in args.configs:
        runs = []
        for seed in args.seeds:
            load = os.getloadavg()[0]
            result = run(CONFIGS[name], seed, args.max_iterations, args.max_seconds, args.eval_every, args.num_envs,
                         args.episode_steps, args.thresholds, args.train_episode_steps)
            result["load_average_before"], result["load_average_after"] = load, os.getloadavg()[0]
            runs.append(result)
            summary = ", ".join(
                f"{k}: " + (f"{v['seconds']:.1f}s/{v['iteration']}it" if v else "not reached")
                for k, v in result["reached"].items()
            )
            print(f"{name} seed {seed}: {summary}; best {result['best_reward_mean']:.3f}; "
                  f"{1000 * result['seconds_per_iteration']:.0f} ms/it; "
                  f"load {load:.1f} -> {result['load_average_after']:.1f}", flush=True)
        results[name] = {"settings": CONFIGS[name], "runs": runs}
        for key in runs[0]["reached"]:
            times = [r["reached"][key]["seconds"] for r in runs if r["reached"][key]]
            if times:
                print(f"  {name} {key}: reached in {len(times)}/{len(runs)} runs, median {statistics.median(times):.1f}s")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "threads": torch.get_num_threads()},
        "num_envs": args.num_envs, "episode_steps": args.episode_steps,
        "train_episode_steps": args.train_episode_steps or args.episode_steps, "references": references,
        "results": results,
    }, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
