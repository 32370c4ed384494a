"""The interface the training script drives, whatever the learning algorithm."""
from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from ...modules import ObservationNormalizer, make_actor

__all__ = ["ACTIVATIONS", "EpisodeReturnTracker", "Learner", "make_policy_from_config", "network_kwargs"]

ACTIVATIONS = {"tanh": nn.Tanh, "elu": nn.ELU, "relu": nn.ReLU}


def network_kwargs(section: DictConfig) -> dict:
    """``hidden`` / ``activation`` / ``layer_norm`` (/ ``init_log_std``) of a network config section,
    as keyword arguments of :func:`~torchrl_diffenvs.modules.make_actor` / ``make_critic``."""
    kwargs = {
        "hidden": tuple(int(h) for h in section.hidden),
        "activation": ACTIVATIONS[section.get("activation", "elu")],
        "layer_norm": bool(section.get("layer_norm", True)),
    }
    if "init_log_std" in section:
        kwargs["init_log_std"] = float(section.init_log_std)
    return kwargs


def make_policy_from_config(loss_cfg: DictConfig, env, return_log_prob: bool = False):
    """The actor a learner trains, built from ``loss_cfg.actor`` (and ``loss_cfg.obs_norm``).

    Returns ``(actor, normalizer)``; the normaliser (or ``None``) sits inside the actor, so the
    actor's ``state_dict`` carries its statistics.
    """
    normalizer = (
        ObservationNormalizer(env.observation_dim, dtype=env.float_dtype).to(env.device)
        if loss_cfg.get("obs_norm", False)
        else None
    )
    actor = make_actor(
        env,
        **network_kwargs(loss_cfg.actor),
        distribution=loss_cfg.actor.get("distribution", "tanh_normal"),
        normalizer=normalizer,
        return_log_prob=return_log_prob,
    ).to(env.device)
    return actor, normalizer


class EpisodeReturnTracker:
    """Undiscounted returns of the training episodes that finish inside each batch ``[N, T]``.

    Keeps each env's running sum across batches (episodes span iterations); its state is saved
    in checkpoints so that a resumed run reports the same returns.
    """

    def __init__(self, num_envs: int, device: torch.device | str = "cpu"):
        self.running = torch.zeros(num_envs, dtype=torch.float64, device=device)

    def update(self, batch: TensorDictBase) -> list[float]:
        """Adds a ``[N, T]`` batch (``("next", "reward")``, ``("next", "done")``); returns the
        returns of the episodes that ended in it."""
        reward = batch.get(("next", "reward")).detach()[..., 0].to(torch.float64)
        done = batch.get(("next", "done"))[..., 0]
        finished: list[float] = []
        for t in range(reward.shape[-1]):
            self.running += reward[:, t]
            if done[:, t].any():
                finished.extend(self.running[done[:, t]].tolist())
                self.running[done[:, t]] = 0.0
        return finished

    def state_dict(self) -> dict:
        return {"running": self.running.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.running.copy_(state["running"])


class Learner(ABC):
    """One learning algorithm behind the interface of ``sota_scripts/train.py``.

    A learner owns its networks, optimisers, schedules and data collection on the training env.
    Each :meth:`train_iteration` collects ``env_steps_per_iteration`` env steps and updates the
    networks; :attr:`policy` is the actor that evaluation runs in deterministic mode.

    Args:
        cfg: the whole run configuration (the learner reads ``cfg.loss``).
        env: the batched training env.
        total_env_steps: the training budget (learning-rate schedules run over it).
    """

    name: str = ""
    policy: TensorDictModuleBase

    def __init__(self, cfg: DictConfig, env, total_env_steps: int):
        self.cfg = cfg
        self.env = env
        self.total_env_steps = int(total_env_steps)

    @property
    @abstractmethod
    def env_steps_per_iteration(self) -> int:
        """Env steps collected by one :meth:`train_iteration`."""

    @property
    def total_iterations(self) -> int:
        return max(1, math.ceil(self.total_env_steps / self.env_steps_per_iteration))

    @abstractmethod
    def train_iteration(self) -> dict[str, float]:
        """Collects data and updates the networks once.

        Returns scalar metrics without a prefix: ``"reward"`` (mean per-step reward of the
        collected data), ``"return"`` (mean return of the episodes that finished, when any did),
        losses, pre-clip gradient norms (``"grad_norm*"``), cumulative skipped steps
        (``"skipped*"``) and learning rates.
        """

    @abstractmethod
    def state_dict(self) -> dict:
        """Everything needed to continue exactly: networks, optimisers, schedules, normalisers,
        the env state being collected from, replay buffers. Plain tensors and containers only."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        """Restores :meth:`state_dict` into a learner built from the same configuration."""

    def close(self) -> None:
        """Releases collectors (override when there is anything to release)."""
