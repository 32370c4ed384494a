"""The task registry behind [`make_env`][torchrl_diffenvs.make_env] and [`list_envs`][torchrl_diffenvs.list_envs].

A task is one file: its physics (a [`DiffEnv`][torchrl_diffenvs.DiffEnv] subclass) and, above the
class, one registration that names it, says how it is drawn and gives its training config:

```python
@register_env(drawer="torchrl_diffenvs.rendering.tasks:PENDULUM")
class PendulumEnv(DiffEnv):
    name = "pendulum"
    ...
```

The drawer is a ``"module:attribute"`` path, imported only when the task is first drawn (so
Pillow stays optional); the training script's ``env=<name>`` config is generated from the
registration ([`env_config`][torchrl_diffenvs.envs.env_config]).
"""
from __future__ import annotations

import importlib
import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field

__all__ = ["TaskSpec", "env_class", "env_config", "env_options", "list_envs", "make_env", "register_env", "task_drawer", "task_spec"]


@dataclass(frozen=True)
class TaskSpec:
    """One registered task.

    Attributes:
        cls: the env class (a ``DiffEnv`` subclass).
        drawer: how the task is drawn: a ``"module:attribute"`` path to a
            [`Drawer`][torchrl_diffenvs.rendering.Drawer] (or to a callable ``(env_class) -> Drawer``),
            a ``Drawer`` itself, or ``None``.
        options: task options shown in (and passed from) the training config's ``env.options``.
        num_envs: the training config's default batch size.
    """

    cls: type
    drawer: object = None
    options: Mapping = field(default_factory=dict)
    num_envs: int = 64


_REGISTRY: dict[str, TaskSpec] = {}
_DRAWERS: dict[str, object] = {}  # resolved drawers, by task name


def register_env(cls: type | None = None, name: str | None = None, *, drawer=None, options: Mapping | None = None,
                 num_envs: int = 64):
    """Registers an env class under ``name`` (default ``cls.name``); usable as a decorator, with
    or without arguments (``@register_env`` or ``@register_env(drawer=...)``).

    Args:
        cls: the env class (a [`DiffEnv`][torchrl_diffenvs.DiffEnv] subclass); ``None`` when used as
            ``@register_env(...)``, which returns the decorator.
        name: the name to register under (default ``cls.name``).
        drawer: how the task is drawn: a ``"module:attribute"`` path to a
            [`Drawer`][torchrl_diffenvs.rendering.Drawer] (or to a callable ``(env_class) -> Drawer``),
            a ``Drawer`` itself, or ``None``.
        options: task options shown in (and passed from) the training config's ``env.options``.
        num_envs: the training config's default batch size.

    Returns:
        ``cls``, registered; without ``cls``, a decorator that registers the class it is given.
    """

    def add(cls: type) -> type:
        key = name or getattr(cls, "name", "")
        if not key:
            raise ValueError(f"{cls.__name__} has no name to register under")
        if key in _REGISTRY and _REGISTRY[key].cls is not cls:
            raise ValueError(f"an env named {key!r} is already registered ({_REGISTRY[key].cls.__name__})")
        if drawer is not None and isinstance(drawer, str) and ":" not in drawer:
            raise ValueError(f"register_env({key!r}): drawer must be a 'module:attribute' path, got {drawer!r}")
        _REGISTRY[key] = TaskSpec(cls, drawer, dict(options or {}), int(num_envs))
        _DRAWERS.pop(key, None)
        return cls

    return add if cls is None else add(cls)


def list_envs() -> list[str]:
    """Every name [`make_env`][torchrl_diffenvs.make_env] accepts."""
    return sorted(_REGISTRY)


def _spec(name: str) -> TaskSpec:
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown env {name!r}; valid names: {', '.join(list_envs())}") from None


def task_spec(name: str) -> TaskSpec:
    """The registration of task ``name``."""
    return _spec(name)


def env_class(name: str) -> type:
    """The class [`make_env`][torchrl_diffenvs.make_env] builds for ``name``.

    Args:
        name: a registered task name (one of [`list_envs`][torchrl_diffenvs.list_envs]).
    """
    return _spec(name).cls


def task_drawer(name: str):
    """The drawer registered with task ``name`` (imported on first use), or ``None``."""
    spec = _spec(name)
    if name in _DRAWERS:
        return _DRAWERS[name]
    drawer = spec.drawer
    if isinstance(drawer, str):
        module, _, attribute = drawer.partition(":")
        drawer = getattr(importlib.import_module(module), attribute)
    if drawer is not None and not hasattr(drawer, "picture"):  # a factory: (env class) -> Drawer
        drawer = drawer(spec.cls)
    _DRAWERS[name] = drawer
    return drawer


def env_config(name: str) -> dict:
    """The training script's ``env`` section for task ``name`` (``python sota_scripts/train.py env=<name>``).

    Args:
        name: a registered task name (one of [`list_envs`][torchrl_diffenvs.list_envs]).
    """
    spec = _spec(name)
    # backend: torchrl_diffenvs (this library's env) | gymnasium (Gymnasium's own, envs/gymnasium_backend.py)
    return {"name": name, "num_envs": spec.num_envs, "max_episode_steps": None, "options": dict(spec.options),
            "params": {}, "randomize": {}, "backend": "torchrl_diffenvs"}


def env_options(name: str) -> list[str]:
    """The keyword arguments [`make_env`][torchrl_diffenvs.make_env] takes for task ``name``:
    those of every ``__init__`` along its class's hierarchy (the common ones, ``device``,
    ``dtype``, ``seed``, ``max_episode_steps``, ``params``, and the task's options).

    Args:
        name: a registered task name (one of [`list_envs`][torchrl_diffenvs.list_envs]).
    """
    keyword = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    names = {parameter.name for cls in env_class(name).__mro__ if "__init__" in vars(cls)
             for parameter in inspect.signature(vars(cls)["__init__"]).parameters.values()
             if parameter.kind in keyword}
    return sorted(names - {"self", "num_envs"})


def make_env(name: str, num_envs: int = 1, **kwargs):
    """Builds a batched differentiable env by name, e.g. ``make_env("swimmer", num_envs=64)``.

    Args:
        name: a registered task name (one of [`list_envs`][torchrl_diffenvs.list_envs]).
        num_envs: the batch size, the number of envs simulated together.
        **kwargs: go to the env class: ``device``, ``dtype``, ``seed``,
            ``max_episode_steps``, ``params`` and task options (``num_links``, ``num_urchins``, ...;
            [`env_options`][torchrl_diffenvs.envs.env_options] lists a task's).
    """
    unknown = sorted(set(kwargs) - set(env_options(name)))
    if unknown:  # a misspelt option must not be silently ignored, nor fail deep in a constructor
        raise TypeError(f"{name}: unknown option(s) {unknown}; valid: {env_options(name)}")
    return env_class(name)(num_envs, **kwargs)
