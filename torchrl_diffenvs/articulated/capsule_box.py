"""Capsule against box, as MuJoCo's ``mjc_CapsuleBox`` (``mjraw_CapsuleBox``,
``engine_collision_box.c``): up to two contacts, each a sphere of the capsule's radius on its axis
against the box (``mjraw_SphereBox``, here [`sphere_box`][torchrl_diffenvs.articulated.sphere_box]).

In the box's frame MuJoCo scans, in its order and with its comparisons, the segment's features
nearest the box: each end over a face (or inside the box), then the segment against each of the
12 edges (their closest points, the box's point in the edge or at a corner). The nearest gives
the first sphere; a second one goes further along the axis, as far as the axis stays over the
face, the edge or the corner's face that the capsule lies along (none where the axis points at a
corner, or at an edge (a T seen along it), or where the nearest end is inside the box).

MuJoCo's quirks are kept, as its contacts are the reference: a capsule through the box with both
ends out gets the spheres of its ends or edges, possibly out of reach (no contact at all); the
second point can coincide with the first (a corner along a face, the first point at an end); an
edge parallel to the axis (to ``mjMINVAL``) is skipped; a pair farther than MuJoCo's initial
``bestdist`` (a length compared with squared distances) finds nothing.

Every candidate and every branch is computed for every pair, and the scan's choice and the
branches are picked with ``torch.where``: fixed shapes, no Python branch on values. Divisions
by quantities that can be zero (an axis square to a box axis, an axis parallel to an edge) take
a safe denominator where MuJoCo's C code would divide by zero (and its comparison fail), so the
gradients stay finite in the branches not taken.
"""
from __future__ import annotations

import torch

from .primitive_types import PairContacts, PosedGeoms, box_corners
from .spatial import _MINVAL
from .sphere_box import sphere_box

__all__ = ["capsule_box"]


def _dot3(a, b):
    """``mju_dot3``, summed in its order (a branch can turn on a distance's last bit)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _mul_mat_t_vec3(mat, vec):
    """``mju_mulMatTVec3``: ``mat^T vec`` in its order of summation."""
    return torch.stack([mat[..., 0, i] * vec[..., 0] + mat[..., 1, i] * vec[..., 1] + mat[..., 2, i] * vec[..., 2]
                        for i in range(3)], dim=-1)


def _mul_mat_vec3(mat, vec):
    """``mju_mulMatVec3``: ``mat vec`` in its order of summation."""
    return torch.stack([mat[..., i, 0] * vec[..., 0] + mat[..., i, 1] * vec[..., 1] + mat[..., i, 2] * vec[..., 2]
                        for i in range(3)], dim=-1)


def _pick(values, index):
    """``values[..., index]`` for ``values [..., 3]`` and a per-pair ``index [...]``."""
    return values.gather(-1, index.unsqueeze(-1)).squeeze(-1)


def _ratio(num, den):
    """``num / den``, ``inf`` where ``den`` is zero: MuJoCo's C code divides by zero there and the
    ``e1 < secondpos`` that follows fails (inf or NaN), which an infinite ratio reproduces; the
    denominator is made safe so that the gradient of the unused quotient is zero, not NaN."""
    zero = den == 0
    return torch.where(zero, torch.inf, num / torch.where(zero, torch.ones_like(den), den))


def _box_edges(like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """MuJoCo's 12 box edges in its order (axis ``j``, then the corners ``i`` with bit ``j`` clear,
    ascending): each edge's axis ``[12]``, the corner it starts from ``[12]`` and the signs of its
    middle ``[12, 3]`` (its corner's, 0 along the edge), made on ``like``'s device and dtype."""
    axis, nth = torch.arange(3, device=like.device).unsqueeze(-1), torch.arange(4, device=like.device)
    # the nth corner with bit j clear: nth with a 0 bit inserted at position j
    low = torch.bitwise_and(nth, torch.bitwise_left_shift(1, axis) - 1)
    corner = torch.bitwise_or(torch.bitwise_left_shift(torch.bitwise_right_shift(nth, axis), axis + 1), low).flatten()
    axis = axis.expand(3, 4).flatten()
    along = torch.arange(3, device=like.device) == axis.unsqueeze(-1)
    return axis, corner, torch.where(along, 0, box_corners(like)[corner])


def _scan(pos, halfaxis, half, radius, halflength, margin):
    """MuJoCo's search for the segment's feature nearest the box (the box's frame): ``(bestsegmentpos,
    bestboxpos, cltype, clface, clcorner, cledge)`` with its encoding (``cltype``: -3 / -1 the
    segment's -/+ end over face ``clface`` (-1: inside the box), ``3 s1 + s2`` the segment against
    edge ``cledge`` from corner ``clcorner``, ``s`` 0 / 2 at the lower / upper end of the edge
    (``s1``) or of the segment (``s2``), 1 between; -4: nothing found). The 14 candidates are
    computed at once, then chosen in MuJoCo's order with its comparisons."""
    device = pos.device
    ends = 2 * torch.arange(2, dtype=pos.dtype, device=device) - 1  # (-1, 1), made on the device: no copy to it
    # each end over a face (out of the box along one axis at most) or inside it
    tips = pos.unsqueeze(-2) + halfaxis.unsqueeze(-2) * ends.unsqueeze(-1)  # [N, P, 2, 3]
    box = half.unsqueeze(-2)
    below, above = tips < -box, tips > box
    out = below | above
    gap = torch.where(below, -box, torch.where(above, box, tips)) - tips
    face_dist = _dot3(gap, gap)
    face_ok = out.sum(-1) <= 1
    face = torch.where(out, torch.arange(3, device=device), -1).amax(-1)  # the last axis it is out along (MuJoCo's c2)
    # the segment against each edge (from its middle along axis j): the closest points of the lines,
    # clamped to the edge (x1), then to the segment (x2) and the edge again, with MuJoCo's labels
    # (s1 keeps its value where x1 is re-solved inside the edge)
    j, edge_corner, edge_middle = _box_edges(pos)
    onehot = torch.nn.functional.one_hot(j, 3).to(pos.dtype)  # [12, 3]
    dif = edge_middle * half.unsqueeze(-2) - pos.unsqueeze(-2)  # [N, P, 12, 3]
    s = half[:, j]  # [P, 12]
    ha = halfaxis[..., j]  # [N, P, 12]
    mc = (halflength * halflength).unsqueeze(-1)
    ma, mb = s * s, -s * ha
    u, v = -s * dif.gather(-1, j.expand(*dif.shape[:-2], -1).unsqueeze(-1)).squeeze(-1), _dot3(halfaxis.unsqueeze(-2), dif)
    det = ma * mc - mb * mb
    parallel = det.abs() < _MINVAL  # MuJoCo skips the edge
    idet = 1 / torch.where(parallel, torch.ones_like(det), det)
    x1, x2 = (mc * u - mb * v) * idet, (ma * v - mb * u) * idet
    high1, low1 = x1 > 1, x1 < -1
    s1 = torch.where(high1, 2, torch.where(low1, 0, 1))
    x2 = torch.where(high1, (v - mb) * (1 / mc), torch.where(low1, (v + mb) * (1 / mc), x2))
    x1 = torch.where(high1, torch.ones_like(x1), torch.where(low1, -torch.ones_like(x1), x1))
    high2, low2 = x2 > 1, x2 < -1
    again = torch.where(high2, (u - mb) * (1 / ma), (u + mb) * (1 / ma))
    clamp2 = high2 | low2
    s1 = torch.where(clamp2, torch.where(again > 1, 2, torch.where(again < -1, 0, s1)), s1)
    x1 = torch.where(clamp2, again.clamp(-1, 1), x1)
    s2 = torch.where(high2, 2, torch.where(low2, 0, 1))
    x2 = torch.where(high2, torch.ones_like(x2), torch.where(low2, -torch.ones_like(x2), x2))
    gap = dif + halfaxis.unsqueeze(-2) * (-x2).unsqueeze(-1) + onehot * (s * x1).unsqueeze(-1)  # (+0 off axis j: exact)
    edge_dist = _dot3(gap, gap)
    # MuJoCo's scan: a later candidate wins only if nearer (an edge: by more than mjMINVAL, so an
    # earlier one as near to rounding keeps its place); its initial bestdist is a length, compared
    # with squared distances: a pair farther than that finds nothing, whatever the margin
    best = (margin + 2 * (radius + halflength + half[:, 0] + half[:, 1] + half[:, 2])).expand(pos.shape[:-1])
    choice = torch.full(pos.shape[:-1], -1, dtype=torch.long, device=device)
    for k in range(2):
        take = face_ok[..., k] & (face_dist[..., k] < best)
        best, choice = torch.where(take, face_dist[..., k], best), torch.where(take, k, choice)
    for k in range(12):
        take = ~parallel[..., k] & (edge_dist[..., k] < best - _MINVAL)
        best, choice = torch.where(take, edge_dist[..., k], best), torch.where(take, k + 2, choice)
    on_face, on_edge = (choice >= 0) & (choice < 2), choice >= 2
    k = choice.clamp(0, 1).unsqueeze(-1)
    e = (choice - 2).clamp(0, 11).unsqueeze(-1)
    label = (s1 * 3 + s2).gather(-1, e).squeeze(-1)
    bestsegmentpos = torch.where(on_edge, x2.gather(-1, e).squeeze(-1),
                                 torch.where(on_face, ends[k.squeeze(-1)], torch.zeros_like(x2[..., 0])))
    bestboxpos = torch.where(on_edge, x1.gather(-1, e).squeeze(-1), torch.zeros_like(x1[..., 0]))
    cltype = torch.where(on_edge, label, torch.where(on_face, 2 * k.squeeze(-1) - 3, -4))
    clface = face.gather(-1, k).squeeze(-1)
    cledge = j[e.squeeze(-1)]
    clcorner = edge_corner[e.squeeze(-1)] + (1 << cledge) * (label // 6)  # the upper corner where s1 = 2
    return bestsegmentpos, bestboxpos, cltype, clface, clcorner, cledge


def _second(axis, halfaxis, pos, half, bestsegmentpos, bestboxpos, cltype, clface, clcorner, cledge):
    """MuJoCo's second point, as an offset ``secondpos`` along the axis from the first, and whether
    there is one: the three branches of ``mjraw_CapsuleBox`` after the scan, each computed. Its
    sequences of ``if (e1 < secondpos) secondpos = e1`` are minima."""
    half = half.expand_as(pos)
    absaxis = halfaxis.abs()
    axisdir = (halfaxis[..., 0] > 0).long() + 2 * (halfaxis[..., 1] > 0).long() + 4 * (halfaxis[..., 2] > 0).long()
    bsp = bestsegmentpos
    across = _ratio(2 * half, absaxis)  # the axis' parameter across the box along each axis

    # nearest to a corner of the box: the axis points at or away from the corner (no second), or
    # lies along the edge (ax) that it crosses the corner's octant by, or along a face
    c1 = axisdir ^ clcorner
    pointing = (c1 == 0) | (c1 == 7)
    flip = (c1 == 3) | (c1 == 5) | (c1 == 6)
    mul = torch.where(flip, -1.0, 1.0).to(pos.dtype)
    c1 = torch.where(flip, 7 - c1, c1)
    de = torch.where(flip, 1 + bsp, 1 - bsp)  # to either end of the segment from the first point
    dp = torch.where(flip, 1 - bsp, 1 + bsp)
    ax = torch.where(c1 == 1, 0, torch.where(c1 == 2, 1, 2))
    along = _pick(axis, ax)
    along_edge = torch.minimum(de, _pick(across, ax)) * mul
    along_face = torch.minimum(dp, torch.minimum(_pick(across, (ax + 1) % 3), _pick(across, (ax + 2) % 3))) * -mul
    corner_pos = torch.where(along * along > 0.5, along_edge, along_face)

    # nearest to the middle of an edge: crossing it (an X, seen along the edge) gives a second
    # point, as far as the axis stays over the face it is flatter to and within the edge
    c1 = (axisdir ^ clcorner) & (7 - (1 << cledge))
    crossing = (c1 == 1) | (c1 == 2) | (c1 == 4)
    ax = cledge
    ax1, ax2 = (ax + 1) % 3, (ax + 2) % 3
    ax1 = torch.where(_pick(absaxis, ax1) > _pick(absaxis, ax2), ax2, ax1)  # (|axis| in MuJoCo: the same order)
    ax2 = 3 - ax - ax1
    ahead = ((c1 >> ax2) & 1) == 1
    e2 = torch.where(((axisdir >> ax) & 1) == ((c1 >> ax2) & 1), 1 - bestboxpos, 1 + bestboxpos)
    edge_pos = torch.minimum(torch.where(ahead, 1 - bsp, 1 + bsp), _pick(across, ax2))
    edge_pos = torch.minimum(edge_pos, _ratio(_pick(half, ax) * e2, _pick(absaxis, ax)))
    edge_pos = edge_pos * torch.where(ahead, 1.0, -1.0).to(pos.dtype)

    # an end nearest a face: the second point where the axis, from that end, leaves the face's
    # column (the nearest of the other faces' planes ahead, within the segment)
    mul = torch.where(cltype == -3, 1.0, -1.0).to(pos.dtype).unsqueeze(-1)
    start = pos - halfaxis * mul
    planes = torch.stack([_ratio(half - start, halfaxis), _ratio(-half - start, halfaxis)], dim=-1) * mul.unsqueeze(-1)
    other = (clface.unsqueeze(-1) != torch.arange(3, device=pos.device)).unsqueeze(-1)
    face_pos = torch.where(other & (planes > 0), planes, 2.0).flatten(-2).amin(-1) * mul.squeeze(-1)

    corner, edge = (cltype >= 0) & (cltype // 3 != 1), (cltype >= 0) & (cltype // 3 == 1)
    face = (cltype == -3) | (cltype == -1)
    secondpos = torch.where(corner, corner_pos, torch.where(edge, edge_pos, face_pos))
    second = (corner & ~pointing) | (edge & crossing) | (face & (clface != -1))
    return torch.where(second, secondpos, torch.zeros_like(secondpos)), second


def capsule_box(capsule: PosedGeoms, box: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """A capsule (geom 1) against a box (geom 2): ``PairContacts`` with two slots, MuJoCo's first and
    second contact (``found``: MuJoCo makes it, active where within the margin).

    Args:
        capsule: the pairs' capsules, posed in the world (``size``: radius, half-length).
        box: the pairs' boxes, posed in the world (``size``: the half-sizes).
        margin: ``[P]`` the pairs' margins.
    """
    radius, halflength, half = capsule.size[:, 0], capsule.size[:, 1], box.size
    pos = _mul_mat_t_vec3(box.rot, capsule.pos - box.pos)
    axis = _mul_mat_t_vec3(box.rot, capsule.rot[..., :, 2])
    halfaxis = axis * halflength.unsqueeze(-1)
    bsp, bbp, cltype, clface, clcorner, cledge = _scan(pos, halfaxis, half, radius, halflength, margin)
    secondpos, second = _second(axis, halfaxis, pos, half, bsp, bbp, cltype, clface, clcorner, cledge)
    found = cltype != -4
    # the two spheres on the axis, placed in the world as MuJoCo does, against the box: MuJoCo's
    # sphere-box, the two slots of each pair side by side as pairs of their own
    along = torch.stack([bsp, secondpos + bsp], dim=-1)  # [N, P, 2]
    centres = pos.unsqueeze(-2) + halfaxis.unsqueeze(-2) * along.unsqueeze(-1)
    rot = box.rot.unsqueeze(-3).expand(*along.shape, 3, 3)
    world = _mul_mat_vec3(rot, centres) + box.pos.unsqueeze(-2)
    flat = lambda x: x.flatten(1, 2)  # noqa: E731
    contacts = sphere_box(PosedGeoms(flat(world), flat(capsule.rot.unsqueeze(-3).expand_as(rot)),
                                     capsule.size.repeat_interleave(2, 0)),
                          PosedGeoms(flat(box.pos.unsqueeze(-2).expand_as(world)), flat(rot),
                                     box.size.repeat_interleave(2, 0)), margin.repeat_interleave(2, 0))
    shape = along.shape
    return PairContacts(contacts.dist.reshape(shape), contacts.pos.reshape(*shape, 3),
                        contacts.normal.reshape(*shape, 3), contacts.tangent.reshape(*shape, 3),
                        torch.stack([found, found & second], dim=-1))
