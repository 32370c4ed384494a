"""How each task is drawn: Ivy Gym's pictures, redrawn with Pillow.

Every drawer receives one env's ``state`` and ``params`` (floats / float64 arrays) and the
reward colour of the main body, ``RGB(1 - r, r, 0)``. The Gymnasium-compatible tasks reuse the
Ivy drawers (their states have the same names); their rewards are mapped onto ``[0, 1]`` by
each drawer's ``reward_range`` (the constants at the end). Each task names its drawer in its
registration, e.g. ``@register_env(drawer="torchrl_diffenvs.rendering.tasks:PENDULUM")``.
"""
from __future__ import annotations

import math

import numpy as np

from .core import Canvas, Drawer, transform

INK = (0, 0, 0)
JOINT = (128, 128, 128)
GOAL = (102, 153, 255)  # Ivy Gym's goal blue, RGB(0.4, 0.6, 1.0)
GROUND = (228, 218, 196)
LIMIT = (200, 60, 60)


def rectangle(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([(x0, y0), (x0, y1), (x1, y1), (x1, y0)], dtype=np.float64)


def regular_points(radius: float, count: int, center=(0.0, 0.0)) -> np.ndarray:
    angles = np.linspace(0.0, 2 * math.pi, count, endpoint=False)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles)], -1) + np.asarray(center)


# ---------------------------------------------------------------------------- cart-pole
def draw_cartpole(canvas: Canvas, state, params, color) -> None:
    """Track, black cart, pole (coloured by reward) hinged at the cart's centre; th = 0 upright.

    A positive ``th`` leans the pole towards +x. Tasks with an ``x_threshold`` parameter
    (CartPole-v1) get red marks where the episode terminates.
    """
    x, th = state["x"], state["th"]
    pole_len = 2.0 * params.get("half_length", 0.5)
    xmin, xmax = canvas.view[:2]
    canvas.line([(xmin, 0.0), (xmax, 0.0)], INK, width=1)
    if "x_threshold" in params:
        for side in (-1.0, 1.0):
            canvas.line([(side * params["x_threshold"], -0.25), (side * params["x_threshold"], 0.25)], LIMIT, width=2)
    canvas.polygon(rectangle(-0.25, 0.25, -0.15, 0.15) + (x, 0.0), INK)
    # the pole points up at th = 0 and turns clockwise as th grows (tip at x + L sin th)
    canvas.polygon(transform(rectangle(-0.04, 0.04, -0.04, pole_len), -th, (x, 0.0)), color)
    canvas.circle((x, 0.0), 0.045, JOINT)


# ---------------------------------------------------------------------------- pendulum
def draw_pendulum(canvas: Canvas, state, params, color) -> None:
    """A capsule-shaped rod (coloured by reward) on a black axle; th = 0 upright, tip at (-sin th, cos th)."""
    length, th = params.get("length", 1.0), state["th"]
    angle = th + math.pi / 2  # Ivy Gym's (and Gymnasium's) rotation: counter-clockwise from upright
    half_width = 0.1 * length
    canvas.polygon(transform(rectangle(0.0, length, -half_width, half_width), angle), color)
    canvas.circle((0.0, 0.0), half_width, color)
    canvas.circle(transform([(length, 0.0)], angle)[0], half_width, color)
    canvas.circle((0.0, 0.0), 0.05 * length, INK)


def _pendulum_bounds(state, params):
    r = 2.2 * params.get("length", 1.0)
    return (-r, r, -r, r)


# ---------------------------------------------------------------------------- mountain car
def hill_height(x):
    """The drawn hill: ``0.45 sin(3x) + 0.55``, Ivy Gym's and Gymnasium's picture of y = sin(3x)."""
    return 0.45 * np.sin(3 * np.asarray(x, dtype=np.float64)) + 0.55


def draw_mountaincar(canvas: Canvas, state, params, color) -> None:
    """The hill, the flag at the goal (``goal`` or ``goal_position``) and the car (coloured by reward)."""
    x = state["x"]
    xmin, xmax, ymin, _ = canvas.view
    xs = np.linspace(xmin, xmax, 200)
    ys = hill_height(xs)
    canvas.polygon(np.concatenate([np.stack([xs, ys], -1), [(xmax, ymin - 1.0), (xmin, ymin - 1.0)]]), GROUND)
    canvas.line(np.stack([xs, ys], -1), INK, width=2)
    goal = params.get("goal", params.get("goal_position", 0.45))
    base = float(hill_height(goal))
    canvas.line([(goal, base), (goal, base + 0.2)], INK, width=1.5)
    canvas.polygon([(goal, base + 0.2), (goal, base + 0.15), (goal + 0.1, base + 0.175)], GOAL)
    # the car sits on the hill, tilted to its slope d/dx (0.45 sin 3x) = 1.35 cos 3x
    angle = math.atan(1.35 * math.cos(3 * x)) if math.isfinite(x) else 0.0
    position = (x, float(hill_height(x)))
    canvas.polygon(transform(rectangle(-0.1, 0.1, 0.035, 0.11), angle, position), color)
    for wheel in transform([(-0.05, 0.035), (0.05, 0.035)], angle, position):
        canvas.circle(wheel, 0.03, JOINT)


# ---------------------------------------------------------------------------- reacher
def draw_reacher(canvas: Canvas, state, params, color) -> None:
    """The goal disc, the black links with grey joints, and the end effector (coloured by reward).

    ``th`` are absolute link angles (any number of links), each link ``link_length`` long.
    """
    link = params.get("link_length", 1.0)
    angles = np.atleast_1d(state["th"])
    canvas.circle(state["goal"], 0.2 * link, GOAL)
    joint = np.zeros(2)
    for angle in angles:
        canvas.polygon(transform(rectangle(0.0, link, -0.08 * link, 0.08 * link), angle, joint), INK)
        canvas.circle(joint, 0.1 * link, JOINT)
        joint = joint + link * np.array([math.cos(angle), math.sin(angle)])
    canvas.circle(joint, 0.14 * link, color)


def _reacher_bounds(state, params):
    r = (len(np.atleast_1d(state["th"])) + 0.25) * params.get("link_length", 1.0)
    return (-r, r, -r, r)


# ---------------------------------------------------------------------------- swimmer
_URCHIN = np.array(
    [(r * math.cos(a), r * math.sin(a))
     for k in range(30) for r, a in [((0.2 if k % 2 == 0 else 0.06), 2 * math.pi * k / 30)]]
)  # a 15-spike star: tips at radius 0.2 (about where the urchin term bites), notches at 0.06
_FISH_BODY = regular_points(1.0, 28) * (0.14, 0.075)  # an ellipse facing +x
_FISH_TAIL = np.array([(-0.11, 0.0), (-0.23, 0.085), (-0.2, 0.0), (-0.23, -0.085)])


def draw_swimmer(canvas: Canvas, state, params, color) -> None:
    """The goal disc, black sea urchins (any number) and the fish (coloured by reward).

    The fish faces its velocity (to the right while it is at rest).
    """
    canvas.circle(state["goal"], 0.2, GOAL)
    for urchin in np.asarray(state["urchins"]).reshape(-1, 2):
        canvas.polygon(_URCHIN + urchin, INK)
    pos, vel = state["pos"], state["vel"]
    speed = math.hypot(vel[0], vel[1])
    heading = math.atan2(vel[1], vel[0]) if math.isfinite(speed) and speed > 1e-6 else 0.0
    canvas.polygon(transform(_FISH_TAIL, heading, pos), color, outline=INK)
    canvas.polygon(transform(_FISH_BODY, heading, pos), color, outline=INK)
    canvas.circle(transform([(0.075, 0.025)], heading, pos)[0], 0.016, INK)


# One colour per fish (its tail and its goal's ring), so that a fish can be matched to its goal.
AGENT_COLORS = [(31, 119, 180), (255, 127, 14), (148, 103, 189), (23, 190, 207), (227, 119, 194), (140, 86, 75)]


def draw_multi_swimmer(canvas: Canvas, state, params, color) -> None:
    """The single swimmer's picture for every fish: goal discs ringed in the fish's colour, the
    urchins, and each fish's body in the reward colour (the mean over fish) with a tail in its own colour."""
    positions = np.asarray(state["pos"]).reshape(-1, 2)
    velocities = np.asarray(state["vel"]).reshape(-1, 2)
    goals = np.asarray(state["goal"]).reshape(-1, 2)
    for i, goal in enumerate(goals):
        canvas.circle(goal, 0.2, GOAL, outline=AGENT_COLORS[i % len(AGENT_COLORS)])
    for urchin in np.asarray(state["urchins"]).reshape(-1, 2):
        canvas.polygon(_URCHIN + urchin, INK)
    for i, (pos, vel) in enumerate(zip(positions, velocities)):
        speed = math.hypot(vel[0], vel[1])
        heading = math.atan2(vel[1], vel[0]) if math.isfinite(speed) and speed > 1e-6 else 0.0
        canvas.polygon(transform(_FISH_TAIL, heading, pos), AGENT_COLORS[i % len(AGENT_COLORS)], outline=INK)
        canvas.polygon(transform(_FISH_BODY, heading, pos), color, outline=INK)
        canvas.circle(transform([(0.075, 0.025)], heading, pos)[0], 0.016, INK)


# ---------------------------------------------------------------------------- registration
#: Gymnasium Pendulum-v1's worst reward, -(pi^2 + 0.1 * 8^2 + 0.001 * 2^2).
PENDULUM_V1_MIN_REWARD = -(math.pi**2 + 0.1 * 8**2 + 0.001 * 2**2)


SQUARE = lambda r: (-r, r, -r, r)  # noqa: E731

# One drawer per built-in task, named in its registration (``@register_env(drawer=...)``).
# Colours of the Gymnasium-compatible tasks, whose rewards are not in [0, 1]: CartPole-v1 maps
# [0, 1] (its reward is +1 every step, so the pole stays green); Pendulum-v1 maps its reward
# range [-16.27, 0] linearly (upright and still is green; its reward is computed on the pre-step
# state, so the colour lags one step); MountainCarContinuous-v0 maps [0, 100] (red while driving,
# whose reward is only the small action cost, green on the step that reaches the flag).
CARTPOLE = Drawer(draw_cartpole, bounds=SQUARE(2.7))
CARTPOLE_V1 = CARTPOLE
PENDULUM = Drawer(draw_pendulum, bounds=_pendulum_bounds)
PENDULUM_V1 = Drawer(draw_pendulum, bounds=_pendulum_bounds, reward_range=(PENDULUM_V1_MIN_REWARD, 0.0))
# Gymnasium's view of the valley: x in [-1.2, 0.6] (the walls of MountainCarContinuous)
MOUNTAINCAR = Drawer(draw_mountaincar, bounds=(-1.2, 0.6, 0.0, 1.25))
MOUNTAINCAR_CONTINUOUS_V0 = Drawer(draw_mountaincar, bounds=(-1.2, 0.6, 0.0, 1.25), reward_range=(0.0, 100.0))
REACHER = Drawer(draw_reacher, bounds=_reacher_bounds)
SWIMMER = Drawer(draw_swimmer, bounds=SQUARE(1.5))
MULTI_SWIMMER = Drawer(draw_multi_swimmer, bounds=SQUARE(1.5))
