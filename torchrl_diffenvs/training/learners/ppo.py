"""PPO through TorchRL itself: ``Collector`` -> GAE -> ``ClipPPOLoss`` minibatch epochs."""
from __future__ import annotations

from collections import defaultdict

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from ...modules import make_critic
from ...objectives import GradientGuard
from ..checkpoint import tensordict_from_state, tensordict_to_state
from .base import EpisodeReturnTracker, Learner, make_policy_from_config, network_kwargs

__all__ = ["PPOLearner", "collector_carrier_state", "load_collector_carrier"]


def collector_carrier_state(collector: Collector) -> dict | None:
    """The env TensorDict a TorchRL ``Collector`` will step from next, as plain tensors.

    TorchRL 0.14's ``Collector.state_dict`` leaves out the in-flight env state ("not generally
    serializable"); our envs keep their whole state in that TensorDict, so saving it lets a
    resumed run continue the same episodes. It lives in the private ``_carrier`` attribute:
    ``None`` (resume then starts fresh episodes) if a future TorchRL renames it.
    """
    carrier = getattr(collector, "_carrier", None)
    if carrier is None:
        return None
    return tensordict_to_state(carrier.exclude("collector"))


def load_collector_carrier(collector: Collector, state: dict | None) -> None:
    """Restores :func:`collector_carrier_state` (no-op for ``None``)."""
    if state is not None and getattr(collector, "_carrier", None) is not None:
        collector._carrier.update(tensordict_from_state(state, device=collector._carrier.device))


class PPOLearner(Learner):
    """TorchRL's ``ClipPPOLoss`` with GAE (``make_value_estimator``) on data from TorchRL's ``Collector``.

    One iteration: collect ``num_envs x rollout_len`` steps with the stochastic policy; then
    ``epochs`` passes, each recomputing GAE advantages with the current critic and taking
    minibatch steps (shuffled, without replacement) on ``loss_objective + loss_critic
    (+ loss_entropy)``; gradients go through a :class:`GradientGuard` (clip to ``max_grad_norm``,
    skip NaN/inf). The learning rate decays linearly to 0 over the budget (``lr_anneal``).
    The observation normaliser (``obs_norm``) is updated after the epochs, so the data of an
    iteration is scored with the statistics it was collected with.
    """

    name = "ppo"

    def __init__(self, cfg, env, total_env_steps: int):
        super().__init__(cfg, env, total_env_steps)
        c = cfg.loss
        self.actor, self.normalizer = make_policy_from_config(c, env, return_log_prob=True)
        self.critic = make_critic(env, **network_kwargs(c.critic), normalizer=self.normalizer).to(env.device)
        self.policy = self.actor
        self.loss = ClipPPOLoss(
            self.actor,
            self.critic,
            clip_epsilon=float(c.clip_epsilon),
            entropy_bonus=float(c.entropy_coeff) > 0,
            entropy_coeff=float(c.entropy_coeff),
            critic_coeff=float(c.critic_coeff),
            loss_critic_type=str(c.loss_critic_type),
            normalize_advantage=bool(c.normalize_advantage),
        )
        self.loss.make_value_estimator(ValueEstimators.GAE, gamma=float(c.gamma), lmbda=float(c.lmbda))
        self.params = [p for p in self.loss.parameters() if p.requires_grad]
        self.optim = torch.optim.Adam(self.params, lr=float(c.lr))
        total = self.total_iterations
        decay = (lambda i: max(0.0, 1.0 - i / total)) if c.lr_anneal else (lambda i: 1.0)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optim, decay)
        self.guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.epochs = int(c.epochs)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(self.env_steps_per_iteration, device=env.device),
            sampler=SamplerWithoutReplacement(),
            batch_size=int(c.minibatch_size),
        )
        self.collector = Collector(
            env,
            self.actor,
            frames_per_batch=self.env_steps_per_iteration,
            total_frames=-1,
            auto_register_policy_transforms=False,  # the policy reads only "observation"
        )
        self._batches = iter(self.collector)
        self.tracker = EpisodeReturnTracker(env.num_envs, env.device)

    @property
    def env_steps_per_iteration(self) -> int:
        return self.env.num_envs * int(self.cfg.loss.rollout_len)

    def train_iteration(self) -> dict[str, float]:
        data = next(self._batches)  # [num_envs, rollout_len], collected under no_grad
        finished = self.tracker.update(data)
        sums: dict[str, float] = defaultdict(float)
        updates = 0
        for _ in range(self.epochs):
            with torch.no_grad():  # advantages with the current critic
                self.loss.value_estimator(
                    data,
                    params=self.loss.critic_network_params,
                    target_params=self.loss.target_critic_network_params,
                )
            self.buffer.extend(data.reshape(-1))
            for batch in self.buffer:
                out = self.loss(batch)
                total = out["loss_objective"] + out["loss_critic"]
                if "loss_entropy" in out.keys():
                    total = total + out["loss_entropy"]
                self.optim.zero_grad(set_to_none=True)
                total.backward()
                info = self.guard.step(self.optim, self.params)
                sums["grad_norm"] += info["grad_norm"]
                for key in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "clip_fraction", "kl_approx"):
                    if key in out.keys():
                        sums[key] += out[key].detach().float().mean().item()
                updates += 1
        metrics = {key: value / max(updates, 1) for key, value in sums.items()}
        metrics.update(
            reward=data.get(("next", "reward")).mean().item(),
            skipped=self.guard.skipped,
            lr=self.optim.param_groups[0]["lr"],
        )
        if finished:
            metrics["return"] = sum(finished) / len(finished)
        self.scheduler.step()
        if self.normalizer is not None:
            self.normalizer.update(data.get("observation"))
        self.collector.update_policy_weights_()
        return metrics

    def state_dict(self) -> dict:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "loss": self.loss.state_dict(),
            "optimizer": self.optim.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "guard": self.guard.state_dict(),
            "tracker": self.tracker.state_dict(),
            "collector": self.collector.state_dict(),
            "carrier": collector_carrier_state(self.collector),
            # the sampler draws the next epoch's permutation as soon as one runs out
            "sampler": self.buffer.sampler.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.loss.load_state_dict(state["loss"])
        self.optim.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.guard.load_state_dict(state["guard"])
        self.tracker.load_state_dict(state["tracker"])
        self.collector.load_state_dict(state["collector"])
        load_collector_carrier(self.collector, state["carrier"])
        self.buffer.sampler.load_state_dict(state["sampler"])

    def close(self) -> None:
        self.collector.shutdown(close_env=False)
