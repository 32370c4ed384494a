"""What Gymnasium's planar runners share: forward reward, control cost, healthy checks, observation."""
import torch
import torch.nn.functional as F

from .base import MuJoCoModelEnv


class PlanarLocomotionEnv(MuJoCoModelEnv):
    """A planar robot (``qpos[0]`` its forward position) rewarded for moving forward.

    Reward ``forward_reward_weight * (x_after - x_before) / dt + healthy_reward * healthy
    - ctrl_cost_weight * |a|^2``; terminated when unhealthy (if ``terminate_when_unhealthy``);
    observation ``[qpos[k:], clip(qvel, -clip_velocity, clip_velocity)]`` where the first
    ``k = position_coordinates`` coordinates (1: ``x``; the swimmer's 2: ``x, y``) are left out
    unless ``exclude_current_positions_from_observation=False``. ``healthy`` is always true for a task
    without healthy ranges (HalfCheetah). Start: ``qpos0 + U(-s, s)`` and ``qvel ~ U(-s, s)``
    (``qvel ~ s N(0, 1)`` where ``velocity_noise = "normal"``), ``s = reset_noise_scale``.

    The healthy bonus is a step function of the state, so its exact gradient is zero and a fall is
    invisible to the analytic gradient. ``healthy_gradient_width=w > 0`` keeps every reward value
    exact (Gymnasium's) but lets the bonus carry the gradient of a smooth surrogate: the product,
    over every finite healthy bound, of ``sigmoid(margin / w)`` (``margin`` the distance to the
    bound, inside positive), as a straight-through estimator: ``bonus + k (soft - soft.detach())``.
    Gradient learners then feel the bonus within about ``w`` of a bound; returns are unchanged.
    ``healthy_gradient_scale=k`` (1 by default) weighs that gradient: a fall costs every later
    bonus (about ``healthy_reward / (1 - gamma)``), not one step's.

    Dynamics: MuJoCo's model and integrator, with a smooth penalty contact instead of MuJoCo's
    soft-constraint solver (see the README, "Articulated robots"): trajectories differ from
    Gymnasium's once a foot touches the ground.
    """

    velocity_noise = "uniform"
    position_coordinates = 1  # leading qpos entries the observation leaves out
    clip_velocity: float | None = None
    healthy_ranges: dict = {}  # name -> what it bounds: "z" (qpos[1]), "angle" (qpos[2]), "state" (state[2:])

    def __init__(self, num_envs: int = 1, *, exclude_current_positions_from_observation: bool = True,
                 healthy_gradient_width: float = 0.0, healthy_gradient_scale: float = 1.0, **kwargs):
        self.exclude_current_positions = bool(exclude_current_positions_from_observation)
        width = healthy_gradient_width
        if isinstance(width, bool) or not isinstance(width, (int, float)) or not 0.0 <= width < float("inf"):
            raise ValueError(f"{self.name}: healthy_gradient_width must be a finite number >= 0 (0: the exact, "
                             f"zero gradient of the healthy bonus), got {width!r}")
        if width > 0 and not self.healthy_ranges:
            raise ValueError(f"{self.name}: healthy_gradient_width applies to tasks with a healthy bonus "
                             f"(Hopper-v5, Walker2d-v5); {self.name} has none")
        scale = healthy_gradient_scale
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.0 <= scale < float("inf"):
            raise ValueError(f"{self.name}: healthy_gradient_scale must be a finite number >= 0, got {scale!r}")
        self.healthy_gradient_width = float(width)
        self.healthy_gradient_scale = float(scale)
        super().__init__(num_envs, **kwargs)

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        qpos = self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise
        if self.velocity_noise == "normal":
            qvel = self.normal(n, self.model.nv) * noise
        else:
            qvel = (2 * self.uniform(0.0, 1.0, n, self.model.nv) - 1) * noise
        return {"qpos": qpos, "qvel": qvel}

    def _healthy_bounds(self, qpos, qvel, params):
        """``(value [N, k], low [N, 1], high [N, 1])`` of every healthy range of the task."""
        for name, what in self.healthy_ranges.items():
            low, high = params[f"healthy_{name}_low"].unsqueeze(-1), params[f"healthy_{name}_high"].unsqueeze(-1)
            if what == "state":
                yield torch.cat([qpos, qvel], dim=-1)[:, 2:], low, high
            else:
                yield (qpos[:, 1:2] if what == "z" else qpos[:, 2:3]), low, high

    def healthy(self, qpos, qvel, params):
        """``[N]`` bool: Gymnasium's open-interval checks of the task's healthy ranges."""
        ok = torch.ones_like(qpos[:, 0], dtype=torch.bool)
        for value, low, high in self._healthy_bounds(qpos, qvel, params):
            ok = ok & ((low < value) & (value < high)).all(-1)
        return ok

    def soft_healthy(self, qpos, qvel, params):
        """``[N]`` in ``(0, 1)``: the smooth surrogate of :meth:`healthy` (``healthy_gradient_width``).

        A log-sum of ``logsigmoid(margin / w)`` over the finite bounds; an infinite bound (Hopper's
        ``healthy_z_high``) contributes exactly 0, with a zero gradient.
        """
        width = self.healthy_gradient_width
        log_soft = torch.zeros_like(qpos[:, 0])
        for value, low, high in self._healthy_bounds(qpos, qvel, params):
            for margin, finite in ((value - low, torch.isfinite(low)), (high - value, torch.isfinite(high))):
                term = F.logsigmoid(torch.where(finite, margin, torch.ones_like(margin)) / width)
                log_soft = log_soft + torch.where(finite, term, torch.zeros_like(term)).sum(-1)
        return log_soft.exp()

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        x_velocity = (result.qpos[:, 0] - state["qpos"][:, 0]) / self.dt
        reward = params["forward_reward_weight"] * x_velocity - params["ctrl_cost_weight"] * (action**2).sum(-1)
        terminated = None
        if self.healthy_ranges:
            healthy = self.healthy(result.qpos, result.qvel, params)
            bonus = healthy.to(reward.dtype)
            if self.healthy_gradient_width > 0:
                soft = self.soft_healthy(result.qpos, result.qvel, params)
                # the exact value, the (scaled) surrogate's gradient
                bonus = bonus + self.healthy_gradient_scale * (soft - soft.detach())
            reward = reward + params["healthy_reward"] * bonus
            terminated = ~healthy & (params["terminate_when_unhealthy"] > 0)
        return {"qpos": result.qpos, "qvel": result.qvel}, reward, terminated

    def observation(self, state, params):
        qpos, qvel = state["qpos"], state["qvel"]
        if self.exclude_current_positions:
            qpos = qpos[:, self.position_coordinates:]
        if self.clip_velocity is not None:
            qvel = torch.clamp(qvel, -self.clip_velocity, self.clip_velocity)
        return torch.cat([qpos, qvel], dim=-1)
