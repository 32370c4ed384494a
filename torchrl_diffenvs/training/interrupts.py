"""Stopping a run cleanly on SIGTERM (a cluster's preemption, e.g. Slurm's) or Ctrl-C (SIGINT).

While training, `StopRequests` replaces the two signals' handlers: the first signal only
records the request, so the current iteration finishes, the loop writes a checkpoint and raises
`TrainingInterrupted`, whose message is the ``resume=`` command. A second Ctrl-C raises
``KeyboardInterrupt`` at once, as Python's default does (the last checkpoint written stays the
resume point). The previous handlers come back when training ends.
"""
from __future__ import annotations

import logging
import signal
import threading
from pathlib import Path

__all__ = ["StopRequests", "TrainingInterrupted"]

log = logging.getLogger("train")

_NAMES = {signal.SIGINT: "Ctrl-C (SIGINT)", signal.SIGTERM: "SIGTERM"}


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by a signal. ``str(err)`` says where and how to continue.

    Attributes:
        checkpoint: the checkpoint to resume from (``None`` when none was written yet).
        reason: what stopped it (``"SIGTERM"``, ``"Ctrl-C (SIGINT)"``, ...).
        exit_code: the conventional exit status for the signal (128 + its number).
    """

    def __init__(self, message: str, checkpoint: Path | None = None, reason: str = "Ctrl-C"):
        super().__init__(message)
        self.checkpoint, self.reason = checkpoint, reason
        self.exit_code = 128 + (signal.SIGTERM if reason == "SIGTERM" else signal.SIGINT)


class StopRequests:
    """A context manager that turns SIGINT / SIGTERM into a request (`requested`, the
    signal's name) that the loop acts on between iterations. Outside the main thread (where
    Python cannot install handlers) it does nothing."""

    def __init__(self):
        self.requested: str | None = None
        self._previous: dict = {}

    def _handle(self, signum, frame):
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt  # the second Ctrl-C: stop now
        self.requested = _NAMES.get(signum, f"signal {signum}")
        log.warning(f"{self.requested}: stopping after this iteration and writing a checkpoint "
                    "(Ctrl-C again to stop at once, without one)")

    def __enter__(self) -> StopRequests:
        if threading.current_thread() is threading.main_thread():
            for signum in _NAMES:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
