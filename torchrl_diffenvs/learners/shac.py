"""SHAC (Xu et al. 2022): BPTT over short windows closed by a learned target critic.

One iteration, in the order of the reference implementation (DiffRL's ``shac.py``):

1. collect a window ``[N, H]`` with the autograd graph on (the env state carried over and
   detached at the window start);
2. actor step: backpropagate the window's return bootstrapped by the *target* critic at
   episode ends and at the window end over the finite envs ([`SHACLoss`][torchrl_diffenvs.objectives.SHACLoss];
   envs with NaN/inf rewards or observations are left out of the actor and critic steps, counted in
   ``"nonfinite_envs"`` and named in a warning), one
   guarded Adam step on the gradient averaged over the ranks (a no-op in one process);
3. critic targets: TD(lambda) returns of the detached window, from the target values the actor
   loss already computed (written under ``"value_target"``);
4. critic passes: ``critic_passes`` x ``critic_minibatches`` guarded MSE steps on shuffled
   minibatches of the window (each rank shuffles its own; gradients averaged over the ranks);
5. target update: ``target <- (1 - target_tau) target + target_tau critic``;
6. update the observation normaliser (shared by actor and critic) from the window, all ranks'
   (and a privileged critic's own input normaliser);
7. step the learning-rate schedules.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

import torch

from .. import checks
from ..collectors import DiffWindowCollector
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys
from ..modules import (
    CRITIC_INPUTS,
    ObservationNormalizer,
    actor_from_config,
    critic_from_config,
    observation_key_of,
    update_privileged_statistics,
)
from ..objectives import GradientGuard, NonFiniteEnvMonitor, SHACLoss
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

__all__ = ["SHACConfig", "SHACLearner"]


@dataclasses.dataclass(frozen=True)
class SHACConfig(LearnerConfig):
    """Settings of [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner] (the ``loss`` section of ``loss=shac``; its defaults are this class's)."""

    horizon: int = checked(16, checks.positive_int)  # window length H: an iteration is N x H env steps
    gamma: float = checked(0.99, checks.in_interval(0.0, 1.0))
    lmbda: float = checked(0.95, checks.in_interval(0.0, 1.0, low_inclusive=True))  # TD(lambda) targets
    actor_lr: float = checked(1e-2, checks.learning_rate)
    critic_lr: float = checked(1e-3, checks.learning_rate)
    betas: tuple = checked((0.7, 0.95), checks.adam_betas)  # Adam betas of both optimisers
    lr_schedule: str = checked("linear", checks.one_of(LR_SCHEDULES))
    min_lr: float = checked(1e-5, checks.learning_rate)  # end of the linear schedule
    lr_decay: float = checked(0.997, checks.in_interval(0.0, 1.0))  # per iteration, exponential schedule
    critic_passes: int = checked(2, checks.positive_int)  # the reference: 16 passes x 4 minibatches
    critic_minibatches: int = checked(2, checks.positive_int)
    # every_pass: a new random split for each pass; once_per_window: one split, visited in the same
    # order by every pass (DiffRL's reference)
    critic_shuffle: str = checked("every_pass", checks.one_of(("every_pass", "once_per_window")))
    target_tau: float = checked(0.8, checks.in_interval(0.0, 1.0))  # the reference keeps 0.2 of the old target
    max_grad_norm: float | None = checked(1.0, checks.optional_positive)  # clip both gradient norms
    skip_above: float | None = checked(1e6, checks.optional_positive)  # skip steps with a larger norm
    obs_norm: bool = checked(True, checks.boolean)  # running observation normalisation (from_config)
    # observation | state: an asymmetric critic that also reads the physical state and parameters (from_config)
    critic_input: str = checked("observation", checks.one_of(CRITIC_INPUTS))
    # multi-agent envs: each agent's value from every agent's observation (true) or its own (from_config)
    centralised_critic: bool = checked(False, checks.boolean)


class SHACLearner(ActorCriticCheckpoint, Learner):
    """Short-horizon actor-critic.

    On a multi-agent env one parameter-shared actor acts for every agent; the critic gives one
    value per agent (from its own observation, or from every agent's with a centralised critic)
    and the actor loss averages the agents' bootstrapped returns.

    Args:
        env: a batched differentiable env.
        actor: the policy to train, writing ``"action"``.
        critic: a state-value network writing ``"state_value"`` (e.g.
            [`make_critic`][torchrl_diffenvs.modules.make_critic]).
        config: [`SHACConfig`][torchrl_diffenvs.learners.SHACConfig].
        total_env_steps: the budget the learning-rate schedules run over.
        normalizer: the [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] inside the actor
            and the critic to update after every window, if any.
        reset_input: for a batch-unlocked env (TorchRL's ``PendulumEnv``), what to reset it with:
            ``lambda: env.gen_params(batch_size=[N])`` (see [`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector]).
        world: the ranks training together (`torchrl_diffenvs.distributed`); ``env`` is this
            rank's batch.
    """

    name = "shac"
    config_class = SHACConfig
    # DiffRL's critic: init=orthogonal (loss=shac_reference)
    networks = MappingProxyType({"actor": ActorNetworkConfig(), "critic": NetworkConfig()})
    run_defaults = MappingProxyType({"train": {"total_env_steps": 400_000, "checkpoint_interval": 200_000},
                                     "eval": {"interval": 50_000}})
    compiles_windows = True

    def __init__(self, env, actor, critic, config: SHACConfig = SHACConfig(), total_env_steps: int = 1_000_000, *,
                 normalizer: ObservationNormalizer | None = None, reset_input=None, world: World = SINGLE_PROCESS):
        super().__init__(env, config, total_env_steps, reset_input=reset_input, world=world)
        c = config
        self.actor = self.policy = actor
        self.normalizer = normalizer
        self.collector = DiffWindowCollector(env, actor, horizon=c.horizon, reset_input=reset_input)
        self.loss = SHACLoss(actor, critic, gamma=c.gamma, lmbda=c.lmbda)
        self.keys = policy_keys(env)
        self.loss.set_keys(reward=self.keys.reward, value=self.keys.value)  # ("agents", ...) on a multi-agent env
        self.target_updater = self.loss.make_target_updater(tau=c.target_tau)
        self.actor_params = [p for p in actor.parameters() if p.requires_grad]
        self.critic_params = [p for p in self.loss.critic_network.parameters() if p.requires_grad]
        # foreach: one kernel per Adam operation for all tensors (about 2x faster for small nets on CPU)
        self.actor_optim = torch.optim.Adam(self.actor_params, lr=c.actor_lr, betas=c.betas, foreach=True)
        self.critic_optim = torch.optim.Adam(self.critic_params, lr=c.critic_lr, betas=c.betas, foreach=True)
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=c.skip_above)
        self.critic_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=c.skip_above)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        self.schedules = [
            lr_scheduler(optim, c.lr_schedule, lambda: self.total_iterations, min_lr=c.min_lr, decay=c.lr_decay)
            for optim in (self.actor_optim, self.critic_optim)
        ]

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> SHACLearner:
        actor, normalizer = actor_from_config(loss_cfg, env)
        critic = critic_from_config(loss_cfg.critic, env, normalizer, loss_cfg.get("critic_input", "observation"),
                                    loss_cfg.get("centralised_critic", False))
        return cls(env, actor, critic, cls.settings_from(loss_cfg), total_env_steps, normalizer=normalizer,
                   world=world)

    @property
    def steps_per_env(self) -> int:
        return self.config.horizon

    def train_iteration(self) -> dict[str, float]:
        c = self.config
        # 1. collect a window with the graph on
        window = self.collector.rollout()
        # 2. actor step on the bootstrapped return (also writes the critic targets: step 3)
        out = self.loss(window)  # over the finite envs (the collector cut the others' gradient)
        keep = self.loss.finite_envs(window)
        nonfinite = self.nonfinite.update(~keep, self.iteration)
        self.actor_optim.zero_grad(set_to_none=True)
        if out["loss_actor"].requires_grad:  # False when nothing depends on the actions
            out["loss_actor"].backward()
        self.world.average_gradients(self.actor_params)
        actor_info = self.actor_guard.step(self.actor_optim, self.actor_params, loss=out["loss_actor"],
                                           context=self.nonfinite.describe)
        metrics = {key: out[key].item() for key in ("loss_actor", "reward_mean", "value_mean")}
        metrics["nonfinite_envs"] = nonfinite
        # 3. the critic fits the detached window and its TD(lambda) targets (those of the finite envs)
        data = window.detach()
        del window, out  # the graph is spent
        flat = data.select(*self.loss.critic_network.in_keys, self.loss.tensor_keys.value_target)
        if keep.any():
            flat = flat[keep].reshape(-1)
        # 4. critic passes over shuffled minibatches; none when every env is non-finite (the env
        # zeroes their rewards: there is nothing true to fit), each planned step counted as skipped
        critic_losses = []
        if not keep.any():
            for _ in range(c.critic_passes * c.critic_minibatches):
                self.critic_guard.skip(context=self.nonfinite.describe)
        for critic_pass in range(c.critic_passes if keep.any() else 0):
            if critic_pass == 0 or c.critic_shuffle == "every_pass":
                split = torch.randperm(flat.shape[0]).chunk(c.critic_minibatches)
            for batch in split:
                critic_loss = self.loss.critic_loss(flat[batch])["loss_critic"]
                self.critic_optim.zero_grad(set_to_none=True)
                critic_loss.backward()
                self.world.average_gradients(self.critic_params)
                self.critic_guard.step(self.critic_optim, self.critic_params, loss=critic_loss,
                                       context=self.nonfinite.describe)
                critic_losses.append(critic_loss.item())
        # 5. the target critic follows the critic
        self.target_updater.step()
        # 6. observation (and privileged-input) statistics, frozen during the window, move after it
        if self.normalizer is not None:
            self.normalizer.update(self.world.gather(data.get(observation_key_of(self.actor, self.keys.observation))))
        update_privileged_statistics(self.loss.critic_network, data, self.world.gather)
        metrics.update({
            "reward": metrics.pop("reward_mean"),
            "value": metrics.pop("value_mean"),
            "loss_critic": sum(critic_losses) / len(critic_losses) if critic_losses else float("nan"),
            "grad_norm_actor": actor_info["grad_norm"],
            "skipped_actor": self.actor_guard.skipped,
            "skipped_critic": self.critic_guard.skipped,
            "lr_actor": self.actor_optim.param_groups[0]["lr"],
        })
        force = window_contact_force(data)  # envs with contacts report their largest normal force
        if force is not None:
            metrics["contact_force_max"] = force.max().item()
        if self.collector.finished_returns:
            metrics["return"] = sum(self.collector.finished_returns) / len(self.collector.finished_returns)
        # 7. learning-rate schedules
        for schedule in self.schedules:
            schedule.step()
        self.iteration += 1
        return metrics
