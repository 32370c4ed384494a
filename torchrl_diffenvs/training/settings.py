"""The run's own sections of the training configuration (``train``, ``eval``, ``selfplay``,
``distributed``): frozen dataclasses whose fields carry their default and their check, as the
learners' settings do (`Settings`).

They are the only place these defaults are written: `register_run_configs` stores them in
Hydra's ConfigStore as ``run_settings``, which ``configs/config.yaml`` lists first in its defaults;
a learner's ``run_defaults`` (its budget) and ``configs/tuned/`` files then change some of them.
`validate_config` checks each section with its class
(unknown keys and bad values, each named with what is valid).
"""
from __future__ import annotations

import dataclasses

from .. import checks
from ..checks import Settings, checked

__all__ = [
    "DistributedSettings", "EvalSettings", "LOGGERS", "LoggerSettings", "RUN_SECTIONS", "RunSettings",
    "SelfPlaySettings", "TrainSettings", "WANDB_MODES", "register_run_configs", "run_defaults",
]

LOGGERS = ("wandb", "csv", "none")
WANDB_MODES = ("offline", "online", "disabled")


def _optional(check: checks.Check, what: str) -> checks.Check:
    def optional(value) -> str | None:
        return None if value is None or check(value) is None else f"{check(value)}, or null {what}"

    return optional


def _number(value) -> str | None:
    return None if checks.is_number(value) else "expected a number"


def _at_least(minimum: int) -> checks.Check:
    def check(value) -> str | None:
        return None if checks.is_int(value) and value >= minimum else f"expected an integer >= {minimum}"

    return check


@dataclasses.dataclass(frozen=True)
class TrainSettings(Settings):
    """``train.*``: the budget, checkpoints and logging of a run. Budgets and intervals count env
    steps of all envs of the batch and of all ranks."""

    total_env_steps: int = checked(300_000, checks.positive_int)  # stop after this many env steps (each learner sets its own)
    checkpoint_interval: int = checked(100_000, checks.positive_int)  # env steps between checkpoints; one is written at the end
    keep_checkpoints: int = checked(2, checks.nonnegative_int)  # numbered checkpoints kept besides last.pt (0: only last.pt)
    log_interval: int = checked(1, checks.positive_int)  # iterations between rows of training metrics
    # stop once an evaluation return reaches this (rl_games' score_to_win); null: train the whole budget
    score_to_win: float | None = checked(None, _optional(_number, "to train the whole budget"))
    # from this env step on, keep checkpoints/best.pt: the best evaluation so far; null: no best.pt
    save_best_after: int | None = checked(None, _optional(checks.nonnegative_int, "(env steps)"))
    progress_bar: bool = checked(True, checks.boolean)


@dataclasses.dataclass(frozen=True)
class EvalSettings(Settings):
    """``eval.*``: the deterministic evaluations during training, the final video, and ``mode=eval``."""

    interval: int = checked(50_000, checks.positive_int)  # env steps between evaluations (also at the start and the end)
    num_envs: int = checked(32, checks.positive_int)  # evaluation envs, separate from the training envs
    max_steps: int | None = checked(None, _optional(checks.positive_int, "for the env's max_episode_steps"))
    seed: int = checked(1_000_003, checks.nonnegative_int)  # the eval envs restart from this seed at every evaluation
    gif: bool = checked(True, checks.boolean)  # write <run dir>/final.gif (or .mp4); mode=eval: eval.gif
    video_format: str = checked("gif", checks.one_of(("gif", "mp4")))  # mp4 needs the video extra (imageio-ffmpeg)
    # write <run dir>/learning_curve.png at the end of the run, and log it (false: e.g. a sweep of many short runs)
    learning_curve: bool = checked(True, checks.boolean)
    deterministic: bool = checked(True, checks.boolean)  # evaluate the mean action (true) or sampled actions
    # also play each evaluation in Gymnasium's own env (a MuJoCo task: MuJoCo itself; the mujoco extra):
    # eval/gymnasium_return beside eval/return, on eval.num_envs episodes from seeds eval.seed + i
    gymnasium: bool = checked(False, checks.boolean)
    # with eval.gymnasium=true: score only there and skip this library's own evaluation (on a GPU its
    # few envs step launch-bound, while MuJoCo's C env on the CPU is quick); eval/return is then NaN
    # and the Gymnasium return picks the best checkpoint and decides train.score_to_win
    only_gymnasium: bool = checked(False, checks.boolean)
    # mode=eval: episodes to play, eval.num_envs at a time; null: eval.num_envs
    games_num: int | None = checked(None, _optional(checks.positive_int, "for eval.num_envs"))
    gif_env_index: int = checked(0, checks.nonnegative_int)  # which evaluation env the video shows
    gif_fps: int = checked(30, checks.positive_int)
    gif_size: int = checked(256, _at_least(16))  # pixels

    @classmethod
    def relation_problems(cls, values, where: str = "") -> list[str]:
        problems = []
        if values["gif_env_index"] >= values["num_envs"]:
            problems.append(f"{where}gif_env_index={values['gif_env_index']!r}: expected an integer in "
                            f"[0, {where}num_envs) = [0, {values['num_envs']})")
        if values["only_gymnasium"] and not values["gymnasium"]:
            problems.append(f"{where}only_gymnasium=true scores the policy only in Gymnasium's own env: it needs "
                            f"{where}gymnasium=true (or drop {where}only_gymnasium)")
        return problems


@dataclasses.dataclass(frozen=True)
class SelfPlaySettings(Settings):
    """``selfplay.*``: rl_games' self-play on a two-player env (``env=swimmer_race``): every
    ``refresh_interval`` env steps the policy is copied into a pool of the last ``pool_size``
    snapshots and the training envs' opponent becomes one of them, drawn uniformly. Evaluations
    play the task's fixed scripted opponent (`torchrl_diffenvs.training.selfplay`)."""

    # env steps between refreshes; null: no self-play (the opponent stays the scripted one)
    refresh_interval: int | None = checked(None, _optional(checks.positive_int, "(env steps) for no self-play"))
    pool_size: int = checked(1, checks.positive_int)  # snapshots kept (1: always the latest)


@dataclasses.dataclass(frozen=True)
class DistributedSettings(Settings):
    """``distributed.*``: data parallel under ``torchrun --nproc_per_node=K sota_scripts/train.py``.
    Each rank simulates ``env.num_envs`` envs and samples the loss's minibatches from its own data;
    budgets, intervals and ``loss.utd_ratio`` count the env steps of all ranks."""

    timeout_s: float = checked(300.0, checks.positive)  # a rank that waits this long for another fails with an error


def _strings(value) -> str | None:
    ok = isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)
    return None if ok else "expected a list of strings"


def _name(value) -> str | None:
    return None if isinstance(value, str) and value else "expected a non-empty string"


def _optional_string(value) -> str | None:
    return None if value is None or isinstance(value, str) else "expected a string, or null"


@dataclasses.dataclass(frozen=True)
class LoggerSettings(Settings):
    """``logger.*``: where the metrics go besides the run directory (``configs/logger/<backend>.yaml``
    holds each backend's defaults; the W&B keys only matter to ``backend=wandb``)."""

    backend: str = checked("wandb", checks.one_of(LOGGERS))
    exp_name: str = checked("run", _name)  # the run's name (configs/config.yaml: env_loss_seed)
    mode: str = checked("offline", checks.one_of(WANDB_MODES))  # W&B: offline never opens a connection
    project: str | None = checked(None, _optional_string)
    entity: str | None = checked(None, _optional_string)
    group: str | None = checked(None, _optional_string)
    tags: tuple[str, ...] = checked((), _strings)


RUN_SECTIONS: dict[str, type[Settings]] = {
    "train": TrainSettings, "eval": EvalSettings, "selfplay": SelfPlaySettings, "distributed": DistributedSettings,
}


def run_defaults() -> dict:
    """``{section: {key: default}}`` of the run's sections."""
    return {name: settings.defaults() for name, settings in RUN_SECTIONS.items()}


def register_run_configs() -> None:
    """Stores `run_defaults` in Hydra's ConfigStore as ``run_settings`` (the first entry of
    ``configs/config.yaml``'s defaults list)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="run_settings", node=run_defaults())


def _section(values) -> dict:
    from omegaconf import DictConfig, OmegaConf

    return OmegaConf.to_container(values, resolve=True) if isinstance(values, DictConfig) else dict(values or {})


def _env_num_envs(env) -> int:
    """``env.num_envs``, checked as the other run settings are."""
    value = env.get("num_envs")
    problem = checks.positive_int(value)
    if problem:
        raise ValueError(f"RunSettings: env.num_envs={value!r}: {problem}")
    return value


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """The typed view of a composed (and checked) training configuration that the training loop,
    ``mode=eval`` and the logger read: the run's sections as their settings classes, plus the
    top-level keys. The env and loss sections stay configuration: they are handed whole to the
    env and learner builders, which check them (`validate_config`).

    Built with `from_config`; every value is checked again on the way (a configuration
    that skipped ``validate_config`` fails here with the key and what is valid).
    """

    mode: str
    seed: int
    device: str
    dtype: str
    compile: bool
    resume: str | None
    checkpoint: str | None
    env_name: str
    loss_name: str
    env_num_envs: int  # envs in one training batch (per rank)
    env_options: dict  # the env's options (resolved), e.g. the contact model; {} when it sets none
    train: TrainSettings
    eval: EvalSettings
    selfplay: SelfPlaySettings
    distributed: DistributedSettings
    logger: LoggerSettings

    @classmethod
    def from_config(cls, cfg) -> RunSettings:
        """From a composed configuration (Hydra's ``DictConfig`` or a mapping)."""
        sections = {name: settings.from_mapping(_section(cfg.get(name))) for name, settings in RUN_SECTIONS.items()}
        return cls(
            mode=str(cfg.get("mode", "train")), seed=int(cfg.get("seed", 0)), device=str(cfg.get("device", "cpu")),
            dtype=str(cfg.get("dtype", "float32")), compile=bool(cfg.get("compile", False)),
            resume=None if cfg.get("resume") is None else str(cfg.get("resume")),
            checkpoint=None if cfg.get("checkpoint") is None else str(cfg.get("checkpoint")),
            env_name=str(cfg["env"]["name"]), loss_name=str(cfg["loss"]["name"]),
            env_num_envs=_env_num_envs(cfg["env"]), env_options=_section(cfg["env"].get("options")),
            logger=LoggerSettings.from_mapping(_section(cfg.get("logger"))), **sections,
        )

    @property
    def torch_dtype(self):
        """``dtype`` as a ``torch.dtype``."""
        import torch

        return getattr(torch, self.dtype)
