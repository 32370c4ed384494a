"""Reacher (Ivy Gym): a planar arm of any number of links whose tip must reach a goal."""
import math

import torch

from .base import DiffEnv
from .registry import register_env


@register_env(drawer="torchrl_diffenvs.rendering.tasks:REACHER", options={"num_links": 2, "goal_sampling": "reachable"})
class ReacherEnv(DiffEnv):
    """Move the tip of an ``num_links``-link arm (absolute link angles) onto a goal point.

    Each link is a double integrator: ``thdd_i = max_accel * a_i``. The tip is
    ``sum_i link_length * (cos th_i, sin th_i)``. Observation
    ``[cos th (L), sin th (L), thd (L), goal (2)]`` (8 for two links); reward
    ``exp(-||tip - goal||^2)``; no termination.
    Start: ``th ~ U[-pi, pi]^L``, ``thd ~ U[-1, 1]^L``, goal as set by ``goal_sampling``:

    * ``"reachable"`` (default): uniform over the disc the arm can reach (radius
      ``L * link_length``), so every episode can be solved;
    * ``"square"``: Ivy Gym's ``U[-R, R]^2`` with ``R = L * link_length``; about 21% of these
      goals lie out of reach for two links.
    """

    name = "reacher"
    default_params = {"link_length": 1.0, "max_accel": 1.0, "dt": 0.05}
    GOAL_SAMPLINGS = ("reachable", "square")

    def __init__(self, num_envs=1, *, num_links: int = 2, goal_sampling: str = "reachable", **kwargs):
        if isinstance(num_links, bool) or not isinstance(num_links, int) or num_links < 1:
            raise ValueError(f"reacher: num_links must be an integer >= 1, got {num_links!r}")
        if goal_sampling not in self.GOAL_SAMPLINGS:
            raise ValueError(f"reacher: goal_sampling must be one of {self.GOAL_SAMPLINGS}, got {goal_sampling!r}")
        self.num_links = num_links
        self.action_dim = num_links
        self.goal_sampling = goal_sampling
        super().__init__(num_envs, **kwargs)

    def tip(self, th, params):
        """End-effector position ``[N, 2]`` for absolute link angles ``th`` ``[N, L]``."""
        link = params["link_length"].unsqueeze(-1)
        return torch.stack([(link * torch.cos(th)).sum(-1), (link * torch.sin(th)).sum(-1)], dim=-1)

    def initial_state(self, params, n):
        reach = self.num_links * params["link_length"]
        if self.goal_sampling == "reachable":
            radius = reach * torch.sqrt(self.uniform(0.0, 1.0, n))
            angle = self.uniform(-math.pi, math.pi, n)
            goal = radius.unsqueeze(-1) * torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)
        else:
            goal = reach.unsqueeze(-1) * self.uniform(-1.0, 1.0, n, 2)
        return {
            "th": self.uniform(-math.pi, math.pi, n, self.num_links),
            "thd": self.uniform(-1.0, 1.0, n, self.num_links),
            "goal": goal,
        }

    def transition(self, state, action, params):
        dt = params["dt"].unsqueeze(-1)
        thd = state["thd"] + dt * params["max_accel"].unsqueeze(-1) * action
        th = state["th"] + dt * thd
        reward = torch.exp(-((self.tip(th, params) - state["goal"]) ** 2).sum(-1))
        return {"th": th, "thd": thd, "goal": state["goal"]}, reward, None

    def observation(self, state, params):
        th = state["th"]
        return torch.cat([torch.cos(th), torch.sin(th), state["thd"], state["goal"]], dim=-1)
