"""torchrl_diffenvs: differentiable batched RL environments and gradient-based learners for TorchRL."""
from .envs import DiffEnv, compile_physics, eager_physics, list_envs, make_env, register_env

__version__ = "0.1.0"
__all__ = ["DiffEnv", "compile_physics", "eager_physics", "list_envs", "make_env", "register_env", "__version__"]
