"""Smooth penalty contact between geoms and ground planes, and the velocity damping of its
forces that the implicit Euler integrator uses."""
from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from .inertia import _composite_mass_matrix
from .kinematics import Kinematics, _tree_sum, body_velocities, generalised_force
from .spatial import Params, _cross, _skew
from .tree import RigidBodyTree

__all__ = ['contact_force', 'body_contact_forces']


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


def contact_force(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params, with_damping=False,
                  contacts: _ContactForces | None = None):
    """``[N, nv]`` generalised force of the smooth ground contacts.

    Each contact point (a capsule end, a sphere, a box corner) with signed distance ``d`` to a
    ground plane gets a normal force ``k * s(-d) + c * sigmoid(-d / w) * (-v_n)`` (clamped at 0),
    where ``s`` is a softplus of width ``w = contact_width`` (the smooth penetration depth), and a
    friction force ``-mu f_n v_t / sqrt(|v_t|^2 + v_eps^2)``: Coulomb's law with the stick-slip
    corner rounded off over ``v_eps = friction_velocity``. Every term is smooth in the state, and
    the forces grow linearly with the depth, so gradients stay finite at deep penetration.

    ``with_damping=True`` also returns ``C [N, nv, nv]``, the (positive semi-definite) velocity
    damping of these forces, ``-d(force)/d(qvel)`` with the friction direction held fixed: the
    Euler integrator treats it implicitly, as MuJoCo treats joint damping. ``contacts``: the
    points' forces (:func:`_contact_points_and_forces`) when the caller has them.
    """
    if tree.contact_body.numel() == 0:
        zero = qvel.new_zeros(qvel.shape)
        return (zero, qvel.new_zeros(*qvel.shape, qvel.shape[-1])) if with_damping else zero
    c = _contact_points_and_forces(tree, kin, qvel, params) if contacts is None else contacts
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
