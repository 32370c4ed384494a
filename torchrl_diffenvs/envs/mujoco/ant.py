"""Gymnasium's ``Ant-v5`` (ant.xml): a four-legged robot on a free joint, with ground contact."""
import torch

from ...articulated.com import root_subtree_com
from ...articulated.kinematics import forward_kinematics
from ...articulated.pipeline import body_contact_wrenches
from ..registry import register_env
from .base import MuJoCoModelEnv
from .healthy import HealthySurrogate


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:ANT")
class AntV5Env(HealthySurrogate, MuJoCoModelEnv):
    """Walk forward (+x) on four legs (8 hinge motors, ``ctrl`` in ``[-1, 1]``; the torso on a free joint).

    As Gymnasium's v5: reward ``forward_reward_weight * vx + healthy_reward * healthy
    - ctrl_cost_weight |a|^2 - contact_cost_weight |clip(cfrc_ext)|^2``, ``vx`` the torso's x
    displacement per ``dt`` (0.05 s: 5 steps of 0.01 s, by MuJoCo's implicit integrator; the file's RK4 with
    ``integrator="model"``); healthy while the state is finite
    and the torso height ``qpos[2]`` is in ``[0.2, 1]`` (closed, as Gymnasium's); terminated when
    unhealthy; truncated after 1000 steps; observation ``[qpos[2:], qvel, clip(cfrc_ext[1:])]``
    (13 + 14 + 78 = 105; 27 with ``include_cfrc_ext_in_observation=False``, 2 more with
    ``exclude_current_positions_from_observation=False``); start ``qpos0 + U(-0.1, 0.1)`` (the
    quaternion too, unnormalised, as Gymnasium's), ``qvel ~ 0.1 N(0, 1)``.

    ``cfrc_ext`` is MuJoCo's per-body external contact wrench (torque about the Ant's centre of
    mass, force; world frame), from the constraint solve's contact forces (from the smooth
    contact model's with ``contact="smooth"``, whose values and trajectories differ from
    Gymnasium's once a leg touches the ground). As Gymnasium does, the torso position
    and ``cfrc_ext`` are read where ``mj_step`` leaves them (the start of the last implicit or Euler step, or the
    last RK4 stage): they travel as
    ``("state", "torso_xy")`` and ``("state", "cfrc_ext")``; ``cfrc_ext`` is 0 after a reset.

    ``healthy_gradient_width`` / ``healthy_gradient_scale``: a surrogate gradient for the healthy
    bonus at the torso height's bounds; ``posture_gradient_scale``: the gradient of dense height
    and uprightness terms (both straight-through: rewards stay Gymnasium's;
    `HealthySurrogate`). ``cfrc_ext_gradient=False``: the observation's
    ``cfrc_ext`` features keep their values but carry no gradient (their derivatives through
    contact are stiff, and can dominate the actor's gradient).
    """

    name = "Ant-v5"
    model_file = "ant.xml"
    # with the smooth contact, MuJoCo's implicit integrator: the file's RK4 gave 10^2-10^4x larger actor gradients,
    # and semi-implicit Euler's explicit Coriolis forces blew up Ants spun fast in the air by resonant full-range
    # square waves (benchmarks/stress.py, docs/simulator.md)
    smooth_integrator = "implicit"
    frame_skip = 5
    # contact="smooth": the Ant weighs 0.9 kg (HalfCheetah 14): a softer, less damped floor than theirs
    contact_params = {"contact_stiffness": 2e3, "contact_damping": 20.0, "contact_width": 0.002,
                      "friction_velocity": 0.01}
    task_params = {
        "forward_reward_weight": 1.0, "ctrl_cost_weight": 0.5, "contact_cost_weight": 5e-4, "healthy_reward": 1.0,
        "terminate_when_unhealthy": 1.0, "healthy_z_low": 0.2, "healthy_z_high": 1.0,
        "contact_force_low": -1.0, "contact_force_high": 1.0, "reset_noise_scale": 0.1,
    }
    healthy_ranges = {"z": "z"}
    healthy_closed = True
    height_coordinate = 2  # the free joint's z

    def __init__(self, num_envs: int = 1, *, exclude_current_positions_from_observation: bool = True,
                 include_cfrc_ext_in_observation: bool = True, cfrc_ext_gradient: bool = True,
                 healthy_gradient_width: float = 0.0, healthy_gradient_scale: float = 1.0,
                 posture_gradient_scale: float = 0.0, **kwargs):
        self.exclude_current_positions = bool(exclude_current_positions_from_observation)
        self.include_cfrc_ext = bool(include_cfrc_ext_in_observation)
        if not isinstance(cfrc_ext_gradient, bool):
            raise ValueError(f"{self.name}: cfrc_ext_gradient must be true or false, got {cfrc_ext_gradient!r}")
        self.cfrc_ext_gradient = cfrc_ext_gradient
        self._set_healthy_gradient(healthy_gradient_width, healthy_gradient_scale)
        self._set_posture_gradient(posture_gradient_scale)
        super().__init__(num_envs, **kwargs)
        self.reading_state_keys = (*self.reading_state_keys, "cfrc_ext")  # 0 after a reset, as MuJoCo's

    def derived_state(self, state, params) -> dict:
        """``torso_xy`` of the given ``qpos`` (for a state reset)."""
        return {"torso_xy": state["qpos"][:, :2]}

    def contact_wrenches(self, qpos, qvel, ctrl, params, solved=None):
        """``[N, nbody, 6]`` MuJoCo's ``cfrc_ext`` at a state: about the centre of mass. ``solved``:
        the contact problem the step solved there (its ``solved_contacts``), else it is solved again."""
        kin = forward_kinematics(self.tree, qpos)  # once per env step, at the state mj_step leaves behind
        centre = root_subtree_com(self.tree, kin, params)[:, 1]  # every body's root is the torso
        return body_contact_wrenches(self.tree, qpos, qvel, ctrl, params, about=centre,
                                     weights=None if solved else self._regulariser_scales(params), solved=solved)

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        qpos = self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise
        qvel = self.normal(n, self.model.nv) * noise
        return {"qpos": qpos, "qvel": qvel, "torso_xy": qpos[:, :2],
                "cfrc_ext": qpos.new_zeros(n, self.model.nbody, 6), **self.contact_state(None, n)}

    def contact_forces(self, state, params):
        """Gymnasium's ``contact_forces``: ``cfrc_ext`` clipped to the contact force range."""
        low, high = params["contact_force_low"], params["contact_force_high"]
        return torch.clamp(state["cfrc_ext"], low[:, None, None], high[:, None, None])

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        torso_xy = result.eval_qpos[:, :2]  # the free joint's coordinates are the torso's world position
        cfrc_ext = self.contact_wrenches(result.eval_qpos, result.eval_qvel, action, params, result.solved_contacts)
        next_state = {"qpos": result.qpos, "qvel": result.qvel, "torso_xy": torso_xy, "cfrc_ext": cfrc_ext,
                      **self.contact_state(result, torso_xy.shape[0])}
        x_velocity = (torso_xy[:, 0] - state["torso_xy"][:, 0]) / self.dt
        finite = torch.isfinite(torch.cat([result.qpos, result.qvel], dim=-1)).all(-1)
        healthy = finite & self.healthy(result.qpos, result.qvel, params)
        contact_cost = params["contact_cost_weight"] * (self.contact_forces(next_state, params) ** 2).sum((-1, -2))
        bonus = self.healthy_bonus(healthy, result.qpos, result.qvel, params)
        reward = (params["forward_reward_weight"] * x_velocity + bonus
                  - params["ctrl_cost_weight"] * (action**2).sum(-1) - contact_cost
                  + self.posture_gradient(result.qpos, params))
        terminated = ~healthy & (params["terminate_when_unhealthy"] > 0)
        return next_state, reward, terminated

    def observation(self, state, params):
        qpos = state["qpos"][:, 2:] if self.exclude_current_positions else state["qpos"]
        parts = [qpos, state["qvel"]]
        if self.include_cfrc_ext:
            forces = self.contact_forces(state, params)[:, 1:].flatten(1)
            # their derivatives are the contact stiffness and the friction slope mu f_n / v_eps:
            # cfrc_ext_gradient=False keeps the values and stops that gradient
            parts.append(forces if self.cfrc_ext_gradient else forces.detach())
        return torch.cat(parts, dim=-1)
