"""Deterministic evaluation on separate envs, the random-policy baseline, and the policy's GIF.

Every evaluation restarts the evaluation envs from the same seed, so successive evaluations (and
runs with different training seeds) are scored on the same start states. Each env plays one
episode of ``steps`` steps; the score of an env is the undiscounted sum of rewards up to and
including the step where its first episode ends (termination or truncation).
"""
from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["episode_returns", "evaluate", "evaluate_random", "record_gif", "uniform_random_policy"]


def episode_returns(rollout: TensorDictBase) -> torch.Tensor:
    """Per-env return of the *first* episode of a ``[N, T]`` rollout (later episodes ignored).

    An env whose episode ends at step ``k`` (``("next", "done")``) counts rewards ``0..k``;
    TorchRL's auto-reset starts a new episode after that, which is not counted.
    """
    reward = rollout.get(("next", "reward"))[..., 0]
    done = rollout.get(("next", "done"))[..., 0]
    ended_before = torch.cumsum(done.to(torch.int64), dim=-1) - done.to(torch.int64)  # dones strictly before t
    return (reward * (ended_before == 0).to(reward.dtype)).sum(-1)


def uniform_random_policy(env):
    """A policy writing uniformly random actions within the action spec, drawn from ``env.rng``
    (so it neither consumes nor disturbs torch's global generator)."""
    space = env.action_spec.space
    low, high = space.low, space.high

    def policy(td: TensorDictBase) -> TensorDictBase:
        u = torch.rand(low.shape, generator=env.rng, device=low.device, dtype=low.dtype)
        return td.set("action", low + (high - low) * u)

    return policy


def _rollout(env, policy, steps: int, seed: int, exploration: ExplorationType) -> TensorDictBase:
    env.set_seed(seed)  # same start states at every evaluation
    with torch.no_grad(), set_exploration_type(exploration):
        return env.rollout(steps, policy, break_when_any_done=False)


def evaluate(env, policy, steps: int, seed: int) -> dict[str, float]:
    """Scores ``policy`` (deterministic mode: the mean action) on ``env``.

    Returns ``{"return": mean, "return_std": std, "return_min": min, "return_max": max}``
    over the envs of ``env``.
    """
    returns = episode_returns(_rollout(env, policy, steps, seed, ExplorationType.DETERMINISTIC)).double()
    return {
        "return": returns.mean().item(),
        "return_std": returns.std(unbiased=False).item(),
        "return_min": returns.min().item(),
        "return_max": returns.max().item(),
    }


def evaluate_random(env, steps: int, seed: int) -> float:
    """Mean return of uniformly random actions on the same start states as :func:`evaluate`."""
    env.set_seed(seed)
    with torch.no_grad():
        rollout = env.rollout(steps, uniform_random_policy(env), break_when_any_done=False)
    return episode_returns(rollout).double().mean().item()


def record_gif(env, policy, steps: int, seed: int, path: str | Path, env_index: int = 0, fps: int = 30,
               size: int = 256) -> Path:
    """Writes a GIF of ``policy`` (deterministic) playing env ``env_index`` of ``env`` for ``steps`` steps.

    Needs Pillow (``pip install "torchrl_diffenvs[render]"``).
    """
    from ..rendering import rollout_frames, save_gif  # Pillow is an optional extra

    rollout = _rollout(env, policy, steps, seed, ExplorationType.DETERMINISTIC)
    frames = rollout_frames(env, rollout, env_index=env_index, size=size)
    return save_gif(frames, path, fps=fps)
