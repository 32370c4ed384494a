"""Tasks built on MuJoCo model files (Gymnasium's v5 MuJoCo envs), simulated in pure torch."""
from .ant import AntV5Env
from .base import MuJoCoModelEnv
from .half_cheetah import HalfCheetahV5Env
from .hopper import HopperV5Env
from .humanoid import HumanoidStandupV5Env, HumanoidV5Env
from .inverted_double_pendulum import InvertedDoublePendulumV5Env
from .inverted_pendulum import InvertedPendulumV5Env
from .pusher import PusherV5Env
from .reacher import ReacherV5Env
from .swimmer import SwimmerV5Env
from .walker2d import Walker2dV5Env

MUJOCO_TASKS = (
    InvertedPendulumV5Env, InvertedDoublePendulumV5Env, ReacherV5Env, SwimmerV5Env, HalfCheetahV5Env, HopperV5Env,
    Walker2dV5Env, AntV5Env, HumanoidV5Env, HumanoidStandupV5Env, PusherV5Env,
)
"""The eleven Gymnasium MuJoCo v5 task classes, in the order the docs list them."""

__all__ = ["MuJoCoModelEnv", "MUJOCO_TASKS", *(cls.__name__ for cls in MUJOCO_TASKS)]
