"""The critics: state values (single-agent, per agent, or asymmetric with the physical state and
parameters as privileged inputs) and SAC's Q-networks."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import ValueOperator

from ..envs.multi_agent import policy_keys
from ..normalization import ObservationNormalizer
from .networks import LeanModule, env_dims, make_agent_mlp, make_mlp

__all__ = ["CRITIC_INPUTS", "make_critic", "make_qvalue", "privileged_inputs", "update_privileged_statistics"]

CRITIC_INPUTS = ("observation", "state")
"""What a critic may read: the policy's observation, or the env's privileged state."""


def privileged_inputs(env) -> list[tuple[tuple[str, str], int]]:
    """``[(key, size), ...]``: every ``("state", ...)`` and ``("params", ...)`` entry of ``env``'s
    observation spec with its size per env (what ``critic_input="state"`` adds to the critic's input).

    Args:
        env: the env; its observation spec must have ``("state", ...)`` entries.
    """
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
    """Merges the privileged inputs of ``tensordict`` into the running statistics of ``critic``'s
    privileged normaliser (``critic_input="state"``); a no-op for any other critic.

    Args:
        critic: the critic ([`make_critic`][torchrl_diffenvs.modules.make_critic]'s).
        tensordict: a batch the critic was trained on.
        gather: collects the ranks' blocks (``world.gather``); by default the identity (one process).
    """
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

    On a multi-agent env it writes ``("agents", "state_value")`` ``[..., A, 1]``, one value per
    agent, from a parameter-shared ``MultiAgentMLP``: from the agent's own observation
    (``centralised=False``, IPPO) or from every agent's (``centralised=True``, MAPPO).

    Args:
        env: the env the critic is for (sizes from [`env_dims`][torchrl_diffenvs.modules.env_dims]).
        hidden: the MLP's hidden sizes ([`make_mlp`][torchrl_diffenvs.modules.make_mlp]).
        activation: the MLP's activation.
        layer_norm: a LayerNorm in each hidden layer.
        norm_after_activation: the LayerNorm after the activation instead of before.
        init: the weights' initialisation, as in [`make_mlp`][torchrl_diffenvs.modules.make_mlp].
        normalizer: an [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] applied to the
            observation part.
        in_key: the observation entry to read (single-agent envs).
        critic_input: ``"observation"`` (default): ``V(observation)``. ``"state"``: an asymmetric
            (privileged) critic ``V(observation, state, params)`` that also reads every ``("state", ...)``
            and ``("params", ...)`` entry of the env's TensorDicts (the physical state and parameters,
            flattened per env), while the actor keeps seeing the observation only.
        centralised: on a multi-agent env, each agent's value from every agent's observation (MAPPO)
            rather than from its own (IPPO).
        privileged_norm: with ``critic_input="state"``, the state and parameters go through their own
            running normaliser (as rl_games normalises its central value's inputs), which the learner
            updates with [`update_privileged_statistics`][torchrl_diffenvs.modules.update_privileged_statistics];
            ``False``: they enter raw.
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
    expects).

    Args:
        env: a single-agent env (sizes from [`env_dims`][torchrl_diffenvs.modules.env_dims]).
        hidden: the MLP's hidden sizes ([`make_mlp`][torchrl_diffenvs.modules.make_mlp]).
        activation: the MLP's activation.
        layer_norm: a LayerNorm in each hidden layer.
        norm_after_activation: the LayerNorm after the activation instead of before.
        init: the weights' initialisation, as in [`make_mlp`][torchrl_diffenvs.modules.make_mlp].
        critic_input: ``"observation"`` (default), or ``"state"``: ``Q(observation, state, params, action)``
            (see [`make_critic`][torchrl_diffenvs.modules.make_critic]), the privileged inputs raw: SAC keeps
            no running input statistics (its replay buffer would mix them).
    """
    if policy_keys(env).num_agents is not None:
        raise ValueError(f"make_qvalue: {type(env).__name__} is a multi-agent env; SAC's Q-networks are single-agent "
                         "(train it with bptt, shac or ppo: loss=mappo / loss=ippo)")
    keys, event_dims, input_dim = _critic_inputs(env, "observation", critic_input)
    _, action_dim, dtype = env_dims(env)
    net = make_mlp(input_dim + action_dim, 1, hidden, activation, layer_norm, dtype, norm_after_activation, init)
    inputs = _ConcatInputs(net) if critic_input == "observation" else _ConcatInputs(net, [*event_dims, 1])
    return ValueOperator(inputs, in_keys=[*keys, "action"], out_keys=["state_action_value"])
