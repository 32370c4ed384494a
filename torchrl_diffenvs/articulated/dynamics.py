"""Batched, differentiable rigid-body dynamics of kinematic trees, in pure torch.

Everything here is a pure function of tensors with a leading batch dimension ``N``: the same code
serves the TorchRL step, the lean rollout path, ``torch.compile``, CPU and CUDA, float32 and
float64. The physics follows MuJoCo's definitions so that contact-free models match MuJoCo to
rounding error:

* kinematics: MuJoCo's joint composition (hinge about its anchor, slide along its axis, ``ref``;
  a ball joint's unit quaternion about its anchor; a free joint's world position and quaternion),
  and MuJoCo's dof motion axes (a ball or free joint turns about its body's own axes);
* mass matrix and bias forces (Coriolis, centrifugal, gravity) from spatial vectors expressed in
  world axes about a reference point on the robot, where velocities add along the tree: with ``S_d`` the motion
  axis of dof ``d`` and ``Ic_d`` the summed inertia of the bodies it moves, the composite-rigid-body
  algorithm's ``M_ij = S_i . Ic_j S_j`` (dof ``i`` moving dof ``j``'s body) plus ``diag(armature)``,
  and ``bias_d = S_d . sum_b (I_b a_b + v_b x* I_b v_b)`` over the bodies ``d`` moves, with ``a_b``
  the velocity-product acceleration (the recursive Newton-Euler terms); every sum over the tree is
  one masked product, not a Python recursion over bodies;
* passive forces ``-damping qvel - stiffness (qpos - springref)``, motors ``gear * clamp(ctrl)``;
* joint limits as MuJoCo's soft constraints (solref/solimp impedance, reference acceleration,
  regulariser from ``dof_invweight0``), solved row by row: exact when one limit is active at a
  time, MuJoCo's coupled solve otherwise;
* smooth penalty contact between geoms and ground planes (`contact_force`), not MuJoCo's
  convex solver: see [`torchrl_diffenvs.articulated`][torchrl_diffenvs.articulated] for the difference;
* MuJoCo's integrators: semi-implicit Euler with implicit joint damping, and MuJoCo 4's RK4 (with
  its rotation correction for ball and free joints), both moving quaternions as
  ``mj_integratePos`` does (`integrate_position`).

Physical parameters come per env in a mapping (``body_mass [N, nbody]``, ``body_inertia
[N, nbody, 3, 3]``, ``damping``/``armature``/``stiffness [N, nv]``, ``gravity [N, 3]``,
``contact_stiffness``/``contact_damping [N]``, ``contact_friction [N, ncontact]``), so they can be
randomised or differentiated like any other input.

The stages live in their own modules, in the order [`accelerations`][torchrl_diffenvs.articulated.accelerations] runs them:
`tree` (the model as tensors), `spatial` (spatial algebra), `kinematics`,
`inertia` (mass matrix and bias), `forces` (motors, passive and fluid forces),
`contact`, `limits`, `pipeline` (the forward dynamics) and `integrators`.
This module gathers their public functions under one name; the stages' private helpers are
imported from the module that defines them.
"""
from __future__ import annotations

from .contact import body_contact_forces, contact_force
from .forces import actuator_force, fluid_force, passive_force
from .inertia import dof_invweight0, mass_matrix_and_bias
from .integrators import StepResult, eager_step, step, stepping_with
from .kinematics import Kinematics, body_velocities, forward_kinematics, generalised_force, integrate_position, site_positions
from .limits import limit_force
from .pipeline import accelerations, constraint_force
from .spatial import Params, cross_force, cross_motion, integrate_quaternion, quaternion_to_matrix
from .tree import RigidBodyTree, default_params

__all__ = [
    "RigidBodyTree", "Kinematics", "StepResult", "forward_kinematics", "integrate_position", "mass_matrix_and_bias",
    "accelerations", "step", "eager_step", "stepping_with", "constraint_force", "site_positions", "default_params",
    "body_contact_forces",
    "contact_force", "limit_force", "actuator_force", "passive_force", "fluid_force", "dof_invweight0",
    "body_velocities", "generalised_force", "integrate_quaternion", "quaternion_to_matrix", "cross_motion",
    "cross_force", "Params",
]
