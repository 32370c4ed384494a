"""Loss modules for gradient-based learning through differentiable envs, and gradient safety."""
from .ahac import AHACLoss, AdaptiveHorizon, TwinCritic
from .bptt import BPTTLoss
from .gradient_guard import GradientGuard
from .sapo import SAPOLoss
from .shac import SHACLoss

__all__ = ["AHACLoss", "AdaptiveHorizon", "BPTTLoss", "GradientGuard", "SAPOLoss", "SHACLoss", "TwinCritic"]
