"""Capsule against box, ``articulated.capsule_box``, against MuJoCo's ``mjc_CapsuleBox``.

Oracle: the installed MuJoCo's ``mj_forward`` on a model of two free bodies (a capsule and a box,
no gravity, 2 mm margin each): its contacts (``d.ncon``, ``d.contact.dist/pos/frame``) at the same
geom poses, to 1e-12 in float64 (from our own kinematics, whose rotations differ from MuJoCo's by
rounding, to 1e-10); its ``mj_step`` for a capsule dropped on a box lying on the floor, to 1e-9.
Which of MuJoCo's branches a pose takes is read from the geometry by an independent helper
(`_branch`). Gradients: ``torch.autograd.gradcheck`` (finite differences, float64) in each branch;
finite gradients at degenerate poses.
"""
import types

import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from torchrl_diffenvs.articulated import RigidBodyTree, forward_kinematics, load_mjcf  # noqa: E402
from torchrl_diffenvs.articulated.collision import collide  # noqa: E402

from _mujoco_steps import gaps_to_mj_step  # noqa: E402

RADIUS, LENGTH = 0.02, 0.1  # the capsule's radius and half-length
HALF = np.array([0.05, 0.08, 0.11])  # the box's half-sizes: all different, a swapped axis shows
BOX_AT = np.array([0.3, -0.2, 0.1])  # the box's centre (world)
PAIR = f"""<mujoco><option gravity="0 0 0"/><worldbody>
    <body name="capsule"><freejoint/><geom name="capsule" type="capsule" size="{RADIUS} {LENGTH}" margin="0.002"/></body>
    <body name="box"><freejoint/><geom name="box" type="box" size="{HALF[0]} {HALF[1]} {HALF[2]}" margin="0.002"/></body>
    </worldbody></mujoco>"""


def _pair(tmp_path, dtype=torch.float64):
    path = tmp_path / "pair.xml"
    path.write_text(PAIR)
    tree = RigidBodyTree.from_model(load_mjcf(str(path)), dtype=dtype)
    mm = mujoco.MjModel.from_xml_path(str(path))
    return tree, mm, mujoco.MjData(mm)


def _quat_mul(a, b):
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    return out


def _rotation(quat):
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, dtype=np.float64))
    return out.reshape(3, 3)


def _quat_from_z(direction, twist=0.0):
    """A unit quaternion turning z onto ``direction`` (after a turn ``twist`` about z)."""
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    axis = np.cross([0.0, 0.0, 1.0], d)
    if np.linalg.norm(axis) < 1e-300:
        turn = np.array([1.0, 0.0, 0.0, 0.0]) if d[2] > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    else:
        angle = np.arctan2(np.linalg.norm(axis), d[2])
        turn = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)])
    return _quat_mul(turn, [np.cos(twist / 2), 0.0, 0.0, np.sin(twist / 2)])


def _qpos(centre, capsule_quat, box_quat):
    """The two free joints' qpos for a capsule at ``centre`` turned by ``capsule_quat``, both in the
    box's frame, and the box at BOX_AT turned by ``box_quat``."""
    return np.concatenate([BOX_AT + _rotation(box_quat) @ centre, _quat_mul(box_quat, capsule_quat), BOX_AT, box_quat])


def _segment_box(centre, axis, half=HALF):
    """``(t, distance)``: the point ``centre + t LENGTH axis`` (``t`` in [-1, 1], the box's frame) of
    the segment nearest the box (half-sizes ``half``) and its distance, by golden section on the
    distance (convex in ``t``); vectorised over the rows of ``centre`` and ``axis``."""
    def distance(t):
        x = centre + (t * LENGTH)[:, None] * axis
        return np.linalg.norm(x - np.clip(x, -half, half), axis=1)

    golden = (5 ** 0.5 - 1) / 2
    lo, hi = -np.ones(len(centre)), np.ones(len(centre))
    for _ in range(100):
        a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
        left = distance(a) < distance(b)
        lo, hi = np.where(left, lo, a), np.where(left, b, hi)
    candidates = np.stack([(lo + hi) / 2, -np.ones_like(lo), np.ones_like(lo)], axis=1)
    values = np.stack([distance(c) for c in candidates.T], axis=1)
    best = values.argmin(1)
    return candidates[np.arange(len(best)), best], values[np.arange(len(best)), best]


def _branches(centres, axes, half=HALF) -> list[str]:
    """MuJoCo's branch for capsules at ``centres`` along ``axes`` (the box's frame), from the
    geometry (`_branch`)."""
    ts, gaps = _segment_box(centres, axes, half)
    return [_branch(*args, half) for args in zip(centres, axes, ts, gaps)]


def _branch(centre, axis, t, gap, half) -> str:
    """MuJoCo's branch for a capsule at ``centre`` along ``axis`` (the box's frame; ``t``, ``gap``:
    `_segment_box`), from the geometry: an end inside the box, the segment crossing it, or the box's
    point nearest the segment on a face, an edge or a corner, with (edge, corner) how the axis lies
    against that feature, which decides MuJoCo's second contact: across an edge (an X seen along
    it) or square to it (a T); pointing at a corner (into or out of its octant), along one of its
    edges or along a face."""
    if any(np.all(np.abs(centre + s * LENGTH * axis) <= half) for s in (-1, 1)):
        return "end inside"
    if gap < 1e-9:
        return "crossing"
    x = centre + t * LENGTH * axis
    out = np.abs(x) > half
    agree = (axis > 0) == (x > 0)  # the axis points outwards along k (MuJoCo's axisdir ^ corner)
    if out.sum() == 1:
        return "face"
    if out.sum() == 2:
        u, v = np.flatnonzero(out)
        return "edge, across it" if agree[u] != agree[v] else "edge, square to it"
    if agree.all() or not agree.any():
        return "corner, pointing at it"
    odd = int(np.flatnonzero(agree != (agree.sum() > 1))[0])
    return "corner, along an edge" if axis[odd] ** 2 > 0.5 else "corner, along a face"


ONE_CONTACT = {"end inside", "edge, square to it", "corner, pointing at it"}
TWO_CONTACTS = {"face", "edge, across it", "corner, along an edge", "corner, along a face"}


def _tilted(direction, normal, angle):
    """``direction`` turned by ``angle`` towards ``normal`` (a unit vector square to it)."""
    return np.cos(angle) * direction + np.sin(angle) * normal


def _poses(rng) -> tuple[np.ndarray, list[str]]:
    """qpos of the pair (about 1000) and what each tests: random poses within reach of the box (some
    penetrating deeply, some just out of reach), the axis nearly parallel to a face and to an edge
    (by 1e-3 to 1e-10 rad), and exactly parallel to them (an unturned box)."""
    random_quat = lambda: (lambda q: q / np.linalg.norm(q))(rng.normal(size=4))  # noqa: E731
    poses, kinds = [], []
    # anywhere within reach: kept where the capsule touches (or nearly touches) the box
    count = 6000
    centres = rng.uniform(-(HALF + LENGTH + 0.03), HALF + LENGTH + 0.03, (count, 3))
    quats = rng.normal(size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    axes = np.stack([_rotation(q)[:, 2] for q in quats])
    _, gaps = _segment_box(centres, axes)
    near, far = np.flatnonzero(gaps < RADIUS + 0.006)[:650], np.flatnonzero((gaps > RADIUS + 0.006) & (gaps < 0.05))[:50]
    for k in np.concatenate([near, far]):
        poses.append(_qpos(centres[k], quats[k], random_quat()))
        kinds.append("random")
    for _ in range(80):  # deep: the centre inside the box
        poses.append(_qpos(rng.uniform(-HALF, HALF), random_quat(), random_quat()))
        kinds.append("deep")
    for _ in range(30):  # an end beyond a corner, the axis in the corner's octant (rare above)
        sign = rng.choice([-1.0, 1.0], 3)
        out, axis = np.abs(rng.normal(size=(2, 3))) * sign
        out, axis = out / np.linalg.norm(out), axis / np.linalg.norm(axis)
        centre = sign * HALF + out * (RADIUS + rng.uniform(-0.008, 0.003)) + axis * LENGTH
        poses.append(_qpos(centre, _quat_from_z(axis * rng.choice([-1.0, 1.0]), rng.uniform(0, 6.3)), random_quat()))
        kinds.append("at a corner")
    angles = [1e-10, 1e-7, 1e-5, 1e-3]
    for k in range(100):  # nearly parallel to a face (the capsule over it, its edges, its corners)
        face, sign = k % 3, rng.choice([-1.0, 1.0])
        normal = np.eye(3)[face] * sign
        direction = np.cross(normal, rng.normal(size=3))
        direction /= np.linalg.norm(direction)
        centre = rng.uniform(-HALF - 0.03, HALF + 0.03)
        centre[face] = sign * (HALF[face] + RADIUS + rng.uniform(-0.01, 0.003))
        axis = _tilted(direction, normal, angles[k % 4] * rng.choice([-1.0, 1.0]))
        poses.append(_qpos(centre, _quat_from_z(axis, rng.uniform(0, 6.3)), random_quat()))
        kinds.append("nearly parallel to a face")
    for k in range(80):  # nearly parallel to an edge, beside it
        edge = k % 3
        u, v = (edge + 1) % 3, (edge + 2) % 3
        side = rng.choice([-1.0, 1.0], 2)
        centre = np.zeros(3)
        centre[edge] = rng.uniform(-HALF[edge], HALF[edge])
        reach = (RADIUS + rng.uniform(-0.008, 0.003)) / np.sqrt(2)
        centre[u], centre[v] = side[0] * (HALF[u] + reach), side[1] * (HALF[v] + reach)
        tilt = rng.normal(size=3)
        tilt[edge] = 0.0
        axis = _tilted(np.eye(3)[edge], tilt / np.linalg.norm(tilt), angles[k % 4])
        poses.append(_qpos(centre, _quat_from_z(axis, rng.uniform(0, 6.3)), random_quat()))
        kinds.append("nearly parallel to an edge")
    # exactly parallel (an unturned box; these quaternions give MuJoCo's matrix exact zeros)
    half_turn = np.sqrt(0.5)
    for k in range(90):
        phi = rng.uniform(0, 6.3) if k % 3 == 0 else (0.0 if k % 3 == 1 else np.pi / 2)
        c, s = np.cos(phi / 2), np.sin(phi / 2)
        quat = [c * half_turn, c * half_turn, s * half_turn, s * half_turn]  # z turned into the xy plane
        if k % 6 == 5:
            quat = [c, 0.0, 0.0, s]  # along z
        centre = rng.uniform(-HALF - 0.05, HALF + 0.05)
        centre[2] = rng.choice([-1.0, 1.0]) * (HALF[2] + RADIUS + rng.uniform(-0.01, 0.003))
        if k % 6 == 5:  # beside an x face
            centre[0] = rng.choice([-1.0, 1.0]) * (HALF[0] + RADIUS + rng.uniform(-0.01, 0.003))
            centre[2] = rng.uniform(-HALF[2] - 0.05, HALF[2] + 0.05)
        poses.append(np.concatenate([BOX_AT + centre, quat, BOX_AT, [1.0, 0.0, 0.0, 0.0]]))
        kinds.append("exactly parallel")
    return np.array(poses), kinds


def _mujoco_kinematics(mm, data, poses):
    """MuJoCo's body poses at each qpos (a stand-in for ours, to compare the primitive alone)."""
    xpos, xmat = [], []
    for pose in poses:
        data.qpos[:] = pose
        mujoco.mj_kinematics(mm, data)
        xpos.append(data.xpos.copy())
        xmat.append(data.xmat.reshape(-1, 3, 3).copy())
    return types.SimpleNamespace(body_pos=torch.as_tensor(np.array(xpos)), body_rot=torch.as_tensor(np.array(xmat)))


@pytest.mark.filterwarnings("ignore")
def test_capsule_box_matches_mj_collision(tmp_path):
    """MuJoCo's ``mjc_CapsuleBox`` at about 1000 poses: the same contacts in the same order (count,
    distance, position, frame), in each of its branches, from MuJoCo's geom poses to 1e-12.

    From our own poses (``forward_kinematics``), whose rotations differ from MuJoCo's by rounding
    (2e-16), the same to 1e-10, except at an exactly parallel axis: where MuJoCo's rotation has an
    exact zero ours can have 2e-16, whose sign turns MuJoCo's branch. The normal of a sphere whose
    centre is just outside the box amplifies the rounding (to 2e-12 here)."""
    tree, mm, data = _pair(tmp_path)
    assert tree.contact_model == "mujoco"
    poses, kinds = _poses(np.random.default_rng(0))
    theirs = _mujoco_kinematics(mm, data, poses)
    exact = collide(tree.contact_slots, theirs)
    ours = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses)))
    generic = [k for k, kind in enumerate(kinds) if kind in ("random", "deep", "at a corner")]
    rot = theirs.body_rot[generic, 2].numpy()  # the box's frame
    centres = (rot.transpose(0, 2, 1) @ (theirs.body_pos[generic, 1] - theirs.body_pos[generic, 2]).numpy()[..., None])
    axes = rot.transpose(0, 2, 1) @ theirs.body_rot[generic, 1, :, 2:].numpy()
    # (a nearly parallel axis makes MuJoCo skip an edge, and its branch is no longer the geometry's)
    branches = dict(zip(generic, _branches(centres[..., 0], axes[..., 0])))
    seen = {}
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        for c, tolerance in ((exact, 1e-12), (ours, 1e-10)):
            if c is ours and kinds[k] == "exactly parallel":
                continue  # our rotation's zeros are MuJoCo's to 2e-16 only: a sign can change the branch
            active = np.flatnonzero(c.active[k].numpy())
            assert len(active) == data.ncon, (k, kinds[k], c.dist[k], data.contact.dist[:data.ncon])
            for i, j in zip(active, range(data.ncon)):  # in MuJoCo's order
                gap = max(abs(c.dist[k, i].item() - data.contact.dist[j]),
                          np.abs(c.pos[k, i].numpy() - data.contact.pos[j]).max(),
                          np.abs(c.frame[k, i].numpy().ravel() - data.contact.frame[j]).max())
                assert gap < tolerance, (k, kinds[k], i, gap)
        seen.setdefault(kinds[k], set()).add(data.ncon)
        if k in branches:
            if branches[k] in ONE_CONTACT:
                assert data.ncon <= 1, (k, branches[k])
            seen.setdefault(branches[k], set()).add(data.ncon)
    for branch in ONE_CONTACT | TWO_CONTACTS | {"crossing"}:
        assert 1 in seen.get(branch, ()), (branch, seen)
    for branch in TWO_CONTACTS:
        assert 2 in seen[branch], (branch, seen)
    for kind in ("random", "deep", "nearly parallel to a face", "nearly parallel to an edge", "exactly parallel"):
        assert {1, 2} <= seen[kind], (kind, seen)
    assert 0 in seen["random"]


BOX_QUAT = np.array([0.96, 0.2, 0.1, 0.15]) / np.linalg.norm([0.96, 0.2, 0.1, 0.15])


def _by_a_corner(axis, offset, along=1.0):
    """``(centre, axis)``: a capsule along ``axis`` whose point at ``along`` (-1 to 1) lies
    ``offset`` from the box's (+, +, +) corner."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return HALF + np.asarray(offset) - along * LENGTH * axis, axis


# (centre, axis) in the box's frame, MuJoCo's branch and its number of contacts there
GRADIENT_POSES = [
    ([0.0, 0.02, 0.127], [0.1, 1.0, 0.05], "face", 2),
    ([0.01, 0.0, 0.228], [0.1, 0.15, 1.0], "face", 1),
    ([0.0, 0.085, 0.128], [0.3, 1.0, -0.03], "edge, across it", 2),
    ([0.01, 0.162, 0.192], [0.3, 1.0, 1.0], "edge, square to it", 1),
    (*_by_a_corner([-1.0, 0.03, 0.02], [0.004, 0.008, 0.008], -1.0), "corner, along an edge", 2),
    ([0.0951, 0.1217, 0.1204], [-0.718, -0.685, 0.126], "corner, along a face", 2),
    (*_by_a_corner([1.0, 0.8, 1.2], [0.004, 0.008, 0.008], -1.0), "corner, pointing at it", 1),
    ([0.01, 0.02, 0.16], [0.1, 0.2, 1.0], "end inside", 1),
    ([0.0, 0.07, 0.1], [1.0, 0.3, 0.4], "crossing", 1),
]


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("centre,axis,branch,count", GRADIENT_POSES, ids=[f"{p[2]}-{p[3]}" for p in GRADIENT_POSES])
def test_capsule_box_gradcheck(tmp_path, centre, axis, branch, count):
    """The gradient of both contacts (distance, position, normal) w.r.t. the capsule's centre and
    the box's orientation, in each of MuJoCo's branches (the pose in the box's frame, checked
    against MuJoCo's contact count and the geometry's branch)."""
    tree, mm, data = _pair(tmp_path)
    centre, axis = np.asarray(centre, dtype=np.float64), np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    assert _branches(centre[None], axis[None]) == [branch]
    qpos = _qpos(centre, _quat_from_z(axis, 0.3), BOX_QUAT)
    data.qpos[:] = qpos
    mujoco.mj_forward(mm, data)
    assert data.ncon == count
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(qpos).unsqueeze(0)))
    assert c.active[0].sum().item() == count and bool(c.found[0].all()) == (branch in TWO_CONTACTS)
    for i, j in zip(np.flatnonzero(c.active[0].numpy()), range(count)):
        assert c.dist[0, i].item() == pytest.approx(data.contact.dist[j], abs=1e-12)
        np.testing.assert_allclose(c.pos[0, i].numpy(), data.contact.pos[j], atol=1e-12)
    rest = torch.as_tensor(qpos[3:]).unsqueeze(0)

    def contact(position, turn):
        q = rest.clone()
        q[:, 7:] = rest[:, 7:] + turn
        q = torch.cat([position, q[:, :7], q[:, 7:] / q[:, 7:].norm(dim=-1, keepdim=True)], dim=-1)
        c = collide(tree.contact_slots, forward_kinematics(tree, q))
        return c.dist, c.pos, c.frame[:, :, 0]

    position = torch.as_tensor(qpos[:3]).unsqueeze(0).requires_grad_(True)
    # fast mode: the Jacobian against finite differences along random directions (any wrong entry shows)
    torch.autograd.gradcheck(contact, (position, torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)),
                             fast_mode=True)


# (capsule centre in the box's frame, capsule quaternion) with an unturned box: exact zeros in both
# MuJoCo's rotation and ours, so the degenerate case is met exactly
DEGENERATE = {
    "centred in the box, along z": ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
    "an end on a face, along z": ([0.01, 0.02, 0.21], [1.0, 0.0, 0.0, 0.0]),
    "an end on a face, along x": ([0.15, 0.01, -0.03], [0.5, 0.5, 0.5, 0.5]),
    "flat on a face": ([0.0, 0.01, 0.127], [0.5, 0.5, 0.5, 0.5]),
    "along an edge": ([0.0, 0.092, 0.12], [0.5, 0.5, 0.5, 0.5]),
    "square to a face, its axis through an edge": ([0.0, 0.08, 0.228], [1.0, 0.0, 0.0, 0.0]),
}


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_capsule_box_gradients_are_finite_at_degenerate_poses(tmp_path, dtype):
    """The axis exactly parallel to faces and edges, the capsule centred in the box, an end exactly
    on a face: MuJoCo's contacts (float64), and finite gradients of every output w.r.t. qpos, also
    through the branches not taken (an edge parallel to the axis, a zero axis component divided by)."""
    tree, mm, data = _pair(tmp_path, dtype)
    poses = np.array([np.concatenate([BOX_AT + centre, quat, BOX_AT, [1.0, 0.0, 0.0, 0.0]])
                      for centre, quat in DEGENERATE.values()])
    qpos = torch.as_tensor(poses, dtype=dtype).requires_grad_(True)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        active = np.flatnonzero(c.active[k].numpy())
        assert data.ncon > 0 and len(active) > 0, list(DEGENERATE)[k]
        if dtype == torch.float32:
            continue  # (float32's rounding moves these poses off their ties: another branch, as MuJoCo's would)
        assert len(active) == data.ncon, (list(DEGENERATE)[k], data.ncon)
        for i, j in zip(active, range(data.ncon)):
            assert c.dist[k, i].item() == pytest.approx(data.contact.dist[j], abs=1e-12)
            np.testing.assert_allclose(c.pos[k, i].detach().numpy(), data.contact.pos[j], atol=1e-12)
            np.testing.assert_allclose(c.frame[k, i].detach().numpy().ravel(), data.contact.frame[j], atol=1e-12)
    for output in (c.dist, c.pos, c.frame):
        (grad,) = torch.autograd.grad(output.sum(), qpos, retain_graph=True)
        assert torch.isfinite(grad).all(), list(DEGENERATE)


CAPSULE_ON_A_BOX = """<mujoco><option timestep="0.005"/><worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="box" pos="0 0 0.05"><freejoint/><geom name="box" type="box" size="0.15 0.12 0.05"/></body>
    <body name="capsule" pos="-0.05 0.02 0.16" euler="80 20 10"><freejoint/>
        <geom name="capsule" type="capsule" size="0.02 0.1"/></body>
    </worldbody></mujoco>"""


@pytest.mark.filterwarnings("ignore")
def test_a_capsule_dropped_on_a_box_steps_as_mj_step(tmp_path):
    """A capsule falls tilted and spinning onto a box lying on the floor, bounces, slides and spins
    lying on its top (MuJoCo's face branch), across its edges (the edge branch) and by a corner, and
    falls off onto the floor: each step from MuJoCo's state against ``mj_step`` (capsule-box, plane-box and
    plane-capsule contacts in one solve)."""
    path = tmp_path / "capsule.xml"
    path.write_text(CAPSULE_ON_A_BOX)
    model = load_mjcf(str(path))
    tree = RigidBodyTree.from_model(model)
    assert tree.contact_model == "mujoco"
    mm = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mm)
    data.qvel[6:12] = [0.6, -0.1, 0.0, 5.9, 2.1, 3.7]  # the capsule: sliding and spinning
    touching, branches = [], set()

    def observe(data):
        touching.append(sum({data.contact.geom[i][0], data.contact.geom[i][1]} == {1, 2} for i in range(data.ncon)))
        if touching[-1]:
            rot = data.geom_xmat[1].reshape(3, 3)
            branches.update(_branches((rot.T @ (data.geom_xpos[2] - data.geom_xpos[1]))[None],
                                      (rot.T @ data.geom_xmat[2].reshape(3, 3)[:, 2])[None], mm.geom_size[1]))

    gaps = gaps_to_mj_step(tree, mm, data, 200, observe)
    on_the_box, two = sum(n > 0 for n in touching), sum(n == 2 for n in touching)
    assert on_the_box > 120 and two > 80 and gaps.max() < 1e-9, (on_the_box, two, gaps.max())
    assert {"face", "edge, across it"} <= branches and any(b.startswith("corner") for b in branches), branches
