"""MuJoCo's soft constraints: the impedance and reference acceleration of a row (shared by the
constraint rows of `constraint`), and the smooth contact model's joint limits: their
regulariser and the exact complementarity solve of the rows that are active together."""
from __future__ import annotations

import torch

from .convergence import ConvergenceWatch
from .spatial import _MINVAL, _solve
from .tree import RigidBodyTree

__all__ = ['limit_force']


def _impedance(solimp: torch.Tensor, violation: torch.Tensor) -> torch.Tensor:
    """MuJoCo's impedance ``d(r)`` in ``(0, 1)`` (solimp: dmin, dmax, width, midpoint, power)."""
    dmin, dmax, width, mid, power = solimp.unbind(-1)
    x = torch.clamp(violation.abs() / width.clamp(min=_MINVAL), max=1.0)
    low = x.clamp(min=_MINVAL) ** power / mid ** (power - 1)
    high = 1 - (1 - x).clamp(min=_MINVAL) ** power / (1 - mid) ** (power - 1)
    y = torch.where(x <= mid, low, high)
    y = torch.where(x >= 1, torch.ones_like(y), torch.where(x <= 0, torch.zeros_like(y), y))
    imp = dmin + y * (dmax - dmin)
    flat = (dmin == dmax) | (width <= 1e-15)
    return torch.where(flat, (dmin + dmax) / 2, imp)


_MINIMP, _MAXIMP = 0.0001, 0.9999  # MuJoCo's mjMINIMP, mjMAXIMP


def _reference(pos, margin, velocity, solref, solimp, timestep: float):
    """``(aref, imp)`` of rows: MuJoCo's ``aref = -B v - K imp (pos - margin)`` with ``K, B`` from
    ``solref`` (its time constant at least two timesteps: ``refsafe``) and the impedance ``imp``
    from ``solimp`` (`_impedance`), clamped as MuJoCo's ``getsolparam`` does."""
    dmin, dmax, width, mid, power = solimp.unbind(-1)
    solimp = torch.stack([dmin.clamp(_MINIMP, _MAXIMP), dmax.clamp(_MINIMP, _MAXIMP), width.clamp_min(0.0),
                          mid.clamp(_MINIMP, _MAXIMP), power.clamp_min(1.0)], dim=-1)
    imp = _impedance(solimp, pos - margin)
    timeconst, dampratio = solref.unbind(-1)
    dmax = solimp[..., 1]
    standard = timeconst > 0
    timeconst = torch.where(standard, timeconst.clamp_min(2 * timestep), timeconst)
    stiffness = torch.where(standard, 1 / (dmax * dmax * timeconst * timeconst * dampratio * dampratio).clamp_min(_MINVAL),
                            -timeconst / (dmax * dmax).clamp_min(_MINVAL))
    damping = torch.where(dampratio > 0, 2 / (dmax * timeconst).clamp_min(_MINVAL), -dampratio / dmax.clamp_min(_MINVAL))
    return -damping * velocity - stiffness * imp * (pos - margin), imp


def limit_force(tree: RigidBodyTree, qpos, qvel, smooth_acc, mass_inv, invweight0) -> torch.Tensor:
    """``[N, nv]`` joint-limit forces: MuJoCo's soft constraint, one row per active limit side.

    For row ``i`` with distance ``r`` (negative when violated), velocity ``v = J qvel`` and
    unconstrained acceleration ``a0 = J qacc_smooth``: ``aref = -B v - K d(r) (r - margin)``,
    ``R = (1 - d) / d * invweight0`` (`dof_invweight0`); the forces ``f >= 0`` of the active
    rows solve MuJoCo's constraint problem jointly (the rows couple through ``A = J M^-1 J^T``):
    the linear complementarity problem ``w = (A + R) f + (a0 - aref) >= 0``, ``f >= 0``,
    ``f . w = 0``, solved exactly by principal pivoting (a fixed number of rounds, batched), and
    applied as ``J^T f``. With one active row this is ``f = max(0, -(a0 - aref) / (A_ii + R_i))``.
    """
    if tree.limit_dof.numel() == 0:
        return torch.zeros_like(qvel)
    dof, sign = tree.limit_dof, tree.limit_sign
    dist = sign * (qpos[:, tree.dof_qpos[dof]] - tree.limit_value)
    active = dist < tree.limit_margin
    aref, imp = _reference(dist, tree.limit_margin, sign * qvel[:, dof], tree.limit_solref, tree.limit_solimp,
                           tree.model.timestep)
    regulariser = torch.clamp((1 - imp) * invweight0[:, dof] / imp, min=_MINVAL)
    offset = sign * smooth_acc[:, dof] - aref  # a0 - aref
    diagonal = mass_inv.diagonal(dim1=-2, dim2=-1)[:, dof] + regulariser  # of A + R

    def coupling(envs) -> torch.Tensor:  # A + R of these envs (built only where rows couple)
        block = mass_inv[envs][:, dof][:, :, dof]
        return sign[:, None] * sign[None, :] * block + torch.diag_embed(regulariser[envs])

    force = _complementary_forces(offset, active, diagonal, coupling)
    return torch.zeros_like(qvel).index_add(1, dof, sign * force)


def _complementary_forces(offset: torch.Tensor, allowed: torch.Tensor, diagonal: torch.Tensor,
                          matrix_of) -> torch.Tensor:
    """``f >= 0`` with ``w = matrix f + offset >= 0`` and ``f . w = 0`` over the ``allowed`` rows
    (``f = 0`` elsewhere), for a positive definite ``matrix`` ``[N, L, L]`` with ``diagonal``
    ``[N, L]``; ``matrix_of(envs)`` builds the matrices of the envs ``envs`` indexes.

    With at most one allowed row it is ``max(0, -offset / matrix_ii)``; envs with several are
    solved by principal pivoting: each round solves the rows of the current set exactly, then
    flips the first row that breaks the conditions (Murty's least-index rule, which cannot cycle):
    a chosen row with a negative force leaves, an allowed row with a negative ``w`` joins. On the
    CPU only the envs with several allowed rows pivot, until no row breaks; on a GPU every env
    pivots (the others masked) without reading the data on the host.

    Under ``torch.compile`` this runs eagerly (a graph break: the code before and after it
    compiles as two graphs): the data-dependent solve of the few coupled envs costs little there,
    while a fixed-size one (every env pivoting ``2 L`` rounds, an ``L x L`` solve each) made the
    graph of a MuJoCo task's step several times larger and its compiled step 3-4x slower than eager.
    """
    return _complementary_forces_eager(offset, allowed, diagonal, matrix_of)


@torch.compiler.disable
def _complementary_forces_eager(offset, allowed, diagonal, matrix_of, host_reads: bool | None = None) -> torch.Tensor:
    """``host_reads`` (default: on the CPU) picks the envs to pivot by reading the data; without
    (a GPU, where a read waits for the device) every env pivots, those with fewer than two
    allowed rows keeping their single-row force, and the rounds stop early through a
    [`ConvergenceWatch`][torchrl_diffenvs.articulated.convergence.ConvergenceWatch]."""
    single = torch.where(allowed, (-offset / diagonal).clamp(min=0.0), torch.zeros_like(offset))
    coupled = allowed.sum(-1) >= 2
    if host_reads is None:
        host_reads = offset.device.type == "cpu"
    if not host_reads:
        envs = torch.arange(offset.shape[0], device=offset.device)
        solved = _pivot(matrix_of(envs), offset, allowed & coupled.unsqueeze(-1), early_exit=True, host_reads=False)
        return torch.where(coupled.unsqueeze(-1), solved, single)
    if not bool(coupled.any()):
        return single
    envs = coupled.nonzero().squeeze(-1)
    solved = _pivot(matrix_of(envs), offset[envs], allowed[envs], early_exit=True)
    return single.index_put((envs,), solved)


def _pivot(matrix, offset, allowed, early_exit: bool, host_reads: bool = True) -> torch.Tensor:
    """The pivoting of `_complementary_forces`; ``early_exit`` stops once no row breaks the
    conditions in any env (read on the host, or without waiting through a
    [`ConvergenceWatch`][torchrl_diffenvs.articulated.convergence.ConvergenceWatch] when
    ``host_reads`` is False; the rounds after that change nothing)."""
    rows = offset.shape[-1]
    watch = ConvergenceWatch.for_device(offset.device) if early_exit and not host_reads else None
    eye = torch.eye(rows, dtype=matrix.dtype, device=matrix.device)
    index = torch.arange(rows, device=offset.device)

    def solve(chosen):
        both = chosen.unsqueeze(-1) & chosen.unsqueeze(-2)
        reduced = torch.where(both, matrix, eye)  # the chosen block, identity elsewhere
        return _solve(reduced, torch.where(chosen, -offset, torch.zeros_like(offset)))

    chosen = allowed & (offset < 0)  # the rows that push on their own
    for _ in range(2 * rows):
        force = solve(chosen)
        slack = (matrix @ force.unsqueeze(-1)).squeeze(-1) + offset
        broken = (chosen & (force < 0)) | (allowed & ~chosen & (slack < 0))
        if early_exit and host_reads and not bool(broken.any()):
            return torch.where(chosen, force.clamp(min=0.0), torch.zeros_like(offset))
        if watch is not None and watch.all_done(~broken.any(-1)):
            break
        first = broken & (index == torch.where(broken, index, rows).min(-1, keepdim=True).values)
        chosen = chosen ^ first
    return torch.where(chosen, solve(chosen).clamp(min=0.0), torch.zeros_like(offset))
