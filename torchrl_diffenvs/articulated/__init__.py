"""Articulated rigid bodies read from MuJoCo model files, simulated in pure, differentiable torch.

One module per stage of the simulator, in the order a physics step runs them:

* :mod:`.mjcf` and :mod:`.model`: the MJCF reader and the parsed model (numpy);
* :mod:`.tree`: the model as tensors (:class:`RigidBodyTree`) and its default physical params;
* :mod:`.spatial`: spatial algebra (6-vector cross products, quaternions, batched solves);
* :mod:`.kinematics`: body poses and dof motion axes, sums along the tree, ``mj_integratePos``;
* :mod:`.inertia`: the mass matrix and bias forces;
* :mod:`.forces`: motors, springs, dampers and the fluid model;
* :mod:`.collision`: MuJoCo's collision detection (contacts between geoms);
* :mod:`.constraint`: MuJoCo's constraint rows (joint limits, contacts) and their solve;
* :mod:`.contact` and :mod:`.limits`: the smooth contact option's penalty contact and its joint limits;
* :mod:`.pipeline`: :func:`accelerations`, the forward dynamics on one screen;
* :mod:`.integrators`: :func:`step` with semi-implicit Euler or RK4.

:mod:`.dynamics` gathers the stages' functions under one name.
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
