"""Humanoid-v5, HumanoidStandup-v5 and Pusher-v5 and what their models need, against MuJoCo and
gymnasium: contact between bodies' geoms (which pairs, their distances), fixed tendons,
MuJoCo's centre-of-mass quantities (``cinert``, ``cvel``, ``xipos``), the physics in the air
and the tasks' observations, rewards and terminations from the same states (float64)."""
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")

from torchrl_diffenvs.articulated import RigidBodyTree, forward_kinematics, gymnasium_asset, load_mjcf, step  # noqa: E402
from torchrl_diffenvs.articulated.com import body_com, com_inertia, com_velocity, mass_center  # noqa: E402
from torchrl_diffenvs.articulated.contact import body_contact_forces, pair_contact_force, pair_geometry, pair_jacobian  # noqa: E402
from torchrl_diffenvs.articulated.dynamics import default_params  # noqa: E402
from torchrl_diffenvs.articulated.forces import passive_force  # noqa: E402
from torchrl_diffenvs.articulated.mjcf import MJCFError  # noqa: E402
from torchrl_diffenvs.envs import make_env  # noqa: E402
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)

CONTACT = {"contact_stiffness": 5e4, "contact_damping": 1000.0, "contact_width": 0.002, "friction_velocity": 0.01}


def _setup(filename, xml=None):
    path = gymnasium_asset(filename)
    if xml is not None:
        path = xml
    model, mm = load_mjcf(path), mujoco.MjModel.from_xml_path(str(path))
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    params.update({k: torch.tensor([v], dtype=torch.float64) for k, v in CONTACT.items()})
    params["contact_friction"] = torch.tensor(tree.contact_pair_friction[None])
    return model, mm, mujoco.MjData(mm), tree, params


@pytest.mark.parametrize("filename", ["humanoid.xml", "humanoidstandup.xml", "pusher_v5.xml"])
def test_centre_of_mass_quantities_match_mujoco(filename):
    """``cinert``, ``cvel``, ``xipos`` and Gymnasium's mass centre at random states."""
    model, mm, data, tree, params = _setup(filename)
    rng = np.random.default_rng(0)
    for _ in range(5):
        data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq) * 0.5
        data.qvel[:] = rng.normal(size=mm.nv)
        mujoco.mj_forward(mm, data)
        kin = forward_kinematics(tree, torch.tensor(data.qpos[None]))
        qvel = torch.tensor(data.qvel[None])
        assert np.abs(data.cinert).max() > 1.0 and np.abs(data.cvel).max() > 1.0
        np.testing.assert_allclose(com_inertia(tree, kin, params)[0].numpy(), data.cinert, atol=1e-12)
        np.testing.assert_allclose(com_velocity(tree, kin, qvel, params)[0].numpy(), data.cvel, atol=1e-12)
        np.testing.assert_allclose(body_com(tree, kin)[0].numpy(), data.xipos, atol=1e-12)
        centre = (mm.body_mass[:, None] * data.xipos).sum(0) / mm.body_mass.sum()
        np.testing.assert_allclose(mass_center(tree, kin, params)[0].numpy(), centre, atol=1e-12)


@pytest.mark.parametrize("filename,count", [("humanoid.xml", 109), ("pusher_v5.xml", 3), ("hopper.xml", 3)])
def test_colliding_geom_pairs_are_mujocos(filename, count):
    """The geom pairs that can touch (MuJoCo's contype/conaffinity, weld and parent filters):
    with a 1 m contact margin MuJoCo reports a contact for every candidate pair within reach, and
    over random configurations the pairs it reports are exactly ours."""
    model, mm, data, tree, params = _setup(filename)
    planes = {n for n, t in zip(model.geom_names, model.geom_type) if t == "plane"}
    ours = {frozenset(p) for p in tree.contact_pairs if not set(p) & planes}
    assert len(ours) == count
    mm.geom_margin[:] = 1.0
    rng = np.random.default_rng(0)
    name = lambda g: mm.geom(g).name or f"geom{g}"  # noqa: E731
    seen = set()
    for _ in range(300 if count > 50 else 50):
        data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq) * 1.5
        mujoco.mj_forward(mm, data)
        seen |= {frozenset((name(c.geom1), name(c.geom2))) for c in data.contact[:data.ncon]}
    seen = {p for p in seen if not p & planes}
    assert seen == ours


def test_pair_distances_match_mj_geom_distance():
    """The signed distance of every humanoid geom pair (capsules and spheres) equals MuJoCo's
    ``mj_geomDistance``, penetrating pairs included, at random configurations."""
    model, mm, data, tree, params = _setup("humanoid.xml")
    rng = np.random.default_rng(1)
    ids = [(mm.geom(a).id, mm.geom(b).id) for a, b in tree.contact_pairs if "floor" not in (a, b)]
    penetrating = 0
    for _ in range(5):
        data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq) * 1.0
        mujoco.mj_forward(mm, data)
        dist, normal, _ = pair_geometry(tree, forward_kinematics(tree, torch.tensor(data.qpos[None])))
        fromto = np.zeros(6)
        theirs = np.array([mujoco.mj_geomDistance(mm, data, a, b, 10.0, fromto) for a, b in ids])
        np.testing.assert_allclose(dist[0].numpy(), theirs, atol=1e-9)
        penetrating += int((theirs < 0).sum())
        assert torch.allclose(normal.norm(dim=-1), torch.ones(1, dtype=torch.float64))
    assert penetrating > 0


def test_pair_contacts_push_the_two_bodies_apart_equally_and_oppositely():
    """A penetrating pair's force on the two bodies sums to zero (cfrc_ext summed over the bodies
    in the air, where only the limbs touch), each side pushed away from the other, and the
    generalised force is ``J^T f`` with ``J`` checked against finite-differenced point motions."""
    model, mm, data, tree, params = _setup("humanoid.xml")
    rng = np.random.default_rng(1)
    while True:
        qpos = torch.tensor((mm.qpos0 + rng.normal(size=mm.nq))[None])
        qpos[0, 2] = 10.0  # far above the floor
        kin = forward_kinematics(tree, qpos)
        dist, normal, point = pair_geometry(tree, kin)
        if (dist < -0.01).any():
            break
    qvel = torch.zeros(1, mm.nv, dtype=torch.float64)
    wrench = body_contact_forces(tree, kin, qvel, params, about=kin.origin)
    assert wrench[0, :, 3:].norm(dim=-1).max() > 1.0
    torch.testing.assert_close(wrench[0].sum(0), torch.zeros(6, dtype=torch.float64), atol=1e-9, rtol=0)
    k = int(dist[0].argmin())
    a, b = tree.pair_body[k].tolist()
    assert (wrench[0, b, 3:] * normal[0, k]).sum() > 0 > (wrench[0, a, 3:] * normal[0, k]).sum()
    # the generalised force is J^T f, J the velocity of B's material point at the contact point
    # minus A's: checked against those two points moved by finite differences of the positions
    from torchrl_diffenvs.articulated.contact import _pair_forces
    from torchrl_diffenvs.articulated.kinematics import integrate_position
    v = torch.tensor(rng.normal(size=(1, mm.nv)))
    c = _pair_forces(tree, kin, qvel, params)
    jacobian = pair_jacobian(tree, kin, c.point)
    world = c.point[0, k] + kin.origin[0]
    local = [kin.body_rot[0, i].T @ (world - kin.body_pos[0, i]) for i in (a, b)]
    h = 1e-6
    moved = [forward_kinematics(tree, integrate_position(tree, qpos, v, s * h)) for s in (1, -1)]
    at = lambda m, i, x: m.body_pos[0, i] + m.body_rot[0, i] @ x  # noqa: E731
    fd = [(at(moved[0], i, x) - at(moved[1], i, x)) / (2 * h) for i, x in zip((a, b), local)]
    torch.testing.assert_close((jacobian[0, k] * v[0, :, None]).sum(0), fd[1] - fd[0], atol=1e-7, rtol=1e-6)
    generalised = pair_contact_force(tree, kin, qvel, params)
    power = (c.force[0] * (jacobian[0] * v[0, :, None]).sum(1)).sum()
    assert (generalised[0] @ v[0]).item() == pytest.approx(power.item(), rel=1e-10)


def _frictional_humanoid(tmp_path):
    """The humanoid with condim 3 on every geom: its limbs' contacts have friction."""
    text = gymnasium_asset("humanoid.xml").read_text().replace('condim="1" contype="1"', 'condim="3" contype="1"')
    path = tmp_path / "humanoid_condim3.xml"
    path.write_text(text)
    return path


def _touching(tree, mm, rng):
    while True:
        qpos = torch.tensor((mm.qpos0 + rng.normal(size=mm.nq))[None])
        if (pair_geometry(tree, forward_kinematics(tree, qpos))[0].abs() < 0.002).any():
            return qpos  # a pair within the contact width: the smooth force's curved part


@pytest.mark.parametrize("frictional", [False, True])
def test_pair_contact_gradcheck(frictional, tmp_path):
    """float64 gradcheck of the body-body contact force and its damping matrix in the positions,
    velocities and contact parameters: the humanoid's frictionless limbs (condim 1) and the same
    model with condim 3 (friction 0.7), so every term is exercised."""
    model, mm, data, tree, params = _setup("humanoid.xml", xml=_frictional_humanoid(tmp_path) if frictional else None)
    assert bool(tree.pair_frictional.all()) == frictional and not bool(tree.pair_frictional.any()) != frictional
    params["contact_friction"] = torch.full_like(params["contact_friction"], 0.7)
    rng = np.random.default_rng(1)
    qpos = _touching(tree, mm, rng)
    qvel = torch.tensor(rng.normal(size=(1, mm.nv)))

    def force(q, v, stiffness, friction):
        p = dict(params, contact_stiffness=stiffness, contact_friction=friction)
        generalised, damping = pair_contact_force(tree, forward_kinematics(tree, q), v, p, with_damping=True)
        return generalised, damping.sum(-1)

    inputs = (qpos.requires_grad_(), qvel.requires_grad_(), params["contact_stiffness"].clone().requires_grad_(),
              params["contact_friction"].clone().requires_grad_())
    # forces of ~1e4 N: an absolute tolerance above central differences' round-off at eps = 1e-6
    assert torch.autograd.gradcheck(force, inputs, eps=1e-6, atol=1e-3, rtol=1e-4)


def test_frictionless_pairs_take_the_short_path_to_the_same_forces(tmp_path):
    """condim 1 (no point Jacobian) and condim 3 with zero friction (the full Jacobian): the same
    generalised force and damping matrix; friction on a condim-1 pair is ignored, as in MuJoCo."""
    plain = _setup("humanoid.xml")
    full = _setup("humanoid.xml", xml=_frictional_humanoid(tmp_path))
    rng = np.random.default_rng(4)
    qpos, qvel = _touching(plain[3], plain[1], rng), torch.tensor(rng.normal(size=(1, plain[1].nv)))
    outs = []
    for _, _, _, tree, params in (plain, full):
        params["contact_friction"] = torch.zeros_like(params["contact_friction"])
        outs.append(pair_contact_force(tree, forward_kinematics(tree, qpos), qvel, params, with_damping=True))
    for ours, theirs in zip(*outs):
        torch.testing.assert_close(ours, theirs, rtol=1e-10, atol=1e-9)
    assert outs[0][0].abs().max() > 1.0
    plain[4]["contact_friction"] = torch.full_like(plain[4]["contact_friction"], 0.7)
    again = pair_contact_force(plain[3], forward_kinematics(plain[3], qpos), qvel, plain[4])
    torch.testing.assert_close(again, outs[0][0])


def _tendon_xml(tmp_path, attributes):
    text = gymnasium_asset("humanoid.xml").read_text()
    text = text.replace('<fixed name="left_hipknee">', f'<fixed name="left_hipknee" {attributes}>')
    text = text.replace('<fixed name="right_hipknee">', '<fixed name="right_hipknee" stiffness="7" damping="0.5">')
    # a spring reference on one of its joints: MuJoCo's default rest length is the length there
    text = text.replace('name="right_knee" pos="0 0 .02"', 'name="right_knee" springref="-30" pos="0 0 .02"')
    path = tmp_path / "humanoid_tendons.xml"
    path.write_text(text)
    return path


def test_fixed_tendon_springs_and_dampers_match_mujocos_passive_force(tmp_path):
    """Tendon springs (an explicit springlength, and MuJoCo's default: the length with the joints at
    their springref, here -30 degrees on the right knee) and dampers on the humanoid's hip-knee
    tendons: the rest lengths and ``qfrc_passive`` equal MuJoCo's at random states."""
    path = _tendon_xml(tmp_path, 'stiffness="30" damping="2" springlength="0.3"')
    model, mm, data, tree, params = _setup("humanoid.xml", xml=path)
    np.testing.assert_allclose(model.tendon_springlength, mm.tendon_lengthspring[:, 0], atol=1e-12)
    assert model.tendon_springlength[1] == pytest.approx(-np.pi / 6)
    rng = np.random.default_rng(2)
    for _ in range(5):
        data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq) * 0.5
        data.qvel[:] = rng.normal(size=mm.nv)
        mujoco.mj_forward(mm, data)
        qpos = torch.tensor(data.qpos[None])
        ours = passive_force(tree, forward_kinematics(tree, qpos), qpos, torch.tensor(data.qvel[None]), params)
        np.testing.assert_allclose(ours[0].numpy(), data.qfrc_passive, atol=1e-10)
    # the humanoid's own tendons carry no spring or damper: its passive force is the joints' alone
    plain = _setup("humanoid.xml")
    assert plain[0].tendon_names == ["left_hipknee", "right_hipknee"] and not plain[0].tendon_stiffness.any()


@pytest.mark.parametrize("attributes,message", [
    ('limited="true" range="-1 1"', "tendon limits are not supported"),
    ('springlength="0.1 0.2"', "deadband"),
    ('frictionloss="1"', "frictionloss"),
])
def test_unsupported_tendon_features_are_refused(tmp_path, attributes, message):
    with pytest.raises(MJCFError, match=message):
        load_mjcf(_tendon_xml(tmp_path, attributes))


def test_humanoid_in_the_air_matches_mj_step():
    """The humanoid (free joint, 17 limited hinges, 2 fixed tendons) 10 m up, semi-implicit Euler:
    60 physics steps of random controls equal ``mj_step``'s to 1e-8 (no contact in MuJoCo either)."""
    model, mm, data, tree, params = _setup("humanoid.xml")
    mm.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    # the file's 50 PGS iterations leave the joint-limit forces ~1e-8 from the exact solution
    # that the limits are solved to here: converge MuJoCo's solver too
    mm.opt.iterations, mm.opt.tolerance = 1000, 1e-15
    # the smooth contact pushes limbs apart from a few contact widths away: off, as in MuJoCo (no contact)
    params["contact_stiffness"] = params["contact_damping"] = torch.zeros(1, dtype=torch.float64)
    rng = np.random.default_rng(3)
    data.qpos[:] = mm.qpos0 + rng.uniform(-0.05, 0.05, size=mm.nq)
    data.qpos[2] = 10.0
    data.qvel[:] = rng.normal(size=mm.nv) * 0.3
    qpos, qvel = torch.tensor(data.qpos[None].copy()), torch.tensor(data.qvel[None].copy())
    limits = 0
    for _ in range(60):
        ctrl = rng.uniform(-0.4, 0.4, size=mm.nu)
        data.ctrl[:] = ctrl
        mujoco.mj_step(mm, data)
        assert data.ncon == 0
        limits += data.nefc > 0
        qpos, qvel, *_ = step(tree, qpos, qvel, torch.tensor(ctrl[None]), params, model.timestep, "euler")
        np.testing.assert_allclose(qpos[0].numpy(), data.qpos, atol=1e-8)
        np.testing.assert_allclose(qvel[0].numpy(), data.qvel, atol=1e-8)
    assert limits > 0  # a joint limit was active


def _same_start(env, genv, qpos, qvel):
    """Puts both envs in the state ``(qpos, qvel)``: gymnasium's ``set_state`` and ours."""
    genv.unwrapped.set_state(qpos, qvel)
    td = env.reset()
    q, v = torch.tensor(qpos[None]), torch.tensor(qvel[None])
    td["state", "qpos"], td["state", "qvel"] = q, v
    if hasattr(env, "derived"):  # the humanoids: what MuJoCo derives at the reset state
        for key, value in env.derived(q, v, env.params).items():
            td["state", key] = value if key != "cfrc_ext" else torch.zeros_like(value)
    else:
        td["state", "body_points"] = env.body_points(q)
    return env.reset(td, set_state=True)


@pytest.mark.parametrize("name", ["Humanoid-v5", "HumanoidStandup-v5"])
def test_humanoids_in_the_air_match_gymnasium(name):
    """Humanoid-v5 lifted 5 m (gravity on), 12 steps of random actions with the file's RK4:
    observations (348: qpos, qvel, cinert, cvel, qfrc_actuator, cfrc_ext), rewards and
    terminations equal gymnasium's to 1e-4 (the healthy range widened in both; the file's RK4 as
    MuJoCo 4's, its rotation correction included; what is left, 2e-8 after one step and 1.4e-5
    after 12, is the residual of MuJoCo's 50 PGS iterations on the joint-limit rows, which this
    library solves to convergence). The smooth contact is switched off, as MuJoCo has none
    there. HumanoidStandup-v5: only its start observation (its hands rest 1.4 cm inside its hips,
    in MuJoCo too, so its steps involve contact; its reward is checked by hand below)."""
    kwargs = {"healthy_z_range": (1.0, 10.0)} if name == "Humanoid-v5" else {}
    genv = gym.make(name, **kwargs)
    params = {"healthy_z_high": 10.0} if name == "Humanoid-v5" else {}
    params.update(contact_stiffness=0.0, contact_damping=0.0)
    env = make_env(name, num_envs=1, dtype=torch.float64, seed=0, params=params, integrator="model")
    genv.reset(seed=0)
    data = genv.unwrapped.data
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    qpos[2] = 5.0
    td = _same_start(env, genv, qpos, qvel)
    gobs = genv.unwrapped._get_obs()
    assert gobs.shape == (348,) and td["observation"].shape == (1, 348)
    np.testing.assert_allclose(td["observation"][0].numpy(), gobs, atol=1e-10)
    if name == "HumanoidStandup-v5":
        assert data.ncon >= 4  # hands against hips and thighs
        return
    rng = np.random.default_rng(0)
    for _ in range(12):
        action = rng.uniform(-0.4, 0.4, size=17)
        gobs, greward, gterm, _, info = genv.step(action)
        assert data.ncon == 0
        td["action"] = torch.tensor(action[None])
        nxt = env.step(td)["next"]
        np.testing.assert_allclose(nxt["observation"][0].numpy(), gobs, atol=1e-4, rtol=1e-4)
        assert nxt["reward"].item() == pytest.approx(greward, abs=1e-4, rel=1e-6)
        assert nxt["terminated"].item() == gterm is False
        td = nxt.clone()
    assert abs(info["x_velocity"]) > 1e-3  # the forward term is exercised


@pytest.mark.parametrize("name", ["Humanoid-v5", "HumanoidStandup-v5"])
def test_humanoid_observation_options_match_gymnasiums_sizes(name):
    flags = ["include_cinert_in_observation", "include_cvel_in_observation", "include_qfrc_actuator_in_observation",
             "include_cfrc_ext_in_observation"]
    for off in [None, *flags]:
        kwargs = {flag: flag != off for flag in flags}
        size = gym.make(name, **kwargs).observation_space.shape[0]
        assert make_env(name, num_envs=2, **kwargs).reset()["observation"].shape == (2, size)
    size = gym.make(name, exclude_current_positions_from_observation=False).observation_space.shape[0]
    assert make_env(name, num_envs=2, exclude_current_positions_from_observation=False).reset()["observation"].shape == (2, size)


def test_humanoid_terminates_outside_its_healthy_height_and_standup_never_does():
    env = make_env("Humanoid-v5", num_envs=2, dtype=torch.float64, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(2, 17, dtype=torch.float64)
    for _ in range(200):  # standing still without motor torques, it falls below 1 m
        td = env.step(td)["next"].clone()
        td["action"] = torch.zeros(2, 17, dtype=torch.float64)
        if td["terminated"].all():
            break
    assert td["terminated"].all() and (td["state", "qpos"][:, 2] <= 1.0).all()
    standup = make_env("HumanoidStandup-v5", num_envs=2, dtype=torch.float64, seed=0)
    td = standup.reset()
    td["action"] = torch.zeros(2, 17, dtype=torch.float64)
    nxt = standup.step(td)["next"]
    assert not nxt["terminated"].any()
    # reward = z / 3 ms + 1 - costs (no action, and the impact cost is small at rest)
    expected = nxt["state", "qpos"][:, 2] / 0.003 + 1.0
    assert torch.allclose(nxt["reward"].flatten(), expected, atol=0.5)


def test_pusher_matches_gymnasium_before_the_wrist_reaches_the_object():
    """From gymnasium's own reset state, 15 steps of random actions: observation (23), reward
    and the physics equal gymnasium's while the only contact is the object resting on the table
    (frictionless, along z: it moves nothing)."""
    genv = gym.make("Pusher-v5")
    env = make_env("Pusher-v5", num_envs=1, dtype=torch.float64, seed=0)
    gobs, _ = genv.reset(seed=0)
    data = genv.unwrapped.data
    td = _same_start(env, genv, data.qpos.copy(), data.qvel.copy())
    np.testing.assert_allclose(td["observation"][0].numpy(), gobs, atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(15):
        action = rng.uniform(-2, 2, size=7)
        gobs, greward, gterm, _, _ = genv.step(action)
        names = {frozenset((genv.unwrapped.model.geom(c.geom1).name, genv.unwrapped.model.geom(c.geom2).name))
                 for c in data.contact[:data.ncon]}
        assert names <= {frozenset(("table", ""))}
        td["action"] = torch.tensor(action[None])
        nxt = env.step(td)["next"]
        np.testing.assert_allclose(nxt["observation"][0].numpy(), gobs, atol=1e-8)
        assert nxt["reward"].item() == pytest.approx(greward, abs=1e-8)
        assert not nxt["terminated"].item() and not gterm
        td = nxt.clone()


def test_pusher_start_states_follow_gymnasiums_distribution():
    env = make_env("Pusher-v5", num_envs=4096, seed=0)
    state = env.reset()["state"]
    qpos, qvel = state["qpos"], state["qvel"]
    cylinder, goal = qpos[:, -4:-2], qpos[:, -2:]
    assert (goal == 0).all() and (cylinder.norm(dim=-1) > 0.17).all()
    assert (cylinder[:, 0] >= -0.3).all() and (cylinder[:, 0] <= 0).all() and (cylinder[:, 1].abs() <= 0.2).all()
    torch.testing.assert_close(qpos[:, :7], env.tree.qpos0[:7].expand(4096, -1).float())
    assert (qvel[:, -4:] == 0).all() and (qvel[:, :7].abs() <= 0.005).all() and qvel[:, :7].std() > 0.002


def _pusher_touching(env):
    """A Pusher state with the wrist lowered to the table and the object 5 mm into its cross bar."""
    tree, model = env.tree, env.model
    qpos = tree.qpos0.clone()[None]
    qpos[0, 1], qpos[0, 3] = 1.0992, -1.3564  # shoulder lift, elbow: the wrist at the object's height
    wrist = forward_kinematics(tree, qpos).body_pos[0, model.body_index("r_wrist_roll_link")]
    base = tree.body_pos[model.body_index("object")]
    low, high = 0.0, 0.2  # bisect the object's offset ahead of the wrist (+x) to a 5 mm overlap
    for _ in range(50):
        mid = (low + high) / 2
        qpos[0, -3], qpos[0, -4] = wrist[0] + mid - base[0], wrist[1] - base[1]  # obj_slidex, obj_slidey
        dist = pair_geometry(tree, forward_kinematics(tree, qpos))[0].min()
        low, high = (mid, high) if dist < -0.005 else (low, mid)
    return qpos


def test_pusher_wrist_pushes_the_object_and_its_gradient_matches_finite_differences():
    """With the wrist's cross bar 5 mm into the object the contact pushes the object away (+x),
    and the object's position after 3 steps has a finite, non-zero derivative in the first
    action that equals central finite differences (float64): gradients flow through the push."""
    env = make_env("Pusher-v5", num_envs=1, dtype=torch.float64, seed=0)
    qpos = _pusher_touching(env)
    td = env.reset()
    td["state", "qpos"], td["state", "qvel"] = qpos, torch.zeros_like(qpos)
    td["state", "body_points"] = env.body_points(qpos)
    td = env.reset(td, set_state=True)

    def object_x(first_action):
        state = td.clone()
        for i in range(3):
            state["action"] = first_action if i == 0 else torch.zeros(1, 7, dtype=torch.float64)
            state = env.step(state)["next"]
        return state["state", "qpos"][0, -3]

    action = torch.full((1, 7), 0.3, dtype=torch.float64, requires_grad=True)
    x = object_x(action)
    assert x > qpos[0, -3] + 1e-4  # pushed ahead of the wrist
    (grad,) = torch.autograd.grad(x, action)
    h = 1e-6
    fd = torch.stack([(object_x(action.detach() + h * e) - object_x(action.detach() - h * e)) / (2 * h)
                      for e in torch.eye(7, dtype=torch.float64).unsqueeze(1)])
    assert torch.isfinite(grad).all() and grad.abs().max() > 1e-4
    torch.testing.assert_close(grad[0], fd, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("name", ["Humanoid-v5", "Pusher-v5", "Ant-v5"])
def test_a_state_reset_needs_only_qpos_and_qvel(name):
    """``reset(td, set_state=True)`` with only ``qpos`` and ``qvel``: the entries MuJoCo derives
    from them are computed, the last step's readings start at 0, and the result equals the
    env's own reset from the same start."""
    env = make_env(name, num_envs=3, dtype=torch.float64, seed=0)
    fresh = env.reset()
    td = fresh.exclude("state")
    td["state"] = fresh["state"].select("qpos", "qvel")
    again = env.reset(td, set_state=True)
    for key in fresh["state"].keys():
        torch.testing.assert_close(again["state", key], fresh["state", key])
    torch.testing.assert_close(again["observation"], fresh["observation"])
