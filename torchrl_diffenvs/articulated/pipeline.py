"""The forward dynamics in the order the simulator computes them, on one screen:
[`accelerations`][torchrl_diffenvs.articulated.accelerations]. Each stage lives in its own module.

Two contact models ([`use_contact_model`][torchrl_diffenvs.articulated.RigidBodyTree.use_contact_model]): ``"mujoco"`` (the default), MuJoCo's own pipeline
(collision, constraint rows, the constraint solve: `_constrained_accelerations`), and
``"smooth"``, a penalty force in the smooth forces with the joint limits solved on their own.
"""
from __future__ import annotations

from dataclasses import fields
from typing import NamedTuple

import torch

from .collision import Contacts, ContactSlots, collide, near_pairs
from . import convergence
from .constraint import ConstraintRows, constraint_rows, contact_frame_forces, contact_normal_forces, solve
from .contact_gradient import ContactGradient
from .contact import _contact_points_and_forces, _pair_forces, body_contact_forces, contact_force, pair_contact_force
from .forces import actuator_force, passive_force
from .inertia import body_invweight0, dof_invweight0, mass_matrix_and_bias
from .kinematics import Kinematics, forward_kinematics
from .limits import limit_force
from .spatial import Params, _cross, _inverse, _solve, solve_spd
from .tree import RigidBodyTree

__all__ = ['ForwardReport', 'SolvedContacts', 'accelerations', 'body_contact_wrenches', 'constraint_force', 'invweight0',
           'InvWeight0']

class InvWeight0(NamedTuple):
    """MuJoCo's ``dof_invweight0 [N, nv]`` and ``body_invweight0 [N, nbody, 2]`` for a batch of
    params: the scales of the constraint rows' regularisers, which depend on the params only."""

    dof: torch.Tensor
    body: torch.Tensor | None


def invweight0(tree: RigidBodyTree, params: Params):
    """What [`accelerations`][torchrl_diffenvs.articulated.accelerations] takes as ``invweight0`` for these
    params (None where nothing needs it).

    Args:
        tree: the model's tensors.
        params: the physical parameters, each ``[N, ...]``.
    """
    if tree.contact_model == "mujoco":
        return InvWeight0(dof_invweight0(tree, params), body_invweight0(tree, params) if tree.contact_slots.count else None)
    return dof_invweight0(tree, params) if tree.limit_dof.numel() else None


class SmoothForces(NamedTuple):
    """Every force but the joint limits, at one state."""

    force: torch.Tensor  # [N, nv] motors + passive + contact - bias
    damping: torch.Tensor | None  # [N, nv, nv] their velocity damping (for the implicit Euler), if asked
    largest_contact: torch.Tensor | None  # [N] the largest contact normal force (newtons), None without contacts


def _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=False) -> SmoothForces:
    """Motors + passive forces + contact - bias: every force but the joint limits.

    ``with_damping``: also ``D [N, nv, nv]``, the velocity damping of these forces that the
    implicit Euler integrator uses (joint damping plus the contact's, see `contact_force`).
    """
    force = actuator_force(tree, ctrl, tree.nv) + passive_force(tree, kin, qpos, qvel, params) - bias
    damping = torch.diag_embed(params["damping"]) if with_damping else None
    largest = None
    for touching, forces, generalised in ((tree.contact_body.numel(), _contact_points_and_forces, contact_force),
                                          (tree.pair_body.numel(), _pair_forces, pair_contact_force)):
        if not touching:
            continue
        contacts = forces(tree, kin, qvel, params)
        peak = contacts.normal_force.detach().amax(-1)
        largest = peak if largest is None else torch.maximum(largest, peak)
        contact = generalised(tree, kin, qvel, params, with_damping=with_damping, contacts=contacts)
        if with_damping:
            contact, contact_damping = contact
            damping = damping + contact_damping
        force = force + contact
    return SmoothForces(force, damping, largest)


def accelerations(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, *, implicit_damping_dt=None,
                  implicit_bias=False, invweight0=None, with_contact_force=False):
    """``qacc [N, nv]`` of MuJoCo's forward dynamics: the simulator's pipeline, stage by stage.

    With the tree's ``"mujoco"`` contact model (the default), MuJoCo's own
    (`_constrained_accelerations`):

    1. kinematics: body poses and dof motion axes (`kinematics`);
    2. inertia and bias: ``M`` and Coriolis, centrifugal and gravity forces (`inertia`);
    3. smooth forces: motors, springs, dampers, fluid (`forces`), and ``qacc_smooth``;
    4. collision ([`collision`][torchrl_diffenvs.articulated.collision]), constraint rows of joint limits and contacts, and their
       solve ([`constraint`][torchrl_diffenvs.articulated.constraint]).

    With ``"smooth"``: stages 1-2, the smooth forces with a penalty ground contact
    (`contact`), the joint limits solved on their own (`limits`), then
    ``M qacc = force``.

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        ctrl: ``[N, nu]`` controls.
        params: the physical parameters, each ``[N, ...]``.
        implicit_damping_dt: ``h`` gives the acceleration of MuJoCo's Euler integrator, which
            solves with ``M + h D``: joint damping treated implicitly (MuJoCo), and with the smooth
            contact its velocity damping too (explicit contact friction and damping at 0.01 s
            steps would be unstable).
        implicit_bias: with ``implicit_damping_dt``, MuJoCo's ``implicit`` integrator, which also
            treats the Coriolis and centrifugal forces implicitly, ``M + h (D + d bias / d qvel)``
            (`bias_velocity_jacobian`): stable where a light body spins fast, where the explicit
            velocity-product forces pump energy into it.
        invweight0: `invweight0` of ``params`` when the caller has it (computed if not).
        with_contact_force: also return what ``mjData`` reports of this forward besides ``qacc``.

    Returns:
        ``qacc [N, nv]``; with ``with_contact_force``, ``(qacc, ForwardReport)``: the largest
        contact normal force ``[N]`` (detached; None for a model without contacts), whether
        MuJoCo's constraint solve converged (``[N]`` bool; None for the smooth model, which has no
        iterative solve) and the contact problem it solved
        ([`SolvedContacts`][torchrl_diffenvs.articulated.pipeline.SolvedContacts]; None without one).
    """
    if tree.contact_model == "mujoco":
        if tree.contact_gradient.mode == "penalty":
            return _penalty_gradient_accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt, implicit_bias,
                                                   invweight0, with_contact_force)
        return _constrained_accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt, implicit_bias,
                                          invweight0, with_contact_force)
    return _smooth_accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt, implicit_bias, invweight0,
                                 with_contact_force)


class SolvedContacts(NamedTuple):
    """The contact problem a MuJoCo-contact forward solved, as ``mjData`` keeps it (``contact``,
    ``efc_J``, ``efc_force``): what ``cfrc_ext`` reads (see `body_contact_wrenches`), kept so that
    a task reading it after ``mj_step`` does not solve the same state again."""

    slots: ContactSlots  # the slots the rows were built for
    contacts: Contacts
    rows: ConstraintRows
    force: torch.Tensor  # [N, rows] efc_force


class ForwardReport(NamedTuple):
    """What a forward reports besides ``qacc`` (``accelerations(..., with_contact_force=True)``),
    as ``mjData`` holds it after ``mj_forward``."""

    contact_force: torch.Tensor | None  # [N] the largest contact normal force (detached); None without contacts
    solver_converged: torch.Tensor | None  # [N] bool: the constraint solve converged; None without a solve
    # MuJoCo's contact model: the solved contact problem (None without contacts, or for the smooth model)
    solved_contacts: SolvedContacts | None = None


class _Inertial(NamedTuple):
    """Stages 1-2 at one state, which both of the penalty gradient's forwards read."""

    kin: Kinematics
    mass: torch.Tensor
    bias: torch.Tensor
    bias_jacobian: torch.Tensor | None  # d bias / d qvel, where the implicit integrator asks for it

    def detached(self) -> "_Inertial":
        kin = Kinematics(**{f.name: getattr(self.kin, f.name).detach() for f in fields(self.kin)})
        return _Inertial(kin, self.mass.detach(), self.bias.detach(),
                         None if self.bias_jacobian is None else self.bias_jacobian.detach())


def _inertial(tree: RigidBodyTree, qpos, qvel, params: Params, with_bias_jacobian: bool) -> _Inertial:
    kin = forward_kinematics(tree, qpos)
    mass, bias, *bias_jacobian = mass_matrix_and_bias(tree, kin, qvel, params, with_velocity_jacobian=with_bias_jacobian)
    return _Inertial(kin, mass, bias, bias_jacobian[0] if bias_jacobian else None)


def _smooth_accelerations(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, implicit_damping_dt, implicit_bias,
                          invweight0, with_contact_force, inertial: _Inertial | None = None):
    """The ``"smooth"`` contact model's ``qacc`` (see [`accelerations`][torchrl_diffenvs.articulated.accelerations]);
    ``inertial``: stages 1-2 when the caller has them."""
    implicit = implicit_damping_dt is not None
    if inertial is None:
        inertial = _inertial(tree, qpos, qvel, params, with_bias_jacobian=implicit and implicit_bias)
    kin, mass, bias = inertial.kin, inertial.mass, inertial.bias
    force, damping, largest = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=implicit)
    if implicit and implicit_bias:
        damping = damping + inertial.bias_jacobian  # the force carries -bias: its velocity damping is +d bias / d qvel
    if tree.limit_dof.numel():
        mass_inv = _inverse(mass)
        smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
        if isinstance(invweight0, InvWeight0):  # a MuJoCo-contact caller's (the penalty gradient's surrogate)
            invweight0 = invweight0.dof
        invweight0 = dof_invweight0(tree, params) if invweight0 is None else invweight0
        force = force + limit_force(tree, qpos, qvel, smooth_acc, mass_inv, invweight0)
    if implicit:
        # the velocity damping's bias part is not symmetric: the general solve
        qacc = _solve(mass + implicit_damping_dt * damping, force)
    else:
        qacc = solve_spd(mass, force)
    return (qacc, ForwardReport(largest, None)) if with_contact_force else qacc


def _penalty_gradient_accelerations(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, implicit_damping_dt,
                                    implicit_bias, weights, with_contact_force):
    """MuJoCo's ``qacc`` with the ``"smooth"`` contact model's gradient: the contact gradient mode
    ``"penalty"`` ([`ContactGradient`][torchrl_diffenvs.articulated.contact_gradient.ContactGradient]). Straight through: the value is
    `_constrained_accelerations`' (computed without a graph), to which the penalty model's
    ``qacc`` minus itself detached adds an exact zero and its whole gradient (motors, bias and the
    penalty contact, at MuJoCo's state)."""
    if not torch.is_grad_enabled():  # no graph recorded (evaluation, collection): MuJoCo's forward only
        return _constrained_accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt, implicit_bias,
                                          weights, with_contact_force)
    # stages 1-2 once, with their graph: MuJoCo's forward reads them detached (the same values)
    inertial = _inertial(tree, qpos, qvel, params, with_bias_jacobian=implicit_bias)
    with torch.no_grad():
        exact = _constrained_accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt, implicit_bias,
                                           weights, with_contact_force, inertial.detached())
    # the penalty force's velocity damping (friction and normal) is stiff: implicit at the physics step
    # under every integrator, as the smooth model runs it, else its RK4 stages' Jacobian diverges
    damping_dt = tree.model.timestep if implicit_damping_dt is None else implicit_damping_dt
    surrogate = _smooth_accelerations(tree, qpos, qvel, ctrl, params, damping_dt, implicit_bias, weights, False,
                                      inertial)
    qacc, report = exact if with_contact_force else (exact, None)
    qacc = qacc + (surrogate - surrogate.detach())
    return (qacc, report) if with_contact_force else qacc


class _MuJoCoForward(NamedTuple):
    kin: object
    mass: torch.Tensor
    smooth_force: torch.Tensor
    slots: ContactSlots  # the slots of ``contacts`` and of the rows: the model's, or those the batch needs
    contacts: Contacts | None
    rows: object
    solution: object
    bias_jacobian: torch.Tensor | None


def _mujoco_forward(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, weights, with_bias_jacobian=False,
                    inertial: _Inertial | None = None):
    """MuJoCo's forward to the constraint solve, with its intermediates (see `_constrained_accelerations`);
    ``inertial``: stages 1-2 when the caller has them."""
    slots = tree.contact_slots
    if not isinstance(weights, InvWeight0):  # None, or a smooth-contact caller's dof_invweight0
        weights = invweight0(tree, params)
    if inertial is None:
        inertial = _inertial(tree, qpos, qvel, params, with_bias_jacobian)
    kin, mass, bias = inertial.kin, inertial.mass, inertial.bias
    smooth_force = actuator_force(tree, ctrl, tree.nv) + passive_force(tree, kin, qpos, qvel, params) - bias
    qacc_smooth = solve_spd(mass, smooth_force)
    gradient = tree.contact_gradient if tree.contact_gradient.shapes_solve else ContactGradient()
    compact = slots.count and convergence.reads_data_freely(qpos.device)
    if compact:  # the broad phase: only the pairs near enough to touch in some env
        slots = near_pairs(slots, kin, gradient.reach if torch.is_grad_enabled() else 0.0)
    contacts = collide(slots, kin) if slots.count else None
    if compact:
        slots, contacts = _slots_in_use(slots, contacts, gradient)
    rows = constraint_rows(tree, slots, kin, contacts, qpos, qvel, params, weights.dof, weights.body)
    solution = solve(mass, qacc_smooth, rows, tree.model.iterations, tree.model.tolerance, gradient)
    return _MuJoCoForward(kin, mass, smooth_force, slots, contacts, rows, solution,
                          inertial.bias_jacobian if with_bias_jacobian else None)


def _slots_in_use(slots: ContactSlots, contacts: Contacts, gradient: ContactGradient):
    """The slots whose rows some env of the batch has (a contact, or one the ``cfd`` surrogate
    holds), and their contacts: eagerly on the CPU, where reading the data is free, the rows of
    the others (no force in any env) are not built; usually most slots touch nothing."""
    used = contacts.active
    if torch.is_grad_enabled():
        used = used | gradient.holds_near(contacts.found, contacts.dist - slots.margin)
    index = used.any(0).nonzero().squeeze(-1)
    if index.numel() == slots.count:
        return slots, contacts
    if index.numel() == 0:  # one slot (without a contact) keeps the contact params in the graph: zero gradients
        index = index.new_zeros(1)
    return slots.subset(index), contacts.subset(index)


def body_contact_wrenches(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, about: torch.Tensor,
                          weights=None, solved: SolvedContacts | None = None) -> torch.Tensor:
    """``[N, nbody, 6]`` MuJoCo's ``cfrc_ext`` at a state: the contact wrench on every body
    (torque about ``about``, force; world frame), from the constraint solve's contact forces
    (``"mujoco"``) or the smooth model's (``"smooth"``).

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        ctrl: ``[N, nu]`` controls.
        params: the physical parameters, each ``[N, ...]``.
        about: ``[N, 3]`` the point the torques are taken about.
        weights: `invweight0` of ``params`` when the caller has it (computed if not).
        solved: the contact problem the step already solved at this state (its
            [`StepResult`][torchrl_diffenvs.articulated.StepResult]'s ``solved_contacts``);
            without it the forward runs again.
    """
    if tree.contact_model != "mujoco":
        return body_contact_forces(tree, forward_kinematics(tree, qpos), qvel, params, about=about)
    if tree.contact_gradient.mode == "penalty" and torch.is_grad_enabled():  # MuJoCo's values, the penalty's gradient
        with torch.no_grad():
            exact = _mujoco_body_contact_wrenches(tree, qpos, qvel, ctrl, params, about, weights, solved)
        surrogate = body_contact_forces(tree, forward_kinematics(tree, qpos), qvel, params, about=about)
        return exact + (surrogate - surrogate.detach())
    return _mujoco_body_contact_wrenches(tree, qpos, qvel, ctrl, params, about, weights, solved)


def _mujoco_body_contact_wrenches(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, about, weights, solved):
    out = qvel.new_zeros(qvel.shape[0], tree.nbody, 6)
    if not tree.contact_slots.count:
        return out
    if solved is None:
        f = _mujoco_forward(tree, qpos, qvel, ctrl, params, weights)
        solved = SolvedContacts(f.slots, f.contacts, f.rows, f.solution.force)
    slots, contacts = solved.slots, solved.contacts
    local = contact_frame_forces(slots, solved.rows, solved.force, params["contact_friction"][:, slots.friction_slot])
    # world frame: sum_k f_k frame_k, and the torsional and rolling friction's torque likewise
    force = (local[..., :3].unsqueeze(-2) @ contacts.frame).squeeze(-2)
    torque = (local[..., 3:].unsqueeze(-2) @ contacts.frame).squeeze(-2)
    wrench = torch.cat([_cross(contacts.pos - about.unsqueeze(1), force) + torque, force], dim=-1)  # on geom 2's body
    out = out.index_add(1, slots.body[:, 1], wrench).index_add(1, slots.body[:, 0], -wrench)
    return torch.cat([torch.zeros_like(out[:, :1]), out[:, 1:]], dim=1)  # MuJoCo keeps none on the world


def _constrained_accelerations(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, implicit_damping_dt,
                               implicit_bias, weights, with_contact_force, inertial: _Inertial | None = None):
    """MuJoCo's ``mj_forward`` from the smooth forces on (see [`accelerations`][torchrl_diffenvs.articulated.accelerations]):

    1. smooth dynamics: ``qacc_smooth = M^-1 (motors + passive - bias)``;
    2. collision: the contacts of every geom pair ([`collide`][torchrl_diffenvs.articulated.collision.collide]);
    3. constraint rows: joint limits and contacts, their impedance and reference
       ([`constraint_rows`][torchrl_diffenvs.articulated.constraint.constraint_rows]);
    4. the constraint solve ([`solve`][torchrl_diffenvs.articulated.constraint.solve]): ``qacc``;
    5. MuJoCo's Euler integrator then solves ``(M + h D) qacc = qfrc_smooth + qfrc_constraint``
       (joint damping implicit), and its ``implicit`` integrator adds ``h d bias / d qvel`` to ``D``.
    """
    implicit = implicit_damping_dt is not None
    f = _mujoco_forward(tree, qpos, qvel, ctrl, params, weights, with_bias_jacobian=implicit and implicit_bias,
                        inertial=inertial)
    slots, mass, smooth_force, rows, solution, bias_jacobian = \
        f.slots, f.mass, f.smooth_force, f.rows, f.solution, f.bias_jacobian
    qacc = solution.qacc
    if implicit:
        damping = torch.diag_embed(params["damping"])
        if bias_jacobian is not None:
            damping = damping + bias_jacobian
        constraint = (rows.jacobian.transpose(-1, -2) @ solution.force.unsqueeze(-1)).squeeze(-1)
        qacc = _solve(mass + implicit_damping_dt * damping, smooth_force + constraint)
    if not with_contact_force:
        return qacc
    largest = None
    if slots.count:  # the slots left out carry no force
        largest = contact_normal_forces(slots, rows, solution.force).detach().amax(-1)
    solved = SolvedContacts(slots, f.contacts, rows, solution.force) if slots.count else None
    return qacc, ForwardReport(largest, solution.converged, solved)


def constraint_force(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params) -> torch.Tensor:
    """MuJoCo's ``qfrc_constraint [N, nv]`` at a state: the joint-limit forces (contact is a smooth force here).

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        ctrl: ``[N, nu]`` controls.
        params: the physical parameters, each ``[N, ...]``.
    """
    kin = forward_kinematics(tree, qpos)
    mass, bias = mass_matrix_and_bias(tree, kin, qvel, params)
    force = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias).force
    mass_inv = _inverse(mass)
    smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
    return limit_force(tree, qpos, qvel, smooth_acc, mass_inv, dof_invweight0(tree, params))
