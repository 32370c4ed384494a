"""Per-env random streams for start states: env ``i``'s ``e``-th start state depends on
``(seed, i, e)`` only.

A counter-based generator: every random number is a hash of ``(seed, env index, episode count,
draw number, element index)``, computed with vectorised integer ops in torch. So env ``i`` gets
the same start states whatever the batch size, and whatever the other envs do (one env resetting
more often never shifts another env's later start states). The hash is Wellons' ``lowbias32``
on 32-bit words held in ``int64`` tensors, every product kept below ``2**63`` (no overflow, the
same bits on every device and under ``torch.compile``).
"""
from __future__ import annotations

import math

import torch

__all__ = ["StartDraw", "seed_words"]

_MASK32 = 0xFFFFFFFF


def _mul32(x, c: int):
    """``(x * c) mod 2**32`` for ``0 <= x < 2**32``, in two 16-bit halves of ``c`` (no int64 overflow)."""
    return (x * (c & 0xFFFF) + (((x * (c >> 16)) & 0xFFFF) << 16)) & _MASK32


def _hash32(x):
    """Wellons' ``lowbias32``: a bijection of 32-bit words with good avalanche (ints or int64 tensors)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def seed_words(seed: int) -> tuple[int, int]:
    """Two 32-bit keys of a (up to 64-bit) seed: two independent hash chains per draw."""
    seed = int(seed) & ((1 << 64) - 1)
    low, high = seed & _MASK32, seed >> 32
    return _hash32(low ^ _hash32(high ^ 0x9E3779B9)), _hash32(high ^ _hash32(low ^ 0x85EBCA6B))


class StartDraw:
    """The random numbers of one ``initial_state`` call for envs ``index`` at episode ``episode``.

    Each :meth:`uniform` / :meth:`normal` call takes the next draw number, so the numbers of a
    task's ``initial_state`` are those of its ``k``-th sampler call, element by element, for each
    env: independent of the batch and of how often the other envs were reset.
    """

    def __init__(self, words: tuple[int, int], index: torch.Tensor, episode: torch.Tensor):
        index = index.to(torch.int64)
        episode = episode.to(torch.int64) & _MASK32
        self.key_a = _hash32(_hash32(words[0] ^ index) ^ episode)
        self.key_b = _hash32(_hash32(words[1] ^ (index ^ 0x27D4EB2F)) ^ episode)
        self.calls = 0

    def _bits(self, shape: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        """Two independent 32-bit words per element of ``[n, *shape[1:]]``."""
        n = self.key_a.shape[0]
        if not shape or shape[0] != n:
            raise ValueError(
                f"start-state samplers draw one row per env being reset: the first dim of the shape must be "
                f"n={n}, got shape {tuple(shape)}"
            )
        event = math.prod(shape[1:])
        call = _hash32(self.calls + 0x165667B1)
        self.calls += 1
        element = _hash32(torch.arange(event, dtype=torch.int64, device=self.key_a.device) ^ call)
        a, b = self.key_a.unsqueeze(-1), self.key_b.unsqueeze(-1)
        bits_a = _hash32(a ^ _hash32(b ^ element))
        bits_b = _hash32(b ^ _hash32(a ^ (element ^ 0x5BD1E995)))
        return bits_a.reshape(shape), bits_b.reshape(shape)

    def uniform(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """``U[0, 1)`` of ``shape`` (every value a multiple of ``2**-24`` in float32, ``2**-53`` in float64)."""
        bits_a, bits_b = self._bits(shape)
        if dtype == torch.float64:
            return ((bits_a >> 5) * (1 << 26) + (bits_b >> 6)).to(dtype) * 2.0**-53
        return (bits_a >> 8).to(dtype) * 2.0**-24

    def normal(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """Standard normal samples (Box-Muller on two uniform draws)."""
        u1, u2 = self.uniform(shape, dtype), self.uniform(shape, dtype)
        return torch.sqrt(-2.0 * torch.log1p(-u1)) * torch.cos((2 * math.pi) * u2)
