"""Gymnasium's ``Humanoid-v5`` (humanoid.xml) and ``HumanoidStandup-v5`` (humanoidstandup.xml):
a 3-D humanoid on a free joint, with smooth contact against the floor and between its limbs."""
import torch

from ...articulated.com import com_inertia, com_velocity, mass_center, root_subtree_com
from ...articulated.pipeline import body_contact_wrenches
from ...articulated.forces import actuator_force
from ...articulated.kinematics import forward_kinematics
from ..registry import register_env
from .base import MuJoCoModelEnv
from .healthy import HealthySurrogate


class _HumanoidBase(MuJoCoModelEnv):
    """What the two humanoid tasks share: the model's derived quantities that the observation reads.

    Observation (Gymnasium's v5): ``[qpos[2:], qvel, cinert[1:], cvel[1:], qfrc_actuator[6:],
    cfrc_ext[1:]]`` (22 + 23 + 130 + 78 + 17 + 78 = 348; each of the last four can be left out,
    and ``exclude_current_positions_from_observation=False`` keeps ``qpos[:2]``). ``cinert``,
    ``cvel`` and ``cfrc_ext`` are read where ``mj_step`` leaves them, at the last evaluated
    physics state, as Gymnasium does; they travel in the state with the mass centre, and
    ``cfrc_ext`` is 0 after a reset. ``cfrc_ext`` comes from the smooth contact model (the floor and
    the limbs touching each other), so it differs from MuJoCo's solver's wherever there is contact.
    """

    model_file = "humanoid.xml"
    frame_skip = 5
    # semi-implicit Euler: the regularised friction of a planted foot is a stiff damper that the
    # file's explicit RK4 at 3 ms cannot integrate stably; Euler treats it implicitly
    smooth_integrator = "euler"  # with contact="smooth" (see MuJoCoModelEnv)
    # a 40 kg robot: a stiffer floor than the default keeps the feet within a centimetre of it
    contact_params = {"contact_stiffness": 5e4, "contact_damping": 1000.0, "contact_width": 0.002,
                      "friction_velocity": 0.01}

    def __init__(self, num_envs: int = 1, *, exclude_current_positions_from_observation: bool = True,
                 include_cinert_in_observation: bool = True, include_cvel_in_observation: bool = True,
                 include_qfrc_actuator_in_observation: bool = True, include_cfrc_ext_in_observation: bool = True,
                 **kwargs):
        self.exclude_current_positions = bool(exclude_current_positions_from_observation)
        self.observed = {"cinert": bool(include_cinert_in_observation), "cvel": bool(include_cvel_in_observation),
                         "qfrc_actuator": bool(include_qfrc_actuator_in_observation),
                         "cfrc_ext": bool(include_cfrc_ext_in_observation)}
        super().__init__(num_envs, **kwargs)
        # readings of the last step (0 after a reset), as contact_force: a state reset may leave them out
        self.reading_state_keys = (*self.reading_state_keys, "cfrc_ext", "qfrc_actuator")

    def derived_state(self, state, params) -> dict:
        """``mass_center_xy``, ``cinert`` and ``cvel`` at the given ``qpos``/``qvel`` (for a state reset)."""
        derived = self.derived(state["qpos"], state["qvel"], params)
        return {key: derived[key] for key in ("mass_center_xy", "cinert", "cvel")}

    def derived(self, qpos, qvel, params, ctrl=None, solved=None) -> dict:
        """The quantities MuJoCo derives from a state that the task reads: ``mass_center_xy``,
        ``cinert``, ``cvel`` and, given the ``ctrl`` of the step, ``cfrc_ext`` (about the subtree
        centre of mass; 0 without ``ctrl``, as after a reset; ``solved``: the contact problem the
        step solved at this state, else it is solved again)."""
        kin = forward_kinematics(self.tree, qpos)
        centre = root_subtree_com(self.tree, kin, params)[:, 1]  # the torso's subtree: the whole humanoid
        cfrc_ext = qpos.new_zeros(qpos.shape[0], self.model.nbody, 6) if ctrl is None else \
            body_contact_wrenches(self.tree, qpos, qvel, ctrl, params, about=centre,
                                  weights=None if solved else self._regulariser_scales(params), solved=solved)
        return {"mass_center_xy": mass_center(self.tree, kin, params)[:, :2],
                "cinert": com_inertia(self.tree, kin, params), "cvel": com_velocity(self.tree, kin, qvel, params),
                "cfrc_ext": cfrc_ext}

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        qpos = self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise
        qvel = (2 * self.uniform(0.0, 1.0, n, self.model.nv) - 1) * noise
        state = {"qpos": qpos, "qvel": qvel, **self.derived(qpos, qvel, params)}
        # after a reset MuJoCo has not run the post-constraint pass: cfrc_ext is 0 (derived without ctrl)
        state["qfrc_actuator"] = qpos.new_zeros(n, self.model.nv - 6)
        return {**state, **self.contact_state(None, n)}

    def advance(self, state, action, params):
        """One env step: the next state and the step's physics result."""
        result = self.simulate(state, action, params)
        qfrc_actuator = actuator_force(self.tree, action, self.model.nv)[:, 6:]
        next_state = {"qpos": result.qpos, "qvel": result.qvel, "qfrc_actuator": qfrc_actuator,
                      **self.derived(result.eval_qpos, result.eval_qvel, params, action, result.solved_contacts),
                      **self.contact_state(result, action.shape[0])}
        return next_state, result

    def observation(self, state, params):
        qpos = state["qpos"][:, 2:] if self.exclude_current_positions else state["qpos"]
        parts = [qpos, state["qvel"]]
        for key in ("cinert", "cvel", "qfrc_actuator", "cfrc_ext"):
            if self.observed[key]:
                value = state[key]
                parts.append(value.flatten(1) if key == "qfrc_actuator" else value[:, 1:].flatten(1))
        return torch.cat(parts, dim=-1)


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:HUMANOID")
class HumanoidV5Env(HealthySurrogate, _HumanoidBase):
    """Walk forward (+x) without falling (17 hinge motors, ``ctrl`` in ``[-0.4, 0.4]``).

    As Gymnasium's v5: reward ``forward_reward_weight * vx + healthy_reward * healthy
    - ctrl_cost_weight |a|^2 - clip(contact_cost_weight |cfrc_ext|^2, max 10)``, ``vx`` the x
    velocity of the mass centre (mass-weighted body centres) over ``dt`` = 0.015 s (five 3 ms
    physics steps); healthy while the state is finite and the torso height ``qpos[2]`` is in
    ``(1, 2)``; terminated when unhealthy; truncated after 1000 steps; start ``qpos0 + U(-0.01,
    0.01)`` and ``qvel ~ U(-0.01, 0.01)``. Observation: see `_HumanoidBase`.

    ``healthy_gradient_width`` / ``healthy_gradient_scale`` and ``posture_gradient_scale``: the
    surrogate gradients of `HealthySurrogate` (reward values stay Gymnasium's).
    """

    name = "Humanoid-v5"
    healthy_ranges = {"z": "z"}
    height_coordinate = 2
    task_params = {
        "forward_reward_weight": 1.25, "ctrl_cost_weight": 0.1, "contact_cost_weight": 5e-7,
        "contact_cost_high": 10.0, "healthy_reward": 5.0, "terminate_when_unhealthy": 1.0,
        "healthy_z_low": 1.0, "healthy_z_high": 2.0, "reset_noise_scale": 1e-2,
    }

    def __init__(self, num_envs: int = 1, *, healthy_gradient_width: float = 0.0, healthy_gradient_scale: float = 1.0,
                 posture_gradient_scale: float = 0.0, **kwargs):
        self._set_healthy_gradient(healthy_gradient_width, healthy_gradient_scale)
        self._set_posture_gradient(posture_gradient_scale)
        super().__init__(num_envs, **kwargs)

    def transition(self, state, action, params):
        next_state, result = self.advance(state, action, params)
        x_velocity = (next_state["mass_center_xy"][:, 0] - state["mass_center_xy"][:, 0]) / self.dt
        finite = torch.isfinite(torch.cat([result.qpos, result.qvel], dim=-1)).all(-1)
        healthy = finite & self.healthy(result.qpos, result.qvel, params)
        contact_cost = torch.minimum(params["contact_cost_weight"] * (next_state["cfrc_ext"] ** 2).sum((-1, -2)),
                                     params["contact_cost_high"])
        reward = (params["forward_reward_weight"] * x_velocity
                  + self.healthy_bonus(healthy, result.qpos, result.qvel, params)
                  - params["ctrl_cost_weight"] * (action**2).sum(-1) - contact_cost
                  + self.posture_gradient(result.qpos, params))
        terminated = ~healthy & (params["terminate_when_unhealthy"] > 0)
        return next_state, reward, terminated


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:HUMANOID_STANDUP")
class HumanoidStandupV5Env(_HumanoidBase):
    """Stand up from lying on the floor (the humanoid's 17 motors, ``ctrl`` in ``[-0.4, 0.4]``).

    As Gymnasium's v5: reward ``uph_cost_weight * qpos[2] / timestep - ctrl_cost_weight |a|^2
    - clip(impact_cost_weight |cfrc_ext|^2, max 10) + 1`` (``timestep`` the model's 3 ms physics
    step, as Gymnasium's); never terminates; truncated after 1000 steps; start ``qpos0 + U(-0.01,
    0.01)``, ``qvel ~ U(-0.01, 0.01)``. Observation: see `_HumanoidBase`.
    """

    name = "HumanoidStandup-v5"
    model_file = "humanoidstandup.xml"
    task_params = {"uph_cost_weight": 1.0, "ctrl_cost_weight": 0.1, "impact_cost_weight": 0.5e-6,
                   "impact_cost_high": 10.0, "reset_noise_scale": 1e-2}

    def transition(self, state, action, params):
        next_state, result = self.advance(state, action, params)
        impact_cost = torch.minimum(params["impact_cost_weight"] * (next_state["cfrc_ext"] ** 2).sum((-1, -2)),
                                    params["impact_cost_high"])
        reward = (params["uph_cost_weight"] * result.qpos[:, 2] / self.model.timestep
                  - params["ctrl_cost_weight"] * (action**2).sum(-1) - impact_cost + 1.0)
        return next_state, reward, None
