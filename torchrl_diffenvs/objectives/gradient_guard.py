"""Gradient safety shared by the gradient-based learners: clip, and never apply a bad step."""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import torch

__all__ = ["GradientGuard", "NonFiniteTrainingError"]


class NonFiniteTrainingError(RuntimeError):
    """Training cannot go on: too many consecutive updates had a NaN/inf loss or gradient."""


class GradientGuard:
    """Clips the gradient (its norm, or each element) and skips optimiser steps whose gradient is unusable.

    Differentiating through long rollouts can produce exploding or non-finite gradients (chaotic
    dynamics, a NaN reward). [`step`][torchrl_diffenvs.objectives.GradientGuard.step] computes the total pre-clip gradient norm of
    ``parameters``; if it is NaN/inf or above ``skip_above`` (or the ``loss`` value passed in is
    NaN/inf: a NaN that does not depend on the parameters, e.g. ``reward + nan``, leaves the
    gradient finite), the optimiser step is *not* taken (parameters and optimiser state stay
    exactly as they were) and `skipped` is incremented. Otherwise the gradients are clipped
    to ``max_norm`` and the step is taken.

    A NaN/inf loss or gradient now and then is survivable; ``max_nonfinite_skips`` of them in a
    row are not (nothing has been learned since): [`step`][torchrl_diffenvs.objectives.GradientGuard.step] then raises a
    [`NonFiniteTrainingError`][torchrl_diffenvs.objectives.NonFiniteTrainingError] naming the likely causes.

    The caller zeroes gradients before its backward pass as usual.

    Args:
        max_norm: clip the total gradient norm to this value; ``None`` disables clipping.
        clip: ``"norm"`` (default: scale the whole gradient so its norm is at most ``max_norm``,
            keeping its direction) or ``"elementwise"`` (clamp every element to
            ``[-max_norm, max_norm]``, as Brax's APG does with ``optax.clip``).
        skip_above: skip the step when the pre-clip norm exceeds this; ``None`` skips only on
            NaN/inf.
        max_nonfinite_skips: raise after this many consecutive steps skipped for a NaN/inf loss
            or gradient (steps skipped for a finite norm above ``skip_above`` do not count);
            ``None`` never raises.

    For example:

    ```python
    guard = GradientGuard(max_norm=1.0, skip_above=1e6)
    optimizer.zero_grad()
    loss.backward()
    info = guard.step(optimizer, actor.parameters(), loss=loss)  # {"grad_norm": ..., "skipped": False}
    ```
    """

    def __init__(self, max_norm: float | None = 1.0, skip_above: float | None = 1e6, clip: str = "norm",
                 max_nonfinite_skips: int | None = 20):
        if max_norm is not None and not max_norm > 0:
            raise ValueError(f"GradientGuard: max_norm must be > 0 or None, got {max_norm!r}")
        if skip_above is not None and not skip_above > 0:
            raise ValueError(f"GradientGuard: skip_above must be > 0 or None, got {skip_above!r}")
        if clip not in self.CLIP_MODES:
            raise ValueError(f"GradientGuard: clip must be one of {self.CLIP_MODES}, got {clip!r}")
        if max_nonfinite_skips is not None and (isinstance(max_nonfinite_skips, bool) or
                                                not isinstance(max_nonfinite_skips, int) or max_nonfinite_skips < 1):
            raise ValueError(f"GradientGuard: max_nonfinite_skips must be a positive integer or None, "
                             f"got {max_nonfinite_skips!r}")
        self.max_nonfinite_skips = max_nonfinite_skips
        self.nonfinite_in_a_row = 0
        self.clip = clip
        self.max_norm = max_norm
        self.skip_above = skip_above
        self.skipped = 0
        self.steps = 0

    CLIP_MODES = ("norm", "elementwise")

    def step(
        self,
        optimizer: torch.optim.Optimizer,
        parameters: Iterable[torch.Tensor] | None = None,
        loss: torch.Tensor | float | None = None,
        context: Callable[[], str] | None = None,
    ) -> dict:
        """Checks, clips and (if safe) applies one optimiser step.

        Args:
            optimizer: the optimiser to step.
            parameters: the parameters whose gradients are checked and clipped; defaults to every
                parameter of ``optimizer``.
            loss: the loss the gradient comes from; a NaN/inf value skips the step.
            context: called only to build the error message when training must stop (e.g.
                which envs were non-finite).

        Returns:
            ``{"grad_norm": float (pre-clip), "skipped": bool}``.
        """
        if parameters is None:
            parameters = [p for group in optimizer.param_groups for p in group["params"]]
        params = [p for p in parameters if p.grad is not None]
        if params:
            norm = torch.linalg.vector_norm(
                torch.stack([torch.linalg.vector_norm(p.grad.detach(), dtype=torch.float64) for p in params])
            ).item()
        else:
            norm = 0.0
        self.steps += 1
        if isinstance(loss, torch.Tensor):
            loss = loss.detach()
        loss_ok = loss is None or math.isfinite(float(loss))
        if not loss_ok or not math.isfinite(norm):
            self.skip(context)
            return {"grad_norm": norm, "skipped": True}
        self.nonfinite_in_a_row = 0
        if self.skip_above is not None and norm > self.skip_above:
            self.skipped += 1
            return {"grad_norm": norm, "skipped": True}
        if self.max_norm is not None and self.clip == "elementwise":
            for p in params:
                p.grad.detach().clamp_(-self.max_norm, self.max_norm)
        elif self.max_norm is not None and norm > self.max_norm:
            scale = self.max_norm / (norm + 1e-6)
            for p in params:
                p.grad.detach().mul_(scale)
        optimizer.step()
        return {"grad_norm": norm, "skipped": False}

    def skip(self, context: Callable[[], str] | None = None) -> None:
        """Counts a step skipped for a non-finite loss or gradient (also one the caller could not
        even compute, e.g. when every env of the batch was non-finite); raises a
        [`NonFiniteTrainingError`][torchrl_diffenvs.objectives.NonFiniteTrainingError] when that makes ``max_nonfinite_skips`` in a row."""
        self.skipped += 1
        self.nonfinite_in_a_row += 1
        if self.max_nonfinite_skips is not None and self.nonfinite_in_a_row >= self.max_nonfinite_skips:
            detail = f" ({context()})" if context is not None else ""
            raise NonFiniteTrainingError(
                f"{self.nonfinite_in_a_row} consecutive updates skipped because the loss or gradient was NaN/inf"
                f"{detail}; likely causes: non-finite physical parameters (a NaN or inf param) or a diverging "
                "simulation; check the env's parameters, or lower the learning rate or the gradient clip"
            )

    def state_dict(self) -> dict:
        """Its counters: updates skipped, updates seen, non-finite gradients in a row (for a checkpoint)."""
        return {"skipped": self.skipped, "steps": self.steps, "nonfinite_in_a_row": self.nonfinite_in_a_row}

    def load_state_dict(self, state: dict) -> None:
        """Restores `state_dict`."""
        self.skipped = int(state["skipped"])
        self.steps = int(state["steps"])
        self.nonfinite_in_a_row = int(state.get("nonfinite_in_a_row", 0))  # absent from older checkpoints

    def __repr__(self) -> str:
        return (f"GradientGuard(max_norm={self.max_norm}, clip={self.clip!r}, skip_above={self.skip_above}, "
                f"skipped={self.skipped}/{self.steps})")
