"""Reading rollout windows ``[N, H]``: what the window losses and the learners (BPTT, SHAC,
AHAC, SAPO) share."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["CONTACT_FORCE_KEY", "SOLVER_UNCONVERGED_KEY", "like_agents", "steps_since_start", "window_contact_force",
           "window_entry", "window_solver_unconverged"]


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


CONTACT_FORCE_KEY = ("state", "contact_force")  # where the MuJoCo contact tasks report it
SOLVER_UNCONVERGED_KEY = ("state", "solver_unconverged")  # the MuJoCo contact tasks' unconverged solves


def window_solver_unconverged(window: TensorDictBase) -> float | None:
    """The share of a window's env steps ``[N, H]`` whose constraint solve did not converge within
    the model file's iterations (``("next", "state", "solver_unconverged")``, written by the tasks
    with MuJoCo's contact model); ``None`` when the window has no such entry."""
    flags = window.get(("next", *SOLVER_UNCONVERGED_KEY), None)
    return None if flags is None else flags.float().mean().item()


def window_contact_force(window: TensorDictBase, who: str | None = None) -> torch.Tensor | None:
    """The largest contact normal force of each step of a window ``[N, H]`` (detached), read from
    ``("next", "state", "contact_force")`` (the MuJoCo contact tasks write it, see
    ``MuJoCoModelEnv.reports_contact_force``) or, for any other env, from a root
    ``("next", "contact_force")`` entry a transform writes (``[N, 1]``, newtons).

    Returns ``None`` when the window has neither, or raises a ``KeyError`` naming the keys and
    the envs that write them when ``who`` (the caller's name) is given.
    """
    value = window.get(("next", *CONTACT_FORCE_KEY), None)
    if value is None:
        value = window.get(("next", "contact_force"), None)
    if value is None:
        if who is None:
            return None
        raise KeyError(
            f"{who}: the rollout has no ('next', 'state', 'contact_force') entry; AHAC adapts its window from the "
            "contact force that the MuJoCo contact tasks (HalfCheetah-v5, Hopper-v5, Walker2d-v5, Ant-v5, the humanoids, Pusher-v5) report at "
            "every step; for another env add a transform that writes ('next', 'contact_force') ([N, 1], newtons)"
        )
    return value.detach().reshape(window.batch_size)
