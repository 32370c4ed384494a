"""Name -> env class registry behind :func:`make_env` and :func:`list_envs`."""
from __future__ import annotations

from .base import DiffEnv

_REGISTRY: dict[str, type[DiffEnv]] = {}


def register_env(cls: type[DiffEnv], name: str | None = None) -> type[DiffEnv]:
    """Adds an env class under ``name`` (default ``cls.name``); usable as a decorator."""
    key = name or cls.name
    if not key:
        raise ValueError(f"{cls.__name__} has no name to register under")
    if key in _REGISTRY and _REGISTRY[key] is not cls:
        raise ValueError(f"an env named {key!r} is already registered ({_REGISTRY[key].__name__})")
    _REGISTRY[key] = cls
    return cls


def list_envs() -> list[str]:
    """Every name :func:`make_env` accepts."""
    return sorted(_REGISTRY)


def env_class(name: str) -> type[DiffEnv]:
    """The class :func:`make_env` builds for ``name``."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown env {name!r}; valid names: {', '.join(list_envs())}") from None


def make_env(name: str, num_envs: int = 1, **kwargs) -> DiffEnv:
    """Builds a batched differentiable env by name, e.g. ``make_env("swimmer", num_envs=64)``.

    Keyword arguments go to the env class: ``device``, ``dtype``, ``seed``,
    ``max_episode_steps``, ``params`` and task options (``num_links``, ``num_urchins``, ...).
    """
    return env_class(name)(num_envs, **kwargs)
