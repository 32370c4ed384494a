"""Articulated rigid bodies read from MuJoCo model files, simulated in pure, differentiable torch."""
from .dynamics import RigidBodyTree, accelerations, forward_kinematics, mass_matrix_and_bias, step
from .mjcf import ArticulatedModel, MJCFError, gymnasium_asset, load_mjcf

__all__ = [
    "ArticulatedModel", "MJCFError", "RigidBodyTree", "accelerations", "forward_kinematics", "gymnasium_asset",
    "load_mjcf", "mass_matrix_and_bias", "step",
]
