"""BPTT and SHAC: gradients through the differentiable env, via the shared :class:`GradientTrainer`."""
from __future__ import annotations

from ...collectors import DiffWindowCollector
from ...modules import make_critic
from ...objectives import BPTTLoss, SHACLoss
from ...trainers import GradientTrainer
from .base import Learner, make_policy_from_config, network_kwargs

__all__ = ["BPTTLearner", "SHACLearner"]


class _GradientLearner(Learner):
    """Windows of ``horizon`` steps with the graph on (:class:`DiffWindowCollector`), one guarded
    actor step per window (:class:`GradientTrainer`); SHAC adds its critic fitting."""

    def __init__(self, cfg, env, total_env_steps: int):
        super().__init__(cfg, env, total_env_steps)
        c = cfg.loss
        self.actor, self.normalizer = make_policy_from_config(c, env)
        self.policy = self.actor
        self.loss = self._make_loss(c, env)
        self.collector = DiffWindowCollector(env, self.actor, horizon=int(c.horizon))
        kwargs = dict(
            actor_lr=float(c.actor_lr),
            betas=tuple(float(b) for b in c.betas),
            lr_schedule=str(c.lr_schedule),
            min_lr=float(c.min_lr),
            lr_decay=float(c.lr_decay),
            total_iterations=self.total_iterations,
            max_grad_norm=c.max_grad_norm,
            skip_above=c.skip_above,
            normalizer=self.normalizer,
        )
        if isinstance(self.loss, SHACLoss):
            kwargs.update(
                critic_lr=float(c.critic_lr),
                critic_passes=int(c.critic_passes),
                critic_minibatches=int(c.critic_minibatches),
                target_tau=float(c.target_tau),
            )
        self.trainer = GradientTrainer(self.collector, self.loss, **kwargs)

    def _make_loss(self, c, env):
        raise NotImplementedError

    @property
    def env_steps_per_iteration(self) -> int:
        return self.env.num_envs * int(self.cfg.loss.horizon)

    def train_iteration(self) -> dict[str, float]:
        m = self.trainer.step()
        metrics = {
            "reward": m["reward_mean"],
            "loss_actor": m["loss_actor"],
            "grad_norm_actor": m["actor_grad_norm"],
            "skipped_actor": m["actor_skipped"],
            "lr_actor": m["actor_lr"],
        }
        if "episode_reward" in m:
            metrics["return"] = m["episode_reward"]
        if "loss_critic" in m:
            metrics["loss_critic"] = m["loss_critic"]
            metrics["skipped_critic"] = m["critic_skipped"]
        return metrics

    def state_dict(self) -> dict:
        return self.trainer.state_dict()  # loss (actor, critic, target), optimisers, schedules, collector

    def load_state_dict(self, state: dict) -> None:
        self.trainer.load_state_dict(state)


class BPTTLearner(_GradientLearner):
    """Back-propagation through time over short windows with carried env state (Brax's APG)."""

    name = "bptt"

    def _make_loss(self, c, env):
        return BPTTLoss(self.actor, gamma=float(c.gamma))


class SHACLearner(_GradientLearner):
    """Short-horizon actor-critic (Xu et al. 2022)."""

    name = "shac"

    def _make_loss(self, c, env):
        critic = make_critic(env, **network_kwargs(c.critic), normalizer=self.normalizer).to(env.device)
        return SHACLoss(self.actor, critic, gamma=float(c.gamma), lmbda=float(c.lmbda))
