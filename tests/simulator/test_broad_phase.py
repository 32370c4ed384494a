"""The broad phase of the eager CPU step (`near_pairs`): MuJoCo's bounding spheres, and a step
that collides only the pairs near enough to touch equals one that collides every pair.

Oracles: MuJoCo's ``geom_rbound``; the full collision stage (every pair) at the same
configurations; the step and its gradients with every pair collided.
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
    """Two spheres (radius 0.1, 2 mm margin each) with a 3 mm gap are near, with a 0.3 m gap they
    are not, unless ``reach`` covers it; with no pair near, the first pair's slot stays."""
    path = tmp_path / "two.xml"
    path.write_text("""<mujoco><option gravity="0 0 0"/><worldbody>
        <body name="a"><freejoint/><geom name="a" type="sphere" size="0.1" margin="0.002"/></body>
        <body name="b"><freejoint/><geom name="b" type="sphere" size="0.1" margin="0.002"/></body>
        <body name="c" pos="5 5 5"><freejoint/><geom name="c" type="sphere" size="0.1"/></body></worldbody></mujoco>""")
    tree = RigidBodyTree.from_model(load_mjcf(str(path)), dtype=torch.float64)
    qpos = tree.qpos0.unsqueeze(0).repeat(2, 1)
    qpos[0, 7] = 0.203  # body b along x: the gap is 3 mm, below the 4 mm margin
    qpos[1, 7] = 0.5  # a gap of 0.3 m
    ab = (0, 1)
    near = near_pairs(tree.contact_slots, forward_kinematics(tree, qpos[:1]))
    assert list(map(tuple, near.geom.tolist())) == [ab]
    assert list(map(tuple, near_pairs(tree.contact_slots, forward_kinematics(tree, qpos[1:])).geom.tolist())) == [ab]
    assert near_pairs(tree.contact_slots, forward_kinematics(tree, qpos[1:]), reach=0.3).count == 1
    far = tree.qpos0.unsqueeze(0).clone()
    far[0, 7] = 2.0
    lone = near_pairs(tree.contact_slots, forward_kinematics(tree, far))
    assert lone.count == 1 and collide(lone, forward_kinematics(tree, far)).active.sum() == 0


def _every_pair(slots, kin, reach=0.0):
    return slots


@pytest.mark.parametrize("task,mode", [("Humanoid-v5", "exact"), ("Pusher-v5", "cfd"), ("Ant-v5", "cfd")])
def test_step_with_the_broad_phase_equals_the_step_colliding_every_pair(task, mode, monkeypatch):
    """Values and gradients (float64, through a few env steps in contact) are the same bit for bit
    whether the step collides the near pairs or every pair."""
    def rollout():
        env = make_env(task, num_envs=4, seed=3, dtype=torch.float64, contact_gradient=mode)
        td = env.reset()
        actions = torch.rand(3, 4, env.action_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        actions = (2 * actions - 1).requires_grad_(True)
        total, states = 0.0, []
        for a in actions:
            td = env.step(td.set("action", a))["next"]
            total = total + td["reward"].sum()
            states.append(td["state", "qvel"])
        (grad,) = torch.autograd.grad(total, actions)
        return torch.stack(states), total.detach(), grad

    broad = rollout()
    monkeypatch.setattr(pipeline, "near_pairs", _every_pair)
    every = rollout()
    for ours, theirs in zip(broad, every):
        assert torch.equal(ours, theirs)
