"""How the backward differentiates MuJoCo's constraint solve: the contact gradient modes.

The forward is MuJoCo's in every mode; a mode shapes the gradient only (a straight-through
estimator in [`solve`][torchrl_diffenvs.articulated.constraint.solve]). The modes, the measurements that compare them and the
learners' choice are in the simulator docs ("Gradients through MuJoCo's contact").
"""
from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["ContactGradient", "GRADIENT_MODES"]

GRADIENT_MODES = ("exact", "cfd", "smooth", "penalty")


class ContactGradient(NamedTuple):
    """How the backward differentiates the constraint solve. The forward is MuJoCo's in every mode,
    bit for bit: a mode other than ``"exact"`` changes the gradient only (a straight-through
    estimator: the value is the exact solve's, the gradient a surrogate solve's).

    - ``"exact"``: the implicit gradient of the solution, with the active set it found.
    - ``"cfd"`` (contacts from distance, after Paulus et al.'s DiffMJX): the surrogate also holds
      the contacts within ``distance`` (metres) beyond their margin, as active rows whose weight
      fades linearly to 0 at ``distance`` (their reference acceleration is MuJoCo's formula at
      that distance). A foot about to land then has a gradient with respect to its height and
      velocity, where the exact one is zero. Contacts MuJoCo has (within the margin) keep their
      exact status: one there that does not push is out of the surrogate, so the backward weight
      of a separating contact jumps from 0 to about 1 as it crosses the margin.
    - ``"smooth"`` (smoothed complementarity): the surrogate's active set is soft, each existing
      row weighted by ``sigmoid(f / (softness f_max))``, ``f`` the force the row would carry at
      the solution if it were active (negative for an inactive one) and ``f_max`` the env's largest
      ``|f|``: rows near the switch count by half, and the gradient no longer jumps where a row
      switches. ``softness -> 0`` gives the exact gradient.
    - ``"penalty"``: the gradient of the smooth penalty contact model (``contact="smooth"``,
      `contact`) at MuJoCo's state, in place of the solve's: straight through at the
      accelerations (and the Ant's ``cfrc_ext``). The penalty force has a gradient wherever a geom
      is within its width of the ground and none of the solve's switches; its parameters
      (``contact_stiffness``, ``contact_damping``, ``contact_width``, ``friction_velocity``) join
      the env's params and shape the backward only.
    """

    mode: str = "exact"
    distance: float = 0.02  # cfd: metres beyond the contact margin
    softness: float = 0.1  # smooth: the sigmoid's width, relative to the env's largest row force

    @property
    def shapes_solve(self) -> bool:
        """Whether the mode is a surrogate of the constraint solve itself (``"penalty"`` replaces
        the whole contact gradient, outside the solve)."""
        return self.mode != "penalty"

    @property
    def reach(self) -> float:
        """How far (metres) beyond its margin a contact still enters the surrogate: ``distance``
        for ``cfd``, 0 in the other modes."""
        return self.distance if self.mode == "cfd" else 0.0

    def holds_near(self, found: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
        """Where the ``cfd`` surrogate holds a contact that MuJoCo's solve does not have: found, its
        distance beyond the margin ``gap`` under ``distance`` (all False in the other modes)."""
        if self.mode != "cfd":
            return torch.zeros_like(found)
        return found & (gap < self.reach)

    @classmethod
    def parse(cls, value) -> "ContactGradient":
        """A [`ContactGradient`][torchrl_diffenvs.articulated.contact_gradient.ContactGradient] from itself, a mode name or a mapping of its fields (a config's
        ``{mode: cfd, distance: 0.05}``); a clear error for anything else."""
        if isinstance(value, cls):
            gradient = value
        elif isinstance(value, str):
            gradient = cls(mode=value)
        elif hasattr(value, "keys"):
            unknown = set(value.keys()) - set(cls._fields)
            if unknown:
                raise ValueError(f"contact_gradient: unknown keys {sorted(unknown)}; valid: {list(cls._fields)}")
            if "mode" not in value.keys():
                raise ValueError(f"contact_gradient: a mapping must name its mode (one of {GRADIENT_MODES}), "
                                 f"got {dict(value)!r}")
            gradient = cls(**dict(value))
        else:
            raise ValueError(f"contact_gradient must be one of {GRADIENT_MODES}, a mapping of {list(cls._fields)} "
                             f"or a ContactGradient, got {value!r}")
        if gradient.mode not in GRADIENT_MODES:
            raise ValueError(f"contact_gradient: unknown mode {gradient.mode!r}; valid: {GRADIENT_MODES}")
        for name in ("distance", "softness"):
            value = getattr(gradient, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"contact_gradient.{name} must be a number > 0, got {value!r}")
        return gradient
