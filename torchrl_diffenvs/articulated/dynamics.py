"""Batched, differentiable rigid-body dynamics of kinematic trees, in pure torch.

Everything here is a pure function of tensors with a leading batch dimension ``N``: the same code
serves the TorchRL step, the lean rollout path, ``torch.compile``, CPU and CUDA, float32 and
float64. The physics follows MuJoCo's definitions so that contact-free models match MuJoCo to
rounding error:

* kinematics: MuJoCo's joint composition (hinge about its anchor, slide along its axis, ``ref``;
  a ball joint's unit quaternion about its anchor; a free joint's world position and quaternion),
  and MuJoCo's dof motion axes (a ball or free joint turns about its body's own axes);
* mass matrix and bias forces (Coriolis, centrifugal, gravity) from spatial vectors expressed in
  the world frame at the origin, where velocities add along the tree: with ``S_d`` the motion
  axis of dof ``d`` and ``Ic_d`` the summed inertia of the bodies it moves, the composite-rigid-body
  algorithm's ``M_ij = S_i . Ic_j S_j`` (dof ``i`` moving dof ``j``'s body) plus ``diag(armature)``,
  and ``bias_d = S_d . sum_b (I_b a_b + v_b x* I_b v_b)`` over the bodies ``d`` moves, with ``a_b``
  the velocity-product acceleration (the recursive Newton-Euler terms); every sum over the tree is
  one masked product, not a Python recursion over bodies;
* passive forces ``-damping qvel - stiffness (qpos - springref)``, motors ``gear * clamp(ctrl)``;
* joint limits as MuJoCo's soft constraints (solref/solimp impedance, reference acceleration,
  regulariser from ``dof_invweight0``), solved row by row: exact when one limit is active at a
  time, MuJoCo's coupled solve otherwise;
* smooth penalty contact between geoms and ground planes (:func:`contact_force`), not MuJoCo's
  convex solver: see :mod:`torchrl_diffenvs.articulated` for the difference;
* MuJoCo's integrators: semi-implicit Euler with implicit joint damping, and classic RK4, both
  moving quaternions as ``mj_integratePos`` does (:func:`integrate_position`).

Physical parameters come per env in a mapping (``body_mass [N, nbody]``, ``body_inertia
[N, nbody, 3, 3]``, ``damping``/``armature``/``stiffness [N, nv]``, ``gravity [N, 3]``,
``contact_stiffness``/``contact_damping [N]``, ``contact_friction [N, ncontact]``), so they can be
randomised or differentiated like any other input.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from .mjcf import ArticulatedModel

__all__ = [
    "RigidBodyTree", "Kinematics", "StepResult", "forward_kinematics", "integrate_position", "mass_matrix_and_bias",
    "accelerations", "step", "constraint_force", "site_positions", "default_params", "body_contact_forces",
]

Params = Mapping[str, torch.Tensor]
_MINVAL = 1e-15  # MuJoCo's mjMINVAL


# The _ex variants do not raise on a singular matrix (they return inf/nan for that env only): one
# diverged env of a batch must not take the others, or the run, down with it; the env base class
# flags and resets it.
def _solve(matrix: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    return torch.linalg.solve_ex(matrix, rhs)[0]


def _inverse(matrix: torch.Tensor) -> torch.Tensor:
    return torch.linalg.inv_ex(matrix)[0]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    # torch.linalg.cross dispatches per call; this is cheaper for the many tiny [.., 3] crosses here
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


def _skew(v: torch.Tensor) -> torch.Tensor:
    """``[.., 3] -> [.., 3, 3]`` such that ``skew(v) @ u == v x u``."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([z, -w, y, w, z, -x, -y, x, z], dim=-1).reshape(*v.shape, 3)


def cross_motion(v: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Spatial motion cross product ``v x u`` of ``[.., 6]`` (angular, linear) vectors."""
    w, vl = v[..., :3], v[..., 3:]
    a, ul = u[..., :3], u[..., 3:]
    return torch.cat([_cross(w, a), _cross(w, ul) + _cross(vl, a)], dim=-1)


def cross_force(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Spatial force cross product ``v x* f`` (``[.., 6]``: torque about the origin, force)."""
    w, vl = v[..., :3], v[..., 3:]
    n, fl = f[..., :3], f[..., 3:]
    return torch.cat([_cross(w, n) + _cross(vl, fl), _cross(w, fl)], dim=-1)


@dataclass
class RigidBodyTree:
    """The constant (non-parameter) part of an :class:`ArticulatedModel`, as tensors.

    Built once per env (device, dtype); the per-env physical parameters travel separately.
    """

    model: ArticulatedModel
    body_parent: list[int]
    body_pos: torch.Tensor  # [nbody, 3]
    body_rot: torch.Tensor  # [nbody, 3, 3]
    body_com: torch.Tensor  # [nbody, 3]
    body_joints: list[list[int]]  # joints of each body, in order
    joint_type: list[str]  # "hinge" | "slide" | "ball" | "free"
    joint_qposadr: list[int]
    joint_dofadr: list[int]
    joint_axis: torch.Tensor  # [njnt, 3] body frame
    joint_pos: torch.Tensor  # [njnt, 3]
    joint_skew: torch.Tensor  # [njnt, 3, 3] skew(axis), for Rodrigues
    qpos0: torch.Tensor  # [nq]
    qpos_spring: torch.Tensor  # [nq]
    dof_qpos: torch.Tensor  # [nv] long: the coordinate of each hinge/slide dof (springs, limits); 0 elsewhere
    dof_has_spring: torch.Tensor  # [nv]: 1 for hinge/slide dofs (springs act on them), 0 for ball/free dofs
    position_segments: list[tuple]  # how qvel integrates into qpos (see integrate_position)
    body_dof_mask: torch.Tensor  # [nbody, nv]: dof d moves body b
    dof_pre_mask: torch.Tensor  # [nv, nv]: dof d' moves the frame dof d is attached to (d' before d)
    dof_support: torch.Tensor  # [nv, nv]: dof i moves the body of dof j (where M_ij = S_i . Ic_j S_j)
    contact_dof_mask: torch.Tensor  # [npoint, nv]: dof d moves the body of contact point p
    # joint limits (rows for the lower and upper side of every limited joint)
    limit_dof: torch.Tensor  # [nlimit] long
    limit_sign: torch.Tensor  # [nlimit] +1 lower side, -1 upper side (the constraint Jacobian)
    limit_value: torch.Tensor  # [nlimit] the range end
    limit_margin: torch.Tensor
    limit_solref: torch.Tensor  # [nlimit, 2]
    limit_solimp: torch.Tensor  # [nlimit, 5]
    kin0: Kinematics | None  # kinematics at qpos0 (for MuJoCo's dof_invweight0, see dof_invweight0())
    # motors
    actuator_dof: torch.Tensor  # [nu] long
    actuator_gear: torch.Tensor
    ctrl_low: torch.Tensor
    ctrl_high: torch.Tensor
    force_low: torch.Tensor
    force_high: torch.Tensor
    # contact: points (capsule end spheres, spheres, box corners) against the ground planes
    contact_body: torch.Tensor  # [npoint] long
    contact_local: torch.Tensor  # [npoint, 3] body frame
    contact_radius: torch.Tensor  # [npoint]
    contact_slot: torch.Tensor  # [npoint] long: which contact pair (friction entry) it belongs to
    contact_plane_point: torch.Tensor  # [npoint, 3]
    contact_plane_normal: torch.Tensor  # [npoint, 3]
    contact_pairs: list[tuple[str, str]]  # (geom, plane) of each slot
    contact_pair_friction: np.ndarray  # [npair] MuJoCo's max of the two geoms' sliding friction
    # fluid: each body's principal axes of inertia (its inertial frame) in the body frame
    body_inertial_frame: torch.Tensor  # [nbody, 3, 3]

    @property
    def has_fluid(self) -> bool:
        return self.model.density > 0 or self.model.viscosity > 0

    @property
    def nv(self) -> int:
        return self.model.nv

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nbody(self) -> int:
        return self.model.nbody

    @classmethod
    def from_model(cls, model: ArticulatedModel, dtype=torch.float64, device="cpu") -> RigidBodyTree:
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
        idx = lambda a: torch.as_tensor(np.asarray(a, dtype=np.int64), device=device)  # noqa: E731
        nb, nv, njnt = model.nbody, model.nv, model.njnt
        body_joints = [[j for j in range(njnt) if model.joint_body[j] == b] for b in range(nb)]
        # the dofs of each joint in groups whose motion axes move together: a free joint's
        # translation, then its rotation; every other joint is one group
        groups = []  # (body, dofs)
        for j in range(njnt):
            first, kind, b = int(model.joint_dofadr[j]), model.joint_type[j], int(model.joint_body[j])
            if kind == "free":
                groups += [(b, list(range(first, first + 3))), (b, list(range(first + 3, first + 6)))]
            else:
                groups.append((b, list(range(first, first + (3 if kind == "ball" else 1)))))
        body_dofs = [[d for g, dofs in groups if g == b for d in dofs] for b in range(nb)]
        # dof d moves body b when d belongs to b or to one of its ancestors
        moves = np.zeros((nb, nv))
        pre = np.zeros((nv, nv))
        for b in range(1, nb):
            chain, a = [], b
            while a > 0:
                chain.append(a)
                a = model.body_parent[a]
            for a in chain:
                moves[b, body_dofs[a]] = 1.0
        # pre[d]: the dofs that move the frame d's axis is attached to: the parent's, and the earlier
        # groups of its own body (not its own group: MuJoCo's cdof_dot of a ball joint uses the parent's
        # velocity; the group's own rotation drops out of the bias force, w x w = 0)
        for i, (b, dofs) in enumerate(groups):
            earlier = [d for g, ds in groups[:i] if g == b for d in ds]
            for d in dofs:
                pre[d] = moves[model.body_parent[b]]
                pre[d, earlier] = 1.0
        dof_body = [b for b, dofs in groups for _ in dofs]
        axis = model.joint_axis
        skew = np.stack([np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]) for a in axis]) \
            if njnt else np.zeros((0, 3, 3))
        dof_qpos, dof_has_spring = np.zeros(nv, dtype=np.int64), np.zeros(nv)
        segments = []  # ("linear", qpos start, dof start, length) | ("quaternion", qpos start, dof start)
        for j in range(njnt):
            kind, qa, da = model.joint_type[j], int(model.joint_qposadr[j]), int(model.joint_dofadr[j])
            if kind in ("hinge", "slide"):
                dof_qpos[da], dof_has_spring[da] = qa, 1.0
            if kind == "free":
                segments += [("linear", qa, da, 3), ("quaternion", qa + 3, da + 3)]
            elif kind == "ball":
                segments.append(("quaternion", qa, da))
            elif segments and segments[-1][0] == "linear" and segments[-1][1] + segments[-1][3] == qa:
                segments[-1] = ("linear", segments[-1][1], segments[-1][2], segments[-1][3] + 1)
            else:
                segments.append(("linear", qa, da, 1))
        # joint limits: one row per side
        rows = [(j, side) for j in range(njnt) if model.limited[j] for side in (0, 1)]
        limit_dof = [int(model.joint_dofadr[j]) for j, _ in rows]
        # contact points against each plane of the world body
        points, pairs, pair_friction = [], [], []
        planes = [g for g in range(len(model.geom_names)) if model.geom_type[g] == "plane"]
        for p in planes:
            if model.geom_body[p] != 0:
                raise ValueError(f"{model.path}: plane {model.geom_names[p]!r} must belong to the world body")
        for g in range(len(model.geom_names)):
            if model.geom_body[g] == 0 or model.geom_type[g] == "plane":
                continue
            for p in planes:
                collide = (model.geom_contype[g] & model.geom_conaffinity[p]) or (
                    model.geom_contype[p] & model.geom_conaffinity[g])
                if not collide:
                    continue
                local = _contact_points(model, g)
                normal = model.geom_rot[p][:, 2]
                slot = len(pairs)
                pairs.append((model.geom_names[g], model.geom_names[p]))
                pair_friction.append(max(model.geom_friction[g, 0], model.geom_friction[p, 0]))
                for offset, radius in local:
                    points.append((model.geom_body[g], offset, radius, slot, model.geom_pos[p], normal))
        tree = cls(
            model=model, body_parent=[int(p) for p in model.body_parent], body_pos=t(model.body_pos),
            body_rot=t(model.body_rot), body_com=t(model.body_com), body_joints=body_joints,
            joint_type=list(model.joint_type), joint_qposadr=[int(a) for a in model.joint_qposadr],
            joint_dofadr=[int(a) for a in model.joint_dofadr], joint_axis=t(axis).reshape(njnt, 3),
            joint_pos=t(model.joint_pos).reshape(njnt, 3), joint_skew=t(skew), qpos0=t(model.qpos0),
            qpos_spring=t(model.qpos_spring), dof_qpos=idx(dof_qpos), dof_has_spring=t(dof_has_spring),
            position_segments=segments, body_dof_mask=t(moves), dof_pre_mask=t(pre),
            dof_support=t(moves[dof_body].T.reshape(nv, nv)),
            contact_dof_mask=t(moves[[p[0] for p in points]].reshape(len(points), nv)),
            limit_dof=idx(limit_dof), limit_sign=t([1.0 if s == 0 else -1.0 for _, s in rows]),
            limit_value=t([model.joint_range[j, s] for j, s in rows]),
            limit_margin=t([model.limit_margin[j] for j, _ in rows]),
            # MuJoCo's "refsafe": a time constant below two physics steps is raised to two steps
            limit_solref=t([[max(model.limit_solref[j, 0], 2 * model.timestep), model.limit_solref[j, 1]]
                            for j, _ in rows]).reshape(len(rows), 2),
            limit_solimp=t([model.limit_solimp[j] for j, _ in rows]).reshape(len(rows), 5),
            kin0=None,
            actuator_dof=idx(model.joint_dofadr[model.actuator_joint]), actuator_gear=t(model.actuator_gear),
            ctrl_low=t(np.where(model.ctrl_limited, model.ctrl_range[:, 0], -np.inf)),
            ctrl_high=t(np.where(model.ctrl_limited, model.ctrl_range[:, 1], np.inf)),
            force_low=t(np.where(model.force_limited, model.force_range[:, 0], -np.inf)),
            force_high=t(np.where(model.force_limited, model.force_range[:, 1], np.inf)),
            contact_body=idx([p[0] for p in points]), contact_local=t([p[1] for p in points]).reshape(-1, 3),
            contact_radius=t([p[2] for p in points]), contact_slot=idx([p[3] for p in points]),
            contact_plane_point=t([p[4] for p in points]).reshape(-1, 3),
            contact_plane_normal=t([p[5] for p in points]).reshape(-1, 3),
            contact_pairs=pairs, contact_pair_friction=np.array(pair_friction),
            body_inertial_frame=t(np.linalg.eigh(model.body_inertia)[1]),
        )
        tree.kin0 = forward_kinematics(tree, tree.qpos0.unsqueeze(0))
        return tree


def _contact_points(model: ArticulatedModel, g: int) -> list[tuple[np.ndarray, float]]:
    """Sphere-swept points (body-frame centre, radius) whose distance to a plane is the geom's."""
    kind, size, pos, rot = model.geom_type[g], model.geom_size[g], model.geom_pos[g], model.geom_rot[g]
    if kind == "sphere":
        return [(pos, size[0])]
    if kind == "capsule":
        half = rot[:, 2] * size[1]
        return [(pos - half, size[0]), (pos + half, size[0])]
    if kind == "box":
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
        return [(pos + rot @ c, 0.0) for c in corners]
    raise ValueError(
        f"{model.path}: geom {model.geom_names[g]!r} of type {kind} can touch the ground plane, but ground "
        "contact is only modelled for spheres, capsules and boxes (set contype/conaffinity to exclude it)"
    )


def default_params(model: ArticulatedModel) -> dict[str, torch.Tensor]:
    """The model file's physical parameters (float64, unbatched): the per-env ``params`` defaults
    (with ``fluid_density`` and ``fluid_viscosity`` for a model in a fluid)."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    params = {
        "body_mass": t(model.body_mass), "body_inertia": t(model.body_inertia), "gravity": t(model.gravity),
        # stiffness per dof, as damping (a joint's stiffness on its dof; ball and free joints have none)
        "damping": t(model.damping), "armature": t(model.armature), "stiffness": t(model.stiffness[model.dof_joint]),
    }
    if model.density > 0 or model.viscosity > 0:
        params.update(fluid_density=t(model.density), fluid_viscosity=t(model.viscosity))
    return params


def fluid_force(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params) -> torch.Tensor:
    """``[N, nv]`` generalised force of MuJoCo's inertia-box fluid model (``mj_inertiaBoxFluidModel``).

    Each body is a box with its mass and principal moments of inertia, moving in a still medium
    of ``fluid_density`` and ``fluid_viscosity``: in the body's inertial frame, with ``b`` the box
    sides, ``d = mean(b)``, ``v`` and ``w`` the linear (at the centre of mass) and angular velocity,

        force_i  = -3 pi d viscosity v_i  - density / 2 * b_j b_k |v_i| v_i
        torque_i = -pi d^3 viscosity w_i  - density / 64 * b_i (b_j^4 + b_k^4) |w_i| w_i

    applied at the centre of mass. Smooth (``|x| x`` is C1), so gradients are defined everywhere.
    """
    mass, inertia = params["body_mass"], params["body_inertia"]
    frame = tree.body_inertial_frame  # principal axes in the body frame, from the model file
    moments = torch.diagonal(frame.transpose(-1, -2) @ inertia @ frame, dim1=-2, dim2=-1)  # [N, nbody, 3]
    has_mass = mass > _MINVAL  # MuJoCo skips massless bodies (the world)
    safe_mass = torch.where(has_mass, mass, torch.ones_like(mass)).unsqueeze(-1)
    opposite = moments.sum(-1, keepdim=True) - 2 * moments  # I_j + I_k - I_i
    box = torch.sqrt(torch.clamp(opposite, min=_MINVAL) / safe_mass * 6.0)
    rot = kin.body_rot @ frame  # inertial frames in the world
    com = kin.body_pos + (kin.body_rot @ tree.body_com.unsqueeze(-1)).squeeze(-1) - kin.origin.unsqueeze(1)
    vel = body_velocities(tree, kin, qvel)  # [N, nbody, 6]: angular, linear at kin.origin
    omega = vel[..., :3]
    local_w = (rot.transpose(-1, -2) @ omega.unsqueeze(-1)).squeeze(-1)
    local_v = (rot.transpose(-1, -2) @ (vel[..., 3:] + _cross(omega, com)).unsqueeze(-1)).squeeze(-1)
    density = params["fluid_density"][:, None, None]
    viscosity = params["fluid_viscosity"][:, None, None]
    diameter = box.mean(-1, keepdim=True)
    b0, b1, b2 = box.unbind(-1)
    area = torch.stack([b1 * b2, b0 * b2, b0 * b1], dim=-1)
    fourth = box**4
    spin = box * (fourth.sum(-1, keepdim=True) - fourth) / 64.0  # b_i (b_j^4 + b_k^4) / 64
    force = -3 * math.pi * diameter * viscosity * local_v - 0.5 * density * area * local_v.abs() * local_v
    torque = -math.pi * diameter**3 * viscosity * local_w - density * spin * local_w.abs() * local_w
    mask = has_mass.to(force.dtype).unsqueeze(-1)
    force_w = (rot @ force.unsqueeze(-1)).squeeze(-1) * mask
    torque_w = (rot @ torque.unsqueeze(-1)).squeeze(-1) * mask
    wrench = torch.cat([torque_w + _cross(com, force_w), force_w], dim=-1)  # about kin.origin
    return generalised_force(tree.body_dof_mask, kin, wrench)


def _tree_sum(mask: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``out[:, a] = sum_b mask[a, b] x[:, b]`` for ``x [N, B, k]``: a sum along the tree (which
    bodies a dof moves, which dofs move a body) as one product; einsum folds ``N`` into one
    matrix product, where ``mask @ x`` would broadcast into ``N`` tiny ones (2x slower on a CPU)."""
    return torch.einsum("ab,nbk->nak", mask, x)


def body_velocities(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor) -> torch.Tensor:
    """``[N, nbody, 6]`` spatial velocity of every body (angular, linear at ``kin.origin``):
    the sum of ``S_d qvel_d`` over the dofs that move it."""
    return _tree_sum(tree.body_dof_mask, kin.motion * qvel.unsqueeze(-1))


def generalised_force(dof_mask: torch.Tensor, kin: Kinematics, wrench: torch.Tensor) -> torch.Tensor:
    """``[N, nv]`` generalised force of wrenches ``[N, K, 6]`` (torque about ``kin.origin``, force)
    on bodies or body points, with ``dof_mask [K, nv]`` saying which dofs move each: ``J^T w``, as
    ``S_d . (sum of the wrenches on what dof d moves)``."""
    return (kin.motion * _tree_sum(dof_mask.transpose(0, 1), wrench)).sum(-1)


@dataclass
class Kinematics:
    """World-frame poses for one batch of configurations.

    Spatial vectors (motion subspaces, body velocities, inertias, wrenches) are expressed in world
    axes about ``origin``, a reference point that moves with the robot (its first body's
    position), so that their lever arms stay short wherever the robot is.
    """

    body_rot: torch.Tensor  # [N, nbody, 3, 3]
    body_pos: torch.Tensor  # [N, nbody, 3] body frame origins (world)
    motion: torch.Tensor  # [N, nv, 6] each dof's motion subspace (angular, linear at ``origin``)
    origin: torch.Tensor  # [N, 3] the reference point of the spatial vectors (world)


def quaternion_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """``[.., 4]`` quaternions ``(w, x, y, z)`` (normalised here, as MuJoCo does) -> ``[.., 3, 3]``."""
    w, x, y, z = (quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quat.shape[:-1], 3, 3)


def _quaternion_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def integrate_quaternion(quat: torch.Tensor, omega: torch.Tensor, dt: float) -> torch.Tensor:
    """MuJoCo's ``mju_quatIntegrate``: rotate ``quat`` (normalised first) by the body-frame angular
    velocity ``omega`` for ``dt``: ``quat * (cos(|w| dt / 2), sin(|w| dt / 2) w / |w|)``.

    Smooth at ``omega = 0`` (``sin(|w| dt / 2) / |w|`` is written through ``sinc``).
    """
    speed = torch.sqrt((omega * omega).sum(-1, keepdim=True).clamp(min=_MINVAL * _MINVAL))
    half = 0.5 * dt * speed
    rotation = torch.cat([torch.cos(half), omega * (0.5 * dt) * torch.sinc(half / math.pi)], dim=-1)
    unit = quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
    return _quaternion_product(unit, rotation)


def integrate_position(tree: RigidBodyTree, qpos: torch.Tensor, qvel: torch.Tensor, dt: float) -> torch.Tensor:
    """MuJoCo's ``mj_integratePos``: ``qpos [N, nq]`` moved by ``qvel [N, nv]`` for ``dt``.

    Hinge, slide and a free joint's translation add ``dt * qvel``; ball joints and a free joint's
    rotation turn their quaternion (:func:`integrate_quaternion`).
    """
    if tree.nq == tree.nv:  # hinges and slides only
        return qpos + dt * qvel
    parts = []
    for segment in tree.position_segments:
        if segment[0] == "linear":
            _, qa, da, n = segment
            parts.append(qpos[:, qa:qa + n] + dt * qvel[:, da:da + n])
        else:
            _, qa, da = segment
            parts.append(integrate_quaternion(qpos[:, qa:qa + 4], qvel[:, da:da + 3], dt))
    return torch.cat(parts, dim=-1)


def forward_kinematics(tree: RigidBodyTree, qpos: torch.Tensor) -> Kinematics:
    """Body poses and dof motion subspaces for ``qpos [N, nq]`` (MuJoCo's mj_kinematics and cdof).

    A free joint sets its body's world pose from ``qpos`` (position, quaternion); its dofs move the
    body along the world axes and turn it about its own axes. A ball joint turns its body about its
    anchor by the quaternion; its dofs turn it about the body's axes.
    """
    n = qpos.shape[0]
    eye = torch.eye(3, dtype=qpos.dtype, device=qpos.device).expand(n, 3, 3)
    rots, poss = [eye], [torch.zeros(n, 3, dtype=qpos.dtype, device=qpos.device)]
    motion = [None] * tree.nv
    turning = []  # (dof, world axis, world anchor) of the rotational dofs, placed once the origin is known
    q = qpos - tree.qpos0
    sin, cos = torch.sin(q), torch.cos(q)
    for b in range(1, tree.nbody):
        parent_rot, parent_pos = rots[tree.body_parent[b]], poss[tree.body_parent[b]]
        rot = parent_rot @ tree.body_rot[b]
        pos = parent_pos + parent_rot @ tree.body_pos[b]
        for j in tree.body_joints[b]:
            kind, qa, da = tree.joint_type[j], tree.joint_qposadr[j], tree.joint_dofadr[j]
            if kind == "hinge":
                axis = rot @ tree.joint_axis[j]
                anchor = pos + rot @ tree.joint_pos[j]
                k = tree.joint_skew[j]
                local = eye + sin[:, qa, None, None] * k + (1 - cos[:, qa, None, None]) * (k @ k)  # Rodrigues
                rot = rot @ local
                pos = anchor - rot @ tree.joint_pos[j]
                turning.append((da, axis, anchor))
            elif kind == "slide":
                axis = rot @ tree.joint_axis[j]
                pos = pos + axis * q[:, qa, None]
                motion[da] = torch.cat([torch.zeros_like(axis), axis], dim=-1)
            else:
                if kind == "free":  # the body's world pose is the joint's coordinates
                    pos, rot = qpos[:, qa:qa + 3], quaternion_to_matrix(qpos[:, qa + 3:qa + 7])
                    anchor, turn = pos, da + 3
                    for i in range(3):
                        linear = eye[:, :, i]
                        motion[da + i] = torch.cat([torch.zeros_like(linear), linear], dim=-1)
                else:
                    anchor, turn = pos + rot @ tree.joint_pos[j], da
                    rot = rot @ quaternion_to_matrix(qpos[:, qa:qa + 4])
                    pos = anchor - rot @ tree.joint_pos[j]
                for i in range(3):
                    turning.append((turn + i, rot[:, :, i], anchor))
        rots.append(rot)
        poss.append(pos)
    # The spatial quantities are taken about the first body's position, not the world origin: a
    # runner 100 m down the track would otherwise carry lever arms of 100 m into every inertia
    # (m |c|^2 ~ 1e5) and contact moment, and float32 cancellation would leave the mass matrix
    # indefinite. Detached: the dynamics do not depend on the choice of reference point.
    origin = (poss[1] if tree.nbody > 1 else poss[0]).detach()
    for da, axis, anchor in turning:
        motion[da] = torch.cat([axis, _cross(anchor - origin, axis)], dim=-1)
    motion_t = torch.stack(motion, dim=1) if tree.nv else qpos.new_zeros(n, 0, 6)
    return Kinematics(torch.stack(rots, dim=1), torch.stack(poss, dim=1), motion_t, origin)


def _spatial_inertia(tree: RigidBodyTree, kin: Kinematics, params: Params) -> torch.Tensor:
    """``[N, nbody, 6, 6]`` body inertias in world axes about ``kin.origin``."""
    rot, mass = kin.body_rot, params["body_mass"]
    com = kin.body_pos + (rot @ tree.body_com.unsqueeze(-1)).squeeze(-1) - kin.origin.unsqueeze(1)
    inertia = rot @ params["body_inertia"] @ rot.transpose(-1, -2)
    c = _skew(com)
    m = mass[..., None, None]
    top = torch.cat([inertia - m * (c @ c), m * c], dim=-1)
    eye = torch.eye(3, dtype=mass.dtype, device=mass.device)
    bottom = torch.cat([-m * c, m * eye], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def _composite_mass_matrix(tree: RigidBodyTree, motion: torch.Tensor, composite: torch.Tensor) -> torch.Tensor:
    """The composite-rigid-body algorithm's ``M_ij = S_i . (Ic_j S_j)`` ``[N, nv, nv]`` from the
    dof motion axes ``[N or 1, nv, 6]`` and ``composite [N, nv, 6, 6]``, ``Ic_j`` the summed
    inertia of everything dof ``j`` moves (world axes, about ``kin.origin``).

    The formula holds where dof ``i`` moves dof ``j``'s body; the other triangle follows by
    symmetry, and dofs on separate branches do not couple.
    """
    momentum = (composite @ motion.unsqueeze(-1)).squeeze(-1)  # Ic_j S_j
    lower = (motion @ momentum.transpose(-1, -2)) * tree.dof_support  # S_i . Ic_j S_j where i moves j
    return lower + lower.transpose(-1, -2) * (1 - tree.dof_support)  # mirrored where j does not move i


def _joint_space_inertia(tree: RigidBodyTree, motion: torch.Tensor, inertia: torch.Tensor) -> torch.Tensor:
    """The mass matrix ``[N, nv, nv]`` (no armature) of the bodies' inertias ``[N, nbody, 6, 6]``."""
    n, nbody = inertia.shape[:2]
    composite = _tree_sum(tree.body_dof_mask.transpose(0, 1), inertia.reshape(n, nbody, 36))
    return _composite_mass_matrix(tree, motion, composite.reshape(n, -1, 6, 6))


def mass_matrix_and_bias(tree, kin: Kinematics, qvel: torch.Tensor, params: Params):
    """Joint-space mass matrix ``[N, nv, nv]`` (armature included) and bias force ``[N, nv]``.

    The bias force is MuJoCo's ``qfrc_bias``: Coriolis, centrifugal and gravity terms.
    """
    inertia = _spatial_inertia(tree, kin, params)
    mass = _joint_space_inertia(tree, kin.motion, inertia) + torch.diag_embed(params["armature"])
    # velocity-product accelerations; gravity enters as an upward acceleration of the world
    dof_motion = kin.motion * qvel.unsqueeze(-1)  # [N, nv, 6]
    body_vel = _tree_sum(tree.body_dof_mask, dof_motion)  # [N, nbody, 6]
    pre_vel = _tree_sum(tree.dof_pre_mask, dof_motion)
    motion_dot = cross_motion(pre_vel, dof_motion)  # [N, nv, 6] d(S_d)/dt qvel_d
    gravity = torch.cat([torch.zeros_like(params["gravity"]), -params["gravity"]], dim=-1)
    body_acc = gravity.unsqueeze(1) + _tree_sum(tree.body_dof_mask, motion_dot)
    momentum = (inertia @ body_vel.unsqueeze(-1)).squeeze(-1)
    force = (inertia @ body_acc.unsqueeze(-1)).squeeze(-1) + cross_force(body_vel, momentum)
    return mass, generalised_force(tree.body_dof_mask, kin, force)


def actuator_force(tree: RigidBodyTree, ctrl: torch.Tensor, nv: int) -> torch.Tensor:
    """``[N, nv]`` generalised motor forces: ``gear * clamp(ctrl)`` (force range applied before the gear)."""
    force = torch.clamp(torch.clamp(ctrl, tree.ctrl_low, tree.ctrl_high), tree.force_low, tree.force_high)
    out = ctrl.new_zeros(ctrl.shape[0], nv)
    return out.index_add(1, tree.actuator_dof, force * tree.actuator_gear)


class _ContactForces(NamedTuple):
    point: torch.Tensor  # [N, P, 3] where each force acts (the point of the sphere nearest the plane)
    force: torch.Tensor  # [N, P, 3] on the body, world frame
    normal: torch.Tensor  # [P, 3]
    normal_force: torch.Tensor  # [N, P]
    touching: torch.Tensor  # [N, P]
    damping: torch.Tensor  # [N, 1]
    mu: torch.Tensor  # [N, P]
    slip: torch.Tensor  # [N, P]


def _contact_points_and_forces(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params) -> _ContactForces:
    """The smooth contact model (see :func:`contact_force`) at every contact point."""
    rot = kin.body_rot[:, tree.contact_body]  # [N, P, 3, 3]
    centre = kin.body_pos[:, tree.contact_body] + (rot @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    normal = tree.contact_plane_normal
    dist = ((centre - tree.contact_plane_point) * normal).sum(-1) - tree.contact_radius  # [N, P]
    point = centre - tree.contact_radius.unsqueeze(-1) * normal
    body_vel = body_velocities(tree, kin, qvel)[:, tree.contact_body]
    lever = point - kin.origin.unsqueeze(1)
    vel = body_vel[..., 3:] + _cross(body_vel[..., :3], lever)  # velocity of the body point at the contact
    normal_vel = (vel * normal).sum(-1)
    tangent_vel = vel - normal_vel.unsqueeze(-1) * normal
    width = params["contact_width"].unsqueeze(-1)
    depth = F.softplus(-dist / width) * width
    touching = torch.sigmoid(-dist / width)
    stiffness, damping = params["contact_stiffness"].unsqueeze(-1), params["contact_damping"].unsqueeze(-1)
    normal_force = torch.clamp(stiffness * depth - damping * touching * normal_vel, min=0.0)
    mu = params["contact_friction"][:, tree.contact_slot]
    eps = params["friction_velocity"].unsqueeze(-1)
    slip = torch.sqrt((tangent_vel * tangent_vel).sum(-1) + eps * eps)
    force = normal_force.unsqueeze(-1) * (normal - (mu / slip).unsqueeze(-1) * tangent_vel)
    return _ContactForces(point, force, normal, normal_force, touching, damping, mu, slip)


def body_contact_forces(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params, about: torch.Tensor) -> torch.Tensor:
    """``[N, nbody, 6]``: the ground's contact wrench on every body (torque, force; world frame),
    the torque taken about the point ``about [N, 3]`` (MuJoCo's ``cfrc_ext`` takes it about the
    subtree centre of mass of the body's root)."""
    out = qvel.new_zeros(qvel.shape[0], tree.nbody, 6)
    if tree.contact_body.numel() == 0:
        return out
    c = _contact_points_and_forces(tree, kin, qvel, params)
    wrench = torch.cat([_cross(c.point - about.unsqueeze(1), c.force), c.force], dim=-1)
    return out.index_add(1, tree.contact_body, wrench)


def contact_force(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params, with_damping=False):
    """``[N, nv]`` generalised force of the smooth ground contacts.

    Each contact point (a capsule end, a sphere, a box corner) with signed distance ``d`` to a
    ground plane gets a normal force ``k * s(-d) + c * sigmoid(-d / w) * (-v_n)`` (clamped at 0),
    where ``s`` is a softplus of width ``w = contact_width`` (the smooth penetration depth), and a
    friction force ``-mu f_n v_t / sqrt(|v_t|^2 + v_eps^2)``: Coulomb's law with the stick-slip
    corner rounded off over ``v_eps = friction_velocity``. Every term is smooth in the state, and
    the forces grow linearly with the depth, so gradients stay finite at deep penetration.

    ``with_damping=True`` also returns ``C [N, nv, nv]``, the (positive semi-definite) velocity
    damping of these forces, ``-d(force)/d(qvel)`` with the friction direction held fixed: the
    Euler integrator treats it implicitly, as MuJoCo treats joint damping.
    """
    if tree.contact_body.numel() == 0:
        zero = qvel.new_zeros(qvel.shape)
        return (zero, qvel.new_zeros(*qvel.shape, qvel.shape[-1])) if with_damping else zero
    c = _contact_points_and_forces(tree, kin, qvel, params)
    point, force, normal, damping, touching = c.point, c.force, c.normal, c.damping, c.touching
    normal_force, mu, slip = c.normal_force, c.mu, c.slip
    lever = point - kin.origin.unsqueeze(1)
    spatial = torch.cat([_cross(lever, force), force], dim=-1)  # wrench about kin.origin
    generalised = generalised_force(tree.contact_dof_mask, kin, spatial)
    if not with_damping:
        return generalised
    # each point damps its normal velocity with a = c * touching (while pushing) and its tangential
    # velocity with b = mu f_n / slip: J^T (a n n^T + b (I - n n^T)) J = b J^T J + (a - b) u u^T, u = J^T n
    pushing = (normal_force > 0).to(qvel.dtype)
    normal_rate = damping * touching * pushing
    tangent_rate = mu * normal_force / slip  # [N, P]
    damping_matrix = _point_mass_matrix(tree, kin, lever, tangent_rate)
    unit_force = torch.cat([_cross(lever, normal.expand_as(point)), normal.expand_as(point)], dim=-1)
    u = (unit_force @ kin.motion.transpose(1, 2)) * tree.contact_dof_mask  # [N, P, nv]: J_p^T n
    damping_matrix = damping_matrix + (u * (normal_rate - tangent_rate).unsqueeze(-1)).transpose(1, 2) @ u
    return generalised, damping_matrix


def _point_mass_matrix(tree: RigidBodyTree, kin: Kinematics, point: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``sum_p weight_p J_p^T J_p`` ``[N, nv, nv]``, ``J_p`` the linear velocity Jacobian of contact
    point ``p`` (``point [N, P, 3]`` relative to ``kin.origin``, ``weight [N, P]``): the mass matrix of point masses ``weight_p``
    at the points, whose summed spatial inertias only need the sums of ``w``, ``w p`` and ``w p p^T``
    (rotational part ``|p|^2 I - p p^T``, coupling ``skew(p)``, translational ``I``)."""
    w = weight.unsqueeze(-1)
    moments = torch.cat([w, w * point, (w.unsqueeze(-1) * point.unsqueeze(-1) * point.unsqueeze(-2)).flatten(-2)], -1)
    summed = _tree_sum(tree.contact_dof_mask.transpose(0, 1), moments)  # [N, nv, 13] over the points each dof moves
    mass, first, second = summed[..., :1, None], summed[..., 1:4], summed[..., 4:].unflatten(-1, (3, 3))
    eye = torch.eye(3, dtype=point.dtype, device=point.device)
    trace = second.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    coupling = _skew(first)
    composite = torch.cat([torch.cat([trace * eye - second, coupling], dim=-1),
                           torch.cat([-coupling, mass * eye], dim=-1)], dim=-2)
    return _composite_mass_matrix(tree, kin.motion, composite)


def _impedance(solimp: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
    """MuJoCo's impedance ``d(r)`` in ``(0, 1)`` (solimp: dmin, dmax, width, midpoint, power)."""
    dmin, dmax, width, mid, power = solimp.unbind(-1)
    x = torch.clamp(violation.abs() / width.clamp(min=_MINVAL), max=1.0)
    low = x.clamp(min=_MINVAL) ** power / mid ** (power - 1)
    high = 1 - (1 - x).clamp(min=_MINVAL) ** power / (1 - mid) ** (power - 1)
    y = torch.where(x <= mid, low, high)
    y = torch.where(x >= 1, torch.ones_like(y), torch.where(x <= 0, torch.zeros_like(y), y))
    imp = dmin + y * (dmax - dmin)
    flat = (dmin == dmax) | (width <= 1e-15)
    return torch.where(flat, (dmin + dmax) / 2, imp)


def dof_invweight0(tree: RigidBodyTree, params: Params) -> torch.Tensor:
    """MuJoCo's ``dof_invweight0 [N, nv]``: ``diag(M^-1)`` at ``qpos0`` for these params' masses
    (averaged over a ball joint's three dofs and over each half of a free joint's, as MuJoCo's).

    MuJoCo computes it when it compiles the model (``mj_setConst``), so a model file with other
    masses gets other values; here it follows the per-env params, as a model compiled with them.
    """
    kin0 = tree.kin0
    inertia = _spatial_inertia(tree, kin0, params)
    mass = _joint_space_inertia(tree, kin0.motion, inertia) + torch.diag_embed(params["armature"])
    weight = _inverse(mass).diagonal(dim1=-2, dim2=-1)
    # MuJoCo averages over a ball joint's dofs and over each half (translation, rotation) of a free joint's
    for kind, da in zip(tree.joint_type, tree.joint_dofadr):
        for first in {"ball": (da,), "free": (da, da + 3)}.get(kind, ()):
            mean = weight[:, first:first + 3].mean(-1, keepdim=True)
            weight = torch.cat([weight[:, :first], mean.expand(-1, 3), weight[:, first + 3:]], dim=-1)
    return weight


def limit_force(tree: RigidBodyTree, qpos, qvel, smooth_acc, mass_inv, invweight0) -> torch.Tensor:
    """``[N, nv]`` joint-limit forces: MuJoCo's soft constraint, one row per active limit side.

    For row ``i`` with distance ``r`` (negative when violated), velocity ``v = J qvel`` and
    unconstrained acceleration ``a0 = J qacc_smooth``: ``aref = -B v - K d(r) (r - margin)``,
    ``R = (1 - d) / d * invweight0`` (:func:`dof_invweight0`); the forces ``f >= 0`` of the active
    rows solve MuJoCo's constraint problem jointly (the rows couple through ``A = J M^-1 J^T``):
    the linear complementarity problem ``w = (A + R) f + (a0 - aref) >= 0``, ``f >= 0``,
    ``f . w = 0``, solved exactly by principal pivoting (a fixed number of rounds, batched), and
    applied as ``J^T f``. With one active row this is ``f = max(0, -(a0 - aref) / (A_ii + R_i))``.
    """
    if tree.limit_dof.numel() == 0:
        return torch.zeros_like(qvel)
    dof, sign = tree.limit_dof, tree.limit_sign
    dist = sign * (qpos[:, tree.dof_qpos[dof]] - tree.limit_value)
    active = dist < tree.limit_margin
    imp = _impedance(tree.limit_solimp, dist - tree.limit_margin)
    timeconst, dampratio = tree.limit_solref.unbind(-1)
    dmax = tree.limit_solimp[:, 1]
    stiffness = 1 / (dmax * dmax * timeconst * timeconst * dampratio * dampratio).clamp(min=_MINVAL)
    damping = 2 / (dmax * timeconst).clamp(min=_MINVAL)
    aref = -damping * sign * qvel[:, dof] - stiffness * imp * (dist - tree.limit_margin)
    regulariser = torch.clamp((1 - imp) * invweight0[:, dof] / imp, min=_MINVAL)
    offset = sign * smooth_acc[:, dof] - aref  # a0 - aref
    diagonal = mass_inv.diagonal(dim1=-2, dim2=-1)[:, dof] + regulariser  # of A + R

    def coupling(envs) -> torch.Tensor:  # A + R of these envs (built only where rows couple)
        block = mass_inv[envs][:, dof][:, :, dof]
        return sign[:, None] * sign[None, :] * block + torch.diag_embed(regulariser[envs])

    force = _complementary_forces(offset, active, diagonal, coupling)
    return torch.zeros_like(qvel).index_add(1, dof, sign * force)


def _complementary_forces(offset: torch.Tensor, allowed: torch.Tensor, diagonal: torch.Tensor,
                          matrix_of) -> torch.Tensor:
    """``f >= 0`` with ``w = matrix f + offset >= 0`` and ``f . w = 0`` over the ``allowed`` rows
    (``f = 0`` elsewhere), for a positive definite ``matrix`` ``[N, L, L]`` with ``diagonal``
    ``[N, L]``; ``matrix_of(envs)`` builds the matrices of the envs ``envs`` indexes.

    With at most one allowed row it is ``max(0, -offset / matrix_ii)``; envs with several are
    solved by principal pivoting: each round solves the rows of the current set exactly, then
    flips the first row that breaks the conditions (Murty's least-index rule, which cannot cycle):
    a chosen row with a negative force leaves, an allowed row with a negative ``w`` joins. Eagerly
    only the envs with several allowed rows pivot, until no row breaks; under ``torch.compile``
    every env takes ``2 L`` rounds (no data-dependent control flow).
    """
    if torch.compiler.is_compiling():
        return _pivot(matrix_of(slice(None)), offset, allowed, early_exit=False)
    single = torch.where(allowed, (-offset / diagonal).clamp(min=0.0), torch.zeros_like(offset))
    coupled = allowed.sum(-1) >= 2
    if not bool(coupled.any()):
        return single
    envs = coupled.nonzero().squeeze(-1)
    solved = _pivot(matrix_of(envs), offset[envs], allowed[envs], early_exit=True)
    return single.index_put((envs,), solved)


def _pivot(matrix, offset, allowed, early_exit: bool) -> torch.Tensor:
    rows = offset.shape[-1]
    eye = torch.eye(rows, dtype=matrix.dtype, device=matrix.device)
    index = torch.arange(rows, device=offset.device)

    def solve(chosen):
        both = chosen.unsqueeze(-1) & chosen.unsqueeze(-2)
        reduced = torch.where(both, matrix, eye)  # the chosen block, identity elsewhere
        return _solve(reduced, torch.where(chosen, -offset, torch.zeros_like(offset)))

    chosen = allowed & (offset < 0)  # the rows that push on their own
    for _ in range(2 * rows):
        force = solve(chosen)
        slack = (matrix @ force.unsqueeze(-1)).squeeze(-1) + offset
        broken = (chosen & (force < 0)) | (allowed & ~chosen & (slack < 0))
        if early_exit and not bool(broken.any()):
            return torch.where(chosen, force.clamp(min=0.0), torch.zeros_like(offset))
        first = broken & (index == torch.where(broken, index, rows).min(-1, keepdim=True).values)
        chosen = chosen ^ first
    return torch.where(chosen, solve(chosen).clamp(min=0.0), torch.zeros_like(offset))


def _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=False):
    """Motors + passive joint forces + ground contact - bias: every force but the joint limits.

    ``with_damping``: also the velocity damping of these forces that an implicit integrator
    uses (joint damping plus the contact's, see :func:`contact_force`).
    """
    # springs act on hinge and slide coordinates (ball and free joints have none, see the loader)
    stretch = (qpos - tree.qpos_spring)[:, tree.dof_qpos] * tree.dof_has_spring
    passive = -params["damping"] * qvel - params["stiffness"] * stretch
    if tree.has_fluid:
        passive = passive + fluid_force(tree, kin, qvel, params)
    force = actuator_force(tree, ctrl, tree.nv) + passive - bias
    damping = torch.diag_embed(params["damping"]) if with_damping else None
    if tree.contact_body.numel():
        contact = contact_force(tree, kin, qvel, params, with_damping=with_damping)
        if with_damping:
            contact, contact_damping = contact
            damping = damping + contact_damping
        force = force + contact
    return (force, damping) if with_damping else force


def accelerations(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, *, implicit_damping_dt=None,
                  invweight0=None):
    """``qacc [N, nv]`` of MuJoCo's forward dynamics (smooth forces, contact, joint limits).

    ``implicit_damping_dt = h`` gives the acceleration of MuJoCo's Euler integrator, which solves
    with ``M + h D``: joint damping treated implicitly (MuJoCo), and here the contact's velocity
    damping too (explicit contact friction and damping at MuJoCo's 0.01 s steps would be unstable).
    ``invweight0``: :func:`dof_invweight0` of ``params`` when the caller has it (computed if not).
    """
    kin = forward_kinematics(tree, qpos)
    mass, bias = mass_matrix_and_bias(tree, kin, qvel, params)
    implicit = implicit_damping_dt is not None
    force = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=implicit)
    if implicit:
        force, damping = force
    if tree.limit_dof.numel():
        mass_inv = _inverse(mass)
        smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
        invweight0 = dof_invweight0(tree, params) if invweight0 is None else invweight0
        force = force + limit_force(tree, qpos, qvel, smooth_acc, mass_inv, invweight0)
    if implicit:
        mass = mass + implicit_damping_dt * damping
    return _solve(mass, force)


class StepResult(NamedTuple):
    """One physics step: the new state, and the state MuJoCo last evaluated (see :func:`step`)."""

    qpos: torch.Tensor
    qvel: torch.Tensor
    eval_qpos: torch.Tensor
    eval_qvel: torch.Tensor


def step(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, dt: float, integrator: str,
         invweight0=None) -> StepResult:
    """One physics step of MuJoCo's ``integrator`` (``"euler"`` or ``"rk4"``).

    Besides the new state, returns the state at which MuJoCo evaluated the forward dynamics last
    (the start state for Euler, the fourth stage for RK4): after ``mj_step`` MuJoCo's derived
    quantities (body and site positions, constraint forces) belong to that state, and Gymnasium's
    observations and rewards read some of them. ``invweight0``: :func:`dof_invweight0` of
    ``params``, if the caller has it.
    """
    # the params are the same at every stage: the limits' regulariser scale is computed once
    # (callers stepping several times with the same params pass it in: see MuJoCoModelEnv.simulate)
    w0 = invweight0
    if w0 is None and tree.limit_dof.numel():
        w0 = dof_invweight0(tree, params)
    if integrator == "euler":
        qacc = accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt=dt, invweight0=w0)
        new_qvel = qvel + dt * qacc
        return StepResult(integrate_position(tree, qpos, new_qvel, dt), new_qvel, qpos, qvel)
    if integrator != "rk4":
        raise ValueError(f"unknown integrator {integrator!r}; valid: 'euler', 'rk4'")
    # MuJoCo's mj_RungeKutta with the classic tableau
    acc1 = accelerations(tree, qpos, qvel, ctrl, params, invweight0=w0)
    vel2 = qvel + 0.5 * dt * acc1
    acc2 = accelerations(tree, integrate_position(tree, qpos, qvel, 0.5 * dt), vel2, ctrl, params, invweight0=w0)
    vel3 = qvel + 0.5 * dt * acc2
    acc3 = accelerations(tree, integrate_position(tree, qpos, vel2, 0.5 * dt), vel3, ctrl, params, invweight0=w0)
    vel4 = qvel + dt * acc3
    pos4 = integrate_position(tree, qpos, vel3, dt)
    acc4 = accelerations(tree, pos4, vel4, ctrl, params, invweight0=w0)
    new_qpos = integrate_position(tree, qpos, (qvel + 2 * vel2 + 2 * vel3 + vel4) / 6, dt)
    new_qvel = qvel + dt / 6 * (acc1 + 2 * acc2 + 2 * acc3 + acc4)
    return StepResult(new_qpos, new_qvel, pos4, vel4)


def constraint_force(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params) -> torch.Tensor:
    """MuJoCo's ``qfrc_constraint [N, nv]`` at a state: the joint-limit forces (contact is a smooth force here)."""
    kin = forward_kinematics(tree, qpos)
    mass, bias = mass_matrix_and_bias(tree, kin, qvel, params)
    force = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias)
    mass_inv = _inverse(mass)
    smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
    return limit_force(tree, qpos, qvel, smooth_acc, mass_inv, dof_invweight0(tree, params))


def site_positions(tree: RigidBodyTree, kin: Kinematics, sites) -> torch.Tensor:
    """World positions ``[N, len(sites), 3]`` of the model's sites with these indices."""
    model = tree.model
    body = torch.as_tensor(model.site_body[list(sites)], device=kin.body_pos.device)
    local = torch.as_tensor(model.site_pos[list(sites)], dtype=kin.body_pos.dtype, device=kin.body_pos.device)
    return kin.body_pos[:, body] + (kin.body_rot[:, body] @ local.unsqueeze(-1)).squeeze(-1)
