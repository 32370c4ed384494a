"""Ivy Gym's ``optimize_policy`` demo, for any task: a policy network trained through the env.

Ivy's original rolls one 100-step episode per update from a fresh random start and
differentiates minus its rewards (Adam 1e-3, 10,000 updates); users reported it never reached
the quality shown. The fix is batching and short windows: here the policy runs in ``num_envs``
envs at once, over windows of ``horizon`` steps with the env state carried from window to window
(:class:`~torchrl_diffenvs.collectors.DiffWindowCollector`), trained by BPTT
(:class:`~torchrl_diffenvs.objectives.BPTTLoss`, the default) or SHAC
(``loss=shac``: the window is closed by a learned critic). ``policy=deterministic`` is Ivy's
tanh MLP; ``policy=stochastic`` a TanhNormal policy (reparameterised samples).

Usage::

    python sota_scripts/optimize_policy.py env=pendulum iterations=150 out_dir=outputs/policy

Writes ``learning_curve.png`` (mean per-step reward of deterministic evaluation episodes from
fresh random starts, and of the training windows) and ``policy.gif`` (evaluation episodes of the
trained policy in a grid of ``gif_envs`` envs) to ``out_dir``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from demo_utils import plot_curve, start_demo
from torchrl_diffenvs import checks, list_envs, make_env
from torchrl_diffenvs.checks import Settings, checked
from torchrl_diffenvs.evaluation import evaluate
from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner, SHACConfig, SHACLearner
from torchrl_diffenvs.modules import ObservationNormalizer, make_actor, make_critic


@dataclass(frozen=True)
class PolicySettings(Settings):
    """The demo's arguments (``key=value``)."""

    env: str = checked("pendulum", checks.one_of(list_envs()))
    loss: str = checked("bptt", checks.one_of(("bptt", "shac")))
    policy: str = checked("deterministic", checks.one_of(("deterministic", "stochastic")))  # Ivy's tanh MLP | TanhNormal
    iterations: int = checked(150, checks.positive_int)
    num_envs: int = checked(64, checks.positive_int)
    horizon: int = checked(16, checks.positive_int)  # window length
    steps: int = checked(100, checks.positive_int)  # episode length
    lr: float = checked(1e-2, checks.learning_rate)
    critic_lr: float = checked(1e-3, checks.learning_rate)
    eval_every: int = checked(10, checks.positive_int)
    eval_envs: int = checked(64, checks.positive_int)
    seed: int = checked(0, checks.nonnegative_int)
    out_dir: str = "outputs/optimize_policy"
    gif: bool = checked(True, checks.boolean)
    gif_envs: int = checked(4, checks.positive_int)
    fps: int = checked(20, checks.positive_int)
    progress: bool = checked(True, checks.boolean)


def main(argv: list[str] | None = None) -> dict:
    args, out_dir = start_demo(PolicySettings, argv, usage=__doc__)

    env = make_env(args.env, num_envs=args.num_envs, seed=args.seed, max_episode_steps=args.steps)
    eval_env = make_env(args.env, num_envs=args.eval_envs, seed=args.seed + 10_000, max_episode_steps=args.steps)
    normalizer = ObservationNormalizer(env.observation_dim, dtype=env.float_dtype)
    distribution = "deterministic" if args.policy == "deterministic" else "tanh_normal"
    actor = make_actor(env, normalizer=normalizer, distribution=distribution)
    budget = args.iterations * args.num_envs * args.horizon
    if args.loss == "shac":
        settings = SHACConfig(horizon=args.horizon, actor_lr=args.lr, critic_lr=args.critic_lr,
                              critic_passes=4, critic_minibatches=4)
        learner = SHACLearner(env, actor, make_critic(env, normalizer=normalizer), settings, budget,
                              normalizer=normalizer)
    else:
        learner = BPTTLearner(env, actor, BPTTConfig(horizon=args.horizon, actor_lr=args.lr), budget,
                              normalizer=normalizer)

    train_x, train_y, eval_x, eval_y = [], [], [], []

    def record_evaluation(iteration):
        eval_x.append(iteration)
        eval_y.append(evaluate(eval_env, actor)["reward_mean"])

    record_evaluation(0)
    bar = tqdm(range(args.iterations), desc=f"optimize_policy[{args.env}, {args.loss}]",
               disable=not args.progress)
    for i in bar:
        metrics = learner.train_iteration()
        train_x.append(i + 1)
        train_y.append(metrics["reward"])
        if (i + 1) % args.eval_every == 0 or i + 1 == args.iterations:
            record_evaluation(i + 1)
        bar.set_postfix(train=f"{train_y[-1]:.3f}", eval=f"{eval_y[-1]:.3f}")

    plot_curve(
        out_dir / "learning_curve.png",
        {"evaluation (fresh random starts)": (eval_x, eval_y), "training windows": (train_x, train_y)},
        "iteration", "mean reward per step", f"optimize_policy: {args.env}, {args.loss}",
    )
    if args.gif:
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        from torchrl_diffenvs.rendering import rollout_frames, save_gif

        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            episode = eval_env.rollout(args.steps, actor, break_when_any_done=False)
        shown = list(range(min(args.gif_envs, args.eval_envs)))
        save_gif(rollout_frames(eval_env, episode, env_index=shown, size=160), out_dir / "policy.gif", fps=args.fps)
    summary = {
        "env": args.env, "loss": args.loss, "iterations": args.iterations,
        "initial_eval_reward": eval_y[0], "final_eval_reward": eval_y[-1],
        "skipped_steps": learner.actor_guard.skipped,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
