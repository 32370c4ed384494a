"""Inertia and bias: the joint-space mass matrix by the composite-rigid-body algorithm, MuJoCo's
``qfrc_bias`` (Coriolis, centrifugal, gravity) by the recursive Newton-Euler terms, and
``dof_invweight0``."""
from __future__ import annotations

import torch

from .kinematics import Kinematics, _tree_sum, forward_kinematics, generalised_force
from .spatial import Params, _inverse, _skew, cross_force, cross_motion, small_matmul, small_matvec
from .tree import RigidBodyTree

__all__ = ['mass_matrix_and_bias', 'bias_velocity_jacobian', 'dof_invweight0']


def _spatial_inertia(tree: RigidBodyTree, kin: Kinematics, params: Params) -> torch.Tensor:
    """``[N, nbody, 6, 6]`` body inertias in world axes about ``kin.origin``."""
    rot, mass = kin.body_rot, params["body_mass"]
    com = kin.body_pos + small_matvec(rot, tree.body_com) - kin.origin.unsqueeze(1)
    inertia = small_matmul(small_matmul(rot, params["body_inertia"]), rot.transpose(-1, -2))
    c = _skew(com)
    m = mass[..., None, None]
    top = torch.cat([inertia - m * small_matmul(c, c), m * c], dim=-1)
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
    momentum = small_matvec(composite, motion)  # Ic_j S_j
    lower = small_matmul(motion, momentum.transpose(-1, -2)) * tree.dof_support  # S_i . Ic_j S_j where i moves j
    return lower + lower.transpose(-1, -2) * (1 - tree.dof_support)  # mirrored where j does not move i


def _joint_space_inertia(tree: RigidBodyTree, motion: torch.Tensor, inertia: torch.Tensor) -> torch.Tensor:
    """The mass matrix ``[N, nv, nv]`` (no armature) of the bodies' inertias ``[N, nbody, 6, 6]``."""
    n, nbody = inertia.shape[:2]
    composite = _tree_sum(tree.body_dof_mask.transpose(0, 1), inertia.reshape(n, nbody, 36))
    return _composite_mass_matrix(tree, motion, composite.reshape(n, -1, 6, 6))


def mass_matrix_and_bias(tree, kin: Kinematics, qvel: torch.Tensor, params: Params, with_velocity_jacobian=False):
    """Joint-space mass matrix ``[N, nv, nv]`` (armature included) and bias force ``[N, nv]``.

    The bias force is MuJoCo's ``qfrc_bias``: Coriolis, centrifugal and gravity terms.

    Args:
        tree: the model's tensors.
        kin: the bodies' [`Kinematics`][torchrl_diffenvs.articulated.Kinematics] at the state.
        qvel: ``[N, nv]`` velocities.
        params: the physical parameters, each ``[N, ...]``.
        with_velocity_jacobian: also return ``d qfrc_bias / d qvel [N, nv, nv]``
            (`bias_velocity_jacobian`), as a third result.
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
    momentum = small_matvec(inertia, body_vel)
    force = small_matvec(inertia, body_acc) + cross_force(body_vel, momentum)
    bias = generalised_force(tree.body_dof_mask, kin, force)
    if with_velocity_jacobian:
        return mass, bias, _bias_velocity_jacobian(tree, kin, qvel, inertia)
    return mass, bias


def bias_velocity_jacobian(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params) -> torch.Tensor:
    """``d qfrc_bias / d qvel [N, nv, nv]`` (entry ``[i, j]``: of bias ``i`` in ``qvel_j``): the
    velocity derivative of the Coriolis and centrifugal forces that MuJoCo's ``implicit``
    integrator treats implicitly (MuJoCo's ``mjd_rne_v``)."""
    return _bias_velocity_jacobian(tree, kin, qvel, _spatial_inertia(tree, kin, params))


def _bias_velocity_jacobian(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, inertia: torch.Tensor):
    """`bias_velocity_jacobian` from the bodies' spatial inertias: the derivative of the
    velocity-product terms of [`mass_matrix_and_bias`][torchrl_diffenvs.articulated.mass_matrix_and_bias] along each ``qvel_j`` at once.

    With ``S_j`` dof ``j``'s motion axis, ``v_b`` body ``b``'s velocity and ``I_b`` its inertia,
    ``qvel_j`` changes ``v_b`` by ``S_j`` (where ``j`` moves ``b``), the velocity-product
    acceleration ``a_b = sum_d v_pre(d) x S_d qvel_d`` (over the dofs ``d`` moving ``b``) by
    ``S_j x sum_d S_d qvel_d`` (over the ``d`` that ``j`` precedes) ``+ v_pre(j) x S_j``, and the
    body force ``I_b a_b + v_b x* I_b v_b`` accordingly; the bias is ``S_i`` against the forces of
    the bodies dof ``i`` moves. Costs ``nv`` bias evaluations' worth of small products in one batch.
    """
    motion, moves = kin.motion, tree.body_dof_mask  # [N, nv, 6], [nbody, nv]
    dof_motion = motion * qvel.unsqueeze(-1)  # [N, nv, 6]: S_d qvel_d
    body_vel = _tree_sum(moves, dof_motion)  # [N, nbody, 6]
    # the cross products as 6x6 matrices, applied by batched products: broadcasting [N, nv, nbody, 6]
    # vectors through element-wise crosses was 10x slower at N = 1024
    axis_cross = _motion_cross_matrix(motion)  # [N, J, 6, 6]: S_j x .
    # d a_b / d qvel_j = S_j x (sum_d moves[b, d] pre[d, j] S_d qvel_d) + moves[b, j] v_pre(j) x S_j, and
    # v_pre(j) x S_j = -S_j x v_pre(j): one cross with S_j of the velocities weighted by tree.bias_carry
    carried = torch.einsum("bdj,ndk->njkb", tree.bias_carry, dof_motion)  # [N, J, 6, nbody]
    moved = moves.transpose(0, 1)[None, :, None, :]  # [1, J, 1, nbody]: dof j moves body b
    acc = axis_cross @ carried  # [N, J, 6, nbody]
    momentum = small_matvec(inertia, body_vel)  # [N, nbody, 6]
    # S_j x* (I_b v_b) = -(S_j x)^T (I_b v_b), and v_b x* (I_b S_j)
    gyroscopic = -axis_cross.transpose(-1, -2) @ momentum.transpose(1, 2).unsqueeze(1)  # [N, J, 6, nbody]
    axis_momentum = torch.einsum("nbkl,njl->nbkj", inertia, motion)  # [N, nbody, 6, J]: I_b S_j
    spin = -_motion_cross_matrix(body_vel).transpose(-1, -2) @ axis_momentum  # [N, nbody, 6, J]
    inertial = torch.einsum("nbkl,njlb->njkb", inertia, acc)  # I_b acc_jb
    force = inertial + moved * (gyroscopic + spin.permute(0, 3, 2, 1))  # [N, J, 6, nbody]

    # bias_i = S_i . sum_b moves[b, i] force_b, for each j
    summed = force @ moves.to(force.dtype)  # [N, J, 6, nv]
    return torch.einsum("njki,nik->nij", summed, motion)


def _motion_cross_matrix(v: torch.Tensor) -> torch.Tensor:
    """``[.., 6] -> [.., 6, 6]``: the matrix of ``u -> v x u`` (`cross_motion`);
    ``-(its transpose)`` is ``f -> v x* f``."""
    w, linear = _skew(v[..., :3]), _skew(v[..., 3:])
    zero = torch.zeros_like(w)
    return torch.cat([torch.cat([w, zero], dim=-1), torch.cat([linear, w], dim=-1)], dim=-2)


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


def body_invweight0(tree: RigidBodyTree, params: Params) -> torch.Tensor:
    """MuJoCo's ``body_invweight0 [N, nbody, 2]`` at ``qpos0`` for these params' masses: the mean
    diagonal of ``J M^-1 J^T`` over the translation (``[..., 0]``) and the rotation (``[..., 1]``)
    of each body's centre of mass, the scale of a contact's regulariser (``mj_diagApprox``).

    Static bodies get 0; MuJoCo's "simple" bodies (slides only, hanging from the world) ``1 / mass``
    and 0. Computed when MuJoCo compiles the model; here it follows the per-env params.
    """
    kin0 = kinematics_at_qpos0(tree)
    inertia = _spatial_inertia(tree, kin0, params)
    mass = _joint_space_inertia(tree, kin0.motion, inertia) + torch.diag_embed(params["armature"])
    com = kin0.body_pos + small_matvec(kin0.body_rot, tree.body_com) - kin0.origin.unsqueeze(1)
    angular = kin0.motion[:, None, :, :3].expand(-1, tree.nbody, -1, -1)  # [1, nbody, nv, 3]
    linear = kin0.motion[:, None, :, 3:] + torch.linalg.cross(angular, com[:, :, None, :].expand_as(angular))
    moves = tree.body_dof_mask[None, :, :, None]  # [1, nbody, nv, 1]
    jac = torch.cat([linear, angular], dim=-1) * moves  # [1, nbody, nv, 6]: each dof's motion of the body's com
    solved = torch.linalg.solve_ex(mass.unsqueeze(1), jac.expand(mass.shape[0], -1, -1, -1))[0]  # [N, nbody, nv, 6]
    diagonal = (jac * solved).sum(-2)  # [N, nbody, 6]
    weight = torch.stack([diagonal[..., :3].mean(-1), diagonal[..., 3:].mean(-1)], dim=-1)
    if tree.simple_dofs:
        body = tree.simple_dof_body
        simple = torch.stack([1.0 / params["body_mass"].index_select(1, body).clamp_min(1e-15),
                              torch.zeros_like(params["body_mass"].index_select(1, body))], dim=-1)
        weight = weight.index_copy(1, body, simple)
    return weight
