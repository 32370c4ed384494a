"""Swimmer (Ivy Gym): a fish (2-D point mass) swims to a goal while avoiding sea urchins."""
import torch

from .base import DiffEnv
from .registry import register_env


@register_env(drawer="torchrl_diffenvs.rendering.tasks:SWIMMER", options={"num_urchins": 5, "urchin_clearance": 0.25,
                                                                             "observe_urchins": True})
class SwimmerEnv(DiffEnv):
    """Steer a point mass to the goal around ``num_urchins`` urchins.

    ``v += dt * max_accel * a``, ``p += dt * v`` (no drag). Observation
    ``[urchins (2K), p, v, goal]`` (16 for K = 5); reward
    ``exp(-0.5 ||p - goal||^2) * prod_k (1 - exp(-urchin_sharpness ||p - u_k||^2))``: it falls to
    zero on an urchin, there is no separate collision penalty and no termination.
    Start: ``p, goal, u_k ~ U[-1, 1]^2``, ``v = 0``. Urchins closer than ``urchin_clearance`` to
    the start or the goal are resampled (default 0.25; ``0`` gives Ivy Gym's original sampling,
    where about 14% of episodes start or end on an urchin). ``observe_urchins=False`` hides the
    urchins from the observation (``[p, v, goal]``, a partial observation; they stay in the state,
    which a privileged critic, ``loss.critic_input=state``, can read).
    """

    name = "swimmer"
    action_dim = 2
    default_params = {"max_accel": 1.0, "urchin_sharpness": 30.0, "dt": 0.05}

    def __init__(self, num_envs=1, *, num_urchins: int = 5, urchin_clearance: float = 0.25,
                 observe_urchins: bool = True, **kwargs):
        check_pond_options(self.name, num_urchins=num_urchins, urchin_clearance=urchin_clearance,
                           observe_urchins=observe_urchins)
        self.observe_urchins = observe_urchins
        self.num_urchins = num_urchins
        self.urchin_clearance = urchin_clearance
        super().__init__(num_envs, **kwargs)

    def initial_state(self, params, n):
        pos, goal = self.uniform(-1.0, 1.0, n, 2), self.uniform(-1.0, 1.0, n, 2)
        urchins = redraw_near(self, self.uniform(-1.0, 1.0, n, self.num_urchins, 2),
                              lambda points: torch.stack([pos, goal], dim=1), self.urchin_clearance)
        return {"pos": pos, "vel": torch.zeros_like(pos), "goal": goal, "urchins": urchins}

    def transition(self, state, action, params):
        dt = params["dt"].unsqueeze(-1)
        vel = state["vel"] + dt * params["max_accel"].unsqueeze(-1) * action
        pos = state["pos"] + dt * vel
        goal, urchins = state["goal"], state["urchins"]
        reward = swimmer_reward(pos, goal, urchins, params["urchin_sharpness"])
        return {"pos": pos, "vel": vel, "goal": goal, "urchins": urchins}, reward, None

    def observation(self, state, params):
        seen = [state["urchins"].flatten(-2)] if self.observe_urchins else []
        return torch.cat([*seen, state["pos"], state["vel"], state["goal"]], dim=-1)


def redraw_near(env: DiffEnv, points: torch.Tensor, anchors, clearance: float, exclude_self: bool = False,
                max_redraws: int = 1000) -> torch.Tensor:
    """Redraws ``points`` ``[n, K, 2]`` from ``U[-1, 1]^2`` (``env.uniform``, so seeding holds)
    where one lies closer than ``clearance`` to an anchor, until none does (or ``max_redraws``).

    ``anchors(points) -> [n, M, 2]``: recomputed every round, so the points can be their own
    anchors (``exclude_self`` then skips each point's distance to itself: ``M == K``).
    """
    n, k = points.shape[:2]
    with env.redraws():  # per-env redraws: the later draws do not depend on the batch's rounds
        for _ in range(max_redraws):
            distance = (points.unsqueeze(-2) - anchors(points).unsqueeze(-3)).norm(dim=-1)  # [n, K, M]
            if exclude_self:
                distance = distance + torch.eye(k, dtype=distance.dtype, device=distance.device) * clearance
            too_close = (distance < clearance).any(-1)
            if not too_close.any():
                break
            points = torch.where(too_close.unsqueeze(-1), env.uniform(-1.0, 1.0, n, k, 2), points)
    return points


def check_pond_options(task: str, *, num_urchins, observe_urchins=True, **clearance) -> None:
    """The options of the swimmer tasks: ``num_urchins`` an integer >= 0, the one clearance
    (``urchin_clearance=`` or ``clearance=``) in ``[0, 1)``, ``observe_urchins`` a bool."""
    if isinstance(num_urchins, bool) or not isinstance(num_urchins, int) or num_urchins < 0:
        raise ValueError(f"{task}: num_urchins must be an integer >= 0, got {num_urchins!r}")
    ((name, value),) = clearance.items()
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{task}: {name} must lie in [0, 1), got {value!r}")
    if not isinstance(observe_urchins, bool):
        raise ValueError(f"{task}: observe_urchins must be true or false, got {observe_urchins!r}")


def swimmer_reward(pos: torch.Tensor, goal: torch.Tensor, urchins: torch.Tensor, sharpness: torch.Tensor) -> torch.Tensor:
    """``exp(-0.5 |p - g|^2) * prod_k (1 - exp(-sharpness |p - u_k|^2))`` of every fish.

    ``pos`` and ``goal`` ``[n, *fish, 2]`` (no fish dim for the single swimmer), ``urchins``
    ``[n, K, 2]`` shared by the fish, ``sharpness`` ``[n]``; returns ``[n, *fish]``.
    """
    fish_dims = pos.dim() - 2
    urchins = urchins.reshape(urchins.shape[0], *([1] * fish_dims), *urchins.shape[1:])
    urchin_dist2 = ((pos.unsqueeze(-2) - urchins) ** 2).sum(-1)  # [n, *fish, K]
    sharpness = sharpness.reshape(-1, *([1] * (fish_dims + 1)))
    return torch.exp(-0.5 * ((pos - goal) ** 2).sum(-1)) * (1 - torch.exp(-sharpness * urchin_dist2)).prod(-1)
