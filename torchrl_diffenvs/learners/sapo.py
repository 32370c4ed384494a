"""SAPO (Xing et al., ICLR 2025, "Stabilizing reinforcement learning in differentiable
multiphysics simulation"; reference: ``etaoxing/mineral``, ``agents/diffrl/shac.py`` with
``cfgs/agent/DFlexAntSAPO.yaml``): SHAC with maximum entropy.

One iteration:

1. collect a window ``[N, H]`` with the graph on; the actor (a tanh-squashed normal with a
   state-dependent standard deviation,
   [`make_sapo_actor`][torchrl_diffenvs.modules.make_sapo_actor]) writes the log-probability of
   every action it samples;
2. actor step on the soft bootstrapped return ([`SAPOLoss`][torchrl_diffenvs.objectives.SAPOLoss]:
   rewards plus ``alpha`` times the entropy estimate, bootstrapped by the mean of the two
   critics), one guarded AdamW step clipped at ``max_grad_norm``;
3. temperature step: ``log_alpha`` on the loss's ``alpha_loss`` of the window's entropy
   (AdamW, clipped at ``max_grad_norm``);
4. soft TD(lambda) critic targets with the new temperature, bootstrapped by the minimum of the
   two critics;
5. ``critic_passes`` x ``critic_minibatches`` guarded AdamW steps of both critics (no target critic);
6. update the observation normaliser; step the learning-rate schedules of actor and critics.

The iteration is [`ShortHorizonLearner`][torchrl_diffenvs.learners.ShortHorizonLearner]'s (in
``learners/short_horizon.py``, with SHAC and AHAC); SAPO fills in its hooks: the temperature step
after the actor's, the soft critic targets with the new temperature.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

import torch

from .. import checks
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys
from ..modules import ObservationNormalizer, SquashedNormalActor, env_dims, make_sapo_actor, network_kwargs
from ..objectives import GradientGuard, SAPOLoss, TwinCritic
from .base import LR_SCHEDULES, LearnerConfig, NetworkConfig, checked
from .short_horizon import CRITIC_SHUFFLES, TwinCriticLearner, twin_critic_from_config

# the policy (SquashedNormalActor, make_sapo_actor) lives with the other networks in modules/actors.py
__all__ = ["SAPOConfig", "SAPOLearner"]


@dataclasses.dataclass(frozen=True)
class SAPOConfig(LearnerConfig):
    """Settings of [`SAPOLearner`][torchrl_diffenvs.learners.SAPOLearner] (the keys of ``loss=sapo``); defaults are the
    reference's (``DFlexAntSHAC2.yaml`` + ``DFlexAntSAPO.yaml``)."""

    horizon: int = checked(32, checks.positive_int)  # window length H: an iteration is N x H env steps
    gamma: float = checked(0.99, checks.in_interval(0.0, 1.0))
    lmbda: float = checked(0.95, checks.in_interval(0.0, 1.0, low_inclusive=True))  # TD(lambda) targets
    actor_lr: float = checked(2e-3, checks.learning_rate)
    critic_lr: float = checked(5e-4, checks.learning_rate)
    alpha_lr: float = checked(5e-3, checks.learning_rate)  # the temperature's (constant)
    betas: tuple = checked((0.7, 0.95), checks.adam_betas)  # AdamW betas of the three optimisers
    weight_decay: float = checked(0.01, checks.nonnegative)  # AdamW's (torch's default, which the reference keeps)
    lr_schedule: str = checked("linear", checks.one_of(LR_SCHEDULES))  # actor and critics
    min_lr: float = checked(1e-5, checks.learning_rate)  # end of the linear schedule
    lr_decay: float = checked(0.997, checks.in_interval(0.0, 1.0))  # per iteration, exponential schedule
    critic_passes: int = checked(16, checks.positive_int)
    critic_minibatches: int = checked(4, checks.positive_int)
    critic_shuffle: str = checked("in_order", checks.one_of(CRITIC_SHUFFLES))  # minibatch order (learners/short_horizon.py)
    max_grad_norm: float | None = checked(0.5, checks.optional_positive)  # clips actor, critics and temperature
    skip_above: float | None = checked(1e6, checks.optional_positive)  # skip steps with a larger norm
    obs_norm: bool = checked(True, checks.boolean)  # running observation normalisation (from_config)
    init_alpha: float = checked(1.0, checks.positive)  # initial temperature
    target_entropy_scale: float = checked(0.5, checks.positive)  # target entropy = -scale * |A|
    entropy_offset: bool = checked(True, checks.boolean)  # entropy term (e + |target|) / 2
    entropy_scale: bool = checked(True, checks.boolean)  # entropy term / |target| (and the temperature step x |target|)
    min_log_std: float = checked(-5.0, checks.in_interval(-20.0, 20.0))  # the actor's log-std is clamped to this range
    max_log_std: float = checked(2.0, checks.in_interval(-20.0, 20.0))
    orthogonal_gain: float = checked(1.0, checks.positive)  # gain of init=orthogonal in the network sections

    @classmethod
    def relation_problems(cls, values: Mapping, where: str = "") -> list[str]:
        if values["min_log_std"] >= values["max_log_std"]:
            return [f"{where}min_log_std={values['min_log_std']!r} must be < {where}max_log_std="
                    f"{values['max_log_std']!r}"]
        return []


# ---------------------------------------------------------------------- the learner
class SAPOLearner(TwinCriticLearner):
    """Soft analytic policy optimisation.

    Args:
        env: a batched differentiable single-agent env.
        actor: a policy writing ``"action"`` and ``"action_log_prob"`` when sampling
            ([`make_sapo_actor`][torchrl_diffenvs.modules.make_sapo_actor]).
        critic: a [`TwinCritic`][torchrl_diffenvs.objectives.TwinCritic].
        config: [`SAPOConfig`][torchrl_diffenvs.learners.SAPOConfig].
        total_env_steps: the budget the learning-rate schedules run over.
        normalizer: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
        reset_input: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
        world: as [`SHACLearner`][torchrl_diffenvs.learners.SHACLearner].
    """

    name = "sapo"
    config_class = SAPOConfig
    # the reference's: 128-64-32 SiLU + LayerNorm actor (its std is state-dependent: no init_log_std),
    # orthogonal initialisation
    networks = MappingProxyType({
        "actor": NetworkConfig(hidden=(128, 64, 32), activation="silu", init="orthogonal"),
        "critic": NetworkConfig(activation="silu", init="orthogonal"),
    })
    run_defaults = MappingProxyType({"train": {"total_env_steps": 400_000, "checkpoint_interval": 200_000},
                                     "eval": {"interval": 50_000}})

    def __init__(self, env, actor, critic: TwinCritic, config: SAPOConfig = SAPOConfig(),
                 total_env_steps: int = 1_000_000, *, normalizer: ObservationNormalizer | None = None,
                 reset_input=None, world: World = SINGLE_PROCESS):
        c = config
        action_dim = env_dims(env, policy_keys(env).observation)[1]
        loss = SAPOLoss(actor, critic, action_dim=action_dim, gamma=c.gamma, lmbda=c.lmbda, init_alpha=c.init_alpha,
                        target_entropy_scale=c.target_entropy_scale, entropy_offset=c.entropy_offset,
                        entropy_scale=c.entropy_scale)
        super().__init__(env, actor, loss, config, total_env_steps, horizon=c.horizon, normalizer=normalizer,
                         reset_input=reset_input, world=world, optimizer=torch.optim.AdamW,
                         optimizer_kwargs={"weight_decay": c.weight_decay}, critic_max_grad_norm=c.max_grad_norm)
        self.loss.set_keys(log_prob=self.keys.log_prob)  # (the reward and value keys: set by the skeleton)
        # the reference's temperature optimiser is the actor's class (AdamW) with its own settings
        self.alpha_optim = torch.optim.AdamW([self.loss.log_alpha], lr=c.alpha_lr, betas=c.betas,
                                             weight_decay=c.weight_decay)
        self.alpha_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)

    @classmethod
    def policy_from_config(cls, loss_cfg: Mapping, env) -> SquashedNormalActor:
        return cls._policy_and_normalizer(loss_cfg, env, cls.settings_from(loss_cfg))[0]

    @staticmethod
    def _policy_and_normalizer(loss_cfg: Mapping, env, config: SAPOConfig
                               ) -> tuple[SquashedNormalActor, ObservationNormalizer | None]:
        """The policy of a ``loss=sapo`` section (and its observation normaliser): what a
        checkpoint's ``"policy"`` state loads into (evaluation)."""
        normalizer = None
        if config.obs_norm:
            observation_dim, _, dtype = env_dims(env, policy_keys(env).observation)
            normalizer = ObservationNormalizer(observation_dim, dtype=dtype).to(env.device)
        actor_kwargs = network_kwargs(loss_cfg["actor"])
        actor_kwargs.pop("init_log_std", None)  # the std is state-dependent
        actor = make_sapo_actor(env, **actor_kwargs, orthogonal_gain=config.orthogonal_gain,
                                min_log_std=config.min_log_std, max_log_std=config.max_log_std,
                                normalizer=normalizer).to(env.device)
        return actor, normalizer

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> SAPOLearner:
        config = cls.settings_from(loss_cfg)
        actor, normalizer = cls._policy_and_normalizer(loss_cfg, env, config)
        critic = twin_critic_from_config(loss_cfg.critic, env, normalizer, orthogonal_gain=config.orthogonal_gain)
        return cls(env, actor, critic, config, total_env_steps, normalizer=normalizer, world=world)

    def update_temperature(self, entropy: torch.Tensor | float) -> dict[str, float]:
        """One guarded AdamW step of ``log_alpha`` on the loss's ``alpha_loss(entropy)``
        (``entropy``: the window's mean of ``-log pi``), the gradient averaged over the ranks."""
        loss = self.loss.alpha_loss(entropy)
        self.alpha_optim.zero_grad(set_to_none=True)
        loss.backward()
        self.world.average_gradients([self.loss.log_alpha])
        info = self.alpha_guard.step(self.alpha_optim, [self.loss.log_alpha], loss=loss)
        return {"loss_alpha": loss.item(), "grad_norm_alpha": info["grad_norm"]}

    def _after_actor_step(self, window, out) -> dict[str, float]:
        entropy = self.world.mean(out["entropy"].item())  # every rank steps the same temperature
        metrics = {"entropy": entropy, "alpha_window": out["alpha"].item()}
        metrics.update(self.update_temperature(entropy))
        metrics["alpha"] = self.loss.alpha.item()
        return metrics

    def _critic_targets(self, data) -> None:
        self.loss.compute_value_targets(data)  # with the temperature after its step (the reference's order)

    def state_dict(self) -> dict:
        return {**super().state_dict(), "alpha_optimizer": self.alpha_optim.state_dict(),
                "alpha_guard": self.alpha_guard.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)  # the loss's state holds log_alpha
        self.alpha_optim.load_state_dict(state["alpha_optimizer"])
        self.alpha_guard.load_state_dict(state["alpha_guard"])
