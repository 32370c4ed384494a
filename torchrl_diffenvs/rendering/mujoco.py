"""Pictures of the MuJoCo-model tasks: every geom of the model projected onto one plane.

The tasks are planar, so a parallel projection is the whole picture: Gymnasium's side view
(world ``x`` right, ``z`` up) for the pendulums and the walkers, and the top view (``x``, ``y``)
for Reacher. Each geom is convex (sphere, capsule, cylinder, ellipsoid, box), so its outline is
the convex hull of its projected surface points; planes are drawn as the ground (side view) or
as the arena floor (top view). Body poses come from the same kinematics the physics uses
([`forward_kinematics`][torchrl_diffenvs.articulated.forward_kinematics], float64 on the CPU), so the
drawing is exactly where MuJoCo puts the geoms (``tests/rendering/test_rendering_mujoco.py`` checks this
against ``mujoco.MjData.geom_xpos``).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from .core import Canvas, Drawer

__all__ = ["MuJoCoView", "geom_outlines", "geom_world_poses"]

GROUND = (228, 218, 196)
FLOOR_TOP = (236, 240, 236)
WORLD_GEOM = (150, 150, 150)
BODY_GEOM = (60, 60, 60)
GOAL = (102, 153, 255)
INK = (0, 0, 0)

_AXES = {"x": 0, "y": 1, "z": 2}


@functools.lru_cache(maxsize=None)
def _tree(model_file: str):
    # float64 CPU copy of the physics' tree, built on the first picture only
    from ..articulated import RigidBodyTree
    from ..envs.mujoco.base import load_model

    model = load_model(model_file)
    return model, RigidBodyTree.from_model(model, dtype=torch.float64, device="cpu")


def _body_poses(model_file: str, qpos) -> tuple[np.ndarray, np.ndarray]:
    """World rotations ``[nbody, 3, 3]`` and origins ``[nbody, 3]`` of every body at ``qpos [nq]``."""
    from ..articulated.dynamics import forward_kinematics

    _, tree = _tree(model_file)
    q = torch.as_tensor(np.asarray(qpos, dtype=np.float64)).reshape(1, -1)
    kin = forward_kinematics(tree, q)
    return kin.body_rot[0].numpy(), kin.body_pos[0].numpy()


def geom_world_poses(model_file: str, qpos) -> tuple[np.ndarray, np.ndarray]:
    """World positions ``[ngeom, 3]`` and rotations ``[ngeom, 3, 3]`` of every geom at ``qpos [nq]``."""
    model, _ = _tree(model_file)
    body_rot, body_pos = _body_poses(model_file, qpos)
    rot = body_rot[model.geom_body] @ model.geom_rot
    pos = body_pos[model.geom_body] + np.einsum("gij,gj->gi", body_rot[model.geom_body], model.geom_pos)
    return pos, rot


def _circle(count: int) -> np.ndarray:
    a = np.linspace(0.0, 2 * math.pi, count, endpoint=False)
    return np.stack([np.cos(a), np.sin(a)], -1)


@functools.lru_cache(maxsize=None)
def _unit_sphere(count: int = 160) -> np.ndarray:
    # Fibonacci points, plus the six poles so axis-aligned silhouettes are exact
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r, phi = np.sqrt(1 - z**2), math.pi * (1 + 5**0.5) * i
    points = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    return np.concatenate([points, np.eye(3), -np.eye(3)])


def _surface_points(kind: str, size: np.ndarray) -> np.ndarray:
    """Points on a geom's surface, in its own frame, whose convex hull is the geom."""
    if kind == "sphere":
        return size[0] * _unit_sphere()
    if kind == "ellipsoid":
        return size * _unit_sphere()
    if kind == "capsule":
        ball = size[0] * _unit_sphere()
        return np.concatenate([ball + (0, 0, size[1]), ball - (0, 0, size[1])])
    if kind == "cylinder":
        rim = np.concatenate([size[0] * _circle(48), np.zeros((48, 1))], -1)
        return np.concatenate([rim + (0, 0, size[1]), rim - (0, 0, size[1])])
    if kind == "box":
        return np.array([(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64) * size
    raise ValueError(f"no outline for geom type {kind!r}")


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """> 0 when ``o -> a -> b`` turns counter-clockwise."""
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain: the hull of ``[K, 2]`` points, counter-clockwise."""
    pts = np.unique(np.round(points, 12), axis=0)
    if len(pts) <= 2:
        return pts

    def half(seq):
        out: list[np.ndarray] = []
        for p in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]))


def geom_outlines(model_file: str, qpos, plane: str = "xz") -> list[tuple[int, np.ndarray | float]]:
    """``(geom index, outline)`` of every geom projected onto ``plane``, model order.

    A solid geom's outline is its projected convex hull ``[K, 2]``; a plane geom gives its height
    along the projection's vertical axis (a float) in a side view, or its rectangle in a top view.
    """
    model, _ = _tree(model_file)
    u, v = (_AXES[a] for a in plane)
    pos, rot = geom_world_poses(model_file, qpos)
    outlines: list[tuple[int, np.ndarray | float]] = []
    for g, kind in enumerate(model.geom_type):
        if kind == "plane":
            if plane == "xy":
                half = model.geom_size[g, :2]
                half = np.where(half > 0, half, 50.0)  # MuJoCo's size 0 means an infinite plane
                corners = np.array([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]) * (*half, 0)
                world = corners @ rot[g].T + pos[g]
                outlines.append((g, world[:, [u, v]]))
            else:
                outlines.append((g, float(pos[g, v])))
            continue
        world = _surface_points(kind, model.geom_size[g]) @ rot[g].T + pos[g]
        outlines.append((g, _convex_hull(world[:, [u, v]])))
    return outlines


@dataclass(frozen=True)
class MuJoCoView:
    """How to look at one MuJoCo-model task; ``view(env_class)`` is its
    [`Drawer`][torchrl_diffenvs.rendering.Drawer] (the model drawn is ``env_class.model_file``).

    Attributes:
        plane: ``"xz"`` (side view) or ``"xy"`` (top view).
        bounds: the world box shown, ``(umin, umax, vmin, vmax)``; with ``follow`` its horizontal
            range is centred on the followed body.
        highlight: names of the bodies drawn in the reward colour.
        goal: names of the bodies drawn in the goal blue (targets).
        follow: a body the camera tracks horizontally (Gymnasium's tracking camera), or ``None``.
        reward_range: rewards mapped onto the colour's ``[0, 1]`` (red to green).
    """

    plane: str
    bounds: tuple[float, float, float, float]
    highlight: tuple[str, ...]
    goal: tuple[str, ...] = ()
    follow: str | None = None
    reward_range: tuple[float, float] = (0.0, 1.0)

    def __call__(self, env_class) -> Drawer:
        model_file = env_class.model_file
        return Drawer(functools.partial(self.draw, model_file),
                      bounds=functools.partial(self.view_bounds, model_file), reward_range=self.reward_range)

    def view_bounds(self, model_file: str, state, params) -> tuple[float, float, float, float]:
        umin, umax, vmin, vmax = self.bounds
        if self.follow is None:
            return self.bounds
        model, _ = _tree(model_file)
        _, body_pos = _body_poses(model_file, state["qpos"])
        centre = float(body_pos[model.body_index(self.follow), _AXES[self.plane[0]]])
        if not math.isfinite(centre):
            centre = 0.0
        return (centre + umin, centre + umax, vmin, vmax)

    def draw(self, model_file: str, canvas: Canvas, state, params, color) -> None:
        model, _ = _tree(model_file)
        highlight = {model.body_index(b) for b in self.highlight}
        goal = {model.body_index(b) for b in self.goal}
        umin, umax, vmin, _ = canvas.view
        for g, outline in geom_outlines(model_file, state["qpos"], self.plane):
            body = int(model.geom_body[g])
            if isinstance(outline, float):  # the ground, with a tick every metre so motion shows
                canvas.polygon([(umin, outline), (umax, outline), (umax, vmin - 1.0), (umin, vmin - 1.0)], GROUND)
                canvas.line([(umin, outline), (umax, outline)], INK, width=1.5)
                for tick in np.arange(math.floor(umin), math.ceil(umax) + 1):
                    canvas.line([(tick, outline), (tick, outline - 0.08)], INK, width=1)
                continue
            if model.geom_type[g] == "plane":
                canvas.polygon(outline, FLOOR_TOP, outline=WORLD_GEOM)
                continue
            fill = GOAL if body in goal else color if body in highlight else WORLD_GEOM if body == 0 else BODY_GEOM
            canvas.polygon(outline, fill, outline=INK if body in highlight else None)


# The view of every built-in MuJoCo-model task, named in its registration
# (``@register_env(drawer="torchrl_diffenvs.rendering.mujoco:HOPPER")``). Reward colour ranges:
# HalfCheetah [-1, 5] (about its forward speed), Hopper [0, 4], Walker2d [0, 5], Reacher [-0.5, 0],
# Swimmer [-0.1, 0.4] (seen from above), Humanoid [0, 8], HumanoidStandup [30, 150] (its height / 3 ms),
# Pusher [-1.5, 0] (from above).
INVERTED_PENDULUM = MuJoCoView("xz", (-1.1, 1.1, -0.35, 0.85), ("pole",))
INVERTED_DOUBLE_PENDULUM = MuJoCoView("xz", (-1.1, 1.1, -0.3, 1.4), ("pole2",), reward_range=(0.0, 10.0))
REACHER = MuJoCoView("xy", (-0.35, 0.35, -0.35, 0.35), ("fingertip",), goal=("target",), reward_range=(-0.5, 0.0))
HALF_CHEETAH = MuJoCoView("xz", (-1.5, 1.5, -0.3, 1.5), ("torso",), follow="torso", reward_range=(-1.0, 5.0))
HOPPER = MuJoCoView("xz", (-1.5, 1.5, -0.2, 1.8), ("torso",), follow="torso", reward_range=(0.0, 4.0))
WALKER2D = MuJoCoView("xz", (-1.5, 1.5, -0.2, 1.8), ("torso",), follow="torso", reward_range=(0.0, 5.0))
ANT = MuJoCoView("xz", (-2.0, 2.0, -0.3, 1.6), ("torso",), follow="torso", reward_range=(-1.0, 3.0))
SWIMMER_V5 = MuJoCoView("xy", (-2.5, 2.5, -2.0, 2.0), ("torso",), follow="torso", reward_range=(-0.1, 0.4))
HUMANOID = MuJoCoView("xz", (-1.5, 1.5, -0.2, 2.0), ("torso",), follow="torso", reward_range=(0.0, 8.0))
HUMANOID_STANDUP = MuJoCoView("xz", (-1.5, 1.5, -0.2, 1.8), ("torso",), follow="torso", reward_range=(30.0, 150.0))
PUSHER = MuJoCoView("xy", (-0.8, 1.0, -1.2, 0.6), ("object",), goal=("goal",), reward_range=(-1.5, 0.0))
