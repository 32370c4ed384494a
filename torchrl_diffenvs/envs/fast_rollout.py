"""The lean rollout's public names, where they have always been imported from.

The implementation lives in `torchrl_diffenvs.envs.rollout`.
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
