"""Gymnasium's ``Hopper-v5`` (hopper.xml) with smooth, differentiable ground contact."""
import math

from ..registry import register_env
from .locomotion import PlanarLocomotionEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:HOPPER")
class HopperV5Env(PlanarLocomotionEnv):
    """Hop forward on one leg without falling (3 motors, ``ctrl`` in ``[-1, 1]``).

    As Gymnasium's v5: reward ``(x_after - x_before) / dt + 1 * healthy - 1e-3 |a|^2``; healthy
    while ``state[2:]`` is in ``(-100, 100)``, the torso height ``qpos[1]`` in ``(0.7, inf)`` and
    its angle ``qpos[2]`` in ``(-0.2, 0.2)``; terminated when unhealthy; truncated after 1000
    steps; observation ``[qpos[1:], clip(qvel, -10, 10)]`` (11); start ``qpos0 + U(-5e-3, 5e-3)``,
    ``qvel ~ U(-5e-3, 5e-3)``; 0.002 s physics steps, 4 per env step, by semi-implicit Euler
    (the file's RK4 with ``integrator="model"``). Contact with the
    floor is the smooth penalty model, not MuJoCo's solver (see `PlanarLocomotionEnv`).
    """

    name = "Hopper-v5"
    model_file = "hopper.xml"
    smooth_integrator = "euler"  # with contact="smooth" (see MuJoCoModelEnv)
    frame_skip = 4
    clip_velocity = 10.0
    healthy_ranges = {"state": "state", "z": "z", "angle": "angle"}
    task_params = {
        "forward_reward_weight": 1.0, "ctrl_cost_weight": 1e-3, "healthy_reward": 1.0,
        "terminate_when_unhealthy": 1.0, "reset_noise_scale": 5e-3,
        "healthy_state_low": -100.0, "healthy_state_high": 100.0,
        "healthy_z_low": 0.7, "healthy_z_high": math.inf,
        "healthy_angle_low": -0.2, "healthy_angle_high": 0.2,
    }
