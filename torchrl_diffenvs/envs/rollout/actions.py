"""The random actions of ``EnvBase.rollout`` without a policy, drawn a block of steps at a time."""
from __future__ import annotations

import torch
from torchrl.envs import EnvBase

__all__ = ["RandomActions"]


class RandomActions:
    """``action_spec.rand()`` per step, as ``EnvBase.rollout`` draws it, from torch's global generator.

    ``Bounded.rand()`` (torchrl 0.14) draws ``uniform_``, scales it to the bounds and sets values
    that rounding pushed past a bound to that bound. Here the same arithmetic runs on a block of
    steps at once: on CPU, ``uniform_`` fills a tensor from the generator element after element,
    so one draw of ``K`` steps gives the values of ``K`` one-step draws, bitwise. `close`
    rewinds the generator to the end of the last action used, so the global random stream goes
    on where TorchRL's rollout leaves it.
    """

    BLOCK_ELEMENTS = 1 << 18  # about 1 MB of float32 per block

    def __init__(self, env: EnvBase, max_steps: int):
        space = env.action_spec.space
        self.low, self.high = space.low, space.high
        self.span = self.high - self.low
        self.shape = (env.num_envs, env.action_dim)
        self.dtype, self.device = env.float_dtype, env.device
        # other devices have counter-based generators whose block draws differ from step draws
        self.block_steps = 1
        if self.device.type == "cpu":
            self.block_steps = min(max_steps, max(1, self.BLOCK_ELEMENTS // (self.shape[0] * self.shape[1])))
        self.remaining = max_steps
        self.block: list[torch.Tensor] = []
        self.used = 0  # actions handed out from the current block
        self.state_before_block = None

    def __iter__(self):
        return self

    def __next__(self) -> torch.Tensor:
        if self.used == len(self.block):
            if self.block_steps > 1:
                self.state_before_block = torch.get_rng_state()
            steps = min(self.block_steps, self.remaining)
            self.remaining -= steps
            raw = torch.rand((steps, *self.shape), dtype=self.dtype, device=self.device)
            self.block = list(torch.clamp(raw * self.span + self.low, self.low, self.high).unbind(0))
            self.used = 0
        self.used += 1
        return self.block[self.used - 1]

    def close(self, unused: int = 0) -> None:
        """Leaves the global generator as if only the used actions had been drawn; ``unused``:
        the last actions handed out that the rollout did not use (rewound within the current
        block, on CPU)."""
        used = self.used - unused
        if self.block_steps > 1 and 0 <= used < len(self.block):
            torch.set_rng_state(self.state_before_block)
            torch.rand((used, *self.shape), dtype=self.dtype, device=self.device)
        self.block = []
