"""AHAC (Georgiev et al., ICML 2024): SHAC with twin critics, no target critic and a window
length adapted from the contact forces the env reports.

* [`TwinCritic`][torchrl_diffenvs.objectives.TwinCritic]: two state-value networks read as one critic writing both values
  ``[..., 2]`` (shared by AHAC and SAPO).
* [`AHACLoss`][torchrl_diffenvs.objectives.AHACLoss]: [`SHACLoss`][torchrl_diffenvs.objectives.SHACLoss] bootstrapped by the
  *minimum* of the twin critics (the live ones: there is no target critic); both critics fit
  the same TD(lambda) targets.
* [`AdaptiveHorizon`][torchrl_diffenvs.objectives.AdaptiveHorizon]: the dual-variable rule that moves the window length between
  iterations.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from .windows import CONTACT_FORCE_KEY, window_contact_force
from .shac import SHACLoss

__all__ = ["CONTACT_FORCE_KEY", "AHACLoss", "AdaptiveHorizon", "TwinCritic", "window_contact_force"]


#: The entry the MuJoCo contact tasks write at every step: the largest contact normal force
#: (newtons) at the step's final physics state, ``[N, 1]``, detached. A window holds it under
#: ``("next", "contact_force")``.
class TwinCritic(TensorDictModuleBase):
    """Two state-value networks with the same inputs, read as one critic writing ``[..., 2]``.

    Each of ``first`` and ``second`` writes ``value_key`` (``[..., 1]``, e.g.
    [`make_critic`][torchrl_diffenvs.modules.make_critic]); this module writes both values side by side
    under ``value_key``. A loss reduces them (AHAC: minimum; SAPO: minimum for the critic
    targets, mean for the actor) and fits both to the same targets: the mean squared error
    against a ``[..., 1]`` target averages the two critics' errors. The two networks have their
    own weights; an [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] may be shared.
    """

    def __init__(self, first: TensorDictModuleBase, second: TensorDictModuleBase, value_key="state_value"):
        super().__init__()
        if list(first.in_keys) != list(second.in_keys):
            raise ValueError(f"TwinCritic: both critics must read the same keys, got {first.in_keys} and "
                             f"{second.in_keys}")
        self.first, self.second = first, second
        self.in_keys = list(first.in_keys)
        self.out_keys = [value_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        key = self.out_keys[0]
        inputs = tensordict.select(*self.in_keys)
        values = [critic(inputs.copy()).get(key) for critic in (self.first, self.second)]
        tensordict.set(key, torch.cat(values, dim=-1))
        return tensordict


class AHACLoss(SHACLoss):
    r"""SHAC's loss ([`SHACLoss`][torchrl_diffenvs.objectives.SHACLoss]) with twin critics and no
    target critic, as AHAC (``imgeorgiev/DiffRL``, ``src/shac/algorithms/ahac.py``).

    The actor's bootstrap and the critic targets use $\min(V_1, V_2)$ of the *current*
    critics (the reference's ``DoubleCriticMLP.forward`` and ``compute_target_values``);
    ``critic_loss`` fits both to the same TD($\lambda$) targets (the reference's
    ``predict``: both values against one target). Everything else is SHAC's: sub-trajectories
    closed at episode ends and at the window end, a terminal state worth 0, the pre-reset
    observation bootstrapped on truncation, the loss divided by $N H$.

    No target weights are created (`make_target_updater` does not apply).

    Args:
        actor_network: the policy that collected the windows.
        critic_network: a critic writing ``"state_value"`` with the values of its members in the
            last dimension ([`TwinCritic`][torchrl_diffenvs.objectives.TwinCritic]: ``[..., 2]``); one member is plain SHAC without
            a target critic.
        gamma: discount.
        lmbda: TD(lambda) parameter.
    """

    def convert_to_functional(self, *args, create_target_params: bool = False, **kwargs):
        """As ``LossModule``'s, never with target parameters: the critics are used as they are."""
        return super().convert_to_functional(*args, create_target_params=False, **kwargs)

    def make_target_updater(self, tau: float = 0.8):
        raise RuntimeError(f"{type(self).__name__} has no target critic: its bootstrap uses the current critics")

    def _next_target_values(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``min`` over the critics of ``V(("next", obs))`` ``[N, H, 1]``: the live critics (no
        target critic), differentiable w.r.t. the observation."""
        values = self._critic(tensordict.get("next"), target=False)
        return values.min(dim=-1, keepdim=True).values


class AdaptiveHorizon:
    r"""AHAC's window length: a dual variable per window step moved by the contact forces.

    State: the horizon $H$ (a float; windows are ``round(H)`` steps, Python's rounding) and
    a dual vector $\lambda$ with one entry per step of the current window. After a window
    whose mean (over the envs) contact force at step $i$ is $f_i$
    ([`update`][torchrl_diffenvs.objectives.AdaptiveHorizon.update]), exactly as the reference (``ahac.py``, ``train()``: "Train horizon", and
    ``init_buffers``):

    ```text
    lambda_i <- lambda_i - lr * (C - f_i)        # every step i of the window
    H        <- clip(H + lr * sum_i lambda_i, min_horizon, max_horizon)
    lambda   <- [lambda_0] * round(H)            # one entry per step of the next window
    ```

    with ``lr`` the dual learning rate of this iteration (the reference decays it linearly to
    1e-5 with the actor's schedule) and ``C = contact_threshold``. $\lambda$ is not
    clipped at 0 (the reference does not clip it). Starting state: $H$ = ``min_horizon``,
    $\lambda = 0$.

    Direction: $\lambda$ rises while the contact forces exceed $C$ and falls while
    they stay below it, and $H$ follows $\sum\lambda$: with this sign the window
    *lengthens* while the forces exceed $C$ and shortens below it (what the reference's
    code does).

    The reference's per-env force is the norm over the bodies' contact-force vectors divided by
    ``max(acceleration, 1)`` (dflex's ``info["contact_forces"]``); here it is the env's
    ``"contact_force"`` entry (the largest contact normal force), so ``C`` depends on the model's
    masses (DiffRL's bodies are about 200x heavier than Gymnasium's).
    """

    def __init__(self, min_horizon: int = 8, max_horizon: int = 64, contact_threshold: float = 500.0):
        if not 0 < min_horizon < max_horizon:
            raise ValueError(f"AdaptiveHorizon: need 0 < min_horizon < max_horizon, got {min_horizon}, {max_horizon}")
        self.min_horizon, self.max_horizon = int(min_horizon), int(max_horizon)
        self.contact_threshold = float(contact_threshold)
        self.horizon = float(min_horizon)
        self.dual = torch.zeros(self.min_horizon, dtype=torch.float64)

    @property
    def steps(self) -> int:
        """Length of the next window: ``round(H)``."""
        return int(round(self.horizon))

    def update(self, contact_force: torch.Tensor, lr: float) -> int:
        """Moves $\\lambda$ and $H$ after a window; returns the next window's length.

        Args:
            contact_force: the window's contact forces ``[N, H]`` (or the per-step means ``[H]``),
                ``H`` = the window's length ([`steps`][torchrl_diffenvs.objectives.AdaptiveHorizon.steps] when it was collected).
            lr: this iteration's dual learning rate.
        """
        force = contact_force.detach().to(device="cpu", dtype=torch.float64)
        per_step = force.mean(0) if force.ndim == 2 else force.reshape(-1)
        if per_step.shape[0] != self.dual.shape[0]:
            raise ValueError(f"AdaptiveHorizon.update: the window has {per_step.shape[0]} steps but the dual variable "
                             f"{self.dual.shape[0]} (one per step of a window of round(H) = {self.steps})")
        dual = self.dual - lr * (self.contact_threshold - per_step)
        self.horizon = min(max(self.horizon + lr * float(dual.sum()), self.min_horizon), self.max_horizon)
        self.dual = dual[0].repeat(self.steps)
        return self.steps

    def state_dict(self) -> dict:
        """The current horizon and its dual variables (for a checkpoint)."""
        return {"horizon": self.horizon, "dual": self.dual.clone()}

    def load_state_dict(self, state: dict) -> None:
        """Restores `state_dict`."""
        self.horizon = float(state["horizon"])
        self.dual = state["dual"].to(torch.float64).clone()

    def __repr__(self) -> str:
        return (f"AdaptiveHorizon(H={self.horizon:.3f}, steps={self.steps}, range=[{self.min_horizon}, "
                f"{self.max_horizon}], C={self.contact_threshold})")
