"""The healthy check and its bonus's surrogate gradient, shared by the tasks that end when the
robot falls (Hopper-v5, Walker2d-v5, Ant-v5, Humanoid-v5)."""
import torch
import torch.nn.functional as F


class HealthySurrogate:
    """Mixin: Gymnasium's healthy bonus, optionally carrying a smooth surrogate's gradient.

    The healthy bonus is a step function of the state, so its exact gradient is zero and a fall is
    invisible to the analytic gradient. ``healthy_gradient_width=w > 0`` keeps every reward value
    exact (Gymnasium's) but lets the bonus carry the gradient of a smooth surrogate: the product,
    over every finite healthy bound, of ``sigmoid(margin / w)`` (``margin`` the distance to the
    bound, inside positive), as a straight-through estimator: ``bonus + k (soft - soft.detach())``.
    Gradient learners then feel the bonus within about ``w`` of a bound; returns are unchanged.
    ``healthy_gradient_scale=k`` (1 by default) weighs that gradient: a fall costs every later
    bonus (about ``healthy_reward / (1 - gamma)``), not one step's.

    A task names its bounds in ``healthy_ranges`` (``name -> what``: ``"z"`` the torso height
    ``qpos[height_coordinate]``, ``"angle"`` ``qpos[2]``, ``"state"`` ``[qpos, qvel][2:]``), read
    from the params ``healthy_<name>_low`` / ``healthy_<name>_high``; Gymnasium checks them as open
    intervals, the Ant's as closed ones (``healthy_closed``).
    """

    healthy_ranges: dict = {}
    healthy_closed = False
    height_coordinate = 1  # the qpos entry of the torso height: a planar runner's rootz, the Ant's free z

    def _set_healthy_gradient(self, width, scale) -> None:
        """Checks and keeps the two options (called by the task's ``__init__``)."""
        if isinstance(width, bool) or not isinstance(width, (int, float)) or not 0.0 <= width < float("inf"):
            raise ValueError(f"{self.name}: healthy_gradient_width must be a finite number >= 0 (0: the exact, "
                             f"zero gradient of the healthy bonus), got {width!r}")
        if width > 0 and not self.healthy_ranges:
            raise ValueError(f"{self.name}: healthy_gradient_width applies to tasks with a healthy bonus "
                             f"(Hopper-v5, Walker2d-v5, Ant-v5, Humanoid-v5); {self.name} has none")
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.0 <= scale < float("inf"):
            raise ValueError(f"{self.name}: healthy_gradient_scale must be a finite number >= 0, got {scale!r}")
        self.healthy_gradient_width = float(width)
        self.healthy_gradient_scale = float(scale)

    def _set_posture_gradient(self, scale) -> None:
        """Checks and keeps ``posture_gradient_scale`` (called by the task's ``__init__``)."""
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.0 <= scale < float("inf"):
            raise ValueError(f"{self.name}: posture_gradient_scale must be a finite number >= 0 (0: off), got {scale!r}")
        self.posture_gradient_scale = float(scale)

    def posture_score(self, qpos, params):
        """``[N]`` dense posture terms in the spirit of DiffRL's locomotion rewards: the torso height
        above the healthy floor ``h = clip(z - healthy_z_low, -1, 0.3)`` (``-200 h^2`` below it),
        plus uprightness: ``1 - (angle / healthy_angle_high)^2`` for a planar runner with an angle
        range, ``0.1 * (the torso's up axis . z)`` for a free-floating torso (the Ant)."""
        height = torch.clamp(qpos[:, self.height_coordinate] - params["healthy_z_low"], -1.0, 0.3)
        score = torch.where(height < 0, -200.0 * height * height, height)
        if self.height_coordinate == 2:  # a free joint: qpos[3:7] is the torso's quaternion (w, x, y, z)
            w, x, y, z = (qpos[:, 3:7] / qpos[:, 3:7].norm(dim=-1, keepdim=True)).unbind(-1)
            score = score + 0.1 * (1 - 2 * (x * x + y * y))
        elif "healthy_angle_high" in params.keys():
            score = score + 1 - (qpos[:, 2] / params["healthy_angle_high"]) ** 2
        return score

    def posture_gradient(self, qpos, params):
        """``[N]``, exactly zero in value: ``posture_gradient_scale`` x the gradient of
        `posture_score` (straight-through), so gradient learners feel "stay up and upright"
        while every reward value stays Gymnasium's."""
        if self.posture_gradient_scale == 0:
            return torch.zeros_like(qpos[:, 0])
        score = self.posture_score(qpos, params)
        return self.posture_gradient_scale * (score - score.detach())

    def _healthy_bounds(self, qpos, qvel, params):
        """``(value [N, k], low [N, 1], high [N, 1])`` of every healthy range of the task."""
        for name, what in self.healthy_ranges.items():
            low, high = params[f"healthy_{name}_low"].unsqueeze(-1), params[f"healthy_{name}_high"].unsqueeze(-1)
            if what == "state":
                yield torch.cat([qpos, qvel], dim=-1)[:, 2:], low, high
            elif what == "z":
                yield qpos[:, self.height_coordinate:self.height_coordinate + 1], low, high
            else:
                yield qpos[:, 2:3], low, high

    def healthy(self, qpos, qvel, params):
        """``[N]`` bool: Gymnasium's checks of the task's healthy ranges."""
        ok = torch.ones_like(qpos[:, 0], dtype=torch.bool)
        for value, low, high in self._healthy_bounds(qpos, qvel, params):
            inside = (low <= value) & (value <= high) if self.healthy_closed else (low < value) & (value < high)
            ok = ok & inside.all(-1)
        return ok

    def soft_healthy(self, qpos, qvel, params):
        """``[N]`` in ``(0, 1)``: the smooth surrogate of the healthy check (``healthy_gradient_width``).

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

    def healthy_bonus(self, healthy, qpos, qvel, params):
        """``[N]`` the bonus ``healthy_reward * healthy`` at the next state: its value exact, its
        gradient the (scaled) surrogate's where ``healthy_gradient_width > 0``."""
        bonus = healthy.to(qpos.dtype)
        if self.healthy_gradient_width > 0:
            soft = self.soft_healthy(qpos, qvel, params)
            bonus = bonus + self.healthy_gradient_scale * (soft - soft.detach())
        return params["healthy_reward"] * bonus
