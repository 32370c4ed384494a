"""MuJoCo's elliptic friction cones (``<option cone="elliptic">``): a frictional contact's
``condim`` rows (`_elliptic_rows`, ``mj_instantiateContact`` and ``mj_makeImpedance``), the
cone's three-zone cost with its force and Hessian (`_cone_state`, ``mj_constraintUpdate``) and
one Newton round on the primal with it (`_elliptic_round`). The solve that drives the rounds and
carries the implicit gradient is [`solve`][torchrl_diffenvs.articulated.constraint.solve]'s."""
from __future__ import annotations

from typing import NamedTuple

import torch

from .collision import Contacts, ContactSlots
from .limits import _reference
from .spatial import _MINVAL, solve_spd
from .tree import RigidBodyTree

__all__ = ["EllipticCones"]


class EllipticCones(NamedTuple):
    """A block of elliptic-cone contacts of one condim ``d``: ``count`` contacts of ``d`` rows each
    from row ``start`` (the normal, the two tangents, then the spin about the normal and the roll
    about the tangents), with the regularised cone's ``mu [N, count]`` (MuJoCo's ``contact.mu``:
    the sliding friction times ``sqrt(R_1 / R_0)``) and ``friction [N, count, d - 1]`` (the
    contact's friction along each of its friction rows)."""

    start: int
    dim: int
    count: int
    mu: torch.Tensor
    friction: torch.Tensor


def _elliptic_rows(tree: RigidBodyTree, slots: ContactSlots, index: torch.Tensor, frame_jacobian: torch.Tensor,
                   dist, cmargin, qvel, mu, translation, solref, contacts: Contacts, start: int):
    """The rows of elliptic-cone contacts of one condim ``d`` (``mj_instantiateContact``,
    ``mj_makeImpedance``): ``frame_jacobian [N, S, d, nv]`` as they are, the distance and margin on
    the normal row only (0 on the friction rows, whose reference acceleration is damping alone),
    ``R_0`` from the normal's impedance and diagApprox, ``R_1 = R_0 / impratio`` and
    ``R_j = R_1 mu_1^2 / mu_j^2`` on the others. Returns the per-row arrays in the order
    `constraint_rows` gathers them, then their [`EllipticCones`][torchrl_diffenvs.articulated.elliptic.EllipticCones]."""
    n, count, d = frame_jacobian.shape[0], index.numel(), frame_jacobian.shape[2]
    zeros = dist.new_zeros(n, count, d - 1)
    row_pos = torch.cat([dist.unsqueeze(-1), zeros], dim=-1)  # [N, S, d]
    row_margin = torch.cat([cmargin.unsqueeze(-1), cmargin.new_zeros(count, d - 1)], dim=-1)  # [S, d]
    velocity = (frame_jacobian @ qvel[:, None, :, None]).squeeze(-1)  # [N, S, d]
    row_aref, imp = _reference(row_pos, row_margin, velocity, solref[:, :, None], slots.solimp[index, None],
                               tree.model.timestep)
    r0 = ((1 - imp[..., 0]) * translation / imp[..., 0]).clamp_min(_MINVAL)
    r1 = r0 / max(_MINVAL, tree.model.impratio)
    # the contact's friction along its friction rows: sliding twice, then torsional, rolling twice
    friction = torch.cat([mu.unsqueeze(-1).expand(-1, -1, 2),
                          slots.spin_friction[None, index, :d - 3].expand(n, -1, -1)], dim=-1)
    r = torch.cat([r0.unsqueeze(-1), r1.unsqueeze(-1) * (mu.unsqueeze(-1) / friction) ** 2], dim=-1)
    active = contacts.active.index_select(1, index)[:, :, None].expand(-1, -1, d)
    cone = EllipticCones(start, d, count, mu * torch.sqrt(r1 / r0), friction)
    return (frame_jacobian.flatten(1, 2), row_pos.flatten(1), row_margin.flatten(), row_aref.flatten(1), r.flatten(1),
            active.flatten(1), contacts.found.index_select(1, index)[:, :, None].expand(-1, -1, d).flatten(1), cone)


def _cone_state(jar, weight, exists, cones: tuple[EllipticCones, ...], with_hessians: bool = True):
    """MuJoCo's ``mj_constraintUpdate`` with elliptic cones, at row residuals ``jar = J qacc - aref``:
    ``(force [N, R], quadratic [N, R], hessians)``. Rows outside the cones (limits, frictionless
    contacts) are quadratic where ``jar < 0``. A cone maps its rows to ``U = (mu jar_0, mu_j jar_j)``,
    ``N = U_0``, ``T = |U_1..|``, and is in the top zone (``N >= mu T``: no force), the bottom zone
    (``mu N + T <= 0``: every row quadratic) or the middle one, whose cost
    ``D_0 / (mu^2 (1 + mu^2)) (N - mu T)^2 / 2`` is not a sum over rows: its force, and its
    ``[N, S, d, d]`` Hessian in ``hessians`` (one per block, zero outside the middle zone).
    ``quadratic`` holds each quadratic row's weight ``D`` (0 elsewhere). ``with_hessians=False``
    skips the Hessians (an empty list) where only the force is read."""
    quadratic = weight * ((jar < 0) & exists)
    force = -quadratic * jar
    hessians = []
    for cone in cones:
        rows = slice(cone.start, cone.start + cone.count * cone.dim)
        r = jar[:, rows].unflatten(1, (cone.count, cone.dim))
        d = weight[:, rows].unflatten(1, (cone.count, cone.dim))
        present = exists[:, rows].unflatten(1, (cone.count, cone.dim))[..., 0]
        mu, friction = cone.mu, cone.friction
        u = r[..., 1:] * friction  # the friction rows, in the regular cone's space
        normal = r[..., 0] * mu
        t_squared = (u * u).sum(-1)
        tangent = torch.sqrt(t_squared.clamp_min(_MINVAL * _MINVAL))  # clamped inside the root: see primitives._sphere_sphere
        flat = t_squared <= 0
        top = (normal >= mu * tangent) | (flat & (normal >= 0))
        bottom = ~top & ((mu * normal + tangent <= 0) | (flat & (normal < 0)))
        middle = ~top & ~bottom & present
        bottom = bottom & present
        scale = d[..., 0] / (mu * mu * (1 + mu * mu))
        gap = normal - mu * tangent
        f_normal = -scale * gap * mu
        # outside the middle zone T may be ~0: a unit denominator there keeps the unselected
        # branch (and its backward) finite
        safe_tangent = torch.where(middle, tangent, torch.ones_like(tangent))
        unit = u / safe_tangent.unsqueeze(-1)  # the friction direction, |unit| = 1 in the middle zone
        f_friction = -f_normal.unsqueeze(-1) * unit * friction
        cone_force = torch.where(middle.unsqueeze(-1), torch.cat([f_normal.unsqueeze(-1), f_friction], -1),
                                 torch.where(bottom.unsqueeze(-1), -d * r, torch.zeros_like(r)))
        force = torch.cat([force[:, :rows.start], cone_force.flatten(1), force[:, rows.stop:]], dim=1)
        quadratic = torch.cat([quadratic[:, :rows.start], (d * bottom.unsqueeze(-1)).flatten(1),
                               quadratic[:, rows.stop:]], dim=1)
        if not with_hessians:
            continue
        # the middle zone's Hessian in U, (1, -mu/T U'; -mu/T U, mu N/T^3 U U' + (mu^2 - mu N/T) I),
        # then scaled by diag(mu, friction) on both sides and by its D
        # (mu N / T^3) U U' written as (mu N / T) e e', e = U / T: no T^3 to underflow in float32
        first = torch.cat([torch.ones_like(tangent).unsqueeze(-1), -mu.unsqueeze(-1) * unit], -1)
        block = (mu * normal / safe_tangent)[..., None, None] * (unit.unsqueeze(-1) * unit.unsqueeze(-2))
        block = block + ((mu * mu - mu * normal / safe_tangent)[..., None, None]
                         * torch.eye(cone.dim - 1, dtype=r.dtype, device=r.device))
        hessian = torch.cat([first.unsqueeze(-2), torch.cat([first[..., 1:].unsqueeze(-1), block], -1)], -2)
        axes = torch.cat([mu.unsqueeze(-1), friction], -1)
        hessian = hessian * axes.unsqueeze(-1) * axes.unsqueeze(-2) * scale[..., None, None]
        hessians.append(torch.where(middle[..., None, None], hessian, torch.zeros_like(hessian)))
    return force, quadratic, hessians


def _cone_curvature(cones: tuple[EllipticCones, ...], hessians, rows_of):
    """``sum_c x_c' H_c x_c`` over the middle-zone cones, ``x = rows_of`` per row: ``[N, R]`` (a
    direction's ``J d``: the line search's curvature, ``[N]``) or ``[N, R, nv]`` (the Jacobian: the
    Hessian's ``J_c' H_c J_c``, ``[N, nv, nv]``)."""
    total = 0
    for cone, hessian in zip(cones, hessians):
        x = rows_of[:, cone.start:cone.start + cone.count * cone.dim].unflatten(1, (cone.count, cone.dim))
        if x.dim() == 3:
            total = total + (x.unsqueeze(-2) @ hessian @ x.unsqueeze(-1)).flatten(1).sum(-1)
        else:
            total = total + torch.einsum("nsiv,nsij,nsjw->nvw", x, hessian, x)
    return total


def _elliptic_round(qacc, m, smooth, j, w, aref, exists, cones, tolerance: float, line_iterations: int):
    """One Newton step on the primal with elliptic cones: ``(new qacc, converged)``. The
    cost along the direction is convex and twice differentiable but piecewise
    (the cones' zones): the line search is Newton's method on its derivative, kept inside the
    bracket of the minimiser (bisection where a step leaves it)."""
    jt = j.transpose(-1, -2)
    jar = (j @ qacc.unsqueeze(-1)).squeeze(-1) - aref
    force, quadratic, hessians = _cone_state(jar, w, exists, cones)
    gradient = (m @ (qacc - smooth).unsqueeze(-1)).squeeze(-1) - (jt @ force.unsqueeze(-1)).squeeze(-1)
    hessian = m + jt @ (quadratic.unsqueeze(-1) * j) + _cone_curvature(cones, hessians, j)
    direction = -solve_spd(hessian, gradient)
    jd = (j @ direction.unsqueeze(-1)).squeeze(-1)
    md = (m @ direction.unsqueeze(-1)).squeeze(-1)
    slope0, curvature0 = (md * (qacc - smooth)).sum(-1), (md * direction).sum(-1)
    def line_step(index, alpha, low, high):
        f, q, h = _cone_state(jar + alpha.unsqueeze(-1) * jd, w, exists, cones)
        slope = slope0 + alpha * curvature0 - (f * jd).sum(-1)
        curvature = curvature0 + (q * jd * jd).sum(-1) + _cone_curvature(cones, h, jd)
        low, high = torch.where(slope < 0, alpha, low), torch.where(slope >= 0, alpha, high)
        step = alpha - slope / curvature.clamp_min(_MINVAL)
        inside = (step >= low) & (step <= high)
        return index + 1, torch.where(inside, step, torch.where(torch.isfinite(high), (low + high) / 2, 2 * alpha)), \
            low, high

    search = (torch.zeros((), dtype=torch.long, device=qacc.device), torch.ones_like(slope0), torch.zeros_like(slope0),
              torch.full_like(slope0, torch.inf))
    if torch.compiler.is_compiling() and hasattr(torch, "while_loop"):  # traced once, not unrolled
        search = torch.while_loop(lambda index, *_: index < line_iterations, line_step, search)
    else:
        for _ in range(line_iterations):
            search = line_step(*search)
    new = qacc + search[1].unsqueeze(-1) * direction
    jar = (j @ new.unsqueeze(-1)).squeeze(-1) - aref
    force, _, _ = _cone_state(jar, w, exists, cones, with_hessians=False)
    inertial = (m @ (new - smooth).unsqueeze(-1)).squeeze(-1)
    constraint = (jt @ force.unsqueeze(-1)).squeeze(-1)
    size = inertial.norm(dim=-1) + constraint.norm(dim=-1) + _MINVAL
    finite = torch.isfinite(new).all(-1)
    stalled = (new - qacc).norm(dim=-1) <= 100 * torch.finfo(qacc.dtype).eps * (qacc.norm(dim=-1) + 1)
    settled = ((inertial - constraint).norm(dim=-1) <= tolerance * size) | stalled | ~finite
    return torch.where(finite.unsqueeze(-1), new, qacc), settled
