"""The MuJoCo-model core and the contact-free tasks against MuJoCo and Gymnasium's own v5 envs.

Oracles: mujoco's compiled model (masses, inertias), ``mj_fullM`` and ``qfrc_bias`` at random
states, ``mj_step``, and gymnasium's ``InvertedPendulum-v5``, ``InvertedDoublePendulum-v5`` and
``Reacher-v5`` and ``Swimmer-v5`` driven from the same states with the same actions (float64);
MuJoCo's ``qfrc_passive`` for the swimmer's fluid forces.
"""
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")
gym = pytest.importorskip("gymnasium")

from torchrl_diffenvs.articulated import RigidBodyTree, forward_kinematics, gymnasium_asset, load_mjcf, mass_matrix_and_bias, step  # noqa: E402
from torchrl_diffenvs.articulated.dynamics import default_params, dof_invweight0  # noqa: E402
from torchrl_diffenvs.articulated.mjcf import quat_to_mat  # noqa: E402
from torchrl_diffenvs.envs import make_env  # noqa: E402

ASSETS = ["inverted_pendulum.xml", "inverted_double_pendulum.xml", "reacher.xml", "half_cheetah.xml", "hopper.xml",
          "walker2d_v5.xml", "swimmer.xml", "ant.xml", "humanoid.xml", "humanoidstandup.xml", "pusher_v5.xml"]


def mj_model(filename):
    return mujoco.MjModel.from_xml_path(str(gymnasium_asset(filename)))


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", ASSETS)
def test_loader_matches_mujoco_compiler(filename):
    model, mm = load_mjcf(gymnasium_asset(filename)), mj_model(filename)
    # (an unnamed body is "body<index>" here, "" in MuJoCo)
    assert model.body_names == [mm.body(i).name or f"body{i}" for i in range(mm.nbody)]
    inertia = np.stack([quat_to_mat(q) @ np.diag(i) @ quat_to_mat(q).T for q, i in zip(mm.body_iquat, mm.body_inertia)])
    np.testing.assert_allclose(model.body_mass, mm.body_mass, atol=1e-12)
    np.testing.assert_allclose(model.body_inertia, inertia, atol=1e-12)
    np.testing.assert_allclose(model.body_com, mm.body_ipos, atol=1e-12)
    np.testing.assert_allclose(model.qpos0, mm.qpos0, atol=1e-12)
    np.testing.assert_array_equal(model.joint_qposadr, mm.jnt_qposadr)
    np.testing.assert_array_equal(model.joint_dofadr, mm.jnt_dofadr)
    np.testing.assert_array_equal(model.dof_joint, mm.dof_jntid)
    assert model.joint_type == [["free", "ball", "slide", "hinge"][t] for t in mm.jnt_type]
    np.testing.assert_allclose(model.joint_range, mm.jnt_range, atol=1e-12)
    np.testing.assert_array_equal(model.limited, mm.jnt_limited.astype(bool))
    for ours, theirs in [(model.armature, mm.dof_armature), (model.damping, mm.dof_damping),
                         (model.stiffness, mm.jnt_stiffness), (model.limit_solimp, mm.jnt_solimp),
                         (model.limit_solref, mm.jnt_solref), (model.actuator_gear, mm.actuator_gear[:, 0]),
                         (model.ctrl_range, mm.actuator_ctrlrange), (model.timestep, mm.opt.timestep),
                         (model.gravity, mm.opt.gravity), (model.density, mm.opt.density),
                         (model.viscosity, mm.opt.viscosity)]:
        np.testing.assert_allclose(ours, theirs, atol=1e-12)
    assert model.integrator == ("rk4" if mm.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4 else "euler")


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", ASSETS)
def test_mass_matrix_and_bias_forces_match_mujoco(filename):
    model, mm = load_mjcf(gymnasium_asset(filename)), mj_model(filename)
    data = mujoco.MjData(mm)
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    rng = np.random.default_rng(0)
    np.testing.assert_allclose(dof_invweight0(tree, params)[0].numpy(), mm.dof_invweight0, rtol=1e-10)
    for _ in range(10):
        data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq)
        data.qvel[:] = rng.normal(size=mm.nv) * 2
        mujoco.mj_forward(mm, data)
        full = np.zeros((mm.nv, mm.nv))
        mujoco.mj_fullM(mm, data, full)
        kin = forward_kinematics(tree, torch.tensor(data.qpos[None]))
        mass, bias = mass_matrix_and_bias(tree, kin, torch.tensor(data.qvel[None]), params)
        np.testing.assert_allclose(kin.body_pos[0].numpy(), data.xpos, atol=1e-12)
        np.testing.assert_allclose(mass[0].numpy(), full, atol=1e-11)
        np.testing.assert_allclose(bias[0].numpy(), data.qfrc_bias, atol=1e-10)


def test_fluid_forces_match_mujocos_passive_force():
    """Swimmer-v5's medium: our inertia-box fluid force equals MuJoCo's ``qfrc_passive`` (the
    swimmer has no joint springs or dampers, so that is all fluid) at random states, also with
    other densities and viscosities set as params and in the compiled model."""
    from torchrl_diffenvs.articulated.dynamics import fluid_force

    model, mm = load_mjcf(gymnasium_asset("swimmer.xml")), mj_model("swimmer.xml")
    assert not mm.dof_damping.any() and not mm.jnt_stiffness.any()
    data = mujoco.MjData(mm)
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    rng = np.random.default_rng(3)
    for density, viscosity in ((4000.0, 0.1), (1000.0, 0.0), (0.0, 2.0)):
        mm.opt.density, mm.opt.viscosity = density, viscosity
        params["fluid_density"] = torch.tensor([density], dtype=torch.float64)
        params["fluid_viscosity"] = torch.tensor([viscosity], dtype=torch.float64)
        for _ in range(5):
            data.qpos[:] = mm.qpos0 + rng.normal(size=mm.nq)
            data.qvel[:] = rng.normal(size=mm.nv) * 2
            mujoco.mj_forward(mm, data)
            kin = forward_kinematics(tree, torch.tensor(data.qpos[None]))
            ours = fluid_force(tree, kin, torch.tensor(data.qvel[None]), params)
            assert np.abs(data.qfrc_passive).max() > 1e-3
            np.testing.assert_allclose(ours[0].numpy(), data.qfrc_passive, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("filename,scale", [("inverted_double_pendulum.xml", 0.3), ("reacher.xml", 1.0),
                                            ("swimmer.xml", 1.0)])
def test_integrators_and_joint_limits_match_mj_step(filename, scale):
    """300 physics steps with random controls, joint limits hit repeatedly (counted)."""
    model, mm = load_mjcf(gymnasium_asset(filename)), mj_model(filename)
    data = mujoco.MjData(mm)
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    rng = np.random.default_rng(1)
    data.qpos[:] = mm.qpos0 + rng.uniform(-scale, scale, size=mm.nq)
    data.qvel[:] = rng.uniform(-scale, scale, size=mm.nv)
    limit_steps = _steps_match_mj_step(mm, data, tree, params, [rng.uniform(-2, 2, size=mm.nu) for _ in range(300)])
    if filename != "swimmer.xml":  # (its +-100 degree limits are rarely reached; it checks the fluid and RK4)
        assert limit_steps >= 10  # the soft joint limit was exercised


def _steps_match_mj_step(mm, data, tree, params, controls, atol=1e-6) -> int:
    """Steps MuJoCo and us from ``data``'s state with ``controls``; returns the steps with a limit active."""
    model = tree.model
    qpos, qvel = torch.tensor(data.qpos[None].copy()), torch.tensor(data.qvel[None].copy())
    limit_steps = 0
    for ctrl in controls:
        data.ctrl[:] = ctrl
        mujoco.mj_step(mm, data)
        limit_steps += data.nefc > 0
        qpos, qvel, *_ = step(tree, qpos, qvel, torch.tensor(ctrl[None]), params, model.timestep, model.integrator)
        np.testing.assert_allclose(qpos[0].numpy(), data.qpos, atol=atol, rtol=atol)
        np.testing.assert_allclose(qvel[0].numpy(), data.qvel, atol=atol, rtol=atol)
    return limit_steps


def test_quaternion_integration_matches_mj_integrate_pos():
    """Ant's free joint (world position, quaternion) and a ball joint moved by random velocities,
    from unnormalised quaternions (MuJoCo normalises them first), as ``mj_integratePos``."""
    from torchrl_diffenvs.articulated.dynamics import integrate_position

    xml = """<mujoco><worldbody><body name="a" pos="0 0 1" euler="10 20 30"><freejoint/>
      <geom type="capsule" size="0.1 0.3"/><body name="b" pos="0 0 0.5"><joint name="ball" type="ball" pos="0 0 0.1"/>
      <geom type="sphere" size="0.1"/><body name="c" pos="0 0 0.3"><joint name="hinge" axis="0 1 0"/>
      <geom type="sphere" size="0.1"/></body></body></body></worldbody></mujoco>"""
    mm = mujoco.MjModel.from_xml_string(xml)
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ball.xml"
        path.write_text(xml)
        model = load_mjcf(path)
    np.testing.assert_allclose(model.qpos0, mm.qpos0, atol=1e-12)  # the free joint starts at the body's pose
    tree = RigidBodyTree.from_model(model)
    rng = np.random.default_rng(4)
    for scale in (1e-9, 0.3, 5.0):
        qpos = mm.qpos0 + rng.uniform(-0.2, 0.2, size=mm.nq)
        qvel = rng.normal(size=mm.nv) * scale
        expected = qpos.copy()
        mujoco.mj_integratePos(mm, expected, qvel, 0.01)
        ours = integrate_position(tree, torch.tensor(qpos[None]), torch.tensor(qvel[None]), 0.01)[0].numpy()
        np.testing.assert_allclose(ours, expected, atol=1e-14)
        data = mujoco.MjData(mm)  # and the kinematics and dynamics of this ball-jointed chain
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(mm, data)
        kin = forward_kinematics(tree, torch.tensor(qpos[None]))
        params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
        full = np.zeros((mm.nv, mm.nv))
        mujoco.mj_fullM(mm, data, full)
        mass, bias = mass_matrix_and_bias(tree, kin, torch.tensor(qvel[None]), params)
        np.testing.assert_allclose(kin.body_pos[0].numpy(), data.xpos, atol=1e-12)
        np.testing.assert_allclose(kin.body_rot[0].numpy(), data.xmat.reshape(-1, 3, 3), atol=1e-12)
        np.testing.assert_allclose(mass[0].numpy(), full, atol=1e-12)
        np.testing.assert_allclose(bias[0].numpy(), data.qfrc_bias, atol=1e-10)


def _ant_in_the_air(integrator):
    """Ant-v5's model in zero gravity, 5 m above the floor, moving: MuJoCo's data, our tree and params."""
    model, mm = load_mjcf(gymnasium_asset("ant.xml")), mj_model("ant.xml")
    mm.opt.gravity[:] = 0.0
    mm.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER if integrator == "euler" else mujoco.mjtIntegrator.mjINT_RK4
    model.integrator = integrator
    data = mujoco.MjData(mm)
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    params["gravity"] = torch.zeros(1, 3, dtype=torch.float64)
    params.update({k: torch.tensor([v], dtype=torch.float64) for k, v in
                   {"contact_stiffness": 1e3, "contact_damping": 10.0, "contact_width": 0.002, "friction_velocity": 0.01}.items()})
    params["contact_friction"] = torch.tensor(tree.contact_pair_friction[None])
    rng = np.random.default_rng(5)
    data.qpos[:] = mm.qpos0 + rng.uniform(-0.1, 0.1, size=mm.nq)
    data.qpos[2] = 5.0
    data.qvel[:] = rng.normal(size=mm.nv)
    return mm, data, tree, params, [rng.uniform(-1, 1, size=mm.nu) for _ in range(150)]


def test_free_joint_ant_matches_mj_step_in_the_air_euler():
    """Ant-v5's model (a free joint, eight limited hinges, the ankles past their limits at the
    start): 150 Euler steps of random controls equal ``mj_step``'s to 1e-9, joint limits active."""
    mm, data, tree, params, controls = _ant_in_the_air("euler")
    limit_steps = _steps_match_mj_step(mm, data, tree, params, controls, atol=1e-9)
    assert data.ncon == 0 and limit_steps >= 50


def test_free_joint_ant_rk4_matches_mj_step_in_the_air():
    """RK4 with a free joint: 150 steps of random controls equal MuJoCo 4's ``mj_step`` to 1e-9,
    joint limits active: its RK4 corrects the rotations that move the orientation (Munthe-Kaas),
    without which the trajectories part by ~1e-7 per step."""
    mm, data, tree, params, controls = _ant_in_the_air("rk4")
    limit_steps = _steps_match_mj_step(mm, data, tree, params, controls, atol=1e-9)
    assert data.ncon == 0 and limit_steps >= 50


def test_rk4_rotation_correction_is_dexp_inverse_in_each_of_mujocos_branches():
    """The Munthe-Kaas correction against its closed form ``w + theta x w / 2 + c theta x (theta x w)``,
    ``c = (1 - (t/2) cot(t/2)) / t^2``: MuJoCo's series below |theta|^2 = 3.0625, the closed form
    above, and rotation vectors past pi wrapped to their nearest representative; gradcheck in
    float64 across the three branches."""
    from torchrl_diffenvs.articulated.integrators import _dexp_inverse

    rng = np.random.default_rng(3)
    directions = rng.normal(size=(6, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    angles = np.array([1e-4, 0.3, 1.74, 1.76, 2.9, 3.1])  # both sides of sqrt(3.0625) = 1.75
    theta, w = directions * angles[:, None], rng.normal(size=(6, 3))
    t = angles[:, None]
    c = (1 - (t / 2) / np.tan(t / 2)) / t**2
    u = np.cross(theta, w)
    expected = w + 0.5 * u + c * np.cross(theta, u)
    ours = _dexp_inverse(torch.tensor(theta), torch.tensor(w)).numpy()
    np.testing.assert_allclose(ours, expected, rtol=1e-12, atol=1e-12)
    # past pi: the same as the equivalent rotation vector of angle t - 2 pi
    far = directions * (angles[:, None] + 2 * np.pi)
    np.testing.assert_allclose(_dexp_inverse(torch.tensor(far), torch.tensor(w)).numpy(), expected, rtol=1e-9,
                               atol=1e-9)
    both = torch.tensor(np.concatenate([theta, directions * 4.0]), requires_grad=True)
    spin = torch.tensor(rng.normal(size=(12, 3)), requires_grad=True)
    assert torch.autograd.gradcheck(_dexp_inverse, (both, spin))


def test_params_act_as_an_edited_model_file(tmp_path):
    """Masses and damping given as params equal a model file edited to them, joint limits included
    (MuJoCo's limit regulariser scales with diag(M^-1) at qpos0, which the masses change)."""
    import xml.etree.ElementTree as ET

    tree_xml = ET.parse(gymnasium_asset("inverted_double_pendulum.xml"))
    for body, mass in (("cart", 6.0), ("pole", 2.0), ("pole2", 7.0)):
        tree_xml.find(f".//body[@name='{body}']/geom").set("mass", str(mass))
    for joint, damping in (("slider", 0.8), ("hinge", 0.3), ("hinge2", 0.02)):
        tree_xml.find(f".//joint[@name='{joint}']").set("damping", str(damping))
    edited = tmp_path / "edited.xml"
    tree_xml.write(edited)
    mm = mujoco.MjModel.from_xml_path(str(edited))
    data = mujoco.MjData(mm)

    model = load_mjcf(gymnasium_asset("inverted_double_pendulum.xml"))  # the unedited file
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    rot = np.stack([quat_to_mat(q) for q in mm.body_iquat])
    params["body_mass"] = torch.tensor(mm.body_mass[None])
    params["body_inertia"] = torch.tensor((rot * mm.body_inertia[:, None, :]) @ rot.transpose(0, 2, 1))[None]
    params["damping"] = torch.tensor(mm.dof_damping[None])
    assert not np.allclose(mm.dof_invweight0, dof_invweight0(tree, {k: v.unsqueeze(0) for k, v in
                                                                   default_params(model).items()})[0].numpy())
    np.testing.assert_allclose(dof_invweight0(tree, params)[0].numpy(), mm.dof_invweight0, rtol=1e-10)
    rng = np.random.default_rng(2)
    data.qpos[:] = rng.uniform(-0.5, 0.5, size=mm.nq)
    # pushes held for 0.6 s drive the cart into both ends of its rail
    controls = [(1.0 if (i // 60) % 2 == 0 else -1.0) + rng.uniform(-0.3, 0.3, size=mm.nu) for i in range(300)]
    assert _steps_match_mj_step(mm, data, tree, params, controls) >= 10


def _gym_state(task, data):
    """Our state TensorDict entries for gymnasium's current MuJoCo data."""
    state = {"qpos": data.qpos.copy(), "qvel": data.qvel.copy()}
    if task == "InvertedDoublePendulum-v5":
        state["qfrc_constraint"] = data.qfrc_constraint.copy()
    if task == "Reacher-v5":
        state["fingertip_to_target"] = data.body("fingertip").xpos - data.body("target").xpos
    return {k: torch.tensor(v[None]) for k, v in state.items()}


@pytest.mark.parametrize("task,action_scale", [
    ("InvertedPendulum-v5", 3.0), ("InvertedDoublePendulum-v5", 1.0), ("Reacher-v5", 1.5), ("Swimmer-v5", 1.5),
])
def test_contact_free_tasks_match_gymnasium(task, action_scale):
    """>= 120 steps over several episodes: observations, rewards, terminated, truncated (float64, 1e-6).

    Actions go past the ctrlrange (MuJoCo clamps them) and Reacher runs through its 50-step limit.
    Swimmer's 1000-step episodes are compared for their first 150 steps, through six joint-limit
    impacts: later (past 300 steps), 1e-12 state differences from summation order can
    switch a limit on one physics step earlier in one simulator than in the other (MuJoCo's limit
    force jumps to its damping term when it activates), and the runs part by ~1e-7.
    """
    genv = gym.make(task)
    env = make_env(task, num_envs=1, dtype=torch.float64, seed=0)
    rng = np.random.default_rng(2)
    compared, episodes = 0, 0
    while compared < 120:
        gobs, _ = genv.reset(seed=episodes)
        episodes += 1
        data = genv.unwrapped.data
        td = env.reset()
        td["state"].update(_gym_state(task, data))
        td = env.reset(td, set_state=True)
        np.testing.assert_allclose(td["observation"][0].numpy(), gobs, atol=1e-6)
        while True:
            action = rng.uniform(-action_scale, action_scale, size=env.action_dim)
            gobs, greward, gterm, gtrunc, _ = genv.step(action)
            td["action"] = torch.tensor(action[None])
            td = env.step(td)
            nxt = td["next"]
            np.testing.assert_allclose(nxt["observation"][0].numpy(), gobs, atol=1e-6, rtol=1e-6)
            assert nxt["reward"].item() == pytest.approx(greward, abs=1e-6)
            assert nxt["terminated"].item() == gterm
            assert nxt["truncated"].item() == gtrunc
            compared += 1
            if gterm or gtrunc or nxt["episode_step"].item() >= 150:
                break
            td = nxt.clone()
    genv.close()


def test_jointly_solved_limit_forces_match_brute_force_enumeration():
    """The limit rows' complementarity problem against trying every set of pushing rows: random
    positive definite couplings, offsets and allowed rows (6 rows, 200 problems): the CPU's path
    (only coupled envs pivot, early exit), the fixed rounds, and the GPU's path without host reads."""
    import itertools

    from torchrl_diffenvs.articulated.limits import _complementary_forces, _complementary_forces_eager, _pivot

    gen = torch.Generator().manual_seed(0)
    n, rows = 200, 6
    base = torch.randn(n, rows, rows, generator=gen, dtype=torch.float64)
    matrix = base @ base.transpose(-1, -2) + 0.5 * torch.eye(rows, dtype=torch.float64)
    offset = torch.randn(n, rows, generator=gen, dtype=torch.float64) * 3
    allowed = torch.rand(n, rows, generator=gen) < 0.6
    expected = torch.zeros(n, rows, dtype=torch.float64)
    for i in range(n):
        idx = [r for r in range(rows) if allowed[i, r]]
        for size in range(len(idx) + 1):
            found = False
            for subset in itertools.combinations(idx, size):
                f = torch.zeros(rows, dtype=torch.float64)
                if subset:
                    s = list(subset)
                    f[s] = torch.linalg.solve(matrix[i][s][:, s], -offset[i, s])
                w = matrix[i] @ f + offset[i]
                if (f >= -1e-12).all() and (w[idx] >= -1e-9).all():
                    expected[i], found = f, True
                    break
            if found:
                break
        assert found, i
    diagonal = matrix.diagonal(dim1=-2, dim2=-1)
    solved = _complementary_forces(offset, allowed, diagonal, lambda envs: matrix[envs])
    torch.testing.assert_close(solved, expected, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(_pivot(matrix, offset, allowed, early_exit=False), expected, rtol=1e-9, atol=1e-9)
    # the GPU's path: no host read, every env pivots (its own rounds stop early on CUDA only)
    without_reads = _complementary_forces_eager(offset, allowed, diagonal, lambda envs: matrix[envs], host_reads=False)
    torch.testing.assert_close(without_reads, expected, rtol=1e-9, atol=1e-9)
    assert (expected > 0).sum(-1).max() >= 3  # several rows pushing at once
