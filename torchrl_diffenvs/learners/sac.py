"""SAC through TorchRL itself: ``Collector`` -> replay buffer -> ``SACLoss`` + ``SoftUpdate``.

One iteration, in the algorithm's order:

1. collect ``num_envs x rollout_len`` steps (uniformly random actions for the first
   ``init_random_frames``) and add them to the replay buffer, except those of the envs with
   NaN/inf rewards or observations (counted in ``"nonfinite_envs"`` and named in a warning; when
   every env is non-finite, the gradient steps of the iteration are skipped);
2. once ``init_random_frames`` steps are in, ``round(utd_ratio x steps collected)`` gradient
   steps on sampled minibatches: actor, both Q-networks and the temperature (separate Adam
   optimisers; actor and Q-networks through a guard), each followed by a soft update of the
   target Q-networks;
3. hand the new weights to the collector.

Data parallel (``world`` with ``K`` ranks): each rank keeps its own replay buffer and samples its
own minibatches of ``batch_size``; every gradient step averages the gradients (actor, Q-networks,
temperature) over the ranks, so a step sees ``K x batch_size`` transitions. ``utd_ratio`` and
``init_random_frames`` count the env steps of all ranks together.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import MappingProxyType

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import SACLoss, SoftUpdate

from .. import checks
from .._compat import collector_carrier_state, load_collector_carrier
from ..collectors import EpisodeReturnTracker
from ..distributed import SINGLE_PROCESS, World
from ..modules import CRITIC_INPUTS, actor_from_config, qvalue_from_config
from ..objectives import GradientGuard, NonFiniteEnvMonitor, nonfinite_envs
from .base import ActorNetworkConfig, Learner, LearnerConfig, NetworkConfig, checked

__all__ = ["SACConfig", "SACLearner"]



@dataclasses.dataclass(frozen=True)
class SACConfig(LearnerConfig):
    """Settings of [`SACLearner`][torchrl_diffenvs.learners.SACLearner] (the ``loss`` section of ``loss=sac``; its defaults are this class's)."""

    rollout_len: int = checked(1, checks.positive_int)  # an iteration is num_envs x rollout_len env steps
    init_random_frames: int = checked(2000, checks.nonnegative_int)  # random actions before learning
    buffer_size: int = checked(100_000, checks.positive_int)  # replay capacity (transitions)
    batch_size: int = checked(256, checks.positive_int)  # transitions per gradient step
    utd_ratio: float = checked(0.5, checks.positive)  # gradient steps per collected env step
    lr: float = checked(3e-4, checks.learning_rate)  # actor and Q-networks
    alpha_lr: float = checked(1e-3, checks.learning_rate)  # temperature
    alpha_init: float = checked(0.1, checks.positive)
    gamma: float = checked(0.99, checks.in_interval(0.0, 1.0))
    tau: float = checked(0.005, checks.in_interval(0.0, 1.0))  # Polyak rate of the target Q-networks
    loss_function: str = checked("l2", checks.one_of(("l1", "l2", "smooth_l1")))
    max_grad_norm: float | None = checked(None, checks.optional_positive)  # clip each network's gradient norm
    save_replay_buffer: bool = checked(True, checks.boolean)  # checkpoints hold the buffer (exact resume)
    # observation | state: Q-networks that also read the physical state and parameters (from_config)
    critic_input: str = checked("observation", checks.one_of(CRITIC_INPUTS))

    @classmethod
    def relation_problems(cls, values, where: str = "") -> list[str]:
        if values["buffer_size"] < values["batch_size"]:
            return [f"{where}buffer_size={values['buffer_size']} is smaller than {where}batch_size={values['batch_size']}"]
        return []


class SACLearner(Learner):
    """TorchRL's ``SACLoss`` (two Q-networks, learned temperature) with a replay buffer and
    ``SoftUpdate`` target networks, on data from TorchRL's ``Collector``.

    Args:
        env: the batched training env (gradients through it are not used).
        actor: a stochastic policy writing ``"action"`` (``make_actor(env)``).
        qvalue: ``Q(observation, action)`` writing ``"state_action_value"``, or with
            ``critic_input="state"`` also reading the state and parameters
            ([`make_qvalue`][torchrl_diffenvs.modules.make_qvalue]); the replay buffer keeps what it reads.
        config: [`SACConfig`][torchrl_diffenvs.learners.SACConfig].
        total_env_steps: the training budget (SAC's learning rates are constant).
        world: the ranks training together (`torchrl_diffenvs.distributed`); ``env`` is this
            rank's batch.
    """

    name = "sac"
    config_class = SACConfig
    networks = MappingProxyType({  # the actor: TanhNormal with a state-independent std; Q(observation, action)
        "actor": ActorNetworkConfig(activation="relu", layer_norm=False, init_log_std=0.0),
        "qvalue": NetworkConfig(activation="relu", layer_norm=False),
    })
    # SAC learns per gradient step, not per env step: few envs, more updates per step
    run_defaults = MappingProxyType({"env": {"num_envs": 8},
                                     "train": {"total_env_steps": 15_000, "checkpoint_interval": 5_000},
                                     "eval": {"interval": 5_000}})
    unsupported_settings = MappingProxyType({"obs_norm": "the replay buffer would mix statistics"})
    needs_stochastic_policy = True
    supports_multi_agent = False

    def __init__(self, env, actor, qvalue, config: SACConfig = SACConfig(), total_env_steps: int = 1_000_000, *,
                 world: World = SINGLE_PROCESS):
        super().__init__(env, config, total_env_steps, world=world)
        c = config
        self.actor = self.policy = actor
        self.loss = SACLoss(
            actor, qvalue, num_qvalue_nets=2, loss_function=c.loss_function, alpha_init=c.alpha_init,
            action_spec=env.action_spec_unbatched,  # target entropy -action_dim
            delay_qvalue=True,
        )
        self.loss.make_value_estimator(gamma=c.gamma)
        self.target_updater = SoftUpdate(self.loss, tau=c.tau)
        self.actor_params = list(self.loss.actor_network_params.values(True, True))
        self.qvalue_params = list(self.loss.qvalue_network_params.values(True, True))
        self.actor_optim = torch.optim.Adam(self.actor_params, lr=c.lr)
        self.qvalue_optim = torch.optim.Adam(self.qvalue_params, lr=c.lr)
        self.alpha_optim = torch.optim.Adam([self.loss.log_alpha], lr=c.alpha_lr)
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.qvalue_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        # what SACLoss reads (the Q-networks' inputs, now and next); the rest of a transition stays out
        observed = [key for key in qvalue.in_keys if key != "action"]
        self.buffer_keys = [*observed, "action", *(("next", *(k if isinstance(k, tuple) else (k,))) for k in observed),
                            ("next", "reward"), ("next", "done"), ("next", "terminated")]
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(c.buffer_size, device=env.device), batch_size=c.batch_size)
        self.updates_per_iteration = max(1, round(c.utd_ratio * self.env_steps_per_iteration))
        self.collector = Collector(
            env, actor, frames_per_batch=self.num_envs * c.rollout_len, total_frames=-1,
            init_random_frames=-(-c.init_random_frames // world.size),  # this rank's share
            auto_register_policy_transforms=False,  # the policy reads only "observation"
        )
        self._batches = iter(self.collector)
        self.tracker = EpisodeReturnTracker(self.num_envs, env.device)
        self.frames = 0

    @classmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> SACLearner:
        if loss_cfg.get("obs_norm"):
            raise ValueError("loss=sac does not support obs_norm (the replay buffer would mix statistics)")
        actor, _ = actor_from_config(loss_cfg, env)
        qvalue = qvalue_from_config(loss_cfg.qvalue, env, loss_cfg.get("critic_input", "observation"))
        return cls(env, actor, qvalue, cls.settings_from(loss_cfg), total_env_steps, world=world)

    @property
    def steps_per_env(self) -> int:
        return self.config.rollout_len

    def train_iteration(self) -> dict[str, float]:
        c = self.config
        # 1. collect into the replay buffer
        data = next(self._batches)  # [num_envs, rollout_len]
        finished, _ = self.tracker.update(data)
        finished = [value for value in finished if math.isfinite(value)]
        self.frames += data.numel() * self.world.size  # all ranks' env steps
        bad = nonfinite_envs(data, self.buffer_keys)
        nonfinite = self.nonfinite.update(bad, self.iteration)
        any_finite = not bool(bad.all())
        data = data[~bad]  # the replay buffer keeps finite transitions only
        if any_finite:
            self.buffer.extend(data.reshape(-1).select(*self.buffer_keys))
        metrics = {"reward": data.get(("next", "reward")).mean().item(), "nonfinite_envs": nonfinite}
        if finished:
            metrics["return"] = sum(finished) / len(finished)
        # 2. gradient steps on sampled minibatches, each followed by the target update
        if not any_finite:  # every env non-finite: no update, and a skip towards the guards' limit
            self.actor_guard.skip(self.nonfinite.describe)
            self.qvalue_guard.skip(self.nonfinite.describe)
        ready = any_finite and self.frames >= c.init_random_frames and len(self.buffer) >= c.batch_size
        if self.world.size > 1:  # the ranks' gradient steps meet in exchanges: all of them step, or none
            ready = self.world.mean(float(ready)) == 1.0
        if ready:
            sums = dict.fromkeys(("loss_actor", "loss_qvalue", "loss_alpha", "grad_norm_actor", "grad_norm_qvalue",
                                  "entropy"), 0.0)
            for _ in range(self.updates_per_iteration):
                for key, value in self.gradient_step(self.buffer.sample()).items():
                    sums[key] += value
            metrics.update({key: value / self.updates_per_iteration for key, value in sums.items()})
            metrics["alpha"] = self.loss.log_alpha.exp().item()
        metrics["skipped_actor"] = self.actor_guard.skipped
        metrics["skipped_qvalue"] = self.qvalue_guard.skipped
        # 3. the collector gets the new weights
        self.collector.update_policy_weights_()
        self.iteration += 1
        return metrics

    def gradient_step(self, batch) -> dict[str, float]:
        """One step of the actor, the Q-networks and the temperature on a minibatch, the gradients
        averaged over the ranks, then the soft update of the target Q-networks."""
        out = self.loss(batch)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        for optim in (self.actor_optim, self.qvalue_optim, self.alpha_optim):
            optim.zero_grad(set_to_none=True)
        total.backward()
        self.world.average_gradients(self.actor_params + self.qvalue_params + [self.loss.log_alpha])
        stats = {
            "grad_norm_actor": self.actor_guard.step(self.actor_optim, self.actor_params, loss=out["loss_actor"],
                                                     context=self.nonfinite.describe)["grad_norm"],
            "grad_norm_qvalue": self.qvalue_guard.step(self.qvalue_optim, self.qvalue_params, loss=out["loss_qvalue"],
                                                       context=self.nonfinite.describe)["grad_norm"],
        }
        alpha_grad = self.loss.log_alpha.grad
        if alpha_grad is None or torch.isfinite(alpha_grad).all():  # a NaN temperature would never recover
            self.alpha_optim.step()
        self.target_updater.step()
        stats.update({key: out[key].detach().float().mean().item()
                      for key in ("loss_actor", "loss_qvalue", "loss_alpha", "entropy")})
        return stats

    def state_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "loss": self.loss.state_dict(),  # actor, Q-networks, their targets, log_alpha
            "actor_optimizer": self.actor_optim.state_dict(),
            "qvalue_optimizer": self.qvalue_optim.state_dict(),
            "alpha_optimizer": self.alpha_optim.state_dict(),
            "actor_guard": self.actor_guard.state_dict(),
            "qvalue_guard": self.qvalue_guard.state_dict(),
            "tracker": self.tracker.state_dict(),
            "collector": self.collector.state_dict(),
            "carrier": collector_carrier_state(self.collector),
            "frames": self.frames,
            "buffer": self.buffer.state_dict() if self.config.save_replay_buffer else None,
        }

    def load_state_dict(self, state: dict) -> None:
        self.iteration = int(state["iteration"])
        self.loss.load_state_dict(state["loss"])
        self.actor_optim.load_state_dict(state["actor_optimizer"])
        self.qvalue_optim.load_state_dict(state["qvalue_optimizer"])
        self.alpha_optim.load_state_dict(state["alpha_optimizer"])
        self.actor_guard.load_state_dict(state["actor_guard"])
        self.qvalue_guard.load_state_dict(state["qvalue_guard"])
        self.tracker.load_state_dict(state["tracker"])
        self.collector.load_state_dict(state["collector"])
        load_collector_carrier(self.collector, state["carrier"])
        self.frames = int(state["frames"])
        if state["buffer"] is not None:
            self.buffer.load_state_dict(state["buffer"])

    def close(self) -> None:
        self.collector.shutdown(close_env=False)
