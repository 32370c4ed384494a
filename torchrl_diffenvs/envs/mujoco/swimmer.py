"""Gymnasium's ``Swimmer-v5`` (swimmer.xml): a three-link swimmer in MuJoCo's viscous, dense medium."""
from ..registry import register_env
from .locomotion import PlanarLocomotionEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:SWIMMER_V5")
class SwimmerV5Env(PlanarLocomotionEnv):
    """Swim forward (2 motors, ``ctrl`` in ``[-1, 1]``); no contact, so Gymnasium's dynamics exactly.

    As Gymnasium's v5: reward ``(x_after - x_before) / dt - 1e-4 |a|^2``, no termination, truncated
    after 1000 steps, observation ``[qpos[2:], qvel]`` (8), start ``qpos0 + U(-0.1, 0.1)``,
    ``qvel ~ U(-0.1, 0.1)``; MuJoCo's RK4 at 0.01 s, 4 steps per env step. The medium is MuJoCo's
    inertia-box fluid model (``articulated.dynamics.fluid_force``) with the file's density 4000 and
    viscosity 0.1, per-env params ``fluid_density`` and ``fluid_viscosity``.
    """

    name = "Swimmer-v5"
    model_file = "swimmer.xml"
    frame_skip = 4
    position_coordinates = 2
    task_params = {"forward_reward_weight": 1.0, "ctrl_cost_weight": 1e-4, "reset_noise_scale": 0.1}
