"""Box against box, as MuJoCo's ``mjc_BoxBox`` (``engine_collision_box.c``, MuJoCo 4): up to
eight contacts per pair, all with one normal (from box 1 to box 2) and MuJoCo's default tangent.

MuJoCo's algorithm, stage 1: the separating-axis test over 15 axes (box 1's face normals, box 2's,
then the nine cross products of an edge of each). Any axis separating the boxes by more than the
margin (plus a rounding slack) means no contact; otherwise the least penetrating axis wins, the
first of equals, an edge axis only if it beats the faces by a relative bias, and an edge axis
within ~8 degrees of the best face normal gives way to that face unless 5 % deeper. Stage 2, an
edge axis: one contact, midway between the closest points of the two supporting edges (both
candidate edges of a box are tried where the axis is ~orthogonal to one of its faces, the closer
pair kept). A face axis: its box is the reference; the face of the other box most opposed to the
normal is clipped to the reference face's four side planes (Sutherland-Hodgman, ``clipHalfPlane``)
and every clipped vertex within the margin, bar near-duplicates of earlier ones, is a contact:
its distance is its height over the reference face, its position midway between the two.

Here every branch runs for every pair, with no value-dependent shape or Python branch: the winning
axis is an index tensor, the edge and face quantities are gathered with it, the clipping runs on a
fixed buffer of eight vertices and a count (each pass emits MuJoCo's vertices in MuJoCo's order,
compacted by rank), and the contacts fill ``K = 8`` slots in MuJoCo's order, ``found`` marking
those MuJoCo has. The arithmetic follows MuJoCo's operation order, so exact ties (aligned faces)
break as MuJoCo's do. Float64 uses MuJoCo's double-precision tolerances; other dtypes its
single-precision build's (``mjUSESINGLE``).
"""
from __future__ import annotations

import torch

from .primitive_types import PairContacts, PosedGeoms
from .spatial import _MINVAL

__all__ = ["box_box", "K"]

#: MuJoCo's most contacts of two boxes: a quadrilateral clipped by four half-planes has at most 8
#: vertices (also the clipping buffer here: MuJoCo's C buffer is larger, which only rounding could fill)
K = 8

# MuJoCo's rounding scales (mjBOXBOX_SEPEPS, _PAREPS, _SGNEPS, _DUPEPS): its double build's, and
# its single-precision build's for other dtypes
_TOLERANCES = {torch.float64: (1e-13, 1e-16, 1e-9, 1e-14)}
_SINGLE = (1e-6, 1e-7, 1e-5, 1e-10)
_EDGEBIAS = 1e-6  # an edge axis must beat the faces by this relative amount (mjBOXBOX_EDGEBIAS)


def _next(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x`` at index ``(i + 1) % 3`` along ``dim`` (a roll: indexing a CUDA tensor with a Python
    list copies the list to the device, a synchronisation)."""
    return torch.roll(x, -1, dim)


def _prev(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x`` at index ``(i + 2) % 3`` along ``dim``."""
    return torch.roll(x, 1, dim)


def _permutations(like: torch.Tensor) -> torch.Tensor:
    """The axis permutations ``[3, 3, 3]``, ``[a] @ v = (v[a + 1], v[a + 2], v[a])`` (indices mod 3):
    a gather as an exact product by 0s and 1s, made on ``like``'s device (a tensor built from
    Python numbers is a host-to-device copy, which synchronises on CUDA)."""
    k = torch.arange(3, device=like.device)
    return torch.eye(3, dtype=like.dtype, device=like.device)[(k[:, None] + k[None, :] + 1) % 3]


def _corner_signs(like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The incident face's winding (MuJoCo's corner_sign), ``(1, -1, -1, 1)`` and ``(1, 1, -1, -1)``,
    made on ``like``'s device."""
    k = torch.arange(4, device=like.device)
    return (1 - 2 * (k % 3 != 0)).to(like.dtype), (1 - 2 * (k >= 2)).to(like.dtype)


# the products below keep MuJoCo's operation order (left to right), so values match to the bit
def _dot3(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _mat_vec(m, v):  # mji_mulMatVec3
    return m[..., :, 0] * v[..., 0, None] + m[..., :, 1] * v[..., 1, None] + m[..., :, 2] * v[..., 2, None]


def _mat_t_vec(m, v):  # mji_mulMatTVec3
    return m[..., 0, :] * v[..., 0, None] + m[..., 1, :] * v[..., 1, None] + m[..., 2, :] * v[..., 2, None]


def _take(v, index):
    """``v[..., index]`` for an index tensor of v's batch shape."""
    return v.gather(-1, index.unsqueeze(-1)).squeeze(-1)


def _compact(candidates, emitted):
    """The emitted candidates ``[.., C, 3]`` moved to the front in order (the first ``K``), and
    their count: MuJoCo's ``out[nout++] = ...`` while ``nout < K``."""
    rank = emitted.long().cumsum(-1)  # [.., C]: 1 + the slot of an emitted candidate
    slots = torch.arange(1, K + 1, device=rank.device).unsqueeze(-1)
    chosen = (emitted.unsqueeze(-2) & (rank.unsqueeze(-2) == slots)).long().argmax(-1)  # [.., K]
    picked = candidates.gather(-2, chosen.unsqueeze(-1).expand(*chosen.shape, candidates.shape[-1]))
    return picked, emitted.sum(-1).clamp_max(K)


def _clip(verts, count, coord: int, sign: float, limit):
    """MuJoCo's ``clipHalfPlane``: the polygon ``verts [.., K, 3]`` (its first ``count``) clipped to
    ``sign * v[coord] <= limit``, each vertex inside kept and each edge strictly crossing the plane
    cut, in MuJoCo's order (a polygon already inside comes out unchanged, as MuJoCo's shortcut)."""
    slot = torch.arange(K, device=count.device)
    valid = slot < count.unsqueeze(-1)
    d = sign * verts[..., coord] - limit.unsqueeze(-1)
    following = torch.where(slot + 1 == count.unsqueeze(-1), 0, (slot + 1) % K)
    dq = d.gather(-1, following)
    q = verts.gather(-2, following.unsqueeze(-1).expand_as(verts))
    keep = valid & (d <= 0)
    crossing = valid & (((d < 0) & (dq > 0)) | ((d > 0) & (dq < 0)))
    t = d / torch.where(crossing, d - dq, 1.0)  # only crossing edges divide (d != dq there)
    cut = verts + t.unsqueeze(-1) * (q - verts)
    candidates = torch.stack([verts, cut], dim=-2).flatten(-3, -2)  # p0, cut0, p1, cut1, ...
    return _compact(candidates, torch.stack([keep, crossing], dim=-1).flatten(-2))


def _separating_axes(size1, size2, pos21, pos12, rot, septol, parallel):
    """Stage 1: ``(separated, code_face, sep_face, edge, sep_best)``: whether an axis separates the
    boxes beyond ``septol``, the best face axis (0-2 box 1's, 3-5 box 2's, the first of equals) and
    its separation, and the edge pair ``3 i + j`` that beats it (-1: none) with its separation."""
    rotabs = rot.abs()
    radius2 = rotabs[..., :, 0] * size2[..., 0, None] + rotabs[..., :, 1] * size2[..., 1, None] \
        + rotabs[..., :, 2] * size2[..., 2, None]
    radius1 = rotabs[..., 0, :] * size1[..., 0, None] + rotabs[..., 1, :] * size1[..., 1, None] \
        + rotabs[..., 2, :] * size1[..., 2, None]
    seps = torch.cat([pos21.abs() - size1 - radius2, pos12.abs() - size2 - radius1], dim=-1)
    sep_face, code_face = seps.max(-1)  # the first of equals, as MuJoCo's strict comparisons
    # edge axes [.., i, j]: e_i x (box 2's axis j) in box 1's frame, its components i1, i2
    row1, row2 = _next(rot, -2), _prev(rot, -2)  # rot[i1, j], rot[i2, j]
    ax1, ax2 = -row2, row1
    norm2 = ax1 * ax1 + ax2 * ax2
    # nearly parallel edges: MuJoCo skips the axis (pure rounding noise); the root is kept off
    # zero there so that its derivative stays finite
    valid = norm2 >= parallel
    inv = 1 / torch.sqrt(torch.where(valid, norm2, 1.0))
    ax1, ax2 = ax1 * inv, ax2 * inv
    radius1 = _next(size1, -1).unsqueeze(-1) * ax1.abs() + _prev(size1, -1).unsqueeze(-1) * ax2.abs()
    a2_1 = ax1 * _next(row1, -1) + ax2 * _next(row2, -1)  # the axis in box 2's frame, components j1, j2
    a2_2 = ax1 * _prev(row1, -1) + ax2 * _prev(row2, -1)
    radius2 = _next(size2, -1).unsqueeze(-2) * a2_1.abs() + _prev(size2, -1).unsqueeze(-2) * a2_2.abs()
    sep = (ax1 * _next(pos21, -1).unsqueeze(-1) + ax2 * _prev(pos21, -1).unsqueeze(-1)).abs() - radius1 - radius2
    sep, valid = sep.flatten(-2), valid.flatten(-2)  # [.., 3 i + j]
    separated = (seps > septol.unsqueeze(-1)).any(-1) | (valid & (sep > septol.unsqueeze(-1))).any(-1)
    # MuJoCo's scan: an edge axis wins if its biased separation beats the best so far
    biased, deeper = sep - _EDGEBIAS * sep.abs(), valid & (sep > sep_face.unsqueeze(-1))
    sep_best, edge = sep_face, torch.full_like(code_face, -1)
    for e in range(9):
        better = deeper[..., e] & (biased[..., e] > sep_best)
        sep_best, edge = torch.where(better, sep[..., e], sep_best), torch.where(better, e, edge)
    return separated, code_face, sep_face, edge, sep_best


def _edge_contact(size1, size2, pos21, rot, i, j, axis, ambiguous, eye):
    """Stage 2a: ``(dist, mid)`` in box 1's frame: the closest points of box 1's edge along ``e_i``
    and box 2's along its axis ``j`` that support ``axis`` (unit, box 1 towards box 2), trying the
    other edge of a box whose choice is ambiguous (``axis`` ~orthogonal to one of its faces) and
    keeping the closer pair, MuJoCo's first of equals."""
    ei, ej = eye[i], eye[j]
    i1, i2, j1, j2 = (i + 1) % 3, (i + 2) % 3, (j + 1) % 3, (j + 2) % 3
    a2 = _mat_t_vec(rot, axis)
    none = torch.zeros_like(axis)
    flip1 = torch.where((_take(axis, i1).abs() < ambiguous).unsqueeze(-1), eye[i1],
                        torch.where((_take(axis, i2).abs() < ambiguous).unsqueeze(-1), eye[i2], none))
    flip2 = torch.where((_take(a2, j1).abs() < ambiguous).unsqueeze(-1), eye[j1],
                        torch.where((_take(a2, j2).abs() < ambiguous).unsqueeze(-1), eye[j2], none))
    d2 = _take(rot, j.unsqueeze(-1).expand_as(axis))  # box 2's axis j
    b = _take(d2, i)  # d1 . d2, d1 = e_i
    denom = 1 - b * b
    parallel = denom < _MINVAL
    half1, half2 = _take(size1, i).unsqueeze(-1), _take(size2, j).unsqueeze(-1)
    # [4, 1]: the four pairs on a new axis, (0, 0, 1, 1) and (0, 1, 0, 1): MuJoCo's loop order, made on the device
    pair = torch.arange(4, device=axis.device)
    v1, v2 = (pair >= 2).to(axis.dtype).unsqueeze(-1), (pair % 2).to(axis.dtype).unsqueeze(-1)
    corner1 = torch.where(axis >= 0, size1, -size1) * (1 - ei)  # support along +axis; component i zero
    corner2 = torch.where(a2 >= 0, -size2, size2) * (1 - ej)  # support along -axis, box 2's frame
    c1 = corner1.unsqueeze(-2) * (1 - 2 * v1 * flip1.unsqueeze(-2))  # [.., 4, 3]
    cc = corner2.unsqueeze(-2) * (1 - 2 * v2 * flip2.unsqueeze(-2))
    c2 = _mat_vec(rot.unsqueeze(-3), cc) + pos21.unsqueeze(-2)
    e = c2 - c1
    d1e, d2e = _take(e, i.unsqueeze(-1).expand(*i.shape, 4)), _dot3(d2.unsqueeze(-2), e)
    b, denom, parallel = b.unsqueeze(-1), denom.unsqueeze(-1), parallel.unsqueeze(-1)
    s = torch.where(parallel, 0.0, (d1e - b * d2e) / torch.where(parallel, 1.0, denom))
    # clamped into the segments, each clamp re-solving the other parameter (MuJoCo's order)
    s = torch.clamp(s, -half1, half1)
    t = torch.clamp(b * s - d2e, -half2, half2)
    s = torch.clamp(d1e + b * t, -half1, half1)
    p1 = c1 + s.unsqueeze(-1) * ei.unsqueeze(-2)
    p2 = c2 + d2.unsqueeze(-2) * t.unsqueeze(-1)
    gap = p2 - p1
    tried = ((v1.squeeze(-1) == 0) | (flip1.sum(-1, keepdim=True) > 0)) & ((v2.squeeze(-1) == 0) | (flip2.sum(-1, keepdim=True) > 0))
    best = torch.where(tried, _dot3(gap, gap), torch.inf).argmin(-1)  # the first closest pair
    pick = best[..., None, None].expand(*best.shape, 1, 3)
    w1, w2 = p1.gather(-2, pick).squeeze(-2), p2.gather(-2, pick).squeeze(-2)
    return _dot3(w2 - w1, axis), 0.5 * (w1 + w2)


def _face_contacts(size1, size2, pos1, pos2, mat1, mat2, pos21, pos12, rot, code, margin, duplicate):
    """Stage 2b: ``(dist [.., K], pos [.., K, 3], normal [.., 3], found [.., K])``: the incident
    face clipped to the reference face ``code`` (0-2 box 1's axis, 3-5 box 2's), the accepted
    vertices first in MuJoCo's order."""
    ref1 = code < 3
    a = torch.where(ref1, code, code - 3)
    r = ref1.unsqueeze(-1)
    sizeref, sizeinc = torch.where(r, size1, size2), torch.where(r, size2, size1)
    posref, posoi = torch.where(r, pos1, pos2), torch.where(r, pos21, pos12)  # posoi: incident centre, reference frame
    matref = torch.where(r.unsqueeze(-1), mat1, mat2)
    rinc = torch.where(r.unsqueeze(-1), rot, rot.transpose(-1, -2))  # rinc[r, c]: incident axis c, reference frame
    permute = _permutations(pos1)
    qa = permute[a]  # reference axes (ax, ay, a): the face's plane, then its normal
    rows = qa @ rinc
    binc = rows[..., 2, :].abs().argmax(-1)  # the incident axis most aligned with the normal, the first of equals
    qb = permute[binc]  # incident axes (bu, bv, binc)
    sref, sinc = _mat_vec(qa, sizeref), _mat_vec(qb, sizeinc)
    poso = _mat_vec(qa, posoi)
    sgn = torch.where(poso[..., 2] >= 0, 1.0, -1.0).to(poso.dtype)  # the side of the reference face facing the incident box
    m = rows @ qb.transpose(-1, -2)  # m[r, s]: component (ax, ay, a)[r] of incident axis (bu, bv, binc)[s]
    tinc = torch.where(sgn * m[..., 2, 2] > 0, -1.0, 1.0).to(poso.dtype)  # the incident face opposing the normal
    # the incident face's centre and half-edges in (x, y) = (axis ax, axis ay) of the reference
    # face and z = the height over it
    cx = poso + (tinc * sinc[..., 2]).unsqueeze(-1) * m[..., :, 2]
    du, dv = sinc[..., 0, None] * m[..., :, 0], sinc[..., 1, None] * m[..., :, 1]
    up = torch.stack([torch.ones_like(sgn), torch.ones_like(sgn), sgn], dim=-1)
    cx = torch.cat([cx[..., :2], (sgn * cx[..., 2] - sref[..., 2]).unsqueeze(-1)], dim=-1)
    du, dv = du * up, dv * up
    su, sv = (c.unsqueeze(-1) for c in _corner_signs(poso))
    poly = cx.unsqueeze(-2) + su * du.unsqueeze(-2) + sv * dv.unsqueeze(-2)
    poly = torch.cat([poly, torch.zeros_like(poly)], dim=-2)  # the buffer of K = 8
    count = torch.full_like(a, 4)
    for coord, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):
        poly, count = _clip(poly, count, coord, sign, sref[..., coord])
    # vertices within the margin, each dropped if (x, y) is within a rounding radius of an earlier
    # accepted one (clipping at a corner of the reference face repeats it)
    within = (torch.arange(K, device=a.device) < count.unsqueeze(-1)) & (poly[..., 2] <= margin.unsqueeze(-1))
    dx = poly[..., None, :, 0] - poly[..., :, None, 0]  # [.., k, q]
    dy = poly[..., None, :, 1] - poly[..., :, None, 1]
    close = dx * dx + dy * dy < (duplicate * (sref[..., 0] * sref[..., 0] + sref[..., 1] * sref[..., 1]))[..., None, None]
    accepted = within.clone()
    for k in range(1, K):
        accepted[..., k] &= ~(accepted[..., :k] & close[..., k, :k]).any(-1)
    verts, naccept = _compact(poly, accepted)
    found = torch.arange(K, device=a.device) < naccept.unsqueeze(-1)
    height = sgn.unsqueeze(-1) * (sref[..., 2, None] + 0.5 * verts[..., 2])  # midway, along the normal
    local = _mat_vec(qa.transpose(-1, -2).unsqueeze(-3), torch.stack([verts[..., 0], verts[..., 1], height], dim=-1))
    pos = _mat_vec(matref.unsqueeze(-3), local) + posref.unsqueeze(-2)
    normal = torch.where(ref1, sgn, -sgn).unsqueeze(-1) * _mat_vec(matref, qa[..., 2, :])
    return verts[..., 2], pos, normal, found


def box_box(box1: PosedGeoms, box2: PosedGeoms, margin: torch.Tensor) -> PairContacts:
    """MuJoCo's ``mjc_BoxBox``: ``K = 8`` slots per pair, the contacts in MuJoCo's order first
    (one from an edge axis, up to eight from a face axis), ``found`` where MuJoCo has them.

    Args:
        box1: the pairs' first boxes, posed in the world (``size``: the half-sizes).
        box2: the pairs' second boxes, posed in the world.
        margin: ``[P]`` the pairs' margins: boxes separated by more (plus a rounding slack) have no
            contact, and a face's clipped vertices are contacts within it.

    Returns:
        The [`PairContacts`][torchrl_diffenvs.articulated.primitive_types.PairContacts], ``K = 8`` per pair,
        the normals from box 1 towards box 2.
    """
    pos1, mat1, pos2, mat2 = box1.pos, box1.rot, box2.pos, box2.rot
    size1, size2 = box1.size.expand_as(pos1), box2.size.expand_as(pos2)
    sepeps, pareps, sgneps, dupeps = _TOLERANCES.get(pos1.dtype, _SINGLE)
    eye = torch.eye(3, dtype=pos1.dtype, device=pos1.device)
    pos21 = _mat_t_vec(mat1, pos2 - pos1)  # box 2's centre in box 1's frame
    pos12 = _mat_t_vec(mat2, pos1 - pos2)
    rot = (mat1[..., 0, :, None] * mat2[..., 0, None, :] + mat1[..., 1, :, None] * mat2[..., 1, None, :]
           + mat1[..., 2, :, None] * mat2[..., 2, None, :])  # box 2's axes in box 1's frame (mju_mulMatTMat3)
    scale = size1[..., 0] + size1[..., 1] + size1[..., 2] + size2[..., 0] + size2[..., 1] + size2[..., 2]
    septol = margin + sepeps * scale  # the separation tests' rounding slack
    separated, code_face, sep_face, edge, sep_best = _separating_axes(size1, size2, pos21, pos12, rot, septol, pareps)

    # the winning edge pair's axis e_i x d2 (d2: box 2's axis j), normalised as mju_normalize3
    pair = edge.clamp_min(0)
    i, j = pair // 3, pair % 3
    d2 = _take(rot, j.unsqueeze(-1).expand_as(pos21))
    raw = -_take(d2, (i + 2) % 3).unsqueeze(-1) * eye[(i + 1) % 3] + _take(d2, (i + 1) % 3).unsqueeze(-1) * eye[(i + 2) % 3]
    # an edge axis that wins has norm >= sqrt(pareps); the clamp keeps the root's derivative
    # finite where it does not (parallel axes)
    norm = torch.sqrt(_dot3(raw, raw).clamp_min(_MINVAL * _MINVAL))
    axis = raw * (1 / norm).unsqueeze(-1)
    # an edge axis within ~8 degrees of the best face normal gives way to that face unless deeper
    # by 5 % of the face's depth
    face_normal = torch.where((code_face < 3).unsqueeze(-1), eye[code_face.clamp_max(2)],
                              _take(rot, (code_face - 3).clamp_min(0).unsqueeze(-1).expand_as(pos21)))
    face_dot = _dot3(axis, face_normal).abs()
    substitute = (face_dot > 0.99) & (sep_best < sep_face + 0.05 * sep_face.abs() + _MINVAL)
    edge_wins = (edge >= 0) & ~substitute
    axis = torch.where((_dot3(axis, pos21) < 0).unsqueeze(-1), -axis, axis)  # from box 1 towards box 2
    edge_dist, mid = _edge_contact(size1, size2, pos21, rot, i, j, axis, sgneps, eye)
    edge_pos = _mat_vec(mat1, mid) + pos1
    edge_normal = _mat_vec(mat1, axis)

    dist, pos, normal, found = _face_contacts(size1, size2, pos1, pos2, mat1, mat2, pos21, pos12, rot, code_face,
                                              margin, dupeps)
    w = edge_wins.unsqueeze(-1)
    dist = torch.cat([torch.where(edge_wins, edge_dist, dist[..., 0]).unsqueeze(-1), dist[..., 1:]], dim=-1)
    pos = torch.cat([torch.where(w, edge_pos, pos[..., 0, :]).unsqueeze(-2), pos[..., 1:, :]], dim=-2)
    normal = torch.where(w, edge_normal, normal).unsqueeze(-2).expand_as(pos)
    first = torch.where(edge_wins, edge_dist <= septol, found[..., 0])
    found = ~separated.unsqueeze(-1) & torch.cat([first.unsqueeze(-1), found[..., 1:] & ~w], dim=-1)
    return PairContacts(dist, pos, normal, torch.zeros_like(pos), found)
