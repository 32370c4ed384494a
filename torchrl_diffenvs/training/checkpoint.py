"""Atomic checkpoints and random-generator snapshots.

A checkpoint is a plain ``dict`` of tensors, numbers, strings, lists and dicts, saved with
``torch.save`` and read back with ``torch.load(weights_only=True)``: loading never unpickles
arbitrary objects, so a checkpoint from elsewhere cannot run code.

Writes are atomic: the file is written to a temporary name in the same directory, flushed to disk,
and only then renamed over the destination (``os.replace``). A crash, a full disk or an exception
half-way through a write leaves the previous checkpoint untouched; the temporary file a killed
process leaves behind is removed by the next run that starts in (or resumes from) that directory
(`remove_stale_temp_files`).

Every checkpoint carries a SHA-256 checksum of its content (each tensor's bytes, dtype and shape,
and every other value), verified on load: a file altered after it was written (a flipped bit on
disk, a copy cut short inside a tensor) is refused with `CheckpointError` instead of
resuming or evaluating altered weights.
"""
from __future__ import annotations

import hashlib
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
    "checksum",
    "load_checkpoint",
    "remove_stale_temp_files",
    "restore_rng_state",
    "save_checkpoint",
]

# 3: a checksum, and no logged history (the run directory's metrics.jsonl holds it)
CHECKPOINT_FORMAT = "torchrl_diffenvs.train/3"
_READABLE_FORMATS = ("torchrl_diffenvs.train/2", CHECKPOINT_FORMAT)  # 2: no checksum to verify


class CheckpointError(RuntimeError):
    """A file that is not a readable checkpoint of this training script (corrupt, truncated, foreign)."""


_TMP_MARK = ".tmp-"


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}{_TMP_MARK}{os.getpid()}")


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists, owned by someone else
    return True


def remove_stale_temp_files(directory: str | os.PathLike) -> list[Path]:
    """Removes the temporary files that interrupted writes (a killed process) left in
    ``directory``: ``.<name>.tmp-<pid>`` whose process no longer runs. Returns them."""
    removed = []
    directory = Path(directory)
    if not directory.is_dir():
        return removed
    for path in directory.glob(f".*{_TMP_MARK}*"):
        pid = path.name.rpartition(_TMP_MARK)[2]
        if pid.isdigit() and (int(pid) == os.getpid() or not _process_alive(int(pid))):
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def _digest(value, h) -> None:
    """Feeds ``value`` (nested dicts / lists / tuples of tensors and plain values) into ``h``."""
    if isinstance(value, torch.Tensor):
        t = value.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(value, Mapping):
        h.update(f"D{len(value)}".encode())
        for key, item in value.items():
            h.update(repr(key).encode())
            _digest(item, h)
    elif isinstance(value, (list, tuple)):
        h.update(f"{type(value).__name__[0]}{len(value)}".encode())
        for item in value:
            _digest(item, h)
    else:
        h.update(repr(value).encode())


def checksum(state: Mapping) -> str:
    """SHA-256 of a checkpoint's content (every key but ``"checksum"``), independent of the
    device its tensors are on."""
    h = hashlib.sha256()
    _digest({k: v for k, v in state.items() if k != "checksum"}, h)
    return h.hexdigest()


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
        content = {"format": CHECKPOINT_FORMAT, **state}
        content["checksum"] = checksum(content)
        with open(tmp, "wb") as f:
            torch.save(content, f)
            f.flush()
            os.fsync(f.fileno())
        _replace_durably(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_copy(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copies ``src`` to ``dst`` with the same all-or-nothing guarantee as `save_checkpoint`."""
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
    """Reads a checkpoint written by `save_checkpoint`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        CheckpointError: ``path`` is a directory, or the file is truncated, corrupt (its checksum
            does not match its content), or not a checkpoint of this script.
    """
    path = Path(path).expanduser()
    if path.is_dir():
        found = [p for p in (path / "checkpoints" / "last.pt", path / "last.pt") if p.is_file()]
        hint = f"; did you mean {str(found[0])!r}?" if found else ""
        raise CheckpointError(f"{str(path)!r} is a directory, not a checkpoint file (<run dir>/checkpoints/last.pt "
                              f"or ckpt_<env steps>.pt){hint}")
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:
        raise CheckpointError(
            f"{str(path)!r} is not a readable checkpoint (truncated or corrupt file?): {type(err).__name__}: {err}"
        ) from None
    if not isinstance(state, dict) or state.get("format") not in _READABLE_FORMATS:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(
            f"{str(path)!r} is not a checkpoint of sota_scripts/train.py (format {found!r}, expected "
            f"{CHECKPOINT_FORMAT!r})"
        )
    if state["format"] == CHECKPOINT_FORMAT and state.get("checksum") != checksum(state):
        raise CheckpointError(f"{str(path)!r} is corrupt: its content does not match the checksum written with it "
                              "(altered on disk or copied incompletely); use another checkpoint of the run "
                              "(checkpoints/ckpt_<env steps>.pt)")
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
    """Restores a `capture_rng_state` snapshot (the named ``generators`` in place)."""
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
