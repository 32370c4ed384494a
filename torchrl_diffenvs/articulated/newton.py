"""Newton's method on MuJoCo's convex primal, without autograd: the search for the active set
(pyramidal cones) that [`solve`][torchrl_diffenvs.articulated.constraint.solve] then solves with
once, differentiably. An exact line search (the cost is piecewise quadratic along a line), rounds
with converged envs held by a mask (no host-device synchronisation), and their drivers, which the
elliptic cones' solve runs its rounds with too: eager rounds, one ``torch.while_loop`` under
``torch.compile``, and on the CPU rounds over the envs and rows that still need them
(`newton_compacted`; `rows_first` also orders the final solve's rows there)."""
from __future__ import annotations

import torch

from . import convergence
from .convergence import ConvergenceWatch
from .spatial import _MINVAL, solve_spd

__all__ = ["active_set", "line_search", "masked_rounds", "newton_compacted", "newton_round", "newton_start",
           "rounds_driver", "rows_first", "while_rounds"]


def line_search(jar, jd, weight, slope0, curvature0):
    """The exact minimiser ``alpha >= 0`` of the cost along a direction: ``f'(alpha) = slope0 +
    alpha curvature0 + sum_i w_i jd_i min(0, jar_i + alpha jd_i)``, piecewise linear and
    increasing. Rows switch at ``t_i = -jar_i / jd_i``; sorted, their running sums give ``f'`` at
    each breakpoint, and the root lies on the piece after the last breakpoint where ``f' < 0``."""
    # rows whose sign changes at some alpha > 0 (a row on the boundary, jar = 0, is inside from 0+
    # on if it moves in and outside if not: it never switches)
    switching = jar * jd < 0
    t = torch.where(switching, -jar / jd, torch.inf)
    active0 = (jar < 0) | ((jar == 0) & (jd < 0))  # the rows inside at alpha = 0+
    wjd = weight * jd
    c1 = curvature0 + (wjd * jd * active0).sum(-1)  # f' = c0 + alpha c1 on the first piece
    c0 = slope0 + (wjd * jar * active0).sum(-1)
    t_sorted, order = t.sort(-1)
    # a switching row enters (moving in) or leaves (moving out) at its t: the coefficients' steps, sorted
    enter = torch.where(jd < 0, wjd, -wjd) * switching
    step1, step0 = (enter * jd).gather(-1, order), (enter * jar).gather(-1, order)
    slope_at = c0.unsqueeze(-1) + step0.cumsum(-1) + t_sorted * (c1.unsqueeze(-1) + step1.cumsum(-1))  # f'(t_k)
    # the breakpoints before the root: a prefix of the sorted ones (f' increases; the cumprod keeps
    # it one where rounding would not)
    passed = (torch.isfinite(t_sorted) & (slope_at < 0)).to(step1.dtype).cumprod(-1)
    a1, a0 = c1 + (step1 * passed).sum(-1), c0 + (step0 * passed).sum(-1)  # f' on the root's piece
    return (-a0 / a1.clamp_min(_MINVAL)).clamp_min(0.0)


def newton_start(qacc, m, smooth, j, w, aref):
    """Newton's state at ``qacc``: ``(qacc, jar = J qacc - aref, inertial = M (qacc - qacc_smooth),
    the cost's gradient)`` (rows that do not exist have weight 0)."""
    jar = (j @ qacc.unsqueeze(-1)).squeeze(-1) - aref
    inertial = (m @ (qacc - smooth).unsqueeze(-1)).squeeze(-1)
    gradient = inertial + (j.transpose(-1, -2) @ (w * (jar < 0) * jar).unsqueeze(-1)).squeeze(-1)
    return qacc, jar, inertial, gradient


def newton_round(state, m, j, w, tolerance: float):
    """One Newton step with the exact line search on the primal from ``state`` (`newton_start`):
    ``(new state, converged)``. Along the step ``jar`` and the inertial term move linearly and are
    updated so, as MuJoCo's solver updates them. Converged: the cost's gradient at the new point is
    below ``tolerance`` relative to the size of its two terms (MuJoCo's test is on a scaled
    gradient; float32 rounding sets a floor)."""
    qacc, jar, inertial, gradient = state
    jt = j.transpose(-1, -2)
    direction = -solve_spd(m + jt @ ((w * (jar < 0)).unsqueeze(-1) * j), gradient)
    jd = (j @ direction.unsqueeze(-1)).squeeze(-1)
    md = (m @ direction.unsqueeze(-1)).squeeze(-1)
    alpha = line_search(jar, jd, w, (direction * inertial).sum(-1), (md * direction).sum(-1)).unsqueeze(-1)
    step = alpha * direction
    jar, inertial = jar + alpha * jd, inertial + alpha * md
    constraint = (jt @ (w * (jar < 0) * jar).unsqueeze(-1)).squeeze(-1)
    new = (qacc + step, jar, inertial, inertial + constraint)
    size = inertial.norm(dim=-1) + constraint.norm(dim=-1) + _MINVAL
    finite = torch.isfinite(new[0]).all(-1)
    # or: the step is down to rounding (float32 can stall above the gradient test's floor)
    stalled = step.norm(dim=-1) <= 100 * torch.finfo(qacc.dtype).eps * (qacc.norm(dim=-1) + 1)
    settled = (new[3].norm(dim=-1) <= tolerance * size) | stalled | ~finite
    return tuple(torch.where(finite.unsqueeze(-1), a, b) for a, b in zip(new, state)), settled


def masked_rounds(round_, start, iterations: int):
    """Newton rounds ``round_(state) -> (new state, settled)`` from the ``start`` state (a tuple of
    ``[N, ..]`` tensors, no autograd), at most ``iterations``, with converged envs held (a mask: no
    host-device synchronisation): ``(state, iterations [N], converged [N])``. They stop once every
    env has converged: on the CPU by reading the flags (free there), on CUDA once the host sees it
    without waiting ([`ConvergenceWatch`][torchrl_diffenvs.articulated.convergence.ConvergenceWatch])."""
    state = start
    converged = torch.zeros(state[0].shape[0], dtype=torch.bool, device=state[0].device)
    used = torch.zeros(state[0].shape[0], dtype=torch.long, device=state[0].device)
    watch = ConvergenceWatch.for_device(state[0].device)
    reads_data = convergence.reads_data_freely(state[0].device)
    for _ in range(iterations):
        new, settled = round_(state)
        state = tuple(torch.where(converged.unsqueeze(-1), a, b) for a, b in zip(state, new))
        used = used + (~converged).long()
        converged = converged | settled
        if (watch is not None and watch.all_done(converged)) or (reads_data and bool(converged.all())):
            break
    return state, used, converged


def while_rounds(round_, start, iterations: int):
    """`masked_rounds` as one ``torch.while_loop`` for ``torch.compile``: the round is traced once
    (an unrolled loop would make a step's graph hundreds of times larger) and the loop ends once
    every env has converged or ``iterations`` rounds have run."""
    n, size = start[0].shape[0], len(start)

    def unfinished(round_index, *carried):
        return (round_index < iterations) & ~carried[-1].all()

    def one_round(round_index, *carried):
        state, used, converged = carried[:size], carried[size], carried[size + 1]
        new, settled = round_(state)
        held = tuple(torch.where(converged.unsqueeze(-1), a, b) for a, b in zip(state, new))
        return (round_index + 1, *held, used + (~converged).long(), converged | settled)

    begin = (torch.zeros((), dtype=torch.long, device=start[0].device), *(x.clone() for x in start),
             torch.zeros(n, dtype=torch.long, device=start[0].device),
             torch.zeros(n, dtype=torch.bool, device=start[0].device))
    carried = torch.while_loop(unfinished, one_round, begin)
    return tuple(carried[1:size + 1]), carried[size + 1], carried[size + 2]


_masked_rounds_outside_the_graph = torch.compiler.disable(masked_rounds)


def rounds_driver(device: torch.device):
    """How Newton's rounds run: eagerly `masked_rounds`; under ``torch.compile`` one
    ``while_loop`` (`while_rounds`), except on CUDA and on a torch without ``torch.while_loop``,
    where they are a graph break (inductor runs a while_loop's condition on the host, a
    synchronisation per round, and leaves it out of CUDA graphs; the eager rounds stop without one)."""
    if not torch.compiler.is_compiling():
        return masked_rounds
    if device.type == "cuda" or not hasattr(torch, "while_loop"):
        return _masked_rounds_outside_the_graph
    return while_rounds


def rows_first(mask):
    """``[N, K]`` each env's row positions with its ``mask`` rows first (in order), ``K`` the
    batch's largest count of them (read on the host: CPU only)."""
    return torch.argsort((~mask).to(torch.int8), dim=-1, stable=True)[:, :int(mask.sum(-1).max())]


def newton_compacted(m, smooth, j, w, aref, exists, iterations: int, tolerance: float):
    """Newton's rounds on the CPU, where reading the data costs nothing: envs without rows keep
    ``qacc_smooth``, the others iterate on their existing rows only (the batch's largest count of
    them), each round on the envs that have not converged yet."""
    n = smooth.shape[0]
    count = exists.sum(-1)
    envs = (count > 0).nonzero().squeeze(-1)
    qacc, used = smooth.clone(), torch.zeros(n, dtype=torch.long, device=smooth.device)
    converged = torch.ones(n, dtype=torch.bool, device=smooth.device)
    if envs.numel() == 0:
        return qacc, used, converged
    # index_select and index_copy_, not x[envs]: advanced indexing is several times slower on the CPU
    of_envs = lambda x: x.index_select(0, envs)  # noqa: E731
    order = rows_first(of_envs(exists))
    rows_of = lambda x: of_envs(x).gather(1, order)  # noqa: E731  (existing rows first)
    args = (of_envs(m), of_envs(j).gather(1, order.unsqueeze(-1).expand(-1, -1, j.shape[-1])), rows_of(w))
    smooth_c = of_envs(smooth)
    state = newton_start(smooth_c.clone(), args[0], smooth_c, args[1], args[2], rows_of(aref))
    left = torch.arange(envs.numel(), device=smooth.device)
    used_c, converged_c = torch.zeros_like(left), torch.zeros_like(left, dtype=torch.bool)
    for _ in range(iterations):
        new, settled = newton_round(tuple(x.index_select(0, left) for x in state),
                                     *(a.index_select(0, left) for a in args), tolerance)
        for x, y in zip(state, new):
            x.index_copy_(0, left, y)
        used_c.index_add_(0, left, torch.ones_like(left))
        converged_c.index_copy_(0, left, settled)
        left = left[~settled]
        if not left.numel():
            break
    return qacc.index_copy(0, envs, state[0]), used.index_copy(0, envs, used_c), converged.index_copy(0, envs, converged_c)


@torch.no_grad()
def active_set(mass, qacc_smooth, jacobian, weight, aref, exists, iterations: int, tolerance: float):
    """The Newton search (no autograd): ``(qacc, iterations, converged, active rows)``: eagerly on
    the CPU on the compacted rows and envs (`newton_compacted`), elsewhere the rounds of
    `rounds_driver`."""
    m, smooth, j, w, ar = mass.detach(), qacc_smooth.detach(), jacobian.detach(), weight.detach(), aref.detach()
    if convergence.reads_data_freely(smooth.device):
        qacc, used, converged = newton_compacted(m, smooth, j, w, ar, exists, iterations, tolerance)
    else:
        state, used, converged = rounds_driver(smooth.device)(
            lambda state: newton_round(state, m, j, w, tolerance), newton_start(smooth, m, smooth, j, w, ar), iterations)
        qacc = state[0]
    active = (((j @ qacc.unsqueeze(-1)).squeeze(-1) - ar) < 0) & exists
    return qacc, used, converged, active
