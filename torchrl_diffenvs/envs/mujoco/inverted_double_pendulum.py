"""Gymnasium's ``InvertedDoublePendulum-v5``: balance two poles on a cart (inverted_double_pendulum.xml)."""
import torch

from ..registry import register_env
from ...articulated.dynamics import constraint_force, forward_kinematics, site_positions
from .base import MuJoCoModelEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:INVERTED_DOUBLE_PENDULUM")
class InvertedDoublePendulumV5Env(MuJoCoModelEnv):
    """Keep the tip of a double pendulum on a cart high (``ctrl`` in ``[-1, 1]``, gear 500).

    As Gymnasium's v5: observation ``[x, sin(q1), sin(q2), cos(q1), cos(q2), clip(qvel, 10),
    clip(qfrc_constraint[0], 10)]`` (9); reward ``healthy_reward * alive - (0.01 x_tip^2 +
    (y_tip - 2)^2) - (1e-3 qd1^2 + 5e-3 qd2^2)``; terminated when the tip is at height ``<= 1``;
    truncated after 1000 steps; start ``qpos0 + U(-0.1, 0.1)``, ``qvel ~ 0.1 N(0, 1)``.

    The tip position and the cart's limit force are read where MuJoCo leaves them after
    ``mj_step`` (the last RK4 stage), as Gymnasium does; ``("state", "qfrc_constraint")`` carries
    that force. Contact-free: the dynamics equal MuJoCo's (float64, to rounding).
    """

    name = "InvertedDoublePendulum-v5"
    model_file = "inverted_double_pendulum.xml"
    frame_skip = 5
    task_params = {"healthy_reward": 10.0, "reset_noise_scale": 0.1}

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        qpos = self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise
        qvel = self.normal(n, self.model.nv) * noise
        ctrl = qpos.new_zeros(n, self.model.nu)  # Gymnasium's reset zeroes ctrl before mj_forward
        return {"qpos": qpos, "qvel": qvel, "qfrc_constraint": constraint_force(self.tree, qpos, qvel, ctrl, params)}

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        tip = site_positions(self.tree, forward_kinematics(self.tree, result.eval_qpos))[:, 0]
        x, y = tip[:, 0], tip[:, 2]
        terminated = y <= 1
        v1, v2 = result.qvel[:, 1], result.qvel[:, 2]
        alive = params["healthy_reward"] * (~terminated).to(x.dtype)
        reward = alive - (0.01 * x**2 + (y - 2) ** 2) - (1e-3 * v1**2 + 5e-3 * v2**2)
        qfrc = constraint_force(self.tree, result.eval_qpos, result.eval_qvel, action, params)
        return {"qpos": result.qpos, "qvel": result.qvel, "qfrc_constraint": qfrc}, reward, terminated

    def observation(self, state, params):
        qpos = state["qpos"]
        return torch.cat([
            qpos[:, :1], torch.sin(qpos[:, 1:]), torch.cos(qpos[:, 1:]),
            torch.clamp(state["qvel"], -10, 10), torch.clamp(state["qfrc_constraint"], -10, 10)[:, :1],
        ], dim=-1)
