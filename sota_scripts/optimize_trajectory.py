"""Ivy Gym's ``optimize_trajectory`` demo, for any task: open-loop trajectory optimisation by BPTT.

One fixed start state; the parameters are a table of action logits ``[T, action_dim]``
(``actions = tanh(logits)``, initialised ``U[-2, 2]``); the loss is minus the episode's rewards,
differentiated through the whole episode. In TorchRL terms that is just an actor that reads the
step counter (:class:`~torchrl_diffenvs.open_loop.OpenLoopActor`) trained with
:class:`~torchrl_diffenvs.objectives.BPTTLoss`: no special machinery.

Usage::

    python sota_scripts/optimize_trajectory.py env=pendulum iterations=100 out_dir=outputs/traj

Writes ``learning_curve.png`` (episode return per iteration) and ``trajectory.gif`` (the optimised
episode) to ``out_dir``. Any ``key=value`` below can be overridden.
"""
from __future__ import annotations

import json

from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from demo_utils import plot_curve, start_demo
from torchrl_diffenvs import checks, list_envs, make_env
from torchrl_diffenvs.checks import Settings, checked
from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner
from torchrl_diffenvs.open_loop import OpenLoopActor

@dataclass(frozen=True)
class TrajectorySettings(Settings):
    """The demo's arguments (``key=value``)."""

    env: str = checked("pendulum", checks.one_of(list_envs()))
    iterations: int = checked(100, checks.positive_int)
    steps: int = checked(100, checks.positive_int)  # episode length T (Ivy: 100)
    lr: float = checked(0.1, checks.learning_rate)  # Adam (Ivy: 0.1)
    seed: int = checked(0, checks.nonnegative_int)
    out_dir: str = "outputs/optimize_trajectory"
    gif: bool = checked(True, checks.boolean)
    fps: int = checked(20, checks.positive_int)
    progress: bool = checked(True, checks.boolean)


def main(argv: list[str] | None = None) -> dict:
    args, out_dir = start_demo(TrajectorySettings, argv, usage=__doc__)

    env = make_env(args.env, num_envs=1, seed=args.seed, max_episode_steps=args.steps)
    start = env.reset()  # the one fixed start state
    actor = OpenLoopActor.from_env(env)
    # every window is the whole episode from `start`
    settings = BPTTConfig(horizon=args.steps, actor_lr=args.lr, betas=(0.9, 0.999), lr_schedule="constant",
                          max_grad_norm=None)
    learner = BPTTLearner(env, actor, settings, total_env_steps=args.iterations * args.steps, start_state=start)
    returns = []
    bar = tqdm(range(args.iterations), desc=f"optimize_trajectory[{args.env}]", disable=not args.progress)
    for _ in bar:
        metrics = learner.train_iteration()
        returns.append(metrics["reward"] * args.steps)  # this iteration's episode return
        bar.set_postfix(ret=f"{returns[-1]:.2f}")

    # the final trajectory (after the last update), without gradients
    with torch.no_grad():
        final = env.rollout(args.steps, actor, tensordict=start.clone(), auto_reset=False)
    final_return = final["next", "reward"].sum().item()
    plot_curve(
        out_dir / "learning_curve.png",
        {"episode return": (list(range(len(returns))), returns)},
        "iteration", f"return over {args.steps} steps", f"optimize_trajectory: {args.env}",
    )
    if args.gif:
        from torchrl_diffenvs.rendering import rollout_frames, save_gif

        save_gif(rollout_frames(env, final, env_index=0, size=256), out_dir / "trajectory.gif", fps=args.fps)
    summary = {
        "env": args.env, "iterations": args.iterations, "initial_return": returns[0] if returns else None,
        "final_return": final_return, "skipped_steps": learner.actor_guard.skipped,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
