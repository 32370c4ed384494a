"""AHAC (Georgiev et al., ICML 2024; ``imgeorgiev/DiffRL``, ``src/shac/algorithms/ahac.py``):
SHAC with twin critics, no target critic, critic fitting until its loss plateaus, and a window
length adapted from the contact forces between iterations.

One iteration:

1. collect a window ``[N, H]`` with the graph on (``H = round(horizon)``);
2. actor step on SHAC's bootstrapped return, bootstrapped by the minimum of the twin critics
   ([`AHACLoss`][torchrl_diffenvs.objectives.AHACLoss]), one guarded Adam step;
3. critic targets: TD(lambda) of the detached window from the same minimum;
4. critic passes over ``critic_minibatches`` minibatches until the mean loss of a pass stops
   moving (``critic_passes: null``: the reference's early stop) or a fixed number of passes;
5. update the observation normaliser from the window;
6. move the dual variable and the horizon from the window's ``("next", "contact_force")``
   ([`AdaptiveHorizon`][torchrl_diffenvs.objectives.AdaptiveHorizon]); the next window has the new length;
7. step the learning-rate schedules (the dual learning rate follows the same schedule).

The iteration is [`ShortHorizonLearner`][torchrl_diffenvs.learners.ShortHorizonLearner]'s (in
``learners/short_horizon.py``, with SHAC and SAPO); AHAC fills in its hooks: the contact-force
check of each window, the critic passes until the losses plateau, the horizon update.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

import torch

from .. import checks
from ..distributed import SINGLE_PROCESS, World
from ..modules import ObservationNormalizer, actor_from_config
from ..objectives import AHACLoss, AdaptiveHorizon, TwinCritic
from ..objectives.windows import window_contact_force
from .base import LR_SCHEDULES, ActorNetworkConfig, LearnerConfig, NetworkConfig, checked
from .short_horizon import CRITIC_SHUFFLES, TwinCriticLearner, twin_critic_from_config

__all__ = ["AHACConfig", "AHACLearner"]


def optional_positive_int(value) -> str | None:
    """``None`` or an integer >= 1."""
    return None if value is None else checks.positive_int(value)


@dataclasses.dataclass(frozen=True)
class AHACConfig(LearnerConfig):
    """Settings of [`AHACLearner`][torchrl_diffenvs.learners.AHACLearner] (the keys of ``loss=ahac``); defaults are the
    reference's (``scripts/cfg/alg/ahac.yaml``)."""

    min_horizon: int = checked(8, checks.positive_int)  # the window length H stays in [min_horizon, max_horizon]
    max_horizon: int = checked(64, checks.positive_int)
    contact_threshold: float = checked(500.0, checks.positive)  # C (newtons): the window lengthens above, shortens below
    horizon_lr: float = checked(5e-4, checks.learning_rate)  # the dual variable's learning rate (lambd_lr)
    gamma: float = checked(0.99, checks.in_interval(0.0, 1.0))
    lmbda: float = checked(0.95, checks.in_interval(0.0, 1.0, low_inclusive=True))  # TD(lambda) targets
    actor_lr: float = checked(2e-3, checks.learning_rate)
    critic_lr: float = checked(2e-3, checks.learning_rate)
    betas: tuple = checked((0.7, 0.95), checks.adam_betas)  # Adam betas of both optimisers
    lr_schedule: str = checked("linear", checks.one_of(LR_SCHEDULES))  # also the dual learning rate's
    min_lr: float = checked(1e-5, checks.learning_rate)  # end of the linear schedule
    lr_decay: float = checked(0.997, checks.in_interval(0.0, 1.0))  # per iteration, exponential schedule
    # critic passes per window; null: until the pass losses plateau (at most max_critic_passes)
    critic_passes: int | None = checked(None, optional_positive_int)
    max_critic_passes: int = checked(64, checks.positive_int)
    critic_plateau: float = checked(0.2, checks.positive)  # stop when |mean change| of the last 5 pass losses is below
    critic_minibatches: int = checked(4, checks.positive_int)
    critic_shuffle: str = checked("in_order", checks.one_of(CRITIC_SHUFFLES))  # minibatch order (learners/short_horizon.py)
    max_grad_norm: float | None = checked(1.0, checks.optional_positive)  # clip the actor's gradient norm
    critic_max_grad_norm: float | None = checked(None, checks.optional_positive)  # the reference does not clip
    skip_above: float | None = checked(1e6, checks.optional_positive)  # skip steps with a larger norm
    obs_norm: bool = checked(True, checks.boolean)  # running observation normalisation (from_config)

    @classmethod
    def relation_problems(cls, values: Mapping, where: str = "") -> list[str]:
        if values["min_horizon"] >= values["max_horizon"]:
            return [f"{where}min_horizon={values['min_horizon']!r} must be < {where}max_horizon={values['max_horizon']!r}"]
        return []


class AHACLearner(TwinCriticLearner):
    """Adaptive-horizon actor-critic.

    Needs an env that reports the largest contact normal force of each step: the MuJoCo contact
    tasks keep it in ``("state", "contact_force")``; for another env add a transform that writes
    ``"contact_force"`` (``[N, 1]``, newtons). The first window has ``min_horizon`` steps.

    Args:
        env: a batched differentiable single-agent env that reports contact forces.
        actor: the policy to train, writing ``"action"``.
        critic: a [`TwinCritic`][torchrl_diffenvs.objectives.TwinCritic].
        config: [`AHACConfig`][torchrl_diffenvs.learners.AHACConfig].
        total_env_steps: the budget the learning-rate schedules run over.
        normalizer: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
        reset_input: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
        world: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
    """

    name = "ahac"
    config_class = AHACConfig
    # DiffRL's: Linear-ELU-LayerNorm, orthogonal critics
    networks = MappingProxyType({"actor": ActorNetworkConfig(norm_after_activation=True),
                                 "critic": NetworkConfig(norm_after_activation=True, init="orthogonal")})
    run_defaults = MappingProxyType({"train": {"total_env_steps": 400_000, "checkpoint_interval": 200_000},
                                     "eval": {"interval": 50_000}})

    def __init__(self, env, actor, critic: TwinCritic, config: AHACConfig = AHACConfig(),
                 total_env_steps: int = 1_000_000, *, normalizer: ObservationNormalizer | None = None,
                 reset_input=None, world: World = SINGLE_PROCESS):
        self.adaptive_horizon = AdaptiveHorizon(config.min_horizon, config.max_horizon, config.contact_threshold)
        loss = AHACLoss(actor, critic, gamma=config.gamma, lmbda=config.lmbda)
        super().__init__(env, actor, loss, config, total_env_steps, horizon=self.adaptive_horizon.steps,
                         normalizer=normalizer, reset_input=reset_input, world=world,
                         critic_max_grad_norm=config.critic_max_grad_norm)

    @classmethod
    def env_problems(cls, env) -> list[str]:
        state = env.full_observation_spec.get("state", None) if hasattr(env, "full_observation_spec") else None
        if state is not None and "contact_force" in state.keys():
            return []
        return [f"env {getattr(env, 'name', type(env).__name__)!r} reports no contact force (AHAC adapts its window to "
                "it): train it with shac, or AHAC on a MuJoCo contact task (HalfCheetah-v5, Hopper-v5, Walker2d-v5, "
                "Ant-v5, Humanoid-v5, HumanoidStandup-v5, Pusher-v5)"]

    @staticmethod
    def _policy_and_normalizer(loss_cfg: Mapping, env):
        """The policy of a ``loss=ahac`` section and its observation normaliser (SHAC's actor)."""
        return actor_from_config(loss_cfg, env)

    @classmethod
    def policy_from_config(cls, loss_cfg: Mapping, env):
        return cls._policy_and_normalizer(loss_cfg, env)[0]

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> AHACLearner:
        actor, normalizer = cls._policy_and_normalizer(loss_cfg, env)
        critic = twin_critic_from_config(loss_cfg.critic, env, normalizer)
        return cls(env, actor, critic, cls.settings_from(loss_cfg), total_env_steps, normalizer=normalizer, world=world)

    @property
    def horizon_lr(self) -> float:
        """This iteration's dual learning rate: ``horizon_lr`` on the actor's schedule (the
        reference: linear from ``lambd_lr`` to 1e-5 over the run)."""
        c = self.config
        if c.lr_schedule == "linear":
            return c.horizon_lr + (c.min_lr - c.horizon_lr) * min(self.iteration / max(1, self.total_iterations), 1.0)
        if c.lr_schedule == "exponential":
            return c.horizon_lr * c.lr_decay**self.iteration
        return c.horizon_lr

    def _critic_pass_count(self) -> tuple[int, bool]:
        c = self.config
        return (c.critic_passes, False) if c.critic_passes is not None else (c.max_critic_passes, True)

    def _check_window(self, window) -> None:
        window_contact_force(window, type(self).__name__)  # a clear error before any update

    def _after_window(self, data, keep) -> dict[str, float]:
        force = window_contact_force(data, type(self).__name__)  # [N, H]
        # the per-step mean over every rank's finite envs: the same horizon on every rank
        weight = keep.to(force.dtype).unsqueeze(-1).expand_as(force)
        total = self.world.gather(torch.where(keep.unsqueeze(-1), force, 0.0)).reshape(-1, force.shape[-1]).sum(0)
        count = self.world.gather(weight).reshape(-1, force.shape[-1]).sum(0).clamp_min(1.0)
        horizon = self.adaptive_horizon.update(total / count, self.horizon_lr)
        self.collector.horizon = horizon  # the collector reads it at each rollout
        return {"horizon": float(self._last_window_steps), "horizon_next": float(horizon),
                "horizon_dual": float(self.adaptive_horizon.dual[0])}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "adaptive_horizon": self.adaptive_horizon.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.adaptive_horizon.load_state_dict(state["adaptive_horizon"])
        self.collector.horizon = self.adaptive_horizon.steps
