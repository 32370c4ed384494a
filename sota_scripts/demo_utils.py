"""Small helpers shared by the demo scripts (argument parsing, plots)."""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from torchrl_diffenvs import list_envs


def parse_args(defaults: dict, argv: list[str] | None = None, usage: str = "") -> dict:
    """Parses ``key=value`` arguments, converting each value to the type of its default."""
    argv = sys.argv[1:] if argv is None else argv
    args = dict(defaults)
    for item in argv:
        if item in ("-h", "--help"):
            print(usage or "arguments (key=value): " + " ".join(f"{k}={v}" for k, v in defaults.items()))
            raise SystemExit(0)
        key, sep, value = item.partition("=")
        if not sep or key not in defaults:
            raise SystemExit(f"unknown argument {item!r}; valid keys (key=value): {', '.join(defaults)}")
        kind = type(defaults[key])
        if kind is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise SystemExit(f"{key} expects true/false, got {value!r}")
            args[key] = value.lower() in ("true", "1")
        elif defaults[key] is None:
            args[key] = value
        else:
            try:
                args[key] = kind(value)
            except ValueError:
                raise SystemExit(f"{key} expects a {kind.__name__}, got {value!r}") from None
    return args


def start_demo(
    defaults: dict, argv: list[str] | None = None, usage: str = "", choices: dict[str, tuple] | None = None,
    check=None,
) -> tuple[dict, Path]:
    """Parses the arguments, checks the env name, the ``choices`` (key -> valid values) and
    ``check(args)`` (raises ``SystemExit`` on a bad value), seeds torch and creates ``out_dir``;
    returns the arguments and ``out_dir``."""
    args = parse_args(defaults, argv, usage)
    valid = {**({"env": tuple(list_envs())} if "env" in defaults else {}), **(choices or {})}
    for key, values in valid.items():
        if args[key] not in values:
            raise SystemExit(f"unknown {key} {args[key]!r}; valid: {', '.join(values)}")
    if check is not None:
        check(args)
    torch.manual_seed(args["seed"])
    out_dir = Path(args["out_dir"])
    out_dir.mkdir(parents=True, exist_ok=True)
    return args, out_dir


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
