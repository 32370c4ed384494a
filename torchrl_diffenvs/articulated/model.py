"""The parsed model: [`ArticulatedModel`][torchrl_diffenvs.articulated.ArticulatedModel] (float64 numpy arrays of a kinematic tree of rigid
bodies, as MuJoCo's compiler lays it out) and the geometry helpers the reader uses (rotations,
geom volumes and inertias)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["ArticulatedModel", "MJCFError", "axis_angle_to_mat", "geom_volume_inertia", "mat_to_quat", "quat_to_mat"]


class MJCFError(ValueError):
    """A model file uses something this reader does not support (or gets wrong)."""


@dataclass
class ArticulatedModel:
    """A kinematic tree of rigid bodies, read from an MJCF file (float64 numpy arrays).

    Index 0 of the body arrays is the world. Joints, their coordinates (``qpos``, ``nq``) and
    their degrees of freedom (``qvel``, ``nv``) are numbered in file order as MuJoCo numbers them:
    a hinge or a slide has one coordinate and one dof; a ball joint a unit quaternion ``(w, x, y,
    z)`` (4) and an angular velocity in the body frame (3); a free joint a world position and a
    quaternion (7) and a world linear velocity and a body-frame angular velocity (6). Frames are
    given relative to the parent body, orientations as rotation matrices; inertias are full 3x3
    tensors about the body's centre of mass, in the body frame.
    """

    name: str
    path: str
    timestep: float
    integrator: str  # "euler" | "implicit" | "rk4"
    gravity: np.ndarray  # [3]
    density: float  # of the medium (MuJoCo's option density; 0: no fluid forces)
    viscosity: float  # of the medium (option viscosity)
    # bodies [nbody] (0 = world)
    body_names: list[str]
    body_parent: np.ndarray  # int
    body_pos: np.ndarray  # [nbody, 3] in the parent frame
    body_rot: np.ndarray  # [nbody, 3, 3] in the parent frame
    body_mass: np.ndarray
    body_com: np.ndarray  # [nbody, 3] centre of mass in the body frame
    body_inertia: np.ndarray  # [nbody, 3, 3] about the com, body frame
    # joints [njnt]
    joint_names: list[str]
    joint_type: list[str]  # "hinge" | "slide" | "ball" | "free"
    joint_body: np.ndarray  # int
    joint_axis: np.ndarray  # [njnt, 3] unit, body frame (hinge, slide)
    joint_pos: np.ndarray  # [njnt, 3] anchor, body frame
    joint_qposadr: np.ndarray  # int: the joint's first coordinate in qpos
    joint_dofadr: np.ndarray  # int: its first dof in qvel
    qpos0: np.ndarray  # [nq] MuJoCo's ``ref`` (a free joint: its body's file pose): the body sits at its file pose
    qpos_spring: np.ndarray  # [nq] ``springref``
    stiffness: np.ndarray  # [njnt]
    # dofs [nv]
    damping: np.ndarray
    armature: np.ndarray
    dof_joint: np.ndarray  # int
    limited: np.ndarray  # bool [njnt]
    joint_range: np.ndarray  # [njnt, 2]
    limit_margin: np.ndarray
    limit_solref: np.ndarray  # [njnt, 2]
    limit_solimp: np.ndarray  # [njnt, 5]
    # geoms [ngeom]
    geom_names: list[str]
    geom_type: list[str]
    geom_body: np.ndarray
    geom_pos: np.ndarray  # [ngeom, 3] body frame
    geom_rot: np.ndarray  # [ngeom, 3, 3] body frame
    geom_size: np.ndarray  # [ngeom, 3]
    geom_friction: np.ndarray  # [ngeom, 3]
    geom_contype: np.ndarray
    geom_conaffinity: np.ndarray
    geom_condim: np.ndarray  # 1: frictionless contact; 3, 4, 6: with (sliding) friction
    # motors [nu]
    actuator_names: list[str]
    actuator_joint: np.ndarray
    actuator_gear: np.ndarray
    ctrl_limited: np.ndarray
    ctrl_range: np.ndarray  # [nu, 2]
    force_limited: np.ndarray
    force_range: np.ndarray  # [nu, 2]
    # sites (named points on bodies; no dynamics)
    site_names: list[str] = field(default_factory=list)
    site_body: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    site_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # fixed tendons [ntendon]: length = tendon_coef @ (hinge and slide coordinates, by dof)
    tendon_names: list[str] = field(default_factory=list)
    tendon_coef: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # [ntendon, nv]
    tendon_stiffness: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tendon_damping: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tendon_springlength: np.ndarray = field(default_factory=lambda: np.zeros(0))  # the spring's rest length
    # contact parameters of the geoms (MuJoCo's defaults where a file sets none) [ngeom]
    geom_margin: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [ngeom] contacts count within it
    geom_solref: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [ngeom, 2]
    geom_solimp: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # [ngeom, 5]
    geom_solmix: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [ngeom] weight in a pair's mix
    geom_priority: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # [ngeom]
    # MuJoCo's constraint solver (``<option>``): "newton", "cg" or "pgs", its iteration count and
    # tolerance, the line search's iteration count, the friction cone and impratio
    solver: str = "newton"
    iterations: int = 100
    tolerance: float = 1e-8
    ls_iterations: int = 50
    cone: str = "pyramidal"
    impratio: float = 1.0

    @property
    def nbody(self) -> int:
        """The number of bodies, the world (body 0) included."""
        return len(self.body_names)

    @property
    def nq(self) -> int:
        """The number of position coordinates (``qpos``)."""
        return len(self.qpos0)

    @property
    def nv(self) -> int:
        """The number of degrees of freedom (``qvel``)."""
        return len(self.damping)

    @property
    def njnt(self) -> int:
        """The number of joints."""
        return len(self.joint_names)

    @property
    def nu(self) -> int:
        """The number of actuators (``ctrl``)."""
        return len(self.actuator_names)

    def joint_index(self, name: str) -> int:
        """The index of the joint named ``name`` (a ``KeyError`` lists the valid names)."""
        return self._index(self.joint_names, name, "joint")

    def body_index(self, name: str) -> int:
        """The index of the body named ``name`` (a ``KeyError`` lists the valid names)."""
        return self._index(self.body_names, name, "body")

    def site_index(self, name: str) -> int:
        """The index of the site named ``name`` (a ``KeyError`` lists the valid names)."""
        return self._index(self.site_names, name, "site")

    def geom_index(self, name: str) -> int:
        """The index of the geom named ``name`` (a ``KeyError`` lists the valid names)."""
        return self._index(self.geom_names, name, "geom")

    def _index(self, names, name, what):
        try:
            return names.index(name)
        except ValueError:
            raise KeyError(f"{self.path}: no {what} named {name!r}; {what}s: {names}") from None


# ------------------------------------------------------------------ geometry helpers
def quat_to_mat(q) -> np.ndarray:
    """MuJoCo's ``(w, x, y, z)`` quaternion (normalised here) -> rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def mat_to_quat(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion ``(w, x, y, z)``, ``w >= 0`` (a free joint's start: MuJoCo
    keeps the file's quaternion, which may be the negated one, the same rotation)."""
    w = math.sqrt(max(0.0, 1.0 + rot[0, 0] + rot[1, 1] + rot[2, 2])) / 2.0
    if w > 1e-4:
        q = np.array([w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
                      (rot[1, 0] - rot[0, 1]) / (4 * w)])
    else:  # a half turn: take the axis from the largest diagonal entry
        i = int(np.argmax(np.diag(rot)))
        j, k = (i + 1) % 3, (i + 2) % 3
        v = np.zeros(3)
        v[i] = math.sqrt(max(0.0, 1.0 + rot[i, i] - rot[j, j] - rot[k, k])) / 2.0
        v[j] = (rot[j, i] + rot[i, j]) / (4 * v[i])
        v[k] = (rot[k, i] + rot[i, k]) / (4 * v[i])
        q = np.array([(rot[k, j] - rot[j, k]) / (4 * v[i]), *v])
        q = -q if q[0] < 0 else q
    return q / np.linalg.norm(q)


def axis_angle_to_mat(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _z_to_vec(vec) -> np.ndarray:
    """The minimal rotation taking +z onto ``vec`` (MuJoCo's frame for ``zaxis`` and ``fromto``)."""
    v = np.asarray(vec, dtype=np.float64)
    v = v / np.linalg.norm(v)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, v)
    s = np.linalg.norm(axis)
    if s < 1e-14:
        return np.eye(3) if v[2] > 0 else axis_angle_to_mat([1.0, 0.0, 0.0], math.pi)
    return axis_angle_to_mat(axis / s, math.atan2(s, v[2]))


# ------------------------------------------------------------------ inertia of geom primitives
def geom_volume_inertia(kind: str, size: np.ndarray) -> tuple[float, np.ndarray]:
    """Volume and the principal inertia per unit density ``[3]`` of a primitive, MuJoCo's formulas."""
    if kind == "sphere":
        r = size[0]
        vol = 4.0 / 3.0 * math.pi * r**3
        return vol, np.full(3, 0.4 * vol * r * r)
    if kind == "capsule":
        r, h = size[0], 2.0 * size[1]
        v_cyl, v_sph = math.pi * r * r * h, 4.0 / 3.0 * math.pi * r**3
        ixy = v_cyl * (3 * r * r + h * h) / 12.0 + v_sph * (0.4 * r * r + h * h / 4.0 + 3.0 * h * r / 8.0)
        return v_cyl + v_sph, np.array([ixy, ixy, v_cyl * r * r / 2.0 + v_sph * 0.4 * r * r])
    if kind == "cylinder":
        r, h = size[0], 2.0 * size[1]
        vol = math.pi * r * r * h
        ixy = vol * (3 * r * r + h * h) / 12.0
        return vol, np.array([ixy, ixy, vol * r * r / 2.0])
    if kind == "ellipsoid":
        a, b, c = size
        vol = 4.0 / 3.0 * math.pi * a * b * c
        return vol, vol / 5.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    if kind == "box":
        a, b, c = size
        vol = 8.0 * a * b * c
        return vol, vol / 3.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    raise MJCFError(f"no inertia for geom type {kind!r}")


# ------------------------------------------------------------------ the reader
