"""Motor, passive and fluid forces: ``gear * clamp(ctrl)``, joint springs and dampers, and
MuJoCo's inertia-box fluid model."""
from __future__ import annotations

import math

import torch

from .kinematics import Kinematics, body_velocities, generalised_force
from .spatial import Params, _MINVAL, _cross
from .tree import RigidBodyTree

__all__ = ['actuator_force', 'passive_force', 'fluid_force']


def actuator_force(tree: RigidBodyTree, ctrl: torch.Tensor, nv: int) -> torch.Tensor:
    """``[N, nv]`` generalised motor forces: ``gear * clamp(ctrl)`` (force range applied before the gear)."""
    force = torch.clamp(torch.clamp(ctrl, tree.ctrl_low, tree.ctrl_high), tree.force_low, tree.force_high)
    out = ctrl.new_zeros(ctrl.shape[0], nv)
    return out.index_add(1, tree.actuator_dof, force * tree.actuator_gear)


def fluid_force(tree: RigidBodyTree, kin: Kinematics, qvel: torch.Tensor, params: Params) -> torch.Tensor:
    """``[N, nv]`` generalised force of MuJoCo's inertia-box fluid model (``mj_inertiaBoxFluidModel``).

    Each body is a box with its mass and principal moments of inertia, moving in a still medium
    of ``fluid_density`` and ``fluid_viscosity``: in the body's inertial frame, with ``b`` the box
    sides, ``d = mean(b)``, ``v`` and ``w`` the linear (at the centre of mass) and angular velocity,

        force_i  = -3 pi d viscosity v_i  - density / 2 * b_j b_k |v_i| v_i
        torque_i = -pi d^3 viscosity w_i  - density / 64 * b_i (b_j^4 + b_k^4) |w_i| w_i

    applied at the centre of mass. Smooth (``|x| x`` is C1), so gradients are defined everywhere.
    """
    mass, inertia = params["body_mass"], params["body_inertia"]
    frame = tree.body_inertial_frame  # principal axes in the body frame, from the model file
    moments = torch.diagonal(frame.transpose(-1, -2) @ inertia @ frame, dim1=-2, dim2=-1)  # [N, nbody, 3]
    has_mass = mass > _MINVAL  # MuJoCo skips massless bodies (the world)
    safe_mass = torch.where(has_mass, mass, torch.ones_like(mass)).unsqueeze(-1)
    opposite = moments.sum(-1, keepdim=True) - 2 * moments  # I_j + I_k - I_i
    box = torch.sqrt(torch.clamp(opposite, min=_MINVAL) / safe_mass * 6.0)
    rot = kin.body_rot @ frame  # inertial frames in the world
    com = kin.body_pos + (kin.body_rot @ tree.body_com.unsqueeze(-1)).squeeze(-1) - kin.origin.unsqueeze(1)
    vel = body_velocities(tree, kin, qvel)  # [N, nbody, 6]: angular, linear at kin.origin
    omega = vel[..., :3]
    local_w = (rot.transpose(-1, -2) @ omega.unsqueeze(-1)).squeeze(-1)
    local_v = (rot.transpose(-1, -2) @ (vel[..., 3:] + _cross(omega, com)).unsqueeze(-1)).squeeze(-1)
    density = params["fluid_density"][:, None, None]
    viscosity = params["fluid_viscosity"][:, None, None]
    diameter = box.mean(-1, keepdim=True)
    b0, b1, b2 = box.unbind(-1)
    area = torch.stack([b1 * b2, b0 * b2, b0 * b1], dim=-1)
    fourth = box**4
    spin = box * (fourth.sum(-1, keepdim=True) - fourth) / 64.0  # b_i (b_j^4 + b_k^4) / 64
    force = -3 * math.pi * diameter * viscosity * local_v - 0.5 * density * area * local_v.abs() * local_v
    torque = -math.pi * diameter**3 * viscosity * local_w - density * spin * local_w.abs() * local_w
    mask = has_mass.to(force.dtype).unsqueeze(-1)
    force_w = (rot @ force.unsqueeze(-1)).squeeze(-1) * mask
    torque_w = (rot @ torque.unsqueeze(-1)).squeeze(-1) * mask
    wrench = torch.cat([torque_w + _cross(com, force_w), force_w], dim=-1)  # about kin.origin
    return generalised_force(tree.body_dof_mask, kin, wrench)


def passive_force(tree: RigidBodyTree, kin: Kinematics, qpos, qvel, params: Params) -> torch.Tensor:
    """``[N, nv]`` MuJoCo's ``qfrc_passive``: joint dampers ``-damping qvel``, springs
    ``-stiffness (qpos - springref)``, fixed tendons' springs and dampers (on the tendon length
    ``L = coef . q``: ``coef * (-k (L - springlength) - b dL/dt)``) and, in a medium, `fluid_force`."""
    # springs act on hinge and slide coordinates (ball and free joints have none, see the loader)
    stretch = (qpos - tree.qpos_spring)[:, tree.dof_qpos] * tree.dof_has_spring
    passive = -params["damping"] * qvel - params["stiffness"] * stretch
    if tree.tendon_coef.shape[0]:
        coordinates = qpos[:, tree.dof_qpos] * tree.dof_has_spring  # fixed tendons span hinges and slides
        length, speed = coordinates @ tree.tendon_coef.T, qvel @ tree.tendon_coef.T
        tension = -params["tendon_stiffness"] * (length - tree.tendon_springlength) - params["tendon_damping"] * speed
        passive = passive + tension @ tree.tendon_coef
    if tree.has_fluid:
        passive = passive + fluid_force(tree, kin, qvel, params)
    return passive
