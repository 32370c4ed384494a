"""Iterative solves on a GPU without host-device synchronisation, stopped early all the same.

A batched solve that holds its converged envs by a mask gives the same result after any number
of extra rounds. On CUDA, `ConvergenceWatch` lets the host stop issuing rounds once every env
has converged, without ever waiting for the device: after a round the flag ``done.all()`` is
copied to pinned host memory asynchronously and an event is recorded behind the copy; later
rounds ask whether the event has completed (a query, not a synchronisation) and read the flag
only then. The host stops a few rounds after the device got there, instead of running every
allowed round (a GPU step of MuJoCo's HalfCheetah launched 11x fewer kernels, docs/performance.md).
"""
from __future__ import annotations

import torch

__all__ = ["ConvergenceWatch", "reads_data_freely"]


def reads_data_freely(device: torch.device) -> bool:
    """Whether the step may look at the data to skip work (converged envs, geom pairs too far apart
    to touch, contact slots and rows no env needs): eagerly on the CPU, where it costs nothing; not
    on a GPU (a host-device synchronisation) nor under ``torch.compile`` (a graph break).

    Args:
        device: the device the step's tensors are on.
    """
    return device.type == "cpu" and not torch.compiler.is_compiling()


class ConvergenceWatch:
    """Tells the host, without making it wait, that every env of a masked CUDA solve is done.

    ``ConvergenceWatch.for_device(device)`` is ``None`` where it does not apply (a CPU, which
    reads the data for free, or a stream being captured into a CUDA graph, whose rounds are
    fixed when replayed). In the loop: ``if watch is not None and watch.all_done(done): break``.
    """

    def __init__(self):
        self.flag = torch.zeros((), dtype=torch.bool, pin_memory=True)
        self.event = torch.cuda.Event()
        self.pending = False

    @classmethod
    def for_device(cls, device: torch.device) -> ConvergenceWatch | None:
        """A watch for ``device``'s solves: on CUDA a new one; ``None`` on the CPU (which reads the flags
        directly) and while a CUDA graph is being captured."""
        if device.type != "cuda":
            return None
        with torch.cuda.device(device):
            return None if torch.cuda.is_current_stream_capturing() else cls()

    def all_done(self, done: torch.Tensor) -> bool:
        """Whether a flag copied after an earlier round says every env was done by then (the
        rounds since are no-ops); else queue this round's flag, if the last copy has landed."""
        if self.pending:
            if not self.event.query():
                return False
            self.pending = False
            if bool(self.flag):  # the copy has landed: reading pinned host memory does not synchronise
                return True
        self.flag.copy_(done.all(), non_blocking=True)
        self.event.record(torch.cuda.current_stream(done.device))  # behind the copy, on its device's stream
        self.pending = True
        return False
