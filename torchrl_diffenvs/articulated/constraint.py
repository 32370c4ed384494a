"""MuJoCo's constraint stage, batched: the rows of joint limits and contacts in one problem
(``mj_makeConstraint``), their impedance, reference acceleration and regulariser
(``mj_makeImpedance``, ``mj_referenceConstraint``), and the solve (``mj_fwdConstraint``).

Rows are laid out at fixed positions: every limit side, then the pyramid edges of the frictional
contact slots (MuJoCo's default pyramidal cone, ``2 (condim - 1)`` edges ``J_n +- mu_d J_d`` per
contact): four per condim-3 slot (sliding friction along the two tangents), then six per condim-4
slot (and torsional friction: ``J_d`` the relative angular velocity about the normal), then ten
per condim-6 slot (and rolling friction: about the two tangents), then one row per frictionless
(condim 1) slot ([`contact_row_blocks`][torchrl_diffenvs.articulated.constraint.contact_row_blocks]). A model with elliptic cones (``<option cone="elliptic">``) has
``condim`` rows per frictional contact instead, its frame's Jacobian as it is (the normal, the
tangents, the spin and the rolls). A row MuJoCo would not create (a limit not
within its margin, a contact slot without a contact) is kept with ``exists = False`` and no force:
the shapes never depend on the state, on a GPU and under ``torch.compile``. Eagerly on the CPU,
where a host read costs nothing, the pipeline builds the rows of the contact slots some env of
the batch uses only (the rows keep their order: the others' rows carry no force), and the solve
with pyramidal cones drops the rows that exist in no env.

The solve minimises MuJoCo's convex primal over ``qacc``,
``1/2 (qacc - qacc_smooth)' M (qacc - qacc_smooth) + sum_i 1/2 D_i min(0, J_i qacc - aref_i)^2``,
whose unique minimiser is what MuJoCo's Newton solver converges to.
[`solve`][torchrl_diffenvs.articulated.constraint.solve] finds it by Newton's method with an exact
line search (the cost is piecewise quadratic along a line, so the search sorts the rows'
breakpoints) without autograd ([`newton`][torchrl_diffenvs.articulated.newton]), then takes one
differentiable solve with the active set it found: the value is the minimiser, and the gradient
is the implicit gradient of the solution (exact wherever the active set does not change). With elliptic cones the cost has a third
piece per contact, ``D_0 / (mu^2 (1 + mu^2)) (N - mu T)^2 / 2`` in the cone's middle zone
(`elliptic._cone_state`, MuJoCo's ``mj_constraintUpdate``): Newton's method with a line search by Newton
steps finds the minimiser, and one Newton step from it with the Hessian held carries the implicit
gradient (`_solve_elliptic`). Differentiating through the
iterations instead would cost a backward pass per iteration and carry the line search's
breakpoints into the gradient; at the solution, one solve gives the same gradient. Under
``torch.compile`` the Newton search is one ``torch.while_loop``
([`rounds_driver`][torchrl_diffenvs.articulated.newton.rounds_driver]) that ends once every env has
converged: a step compiles into one graph. On CUDA it stays eager (a graph break): inductor reads
a while_loop's condition on the host every round and keeps it out of CUDA graphs, while the eager
rounds stop without a synchronisation.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from .collision import MIN_FRICTION, Contacts, ContactSlots
from .contact_gradient import ContactGradient
from . import convergence
from .elliptic import EllipticCones, _cone_curvature, _cone_state, _elliptic_round, _elliptic_rows
from .kinematics import Kinematics
from .limits import _reference
from .newton import active_set, rounds_driver, rows_first
from .spatial import _MINVAL, Params, _cross, solve_spd, small_matmul, small_matvec
from .tree import RigidBodyTree

__all__ = ["ConstraintRows", "constraint_rows", "contact_frame_forces", "contact_normal_forces", "contact_row_blocks",
           "solve", "SolverResult"]


class ConstraintRows(NamedTuple):
    """MuJoCo's ``efc_*`` arrays ``[N, R]`` at fixed row positions of the slots they were built for
    (see the module docstring)."""

    jacobian: torch.Tensor  # [N, R, nv] efc_J
    pos: torch.Tensor  # [N, R] efc_pos: the distance (a limit's, or the contact's for all its edges)
    margin: torch.Tensor  # [R] efc_margin
    aref: torch.Tensor  # [N, R] efc_aref
    regulariser: torch.Tensor  # [N, R] efc_R
    exists: torch.Tensor  # [N, R] bool: MuJoCo has this row
    found: torch.Tensor  # [N, R] bool: a contact row whose contact is there at any distance (limits: False)
    # (limit rows, frictional contact rows of every condim): where the contact rows start, and the frictionless
    rows_per_slot: tuple[int, int]
    cones: tuple[EllipticCones, ...] = ()  # the elliptic cones' row blocks (none with pyramidal cones)

    @property
    def weight(self) -> torch.Tensor:
        """``efc_D = 1 / efc_R`` where the row exists, 0 elsewhere ``[N, R]``."""
        return torch.where(self.exists, 1.0 / self.regulariser, torch.zeros_like(self.regulariser))


def _contact_frame_jacobian(tree: RigidBodyTree, kin: Kinematics, body1: torch.Tensor, body2: torch.Tensor,
                            point: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
    """``[N, C, 3, nv]`` each dof's velocity of the material point ``point [N, C, 3]`` (world) of
    ``body2 [C]`` relative to that of ``body1 [C]``, along the rows of ``frame [N, C, 3, 3]``
    (normal, tangents): MuJoCo's ``mj_jacDifPair`` rotated into the contact frame."""
    lever = point - kin.origin.unsqueeze(1)  # [N, C, 3]
    # a frame row n sees a dof (angular w, linear v at the origin) move the point at n . (v + w x lever)
    # = (lever x n) . w + n . v: one [3, 6] row block per contact instead of the point's [nv, 3] velocities
    rows = torch.cat([_cross(lever.unsqueeze(2).expand_as(frame), frame), frame], dim=-1)  # [N, C, 3, 6]
    mask = tree.body_dof_mask[body2] - tree.body_dof_mask[body1]  # [C, nv]: +1 body2's dofs, -1 body1's
    jacobian = small_matmul(rows.flatten(1, 2), kin.motion.transpose(-1, -2)).unflatten(1, rows.shape[1:3])
    return jacobian * mask.unsqueeze(-2)


def _rows_per_contact(condim: int, cone: str = "pyramidal") -> int:
    """A contact's constraint rows: its pyramid's ``2 (condim - 1)`` edges, an elliptic cone's
    ``condim`` rows, or the normal alone (condim 1)."""
    if condim == 1 or cone == "elliptic":
        return condim
    return 2 * (condim - 1)


def _angular_jacobian(tree: RigidBodyTree, kin: Kinematics, body1: torch.Tensor, body2: torch.Tensor) -> torch.Tensor:
    """``[N, S, nv, 3]`` each dof's angular velocity of ``body2 [S]`` relative to ``body1 [S]`` (world)."""
    angular = kin.motion[..., :3].unsqueeze(1)  # [N, 1, nv, 3]
    return angular * (tree.body_dof_mask[body2] - tree.body_dof_mask[body1]).unsqueeze(-1)


def constraint_rows(tree: RigidBodyTree, slots: ContactSlots, kin: Kinematics, contacts: Contacts, qpos, qvel,
                    params: Params, dof_weight: torch.Tensor, body_weight: torch.Tensor) -> ConstraintRows:
    """The constraint rows at a state: joint limits, then contacts (pyramidal or elliptic cones, the
    model's; the layout is the module docstring's).

    Args:
        tree: the model's tensors.
        slots: the model's contact slots (those ``contacts`` were collided for).
        kin: the bodies' [`Kinematics`][torchrl_diffenvs.articulated.Kinematics] at the state.
        contacts: the slots' [`Contacts`][torchrl_diffenvs.articulated.collision.Contacts] at the state.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        params: the physical parameters, each ``[N, ...]``.
        dof_weight: ``[N, nv]`` MuJoCo's ``dof_invweight0`` for these params (`dof_invweight0`),
            a scale of the regularisers (``mj_diagApprox``).
        body_weight: ``[N, nbody, 2]`` MuJoCo's ``body_invweight0`` for these params
            (`body_invweight0`), a scale of the regularisers (``mj_diagApprox``).
    """
    timestep = tree.model.timestep
    n, nv = qpos.shape[0], tree.nv
    dtype = qpos.dtype
    jac, pos, margin, aref, reg, exists, found, cones = [], [], [], [], [], [], [], []
    # joint limits: one row per side, J = +-1 on its dof
    if tree.limit_dof.numel():
        dof, sign = tree.limit_dof, tree.limit_sign
        dist = sign * (qpos[:, tree.dof_qpos[dof]] - tree.limit_value)
        velocity = sign * qvel[:, dof]
        row_aref, imp = _reference(dist, tree.limit_margin, velocity, tree.limit_solref, tree.limit_solimp, timestep)
        jac.append((sign[:, None] * torch.nn.functional.one_hot(dof, nv).to(dtype)).expand(n, -1, -1))
        pos.append(dist)
        margin.append(tree.limit_margin)
        aref.append(row_aref)
        reg.append(((1 - imp) * dof_weight[:, dof] / imp).clamp_min(_MINVAL))
        exists.append(dist < tree.limit_margin)
        found.append(torch.zeros_like(exists[-1]))
    limit_rows = sum(p.shape[-1] for p in pos)
    pyramid_rows = 0
    if slots.count:
        body1, body2 = slots.body[:, 0], slots.body[:, 1]
        in_frame = _contact_frame_jacobian(tree, kin, body1, body2, contacts.pos, contacts.frame)  # [N, C, 3, nv]
        translation = body_weight[:, body1, 0] + body_weight[:, body2, 0]  # [N, C]
        # [N, C]; at least MuJoCo's mjMINMU, as mj_assignFriction clamps it
        mu = params["contact_friction"][:, slots.friction_slot].clamp_min(MIN_FRICTION)
        # [N or 1, C, 2]: each env's time constant and damping ratio of its pair, or the model's
        solref = params["contact_solref"][:, slots.friction_slot] if "contact_solref" in params else slots.solref[None]
        for condim, index in (*slots.frictional(), (1, slots.normal_index)):
            if not index.numel():
                continue
            # index_select, not x[:, index]: advanced indexing is several times slower on the CPU
            c = in_frame.index_select(1, index)
            dist, cmargin = contacts.dist.index_select(1, index), slots.margin[index]
            slot_mu, slot_translation = mu.index_select(1, index), translation.index_select(1, index)
            if condim > 3:  # torsional (and rolling): the relative angular velocity about the normal (and tangents)
                spin = contacts.frame[:, index, :condim - 3] @ _angular_jacobian(tree, kin, body1[index],
                                                                                 body2[index]).transpose(-1, -2)
                c = torch.cat([c, spin], dim=2)  # [N, S, condim, nv]
            if condim > 1 and slots.cone == "elliptic":
                block = _elliptic_rows(tree, slots, index, c, dist, cmargin, qvel, slot_mu, slot_translation,
                                       solref.index_select(1, index), contacts, start=sum(p.shape[-1] for p in pos))
                for out, value in zip((jac, pos, margin, aref, reg, exists, found), block[:-1]):
                    out.append(value)
                cones.append(block[-1])
                pyramid_rows += condim * index.numel()
                continue
            if condim > 1:
                m = slot_mu[:, :, None, None]  # the sliding friction, on both tangents
                normal, directions = c[:, :, :1], c[:, :, 1:]
                if condim > 3:
                    m = torch.cat([m.expand(-1, -1, 2, -1),
                                   slots.spin_friction[None, index, :condim - 3, None].expand(n, -1, -1, -1)], dim=2)
                # MuJoCo's edge pairs J_n +- mu_d J_d, d = t1 t2 (then the normal's spin, the tangents' roll)
                # (d1+, d1-, d2+, ...): one broadcast op, several times faster than stacking the two signs
                # (1, -1) made on the device: a tensor built from Python numbers is a host-to-device copy,
                # which synchronises on CUDA
                plus_minus = 1 - 2 * torch.arange(2, dtype=c.dtype, device=c.device).unsqueeze(-1)
                edges = (normal.unsqueeze(3) + plus_minus * (m * directions).unsqueeze(3)).flatten(2, 3)
                rows = _rows_per_contact(condim)
                # diagApprox of the first edge, R from it, and MuJoCo's common pyramid R = 2 mu^2 R / impratio
                diag = slot_translation * (1 + slot_mu ** 2)
            else:
                edges, rows = c[:, :, :1], 1
                diag = slot_translation
            velocity = small_matvec(edges, qvel[:, None, :])  # [N, S, rows]
            row_aref, imp = _reference(dist.unsqueeze(-1), cmargin[:, None], velocity, solref.index_select(1, index)[:, :, None],
                                       slots.solimp[index, None], timestep)
            r = ((1 - imp[..., 0]) * diag / imp[..., 0]).clamp_min(_MINVAL)
            if condim > 1:
                r = 2 * slot_mu ** 2 * r / tree.model.impratio
            jac.append(edges.flatten(1, 2))
            pos.append(dist.repeat_interleave(rows, dim=1))
            margin.append(cmargin.repeat_interleave(rows))
            aref.append(row_aref.flatten(1))
            reg.append(r.repeat_interleave(rows, dim=1))
            exists.append(contacts.active.index_select(1, index).repeat_interleave(rows, dim=1))
            found.append(contacts.found.index_select(1, index).repeat_interleave(rows, dim=1))
            if condim > 1:
                pyramid_rows += rows * index.numel()
    if not jac:
        empty = qvel.new_zeros(n, 0)
        return ConstraintRows(qvel.new_zeros(n, 0, nv), empty, qvel.new_zeros(0), empty, empty,
                              empty.bool(), empty.bool(), (0, 0))
    return ConstraintRows(torch.cat(jac, 1), torch.cat(pos, 1), torch.cat(margin), torch.cat(aref, 1),
                          torch.cat(reg, 1), torch.cat(exists, 1), torch.cat(found, 1), (limit_rows, pyramid_rows),
                          tuple(cones))


class SolverResult(NamedTuple):
    """What the constraint solve returns for a batch of envs with ``R`` rows."""

    qacc: torch.Tensor  # [N, nv]
    force: torch.Tensor  # [N, R] efc_force
    active: torch.Tensor  # [N, R] bool: the rows pushing at the solution
    iterations: torch.Tensor  # [N] Newton iterations until the active set settled
    converged: torch.Tensor  # [N] bool


def _surrogate_share(gradient: ContactGradient, jacobian, aref, exists, found, pos, margin, regulariser, active, qacc):
    """The share ``[N, R]`` in ``[0, 1]`` of each row's weight ``1 / R`` in the surrogate solve of a
    gradient mode (detached: the weights keep their own gradient, as the exact solve's do)."""
    with torch.no_grad():
        if gradient.mode == "cfd":
            beyond = (pos - margin) / gradient.distance
            near = gradient.holds_near(found, pos - margin) & ~exists
            fade = torch.where(exists, torch.ones_like(beyond), (1 - beyond).clamp(0, 1))
            return fade * (active | near)
        residual = (jacobian @ qacc.unsqueeze(-1)).squeeze(-1) - aref  # J qacc - aref at the solution
        hypothetical = torch.where(exists, -residual / regulariser, torch.zeros_like(residual))  # the force if active
        largest = hypothetical.abs().amax(-1, keepdim=True) if hypothetical.shape[-1] else hypothetical.new_ones(1)
        scale = largest.clamp_min(_MINVAL) * gradient.softness
        return exists * torch.sigmoid(hypothetical / scale)


def _solve_with(mass, qacc_smooth, jacobian, aref, row_weight):
    """The solve with fixed row weights: ``(M + J' W J) qacc = M qacc_smooth + J' W aref``, and the
    rows' forces ``-W (J qacc - aref)``. On the CPU (reading the data is free) the products run
    over each env's rows of nonzero weight only, which add all there is: the Ant's are ~3 of 60."""
    if convergence.reads_data_freely(row_weight.device) and row_weight.shape[-1]:
        order = rows_first(row_weight != 0)
        if order.shape[1] < row_weight.shape[-1]:
            qacc, force = _solve_with_rows(mass, qacc_smooth, jacobian.gather(1, order.unsqueeze(-1).expand(
                -1, -1, jacobian.shape[-1])), aref.gather(1, order), row_weight.gather(1, order))
            return qacc, force.new_zeros(aref.shape).scatter(1, order, force)
    return _solve_with_rows(mass, qacc_smooth, jacobian, aref, row_weight)


def _solve_with_rows(mass, qacc_smooth, jacobian, aref, row_weight):
    """`_solve_with` over all the rows given."""
    jt = jacobian.transpose(-1, -2)
    hessian = mass + jt @ (row_weight.unsqueeze(-1) * jacobian)
    rhs = (mass @ qacc_smooth.unsqueeze(-1)).squeeze(-1) + (jt @ (row_weight * aref).unsqueeze(-1)).squeeze(-1)
    qacc = solve_spd(hessian, rhs)
    return qacc, -row_weight * ((jacobian @ qacc.unsqueeze(-1)).squeeze(-1) - aref)


#: the line search's Newton iterations in the elliptic solve (quadratic convergence once bracketed)
_ELLIPTIC_LINE_ITERATIONS = 20


@torch.no_grad()
def _elliptic_minimiser(mass, qacc_smooth, jacobian, weight, aref, exists, cones, iterations: int,
                        tolerance: float):
    """The minimiser of the primal with elliptic cones (no autograd), by the rounds of
    [`rounds_driver`][torchrl_diffenvs.articulated.newton.rounds_driver]: ``(qacc, iterations, converged)``."""
    m, smooth, j, w, ar = mass.detach(), qacc_smooth.detach(), jacobian.detach(), weight.detach(), aref.detach()
    cones = tuple(c._replace(mu=c.mu.detach(), friction=c.friction.detach()) for c in cones)
    def one_round(state):
        new, settled = _elliptic_round(state[0], m, smooth, j, w, ar, exists, cones, tolerance, _ELLIPTIC_LINE_ITERATIONS)
        return (new,), settled

    (qacc,), used, converged = rounds_driver(smooth.device)(one_round, (smooth,), iterations)
    return qacc, used, converged


def _solve_elliptic(mass, qacc_smooth, rows: ConstraintRows, iterations: int, tolerance: float) -> SolverResult:
    """The solve with elliptic cones: Newton's method finds the minimiser ``qacc*`` without
    autograd, then one Newton step from it with the Hessian held, ``qacc* - H^-1 g(qacc*)``, gives
    the value (``g`` is below the tolerance there) and the implicit gradient of the solution,
    ``-H^-1 dg``: the cones' middle zone makes the cost non-quadratic, so no fixed row weights
    reproduce the solution as with pyramidal cones."""
    weight = rows.weight
    found, used, converged = _elliptic_minimiser(mass, qacc_smooth, rows.jacobian, weight, rows.aref, rows.exists,
                                                 rows.cones, iterations, tolerance)
    jt = rows.jacobian.transpose(-1, -2)
    with torch.no_grad():
        jar = (rows.jacobian.detach() @ found.unsqueeze(-1)).squeeze(-1) - rows.aref.detach()
        held = tuple(c._replace(mu=c.mu.detach(), friction=c.friction.detach()) for c in rows.cones)
        _, quadratic, hessians = _cone_state(jar, weight.detach(), rows.exists, held)
        j = rows.jacobian.detach()
        hessian = mass.detach() + j.transpose(-1, -2) @ (quadratic.unsqueeze(-1) * j) + _cone_curvature(held, hessians, j)
    jar = (rows.jacobian @ found.unsqueeze(-1)).squeeze(-1) - rows.aref
    force, _, _ = _cone_state(jar, weight, rows.exists, rows.cones, with_hessians=False)
    gradient = (mass @ (found - qacc_smooth).unsqueeze(-1)).squeeze(-1) - (jt @ force.unsqueeze(-1)).squeeze(-1)
    qacc = found - solve_spd(hessian, gradient)
    jar = (rows.jacobian @ qacc.unsqueeze(-1)).squeeze(-1) - rows.aref
    force, _, _ = _cone_state(jar, weight, rows.exists, rows.cones, with_hessians=False)
    return SolverResult(qacc, force, (force != 0) & rows.exists, used, converged)


def solve(mass: torch.Tensor, qacc_smooth: torch.Tensor, rows: ConstraintRows, iterations: int,
          tolerance: float = 1e-8, gradient: ContactGradient = ContactGradient()) -> SolverResult:
    """The constrained acceleration (see the module docstring): at most ``iterations`` Newton
    steps find the active set; a differentiable solve with it gives ``qacc``.

    An env has converged once its cost's gradient is below ``tolerance`` relative to the size of
    its terms (at least ``1000 eps`` of the dtype). On the CPU the iterations stop once every env
    has; on other devices converged envs are held by a mask (no host-device synchronisation), and
    on CUDA the host stops issuing rounds once it sees, without waiting, that every env has
    converged ([`ConvergenceWatch`][torchrl_diffenvs.articulated.convergence.ConvergenceWatch]).

    Args:
        mass: ``[N, nv, nv]`` the mass matrix ``M``.
        qacc_smooth: ``[N, nv]`` the unconstrained acceleration ``qacc_smooth``.
        rows: the constraint rows ([`constraint_rows`][torchrl_diffenvs.articulated.constraint.constraint_rows]).
        iterations: the most Newton steps.
        tolerance: an env has converged once its cost's gradient is below it, relative to the size
            of its terms (at least ``1000 eps`` of the dtype).
        gradient: how the backward differentiates the solve
            ([`ContactGradient`][torchrl_diffenvs.articulated.contact_gradient.ContactGradient]; the values are
            the same in every mode).

    Returns:
        A [`SolverResult`][torchrl_diffenvs.articulated.constraint.SolverResult]: ``qacc`` and the rows' forces.
    """
    tolerance = max(tolerance, 1000 * torch.finfo(mass.dtype).eps)
    if rows.jacobian.shape[1] == 0:
        empty = qacc_smooth.new_zeros(qacc_smooth.shape[0], 0)
        done = torch.ones(qacc_smooth.shape[0], dtype=torch.bool, device=qacc_smooth.device)
        return SolverResult(qacc_smooth, empty, empty.bool(), torch.zeros_like(done, dtype=torch.long), done)
    if rows.cones:
        if gradient.mode != "exact":
            raise ValueError(f"contact_gradient={gradient.mode!r} shapes the solve of pyramidal friction cones only; "
                             "with elliptic cones valid: 'exact', 'penalty'")
        return _solve_elliptic(mass, qacc_smooth, rows, iterations, tolerance)
    compact = convergence.reads_data_freely(qacc_smooth.device)

    def rows_where(needed, *arrays):
        """``arrays`` (per row), on the CPU without the rows needed in no env of the batch (a host
        read costs nothing there), and the kept positions (None: all)."""
        if not compact:
            return arrays, None
        keep = needed.any(0).nonzero().squeeze(-1)
        return tuple(a.index_select(1, keep) for a in arrays), keep

    def full(x, keep):  # back to the fixed row positions
        return x if keep is None else x.new_zeros(rows.aref.shape).index_copy(1, keep, x)

    (jacobian, aref, exists, weight), keep = rows_where(rows.exists, rows.jacobian, rows.aref, rows.exists, rows.weight)
    qacc, used, converged, active = active_set(mass, qacc_smooth, jacobian, weight, aref, exists, iterations,
                                                tolerance)
    # one differentiable solve with the active set: the value, and in the exact mode the gradient
    aw = weight * active
    if gradient.mode == "exact" or not torch.is_grad_enabled():  # no graph recorded: no surrogate to build
        qacc, force = _solve_with(mass, qacc_smooth, jacobian, aref, aw)
        return SolverResult(qacc, full(force, keep), full(active, keep), used, converged)
    with torch.no_grad():
        qacc, force = _solve_with(mass, qacc_smooth, jacobian, aref, aw)
    force, active = full(force, keep), full(active, keep)
    # the surrogate, on the rows its mode needs: the exact solve's value with its gradient (straight through)
    needed = rows.exists | gradient.holds_near(rows.found, rows.pos - rows.margin)
    (jacobian, aref, exists, found, pos, margin, reg), keep = rows_where(
        needed, rows.jacobian, rows.aref, rows.exists, rows.found, rows.pos, rows.margin.expand_as(rows.pos),
        rows.regulariser)
    share = _surrogate_share(gradient, jacobian, aref, exists, found, pos, margin, reg,
                             active if keep is None else active[:, keep], qacc)
    qacc_s, force_s = _solve_with(mass, qacc_smooth, jacobian, aref, share / reg)
    qacc = qacc + (qacc_s - qacc_s.detach())
    force = force + full(force_s - force_s.detach(), keep)
    return SolverResult(qacc, force, active, used, converged)


def contact_row_blocks(slots: ContactSlots, rows: ConstraintRows) -> list[tuple[int, torch.Tensor, int]]:
    """Where each condim's contact rows lie: ``(condim, slots [S] long, first row)``, each slot
    taking ``2 (condim - 1)`` consecutive rows (its pyramid's edges), ``condim`` with elliptic
    cones, or 1 for condim 1 (see the module docstring); condims without slots are left out.

    Args:
        slots: the contact slots the rows were built for.
        rows: the constraint rows ([`constraint_rows`][torchrl_diffenvs.articulated.constraint.constraint_rows]).
    """
    out, start = [], rows.rows_per_slot[0]
    for condim, index in (*slots.frictional(), (1, slots.normal_index)):
        if index.numel():
            out.append((condim, index, start))
            start += _rows_per_contact(condim, slots.cone) * index.numel()
    return out


def contact_normal_forces(slots: ContactSlots, rows: ConstraintRows, force: torch.Tensor) -> torch.Tensor:
    """``[N, C]`` each contact slot's normal force (the sum of its pyramid's edge forces, an
    elliptic cone's normal row).

    Args:
        slots: the contact slots the rows were built for.
        rows: the constraint rows.
        force: ``[N, R]`` the rows' forces (``efc_force``, the solve's ``force``).
    """
    out = force.new_zeros(force.shape[0], slots.count)
    for condim, index, start in contact_row_blocks(slots, rows):
        edges = _rows_per_contact(condim, slots.cone)
        block = force[:, start:start + edges * index.numel()].unflatten(1, (-1, edges))
        out = out.index_copy(1, index, block[..., 0] if slots.cone == "elliptic" else block.sum(-1))
    return out


def contact_frame_forces(slots: ContactSlots, rows: ConstraintRows, force: torch.Tensor, friction: torch.Tensor) -> torch.Tensor:
    """``[N, C, 6]`` each contact slot's force and torque in its frame, MuJoCo's
    ``mj_contactForce``: the force along the normal and the two tangents, then the torque about
    the normal (torsional friction, condim 4 and 6) and the two tangents (rolling friction, condim
    6). A pyramid's normal force is the sum of its edges', its friction in direction ``d`` is
    ``mu_d (f_{+d} - f_{-d})``; an elliptic cone's rows are these forces.

    Args:
        slots: the contact slots the rows were built for.
        rows: the constraint rows.
        force: ``[N, R]`` the rows' forces (``efc_force``, the solve's ``force``).
        friction: ``[N, C]`` each slot's sliding ``mu`` (the torsional and rolling ones are the
            model's, ``slots.spin_friction``).
    """
    out = force.new_zeros(force.shape[0], slots.count, 6)
    for condim, index, start in contact_row_blocks(slots, rows):
        if condim == 1 or slots.cone == "elliptic":
            local = force[:, start:start + condim * index.numel()].unflatten(1, (-1, condim))
            out = out.index_copy(1, index, torch.cat([local, local.new_zeros(*local.shape[:-1], 6 - condim)], -1))
            continue
        edges = force[:, start:start + 2 * (condim - 1) * index.numel()].unflatten(1, (-1, condim - 1, 2))  # [N, S, d, +-]
        mu = friction[:, index, None].clamp_min(MIN_FRICTION).expand(-1, -1, 2)  # as the rows' (mj_assignFriction)
        if condim > 3:
            mu = torch.cat([mu, slots.spin_friction[None, index, :condim - 3].expand(mu.shape[0], -1, -1)], -1)
        local = torch.cat([edges.sum((-1, -2)).unsqueeze(-1), mu * (edges[..., 0] - edges[..., 1])], dim=-1)
        out = out.index_copy(1, index, torch.cat([local, local.new_zeros(*local.shape[:-1], 6 - condim)], -1))
    return out
