"""The training loop and its pieces: configuration checks, logging, checkpoints, self-play.

`run` is what ``sota_scripts/train.py`` (a thin Hydra entry point) calls with the composed
configuration; `Trainer` is the loop (`loop`), `evaluate_checkpoint` the
``mode=eval`` player (`eval_mode`). The configuration's defaults live in dataclasses: the
run's sections in `settings` (``train``, ``eval``, ``selfplay``, ``distributed``), each
learner's in its settings class (`torchrl_diffenvs.learners`); `validate_config` checks
a composed configuration with them and lists every problem at once. Evaluation rollouts are
`torchrl_diffenvs.evaluation`.
"""
from .checkpoint import (
    CheckpointError,
    capture_rng_state,
    load_checkpoint,
    remove_stale_temp_files,
    restore_rng_state,
    save_checkpoint,
)
from .config import (
    ConfigError,
    make_env_from_config,
    merge_overrides,
    resolve_device,
    resolve_dtype,
    validate_config,
)
from .eval_mode import evaluate_checkpoint
from .interrupts import TrainingInterrupted
from .loop import Trainer, run, train
from .run_logger import RunLogger, plot_learning_curve
from .settings import DistributedSettings, EvalSettings, LoggerSettings, RunSettings, SelfPlaySettings, TrainSettings

__all__ = [
    "CheckpointError", "ConfigError", "DistributedSettings", "EvalSettings", "LoggerSettings", "RunLogger",
    "RunSettings", "SelfPlaySettings",
    "TrainSettings", "Trainer", "TrainingInterrupted",
    "capture_rng_state", "evaluate_checkpoint", "load_checkpoint",
    "make_env_from_config", "merge_overrides", "plot_learning_curve", "remove_stale_temp_files", "resolve_device",
    "resolve_dtype", "restore_rng_state", "run", "save_checkpoint", "train", "validate_config",
]
