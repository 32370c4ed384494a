"""Metrics of a training run: files in the run directory, plus a TorchRL logger (W&B, CSV or none).

Whatever the logger, the run directory gets:

* ``metrics.jsonl``: one JSON object per logged row (``{"env_steps": ..., "train/return": ...}``);
* ``metrics.csv``: the same rows as a table (one column per metric, blank where a row lacks it);
* ``learning_curve.png``: evaluation and training returns against env steps.

The external logger comes from `torchrl.record.loggers.get_logger`: ``"wandb"`` (offline by
default: the run lives in ``<run dir>/wandb`` and needs no network), ``"csv"`` (TorchRL's CSV logger
under ``<run dir>/csv``) or ``"none"``. Metrics are logged against the number of env steps.
"""
from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

from torchrl.record.loggers import get_logger

from .settings import LoggerSettings

__all__ = ["RunLogger", "plot_learning_curve", "read_history"]


def _jsonable(value):
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # JSON has no NaN / inf
    return value


class RunLogger:
    """Logs rows of scalar metrics to the run directory and to the configured TorchRL logger.

    Args:
        settings: the run's ``logger`` section (its backend, name and W&B keys).
        run_dir: the Hydra run directory.
        history: rows logged before a resume (`read_history`); they are written again so
            the run directory always holds the whole run.
        wandb_run_id: the W&B run id to continue (resume), or ``None`` for a new run.
        hyperparameters: logged once to the backend (the training loop passes the whole
            configuration).
    """

    def __init__(
        self,
        settings: LoggerSettings,
        run_dir: str | Path,
        history: Iterable[Mapping] = (),
        wandb_run_id: str | None = None,
        hyperparameters: Mapping | None = None,
    ):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.rows: list[dict] = [dict(row) for row in history]
        self.backend_name = settings.backend
        self.backend = self._make_backend(settings, wandb_run_id)
        self._jsonl = open(self.run_dir / "metrics.jsonl", "w")
        for row in self.rows:
            self._write_jsonl(row)
        if self.backend is not None and hyperparameters is not None:
            self.backend.log_hparams(dict(hyperparameters))

    def _make_backend(self, settings: LoggerSettings, wandb_run_id: str | None):
        name = settings.exp_name
        if self.backend_name == "wandb":
            wandb_kwargs = {
                "project": settings.project,
                "entity": settings.entity,
                "group": settings.group,
                "tags": list(settings.tags),
                # passed to wandb.init: "offline" never opens a connection
                "mode": settings.mode,
                "log_env_packages": False,
            }
            if wandb_run_id is not None:
                wandb_kwargs.update(id=wandb_run_id, resume="allow")
            return get_logger("wandb", logger_name=str(self.run_dir), experiment_name=name, wandb_kwargs=wandb_kwargs)
        if self.backend_name == "csv":
            return get_logger("csv", logger_name=str(self.run_dir / "csv"), experiment_name=name)
        return None

    @property
    def wandb_run_id(self) -> str | None:
        """The W&B run id (saved in checkpoints so that a resumed run continues it)."""
        if self.backend_name != "wandb" or self.backend is None:
            return None
        return getattr(self.backend.experiment, "id", None)

    @property
    def wandb_dir(self) -> Path | None:
        """The local directory of the W&B run (``<run dir>/wandb/<offline-run-...>``)."""
        if self.backend_name != "wandb" or self.backend is None:
            return None
        run_dir = getattr(self.backend.experiment, "dir", None)  # .../wandb/<run>/files
        return Path(run_dir).parent if run_dir else None

    # ------------------------------------------------------------------ logging
    def _write_jsonl(self, row: Mapping) -> None:
        self._jsonl.write(json.dumps({k: _jsonable(v) for k, v in row.items()}) + "\n")
        self._jsonl.flush()

    def log(self, metrics: Mapping[str, float], env_steps: int) -> None:
        """Logs scalar ``metrics`` at ``env_steps``."""
        row = {"env_steps": int(env_steps), **{k: float(v) for k, v in metrics.items()}}
        self.rows.append(row)
        self._write_jsonl(row)
        if self.backend is not None:
            self.backend.log_metrics(dict(metrics), step=int(env_steps))

    def log_files(self, images: Mapping[str, Path] = (), gifs: Mapping[str, Path] = ()) -> None:
        """Attaches image files (PNG) and videos (GIF or MP4) to the W&B run (other backends: no-op,
        the files are already in the run directory)."""
        if self.backend_name != "wandb" or self.backend is None:
            return
        import wandb

        media = {name: wandb.Image(str(path)) for name, path in dict(images).items()}
        media.update({name: wandb.Video(str(path), format=Path(path).suffix.lstrip(".") or "gif")
                      for name, path in dict(gifs).items()})
        if media:
            self.backend.experiment.log(media)

    def write_csv(self) -> Path:
        """Writes every row so far to ``metrics.csv`` (one column per metric)."""
        columns: dict[str, None] = {}
        for row in self.rows:
            columns.update(dict.fromkeys(row))
        path = self.run_dir / "metrics.csv"
        with open(path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(columns))
            writer.writeheader()
            writer.writerows(self.rows)
        return path

    def close(self) -> None:
        """Writes ``metrics.csv`` and closes the backend (W&B: finishes the run)."""
        self.write_csv()
        self._jsonl.close()
        if self.backend is not None:
            self.backend.shutdown()
            self.backend = None


def read_history(checkpoint: dict, path: str | Path) -> list[dict]:
    """The rows logged up to a checkpoint, for the run that resumes it: the first
    ``progress["logged_rows"]`` rows of the ``metrics.jsonl`` of the run that wrote it (its run
    directory holds the history; the checkpoint holds only the row count, so its size does not
    grow with the run's length). Looked for in ``<checkpoint's dir>/..`` and then in the run
    directory recorded in the checkpoint; an older checkpoint carries its rows itself.

    Returns ``[]`` (with a warning) when the file is gone: the resumed run's files then start at
    the checkpoint.
    """
    import warnings

    if "history" in checkpoint:  # written before the history moved out of checkpoints
        return [dict(row) for row in checkpoint["history"]]
    count = int(checkpoint["progress"].get("logged_rows", 0))
    if count == 0:
        return []
    candidates = [Path(path).expanduser().resolve().parent.parent / "metrics.jsonl"]
    if checkpoint.get("run_dir"):
        candidates.append(Path(checkpoint["run_dir"]) / "metrics.jsonl")
    for jsonl in candidates:
        if jsonl.is_file():
            with open(jsonl) as f:
                rows = [json.loads(line) for line, _ in zip(f, range(count))]
            if len(rows) == count:
                return [{k: float(v) if isinstance(v, str) else v for k, v in row.items()} for row in rows]
    warnings.warn(f"the metrics of the run before {str(path)!r} were not found ({candidates[0]} has fewer than "
                  f"{count} rows or is missing): the resumed run's metrics files start at the checkpoint",
                  stacklevel=2)
    return []


def plot_learning_curve(rows: Iterable[Mapping], path: str | Path, title: str = "") -> Path | None:
    """Draws ``eval/return``, ``eval/gymnasium_return`` and ``train/return`` against env steps into a PNG.

    Needs matplotlib (``pip install "torchrl_diffenvs[render]"``); returns ``None`` (and writes
    nothing) when it is not installed.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")  # no display needed
        import matplotlib.pyplot as plt
    except ImportError:
        return None

    def series(key):
        points = [(r["env_steps"], r[key]) for r in rows if key in r and math.isfinite(r[key])]
        return [p[0] for p in points], [p[1] for p in points]

    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=100)
    x, y = series("train/return")
    if x:
        ax.plot(x, y, color="tab:blue", alpha=0.45, linewidth=1, label="training episodes (stochastic)")
    x, y = series("eval/return")
    if x:
        ax.plot(x, y, color="tab:orange", marker="o", markersize=3, label="evaluation (deterministic)")
    x, y = series("eval/gymnasium_return")
    if x:
        ax.plot(x, y, color="tab:green", marker="s", markersize=3, label="evaluation in Gymnasium's own env")
    _, baseline = series("eval/random_return")
    if baseline:
        ax.axhline(baseline[0], color="grey", linestyle="--", linewidth=1, label="random policy")
    ax.set_xlabel("env steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
