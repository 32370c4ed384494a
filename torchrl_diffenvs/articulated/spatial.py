"""Spatial and linear algebra for the articulated core: 3-vector and 6-vector (angular, linear)
cross products, quaternions, the products of small blocks (as each device runs them fastest),
and the batched solves.

Spatial vectors are ``[.., 6]`` tensors, angular part first, in world axes about a reference point
(see [`Kinematics`][torchrl_diffenvs.articulated.Kinematics]).
"""
from __future__ import annotations

import math
from collections.abc import Mapping

import torch

__all__ = ['cross_motion', 'cross_force', 'quaternion_to_matrix', 'integrate_quaternion', 'small_matmul', 'small_matvec',
           'solve_spd']


Params = Mapping[str, torch.Tensor]
_MINVAL = 1e-15  # MuJoCo's mjMINVAL


# The _ex variants do not raise on a singular matrix (they return inf/nan for that env only): one
# diverged env of a batch must not take the others, or the run, down with it; the env base class
# flags and resets it.
def _solve(matrix: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    return torch.linalg.solve_ex(matrix, rhs)[0]


def solve_spd(matrix: torch.Tensor, rhs: torch.Tensor, by_cholesky: bool | None = None) -> torch.Tensor:
    """``matrix^-1 rhs`` for symmetric positive definite ``matrix`` (mass matrices and the solver's
    Hessians ``M + J' W J``). On the CPU by its Cholesky factor, as MuJoCo factors them (faster
    than the general solve there at the steps' sizes); on CUDA by the general solve, which is the
    faster there (both measured by ``benchmarks/batched_products.py``). An env whose matrix is not
    positive definite gets NaN on the CPU (the general solve's inf or NaN on a singular one):
    the env base class flags and resets it. ``by_cholesky`` forces one way (by default: not on CUDA)."""
    if by_cholesky is None:
        by_cholesky = matrix.device.type != "cuda"
    if not by_cholesky:
        return _solve(matrix, rhs)
    factor, info = torch.linalg.cholesky_ex(matrix)
    solution = torch.cholesky_solve(rhs.unsqueeze(-1), factor).squeeze(-1)
    return torch.where((info == 0).unsqueeze(-1), solution, torch.full_like(solution, math.nan))


def _inverse(matrix: torch.Tensor) -> torch.Tensor:
    return torch.linalg.inv_ex(matrix)[0]


def small_matmul(a: torch.Tensor, b: torch.Tensor, broadcast: bool | None = None) -> torch.Tensor:
    """``a @ b`` for batches of small blocks (3x3 rotations, 6x6 inertias, their products with
    vectors).

    Args:
        a: ``[.., m, k]`` the left blocks.
        b: ``[.., k, n]`` the right blocks (broadcast against ``a``'s batch axes).
        broadcast: as a broadcast product summed over the shared axis (one elementwise kernel and
            one reduction) rather than a batched GEMM; by default (``None``) on CUDA, where cuBLAS's
            batched GEMM is slow for such blocks (3-8x slower at N = 65536 on an H200), not on the
            CPU, where ``@`` is the faster (both measured by ``benchmarks/batched_products.py``).
    """
    if broadcast is None:
        broadcast = a.device.type == "cuda"
    if broadcast:
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def small_matvec(a: torch.Tensor, v: torch.Tensor, broadcast: bool | None = None) -> torch.Tensor:
    """``(a @ v[..., None])[..., 0]`` for small blocks ``a``, by `small_matmul`.

    Args:
        a: ``[.., m, k]`` the blocks.
        v: ``[.., k]`` the vectors.
        broadcast: as in `small_matmul` (by default on CUDA only).
    """
    return small_matmul(a, v.unsqueeze(-1), broadcast).squeeze(-1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    # one kernel: written out in components it was twelve ops, 7x slower on a [16, 13, 3] batch
    return torch.linalg.cross(a, b)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _skew(v: torch.Tensor) -> torch.Tensor:
    """``[.., 3] -> [.., 3, 3]`` such that ``skew(v) @ u == v x u``."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([z, -w, y, w, z, -x, -y, x, z], dim=-1).reshape(*v.shape, 3)


def cross_motion(v: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Spatial motion cross product ``v x u`` of ``[.., 6]`` (angular, linear) vectors.

    Args:
        v: ``[.., 6]`` motion vectors (angular, linear).
        u: ``[.., 6]`` motion vectors (angular, linear).
    """
    w, vl = v[..., :3], v[..., 3:]
    a, ul = u[..., :3], u[..., 3:]
    return torch.cat([_cross(w, a), _cross(w, ul) + _cross(vl, a)], dim=-1)


def cross_force(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Spatial force cross product ``v x* f``.

    Args:
        v: ``[.., 6]`` motion vectors (angular, linear).
        f: ``[.., 6]`` force vectors (torque about the origin, force).
    """
    w, vl = v[..., :3], v[..., 3:]
    n, fl = f[..., :3], f[..., 3:]
    return torch.cat([_cross(w, n) + _cross(vl, fl), _cross(w, fl)], dim=-1)


def quaternion_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """``[.., 4]`` quaternions ``(w, x, y, z)`` -> ``[.., 3, 3]`` rotation matrices.

    Args:
        quat: ``[.., 4]`` quaternions ``(w, x, y, z)`` (normalised here, as MuJoCo does).
    """
    w, x, y, z = (quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quat.shape[:-1], 3, 3)


def _quaternion_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def integrate_quaternion(quat: torch.Tensor, omega: torch.Tensor, dt: float) -> torch.Tensor:
    """MuJoCo's ``mju_quatIntegrate``: rotate ``quat`` (normalised first) by the body-frame angular
    velocity ``omega`` for ``dt``: ``quat * (cos(|w| dt / 2), sin(|w| dt / 2) w / |w|)``.

    Smooth at ``omega = 0`` (``sin(|w| dt / 2) / |w|`` is written through ``sinc``).

    Args:
        quat: ``[.., 4]`` quaternions ``(w, x, y, z)``, normalised first.
        omega: ``[.., 3]`` body-frame angular velocities.
        dt: the time step (s).
    """
    speed = torch.sqrt((omega * omega).sum(-1, keepdim=True).clamp(min=_MINVAL * _MINVAL))
    half = 0.5 * dt * speed
    rotation = torch.cat([torch.cos(half), omega * (0.5 * dt) * torch.sinc(half / math.pi)], dim=-1)
    unit = quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True)
    return _quaternion_product(unit, rotation)
