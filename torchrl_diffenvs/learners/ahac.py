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

`TwinCriticLearner` holds what AHAC and SAPO share (steps 1-5).
"""
from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Mapping
from types import MappingProxyType

import torch

from .. import checks
from ..collectors import DiffWindowCollector
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys
from ..modules import ObservationNormalizer, actor_from_config, critic_from_config
from ..objectives import AHACLoss, AdaptiveHorizon, GradientGuard, NonFiniteEnvMonitor, TwinCritic
from ..objectives.windows import window_contact_force
from .base import (
    LR_SCHEDULES,
    ActorCriticCheckpoint,
    ActorNetworkConfig,
    Learner,
    LearnerConfig,
    NetworkConfig,
    checked,
    lr_scheduler,
)

__all__ = ["AHACConfig", "AHACLearner", "TwinCriticLearner"]


def optional_positive_int(value) -> str | None:
    """``None`` or an integer >= 1."""
    return None if value is None else checks.positive_int(value)


# in_order: contiguous blocks of the window in time order, [t0, t1) x all envs (the references: DiffRL and mineral
# build their critic datasets unshuffled); once_per_window: one random split; every_pass: a new one per pass
CRITIC_SHUFFLES = ("in_order", "once_per_window", "every_pass")


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
    critic_shuffle: str = checked("in_order", checks.one_of(CRITIC_SHUFFLES))  # minibatch order (see CRITIC_SHUFFLES)
    max_grad_norm: float | None = checked(1.0, checks.optional_positive)  # clip the actor's gradient norm
    critic_max_grad_norm: float | None = checked(None, checks.optional_positive)  # the reference does not clip
    skip_above: float | None = checked(1e6, checks.optional_positive)  # skip steps with a larger norm
    obs_norm: bool = checked(True, checks.boolean)  # running observation normalisation (from_config)

    @classmethod
    def relation_problems(cls, values: Mapping, where: str = "") -> list[str]:
        if values["min_horizon"] >= values["max_horizon"]:
            return [f"{where}min_horizon={values['min_horizon']!r} must be < {where}max_horizon={values['max_horizon']!r}"]
        return []


def twin_critic_from_config(section: Mapping, env, normalizer: ObservationNormalizer | None) -> TwinCritic:
    """Two critics from one ``loss.critic`` section (separate weights, the actor's normaliser shared)."""
    return TwinCritic(critic_from_config(section, env, normalizer), critic_from_config(section, env, normalizer))


class TwinCriticLearner(ActorCriticCheckpoint, Learner):
    """SHAC's window loop with twin critics and no target critic: what AHAC and SAPO share.

    Subclasses give the loss and the optimiser and may override `_after_actor_step`
    (metrics, temperature), `_critic_targets` and `_after_window` (horizon).

    Args:
        env, actor, reset_input, world: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
        loss: the window loss ([`AHACLoss`][torchrl_diffenvs.objectives.AHACLoss] or
            [`SAPOLoss`][torchrl_diffenvs.objectives.SAPOLoss]), holding the critics.
        config: the learner's settings (``actor_lr``, ``critic_lr``, ``betas``, ``lr_schedule``,
            ``min_lr``, ``lr_decay``, ``critic_minibatches``, ``critic_shuffle``,
            ``max_grad_norm``, ``skip_above`` are read here).
        horizon: the first window's length.
        normalizer: the observation normaliser shared by actor and critics, updated after every window.
        optimizer: the optimiser class of actor and critics (``torch.optim.Adam`` or ``AdamW``).
        optimizer_kwargs: its extra arguments (e.g. ``weight_decay``).
        critic_max_grad_norm: the critics' gradient-norm clip (``None``: no clipping).
    """

    supports_multi_agent = False  # one actor, one value per env: the multi-agent keys are SHAC's and PPO's

    def __init__(self, env, actor, loss, config: LearnerConfig, total_env_steps: int, *, horizon: int,
                 normalizer: ObservationNormalizer | None = None, reset_input=None, world: World = SINGLE_PROCESS,
                 optimizer: type[torch.optim.Optimizer] = torch.optim.Adam, optimizer_kwargs: Mapping | None = None,
                 critic_max_grad_norm: float | None = None):
        super().__init__(env, config, total_env_steps, reset_input=reset_input, world=world)
        c = config
        self.keys = policy_keys(env)
        if self.keys.num_agents is not None:
            raise ValueError(f"{type(self).__name__}: single-agent envs only; {type(env).__name__} is multi-agent "
                             "(train it with bptt, shac or ppo)")
        self.actor = self.policy = actor
        self.normalizer = normalizer
        self.collector = DiffWindowCollector(env, actor, horizon=int(horizon), reset_input=reset_input)
        self._last_window_steps = int(horizon)
        self.loss = loss
        self.actor_params = [p for p in actor.parameters() if p.requires_grad]
        self.critic_params = [p for p in self.loss.critic_network.parameters() if p.requires_grad]
        kwargs = dict(optimizer_kwargs or {})
        self.actor_optim = optimizer(self.actor_params, lr=c.actor_lr, betas=c.betas, foreach=True, **kwargs)
        self.critic_optim = optimizer(self.critic_params, lr=c.critic_lr, betas=c.betas, foreach=True, **kwargs)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=c.skip_above)
        self.critic_guard = GradientGuard(max_norm=critic_max_grad_norm, skip_above=c.skip_above)
        self.schedules = [
            lr_scheduler(optim, c.lr_schedule, lambda: self.total_iterations, min_lr=c.min_lr, decay=c.lr_decay)
            for optim in (self.actor_optim, self.critic_optim)
        ]

    @property
    def steps_per_env(self) -> int:
        """Length of the window the last `train_iteration` collected (the next one's before any)."""
        return self._last_window_steps

    # ------------------------------------------------------------------ hooks
    def _check_window(self, window) -> None:
        """Right after the rollout: raise if the window lacks an entry the learner needs."""

    def _after_actor_step(self, window, out) -> dict[str, float]:
        """After the actor's step, before the window is detached: extra metrics."""
        return {}

    def _critic_targets(self, data) -> None:
        """The critic targets of the detached window: those the loss wrote (override to recompute)."""

    def _after_window(self, data, keep) -> dict[str, float]:
        """After the critic and normaliser updates, before the schedules step: extra metrics
        (``keep [N]``: the finite envs)."""
        return {}

    def _critic_pass_count(self) -> tuple[int, bool]:
        """``(most passes, stop early when the losses plateau)``."""
        return self.config.critic_passes, False

    # ------------------------------------------------------------------ one iteration
    def _fit_critic(self, flat, window_shape: tuple[int, int]) -> tuple[float, int]:
        """Critic passes over minibatches of the window flattened from ``window_shape`` ``(N, H)``;
        returns the last pass's mean loss and the number of passes made."""
        c = self.config
        most, until_plateau = self._critic_pass_count()
        recent: deque[float] = deque(maxlen=5)
        pass_loss, passes = float("nan"), 0
        for critic_pass in range(most):
            if critic_pass == 0 and c.critic_shuffle == "in_order":
                n, h = window_shape
                split = torch.arange(n * h).reshape(n, h).t().reshape(-1).chunk(c.critic_minibatches)
            elif critic_pass == 0 or c.critic_shuffle == "every_pass":
                split = torch.randperm(flat.shape[0]).chunk(c.critic_minibatches)
            losses = []
            for batch in split:
                critic_loss = self.loss.critic_loss(flat[batch])["loss_critic"]
                self.critic_optim.zero_grad(set_to_none=True)
                critic_loss.backward()
                self.world.average_gradients(self.critic_params)
                self.critic_guard.step(self.critic_optim, self.critic_params, loss=critic_loss,
                                       context=self.nonfinite.describe)
                losses.append(critic_loss.item())
            pass_loss, passes = sum(losses) / len(losses), critic_pass + 1
            # the reference's early stop: the mean change over the previous 5 pass losses
            if until_plateau and len(recent) == 5:
                history = list(recent)
                if abs((history[-1] - history[0]) / 4) < c.critic_plateau:
                    break
            recent.append(pass_loss)
        return pass_loss, passes

    def train_iteration(self) -> dict[str, float]:
        window = self.collector.rollout()
        self._last_window_steps = window.shape[1]
        self._check_window(window)
        # actor step on the bootstrapped return over the finite envs (the loss also writes the critic targets)
        out = self.loss(window)
        keep = self.loss.finite_envs(window)
        nonfinite = self.nonfinite.update(~keep, self.iteration)
        self.actor_optim.zero_grad(set_to_none=True)
        if out["loss_actor"].requires_grad:
            out["loss_actor"].backward()
        self.world.average_gradients(self.actor_params)
        actor_info = self.actor_guard.step(self.actor_optim, self.actor_params, loss=out["loss_actor"],
                                           context=self.nonfinite.describe)
        metrics = {key: out[key].item() for key in ("loss_actor", "reward_mean", "value_mean")}
        metrics["nonfinite_envs"] = nonfinite
        metrics.update(self._after_actor_step(window, out))
        data = window.detach()
        del window, out  # the graph is spent
        self._critic_targets(data)
        # the critics fit the finite envs' targets; none when every env is non-finite (each planned step skipped)
        loss_critic, passes = float("nan"), 0
        if keep.any():
            flat = data[keep].select(*self.loss.critic_network.in_keys, self.loss.tensor_keys.value_target)
            loss_critic, passes = self._fit_critic(flat.reshape(-1), tuple(flat.batch_size))
        else:
            for _ in range(self._critic_pass_count()[0] * self.config.critic_minibatches):
                self.critic_guard.skip(context=self.nonfinite.describe)
        if self.normalizer is not None:
            self.normalizer.update(self.world.gather(data.get(self.keys.observation)))
        metrics.update({
            "reward": metrics.pop("reward_mean"),
            "value": metrics.pop("value_mean"),
            "loss_critic": loss_critic,
            "critic_passes": passes,
            "grad_norm_actor": actor_info["grad_norm"],
            "skipped_actor": self.actor_guard.skipped,
            "skipped_critic": self.critic_guard.skipped,
            "lr_actor": self.actor_optim.param_groups[0]["lr"],
        })
        force = window_contact_force(data)
        if force is not None:
            metrics["contact_force_max"] = force.max().item()
        metrics.update(self._after_window(data, keep))
        if self.collector.finished_returns:
            metrics["return"] = sum(self.collector.finished_returns) / len(self.collector.finished_returns)
        for schedule in self.schedules:
            schedule.step()
        self.iteration += 1
        return metrics

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        return {**super().state_dict(), "last_window_steps": self._last_window_steps}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)  # actor, both critics (normaliser included), optimisers, ...
        self._last_window_steps = int(state["last_window_steps"])


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
        self.loss.set_keys(reward=self.keys.reward, value=self.keys.value)

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
        settings = {k: v for k, v in loss_cfg.items() if k not in ("name", "actor", "critic")}
        return cls(env, actor, critic, AHACConfig.from_mapping(settings), total_env_steps, normalizer=normalizer,
                   world=world)

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
