"""The one env step and the one auto-reset merge, on plain tensors.

:func:`physics_step` is what ``DiffEnv._step`` computes, what the lean rollout loop computes at
every step and what :func:`~torchrl_diffenvs.envs.rollout.compiled.compile_physics` traces;
:func:`merge_reset` is how every rollout path (eager steps and compiled chunks) replaces the
entries of the envs that are done by fresh start states. Both are pure tensor code, so
``torch.compile`` traces them, and both act on each env separately (one env's values never
change another's).

Entries are plain dicts: ``"observation"``, ``"state"`` (a dict of tensors), ``"params"`` (a
dict), ``"episode_step"``, and for a step's ``"next"`` also ``"reward"`` and the flags
``"terminated"``, ``"truncated"``, ``"done"``, ``"nonfinite"``, each ``[N]`` (the TorchRL layout
adds a trailing ``1`` when they go into a TensorDict).
"""
from __future__ import annotations

import torch

__all__ = ["ENV_KEYS", "FLAG_KEYS", "NESTED_ENV_KEYS", "merge_reset", "nonfinite_envs", "physics_step",
           "zero_nonfinite"]

# Entries the env owns at the root of a step TensorDict; everything else there ("action", a
# policy's "loc"/"scale", a user's own entries) belongs to the policy or the user.
FLAG_KEYS = ("terminated", "truncated", "done", "nonfinite")
ENV_KEYS = ("observation", "state", "params", "episode_step", *FLAG_KEYS)
NESTED_ENV_KEYS = ("state", "params")


def nonfinite_envs(n: int, tensors, device=None) -> torch.Tensor:
    """``[N]`` bool: the envs with a NaN or infinite value in any of ``tensors`` (``[N, ...]``).

    One sum per entry: a NaN or inf anywhere in an env's values makes its sum non-finite (so
    does a sum that overflows, i.e. values near the dtype's largest: a diverged env too).
    """
    total = None
    with torch.no_grad():  # a flag: no autograd graph for it
        for value in tensors:
            if not value.is_floating_point():
                continue
            value = value if value.dim() == 1 else value.reshape(n, -1).sum(-1)
            total = value if total is None else total + value
    if total is None:
        return torch.zeros(n, dtype=torch.bool, device=device)
    return ~torch.isfinite(total)


def physics_step(env, state: dict, params: dict, episode_step: torch.Tensor, action: torch.Tensor,
                 zero: bool = True) -> dict:
    """One step of ``env``'s physics: the ``"next"`` entries (``"params"`` excepted: unchanged).

    Clips the action if the task does (``clip_actions``), runs ``transition``, counts the step,
    then flags the envs whose new state or reward is not finite (``"nonfinite"``): they are
    marked terminated (so an auto-reset restarts them, and a value target does not bootstrap
    from them), and the non-finite elements of their ``"observation"`` and ``"reward"`` are
    replaced by ``0`` (their finite elements are kept), so that they cannot poison batch
    statistics. Their ``"state"`` keeps the non-finite values. For finite envs this changes
    nothing, values and gradients alike.

    ``zero=False`` leaves the zeroing to the caller (:func:`zero_nonfinite`): the eager loop
    applies it only at steps where some env is done (a flagged env is always done).
    """
    if env.clip_actions:
        action = action.clamp(env.action_low, env.action_high)
    state, reward, terminated = env.transition(state, action, params)
    episode_step = episode_step + 1
    nonfinite = nonfinite_envs(episode_step.shape[0], (*state.values(), reward), episode_step.device)
    terminated = nonfinite if terminated is None else terminated | nonfinite
    truncated = env._truncated(episode_step, terminated)
    nxt = {
        "observation": env.observation(state, params),
        "state": state,
        "episode_step": episode_step,
        "reward": reward,
        "terminated": terminated,
        "truncated": truncated,
        "done": terminated | truncated,
        "nonfinite": nonfinite,
    }
    return zero_nonfinite(nxt) if zero else nxt


def zero_nonfinite(nxt: dict) -> dict:
    """Replaces the NaN/inf elements of a step's ``"observation"`` and ``"reward"`` by ``0``
    (in place; returns ``nxt``). The gradient of the other elements passes unchanged."""
    for key in ("observation", "reward"):
        nxt[key] = torch.nan_to_num(nxt[key], nan=0.0, posinf=0.0, neginf=0.0)
    return nxt


def _where(keep: torch.Tensor, old: torch.Tensor, new) -> torch.Tensor:
    return torch.where(keep.reshape(keep.shape + (1,) * (old.ndim - 1)), old, new)


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
        "episode_step": _where(keep, nxt["episode_step"], torch.zeros((), dtype=nxt["episode_step"].dtype,
                                                                    device=done.device)),
        **{key: false for key in FLAG_KEYS},
    }
    keep_extras = keep | done.all()
    extras = {key: _zero_where(keep_extras, value) for key, value in extras.items()}
    return root, extras


def _zero_where(keep: torch.Tensor, value):
    """``value`` with the entries of the envs not kept set to zero (a tensor or a TensorDict)."""
    if isinstance(value, torch.Tensor):
        return _where(keep, value, torch.zeros((), dtype=value.dtype, device=value.device))
    return value.where(keep, other=value.empty(), pad=0)
