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
from ..normalization import ObservationNormalizer
from .actors import DISTRIBUTIONS, SquashedNormalActor, TanhNormalActor, make_actor, make_sapo_actor
from .critics import CRITIC_INPUTS, make_critic, make_qvalue, privileged_inputs, update_privileged_statistics
from .from_config import actor_from_config, critic_from_config, network_kwargs, qvalue_from_config
from .networks import (
    ACTIVATIONS,
    NETWORK_INITS,
    LeanModule,
    env_dims,
    make_agent_mlp,
    make_mlp,
    observation_key_of,
    orthogonal_init_,
)

__all__ = [
    "ACTIVATIONS",
    "CRITIC_INPUTS",
    "DISTRIBUTIONS",
    "LeanModule",
    "NETWORK_INITS",
    "ObservationNormalizer",
    "SquashedNormalActor",
    "TanhNormalActor",
    "actor_from_config",
    "critic_from_config",
    "env_dims",
    "make_actor",
    "make_agent_mlp",
    "make_critic",
    "make_mlp",
    "make_qvalue",
    "make_sapo_actor",
    "network_kwargs",
    "observation_key_of",
    "orthogonal_init_",
    "privileged_inputs",
    "qvalue_from_config",
    "update_privileged_statistics",
]
