"""Multi-swimmer: several fish in one pond, each to its own goal, around the urchins and each other."""
import torch

from .multi_agent import MultiAgentDiffEnv
from .registry import register_env
from .swimmer import check_pond_options, redraw_near, swimmer_reward


def others(x: torch.Tensor) -> torch.Tensor:
    """``x [n, A, d]`` -> ``[n, A, A - 1, d]``: for each agent, the other agents' rows in index order."""
    n, a, d = x.shape
    mask = ~torch.eye(a, dtype=torch.bool, device=x.device)
    return x.unsqueeze(1).expand(n, a, a, d)[:, mask].reshape(n, a, a - 1, d)


@register_env(drawer="torchrl_diffenvs.rendering.tasks:MULTI_SWIMMER",
              options={"num_agents": 3, "num_urchins": 5, "clearance": 0.25, "observe_urchins": True})
class MultiSwimmerEnv(MultiAgentDiffEnv):
    """``num_agents`` swimmers (Ivy Gym's fish) share a pond with ``num_urchins`` urchins.

    Each fish ``i`` is a 2-D point mass: ``v_i += dt * max_accel * a_i``, ``p_i += dt * v_i``.
    Its reward is the single swimmer's, times a collision factor for every other fish:

    ```text
    r_i = exp(-0.5 |p_i - g_i|^2) * prod_k (1 - exp(-urchin_sharpness |p_i - u_k|^2))
                                  * prod_{j != i} (1 - exp(-fish_sharpness |p_i - p_j|^2))
    ```

    so it falls to zero on an urchin or on another fish; no termination. Observation of fish
    ``i`` (``2K + 6 + 4(A - 1)``): ``[urchins (2K, if observe_urchins), p_i, v_i, g_i,
    p_j - p_i for j != i, v_j for j != i]``. Start: ``p_i, g_i, u_k ~ U[-1, 1]^2``, ``v_i = 0``;
    fish starting closer than ``clearance`` to another fish, and urchins closer than it to any
    start or goal, are redrawn. With one agent and ``fish_sharpness`` unused this is the
    ``swimmer`` task.
    """

    name = "multi_swimmer"
    action_dim = 2
    default_params = {"max_accel": 1.0, "urchin_sharpness": 30.0, "fish_sharpness": 30.0, "dt": 0.05}

    def __init__(self, num_envs=1, *, num_agents: int = 3, num_urchins: int = 5, clearance: float = 0.25,
                 observe_urchins: bool = True, **kwargs):
        check_pond_options(self.name, num_urchins=num_urchins, clearance=clearance, observe_urchins=observe_urchins)
        self.num_urchins = num_urchins
        self.clearance = clearance
        self.observe_urchins = observe_urchins
        super().__init__(num_envs, num_agents=num_agents, **kwargs)

    def initial_state(self, params, n):
        a = self.num_agents
        pos = redraw_near(self, self.uniform(-1.0, 1.0, n, a, 2), lambda fish: fish, self.clearance,
                          exclude_self=True)
        goal = self.uniform(-1.0, 1.0, n, a, 2)
        urchins = redraw_near(self, self.uniform(-1.0, 1.0, n, self.num_urchins, 2),
                              lambda points: torch.cat([pos, goal], dim=1), self.clearance)
        return {"pos": pos, "vel": torch.zeros_like(pos), "goal": goal, "urchins": urchins}

    def transition(self, state, action, params):
        dt, accel = params["dt"][:, None, None], params["max_accel"][:, None, None]
        vel = state["vel"] + dt * accel * action
        pos = state["pos"] + dt * vel
        goal, urchins = state["goal"], state["urchins"]
        reward = swimmer_reward(pos, goal, urchins, params["urchin_sharpness"])  # [n, A]
        fish_dist2 = ((pos.unsqueeze(-2) - others(pos)) ** 2).sum(-1)  # [n, A, A - 1]
        reward = reward * (1 - torch.exp(-params["fish_sharpness"][:, None, None] * fish_dist2)).prod(-1)
        return {"pos": pos, "vel": vel, "goal": goal, "urchins": urchins}, reward, None

    def observation(self, state, params):
        pos, vel = state["pos"], state["vel"]
        n, a, _ = pos.shape
        seen = [state["urchins"].flatten(-2).unsqueeze(1).expand(n, a, 2 * self.num_urchins)] if self.observe_urchins else []
        relative = (others(pos) - pos.unsqueeze(-2)).flatten(-2)
        return torch.cat([*seen, pos, vel, state["goal"], relative, others(vel).flatten(-2)], dim=-1)
