"""Per-env random streams for start states: env ``i``'s ``e``-th start state depends on
``(seed, i, e)`` only.

A counter-based generator: every random number is a hash (splitmix64) of ``(seed, env index,
episode count, draw number, element index)``. So env ``i`` gets the same start states whatever
the batch size, and whatever the other envs do (one env resetting more often never shifts
another env's later start states). The hashing runs vectorised in numpy on the CPU, where
unsigned 64-bit arithmetic wraps as the hash needs (a handful of array operations per draw,
about as cheap as ``torch.rand`` for small batches); the samples then go to the env's device.
"""
from __future__ import annotations

import hashlib
import math
import warnings

import numpy as np
import torch

__all__ = ["EnvGenerator", "StartDraw", "env_index_keys", "seed_key"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31 = np.uint64(30), np.uint64(27), np.uint64(31)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: a bijection of 64-bit words with full avalanche (wrapping arithmetic)."""
    x = x ^ (x >> _S30)  # a new array: the input is left as it is, the rest works in place
    x *= _M1
    x ^= x >> _S27
    x *= _M2
    x ^= x >> _S31
    return x


_MASK64 = (1 << 64) - 1


def _mix_int(x: int) -> int:
    """`_mix` of one Python int (no numpy scalar overflow warnings)."""
    x &= _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def seed_key(seed: int) -> np.uint64:
    """The 64-bit key of a seed (any Python int; taken modulo ``2**64``)."""
    return np.uint64(_mix_int(int(seed) + 0x9E3779B97F4A7C15))


def _as_words(values: torch.Tensor) -> np.ndarray:
    """An integer tensor's values as 64-bit words (int64's bits as they are: no copy on the CPU)."""
    values = values.detach().cpu().numpy()
    return values.view(np.uint64) if values.dtype == np.int64 else values.astype(np.uint64)


def env_index_keys(key: np.uint64, index: torch.Tensor) -> np.ndarray:
    """``[n]``: the part of each env's stream key that depends on the seed's key and its index only."""
    return _mix(key ^ (_as_words(index) * _GOLDEN))


_POSITIONS: dict[tuple[int, int], np.ndarray] = {}


def _positions(start: int, count: int) -> np.ndarray:
    """``[count]``: the hashed-in offsets of stream positions ``start ... start + count - 1`` (cached)."""
    positions = _POSITIONS.get((start, count))
    if positions is None:
        positions = np.arange(start + 1, start + count + 1, dtype=np.uint64) * _GOLDEN
        if len(_POSITIONS) < 4096:
            _POSITIONS[(start, count)] = positions
    return positions


def _to_uniform(bits: np.ndarray, dtype: torch.dtype, device) -> torch.Tensor:
    """``U[0, 1)`` values of 64-bit words: the top 53 (float64) or 24 (float32) bits."""
    if dtype == torch.float64:
        values = (bits >> np.uint64(11)).astype(np.float64) * 2.0**-53
    else:
        values = (bits >> np.uint64(40)).astype(np.float32) * np.float32(2.0**-24)
    return torch.from_numpy(values).to(device=device, dtype=dtype)


class StartDraw:
    """The random numbers of one ``initial_state`` call for envs ``index`` at episode ``episode``.

    Env ``i``'s stream is a sequence of 64-bit words, word ``p`` a hash of (its key, ``p``);
    each `uniform` / `normal` call takes the next words (``calls`` is the position),
    the same for every env, so the numbers of a task's ``initial_state`` are, element by
    element, independent of the batch and of how often the other envs reset.

    ``block``: how many words to hash at once up front (the words the task's previous
    ``initial_state`` used: one hash of the whole block instead of one per call); a call beyond
    it is hashed on its own, with the same result.
    """

    def __init__(self, key: np.uint64, index: torch.Tensor, episode: torch.Tensor, block: int = 0,
                 index_keys: np.ndarray | None = None):
        self.device = index.device
        # (array arithmetic wraps modulo 2**64 silently, as the hash needs; int64 -> uint64 is a
        # reinterpretation of the same bits, as astype would give)
        if index_keys is None:  # (the env caches them: they depend on the seed and the batch only)
            index_keys = env_index_keys(key, index)
        episode = _as_words(episode)
        self.env_keys = _mix(index_keys + episode * _M1)  # [n]
        self.calls = 0  # the next word's position
        self.used = 0  # the last position + 1 of the main words (not those of redraws)
        self.block = None
        self.block = self._words(0, block) if block > 0 else None
        self.block_values: dict = {}  # dtype -> the block's uniform samples, converted once

    def _words(self, start: int, count: int) -> np.ndarray:
        """``[n, count]``: the words at positions ``start ... start + count - 1`` of every env."""
        if self.block is not None and start + count <= self.block.shape[1]:
            return self.block[:, start:start + count]
        return _mix(self.env_keys[:, None] ^ _positions(start, count)[None, :])

    def _take(self, shape: tuple[int, ...]) -> tuple[int, int]:
        """The positions ``(start, count)`` of the next draw of one word per element of ``shape``."""
        n = self.env_keys.shape[0]
        if not shape or shape[0] != n:
            raise ValueError(
                f"start-state samplers draw one row per env being reset: the first dim of the shape must be "
                f"n={n}, got shape {tuple(shape)}"
            )
        start, event = self.calls, math.prod(shape[1:])
        self.calls += event
        if self.calls < 1 << 20:  # a main draw (redraws take positions from 2**20 on)
            self.used = max(self.used, self.calls)
        return start, event

    def _bits(self, shape: tuple[int, ...]) -> np.ndarray:
        """One 64-bit word per element of ``shape`` (``[n, ...]``), from the next draw number."""
        start, event = self._take(shape)
        return self._words(start, event).reshape(shape)

    def uniform(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """``U[0, 1)`` of ``shape``: every value a multiple of ``2**-24`` (float32) or ``2**-53`` (float64).

        Draws within the block hashed up front are slices of the block converted once (the same
        values element by element)."""
        start, event = self._take(shape)
        if self.block is not None and start + event <= self.block.shape[1]:
            values = self.block_values.get(dtype)
            if values is None:
                values = self.block_values[dtype] = _to_uniform(self.block, dtype, self.device)
            return values[:, start:start + event].reshape(shape)
        return _to_uniform(self._words(start, event).reshape(shape), dtype, self.device)

    def normal(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """Standard normal samples (Box-Muller on two uniform draws)."""
        u1, u2 = self.uniform(shape, dtype), self.uniform(shape, dtype)
        return torch.sqrt(-2.0 * torch.log1p(-u1)) * torch.cos((2 * math.pi) * u2)


_CUDA_STATE_BYTES = 16  # a CUDA generator's state: its Philox seed and offset, 8 bytes each


def _cpu_state_bytes() -> int:
    return torch.Generator().get_state().numel()


class EnvGenerator(torch.Generator):
    """``env.rng``: a ``torch.Generator`` that also holds the env's start-state streams.

    ``key`` (the seed's 64-bit key, `seed_key`) and ``episodes`` (``[N]`` int64, on the
    env's device: how many start states each env has drawn) say where every env's stream is.
    `get_state` appends them to the generator's own state, so everything that saves and
    restores ``env.rng`` (checkpoints, ``DiffWindowCollector.state_dict``) resumes the start
    states exactly too; `set_state` also takes a plain generator state (the streams are
    then left as they are).
    """

    def __new__(cls, device, num_envs: int, seed: int):  # torch.Generator takes its arguments in __new__
        return super().__new__(cls, device)

    def __init__(self, device, num_envs: int, seed: int):
        self.manual_seed(seed)
        self.key = seed_key(seed)
        self.episodes = torch.zeros(num_envs, dtype=torch.int64, device=device)

    def __reduce__(self):  # pickling and deepcopy (torch.Generator's would rebuild a plain Generator)
        return _rebuild_env_generator, (str(self.device), self.episodes.numel(), self.get_state())

    def __deepcopy__(self, memo):
        return _rebuild_env_generator(str(self.device), self.episodes.numel(), self.get_state())

    def get_state(self) -> torch.Tensor:
        counts = self.episodes.detach().cpu()
        tail = torch.tensor([int(self.key) - (1 << 64 if int(self.key) >= 1 << 63 else 0), counts.numel()],
                            dtype=torch.int64)
        return torch.cat([super().get_state(), counts.view(torch.uint8), tail.view(torch.uint8)])

    def _set_own_state(self, own: torch.Tensor, streams: str) -> None:
        """The generator's own state; one saved by a generator on the other kind of device (a CPU
        generator's Mersenne Twister state against a CUDA generator's Philox seed and offset: a run
        resumed on another device) cannot be loaded, and seeds this one instead (deterministically).
        ``streams`` says, for the warning, what happens to the start-state streams."""
        size, own_size = own.numel(), super().get_state().numel()
        if size == own_size:
            super().set_state(own)
            return
        other = {"cpu": ("cuda", _CUDA_STATE_BYTES), "cuda": ("cpu", _cpu_state_bytes())}.get(self.device.type)
        if other is None or size != other[1]:
            raise ValueError(f"env.rng.set_state: a generator state of {size} bytes is neither a {self.device.type} "
                             f"generator's ({own_size} bytes) nor one saved on the other kind of device"
                             + (f" ({other[0]}: {other[1]} bytes)" if other else "")
                             + "; pass what env.rng.get_state() returned (for the same num_envs) or a plain generator "
                             "state")
        self.manual_seed(int.from_bytes(hashlib.sha256(own.numpy().tobytes()).digest()[:8], "little") >> 1)
        warnings.warn(f"env.rng: the saved generator state is a {other[0]} generator's ({size} bytes), this one is on "
                      f"{self.device.type} (a run resumed on another device): its random actions and noise continue "
                      f"from a seed derived from the saved state, not the same numbers; {streams}",
                      RuntimeWarning, stacklevel=3)

    def set_state(self, new_state: torch.Tensor) -> EnvGenerator:
        new_state = new_state.detach().cpu()
        n = self.episodes.numel()
        own = new_state.numel() - 8 * (n + 2)
        if own <= 0 or int(new_state[-8:].clone().view(torch.int64)) != n:  # a plain generator state
            self._set_own_state(new_state, "the start-state streams are left as they are")
            return self
        self._set_own_state(new_state[:own].clone(), "the start-state streams continue exactly")
        self.episodes = new_state[own:-16].clone().view(torch.int64).to(self.episodes.device)
        self.key = np.uint64(int(new_state[-16:-8].clone().view(torch.int64)) & _MASK64)
        return self


def _rebuild_env_generator(device: str, num_envs: int, state: torch.Tensor) -> EnvGenerator:
    return EnvGenerator(torch.device(device), num_envs, 0).set_state(state)
