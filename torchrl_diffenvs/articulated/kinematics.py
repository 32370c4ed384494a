"""Forward kinematics: body poses and dof motion axes from ``qpos`` (MuJoCo's ``mj_kinematics``
and ``cdof``), the sums along the tree that turn dof quantities into body quantities and back,
and ``mj_integratePos``."""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .spatial import _cross, integrate_quaternion, quaternion_to_matrix, small_matmul, small_matvec
from .tree import RigidBodyTree

__all__ = ['Kinematics', 'body_velocities', 'generalised_force', 'integrate_position', 'forward_kinematics', 'site_positions']


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


def integrate_position(tree: RigidBodyTree, qpos: torch.Tensor, qvel: torch.Tensor, dt: float) -> torch.Tensor:
    """MuJoCo's ``mj_integratePos``: ``qpos [N, nq]`` moved by ``qvel [N, nv]`` for ``dt``.

    Hinge, slide and a free joint's translation add ``dt * qvel``; ball joints and a free joint's
    rotation turn their quaternion (`integrate_quaternion`).
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


def _apply(rot: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``rot [N, g, 3, 3] @ v [g, 3]`` (or ``[N, g, 3]``) -> ``[N, g, 3]``."""
    return small_matvec(rot, v)


def _coordinates(q: torch.Tensor, first: torch.Tensor, count: int) -> torch.Tensor:
    """``[N, g, count]``: ``count`` coordinates of ``q [N, nq]`` from each of ``first [g]``."""
    return q[:, first.unsqueeze(-1) + torch.arange(count, device=q.device)]


def forward_kinematics(tree: RigidBodyTree, qpos: torch.Tensor) -> Kinematics:
    """Body poses and dof motion subspaces (MuJoCo's mj_kinematics and cdof).

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.

    Returns:
        The [`Kinematics`][torchrl_diffenvs.articulated.Kinematics] of the batch.

    A free joint sets its body's world pose from ``qpos`` (position, quaternion); its dofs move the
    body along the world axes and turn it about its own axes. A ball joint turns its body about its
    anchor by the quaternion; its dofs turn it about the body's axes. The bodies are posed a group
    at a time (`RigidBodyTree.body_groups`: the same depth and joint kinds), parents first.
    """
    n = qpos.shape[0]
    eye = torch.eye(3, dtype=qpos.dtype, device=qpos.device)
    rots = eye.expand(n, tree.nbody, 3, 3)
    poss = qpos.new_zeros(n, tree.nbody, 3)
    linear_dofs, linear_axes = [], []  # slide dofs and a free joint's translation: (dofs [k], world axes [N, k, 3])
    turning = []  # (dofs [k], world axes [N, k, 3], world anchors [N, k, 3]) of the rotational dofs
    q = qpos - tree.qpos0
    sin, cos = torch.sin(q), torch.cos(q)
    for group in tree.body_groups:
        # index_select, not rots[:, parents]: advanced indexing is several times slower on the CPU
        parent_rot, parent_pos = rots.index_select(1, group.parents), poss.index_select(1, group.parents)
        rot = small_matmul(parent_rot, group.body_rot)
        pos = parent_pos + _apply(parent_rot, group.body_pos)
        for k, (kind, qa, da) in enumerate(zip(group.kinds, group.qposadr, group.dofadr)):
            if kind == "hinge":
                axis = _apply(rot, group.joint_axis[k])
                anchor = pos + _apply(rot, group.joint_pos[k])
                local = (eye + sin.index_select(1, qa)[..., None, None] * group.joint_skew[k]
                         + (1 - cos.index_select(1, qa))[..., None, None] * group.joint_skew_squared[k])  # Rodrigues
                rot = small_matmul(rot, local)
                pos = anchor - _apply(rot, group.joint_pos[k])
                turning.append((da, axis, anchor))
            elif kind == "slide":
                axis = _apply(rot, group.joint_axis[k])
                pos = pos + axis * q.index_select(1, qa).unsqueeze(-1)
                linear_dofs.append(da)
                linear_axes.append(axis)
            else:
                if kind == "free":  # the body's world pose is the joint's coordinates
                    pos, rot = _coordinates(qpos, qa, 3), quaternion_to_matrix(_coordinates(qpos, qa + 3, 4))
                    anchor, turn = pos, da + 3
                    for i in range(3):
                        linear_dofs.append(da + i)
                        linear_axes.append(eye[:, i].expand_as(pos))
                else:
                    anchor, turn = pos + _apply(rot, group.joint_pos[k]), da
                    rot = small_matmul(rot, quaternion_to_matrix(_coordinates(qpos, qa, 4)))
                    pos = anchor - _apply(rot, group.joint_pos[k])
                for i in range(3):
                    turning.append((turn + i, rot[..., :, i], anchor))
        rots = rots.index_copy(1, group.bodies, rot)
        poss = poss.index_copy(1, group.bodies, pos)
    # The spatial quantities are taken about the first body's position, not the world origin: a
    # runner 100 m down the track would otherwise carry lever arms of 100 m into every inertia
    # (m |c|^2 ~ 1e5) and contact moment, and float32 cancellation would leave the mass matrix
    # indefinite. Detached: the dynamics do not depend on the choice of reference point.
    origin = (poss[:, 1] if tree.nbody > 1 else poss[:, 0]).detach()
    dofs, rows = [], []
    if turning:
        axis = torch.cat([a for _, a, _ in turning], dim=1)
        anchor = torch.cat([p for _, _, p in turning], dim=1)
        dofs += [d for d, _, _ in turning]
        rows.append(torch.cat([axis, _cross(anchor - origin.unsqueeze(1), axis)], dim=-1))
    if linear_axes:
        axis = torch.cat(linear_axes, dim=1)
        dofs += linear_dofs
        rows.append(torch.cat([torch.zeros_like(axis), axis], dim=-1))
    motion = qpos.new_zeros(n, tree.nv, 6)
    if dofs:
        motion = motion.index_copy(1, torch.cat(dofs), torch.cat(rows, dim=1))
    return Kinematics(rots, poss, motion, origin)


def site_positions(tree: RigidBodyTree, kin: Kinematics, sites=None) -> torch.Tensor:
    """World positions ``[N, nsite, 3]`` of the model's sites, or ``[N, len(sites), 3]`` of those
    with these indices (on a GPU a list of indices is copied to the device, a synchronisation: in
    a step, index the positions of all sites instead)."""
    body, local = tree.site_body, tree.site_pos.to(kin.body_pos.dtype)
    if sites is not None:
        body, local = body[list(sites)], local[list(sites)]
    return kin.body_pos.index_select(1, body) + small_matvec(kin.body_rot.index_select(1, body), local)
