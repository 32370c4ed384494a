"""When the lean rollout applies: `fast_rollout_unsupported` says why a call must take
``EnvBase.rollout`` instead (an argument the lean path does not implement, an env that overrides
a method it reimplements, TorchRL machinery in use)."""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from tensordict import TensorDict
from torchrl.envs import EnvBase

from ..._compat import ENVBASE_STEP_METHODS, rollout_machinery_in_use

__all__ = ["FAST_ROLLOUT_KWARGS", "fast_rollout_unsupported"]

_DONE_KEYS = ("terminated", "truncated", "done")

# Keyword arguments of EnvBase.rollout that the lean path implements, with the values it accepts
# (``None`` = any value). Anything else sends the call to EnvBase.rollout.
FAST_ROLLOUT_KWARGS: dict[str, tuple | None] = {
    "auto_reset": None,
    "break_when_any_done": None,
    "break_when_all_done": (None, False),
    "return_contiguous": None,
    "tensordict": None,
    "set_truncated": None,
    "trust_policy": None,
    "set_state": None,
    "actions": None,
    "auto_cast_to_device": (False,),
    "storing_device": (None,),
    "out": (None,),
}

# Methods whose TorchRL / DiffEnv versions the lean loop reimplements: a subclass that overrides
# one of them gets EnvBase.rollout, which calls the override.
_REIMPLEMENTED_METHODS = (
    "_step", "_reset", "step", "reset", "maybe_reset", "step_and_maybe_reset", "rand_action", "any_done", "_output",
    *ENVBASE_STEP_METHODS,
)


def fast_rollout_unsupported(env: EnvBase, callback: Callable | None, kwargs: Mapping[str, Any]) -> str | None:
    """Why ``env.rollout(..., callback=callback, **kwargs)`` must take ``EnvBase.rollout``.

    Returns ``None`` when the lean path reproduces the call, else a short reason (useful when
    debugging a slow rollout: ``fast_rollout_unsupported(env, None, kwargs)``).
    """
    if not getattr(env, "use_fast_rollout", True):
        return "env.use_fast_rollout is False"
    if callback is not None:
        return "a callback is given"
    for key, value in kwargs.items():
        if key not in FAST_ROLLOUT_KWARGS:
            return f"unknown keyword argument {key!r}"
        allowed = FAST_ROLLOUT_KWARGS[key]
        if allowed is not None and not any(value is a or (a is not None and value == a) for a in allowed):
            return f"{key}={value!r}"
    # (a task with its own truncation rule overrides DiffEnv._truncated, which the loop calls)
    overridden = type(env).overridden_methods(_REIMPLEMENTED_METHODS)
    if overridden:
        return f"{type(env).__name__} overrides {overridden[0]}"
    machinery = rollout_machinery_in_use(env)
    if machinery is not None:
        return machinery
    if env.run_type_checks:
        return "run_type_checks"
    if env.action_keys != ["action"] or env.reward_keys != ["reward"] or sorted(env.done_keys) != sorted(_DONE_KEYS):
        return "non-default action/reward/done keys"
    td = kwargs.get("tensordict")
    if td is not None and (not isinstance(td, TensorDict) or "next" in td.keys() or "_step" in td.keys()):
        return "the input tensordict is not a plain TensorDict without 'next'/'_step' entries"
    return None
