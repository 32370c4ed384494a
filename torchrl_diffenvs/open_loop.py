"""Open-loop control: a learnable table of actions (trajectory optimisation with BPTT)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from .modules.actors import action_bounds, ScaledTanh

__all__ = ["OpenLoopActor"]


class OpenLoopActor(TensorDictModuleBase):
    """Open-loop control: ``action = squash(logits[episode_step])`` with a learnable table.

    Trajectory optimisation is then ordinary BPTT: roll this actor through the env from one fixed
    start state and minimise [`BPTTLoss`][torchrl_diffenvs.objectives.BPTTLoss] (Ivy Gym's
    ``optimize_trajectory``). Every env of the batch uses the same table, indexed by its own
    ``"episode_step"``.

    Args:
        horizon: number of time steps ``T`` (rows of the table).
        action_dim: action size ``A``.
        init_range: the logits start ``U[low, high]`` (Ivy: ``U[-2, 2]``).
        low: lower action bound.
        high: upper action bound; ``action = low + (tanh(logit) + 1) / 2 * (high - low)``.
        dtype: parameter dtype.
        generator: torch generator for the initial logits (seeding).
    """

    def __init__(
        self,
        horizon: int,
        action_dim: int,
        init_range: tuple[float, float] = (-2.0, 2.0),
        low: float = -1.0,
        high: float = 1.0,
        dtype: torch.dtype = torch.float32,
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        if not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"OpenLoopActor: horizon must be a positive integer, got {horizon!r}")
        self.in_keys = ["episode_step"]
        self.out_keys = ["action"]
        a, b = init_range
        self.logits = nn.Parameter(torch.rand(horizon, action_dim, generator=generator, dtype=dtype) * (b - a) + a)
        self.squash = ScaledTanh(low, high)

    @classmethod
    def from_env(cls, env, horizon: int | None = None, **kwargs) -> OpenLoopActor:
        """Sized for ``env``: ``horizon`` defaults to ``env.max_episode_steps``."""
        horizon = horizon if horizon is not None else env.max_episode_steps
        if horizon is None:
            raise ValueError("OpenLoopActor.from_env: the env never truncates; pass horizon=")
        low, high = action_bounds(env)
        action = env.full_action_spec[env.action_key]  # the (transformed) spec the actions must fit
        return cls(horizon, int(action.shape[-1]), low=low, high=high, dtype=action.dtype, **kwargs)

    @property
    def horizon(self) -> int:
        """The number of steps the action sequence covers."""
        return self.logits.shape[0]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        step = tensordict.get("episode_step")
        if (step >= self.horizon).any() or (step < 0).any():
            raise IndexError(
                f"OpenLoopActor: episode_step must lie in [0, {self.horizon}), got values up to {int(step.max())}; "
                f"use an env with max_episode_steps <= {self.horizon}"
            )
        tensordict.set("action", self.squash(self.logits[step]))
        return tensordict

    def actions(self) -> torch.Tensor:
        """The whole open-loop action sequence ``[T, A]``."""
        return self.squash(self.logits)
