"""Gymnasium 1.4's classic-control tasks, transition for transition, as batched differentiable envs.

``make_env("CartPole-v1")``, ``make_env("Pendulum-v1")`` and ``make_env("MountainCarContinuous-v0")``
reproduce Gymnasium's dynamics, clipping, observations, rewards, termination, truncation and reset
ranges, in Gymnasium's order of operations (tests/envs/test_gymnasium_parity.py drives gymnasium's own envs
and these from the same states with the same actions). The one deliberate deviation: CartPole takes a
continuous action ``a`` (force ``10 a``) instead of ``Discrete(2)``; ``a = +1`` / ``a = -1`` are
Gymnasium's actions ``1`` / ``0``.

The three tasks share one file because they share one contract (Gymnasium parity, and its
``TimeLimit`` truncation rule in `GymnasiumClassicEnv`); each task is still physics only.
Every constant of Gymnasium's model is a per-env parameter (``env.params``), so the tasks can be
randomised or differentiated like the Ivy-style ones; the defaults are Gymnasium's values.
"""
import math

import torch

from .base import DiffEnv, angle_normalize
from .cartpole import cartpole_accelerations
from .registry import register_env

__all__ = ["GymnasiumClassicEnv", "CartPoleV1Env", "PendulumV1Env", "MountainCarContinuousV0Env"]


class GymnasiumClassicEnv(DiffEnv):
    """Base of the Gymnasium-compatible tasks: Gymnasium's ``TimeLimit`` truncation rule.

    Gymnasium's ``TimeLimit`` sets ``truncated=True`` at the step limit even when that step also
    terminates (both flags true); [`DiffEnv`][torchrl_diffenvs.DiffEnv] reports only ``terminated`` then. ``done`` is
    the same under both rules; only the ``truncated`` flag of that one step differs.
    """

    def _truncated(self, episode_step: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
        if self.max_episode_steps is None:
            return torch.zeros_like(terminated)
        return episode_step >= self.max_episode_steps


@register_env(drawer="torchrl_diffenvs.rendering.tasks:CARTPOLE_V1")
class CartPoleV1Env(GymnasiumClassicEnv):
    """Gymnasium's ``CartPole-v1`` (balance the pole; theta = 0 upright) with a continuous force.

    Dynamics: Gymnasium's cart-pole equations (`cartpole_accelerations`) with its default
    explicit Euler integrator (positions advance with the *old* velocities), force ``10 a``.
    Observation ``[x, xd, th, thd]``; reward ``+1`` per step, the terminating step included;
    terminated when ``|x| > 2.4`` or ``|th| > 12 deg``; truncated after 500 steps. Start: all four
    ``~ U[-0.05, 0.05]``.

    Deviation from Gymnasium (deliberate): the action is ``a`` in ``Box(-1, 1)``, not
    ``Discrete(2)``; ``a = +1`` / ``-1`` reproduce Gymnasium's actions ``1`` / ``0`` exactly.
    Actions outside ``[-1, 1]`` are clipped (so the force never exceeds Gymnasium's 10 N), which
    zeroes their gradient. Termination is a hard threshold: it carries no gradient.
    Stepping past a termination (without reset) keeps integrating and keeps rewarding ``+1``;
    Gymnasium calls that undefined and returns reward 0. TorchRL's rollouts reset there anyway.
    """

    name = "CartPole-v1"
    action_dim = 1
    default_max_episode_steps = 500
    clip_actions = True
    default_params = {
        "g": 9.8, "cart_mass": 1.0, "pole_mass": 0.1, "half_length": 0.5, "max_force": 10.0, "dt": 0.02,
        "x_threshold": 2.4, "theta_threshold": 12 * 2 * math.pi / 360,
    }

    def initial_state(self, params, n):
        return {k: self.uniform(-0.05, 0.05, n) for k in ("x", "xd", "th", "thd")}

    def transition(self, state, action, params):
        dt = params["dt"]
        force = params["max_force"] * action[..., 0]
        x_acc, th_acc = cartpole_accelerations(state["th"], state["thd"], force, params)
        # explicit Euler, Gymnasium's default: positions move with the pre-step velocities
        x = state["x"] + dt * state["xd"]
        xd = state["xd"] + dt * x_acc
        th = state["th"] + dt * state["thd"]
        thd = state["thd"] + dt * th_acc
        terminated = (x.abs() > params["x_threshold"]) | (th.abs() > params["theta_threshold"])
        reward = torch.ones_like(x)
        return {"x": x, "xd": xd, "th": th, "thd": thd}, reward, terminated

    def observation(self, state, params):
        return torch.stack([state["x"], state["xd"], state["th"], state["thd"]], dim=-1)


@register_env(drawer="torchrl_diffenvs.rendering.tasks:PENDULUM_V1")
class PendulumV1Env(GymnasiumClassicEnv):
    """Gymnasium's ``Pendulum-v1``: swing up and hold a pendulum (theta = 0 upright), g = 10.

    Torque ``u = clip(a, -2, 2)``; ``thd <- clip(thd + (3g/(2l) sin th + 3/(m l^2) u) dt, -8, 8)``,
    then ``th <- th + thd dt`` (semi-implicit Euler). Reward
    ``-(angle_normalize(th)^2 + 0.1 thd^2 + 0.001 u^2)`` on the *pre-step* state, as Gymnasium
    computes it. Observation ``[cos th, sin th, thd]``; no termination; truncated after 200 steps.
    Start: ``th ~ U[-pi, pi]``, ``thd ~ U[-1, 1]``.

    Gradients: the torque clip zeroes the gradient of actions outside ``[-2, 2]`` and the speed
    clip zeroes it while ``|thd|`` is held at 8. ``angle_normalize`` jumps at ``th = pi`` (mod
    ``2 pi``); the cost stays continuous there (``pi^2`` either side) but its slope flips sign.
    """

    name = "Pendulum-v1"
    action_dim = 1
    default_max_episode_steps = 200
    action_low, action_high = -2.0, 2.0
    clip_actions = True
    default_params = {"g": 10.0, "mass": 1.0, "length": 1.0, "dt": 0.05, "max_speed": 8.0}

    def initial_state(self, params, n):
        return {"th": self.uniform(-math.pi, math.pi, n), "thd": self.uniform(-1.0, 1.0, n)}

    def transition(self, state, action, params):
        g, m, l, dt, max_speed = params["g"], params["mass"], params["length"], params["dt"], params["max_speed"]
        th, thd, u = state["th"], state["thd"], action[..., 0]  # u already clipped to [-2, 2] by DiffEnv
        cost = angle_normalize(th) ** 2 + 0.1 * thd**2 + 0.001 * u**2  # pre-step state, as Gymnasium
        new_thd = thd + (3 * g / (2 * l) * torch.sin(th) + 3.0 / (m * l**2) * u) * dt
        new_thd = torch.clamp(new_thd, -max_speed, max_speed)
        new_th = th + new_thd * dt
        return {"th": new_th, "thd": new_thd}, -cost, None

    def observation(self, state, params):
        th = state["th"]
        return torch.stack([torch.cos(th), torch.sin(th), state["thd"]], dim=-1)


@register_env(drawer="torchrl_diffenvs.rendering.tasks:MOUNTAINCAR_CONTINUOUS_V0")
class MountainCarContinuousV0Env(GymnasiumClassicEnv):
    """Gymnasium's ``MountainCarContinuous-v0``: an underpowered car must rock itself up the hill.

    Force ``f = clip(a, -1, 1)``; ``v <- clip(v + f * power - gravity cos(3x), -0.07, 0.07)``;
    ``x <- clip(x + v, -1.2, 0.6)``; ``v <- 0`` when the car sits on the left wall (``x = -1.2``)
    moving left. Terminated when ``x >= 0.45`` and ``v >= goal_velocity`` (default 0, Gymnasium's
    ``goal_velocity`` argument). Reward ``100 * terminated - 0.1 a^2`` where ``a`` is the *raw*
    action, as in Gymnasium: its reward uses ``action[0]`` before the force clip, so an action
    outside ``[-1, 1]`` is penalised in full (and keeps that part of its gradient) while its
    force saturates. Observation ``[x, v]``; truncated after 999 steps. Start:
    ``x ~ U[-0.6, -0.4]``, ``v = 0``. (``power = 0.0015``, ``gravity = 0.0025``.)

    Hence ``clip_actions = False``: the env clips the force itself so the reward can see the raw
    action. Gradients: the force clip, the speed and position clips and the wall rule zero the
    gradient wherever they are active; the goal reward is a step, with no gradient.
    Gymnasium stores its state as float32 after every step; this env keeps the env's dtype
    (float64 gives Gymnasium's formulas without its float32 rounding).
    """

    name = "MountainCarContinuous-v0"
    action_dim = 1
    default_max_episode_steps = 999
    clip_actions = False
    default_params = {
        "power": 0.0015, "gravity": 0.0025, "max_speed": 0.07, "min_position": -1.2, "max_position": 0.6,
        "goal_position": 0.45, "goal_velocity": 0.0,
    }

    def initial_state(self, params, n):
        return {"x": self.uniform(-0.6, -0.4, n), "xd": torch.zeros_like(params["power"])}

    def transition(self, state, action, params):
        a = action[..., 0]
        force = torch.clamp(a, self.action_low, self.action_high)
        v = state["xd"] + (force * params["power"] - params["gravity"] * torch.cos(3 * state["x"]))
        v = torch.clamp(v, -params["max_speed"], params["max_speed"])
        x = torch.clamp(state["x"] + v, params["min_position"], params["max_position"])
        v = torch.where((x == params["min_position"]) & (v < 0), torch.zeros_like(v), v)  # inelastic left wall
        terminated = (x >= params["goal_position"]) & (v >= params["goal_velocity"])
        reward = 100.0 * terminated.to(x.dtype) - a**2 * 0.1
        return {"x": x, "xd": v}, reward, terminated

    def observation(self, state, params):
        return torch.stack([state["x"], state["xd"]], dim=-1)
