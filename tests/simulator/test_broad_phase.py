"""Bounding spheres: MuJoCo's filter in the collision stage (a pair is collided only where its
bounding spheres come within its margin), and the broad phase of the eager CPU step
(`near_pairs`): a step that collides only the pairs near enough to touch equals one that
collides every pair.

Oracles: MuJoCo's ``geom_rbound`` and its contacts (``mj_forward``'s ``ncon``); the full
collision stage (every pair) at the same configurations; the step and its gradients with every
pair collided.
"""
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

import torchrl_diffenvs.articulated.pipeline as pipeline  # noqa: E402
from torchrl_diffenvs.articulated import RigidBodyTree, forward_kinematics, gymnasium_asset, load_mjcf  # noqa: E402
from torchrl_diffenvs.articulated.collision import bounding_radius, collide, near_pairs  # noqa: E402
from torchrl_diffenvs.envs import make_env  # noqa: E402

ASSETS = ["half_cheetah.xml", "ant.xml", "humanoid.xml", "pusher_v5.xml"]

# every pair type but cylinder-box (no primitive: the bits keep them apart) and the ellipsoid (no contacts)
SCENE = """<mujoco><option gravity="0 0 0"/><worldbody>
    <geom name="floor" type="plane" size="5 5 .1" contype="3" conaffinity="3"/>
    <body name="a" pos="0 0 0.5"><freejoint/><geom name="a" type="box" size="0.1 0.2 0.05" margin="0.01"/></body>
    <body name="a2" pos="0 -0.3 0.5"><freejoint/><geom name="a2" type="box" size="0.06 0.05 0.1" margin="0.01"/></body>
    <body name="b" pos="0.3 0 0.5"><freejoint/><geom name="b" type="cylinder" size="0.05 0.1" contype="2"
        conaffinity="2"/></body>
    <body name="c" pos="0 0.4 0.5"><freejoint/><geom name="c" type="capsule" size="0.04 0.15" contype="3"
        conaffinity="3"/></body>
    <body name="d" pos="0.3 0.4 0.5"><freejoint/><geom name="d" type="sphere" size="0.07" contype="3"
        conaffinity="3"/></body>
    <body name="e" pos="0.6 0.4 0.5"><freejoint/><geom name="e" type="ellipsoid" size="0.03 0.05 0.08"
        contype="0" conaffinity="0"/></body></worldbody></mujoco>"""


def _scene(tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text(SCENE)
    return str(path)


@pytest.mark.parametrize("filename", ASSETS + ["scene"])
def test_bounding_radius_is_mujocos_geom_rbound(filename, tmp_path):
    path = _scene(tmp_path) if filename == "scene" else str(gymnasium_asset(filename))
    model, mm = load_mjcf(path), mujoco.MjModel.from_xml_path(path)
    checked = 0
    for g, kind in enumerate(model.geom_type):
        if kind == "plane":
            continue
        size = torch.as_tensor(np.asarray(model.geom_size[g:g + 1], dtype=np.float64))
        assert bounding_radius(kind, size).item() == pytest.approx(mm.geom_rbound[g], rel=1e-12), model.geom_names[g]
        checked += 1
    assert checked >= 4


def test_bounding_radius_names_the_valid_types():
    with pytest.raises(ValueError, match="'plane' has no bounding sphere; valid: sphere, capsule"):
        bounding_radius("plane", torch.zeros(1, 3))


def _slots_of(slots) -> dict:
    """Each geom pair's slot positions, in order."""
    out = {}
    for i, pair in enumerate(map(tuple, slots.geom.tolist())):
        out.setdefault(pair, []).append(i)
    return out


def _random_configurations(model, rng, count):
    q = model.qpos0 + rng.normal(0.0, 0.4, (count, model.nq))
    for kind, adr in zip(model.joint_type, model.joint_qposadr):
        if kind == "free":
            q[:, adr:adr + 3] = model.qpos0[adr:adr + 3] + rng.uniform(-0.3, 0.3, (count, 3))
            q[:, adr + 3:adr + 7] /= np.linalg.norm(q[:, adr + 3:adr + 7], axis=-1, keepdims=True)
    return torch.as_tensor(q)


@pytest.mark.parametrize("filename", ["humanoid.xml", "pusher_v5.xml", "scene"])
@pytest.mark.parametrize("reach", [0.0, 0.05])
def test_near_pairs_keep_every_pair_within_reach_with_the_same_contacts(filename, reach, tmp_path):
    """Every contact the full collision finds within its margin plus ``reach`` is in a pair the
    broad phase keeps, whose contacts are the full stage's bit for bit; far pairs are left out."""
    path = _scene(tmp_path) if filename == "scene" else str(gymnasium_asset(filename))
    model = load_mjcf(path)
    tree = RigidBodyTree.from_model(model, dtype=torch.float64)
    slots, rng, dropped, touching = tree.contact_slots, np.random.default_rng(0), 0, 0
    for _ in range(8):
        kin = forward_kinematics(tree, _random_configurations(model, rng, 16))
        full, near = collide(slots, kin), near_pairs(slots, kin, reach)
        within = full.found & (full.dist < slots.margin + reach)
        touching += int(within.any(0).sum())
        kept = _slots_of(near)
        for pair, positions in _slots_of(slots).items():
            if pair not in kept:
                assert not within[:, positions].any(), f"pair {pair} touches but was left out"
                dropped += 1
        ours = collide(near, kin)
        for pair, positions in kept.items():
            at = _slots_of(slots)[pair]
            for field in ("dist", "pos", "frame", "active", "found"):
                assert torch.equal(getattr(ours, field)[:, positions], getattr(full, field)[:, at]), (pair, field)
    assert dropped > 0 and touching > 0  # it prunes, and keeps pairs in touch: neither half is vacuous


def test_near_pairs_threshold_is_the_margin_plus_reach(tmp_path):
    """Spheres b and c (radius 0.1, 2 mm margin each) with a 3 mm gap are near, with a 0.3 m gap
    they are not, unless ``reach`` covers it; with no pair near, the model's first pair (a, b),
    far from each other, stands in and holds no contact."""
    path = tmp_path / "three.xml"
    path.write_text("""<mujoco><option gravity="0 0 0"/><worldbody>
        <body name="a" pos="5 5 5"><freejoint/><geom name="a" type="sphere" size="0.1"/></body>
        <body name="b"><freejoint/><geom name="b" type="sphere" size="0.1" margin="0.002"/></body>
        <body name="c"><freejoint/><geom name="c" type="sphere" size="0.1" margin="0.002"/></body></worldbody></mujoco>""")
    tree = RigidBodyTree.from_model(load_mjcf(str(path)), dtype=torch.float64)
    slots = tree.contact_slots
    assert list(map(tuple, slots.geom.tolist())) == [(0, 1), (0, 2), (1, 2)]

    def kept(gap, reach=0.0):
        qpos = tree.qpos0.unsqueeze(0).clone()
        qpos[0, 14] = 0.2 + gap  # body c along x from b
        kin = forward_kinematics(tree, qpos)
        near = near_pairs(slots, kin, reach)
        return list(map(tuple, near.geom.tolist())), collide(near, kin).active.any().item()

    assert kept(0.003) == ([(1, 2)], True)
    assert kept(0.0041) == ([(1, 2)], False)  # within a thousandth of the radii: kept for rounding, not touching
    assert kept(0.0043) == ([(0, 1)], False)
    assert kept(0.3) == ([(0, 1)], False)
    assert kept(0.3, reach=0.3) == ([(1, 2)], False)
    assert kept(0.3, reach=0.29) == ([(0, 1)], False)


def _every_pair(slots, kin, reach=0.0):
    return slots


@pytest.mark.parametrize("task,mode", [("Humanoid-v5", "cfd"), ("HumanoidStandup-v5", "exact"), ("Ant-v5", "cfd")])
def test_step_with_the_broad_phase_equals_the_step_colliding_every_pair(task, mode, monkeypatch):
    """Values and gradients (float64, through env steps in contact: the humanoid after it has
    fallen) are the same bit for bit whether the step collides the near pairs or every pair."""
    env = make_env(task, num_envs=4, seed=3, dtype=torch.float64, contact_gradient=mode)
    generator = torch.Generator().manual_seed(0)
    start = env.reset()
    with torch.no_grad():  # into contact (the same values either way: the warm-up runs once)
        for _ in range({"Humanoid-v5": 25, "Ant-v5": 12}.get(task, 3)):
            start = env.step(start.set("action", 0.4 * torch.randn(4, env.action_dim, dtype=torch.float64,
                                                                     generator=generator)))["next"]
    actions = 2 * torch.rand(3, 4, env.action_dim, dtype=torch.float64, generator=generator) - 1

    def rollout():
        td, total, states = start.clone(), 0.0, []
        a = actions.clone().requires_grad_()
        for action in a:
            td = env.step(td.set("action", action))["next"]
            total = total + td["reward"].sum()
            states.append(td["state", "qvel"])
        (grad,) = torch.autograd.grad(total, a)
        state = td["state"]
        _, report = pipeline.accelerations(env.tree, state["qpos"], state["qvel"], actions[-1], env.params,
                                           with_contact_force=True)
        return (torch.stack(states), total.detach(), grad), report

    broad, report = rollout()
    assert (report.contact_force > 0).any()  # in contact: a comparison without contacts could not fail
    assert report.solved_contacts.slots.count < env.tree.contact_slots.count
    monkeypatch.setattr(pipeline, "near_pairs", _every_pair)
    every, _ = rollout()
    for ours, theirs in zip(broad, every):
        assert torch.equal(ours, theirs)


def test_bounding_sphere_filter_is_mujocos_for_boxes_corner_to_corner(tmp_path):
    """Two boxes (5 mm margin each) corner to corner, their bounding spheres 10.5 mm apart: box-box's
    edge axis separates them by 9.4 mm, within the margin, but MuJoCo's bounding-sphere filter
    leaves the pair out (no contact); so does the collision stage, with or without the broad phase,
    and where it has no contact its gap is the spheres' (the larger lower bound of the distance)."""
    path = tmp_path / "boxes.xml"
    path.write_text("""<mujoco><option gravity="0 0 0"/><worldbody>
        <body name="a"><freejoint/><geom name="a" type="box" size="0.1 0.2 0.05" margin="0.005"/></body>
        <body name="b"><freejoint/><geom name="b" type="box" size="0.1 0.2 0.05" margin="0.005"/></body>
        </worldbody></mujoco>""")
    qpos = np.array([0.0, 0.0, 0.0, 0.8379823890607561, 0.13537744587526088, 0.3847563860925626, -0.3625203251313083,
                     0.437380569400513, 0.13189137831748385, -0.10505503698445245, 0.43699208851538185,
                     0.3890814903843009, -0.4582271293064549, 0.6690899837711377])
    mm = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mm)
    data.qpos[:] = qpos
    mujoco.mj_forward(mm, data)
    assert data.ncon == 0
    tree = RigidBodyTree.from_model(load_mjcf(str(path)), dtype=torch.float64)
    kin = forward_kinematics(tree, torch.as_tensor(qpos).unsqueeze(0))
    spheres_gap = np.linalg.norm(data.geom_xpos[1] - data.geom_xpos[0]) - mm.geom_rbound.sum()
    assert 0.01 < spheres_gap < 0.011
    contacts = collide(tree.contact_slots, kin)
    assert not contacts.active.any()
    assert contacts.found.any() and contacts.dist.min().item() == pytest.approx(spheres_gap, abs=1e-12)
    assert not collide(near_pairs(tree.contact_slots, kin), kin).active.any()
    # MuJoCo's contacts at random poses of the two boxes, pressed together: the same count
    rng, touching = np.random.default_rng(4), 0
    for _ in range(300):
        q = qpos.copy()
        q[7:10] = rng.normal(0.0, 0.15, 3)
        q[3:7], q[10:] = rng.normal(size=4), rng.normal(size=4)
        q[3:7] /= np.linalg.norm(q[3:7])
        q[10:] /= np.linalg.norm(q[10:])
        data.qpos[:] = q
        mujoco.mj_forward(mm, data)
        ours = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(q).unsqueeze(0)))
        assert int(ours.active.sum()) == data.ncon
        touching += data.ncon > 0
    assert 30 < touching < 270  # poses in touch and apart
