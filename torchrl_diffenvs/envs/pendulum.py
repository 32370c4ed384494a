"""Pendulum swing-up (Ivy Gym): a rigid pendulum, theta = 0 upright, torque = max_torque * a."""
import math

import torch

from .base import DiffEnv
from .registry import register_env


@register_env(drawer="torchrl_diffenvs.rendering.tasks:PENDULUM", options={"observe_velocity": True})
class PendulumEnv(DiffEnv):
    """Swing a pendulum up and keep it upright.

    Observation ``[cos th, sin th, thd]``, or with ``observe_velocity=False`` only
    ``[cos th, sin th]`` (a partial observation: the angular velocity stays in the state, which a
    privileged critic, ``loss.critic_input=state``, can read); reward ``(cos th + 1) / 2`` on the
    post-step state; no termination. Start: ``th ~ U[-pi, pi]``, ``thd ~ U[-1, 1]``.
    """

    name = "pendulum"
    action_dim = 1
    default_params = {"g": 9.8, "mass": 1.0, "length": 1.0, "max_torque": 1.0, "dt": 0.05}

    def __init__(self, num_envs=1, *, observe_velocity: bool = True, **kwargs):
        if not isinstance(observe_velocity, bool):
            raise ValueError(f"pendulum: observe_velocity must be true or false, got {observe_velocity!r}")
        self.observe_velocity = observe_velocity
        super().__init__(num_envs, **kwargs)

    def initial_state(self, params, n):
        return {"th": self.uniform(-math.pi, math.pi, n), "thd": self.uniform(-1.0, 1.0, n)}

    def transition(self, state, action, params):
        g, m, l, dt = params["g"], params["mass"], params["length"], params["dt"]
        torque = params["max_torque"] * action[..., 0]
        thdd = 3 * g / (2 * l) * torch.sin(state["th"]) + 3 / (m * l**2) * torque
        thd = state["thd"] + dt * thdd  # semi-implicit Euler: velocity first
        th = state["th"] + dt * thd
        reward = (torch.cos(th) + 1) / 2
        return {"th": th, "thd": thd}, reward, None

    def observation(self, state, params):
        th = state["th"]
        seen = [torch.cos(th), torch.sin(th)] + ([state["thd"]] if self.observe_velocity else [])
        return torch.stack(seen, dim=-1)
