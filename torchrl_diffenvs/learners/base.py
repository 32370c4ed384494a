"""What every learner shares: its settings' checks, the interface the training script drives and
the learning-rate schedules."""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping

import torch
from tensordict.nn import TensorDictModuleBase

from ..checks import Settings, checked
from ..collectors import batch_size_of
from ..distributed import SINGLE_PROCESS, World

__all__ = ["LR_SCHEDULES", "Learner", "LearnerConfig", "checked", "load_lr_scheduler", "lr_scheduler"]  # checked: re-exported for the learner files

LR_SCHEDULES = ("linear", "exponential", "constant")


class LearnerConfig(Settings):
    """Base of a learner's settings: a frozen dataclass whose fields carry their checks
    (:func:`~torchrl_diffenvs.checks.checked`).

    The fields are the keys of the learner's ``configs/loss/<name>.yaml`` (besides ``name`` and
    the network sections), so the training script and Python code build learners alike.
    """


def lr_scheduler(optimizer: torch.optim.Optimizer, kind: str, total_iterations: Callable[[], int], *,
                 min_lr: float = 0.0, decay: float = 1.0) -> torch.optim.lr_scheduler.LambdaLR:
    """A learning-rate schedule that follows the budget as it is *now*.

    ``"linear"`` decays from the optimiser's learning rate to ``min_lr`` over
    ``total_iterations()`` iterations, then stays there; ``"exponential"`` multiplies it by
    ``decay`` every iteration; ``"constant"`` keeps it. ``total_iterations`` is called at every
    step, so a run resumed with a larger budget stretches the rest of its schedule over the new
    budget (``LinearLR`` would keep the old length saved in its state).
    """
    if kind not in LR_SCHEDULES:
        raise ValueError(f"unknown lr_schedule {kind!r}; valid: {', '.join(LR_SCHEDULES)}")
    end = min(1.0, min_lr / optimizer.param_groups[0]["lr"])
    if kind == "linear":
        def factor(i: int) -> float:
            return 1.0 - (1.0 - end) * min(i / max(1, total_iterations()), 1.0)
    elif kind == "exponential":
        def factor(i: int) -> float:
            return decay**i
    else:
        def factor(i: int) -> float:
            return 1.0
    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def load_lr_scheduler(schedule: torch.optim.lr_scheduler.LambdaLR, state: dict) -> None:
    """Restores a :func:`lr_scheduler` and sets the optimiser's learning rates to what the
    schedule gives *now*: after a resume with another budget, the saved rates were the old
    schedule's."""
    schedule.load_state_dict(state)
    for group, base_lr, factor in zip(schedule.optimizer.param_groups, schedule.base_lrs, schedule.lr_lambdas):
        group["lr"] = base_lr * factor(schedule.last_epoch)


class Learner(ABC):
    """One learning algorithm behind one interface, used alike by ``sota_scripts/train.py``, the
    demos, the benchmarks and the tests.

    A learner owns its networks, optimisers, schedules and data collection on the training env.
    Each :meth:`train_iteration` collects :attr:`env_steps_per_iteration` env steps and updates
    the networks; :attr:`policy` is the actor that evaluation runs in deterministic mode.
    :meth:`from_config` builds one from a ``loss`` configuration section.

    Args:
        env: the training env: any TorchRL ``EnvBase`` with a batch dimension ``[N]`` (BPTT and
            SHAC also take a batch-unlocked one with ``reset_input``); BPTT and SHAC need its
            rewards or observations to carry gradients w.r.t. the actions.
        config: the learner's settings (its :class:`LearnerConfig` subclass).
        total_env_steps: the training budget (global: all ranks together); the learning-rate
            schedules run over it, and it can be changed later (a resumed run with a larger budget).
        world: the ranks training together (:class:`~torchrl_diffenvs.distributed.World`; default
            one process). Every gradient is averaged over them before the optimiser step, and
            :attr:`env_steps_per_iteration` counts the env steps of all of them.
    """

    name: str = ""
    config_class: type[LearnerConfig] = LearnerConfig
    policy: TensorDictModuleBase

    def __init__(self, env, config: LearnerConfig, total_env_steps: int, *, reset_input=None,
                 world: World = SINGLE_PROCESS):
        if not isinstance(config, self.config_class):
            raise TypeError(f"{type(self).__name__}: config must be a {self.config_class.__name__}, "
                            f"got {type(config).__name__}")
        self._num_envs = batch_size_of(env, reset_input, type(self).__name__)
        self.env = env
        self.config = config
        self.total_env_steps = int(total_env_steps)
        self.world = world
        self.iteration = 0

    @classmethod
    @abstractmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> Learner:
        """Builds the learner and its networks from a ``loss`` section (``configs/loss/<name>.yaml``)."""

    @property
    def num_envs(self) -> int:
        return self._num_envs

    @property
    @abstractmethod
    def steps_per_env(self) -> int:
        """Steps each env takes in one :meth:`train_iteration` (the window or rollout length)."""

    @property
    def env_steps_per_iteration(self) -> int:
        """Env steps collected by one :meth:`train_iteration`, on all ranks together."""
        return self.num_envs * self.steps_per_env * self.world.size

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
