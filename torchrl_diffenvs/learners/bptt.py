"""BPTT: the analytic policy gradient through short windows of the differentiable env (Brax's APG).

One iteration, in the algorithm's order:

1. collect a window ``[N, H]`` with the autograd graph on, the env state carried over from the
   previous window and detached at its start ([`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector]);
2. actor step: backpropagate the window's (discounted) negative return over its finite envs
   ([`BPTTLoss`][torchrl_diffenvs.objectives.BPTTLoss]; envs with NaN/inf rewards or observations
   are left out, counted in ``"nonfinite_envs"`` and named in a warning), average the gradient over the ranks (data
   parallel; a no-op in one process) and take one guarded Adam step (clip the gradient norm;
   skip NaN/inf or absurd gradients);
3. update the observation normaliser from the window's raw observations, all ranks' (frozen
   during the window);
4. step the learning-rate schedule.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

import torch
from tensordict import TensorDictBase

from .. import checks
from ..collectors import DiffWindowCollector
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys
from ..modules import ObservationNormalizer, actor_from_config, observation_key_of
from ..objectives import BPTTLoss, GradientGuard, NonFiniteEnvMonitor
from ..objectives.windows import window_contact_force, window_solver_unconverged
from .base import ActorNetworkConfig, LR_SCHEDULES, Learner, LearnerConfig, checked, load_lr_scheduler, lr_scheduler

__all__ = ["BPTTConfig", "BPTTLearner"]


@dataclasses.dataclass(frozen=True)
class BPTTConfig(LearnerConfig):
    """Settings of [`BPTTLearner`][torchrl_diffenvs.learners.BPTTLearner] (the ``loss`` section of ``loss=bptt``; its defaults are this class's)."""

    horizon: int = checked(16, checks.positive_int)  # window length H: an iteration is N x H env steps
    gamma: float = checked(1.0, checks.in_interval(0.0, 1.0))  # discount inside a window (Brax APG: 1)
    actor_lr: float = checked(1e-2, checks.learning_rate)
    betas: tuple = checked((0.7, 0.95), checks.adam_betas)  # Adam betas (SHAC, Brax APG)
    lr_schedule: str = checked("linear", checks.one_of(LR_SCHEDULES))
    min_lr: float = checked(1e-5, checks.learning_rate)  # end of the linear schedule
    lr_decay: float = checked(0.997, checks.in_interval(0.0, 1.0))  # per iteration, exponential schedule
    max_grad_norm: float | None = checked(1.0, checks.optional_positive)  # the clip threshold
    grad_clip: str = checked("norm", checks.one_of(GradientGuard.CLIP_MODES))  # Brax APG: elementwise
    skip_above: float | None = checked(1e6, checks.optional_positive)  # skip steps with a larger norm
    stagger_episodes: bool = checked(False, checks.boolean)  # random episode phases (Brax APG: true)
    obs_norm: bool = checked(True, checks.boolean)  # running observation normalisation (from_config)


class BPTTLearner(Learner):
    """Back-propagation through time over short windows with carried env state.

    On a multi-agent env one parameter-shared actor acts for every agent and the loss is the
    team's mean return ([`BPTTLoss`][torchrl_diffenvs.objectives.BPTTLoss]).

    Args:
        env: a batched differentiable env (rewards and observations carry gradients w.r.t. actions).
        actor: the policy to train, writing ``"action"`` (e.g. [`make_actor`][torchrl_diffenvs.modules.make_actor]).
        config: [`BPTTConfig`][torchrl_diffenvs.learners.BPTTConfig].
        total_env_steps: the budget the learning-rate schedule runs over.
        normalizer: the [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] inside ``actor``
            to update after every window, if any.
        start_state: start every window from this TensorDict's ``"state"`` instead of carrying
            the env state on (trajectory optimisation from a fixed start).
        reset_input: for a batch-unlocked env (TorchRL's ``PendulumEnv``), what to reset it with:
            ``lambda: env.gen_params(batch_size=[N])`` (see [`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector]).
        world: the ranks training together (`torchrl_diffenvs.distributed`); ``env`` is this
            rank's batch.
    """

    name = "bptt"
    config_class = BPTTConfig
    networks = MappingProxyType({"actor": ActorNetworkConfig()})
    run_defaults = MappingProxyType({"train": {"total_env_steps": 600_000, "checkpoint_interval": 200_000},
                                     "eval": {"interval": 100_000}})
    compiles_windows = True

    def __init__(self, env, actor, config: BPTTConfig = BPTTConfig(), total_env_steps: int = 1_000_000, *,
                 normalizer: ObservationNormalizer | None = None, start_state: TensorDictBase | None = None,
                 reset_input=None, world: World = SINGLE_PROCESS):
        super().__init__(env, config, total_env_steps, reset_input=reset_input, world=world)
        c = config
        self.actor = self.policy = actor
        self.normalizer = normalizer
        self.collector = DiffWindowCollector(env, actor, horizon=c.horizon, start_state=start_state,
                                             stagger_episodes=c.stagger_episodes, reset_input=reset_input)
        self.loss = BPTTLoss(actor, gamma=c.gamma)
        self.keys = policy_keys(env)
        self.loss.set_keys(reward=self.keys.reward)  # ("agents", "reward") on a multi-agent env
        self.actor_params = [p for p in actor.parameters() if p.requires_grad]
        # foreach: one kernel per Adam operation for all tensors (about 2x faster for small nets on CPU)
        self.actor_optim = torch.optim.Adam(self.actor_params, lr=c.actor_lr, betas=c.betas, foreach=True)
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=c.skip_above, clip=c.grad_clip)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        self.actor_schedule = lr_scheduler(self.actor_optim, c.lr_schedule, lambda: self.total_iterations,
                                           min_lr=c.min_lr, decay=c.lr_decay)

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> BPTTLearner:
        actor, normalizer = actor_from_config(loss_cfg, env)
        return cls(env, actor, cls.settings_from(loss_cfg), total_env_steps, normalizer=normalizer,
                   world=world)

    @property
    def steps_per_env(self) -> int:
        return self.config.horizon

    def train_iteration(self) -> dict[str, float]:
        # 1. collect a window with the graph on
        window = self.collector.rollout()
        # 2. actor step on the window's negative return
        out = self.loss(window)  # over the finite envs (the collector cut the others' gradient)
        nonfinite = self.nonfinite.update(self.collector.nonfinite, self.iteration)
        self.actor_optim.zero_grad(set_to_none=True)
        if out["loss_actor"].requires_grad:  # False when no reward depends on the actions (CartPole-v1's +1)
            out["loss_actor"].backward()
        self.world.average_gradients(self.actor_params)
        actor_info = self.actor_guard.step(self.actor_optim, self.actor_params, loss=out["loss_actor"],
                                           context=self.nonfinite.describe)
        metrics = {
            "nonfinite_envs": nonfinite,
            "reward": out["reward_mean"].item(),
            "loss_actor": out["loss_actor"].item(),
            "grad_norm_actor": actor_info["grad_norm"],
            "skipped_actor": self.actor_guard.skipped,
            "lr_actor": self.actor_optim.param_groups[0]["lr"],
        }
        force = window_contact_force(window)  # envs with contacts report their largest normal force
        if force is not None:
            metrics["contact_force_max"] = force.max().item()
        unconverged = window_solver_unconverged(window)  # MuJoCo's contact: solves cut at the model's iterations
        if unconverged is not None:
            metrics["solver_unconverged"] = unconverged
        if self.collector.finished_returns:
            metrics["return"] = sum(self.collector.finished_returns) / len(self.collector.finished_returns)
        # 3. observation statistics, frozen during the window, move after it
        if self.normalizer is not None:
            self.normalizer.update(self.world.gather(window.get(observation_key_of(self.actor, self.keys.observation))))
        # 4. learning-rate schedule
        self.actor_schedule.step()
        self.iteration += 1
        return metrics

    def state_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "actor": self.actor.state_dict(),  # the normaliser's statistics included
            "actor_optimizer": self.actor_optim.state_dict(),
            "actor_schedule": self.actor_schedule.state_dict(),
            "actor_guard": self.actor_guard.state_dict(),
            "collector": self.collector.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.iteration = int(state["iteration"])
        self.actor.load_state_dict(state["actor"])
        self.actor_optim.load_state_dict(state["actor_optimizer"])
        load_lr_scheduler(self.actor_schedule, state["actor_schedule"])
        self.actor_guard.load_state_dict(state["actor_guard"])
        self.collector.load_state_dict(state["collector"])
