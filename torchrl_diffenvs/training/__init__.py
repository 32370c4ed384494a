"""The pieces of ``sota_scripts/train.py``: configuration checks, learners, evaluation, logging and
checkpoints. The script itself only wires them together, top to bottom."""
from .checkpoint import (
    CheckpointError,
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from .config import ConfigError, make_env_from_config, resolve_device, resolve_dtype, validate_config
from .evaluation import episode_returns, evaluate, evaluate_random, record_gif
from .learners import LEARNERS, EpisodeReturnTracker, Learner, make_learner
from .run_logger import RunLogger, plot_learning_curve

__all__ = [
    "CheckpointError", "ConfigError", "EpisodeReturnTracker", "LEARNERS", "Learner", "RunLogger",
    "capture_rng_state", "episode_returns", "evaluate", "evaluate_random", "load_checkpoint",
    "make_env_from_config", "make_learner", "plot_learning_curve", "record_gif", "resolve_device",
    "resolve_dtype", "restore_rng_state", "save_checkpoint", "validate_config",
]
