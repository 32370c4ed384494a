"""One :class:`Learner` per ``loss`` choice of the training script."""
from __future__ import annotations

from .base import EpisodeReturnTracker, Learner, make_policy_from_config, network_kwargs
from .gradient import BPTTLearner, SHACLearner
from .ppo import PPOLearner
from .sac import SACLearner, make_qvalue

LEARNERS: dict[str, type[Learner]] = {
    "bptt": BPTTLearner,
    "shac": SHACLearner,
    "ppo": PPOLearner,
    "sac": SACLearner,
}


def make_learner(cfg, env, total_env_steps: int | None = None) -> Learner:
    """Builds the learner named by ``cfg.loss.name`` for the training env ``env``."""
    try:
        cls = LEARNERS[cfg.loss.name]
    except KeyError:
        raise ValueError(f"unknown loss {cfg.loss.name!r}; valid: {', '.join(LEARNERS)}") from None
    return cls(cfg, env, cfg.train.total_env_steps if total_env_steps is None else total_env_steps)


__all__ = [
    "BPTTLearner", "EpisodeReturnTracker", "LEARNERS", "Learner", "PPOLearner", "SACLearner", "SHACLearner",
    "make_learner", "make_policy_from_config", "make_qvalue", "network_kwargs",
]
