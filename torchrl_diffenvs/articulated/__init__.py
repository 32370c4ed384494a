"""Articulated rigid bodies read from MuJoCo model files, simulated in pure, differentiable torch.

One module per stage of the simulator, in the order a physics step runs them:

* `mjcf` and `model`: the MJCF reader and the parsed model (numpy);
* `tree`: the model as tensors ([`RigidBodyTree`][torchrl_diffenvs.articulated.RigidBodyTree]) and its default physical params;
* `spatial`: spatial algebra (6-vector cross products, quaternions, batched solves);
* `kinematics`: body poses and dof motion axes, sums along the tree, ``mj_integratePos``;
* `inertia`: the mass matrix and bias forces;
* `forces`: motors, springs, dampers and the fluid model;
* [`collision`][torchrl_diffenvs.articulated.collision]: MuJoCo's collision detection (contacts between geoms),
  one function per pair of geom types in `primitives` (their types in `primitive_types`; the larger ones in `sphere_box`, `capsule_cylinder`, `capsule_box`, `box_box`);
* [`constraint`][torchrl_diffenvs.articulated.constraint]: MuJoCo's constraint rows (joint limits, contacts) and their solve;
  [`newton`][torchrl_diffenvs.articulated.newton] the solve's Newton search,
  [`elliptic`][torchrl_diffenvs.articulated.elliptic] the rows and cost of elliptic friction cones;
* `contact` and `limits`: the smooth contact option's penalty contact and its joint limits;
* `pipeline`: [`accelerations`][torchrl_diffenvs.articulated.accelerations], the forward dynamics on one screen;
* `integrators`: [`step`][torchrl_diffenvs.articulated.step] with semi-implicit Euler or RK4.

`dynamics` gathers the stages' functions under one name.
"""
from .integrators import StepResult, step
from .kinematics import Kinematics, forward_kinematics
from .inertia import mass_matrix_and_bias
from .mjcf import ArticulatedModel, MJCFError, gymnasium_asset, load_mjcf
from .pipeline import accelerations
from .tree import RigidBodyTree, default_params

__all__ = [
    "ArticulatedModel", "Kinematics", "MJCFError", "RigidBodyTree", "StepResult", "accelerations", "default_params",
    "forward_kinematics", "gymnasium_asset", "load_mjcf", "mass_matrix_and_bias", "step",
]
