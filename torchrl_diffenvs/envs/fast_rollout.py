"""The lean rollout's public names under their old import path: import them from
`torchrl_diffenvs.envs.rollout`, where they live.

Kept only until ``torchrl_diffenvs/training/loop.py`` and the benchmarks (``gpu_throughput.py``,
``compile_physics.py``, ``env_throughput.py``) import from there; then delete this file.
"""
from .rollout import (
    FAST_ROLLOUT_KWARGS,
    compile_physics,
    compile_report,
    eager_physics,
    fast_rollout,
    fast_rollout_unsupported,
)

__all__ = [
    "fast_rollout", "fast_rollout_unsupported", "compile_physics", "eager_physics", "compile_report",
    "FAST_ROLLOUT_KWARGS",
]
