"""Smooth penalty contact between geoms and ground planes and between the geoms of two bodies,
and the velocity damping of its forces that the implicit Euler integrator uses."""
from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from .inertia import _composite_mass_matrix
from .kinematics import Kinematics, _tree_sum, body_velocities, generalised_force
from .spatial import Params, _cross, _skew
from .tree import RigidBodyTree

__all__ = ['contact_force', 'body_contact_forces', 'pair_contact_force', 'pair_geometry', 'pair_jacobian',
           'has_contacts']


class _ContactForces(NamedTuple):
    point: torch.Tensor  # [N, P, 3] where each force acts (the point of the sphere nearest the plane)
    force: torch.Tensor  # [N, P, 3] on the body, world frame
    normal: torch.Tensor  # [P, 3]
    normal_force: torch.Tensor  # [N, P]
    touching: torch.Tensor  # [N, P]
    damping: torch.Tensor  # [N, 1]
    mu: torch.Tensor  # [N, P]
    slip: torch.Tensor  # [N, P]


class _PairForces(NamedTuple):
    point: torch.Tensor  # [N, K, 3] midway between the two surfaces, relative to kin.origin
    force: torch.Tensor  # [N, K, 3] on body B (A gets its opposite), world frame
    normal: torch.Tensor  # [N, K, 3] from A to B
    normal_force: torch.Tensor  # [N, K]
    normal_rate: torch.Tensor  # [N, K] the normal velocity damping while pushing
    tangent_rate: torch.Tensor  # [N, K] the friction's velocity damping
    jacobian: torch.Tensor | None  # [N, K, nv, 3] d(B's point velocity - A's) / d(qvel), None: frictionless pairs


def _penalty_force(dist, vel, normal, mu, params: Params):
    """The smooth contact force (see `contact_force`) at points ``[N, K]`` with signed
    distance ``dist``, relative velocity ``vel [N, K, 3]``, unit ``normal`` (pushing along it) and
    friction ``mu``: ``(force, normal_force, touching, damping [N, 1], slip)``."""
    normal_vel = (vel * normal).sum(-1)
    tangent_vel = vel - normal_vel.unsqueeze(-1) * normal
    width = params["contact_width"].unsqueeze(-1)
    depth = F.softplus(-dist / width) * width
    touching = torch.sigmoid(-dist / width)
    stiffness, damping = params["contact_stiffness"].unsqueeze(-1), params["contact_damping"].unsqueeze(-1)
    normal_force = torch.clamp(stiffness * depth - damping * touching * normal_vel, min=0.0)
    eps = params["friction_velocity"].unsqueeze(-1)
    slip = torch.sqrt((tangent_vel * tangent_vel).sum(-1) + eps * eps)
    force = normal_force.unsqueeze(-1) * (normal - (mu / slip).unsqueeze(-1) * tangent_vel)
    return force, normal_force, touching, damping, slip


def has_contacts(tree: RigidBodyTree) -> bool:
    """Whether the model has any contact (geom-plane points or geom pairs)."""
    return bool(tree.contact_body.numel() or tree.pair_body.numel())


def _closest_points(p1, q1, p2, q2):
    """The closest points ``(c1, c2)`` of segments ``p1 q1`` and ``p2 q2`` (``[..., 3]``; a segment
    may be a point), Ericson's clamped solution (Real-Time Collision Detection, 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = (d1 * d1).sum(-1), (d2 * d2).sum(-1), (d2 * r).sum(-1)
    b, c = (d1 * d2).sum(-1), (d1 * r).sum(-1)
    eps = 1e-12
    point1, point2 = a <= eps, e <= eps
    safe_a, safe_e = torch.where(point1, torch.ones_like(a), a), torch.where(point2, torch.ones_like(e), e)
    denom = a * e - b * b
    parallel = denom <= eps * a * e + 1e-30
    s = torch.where(parallel, torch.zeros_like(a), torch.clamp((b * f - c * e) / torch.where(parallel, torch.ones_like(denom), denom), 0, 1))
    t = (b * s + f) / safe_e
    s = torch.where(t < 0, torch.clamp(-c / safe_a, 0, 1), torch.where(t > 1, torch.clamp((b - c) / safe_a, 0, 1), s))
    t = torch.clamp(t, 0, 1)
    # a point against a segment, or two points
    s = torch.where(point2, torch.clamp(-c / safe_a, 0, 1), s)
    t = torch.where(point2, torch.zeros_like(t), t)
    t = torch.where(point1, torch.clamp(f / safe_e, 0, 1), t)
    s = torch.where(point1, torch.zeros_like(s), s)
    return p1 + s.unsqueeze(-1) * d1, p2 + t.unsqueeze(-1) * d2


def pair_geometry(tree: RigidBodyTree, kin: Kinematics):
    """``(dist [N, K], normal [N, K, 3], point [N, K, 3])`` of every geom pair: the signed distance
    between the two surfaces (negative: penetrating), the unit normal from A to B, and the point
    midway between the surfaces (relative to ``kin.origin``), MuJoCo's contact frame."""
    rot = kin.body_rot[:, tree.pair_body]  # [N, K, 2, 3, 3]
    pos = kin.body_pos[:, tree.pair_body] - kin.origin[:, None, None]  # [N, K, 2, 3] about kin.origin
    ends = pos.unsqueeze(-2) + (rot.unsqueeze(-3) @ tree.pair_segment.unsqueeze(-1)).squeeze(-1)  # [N, K, 2, 2, 3]
    ca, cb = _closest_points(ends[..., 0, 0, :], ends[..., 0, 1, :], ends[..., 1, 0, :], ends[..., 1, 1, :])
    gap = cb - ca
    length = torch.sqrt((gap * gap).sum(-1) + 1e-12)  # smooth where the two core segments cross
    normal = gap / length.unsqueeze(-1)
    radius_a, radius_b = tree.pair_radius[:, 0], tree.pair_radius[:, 1]
    dist = length - radius_a - radius_b
    return dist, normal, ca + (radius_a + 0.5 * dist).unsqueeze(-1) * normal


def pair_jacobian(tree: RigidBodyTree, kin: Kinematics, point: torch.Tensor) -> torch.Tensor:
    """``[N, K, nv, 3]`` d(B's material point velocity - A's at ``point``)/d(qvel): each dof's
    velocity of the point (``point`` relative to ``kin.origin``), +1 for B's dofs, -1 for A's."""
    motion = kin.motion.unsqueeze(1)  # [N, 1, nv, 6]
    return (_cross(motion[..., :3], point.unsqueeze(2)) + motion[..., 3:]) * tree.pair_dof_sign[..., None]


def _pair_forces(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params) -> _PairForces:
    """The smooth contact model (see `contact_force`) between the geoms of two bodies: the
    same normal force and regularised friction on the signed distance of two sphere-swept segments.

    Models whose body-body contacts are all frictionless (``condim=1``, as the humanoid's and the
    Pusher's) skip the ``[N, K, nv, 3]`` point Jacobian: the relative velocity comes from the
    bodies' velocities and the damping from ``J^T n`` alone.
    """
    dist, normal, point = pair_geometry(tree, kin)
    jacobian = None
    if tree.has_frictional_pairs:
        jacobian = pair_jacobian(tree, kin, point)
        vel = (jacobian * qvel[:, None, :, None]).sum(2)  # B's point velocity relative to A's
    else:
        body_vel = body_velocities(tree, kin, qvel)[:, tree.pair_body]  # [N, K, 2, 6]
        at_point = body_vel[..., 3:] + _cross(body_vel[..., :3], point.unsqueeze(2))
        vel = at_point[:, :, 1] - at_point[:, :, 0]
    # MuJoCo's condim=1 contacts are frictionless whatever their friction coefficient
    mu = params["contact_friction"][:, tree.pair_slot] * tree.pair_frictional
    force, normal_force, touching, damping, slip = _penalty_force(dist, vel, normal, mu, params)
    pushing = (normal_force > 0).to(qvel.dtype)
    return _PairForces(point, force, normal, normal_force, damping * touching * pushing, mu * normal_force / slip,
                       jacobian)


def pair_contact_force(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params, with_damping=False,
                       contacts: _PairForces | None = None):
    """``[N, nv]`` generalised force of the contacts between bodies' geoms: ``J^T f`` with ``J`` the
    Jacobian of B's point velocity relative to A's. ``with_damping=True`` also returns its velocity
    damping ``J^T (a n n^T + b (I - n n^T)) J`` ``[N, nv, nv]`` (see `contact_force`)."""
    c = _pair_forces(tree, kin, qvel, params) if contacts is None else contacts
    wrench = torch.cat([_cross(c.point, c.force), c.force], dim=-1)  # on B, about kin.origin; A: -wrench
    generalised = generalised_force(tree.pair_dof_sign, kin, wrench)
    if not with_damping:
        return generalised
    unit = torch.cat([_cross(c.point, c.normal), c.normal], dim=-1)
    u = (unit @ kin.motion.transpose(1, 2)) * tree.pair_dof_sign  # [N, K, nv]: J^T n
    # one batched product each (an einsum over three operands materialises [N, nv, nv, K] first)
    damping_matrix = (u * (c.normal_rate - c.tangent_rate).unsqueeze(-1)).transpose(1, 2) @ u
    if c.jacobian is not None:
        jac = c.jacobian.transpose(1, 2).flatten(2)  # [N, nv, K * 3]
        weighted = (c.jacobian * c.tangent_rate[..., None, None]).transpose(1, 2).flatten(2)
        damping_matrix = damping_matrix + weighted @ jac.transpose(1, 2)
    return generalised, damping_matrix


def _contact_points_and_forces(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params) -> _ContactForces:
    """The smooth contact model (see `contact_force`) at every contact point."""
    rot = kin.body_rot[:, tree.contact_body]  # [N, P, 3, 3]
    centre = kin.body_pos[:, tree.contact_body] + (rot @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    normal = tree.contact_plane_normal
    dist = ((centre - tree.contact_plane_point) * normal).sum(-1) - tree.contact_radius  # [N, P]
    point = centre - tree.contact_radius.unsqueeze(-1) * normal
    body_vel = body_velocities(tree, kin, qvel)[:, tree.contact_body]
    lever = point - kin.origin.unsqueeze(1)
    vel = body_vel[..., 3:] + _cross(body_vel[..., :3], lever)  # velocity of the body point at the contact
    mu = params["contact_friction"][:, tree.contact_slot] * tree.contact_frictional  # condim 1: frictionless
    force, normal_force, touching, damping, slip = _penalty_force(dist, vel, normal, mu, params)
    return _ContactForces(point, force, normal, normal_force, touching, damping, mu, slip)


def body_contact_forces(tree: RigidBodyTree, kin: Kinematics, qvel, params: Params, about: torch.Tensor) -> torch.Tensor:
    """``[N, nbody, 6]``: the contact wrench on every body (torque, force; world frame) from the
    ground and from other bodies,
    the torque taken about the point ``about [N, 3]`` (MuJoCo's ``cfrc_ext`` takes it about the
    subtree centre of mass of the body's root)."""
    out = qvel.new_zeros(qvel.shape[0], tree.nbody, 6)
    if tree.contact_body.numel():
        c = _contact_points_and_forces(tree, kin, qvel, params)
        wrench = torch.cat([_cross(c.point - about.unsqueeze(1), c.force), c.force], dim=-1)
        out = out.index_add(1, tree.contact_body, wrench)
    if tree.pair_body.numel():
        c = _pair_forces(tree, kin, qvel, params)
        lever = c.point + (kin.origin - about).unsqueeze(1)
        wrench = torch.cat([_cross(lever, c.force), c.force], dim=-1)  # on B; A gets -wrench
        out = out.index_add(1, tree.pair_body[:, 1], wrench).index_add(1, tree.pair_body[:, 0], -wrench)
    return out


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
    points' forces (`_contact_points_and_forces`) when the caller has them.
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
