"""Sphere against box, as MuJoCo's ``mjraw_SphereBox`` (``engine_collision_box.c``): one contact,
the sphere against the box's nearest point; capsule-box places its spheres on the capsule's axis
and collides them with it."""
from __future__ import annotations

import torch

from .primitive_types import PairContacts, PosedGeoms, one_contact
from .spatial import _MINVAL, _dot

__all__ = ["sphere_box"]


def sphere_box(sphere: PosedGeoms, box: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """MuJoCo's ``mjraw_SphereBox``: the sphere against the box's nearest point (its centre clamped
    to the box, in the box's frame); a centre inside the box leaves through the nearest face (the
    first in MuJoCo's order -x, +x, -y, +y, -z, +z where two are as near).

    Args:
        sphere: the pairs' spheres, posed in the world (``size``: the radius first).
        box: the pairs' boxes, posed in the world (``size``: the half-sizes).
        margin: ``[P]`` the pairs' margins (unused: the one contact is returned at any distance,
            and the collision stage compares its distance with the margin).

    Returns:
        One contact per pair, its normal from the sphere to the box.
    """
    radius, half = sphere.size[:, 0], box.size  # [P], [P, 3]
    centre = (box.rot.transpose(-1, -2) @ (sphere.pos - box.pos).unsqueeze(-1)).squeeze(-1)  # the box's frame
    clamped = torch.maximum(torch.minimum(centre, half), -half)
    towards = clamped - centre  # from the centre to the box
    squared = _dot(towards, towards)
    # clamped inside the root (a centre inside the box takes the face branch): see primitives._sphere_sphere
    length = torch.sqrt(squared.clamp_min(_MINVAL * _MINVAL))
    inside = length <= _MINVAL
    outward = towards / length.unsqueeze(-1)
    outside_pos = (clamped + centre + outward * radius.unsqueeze(-1)) / 2
    # inside: the nearest face; face 2k is at -half_k and 2k+1 at +half_k, the normal points inwards
    faces = torch.stack([half + centre, half - centre], dim=-1).flatten(-2)  # [N, P, 6]: -x, +x, -y, ...
    closest, face = faces.min(-1)
    nearest = torch.zeros_like(faces).scatter(-1, face.unsqueeze(-1), 1.0).unflatten(-1, (3, 2))
    nearest = nearest[..., 0] - nearest[..., 1]  # +1 towards a -face's axis, -1 for a +face
    inside_pos = centre + nearest * ((radius - closest) / 2).unsqueeze(-1)
    dist = torch.where(inside, -closest, length) - radius
    local_pos = torch.where(inside.unsqueeze(-1), inside_pos, outside_pos)
    local_normal = torch.where(inside.unsqueeze(-1), nearest, outward)
    pos = box.pos + (box.rot @ local_pos.unsqueeze(-1)).squeeze(-1)
    return one_contact(dist, pos, (box.rot @ local_normal.unsqueeze(-1)).squeeze(-1))
