"""Gymnasium's ``Pusher-v5`` (pusher_v5.xml): a 7-joint arm pushes a cylinder to a goal on a table."""
import torch

from ...articulated.kinematics import forward_kinematics
from ..registry import register_env
from .base import MuJoCoModelEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:PUSHER")
class PusherV5Env(MuJoCoModelEnv):
    """Push a cylinder onto a goal with a 7-joint arm (7 hinge motors, ``ctrl`` in ``[-2, 2]``; no gravity).

    As Gymnasium's v5: reward ``-reward_dist_weight |object - goal| - reward_near_weight
    |object - fingertip| - reward_control_weight |a|^2`` (body origins ``object``, ``goal`` and
    ``tips_arm``); no termination; truncated after 100 steps; observation ``[qpos[:7], qvel[:7],
    tips_arm, object, goal]`` (23); start at ``qpos0`` with the goal at the origin and the object
    uniform in ``[-0.3, 0] x [-0.2, 0.2]`` at least 0.17 from it (rejection sampling), the arm's
    ``qvel ~ U(-0.005, 0.005)`` (the object's and the goal's 0). As Gymnasium does, the three
    positions are read where ``mj_step`` leaves them (the start of the last Euler step); they travel
    as ``("state", "body_points")``.

    Contact (the wrist's capsules against the object and the table): MuJoCo's own by default
    ([`collision`][torchrl_diffenvs.articulated.collision]: plane-capsule, plane-cylinder and
    capsule-cylinder), frictionless as the file's ``condim=1`` says. MuJoCo collides capsules with
    cylinders by its general convex collision (GJK/EPA to ``ccd_tolerance``, then its multi-contact:
    two contacts where a wrist capsule lies along the object's cap); here those contacts are the
    exact solution of the same problem, so one step lands within EPA's residual of ``mj_step``'s
    (measured in ``benchmarks/contact_model.py`` on a trajectory that pushes the object). ``contact="smooth"``: the penalty model,
    with the object's cylinder taken as the capsule inscribed in it.
    """

    name = "Pusher-v5"
    model_file = "pusher_v5.xml"
    frame_skip = 5
    default_max_episode_steps = 100
    task_params = {"reward_near_weight": 0.5, "reward_dist_weight": 1.0, "reward_control_weight": 0.1}
    # contact="smooth": the object's slides carry 0.04 kg of armature, a softer contact than the locomotion default
    contact_params = {"contact_stiffness": 2e3, "contact_damping": 20.0, "contact_width": 0.002,
                      "friction_velocity": 0.01}
    points = ("tips_arm", "object", "goal")

    def body_points(self, qpos):
        """``[N, 3, 3]`` the world positions of the ``tips_arm``, ``object`` and ``goal`` bodies."""
        if "_point_bodies" not in self.__dict__:
            self._point_bodies = torch.tensor([self.model.body_index(b) for b in self.points], device=self.device)
        return forward_kinematics(self.tree, qpos).body_pos.index_select(1, self._point_bodies)

    def derived_state(self, state, params) -> dict:
        return {"body_points": self.body_points(state["qpos"])}

    def initial_state(self, params, n):
        draw = lambda: torch.cat([self.uniform(-0.3, 0.0, n, 1), self.uniform(-0.2, 0.2, n, 1)], dim=-1)  # noqa: E731
        cylinder = draw()
        goal = torch.zeros_like(cylinder)
        with self.redraws():  # per-env redraws: the later draws do not depend on the batch's rounds
            while True:  # Gymnasium's rejection sampling: the object more than 0.17 from the goal
                reject = (cylinder - goal).norm(dim=-1) <= 0.17
                if not reject.any():
                    break
                cylinder = torch.where(reject.unsqueeze(-1), draw(), cylinder)
        qpos = torch.cat([self.init_qpos(n)[:, :-4], cylinder, goal], dim=-1)
        arm = self.model.nv - 4
        qvel = torch.cat([self.uniform(-0.005, 0.005, n, arm), qpos.new_zeros(n, 4)], dim=-1)
        return {"qpos": qpos, "qvel": qvel, "body_points": self.body_points(qpos), **self.contact_state(None, n)}

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        points = self.body_points(result.eval_qpos)
        tips, obj, goal = points.unbind(1)
        reward = (-(obj - tips).norm(dim=-1) * params["reward_near_weight"]
                  - (obj - goal).norm(dim=-1) * params["reward_dist_weight"]
                  - (action**2).sum(-1) * params["reward_control_weight"])
        next_state = {"qpos": result.qpos, "qvel": result.qvel, "body_points": points,
                      **self.contact_state(result, action.shape[0])}
        return next_state, reward, None

    def observation(self, state, params):
        return torch.cat([state["qpos"][:, :7], state["qvel"][:, :7], state["body_points"].flatten(1)], dim=-1)
