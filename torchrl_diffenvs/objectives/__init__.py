"""Loss modules for gradient-based learning through differentiable envs, and gradient safety."""
from .ahac import AHACLoss, AdaptiveHorizon, TwinCritic
from .bptt import BPTTLoss
from .gradient_guard import GradientGuard, NonFiniteTrainingError
from .nonfinite import NonFiniteEnvMonitor, NonFiniteEnvWarning, nonfinite_envs
from .sapo import SAPOLoss
from .shac import SHACLoss

__all__ = [
    "AHACLoss", "AdaptiveHorizon", "BPTTLoss", "GradientGuard", "NonFiniteEnvMonitor", "NonFiniteEnvWarning",
    "NonFiniteTrainingError", "SAPOLoss", "SHACLoss", "TwinCritic", "nonfinite_envs",
]
