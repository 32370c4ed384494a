"""Mountain car (Ivy Gym): a car on the hill y = sin(3x) driven to the flag at x = 0.45."""
import torch

from .base import DiffEnv
from .registry import register_env


@register_env(drawer="torchrl_diffenvs.rendering.tasks:MOUNTAINCAR")
class MountainCarEnv(DiffEnv):
    """Drive the car up to the goal; the motor is strong enough to climb directly.

    ``xdd = max_force * a - g cos(3x)``; no walls or speed limits. Observation ``[x, xd]``;
    reward ``exp(-5 (x - goal)^2)``; no termination. Start: ``x ~ U[-0.9, -0.2]``, ``xd = 0``.
    """

    name = "mountaincar"
    action_dim = 1
    default_params = {"g": 9.8, "max_force": 3.0, "goal": 0.45, "dt": 0.02}

    def initial_state(self, params, n):
        return {"x": self.uniform(-0.9, -0.2, n), "xd": torch.zeros_like(params["dt"])}

    def transition(self, state, action, params):
        dt = params["dt"]
        xdd = params["max_force"] * action[..., 0] - params["g"] * torch.cos(3 * state["x"])
        xd = state["xd"] + dt * xdd
        x = state["x"] + dt * xd
        reward = torch.exp(-5 * (x - params["goal"]) ** 2)
        return {"x": x, "xd": xd}, reward, None

    def observation(self, state, params):
        return torch.stack([state["x"], state["xd"]], dim=-1)
