"""Gymnasium's ``InvertedPendulum-v5``: balance a pole on a cart (MuJoCo's inverted_pendulum.xml)."""
import torch

from ..registry import register_env
from .base import MuJoCoModelEnv


@register_env(drawer="torchrl_diffenvs.rendering.mujoco:INVERTED_PENDULUM")
class InvertedPendulumV5Env(MuJoCoModelEnv):
    """Keep the hinged pole within 0.2 rad of upright by pushing the cart (``ctrl`` in ``[-3, 3]``).

    As Gymnasium's v5: observation ``[qpos, qvel]`` (4); reward 1 per step while the pole is
    within 0.2 rad (0 on the terminating step); terminated when ``|qpos[1]| > 0.2`` or the
    observation is not finite; truncated after 1000 steps; start ``qpos0 + U(-0.01, 0.01)``,
    ``qvel ~ U(-0.01, 0.01)``. Contact-free: the dynamics equal MuJoCo's (float64, to rounding).
    """

    name = "InvertedPendulum-v5"
    model_file = "inverted_pendulum.xml"
    frame_skip = 2
    task_params = {"reset_noise_scale": 0.01}

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        return {
            "qpos": self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise,
            "qvel": (2 * self.uniform(0.0, 1.0, n, self.model.nv) - 1) * noise,
        }

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        obs = torch.cat([result.qpos, result.qvel], dim=-1)
        terminated = ~torch.isfinite(obs).all(-1) | (result.qpos[:, 1].abs() > 0.2)
        return {"qpos": result.qpos, "qvel": result.qvel}, (~terminated).to(obs.dtype), terminated

    def observation(self, state, params):
        return torch.cat([state["qpos"], state["qvel"]], dim=-1)
