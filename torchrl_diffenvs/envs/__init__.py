"""Differentiable batched environments (TorchRL ``EnvBase`` subclasses).

Each task registers itself in its own file (``@register_env(...)`` above its class); importing
the task modules here is what makes them known to [`make_env`][torchrl_diffenvs.make_env]."""
from .base import DiffEnv
from .cartpole import CartPoleEnv
from .rollout import compile_physics, eager_physics
from .gym_classic import CartPoleV1Env, MountainCarContinuousV0Env, PendulumV1Env
from .mountaincar import MountainCarEnv
from .multi_agent import MultiAgentDiffEnv, is_multi_agent
from .multi_swimmer import MultiSwimmerEnv
from .opponent import TwoPlayerDiffEnv, opponent_from_actor
from .mujoco import (
    MUJOCO_TASKS,
    HalfCheetahV5Env,
    HopperV5Env,
    InvertedDoublePendulumV5Env,
    InvertedPendulumV5Env,
    MuJoCoModelEnv,
    ReacherV5Env,
    SwimmerV5Env,
    Walker2dV5Env,
)
from .pendulum import PendulumEnv
from .reacher import ReacherEnv
from .registry import env_class, env_config, env_options, list_envs, make_env, register_env
from .swimmer import SwimmerEnv
from .swimmer_race import SwimmerRaceEnv

__all__ = [
    "DiffEnv", "MUJOCO_TASKS", "CartPoleEnv", "PendulumEnv", "MountainCarEnv", "ReacherEnv", "SwimmerEnv",
    "CartPoleV1Env", "PendulumV1Env", "MountainCarContinuousV0Env", "MuJoCoModelEnv", "InvertedPendulumV5Env",
    "InvertedDoublePendulumV5Env", "ReacherV5Env", "HalfCheetahV5Env", "HopperV5Env", "Walker2dV5Env", "SwimmerV5Env",
    "MultiAgentDiffEnv", "MultiSwimmerEnv", "is_multi_agent", "SwimmerRaceEnv", "TwoPlayerDiffEnv",
    "opponent_from_actor", "env_class", "env_config", "env_options", "list_envs", "make_env", "register_env", "compile_physics", "eager_physics",
]
