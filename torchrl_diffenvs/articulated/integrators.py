"""MuJoCo's integrators over [`accelerations`][torchrl_diffenvs.articulated.accelerations]:
semi-implicit Euler (with implicit joint and contact damping), MuJoCo's ``implicit`` (Euler with
the Coriolis and centrifugal forces implicit too) and classic RK4."""
from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from .kinematics import integrate_position
from .pipeline import accelerations, invweight0 as constraint_scales
from .spatial import Params
from .tree import RigidBodyTree

__all__ = ['StepResult', 'eager_step', 'physics_stepper', 'step', 'stepping_with']


class StepResult(NamedTuple):
    """One physics step: the new state, and the state MuJoCo last evaluated (see [`step`][torchrl_diffenvs.articulated.step])."""

    qpos: torch.Tensor
    qvel: torch.Tensor
    eval_qpos: torch.Tensor
    eval_qvel: torch.Tensor
    contact_force: torch.Tensor | None = None  # [N] the largest contact normal force at the evaluated state
    # [N] bool: MuJoCo's constraint solve at the evaluated state converged within the model's iterations
    # (None: no iterative solve, the smooth contact model or no constraints)
    solver_converged: torch.Tensor | None = None


class stepping_with:  # noqa: N801 (a context manager, used as a function)
    """Within ``with stepping_with(tree, stepper):``, [`step`][torchrl_diffenvs.articulated.step] on ``tree`` calls ``stepper``
    (same arguments, same result) instead of `eager_step`: how
    [`compile_physics`][torchrl_diffenvs.compile_physics] runs the articulated tasks, whose env step is
    ``frame_skip`` physics steps, through one compiled physics step reused at every step (a
    graph ``frame_skip`` times smaller than the env step's, and the same graph for every step of
    a chunk). Code being traced by ``torch.compile`` always takes the eager step (no nesting).

    The stepper is the tree's own ``physics_stepper`` attribute while the block runs (``None``
    outside, or the enclosing block's): no state outside the tree.
    """

    def __init__(self, tree: RigidBodyTree, stepper: Callable):
        self.tree, self.stepper = tree, stepper

    def __enter__(self):
        self.previous = physics_stepper(self.tree)
        self.tree.physics_stepper = self.stepper
        return self

    def __exit__(self, *exc):
        self.tree.physics_stepper = self.previous
        return False


def physics_stepper(tree: RigidBodyTree) -> Callable | None:
    """The function that runs ``tree``'s physics steps instead of `eager_step` (set by
    `stepping_with`), or ``None``."""
    return tree.physics_stepper


def step(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, dt: float, integrator: str,
         invweight0=None) -> StepResult:
    """One physics step (`eager_step`, or the stepper `stepping_with` set for ``tree``)."""
    stepper = physics_stepper(tree)
    if stepper is not None and not torch.compiler.is_compiling():
        return stepper(tree, qpos, qvel, ctrl, params, dt, integrator, invweight0)
    return eager_step(tree, qpos, qvel, ctrl, params, dt, integrator, invweight0)


def eager_step(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, dt: float, integrator: str,
               invweight0=None) -> StepResult:
    """One physics step of MuJoCo's ``integrator`` (``"euler"``, ``"implicit"`` or ``"rk4"``).

    Besides the new state, returns the state at which MuJoCo evaluated the forward dynamics last
    (the start state for Euler and implicit, the fourth stage for RK4): after ``mj_step`` MuJoCo's derived
    quantities (body and site positions, constraint forces) belong to that state, and Gymnasium's
    observations and rewards read some of them, the largest contact normal force there
    (``contact_force [N]``, detached; None without contacts) and whether MuJoCo's constraint
    solve there converged (``solver_converged [N]``; None without one). ``invweight0``:
    `invweight0` of ``params``, if the caller has it.
    """
    # the params are the same at every stage: the constraints' regulariser scales are computed once
    # (callers stepping several times with the same params pass them in: see MuJoCoModelEnv.simulate)
    w0 = constraint_scales(tree, params) if invweight0 is None else invweight0
    if integrator in ("euler", "implicit"):
        qacc, report = accelerations(tree, qpos, qvel, ctrl, params, implicit_damping_dt=dt,
                                     implicit_bias=integrator == "implicit", invweight0=w0, with_contact_force=True)
        new_qvel = qvel + dt * qacc
        return StepResult(integrate_position(tree, qpos, new_qvel, dt), new_qvel, qpos, qvel, *report)
    if integrator != "rk4":
        raise ValueError(f"unknown integrator {integrator!r}; valid: 'euler', 'implicit', 'rk4'")
    # MuJoCo's mj_RungeKutta with the classic tableau
    acc1 = accelerations(tree, qpos, qvel, ctrl, params, invweight0=w0)
    vel2 = qvel + 0.5 * dt * acc1
    acc2 = accelerations(tree, integrate_position(tree, qpos, qvel, 0.5 * dt), vel2, ctrl, params, invweight0=w0)
    vel3 = qvel + 0.5 * dt * acc2
    acc3 = accelerations(tree, integrate_position(tree, qpos, vel2, 0.5 * dt), vel3, ctrl, params, invweight0=w0)
    vel4 = qvel + dt * acc3
    pos4 = integrate_position(tree, qpos, vel3, dt)
    acc4, report = accelerations(tree, pos4, vel4, ctrl, params, invweight0=w0, with_contact_force=True)
    new_qpos = integrate_position(tree, qpos, (qvel + 2 * vel2 + 2 * vel3 + vel4) / 6, dt)
    new_qvel = qvel + dt / 6 * (acc1 + 2 * acc2 + 2 * acc3 + acc4)
    return StepResult(new_qpos, new_qvel, pos4, vel4, *report)
