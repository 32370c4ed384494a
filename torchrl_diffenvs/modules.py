"""Networks shared by the gradient-based learners, the demos and the training script.

* [`make_actor`][torchrl_diffenvs.modules.make_actor]: a stochastic policy (``TanhNormal`` with a state-independent log-std) as a
  TorchRL ``ProbabilisticActor``, usable by [`BPTTLoss`][torchrl_diffenvs.objectives.BPTTLoss],
  [`SHACLoss`][torchrl_diffenvs.objectives.SHACLoss] and TorchRL's PPO / SAC losses; or a
  deterministic tanh-MLP policy (Ivy Gym's ``optimize_policy`` demo).
* [`make_sapo_actor`][torchrl_diffenvs.modules.make_sapo_actor]: SAPO's policy, a
  [`SquashedNormalActor`][torchrl_diffenvs.modules.SquashedNormalActor] with a state-dependent
  standard deviation that writes the exact log-probability of its samples.
* [`make_critic`][torchrl_diffenvs.modules.make_critic]: a state-value network writing ``"state_value"``.
* [`make_qvalue`][torchrl_diffenvs.modules.make_qvalue]: ``Q(observation, action)`` writing ``"state_action_value"`` (SAC).
* [`actor_from_config`][torchrl_diffenvs.modules.actor_from_config], [`critic_from_config`][torchrl_diffenvs.modules.critic_from_config], [`qvalue_from_config`][torchrl_diffenvs.modules.qvalue_from_config]: the same
  builders driven by a ``loss`` configuration section (the learners' network settings).
* [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] (re-exported here): running mean /
  std of observations, updated explicitly outside the autograd graph and applied with frozen
  statistics inside it.

All builders take sizes and dtypes from the env's (transformed) specs ([`env_dims`][torchrl_diffenvs.modules.env_dims]): a float64
env gives float64 networks (gradient checks), a ``TransformedEnv`` networks sized for what its
transforms output.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, InteractionType, TensorDictModuleBase
from torch import nn
from torch.distributions import AffineTransform
from torchrl.modules import MLP, MultiAgentMLP, ProbabilisticActor, TanhNormal, ValueOperator

from ._compat import SafeTanhTransform, current_interaction_type, sampler_has_own_generator, standard_normal
from .envs.multi_agent import policy_keys
from .normalization import ObservationNormalizer

__all__ = [
    "LeanModule",
    "ObservationNormalizer",
    "SquashedNormalActor",
    "TanhNormalActor",
    "actor_from_config",
    "env_dims",
    "observation_key_of",
    "CRITIC_INPUTS",
    "privileged_inputs",
    "update_privileged_statistics",
    "critic_from_config",
    "make_actor",
    "make_agent_mlp",
    "make_critic",
    "make_mlp",
    "make_qvalue",
    "make_sapo_actor",
    "orthogonal_init_",
    "qvalue_from_config",
]

DISTRIBUTIONS = ("tanh_normal", "deterministic")
ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "elu": nn.ELU, "relu": nn.ReLU, "silu": nn.SiLU}
NETWORK_INITS = ("default", "orthogonal")


class LeanModule(TensorDictModuleBase):
    """Reads ``in_keys``, calls ``module`` on those tensors and writes its output(s) to ``out_keys``.

    What ``tensordict.nn.TensorDictModule`` does for plain tensor outputs, without its
    per-output conversion step, which in tensordict 0.14.3 probes the filesystem for an
    optional package (about 80 us per output tensor, more than a pendulum step costs).
    """

    def __init__(self, module: nn.Module, in_keys: Sequence, out_keys: Sequence):
        super().__init__()
        self.module = module
        self.in_keys = list(in_keys)
        self.out_keys = list(out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        outputs = self.module(*(tensordict.get(key) for key in self.in_keys))
        if isinstance(outputs, torch.Tensor):
            outputs = (outputs,)
        if len(outputs) != len(self.out_keys):
            raise RuntimeError(f"LeanModule: {len(outputs)} outputs for out_keys {self.out_keys}")
        for key, value in zip(self.out_keys, outputs):
            tensordict.set(key, value)
        return tensordict


def orthogonal_init_(module: nn.Module, gain: float) -> None:
    """Every ``nn.Linear`` in ``module`` (nested ones included) gets orthogonal weights of
    ``gain`` and zero biases, in place."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain=gain)
            nn.init.zeros_(layer.bias)


def make_mlp(
    in_dim: int,
    out_dim: int,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    dtype: torch.dtype = torch.float32,
    norm_after_activation: bool = False,
    init: str = "default",
) -> nn.Sequential:
    """``[Linear -> (LayerNorm) -> activation] * len(hidden) -> Linear``: TorchRL's ``MLP``.

    ``norm_after_activation=True`` gives ``Linear -> activation -> LayerNorm`` per hidden layer (the
    order of DiffRL's SHAC networks), which TorchRL's ``MLP`` cannot build: then a plain
    ``nn.Sequential`` of the same layers. ``init="orthogonal"`` initialises every Linear with
    orthogonal weights of gain sqrt(2) and zero biases (DiffRL's critic); ``"default"`` keeps
    PyTorch's. Parameters are created in ``dtype`` (float64 networks for gradient checks).
    """
    if init not in NETWORK_INITS:
        raise ValueError(f"make_mlp: init must be one of {NETWORK_INITS}, got {init!r}")
    hidden = [int(width) for width in hidden]
    if not norm_after_activation:
        net = MLP(in_features=in_dim, out_features=out_dim, **_torchrl_mlp_layers(hidden, activation, layer_norm, dtype))
    else:
        layers: list[nn.Module] = []
        for width in hidden:
            layers.append(nn.Linear(in_dim, width, dtype=dtype))
            layers.extend([activation(), nn.LayerNorm(width, dtype=dtype)] if layer_norm else [activation()])
            in_dim = width
        layers.append(nn.Linear(in_dim, out_dim, dtype=dtype))
        net = nn.Sequential(*layers)
    if init == "orthogonal":
        orthogonal_init_(net, math.sqrt(2))
    return net


def _torchrl_mlp_layers(hidden, activation, layer_norm: bool, dtype) -> dict:
    """The hidden-layer arguments of TorchRL's ``MLP`` (and ``MultiAgentMLP``): Linear-(LayerNorm)-activation."""
    norm = {}
    if layer_norm:
        norm = {"norm_class": nn.LayerNorm, "norm_kwargs": [{"normalized_shape": int(w), "dtype": dtype} for w in hidden]}
    return {"num_cells": [int(w) for w in hidden], "activation_class": activation, "layer_kwargs": {"dtype": dtype},
            **norm}


def make_agent_mlp(
    in_dim: int,
    out_dim: int,
    num_agents: int,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    dtype: torch.dtype = torch.float32,
    norm_after_activation: bool = False,
    init: str = "default",
    centralised: bool = False,
) -> MultiAgentMLP:
    """The networks of a multi-agent env: TorchRL's ``MultiAgentMLP`` on ``[..., num_agents, in_dim]``.

    ``centralised=False``: each agent's output from its own input, one network shared by the
    agents (a decentralised policy or critic: [`make_mlp`][torchrl_diffenvs.modules.make_mlp] applied to every agent).
    ``True``: each agent's output from every agent's input (MAPPO's centralised critic), with one
    network per agent: a shared one would give every agent the same value, which per-agent
    rewards (``multi_swimmer``'s) do not have."""
    if norm_after_activation or init != "default":
        raise ValueError("the multi-agent networks (TorchRL's MultiAgentMLP) are Linear-LayerNorm-activation with "
                         "PyTorch's initialisation: set norm_after_activation=false and init=default")
    return MultiAgentMLP(in_dim, out_dim, num_agents, centralized=centralised, share_params=not centralised,
                         **_torchrl_mlp_layers(hidden, activation, layer_norm, dtype))


class _ScaledTanh(nn.Module):
    """``low + (tanh(x) + 1) / 2 * (high - low)``: squashes into the action bounds."""

    def __init__(self, low: float, high: float):
        super().__init__()
        self.low, self.high = float(low), float(high)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.low + (torch.tanh(x) + 1) * (0.5 * (self.high - self.low))


def env_dims(env, in_key="observation") -> tuple[int, int, torch.dtype]:
    """``(observation size, action size, float dtype)`` of any TorchRL env the networks are built for.

    Always read from the env's specs: the last dimension and dtype of ``in_key`` in its
    observation spec, and the last dimension of its action spec. For a ``TransformedEnv`` these
    are the *transformed* specs (``CatFrames``, ``CatTensors``, ``DoubleToFloat``,
    ``ObservationNorm``, ...), which is what the networks receive; attributes of a DiffEnv such as
    ``observation_dim`` describe the base env and are forwarded unchanged through a transform.

    Raises a ``ValueError`` when ``in_key`` is missing or not floating point, or when the action
    dtype differs from the observation dtype (the networks compute in one dtype).
    """
    observation = env.observation_spec.get(in_key, None)
    if observation is None:
        raise ValueError(
            f"{type(env).__name__}: the networks read {in_key!r}, which its observation spec lacks (it has "
            f"{sorted(map(str, env.observation_spec.keys()))}); add one with a transform, e.g. "
            f"TransformedEnv(env, CatTensors(in_keys=[...], out_key={in_key!r}, del_keys=False))"
        )
    if not observation.dtype.is_floating_point:
        raise ValueError(f"{type(env).__name__}: {in_key!r} must be floating point, got {observation.dtype}")
    action = env.full_action_spec[env.action_key]
    if action.dtype.is_floating_point and action.dtype != observation.dtype:
        raise ValueError(
            f"{type(env).__name__}: the observation {in_key!r} is {observation.dtype} but the action is "
            f"{action.dtype}; the networks compute in one dtype: cast both, e.g. "
            f"DoubleToFloat(in_keys=[{in_key!r}, 'reward'], in_keys_inv=['action'])"
        )
    return int(observation.shape[-1]), int(action.shape[-1]), observation.dtype


def observation_key_of(policy, default="observation"):
    """The observation entry ``policy`` reads (its only in-key), else ``default``: what a learner
    updates the policy's [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] from (e.g. a key a ``CatTensors`` added)."""
    in_keys = list(getattr(policy, "in_keys", ()))
    return in_keys[0] if len(in_keys) == 1 else default


def _action_bounds(env, who: str = "make_actor") -> tuple[float, float]:
    """``(low, high)`` of ``env``'s action spec, the same for every action dimension (``who``:
    the caller's name, for the error)."""
    spec = env.full_action_spec_unbatched[env.action_key]
    low, high = spec.space.low, spec.space.high
    if not (torch.all(low == low.flatten()[0]) and torch.all(high == high.flatten()[0])):
        raise ValueError(f"{who}: expected the same bounds for every action dimension, got {low} and {high}")
    return float(low.flatten()[0]), float(high.flatten()[0])


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
    low, high = _action_bounds(env)
    if keys.num_agents is None:
        net = make_mlp(observation_dim, action_dim, hidden, activation, layer_norm, dtype, norm_after_activation, init)
    else:
        net = make_agent_mlp(observation_dim, action_dim, keys.num_agents, hidden, activation, layer_norm, dtype,
                             norm_after_activation, init)
    prefix = [normalizer] if normalizer is not None else []
    if distribution == "deterministic":
        return LeanModule(nn.Sequential(*prefix, net, _ScaledTanh(low, high)), in_keys=[in_key], out_keys=[keys.action])
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
    writes ``action = squash(u)`` and its log-probability from ``u``::

        sum_i [ -eps_i^2 / 2 - log scale_i - log(2 pi) / 2 - log(1 - tanh(u_i)^2) - log((high - low) / 2) ]

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
    in ``[-5, 2]``. ``init="orthogonal"`` uses ``orthogonal_gain``; ``"default"`` PyTorch's.
    """
    keys = policy_keys(env)
    if keys.num_agents is not None:
        raise ValueError(f"make_sapo_actor: {type(env).__name__} is multi-agent; SAPO is single-agent")
    observation_dim, action_dim, dtype = env_dims(env, keys.observation)
    low, high = _action_bounds(env, "make_sapo_actor")
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


CRITIC_INPUTS = ("observation", "state")


def privileged_inputs(env) -> list[tuple[tuple[str, str], int]]:
    """``[(key, size), ...]``: every ``("state", ...)`` and ``("params", ...)`` entry of ``env``'s
    observation spec with its size per env (what ``critic_input="state"`` adds to the critic's input)."""
    batch_dims = len(env.batch_size)
    found = [(key, math.prod(env.observation_spec[key].shape[batch_dims:]))
             for key in env.observation_spec.keys(True, True)
             if isinstance(key, tuple) and key[0] in ("state", "params")]
    if not any(key[0] == "state" for key, _ in found):
        raise ValueError(f"critic_input='state': {type(env).__name__} has no ('state', ...) entries in its observation "
                         "spec to give the critic; use critic_input='observation'")
    return found


class _ConcatInputs(nn.Module):
    """Feeds ``cat(inputs)`` to ``net`` (a ``ValueOperator`` or ``LeanModule`` passes them one by
    one): each input is flattened per env (its trailing ``event_dims``, 0 for a scalar), the first
    one (the observation) goes through ``normalizer`` when given, and the privileged block (the
    inputs read from ``privileged_keys``, right after the observation) through
    ``privileged_normalizer`` when given (see [`update_privileged_statistics`][torchrl_diffenvs.modules.update_privileged_statistics])."""

    def __init__(self, net: nn.Module, event_dims: Sequence[int] | None = None,
                 normalizer: ObservationNormalizer | None = None, privileged_keys: Sequence = (),
                 privileged_normalizer: ObservationNormalizer | None = None):
        super().__init__()
        self.net = net
        self.event_dims = None if event_dims is None else tuple(event_dims)
        self.normalizer = normalizer
        self.privileged_keys = list(privileged_keys)
        self.privileged_normalizer = privileged_normalizer

    def _flat(self, inputs, event_dims, dtype) -> list[torch.Tensor]:
        return [(x.unsqueeze(-1) if k == 0 else x.flatten(-k)).to(dtype) for x, k in zip(inputs, event_dims)]

    def privileged_block(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The privileged inputs of ``tensordict`` flattened and concatenated ``[..., P]``, raw."""
        count = len(self.privileged_keys)
        dtype = self.privileged_normalizer.mean.dtype
        return torch.cat(self._flat([tensordict.get(key) for key in self.privileged_keys],
                                    self.event_dims[1:1 + count], dtype), dim=-1)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        if self.normalizer is not None:
            inputs = (self.normalizer(inputs[0]), *inputs[1:])
        if self.event_dims is not None:
            inputs = self._flat(inputs, self.event_dims, inputs[0].dtype)
        if self.privileged_normalizer is not None:
            count = len(self.privileged_keys)
            block = self.privileged_normalizer(torch.cat(inputs[1:1 + count], dim=-1))
            inputs = [inputs[0], block, *inputs[1 + count:]]
        return self.net(torch.cat(inputs, dim=-1))


@torch.no_grad()
def update_privileged_statistics(critic: nn.Module, tensordict: TensorDictBase, gather=lambda x: x) -> None:
    """Merges the privileged inputs of ``tensordict`` (a batch the critic was trained on) into the
    running statistics of ``critic``'s privileged normaliser (``critic_input="state"``); a no-op
    for any other critic. ``gather`` collects the ranks' blocks (``world.gather``)."""
    for module in critic.modules():
        if isinstance(module, _ConcatInputs) and module.privileged_normalizer is not None:
            module.privileged_normalizer.update(gather(module.privileged_block(tensordict)))


def _critic_inputs(env, in_key: str, critic_input: str) -> tuple[list, list[int], int]:
    """The critic's input keys, their event dims and total size for ``critic_input``."""
    if critic_input not in CRITIC_INPUTS:
        raise ValueError(f"critic_input must be one of {CRITIC_INPUTS}, got {critic_input!r}")
    observation_dim = env_dims(env, in_key)[0]
    if critic_input == "observation":
        return [in_key], [1], observation_dim
    batch_dims = len(env.batch_size)
    privileged = privileged_inputs(env)
    keys = [in_key] + [key for key, _ in privileged]
    event_dims = [1] + [len(env.observation_spec[key].shape) - batch_dims for key, _ in privileged]
    return keys, event_dims, observation_dim + sum(size for _, size in privileged)


def make_critic(
    env,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    norm_after_activation: bool = False,
    init: str = "default",
    normalizer: ObservationNormalizer | None = None,
    in_key: str = "observation",
    critic_input: str = "observation",
    centralised: bool = False,
    privileged_norm: bool = True,
) -> LeanModule:
    """A state-value network writing ``"state_value"`` (``[..., 1]``).

    ``critic_input="observation"`` (default): ``V(observation)``. ``"state"``: an asymmetric
    (privileged) critic ``V(observation, state, params)`` that also reads every ``("state", ...)``
    and ``("params", ...)`` entry of the env's TensorDicts (the physical state and parameters,
    flattened per env), while the actor keeps seeing the observation only. ``normalizer``
    applies to the observation part; the state and parameters go through their own running
    normaliser (as rl_games normalises its central value's inputs), which the learner updates
    with [`update_privileged_statistics`][torchrl_diffenvs.modules.update_privileged_statistics] (``privileged_norm=False``: they enter raw).

    On a multi-agent env it writes ``("agents", "state_value")`` ``[..., A, 1]``, one value per
    agent, from a parameter-shared ``MultiAgentMLP``: from the agent's own observation
    (``centralised=False``, IPPO) or from every agent's (``centralised=True``, MAPPO).
    """
    agent_keys = policy_keys(env)
    if agent_keys.num_agents is not None:
        if critic_input != "observation":
            raise ValueError(f"critic_input={critic_input!r}: a multi-agent critic reads the agents' observations; "
                             "use critic_input='observation' (with centralised=True it sees every agent's)")
        observation_dim, _, dtype = env_dims(env, agent_keys.observation)
        net = make_agent_mlp(observation_dim, 1, agent_keys.num_agents, hidden, activation, layer_norm, dtype,
                             norm_after_activation, init, centralised=centralised)
        return LeanModule(nn.Sequential(normalizer, net) if normalizer is not None else net,
                          in_keys=[agent_keys.observation], out_keys=[agent_keys.value])
    if centralised:
        raise ValueError(f"centralised critic: {type(env).__name__} has a single agent (no ('agents', ...) group)")
    keys, event_dims, input_dim = _critic_inputs(env, in_key, critic_input)
    dtype = env_dims(env, in_key)[2]
    net = make_mlp(input_dim, 1, hidden, activation, layer_norm, dtype, norm_after_activation, init)
    if critic_input == "observation":
        return LeanModule(nn.Sequential(normalizer, net) if normalizer is not None else net, in_keys=keys,
                          out_keys=["state_value"])
    privileged_normalizer = None
    if privileged_norm:
        privileged_normalizer = ObservationNormalizer(input_dim - env_dims(env, in_key)[0], dtype=dtype).to(env.device)
    inputs = _ConcatInputs(net, event_dims, normalizer, keys[1:], privileged_normalizer)
    return LeanModule(inputs, in_keys=keys, out_keys=["state_value"])


def make_qvalue(env, hidden: Sequence[int] = (256, 256), activation: type[nn.Module] = nn.ReLU,
                layer_norm: bool = False, norm_after_activation: bool = False, init: str = "default",
                critic_input: str = "observation") -> ValueOperator:
    """``Q(observation, action)`` writing ``"state_action_value"`` (what TorchRL's ``SACLoss``
    expects); with ``critic_input="state"``, ``Q(observation, state, params, action)`` (see
    [`make_critic`][torchrl_diffenvs.modules.make_critic]), the privileged inputs raw: SAC keeps no running input statistics (its
    replay buffer would mix them)."""
    if policy_keys(env).num_agents is not None:
        raise ValueError(f"make_qvalue: {type(env).__name__} is a multi-agent env; SAC's Q-networks are single-agent "
                         "(train it with bptt, shac or ppo: loss=mappo / loss=ippo)")
    keys, event_dims, input_dim = _critic_inputs(env, "observation", critic_input)
    _, action_dim, dtype = env_dims(env)
    net = make_mlp(input_dim + action_dim, 1, hidden, activation, layer_norm, dtype, norm_after_activation, init)
    inputs = _ConcatInputs(net) if critic_input == "observation" else _ConcatInputs(net, [*event_dims, 1])
    return ValueOperator(inputs, in_keys=[*keys, "action"], out_keys=["state_action_value"])


# ---------------------------------------------------------------------- from a loss config section
def network_kwargs(section: Mapping) -> dict:
    """``hidden`` / ``activation`` / ``layer_norm`` (/ ``norm_after_activation``, ``init``,
    ``init_log_std``) of a network section
    (``loss.actor``, ``loss.critic``, ``loss.qvalue``) as keyword arguments of the builders."""
    activation = section.get("activation", "elu")
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation={activation!r}: valid: {', '.join(ACTIVATIONS)}")
    kwargs = {
        "hidden": tuple(int(h) for h in section["hidden"]),
        "activation": ACTIVATIONS[activation],
        "layer_norm": bool(section.get("layer_norm", True)),
    }
    if "init_log_std" in section:
        kwargs["init_log_std"] = float(section["init_log_std"])
    for key, cast in (("norm_after_activation", bool), ("init", str)):
        if key in section:
            kwargs[key] = cast(section[key])
    return kwargs


def actor_from_config(loss_cfg: Mapping, env, return_log_prob: bool = False):
    """The actor a learner trains, from ``loss_cfg.actor`` and ``loss_cfg.obs_norm``.

    Returns ``(actor, normalizer)``; the normaliser (or ``None``) is the actor's first layer, so
    the actor's ``state_dict`` carries its statistics; pass it on to the critic.
    """
    normalizer = None
    if loss_cfg.get("obs_norm", False):
        observation_dim, _, dtype = env_dims(env, policy_keys(env).observation)
        normalizer = ObservationNormalizer(observation_dim, dtype=dtype).to(env.device)
    actor_cfg = loss_cfg["actor"]
    actor = make_actor(env, **network_kwargs(actor_cfg), distribution=actor_cfg.get("distribution", "tanh_normal"),
                       normalizer=normalizer, return_log_prob=return_log_prob)
    return actor.to(env.device), normalizer


def critic_from_config(section: Mapping, env, normalizer: ObservationNormalizer | None = None,
                       critic_input: str = "observation", centralised: bool = False) -> LeanModule:
    """[`make_critic`][torchrl_diffenvs.modules.make_critic] from a ``loss.critic`` section, sharing the actor's normaliser."""
    return make_critic(env, **network_kwargs(section), normalizer=normalizer, critic_input=critic_input,
                       centralised=centralised).to(env.device)


def qvalue_from_config(section: Mapping, env, critic_input: str = "observation") -> ValueOperator:
    """[`make_qvalue`][torchrl_diffenvs.modules.make_qvalue] from a ``loss.qvalue`` section."""
    return make_qvalue(env, **network_kwargs(section), critic_input=critic_input).to(env.device)
