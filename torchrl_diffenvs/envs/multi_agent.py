"""The base class of multi-agent tasks: TorchRL's multi-agent layout over a [`DiffEnv`][torchrl_diffenvs.DiffEnv].

What a policy reads and writes moves into an ``"agents"`` group of shape ``[N, A]``
(``A = num_agents``), as in TorchRL's VMAS and PettingZoo wrappers:

```text
("agents", "observation")    [N, A, obs_dim]   each agent's own view
("agents", "action")         [N, A, action_dim]
("next", "agents", "reward") [N, A, 1]         each agent's own reward
"done" | "terminated" | "truncated"   [N, 1]   shared: the agents live in one episode
("state", ...), ("params", ...), "episode_step"  [N, ...]  as for every DiffEnv
```

So TorchRL's multi-agent parts apply unchanged (``MultiAgentMLP``, ``MAPPOLoss`` /
``IPPOLoss`` with ``MultiAgentGAE``, which broadcasts the shared done flags over the agents),
and the physics stays one batched function: rewards and observations carry gradients w.r.t.
every agent's actions, the other agents' included.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite, Unbounded

from .base import DiffEnv

__all__ = ["AGENTS", "MultiAgentDiffEnv", "PolicyKeys", "is_multi_agent", "policy_keys", "reward_per_env"]

AGENTS = "agents"  # the group's name, TorchRL's convention


def is_multi_agent(env) -> bool:
    """Whether ``env`` uses the ``("agents", ...)`` layout for its actions.

    Args:
        env: any TorchRL env.
    """
    return env.action_key == (AGENTS, "action")


@dataclass(frozen=True)
class PolicyKeys:
    """Where the entries a policy, a critic and a loss exchange live in an env's TensorDicts:
    at the root for a single-agent env (``"observation"``, ``"action"``, ...), in the
    ``"agents"`` group for a multi-agent one (``("agents", "observation")``, ...).

    ``num_agents`` is ``None`` for a single-agent env.
    """

    observation: NestedKey = "observation"
    action: NestedKey = "action"
    reward: NestedKey = "reward"
    loc: NestedKey = "loc"
    scale: NestedKey = "scale"
    log_prob: NestedKey = "action_log_prob"
    value: NestedKey = "state_value"
    num_agents: int | None = None


def policy_keys(env) -> PolicyKeys:
    """The `PolicyKeys` of ``env`` (any TorchRL env)."""
    if not is_multi_agent(env):
        return PolicyKeys()
    names = ("observation", "action", "reward", "loc", "scale", "log_prob", "value")
    grouped = {name: (AGENTS, getattr(PolicyKeys, name)) for name in names}
    return PolicyKeys(**grouped, num_agents=int(env.full_action_spec[env.action_key].shape[-2]))


def reward_per_env(tensordict: TensorDictBase, key: NestedKey = "reward") -> torch.Tensor:
    """``("next", key)`` of a ``[*B]`` TensorDict as ``[*B]``: a multi-agent env's rewards
    ``[*B, A, 1]`` are averaged over its agents (the team's mean reward)."""
    reward = tensordict.get(("next", *((key,) if isinstance(key, str) else key)))
    return reward.reshape(*tensordict.batch_size, -1).mean(-1)


class MultiAgentDiffEnv(DiffEnv):
    """A [`DiffEnv`][torchrl_diffenvs.DiffEnv] with ``num_agents`` agents in one batched simulation.

    A subclass defines the same physics functions as for a [`DiffEnv`][torchrl_diffenvs.DiffEnv], with an agent
    dimension:

    * ``transition(state, action, params) -> (next_state, reward, terminated)``: ``action`` is
      ``[N, A, action_dim]``, ``reward`` ``[N, A]`` (one per agent), ``terminated`` ``[N]`` or
      ``None`` (the episode is shared);
    * ``observation(state, params) -> Tensor [N, A, obs_dim]``.

    ``action_dim`` and ``observation_dim`` are per agent.

    Args:
        num_envs: simulations in the batch.
        num_agents: agents per simulation (``>= 1``).
        **kwargs: as [`DiffEnv`][torchrl_diffenvs.DiffEnv] (device, dtype, seed, max_episode_steps, params).
    """

    min_agents: int = 1

    def __init__(self, num_envs: int = 1, *, num_agents: int = 2, **kwargs):
        if isinstance(num_agents, bool) or not isinstance(num_agents, int) or num_agents < self.min_agents:
            raise ValueError(f"{self.name}: num_agents must be an integer >= {self.min_agents}, got {num_agents!r}")
        self.num_agents = num_agents
        super().__init__(num_envs, **kwargs)

    @property
    def action_shape(self) -> tuple[int, ...]:
        return (self.num_agents, self.action_dim)

    def _policy_specs(self):
        n, a, dtype, device = self.num_envs, self.num_agents, self.float_dtype, self.device

        def group(**specs):
            return Composite(specs, shape=(n, a), device=device)

        observation = group(observation=Unbounded(shape=(n, a, self.observation_dim), dtype=dtype, device=device))
        action = Bounded(low=self.action_low, high=self.action_high, shape=(n, a, self.action_dim), dtype=dtype,
                         device=device)
        reward = Unbounded(shape=(n, a, 1), dtype=dtype, device=device)
        return ({AGENTS: observation}, Composite({AGENTS: group(action=action)}, shape=(n,), device=device),
                Composite({AGENTS: group(reward=reward)}, shape=(n,), device=device))

    def _policy_entries(self, observation: torch.Tensor, reward: torch.Tensor | None) -> dict:
        entries = {"observation": observation}
        if reward is not None:
            entries["reward"] = reward.unsqueeze(-1)
        return {AGENTS: TensorDict(entries, batch_size=[self.num_envs, self.num_agents])}

    def __repr__(self) -> str:
        return super().__repr__()[:-1] + f", num_agents={self.num_agents})"
