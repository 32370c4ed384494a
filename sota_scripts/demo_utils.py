"""Small helpers shared by the demo scripts: typed ``key=value`` arguments (OmegaConf, as the
training script's Hydra uses) and plots."""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_diffenvs.checks import Settings


def parse_settings(settings_class: type[Settings], argv: list[str] | None = None, usage: str = "") -> Settings:
    """Parses ``key=value`` arguments into ``settings_class`` (a :class:`~torchrl_diffenvs.checks.Settings`
    dataclass) with OmegaConf, the configuration system of ``sota_scripts/train.py``: values are
    converted to the fields' types, unknown keys and failed checks stop with a message."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(item in ("-h", "--help") for item in argv):
        defaults = " ".join(f"{k}={v}" for k, v in settings_class.defaults().items())
        print((usage or "") + f"\narguments (key=value), with their defaults: {defaults}")
        raise SystemExit(0)
    valid = settings_class.defaults()
    for item in argv:
        key, sep, _ = item.partition("=")
        if not sep or key not in valid:
            raise SystemExit(f"error: unknown argument {item!r}; valid keys (key=value): {', '.join(valid)}")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(settings_class), OmegaConf.from_dotlist(argv))
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:  # a value of the wrong type
        key = getattr(err, "full_key", None)
        raise SystemExit(f"error: {key}: {str(err).splitlines()[0]}" if key else f"error: {err}") from None
    except ValueError as err:  # a field's check
        raise SystemExit(f"error: {err}") from None


def start_demo(settings_class: type[Settings], argv: list[str] | None = None, usage: str = "") -> tuple[Settings, Path]:
    """Parses the settings (:func:`parse_settings`), seeds torch and creates ``settings.out_dir``;
    returns the settings and ``out_dir``."""
    settings = parse_settings(settings_class, argv, usage)
    torch.manual_seed(settings.seed)
    out_dir = Path(settings.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return settings, out_dir


def plot_curve(path: Path, curves: dict[str, tuple[list, list]], xlabel: str, ylabel: str, title: str) -> Path:
    """Writes a line plot of ``curves`` (label -> (x, y)) to ``path`` (PNG, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=100)
    for label, (x, y) in curves.items():
        ax.plot(x, y, label=label, marker="o" if len(x) < 30 else None, markersize=3)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
