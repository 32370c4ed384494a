"""Gymnasium's ``Walker2d-v5`` (walker2d_v5.xml) with smooth, differentiable ground contact."""
from ..registry import register_env
from .locomotion import PlanarLocomotionEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:WALKER2D")
class Walker2dV5Env(PlanarLocomotionEnv):
    """Walk forward on two legs without falling (6 motors, ``ctrl`` in ``[-1, 1]``).

    As Gymnasium's v5: reward ``(x_after - x_before) / dt + 1 * healthy - 1e-3 |a|^2``; healthy
    while the torso height ``qpos[1]`` is in ``(0.8, 2)`` and its angle ``qpos[2]`` in ``(-1, 1)``;
    terminated when unhealthy; truncated after 1000 steps; observation ``[qpos[1:], clip(qvel,
    -10, 10)]`` (17); start ``qpos0 + U(-5e-3, 5e-3)``, ``qvel ~ U(-5e-3, 5e-3)``; 0.002 s physics
    steps, 4 per env step, by semi-implicit Euler (the file's RK4 with ``integrator="model"``). Contact with the floor is the smooth penalty model, not
    MuJoCo's solver (see `PlanarLocomotionEnv`).
    """

    name = "Walker2d-v5"
    model_file = "walker2d_v5.xml"
    smooth_integrator = "euler"  # with contact="smooth" (see MuJoCoModelEnv)
    frame_skip = 4
    clip_velocity = 10.0
    healthy_ranges = {"z": "z", "angle": "angle"}
    task_params = {
        "forward_reward_weight": 1.0, "ctrl_cost_weight": 1e-3, "healthy_reward": 1.0,
        "terminate_when_unhealthy": 1.0, "reset_noise_scale": 5e-3,
        "healthy_z_low": 0.8, "healthy_z_high": 2.0, "healthy_angle_low": -1.0, "healthy_angle_high": 1.0,
    }
