"""Checks a composed training configuration before anything is built, and turns it into objects.

`validate_config` collects *every* problem of a configuration and raises one
`ConfigError` that lists them, each naming the key, the value found and what is valid, so a
typo costs one run, not one run per typo. It runs before any env, network or logger is created.
"""
from __future__ import annotations

import importlib.util

import math
from collections.abc import Mapping
from pathlib import Path

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from ..checks import is_int as _is_int
from ..checks import is_number
from ..envs import env_config, is_multi_agent, list_envs, make_env
from ..envs.gymnasium_backend import ENV_BACKENDS, GRADIENT_FREE_LOSSES, GymnasiumBackedEnv, gymnasium_env_problems
from ..learners import LEARNERS
from .settings import LOGGERS, RUN_SECTIONS, WANDB_MODES, LoggerSettings, register_run_configs
from ..modules import privileged_inputs

__all__ = [
    "ConfigError",
    "register_env_configs",
    "DTYPES",
    "ENV_BACKENDS",
    "LOGGERS",
    "LOSSES",
    "MODES",
    "WANDB_MODES",
    "check_checkpoint_path",
    "check_gymnasium_eval",
    "check_group_choice",
    "check_gymnasium_backend",
    "env_backend",
    "check_resume_compatible",
    "env_kwargs",
    "make_env_from_config",
    "merge_overrides",
    "resolve_device",
    "resolve_dtype",
    "validate_config",
]

LOSSES = tuple(LEARNERS)  # the built-in learners (register_learner adds to LEARNERS)
MODES = ("train", "eval")
DTYPES = {"float32": torch.float32, "float64": torch.float64}

def register_env_configs() -> None:
    """Makes ``env=<name>`` of the training script's configuration (a Hydra config group) know
    every registered task: its section is generated from the task's registration
    (`env_config`), so a new task needs no config file.
    Runs on import; call it again after registering a task of your own."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for name in list_envs():
        store.store(group="env", name=name, node=env_config(name))


register_env_configs()
register_run_configs()


def _plain(values) -> dict:
    """A configuration section as plain Python values (lists for list nodes)."""
    return OmegaConf.to_container(values, resolve=True) if isinstance(values, DictConfig) else dict(values)


class ConfigError(ValueError):
    """A configuration that cannot run; the message lists every problem found."""


def resolve_device(name: str) -> torch.device:
    """``"cpu"``, ``"cuda"`` or ``"cuda:<i>"`` as a ``torch.device``, checking that it exists."""
    try:
        device = torch.device(str(name))
    except (RuntimeError, TypeError) as err:
        raise ConfigError(f"device={name!r} is not a torch device ({err}); valid: cpu, cuda, cuda:<index>") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"device={name!r} but torch.cuda.is_available() is False (no GPU, or a CPU-only torch build); "
                "use device=cpu"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(f"device={name!r} but only {torch.cuda.device_count()} CUDA device(s) exist")
    elif device.type != "cpu":
        raise ConfigError(f"device={name!r} is not supported; valid: cpu, cuda, cuda:<index>")
    return device


def resolve_dtype(name: str) -> torch.dtype:
    """``"float32"`` / ``"float64"`` as a ``torch.dtype``."""
    try:
        return DTYPES[str(name)]
    except KeyError:
        raise ConfigError(f"dtype={name!r} is not supported; valid: {', '.join(DTYPES)}") from None


def env_kwargs(env_cfg: Mapping) -> dict:
    """The keyword arguments of `make_env` that an ``env`` config section sets
    (everything except ``name``, ``num_envs``, device, dtype and seed)."""
    def plain(value) -> dict:
        return OmegaConf.to_container(value, resolve=True) if isinstance(value, DictConfig) else dict(value or {})

    kwargs = plain(env_cfg.get("options"))
    params = plain(env_cfg.get("params"))
    if params:
        kwargs["params"] = params
    if env_cfg.get("max_episode_steps") is not None:
        kwargs["max_episode_steps"] = int(env_cfg.max_episode_steps)
    return kwargs


def randomized_params(ranges: Mapping, num_envs: int, seed: int) -> dict[str, torch.Tensor]:
    """``env.randomize``: one value per env for each named physical parameter, uniform in its
    ``[low, high]``, drawn from a generator seeded with ``seed`` (the env's seed: each rank and
    the evaluation envs get their own draw, the same at every run). Fixed for the env's life."""
    generator = torch.Generator().manual_seed(int(seed))
    values = {}
    for key in sorted(ranges):
        low, high = (float(bound) for bound in ranges[key])
        values[key] = low + (high - low) * torch.rand(num_envs, generator=generator, dtype=torch.float64)
    return values


def env_backend(env_cfg: Mapping) -> str:
    """``env.backend``: ``"torchrl_diffenvs"`` (this library's env; also for a section written
    before the key existed) or ``"gymnasium"`` (Gymnasium's own env)."""
    return env_cfg.get("backend") or "torchrl_diffenvs"


def make_env_from_config(cfg: DictConfig, num_envs: int, seed: int):
    """Builds the env named by ``cfg.env`` with ``num_envs`` envs on ``cfg.device`` in ``cfg.dtype``:
    this library's, or with ``env.backend=gymnasium`` Gymnasium's own
    (`GymnasiumBackedEnv`)."""
    if env_backend(cfg.env) == "gymnasium":
        return GymnasiumBackedEnv(cfg.env.name, num_envs, device=resolve_device(cfg.device),
                                  dtype=resolve_dtype(cfg.dtype), seed=seed,
                                  max_episode_steps=cfg.env.get("max_episode_steps"),
                                  options=_plain(cfg.env.get("options") or {}))
    kwargs = env_kwargs(cfg.env)
    ranges = cfg.env.get("randomize")
    if ranges:
        kwargs["params"] = {**kwargs.get("params", {}), **randomized_params(ranges, num_envs, seed)}
    return make_env(
        cfg.env.name,
        num_envs=num_envs,
        device=resolve_device(cfg.device),
        dtype=resolve_dtype(cfg.dtype),
        seed=seed,
        **kwargs,
    )


def _check_loss(loss, problems: list[str]) -> None:
    """The learner's own checks: its settings dataclass, its network sections, what it refuses
    (`config_problems`)."""
    problems.extend(LEARNERS[loss.name].config_problems(loss, "loss."))


def _non_finite(value) -> bool:
    """A NaN or infinite number anywhere in ``value`` (a number or nested lists of numbers)."""
    if isinstance(value, (list, tuple, ListConfig)):
        return any(_non_finite(v) for v in value)
    return isinstance(value, float) and not math.isfinite(value)


def _check_params(env_cfg, problems: list[str]) -> None:
    """Physical parameters must be finite: one NaN mass makes an env's states NaN, and the
    learners then skip or mask its updates; refuse it before anything is built."""
    params = env_cfg.get("params") or {}
    if not isinstance(params, Mapping):
        problems.append(f"env.params={params!r}: expected a mapping of physical parameter -> value, e.g. {{mass: 1.0}}")
        return
    for key, value in params.items():
        if _non_finite(value):
            shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
            problems.append(f"env.params.{key}={shown!r}: physical parameters must be finite numbers (not nan or inf)")


def _check_file(value, key: str, problems: list[str]) -> None:
    path = Path(str(value)).expanduser()
    if path.is_dir():
        found = [p for p in (path / "checkpoints" / "last.pt", path / "last.pt") if p.is_file()]
        problems.append(f"{key}={value!r} is a directory; valid: a checkpoint file (<run dir>/checkpoints/last.pt or "
                        f"ckpt_<env steps>.pt)" + (f", e.g. {key}={found[0]}" if found else ""))
    elif not path.is_file():
        problems.append(f"{key}={value!r}: no such checkpoint file; valid: a checkpoint a training run wrote "
                        "(<run dir>/checkpoints/last.pt or ckpt_<env steps>.pt)")


def _check_randomize(env_cfg, problems: list[str]) -> None:
    ranges = env_cfg.get("randomize") or {}
    example = "e.g. env.randomize={mass:[0.5,1.5]} (one value per env, uniform, fixed for the env's life)"
    if not isinstance(ranges, Mapping):
        problems.append(f"env.randomize={ranges!r}: expected a mapping of physical parameter -> [low, high], {example}")
        return
    for key, bounds in ranges.items():
        pair = list(bounds) if isinstance(bounds, (list, tuple, ListConfig)) else None
        if pair is None or len(pair) != 2 or not all(is_number(b) for b in pair) or pair[0] > pair[1]:
            shown = OmegaConf.to_container(bounds) if isinstance(bounds, (DictConfig, ListConfig)) else bounds
            problems.append(f"env.randomize.{key}={shown!r}: expected [low, high] with low <= high, {example}")
        elif key in (env_cfg.get("params") or {}):
            problems.append(f"env.randomize.{key} and env.params.{key} are both set: keep one")


def check_gymnasium_eval(env: DictConfig, problems: list[str]) -> None:
    """``eval.gymnasium=true``: the env must be one of Gymnasium's with the same continuous
    actions and observations, with its physics (no ``env.params`` or ``env.randomize``), and
    Gymnasium (with MuJoCo for a MuJoCo task) installed."""
    from ..evaluation import gymnasium_kwargs

    name = env.get("name")
    try:
        import gymnasium

        gymnasium.spec(name)
    except Exception:  # gymnasium's NameNotFound/VersionNotFound, or not installed
        problems.append(f"eval.gymnasium=true: env {name!r} is not one of Gymnasium's registered envs (the MuJoCo "
                        "and classic-control tasks are)")
        return
    if env.get("params"):
        problems.append(f"eval.gymnasium=true: env.params={_plain(env.params)} change the physics, and Gymnasium's "
                        f"env {name!r} runs its own; drop env.params to score the policy in it")
    if env.get("randomize"):
        problems.append(f"eval.gymnasium=true: env.randomize={_plain(env.randomize)} changes the physics per env, "
                        f"and Gymnasium's env {name!r} runs its model file's; drop env.randomize")
    try:
        options = gymnasium_kwargs(name, _plain(env.get("options") or {}))
    except ValueError as err:
        problems.append(f"eval.gymnasium=true: {err}")
        return
    if name.endswith("-v5") and importlib.util.find_spec("mujoco") is None:
        problems.append(f"eval.gymnasium=true: Gymnasium's {name!r} needs MuJoCo: pip install \"torchrl_diffenvs[mujoco]\"")
        return
    try:
        ours = make_env(name, num_envs=1, **_plain(env.get("options") or {}))
    except (ValueError, TypeError, KeyError):
        return  # the env's own check (below, in validate_config) names the bad option
    theirs = gymnasium.make(name, **options)
    action_dim = ours.full_action_spec[ours.action_key].shape[-1]
    obs_dim = ours.observation_spec["observation"].shape[-1] if "observation" in ours.observation_spec.keys() else None
    if not isinstance(theirs.action_space, gymnasium.spaces.Box) or theirs.action_space.shape != (action_dim,) or \
            (obs_dim is not None and theirs.observation_space.shape != (obs_dim,)):
        problems.append(f"eval.gymnasium=true: Gymnasium's {name!r} has actions {theirs.action_space} and observations "
                        f"of shape {theirs.observation_space.shape}, this library's task {action_dim} continuous actions "
                        f"and {obs_dim} observations: its policy cannot be played there")
    theirs.close()


def check_gymnasium_backend(cfg: DictConfig, problems: list[str]) -> None:
    """``env.backend``: one of `ENV_BACKENDS`; with ``gymnasium``, a gradient-free learner
    (`GRADIENT_FREE_LOSSES`) on one of Gymnasium's envs with continuous actions, its own
    physics (no ``env.params`` / ``env.randomize``) and no ``compile=true``."""
    backend = cfg.env.get("backend", "torchrl_diffenvs")
    if backend not in ENV_BACKENDS:
        problems.append(f"env.backend={backend!r}: unknown backend; valid: torchrl_diffenvs (this library's "
                        "differentiable env, the default), gymnasium (Gymnasium's own env, for ppo and sac)")
        return
    if backend != "gymnasium":
        return
    loss = cfg.loss.get("name")
    if loss not in GRADIENT_FREE_LOSSES:
        problems.append(f"loss={loss} needs a differentiable env (its gradients flow through the simulation), and "
                        f"env.backend=gymnasium runs Gymnasium's own env, which has none; with env.backend=gymnasium "
                        f"train loss={' or loss='.join(GRADIENT_FREE_LOSSES)}, or drop env.backend=gymnasium")
    problems.extend(gymnasium_env_problems(cfg.env.get("name"), _plain(cfg.env.get("options") or {})))
    for key, what in (("params", "change the physics"), ("randomize", "change the physics per env")):
        if cfg.env.get(key):
            problems.append(f"env.backend=gymnasium: env.{key}={_plain(cfg.env[key])} {what}, and Gymnasium's env "
                            f"runs its model file's; drop env.{key}")
    if OmegaConf.select(cfg, "compile", default=False) is True:
        problems.append("compile=true: env.backend=gymnasium steps Gymnasium's env, which torch cannot compile; "
                        "drop compile=true")


def validate_config(cfg: DictConfig) -> None:
    """Raises `ConfigError` listing every problem of ``cfg``; returns ``None`` when it can run.

    Checked: mode, env name and its options/params (by building one env; physical parameters must
    be finite), the loss section by its learner (`config_problems`:
    its settings dataclass, network sections and what it refuses), the ``train`` / ``eval`` /
    ``selfplay`` / ``distributed`` sections by their dataclasses (`settings`), logger,
    device, dtype, and the ``resume`` / ``checkpoint`` files.
    """
    problems: list[str] = []
    try:
        OmegaConf.to_container(cfg, resolve=True)
    except Exception as err:  # e.g. an interpolation that cannot resolve
        raise ConfigError(f"invalid configuration: {err}") from None

    mode = cfg.get("mode")
    if mode not in MODES:
        problems.append(f"mode={mode!r}: valid: {', '.join(MODES)}")

    env_name = cfg.env.get("name")
    if env_name not in list_envs():
        problems.append(f"env.name={env_name!r}: unknown env; valid: {', '.join(list_envs())}")
    loss_name = cfg.loss.get("name")
    if loss_name not in LEARNERS:
        problems.append(f"loss.name={loss_name!r}: unknown loss; valid: {', '.join(LEARNERS)}")
    logger = cfg.get("logger")
    if isinstance(logger, (DictConfig, Mapping)):
        problems.extend(LoggerSettings.problems(_plain(logger), "logger."))
    else:
        problems.append(f"logger={logger!r}: expected a section of settings ({', '.join(LoggerSettings.defaults())})")

    for resolver, key in ((resolve_device, "device"), (resolve_dtype, "dtype")):
        try:
            resolver(cfg.get(key))
        except ConfigError as err:
            problems.append(str(err))

    if not _is_int(cfg.get("seed")) or cfg.seed < 0:
        problems.append(f"seed={cfg.get('seed')!r}: expected an integer >= 0")
    for section, settings in RUN_SECTIONS.items():  # train, eval, selfplay, distributed: their dataclasses
        values = cfg.get(section)
        if isinstance(values, (DictConfig, Mapping)):
            problems.extend(settings.problems(_plain(values), f"{section}."))
        else:
            problems.append(f"{section}={values!r}: expected a section of settings ({', '.join(settings.defaults())})")
    num_envs = OmegaConf.select(cfg, "env.num_envs")
    if not _is_int(num_envs) or num_envs < 1:
        problems.append(f"env.num_envs={num_envs!r}: expected an integer >= 1")
    max_steps = OmegaConf.select(cfg, "env.max_episode_steps")
    if max_steps is not None and (not _is_int(max_steps) or max_steps < 1):
        problems.append(f"env.max_episode_steps={max_steps!r}: expected an integer >= 1, or null for the env's default")
    if not isinstance(OmegaConf.select(cfg, "compile", default=False), bool):
        problems.append(f"compile={OmegaConf.select(cfg, 'compile')!r}: expected true or false")

    if loss_name in LEARNERS:
        _check_loss(cfg.loss, problems)

    if mode == "eval":
        if cfg.get("checkpoint") is None:
            problems.append("mode=eval needs checkpoint=<path of a .pt file written by a training run>")
        else:
            _check_file(cfg.checkpoint, "checkpoint", problems)
    elif cfg.get("checkpoint") is not None:
        problems.append(
            f"checkpoint={cfg.checkpoint!r} is only read in mode=eval; to continue training use resume=<path>"
        )
    if cfg.get("resume") is not None:
        if mode == "eval":
            problems.append("resume= continues training; with mode=eval use checkpoint=<path> instead")
        else:
            _check_file(cfg.resume, "resume", problems)

    _check_randomize(cfg.env, problems)
    _check_params(cfg.env, problems)
    check_gymnasium_backend(cfg, problems)
    gymnasium_backend = env_backend(cfg.env) == "gymnasium"
    if OmegaConf.select(cfg, "eval.gymnasium", default=False) is True and mode != "eval" and not gymnasium_backend:
        check_gymnasium_eval(cfg.env, problems)  # mode=eval: on the checkpoint's env (eval_mode)
    refresh = OmegaConf.select(cfg, "selfplay.refresh_interval")

    # build one env: catches bad options / params / max_episode_steps with the env's own message
    if env_name in list_envs() and not any(p.startswith(("env.", "device", "dtype")) for p in problems):
        try:
            env = make_env_from_config(cfg, num_envs=1, seed=0)
        except (ValueError, TypeError, KeyError) as err:
            problems.append(f"env.options / env.params rejected by {env_name!r}: {err}")
        except Exception as err:  # noqa: BLE001 - Gymnasium's own errors (a bad keyword, MuJoCo missing)
            if not gymnasium_backend:
                raise
            problems.append(f"env.backend=gymnasium: Gymnasium could not build {env_name!r}: {err}")
        else:
            if env.max_episode_steps is None and cfg.eval.get("max_steps") is None:
                problems.append(f"env {env_name!r} never truncates episodes: set eval.max_steps")
            multi_agent = is_multi_agent(env)
            critic_input = OmegaConf.select(cfg, "loss.critic_input", default="observation")
            learner = LEARNERS.get(loss_name)
            if learner is not None:
                problems.extend(f"loss={loss_name}: {problem}" for problem in learner.env_problems(env))
            if multi_agent and learner is not None and not learner.supports_multi_agent:
                valid = [choice for name, other in LEARNERS.items() if other.supports_multi_agent
                         for choice in (other.multi_agent_choices or (name,))]
                problems.append(f"loss={loss_name}: env {env_name!r} is multi-agent; train it with "
                                f"{', '.join(valid[:-1])} or {valid[-1]}")
            elif multi_agent and critic_input != "observation":
                problems.append(f"loss.critic_input={critic_input}: env {env_name!r} is multi-agent; its critic reads "
                                "the agents' observations (loss.centralised_critic=true: every agent's)")
            elif critic_input == "state":
                try:
                    privileged_inputs(env)
                except ValueError as err:
                    problems.append(f"loss.critic_input=state: {err}")
            if multi_agent and cfg.get("compile"):
                problems.append(f"compile=true: env {env_name!r} is multi-agent; its rollouts take TorchRL's "
                                "EnvBase.rollout, and the compiled chunks are for single-agent envs")
            if refresh is not None and not hasattr(env, "set_opponent"):
                problems.append(f"selfplay.refresh_interval={refresh}: env {env_name!r} has no opponent to replace; "
                                "self-play needs a two-player env (e.g. env=swimmer_race)")
            if not multi_agent and OmegaConf.select(cfg, "loss.centralised_critic", default=False) is True:
                problems.append(f"loss.centralised_critic=true: env {env_name!r} has a single agent (MAPPO's "
                                "centralised critic needs a multi-agent env, e.g. env=multi_swimmer)")

    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise ConfigError(f"invalid configuration ({len(problems)} problem{'s' * (len(problems) > 1)}):\n{lines}")


# ---------------------------------------------------------------------- resuming
_NOT_CARRIED = ("resume", "mode", "checkpoint")


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def check_checkpoint_path(value, key: str = "resume") -> None:
    """Raises `ConfigError` unless ``value`` is a checkpoint file (missing, or a directory:
    the message names what is valid)."""
    problems: list[str] = []
    _check_file(value, key, problems)
    if problems:
        raise ConfigError(problems[0])


def check_group_choice(group: str, overrides: list[str], options: list[str]) -> None:
    """Raises `ConfigError` when the command line chooses ``<group>=<name>`` and no such
    config exists. For an optional group (``tuned``) Hydra would skip the missing file and train
    without it."""
    for override in overrides:
        key, sep, value = override.partition("=")
        if key.lstrip("+") != group or not sep or value in ("null", ""):
            continue
        if value not in options:
            raise ConfigError(f"{group}={value!r}: no such {group} config; valid: {', '.join(sorted(options))} "
                              f"(configs/{group}/), or {group}=null for none")


def merge_overrides(saved: list[str], current: list[str]) -> list[str]:
    """Command-line overrides of a resumed run: those the checkpointed run was started with, then
    today's; for a key given in both, today's wins. ``hydra.*`` overrides and the original run's
    ``resume`` / ``mode`` / ``checkpoint`` are dropped."""
    merged: dict[str, str] = {}
    for overrides, dropped in ((saved, _NOT_CARRIED), (current, ())):
        for override in overrides:
            key = _override_key(override)
            if key.startswith("hydra.") or key in dropped:
                continue
            merged.pop(key, None)  # re-insert: the later value, at the later position
            merged[key] = override
    return list(merged.values())


def check_resume_compatible(trained: DictConfig, cfg: DictConfig) -> None:
    """Raises `ConfigError` unless ``cfg`` trains the same env and learner as the
    checkpointed config ``trained`` (budget, evaluation, logging and device may change)."""
    problems = []
    for section in ("env", "loss"):
        old = OmegaConf.to_container(trained[section], resolve=True)
        new = OmegaConf.to_container(cfg[section], resolve=True)
        learner = LEARNERS.get(old.get("name")) if section == "loss" else None
        if learner is not None:  # a key a checkpoint lacks had its default (older checkpoints wrote fewer keys)
            defaults = OmegaConf.create(learner.default_config()["loss"])
            old = OmegaConf.to_container(OmegaConf.merge(defaults, old))
            new = OmegaConf.to_container(OmegaConf.merge(defaults, new))
        if section == "env":  # a section written before env.backend existed trained this library's env
            old["backend"], new["backend"] = env_backend(old), env_backend(new)
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                problems.append(f"{section}.{key}: checkpoint {old.get(key)!r}, now {new.get(key)!r}")
    for key in ("dtype", "seed"):
        if trained.get(key) != cfg.get(key):
            problems.append(f"{key}: checkpoint {trained.get(key)!r}, now {cfg.get(key)!r}")
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise ConfigError(
            f"resume={cfg.resume!r} was trained with a different env/learner setup; the saved state would not "
            f"fit. Differences:\n{lines}\nDrop these overrides to continue that run, or start a new run."
        )
