"""MuJoCo's integrators over [`accelerations`][torchrl_diffenvs.articulated.accelerations]:
semi-implicit Euler (with implicit joint and contact damping), MuJoCo's ``implicit`` (Euler with
the Coriolis and centrifugal forces implicit too) and MuJoCo 4's RK4 (the classic tableau, with
the Runge-Kutta-Munthe-Kaas correction of ball and free joint rotations)."""
from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from .kinematics import integrate_position
from .pipeline import SolvedContacts, accelerations, invweight0 as constraint_scales
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
    # MuJoCo's contact model: the contact problem solved at the evaluated state, which cfrc_ext reads
    # (None from compile_physics' compiled physics step, whose graph returns tensors only: the task then
    # solves that state again)
    solved_contacts: SolvedContacts | None = None


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
    """One physics step (`eager_step`, or the stepper `stepping_with` set for ``tree``).

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        ctrl: ``[N, nu]`` controls, held through the step.
        params: the physical parameters, each ``[N, ...]``.
        dt: the step's length (s).
        integrator: ``"euler"``, ``"implicit"`` or ``"rk4"``.
        invweight0: `invweight0` of ``params``, if the caller has it (computed if not).

    Returns:
        A [`StepResult`][torchrl_diffenvs.articulated.StepResult], as `eager_step` returns it.
    """
    stepper = physics_stepper(tree)
    if stepper is not None and not torch.compiler.is_compiling():
        return stepper(tree, qpos, qvel, ctrl, params, dt, integrator, invweight0)
    return eager_step(tree, qpos, qvel, ctrl, params, dt, integrator, invweight0)


def eager_step(tree: RigidBodyTree, qpos, qvel, ctrl, params: Params, dt: float, integrator: str,
               invweight0=None) -> StepResult:
    """One physics step of MuJoCo's ``integrator``.

    Args:
        tree: the model's tensors.
        qpos: ``[N, nq]`` positions.
        qvel: ``[N, nv]`` velocities.
        ctrl: ``[N, nu]`` controls, held through the step.
        params: the physical parameters, each ``[N, ...]``.
        dt: the step's length (s).
        integrator: ``"euler"``, ``"implicit"`` or ``"rk4"``.
        invweight0: `invweight0` of ``params``, if the caller has it (computed if not).

    Returns:
        A [`StepResult`][torchrl_diffenvs.articulated.StepResult]: the new state and the state at
        which MuJoCo evaluated the forward dynamics last (the start state for Euler and implicit,
        the fourth stage for RK4). After ``mj_step`` MuJoCo's derived quantities (body and site
        positions, constraint forces) belong to that state, and Gymnasium's observations and
        rewards read some of them; with them, the largest contact normal force there
        (``contact_force [N]``, detached; None without contacts), whether MuJoCo's constraint
        solve there converged (``solver_converged [N]``; None without one) and the contact problem
        that solve solved (``solved_contacts``, which ``cfrc_ext`` reads).
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
    # MuJoCo 4's mj_RungeKutta: the classic tableau; the velocities that move the positions (not
    # the stage velocities the dynamics see) have their rotations corrected (Munthe-Kaas)
    acc1 = accelerations(tree, qpos, qvel, ctrl, params, invweight0=w0)
    vel2 = qvel + 0.5 * dt * acc1
    acc2 = accelerations(tree, integrate_position(tree, qpos, qvel, 0.5 * dt), vel2, ctrl, params, invweight0=w0)
    turn2 = munthe_kaas(tree, vel2, dt * (0.5 * qvel))
    vel3 = qvel + 0.5 * dt * acc2
    acc3 = accelerations(tree, integrate_position(tree, qpos, turn2, 0.5 * dt), vel3, ctrl, params, invweight0=w0)
    turn3 = munthe_kaas(tree, vel3, dt * (0.5 * turn2))
    vel4 = qvel + dt * acc3
    pos4 = integrate_position(tree, qpos, turn3, dt)
    acc4, report = accelerations(tree, pos4, vel4, ctrl, params, invweight0=w0, with_contact_force=True)
    turn4 = munthe_kaas(tree, vel4, dt * turn3)
    new_qpos = integrate_position(tree, qpos, (qvel + 2 * turn2 + 2 * turn3 + turn4) / 6, dt)
    new_qvel = qvel + dt / 6 * (acc1 + 2 * acc2 + 2 * acc3 + acc4)
    return StepResult(new_qpos, new_qvel, pos4, vel4, *report)


# c(s) of dexp^-1 for s = |theta|^2 < 3.0625: MuJoCo 4's polynomial (1/12 + s/720 + ...), highest power first
_DEXPINV_SERIES = (1.230313397310169e-14, 3.161551550077822e-13, 1.3455485951057888e-11, 5.282849430384459e-10,
                   2.0876900642039142e-08, 8.267194907152073e-07, 3.30687830944332e-05, 0.0013888888888859755,
                   0.08333333333333338)


def munthe_kaas(tree: RigidBodyTree, stage_qvel: torch.Tensor, turned: torch.Tensor) -> torch.Tensor:
    """``stage_qvel [N, nv]`` as MuJoCo 4's RK4 combines it into positions: each ball joint's and
    free joint's angular velocity ``w`` becomes ``dexp^-1_theta(w) = w + theta x w / 2 + c(|theta|)
    theta x (theta x w)``, where ``theta`` is the rotation vector ``turned [N, nv]`` by which the
    stage's orientation was reached. The stage's dynamics keep ``stage_qvel``: the correction makes
    RK4 fourth-order in the orientations (MuJoCo 4's ``mj_RungeKutta``, same operations, same
    order). Hinges and slides (and trees without ball or free joints) are left as they are.
    """
    starts = [segment[2] for segment in tree.position_segments if segment[0] != "linear"]
    if not starts:
        return stage_qvel
    out = stage_qvel.clone()
    for da in starts:
        out[:, da:da + 3] = _dexp_inverse(turned[:, da:da + 3], stage_qvel[:, da:da + 3])
    return out


def _dexp_inverse(theta: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``dexp^-1_theta(w)`` for ``[N, 3]`` rotation vectors, as MuJoCo 4 computes it: ``theta`` past
    pi is first wrapped to its nearest representative; ``c`` is a polynomial in ``|theta|^2``
    below 3.0625, else ``(1 - (t/2) / tan(t/2)) / t^2``."""
    def squared(v):
        return v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2]

    s = squared(theta)
    wraps = s > 9.869604401089358  # pi^2
    t = torch.sqrt(torch.where(wraps, s, 1.0))  # safe values where a branch is not taken: finite gradients
    scale = (torch.floor(t / 6.283185307179586 + 0.5) * -6.283185307179586 + t) / t
    theta = torch.where(wraps[:, None], theta * scale[:, None], theta)
    s = torch.where(wraps, squared(theta), s)
    series = _DEXPINV_SERIES[0] * s
    for coefficient in _DEXPINV_SERIES[1:-1]:
        series = (series + coefficient) * s
    series = series + _DEXPINV_SERIES[-1]
    large = s >= 3.0625
    s_large = torch.where(large, s, 4.0)
    half = 0.5 * torch.sqrt(s_large)
    c = torch.where(large, (1.0 - half / torch.tan(half)) / s_large, series)[:, None]
    u = _cross(theta, w)
    return c * _cross(theta, u) + (0.5 * u + w)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a x b`` of ``[N, 3]`` vectors, each component as MuJoCo writes it (``a_y b_z - a_z b_y``)."""
    return torch.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                        a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], dim=-1)
