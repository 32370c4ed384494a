"""Swimmer race: two fish race to one goal around the urchins; the learner is fish 0."""
import math

import torch

from .opponent import TwoPlayerDiffEnv
from .registry import register_env
from .swimmer import check_pond_options, redraw_near, swimmer_reward


@register_env(drawer="torchrl_diffenvs.rendering.tasks:MULTI_SWIMMER",
              options={"num_urchins": 5, "urchin_clearance": 0.25})
class SwimmerRaceEnv(TwoPlayerDiffEnv):
    """Two fish (the swimmer's point masses) start at the same distance from one goal, on opposite
    sides of it; fish 0 is the learner, fish 1 the opponent ([`set_opponent`][torchrl_diffenvs.envs.TwoPlayerDiffEnv.set_opponent]; default: the
    scripted controller below).

    Zero-sum reward of fish 0: ``c_0 - c_1`` with ``c_i = exp(-0.5 |p_i - g|^2) * prod_k (1 -
    exp(-urchin_sharpness |p_i - u_k|^2))``, the single swimmer's reward of each fish: positive
    while fish 0 is nearer the goal (and clear of urchins) than fish 1. Fish 0 wins a race when it
    comes within ``GOAL_RADIUS`` of the goal first (the state counts each fish's steps until it
    arrives: ``steps_to_goal``, ``arrived``; bookkeeping, no gradient). Observation of fish ``i`` (``2K + 10``): ``[urchins (2K), p_i,
    v_i, g, p_j - p_i, v_j]``. Start: ``g ~ U[-0.5, 0.5]^2``, ``p_{0,1} = g +- r (cos a, sin a)``
    with ``r ~ U[0.7, 1]``, ``a ~ U[0, 2 pi)``, ``v = 0``; urchins ``U[-1, 1]^2`` away from both
    starts and the goal by ``urchin_clearance``. Scripted opponent: ``tanh(2 (g - p) - 2 v)``, straight
    to the goal, blind to the urchins.
    """

    name = "swimmer_race"
    action_dim = 2
    GOAL_RADIUS = 0.1
    default_params = {"max_accel": 1.0, "urchin_sharpness": 30.0, "dt": 0.05}

    def __init__(self, num_envs=1, *, num_urchins: int = 5, urchin_clearance: float = 0.25, **kwargs):
        check_pond_options(self.name, num_urchins=num_urchins, urchin_clearance=urchin_clearance)
        self.num_urchins = num_urchins
        self.urchin_clearance = urchin_clearance
        super().__init__(num_envs, **kwargs)

    def initial_state(self, params, n):
        goal = self.uniform(-0.5, 0.5, n, 2)
        radius, angle = self.uniform(0.7, 1.0, n, 1), self.uniform(0.0, 2 * math.pi, n, 1)
        offset = radius * torch.cat([torch.cos(angle), torch.sin(angle)], dim=-1)
        pos = torch.stack([goal + offset, goal - offset], dim=1)  # [n, 2 fish, 2]
        urchins = redraw_near(self, self.uniform(-1.0, 1.0, n, self.num_urchins, 2),
                              lambda points: torch.cat([pos, goal.unsqueeze(1)], dim=1), self.urchin_clearance)
        not_yet = torch.zeros_like(pos[..., 0])  # [n, 2]
        return {"pos": pos, "vel": torch.zeros_like(pos), "goal": goal, "urchins": urchins,
                "steps_to_goal": not_yet, "arrived": not_yet.clone()}

    def play(self, state, actions, params):
        dt, accel = params["dt"][:, None, None], params["max_accel"][:, None, None]
        vel = state["vel"] + dt * accel * actions
        pos = state["pos"] + dt * vel
        goal, urchins = state["goal"], state["urchins"]
        c = swimmer_reward(pos, goal.unsqueeze(1), urchins, params["urchin_sharpness"])  # c_i of both fish
        # who got there first: counters (the arrival test is a comparison, so nothing depends on the
        # actions through them; plain tensor ops keep the step differentiable in every state entry)
        steps_to_goal = state["steps_to_goal"] + (1 - state["arrived"])
        at_goal = ((pos - goal.unsqueeze(1)) ** 2).sum(-1) < self.GOAL_RADIUS**2
        arrived = torch.maximum(state["arrived"], at_goal.to(pos.dtype))
        next_state = {"pos": pos, "vel": vel, "goal": goal, "urchins": urchins, "steps_to_goal": steps_to_goal,
                      "arrived": arrived}
        return next_state, c[:, 0] - c[:, 1], None

    def observe(self, state, params, player):
        me, other = state["pos"][:, player], state["pos"][:, 1 - player]
        return torch.cat([state["urchins"].flatten(-2), me, state["vel"][:, player], state["goal"], other - me,
                          state["vel"][:, 1 - player]], dim=-1)

    def scripted_action(self, state, params):
        return torch.tanh(2.0 * (state["goal"] - state["pos"][:, 1]) - 2.0 * state["vel"][:, 1])

    def player_wins(self, state, params):
        """``[N]`` bool: player 0 reached the goal, and before player 1 did (or player 1 did not)."""
        arrived, steps = state["arrived"].bool(), state["steps_to_goal"]
        return arrived[:, 0] & (~arrived[:, 1] | (steps[:, 0] < steps[:, 1]))
