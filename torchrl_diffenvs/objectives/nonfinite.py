"""Non-finite envs: found per env, left out of the losses, reported.

One env of a batch with a NaN physical parameter, or whose simulation diverged, gives NaN
rewards and observations. Averaged into a loss, it makes the whole batch's loss and gradient NaN,
so every update is skipped and nothing learns. The learners instead find such envs per rollout
([`nonfinite_envs`][torchrl_diffenvs.objectives.nonfinite_envs]), leave them out of the loss (the losses' ``keep`` masks; the window
collector also cuts their gradient at the actions) and report them ([`NonFiniteEnvMonitor`][torchrl_diffenvs.objectives.NonFiniteEnvMonitor]:
a warning naming the envs, a count in the metrics).
"""
from __future__ import annotations

import warnings
from collections.abc import Iterable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = [
    "ISOLATED_KEY", "NONFINITE_KEY", "NonFiniteEnvMonitor", "NonFiniteEnvWarning", "next_key", "nonfinite_envs",
    "now_and_next",
]

#: the per-step flag an env may report under ``"next"``: its state became non-finite at that step
NONFINITE_KEY = "nonfinite"
#: written by the window collector into a window ``[N, H]``: the env is left out of this window's loss
ISOLATED_KEY = "isolated"


class NonFiniteEnvWarning(RuntimeWarning):
    """Some envs of the batch produced non-finite values and are left out of the loss."""


def next_key(key: NestedKey) -> tuple:
    """``("next", *key)``: where a rollout keeps the entry ``key`` after the step."""
    return ("next", *(key if isinstance(key, tuple) else (key,)))


def now_and_next(keys: Iterable[NestedKey]) -> list:
    """Every key of ``keys`` and its ``"next"`` counterpart (the inputs a network reads in a rollout)."""
    return [entry for key in keys for entry in (key, next_key(key))]


def nonfinite_envs(batch: TensorDictBase, keys: Iterable[NestedKey] = (("next", "reward"),)) -> torch.Tensor:
    """``[N]`` bool: the envs of ``batch`` with a NaN/inf in any floating-point entry ``keys`` at
    any step, with ``("next", "nonfinite")`` set at any step (the flag an env reports itself), or
    marked ``"isolated"`` (by the window collector).

    Args:
        batch: a TensorDict of batch size ``[N]`` or ``[N, T]``.
        keys: the entries checked for NaN/inf (default: the reward); missing entries are ignored.
    """
    n = batch.batch_size[0]
    # on the batch's device; a batch without one (TorchRL's collectors on CUDA) gets a CPU mask,
    # which indexes its entries on any device
    bad = torch.zeros(n, dtype=torch.bool, device=batch.device)
    for key in keys:
        value = batch.get(key, None)
        if isinstance(value, torch.Tensor) and value.dtype.is_floating_point:
            bad |= (~torch.isfinite(value.detach()).reshape(n, -1).all(-1)).to(bad.device)
    for key in (("next", NONFINITE_KEY), ISOLATED_KEY):
        flag = batch.get(key, None)
        if isinstance(flag, torch.Tensor):
            bad |= flag.reshape(n, -1).any(-1).to(bad.device)
    return bad


class NonFiniteEnvMonitor:
    """Reports the non-finite envs of each iteration: [`update`][torchrl_diffenvs.objectives.NonFiniteEnvMonitor.update] returns their count (a
    learner's ``"nonfinite_envs"`` metric) and warns ([`NonFiniteEnvWarning`][torchrl_diffenvs.objectives.NonFiniteEnvWarning]) with their
    indices once per burst: when envs become non-finite that were not in the previous iteration.

    Args:
        who: the learner's name, for the messages.
    """

    def __init__(self, who: str):
        self.who = who
        self.current: list[int] = []  # the non-finite envs of the latest update
        self.num_envs = 0

    def update(self, bad: torch.Tensor, iteration: int) -> int:
        """Records the mask ``bad`` ``[N]`` of ``iteration``; returns how many envs it flags."""
        indices = bad.nonzero().flatten().tolist()
        self.num_envs = bad.numel()
        new = sorted(set(indices) - set(self.current))
        self.current = indices
        if new:
            warnings.warn(
                f"{self.who}: env(s) {_listed(indices)} of {self.num_envs} produced non-finite rewards or observations "
                f"at iteration {iteration}; they are left out of the loss until they are finite again. Likely cause: "
                "non-finite physical parameters or a diverging simulation in those envs",
                NonFiniteEnvWarning, stacklevel=3,
            )
        return len(indices)

    def describe(self) -> str:
        """Which envs were non-finite in the latest update, for an error message."""
        if not self.current:
            return "every env's rewards and observations were finite in the latest rollout"
        return f"env(s) {_listed(self.current)} of {self.num_envs} were non-finite in the latest rollout"


def _listed(indices: list[int], most: int = 20) -> str:
    shown = ", ".join(map(str, indices[:most]))
    return f"[{shown}{', ...' if len(indices) > most else ''}]"
