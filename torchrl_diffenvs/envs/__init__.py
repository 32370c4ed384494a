"""Differentiable batched environments (TorchRL ``EnvBase`` subclasses)."""
from .base import DiffEnv
from .cartpole import CartPoleEnv
from .fast_rollout import compile_physics, eager_physics
from .gym_classic import CartPoleV1Env, MountainCarContinuousV0Env, PendulumV1Env
from .mountaincar import MountainCarEnv
from .mujoco import (
    MUJOCO_TASKS,
    HalfCheetahV5Env,
    HopperV5Env,
    InvertedDoublePendulumV5Env,
    InvertedPendulumV5Env,
    MuJoCoModelEnv,
    ReacherV5Env,
    Walker2dV5Env,
)
from .pendulum import PendulumEnv
from .reacher import ReacherEnv
from .registry import list_envs, make_env, register_env
from .swimmer import SwimmerEnv

for _cls in (CartPoleEnv, PendulumEnv, MountainCarEnv, ReacherEnv, SwimmerEnv):
    register_env(_cls)
# Gymnasium-compatible variants, registered under their Gymnasium ids
for _cls in (CartPoleV1Env, PendulumV1Env, MountainCarContinuousV0Env):
    register_env(_cls)
# Gymnasium's MuJoCo tasks (v5), read from the model files that ship with gymnasium
for _cls in MUJOCO_TASKS:
    register_env(_cls)

__all__ = [
    "DiffEnv", "CartPoleEnv", "PendulumEnv", "MountainCarEnv", "ReacherEnv", "SwimmerEnv",
    "CartPoleV1Env", "PendulumV1Env", "MountainCarContinuousV0Env", "MuJoCoModelEnv", "InvertedPendulumV5Env",
    "InvertedDoublePendulumV5Env", "ReacherV5Env", "HalfCheetahV5Env", "HopperV5Env", "Walker2dV5Env",
    "list_envs", "make_env", "register_env", "compile_physics", "eager_physics",
]
