"""A backward-only cap on the envs whose gradient explodes: the ``gradient_outlier_clip`` option.

Differentiating a window through stiff, switching contact, a few envs of a batch can carry a
gradient many orders of magnitude larger than the rest (a near-singular contact configuration,
an RK4 stage through a sticking foot): the batch's mean gradient is then theirs alone, and the
learner's guard skips the update. Capping each env's cotangent at a multiple of the batch's
median keeps those envs in the update at the size of the others and leaves every forward value
as it was.
"""
from __future__ import annotations

import torch

__all__ = ["clip_outlier_gradients", "check_outlier_clip"]


def check_outlier_clip(name: str, value) -> float | None:
    """``value`` as the option's float (``None``: off); a clear error unless it is ``None`` or a
    finite number >= 1."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 1.0 <= value < float("inf"):
        raise ValueError(f"{name}: gradient_outlier_clip must be None (off) or a finite number >= 1 (a multiple "
                         f"of the batch's median per-env gradient norm), got {value!r}")
    return float(value)


class _ClipOutlierGradients(torch.autograd.Function):
    """Identity forward; the backward caps each env's joint cotangent norm over the tensors at
    ``factor`` times the median over the envs whose cotangent is finite and nonzero."""

    @staticmethod
    def forward(ctx, factor, *tensors):
        ctx.factor = factor
        return tuple(t.view_as(t) for t in tensors)

    @staticmethod
    @torch.autograd.function.once_differentiable  # a second derivative through the cap is not defined here
    def backward(ctx, *grads):
        # float64: a float32 outlier of norm above ~1.8e19 (seen in training) would square to inf
        norm = sum(g.reshape(g.shape[0], -1).double().square().sum(-1) for g in grads).sqrt()  # [N]
        finite = torch.isfinite(norm)
        # envs with no gradient (reset this step, or outside the loss) do not set the scale
        median = torch.nanmedian(torch.where(finite & (norm > 0), norm, torch.nan))
        cap = ctx.factor * median  # NaN when no env has a gradient: then nothing is scaled
        scale = torch.where(norm > cap, cap / norm, torch.ones_like(norm))

        def shaped(g):
            per_env = (-1, *([1] * (g.ndim - 1)))
            return torch.where(finite.reshape(per_env), g * scale.reshape(per_env).to(g.dtype), torch.zeros_like(g))

        return (None, *(shaped(g) for g in grads))


def clip_outlier_gradients(factor: float | None, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The same ``tensors`` (each ``[N, ...]``, the envs first), whose backward caps each env's
    cotangent at ``factor`` times the batch's median.

    The forward returns the values unchanged, as views of the inputs (not to be modified in
    place). In the backward, env ``i``'s cotangent ``g_i`` (the Euclidean norm over all
    ``tensors`` together) becomes ``g_i * min(1, c / |g_i|)`` with ``c = factor * median_j
    |g_j|``, the median over the envs whose cotangent is finite and nonzero (for an even count,
    the lower of the two middle ones); an env with a NaN/inf cotangent gets zero (it is the
    extreme outlier), whether or not any other env has a gradient. ``factor=None``, or no tensor
    requiring grad, returns the tensors themselves. No host-device synchronisation. First order
    only: a double backward through it raises.

    >>> x = torch.ones(4, 2, requires_grad=True)
    >>> (y,) = clip_outlier_gradients(2.0, x)
    >>> (y * torch.tensor([[1.0], [1.0], [1.0], [100.0]])).sum().backward()
    >>> x.grad[:, 0]
    tensor([1., 1., 1., 2.])
    """
    if factor is None or not torch.is_grad_enabled() or not any(t.requires_grad for t in tensors):
        return tensors
    return _ClipOutlierGradients.apply(factor, *tensors)
