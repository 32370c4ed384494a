"""The base class of the tasks built on a MuJoCo model file: Gymnasium's MuJoCo envs in pure torch.

A task names its model file (one that ships with gymnasium, or a path), its ``frame_skip`` and its
task constants, and writes its reset noise, reward, termination and observation like Gymnasium's
v5 class. By default the physics is MuJoCo's own (its collision, constraint solve and the model
file's integrator: ``contact="mujoco"``); ``contact="smooth"`` swaps in a smooth penalty contact,
an approximation. the model's physics ([`torchrl_diffenvs.articulated`][torchrl_diffenvs.articulated]) and every TorchRL concern
([`DiffEnv`][torchrl_diffenvs.DiffEnv]) live elsewhere.

State: MuJoCo's coordinates ``("state", "qpos")`` and ``("state", "qvel")`` ``[N, nq]``, plus
task extras. Params (per env, float or ``[num_envs, ...]``): the model's ``body_mass [nbody]``,
``body_inertia [nbody, 3, 3]``, ``gravity [3]``, ``damping``/``armature``/``stiffness [nv]``; for
models with contact ``contact_friction [ncontact]`` (one per geom pair, MuJoCo's sliding friction
by default) and, with MuJoCo's contact model, ``contact_solref [ncontact, 2]`` (each pair's
``solref``: the time constant and damping ratio of its soft contact, MuJoCo's mixed values by
default; a time constant under two timesteps acts as two, MuJoCo's ``refsafe``), and with ``contact="smooth"`` ``contact_stiffness``, ``contact_damping``,
``contact_width`` and ``friction_velocity``; for models in a fluid (``<option density/viscosity>``, Swimmer)
``fluid_density`` and ``fluid_viscosity``; and the task's constants (reward weights, healthy
ranges, reset noise). Truncation follows Gymnasium's ``TimeLimit`` (as the classic Gymnasium tasks).
"""
from __future__ import annotations

import functools
from pathlib import Path

import torch

from ...articulated import RigidBodyTree, load_mjcf, step
from ...articulated.integrators import physics_stepper, stepping_with
from ...articulated.contact import has_contacts
from ...articulated.dynamics import StepResult, default_params
from ...articulated.inertia import kinematics_at_qpos0
from ...articulated.mjcf import ArticulatedModel, gymnasium_asset
from ...articulated.pipeline import invweight0
from ...articulated.tree import CONTACT_MODELS
from ..gym_classic import GymnasiumClassicEnv
from .outlier_gradient import check_outlier_clip, clip_outlier_gradients

__all__ = ["MuJoCoModelEnv"]


@functools.lru_cache(maxsize=None)
def load_model(model_file: str) -> ArticulatedModel:
    """The parsed model of a file path or of a model file shipped with gymnasium (cached)."""
    path = Path(model_file)
    return load_mjcf(path if path.is_file() else gymnasium_asset(model_file))


#: Smooth ground-contact defaults (``contact="smooth"``, see ``articulated.contact.contact_force``); a task may override.
CONTACT_DEFAULTS = {"contact_stiffness": 2e4, "contact_damping": 500.0, "contact_width": 0.002,
                    "friction_velocity": 0.01}


class MuJoCoModelEnv(GymnasiumClassicEnv):
    """A batched, differentiable env simulating a MuJoCo model file (hinge and slide joints).

    Subclasses set ``name``, ``model_file``, ``frame_skip``, ``task_params`` (constants that are
    per-env params too) and write ``initial_state``, ``transition`` (calling [`simulate`][torchrl_diffenvs.envs.MuJoCoModelEnv.simulate])
    and ``observation``; the action is MuJoCo's ``ctrl`` (its spec is the model's ctrlrange;
    MuJoCo clamps out-of-range controls, so their gradient is zero).

    Args:
        num_envs: the envs in the batch, as [`DiffEnv`][torchrl_diffenvs.DiffEnv].
        contact: ``"mujoco"`` (the default): MuJoCo's own contact dynamics (its collision, the
            constraint rows of contacts and joint limits, and the solve, as ``mj_step``), with the
            model file's integrator: the task is Gymnasium's. ``"smooth"``: a smooth penalty
            contact force instead (`contact`), an approximation
            whose trajectories differ from MuJoCo's once a body touches; ``None``: the task's
            ``default_contact``.
        integrator: ``None`` (default): the model file's with ``contact="mujoco"``, the task's
            ``smooth_integrator`` with ``contact="smooth"``; else ``"model"`` (the model file's own, as MuJoCo and Gymnasium run it),
            ``"euler"`` (MuJoCo's semi-implicit Euler, with the joint damping and, with the smooth
            contact, its velocity damping treated implicitly), ``"implicit"`` (MuJoCo's: Euler with
            the Coriolis and centrifugal forces implicit too) or ``"rk4"``. An integrator other
            than the file's changes the forward: the task is then no longer MuJoCo's. With the
            smooth contact the choice changes how well the step's Jacobian is conditioned while a
            foot sticks (its regularised friction is a stiff damper): HalfCheetah, Hopper and
            Walker2d use ``"euler"`` there, the Ant ``"implicit"``; the docs list each option's numbers.
        substeps: ``k >= 1`` physics steps of ``timestep / k`` for each of MuJoCo's steps (the
            env step ``dt`` is unchanged).
        contact_gradient: how the backward differentiates MuJoCo's constraint solve, with
            ``contact="mujoco"``; the forward values are the same in every mode.
            ``"exact"`` (default): the implicit gradient of the solution. ``"cfd"`` (contacts
            from distance): contacts within ``distance`` beyond touching contribute a backward-only
            force, so a foot about to land has a gradient. ``"smooth"``: a soft active set in the
            backward. ``"penalty"``: the smooth penalty contact model's gradient at MuJoCo's
            state (its parameters join the params). A mapping sets the fields of
            [`ContactGradient`][torchrl_diffenvs.articulated.contact_gradient.ContactGradient], e.g.
            ``{"mode": "cfd", "distance": 0.05}``.
        recompute_in_backward: ``True``: a graph keeps only each env step's inputs of the
            physics and runs its ``frame_skip`` physics steps again in the backward (activation
            checkpointing, ``torch.utils.checkpoint``) instead of saving their intermediates: a
            BPTT window's memory shrinks by about the physics' share (measured in
            ``benchmarks/gradient_throughput.py``) for one more forward of the physics per
            backward. Values and gradients are the same.
        gradient_outlier_clip: ``None`` (default) or ``c >= 1``: at every env step (its
            ``frame_skip x substeps`` physics steps), the backward caps the norm of each env's
            gradient with respect to the step's ``qpos``, ``qvel`` and action together at ``c``
            times the median over the envs with a finite, nonzero one, and zeroes a NaN/inf one
            ([`clip_outlier_gradients`][torchrl_diffenvs.envs.mujoco.outlier_gradient.clip_outlier_gradients]):
            the few envs whose gradient explodes through contact then count in an update at the
            size of the others, instead of making the learner skip it. Applied again at every
            step of a window. The forward values are the same; it needs a batch (one env is its
            own median).
        **kwargs: ``device``, ``dtype``, ``seed``, ``max_episode_steps`` and ``params``, as
            [`DiffEnv`][torchrl_diffenvs.DiffEnv]; and the task's own options.
    """

    INTEGRATORS = ("model", "euler", "implicit", "rk4")
    default_contact = "mujoco"
    smooth_integrator = "model"  # with contact="smooth": the planar contact tasks and the humanoids "euler", the Ant "implicit"

    model_file: str = ""
    frame_skip: int = 1
    task_params: dict = {}
    contact_params: dict = CONTACT_DEFAULTS
    default_max_episode_steps = 1000

    def __init__(self, num_envs: int = 1, *, contact: str | None = None, integrator: str | None = None,
                 substeps: int = 1, contact_gradient="exact", recompute_in_backward: bool = False,
                 gradient_outlier_clip: float | None = None, **kwargs):
        model = load_model(self.model_file)
        self.model = model
        contact = self.default_contact if contact is None else contact
        if contact not in CONTACT_MODELS:
            raise ValueError(f"{self.name}: unknown contact model {contact!r}; valid: "
                             f"{', '.join(repr(c) for c in CONTACT_MODELS)}")
        self.contact = contact
        if integrator is None:
            integrator = "model" if contact == "mujoco" else self.smooth_integrator
        if integrator not in self.INTEGRATORS:
            raise ValueError(f"{self.name}: unknown integrator {integrator!r}; valid: "
                             f"{', '.join(repr(i) for i in self.INTEGRATORS)} ('model': the file's {model.integrator!r})")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ValueError(f"{self.name}: substeps must be an integer >= 1 (physics steps per MuJoCo step), "
                             f"got {substeps!r}")
        self.integrator = model.integrator if integrator == "model" else integrator
        if self.integrator == "implicit" and (model.viscosity or model.density):
            raise ValueError(f"{self.name}: integrator 'implicit' is not available for a model with fluid forces "
                             "(MuJoCo's also treats their velocity derivative implicitly; this one does not); "
                             "valid here: 'euler', 'rk4'")
        self.substeps = substeps
        if not isinstance(recompute_in_backward, bool):
            raise ValueError(f"{self.name}: recompute_in_backward must be True or False, got {recompute_in_backward!r}")
        self.recompute_in_backward = recompute_in_backward
        self.gradient_outlier_clip = check_outlier_clip(self.name, gradient_outlier_clip)
        self.action_dim = model.nu
        low, high = model.ctrl_range[:, 0], model.ctrl_range[:, 1]
        if not ((low == low[0]).all() and (high == high[0]).all()):
            raise ValueError(f"{self.model_file}: motors with different ctrlranges are not supported yet")
        self.action_low, self.action_high = float(low[0]), float(high[0])
        self.dt = model.timestep * self.frame_skip  # one env step, as Gymnasium's env.dt
        dtype = kwargs.get("dtype", torch.float32)
        device = torch.device(kwargs.get("device") or "cpu")
        self.tree = RigidBodyTree.from_model(model, dtype=dtype, device=device, contact=contact)
        try:
            self.tree.use_contact_gradient(contact_gradient)
        except ValueError as err:
            raise ValueError(f"{self.name}: {err}") from None
        self.contact_gradient = self.tree.contact_gradient
        if has_contacts(self.tree):
            self.reading_state_keys = ("contact_force",)  # see reports_contact_force
            if self.tree.contact_model == "mujoco":  # an iterative constraint solve
                self.reading_state_keys += ("solver_unconverged",)
        kinematics_at_qpos0(self.tree)  # kept on the tree: computed here, not inside a compiled step
        defaults = dict(default_params(model))
        if has_contacts(self.tree):
            if contact == "smooth" or self.contact_gradient.mode == "penalty":  # the penalty model's
                defaults.update(self.contact_params)
            defaults["contact_friction"] = torch.as_tensor(self.tree.contact_pair_friction)
            if self.tree.contact_model == "mujoco":
                defaults["contact_solref"] = self.tree.contact_slots.pair_solref.cpu().double()
        defaults.update(self.task_params)
        self.default_params = defaults
        super().__init__(num_envs, **kwargs)

    # ------------------------------------------------------------------ helpers for tasks
    @property
    def reports_contact_force(self) -> bool:
        """True for models with ground contact: their state carries ``"contact_force"`` ``[N]``,
        the largest contact normal force (newtons, detached) over the last env step's physics
        steps (0 after a reset): the signal AHAC adapts its horizon to, and what the learners log
        as ``contact_force_max``. Like the Ant's ``cfrc_ext``, it is read where ``mj_step`` leaves
        it, not an input of the next step."""
        return bool(has_contacts(self.tree))

    def contact_state(self, result: StepResult | None, n: int) -> dict:
        """``{"contact_force": [N]}`` of a step's result (``None``: after a reset) for a model with
        contacts, else ``{}``: what a task adds to its state. With MuJoCo's contact model also
        ``"solver_unconverged"`` ``[N]`` bool: some constraint solve of the step used all of the
        model file's ``iterations`` without reaching its ``tolerance`` (MuJoCo's ``solver_niter``
        at its limit). The step still takes the solver's last iterate, as MuJoCo's does; the flag
        says which envs to distrust (False after a reset)."""
        if not self.reports_contact_force:
            return {}
        mujoco_solve = "solver_unconverged" in self.reading_state_keys
        if result is None:
            out = {"contact_force": torch.zeros(n, dtype=self.float_dtype, device=self.device)}
            if mujoco_solve:
                out["solver_unconverged"] = torch.zeros(n, dtype=torch.bool, device=self.device)
            return out
        out = {"contact_force": result.contact_force.detach()}
        if mujoco_solve:
            out["solver_unconverged"] = ~result.solver_converged
        return out

    def init_qpos(self, n: int) -> torch.Tensor:
        """MuJoCo's ``qpos0`` (Gymnasium's ``init_qpos``) for ``n`` envs."""
        return self.tree.qpos0.expand(n, -1)

    def _regulariser_scales(self, params):
        """MuJoCo's ``dof_invweight0`` and ``body_invweight0`` for these params, the scales of the
        constraints' regularisers: constants of the model (MuJoCo computes them once, in
        ``mj_setConst``), computed again only when a param tensor is replaced or changed in place,
        and at every step while a param carries a graph (its gradient flows through them), is an
        inference tensor (which has no version to watch) or under ``torch.compile`` (traced with
        the step)."""
        if torch.compiler.is_compiling() or any(value.requires_grad or value.is_inference()
                                                for value in params.values()):
            return invweight0(self.tree, params)
        # the tensors themselves are kept (an id could be reused once one is freed) with their versions
        key = [(self.tree, None), *((value, value._version) for value in params.values())]
        cached = self.__dict__.get("_cached_regulariser_scales")
        if cached is not None and len(cached[0]) == len(key) and all(
                a is b and va == vb for (a, va), (b, vb) in zip(cached[0], key)):
            return cached[1]
        weights = invweight0(self.tree, params)
        self.__dict__["_cached_regulariser_scales"] = (key, weights)  # not nn.Module state: never in a state_dict
        return weights

    def simulate(self, state, action, params) -> StepResult:
        """``frame_skip`` physics steps with ``ctrl = action`` (Gymnasium's ``do_simulation``), each
        as ``substeps`` steps of the chosen ``integrator``.

        Returns the last step's [`StepResult`][torchrl_diffenvs.articulated.StepResult]: the new
        ``qpos``/``qvel`` and the state MuJoCo's derived quantities belong to after ``mj_step``;
        its ``contact_force`` is the largest contact normal force over all the physics steps, its
        ``solver_converged`` whether every constraint solve of them converged.
        """
        qpos, qvel = state["qpos"], state["qvel"]
        qpos, qvel, action = clip_outlier_gradients(self.gradient_outlier_clip, qpos, qvel, action)
        if self.recompute_in_backward and torch.is_grad_enabled():
            stepper = physics_stepper(self.tree)  # compile_physics' step, if a compiled rollout runs this

            def physics(qpos, qvel, action, params):
                # the backward's recomputation runs outside the rollout: it must take the same step
                with stepping_with(self.tree, stepper):
                    return self._simulate(qpos, qvel, action, params)

            return torch.utils.checkpoint.checkpoint(physics, qpos, qvel, action, params, use_reentrant=False)
        return self._simulate(qpos, qvel, action, params)

    def _simulate(self, qpos, qvel, action, params) -> StepResult:
        weights = self._regulariser_scales(params)
        largest = converged = None
        for _ in range(self.frame_skip * self.substeps):
            result = step(self.tree, qpos, qvel, action, params, self.model.timestep / self.substeps,
                          self.integrator, weights)
            qpos, qvel = result.qpos, result.qvel
            if result.contact_force is not None:
                largest = result.contact_force if largest is None else torch.maximum(largest, result.contact_force)
            if result.solver_converged is not None:
                converged = result.solver_converged if converged is None else converged & result.solver_converged
        return result._replace(contact_force=largest, solver_converged=converged)
