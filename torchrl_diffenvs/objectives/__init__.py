"""Loss modules for gradient-based learning through differentiable envs, and gradient safety."""
from .bptt import BPTTLoss
from .gradient_guard import GradientGuard
from .shac import SHACLoss

__all__ = ["BPTTLoss", "GradientGuard", "SHACLoss"]
