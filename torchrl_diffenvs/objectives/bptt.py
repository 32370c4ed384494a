"""Back-propagation through time (analytic policy gradient) as a TorchRL loss module."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from .windows import like_agents, steps_since_start, window_entry
from .nonfinite import nonfinite_envs

__all__ = ["BPTTLoss"]


class BPTTLoss(LossModule):
    r"""BPTT / analytic policy gradient on a differentiable rollout window.

    For a window ``[N, H]`` collected with the graph on (see
    [`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector])

    $$
    \mathcal{L}_{actor} = -\frac{1}{N H} \sum_{i=1}^{N} \sum_{t=0}^{H-1} \gamma^{k_{i,t}} r_{i,t}
    $$

    where $k_{i,t}$ counts the steps since env ``i``'s sub-trajectory started (the window
    start, or the reset after an episode ended inside the window). Dividing by ``H`` makes the
    learning rate independent of the window length. With a multi-agent reward
    (``set_keys(reward=("agents", "reward"))``, ``[N, H, A, 1]``) the agents' rewards are
    averaged: the team's return, whose gradient reaches each agent's actions also through the
    other agents' rewards. With ``H`` equal to the episode length and
    one episode per window this is full-episode BPTT (Ivy Gym's demos, TorchRL's Pendulum
    tutorial); with short windows and carried state it is Brax's APG.

    **Non-finite envs** (a NaN/inf reward, a ``("next", "nonfinite")`` flag, or marked
    ``"isolated"`` by the collector) are left out: the sums run over the other envs and $N$
    counts only them (``nonfinite_envs`` says how many were left out). Their gradient must also be
    kept out of the backward pass, which the window collector does
    ([`IsolatingPolicy`][torchrl_diffenvs.collectors.IsolatingPolicy]).

    The policy is not called here: the gradient reaches it through the rollout's graph. The actor
    is held so that ``loss.parameters()`` lists what to optimise.

    Args:
        actor_network: the policy used to collect the windows.
        gamma: discount (default ``1.0``, undiscounted as in Ivy Gym, Brax APG and TorchRL's
            tutorial).

    Returns (``forward``): a TensorDict with ``loss_actor``, ``reward_mean`` (the window's mean
    per-step reward over the finite envs, detached) and ``nonfinite_envs`` (how many envs were
    left out); NaN when every env was. Episode returns come from the collector
    (`finished_returns`).
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys (``loss.set_keys(reward=...)``), read under ``"next"``."""

        reward: NestedKey = "reward"
        done: NestedKey = "done"

    default_keys = _AcceptedKeys

    def __init__(self, actor_network: TensorDictModuleBase, *, gamma: float = 1.0):
        super().__init__()
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"BPTTLoss: gamma must lie in (0, 1], got {gamma!r}")
        self.actor_network = actor_network
        self.gamma = float(gamma)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        """The rollout entries the loss reads."""
        return [("next", self.tensor_keys.reward), ("next", self.tensor_keys.done)]

    @property
    def out_keys(self):
        """The entries of the loss's output TensorDict."""
        return ["loss_actor", "reward_mean", "nonfinite_envs"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        reward = window_entry(tensordict, self.tensor_keys.reward, "BPTTLoss")
        done = window_entry(tensordict, self.tensor_keys.done, "BPTTLoss").bool()
        bad = nonfinite_envs(tensordict, [("next", self.tensor_keys.reward)])
        reward, done = reward[~bad], done[~bad]  # the finite envs only
        discount = like_agents(self.gamma ** steps_since_start(done).to(reward.dtype), reward)
        out = {
            "loss_actor": -(discount * reward).sum() / reward.numel(),  # NaN (0 / 0) when no env is left
            "reward_mean": reward.detach().mean(),
            "nonfinite_envs": bad.sum(),
        }
        return TensorDict(out, batch_size=[])
