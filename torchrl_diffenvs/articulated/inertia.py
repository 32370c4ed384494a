"""Inertia and bias: the joint-space mass matrix by the composite-rigid-body algorithm, MuJoCo's
``qfrc_bias`` (Coriolis, centrifugal, gravity) by the recursive Newton-Euler terms, and
``dof_invweight0``."""
from __future__ import annotations

import torch

from .kinematics import Kinematics, _tree_sum, forward_kinematics, generalised_force
from .spatial import Params, _inverse, _skew, cross_force, cross_motion
from .tree import RigidBodyTree

__all__ = ['mass_matrix_and_bias', 'dof_invweight0']


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


def dof_invweight0(tree: RigidBodyTree, params: Params) -> torch.Tensor:
    """MuJoCo's ``dof_invweight0 [N, nv]``: ``diag(M^-1)`` at ``qpos0`` for these params' masses
    (averaged over a ball joint's three dofs and over each half of a free joint's, as MuJoCo's).

    MuJoCo computes it when it compiles the model (``mj_setConst``), so a model file with other
    masses gets other values; here it follows the per-env params, as a model compiled with them.
    """
    kin0 = kinematics_at_qpos0(tree)
    inertia = _spatial_inertia(tree, kin0, params)
    mass = _joint_space_inertia(tree, kin0.motion, inertia) + torch.diag_embed(params["armature"])
    weight = _inverse(mass).diagonal(dim1=-2, dim2=-1)
    # MuJoCo averages over a ball joint's dofs and over each half (translation, rotation) of a free joint's
    for kind, da in zip(tree.joint_type, tree.joint_dofadr):
        for first in {"ball": (da,), "free": (da, da + 3)}.get(kind, ()):
            mean = weight[:, first:first + 3].mean(-1, keepdim=True)
            weight = torch.cat([weight[:, :first], mean.expand(-1, 3), weight[:, first + 3:]], dim=-1)
    if tree.simple_dofs:  # MuJoCo: a slide-only body hanging from the world weighs its mass, armature aside
        mass = params["body_mass"].index_select(1, tree.simple_dof_body)
        weight = weight.index_copy(1, tree.simple_dof_index, 1.0 / mass.clamp_min(1e-15))
    return weight


def kinematics_at_qpos0(tree: RigidBodyTree) -> Kinematics:
    """The kinematics at ``qpos0`` (computed once per tree, then kept on it)."""
    if tree.kin0 is None:
        tree.kin0 = forward_kinematics(tree, tree.qpos0.unsqueeze(0))
    return tree.kin0
