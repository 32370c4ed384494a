"""Short-horizon actor-critic (SHAC, Xu et al. 2022) as a TorchRL loss module."""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule, SoftUpdate
from torchrl.objectives.value import TDLambdaEstimator

from .windows import like_agents, steps_since_start, window_entry
from .nonfinite import next_key, nonfinite_envs, now_and_next

__all__ = ["SHACLoss"]


class SHACLoss(LossModule):
    r"""SHAC: BPTT over a short window, closed by a learned terminal value.

    **Actor.** For a window ``[N, H]`` collected with the graph on, each env's window splits into
    sub-trajectories that end at an episode end or at the window end. A sub-trajectory ending at
    step $K$ (with $k$ counting from its start) contributes

    $$
    -\Big(\sum_{k<K} \gamma^k r_k + \gamma^K \bar V(s_K)\Big),
    $$

    summed over all sub-trajectories and divided by $N H$ (``loss_actor``). $\bar V$
    is the *target* critic, evaluated inside the graph on ``("next", "observation")``: gradients
    flow into the observation, not into the critic's weights. $\bar V(s_K)$ is 0 on
    termination; on truncation (time limit) it is evaluated on the pre-reset observation; every
    env is bootstrapped at the window end.

    **Critic.** Targets are truncated TD($\lambda$) returns computed from detached rewards
    and target-critic values of the next observations, with the window end treated as a
    trajectory end (TorchRL's `TDLambdaEstimator`
    ``.value_estimate(td, next_value=...)``):

    $$
    G_t = r_t + \gamma\,[(1-\lambda)\,\bar V(s_{t+1}) + \lambda\, G_{t+1}],\qquad
    G_t = r_t + \gamma\,\bar V(s_{t+1}) \text{ at a done step or } t = H-1,
    $$

    with $\bar V = 0$ after a termination. ``loss_critic`` is the mean squared error
    $(V(s_t) - G_t)^2$.

    **Target critic.** Its weights are separate, updated with TorchRL's
    `SoftUpdate` (see [`make_target_updater`][torchrl_diffenvs.objectives.SHACLoss.make_target_updater]). Convention: after
    each update ``target = eps * target + (1 - eps) * critic`` with ``eps = 1 - tau``; SHAC's
    reference keeps 0.2 of the old target, i.e. ``tau = 0.8`` (``eps = 0.2``). Buffers of the
    critic (e.g. the statistics of an [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer])
    are shared by the critic and the target critic: only the weights lag.

    **Multi-agent.** With ``set_keys(reward=("agents", "reward"), value=("agents", "state_value"))``
    each agent has its own return and value (``[N, H, A, 1]``; the done flags are shared); the
    actor loss averages the agents' bootstrapped returns, the critic fits each agent's targets.

    **Non-finite envs** (a NaN/inf reward or critic input, a ``("next", "nonfinite")`` flag, or
    marked ``"isolated"`` by the collector) are left out of ``loss_actor`` and the diagnostics (the
    sums run over the other envs, $N$ counts only them; ``nonfinite_envs`` says how many were
    left out); their critic targets are NaN, so the critic must be fitted on the other envs
    ([`finite_envs`][torchrl_diffenvs.objectives.SHACLoss.finite_envs] gives the mask). Their gradient must also be kept out of the backward
    pass, which the window collector does ([`IsolatingPolicy`][torchrl_diffenvs.collectors.IsolatingPolicy]).

    **Usage.** ``forward(window)`` returns ``loss_actor`` (backpropagate it into the actor) and
    detached diagnostics (``reward_mean``, ``value_mean``), and writes the detached critic targets
    into the window under ``"value_target"`` (as TorchRL's PPO writes its advantage; they reuse the
    target values the actor loss needs). The critic is then fitted with [`critic_loss`][torchrl_diffenvs.objectives.SHACLoss.critic_loss] on
    minibatches of the detached window (SHAC's passes x minibatches);
    [`compute_value_targets`][torchrl_diffenvs.objectives.SHACLoss.compute_value_targets] writes the targets alone.

    Args:
        actor_network: the policy that collected the windows (held for ``parameters()``; it is
            not called here: the gradient reaches it through the rollout's graph).
        critic_network: a TensorDict module writing ``"state_value"`` (``[..., 1]``).
        gamma: discount.
        lmbda: TD(lambda) parameter of the critic targets.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys (``loss.set_keys(...)``); reward/done/terminated are read under ``"next"``."""

        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        value: NestedKey = "state_value"
        value_target: NestedKey = "value_target"

    default_keys = _AcceptedKeys

    actor_network: TensorDictModuleBase
    critic_network: TensorDictModule
    critic_network_params: TensorDictBase
    target_critic_network_params: TensorDictBase

    def __init__(
        self,
        actor_network: TensorDictModuleBase,
        critic_network: TensorDictModule,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.95,
    ):
        super().__init__()
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"SHACLoss: gamma must lie in (0, 1], got {gamma!r}")
        if not 0.0 <= lmbda <= 1.0:
            raise ValueError(f"SHACLoss: lmbda must lie in [0, 1], got {lmbda!r}")
        self.actor_network = actor_network
        self.convert_to_functional(critic_network, "critic_network", create_target_params=True)
        # The target critic swaps in only the lagging *weights*; buffers stay the live ones
        # (TorchRL's SoftUpdate never updates buffers, so target copies of them would go stale).
        self._critic_weight_keys = [
            key for key, value in self.critic_network_params.items(True, True) if isinstance(value, nn.Parameter)
        ]
        self.gamma = float(gamma)
        self.lmbda = float(lmbda)
        dtype = next(critic_network.parameters()).dtype
        # vectorized=False: the plain backward recursion, exact in the critic's dtype (the
        # vectorised version builds its lambda table in float32) and cheap for short windows
        estimator = TDLambdaEstimator(gamma=gamma, lmbda=lmbda, value_network=None, vectorized=False)
        # its gamma/lmbda buffers are created in float32; rebuild them in the critic's dtype
        estimator.gamma = torch.tensor(gamma, dtype=dtype)
        estimator.lmbda = torch.tensor(lmbda, dtype=dtype)
        self._value_estimator = estimator

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self.value_estimator.set_keys(
            reward=self.tensor_keys.reward, done=self.tensor_keys.done, terminated=self.tensor_keys.terminated
        )

    @property
    def in_keys(self):
        """The rollout entries the loss reads (rewards, done flags and the critic's inputs, now and next)."""
        keys = [("next", self.tensor_keys.reward), ("next", self.tensor_keys.done), ("next", self.tensor_keys.terminated)]
        return keys + list(self.critic_network.in_keys) + [("next", k) for k in self.critic_network.in_keys]

    @property
    def out_keys(self):
        """The entries of the loss's output TensorDict."""
        return ["loss_actor", "reward_mean", "value_mean", "nonfinite_envs"]

    def make_target_updater(self, tau: float = 0.8) -> SoftUpdate:
        """TorchRL's `SoftUpdate` for the target critic: ``target <- (1-tau) target + tau critic``.

        ``tau = 0.8`` is the SHAC reference for simple tasks (0.2 of the old target kept);
        humanoids use ``tau = 0.005``. Call ``.step()`` on the result once per iteration.
        """
        with warnings.catch_warnings():
            # SoftUpdate warns for eps < 0.5 because DQN-style targets usually move slowly; SHAC's don't.
            warnings.filterwarnings("ignore", message="Found an eps value < 0.5")
            return SoftUpdate(self, tau=tau)

    # ------------------------------------------------------------------ critic evaluation
    def _critic(self, obs_td: TensorDictBase, target: bool) -> torch.Tensor:
        obs_td = obs_td.select(*self.critic_network.in_keys)
        if target:
            weights = self.target_critic_network_params.select(*self._critic_weight_keys)
            with weights.to_module(self.critic_network):
                out = self.critic_network(obs_td)
        else:
            out = self.critic_network(obs_td)
        return out.get(self.tensor_keys.value)

    def _next_target_values(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Target-critic values of ``("next", obs)`` ``[N, H, 1]``, differentiable w.r.t. the observation."""
        return self._critic(tensordict.get("next"), target=True)

    @torch.no_grad()
    def _value_targets(self, tensordict: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
        keys = self.tensor_keys
        data = tensordict.select(("next", keys.reward), ("next", keys.done), ("next", keys.terminated)).detach()
        reward = data.get(("next", keys.reward))
        if reward.shape == tensordict.batch_size:  # the estimator wants a trailing feature dim
            reward = reward.unsqueeze(-1)
            data.set(("next", keys.reward), reward)
        for key in (keys.done, keys.terminated):
            # [N, H, 1], or [N, H, A, 1] beside a multi-agent reward: the agents share the episode
            flag = data.get(("next", key)).reshape(*tensordict.batch_size, *([1] * (reward.ndim - 2)))
            data.set(("next", key), flag.expand(reward.shape), inplace=False)
        return self.value_estimator.value_estimate(data, next_value=next_value.detach(), time_dim=1)

    def compute_value_targets(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Writes the detached TD(lambda) targets ``[N, H, 1]`` into ``tensordict["value_target"]``
        (and returns them). Call once per window, before the critic passes."""
        window_entry(tensordict, self.tensor_keys.reward, "SHACLoss")  # validates the layout
        with torch.no_grad():
            next_value = self._next_target_values(tensordict)
        targets = self._value_targets(tensordict, next_value)
        tensordict.set(self.tensor_keys.value_target, targets)
        return targets

    def critic_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``loss_critic`` = mean of ``(V(obs) - value_target)^2`` over any batch shape (e.g. a
        minibatch of a flattened window that went through [`compute_value_targets`][torchrl_diffenvs.objectives.SHACLoss.compute_value_targets])."""
        target = tensordict.get(self.tensor_keys.value_target, None)
        if target is None:
            raise KeyError(
                f"SHACLoss.critic_loss: no {self.tensor_keys.value_target!r} entry; call "
                "compute_value_targets(window) (or forward(window)) first"
            )
        # detached: the critic fits the data, it never pushes gradients into the rollout
        value = self._critic(tensordict.select(*self.critic_network.in_keys).detach(), target=False)
        return TensorDict({"loss_critic": (value - target.detach()).pow(2).mean()}, batch_size=[])

    # ------------------------------------------------------------------ the loss
    def finite_envs(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``[N]`` bool: the envs of a window whose rewards and critic inputs (now and next) are
        finite and that nothing flags as non-finite (see [`nonfinite_envs`][torchrl_diffenvs.objectives.nonfinite_envs])."""
        return ~nonfinite_envs(tensordict, [next_key(self.tensor_keys.reward), *now_and_next(self.critic_network.in_keys)])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        reward = window_entry(tensordict, keys.reward, "SHACLoss")
        done = window_entry(tensordict, keys.done, "SHACLoss").bool()
        terminated = window_entry(tensordict, keys.terminated, "SHACLoss").bool()

        next_value = self._next_target_values(tensordict)  # [N, H, (A,) 1], graph through the observation
        # the critic targets of every env (NaN for the non-finite ones), then the loss of the finite ones
        targets = self._value_targets(tensordict, next_value)
        tensordict.set(keys.value_target, targets)
        keep = self.finite_envs(tensordict)
        reward, done, terminated, next_value = reward[keep], done[keep], terminated[keep], next_value[keep]
        k = like_agents(steps_since_start(done).to(reward.dtype), reward)
        # a sub-trajectory closes at an episode end or at the window end; a terminal state is worth 0
        closes = done.clone()
        closes[:, -1] = True
        bootstrap_here = like_agents(closes & ~terminated, reward)
        bootstrap = torch.where(bootstrap_here, self.gamma ** (k + 1) * next_value.reshape(reward.shape), 0.0)
        loss_actor = -((self.gamma**k) * reward + bootstrap).sum() / reward.numel()  # NaN (0 / 0) if no env is left
        out = {
            "loss_actor": loss_actor,
            "reward_mean": reward.detach().mean(),
            "value_mean": next_value.detach().mean(),
            "nonfinite_envs": (~keep).sum(),
        }
        return TensorDict(out, batch_size=[])
