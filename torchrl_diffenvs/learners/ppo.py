"""PPO through TorchRL itself: ``Collector`` -> GAE -> ``ClipPPOLoss`` minibatch epochs.

One iteration, in the algorithm's order:

1. collect ``num_envs x rollout_len`` steps with the stochastic policy (TorchRL's ``Collector``,
   no gradients); envs with NaN/inf rewards or observations are left out of the batch (counted
   in ``"nonfinite_envs"`` and named in a warning);
2. ``epochs`` passes, each recomputing GAE advantages with the current critic, then taking
   shuffled minibatch steps (without replacement) on ``loss_objective + loss_critic
   (+ loss_entropy) (+ bounds loss)``, each on the gradient averaged over the ranks and through
   a guard (clip to ``max_grad_norm``; skip NaN/inf); with ``lr_schedule=adaptive`` the learning
   rate follows each step's KL estimate;
3. step the learning-rate schedule (linear to 0 over the budget, or constant);
4. update the observation normaliser (and a privileged critic's input normaliser), so the data
   of an iteration is scored with the statistics it was collected with; hand the new weights to
   the collector.

Data parallel (``world`` with ``K`` ranks): each rank collects and samples its own minibatches of
``minibatch_size``; a step sees the union of the ranks' minibatches (``K x minibatch_size``):
gradients are averaged, advantages standardised and the value normaliser updated with the
statistics of that union, and the adaptive schedule follows the mean KL.
"""
from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from collections.abc import Mapping
from types import MappingProxyType

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.modules import RunningValueNorm
from torchrl.objectives import ClipPPOLoss, ValueEstimators
from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss

from .. import checks
from .._compat import collector_carrier_state, load_collector_carrier
from ..collectors import EpisodeReturnTracker
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys, reward_per_env
from ..modules import (
    CRITIC_INPUTS,
    ObservationNormalizer,
    actor_from_config,
    critic_from_config,
    env_dims,
    observation_key_of,
    update_privileged_statistics,
)
from ..objectives import GradientGuard, NonFiniteEnvMonitor, nonfinite_envs
from ..objectives.nonfinite import next_key, now_and_next
from .base import ActorNetworkConfig, Learner, LearnerConfig, NetworkConfig, checked, load_lr_scheduler, lr_scheduler

__all__ = ["PPOConfig", "PPOLearner"]


@dataclasses.dataclass(frozen=True)
class PPOConfig(LearnerConfig):
    """Settings of [`PPOLearner`][torchrl_diffenvs.learners.PPOLearner] (the ``loss`` section of ``loss=ppo``; its defaults are this class's)."""

    rollout_len: int = checked(32, checks.positive_int)  # an iteration is num_envs x rollout_len env steps
    epochs: int = checked(5, checks.positive_int)  # passes over each batch
    minibatch_size: int = checked(512, checks.positive_int)  # transitions per gradient step
    lr: float = checked(1e-3, checks.learning_rate)
    # linear (to 0 over the budget) | constant | adaptive (rl_games: after each minibatch step the lr is
    # divided by 1.5 when the KL estimate exceeds 2 x kl_threshold, multiplied by 1.5 below half of it)
    lr_schedule: str = checked("linear", checks.one_of(("linear", "constant", "adaptive")))
    kl_threshold: float = checked(0.008, checks.positive)  # adaptive schedule's target KL
    min_lr: float = checked(1e-6, checks.learning_rate)  # adaptive schedule's bounds
    max_lr: float = checked(1e-2, checks.learning_rate)
    gamma: float = checked(0.99, checks.in_interval(0.0, 1.0))
    lmbda: float = checked(0.95, checks.in_interval(0.0, 1.0, low_inclusive=True))  # GAE lambda
    clip_epsilon: float = checked(0.2, checks.positive)
    entropy_coeff: float = checked(0.0, checks.nonnegative)
    critic_coeff: float = checked(0.5, checks.nonnegative)
    clip_value: bool = checked(False, checks.boolean)  # clip the value update to +-clip_epsilon (rl_games)
    # rl_games' bounds loss on the policy's pre-squash mean: bound: sum of max(|loc| - 1.1, 0)^2 per
    # action (soft bounds); regularisation: sum of loc^2; weight bounds_loss_coef (0: off)
    bounds_loss_coef: float = checked(0.0, checks.nonnegative)
    bound_loss_type: str = checked("bound", checks.one_of(("bound", "regularisation")))
    loss_critic_type: str = checked("l2", checks.one_of(("l1", "l2", "smooth_l1")))
    normalize_advantage: bool = checked(True, checks.boolean)
    # rl_games' normalize_value: the critic's targets and predictions are standardised by the running
    # mean / std of the targets before the critic loss (TorchRL's RunningValueNorm, as its MAPPO loss)
    value_normalization: bool = checked(False, checks.boolean)
    max_grad_norm: float | None = checked(1.0, checks.optional_positive)  # clip the global gradient norm
    obs_norm: bool = checked(False, checks.boolean)  # running observation normalisation (from_config)
    # observation | state: an asymmetric critic that also reads the physical state and parameters (from_config)
    critic_input: str = checked("observation", checks.one_of(CRITIC_INPUTS))
    # multi-agent envs: MAPPO (true: each agent's value from every agent's observation, TorchRL's MAPPOLoss)
    # or IPPO (false: from its own observation, IPPOLoss) (from_config)
    centralised_critic: bool = checked(False, checks.boolean)

    @classmethod
    def relation_problems(cls, values, where: str = "") -> list[str]:
        if values["lr_schedule"] == "adaptive" and not values["min_lr"] <= values["lr"] <= values["max_lr"]:
            return [f"{where}lr={values['lr']} must lie in [{where}min_lr, {where}max_lr] = "
                    f"[{values['min_lr']}, {values['max_lr']}] for the adaptive schedule"]
        return []


class PPOLearner(Learner):
    """TorchRL's ``ClipPPOLoss`` with GAE (``make_value_estimator``) on data from TorchRL's ``Collector``.

    On a multi-agent env (``("agents", ...)`` keys): TorchRL's ``MAPPOLoss`` (a centralised
    critic, ``centralised_critic=True``) or ``IPPOLoss`` (each agent's critic reads its own
    observation) with ``MultiAgentGAE``, a parameter-shared actor and per-agent rewards.

    Args:
        env: the batched training env (gradients through it are not used).
        actor: a stochastic policy writing ``"action"`` and its log-probability
            (``make_actor(env, return_log_prob=True)``).
        critic: a state-value network writing ``"state_value"``.
        config: [`PPOConfig`][torchrl_diffenvs.learners.PPOConfig].
        total_env_steps: the budget the learning-rate schedule runs over.
        normalizer: the [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] inside actor
            and critic to update after every iteration, if any.
        world: the ranks training together (`torchrl_diffenvs.distributed`); ``env`` is this
            rank's batch.
    """

    name = "ppo"
    config_class = PPOConfig
    networks = MappingProxyType({  # TanhNormal with a state-independent std
        "actor": ActorNetworkConfig(activation="tanh", layer_norm=False, init_log_std=0.0),
        "critic": NetworkConfig(activation="tanh", layer_norm=False),
    })
    run_defaults = MappingProxyType({"train": {"total_env_steps": 500_000, "checkpoint_interval": 250_000},
                                     "eval": {"interval": 100_000}})
    needs_stochastic_policy = True
    policy_log_prob = True  # the ratio of ClipPPOLoss
    multi_agent_choices = ("mappo", "ippo")  # presets with a centralised / decentralised critic

    def __init__(self, env, actor, critic, config: PPOConfig = PPOConfig(), total_env_steps: int = 1_000_000, *,
                 normalizer: ObservationNormalizer | None = None, world: World = SINGLE_PROCESS):
        super().__init__(env, config, total_env_steps, world=world)
        c = config
        self.actor = self.policy = actor
        self.critic = critic
        self.normalizer = normalizer
        settings = dict(
            clip_epsilon=c.clip_epsilon, entropy_bonus=c.entropy_coeff > 0, entropy_coeff=c.entropy_coeff,
            critic_coeff=c.critic_coeff, loss_critic_type=c.loss_critic_type,
            clip_value=c.clip_value or None,
            # across ranks, a minibatch's advantages are standardised with the statistics of the
            # union of the ranks' minibatches (standardize_advantage); ClipPPOLoss would use its own
            normalize_advantage=c.normalize_advantage and world.size == 1,
        )
        self.keys = keys = policy_keys(env)
        norm = None
        if c.value_normalization:
            norm = AllRanksValueNorm(world, shape=1).to(device=env.device, dtype=env_dims(env, keys.observation)[2])
        if keys.num_agents is not None:
            # MAPPO / IPPO: the same clipped objective; the critic (centralised or not) makes the difference.
            # MultiAgentGAE broadcasts the shared done flags over the agents; advantages are
            # standardised per agent (the agent dim excluded), as TorchRL's losses do
            loss_class = MAPPOLoss if c.centralised_critic else IPPOLoss
            self.loss = loss_class(actor, critic, value_norm=norm, **settings)
            self.loss.set_keys(action=keys.action, sample_log_prob=keys.log_prob, value=keys.value, reward=keys.reward)
            self.loss.make_value_estimator(ValueEstimators.MAGAE, gamma=c.gamma, lmbda=c.lmbda)
        else:
            if norm is not None:
                # TorchRL's MAPPOLoss is ClipPPOLoss plus a value normaliser; with one agent (no agent dim
                # to exclude) and plain GAE it is single-agent PPO with normalised critic targets
                self.loss = MAPPOLoss(actor, critic, value_norm=norm, normalize_advantage_exclude_dims=(), **settings)
            else:
                self.loss = ClipPPOLoss(actor, critic, **settings)
            self.loss.make_value_estimator(ValueEstimators.GAE, gamma=c.gamma, lmbda=c.lmbda)
        self.params = [p for p in self.loss.parameters() if p.requires_grad]
        self.optim = torch.optim.Adam(self.params, lr=c.lr)
        # the adaptive schedule moves the lr itself (in _adapt_lr); the scheduler then keeps it constant
        self.schedule = lr_scheduler(self.optim, "linear" if c.lr_schedule == "linear" else "constant",
                                     lambda: self.total_iterations)
        self.guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(self.num_envs * c.rollout_len, device=env.device),
            sampler=SamplerWithoutReplacement(),
            batch_size=c.minibatch_size,
        )
        self.collector = Collector(
            env, actor, frames_per_batch=self.num_envs * c.rollout_len, total_frames=-1,
            auto_register_policy_transforms=False,  # the policy reads only "observation"
        )
        self._batches = iter(self.collector)
        self.tracker = EpisodeReturnTracker(self.num_envs, env.device, env.reward_key)

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> PPOLearner:
        actor, normalizer = actor_from_config(loss_cfg, env, return_log_prob=True)
        critic = critic_from_config(loss_cfg.critic, env, normalizer, loss_cfg.get("critic_input", "observation"),
                                    loss_cfg.get("centralised_critic", False))
        return cls(env, actor, critic, cls.settings_from(loss_cfg), total_env_steps, normalizer=normalizer,
                   world=world)

    @property
    def steps_per_env(self) -> int:
        return self.config.rollout_len

    def train_iteration(self) -> dict[str, float]:
        # 1. collect (no gradients)
        data = next(self._batches)  # [num_envs, rollout_len]
        finished, _ = self.tracker.update(data)
        finished = [value for value in finished if math.isfinite(value)]
        data, nonfinite = self.finite_envs(data)
        # 2. epochs of minibatch steps, advantages recomputed with the current critic; none when
        # every env is non-finite (the env zeroes their rewards: there is nothing true to learn from)
        sums: dict[str, float] = defaultdict(float)
        updates = 0
        if nonfinite == self.num_envs:
            self.guard.skip(context=self.nonfinite.describe)
        for _ in range(self.config.epochs if nonfinite < self.num_envs else 0):
            with torch.no_grad():
                self.loss.value_estimator(
                    data, params=self.loss.critic_network_params, target_params=self.loss.target_critic_network_params
                )
            if data.numel() != self.buffer.storage.max_size:
                self.buffer.empty()  # a batch without its non-finite envs must not leave older transitions behind
            self.buffer.extend(data.reshape(-1))
            for batch in self.buffer:
                for key, value in self.gradient_step(batch).items():
                    sums[key] += value
                updates += 1
        metrics = {key: value / max(updates, 1) for key, value in sums.items()}
        metrics.update(reward=reward_per_env(data, self.keys.reward).mean().item(), skipped=self.guard.skipped,
                       lr=self.optim.param_groups[0]["lr"], nonfinite_envs=nonfinite)
        if finished:
            metrics["return"] = sum(finished) / len(finished)
        # 3. learning-rate schedule (the adaptive one moved the lr after each step already)
        if self.config.lr_schedule != "adaptive":
            self.schedule.step()
        # 4. normaliser statistics, then the collector gets the new weights
        if self.normalizer is not None:
            self.normalizer.update(self.world.gather(data.get(observation_key_of(self.actor, self.keys.observation))))
        update_privileged_statistics(self.critic, data, self.world.gather)
        self.collector.update_policy_weights_()
        self.iteration += 1
        return metrics

    def finite_envs(self, data):
        """``(data of the finite envs, how many were left out)``: the envs of a batch ``[N, T]``
        whose rewards and network inputs (now and next) are all finite, and that nothing flags as
        non-finite. With no finite env left, the batch is kept whole and the iteration makes no
        update (a skip that counts towards the guard's limit).

        With several ranks, every rank keeps the same number of envs (their minibatch steps and
        exchanges must match): a rank with fewer non-finite envs than another also leaves out its
        last finite ones for this iteration; when some rank has no finite env, every rank keeps
        its batch whole (the averaged NaN gradient skips the steps everywhere).
        """
        inputs = now_and_next(dict.fromkeys([*self.actor.in_keys, *self.critic.in_keys]))
        bad = nonfinite_envs(data, [next_key(self.keys.reward), *inputs])
        count = self.nonfinite.update(bad, self.iteration)
        most = count
        if self.world.size > 1:
            most = int(self.world.gather(bad.sum().reshape(1)).max())
        if 0 < most < bad.numel():
            drop = bad.clone()
            if most > count:  # the same number of envs as the rank that lost the most
                drop[(~bad).nonzero().flatten()[count - most:]] = True
            data = data[~drop]
        return data, count

    def gradient_step(self, batch) -> dict[str, float]:
        """One guarded optimiser step on a minibatch (with advantages and value targets), the
        gradient averaged over the ranks; returns the step's losses and statistics."""
        c = self.config
        if c.normalize_advantage and self.world.size > 1:
            key = self.loss.tensor_keys.advantage
            per_agent = (-2,) if self.keys.num_agents is not None else ()
            batch.set(key, standardize_advantage(batch.get(key), self.world, per_agent))
        out = self.loss(batch)
        total = out["loss_objective"] + out["loss_critic"]
        if "loss_entropy" in out.keys():
            total = total + out["loss_entropy"]
        stats = {}
        if c.bounds_loss_coef > 0:
            bounds = self.bounds_loss(batch)
            total = total + c.bounds_loss_coef * bounds
            stats["loss_bounds"] = bounds.item()
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        self.world.average_gradients(self.params)
        # the loss too: a NaN that does not reach the gradient (a NaN advantage) must also skip
        stats["grad_norm"] = self.guard.step(self.optim, self.params, loss=total,
                                             context=self.nonfinite.describe)["grad_norm"]
        for key in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "clip_fraction", "kl_approx"):
            if key in out.keys():
                stats[key] = out[key].detach().float().mean().item()
        if c.lr_schedule == "adaptive":
            self._adapt_lr(self.world.mean(stats["kl_approx"]))
        return stats

    def bounds_loss(self, batch) -> torch.Tensor:
        """rl_games' bounds loss on the pre-squash mean ``loc`` of the policy, averaged over the batch."""
        loc = self.actor.module[0](batch.select(*self.actor.module[0].in_keys).clone()).get(self.keys.loc)
        if self.config.bound_loss_type == "regularisation":
            return loc.pow(2).sum(-1).mean()
        soft_bound = 1.1
        return ((loc - soft_bound).clamp_min(0).pow(2) + (loc + soft_bound).clamp_max(0).pow(2)).sum(-1).mean()

    def _adapt_lr(self, kl: float) -> None:
        """rl_games' adaptive schedule: lr / 1.5 when KL > 2 x threshold, x 1.5 when KL < threshold / 2."""
        c = self.config
        for group in self.optim.param_groups:
            if kl > 2.0 * c.kl_threshold:
                group["lr"] = max(group["lr"] / 1.5, c.min_lr)
            elif kl < 0.5 * c.kl_threshold:
                group["lr"] = min(group["lr"] * 1.5, c.max_lr)

    def state_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "actor": self.actor.state_dict(),  # the normaliser's statistics included
            "critic": self.critic.state_dict(),
            "loss": self.loss.state_dict(),
            "optimizer": self.optim.state_dict(),
            "schedule": self.schedule.state_dict(),
            "guard": self.guard.state_dict(),
            "tracker": self.tracker.state_dict(),
            "collector": self.collector.state_dict(),
            "carrier": collector_carrier_state(self.collector),
            # the sampler draws the next epoch's permutation as soon as one runs out
            "sampler": self.buffer.sampler.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.iteration = int(state["iteration"])
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.loss.load_state_dict(state["loss"])
        self.optim.load_state_dict(state["optimizer"])
        if self.config.lr_schedule == "adaptive":  # the optimiser's state holds the adapted lr
            self.schedule.load_state_dict(state["schedule"])
        else:
            load_lr_scheduler(self.schedule, state["schedule"])
        self.guard.load_state_dict(state["guard"])
        self.tracker.load_state_dict(state["tracker"])
        self.collector.load_state_dict(state["collector"])
        load_collector_carrier(self.collector, state["carrier"])
        self.buffer.sampler.load_state_dict(state["sampler"])

    def close(self) -> None:
        self.collector.shutdown(close_env=False)


def standardize_advantage(advantage: torch.Tensor, world: World, exclude_dims: tuple[int, ...] = ()) -> torch.Tensor:
    """``(a - mean) / std`` with the mean and (unbiased) std of all ranks' minibatches together:
    TorchRL's ``ClipPPOLoss(normalize_advantage=True)`` formula, on the union of the ranks' data.
    ``exclude_dims`` keep their own statistics (``(-2,)``: per agent, as TorchRL's MAPPO/IPPO losses)."""
    union = world.gather(advantage)
    excluded = {dim % union.ndim for dim in exclude_dims}
    dims = [dim for dim in range(union.ndim) if dim not in excluded]
    mean, std = union.mean(dims, keepdim=True), union.std(dims, keepdim=True)
    return (advantage - mean) / std.clamp_min(torch.finfo(torch.float).resolution)


class AllRanksValueNorm(RunningValueNorm):
    """TorchRL's ``RunningValueNorm`` whose statistics follow the value targets of every rank's
    minibatch, so that the ranks' normalisers stay identical (one process: unchanged)."""

    def __init__(self, world: World, **kwargs):
        super().__init__(**kwargs)
        self.world = world

    def update(self, value_target: torch.Tensor) -> None:
        super().update(self.world.gather(value_target))
