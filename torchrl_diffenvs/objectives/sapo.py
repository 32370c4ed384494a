"""SAPO (Xing et al., ICLR 2025): SHAC with maximum entropy, twin critics and no target critic,
as a TorchRL loss module."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from .windows import steps_since_start, window_entry
from .ahac import AHACLoss
from .shac import SHACLoss

__all__ = ["SAPOLoss"]


class SAPOLoss(AHACLoss):
    r"""Soft analytic policy optimisation: SHAC's window loss with an entropy bonus.

    Per step the reward becomes the *soft* reward $r_t + \alpha\, e_t$, with the entropy
    estimate $e_t$ from the log-probability of the action actually taken (written by the
    actor under ``"action_log_prob"`` during the rollout, with its graph):

    $$
    e_t = -\log\pi(a_t|s_t), \quad\text{then}\quad
    e_t \leftarrow (e_t + |\bar H|)/2 \ \text{(entropy_offset)},\quad
    e_t \leftarrow e_t / |\bar H| \ \text{(entropy_scale)},
    $$

    $\bar H = -$ ``target_entropy_scale`` $\cdot|A|$ the target entropy. (The
    reference, ``etaoxing/mineral`` ``agents/diffrl/shac.py`` with its ``DFlexAntSAPO`` settings,
    scales and offsets the same way; its ``use_distr_ent`` draws a second sample for the
    estimate, this uses the action taken: both are unbiased.)

    **Actor** (``loss_actor``): SHAC's bootstrapped return of the soft rewards, the bootstrap
    being the *mean* of the two critics (``actor_loss_avgcritics``), $\alpha$ detached.
    Gradients reach the actor through the rewards, the observations and the log-probabilities.

    **Critic targets**: TD($\lambda$) of the detached soft rewards bootstrapped by the
    *minimum* of the two critics (the reference's ``compute_target_values_with_entropy``), the
    window end treated as a trajectory end; both critics fit them ([`critic_loss`][torchrl_diffenvs.objectives.SHACLoss.critic_loss]). There is
    no target critic: values come from the current critics (as in
    [`AHACLoss`][torchrl_diffenvs.objectives.AHACLoss]).

    **Temperature**: `log_alpha` (initial ``log(init_alpha)``) is trained on
    [`alpha_loss`][torchrl_diffenvs.objectives.SAPOLoss.alpha_loss] ``= alpha' * (H_est - target_entropy)`` with ``H_est`` the window's mean
    of $-\log\pi$ (detached) and ``alpha' = alpha * |target_entropy|`` when the entropy is
    scaled (the reference's ``unscale_entropy_alpha``), else ``alpha``: the temperature falls
    while the entropy is above the target.

    Single-agent envs only.

    Args:
        actor_network: the policy; it must write ``"action_log_prob"`` when sampling
            (`make_sapo_actor`).
        critic_network: a [`TwinCritic`][torchrl_diffenvs.objectives.TwinCritic] (``[..., 2]``).
        action_dim: ``|A|``.
        gamma: discount.
        lmbda: TD(lambda) parameter.
        init_alpha: the initial temperature.
        target_entropy_scale: the target entropy is ``-target_entropy_scale * action_dim``.
        entropy_offset: the offset normalisation of $e_t$ above.
        entropy_scale: the scale normalisation of $e_t$ above.
    """

    @dataclass
    class _AcceptedKeys(SHACLoss._AcceptedKeys):
        """SHAC's keys and the log-probability the actor writes at each step."""

        log_prob: NestedKey = "action_log_prob"

    default_keys = _AcceptedKeys

    def __init__(
        self,
        actor_network,
        critic_network,
        *,
        action_dim: int,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        init_alpha: float = 1.0,
        target_entropy_scale: float = 0.5,
        entropy_offset: bool = True,
        entropy_scale: bool = True,
    ):
        super().__init__(actor_network, critic_network, gamma=gamma, lmbda=lmbda)
        if not init_alpha > 0:
            raise ValueError(f"SAPOLoss: init_alpha must be > 0, got {init_alpha!r}")
        if not target_entropy_scale > 0:
            raise ValueError(f"SAPOLoss: target_entropy_scale must be > 0, got {target_entropy_scale!r}")
        reference = next(critic_network.parameters())
        self.target_entropy = -float(target_entropy_scale) * int(action_dim)
        self.entropy_offset = bool(entropy_offset)
        self.entropy_scale = bool(entropy_scale)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(init_alpha), dtype=reference.dtype, device=reference.device))

    @property
    def alpha(self) -> torch.Tensor:
        """The temperature ``exp(log_alpha)`` (detached)."""
        return self.log_alpha.detach().exp()

    @property
    def in_keys(self):
        """SHAC's entries and the actions' log-probabilities."""
        return super().in_keys + [self.tensor_keys.log_prob]

    @property
    def out_keys(self):
        """The entries of the loss's output TensorDict."""
        return ["loss_actor", "reward_mean", "value_mean", "entropy", "alpha"]

    # ------------------------------------------------------------------ entropy
    def entropy_bonus(self, log_prob: torch.Tensor) -> torch.Tensor:
        """$e_t$ from ``log_prob`` (offset and scaled as configured), same shape."""
        bonus = -log_prob
        h = abs(self.target_entropy)
        if self.entropy_offset:
            bonus = (bonus + h) * 0.5
        if self.entropy_scale:
            bonus = bonus / h
        return bonus

    def alpha_loss(self, entropy: torch.Tensor | float) -> torch.Tensor:
        """The temperature's loss for the entropy estimate ``entropy`` (mean of
        $-\\log\\pi$ over a window); its gradient reaches `log_alpha` only."""
        entropy = torch.as_tensor(entropy, dtype=self.log_alpha.dtype, device=self.log_alpha.device).detach()
        alpha = self.log_alpha.exp()
        if self.entropy_scale:  # the bonus was divided by |target|: the temperature's step is not
            alpha = alpha * abs(self.target_entropy)
        return (alpha * (entropy - self.target_entropy)).mean()

    def _log_prob(self, tensordict: TensorDictBase) -> torch.Tensor:
        log_prob = tensordict.get(self.tensor_keys.log_prob, None)
        if log_prob is None:
            raise KeyError(f"SAPOLoss: the window has no {self.tensor_keys.log_prob!r} entry: the actor must write the "
                           "log-probability of the action it samples (make_sapo_actor does)")
        return log_prob.reshape(tensordict.batch_size)

    def _soft_reward(self, tensordict: TensorDictBase, reward: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        if reward.ndim != 2:
            raise ValueError(f"SAPOLoss: single-agent envs only (one reward per env and step), got rewards of shape "
                             f"{tuple(reward.shape)}")
        return reward + alpha * self.entropy_bonus(self._log_prob(tensordict))

    # ------------------------------------------------------------------ critic targets
    @torch.no_grad()
    def _soft_targets(self, tensordict: TensorDictBase, soft_reward: torch.Tensor, next_value: torch.Tensor):
        keys = self.tensor_keys
        data = tensordict.select(("next", keys.reward), ("next", keys.done), ("next", keys.terminated)).detach()
        original = data.get(("next", keys.reward))
        data.set(("next", keys.reward), soft_reward.detach().reshape(original.shape).to(original.dtype))
        return self._value_targets(data, next_value)

    def compute_value_targets(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Writes the detached soft TD(lambda) targets ``[N, H, 1]`` under ``"value_target"``
        with the *current* temperature (the reference computes them after the temperature's
        step) and returns them."""
        with torch.no_grad():
            reward = window_entry(tensordict, self.tensor_keys.reward, "SAPOLoss")
            soft = self._soft_reward(tensordict, reward, self.alpha)
            next_value = self._critic(tensordict.get("next"), target=False).min(dim=-1, keepdim=True).values
            targets = self._soft_targets(tensordict, soft, next_value)
        tensordict.set(self.tensor_keys.value_target, targets)
        return targets

    # ------------------------------------------------------------------ the loss
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        reward = window_entry(tensordict, keys.reward, "SAPOLoss")
        done = window_entry(tensordict, keys.done, "SAPOLoss").bool()
        terminated = window_entry(tensordict, keys.terminated, "SAPOLoss").bool()
        alpha = self.alpha
        soft = self._soft_reward(tensordict, reward, alpha)

        values = self._critic(tensordict.get("next"), target=False)  # [N, H, 2], graph through the observation
        next_min = values.detach().min(dim=-1, keepdim=True).values
        tensordict.set(keys.value_target, self._soft_targets(tensordict, soft, next_min))
        # the loss of the finite envs only (as SHACLoss): a non-finite env's NaN would poison the sums
        keep = self.finite_envs(tensordict)
        soft, done, terminated, values = soft[keep], done[keep], terminated[keep], values[keep]
        k = steps_since_start(done).to(reward.dtype)
        closes = done.clone()
        closes[:, -1] = True
        bootstrap_value = values.mean(dim=-1).reshape(soft.shape)
        bootstrap = torch.where(closes & ~terminated, self.gamma ** (k + 1) * bootstrap_value, 0.0)
        loss_actor = -((self.gamma**k) * soft + bootstrap).sum() / soft.numel()  # NaN (0 / 0) if no env is left
        out = {
            "loss_actor": loss_actor,
            "reward_mean": reward[keep].detach().mean(),
            "value_mean": bootstrap_value.detach().mean(),
            "entropy": -self._log_prob(tensordict)[keep].detach().mean(),
            "alpha": alpha,
            "nonfinite_envs": (~keep).sum(),
        }
        return TensorDict(out, batch_size=[])
