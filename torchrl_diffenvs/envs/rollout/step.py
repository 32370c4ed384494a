"""The one env step and the one auto-reset merge, on plain tensors.

`physics_step` is what ``DiffEnv._step`` computes, what the lean rollout loop computes at
every step and what [`compile_physics`][torchrl_diffenvs.compile_physics] traces;
`merge_reset` is how every rollout path (eager steps and compiled chunks) replaces the
entries of the envs that are done by fresh start states. Both are pure tensor code, so
``torch.compile`` traces them, and both act on each env separately (one env's values never
change another's).

Entries are plain dicts: ``"observation"``, ``"state"`` (a dict of tensors), ``"params"`` (a
dict), ``"episode_step"``, and for a step's ``"next"`` also ``"reward"`` and the flags
``"terminated"``, ``"truncated"``, ``"done"``, ``"nonfinite"``, each ``[N]`` (the TorchRL layout
adds a trailing ``1`` when they go into a TensorDict).
"""
from __future__ import annotations

import math

import torch

__all__ = ["ENV_KEYS", "FLAG_KEYS", "NESTED_ENV_KEYS", "merge_reset", "nonfinite_rows", "physics_step"]

# Entries the env owns at the root of a step TensorDict; everything else there ("action", a
# policy's "loc"/"scale", a user's own entries) belongs to the policy or the user.
FLAG_KEYS = ("terminated", "truncated", "done", "nonfinite")
ENV_KEYS = ("observation", "state", "params", "episode_step", *FLAG_KEYS)
NESTED_ENV_KEYS = ("state", "params")


def nonfinite_rows(n: int, tensors, device=None) -> torch.Tensor:
    """``[N]`` bool: the rows (envs) with a NaN or infinite value in any of the plain
    ``tensors`` (``[N, ...]``), as one env step needs it (the learners' mask over a rollout's
    entries is [`nonfinite_envs`][torchrl_diffenvs.objectives.nonfinite_envs]).

    One sum per entry: a NaN or inf anywhere in an env's values makes its sum non-finite (so
    does a sum that overflows, i.e. values near the dtype's largest: a diverged env too).
    """
    if not any(value.is_floating_point() for value in tensors):
        return torch.zeros(n, dtype=torch.bool, device=device)
    total = _flat(n, tensors).sum(1)
    return (total - total) != 0  # NaN exactly where the sum is NaN or inf (torch.isfinite takes 3 ops)


def physics_step(env, state: dict, params: dict, episode_step: torch.Tensor, action: torch.Tensor,
                 all_false: torch.Tensor | None = None, check: bool = True) -> dict:
    """One step of ``env``'s physics: the ``"next"`` entries (``"params"`` excepted: unchanged).

    Clips the action if the task does (``clip_actions``), runs ``transition``, counts the step,
    then flags the envs whose new state or reward is not finite (``"nonfinite"``): they are
    marked terminated (so an auto-reset restarts them, and a value target does not bootstrap
    from them), and the non-finite elements of their ``"observation"`` and ``"reward"`` are
    replaced by ``0`` (their finite elements are kept), so that they cannot poison batch
    statistics. Their ``"state"`` keeps the non-finite values. For finite envs this changes
    nothing, values and gradients alike.

    ``all_false`` (an ``[N]`` all-``False`` tensor; eager callers only): first one check of the
    whole batch (one host sync), and per-env flags only if something is not finite; flags that
    need no computation are ``all_false`` itself, and ``"done"`` is ``"truncated"`` itself for
    a task without termination: fewer ops per step, and the same tensors from step to step
    (the rollout output expands them instead of stacking). The values are the same.

    ``check=False`` (with ``all_false``): no check at all, every env is taken as finite; for a
    caller that checks the values afterwards and steps again with checks if one is not
    (the eager loop without a policy, see `loop`).
    """
    if env.clip_actions:
        action = action.clamp(env.action_low, env.action_high)
    state, reward, terminated = env.transition(state, action, params)
    episode_step = episode_step + 1
    observation = env.observation(state, params)
    n, values = episode_step.shape[0], (*state.values(), reward)
    if all_false is None or (check and not _all_finite(values)):
        nonfinite = nonfinite_rows(n, values, episode_step.device)
        terminated = nonfinite if terminated is None else terminated | nonfinite
        observation, reward = (torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) for x in (observation, reward))
    else:
        nonfinite = all_false
    if terminated is None:  # only with all_false: nothing terminated, done is truncated
        if getattr(type(env)._truncated, "time_limit_rule", False):  # DiffEnv's own rule: one comparison
            limit = env.max_episode_steps
            truncated = all_false if limit is None else episode_step >= limit
        else:
            truncated = env._truncated(episode_step, all_false)
        terminated, done = all_false, truncated
    else:
        truncated = env._truncated(episode_step, terminated)
        done = terminated | truncated
    return {"observation": observation, "state": state, "episode_step": episode_step, "reward": reward,
            "terminated": terminated, "truncated": truncated, "done": done, "nonfinite": nonfinite}


def _all_finite(values) -> bool:
    """Whether every value is finite: one sum of them all, one host sync (non-finite exactly when
    the sum of `_flat`'s ``[N, K]`` is: the same values in another layout, ``cat`` and
    ``stack`` promoting to the widest dtype as ``_flat`` converts; integer entries are finite and
    change nothing). No autograd bookkeeping for it, and none of ``torch.no_grad``'s when autograd
    is off already.
    """
    grad = torch.is_grad_enabled()
    if grad:
        torch.set_grad_enabled(False)
    try:
        if all(value.dim() == 1 for value in values):  # one op, no reshapes
            total = torch.stack(values).sum()
        else:
            total = torch.cat([value.reshape(-1) for value in values]).sum()
        return math.isfinite(total.item())
    finally:
        if grad:
            torch.set_grad_enabled(True)


def _flat(n: int, values) -> torch.Tensor:
    """``[N, K]``: every floating-point value of each env in one row, detached (a sum of them
    is non-finite if one is)."""
    values = [value for value in values if value.is_floating_point()]
    with torch.no_grad():  # a flag: no autograd graph for it
        if len({value.dtype for value in values}) > 1:
            values = [value.to(torch.float64) for value in values]
        if all(value.dim() == 1 for value in values):  # one op, no reshapes
            return torch.stack(values, dim=1)
        return torch.cat([value.reshape(n, -1) for value in values], dim=1)


def _where(keep: torch.Tensor, old: torch.Tensor, new) -> torch.Tensor:
    return torch.where(keep if old.ndim == 1 else keep.reshape(keep.shape + (1,) * (old.ndim - 1)), old, new)


def merge_reset(done: torch.Tensor, nxt: dict, start: dict, extras: dict, params: dict,
                start_params: dict | None) -> tuple[dict, dict]:
    """The root entries of the step after ``nxt`` when the envs ``done`` (``[N]`` bool) restart.

    What TorchRL's ``maybe_reset`` does with ``torch.where(~done, old, fresh)``: done envs take
    ``start`` (``{"observation", "state"}`` drawn for every env, as ``DiffEnv._reset`` draws
    them), episode step ``0``, all flags ``False`` and ``start_params`` (``None``: the physical
    parameters ``params`` stay as they are); the others keep ``nxt``'s entries. The graph is cut
    for the done envs only. The other root entries (``extras``: the action, the policy's
    outputs, a user's entries) are zeroed for the done envs, unless every env is done (TorchRL
    then leaves them as they are).
    """
    keep = ~done
    false = torch.zeros_like(done)
    root = {
        "observation": _where(keep, nxt["observation"], start["observation"]),
        "state": {key: _where(keep, value, start["state"][key]) for key, value in nxt["state"].items()},
        "params": params if start_params is None else
        {key: _where(keep, value, start_params[key]) for key, value in params.items()},
        "episode_step": torch.where(keep, nxt["episode_step"], 0),
        **{key: false for key in FLAG_KEYS},
    }
    if extras:
        keep_extras = keep | done.all()
        extras = {key: _zero_where(keep_extras, value) for key, value in extras.items()}
    return root, extras


def _zero_where(keep: torch.Tensor, value):
    """``value`` with the entries of the envs not kept set to zero (a tensor or a TensorDict)."""
    if isinstance(value, torch.Tensor):
        return _where(keep, value, torch.zeros((), dtype=value.dtype, device=value.device))
    return value.where(keep, other=value.empty(), pad=0)
