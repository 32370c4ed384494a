"""Collision primitives: the contacts of one geom-type pair, as ``engine_collision_primitive.c``.

Each primitive takes the two geoms posed in the world ([`PosedGeoms`][torchrl_diffenvs.articulated.primitive_types.PosedGeoms],
``P`` pairs of one type in a batch of ``N`` configurations) and the pairs' margins, and returns a
fixed number ``K`` of contacts per pair ([`PairContacts`][torchrl_diffenvs.articulated.primitive_types.PairContacts]):
plane-sphere and sphere-sphere one, plane-capsule two (one per end), plane-cylinder up to four
(``mjc_PlaneCylinder``: the lowest rim point, the opposite end's and two more on the lowest disk),
plane-box up to four (``mjc_PlaneBox``: the lower corners within the margin),
sphere-capsule, sphere-cylinder and sphere-box one, capsule-capsule one (two where the axes are parallel), capsule-cylinder one (two where the capsule lies along a cap)
([`capsule_cylinder`][torchrl_diffenvs.articulated.capsule_cylinder]), capsule-box up to two
(``mjc_CapsuleBox``, [`capsule_box`][torchrl_diffenvs.articulated.capsule_box]), box-box up to eight (``mjc_BoxBox``: the
clipped face or the edges' closest points, [`box_box`][torchrl_diffenvs.articulated.box_box]). The same ops run whatever touches.

To collide a new pair of geom types: write its function with this signature and add it to
[`PRIMITIVES`][torchrl_diffenvs.articulated.primitives.PRIMITIVES] under the two types in MuJoCo's
order (plane < sphere < capsule < ellipsoid < cylinder < box); the collision stage, the pair
filter and the constraint rows pick it up from there.
"""
from __future__ import annotations

import torch

from .box_box import box_box
from .capsule_box import capsule_box
from .capsule_cylinder import capsule_cylinder as _capsule_cylinder
from .primitive_types import PairContacts, PosedGeoms, Primitive, box_corners, one_contact
from .spatial import _MINVAL, _cross, _dot
from .sphere_box import sphere_box

__all__ = ["PRIMITIVES"]


def _where(mask, a, b):
    """``torch.where`` of a per-contact ``mask [N, P]`` over values with or without a last axis of 3."""
    return torch.where(mask.reshape(*mask.shape, *[1] * (a.dim() - mask.dim())), a, b)


def _plane_sphere(plane_pos, plane_rot, centre, radius):
    """``(dist, pos, normal)`` of a sphere against a plane (the plane's z axis is the normal)."""
    normal = plane_rot[..., :, 2]
    dist = _dot(centre - plane_pos, normal) - radius
    pos = centre - (dist / 2 + radius).unsqueeze(-1) * normal
    return dist, pos, normal


def _sphere_sphere(centre1, radius1, centre2, radius2, axis1, axis2):
    """``(dist, pos, normal)`` of two spheres; coincident centres take the normal from the geoms'
    z axes as MuJoCo does (their cross product, or x where those are parallel)."""
    gap = centre2 - centre1
    squared_length = _dot(gap, gap)
    # coincident centres (a sphere centred on a capsule's or cylinder's axis) give sqrt(0), whose
    # derivative is infinite: that root is detached (its value kept), the others differentiated
    same_centre = squared_length < _MINVAL * _MINVAL
    length = torch.where(same_centre, torch.sqrt(squared_length).detach(),
                         torch.sqrt(torch.where(same_centre, 1.0, squared_length)))
    fallback = _cross(axis1, axis2)
    squared = _dot(fallback, fallback)
    # clamped inside the root: parallel axes give sqrt(0), whose infinite derivative times the zero
    # gradient of the branch not taken would be NaN (the values are those of sqrt(.).clamp_min)
    fallback_length = torch.sqrt(squared.clamp_min(_MINVAL * _MINVAL))
    x_axis = torch.zeros_like(gap)
    x_axis[..., 0] = 1.0
    fallback = torch.where((squared < _MINVAL * _MINVAL).unsqueeze(-1), x_axis, fallback / fallback_length.unsqueeze(-1))
    coincident = (length < _MINVAL).unsqueeze(-1)
    normal = torch.where(coincident, fallback, gap / torch.where(coincident.squeeze(-1), 1.0, length).unsqueeze(-1))
    dist = length - radius1 - radius2
    return dist, centre1 + (radius1 + dist / 2).unsqueeze(-1) * normal, normal


def _capsule_capsule(pos1, axis1, radius1, pos2, axis2, radius2, margin):
    """MuJoCo's ``mjraw_CapsuleCapsule``: ``(dist, pos, normal, found)``, each ``[N, P, 2, ...]``:
    the closest points of the two axes, or (parallel axes) up to two of the four end-point tests."""
    a1, a2 = axis1, axis2  # half-axes, scaled
    dif = pos1 - pos2
    ma, mb, mc = _dot(a1, a1), -_dot(a1, a2), _dot(a2, a2)
    u, v = -_dot(a1, dif), _dot(a2, dif)
    det = ma * mc - mb * mb
    parallel = det.abs() < _MINVAL
    safe_det = torch.where(parallel, 1.0, det)
    x1, x2 = (mc * u - mb * v) / safe_det, (ma * v - mb * u) / safe_det
    x2 = torch.where(x1 > 1, (v - mb) / mc, torch.where(x1 < -1, (v + mb) / mc, x2))
    x1 = x1.clamp(-1, 1)
    x1 = torch.where(x2 > 1, ((u - mb) / ma).clamp(-1, 1), torch.where(x2 < -1, ((u + mb) / ma).clamp(-1, 1), x1))
    x2 = x2.clamp(-1, 1)
    general = (pos1 + x1.unsqueeze(-1) * a1, pos2 + x2.unsqueeze(-1) * a2)
    # parallel axes: the end points of each against the other's axis, in MuJoCo's order
    ones = torch.ones_like(x1)
    candidates = [(ones, ((v - mb) / mc).clamp(-1, 1)), (-ones, ((v + mb) / mc).clamp(-1, 1)),
                  (((u - mb) / ma).clamp(-1, 1), ones), (((u + mb) / ma).clamp(-1, 1), -ones)]
    ends1 = torch.stack([pos1 + c[0].unsqueeze(-1) * a1 for c in candidates], dim=-2)  # [N, P, 4, 3]
    ends2 = torch.stack([pos2 + c[1].unsqueeze(-1) * a2 for c in candidates], dim=-2)
    gap = ends2 - ends1
    reach = (margin + radius1 + radius2).unsqueeze(-1)
    within = _dot(gap, gap) <= reach * reach  # [N, P, 4]: the candidates MuJoCo keeps, in order
    rank = within.long().cumsum(-1)
    picks = []
    for k in (1, 2):
        chosen = (within & (rank == k)).long().argmax(-1, keepdim=True)  # first candidate of rank k
        found = (within & (rank == k)).any(-1)
        picks.append((ends1.gather(-2, chosen.unsqueeze(-1).expand(*chosen.shape, 3)).squeeze(-2),
                      ends2.gather(-2, chosen.unsqueeze(-1).expand(*chosen.shape, 3)).squeeze(-2), found))
    p = parallel.unsqueeze(-1)
    first1 = torch.where(p, picks[0][0], general[0])
    first2 = torch.where(p, picks[0][1], general[1])
    centres1 = torch.stack([first1, picks[1][0]], dim=-2)
    centres2 = torch.stack([first2, picks[1][1]], dim=-2)
    found = torch.stack([torch.ones_like(parallel), parallel & picks[1][2]], dim=-1)
    return centres1, centres2, found


def _plane_cylinder(plane_pos, plane_rot, pos, rot, size):
    """MuJoCo's ``mjc_PlaneCylinder``: ``(dist [N, P, 4], pos [N, P, 4, 3], normal [N, P, 3])`` of
    its four candidate contacts in its order: the rim point nearest the plane, the same point of the
    other disk, and two points of the nearer disk at 120 degrees from the first (MuJoCo's triangle)."""
    normal = plane_rot[..., :, 2]
    axis = rot[..., :, 2]
    prjaxis = _dot(normal, axis)
    towards = (prjaxis > 0).unsqueeze(-1)  # make the axis point towards the plane
    axis, prjaxis = torch.where(towards, -axis, axis), -prjaxis.abs()
    dist0 = _dot(pos - plane_pos, normal)
    vec = prjaxis.unsqueeze(-1) * axis - normal  # towards the plane, across the axis
    squared = _dot(vec, vec)
    radius, half = size[:, 0], size[:, 1]
    # a disk parallel to the plane: MuJoCo takes the cylinder's x axis (see _sphere_sphere for the clamp)
    scaled = vec * (radius / torch.sqrt(squared.clamp_min(_MINVAL * _MINVAL))).unsqueeze(-1)
    vec = torch.where((squared >= _MINVAL * _MINVAL).unsqueeze(-1), scaled, rot[..., :, 0] * radius.unsqueeze(-1))
    prjvec = _dot(vec, normal)
    axis, prjaxis = axis * half.unsqueeze(-1), prjaxis * half
    side = _cross(vec, axis)
    side = side * (radius * 3 ** 0.5 / 2 / torch.sqrt(_dot(side, side).clamp_min(_MINVAL * _MINVAL))).unsqueeze(-1)
    near_disk = pos + axis
    points = torch.stack([near_disk + vec, pos - axis + vec, near_disk + side - vec / 2, near_disk - side - vec / 2], dim=-2)
    triangle = dist0 + prjaxis - prjvec / 2
    dist = torch.stack([dist0 + prjaxis + prjvec, dist0 - prjaxis + prjvec, triangle, triangle], dim=-1)
    return dist, points - (dist / 2).unsqueeze(-1) * normal.unsqueeze(-2), normal


def plane_sphere(plane: PosedGeoms, sphere: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    return one_contact(*_plane_sphere(plane.pos, plane.rot, sphere.pos, sphere.size[:, 0]))


def plane_capsule(plane: PosedGeoms, capsule: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """Each end's sphere against the plane (MuJoCo: the +axis end first), the axis as tangent."""
    axis = capsule.rot[..., :, 2]
    half = capsule.size[:, 1, None] * axis
    ends = torch.stack([capsule.pos + half, capsule.pos - half], dim=-2)
    dist, pos, normal = _plane_sphere(plane.pos.unsqueeze(-2), plane.rot.unsqueeze(-3), ends, capsule.size[:, 0, None])
    return PairContacts(dist, pos, normal.expand_as(pos), axis.unsqueeze(-2).expand_as(pos),
                        torch.ones_like(dist, dtype=torch.bool))


def plane_cylinder(plane: PosedGeoms, cylinder: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    dist, pos, normal = _plane_cylinder(plane.pos, plane.rot, cylinder.pos, cylinder.rot, cylinder.size)
    return PairContacts(dist, pos, normal.unsqueeze(-2).expand_as(pos), torch.zeros_like(pos),
                        torch.ones_like(dist, dtype=torch.bool))


#: the box's corners in MuJoCo's order (corner i has +size_k where bit k of i is set)
def plane_box(plane: PosedGeoms, box: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """MuJoCo's ``mjc_PlaneBox``: the corners below the box's centre (towards the plane) within the
    margin, the first four in MuJoCo's corner order, one contact each. Slot ``k`` holds the
    ``k``-th such corner (``found``: there is one)."""
    normal = plane.rot[..., :, 2]
    centre = _dot(box.pos - plane.pos, normal)  # [N, P]
    local = box_corners(box.size) * box.size.unsqueeze(-2)  # [P, 8, 3]
    corners = (box.rot.unsqueeze(-3) @ local.unsqueeze(-1)).squeeze(-1)  # [N, P, 8, 3], from the centre
    below = _dot(normal.unsqueeze(-2), corners)  # [N, P, 8]
    dist = centre.unsqueeze(-1) + below
    within = (dist <= margin.unsqueeze(-1)) & (below <= 0)
    rank = within.long().cumsum(-1)
    picks = [(within & (rank == k)) for k in range(1, 5)]
    chosen = torch.stack([p.long().argmax(-1) for p in picks], dim=-1)  # [N, P, 4]: the k-th corner kept
    found = torch.stack([p.any(-1) for p in picks], dim=-1)
    dist = dist.gather(-1, chosen)
    corner = corners.gather(-2, chosen.unsqueeze(-1).expand(*chosen.shape, 3))
    pos = box.pos.unsqueeze(-2) + corner - (dist / 2).unsqueeze(-1) * normal.unsqueeze(-2)
    normal = normal.unsqueeze(-2).expand_as(pos)
    return PairContacts(dist, pos, normal, torch.zeros_like(pos), found)


def sphere_sphere(sphere1: PosedGeoms, sphere2: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    return one_contact(*_sphere_sphere(sphere1.pos, sphere1.size[:, 0], sphere2.pos, sphere2.size[:, 0],
                                sphere1.rot[..., :, 2], sphere2.rot[..., :, 2]))


def sphere_capsule(sphere: PosedGeoms, capsule: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """The sphere against the sphere at the capsule axis' nearest point."""
    axis = capsule.rot[..., :, 2]
    along = _dot(axis, sphere.pos - capsule.pos).clamp(-capsule.size[:, 1], capsule.size[:, 1])
    nearest = capsule.pos + along.unsqueeze(-1) * axis
    return one_contact(*_sphere_sphere(sphere.pos, sphere.size[:, 0], nearest, capsule.size[:, 0], sphere.rot[..., :, 2], axis))


def sphere_cylinder(sphere: PosedGeoms, cylinder: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """MuJoCo's ``mjc_SphereCylinder``: the sphere against the side (a sphere at the centre's
    projection on the axis), a cap (the cap's plane) or, beyond both, the nearest rim point. A
    centre inside the cylinder leaves by the nearer of the side and the cap."""
    radius, half = cylinder.size[:, 0], cylinder.size[:, 1]
    axis = cylinder.rot[..., :, 2]
    offset = sphere.pos - cylinder.pos
    along = _dot(axis, offset)
    on_axis = axis * along.unsqueeze(-1)
    across = offset - on_axis
    squared = _dot(across, across)
    # clamped inside the root (a centre on the axis takes the side or cap branch): see _sphere_sphere
    spread = torch.sqrt(squared.clamp_min(_MINVAL * _MINVAL))
    beside, over = along.abs() < half, squared < radius * radius
    cap_nearer = half - along.abs() < radius - spread  # inside: leave through the nearer surface
    beside, over = beside & ~(over & cap_nearer), over & ~(beside & ~cap_nearer)
    z1, z2 = sphere.rot[..., :, 2], axis
    side = _sphere_sphere(sphere.pos, sphere.size[:, 0], cylinder.pos + on_axis, radius, z1, z2)
    up = torch.where(along > 0, 1.0, -1.0).to(along.dtype).unsqueeze(-1)
    cap_normal = axis * up  # the cap's outward normal; the contact's points into the cylinder
    cap_dist = _dot(sphere.pos - (cylinder.pos + cap_normal * half.unsqueeze(-1)), cap_normal) - sphere.size[:, 0]
    cap = (cap_dist, sphere.pos - cap_normal * (sphere.size[:, 0] + cap_dist / 2).unsqueeze(-1), -cap_normal)
    rim = cylinder.pos + cap_normal * half.unsqueeze(-1) + across * (radius / spread).unsqueeze(-1)
    corner = _sphere_sphere(sphere.pos, sphere.size[:, 0], rim, torch.zeros_like(radius), z1, z2)
    return one_contact(*(_where(beside, a, _where(over, b, c)) for a, b, c in zip(side, cap, corner)))


def capsule_capsule(capsule1: PosedGeoms, capsule2: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """The spheres at the axes' closest points (parallel axes: up to two of them)."""
    centres1, centres2, found = _capsule_capsule(
        capsule1.pos, capsule1.size[:, 1, None] * capsule1.rot[..., :, 2], capsule1.size[:, 0],
        capsule2.pos, capsule2.size[:, 1, None] * capsule2.rot[..., :, 2], capsule2.size[:, 0], margin)
    r1, r2 = capsule1.size[:, 0, None].expand(-1, 2), capsule2.size[:, 0, None].expand(-1, 2)
    z1 = capsule1.rot[..., :, 2].unsqueeze(-2).expand_as(centres1)
    z2 = capsule2.rot[..., :, 2].unsqueeze(-2).expand_as(centres2)
    dist, pos, normal = _sphere_sphere(centres1, r1, centres2, r2, z1, z2)
    return PairContacts(dist, pos, normal, torch.zeros_like(pos), found)


def capsule_cylinder(capsule: PosedGeoms, cylinder: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """MuJoCo's convex collision: one contact, two where the capsule lies along a cap."""
    dist, pos, normal, found = _capsule_cylinder(capsule.pos, capsule.size[:, 1, None] * capsule.rot[..., :, 2],
                                                 capsule.size[:, 0], cylinder.pos, cylinder.rot, cylinder.size, margin)
    return PairContacts(dist, pos, normal, torch.zeros_like(pos), found)


PRIMITIVES: dict[tuple[str, str], Primitive] = {
    ("plane", "sphere"): Primitive(1, plane_sphere),
    ("plane", "capsule"): Primitive(2, plane_capsule),
    ("plane", "cylinder"): Primitive(4, plane_cylinder),
    ("plane", "box"): Primitive(4, plane_box),
    ("sphere", "sphere"): Primitive(1, sphere_sphere),
    ("sphere", "capsule"): Primitive(1, sphere_capsule),
    ("sphere", "cylinder"): Primitive(1, sphere_cylinder),
    ("sphere", "box"): Primitive(1, sphere_box),
    ("capsule", "capsule"): Primitive(2, capsule_capsule),
    ("capsule", "cylinder"): Primitive(2, capsule_cylinder),
    ("capsule", "box"): Primitive(2, capsule_box),
    ("box", "box"): Primitive(8, box_box),
}
"""The primitive of each pair of geom types (keys in MuJoCo's type order: plane < sphere < capsule <
ellipsoid < cylinder < box), in the order the contact slots are laid out."""
