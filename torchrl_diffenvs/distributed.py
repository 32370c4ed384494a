"""Data-parallel training across processes: what the learners and the training script need
from ``torch.distributed`` under ``torchrun``.

Each process (rank) simulates its own env batch from its own seed stream and computes its own
gradients; every gradient step first averages the gradients over the ranks (one all-reduce),
so every rank takes the same step and the networks and optimisers stay identical. What would
otherwise drift apart is reduced as well: observation-normaliser statistics are computed on
the observations of all ranks, PPO's advantage standardisation and value normaliser on the
union of the ranks' minibatches, the adaptive learning rate on the mean KL.

With equal per-rank batches this is the single-process algorithm on the concatenated batch:
``K`` ranks with ``N`` envs each take the steps of one process with ``K x N`` envs (up to
floating-point summation order), which ``tests/training/test_distributed.py`` checks in float64.

The learners hold a `World`; the default `SINGLE_PROCESS` makes every method a
no-op, so single-process code pays nothing. ``torchrun`` sets ``WORLD_SIZE``, ``RANK`` and
``LOCAL_RANK``; `World.from_environment` reads them and joins the process group (gloo on
CPU, NCCL on CUDA).

Why an explicit all-reduce rather than ``DistributedDataParallel``: TorchRL's loss modules call
their networks functionally (parameters held by the loss, not by one ``nn.Module`` forward), and
BPTT/SHAC backpropagate through a whole rollout window; DDP's hooks assume one module's forward
per backward. One flat all-reduce per optimiser step is what DDP would do, without the hooks.
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import os
from collections.abc import Iterable, Mapping, Sequence

import torch
import torch.distributed as dist
from tensordict import TensorDictBase

__all__ = ["SINGLE_PROCESS", "DistributedError", "World", "parameters_checksum", "rank_seed"]

# how far apart the ranks' seeds are: rank r of a run with seed s uses s + r * RANK_SEED_STRIDE,
# so that runs with nearby seeds do not share streams
RANK_SEED_STRIDE = 1_000_003


class DistributedError(RuntimeError):
    """The ranks disagree (configurations, parameters) or one of them is gone."""


def rank_seed(seed: int, rank: int) -> int:
    """The seed of rank ``rank``'s env and exploration streams (rank 0 keeps ``seed``, so a
    single-process run is unchanged)."""
    return int(seed) + int(rank) * RANK_SEED_STRIDE


@dataclasses.dataclass(frozen=True)
class World:
    """The process group a run trains in: ``size`` ranks, this process being ``rank``.

    ``World()`` is a single process (every collective returns its input).
    """

    size: int = 1
    rank: int = 0
    local_rank: int = 0
    backend: str | None = None

    # ------------------------------------------------------------------ setup
    @classmethod
    def from_environment(cls, device: torch.device | str = "cpu", timeout_s: float = 300.0) -> World:
        """The world ``torchrun`` describes in ``WORLD_SIZE`` / ``RANK`` / ``LOCAL_RANK``; joins
        the process group when there is more than one rank (gloo for CPU, NCCL for CUDA devices).

        A collective that waits longer than ``timeout_s`` for another rank (dead or stalled)
        raises instead of hanging.
        """
        size = int(os.environ.get("WORLD_SIZE", "1"))
        if size <= 1:
            return SINGLE_PROCESS
        rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
        backend = "nccl" if torch.device(device).type == "cuda" else "gloo"
        if not dist.is_available():
            raise DistributedError("WORLD_SIZE > 1 but this torch build has no torch.distributed")
        if not dist.is_initialized():
            if backend == "nccl":
                torch.cuda.set_device(local_rank)
            dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
        return cls(size=size, rank=rank, local_rank=local_rank, backend=backend)

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that evaluates, logs and writes checkpoints."""
        return self.rank == 0

    def device(self, device: torch.device | str) -> torch.device:
        """This rank's device: ``cuda`` becomes ``cuda:<local rank>`` (one GPU per rank)."""
        device = torch.device(device)
        if device.type == "cuda" and self.size > 1:
            return torch.device("cuda", self.local_rank)
        return device

    def close(self) -> None:
        """Leaves the process group."""
        if self.size > 1 and dist.is_initialized():
            dist.destroy_process_group()

    # ------------------------------------------------------------------ gradients
    @torch.no_grad()
    def average_gradients(self, params: Sequence[torch.Tensor]) -> None:
        """Replaces every ``p.grad`` by its mean over the ranks (one flat all-reduce per dtype and
        device).

        A gradient missing (``None``) on a rank counts as zero there; it stays ``None`` only
        where every rank lacks it (then the optimiser skips it, as a single process would).
        """
        if self.size == 1:
            return
        groups: dict[tuple, list[torch.Tensor]] = {}
        for p in params:
            groups.setdefault((p.dtype, p.device), []).append(p)
        for group in groups.values():
            present = torch.tensor([p.grad is not None for p in group], dtype=group[0].dtype, device=group[0].device)
            flat = torch.cat([present] + [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1)
                                          for p in group])
            self._all_reduce(flat, "gradients")
            offset = len(group)
            for p, seen in zip(group, flat[: len(group)].tolist()):
                if seen:
                    p.grad = flat[offset: offset + p.numel()].view_as(p) / self.size
                offset += p.numel()

    # ------------------------------------------------------------------ data and metrics
    def gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` (same shape on each) concatenated along dim 0, in rank order:
        what one process with all the ranks' envs would hold."""
        if self.size == 1:
            return tensor
        # through the backend's device (NCCL gathers CUDA tensors, gloo CPU ones), back on the tensor's
        where = tensor.device
        tensor = tensor.detach().to(self._backend_device()).contiguous()
        parts = [torch.empty_like(tensor) for _ in range(self.size)]
        self._call(dist.all_gather, parts, tensor, what="data")
        return torch.cat(parts, 0).to(where)

    def _backend_device(self) -> torch.device:
        """Where the backend's collectives take tensors: NCCL only CUDA ones, gloo CPU ones."""
        return torch.device("cuda", self.local_rank) if self.backend == "nccl" else torch.device("cpu")

    def mean(self, value: float) -> float:
        """The mean of a scalar over the ranks."""
        if self.size == 1:
            return value
        total = torch.tensor([float(value)], dtype=torch.float64, device=self._backend_device())
        self._all_reduce(total, "a scalar")
        return total.item() / self.size

    def mean_metrics(self, metrics: Mapping[str, float]) -> dict[str, float]:
        """Each metric averaged over the ranks that reported it (``"return"`` exists only on
        ranks where an episode finished)."""
        if self.size == 1:
            return dict(metrics)
        everyone = self.all_gather_object(dict(metrics))
        keys = dict.fromkeys(key for reported in everyone for key in reported)  # ordered union
        return {key: sum(r[key] for r in everyone if key in r) / sum(key in r for r in everyone) for key in keys}

    def all_gather_object(self, obj) -> list:
        """Every rank's picklable ``obj``, in rank order."""
        if self.size == 1:
            return [obj]
        out = [None] * self.size
        self._call(dist.all_gather_object, out, obj, what="objects")
        return out

    def gather_object(self, obj) -> list | None:
        """Every rank's picklable ``obj`` in rank order, on rank 0; ``None`` on the others.
        Tensors travel through the CPU (a rank's CUDA tensors would not unpickle on rank 0's GPU)."""
        if self.size == 1:
            return [obj]
        obj = _to_cpu(obj)
        out = [None] * self.size if self.is_main else None
        self._call(dist.gather_object, obj, out, 0, what="state for the checkpoint")
        return out

    def broadcast_object(self, obj):
        """Rank 0's picklable ``obj``, on every rank."""
        if self.size == 1:
            return obj
        box = [obj]
        self._call(dist.broadcast_object_list, box, 0, what="rank 0's decision")
        return box[0]

    def check_same(self, value: str, what: str) -> None:
        """Raises `DistributedError` on every rank unless all ranks hold the same ``value``
        (e.g. the configuration, a checksum of the initial parameters)."""
        if self.size == 1:
            return
        digests = self.all_gather_object(hashlib.sha256(value.encode()).hexdigest())
        differing = [rank for rank, digest in enumerate(digests) if digest != digests[0]]
        if differing:
            raise DistributedError(f"ranks {differing} have a different {what} than rank 0; every rank must be "
                                   "started with the same command line")

    # ------------------------------------------------------------------ plumbing
    def _all_reduce(self, tensor: torch.Tensor, what: str) -> None:
        self._call(dist.all_reduce, tensor, what=what)

    def _call(self, collective, *args, what: str):
        try:
            return collective(*args)
        except (RuntimeError, ConnectionError) as err:  # gloo / NCCL report a lost peer as RuntimeError
            raise DistributedError(
                f"rank {self.rank}: exchanging {what} with the other {self.size - 1} rank(s) failed: a rank died or "
                f"stalled past distributed.timeout_s ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}). "
                "Restart the run with resume=<run dir>/checkpoints/last.pt"
            ) from err


SINGLE_PROCESS = World()


def _to_cpu(obj):
    """``obj`` with its tensors (also inside dicts, lists, tuples and TensorDicts) on the CPU."""
    if isinstance(obj, (torch.Tensor, TensorDictBase)):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return type(obj)((key, _to_cpu(value)) for key, value in obj.items())
    if isinstance(obj, (list, tuple)) and type(obj) in (list, tuple):
        return type(obj)(_to_cpu(value) for value in obj)
    return obj


def parameters_checksum(tensors: Iterable[torch.Tensor]) -> str:
    """A string that differs when any of ``tensors`` differs (to compare ranks' initial networks)."""
    digest = hashlib.sha256()
    for t in tensors:
        digest.update(t.detach().cpu().reshape(-1).contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()
