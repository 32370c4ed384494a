"""Every use of TorchRL's, tensordict's and torch's private names, in one fenced module.

The rest of the package touches public APIs only; what it needs beyond them is here, each with
why. Checked against the versions in `CHECKED_VERSIONS`; ``tests/project/test_compat.py``
exercises every assumption below and fails loudly on a version where one breaks (run it first
after upgrading TorchRL or tensordict).
"""
from __future__ import annotations

import torch
import torch._dynamo.exc
from tensordict import TensorDict, TensorDictBase
from tensordict.nn.probabilistic import interaction_type as _interaction_type
from torch.distributions.utils import _standard_normal
from torchrl.envs.utils import _make_compatible_policy
from torchrl.modules.distributions.continuous import SafeTanhTransform

__all__ = [
    "CHECKED_VERSIONS", "ENVBASE_STEP_METHODS", "SafeTanhTransform", "collector_carrier_state",
    "current_interaction_type", "has_dynamic_specs", "load_collector_carrier", "make_compatible_policy",
    "rollout_machinery_in_use", "sampler_has_own_generator", "standard_normal", "unchecked_tensordict",
]

CHECKED_VERSIONS = {"torchrl": "0.14.1", "tensordict": "0.14.3", "torch": "2.13.0"}


# ---------------------------------------------------------------------- the lean rollout (envs/rollout/)
# TorchRL's private EnvBase methods that ``EnvBase.rollout`` goes through and the lean loop
# reimplements: an env class overriding one of them must take ``EnvBase.rollout``.
ENVBASE_STEP_METHODS = ("_step_proc_data", "_reset_proc_data", "_step_and_maybe_reset")


def make_compatible_policy(policy, env, trust_policy: bool):
    """The policy wrapping ``EnvBase.rollout`` applies (plain callables become TensorDict
    modules), so that the lean loop calls the policy exactly as TorchRL does."""
    return _make_compatible_policy(policy, env.observation_spec, env=env, fast_wrap=True, trust_policy=trust_policy)


def rollout_machinery_in_use(env) -> str | None:
    """What TorchRL would run inside ``EnvBase.rollout`` for ``env`` beyond its plain step loop
    (the lean loop then stands aside), or ``None``."""
    if env.__dict__.get("_compiled_step_and_maybe_reset") is not None:  # set by EnvBase.compile()
        return "env.compile() is active"
    if env.__dict__.get("_torchrl_native_autoreset", False):
        return "native auto-reset"
    if env._post_step_mdp_hooks is not None:
        return "post-step-mdp hooks"
    return None


def has_dynamic_specs(env) -> bool:
    """``EnvBase.rollout``'s default for ``return_contiguous`` is ``not env._has_dynamic_specs``."""
    return bool(env._has_dynamic_specs)


def unchecked_tensordict(source: dict, batch_size: torch.Size, device) -> TensorDict:
    """A TensorDict built without validating its entries (every entry already has the right batch
    size and device): about 15 us per TensorDict saved in the per-step loop."""
    return TensorDict._new_unsafe(source, batch_size=batch_size, device=device)


# ---------------------------------------------------------------------- the actor shortcut (modules/actors.py)
def current_interaction_type():
    """The exploration/interaction mode set by ``set_exploration_type`` / ``set_interaction_type``
    (``None`` when none is set)."""
    return _interaction_type()


def sampler_has_own_generator(sampler) -> bool:
    """Whether a ``ProbabilisticTensorDictModule`` samples from its own generator (then the
    shortcut, which draws from torch's global stream, must not be used)."""
    return any(getattr(sampler, name, None) is not None for name in ("_generator", "_generator_key"))


def standard_normal(shape, dtype, device) -> torch.Tensor:
    """The noise ``Normal.rsample`` draws (same call, same random stream)."""
    return _standard_normal(shape, dtype=dtype, device=device)


# ---------------------------------------------------------------------- collector state (learners/ppo.py, sac.py)
def collector_carrier_state(collector) -> dict | None:
    """The env TensorDict a TorchRL ``Collector`` will step from next, as plain tensors.

    TorchRL's ``Collector.state_dict`` leaves out the in-flight env state ("not generally
    serializable"); our envs keep their whole state in that TensorDict, so saving it lets a
    resumed run continue the same episodes. It lives in the private ``_carrier`` attribute;
    ``None`` (resume then starts fresh episodes) if a future TorchRL renames it.
    """
    carrier = getattr(collector, "_carrier", None)
    if not isinstance(carrier, TensorDictBase):
        return None
    carrier = carrier.exclude("collector")
    return {"batch_size": list(carrier.batch_size), "data": carrier.to_dict()}


def load_collector_carrier(collector, state: dict | None) -> None:
    """Restores `collector_carrier_state` (no-op for ``None``)."""
    carrier = getattr(collector, "_carrier", None)
    if state is not None and isinstance(carrier, TensorDictBase):
        carrier.update(TensorDict(state["data"], batch_size=state["batch_size"], device=carrier.device))


# torch.compile's failures (no C++ compiler for inductor, an operation dynamo cannot trace, a
# backend error): the compiled rollout chunks fall back to eager on these, and only these.
COMPILE_ERRORS: tuple[type[BaseException], ...] = (torch._dynamo.exc.TorchDynamoException,)
