"""Cart-pole swing-up (Ivy Gym): Gymnasium's cart-pole equations, theta = 0 upright, force 10*a."""
import math

import torch

from .base import DiffEnv
from .registry import register_env


def cartpole_accelerations(theta, theta_dot, force, params):
    """Cart and pole accelerations of Gymnasium's cart-pole model (Florian 2007, no friction)."""
    g, m_cart, m_pole, half_len = params["g"], params["cart_mass"], params["pole_mass"], params["half_length"]
    total_mass = m_cart + m_pole
    cos, sin = torch.cos(theta), torch.sin(theta)
    tmp = (force + m_pole * half_len * theta_dot**2 * sin) / total_mass
    theta_acc = (g * sin - cos * tmp) / (half_len * (4.0 / 3.0 - m_pole * cos**2 / total_mass))
    x_acc = tmp - m_pole * half_len * theta_acc * cos / total_mass
    return x_acc, theta_acc


@register_env(drawer="torchrl_diffenvs.rendering.tasks:CARTPOLE")
class CartPoleEnv(DiffEnv):
    """Swing the pole up from any angle and balance it, keeping the cart near the centre.

    Observation ``[x, xd, cos th, sin th, thd]``; reward ``exp(-x^2) (cos th + 1) / 2``; no
    termination, no track limits. Start: ``x ~ U[-1, 1]``, ``xd, thd ~ U[-0.3, 0.3]``,
    ``th ~ U[-pi, pi]``.
    """

    name = "cartpole"
    action_dim = 1
    default_params = {
        "g": 9.8, "cart_mass": 1.0, "pole_mass": 0.1, "half_length": 0.5, "max_force": 10.0, "dt": 0.02,
    }

    def initial_state(self, params, n):
        return {
            "x": self.uniform(-1.0, 1.0, n),
            "xd": self.uniform(-0.3, 0.3, n),
            "th": self.uniform(-math.pi, math.pi, n),
            "thd": self.uniform(-0.3, 0.3, n),
        }

    def transition(self, state, action, params):
        dt = params["dt"]
        force = params["max_force"] * action[..., 0]
        x_acc, th_acc = cartpole_accelerations(state["th"], state["thd"], force, params)
        xd = state["xd"] + dt * x_acc  # semi-implicit Euler
        thd = state["thd"] + dt * th_acc
        x = state["x"] + dt * xd
        th = state["th"] + dt * thd
        reward = torch.exp(-(x**2)) * (torch.cos(th) + 1) / 2
        return {"x": x, "xd": xd, "th": th, "thd": thd}, reward, None

    def observation(self, state, params):
        th = state["th"]
        return torch.stack([state["x"], state["xd"], torch.cos(th), torch.sin(th), state["thd"]], dim=-1)
