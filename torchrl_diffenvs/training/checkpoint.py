"""Atomic checkpoints and random-generator snapshots.

A checkpoint is a plain ``dict`` of tensors, numbers, strings, lists and dicts, saved with
``torch.save`` and read back with ``torch.load(weights_only=True)``: loading never unpickles
arbitrary objects, so a checkpoint from elsewhere cannot run code.

Writes are atomic: the file is written to a temporary name in the same directory, flushed to disk,
and only then renamed over the destination (``os.replace``). A crash, a full disk or an exception
half-way through a write leaves the previous checkpoint untouched.
"""
from __future__ import annotations

import os
import random
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "atomic_copy",
    "capture_rng_state",
    "load_checkpoint",
    "restore_rng_state",
    "save_checkpoint",
]

CHECKPOINT_FORMAT = "torchrl_diffenvs.train/2"  # 2: one learner per algorithm (torchrl_diffenvs.learners)


class CheckpointError(RuntimeError):
    """A file that is not a readable checkpoint of this training script (corrupt, truncated, foreign)."""


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def _replace_durably(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)
    try:  # make the rename itself durable (POSIX); not possible everywhere, and not needed for correctness
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_checkpoint(state: Mapping, path: str | os.PathLike) -> Path:
    """Writes ``state`` (plus a format tag) to ``path`` atomically; returns the path.

    The previous file at ``path``, if any, is replaced only once the new one is completely on
    disk; if anything fails, it is left as it was and the temporary file is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(path)
    try:
        with open(tmp, "wb") as f:
            torch.save({"format": CHECKPOINT_FORMAT, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        _replace_durably(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_copy(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copies ``src`` to ``dst`` with the same all-or-nothing guarantee as :func:`save_checkpoint`."""
    dst = Path(dst)
    tmp = _tmp_name(dst)
    try:
        shutil.copyfile(src, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        _replace_durably(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)
    return dst


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """Reads a checkpoint written by :func:`save_checkpoint`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        CheckpointError: the file is truncated, corrupt, or not a checkpoint of this script.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:
        raise CheckpointError(
            f"{str(path)!r} is not a readable checkpoint (truncated or corrupt file?): {type(err).__name__}: {err}"
        ) from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(
            f"{str(path)!r} is not a checkpoint of sota_scripts/train.py (format {found!r}, expected "
            f"{CHECKPOINT_FORMAT!r})"
        )
    return state


# ---------------------------------------------------------------------- random generators
def capture_rng_state(generators: Mapping[str, torch.Generator] | None = None) -> dict:
    """Snapshots torch's, CUDA's, numpy's and Python's global generators and the named ``generators``."""
    np_state = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), *[float(x) for x in np_state[2:]]],
        "python": random.getstate(),
        "generators": {name: g.get_state() for name, g in (generators or {}).items()},
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: Mapping, generators: Mapping[str, torch.Generator] | None = None) -> None:
    """Restores a :func:`capture_rng_state` snapshot (the named ``generators`` in place)."""
    # generator states are CPU byte tensors, whatever map_location the checkpoint was loaded with
    torch.set_rng_state(state["torch"].cpu())
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.cpu().numpy().astype(np.uint32), int(pos), int(has_gauss), float(cached)))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
    saved = state.get("generators", {})
    for gen_name, gen in (generators or {}).items():
        if gen_name in saved:
            gen.set_state(saved[gen_name].cpu())
