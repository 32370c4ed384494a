"""Gymnasium's ``HalfCheetah-v5`` (half_cheetah.xml) with smooth, differentiable ground contact."""
from ..registry import register_env
from .locomotion import PlanarLocomotionEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:HALF_CHEETAH")
class HalfCheetahV5Env(PlanarLocomotionEnv):
    """Run forward with a planar cheetah (6 motors, ``ctrl`` in ``[-1, 1]``).

    As Gymnasium's v5: reward ``(x_after - x_before) / dt - 0.1 |a|^2``, no termination, truncated
    after 1000 steps, observation ``[qpos[1:], qvel]`` (17), start ``qpos0 + U(-0.1, 0.1)``,
    ``qvel ~ 0.1 N(0, 1)``; MuJoCo's Euler integrator at 0.01 s, 5 steps per env step. Contact
    with the floor is the smooth penalty model, not MuJoCo's solver (see `PlanarLocomotionEnv`).
    """

    name = "HalfCheetah-v5"
    model_file = "half_cheetah.xml"
    frame_skip = 5
    velocity_noise = "normal"
    task_params = {"forward_reward_weight": 1.0, "ctrl_cost_weight": 0.1, "reset_noise_scale": 0.1}
