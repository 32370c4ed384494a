"""Helpers shared by the window losses (BPTT, SHAC)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase


def steps_since_start(done: torch.Tensor) -> torch.Tensor:
    """For a window ``done`` ``[N, H]`` (bool), the number of steps since the start of each
    sub-trajectory: ``k_t = 0`` at the window start and right after every done step.

    >>> steps_since_start(torch.tensor([[False, False, True, False]]))
    tensor([[0, 1, 2, 0]])
    """
    n, h = done.shape
    t = torch.arange(h, device=done.device).expand(n, h)
    starts = torch.zeros_like(t)
    starts[:, 1:] = torch.where(done[:, :-1], t[:, 1:], 0)
    return t - starts.cummax(dim=-1).values


def window_entry(td: TensorDictBase, key, name: str) -> torch.Tensor:
    """``td[("next", key)]`` of a window ``[N, H]`` as ``[N, H]`` (the trailing 1 removed), or
    ``[N, H, A]`` for a multi-agent entry ``[N, H, A, 1]`` (e.g. ``("agents", "reward")``)."""
    if td.batch_dims != 2:
        raise ValueError(
            f"{name}: expected a rollout window with batch size [N, H] (envs, time), got {tuple(td.batch_size)}"
        )
    value = td.get(("next", key), None)
    if value is None:
        raise KeyError(f"{name}: the window has no ('next', {key!r}) entry; keys: {sorted(map(str, td.keys(True, True)))}")
    if value.shape[2:] in ((), (1,)):
        return value.reshape(td.batch_size)
    if value.ndim == 4 and value.shape[-1] == 1:
        return value.squeeze(-1)
    raise ValueError(f"{name}: expected ('next', {key!r}) of shape [N, H], [N, H, 1] or [N, H, A, 1] "
                     f"(A agents), got {tuple(value.shape)}")


def like_agents(flags: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    """Per-env ``flags`` ``[N, H]`` (done, discounts) broadcastable against ``reward`` ``[N, H]``
    or ``[N, H, A]``: the agents of a multi-agent env share one episode."""
    return flags.reshape(*flags.shape, *([1] * (reward.ndim - flags.ndim)))
