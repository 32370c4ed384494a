"""SAC through TorchRL itself: ``Collector`` -> replay buffer -> ``SACLoss`` + ``SoftUpdate``."""
from __future__ import annotations

import torch
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

from ...modules import make_mlp
from ...objectives import GradientGuard
from .base import EpisodeReturnTracker, Learner, make_policy_from_config, network_kwargs
from .ppo import collector_carrier_state, load_collector_carrier

__all__ = ["SACLearner", "make_qvalue"]

# what SACLoss reads; the rest of a transition (physical state, params) stays out of the buffer
_BUFFER_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)


class _ConcatInputs(nn.Module):
    """Feeds ``cat(observation, action)`` to an MLP (``ValueOperator`` passes them separately)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat(inputs, dim=-1))


def make_qvalue(env, hidden=(256, 256), activation=nn.ReLU, layer_norm=False) -> ValueOperator:
    """``Q(observation, action)`` writing ``"state_action_value"`` (what ``SACLoss`` expects)."""
    net = make_mlp(env.observation_dim + env.action_dim, 1, hidden, activation, layer_norm, env.float_dtype)
    return ValueOperator(_ConcatInputs(net), in_keys=["observation", "action"], out_keys=["state_action_value"])


class SACLearner(Learner):
    """TorchRL's ``SACLoss`` (two Q-networks, learned temperature) with a replay buffer and
    ``SoftUpdate`` target networks, on data from TorchRL's ``Collector``.

    One iteration: collect ``num_envs x rollout_len`` steps (uniformly random actions for the
    first ``init_random_frames``), add them to the buffer, then take
    ``round(utd_ratio x steps collected)`` gradient steps on sampled minibatches, each followed
    by a soft update of the target Q-networks. Actor, Q-networks and temperature have separate
    Adam optimisers; each step goes through a :class:`GradientGuard` (optional clipping; skip
    NaN/inf).
    """

    name = "sac"

    def __init__(self, cfg, env, total_env_steps: int):
        super().__init__(cfg, env, total_env_steps)
        c = cfg.loss
        self.actor, self.normalizer = make_policy_from_config(c, env)
        if self.normalizer is not None:
            raise ValueError("loss=sac does not support obs_norm (the replay buffer would mix statistics)")
        self.policy = self.actor
        qvalue = make_qvalue(env, **network_kwargs(c.qvalue)).to(env.device)
        self.loss = SACLoss(
            self.actor,
            qvalue,
            num_qvalue_nets=2,
            loss_function=str(c.loss_function),
            alpha_init=float(c.alpha_init),
            action_spec=env.action_spec_unbatched,  # target entropy -action_dim
            delay_qvalue=True,
        )
        self.loss.make_value_estimator(gamma=float(c.gamma))
        self.target_updater = SoftUpdate(self.loss, tau=float(c.tau))
        self.actor_params = list(self.loss.actor_network_params.values(True, True))
        self.qvalue_params = list(self.loss.qvalue_network_params.values(True, True))
        self.actor_optim = torch.optim.Adam(self.actor_params, lr=float(c.lr))
        self.qvalue_optim = torch.optim.Adam(self.qvalue_params, lr=float(c.lr))
        self.alpha_optim = torch.optim.Adam([self.loss.log_alpha], lr=float(c.alpha_lr))
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.qvalue_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=None)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(int(c.buffer_size), device=env.device), batch_size=int(c.batch_size)
        )
        self.updates_per_iteration = max(1, round(float(c.utd_ratio) * self.env_steps_per_iteration))
        self.collector = Collector(
            env,
            self.actor,
            frames_per_batch=self.env_steps_per_iteration,
            total_frames=-1,
            init_random_frames=int(c.init_random_frames),
            auto_register_policy_transforms=False,  # the policy reads only "observation"
        )
        self._batches = iter(self.collector)
        self.tracker = EpisodeReturnTracker(env.num_envs, env.device)
        self.frames = 0

    @property
    def env_steps_per_iteration(self) -> int:
        return self.env.num_envs * int(self.cfg.loss.rollout_len)

    def train_iteration(self) -> dict[str, float]:
        data = next(self._batches)  # [num_envs, rollout_len]
        finished = self.tracker.update(data)
        self.buffer.extend(data.reshape(-1).select(*_BUFFER_KEYS))
        self.frames += data.numel()
        metrics = {"reward": data.get(("next", "reward")).mean().item()}
        if finished:
            metrics["return"] = sum(finished) / len(finished)
        if self.frames >= int(self.cfg.loss.init_random_frames) and len(self.buffer) >= int(self.cfg.loss.batch_size):
            sums = {"loss_actor": 0.0, "loss_qvalue": 0.0, "loss_alpha": 0.0, "grad_norm_actor": 0.0,
                    "grad_norm_qvalue": 0.0, "entropy": 0.0}
            for _ in range(self.updates_per_iteration):
                out = self.loss(self.buffer.sample())
                total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
                for optim in (self.actor_optim, self.qvalue_optim, self.alpha_optim):
                    optim.zero_grad(set_to_none=True)
                total.backward()
                sums["grad_norm_actor"] += self.actor_guard.step(self.actor_optim, self.actor_params)["grad_norm"]
                sums["grad_norm_qvalue"] += self.qvalue_guard.step(self.qvalue_optim, self.qvalue_params)["grad_norm"]
                self.alpha_optim.step()
                self.target_updater.step()
                for key in ("loss_actor", "loss_qvalue", "loss_alpha", "entropy"):
                    sums[key] += out[key].detach().float().mean().item()
            metrics.update({key: value / self.updates_per_iteration for key, value in sums.items()})
            metrics["alpha"] = self.loss.log_alpha.exp().item()
        metrics["skipped_actor"] = self.actor_guard.skipped
        metrics["skipped_qvalue"] = self.qvalue_guard.skipped
        self.collector.update_policy_weights_()
        return metrics

    def state_dict(self) -> dict:
        state = {
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
            "buffer": self.buffer.state_dict() if self.cfg.loss.save_replay_buffer else None,
        }
        return state

    def load_state_dict(self, state: dict) -> None:
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
