"""One learner per algorithm, each in one file that reads like its algorithm.

``bptt`` and ``shac`` backpropagate through the differentiable env; ``ppo`` and ``sac`` are
TorchRL's own losses and collectors. All four share :class:`Learner`'s interface, used alike by
``sota_scripts/train.py``, the demos, the benchmarks and the tests::

    learner = SHACLearner(env, make_actor(env), make_critic(env), SHACConfig(horizon=8))
    for _ in range(100):
        metrics = learner.train_iteration()
"""
from __future__ import annotations

from collections.abc import Mapping

from ..distributed import SINGLE_PROCESS, World

from .ahac import AHACConfig, AHACLearner
from .base import LR_SCHEDULES, Learner, LearnerConfig, lr_scheduler
from .bptt import BPTTConfig, BPTTLearner
from .ppo import PPOConfig, PPOLearner
from .sac import SACConfig, SACLearner
from .sapo import SAPOConfig, SAPOLearner
from .shac import SHACConfig, SHACLearner

LEARNERS: dict[str, type[Learner]] = {
    "bptt": BPTTLearner,
    "shac": SHACLearner,
    "ppo": PPOLearner,
    "sac": SACLearner,
    "ahac": AHACLearner,
    "sapo": SAPOLearner,
}


def make_learner(loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> Learner:
    """Builds the learner named by ``loss_cfg.name`` (a ``configs/loss/*.yaml`` section) on ``env``
    (this rank's envs when ``world`` has several ranks)."""
    name = loss_cfg.get("name")
    if name not in LEARNERS:
        raise ValueError(f"unknown loss {name!r}; valid: {', '.join(LEARNERS)}")
    return LEARNERS[name].from_config(loss_cfg, env, total_env_steps, world)


__all__ = [
    "AHACConfig", "AHACLearner", "BPTTConfig", "BPTTLearner", "LEARNERS", "LR_SCHEDULES", "Learner", "LearnerConfig",
    "PPOConfig", "PPOLearner", "SACConfig", "SACLearner", "SAPOConfig", "SAPOLearner", "SHACConfig", "SHACLearner",
    "lr_scheduler", "make_learner",
]
