"""MuJoCo's collision detection, batched: the contacts ``mj_collision`` finds between geoms.

Every geom pair that MuJoCo's filter lets touch ([`colliding_pairs`][torchrl_diffenvs.articulated.collision.colliding_pairs]) is tested by the
primitive of its two geom types ([`primitives`][torchrl_diffenvs.articulated.primitives]), which gives a fixed number of contacts
per pair (a slot per possible contact); a slot holds a contact when MuJoCo's would: ``active``
is where its distance is below the pair's margin and the pair passes MuJoCo's bounding-sphere
filter (``geom_rbound``, `bounding_radius`). No data-dependent shape or Python branch: the
same ops run whatever touches. The eager CPU step first keeps the pairs that may touch in some env
(`near_pairs`, MuJoCo's broad phase by bounding spheres) and collides those alone.

Each contact has MuJoCo's ``pos``, ``frame`` (normal first, pointing from geom 1 to geom 2),
``dist`` and the pair's mixed parameters (``condim``, friction, ``solref``, ``solimp``,
``includemargin``: `_mix`, as ``mj_contactParam``). ``condim`` 1 (frictionless), 3 (sliding
friction), 4 (and torsional) and 6 (and rolling) are supported, with the model's friction cone:
MuJoCo's default pyramidal, or elliptic.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from .model import ArticulatedModel
from .primitive_types import PosedGeoms
from .primitives import PRIMITIVES
from .spatial import _MINVAL, _cross, _dot, small_matmul, small_matvec

__all__ = ["Contacts", "ContactSlots", "bounding_radius", "colliding_pairs", "contact_slots", "collide", "near_pairs",
           "unsupported_pairs"]

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
    static, and (``filterparent``) not a body and its parent unless that parent is the world.

    Args:
        model: the parsed model file.
    """
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
    if condim not in (1, 3, 4, 6):
        raise ValueError(f"{model.path}: geoms {model.geom_names[g1]!r} and {model.geom_names[g2]!r}: condim "
                         f"{condim} is not supported by MuJoCo's contact model here; supported: 1 (frictionless), "
                         "3 (sliding friction), 4 (and torsional) and 6 (and rolling)")
    return dict(condim=condim, friction=float(fri[0]), torsional=float(fri[1]), rolling=float(fri[2]),
                solref=np.array(solref, dtype=np.float64), solimp=solimp,
                margin=float(model.geom_margin[g1] + model.geom_margin[g2]))


#: MuJoCo's friction cones (``<option cone>``), its default first
CONES = ("pyramidal", "elliptic")
#: MuJoCo's ``mjMINMU``: every friction coefficient of a contact is at least this (``mj_assignFriction``)
MIN_FRICTION = 1e-5


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

    def margins(self, slots: "ContactSlots") -> torch.Tensor:
        """``[P]`` each pair's margin (its slots share it)."""
        per_pair = PRIMITIVES[self.kind].contacts
        return slots.margin[self.first:self.first + per_pair * self.geom1.body.numel():per_pair]

    def of_pairs(self, pairs: torch.Tensor, first: int) -> "_PrimitiveGroup":
        """The group of the pairs ``pairs [K]`` only, its slots from ``first`` on."""
        return _PrimitiveGroup(self.kind, first, _Geoms(*(x.index_select(0, pairs) for x in self.geom1)),
                               _Geoms(*(x.index_select(0, pairs) for x in self.geom2)))


def _geoms(model: ArticulatedModel, index: list[int], dtype, device) -> _Geoms:
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    return _Geoms(torch.as_tensor(model.geom_body[index], device=device), t(model.geom_pos[index]),
                  t(model.geom_rot[index]), t(model.geom_size[index]))


@dataclass
class ContactSlots:
    """The constant part of a model's contacts: one entry per contact slot ``[C]``, grouped by
    primitive (``groups``: `_PrimitiveGroup`, each pair giving ``PRIMITIVES[kind].contacts``
    consecutive slots)."""

    groups: list[_PrimitiveGroup]
    geom: torch.Tensor  # [C, 2] long
    body: torch.Tensor  # [C, 2] long
    condim: list[int]  # [C]
    friction_slot: torch.Tensor  # [C] long: the entry of params["contact_friction"] of its geom pair
    solref: torch.Tensor  # [C, 2]
    solimp: torch.Tensor  # [C, 5]
    margin: torch.Tensor  # [C] MuJoCo's includemargin (margin - gap; gap is 0 here)
    pyramid_index: torch.Tensor  # [C3] long: the slots with sliding friction (condim 3: four pyramid edges each)
    normal_index: torch.Tensor  # [C1] long: the frictionless slots (condim 1: one row each)
    torsional_index: torch.Tensor  # [C4] long: the slots with torsional friction too (condim 4: six edges each)
    rolling_index: torch.Tensor  # [C6] long: the slots with torsional and rolling friction (condim 6: ten edges)
    # [C, 3] the pair's mixed torsional, rolling, rolling friction (MuJoCo's contact friction[2:5]; the
    # sliding friction[0:2] is the per-env params["contact_friction"])
    spin_friction: torch.Tensor
    # [npair, 2] each geom pair's mixed solref (the entries of params["contact_friction"]): the
    # default of the params' contact_solref; MuJoCo's default (0.02, 1) for a pair with no slot
    pair_solref: torch.Tensor
    # the model's friction cone: "pyramidal" (MuJoCo's default: 2 (condim - 1) edge rows per
    # frictional contact) or "elliptic" (condim rows: the normal, then the frame's friction directions)
    cone: str = "pyramidal"

    @property
    def count(self) -> int:
        """The number of contact slots (geom pairs that can touch)."""
        return len(self.condim)

    def frictional(self) -> tuple[tuple[int, torch.Tensor], ...]:
        """The frictional slots by condim, in the order of their constraint rows: ``(condim,
        slots)`` for condim 3, 4 and 6 (each slot ``2 (condim - 1)`` pyramid edges, or ``condim``
        rows of an elliptic cone)."""
        return (3, self.pyramid_index), (4, self.torsional_index), (6, self.rolling_index)

    def subset(self, index: torch.Tensor, groups: list[_PrimitiveGroup] | None = None) -> ContactSlots:
        """The slots ``index [K]`` (ascending), as a model of their own for the constraint stage:
        their rows keep their order, so a problem built on them is the full one without the rows
        of the other slots. For the eager CPU step (it reads ``index`` on the host). `collide`
        runs on its ``groups``: none unless given (`near_pairs` gives those of whole pairs)."""
        keep = index.tolist()
        condim = [self.condim[i] for i in keep]
        of = lambda d: torch.as_tensor([j for j, c in enumerate(condim) if c == d], dtype=torch.long,  # noqa: E731
                                       device=index.device)
        return ContactSlots(
            groups=groups or [], geom=self.geom.index_select(0, index), body=self.body.index_select(0, index), condim=condim,
            friction_slot=self.friction_slot.index_select(0, index), solref=self.solref.index_select(0, index),
            solimp=self.solimp.index_select(0, index), margin=self.margin.index_select(0, index),
            pyramid_index=of(3), normal_index=of(1), torsional_index=of(4), rolling_index=of(6),
            spin_friction=self.spin_friction.index_select(0, index), pair_solref=self.pair_solref, cone=self.cone)


def unsupported_pairs(model: ArticulatedModel) -> list[tuple[str, str]]:
    """The colliding geom pairs (names) whose types have no primitive here (empty: MuJoCo's
    contact model covers the model).

    Args:
        model: the parsed model file.
    """
    return [(model.geom_names[g1], model.geom_names[g2]) for g1, g2 in colliding_pairs(model)
            if (model.geom_type[g1], model.geom_type[g2]) not in PRIMITIVES]


def contact_slots(model: ArticulatedModel, friction_slots: list[tuple[str, str]], dtype, device) -> ContactSlots:
    """The [`ContactSlots`][torchrl_diffenvs.articulated.collision.ContactSlots] of a model.

    Args:
        model: the parsed model file.
        friction_slots: the geom-name pairs of the ``contact_friction`` param
            (``RigidBodyTree.contact_pairs``, either order).
        dtype: the floating-point dtype of the slots' tensors.
        device: the device of the slots' tensors.
    """
    if model.cone not in CONES:
        raise ValueError(f"{model.path}: friction cone {model.cone!r} is invalid; valid: {', '.join(map(repr, CONES))}")
    slot_of = {frozenset(pair): i for i, pair in enumerate(friction_slots)}
    by_primitive: dict[tuple[str, str], list[tuple[int, int]]] = {}
    for g1, g2 in colliding_pairs(model):
        kind = (model.geom_type[g1], model.geom_type[g2])
        if kind not in PRIMITIVES:
            raise ValueError(f"{model.path}: geoms {model.geom_names[g1]!r} ({kind[0]}) and {model.geom_names[g2]!r} "
                             f"({kind[1]}) can touch, but MuJoCo's contact model here collides only "
                             f"{', '.join('-'.join(k) for k in PRIMITIVES)} (use contact='smooth', or set "
                             "contype/conaffinity to exclude the pair)")
        by_primitive.setdefault(kind, []).append((g1, g2))
    groups, rows = [], []
    for kind in PRIMITIVES:
        pairs = by_primitive.get(kind, [])
        if not pairs:
            continue
        groups.append(_PrimitiveGroup(kind, len(rows), _geoms(model, [p[0] for p in pairs], dtype, device),
                                      _geoms(model, [p[1] for p in pairs], dtype, device)))
        for g1, g2 in pairs:
            key = frozenset((model.geom_names[g1], model.geom_names[g2]))
            if key not in slot_of:
                raise ValueError(f"{model.path}: no contact_friction entry for geoms {sorted(key)}")
            rows += [(g1, g2, slot_of[key], _mix(model, g1, g2))] * PRIMITIVES[kind].contacts
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
        torsional_index=idx([i for i, r in enumerate(rows) if r[3]["condim"] == 4], (-1,)),
        rolling_index=idx([i for i, r in enumerate(rows) if r[3]["condim"] == 6], (-1,)),
        spin_friction=t([[max(MIN_FRICTION, r[3]["torsional"]), max(MIN_FRICTION, r[3]["rolling"]),
                          max(MIN_FRICTION, r[3]["rolling"])] for r in rows], (-1, 3)),
        pair_solref=t(_pair_solref(rows, len(friction_slots)), (-1, 2)), cone=model.cone)


def _pair_solref(rows: list, npair: int) -> np.ndarray:
    """``[npair, 2]`` the mixed solref of each geom pair from its slots' rows (MuJoCo's default
    ``(0.02, 1)`` for a pair without one)."""
    out = np.tile(np.array([0.02, 1.0]), (npair, 1))
    for _, _, pair, mixed in rows:
        out[pair] = mixed["solref"]
    return out


class Contacts(NamedTuple):
    """The contacts at a batch of configurations, one per slot of [`ContactSlots`][torchrl_diffenvs.articulated.collision.ContactSlots]."""

    # [N, C] signed distance (negative: penetrating); where MuJoCo has no contact, a lower bound of the
    # pair's distance (the primitive's, or the bounding spheres' gap where that is larger)
    dist: torch.Tensor
    pos: torch.Tensor  # [N, C, 3] world position, midway between the surfaces
    frame: torch.Tensor  # [N, C, 3, 3] rows: the normal (from geom 1 to geom 2), then two tangents
    active: torch.Tensor  # [N, C] bool: MuJoCo has this contact (found, dist < includemargin, bounding spheres within it)
    found: torch.Tensor  # [N, C] bool: the slot's points exist at any distance (capsule-capsule's second: parallel axes)

    def subset(self, index: torch.Tensor) -> Contacts:
        """The contacts of the slots ``index [K]`` (see `ContactSlots.subset`)."""
        return Contacts(*(x.index_select(1, index) for x in self))


def _posed(kin, geoms: _Geoms) -> PosedGeoms:
    """Geoms in the world at the configurations of ``kin`` (MuJoCo's geom_xpos, geom_xmat)."""
    rot = kin.body_rot.index_select(1, geoms.body)
    return PosedGeoms(kin.body_pos.index_select(1, geoms.body) + small_matvec(rot, geoms.pos), small_matmul(rot, geoms.rot),
                      geoms.size)


def _make_frame(normal, tangent):
    """MuJoCo's ``mju_makeFrame``: rows normal, first tangent (``tangent`` made orthogonal to the
    normal; where it is unset, y or, for normals near y, z), second tangent ``normal x first``."""
    unset = _dot(tangent, tangent) < 0.25
    y_axis, z_axis = torch.zeros_like(normal), torch.zeros_like(normal)
    y_axis[..., 1], z_axis[..., 2] = 1.0, 1.0
    default = torch.where((normal[..., 1].abs() < 0.5).unsqueeze(-1), y_axis, z_axis)
    tangent = torch.where(unset.unsqueeze(-1), default, tangent)
    tangent = tangent - _dot(normal, tangent).unsqueeze(-1) * normal
    tangent = tangent / torch.sqrt(_dot(tangent, tangent).clamp_min(_MINVAL * _MINVAL)).unsqueeze(-1)  # see primitives._sphere_sphere
    return torch.stack([normal, tangent, _cross(normal, tangent)], dim=-2)


def collide(slots: ContactSlots, kin) -> Contacts:
    """The contacts of every slot at the configurations of ``kin``:
    [`Contacts`][torchrl_diffenvs.articulated.collision.Contacts].

    Args:
        slots: the model's contact slots ([`contact_slots`][torchrl_diffenvs.articulated.collision.contact_slots]).
        kin: a [`Kinematics`][torchrl_diffenvs.articulated.Kinematics] (not imported here: the kinematics
            import the tree, which imports this module).
    """
    dists, poss, frames, founds, bounds = [], [], [], [], []
    for group in slots.groups:
        primitive = PRIMITIVES[group.kind]
        posed1, posed2 = _posed(kin, group.geom1), _posed(kin, group.geom2)
        contacts = primitive.collide(posed1, posed2, group.margins(slots))
        dists.append(contacts.dist.flatten(1))
        poss.append(contacts.pos.flatten(1, 2))
        frames.append(_make_frame(contacts.normal, contacts.tangent).flatten(1, 2))
        founds.append(contacts.found.flatten(1))
        bounds.append(_separation_bound(group.kind, posed1, posed2).repeat_interleave(primitive.contacts, dim=1))
    dist, found, bound = torch.cat(dists, dim=1), torch.cat(founds, dim=1), torch.cat(bounds, dim=1)
    # MuJoCo collides a pair only where its bounding spheres come within the margin (mj_collideGeoms'
    # filter): box-box's edge contacts measure the separation along an axis, below the pair's true
    # distance, and would otherwise count within the margin where MuJoCo has no contact
    active = found & (dist < slots.margin) & (bound <= slots.margin)
    # where MuJoCo has no contact the distance is a gap for the cfd surrogate: the larger of the two
    # lower bounds of the true distance (the same for every primitive but box-box)
    dist = torch.where(active, dist, torch.maximum(dist, bound))
    return Contacts(dist, torch.cat(poss, dim=1), torch.cat(frames, dim=1), active, found)


def bounding_radius(kind: str, size: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``geom_rbound [P]`` of geoms of one type from their ``size [P, 3]``: the radius of
    the sphere about the geom's centre that holds it (a plane has none: it is infinite).

    Args:
        kind: the geom type (``"sphere"``, ``"capsule"``, ``"ellipsoid"``, ``"cylinder"`` or ``"box"``).
        size: ``[P, 3]`` MuJoCo's ``geom_size`` of the geoms.
    """
    if kind == "sphere":
        return size[:, 0]
    if kind == "capsule":  # radius, half-length
        return size[:, 0] + size[:, 1]
    if kind == "ellipsoid":
        return size.amax(-1)
    if kind == "cylinder":  # radius, half-height
        return torch.sqrt(size[:, 0] ** 2 + size[:, 1] ** 2)
    if kind == "box":  # half-sizes
        return torch.linalg.vector_norm(size, dim=-1)
    raise ValueError(f"geom type {kind!r} has no bounding sphere; valid: sphere, capsule, ellipsoid, cylinder, box")


def _separation_bound(kind: tuple[str, str], geom1: PosedGeoms, geom2: PosedGeoms) -> torch.Tensor:
    """``[N, P]`` a lower bound of each pair's distance: its bounding spheres' gap, or for a plane
    the height of the other geom's bounding sphere above it (MuJoCo's filter in ``mj_collideGeoms``)."""
    radius2 = bounding_radius(kind[1], geom2.size)
    if kind[0] == "plane":  # the plane's normal: its z axis
        return _dot(geom2.pos - geom1.pos, geom1.rot[..., :, 2]) - radius2
    gap = geom2.pos - geom1.pos
    # clamped inside the root: coincident centres would give sqrt(0), whose infinite derivative
    # times the zero gradient of a branch not taken is NaN
    return torch.sqrt(_dot(gap, gap).clamp_min(_MINVAL * _MINVAL)) - bounding_radius(kind[0], geom1.size) - radius2


def near_pairs(slots: ContactSlots, kin, reach: float = 0.0) -> ContactSlots:
    """The slots of the geom pairs that may touch in some env of the batch: MuJoCo's broad phase,
    by bounding spheres (``geom_rbound``). A pair is left out only where, in every env, its
    bounding spheres are further apart than its margin plus ``reach`` (and a thousandth of their
    radii, for rounding): `collide`, which applies MuJoCo's bounding-sphere filter itself, would
    give it no contact within the margin, nor a gap within ``reach`` beyond it. The pairs kept
    keep their order and their groups, so `collide` runs on them alone and gives the same contacts
    for them; at least one pair is kept (the constraint stage expects a slot).

    For the eager CPU step, which reads the result on the host: on a GPU or under
    ``torch.compile`` every pair is collided (no data-dependent shape).

    Args:
        slots: contact slots with their groups (the model's, `contact_slots`).
        kin: a [`Kinematics`][torchrl_diffenvs.articulated.Kinematics] of the batch.
        reach: metres beyond the margin within which a pair counts as near (the ``cfd``
            gradient's distance, where it holds contacts that have not touched yet).
    """
    kept = []  # (group, its near pairs)
    for group in slots.groups:
        geom1, geom2 = group.geom1, group.geom2
        with torch.no_grad():
            bound = _separation_bound(group.kind, _posed(kin, geom1), _posed(kin, geom2))
            slack = 1e-3 * (geom2.size.amax(-1) + (0 if group.kind[0] == "plane" else geom1.size.amax(-1)))
            near = (bound < group.margins(slots) + reach + slack).any(0).nonzero().squeeze(-1)
        if near.numel():
            kept.append((group, near))
    if not kept:  # nothing near anywhere: the first pair, whose slots then hold no contact
        kept = [(slots.groups[0], torch.zeros(1, dtype=torch.long, device=slots.geom.device))]
    index, groups, first = [], [], 0
    for group, near in kept:
        per_pair = PRIMITIVES[group.kind].contacts
        groups.append(group.of_pairs(near, first))
        index.append((group.first + per_pair * near[:, None] + torch.arange(per_pair, device=near.device)).flatten())
        first += per_pair * near.numel()
    index = torch.cat(index)
    if index.numel() == slots.count:
        return slots
    return slots.subset(index, groups)
