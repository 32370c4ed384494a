"""torchrl_diffenvs: differentiable batched RL environments and gradient-based learners for TorchRL."""
from .envs import DiffEnv, list_envs, make_env, register_env

__version__ = "0.1.0"
__all__ = ["DiffEnv", "list_envs", "make_env", "register_env", "__version__"]
