"""The policies: TorchRL ``ProbabilisticActor``s with a ``TanhNormal`` squashed into the action
bounds (a direct path for a rollout's calls), SAPO's squashed normal with its exact
log-probability, and Ivy Gym's deterministic tanh policy."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, InteractionType, TensorDictModuleBase
from torch import nn
from torch.distributions import AffineTransform
from torchrl.modules import ProbabilisticActor, TanhNormal

from .._compat import SafeTanhTransform, current_interaction_type, sampler_has_own_generator, standard_normal
from ..envs.multi_agent import policy_keys
from ..normalization import ObservationNormalizer
from .networks import LeanModule, env_dims, make_agent_mlp, make_mlp, orthogonal_init_

__all__ = ["DISTRIBUTIONS", "ScaledTanh", "SquashedNormalActor", "TanhNormalActor", "action_bounds", "make_actor",
           "make_sapo_actor"]

DISTRIBUTIONS = ("tanh_normal", "deterministic")
"""The valid ``distribution`` names of `make_actor`."""


def action_bounds(env, who: str = "make_actor") -> tuple[float, float]:
    """``(low, high)`` of ``env``'s action spec, the same for every action dimension (``who``:
    the caller's name, for the error)."""
    spec = env.full_action_spec_unbatched[env.action_key]
    low, high = spec.space.low, spec.space.high
    if not (torch.all(low == low.flatten()[0]) and torch.all(high == high.flatten()[0])):
        raise ValueError(f"{who}: expected the same bounds for every action dimension, got {low} and {high}")
    return float(low.flatten()[0]), float(high.flatten()[0])


class ScaledTanh(nn.Module):
    """``low + (tanh(x) + 1) / 2 * (high - low)``: squashes into the action bounds."""

    def __init__(self, low: float, high: float):
        super().__init__()
        self.low, self.high = float(low), float(high)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.low + (torch.tanh(x) + 1) * (0.5 * (self.high - self.low))


class TanhNormalActor(ProbabilisticActor):
    """The ``ProbabilisticActor`` that [`make_actor`][torchrl_diffenvs.modules.make_actor] builds: a ``TanhNormal`` over ``"loc"`` /
    ``"scale"`` squashed into ``[low, high]``, with a direct path for the calls a rollout makes.

    A rollout calls the policy once per step. ``ProbabilisticActor.forward`` builds a
    ``TanhNormal`` (with its transforms and argument checks) and runs tensordict's generic
    sampling machinery: about 0.5 ms per call on top of the network here, more than a 64-64 MLP
    or a pendulum step costs at N = 64. For the common calls (sampling under
    ``ExplorationType.RANDOM``, or the squashed mean under ``DETERMINISTIC``, without a
    log-probability, an output TensorDict or a per-call generator) `forward` computes the
    same thing directly: ``loc + eps * scale`` with
    ``eps`` drawn exactly as ``Normal.rsample`` draws it, then TorchRL's ``SafeTanhTransform``
    and the affine map into the bounds. Same values, same gradients, same random stream
    (``tests/learners/test_modules.py`` checks them bit for bit against ``ProbabilisticActor.forward``).
    Every other call, and `get_dist` (used by TorchRL's PPO and SAC losses), goes
    through ``ProbabilisticActor`` unchanged.
    """

    def __init__(self, module: TensorDictModuleBase, low: float, high: float, **kwargs):
        super().__init__(
            module,
            in_keys=list(module.out_keys),  # "loc", "scale" (or ("agents", "loc"), ...)
            distribution_class=TanhNormal,
            distribution_kwargs={"low": low, "high": high},
            **kwargs,
        )
        low_t, high_t = torch.as_tensor(low), torch.as_tensor(high)  # as TanhNormal stores them
        self._tanh = SafeTanhTransform()
        # TanhNormal skips the affine map for the bounds [-1, 1]
        trivial = bool(low_t == -1.0) and bool(high_t == 1.0)
        self._affine = None if trivial else AffineTransform(loc=(high_t + low_t) / 2, scale=(high_t - low_t) / 2)

    def _direct_mode(self, tensordict, tensordict_out, kwargs) -> InteractionType | None:
        sampler = self.module[-1]
        # anything ProbabilisticActor would do beyond "sample, squash, write": leave it to it
        # (these are attributes, not constructor constants: users may change them later)
        if tensordict_out is not None or kwargs or not isinstance(tensordict, TensorDictBase):
            return None
        if sampler.return_log_prob or getattr(sampler, "safe", False) or len(self.module) != 2:
            return None
        if getattr(sampler, "num_samples", None) is not None or sampler_has_own_generator(sampler):
            return None
        mode = current_interaction_type()
        if mode is None:
            mode = sampler.default_interaction_type
        return mode if mode in (InteractionType.RANDOM, InteractionType.DETERMINISTIC) else None

    def forward(self, tensordict, tensordict_out=None, **kwargs):
        mode = self._direct_mode(tensordict, tensordict_out, kwargs)
        if mode is None:
            return super().forward(tensordict, tensordict_out, **kwargs)
        tensordict = self.module[0](tensordict)  # writes "loc" and "scale"
        loc_key, scale_key = self.module[0].out_keys
        loc = tensordict.get(loc_key)
        pre_tanh = loc
        if mode is InteractionType.RANDOM:
            scale = tensordict.get(scale_key)
            # Normal.rsample: loc + eps * scale, eps from the global stream
            pre_tanh = loc + standard_normal(loc.shape, dtype=loc.dtype, device=loc.device) * scale
        tensordict.set(self.module[-1].out_keys[0], self.squash(pre_tanh))  # "action"
        return tensordict

    def mean_action(self, observation: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``squash(loc)`` for an observation tensor (no TensorDict):
        what a frozen copy of this actor plays as an opponent."""
        return self.squash(self.module[0].module(observation)[0])

    def squash(self, pre_tanh: torch.Tensor) -> torch.Tensor:
        """TanhNormal's map into the action bounds; ``squash(loc)`` is the deterministic action."""
        action = self._tanh(pre_tanh)
        return self._affine(action) if self._affine is not None else action


def make_actor(
    env,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    norm_after_activation: bool = False,
    init: str = "default",
    init_log_std: float = -1.0,
    distribution: str = "tanh_normal",
    normalizer: ObservationNormalizer | None = None,
    return_log_prob: bool = False,
    in_key: str | None = None,
) -> TensorDictModuleBase:
    """A policy for ``env`` reading ``in_key`` and writing ``"action"``.

    On a multi-agent env (``("agents", ...)`` keys) the same policy acts for every agent from its
    own observation: a parameter-shared ``MultiAgentMLP`` reading ``("agents", "observation")``
    and writing ``("agents", "loc")``, ``("agents", "scale")``, ``("agents", "action")``.

    Args:
        env: a [`DiffEnv`][torchrl_diffenvs.DiffEnv], or any TorchRL env with a floating-point
            ``in_key`` observation and a bounded action spec (sizes from [`env_dims`][torchrl_diffenvs.modules.env_dims]).
        hidden: the MLP's hidden sizes ([`make_mlp`][torchrl_diffenvs.modules.make_mlp]; SHAC's reference: ``(64, 64)``).
        activation: the MLP's activation (SHAC's reference: ELU).
        layer_norm: a LayerNorm in each hidden layer (SHAC's reference: yes).
        norm_after_activation: the LayerNorm after the activation (SHAC's reference) instead of before.
        init: the weights' initialisation, as in [`make_mlp`][torchrl_diffenvs.modules.make_mlp].
        init_log_std: initial log standard deviation (pre-tanh) of the stochastic policy.
        distribution: ``"tanh_normal"`` (default): a ``ProbabilisticActor`` with a ``TanhNormal``
            squashed into the action bounds; it writes ``"loc"``, ``"scale"``, ``"action"`` (and
            the log-probability when ``return_log_prob``). Under ``ExplorationType.RANDOM`` it
            samples with ``rsample`` (reparameterised: gradients reach loc and scale); under
            ``DETERMINISTIC`` it returns the squashed mean. ``"deterministic"``: a module
            ``MLP -> tanh`` scaled into the action bounds writing ``"action"`` (Ivy Gym's
            policy); no sampling.
        normalizer: an [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] applied to the observation first.
        return_log_prob: store the log-probability of the sampled action (needed by PPO).
        in_key: the observation entry to read (default: the env's, `policy_keys`).
    """
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"make_actor: unknown distribution {distribution!r}; valid: {DISTRIBUTIONS}")
    keys = policy_keys(env)
    in_key = keys.observation if in_key is None else in_key
    observation_dim, action_dim, dtype = env_dims(env, in_key)
    low, high = action_bounds(env)
    if keys.num_agents is None:
        net = make_mlp(observation_dim, action_dim, hidden, activation, layer_norm, dtype, norm_after_activation, init)
    else:
        net = make_agent_mlp(observation_dim, action_dim, keys.num_agents, hidden, activation, layer_norm, dtype,
                             norm_after_activation, init)
    prefix = [normalizer] if normalizer is not None else []
    if distribution == "deterministic":
        return LeanModule(nn.Sequential(*prefix, net, ScaledTanh(low, high)), in_keys=[in_key], out_keys=[keys.action])
    # loc = MLP(observation), scale = exp(log-std), one learned value per action dimension
    scale = AddStateIndependentNormalScale(action_dim, scale_mapping="exp", init_value=float(init_log_std))
    head = nn.Sequential(*prefix, net, scale.to(dtype))
    module = LeanModule(head, in_keys=[in_key], out_keys=[keys.loc, keys.scale])
    return TanhNormalActor(module, low, high, spec=env.full_action_spec_unbatched[keys.action], out_keys=[keys.action],
                           return_log_prob=return_log_prob, log_prob_key=keys.log_prob)


class _LocScale(nn.Module):
    """Splits ``[..., 2A]`` into ``loc`` and ``scale = exp(clamp(log_std, low, high))``."""

    def __init__(self, action_dim: int, min_log_std: float, max_log_std: float):
        super().__init__()
        self.action_dim, self.min_log_std, self.max_log_std = int(action_dim), float(min_log_std), float(max_log_std)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = x.split(self.action_dim, dim=-1)
        return loc, log_std.clamp(self.min_log_std, self.max_log_std).exp()


class SquashedNormalActor(TanhNormalActor):
    """A ``TanhNormal`` policy that writes the exact log-probability of the actions it samples.

    TorchRL's ``TanhNormal.log_prob(action)`` inverts the squashing (``atanh`` of the action),
    which loses the pre-tanh value once ``tanh`` rounds to +-1 (in float32 from about
    ``|u| > 9``). When it samples (``ExplorationType.RANDOM``) this actor draws
    ``u = loc + eps * scale`` (``rsample``: the same random stream as ``Normal.rsample``) and
    writes ``action = squash(u)`` and its log-probability from ``u``:

    ```text
    sum_i [ -eps_i^2 / 2 - log scale_i - log(2 pi) / 2 - log(1 - tanh(u_i)^2) - log((high - low) / 2) ]
    ```

    with ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))`` (finite for every ``u``). In
    ``DETERMINISTIC`` mode it writes ``squash(loc)``. Every other call, and ``get_dist``, is
    ``ProbabilisticActor``'s.
    """

    def __init__(self, module, low: float, high: float, log_prob_key="action_log_prob", **kwargs):
        super().__init__(module, low, high, return_log_prob=True, log_prob_key=log_prob_key, **kwargs)
        self._log_prob_out = log_prob_key
        self._log_half_range = math.log((float(high) - float(low)) / 2)

    def log_prob_from_noise(self, eps: torch.Tensor, scale: torch.Tensor, pre_tanh: torch.Tensor) -> torch.Tensor:
        """Log-probability ``[...]`` of ``squash(pre_tanh)`` with ``pre_tanh = loc + eps * scale``."""
        normal = -0.5 * eps.pow(2) - scale.log() - 0.5 * math.log(2 * math.pi)
        log_jacobian = 2 * (math.log(2) - pre_tanh - nn.functional.softplus(-2 * pre_tanh)) + self._log_half_range
        return (normal - log_jacobian).sum(-1)

    def forward(self, tensordict, tensordict_out=None, **kwargs):
        mode = current_interaction_type()
        if mode is None:
            mode = self.module[-1].default_interaction_type
        plain = tensordict_out is None and not kwargs and isinstance(tensordict, TensorDictBase)
        if not plain or mode not in (InteractionType.RANDOM, InteractionType.DETERMINISTIC):
            return super().forward(tensordict, tensordict_out, **kwargs)
        tensordict = self.module[0](tensordict)  # "loc", "scale"
        loc_key, scale_key = self.module[0].out_keys
        loc = tensordict.get(loc_key)
        if mode is InteractionType.DETERMINISTIC:
            tensordict.set(self.module[-1].out_keys[0], self.squash(loc))
            return tensordict
        scale = tensordict.get(scale_key)
        eps = standard_normal(loc.shape, dtype=loc.dtype, device=loc.device)
        pre_tanh = loc + eps * scale
        tensordict.set(self.module[-1].out_keys[0], self.squash(pre_tanh))
        tensordict.set(self._log_prob_out, self.log_prob_from_noise(eps, scale, pre_tanh))
        return tensordict


def make_sapo_actor(
    env,
    hidden: Sequence[int] = (128, 64, 32),
    activation: type[nn.Module] = nn.SiLU,
    layer_norm: bool = True,
    norm_after_activation: bool = False,
    init: str = "orthogonal",
    orthogonal_gain: float = 1.0,
    min_log_std: float = -5.0,
    max_log_std: float = 2.0,
    normalizer: ObservationNormalizer | None = None,
) -> SquashedNormalActor:
    """SAPO's policy: an MLP writing ``loc`` and a state-dependent ``scale`` (log-std clamped to
    ``[min_log_std, max_log_std]``), squashed into the action bounds
    ([`SquashedNormalActor`][torchrl_diffenvs.modules.SquashedNormalActor], writing ``"action"`` and ``"action_log_prob"``).

    The reference: ``[128, 64, 32]`` Linear-LayerNorm-SiLU, orthogonal weights of gain 1, log-std
    in ``[-5, 2]``.

    Args:
        env: a single-agent env with a bounded action spec (sizes from [`env_dims`][torchrl_diffenvs.modules.env_dims]).
        hidden: the MLP's hidden sizes ([`make_mlp`][torchrl_diffenvs.modules.make_mlp]).
        activation: the MLP's activation.
        layer_norm: a LayerNorm in each hidden layer.
        norm_after_activation: the LayerNorm after the activation instead of before.
        init: ``"orthogonal"`` uses ``orthogonal_gain``; ``"default"`` PyTorch's.
        orthogonal_gain: the gain of the orthogonal weights (zero biases).
        min_log_std: the lower clamp of the log-std.
        max_log_std: the upper clamp of the log-std.
        normalizer: an [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] applied to the
            observation first.
    """
    keys = policy_keys(env)
    if keys.num_agents is not None:
        raise ValueError(f"make_sapo_actor: {type(env).__name__} is multi-agent; SAPO is single-agent")
    observation_dim, action_dim, dtype = env_dims(env, keys.observation)
    low, high = action_bounds(env, "make_sapo_actor")
    net = make_mlp(observation_dim, 2 * action_dim, hidden, activation, layer_norm, dtype, norm_after_activation)
    if init == "orthogonal":
        orthogonal_init_(net, orthogonal_gain)
    elif init != "default":
        raise ValueError(f"make_sapo_actor: init must be 'default' or 'orthogonal', got {init!r}")
    prefix = [normalizer] if normalizer is not None else []
    head = nn.Sequential(*prefix, net, _LocScale(action_dim, min_log_std, max_log_std))
    module = LeanModule(head, in_keys=[keys.observation], out_keys=[keys.loc, keys.scale])
    return SquashedNormalActor(module, low, high, log_prob_key=keys.log_prob,
                               spec=env.full_action_spec_unbatched[keys.action], out_keys=[keys.action])
