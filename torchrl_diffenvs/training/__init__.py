"""The pieces of ``sota_scripts/train.py``: configuration checks, logging and checkpoints (the
learners are :mod:`torchrl_diffenvs.learners`, evaluation is :mod:`torchrl_diffenvs.evaluation`).
The script itself only wires them together, top to bottom."""
from .checkpoint import (
    CheckpointError,
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from .config import ConfigError, make_env_from_config, resolve_device, resolve_dtype, validate_config
from .run_logger import RunLogger, plot_learning_curve

__all__ = [
    "CheckpointError", "ConfigError", "RunLogger",
    "capture_rng_state", "load_checkpoint",
    "make_env_from_config", "plot_learning_curve", "resolve_device",
    "resolve_dtype", "restore_rng_state", "save_checkpoint", "validate_config",
]
