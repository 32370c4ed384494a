"""The forward dynamics in the order the simulator computes them, on one screen:
:func:`accelerations`. Each stage lives in its own module."""
from __future__ import annotations

from typing import NamedTuple

import torch

from .contact import _contact_points_and_forces, _pair_forces, contact_force, pair_contact_force
from .forces import actuator_force, passive_force
from .inertia import dof_invweight0, mass_matrix_and_bias
from .kinematics import forward_kinematics
from .limits import limit_force
from .spatial import Params, _inverse, _solve
from .tree import RigidBodyTree

__all__ = ['accelerations', 'constraint_force']


class SmoothForces(NamedTuple):
    """Every force but the joint limits, at one state."""

    force: torch.Tensor  # [N, nv] motors + passive + contact - bias
    damping: torch.Tensor | None  # [N, nv, nv] their velocity damping (for the implicit Euler), if asked
    largest_contact: torch.Tensor | None  # [N] the largest contact normal force (newtons), None without contacts


def _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=False) -> SmoothForces:
    """Motors + passive forces + contact - bias: every force but the joint limits.

    ``with_damping``: also ``D [N, nv, nv]``, the velocity damping of these forces that the
    implicit Euler integrator uses (joint damping plus the contact's, see :func:`contact_force`).
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

    1. kinematics: body poses and dof motion axes (:mod:`.kinematics`);
    2. inertia and bias: ``M`` and Coriolis, centrifugal and gravity forces (:mod:`.inertia`);
    3. smooth forces: motors, springs, dampers, fluid (:mod:`.forces`) and ground contact
       (:mod:`.contact`);
    4. joint limits: MuJoCo's soft constraints on the unconstrained acceleration (:mod:`.limits`);
    5. solve ``M qacc = force`` (``M + h D`` for the implicit Euler integrator).

    ``implicit_damping_dt = h`` gives the acceleration of MuJoCo's Euler integrator, which solves
    with ``M + h D``: joint damping treated implicitly (MuJoCo), and here the contact's velocity
    damping too (explicit contact friction and damping at MuJoCo's 0.01 s steps would be unstable).
    ``implicit_bias=True`` (with ``implicit_damping_dt``): MuJoCo's ``implicit`` integrator, which
    also treats the Coriolis and centrifugal forces implicitly, ``M + h (D + d bias / d qvel)``
    (:func:`~.inertia.bias_velocity_jacobian`): stable where a light body spins fast, where the
    explicit velocity-product forces pump energy into it.
    ``invweight0``: :func:`dof_invweight0` of ``params`` when the caller has it (computed if not).
    ``with_contact_force``: also return the largest contact normal force ``[N]`` (detached; None
    for a model without contacts), as ``(qacc, largest)``.
    """
    implicit = implicit_damping_dt is not None
    kin = forward_kinematics(tree, qpos)
    mass, bias, *bias_jacobian = mass_matrix_and_bias(tree, kin, qvel, params,
                                                      with_velocity_jacobian=implicit and implicit_bias)
    force, damping, largest = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias, with_damping=implicit)
    if bias_jacobian:
        damping = damping + bias_jacobian[0]  # the force carries -bias: its velocity damping is +d bias / d qvel
    if tree.limit_dof.numel():
        mass_inv = _inverse(mass)
        smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
        invweight0 = dof_invweight0(tree, params) if invweight0 is None else invweight0
        force = force + limit_force(tree, qpos, qvel, smooth_acc, mass_inv, invweight0)
    if implicit:
        mass = mass + implicit_damping_dt * damping
    qacc = _solve(mass, force)
    return (qacc, largest) if with_contact_force else qacc


def constraint_force(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params) -> torch.Tensor:
    """MuJoCo's ``qfrc_constraint [N, nv]`` at a state: the joint-limit forces (contact is a smooth force here)."""
    kin = forward_kinematics(tree, qpos)
    mass, bias = mass_matrix_and_bias(tree, kin, qvel, params)
    force = _smooth_force(tree, kin, qpos, qvel, ctrl, params, bias).force
    mass_inv = _inverse(mass)
    smooth_acc = (mass_inv @ force.unsqueeze(-1)).squeeze(-1)
    return limit_force(tree, qpos, qvel, smooth_acc, mass_inv, dof_invweight0(tree, params))
