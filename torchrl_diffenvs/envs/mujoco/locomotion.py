"""What Gymnasium's planar runners share: forward reward, control cost, healthy checks, observation."""
import torch

from .base import MuJoCoModelEnv
from .healthy import HealthySurrogate


class PlanarLocomotionEnv(HealthySurrogate, MuJoCoModelEnv):
    """A planar robot (``qpos[0]`` its forward position) rewarded for moving forward.

    Reward ``forward_reward_weight * (x_after - x_before) / dt + healthy_reward * healthy
    - ctrl_cost_weight * |a|^2``; terminated when unhealthy (if ``terminate_when_unhealthy``);
    observation ``[qpos[k:], clip(qvel, -clip_velocity, clip_velocity)]`` where the first
    ``k = position_coordinates`` coordinates (1: ``x``; the swimmer's 2: ``x, y``) are left out
    unless ``exclude_current_positions_from_observation=False``. ``healthy`` is always true for a task
    without healthy ranges (HalfCheetah). Start: ``qpos0 + U(-s, s)`` and ``qvel ~ U(-s, s)``
    (``qvel ~ s N(0, 1)`` where ``velocity_noise = "normal"``), ``s = reset_noise_scale``.

    ``healthy_gradient_width`` / ``healthy_gradient_scale``: a surrogate gradient for the healthy
    bonus; ``posture_gradient_scale``: the gradient of dense height and uprightness terms (both
    straight-through: reward values stay Gymnasium's; `HealthySurrogate`).

    Dynamics: MuJoCo's own (its collision, constraint solve and the model file's integrator:
    `MuJoCoModelEnv`); ``contact="smooth"`` swaps in a smooth penalty contact, an approximation
    whose trajectories differ from Gymnasium's once a foot touches the ground.
    """

    velocity_noise = "uniform"
    position_coordinates = 1  # leading qpos entries the observation leaves out
    clip_velocity: float | None = None

    def __init__(self, num_envs: int = 1, *, exclude_current_positions_from_observation: bool = True,
                 healthy_gradient_width: float = 0.0, healthy_gradient_scale: float = 1.0,
                 posture_gradient_scale: float = 0.0, **kwargs):
        self.exclude_current_positions = bool(exclude_current_positions_from_observation)
        self._set_healthy_gradient(healthy_gradient_width, healthy_gradient_scale)
        self._set_posture_gradient(posture_gradient_scale)
        if posture_gradient_scale > 0 and not self.healthy_ranges:
            raise ValueError(f"{self.name}: posture_gradient_scale applies to tasks with a healthy height "
                             f"(Hopper-v5, Walker2d-v5, Ant-v5, Humanoid-v5); {self.name} has none")
        super().__init__(num_envs, **kwargs)

    def initial_state(self, params, n):
        noise = params["reset_noise_scale"].unsqueeze(-1)
        qpos = self.init_qpos(n) + (2 * self.uniform(0.0, 1.0, n, self.model.nq) - 1) * noise
        if self.velocity_noise == "normal":
            qvel = self.normal(n, self.model.nv) * noise
        else:
            qvel = (2 * self.uniform(0.0, 1.0, n, self.model.nv) - 1) * noise
        return {"qpos": qpos, "qvel": qvel, **self.contact_state(None, n)}

    def transition(self, state, action, params):
        result = self.simulate(state, action, params)
        x_velocity = (result.qpos[:, 0] - state["qpos"][:, 0]) / self.dt
        reward = params["forward_reward_weight"] * x_velocity - params["ctrl_cost_weight"] * (action**2).sum(-1)
        terminated = None
        if self.healthy_ranges:
            healthy = self.healthy(result.qpos, result.qvel, params)
            reward = reward + self.healthy_bonus(healthy, result.qpos, result.qvel, params)
            reward = reward + self.posture_gradient(result.qpos, params)
            terminated = ~healthy & (params["terminate_when_unhealthy"] > 0)
        return {"qpos": result.qpos, "qvel": result.qvel, **self.contact_state(result, reward.shape[0])}, reward, terminated

    def observation(self, state, params):
        qpos, qvel = state["qpos"], state["qvel"]
        if self.exclude_current_positions:
            qpos = qpos[:, self.position_coordinates:]
        if self.clip_velocity is not None:
            qvel = torch.clamp(qvel, -self.clip_velocity, self.clip_velocity)
        return torch.cat([qpos, qvel], dim=-1)
