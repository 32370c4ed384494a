"""Loss modules for gradient-based learning through differentiable envs, and gradient safety."""
from .bptt import BPTTLoss
from .gradient_guard import GradientGuard, NonFiniteTrainingError
from .nonfinite import NonFiniteEnvMonitor, NonFiniteEnvWarning, nonfinite_envs
from .shac import SHACLoss

__all__ = [
    "BPTTLoss", "GradientGuard", "NonFiniteEnvMonitor", "NonFiniteEnvWarning", "NonFiniteTrainingError", "SHACLoss",
    "nonfinite_envs",
]
