"""Observation normalisation with statistics frozen inside the autograd graph."""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["ObservationNormalizer"]


class ObservationNormalizer(nn.Module):
    """``(x - mean) / max(sqrt(var + eps), min_std)`` with running statistics that change only in
    [`update`][torchrl_diffenvs.modules.ObservationNormalizer.update].

    Design: the normaliser is an ``nn.Module`` placed as the first layer of the actor and critic
    networks (``make_actor(env, normalizer=norm)``, ``make_critic(env, normalizer=norm)``; pass the
    *same* instance to both). Its statistics are buffers, so they are saved in the actor's and the
    critic's ``state_dict`` and an exported actor carries its normalisation with it.

    Calling the module never changes the statistics: they are frozen for the duration of a
    rollout window, so every step of the window and the backward pass see the same affine map
    (gradients flow through it to the observation). The training loop calls [`update`][torchrl_diffenvs.modules.ObservationNormalizer.update] with
    the window's raw observations *after* the backward pass; [`update`][torchrl_diffenvs.modules.ObservationNormalizer.update] works in place under
    ``no_grad`` and ignores rows that contain NaN/inf.

    Statistics are merged with Chan et al.'s parallel algorithm; before the first update the map
    is the identity (mean 0, var 1).

    Args:
        dim: observation size (last dimension).
        eps: added to the variance before the square root.
        min_std: the smallest divisor: a feature that barely varies (a contact force while the
            robot is in the air) is amplified at most ``1 / min_std`` times, so its derivatives
            do not swamp the others' (TorchRL's ``VecNorm`` floors its std at 1e-2 alike).
        clip: if given, normalised values are clamped to ``[-clip, clip]`` (which zeroes their
            gradient outside that range); ``None`` (default) does not clamp.
        dtype: dtype of the statistics and of the output.
    """

    def __init__(self, dim: int, eps: float = 1e-5, clip: float | None = None, dtype: torch.dtype = torch.float32,
                 min_std: float = 1e-2):
        super().__init__()
        if not isinstance(dim, int) or dim < 1:
            raise ValueError(f"ObservationNormalizer: dim must be a positive integer, got {dim!r}")
        if not (isinstance(min_std, (int, float)) and 0.0 <= min_std < float("inf")):
            raise ValueError(f"ObservationNormalizer: min_std must be a finite number >= 0, got {min_std!r}")
        self.eps = eps
        self.min_std = float(min_std)
        self.clip = clip
        self.register_buffer("mean", torch.zeros(dim, dtype=dtype))
        self.register_buffer("var", torch.ones(dim, dtype=dtype))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = (x - self.mean) / torch.sqrt(self.var + self.eps).clamp(min=self.min_std)
        if self.clip is not None:
            out = out.clamp(-self.clip, self.clip)
        return out

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merges the observations ``x`` (``[..., dim]``) into the running statistics."""
        if x.shape[-1] != self.mean.shape[0]:
            raise ValueError(
                f"ObservationNormalizer.update: expected observations of size {self.mean.shape[0]} in the last "
                f"dimension, got shape {tuple(x.shape)}"
            )
        x = x.detach().reshape(-1, x.shape[-1])
        x = x[torch.isfinite(x).all(-1)].to(torch.float64)
        n = x.shape[0]
        if n == 0:
            return
        batch_mean, batch_var = x.mean(0), x.var(0, unbiased=False)
        mean, var, count = self.mean.to(torch.float64), self.var.to(torch.float64), self.count
        total = count + n
        delta = batch_mean - mean
        new_mean = mean + delta * n / total
        new_var = (var * count + batch_var * n + delta**2 * count * n / total) / total
        # in place, so that every holder of these buffers (e.g. a loss module's parameter
        # TensorDict) sees the new values
        self.mean.copy_(new_mean)
        self.var.copy_(new_var)
        self.count.copy_(total)

    def extra_repr(self) -> str:
        return f"dim={self.mean.shape[0]}, eps={self.eps}, clip={self.clip}, count={int(self.count)}"
