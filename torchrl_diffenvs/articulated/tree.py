"""The model as tensors: [`RigidBodyTree`][torchrl_diffenvs.articulated.RigidBodyTree] (the constant part of a parsed MuJoCo model: tree
structure, joint axes, contact points, limits) and [`default_params`][torchrl_diffenvs.articulated.default_params] (the per-env physical
parameters a model file sets)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from .collision import ContactSlots, _weld, colliding_pairs, contact_slots, unsupported_pairs
from .contact_gradient import ContactGradient
from .model import ArticulatedModel

__all__ = ['BodyGroup', 'RigidBodyTree', 'default_params', 'CONTACT_MODELS']

CONTACT_MODELS = ("mujoco", "smooth")


class BodyGroup(NamedTuple):
    """Bodies at the same depth of the tree whose joints are of the same kinds in the same order:
    forward kinematics poses a group with one batched op per stage instead of one per body. The
    model's constants of the group's bodies and joints are gathered here once, not every step."""

    bodies: torch.Tensor  # [g] long
    parents: torch.Tensor  # [g] long
    kinds: tuple[str, ...]  # the kind of each body's k-th joint ("hinge" | "slide" | "ball" | "free")
    joints: tuple[torch.Tensor, ...]  # per kind, [g] long: each body's k-th joint
    qposadr: tuple[torch.Tensor, ...]  # per kind, [g] long: its first coordinate
    dofadr: tuple[torch.Tensor, ...]  # per kind, [g] long: its first dof
    body_pos: torch.Tensor  # [g, 3] each body's position in its parent's frame
    body_rot: torch.Tensor  # [g, 3, 3] its orientation in its parent's frame
    joint_axis: tuple[torch.Tensor, ...]  # per kind, [g, 3] the joint's axis (body frame)
    joint_pos: tuple[torch.Tensor, ...]  # per kind, [g, 3] its anchor (body frame)
    joint_skew: tuple[torch.Tensor, ...]  # per kind, [g, 3, 3] skew(axis), for Rodrigues
    joint_skew_squared: tuple[torch.Tensor, ...]  # per kind, [g, 3, 3] skew(axis)^2


def _body_groups(model: ArticulatedModel, body_joints: list[list[int]], t, idx, axis, skew) -> list[BodyGroup]:
    """The bodies (world excluded) grouped by depth and joint kinds, parents' groups first (``t``,
    ``idx``: arrays to the tree's float and index tensors; ``axis [njnt, 3]``, ``skew [njnt, 3, 3]``:
    the joints' unit axes and their skew matrices)."""
    depth = [0] * model.nbody
    for b in range(1, model.nbody):  # MuJoCo orders parents before children
        depth[b] = depth[model.body_parent[b]] + 1
    keys: dict[tuple, list[int]] = {}
    for b in range(1, model.nbody):
        keys.setdefault((depth[b], tuple(model.joint_type[j] for j in body_joints[b])), []).append(b)
    groups = []
    for (_, kinds), bodies in sorted(keys.items(), key=lambda item: (item[0][0], min(item[1]))):
        joints = [[body_joints[b][k] for b in bodies] for k in range(len(kinds))]
        per_joint = lambda values: tuple(t(np.asarray(values)[js]) for js in joints)  # noqa: E731
        groups.append(BodyGroup(idx(bodies), idx([model.body_parent[b] for b in bodies]), kinds,
                                tuple(idx(js) for js in joints),
                                tuple(idx([model.joint_qposadr[j] for j in js]) for js in joints),
                                tuple(idx([model.joint_dofadr[j] for j in js]) for js in joints),
                                t(np.asarray(model.body_pos)[bodies]), t(np.asarray(model.body_rot)[bodies]),
                                per_joint(np.asarray(axis).reshape(-1, 3)),
                                per_joint(np.asarray(model.joint_pos).reshape(-1, 3)),
                                per_joint(skew), per_joint(skew @ skew)))
    return groups


@dataclass
class RigidBodyTree:
    """The constant (non-parameter) part of an [`ArticulatedModel`][torchrl_diffenvs.articulated.ArticulatedModel], as tensors.

    Built once per env (device, dtype); the per-env physical parameters travel separately.
    """

    model: ArticulatedModel
    body_parent: list[int]
    body_pos: torch.Tensor  # [nbody, 3]
    body_rot: torch.Tensor  # [nbody, 3, 3]
    body_com: torch.Tensor  # [nbody, 3]
    site_body: torch.Tensor  # [nsite] long: the body each site is fixed to
    site_pos: torch.Tensor  # [nsite, 3] in its body's frame
    body_joints: list[list[int]]  # joints of each body, in order
    joint_type: list[str]  # "hinge" | "slide" | "ball" | "free"
    joint_qposadr: list[int]
    joint_dofadr: list[int]
    joint_axis: torch.Tensor  # [njnt, 3] body frame
    joint_pos: torch.Tensor  # [njnt, 3]
    joint_skew: torch.Tensor  # [njnt, 3, 3] skew(axis), for Rodrigues
    joint_skew_squared: torch.Tensor  # [njnt, 3, 3] skew(axis)^2
    body_groups: list[BodyGroup]  # the bodies in the groups forward kinematics poses together
    qpos0: torch.Tensor  # [nq]
    qpos_spring: torch.Tensor  # [nq]
    dof_qpos: torch.Tensor  # [nv] long: the coordinate of each hinge/slide dof (springs, limits); 0 elsewhere
    dof_has_spring: torch.Tensor  # [nv]: 1 for hinge/slide dofs (springs act on them), 0 for ball/free dofs
    position_segments: list[tuple]  # how qvel integrates into qpos (see integrate_position)
    body_dof_mask: torch.Tensor  # [nbody, nv]: dof d moves body b
    dof_pre_mask: torch.Tensor  # [nv, nv]: dof d' moves the frame dof d is attached to (d' before d)
    dof_support: torch.Tensor  # [nv, nv]: dof i moves the body of dof j (where M_ij = S_i . Ic_j S_j)
    # [nbody, nv (d), nv (j)]: moves[b, d] pre[d, j] - moves[b, j] pre[j, d], the weight of S_d qvel_d in the
    # change of body b's velocity-product acceleration per qvel_j (inertia.bias_velocity_jacobian)
    bias_carry: torch.Tensor
    contact_dof_mask: torch.Tensor  # [npoint, nv]: dof d moves the body of contact point p
    # joint limits (rows for the lower and upper side of every limited joint)
    limit_dof: torch.Tensor  # [nlimit] long
    limit_sign: torch.Tensor  # [nlimit] +1 lower side, -1 upper side (the constraint Jacobian)
    limit_value: torch.Tensor  # [nlimit] the range end
    limit_margin: torch.Tensor
    limit_solref: torch.Tensor  # [nlimit, 2]
    limit_solimp: torch.Tensor  # [nlimit, 5]
    kin0: object | None  # Kinematics at qpos0, for MuJoCo's dof_invweight0: see inertia.kinematics_at_qpos0
    # motors
    actuator_dof: torch.Tensor  # [nu] long
    actuator_gear: torch.Tensor
    ctrl_low: torch.Tensor
    ctrl_high: torch.Tensor
    force_low: torch.Tensor
    force_high: torch.Tensor
    # contact: points (capsule end spheres, spheres, box corners) against the ground planes
    contact_body: torch.Tensor  # [npoint] long
    contact_local: torch.Tensor  # [npoint, 3] body frame
    contact_radius: torch.Tensor  # [npoint]
    contact_slot: torch.Tensor  # [npoint] long: which contact pair (friction entry) it belongs to
    contact_plane_point: torch.Tensor  # [npoint, 3]
    contact_plane_normal: torch.Tensor  # [npoint, 3]
    contact_pairs: list[tuple[str, str]]  # (geom, plane), then (geom, geom), of each slot
    contact_pair_friction: np.ndarray  # [nslot] MuJoCo's max of the two geoms' sliding friction (0: condim 1)
    contact_frictional: torch.Tensor  # [npoint]: 0 where the geom-plane pair's larger condim is 1 (frictionless)
    # contact between two bodies' geoms: sphere-swept segments (a sphere's is a point), [npair]
    pair_body: torch.Tensor  # [npair, 2] long: bodies A and B
    pair_segment: torch.Tensor  # [npair, 2, 2, 3]: (A, B) x (start, end), each in its body's frame
    pair_radius: torch.Tensor  # [npair, 2]
    pair_slot: torch.Tensor  # [npair] long: its friction entry
    pair_dof_sign: torch.Tensor  # [npair, nv]: +1 dof moves B only, -1 A only, 0 both or neither
    pair_frictional: torch.Tensor  # [npair]: 1 where the pair's larger condim is above 1 (MuJoCo: 1 is frictionless)
    has_frictional_pairs: bool  # any of them (a Python bool: no device sync in the step)
    # dofs of MuJoCo's "simple" bodies (children of the world with orthogonal slides only and no
    # children): (dof, body) pairs, whose dof_invweight0 MuJoCo takes as 1 / mass (no armature)
    simple_dofs: list[tuple[int, int]]
    simple_dof_index: torch.Tensor  # [nsimple] long: those dofs
    simple_dof_body: torch.Tensor  # [nsimple] long: their bodies
    root_subtree_mask: torch.Tensor  # [nbody, nbody]: body c is in the subtree of body b's root (b = 0: all)
    # fixed tendons
    tendon_coef: torch.Tensor  # [ntendon, nv]
    tendon_springlength: torch.Tensor  # [ntendon]
    # fluid: each body's principal axes of inertia (its inertial frame) in the body frame
    body_inertial_frame: torch.Tensor  # [nbody, 3, 3]
    # how contact is simulated (see use_contact_model), and MuJoCo's contact slots
    contact_model: str = "mujoco"
    contact_slots: ContactSlots | None = None
    # why the smooth model cannot simulate this model's contacts (a pair it has no shape for); None: it can
    smooth_refusal: str | None = None
    # how the backward differentiates MuJoCo's constraint solve (see use_contact_gradient)
    contact_gradient: ContactGradient = ContactGradient()
    # the physics step the integrators call while a compiled rollout runs (see integrators.stepping_with); None: eager
    physics_stepper: Callable | None = None

    def use_contact_model(self, contact: str) -> RigidBodyTree:
        """Set how contacts are simulated: ``"mujoco"`` (MuJoCo's collision, constraint rows and
        solve: [`collision`][torchrl_diffenvs.articulated.collision], [`constraint`][torchrl_diffenvs.articulated.constraint]; the default) or ``"smooth"`` (the penalty
        model of `contact`, an approximation of MuJoCo's). Returns the tree."""
        if contact not in CONTACT_MODELS:
            raise ValueError(f"{self.model.path}: unknown contact model {contact!r}; valid: "
                             f"{', '.join(repr(c) for c in CONTACT_MODELS)}")
        if contact == "smooth" and self.smooth_refusal is not None:
            raise ValueError(f"{self.smooth_refusal}: use contact='mujoco' (MuJoCo's collision covers the "
                             "model), or set contype/conaffinity to exclude the pair")
        if contact == "mujoco" and self.contact_slots is None:
            self.contact_slots = contact_slots(self.model, self.contact_pairs, self.body_pos.dtype, self.body_pos.device)
        self.contact_model = contact
        return self

    def use_contact_gradient(self, gradient) -> RigidBodyTree:
        """Set how the backward differentiates MuJoCo's constraint solve: ``"exact"``, ``"cfd"``,
        ``"smooth"``, a mapping of [`ContactGradient`][torchrl_diffenvs.articulated.contact_gradient.ContactGradient]'s fields or one (the forward
        values are MuJoCo's in every mode). Only the ``"mujoco"`` contact model has the solve.
        Returns the tree."""
        gradient = ContactGradient.parse(gradient)
        if gradient.mode != "exact" and self.contact_model != "mujoco":
            raise ValueError(f"contact_gradient={gradient.mode!r} shapes the gradient of MuJoCo's constraint solve; "
                             f"this tree uses the {self.contact_model!r} contact model (valid there: 'exact')")
        if gradient.mode in ("cfd", "smooth") and self.model.cone == "elliptic":
            raise ValueError(f"contact_gradient={gradient.mode!r} shapes the solve of pyramidal friction cones; "
                             "this model's cones are elliptic (valid there: 'exact', 'penalty')")
        self.contact_gradient = gradient
        return self

    @property
    def has_fluid(self) -> bool:
        """Whether the model's medium (density or viscosity) exerts fluid forces."""
        return self.model.density > 0 or self.model.viscosity > 0

    @property
    def nv(self) -> int:
        """The number of degrees of freedom (the model's)."""
        return self.model.nv

    @property
    def nq(self) -> int:
        """The number of position coordinates (the model's)."""
        return self.model.nq

    @property
    def nbody(self) -> int:
        """The number of bodies, the world included (the model's)."""
        return self.model.nbody

    @classmethod
    def from_model(cls, model: ArticulatedModel, dtype=torch.float64, device="cpu", contact: str | None = None
                   ) -> RigidBodyTree:
        """The tree of ``model`` on ``device`` in ``dtype``, simulating contact with ``contact``
        ([`use_contact_model`][torchrl_diffenvs.articulated.RigidBodyTree.use_contact_model]; ``None``: ``"mujoco"`` where MuJoCo's collision here covers
        every geom pair of the model that can touch, else ``"smooth"``)."""
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
        idx = lambda a: torch.as_tensor(np.asarray(a, dtype=np.int64), device=device)  # noqa: E731
        nb, nv, njnt = model.nbody, model.nv, model.njnt
        body_joints = [[j for j in range(njnt) if model.joint_body[j] == b] for b in range(nb)]
        # the dofs of each joint in groups whose motion axes move together: a free joint's
        # translation, then its rotation; every other joint is one group
        groups = []  # (body, dofs)
        for j in range(njnt):
            first, kind, b = int(model.joint_dofadr[j]), model.joint_type[j], int(model.joint_body[j])
            if kind == "free":
                groups += [(b, list(range(first, first + 3))), (b, list(range(first + 3, first + 6)))]
            else:
                groups.append((b, list(range(first, first + (3 if kind == "ball" else 1)))))
        body_dofs = [[d for g, dofs in groups if g == b for d in dofs] for b in range(nb)]
        # dof d moves body b when d belongs to b or to one of its ancestors
        moves = np.zeros((nb, nv))
        pre = np.zeros((nv, nv))
        for b in range(1, nb):
            chain, a = [], b
            while a > 0:
                chain.append(a)
                a = model.body_parent[a]
            for a in chain:
                moves[b, body_dofs[a]] = 1.0
        # pre[d]: the dofs that move the frame d's axis is attached to: the parent's, and the earlier
        # groups of its own body (not its own group: MuJoCo's cdof_dot of a ball joint uses the parent's
        # velocity; the group's own rotation drops out of the bias force, w x w = 0)
        for i, (b, dofs) in enumerate(groups):
            earlier = [d for g, ds in groups[:i] if g == b for d in ds]
            for d in dofs:
                pre[d] = moves[model.body_parent[b]]
                pre[d, earlier] = 1.0
        dof_body = [b for b, dofs in groups for _ in dofs]
        axis = model.joint_axis
        skew = np.stack([np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]) for a in axis]) \
            if njnt else np.zeros((0, 3, 3))
        dof_qpos, dof_has_spring = np.zeros(nv, dtype=np.int64), np.zeros(nv)
        segments = []  # ("linear", qpos start, dof start, length) | ("quaternion", qpos start, dof start)
        for j in range(njnt):
            kind, qa, da = model.joint_type[j], int(model.joint_qposadr[j]), int(model.joint_dofadr[j])
            if kind in ("hinge", "slide"):
                dof_qpos[da], dof_has_spring[da] = qa, 1.0
            if kind == "free":
                segments += [("linear", qa, da, 3), ("quaternion", qa + 3, da + 3)]
            elif kind == "ball":
                segments.append(("quaternion", qa, da))
            elif segments and segments[-1][0] == "linear" and segments[-1][1] + segments[-1][3] == qa:
                segments[-1] = ("linear", segments[-1][1], segments[-1][2], segments[-1][3] + 1)
            else:
                segments.append(("linear", qa, da, 1))
        # joint limits: one row per side
        rows = [(j, side) for j in range(njnt) if model.limited[j] for side in (0, 1)]
        limit_dof = [int(model.joint_dofadr[j]) for j, _ in rows]
        # contact points against each plane of the world body
        points, pairs, pair_friction = [], [], []

        def friction(g1, g2):  # MuJoCo: the larger condim and the larger sliding friction of the two
            return 0.0 if max(model.geom_condim[g1], model.geom_condim[g2]) == 1 else \
                max(model.geom_friction[g1, 0], model.geom_friction[g2, 0])
        frictional = []  # per slot

        planes = [g for g in range(len(model.geom_names)) if model.geom_type[g] == "plane"]
        for p in planes:
            if model.geom_body[p] != 0:
                raise ValueError(f"{model.path}: plane {model.geom_names[p]!r} must belong to the world body")
        for g in range(len(model.geom_names)):
            if model.geom_body[g] == 0 or model.geom_type[g] == "plane":
                continue
            for p in planes:
                collide = (model.geom_contype[g] & model.geom_conaffinity[p]) or (
                    model.geom_contype[p] & model.geom_conaffinity[g])
                if not collide:
                    continue
                slot = len(pairs)
                pairs.append((model.geom_names[g], model.geom_names[p]))
                pair_friction.append(friction(g, p))
                frictional.append(max(model.geom_condim[g], model.geom_condim[p]) > 1)
                if _slides_along(model, int(model.geom_body[g]), model.geom_rot[p][:, 2]):
                    continue  # the pair keeps its friction entry (MuJoCo's contact has it) but no smooth points
                local = _contact_points(model, g)
                normal = model.geom_rot[p][:, 2]
                for offset, radius in local:
                    points.append((model.geom_body[g], offset, radius, slot, model.geom_pos[p], normal))
        geom_pairs = []  # (A, B, A's segment, B's segment, radii, slot)
        smooth_refusal = None  # why the smooth model cannot simulate this model's contacts (None: it can)
        for g1, g2 in _colliding_geom_pairs(model):
            try:
                cores = _segment(model, g1), _segment(model, g2)
            except ValueError as error:
                smooth_refusal = smooth_refusal or str(error)
            else:
                geom_pairs.append((model.geom_body[g1], model.geom_body[g2], *cores,
                                   (model.geom_size[g1, 0], model.geom_size[g2, 0]), len(pairs),
                                   max(model.geom_condim[g1], model.geom_condim[g2]) > 1))
            pairs.append((model.geom_names[g1], model.geom_names[g2]))
            pair_friction.append(friction(g1, g2))
        tendon_coef = np.asarray(model.tendon_coef).reshape(len(model.tendon_names), nv)
        simple_dofs = []
        for b in range(1, nb):
            joints = body_joints[b]
            axes = model.joint_axis[joints] if joints else np.zeros((0, 3))
            if (model.body_parent[b] == 0 and joints and all(model.joint_type[j] == "slide" for j in joints)
                    and b not in model.body_parent and np.allclose(axes @ axes.T, np.eye(len(joints)))):
                simple_dofs += [(int(model.joint_dofadr[j]), b) for j in joints]
        tree = cls(
            model=model, body_parent=[int(p) for p in model.body_parent], body_pos=t(model.body_pos),
            body_rot=t(model.body_rot), body_com=t(model.body_com), body_joints=body_joints,
            site_body=idx(model.site_body), site_pos=t(model.site_pos).reshape(-1, 3),
            joint_type=list(model.joint_type), joint_qposadr=[int(a) for a in model.joint_qposadr],
            joint_dofadr=[int(a) for a in model.joint_dofadr], joint_axis=t(axis).reshape(njnt, 3),
            joint_pos=t(model.joint_pos).reshape(njnt, 3), joint_skew=t(skew),
            joint_skew_squared=t(skew @ skew), body_groups=_body_groups(model, body_joints, t, idx, axis, skew), qpos0=t(model.qpos0),
            qpos_spring=t(model.qpos_spring), dof_qpos=idx(dof_qpos), dof_has_spring=t(dof_has_spring),
            position_segments=segments, body_dof_mask=t(moves), dof_pre_mask=t(pre),
            dof_support=t(moves[dof_body].T.reshape(nv, nv)),
            bias_carry=t(np.asarray(moves)[:, :, None] * np.asarray(pre)[None]
                         - np.asarray(moves)[:, None, :] * np.asarray(pre).T[None]),
            contact_dof_mask=t(moves[[p[0] for p in points]].reshape(len(points), nv)),
            limit_dof=idx(limit_dof), limit_sign=t([1.0 if s == 0 else -1.0 for _, s in rows]),
            limit_value=t([model.joint_range[j, s] for j, s in rows]),
            limit_margin=t([model.limit_margin[j] for j, _ in rows]),
            # MuJoCo's "refsafe": a time constant below two physics steps is raised to two steps
            limit_solref=t([[max(model.limit_solref[j, 0], 2 * model.timestep), model.limit_solref[j, 1]]
                            for j, _ in rows]).reshape(len(rows), 2),
            limit_solimp=t([model.limit_solimp[j] for j, _ in rows]).reshape(len(rows), 5),
            kin0=None,
            actuator_dof=idx(model.joint_dofadr[model.actuator_joint]), actuator_gear=t(model.actuator_gear),
            ctrl_low=t(np.where(model.ctrl_limited, model.ctrl_range[:, 0], -np.inf)),
            ctrl_high=t(np.where(model.ctrl_limited, model.ctrl_range[:, 1], np.inf)),
            force_low=t(np.where(model.force_limited, model.force_range[:, 0], -np.inf)),
            force_high=t(np.where(model.force_limited, model.force_range[:, 1], np.inf)),
            contact_body=idx([p[0] for p in points]), contact_local=t([p[1] for p in points]).reshape(-1, 3),
            contact_radius=t([p[2] for p in points]), contact_slot=idx([p[3] for p in points]),
            contact_plane_point=t([p[4] for p in points]).reshape(-1, 3),
            contact_plane_normal=t([p[5] for p in points]).reshape(-1, 3),
            contact_pairs=pairs, contact_pair_friction=np.array(pair_friction),
            contact_frictional=t([float(frictional[p[3]]) for p in points]),
            pair_body=idx([[p[0], p[1]] for p in geom_pairs]).reshape(-1, 2),
            pair_segment=t([[p[2], p[3]] for p in geom_pairs]).reshape(-1, 2, 2, 3),
            pair_radius=t([p[4] for p in geom_pairs]).reshape(-1, 2),
            pair_slot=idx([p[5] for p in geom_pairs]), pair_frictional=t([float(p[6]) for p in geom_pairs]),
            has_frictional_pairs=any(p[6] for p in geom_pairs),
            pair_dof_sign=t(np.array([moves[p[1]] - moves[p[0]] for p in geom_pairs]).reshape(-1, nv)),
            tendon_coef=t(tendon_coef), tendon_springlength=t(model.tendon_springlength), simple_dofs=simple_dofs,
            simple_dof_index=idx([d for d, _ in simple_dofs]), simple_dof_body=idx([b for _, b in simple_dofs]),
            root_subtree_mask=t(_root_subtree_mask(model)),
            body_inertial_frame=t(np.linalg.eigh(model.body_inertia)[1]),
            smooth_refusal=smooth_refusal,
        )
        missing = unsupported_pairs(model)
        if missing and smooth_refusal is not None:
            raise ValueError(f"{smooth_refusal}, and MuJoCo's contact model here has no primitive for "
                             f"{', '.join(f'{a!r}-{b!r}' for a, b in missing)}: neither contact model covers "
                             "the model (set contype/conaffinity to exclude those pairs)")
        if contact is None:
            contact = "smooth" if missing else "mujoco"
        return tree.use_contact_model(contact)


def _slides_along(model: ArticulatedModel, body: int, normal: np.ndarray) -> bool:
    """Whether only slides parallel to a plane move ``body`` (the Pusher's object on its table):
    its contact with that plane could push it along no dof, so the smooth model gives it no
    contact points (MuJoCo's computes it, to no effect; the pair keeps its friction entry)."""
    rot, chain = np.eye(3), []
    while body != 0:
        chain.append(body)
        body = int(model.body_parent[body])
    joints = [j for j in range(model.njnt) if model.joint_body[j] in chain]
    if not joints or any(model.joint_type[j] != "slide" for j in joints):
        return False
    for b in reversed(chain):  # slides do not turn anything: the world axes are the file's
        rot = rot @ model.body_rot[b]
        if any(abs((rot @ model.joint_axis[j]) @ normal) > 1e-12 for j in joints if model.joint_body[j] == b):
            return False
    return True


def _root_subtree_mask(model: ArticulatedModel) -> np.ndarray:
    """``mask[b, c] = 1`` where body ``c`` is in the subtree of ``b``'s root (MuJoCo's
    ``body_rootid``; the world's root is the world, whose subtree is every body)."""
    parent = [int(p) for p in model.body_parent]
    root = [0] * len(parent)
    for b in range(1, len(parent)):
        root[b] = b if parent[b] == 0 else root[parent[b]]
    return np.array([[1.0 if b == 0 or root[c] == root[b] else 0.0 for c in range(len(parent))]
                     for b in range(len(parent))])


def _colliding_geom_pairs(model: ArticulatedModel) -> list[tuple[int, int]]:
    """The geom pairs (neither a plane; lower index first) that MuJoCo's collision filter lets
    touch ([`colliding_pairs`][torchrl_diffenvs.articulated.collision.colliding_pairs]), for the smooth model's body-body contacts."""
    out = []
    for g1, g2 in sorted(tuple(sorted(pair)) for pair in colliding_pairs(model)):
        if "plane" in (model.geom_type[g1], model.geom_type[g2]):
            continue
        if 0 in (_weld(model, int(model.geom_body[g1])), _weld(model, int(model.geom_body[g2]))):
            raise ValueError(f"{model.path}: geoms {model.geom_names[g1]!r} and {model.geom_names[g2]!r}: contact "
                             "with a static geom other than a plane is not modelled (set contype/conaffinity "
                             "to exclude it)")
        out.append((g1, g2))
    return out


def _segment(model: ArticulatedModel, g: int) -> np.ndarray:
    """``[2, 3]`` the geom's core segment in its body frame: the geom is the set of points within
    its radius of it. A sphere's is its centre (twice), a capsule's its axis; a cylinder is
    taken as the capsule inscribed in it (its axis shortened by the radius at both ends: exact on
    its side between the ends' rounding, never larger than the cylinder)."""
    kind, size, pos, rot = model.geom_type[g], model.geom_size[g], model.geom_pos[g], model.geom_rot[g]
    if kind == "sphere":
        return np.stack([pos, pos])
    if kind in ("capsule", "cylinder"):
        length = size[1] if kind == "capsule" else max(size[1] - size[0], 0.0)
        half = rot[:, 2] * length
        return np.stack([pos - half, pos + half])
    raise ValueError(
        f"{model.path}: geom {model.geom_names[g]!r} of type {kind} can touch another body's geom, but the "
        "smooth contact model shapes contact between bodies only for spheres, capsules and cylinders")


def _contact_points(model: ArticulatedModel, g: int) -> list[tuple[np.ndarray, float]]:
    """Sphere-swept points (body-frame centre, radius) whose distance to a plane is the geom's."""
    kind, size, pos, rot = model.geom_type[g], model.geom_size[g], model.geom_pos[g], model.geom_rot[g]
    if kind == "sphere":
        return [(pos, size[0])]
    if kind == "capsule":
        half = rot[:, 2] * size[1]
        return [(pos - half, size[0]), (pos + half, size[0])]
    if kind == "box":
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
        return [(pos + rot @ c, 0.0) for c in corners]
    if kind == "cylinder":  # the rims of its two flat ends, 8 points each
        angles = np.arange(8) * (2 * np.pi / 8)
        rim = [np.array([size[0] * np.cos(a), size[0] * np.sin(a), sz * size[1]]) for sz in (-1, 1) for a in angles]
        return [(pos + rot @ c, 0.0) for c in rim]
    raise ValueError(
        f"{model.path}: geom {model.geom_names[g]!r} of type {kind} can touch the ground plane, but ground "
        "contact is only modelled for spheres, capsules, cylinders and boxes (set contype/conaffinity to exclude it)"
    )


def default_params(model: ArticulatedModel) -> dict[str, torch.Tensor]:
    """The model file's physical parameters (float64, unbatched): the per-env ``params`` defaults.

    Args:
        model: the parsed model file.

    Returns:
        ``body_mass``, ``body_inertia``, ``gravity``, ``damping``, ``armature`` and ``stiffness``;
        ``fluid_density`` and ``fluid_viscosity`` for a model in a fluid, ``tendon_stiffness`` and
        ``tendon_damping`` for a model with tendons.
    """
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    params = {
        "body_mass": t(model.body_mass), "body_inertia": t(model.body_inertia), "gravity": t(model.gravity),
        # stiffness per dof, as damping (a joint's stiffness on its dof; ball and free joints have none)
        "damping": t(model.damping), "armature": t(model.armature), "stiffness": t(model.stiffness[model.dof_joint]),
    }
    if model.density > 0 or model.viscosity > 0:
        params.update(fluid_density=t(model.density), fluid_viscosity=t(model.viscosity))
    if len(model.tendon_names):
        params.update(tendon_stiffness=t(model.tendon_stiffness), tendon_damping=t(model.tendon_damping))
    return params
