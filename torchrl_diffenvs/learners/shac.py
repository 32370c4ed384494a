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

from .. import checks
from ..distributed import SINGLE_PROCESS, World
from ..modules import CRITIC_INPUTS, ObservationNormalizer, actor_from_config, critic_from_config
from ..objectives import SHACLoss
from .base import LR_SCHEDULES, ActorNetworkConfig, LearnerConfig, NetworkConfig, checked
from .short_horizon import ShortHorizonLearner

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


class SHACLearner(ShortHorizonLearner):
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
        loss = SHACLoss(actor, critic, gamma=config.gamma, lmbda=config.lmbda)
        super().__init__(env, actor, loss, config, total_env_steps, horizon=config.horizon, normalizer=normalizer,
                         reset_input=reset_input, world=world, critic_max_grad_norm=config.max_grad_norm)
        self.target_updater = self.loss.make_target_updater(tau=config.target_tau)

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> SHACLearner:
        actor, normalizer = actor_from_config(loss_cfg, env)
        critic = critic_from_config(loss_cfg.critic, env, normalizer, loss_cfg.get("critic_input", "observation"),
                                    loss_cfg.get("centralised_critic", False))
        return cls(env, actor, critic, cls.settings_from(loss_cfg), total_env_steps, normalizer=normalizer,
                   world=world)

    def _after_critic_fit(self) -> None:
        self.target_updater.step()  # 5. the target critic follows the critic
