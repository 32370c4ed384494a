"""MuJoCo's collision detection, batched: the contacts ``mj_collision`` finds between geoms.

Every geom pair that MuJoCo's filter lets touch ([`colliding_pairs`][torchrl_diffenvs.articulated.collision.colliding_pairs]) is tested by its
primitive, as ``engine_collision_primitive.c`` does: plane-sphere and sphere-sphere give one
contact, plane-capsule two (one per end), plane-cylinder up to four (``mjc_PlaneCylinder``: the
lowest rim point, the opposite end's and two more on the lowest disk), sphere-capsule one,
capsule-capsule one (two where the axes are parallel). The number of contacts is fixed per pair
(a slot per possible contact), and a slot holds a contact when MuJoCo's would: ``active`` is where
its distance is below the pair's margin. No data-dependent shape or Python branch: the same ops run
whatever touches.

Capsule-cylinder, which MuJoCo collides by its general convex collision (GJK and EPA on the two
shapes grown by half the margin each, ``mjc_Convex``), is the exact solution of the same problem
here, one contact: the signed distance between the capsule's axis and the cylinder less the
capsule's radius, along the direction that minimises it. Where the axis stays outside the
cylinder that is its nearest point (a 1-D convex minimisation: golden section, then a Newton
step that also carries the implicit gradient); where it enters, the minimal translation that
separates them, the minimiser of the support function of their difference among the directions
that can minimise it (`_segment_cylinder`). Against MuJoCo's convex collision run to 1e-11 it
agrees to 1e-11 in distance, 2e-5 in the normal and 5e-7 in position at random poses; MuJoCo's
default ``ccd_tolerance`` (1e-6) leaves its own answer up to ~4e-3 (normal) and ~1e-4 (position)
from the exact one in deep contacts. Where the witness points are not unique (a capsule lying
exactly along a face) any point of the overlap is a valid contact and EPA's choice is not
reproduced; nor are the extra contacts MuJoCo 4's multi-contact adds when a capsule lies along
the cylinder's cap (one contact here).

Each contact has MuJoCo's ``pos``, ``frame`` (normal first, pointing from geom 1 to geom 2),
``dist`` and the pair's mixed parameters (``condim``, friction, ``solref``, ``solimp``,
``includemargin``: `_mix`, as ``mj_contactParam``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from .model import ArticulatedModel
from .spatial import _MINVAL, _cross

__all__ = ["Contacts", "ContactSlots", "colliding_pairs", "contact_slots", "collide", "unsupported_pairs"]

#: the primitives this module implements (MuJoCo's geom type order: plane < sphere < capsule), and
#: the contacts each gives at most
_PRIMITIVES = {("plane", "sphere"): 1, ("plane", "capsule"): 2, ("plane", "cylinder"): 4, ("sphere", "sphere"): 1,
               ("sphere", "capsule"): 1, ("capsule", "capsule"): 2, ("capsule", "cylinder"): 1}
#: golden-section iterations of the capsule-cylinder search: the bracket of the axis parameter
#: shrinks to 2 * 0.618**40 ~ 1e-8 before the Newton step
_GOLDEN_ITERATIONS = 40
_GOLDEN = (5 ** 0.5 - 1) / 2
_TOUCHING = 1e-9  # metres: an axis this close to the cylinder is treated as entering it (see _segment_cylinder)
_EDGE_SAMPLES = 32  # directions across a segment sampled before the golden section (edge against rim)
_EDGE_CANDIDATES = 3  # the best local minima of those samples refined
_TYPE_ORDER = ("plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh")


def _weld(model: ArticulatedModel, body: int) -> int:
    """MuJoCo's ``body_weldid``: the body itself if it has joints, else its parent's (the world's is 0)."""
    while body != 0 and not np.any(model.joint_body == body):
        body = int(model.body_parent[body])
    return body


def colliding_pairs(model: ArticulatedModel) -> list[tuple[int, int]]:
    """The geom pairs ``(g1, g2)`` MuJoCo's collision filter lets touch, ordered as MuJoCo orders
    them (``g1``'s type first in MuJoCo's type order, so the normal points from ``g1`` to ``g2``):
    compatible ``contype``/``conaffinity`` bits, bodies that do not move together and are not both
    static, and (``filterparent``) not a body and its parent unless that parent is the world."""
    out = []
    ngeom = len(model.geom_names)
    for g1 in range(ngeom):
        for g2 in range(g1 + 1, ngeom):
            if not ((model.geom_contype[g1] & model.geom_conaffinity[g2])
                    or (model.geom_contype[g2] & model.geom_conaffinity[g1])):
                continue
            w1, w2 = _weld(model, int(model.geom_body[g1])), _weld(model, int(model.geom_body[g2]))
            if w1 == w2:
                continue
            p1 = _weld(model, int(model.body_parent[w1])) if w1 else -1
            p2 = _weld(model, int(model.body_parent[w2])) if w2 else -1
            if w1 and w2 and (w1 == p2 or w2 == p1):
                continue
            a, b = (g1, g2) if _TYPE_ORDER.index(model.geom_type[g1]) <= _TYPE_ORDER.index(model.geom_type[g2]) \
                else (g2, g1)
            out.append((a, b))
    return out


def _mix(model: ArticulatedModel, g1: int, g2: int) -> dict:
    """MuJoCo's ``mj_contactParam`` of one geom pair: the higher priority's parameters, or at equal
    priority the larger condim and friction and ``solref``/``solimp`` mixed by ``solmix``."""
    p1, p2 = model.geom_priority[g1], model.geom_priority[g2]
    if p1 != p2:
        g = g1 if p1 > p2 else g2
        condim, solref, solimp, fri = (int(model.geom_condim[g]), model.geom_solref[g], model.geom_solimp[g],
                                       model.geom_friction[g])
    else:
        condim = int(max(model.geom_condim[g1], model.geom_condim[g2]))
        s1, s2 = model.geom_solmix[g1], model.geom_solmix[g2]
        if s1 >= _MINVAL and s2 >= _MINVAL:
            mix = s1 / (s1 + s2)
        else:
            mix = 0.5 if (s1 < _MINVAL and s2 < _MINVAL) else (0.0 if s1 < _MINVAL else 1.0)
        r1, r2 = model.geom_solref[g1], model.geom_solref[g2]
        solref = mix * r1 + (1 - mix) * r2 if (r1[0] > 0 and r2[0] > 0) else np.minimum(r1, r2)
        solimp = mix * model.geom_solimp[g1] + (1 - mix) * model.geom_solimp[g2]
        fri = np.maximum(model.geom_friction[g1], model.geom_friction[g2])
    if condim not in (1, 3):
        raise ValueError(f"{model.path}: geoms {model.geom_names[g1]!r} and {model.geom_names[g2]!r}: condim "
                         f"{condim} is not supported by MuJoCo's contact model here; supported: 1 and 3")
    return dict(condim=condim, friction=float(fri[0]), solref=np.array(solref, dtype=np.float64), solimp=solimp,
                margin=float(model.geom_margin[g1] + model.geom_margin[g2]))


class _Geoms(NamedTuple):
    """Geoms as their bodies see them: ``body [P]`` long, ``pos [P, 3]``, ``rot [P, 3, 3]`` (body
    frame) and ``size [P, 3]``."""

    body: torch.Tensor
    pos: torch.Tensor
    rot: torch.Tensor
    size: torch.Tensor


class _PrimitiveGroup(NamedTuple):
    kind: tuple[str, str]
    first: int  # its first slot
    geom1: _Geoms
    geom2: _Geoms


def _geoms(model: ArticulatedModel, index: list[int], dtype, device) -> _Geoms:
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    return _Geoms(torch.as_tensor(model.geom_body[index], device=device), t(model.geom_pos[index]),
                  t(model.geom_rot[index]), t(model.geom_size[index]))


@dataclass
class ContactSlots:
    """The constant part of a model's contacts: one entry per contact slot ``[C]``, grouped by
    primitive (``groups``: `_PrimitiveGroup`, each pair giving ``_PRIMITIVES[primitive]``
    consecutive slots)."""

    groups: list[_PrimitiveGroup]
    geom: torch.Tensor  # [C, 2] long
    body: torch.Tensor  # [C, 2] long
    condim: list[int]  # [C]
    friction_slot: torch.Tensor  # [C] long: the entry of params["contact_friction"] of its geom pair
    solref: torch.Tensor  # [C, 2]
    solimp: torch.Tensor  # [C, 5]
    margin: torch.Tensor  # [C] MuJoCo's includemargin (margin - gap; gap is 0 here)
    pyramid_index: torch.Tensor  # [C3] long: the frictional slots (condim 3: four pyramid edges each)
    normal_index: torch.Tensor  # [C1] long: the frictionless slots (condim 1: one row each)
    # [npair, 2] each geom pair's mixed solref (the entries of params["contact_friction"]): the
    # default of the params' contact_solref; MuJoCo's default (0.02, 1) for a pair with no slot
    pair_solref: torch.Tensor

    @property
    def count(self) -> int:
        return len(self.condim)


def unsupported_pairs(model: ArticulatedModel) -> list[tuple[str, str]]:
    """The colliding geom pairs (names) whose types have no primitive here (empty: MuJoCo's
    contact model covers the model)."""
    return [(model.geom_names[g1], model.geom_names[g2]) for g1, g2 in colliding_pairs(model)
            if (model.geom_type[g1], model.geom_type[g2]) not in _PRIMITIVES]


def contact_slots(model: ArticulatedModel, friction_slots: list[tuple[str, str]], dtype, device) -> ContactSlots:
    """The [`ContactSlots`][torchrl_diffenvs.articulated.collision.ContactSlots] of a model. ``friction_slots``: the geom-name pairs of the
    ``contact_friction`` param (``RigidBodyTree.contact_pairs``, either order)."""
    slot_of = {frozenset(pair): i for i, pair in enumerate(friction_slots)}
    by_primitive: dict[tuple[str, str], list[tuple[int, int]]] = {}
    for g1, g2 in colliding_pairs(model):
        kind = (model.geom_type[g1], model.geom_type[g2])
        if kind not in _PRIMITIVES:
            raise ValueError(f"{model.path}: geoms {model.geom_names[g1]!r} ({kind[0]}) and {model.geom_names[g2]!r} "
                             f"({kind[1]}) can touch, but MuJoCo's contact model here collides only "
                             f"{', '.join('-'.join(k) for k in _PRIMITIVES)} (use contact='smooth', or set "
                             "contype/conaffinity to exclude the pair)")
        by_primitive.setdefault(kind, []).append((g1, g2))
    groups, rows = [], []
    for kind in _PRIMITIVES:
        pairs = by_primitive.get(kind, [])
        if not pairs:
            continue
        groups.append(_PrimitiveGroup(kind, len(rows), _geoms(model, [p[0] for p in pairs], dtype, device),
                                      _geoms(model, [p[1] for p in pairs], dtype, device)))
        for g1, g2 in pairs:
            key = frozenset((model.geom_names[g1], model.geom_names[g2]))
            if key not in slot_of:
                raise ValueError(f"{model.path}: no contact_friction entry for geoms {sorted(key)}")
            rows += [(g1, g2, slot_of[key], _mix(model, g1, g2))] * _PRIMITIVES[kind]
    t = lambda a, shape: torch.as_tensor(np.asarray(a, dtype=np.float64).reshape(shape), dtype=dtype, device=device)  # noqa: E731
    idx = lambda a, shape: torch.as_tensor(np.asarray(a, dtype=np.int64).reshape(shape), device=device)  # noqa: E731
    return ContactSlots(
        groups=groups, geom=idx([[r[0], r[1]] for r in rows], (-1, 2)),
        body=idx([[model.geom_body[r[0]], model.geom_body[r[1]]] for r in rows], (-1, 2)),
        condim=[r[3]["condim"] for r in rows], friction_slot=idx([r[2] for r in rows], (-1,)),
        solref=t([r[3]["solref"] for r in rows], (-1, 2)), solimp=t([r[3]["solimp"] for r in rows], (-1, 5)),
        margin=t([r[3]["margin"] for r in rows], (-1,)),
        pyramid_index=idx([i for i, r in enumerate(rows) if r[3]["condim"] == 3], (-1,)),
        normal_index=idx([i for i, r in enumerate(rows) if r[3]["condim"] == 1], (-1,)),
        pair_solref=t(_pair_solref(rows, len(friction_slots)), (-1, 2)))


def _pair_solref(rows: list, npair: int) -> np.ndarray:
    """``[npair, 2]`` the mixed solref of each geom pair from its slots' rows (MuJoCo's default
    ``(0.02, 1)`` for a pair without one)."""
    out = np.tile(np.array([0.02, 1.0]), (npair, 1))
    for _, _, pair, mixed in rows:
        out[pair] = mixed["solref"]
    return out


class Contacts(NamedTuple):
    """The contacts at a batch of configurations, one per slot of [`ContactSlots`][torchrl_diffenvs.articulated.collision.ContactSlots]."""

    dist: torch.Tensor  # [N, C] signed distance (negative: penetrating)
    pos: torch.Tensor  # [N, C, 3] world position, midway between the surfaces
    frame: torch.Tensor  # [N, C, 3, 3] rows: the normal (from geom 1 to geom 2), then two tangents
    active: torch.Tensor  # [N, C] bool: MuJoCo has this contact (found, and dist < includemargin)
    found: torch.Tensor  # [N, C] bool: the slot's points exist at any distance (capsule-capsule's second: parallel axes)


def _geom_poses(kin, geoms: _Geoms):
    """World position ``[N, P, 3]`` and rotation ``[N, P, 3, 3]`` of geoms (MuJoCo's geom_xpos, geom_xmat)."""
    rot = kin.body_rot[:, geoms.body]
    return kin.body_pos[:, geoms.body] + (rot @ geoms.pos.unsqueeze(-1)).squeeze(-1), rot @ geoms.rot


def _dot(a, b):
    return (a * b).sum(-1)


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
    length = torch.sqrt(_dot(gap, gap))
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


def _make_frame(normal, tangent):
    """MuJoCo's ``mju_makeFrame``: rows normal, first tangent (``tangent`` made orthogonal to the
    normal; where it is unset, y or, for normals near y, z), second tangent ``normal x first``."""
    unset = _dot(tangent, tangent) < 0.25
    y_axis, z_axis = torch.zeros_like(normal), torch.zeros_like(normal)
    y_axis[..., 1], z_axis[..., 2] = 1.0, 1.0
    default = torch.where((normal[..., 1].abs() < 0.5).unsqueeze(-1), y_axis, z_axis)
    tangent = torch.where(unset.unsqueeze(-1), default, tangent)
    tangent = tangent - _dot(normal, tangent).unsqueeze(-1) * normal
    tangent = tangent / torch.sqrt(_dot(tangent, tangent).clamp_min(_MINVAL * _MINVAL)).unsqueeze(-1)  # see _sphere_sphere
    return torch.stack([normal, tangent, _cross(normal, tangent)], dim=-2)


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


def _cylinder_nearest(p, radius, half):
    """The signed distance of points ``p [..., 3]`` (the cylinder's frame) to a cylinder, the nearest
    point of its surface and the outward unit normal there: ``(sdf, q, outward)``. Outside, the
    nearest point is unique (the distance is differentiable); inside, the nearer of the side and
    the caps."""
    x, y, z = p.unbind(-1)
    rho = torch.sqrt((x * x + y * y).clamp_min(_MINVAL * _MINVAL))  # clamped inside the root: see _sphere_sphere
    radial = torch.stack([x / rho, y / rho, torch.zeros_like(x)], dim=-1)
    up = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    beyond_side, beyond_cap = rho > radius, z.abs() > half
    outside = beyond_side | beyond_cap
    scale = torch.where(beyond_side, radius / rho, torch.ones_like(rho))
    clamped = torch.stack([x * scale, y * scale, torch.minimum(torch.maximum(z, -half), half)], dim=-1)
    gap = p - clamped
    distance = torch.sqrt(_dot(gap, gap).clamp_min(_MINVAL * _MINVAL))
    # inside: out through the side or through the nearer cap, whichever is closer
    through_side = (radius - rho < half - z.abs()).unsqueeze(-1)
    cap_point = torch.stack([x, y, up * half], dim=-1)
    side_point = torch.stack([x * radius / rho, y * radius / rho, z], dim=-1)
    cap_normal = torch.stack([torch.zeros_like(z), torch.zeros_like(z), up], dim=-1)
    inside_q = torch.where(through_side, side_point, cap_point)
    inside_normal = torch.where(through_side, radial, cap_normal)
    inside_sdf = -torch.minimum(radius - rho, half - z.abs())
    o = outside.unsqueeze(-1)
    return (torch.where(outside, distance, inside_sdf), torch.where(o, clamped, inside_q),
            torch.where(o, gap / distance.unsqueeze(-1), inside_normal))


def _cylinder_sdf(p, radius, half):
    """The signed distance of points ``p [..., 3]`` (the cylinder's frame) to the cylinder (see
    `_cylinder_nearest`), alone: what the searches evaluate."""
    side = torch.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2) - radius
    cap = p[..., 2].abs() - half
    return torch.sqrt(side.clamp_min(0) ** 2 + cap.clamp_min(0) ** 2) + torch.maximum(side, cap).clamp_max(0)


def _axis_parameter(start, axis, radius, half):
    """``t`` in ``[-1, 1]`` minimising the cylinder's signed distance at ``start + t axis`` (a convex
    function of ``t``): golden section without gradient, the better of it and the two ends, then
    one Newton step at an interior minimum outside the cylinder, whose derivative is the implicit
    one of the minimiser (``dt = -f_t' / f_tt``, ``f`` the distance)."""
    with torch.no_grad():
        s, a = start.detach(), axis.detach()
        f = lambda t: _cylinder_sdf(s + t.unsqueeze(-1) * a, radius, half)  # noqa: E731
        t_best, f_best = _golden_search(f, torch.full_like(s[..., 0], -1.0), torch.full_like(s[..., 0], 1.0),
                                        _GOLDEN_ITERATIONS)
        candidates = torch.stack([t_best, -torch.ones_like(t_best), torch.ones_like(t_best)], dim=-1)
        values = torch.stack([f_best, f(candidates[..., 1]), f(candidates[..., 2])], dim=-1)
        t0 = candidates.gather(-1, values.argmin(-1, keepdim=True)).squeeze(-1)
    # the Newton step: f_t = o . axis, f_tt = axis^T (I - o o^T)(I - dq/dp) axis / distance outside
    p = start + t0.unsqueeze(-1) * axis
    sdf, _, outward = _cylinder_nearest(p, radius, half)
    x, y, z = p.unbind(-1)
    rho = torch.sqrt((x * x + y * y).clamp_min(_MINVAL * _MINVAL))
    radial = torch.stack([x / rho, y / rho], dim=-1)
    beyond_side = (rho > radius).unsqueeze(-1)
    across = axis[..., :2]
    moving = torch.cat([torch.where(beyond_side, (1 - radius / rho).unsqueeze(-1) * across
                                    + (radius / rho).unsqueeze(-1) * _dot(radial, across).unsqueeze(-1) * radial,
                                    torch.zeros_like(across)),
                        torch.where(z.abs() > half, axis[..., 2], torch.zeros_like(z)).unsqueeze(-1)], dim=-1)
    slope = _dot(outward, axis)
    curvature = (_dot(moving, axis) - slope * _dot(outward, moving)) / sdf.clamp_min(_MINVAL)
    newton = (t0.abs() < 1) & (sdf > 0) & (curvature > 1e-12)
    change = (slope / torch.where(newton, curvature, 1.0)).clamp(-1e-7, 1e-7)
    return torch.where(newton, t0 - change, t0)


def _golden_search(f, lo, hi, iterations: int):
    """The minimiser of a unimodal ``f`` over ``[lo, hi]`` (elementwise, no gradient): golden section."""
    x1, x2 = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    f1, f2 = f(x1), f(x2)
    for _ in range(iterations):
        left = f1 < f2  # the minimum lies in [lo, x2]
        lo, hi = torch.where(left, lo, x1), torch.where(left, x2, hi)
        new = torch.where(left, hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo))
        fnew = f(new)
        x1, x2, f1, f2 = (torch.where(left, new, x2), torch.where(left, x1, new),
                          torch.where(left, fnew, f2), torch.where(left, f1, fnew))
    return torch.where(f1 < f2, x1, x2), torch.minimum(f1, f2)


def _support(start, axis, radius, half, u):
    """``h(u) = start.u + |axis.u| + R |u_xy| + H |u_z|``: the support function of the segment
    ``start + t axis`` minus the cylinder (its frame) in unit directions ``u [..., K, 3]``."""
    s, a = start.unsqueeze(-2), axis.unsqueeze(-2)
    return (_dot(s, u) + _dot(a, u).abs() + radius.unsqueeze(-1) * torch.sqrt((u[..., 0] ** 2 + u[..., 1] ** 2)
            .clamp_min(_MINVAL * _MINVAL)) + half.unsqueeze(-1) * u[..., 2].abs())


def _edge_directions(start, axis, radius, half):
    """The segment's edge against a rim: the local minima of ``h`` on the great circle across the
    segment (where ``axis.u = 0``), ``[..., _EDGE_CANDIDATES, 3]``. The circle is sampled, the
    best local minima refined by golden section (no gradient), then one Newton step in the angle
    carries the derivative (``u`` built from a basis that follows the axis)."""
    tiny = _MINVAL * _MINVAL
    z_axis = torch.zeros_like(start)
    z_axis[..., 2] = 1.0
    direction = axis / torch.sqrt(_dot(axis, axis).clamp_min(tiny)).unsqueeze(-1)
    helper = torch.where((direction[..., 2].abs() < 0.9).unsqueeze(-1), z_axis, torch.roll(z_axis, 1, -1))
    b1 = _cross(direction, helper)
    b1 = b1 / torch.sqrt(_dot(b1, b1).clamp_min(tiny)).unsqueeze(-1)
    b2 = _cross(direction, b1)
    r, h2, s = radius.unsqueeze(-1), half.unsqueeze(-1), start.unsqueeze(-2)
    with torch.no_grad():
        c1, c2, sd = b1.detach().unsqueeze(-2), b2.detach().unsqueeze(-2), s.detach()

        def h(phi):  # [..., K] -> [..., K]: h on the circle (axis.u = 0 there)
            u = torch.cos(phi).unsqueeze(-1) * c1 + torch.sin(phi).unsqueeze(-1) * c2
            return _dot(sd, u) + r * torch.sqrt((u[..., 0] ** 2 + u[..., 1] ** 2).clamp_min(tiny)) + h2 * u[..., 2].abs()

        step = 2 * torch.pi / _EDGE_SAMPLES
        # half a step off the circle's crossings of the horizontal plane (b1 is horizontal), h's kinks
        phis = (torch.arange(_EDGE_SAMPLES, dtype=start.dtype, device=start.device) + 0.5) * step
        values = h(phis.expand(*start.shape[:-1], -1))
        local = (values <= torch.roll(values, 1, -1)) & (values <= torch.roll(values, -1, -1))
        best = torch.topk(torch.where(local, -values, -torch.inf), _EDGE_CANDIDATES, dim=-1).indices
        centre = phis[best]
        phi0, _ = _golden_search(h, centre - step, centre + step, _GOLDEN_ITERATIONS)
    # the Newton step: h' and h'' along the circle (u'' = -u)
    cos, sin = torch.cos(phi0).unsqueeze(-1), torch.sin(phi0).unsqueeze(-1)
    u = cos * b1.unsqueeze(-2) + sin * b2.unsqueeze(-2)
    du = -sin * b1.unsqueeze(-2) + cos * b2.unsqueeze(-2)
    flat = torch.sqrt((u[..., 0] ** 2 + u[..., 1] ** 2).clamp_min(tiny))
    turn = u[..., 0] * du[..., 0] + u[..., 1] * du[..., 1]
    up = torch.where(u[..., 2] >= 0, torch.ones_like(flat), -torch.ones_like(flat))
    slope = _dot(s, du) + r * turn / flat + h2 * up * du[..., 2]
    curvature = (-_dot(s, u) + r * ((du[..., 0] ** 2 + du[..., 1] ** 2 - flat ** 2) / flat - turn ** 2 / flat ** 3)
                 - h2 * up * u[..., 2])
    newton = curvature > 1e-12
    phi = phi0 - (slope / torch.where(newton, curvature, torch.ones_like(curvature))).clamp(-1e-6, 1e-6) * newton
    return torch.cos(phi).unsqueeze(-1) * b1.unsqueeze(-2) + torch.sin(phi).unsqueeze(-1) * b2.unsqueeze(-2)


def _segment_cylinder(start, axis, radius, half):
    """A segment ``start + t axis`` (``t`` in ``[-1, 1]``, the cylinder's frame) against the
    cylinder: ``(sd, x1, x2, u)``, the signed distance (negative: the minimal translation that
    separates them), a witness point on each (``x1 - x2 = -sd u``) and the unit direction from
    the segment to the cylinder.

    Outside, the axis' nearest point (`_axis_parameter`). Where the axis enters (or touches) the
    cylinder, the minimiser of the support function ``h`` of their difference (`_support`) among
    the directions that can minimise it, each with its witness on the segment: the cap normals
    (the end that leads), the side (the segment point whose shadow is nearest the axis; across
    the shadow where it passes through the axis), each end against each rim (that end) and the
    segment's edge against a rim (`_edge_directions`; the rim point, moved back by the depth).
    Inside each region of fixed signs of ``axis.u`` and ``u_z``, ``h`` has one minimum at most,
    at one of these."""
    t = _axis_parameter(start, axis, radius, half)
    p = start + t.unsqueeze(-1) * axis  # outside: the segment's nearest point
    sdf, q, outward = _cylinder_nearest(p, radius, half)
    tiny = _MINVAL * _MINVAL
    one = torch.ones_like(start[..., 0])
    z_axis = torch.zeros_like(start)
    z_axis[..., 2] = 1.0
    unit = lambda v: v / torch.sqrt(_dot(v, v).clamp_min(tiny)).unsqueeze(-1)  # noqa: E731
    # caps: the leading end
    caps = torch.stack([z_axis, -z_axis], dim=-2)
    lead = torch.where(axis[..., 2] >= 0, one, -one).unsqueeze(-1)
    cap_witness = torch.stack([start + lead * axis, start - lead * axis], dim=-2)
    # the side: minus the point of the segment's shadow nearest the axis, or across the shadow
    shadow, across = start[..., :2], axis[..., :2]
    along = (-_dot(shadow, across) / _dot(across, across).clamp_min(tiny)).clamp(-1, 1)
    nearest = shadow + along.unsqueeze(-1) * across
    perp = torch.stack([-across[..., 1], across[..., 0]], dim=-1)
    flat = lambda v: unit(torch.cat([v, torch.zeros_like(v[..., :1])], dim=-1))  # noqa: E731
    sides = torch.stack([flat(-nearest), flat(perp), flat(-perp)], dim=-2)
    side_witness = (start + along.unsqueeze(-1) * axis).unsqueeze(-2).expand_as(sides)
    # each end against each rim: u = -(A v, B) / |(A, B)|, v = -w_xy / |w_xy|, A = R - |w_xy|, B = w_z
    rims, rim_witness = [], []
    for end in (start + axis, start - axis):
        for sign in (1.0, -1.0):
            w = end + sign * half.unsqueeze(-1) * z_axis
            reach = torch.sqrt(_dot(w[..., :2], w[..., :2]).clamp_min(tiny))
            a, b = radius - reach, w[..., 2]
            rims.append(unit(torch.cat([a.unsqueeze(-1) * w[..., :2] / reach.unsqueeze(-1), -b.unsqueeze(-1)], dim=-1)))
            rim_witness.append(end)
    rims, rim_witness = torch.stack(rims, dim=-2), torch.stack(rim_witness, dim=-2)
    # the edge: the rim point at -u, moved back by the depth
    edges = _edge_directions(start, axis, radius, half)
    edge_flat = torch.sqrt((edges[..., 0] ** 2 + edges[..., 1] ** 2).clamp_min(tiny))
    rim_point = torch.stack([-radius.unsqueeze(-1) * edges[..., 0] / edge_flat,
                             -radius.unsqueeze(-1) * edges[..., 1] / edge_flat,
                             -half.unsqueeze(-1) * torch.where(edges[..., 2] >= 0, 1.0, -1.0).to(edges.dtype)], dim=-1)
    edge_witness = rim_point + _support(start, axis, radius, half, edges).unsqueeze(-1) * edges
    directions = torch.cat([caps, sides, rims, edges], dim=-2)
    witnesses = torch.cat([cap_witness, side_witness, rim_witness, edge_witness], dim=-2)
    # a family without a direction here (a shadow through the axis, an end on it) gives a short
    # vector: any unit vector stands in (a candidate that is not the minimiser is harmless)
    length = torch.sqrt(_dot(directions, directions).clamp_min(tiny)).unsqueeze(-1)
    directions = torch.where(length > 0.5, directions, z_axis.unsqueeze(-2).expand_as(directions))
    support = _support(start, axis, radius, half, directions)
    # ties within rounding go to the earlier family: a capsule along the side also has a (horizontal)
    # edge direction, whose rim witness would be wrong there
    scale = torch.sqrt(_dot(start, start)) + torch.sqrt(_dot(axis, axis)) + radius + half
    lowest = support.min(-1, keepdim=True).values
    within = support <= lowest + 16 * torch.finfo(support.dtype).eps * scale.unsqueeze(-1)
    best = within.to(torch.uint8).argmax(-1, keepdim=True)  # the first candidate within the tie
    depth = support.gather(-1, best).squeeze(-1)
    u = directions.gather(-2, best.unsqueeze(-1).expand(*best.shape, 3)).squeeze(-2)
    x1 = witnesses.gather(-2, best.unsqueeze(-1).expand(*best.shape, 3)).squeeze(-2)
    x2 = x1 - depth.unsqueeze(-1) * u
    # the directions also where the axis only touches the cylinder: the outward normal there is 0 / 0
    inside = sdf < _TOUCHING
    return (torch.where(inside, -depth, sdf), torch.where(inside.unsqueeze(-1), x1, p),
            torch.where(inside.unsqueeze(-1), x2, q), torch.where(inside.unsqueeze(-1), u, -outward))


def _capsule_cylinder(pos1, half_axis1, radius1, pos2, rot2, size2):
    """Capsule against cylinder (see the module's docstring): ``(dist, pos, normal)``, ``[N, P, ...]``."""
    to_local = rot2.transpose(-1, -2)
    start = (to_local @ (pos1 - pos2).unsqueeze(-1)).squeeze(-1)
    axis = (to_local @ half_axis1.unsqueeze(-1)).squeeze(-1)
    sd, x1, x2, u = _segment_cylinder(start, axis, size2[:, 0], size2[:, 1])
    middle = (x1 + x2 + radius1.unsqueeze(-1) * u) / 2
    return sd - radius1, pos2 + (rot2 @ middle.unsqueeze(-1)).squeeze(-1), (rot2 @ u.unsqueeze(-1)).squeeze(-1)


def collide(slots: ContactSlots, kin) -> Contacts:
    """The contacts of every slot at the configurations of ``kin`` (a
    [`Kinematics`][torchrl_diffenvs.articulated.Kinematics]; not imported here: the kinematics import the tree, which
    imports this module): [`Contacts`][torchrl_diffenvs.articulated.collision.Contacts]."""
    dists, poss, frames, founds = [], [], [], []
    for kind, first, g1, g2 in slots.groups:
        pos1, rot1 = _geom_poses(kin, g1)
        pos2, rot2 = _geom_poses(kin, g2)
        size1, size2 = g1.size, g2.size
        zero = torch.zeros_like(pos2)
        if kind == ("plane", "sphere"):
            dist, pos, normal = _plane_sphere(pos1, rot1, pos2, size2[:, 0])
            dist, pos, normal, tangent = dist[..., None], pos[..., None, :], normal[..., None, :], zero[..., None, :]
        elif kind == ("plane", "capsule"):
            axis = rot2[..., :, 2]
            half = size2[:, 1, None] * axis
            ends = torch.stack([pos2 + half, pos2 - half], dim=-2)  # MuJoCo: the +axis end first
            dist, pos, normal = _plane_sphere(pos1.unsqueeze(-2), rot1.unsqueeze(-3), ends, size2[:, 0, None])
            normal, tangent = normal.expand_as(pos), axis.unsqueeze(-2).expand_as(pos)
        elif kind == ("plane", "cylinder"):
            dist, pos, normal = _plane_cylinder(pos1, rot1, pos2, rot2, size2)
            normal = normal.unsqueeze(-2).expand_as(pos)
            tangent = torch.zeros_like(pos)
        elif kind == ("capsule", "cylinder"):
            dist, pos, normal = _capsule_cylinder(pos1, size1[:, 1, None] * rot1[..., :, 2], size1[:, 0], pos2, rot2, size2)
            dist, pos, normal, tangent = dist[..., None], pos[..., None, :], normal[..., None, :], zero[..., None, :]
        elif kind == ("sphere", "sphere"):
            dist, pos, normal = _sphere_sphere(pos1, size1[:, 0], pos2, size2[:, 0], rot1[..., :, 2], rot2[..., :, 2])
            dist, pos, normal, tangent = dist[..., None], pos[..., None, :], normal[..., None, :], zero[..., None, :]
        elif kind == ("sphere", "capsule"):
            axis = rot2[..., :, 2]
            along = _dot(axis, pos1 - pos2).clamp(-size2[:, 1], size2[:, 1])
            nearest = pos2 + along.unsqueeze(-1) * axis
            dist, pos, normal = _sphere_sphere(pos1, size1[:, 0], nearest, size2[:, 0], rot1[..., :, 2], axis)
            dist, pos, normal, tangent = dist[..., None], pos[..., None, :], normal[..., None, :], zero[..., None, :]
        else:  # capsule-capsule
            pair_margin = slots.margin[first:first + 2 * g1.body.numel():2]
            centres1, centres2, found = _capsule_capsule(
                pos1, size1[:, 1, None] * rot1[..., :, 2], size1[:, 0], pos2, size2[:, 1, None] * rot2[..., :, 2],
                size2[:, 0], pair_margin)
            r1, r2 = size1[:, 0, None].expand(-1, 2), size2[:, 0, None].expand(-1, 2)
            z1, z2 = rot1[..., :, 2].unsqueeze(-2).expand_as(centres1), rot2[..., :, 2].unsqueeze(-2).expand_as(centres2)
            dist, pos, normal = _sphere_sphere(centres1, r1, centres2, r2, z1, z2)
            tangent = torch.zeros_like(pos)
            founds.append(found.flatten(1))
        if kind != ("capsule", "capsule"):
            founds.append(torch.ones_like(dist, dtype=torch.bool).flatten(1))
        dists.append(dist.flatten(1))
        poss.append(pos.flatten(1, 2))
        frames.append(_make_frame(normal, tangent).flatten(1, 2))
    dist, found = torch.cat(dists, dim=1), torch.cat(founds, dim=1)
    return Contacts(dist, torch.cat(poss, dim=1), torch.cat(frames, dim=1), found & (dist < slots.margin), found)
