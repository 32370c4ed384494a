"""The lean implementation of ``EnvBase.rollout`` for [`DiffEnv`][torchrl_diffenvs.DiffEnv].

TorchRL's generic rollout builds, validates, copies and merges several TensorDicts per step
(``step``, ``step_mdp``, ``maybe_reset``, the random-action TensorDict): on CPU that machinery
costs several times the physics of our tasks. Because a DiffEnv's physics are pure tensor
functions, a rollout can instead loop over plain tensors, call the policy on one light
TensorDict per step (only when there is a policy), stack each entry once at the end and build
the output TensorDict once. ``DiffEnv.rollout`` takes this path when
`fast_rollout_unsupported` finds nothing in the way, and ``EnvBase.rollout`` otherwise.

Modules:

* `step`: the one step (`physics_step`, also ``DiffEnv._step``) and the one
  auto-reset merge (`merge_reset`);
* `loop`: the loop (`fast_rollout`), eager steps and compiled chunks;
* `compiled`: [`compile_physics`][torchrl_diffenvs.compile_physics] and the chunk function it compiles;
* `output`: TensorDicts in and out; `actions`: random actions without a policy.

The result equals ``EnvBase.rollout``'s for the same env seed and the same actions: keys,
shapes, dtypes, values (bitwise, eagerly), gradients, auto-resets, ``break_when_any_done`` and
the side effects on the input ``tensordict``; random actions come from torch's global
generator as TorchRL draws them. Compiled chunks draw a stochastic policy's noise from
inductor's generator, so the global random stream is not TorchRL's there.
"""
from .compiled import compile_physics, compile_report, eager_physics
from .loop import fast_rollout
from .support import FAST_ROLLOUT_KWARGS, fast_rollout_unsupported
from .step import merge_reset, physics_step

__all__ = [
    "FAST_ROLLOUT_KWARGS", "compile_physics", "compile_report", "eager_physics", "fast_rollout",
    "fast_rollout_unsupported", "merge_reset", "physics_step",
]
