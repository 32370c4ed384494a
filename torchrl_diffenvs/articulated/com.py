"""Centre-of-mass quantities that Gymnasium's observations and rewards read: MuJoCo's
``subtree_com``, ``cinert``, ``cvel``, ``xipos`` and the whole-model mass centre."""
from __future__ import annotations

import torch

from .kinematics import Kinematics, body_velocities
from .spatial import Params, _cross
from .tree import RigidBodyTree

__all__ = ["body_com", "com_inertia", "com_velocity", "mass_center", "root_subtree_com"]


def body_com(tree: RigidBodyTree, kin: Kinematics) -> torch.Tensor:
    """``[N, nbody, 3]`` every body's centre of mass in the world (MuJoCo's ``xipos``)."""
    return kin.body_pos + (kin.body_rot @ tree.body_com.unsqueeze(-1)).squeeze(-1)


def root_subtree_com(tree: RigidBodyTree, kin: Kinematics, params: Params) -> torch.Tensor:
    """``[N, nbody, 3]`` for every body, the centre of mass of its root's subtree
    (``subtree_com[body_rootid]``): the point MuJoCo takes ``cinert``, ``cvel`` and ``cfrc_ext`` about."""
    mass = params["body_mass"]  # [N, nbody]
    mask = tree.root_subtree_mask
    weighted = torch.einsum("bc,nc,nck->nbk", mask, mass, body_com(tree, kin))
    total = (mass @ mask.T).clamp_min(1e-12)
    return weighted / total.unsqueeze(-1)


def mass_center(tree: RigidBodyTree, kin: Kinematics, params: Params) -> torch.Tensor:
    """``[N, 3]`` Gymnasium's ``mass_center``: the mass-weighted mean of the bodies' ``xipos``."""
    mass = params["body_mass"]
    return (mass.unsqueeze(-1) * body_com(tree, kin)).sum(1) / mass.sum(1, keepdim=True)


def com_inertia(tree: RigidBodyTree, kin: Kinematics, params: Params) -> torch.Tensor:
    """``[N, nbody, 10]`` MuJoCo's ``cinert``: each body's inertia about its root's subtree centre of
    mass ``c`` in world axes, ``(Ixx, Iyy, Izz, Ixy, Ixz, Iyz, m d, m)`` with ``d = xipos - c``
    (the rotated body inertia plus ``m (|d|^2 I - d d^T)``)."""
    mass = params["body_mass"].unsqueeze(-1)  # [N, nbody, 1]
    rot = kin.body_rot
    inertia = rot @ params["body_inertia"] @ rot.transpose(-1, -2)  # about the body's com, world axes
    d = body_com(tree, kin) - root_subtree_com(tree, kin, params)
    eye = torch.eye(3, dtype=d.dtype, device=d.device)
    shifted = inertia + mass.unsqueeze(-1) * ((d * d).sum(-1)[..., None, None] * eye - d.unsqueeze(-1) * d.unsqueeze(-2))
    i, j = [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]
    return torch.cat([shifted[..., i, j], mass * d, mass], dim=-1)


def com_velocity(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params) -> torch.Tensor:
    """``[N, nbody, 6]`` MuJoCo's ``cvel``: each body's spatial velocity (angular, then the linear
    velocity of the body-fixed point at its root's subtree centre of mass), world axes."""
    vel = body_velocities(tree, kin, qvel)  # linear part at kin.origin
    lever = root_subtree_com(tree, kin, params) - kin.origin.unsqueeze(1)
    return torch.cat([vel[..., :3], vel[..., 3:] + _cross(vel[..., :3], lever)], dim=-1)
