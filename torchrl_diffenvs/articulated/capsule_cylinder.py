"""Capsule against cylinder, as MuJoCo 4 collides them (``mjc_Convex``: GJK and EPA on the two
shapes grown by half the margin each, then its multi-contact): one contact, or two where the
capsule lies along a cap.

The single contact is the exact solution of the problem GJK and EPA solve: the signed distance
between the capsule's axis and the cylinder less the capsule's radius, along the direction that
minimises it. Where the axis stays outside the cylinder that is its nearest point (a 1-D convex
minimisation: golden section, then a Newton step that also carries the implicit gradient,
`_axis_parameter`); where it enters, the minimal translation that separates them, the minimiser
of the support function of their difference among the directions that can minimise it
(`_segment_cylinder`). Every search runs a fixed number of iterations without gradient, and one
Newton step at its answer carries the derivative: no data-dependent shape, no Python branch on
values.

Where the cylinder's witness is on a cap (or its rim) and the capsule's axis is within 5.09
degrees of the cap's plane, MuJoCo 4 (multi-CCD, on by default) clips the capsule's edge against
the cap's 16-gon and gives each clipped point a contact with the cap's normal and its own depth
(`_cap_contacts`; in MuJoCo 4.0.0 a clipped point left alone is returned twice). That algorithm's
source is not public for 4.0: it was measured against mujoco 4.0.0 (the contact count at every
pose tested, values to its convex collision's tolerance).

Against MuJoCo's convex collision run to 1e-11 the contacts agree to 2e-9 in distance, 2e-5 in the
normal and 5e-7 in position at random poses; MuJoCo's default ``ccd_tolerance`` (1e-6) leaves its
own answer up to ~4e-3 (normal) and ~1e-4 (position) from the exact one in deep contacts. Where the
witness points are not unique (a capsule lying exactly along a face, the single contact) any point
of the overlap is a valid contact and EPA's choice is not reproduced.
"""
from __future__ import annotations

import torch

from .spatial import _MINVAL, _cross, _dot

__all__ = ["capsule_cylinder"]

#: golden-section iterations of the searches: the bracket of the axis parameter shrinks to
#: 2 * 0.618**40 ~ 1e-8 before the Newton step
_GOLDEN_ITERATIONS = 40
_GOLDEN = (5 ** 0.5 - 1) / 2
_TOUCHING = 1e-9  # metres: an axis this close to the cylinder is treated as entering it (see _segment_cylinder)
_EDGE_SAMPLES = 32  # directions across a segment sampled before the golden section (edge against rim)
_EDGE_CANDIDATES = 3  # the best local minima of those samples refined
#: MuJoCo's mjEDGE_TOL: a capsule whose axis is this close to a cap's plane (``|axis . normal|``,
#: the sine of its tilt) lies along the cap, and its contact is clipped against the cap
_EDGE_TOLERANCE = 0.0888
_CAP_SIDES = 16  # the edges of MuJoCo's polygon of a cylinder's cap


def _cylinder_nearest(p, radius, half):
    """The signed distance of points ``p [..., 3]`` (the cylinder's frame) to a cylinder, the nearest
    point of its surface and the outward unit normal there: ``(sdf, q, outward)``. Outside, the
    nearest point is unique (the distance is differentiable); inside, the nearer of the side and
    the caps."""
    x, y, z = p.unbind(-1)
    rho = torch.sqrt((x * x + y * y).clamp_min(_MINVAL * _MINVAL))  # clamped inside the root: see primitives._sphere_sphere
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
    # a shadow shorter than sqrt(eps) of the segment is a point (its t saturates): the floor keeps
    # the quotient's backward finite in float32, where across^2 ~ 1e-29 made it inf * 0
    floor = torch.finfo(start.dtype).eps * _dot(axis, axis)
    along = (-_dot(shadow, across) / torch.maximum(_dot(across, across), floor).clamp_min(tiny)).clamp(-1, 1)
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


def _cap_contacts(start, axis, u, x1, x2, sd, radius1, radius, half, margin):
    """MuJoCo 4's multi-contact of a capsule lying along a cylinder's cap (the cylinder's frame).

    MuJoCo takes it where the cylinder's witness is on a cap or its rim and the capsule's axis is
    within ``asin(_EDGE_TOLERANCE)`` (5.09 degrees) of the cap's plane, and the pair touches. The
    capsule's edge, its segment moved towards the cylinder by its radius plus half the margin along
    ``w = u - (u.a) a`` (``a`` the unit axis; ``w`` is not renormalised, as MuJoCo's), is clipped
    against the cap's 16-gon (radius ``R``, not grown; in the plane ``H + margin / 2``, grown), and
    every clipped point at or below that plane is a contact with the cap's normal and its own depth.
    MuJoCo's clip (``polygonClip``, Sutherland-Hodgman) of a two-point polygon lists each clipped
    end twice and an original end once: one clipped end left alone after pruning comes back as two
    equal contacts (mujoco 4.0.0), an original end as one; none left keeps the single contact.
    The order of two contacts follows the rotation of MuJoCo's clip list and is not reproduced.

    Args:
        start: ``[.., 3]`` the capsule's centre.
        axis: ``[.., 3]`` its half-axis; its segment runs from ``start - axis`` to ``start + axis``.
        u: ``[.., 3]`` the unit direction from the segment to the cylinder (`_segment_cylinder`).
        x1: ``[.., 3]`` the segment's witness point.
        x2: ``[.., 3]`` the cylinder's witness point.
        sd: ``[..]`` the segment's signed distance to the cylinder (not the capsule's).
        radius1: ``[P]`` the capsule's radius.
        radius: ``[P]`` the cylinder's radius.
        half: ``[P]`` the cylinder's half-height.
        margin: ``[P]`` the pair's margin.

    Returns:
        ``(multi [..], dist [.., 2], pos [.., 2, 3], normal [.., 3], has_second [..])``: where the
        multi-contact applies, its contacts (the second meaningful where ``has_second``) and their
        common normal, from the capsule into the cap.
    """
    tiny = _MINVAL * _MINVAL
    eps = torch.finfo(start.dtype).eps
    scale = torch.sqrt(_dot(start, start)) + torch.sqrt(_dot(axis, axis)) + radius + half
    # the cap the cylinder's witness is on: beyond the segment's nearest point outside; sunk, the
    # exit point lies on the cap's plane (to rounding: x2 = x1 - depth u)
    beyond = torch.where(sd > 0, x1[..., 2].abs() > half, x2[..., 2].abs() >= half - 64 * eps * scale)
    side = torch.where(torch.where(sd > 0, x1[..., 2], x2[..., 2]) >= 0, 1.0, -1.0).to(start.dtype)
    a = axis / torch.sqrt(_dot(axis, axis).clamp_min(tiny)).unsqueeze(-1)
    aligned = a[..., 2].abs() < _EDGE_TOLERANCE  # strictly below, as MuJoCo's test
    touching = sd - radius1 < margin  # the single contact exists
    w = u - _dot(u, a).unsqueeze(-1) * a
    edge_start = start - axis + (radius1 + margin / 2).unsqueeze(-1) * w  # the -axis end first, as MuJoCo's
    edge = 2 * axis
    # the 16-gon's vertices at -2 pi k / 16 (the top cap's order, clockwise seen from outside) and
    # each edge's inward normal (edge x z) / |edge|: the bottom cap's polygon is its mirror image in
    # y, the same 16 half-planes, and the clipped segment does not depend on their order
    angle = torch.arange(_CAP_SIDES + 1, dtype=start.dtype, device=start.device) * (-2 * torch.pi / _CAP_SIDES)
    vx, vy = torch.cos(angle), torch.sin(angle)
    ex, ey = vx[1:] - vx[:-1], vy[1:] - vy[:-1]
    length = torch.sqrt(ex * ex + ey * ey)
    nx, ny = ey / length, -ex / length
    r = radius.unsqueeze(-1)
    # Sutherland-Hodgman against convex half-planes, in closed form: the segment's parameters t in
    # [0, 1] inside every half-plane, pn . (Q0 - V) + t pn . D >= 0
    offset = (edge_start[..., :1] - r * vx[:-1]) * nx + (edge_start[..., 1:2] - r * vy[:-1]) * ny  # [.., 16]
    rate = edge[..., :1] * nx + edge[..., 1:2] * ny
    # an edge parallel to a side (to rounding) is inside or out of it whole; the guard also keeps
    # the unselected roots' backward finite
    parallel = rate.abs() <= 16 * eps * torch.sqrt(_dot(edge, edge)).unsqueeze(-1)  # (a near-vertical edge: all)
    root = -offset / torch.where(parallel, 1.0, rate)
    t_lo = torch.where(parallel | (rate < 0), -torch.inf, root).amax(-1).clamp_min(0.0)
    t_hi = torch.where(parallel | (rate > 0), torch.inf, root).amin(-1).clamp_max(1.0)
    crossing = (t_lo <= t_hi) & ~(parallel & (offset < 0)).any(-1)
    # the clip's two points (a clipped one where t_lo > 0 or t_hi < 1), kept in [0, 1] for the
    # slots where the segment misses the polygon (unused there)
    t = torch.stack([t_lo.clamp_max(1.0), t_hi.clamp_min(0.0)], dim=-1)
    clip_points = edge_start.unsqueeze(-2) + t.unsqueeze(-1) * edge.unsqueeze(-2)  # [.., 2, 3]
    height = side.unsqueeze(-1) * clip_points[..., 2] - (half + margin / 2).unsqueeze(-1)  # > 0: pruned
    kept = (height <= 0) & crossing.unsqueeze(-1)
    listed_twice = torch.stack([t_lo > 0, t_hi < 1], dim=-1)  # clipped points
    both = kept.all(-1) & (t_lo < t_hi)
    alone = kept.any(-1) & ~both
    index0 = torch.where(alone & ~kept[..., 0], 1, 0)  # the first contact: the one kept where only one is
    index1 = torch.where(alone, index0, 1)
    index = torch.stack([index0, index1], dim=-1)
    point = clip_points.gather(-2, index.unsqueeze(-1).expand(*index.shape, 3))
    depth = height.gather(-1, index)  # <= 0 where kept
    zero = torch.zeros_like(depth)
    pos = point + torch.stack([zero, zero, -side.unsqueeze(-1) * depth / 2], dim=-1)  # midway to the grown plane
    normal = torch.stack([torch.zeros_like(side), torch.zeros_like(side), -side], dim=-1)
    multi = beyond & aligned & touching & (both | alone)
    has_second = multi & (both | (alone & listed_twice.gather(-1, index0.unsqueeze(-1)).squeeze(-1)))
    return multi, margin.unsqueeze(-1) + depth, pos, normal, has_second


def capsule_cylinder(pos1, half_axis1, radius1, pos2, rot2, size2, margin):
    """A capsule against a cylinder: up to two contacts per pair, ``[N, P, 2, ...]``, normals from
    the capsule to the cylinder (see the module's docstring): MuJoCo 4's multi-contact where the
    capsule lies along a cap (`_cap_contacts`), else the single contact of their convex collision
    (the second slot unused).

    Args:
        pos1: ``[N, P, 3]`` the capsule's centre.
        half_axis1: ``[N, P, 3]`` the capsule's half-axis (from the centre to one end of its segment).
        radius1: ``[P]`` the capsule's radius.
        pos2: ``[N, P, 3]`` the cylinder's centre.
        rot2: ``[N, P, 3, 3]`` the cylinder's orientation (its axis is the third column).
        size2: ``[P, 3]`` the cylinder's size: its radius and half-height first.
        margin: ``[P]`` the pair's margin (MuJoCo's ``includemargin``).

    Returns:
        ``(dist, pos, normal, found)``: the signed distances ``[N, P, 2]`` (negative: penetrating),
        the contact points ``[N, P, 2, 3]`` midway between the surfaces, the unit normals
        ``[N, P, 2, 3]`` from the capsule to the cylinder, and which contacts exist ``[N, P, 2]``:
        the first always (the single contact wherever the multi-contact does not apply), the
        second only where MuJoCo makes two, which is in touch only (a capsule hovering over a cap
        has one contact until it touches, for the contact-gradient modes too).
    """
    to_local = rot2.transpose(-1, -2)
    start = (to_local @ (pos1 - pos2).unsqueeze(-1)).squeeze(-1)
    axis = (to_local @ half_axis1.unsqueeze(-1)).squeeze(-1)
    radius, half = size2[:, 0], size2[:, 1]
    sd, x1, x2, u = _segment_cylinder(start, axis, radius, half)
    middle = (x1 + x2 + radius1.unsqueeze(-1) * u) / 2
    multi, cap_dist, cap_pos, cap_normal, second = _cap_contacts(start, axis, u, x1, x2, sd, radius1, radius, half,
                                                                 margin)
    dist = torch.stack([torch.where(multi, cap_dist[..., 0], sd - radius1), cap_dist[..., 1]], dim=-1)
    local_pos = torch.stack([torch.where(multi.unsqueeze(-1), cap_pos[..., 0, :], middle), cap_pos[..., 1, :]], dim=-2)
    local_normal = torch.stack([torch.where(multi.unsqueeze(-1), cap_normal, u), cap_normal], dim=-2)
    world = lambda v: (rot2.unsqueeze(-3) @ v.unsqueeze(-1)).squeeze(-1)  # noqa: E731
    found = torch.stack([torch.ones_like(multi), second], dim=-1)
    return dist, pos2.unsqueeze(-2) + world(local_pos), world(local_normal), found
