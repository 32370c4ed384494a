"""Box-box contact (``articulated.box_box``, MuJoCo's ``mjc_BoxBox``) against MuJoCo itself.

Oracles: the installed ``mujoco``'s ``mj_forward`` on two free boxes (its contacts ``d.ncon``,
``d.contact.dist``, ``pos``, ``frame``, in its order) at random, structured and knife-edge poses
(through our kinematics, and the primitive alone on MuJoCo's own geom poses), and its ``mj_step``
for a box dropped on a box lying on a floor; ``torch.autograd.gradcheck`` (finite differences,
float64) for the gradients. The poses are classified into MuJoCo's branches by `_branch`, an
independent separating-axis computation in numpy, to show each one is exercised.
"""
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from torchrl_diffenvs.articulated import RigidBodyTree, forward_kinematics, load_mjcf  # noqa: E402
from torchrl_diffenvs.articulated.box_box import box_box  # noqa: E402
from torchrl_diffenvs.articulated.collision import collide  # noqa: E402
from torchrl_diffenvs.articulated.primitive_types import PosedGeoms  # noqa: E402
from torchrl_diffenvs.articulated.spatial import quaternion_to_matrix  # noqa: E402

from _mujoco_steps import gaps_to_mj_step  # noqa: E402

SIZE1, SIZE2 = np.array([0.05, 0.08, 0.11]), np.array([0.07, 0.04, 0.09])  # three different half-sizes each
MARGIN = 0.004  # 2 mm per geom
TWO_BOXES = f"""<mujoco><option gravity="0 0 0"/><worldbody>
    <body name="a"><freejoint/><geom name="a" type="box" size="{' '.join(map(str, SIZE1))}" margin="0.002"/></body>
    <body name="b"><freejoint/><geom name="b" type="box" size="{' '.join(map(str, SIZE2))}" margin="0.002"/></body>
    </worldbody></mujoco>"""
IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _setup(tmp_path, dtype=torch.float64):
    path = tmp_path / "boxes.xml"
    path.write_text(TWO_BOXES)
    tree = RigidBodyTree.from_model(load_mjcf(str(path)), dtype=dtype)
    mm = mujoco.MjModel.from_xml_path(str(path))
    return tree, mm, mujoco.MjData(mm)


def _quat(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    return np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis / np.linalg.norm(axis)]


def _mat(quat):
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, dtype=np.float64))
    return out.reshape(3, 3)


def _qmul(a, b):
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    return out


def _random_poses(count: int, rng) -> np.ndarray:
    """Both boxes turned at random, box b's centre within 0.15 of box a's on each axis: mostly
    interpenetrating, some apart."""
    poses = np.zeros((count, 14))
    poses[:, 3:7], poses[:, 10:14] = rng.normal(size=(count, 4)), rng.normal(size=(count, 4))
    for q in (poses[:, 3:7], poses[:, 10:14]):
        q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses[:, 7:10] = rng.uniform(-0.15, 0.15, (count, 3))
    return poses


def _pose(quat_a, pos_b, quat_b):
    return np.r_[0.0, 0.0, 0.0, quat_a, pos_b, quat_b]


def _structured_poses() -> dict[str, np.ndarray]:
    """Box a at the origin, box b placed 1 mm into it (most of them): face on face (aligned,
    offset, below, on a side face, both turned alike, turned about the normal), coincident
    centres, an edge on a face, crossing edges, a corner on a face, nearly parallel faces, a
    corner of b's face over a corner of a's (clipping repeats the corner: MuJoCo drops the copy),
    an edge axis separating by less than MuJoCo's bias more than a face, edges within the margin
    meeting past an end, and a face whose clipped vertices are all beyond the margin."""
    h = SIZE1[2] + SIZE2[2] - 0.001
    turned = np.array([0.6, -0.3, 0.5, 0.4]) / np.linalg.norm([0.6, -0.3, 0.5, 0.4])
    edge_down = _quat([1, 0, 0], np.pi / 4)  # b's edge along x lowest
    edge_half = (SIZE2[1] + SIZE2[2]) / np.sqrt(2)
    a_edge_up = _quat([0, 1, 0], np.pi / 4)  # a's edge along y highest
    a_top = (SIZE1[0] + SIZE1[2]) / np.sqrt(2)
    v = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    corner_down = _quat(np.cross(v, [0, 0, -1.0]), np.arccos(-v[2]))
    lowest = SIZE2 * np.sign(_mat(corner_down)[2]) * -1  # b's lowest corner, b's frame
    poses = {
        "aligned": _pose(IDENTITY, [0, 0, h], IDENTITY),
        "aligned, offset": _pose(IDENTITY, [0.03, -0.05, h], IDENTITY),
        "aligned, below": _pose(IDENTITY, [0.01, 0.02, -h - 0.0005], IDENTITY),
        "aligned, side faces": _pose(IDENTITY, [SIZE1[0] + SIZE2[0] - 0.002, 0.01, 0.02], IDENTITY),
        "aligned, both turned": _pose(turned, _mat(turned) @ [0.01, 0.02, h], turned),
        "coincident centres": _pose(IDENTITY, [0, 0, 0], IDENTITY),
        "coincident centres, turned": _pose(turned, [0, 0, 0], _qmul(turned, _quat([1, 2, 3], 0.4))),
        "edge on face": _pose(IDENTITY, [0.01, 0, SIZE1[2] + edge_half - 0.001], edge_down),
        "edge on face, 30 degrees": _pose(IDENTITY, [0.01, 0, SIZE1[2] + SIZE2[1] / 2 + SIZE2[2] * np.cos(np.pi / 6)
                                                     - 0.001], _quat([1, 0, 0], np.pi / 6)),
        "edges crossing": _pose(a_edge_up, [0, 0, a_top + edge_half - 0.001], edge_down),
        "edges crossing, skew": _pose(a_edge_up, [0.01, -0.02, a_top + edge_half - 0.001],
                                      _qmul(_quat([0, 0, 1], 0.3), edge_down)),
        "corner on face": _pose(IDENTITY, np.array([0, 0, SIZE1[2] - 0.001]) - _mat(corner_down) @ lowest, corner_down),
        "nearly parallel, 1e-9": _pose(IDENTITY, [0.01, 0, h], _quat([1, 0, 0], 1e-9)),
        "nearly parallel, 1e-4": _pose(IDENTITY, [0.01, 0, h], _quat([1, 1, 0], 1e-4)),
        "nearly parallel, 0.05": _pose(IDENTITY, [0.02, 0.01, h], _quat([1, 0.3, 0], 0.05)),
    }
    for angle in np.linspace(0.1, 1.5, 8):  # turned about the normal: the clipped polygon has up to 8 corners
        for offset in ([0.002, 0.0], [0.005, 0.003]):
            poses[f"turned {angle:.1f} about the normal, {offset}"] = _pose(IDENTITY, [*offset, h], _quat([0, 0, 1], angle))
    poses["an edge axis within the bias of a face"] = _edge_within_the_bias_of_a_face()
    # edges within the margin whose closest points lie past an end of box a's (the end clamps
    # them), found by a search of random poses
    poses["edges past an end, 0"] = np.array([
        0.0, 0.0, 0.0, -0.05103590395531619, 0.8116592322504251, 0.4655790543605873, 0.34905697436208827,
        -0.0526637530920811, 0.17962661886164727, -0.09886155714670877, -0.3038933590475347, -0.7108303477167586,
        0.632717196298518, 0.045144131399562734])
    # no axis separates them, but every clipped vertex of the incident face is beyond the margin: no
    # contact (found by a search of random poses)
    poses["no clipped vertex within the margin"] = np.array([
        0.0, 0.0, 0.0, -0.16141126145569706, -0.5116861300226166, -0.6123054076315916, -0.5806942369292714,
        0.1006222706083516, 0.16991463562721587, 0.14093957525285172, -0.5878246347705488, 0.579123141164525,
        0.3108399419743276, 0.4716535980971642])
    poses["edges past an end, 1"] = np.array([
        0.0, 0.0, 0.0, 0.7511345040836493, -0.05204402745567135, -0.6189817834456042, -0.22349480473537336,
        0.17127281643532338, 0.12880700772030879, -0.12654825945601078, 0.04935845314497331, -0.11973604688226791,
        0.3683971960611218, -0.9206033500452007])
    for angle in np.linspace(0.05, 1.5, 30):  # b's corner (+x, +y, -z) exactly over a's top corner (+x, +y)
        quat = _quat([0, 0, 1], angle)
        corner = np.array([SIZE2[0], SIZE2[1], -SIZE2[2]])
        poses[f"corner over corner, {angle:.2f}"] = _pose(IDENTITY, np.array([SIZE1[0], SIZE1[1], SIZE1[2] - 0.001])
                                                          - _mat(quat) @ corner, quat)
    return poses


def _separations(pos1, mat1, pos2, mat2) -> tuple[float, float]:
    """The separating-axis test in numpy: the largest separation along a face normal of either
    box, and along a cross product of their edges (those not within 1e-6 of parallel)."""
    crosses = np.cross(mat1.T[:, None], mat2.T[None]).reshape(9, 3)
    lengths = np.linalg.norm(crosses, axis=1)
    axes = np.concatenate([mat1.T, mat2.T, crosses[lengths > 1e-6] / lengths[lengths > 1e-6, None]])
    separation = np.abs(axes @ (pos2 - pos1)) - np.abs(axes @ mat1) @ SIZE1 - np.abs(axes @ mat2) @ SIZE2
    return separation[:6].max(), separation[6:].max(initial=-np.inf)


def _edge_within_the_bias_of_a_face() -> np.ndarray:
    """Box b's corner 2 mm into box a's top face, slid towards a's edge until an edge axis
    separates them by half of MuJoCo's edge bias (1e-6, relative) more than the face: MuJoCo keeps
    the face (the edge must beat it by the bias), and the edge axis is far from the face normal
    (no substitution)."""
    quat = _quat([0.3, 1.0, 0.2], 0.8)
    mat, z = _mat(quat), SIZE1[2] + np.abs(_mat(quat)[2]) @ SIZE2 - 0.002

    def excess(x):
        face, edge = _separations(np.zeros(3), np.eye(3), np.array([x, 0.01, z]), mat)
        return edge - face - 0.5e-6 * abs(face)

    low, high = 0.05, 0.06
    assert excess(low) < 0 < excess(high)
    for _ in range(60):
        middle = (low + high) / 2
        low, high = (middle, high) if excess(middle) < 0 else (low, middle)
    return _pose(IDENTITY, [high, 0.01, z], quat)


def _knife_edge_poses() -> dict[str, np.ndarray]:
    """Poses where MuJoCo's choice turns on the last bit of its geom_xmat (compared on MuJoCo's
    own geom poses only): box b's edge at exactly 45 degrees on a's face (its two faces equally
    opposed: the first is the incident one), and faces touching to 1e-10 with b tilted by 1e-12 to
    1e-8, where an edge axis wins that is ~orthogonal to a face of a box, of b, or of both (MuJoCo
    tries both supporting edges of each such box and keeps the closest pair)."""
    half = np.pi / 8 - 8e-17  # cos(2 half) == sin(2 half) in MuJoCo's quaternion-to-matrix
    edge_down = np.array([np.cos(half), np.sin(half), 0.0, 0.0])
    poses = {"edge on face, two faces equally opposed":
             _pose(IDENTITY, [0.01, 0, SIZE1[2] + (SIZE2[1] + SIZE2[2]) / np.sqrt(2) - 0.001], edge_down)}
    touching = [  # box b's qpos (box a unturned at the origin), found by a search over tilts and gaps:
        # ambiguous on a (MuJoCo keeps a's other edge), on b (b's other edge), on both (keeping b's
        # other edge, a's, both)
        [0.012359230019173027, -0.008952424342525847, 0.19999999992996523, 0.9966501680607096, 7.826582570741492e-10,
         4.749488834844628e-10, 0.08178289860697913],
        [-0.007246507574441554, 0.0005828396747436793, 0.19999999997976045, 0.9910893002439712, 2.0350912975119323e-10,
         -1.7433112238873298e-09, 0.13319909512423667],
        [0.00736201792300132, 0.012951254335710868, 0.2000000000010808, 0.9952085263765196, -2.100140872285812e-11,
         -3.1601114087924106e-11, 0.09777519638168161],
        [0.009030307402074795, -0.01668765696414021, 0.20000000000128584, 0.9928253621034924, -1.758567042429921e-11,
         -2.6746229442260838e-11, 0.1195734099374492],
        [-0.014046747620447681, -0.015589893954546375, 0.19999999998928134, 0.9899485400164314, -1.280646792801079e-11,
         -1.1744614556145252e-11, 0.1414280315896956],
    ]
    for k, b in enumerate(touching):
        poses[f"touching, tilted, {k}"] = np.r_[0.0, 0.0, 0.0, IDENTITY, b]
    return poses


def _corners(pos, mat, size):
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return pos + (signs * size) @ mat.T


def _branch(data) -> str:
    """MuJoCo's branch at ``data`` (after ``mj_forward``), from `_separations` and MuJoCo's
    contacts, with MuJoCo's count: apart (along a face axis, or only along an edge axis), an
    edge-edge contact (a normal that is no box axis; "ambiguous" where the normal is within 1e-9
    of a box's face normal: MuJoCo tries both supporting edges of that box), or a face contact
    (the normal is a box axis: box a's, box b's, both (parallel faces), with a corner of b's face
    over a corner of a's, or where an edge axis separates more, yielding to the face (beyond
    MuJoCo's bias) or not (within it))."""
    pos1, pos2 = data.geom_xpos[0], data.geom_xpos[1]
    mat1, mat2 = data.geom_xmat[0].reshape(3, 3), data.geom_xmat[1].reshape(3, 3)
    face, edge = _separations(pos1, mat1, pos2, mat2)
    if data.ncon == 0:
        if face > MARGIN:
            return "apart along a face axis"
        return "apart along an edge axis only" if edge > MARGIN else "no clipped vertex within the margin"
    normal = data.contact.frame[0][:3]

    def along(mat):  # the face branch's normal is a column of the reference box's geom_xmat
        return min(np.abs(normal - sign * mat[:, k]).max() for k in range(3) for sign in (1, -1)) < 1e-13

    if not (along(mat1) or along(mat2)):
        near = [name for name, mat in (("a", mat1), ("b", mat2)) if np.sort(np.abs(mat.T @ normal))[1] < 1e-9]
        return f"edge-edge{', ambiguous on ' + ' and '.join(near) if near else ''}, {data.ncon} contacts"
    if edge - 1e-6 * abs(edge) > face:
        kind = "an edge axis yielding to a face"
    elif edge > face + 1e-12:  # beyond rounding (an edge lying on a face is a tie)
        kind = "an edge axis within the bias of a face"
    elif along(mat1) and along(mat2):
        over = (_corners(pos1, mat1, SIZE1)[:, None] - _corners(pos2, mat2, SIZE2)[None]) @ mat1[:, :2]
        kind = "corner over corner" if np.linalg.norm(over, axis=-1).min() < 1e-9 else "parallel faces"
    else:
        kind = "box a's face" if along(mat1) else "box b's face"
    return f"{kind}, {data.ncon} contacts"


def _assert_matches(c, k, data, tol=1e-12, in_order=True):
    """Slot contacts ``c`` of configuration ``k`` against MuJoCo's: count, order (or, not
    ``in_order``, the same contacts in a cyclic order), dist, pos, frame. Returns whether the
    order was MuJoCo's."""
    ours = np.flatnonzero(c.active[k].numpy())
    assert len(ours) == data.ncon, (k, len(ours), data.ncon)
    assert list(ours) == list(range(data.ncon))  # MuJoCo's contacts fill the first slots
    dist, pos, frame = c.dist[k, ours].numpy(), c.pos[k, ours].numpy(), c.frame[k, ours].numpy().reshape(-1, 9)
    shifts = [0] if in_order else [s for s in range(len(ours))
                                   if np.abs(np.roll(pos, s, axis=0) - data.contact.pos[:data.ncon]).max() < tol] or [0]
    dist, pos, frame = (np.roll(a, shifts[0], axis=0) for a in (dist, pos, frame))
    np.testing.assert_allclose(dist, data.contact.dist[:data.ncon], rtol=0, atol=tol)
    np.testing.assert_allclose(pos, data.contact.pos[:data.ncon], rtol=0, atol=tol)
    np.testing.assert_allclose(frame, data.contact.frame[:data.ncon], rtol=0, atol=tol)
    return shifts[0] == 0


@pytest.mark.filterwarnings("ignore")
def test_box_box_matches_mj_collision(tmp_path):
    """1000 random poses and the structured ones, through our kinematics: every contact as
    MuJoCo's (count, order, dist, pos, frame) to 1e-12, and every branch of MuJoCo's exercised.
    A corner of b's face exactly over a corner of a's is inside or outside a's side planes by the
    last bit of the rotation matrices (ours and MuJoCo's differ there): kept first or cut later, the
    same contacts come in another cyclic order (the primitive on MuJoCo's own poses keeps its
    order: the next test)."""
    tree, mm, data = _setup(tmp_path)
    assert tree.contact_model == "mujoco"
    structured = _structured_poses()
    names = [""] * 1000 + list(structured)
    poses = np.concatenate([_random_poses(1000, np.random.default_rng(0)), np.stack(list(structured.values()))])
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses)))
    assert c.dist.shape == (len(poses), 8)
    branches, seen, reordered = {}, set(), 0
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        reordered += not _assert_matches(c, k, data, in_order=not names[k].startswith("corner over corner"))
        branch = _branch(data)
        seen.add(branch.split(",")[0])
        branches[branch] = branches.get(branch, 0) + 1
    assert {"apart along a face axis", "apart along an edge axis only", "edge-edge", "box a's face", "box b's face",
            "parallel faces", "an edge axis yielding to a face", "an edge axis within the bias of a face",
            "corner over corner", "no clipped vertex within the margin"} <= seen, branches
    face_counts = {int(b.split(", ")[-1].split()[0]) for b in branches if "contacts" in b and "edge-edge" not in b}
    assert face_counts == set(range(1, 9)), branches  # the clipped polygon: one to eight vertices within the margin
    assert branches["edge-edge, 1 contacts"] >= 100, branches
    assert reordered <= 10, reordered


@pytest.mark.filterwarnings("ignore")
def test_box_box_primitive_in_float64_and_float32_from_mujocos_poses(tmp_path):
    """The primitive alone on MuJoCo's own geom poses (``geom_xpos``, ``geom_xmat``, bit for bit),
    at random, structured and knife-edge poses (`_knife_edge_poses`): float64 as MuJoCo to 1e-12,
    in MuJoCo's order; float32 (MuJoCo's single-precision tolerances) with MuJoCo's count at the
    random poses and its values to float32's rounding."""
    _, mm, data = _setup(tmp_path)
    knife_edge = _knife_edge_poses()
    poses = np.concatenate([_random_poses(300, np.random.default_rng(3)), np.stack(list(_structured_poses().values())),
                            np.stack(list(knife_edge.values()))])
    xpos, xmat, reference, branches = [], [], [], set()
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        if k >= len(poses) - len(knife_edge):
            branches.add(_branch(data))
            if k == len(poses) - len(knife_edge):  # the edge on the face: its two faces equally opposed, to the bit
                assert abs(data.geom_xmat[1][7]) == abs(data.geom_xmat[1][8]), data.geom_xmat[1]
        xpos.append(data.geom_xpos.copy())
        xmat.append(data.geom_xmat.reshape(2, 3, 3).copy())
        reference.append((data.ncon, data.contact.dist[:data.ncon].copy(), data.contact.pos[:data.ncon].copy(),
                          data.contact.frame[:data.ncon, :3].copy()))
    xpos, xmat = np.stack(xpos), np.stack(xmat)
    assert {"edge-edge, ambiguous on a, 1 contacts", "edge-edge, ambiguous on b, 1 contacts",
            "edge-edge, ambiguous on a and b, 1 contacts", "box a's face, 2 contacts"} <= branches, branches
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-6)):
        t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
        c = box_box(PosedGeoms(t(xpos[:, :1]), t(xmat[:, :1]), t(SIZE1[None])),
                    PosedGeoms(t(xpos[:, 1:]), t(xmat[:, 1:]), t(SIZE2[None])), t([MARGIN]))
        assert c.dist.dtype == dtype
        active = (c.found & (c.dist < MARGIN))[:, 0]
        for k, (ncon, dist, pos, normal) in enumerate(reference):
            if dtype == torch.float32 and k >= 300:
                continue  # structured ties (aligned faces, corner over corner) break by float64 rounding
            assert active[k].sum().item() == ncon and active[k, :ncon].all(), (dtype, k)
            np.testing.assert_allclose(c.dist[k, 0, :ncon].double().numpy(), dist, rtol=0, atol=tol)
            np.testing.assert_allclose(c.pos[k, 0, :ncon].double().numpy(), pos, rtol=0, atol=tol)
            np.testing.assert_allclose(c.normal[k, 0, :ncon].double().numpy(), normal, rtol=0, atol=tol)


def _gradient_poses() -> dict[str, np.ndarray]:
    """A generic pose of each branch (box a turned by A_TURN; box b 1 mm into it, or less)."""
    a = _mat(A_TURN)
    face_a = _qmul(_quat([0, 0, 1], 0.9), _quat([1, 0, 0], 0.15))  # b's lowest edge across a's top face
    face_b = _qmul(_quat([1, 0, 0], 0.2), _quat([0, 0, 1], 0.4))  # b's top face under a's lowest edge (along x)
    normal_b = _mat(face_b)[:, 2]
    lowest_a = -SIZE1 * np.sign(normal_b)  # that edge's midpoint, a's frame
    structured = _structured_poses()
    return {
        "box a's face": _pose(A_TURN, a @ [0.01, 0.005, SIZE1[2] + SIZE2 @ np.abs(_mat(face_a)[2]) - 0.001],
                              _qmul(A_TURN, face_a)),
        "box b's face": _pose(A_TURN, a @ (lowest_a - (SIZE2[2] - 0.001) * normal_b + _mat(face_b) @ [0.01, 0.005, 0]),
                              _qmul(A_TURN, face_b)),
        "an edge axis yielding to a face": _pose(A_TURN, a @ [0.006, 0.004, SIZE1[2] + SIZE2[2] - 0.0012],
                                                 _qmul(A_TURN, _qmul(_quat([0, 0, 1], 0.9), _quat([1, 0.4, 0], 0.003)))),
        "edge-edge": structured["edges crossing, skew"],
        "edge-edge, past an end": structured["edges past an end, 0"],
        "box a's face, a corner": structured["corner on face"] + np.r_[np.zeros(7), 0.01, -0.02, 0.0, np.zeros(4)],
    }


A_TURN = _quat([0.2, -0.5, 1.0], 0.3)
GRADIENT_POSES = _gradient_poses()


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("branch", list(GRADIENT_POSES))
def test_box_box_gradcheck(tmp_path, branch):
    """The gradient of every contact's dist, pos and normal w.r.t. box b's centre and orientation
    (its quaternion, normalised), in each branch, against finite differences (the primitive, box a
    where MuJoCo has it)."""
    _, mm, data = _setup(tmp_path)
    pose = GRADIENT_POSES[branch]
    data.qpos[:] = pose
    mujoco.mj_forward(mm, data)
    assert _branch(data).startswith(branch.split(",")[0]), _branch(data)
    assert data.ncon >= (1 if branch.startswith("edge-edge") or branch.endswith("a corner") else 3), data.ncon
    slots = list(range(data.ncon))
    box_a = PosedGeoms(*(torch.as_tensor(x).reshape(1, 1, *shape) for x, shape in
                         ((data.geom_xpos[0], (3,)), (data.geom_xmat[0], (3, 3)))), torch.as_tensor(SIZE1[None]))

    def contact(centre, quat):
        rot = quaternion_to_matrix(quat / quat.norm(dim=-1, keepdim=True))
        c = box_box(box_a, PosedGeoms(centre.reshape(1, 1, 3), rot.reshape(1, 1, 3, 3), torch.as_tensor(SIZE2[None])),
                    torch.tensor([MARGIN], dtype=torch.float64))
        assert c.found[0, 0, slots].all() and not c.found[0, 0, data.ncon:].any()
        return c.dist[0, 0, slots], c.pos[0, 0, slots], c.normal[0, 0, slots]

    centre = torch.as_tensor(pose[7:10]).requires_grad_(True)
    quat = torch.as_tensor(pose[10:14]).requires_grad_(True)
    dist, pos, normal = contact(centre, quat)
    np.testing.assert_allclose(dist.detach().numpy(), data.contact.dist[:data.ncon], rtol=0, atol=1e-12)
    np.testing.assert_allclose(pos.detach().numpy(), data.contact.pos[:data.ncon], rtol=0, atol=1e-12)
    np.testing.assert_allclose(normal.detach().numpy(), data.contact.frame[:data.ncon, :3], rtol=0, atol=1e-12)
    torch.autograd.gradcheck(contact, (centre, quat))


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_box_box_gradients_are_finite_at_degenerate_poses(tmp_path, dtype):
    """Exactly aligned faces (parallel edges: MuJoCo skips those axes), coincident centres, an edge
    at 45 degrees (two faces equally opposed), a corner over a corner (a repeated clipped vertex),
    touching faces tilted by 1e-10 (ambiguous supporting edges): every output of every slot, found
    or not, has finite gradients w.r.t. both boxes' qpos."""
    tree, _, _ = _setup(tmp_path, dtype)
    structured = {**_structured_poses(), **_knife_edge_poses()}
    names = ["aligned", "aligned, offset", "aligned, side faces", "coincident centres", "coincident centres, turned",
             "edge on face", "nearly parallel, 1e-9", "corner over corner, 0.10", "edge on face, two faces equally opposed",
             "touching, tilted, 4", "edges past an end, 0"]
    qpos = torch.as_tensor(np.stack([structured[n] for n in names]), dtype=dtype).requires_grad_(True)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    assert c.active.any(-1).all()
    (grad,) = torch.autograd.grad(c.dist.sum() + c.pos.sum() + c.frame.sum(), qpos)
    assert torch.isfinite(grad).all(), [n for n, g in zip(names, grad) if not torch.isfinite(g).all()]
    assert grad.abs().sum() > 0


BOX_ON_A_BOX = """<mujoco><option timestep="0.005"/><worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="base" pos="0 0 0.04"><freejoint/><geom name="base" type="box" size="0.1 0.08 0.04"/></body>
    <body name="top" pos="0.09 0.01 0.15" quat="0.831973 0.344421 0.166374 0.401889"><freejoint/>
        <geom name="top" type="box" size="0.06 0.035 0.025"/></body>
    </worldbody></mujoco>"""


@pytest.mark.filterwarnings("ignore")
def test_a_box_dropped_on_a_box_steps_as_mj_step(tmp_path):
    """A box, turned with an edge down, falls on the edge of a free box lying on the floor, rocks
    between edge-edge and edge-on-face contacts, and settles face on face: each of 200 steps of
    ours from MuJoCo's state before it (one batch) against ``mj_step``, box-box and plane-box
    contacts in one solve."""
    path = tmp_path / "stack.xml"
    path.write_text(BOX_ON_A_BOX)
    model = load_mjcf(str(path))
    tree = RigidBodyTree.from_model(model)
    assert tree.contact_model == "mujoco"
    mm = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mm)
    kinds = []

    def observe(data):
        ours = [i for i in range(data.ncon) if {data.contact.geom[i][0], data.contact.geom[i][1]} == {1, 2}]
        if ours:  # a normal along neither box's axes: edge-edge
            normal = data.contact.frame[ours[0]][:3]
            face = max(np.abs(data.geom_xmat[g].reshape(3, 3).T @ normal).max() for g in (1, 2)) > 1 - 1e-12
            kinds.append(f"{'face' if face else 'edge-edge'}, {len(ours)}")

    gaps = gaps_to_mj_step(tree, mm, data, 200, observe)
    assert len(kinds) > 150 and kinds.count("edge-edge, 1") >= 5, kinds
    assert {"face, 2", "face, 4", "face, 6"} <= set(kinds), kinds
    assert max(gaps) < 1e-9, max(gaps)
