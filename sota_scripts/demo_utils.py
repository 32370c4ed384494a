"""Small helpers shared by the demo scripts: typed ``key=value`` arguments (OmegaConf, as the
training script's Hydra uses) and plots."""
from __future__ import annotations

from pathlib import Path

import torch

from torchrl_diffenvs.checks import Settings, parse_cli


def start_demo(settings_class: type[Settings], argv: list[str] | None = None, usage: str = "") -> tuple[Settings, Path]:
    """Parses the ``key=value`` settings (:func:`torchrl_diffenvs.checks.parse_cli`), seeds torch and creates ``settings.out_dir``;
    returns the settings and ``out_dir``."""
    settings = parse_cli(settings_class, argv, usage)
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
