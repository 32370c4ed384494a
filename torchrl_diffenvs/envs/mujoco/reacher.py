"""Gymnasium's ``Reacher-v5``: a two-link arm reaches for a target (MuJoCo's reacher.xml)."""
import torch

from ..registry import register_env
from ...articulated.dynamics import forward_kinematics
from .base import MuJoCoModelEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:REACHER")
class ReacherV5Env(MuJoCoModelEnv):
    """Move the fingertip of a planar two-link arm onto a random target (``ctrl`` in ``[-1, 1]``).

    As Gymnasium's v5: observation ``[cos q01, sin q01, target xy, qd01, (fingertip - target)_xy]``
    (10); reward ``-reward_dist_weight |fingertip - target| - reward_control_weight |a|^2``; no
    termination; truncated after 50 steps; start ``qpos0 + U(-0.1, 0.1)`` with the target uniform
    in the disc of radius 0.2 (rejection sampling), ``qvel ~ U(-0.005, 0.005)`` (target's 0).

    The fingertip offset is read where MuJoCo leaves the body positions after ``mj_step`` (the
    last RK4 stage), as Gymnasium does; ``("state", "fingertip_to_target")`` carries it. The
    elbow's joint limit is MuJoCo's soft constraint: the dynamics equal MuJoCo's (float64).
    """

    name = "Reacher-v5"
    model_file = "reacher.xml"
    frame_skip = 2
    default_max_episode_steps = 50
    task_params = {"reward_dist_weight": 1.0, "reward_control_weight": 1.0}

    def _fingertip_to_target(self, qpos):
        kin = forward_kinematics(self.tree, qpos)
        return kin.body_pos[:, self.model.body_index("fingertip")] - kin.body_pos[:, self.model.body_index("target")]

    def initial_state(self, params, n):
        qpos = self.init_qpos(n) + self.uniform(-0.1, 0.1, n, self.model.nq)
        goal = self.uniform(-0.2, 0.2, n, 2)
        with self.redraws():  # per-env redraws: the later draws do not depend on the batch's rounds
            while True:  # Gymnasium's rejection sampling of a goal inside the disc of radius 0.2
                reject = goal.norm(dim=-1) >= 0.2
                if not reject.any():
                    break
                goal = torch.where(reject.unsqueeze(-1), self.uniform(-0.2, 0.2, n, 2), goal)
        qpos = torch.cat([qpos[:, :-2], goal], dim=-1)
        qvel = torch.cat([self.uniform(-0.005, 0.005, n, self.model.nv - 2), qpos.new_zeros(n, 2)], dim=-1)
        return {"qpos": qpos, "qvel": qvel, "fingertip_to_target": self._fingertip_to_target(qpos)}

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        offset = self._fingertip_to_target(result.eval_qpos)
        reward = -offset.norm(dim=-1) * params["reward_dist_weight"] - (action**2).sum(-1) * params["reward_control_weight"]
        return {"qpos": result.qpos, "qvel": result.qvel, "fingertip_to_target": offset}, reward, None

    def observation(self, state, params):
        qpos = state["qpos"]
        return torch.cat([
            torch.cos(qpos[:, :2]), torch.sin(qpos[:, :2]), qpos[:, 2:], state["qvel"][:, :2],
            state["fingertip_to_target"][:, :2],
        ], dim=-1)
