"""MuJoCo's contact pipeline (the default ``contact="mujoco"``) stage by stage against mjData.

Oracles: MuJoCo's own ``mj_forward`` and ``mj_step`` at the same states (float64): the contacts of
``mj_collision`` (``d.contact``), the constraint rows (``efc_J``, ``efc_pos``, ``efc_R``,
``efc_aref``), the solve (``efc_force``, ``qfrc_constraint``, ``qacc``), ``body_invweight0``, and
full steps along random-action trajectories of MuJoCo's own; finite differences in float64 for
the gradients.
"""
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from torchrl_diffenvs.articulated import RigidBodyTree, default_params, forward_kinematics, gymnasium_asset, load_mjcf, step  # noqa: E402
from torchrl_diffenvs.articulated.collision import collide  # noqa: E402
from torchrl_diffenvs.articulated.constraint import constraint_rows, solve  # noqa: E402
from torchrl_diffenvs.articulated.newton import line_search  # noqa: E402
from torchrl_diffenvs.articulated.inertia import body_invweight0, mass_matrix_and_bias  # noqa: E402
from torchrl_diffenvs.articulated.pipeline import accelerations, body_contact_wrenches, invweight0  # noqa: E402
from torchrl_diffenvs.envs import make_env  # noqa: E402

from _env_helpers import REPO, load_script  # noqa: E402
from _mujoco_steps import gaps_to_mj_step, mujoco_converged  # noqa: E402

# the Pusher's pushing trajectories (MuJoCo's own) come from the benchmark that reports them
CONTACT_MODEL = load_script("contact_model", REPO / "benchmarks" / "contact_model.py")

CONTACT_ASSETS = ["half_cheetah.xml", "hopper.xml", "walker2d_v5.xml", "ant.xml", "humanoid.xml", "humanoidstandup.xml"]
# the files without a free joint: their full MuJoCo step is matched (see test_step_matches_mj_step)
PLANAR = ["half_cheetah.xml", "hopper.xml", "walker2d_v5.xml"]


def setup(filename):
    model = load_mjcf(gymnasium_asset(filename))
    mm = mujoco.MjModel.from_xml_path(str(gymnasium_asset(filename)))
    tree = RigidBodyTree.from_model(model)
    params = {k: v.unsqueeze(0) for k, v in default_params(model).items()}
    params["contact_friction"] = torch.as_tensor(tree.contact_pair_friction).unsqueeze(0)
    return model, mm, mujoco.MjData(mm), tree, params


def trajectory_states(mm, data, steps, seed, every=1):
    """``(qpos, qvel, ctrl)`` along a random-action trajectory of MuJoCo's own (from a perturbed qpos0)."""
    rng = np.random.default_rng(seed)
    mujoco.mj_resetData(mm, data)
    data.qpos[:] += rng.uniform(-0.1, 0.1, mm.nq)
    mujoco.mj_normalizeQuat(mm, data.qpos)
    out = []
    for t in range(steps):
        data.ctrl[:] = rng.uniform(mm.actuator_ctrlrange[:, 0], mm.actuator_ctrlrange[:, 1])
        if t % every == 0:
            out.append((data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()))
        mujoco.mj_step(mm, data)
    return out


def forward(mm, data, qpos, qvel, ctrl):
    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
    data.qacc_warmstart[:] = 0
    mujoco.mj_forward(mm, data)


def t64(*arrays):
    return [torch.as_tensor(np.asarray(a, dtype=np.float64)).unsqueeze(0) for a in arrays]


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", CONTACT_ASSETS)
def test_body_invweight0_matches_mujoco(filename):
    _, mm, _, tree, params = setup(filename)
    np.testing.assert_allclose(body_invweight0(tree, params)[0].numpy(), mm.body_invweight0, rtol=1e-10, atol=1e-14)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", CONTACT_ASSETS)
def test_contacts_match_mj_collision(filename):
    """The same contacts per geom pair (count, pos, frame, dist, includemargin) at random
    configurations pressed into the floor and along a trajectory."""
    model, mm, data, tree, params = setup(filename)
    rng = np.random.default_rng(1)
    states = [s[0] for s in trajectory_states(mm, data, 200, seed=2, every=10)]
    for _ in range(40):  # random configurations, some deep in the floor
        q = model.qpos0 + rng.normal(0.0, 0.3, model.nq)
        if model.joint_type[0] == "free":
            q[2] = rng.uniform(-0.1, 0.6)
            q[3:7] /= np.linalg.norm(q[3:7])
        else:
            q[1] += rng.uniform(-1.2, 0.0)
        states.append(q)
    slots, compared = tree.contact_slots, 0
    for q in states:
        forward(mm, data, q, np.zeros(mm.nv), np.zeros(mm.nu))
        (qpos,) = t64(q)
        c = collide(slots, forward_kinematics(tree, qpos))
        ours = sorted((tuple(slots.geom[i].tolist()), c.dist[0, i].item(), i) for i in np.flatnonzero(c.active[0].numpy()))
        theirs = sorted((tuple(map(int, data.contact.geom[i])), data.contact.dist[i], i)
                        for i in range(data.ncon) if not data.contact.exclude[i])
        assert [o[0] for o in ours] == [t[0] for t in theirs]
        for (_, dist, i), (_, mj_dist, j) in zip(ours, theirs):
            assert dist == pytest.approx(mj_dist, abs=1e-12)
            np.testing.assert_allclose(c.pos[0, i].numpy(), data.contact.pos[j], atol=1e-12)
            np.testing.assert_allclose(c.frame[0, i].numpy().ravel(), data.contact.frame[j], atol=1e-12)
            assert slots.margin[i].item() == pytest.approx(data.contact.includemargin[j], abs=1e-15)
            assert slots.condim[i] == data.contact.dim[j]
        compared += len(ours)
    assert compared > 60


def _mujoco_rows(mm, data):
    """MuJoCo's rows as ``{(kind, key): (J [k, nv], pos, R [k], aref [k], force [k])}``: limits keyed by
    their order, contacts by (geom pair, rounded position)."""
    rows, nv = {}, mm.nv
    jac = data.efc_J.reshape(data.nefc, nv)
    i, limit = 0, 0
    while i < data.nefc:
        kind = data.efc_type[i]
        if kind == mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT:
            rows[("limit", int(data.efc_id[i]), float(np.sign(jac[i][jac[i] != 0][0])))] = \
                (jac[i:i + 1], data.efc_pos[i], data.efc_R[i:i + 1], data.efc_aref[i:i + 1], data.efc_force[i:i + 1])
            i, limit = i + 1, limit + 1
            continue
        con = data.contact[int(data.efc_id[i])]
        k = 1 if kind == mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS else 2 * (con.dim - 1)
        key = ("contact", tuple(map(int, con.geom)), tuple(np.round(con.pos, 9)))
        rows[key] = (jac[i:i + k], data.efc_pos[i], data.efc_R[i:i + k], data.efc_aref[i:i + k], data.efc_force[i:i + k])
        i += k
    return rows


def _our_rows(model, tree, slots, contacts, rows, force):
    out = {}
    limits, pyramid = rows.rows_per_slot
    for r in range(limits):
        if rows.exists[0, r]:
            joint = int(model.dof_joint[tree.limit_dof[r]])
            out[("limit", joint, float(tree.limit_sign[r]))] = slice(r, r + 1)
    for n, s in enumerate(slots.pyramid_index.tolist()):
        if contacts.active[0, s]:
            out[("contact", tuple(slots.geom[s].tolist()), tuple(np.round(contacts.pos[0, s].numpy(), 9)))] = \
                slice(limits + 4 * n, limits + 4 * n + 4)
    for n, s in enumerate(slots.normal_index.tolist()):
        if contacts.active[0, s]:
            out[("contact", tuple(slots.geom[s].tolist()), tuple(np.round(contacts.pos[0, s].numpy(), 9)))] = \
                slice(limits + pyramid + n, limits + pyramid + n + 1)
    return out


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", CONTACT_ASSETS)
def test_constraint_rows_force_and_qacc_match_mjdata(filename):
    """efc_J, efc_pos, efc_R (hence efc_D), efc_aref, efc_force, qfrc_constraint and qacc at states
    of a trajectory (feet sliding and sticking, limits hit), where MuJoCo's Newton converged."""
    model, mm, data, tree, params = setup(filename)
    mm.opt.solver, mm.opt.iterations = mujoco.mjtSolver.mjSOL_NEWTON, 100  # the humanoids' files ask for PGS
    weights = invweight0(tree, params)
    slots, checked = tree.contact_slots, 0
    for q, v, u in trajectory_states(mm, data, 300, seed=3, every=10 if "humanoid" in filename else 3):
        forward(mm, data, q, v, u)
        qpos, qvel, ctrl = t64(q, v, u)
        kin = forward_kinematics(tree, qpos)
        contacts = collide(slots, kin)
        rows = constraint_rows(tree, slots, kin, contacts, qpos, qvel, params, weights.dof, weights.body)
        mass, _ = mass_matrix_and_bias(tree, kin, qvel, params)
        solution = solve(mass, torch.as_tensor(data.qacc_smooth).unsqueeze(0), rows, mm.opt.iterations)
        theirs, ours = _mujoco_rows(mm, data), _our_rows(model, tree, slots, contacts, rows, solution.force)
        assert set(ours) == set(theirs)
        for key, index in ours.items():
            jac, pos, reg, aref, force = theirs[key]
            np.testing.assert_allclose(rows.jacobian[0, index].numpy(), jac, atol=1e-10)
            np.testing.assert_allclose(rows.pos[0, index].numpy(), pos, atol=1e-12)
            np.testing.assert_allclose(rows.regulariser[0, index].numpy(), reg, rtol=1e-9)
            np.testing.assert_allclose(rows.aref[0, index].numpy(), aref, rtol=1e-8, atol=1e-8)
            np.testing.assert_allclose(solution.force[0, index].numpy(), force, rtol=1e-6, atol=1e-6)
        constraint = (rows.jacobian.transpose(-1, -2) @ solution.force.unsqueeze(-1)).squeeze(-1)
        np.testing.assert_allclose(constraint[0].numpy(), data.qfrc_constraint, rtol=1e-6, atol=1e-6)
        qacc = accelerations(tree, qpos, qvel, ctrl, params, invweight0=weights)
        np.testing.assert_allclose(qacc[0].numpy(), data.qacc, rtol=1e-6, atol=1e-6)
        checked += len(ours)
    assert checked > 50


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", PLANAR)
def test_step_matches_mj_step(filename):
    """One physics step from MuJoCo's own state along a 1000-step random-action trajectory lands on
    mj_step's next state: 1e-6 in qpos and 1e-5 in qvel (measured: 1e-8 or better). The 1000 start states
    are stepped here as one batch."""
    model, mm, data, tree, params = setup(filename)
    rng = np.random.default_rng(4)
    mujoco.mj_resetData(mm, data)
    data.qpos[:] += rng.uniform(-0.1, 0.1, mm.nq)
    starts, ends, touching = [], [], 0
    for _ in range(1000):
        data.ctrl[:] = rng.uniform(-1.0, 1.0, mm.nu)
        starts.append((data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()))
        mujoco.mj_step(mm, data)
        touching += data.ncon > 0
        ends.append((data.qpos.copy(), data.qvel.copy()))
    qpos, qvel, ctrl = (torch.as_tensor(np.stack([s[i] for s in starts])) for i in range(3))
    batch = {k: v.expand(len(starts), *v.shape[1:]) for k, v in params.items()}
    result = step(tree, qpos, qvel, ctrl, batch, mm.opt.timestep, model.integrator, invweight0(tree, batch))
    worst_q = np.abs(result.qpos.numpy() - np.stack([e[0] for e in ends])).max()
    worst_v = np.abs(result.qvel.numpy() - np.stack([e[1] for e in ends])).max()
    assert touching > 300
    assert worst_q < 1e-6 and worst_v < 1e-5, (worst_q, worst_v)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", ["ant.xml", "humanoid.xml"])
def test_free_body_rk4_step_through_contact_matches_mj_step(filename):
    """The Ant's and the humanoid's RK4 step (a free joint: MuJoCo 4's rotation correction) equals
    ``mj_step``'s through contact, one step from each of 200 states of a trajectory: the Ant
    (Newton, its file's solver) to 1e-12 in qpos and 1e-10 in qvel; the humanoid, to 1e-9 and 1e-7, with its file's
    50 PGS iterations swapped for a converged Newton solve (the same minimiser), as the
    residual of MuJoCo's unconverged PGS is not reproduced."""
    model, mm, data, tree, params = setup(filename)
    mm.opt.solver, mm.opt.iterations = mujoco.mjtSolver.mjSOL_NEWTON, 100
    starts = trajectory_states(mm, data, 400, seed=5, every=2)
    ends = []
    for q, v, u in starts:
        data.qpos[:], data.qvel[:], data.ctrl[:], data.qacc_warmstart[:] = q, v, u, 0.0
        mujoco.mj_step(mm, data)
        ends.append((data.qpos.copy(), data.qvel.copy()))
    qpos, qvel, ctrl = (torch.as_tensor(np.stack([s[i] for s in starts])) for i in range(3))
    batch = {k: v.expand(len(starts), *v.shape[1:]) for k, v in params.items()}
    result = step(tree, qpos, qvel, ctrl, batch, mm.opt.timestep, "rk4", invweight0(tree, batch))
    qpos_tol, qvel_tol = (1e-12, 1e-10) if filename == "ant.xml" else (1e-9, 1e-7)
    np.testing.assert_allclose(result.qpos.numpy(), np.stack([e[0] for e in ends]), atol=qpos_tol)
    np.testing.assert_allclose(result.qvel.numpy(), np.stack([e[1] for e in ends]), atol=qvel_tol)
    assert collide(tree.contact_slots, forward_kinematics(tree, qpos)).active.any(-1).sum() > 10  # through contact


@pytest.mark.filterwarnings("ignore")
def test_deep_penetration_matches_mjdata():
    """HalfCheetah pressed 5-15 cm into the floor, feet moving: qacc as MuJoCo's."""
    model, mm, data, tree, params = setup("half_cheetah.xml")
    rng = np.random.default_rng(6)
    for depth in (0.05, 0.1, 0.15):
        q = model.qpos0 + rng.normal(0.0, 0.2, model.nq)
        q[1] = -depth
        v = rng.normal(0.0, 2.0, model.nv)
        u = rng.uniform(-1, 1, model.nu)
        forward(mm, data, q, v, u)
        assert data.ncon >= 1
        ours = accelerations(tree, *t64(q, v, u), params)
        np.testing.assert_allclose(ours[0].numpy(), data.qacc, rtol=1e-7, atol=1e-6)


@pytest.mark.filterwarnings("ignore")
def test_ant_cfrc_ext_matches_mujoco():
    """The Ant env's ``cfrc_ext`` (MuJoCo's contact wrenches) at trajectory states with contact."""
    model, mm, data, tree, params = setup("ant.xml")
    from torchrl_diffenvs.articulated.com import root_subtree_com
    checked = 0
    for q, v, u in trajectory_states(mm, data, 300, seed=7, every=5):
        forward(mm, data, q, v, u)
        if data.ncon == 0:
            continue
        mujoco.mj_rnePostConstraint(mm, data)
        qpos, qvel, ctrl = t64(q, v, u)
        centre = root_subtree_com(tree, forward_kinematics(tree, qpos), params)[:, 1]
        ours = body_contact_wrenches(tree, qpos, qvel, ctrl, params, about=centre)
        np.testing.assert_allclose(ours[0].numpy(), data.cfrc_ext, rtol=1e-6, atol=1e-6)
        checked += 1
    assert checked > 5


# ------------------------------------------------------------------ gradients through contact
def _cheetah_on_the_floor():
    env = make_env("HalfCheetah-v5", num_envs=1, dtype=torch.float64)
    assert env.contact == "mujoco" and env.integrator == "euler"
    td = env.reset()
    # run it into contact with fixed actions
    for _ in range(20):
        td = env.step(td.set("action", torch.full((1, 6), 0.5, dtype=torch.float64)))["next"]
    return env, td["state"]


@pytest.mark.filterwarnings("ignore")
def test_one_step_gradcheck_with_contacts_active():
    env, state = _cheetah_on_the_floor()
    tree, params = env.tree, {k: v for k, v in env.params.items()}
    qpos, qvel = state["qpos"].detach(), state["qvel"].detach()
    weights = invweight0(tree, params)
    kin = forward_kinematics(tree, qpos)
    assert collide(tree.contact_slots, kin).active.any()
    ctrl = torch.full((1, 6), 0.3, dtype=torch.float64, requires_grad=True)
    qp, qv = qpos.clone().requires_grad_(True), qvel.clone().requires_grad_(True)

    def one_step(ctrl, qpos, qvel):
        result = step(tree, qpos, qvel, ctrl, params, tree.model.timestep, "euler", weights)
        return result.qpos, result.qvel

    assert torch.autograd.gradcheck(one_step, (ctrl, qp, qv), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", ["half_cheetah.xml", "hopper.xml"])
def test_per_env_contact_solref_steps_as_mujoco_with_those_geom_solrefs(filename):
    """``contact_solref`` per env: env 0 keeps the model's, env 1 has every pair at (0.05, 0.7)
    (softer, under-damped), env 2 at (0.001, 1): a time constant under two timesteps, which
    MuJoCo's refsafe raises to two. Each steps as mj_step on a MuJoCo model whose geoms all carry
    that solref (equal geoms' values mix to the same), from states along a trajectory in contact."""
    model, mm, data, tree, params = setup(filename)
    default = tree.contact_slots.pair_solref.to(torch.float64)
    solrefs = [None, (0.05, 0.7), (0.001, 1.0)]
    per_env = torch.stack([default if r is None else torch.tensor(r, dtype=torch.float64).expand_as(default)
                           for r in solrefs])
    states = trajectory_states(mm, data, 300, seed=2, every=30)
    qpos, qvel, ctrl = (torch.as_tensor(np.stack([s[i] for s in states])).repeat_interleave(3, 0) for i in range(3))
    n = qpos.shape[0]
    batch = {k: v.expand(n, *v.shape[1:]) for k, v in params.items()}
    batch["contact_solref"] = per_env.repeat(len(states), 1, 1)
    result = step(tree, qpos, qvel, ctrl, batch, mm.opt.timestep, model.integrator, invweight0(tree, batch))
    touching = 0
    for i in range(n):
        solref = solrefs[i % 3]
        mm_i = mujoco.MjModel.from_xml_path(str(gymnasium_asset(filename)))
        if solref is not None:
            mm_i.geom_solref[:] = solref
        d = mujoco.MjData(mm_i)
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i].numpy(), qvel[i].numpy(), ctrl[i].numpy()
        mujoco.mj_step(mm_i, d)
        touching += d.ncon > 0
        np.testing.assert_allclose(result.qvel[i].numpy(), d.qvel, rtol=0, atol=1e-5, err_msg=f"env {i}, solref {solref}")
        np.testing.assert_allclose(result.qpos[i].numpy(), d.qpos, rtol=0, atol=1e-6, err_msg=f"env {i}, solref {solref}")
    assert touching > n / 2
    assert not torch.allclose(result.qvel[0::3], result.qvel[1::3], atol=1e-3)  # the solref matters here


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("wrt", ["actions", "start", "friction", "mass", "solref"])
def test_multi_step_return_gradient_matches_finite_differences_through_contact(wrt):
    """d(return of 5 env steps in contact)/d(actions, start qvel, friction, a body mass, the pairs'
    solref) against central differences in float64."""
    env, state = _cheetah_on_the_floor()
    base = {k: v.detach().clone() for k, v in env.params.items()}
    actions0 = torch.linspace(-0.8, 0.8, 5 * 6, dtype=torch.float64).reshape(5, 1, 6)

    def rollout(x):
        params, actions, qvel = dict(base), actions0, state["qvel"].detach()
        if wrt == "actions":
            actions = x.reshape(5, 1, 6)
        elif wrt == "start":
            qvel = x.reshape(1, -1)
        elif wrt == "friction":
            params["contact_friction"] = x.reshape(1, -1)
        elif wrt == "solref":
            params["contact_solref"] = x.reshape(1, -1, 2)
        else:
            params["body_mass"] = torch.cat([base["body_mass"][:, :4], x.reshape(1, 1), base["body_mass"][:, 5:]], 1)
        s = {**{k: v.detach() for k, v in state.items()}, "qvel": qvel}
        total = 0.0
        for a in actions:
            s, reward, _ = env.transition(s, a, params)
            total = total + reward.sum()
        return total

    x0 = {"actions": actions0.flatten(), "start": state["qvel"].detach().flatten(),
          "friction": base["contact_friction"].flatten(), "mass": base["body_mass"][0, 4:5],
          # away from refsafe's kink: HalfCheetah's time constant 0.02 is exactly two of its timesteps
          "solref": (base["contact_solref"] * torch.tensor([1.5, 0.9], dtype=torch.float64)).flatten()}[wrt].clone()
    x = x0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(rollout(x), x)
    eps = 1e-6
    fd = torch.stack([(rollout(x0 + eps * e) - rollout(x0 - eps * e)) / (2 * eps) for e in torch.eye(x0.numel(), dtype=x0.dtype)])
    assert grad.abs().max() > 1e-3
    torch.testing.assert_close(grad, fd, rtol=1e-4, atol=1e-5 * fd.abs().max().item())


@pytest.mark.filterwarnings("ignore")
def test_contact_option_defaults_and_errors():
    """MuJoCo's contact and the file's integrator by default; the smooth model on request, with its
    own integrators and params; bad values name what is valid."""
    hopper = make_env("Hopper-v5")
    assert hopper.contact == "mujoco" and hopper.integrator == "rk4" and "contact_stiffness" not in hopper.params.keys()
    smooth = make_env("Hopper-v5", contact="smooth")
    assert smooth.integrator == "euler" and "contact_stiffness" in smooth.params.keys()
    assert make_env("Ant-v5", contact="smooth").integrator == "implicit"
    assert make_env("Pusher-v5").contact == "mujoco"
    with pytest.raises(ValueError, match=r"unknown contact model 'soft'; valid: 'mujoco', 'smooth'"):
        make_env("Hopper-v5", contact="soft")


def _two_bodies(tmp_path, geom1: str, geom2: str, dtype=torch.float64):
    """A tree of two free bodies, one geom each (MJCF attributes), 2 mm margin each (the file is
    ``tmp_path / "pair.xml"``)."""
    path = tmp_path / "pair.xml"
    path.write_text(f"""<mujoco><option gravity="0 0 0"/><worldbody>
        <body name="a"><freejoint/><geom name="a" {geom1} margin="0.002"/></body>
        <body name="b"><freejoint/><geom name="b" {geom2} margin="0.002"/></body></worldbody></mujoco>""")
    return RigidBodyTree.from_model(load_mjcf(str(path)), dtype=dtype)


@pytest.mark.filterwarnings("ignore")
def test_a_pair_without_a_primitive_is_refused_with_what_is_available(tmp_path):
    tree = _two_bodies(tmp_path, 'type="cylinder" size="0.03 0.05"', 'type="cylinder" size="0.05 0.05"')
    assert tree.contact_model == "smooth"  # chosen when MuJoCo's contact cannot cover the model
    with pytest.raises(ValueError, match=r"'a' \(cylinder\) and 'b' \(cylinder\).*collides only.*capsule-cylinder"
                                         r".*contact='smooth'"):
        tree.use_contact_model("mujoco")
    # two ellipsoids: MuJoCo's contact here has no ellipsoid primitive, the smooth model no shape for one
    with pytest.raises(ValueError, match=r"'a' of type ellipsoid can touch another body's geom.*no primitive for "
                                         r"'a'-'b': neither contact model covers the model"):
        _two_bodies(tmp_path, 'type="ellipsoid" size="0.03 0.04 0.05"', 'type="ellipsoid" size="0.05 0.04 0.03"')


SPHERE = 'type="sphere" size="0.03"'

BOX_ON_A_PLANE = """<mujoco><option timestep="0.005"/><worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" margin="0.003"/>
    <body name="box" pos="0 0 0.2"><freejoint/><geom name="box" type="box" size="0.1 0.06 0.04" margin="0.002"/></body>
    </worldbody></mujoco>"""


@pytest.mark.filterwarnings("ignore")
def test_plane_box_contacts_and_steps_match_mujoco(tmp_path):
    """MuJoCo's ``mjc_PlaneBox`` at random poses (tilted, resting, deep): the same contacts in the
    same order (count, distance, position, frame); and one step of a box dropped on the floor,
    tumbling and sliding, from MuJoCo's states against ``mj_step``."""
    path = tmp_path / "box.xml"
    path.write_text(BOX_ON_A_PLANE)
    model = load_mjcf(str(path))
    tree = RigidBodyTree.from_model(model)
    assert tree.contact_model == "mujoco"
    mm = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(0)
    poses = np.zeros((400, 7))
    poses[:, 2] = rng.uniform(-0.05, 0.15, 400)
    poses[:, 3:] = rng.normal(size=(400, 4))
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    poses[:50, 3:] = [1.0, 0.0, 0.0, 0.0]  # flat: four corners at one height
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses)))
    counts = set()
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        ours = np.flatnonzero(c.active[k].numpy())
        assert len(ours) == data.ncon, k
        counts.add(data.ncon)
        for i, j in zip(ours, range(data.ncon)):  # in MuJoCo's order
            assert c.dist[k, i].item() == pytest.approx(data.contact.dist[j], abs=1e-12)
            np.testing.assert_allclose(c.pos[k, i].numpy(), data.contact.pos[j], atol=1e-12)
            np.testing.assert_allclose(c.frame[k, i].numpy().ravel(), data.contact.frame[j], atol=1e-12)
    assert {0, 1, 2, 4} <= counts
    mujoco.mj_resetData(mm, data)
    data.qvel[:] = [0.5, -0.3, 0.0, 2.0, -1.0, 3.0]  # tumbling onto the floor
    contacts = []
    gaps = gaps_to_mj_step(tree, mm, data, 150, lambda d: contacts.append(d.ncon))
    assert sum(n > 0 for n in contacts) > 60 and gaps.max() < 1e-9, (contacts, gaps.max())


@pytest.mark.filterwarnings("ignore")
def test_plane_box_gradcheck(tmp_path):
    path = tmp_path / "box.xml"
    path.write_text(BOX_ON_A_PLANE)
    tree = RigidBodyTree.from_model(load_mjcf(str(path)))
    turn = torch.tensor([[0.97, 0.1, 0.2, 0.05]], dtype=torch.float64)

    def contact(height, quat):
        qpos = torch.cat([torch.zeros(1, 2, dtype=torch.float64), height, quat / quat.norm(dim=-1, keepdim=True)], -1)
        c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
        return c.dist, c.pos

    height = torch.tensor([[0.05]], dtype=torch.float64, requires_grad=True)
    qpos = torch.cat([torch.zeros(1, 2, dtype=torch.float64), height.detach(), turn / turn.norm()], -1)
    assert collide(tree.contact_slots, forward_kinematics(tree, qpos)).active.sum() >= 1
    torch.autograd.gradcheck(contact, (height, turn.clone().requires_grad_(True)))


BOX = 'type="box" size="0.05 0.08 0.11"'  # three different half-sizes: a swapped axis shows


def _single_contacts_match(tree, mm, data, poses, branch_of) -> set[str]:
    """A sphere (body 1) against a geom of body 2 at free-joint ``poses [P, 14]``: our one contact
    slot as ``mj_collision``'s contact (there or not; distance, position, frame to 1e-12); the
    branches (``branch_of`` the sphere's centre in body 2's frame) of the poses in contact."""
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses)))
    branches = set()
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        assert bool(c.active[k, 0]) == (data.ncon == 1), k
        if data.ncon:
            assert c.dist[k, 0].item() == pytest.approx(data.contact.dist[0], abs=1e-12)
            np.testing.assert_allclose(c.pos[k, 0].numpy(), data.contact.pos[0], atol=1e-12)
            np.testing.assert_allclose(c.frame[k, 0].numpy().ravel(), data.contact.frame[0], atol=1e-12)
            branches.add(branch_of(data.xmat[2].reshape(3, 3).T @ (pose[:3] - pose[7:10])))
    return branches


def _sphere_box_branch(centre) -> str:
    """MuJoCo's branch for a sphere centred at ``centre`` (the box's frame, BOX): outside, the box's
    nearest point is on a face, an edge or a corner; inside, it leaves through the nearest face."""
    beyond = int((np.abs(centre) > [0.05, 0.08, 0.11]).sum())
    return ["inside", "face", "edge", "corner"][beyond]


@pytest.mark.filterwarnings("ignore")
def test_sphere_box_matches_mj_collision(tmp_path):
    """MuJoCo's ``mjraw_SphereBox`` at random poses (the sphere near a face, an edge, a corner, and
    centred inside the box, on a face's plane too): the same contacts, distance, position and frame."""
    tree = _two_bodies(tmp_path, SPHERE, BOX)
    assert tree.contact_model == "mujoco"
    mm = mujoco.MjModel.from_xml_path(str(tmp_path / "pair.xml"))
    data = mujoco.MjData(mm)
    poses = _sphere_cylinder_poses(1000, np.random.default_rng(1))
    poses[:30, 10:14] = [1.0, 0.0, 0.0, 0.0]  # an unturned box, centres inside it
    poses[:30, :3] = np.random.default_rng(2).uniform(-0.04, 0.04, (30, 3))
    poses[:10, 0], poses[:10, 1] = 0.03, -0.06  # as near +x as -y (0.02, to rounding): the order decides
    branches = _single_contacts_match(tree, mm, data, poses, _sphere_box_branch)
    assert branches == {"inside", "face", "edge", "corner"}


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("where", [[0.0, 0.1, 0.02], [0.07, 0.09, 0.0], [0.06, -0.09, 0.12], [0.01, 0.05, -0.02]])
def test_sphere_box_gradcheck(tmp_path, where):
    """The gradient of the contact w.r.t. the sphere's centre and the box's orientation, the box's
    nearest point on a face, an edge, a corner, and the centre inside (``where``: the box's frame)."""
    tree = _two_bodies(tmp_path, SPHERE, BOX)
    quat = torch.tensor([[0.96, 0.2, 0.1, 0.15]], dtype=torch.float64)
    quat = quat / quat.norm()
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat[0].numpy())
    centre = (torch.as_tensor(rot.reshape(3, 3)) @ torch.tensor(where, dtype=torch.float64)).unsqueeze(0)
    still = torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)

    def contact(centre, turn):
        q = quat + turn
        qpos = torch.cat([centre, still, q / q.norm(dim=-1, keepdim=True)], dim=-1)
        c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
        return c.dist, c.pos, c.frame[:, :, 0]

    assert collide(tree.contact_slots, forward_kinematics(tree, torch.cat([centre, still, quat], -1))).active.all()
    torch.autograd.gradcheck(contact, (centre.requires_grad_(True), torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)))


BALL_ON_A_BOX = """<mujoco><option timestep="0.005"/><worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="box" pos="0 0 0.04"><freejoint/><geom name="box" type="box" size="0.1 0.06 0.04"/></body>
    <body name="ball" pos="0.0 0.02 0.15"><freejoint/><geom name="ball" type="sphere" size="0.03"/></body>
    </worldbody></mujoco>"""


@pytest.mark.filterwarnings("ignore")
def test_a_ball_dropped_on_a_box_steps_as_mj_step(tmp_path):
    """A ball falls onto a box lying on the floor, rolls along it and off its edge: each step
    from MuJoCo's state against ``mj_step`` (sphere-box and plane-box contacts in one solve). The
    smooth model has no shape for a box between bodies and says so."""
    path = tmp_path / "ball.xml"
    path.write_text(BALL_ON_A_BOX)
    model = load_mjcf(str(path))
    tree = RigidBodyTree.from_model(model)
    assert tree.contact_model == "mujoco"
    with pytest.raises(ValueError, match=r"'box' of type box can touch another body's geom, but the smooth contact "
                                         r"model .* only for spheres, capsules and cylinders: use contact='mujoco'"):
        tree.use_contact_model("smooth")
    mm = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(mm)
    data.qvel[6:9] = [0.4, 0.0, 0.0]
    on_the_box = []
    gaps = gaps_to_mj_step(tree, mm, data, 250, lambda d: on_the_box.append(
        any({d.contact.geom[i][0], d.contact.geom[i][1]} == {1, 2} for i in range(d.ncon))))
    assert sum(on_the_box) > 20 and gaps.max() < 1e-9, (sum(on_the_box), gaps.max())


TALL_CYLINDER = 'type="cylinder" size="0.04 0.09"'  # radius and half-height differ: a swap shows


def _sphere_cylinder_poses(count: int, rng) -> np.ndarray:
    """Free-joint qpos of the two bodies: the sphere (turned at random) anywhere within reach of a
    cylinder (radius 0.04, half-height 0.09) turned at random about the origin, inside it too."""
    poses = np.zeros((count, 14))
    poses[:, :3] = rng.uniform(-0.14, 0.14, (count, 3))
    poses[:, 3:7] = rng.normal(size=(count, 4))
    poses[:, 10:14] = rng.normal(size=(count, 4))
    for q in (poses[:, 3:7], poses[:, 10:14]):
        q /= np.linalg.norm(q, axis=1, keepdims=True)
    return poses


def _sphere_cylinder_branch(centre) -> str:
    """MuJoCo's branch for a sphere centred at ``centre`` (the cylinder's frame, TALL_CYLINDER)."""
    beside, over = abs(centre[2]) < 0.09, np.hypot(*centre[:2]) < 0.04
    if beside and over:
        return "inside, out through the cap" if 0.09 - abs(centre[2]) < 0.04 - np.hypot(*centre[:2]) else "inside, out through the side"
    return "side" if beside else "cap" if over else "rim"


@pytest.mark.filterwarnings("ignore")
def test_sphere_cylinder_matches_mj_collision(tmp_path):
    """MuJoCo's ``mjc_SphereCylinder`` at random poses: beside the side, over a cap, near a rim and
    with the centre inside (out through the nearer surface), and centred on the axis: the same
    contacts, distance, position and frame."""
    tree = _two_bodies(tmp_path, SPHERE, TALL_CYLINDER)
    assert tree.contact_model == "mujoco"
    mm = mujoco.MjModel.from_xml_path(str(tmp_path / "pair.xml"))
    data = mujoco.MjData(mm)
    poses = _sphere_cylinder_poses(800, np.random.default_rng(0))
    poses[:40, 10:14] = [1.0, 0.0, 0.0, 0.0]  # an upright cylinder, the sphere on its axis
    poses[:40, :2] = 0.0
    poses[:40, 2] = np.linspace(-0.14, 0.14, 40)
    branches = _single_contacts_match(tree, mm, data, poses, _sphere_cylinder_branch)
    assert branches == {"side", "cap", "rim", "inside, out through the cap", "inside, out through the side"}


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("where,branch", [([0.0, 0.06, 0.01], "side"), ([0.01, 0.0, 0.11], "cap"),
                                          ([0.05, 0.0, 0.1], "rim"), ([0.01, 0.0, 0.07], "inside, out through the cap"),
                                          ([0.0, 0.03, 0.005], "inside, out through the side")])
def test_sphere_cylinder_gradcheck(tmp_path, where, branch):
    """The gradient of the contact w.r.t. the sphere's centre and the cylinder's orientation, in each
    of MuJoCo's branches (``where``: the centre in the cylinder's frame)."""
    tree = _two_bodies(tmp_path, SPHERE, TALL_CYLINDER)
    quat = torch.tensor([[0.96, 0.2, 0.1, 0.15]], dtype=torch.float64)
    quat = quat / quat.norm()
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat[0].numpy())
    rot = torch.as_tensor(rot.reshape(3, 3))
    assert _sphere_cylinder_branch(np.asarray(where)) == branch
    centre = (rot @ torch.tensor(where, dtype=torch.float64)).unsqueeze(0).requires_grad_(True)
    still = torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)

    def contact(centre, turn):
        q = quat + turn
        qpos = torch.cat([centre, still, q / q.norm(dim=-1, keepdim=True)], dim=-1)
        c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
        return c.dist, c.pos, c.frame[:, :, 0]

    assert collide(tree.contact_slots, forward_kinematics(tree, torch.cat([centre.detach(), still, quat], -1))).active.all()
    torch.autograd.gradcheck(contact, (centre, torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)))


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("height", [0.5, 0.11, 0.06, -0.07])
def test_sphere_centred_on_a_cylinders_axis_has_finite_gradients(tmp_path, height):
    """A sphere right above (or inside) an upright cylinder, on its axis, in contact or far away:
    the side branch's sphere-sphere has coincident centres there, not taken but evaluated."""
    tree = _two_bodies(tmp_path, SPHERE, TALL_CYLINDER)
    qpos = torch.tensor([[0.0, 0.0, height, 1, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0]], dtype=torch.float64, requires_grad=True)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    (everything,) = torch.autograd.grad(c.dist.sum() + c.pos.sum() + c.frame.sum(), qpos, retain_graph=True)
    assert torch.isfinite(everything).all()
    (grad,) = torch.autograd.grad(c.dist.sum(), qpos)
    assert grad[0, 2].item() == pytest.approx(1.0 if height > 0 else -1.0)  # the distance to the nearer cap


CAPSULE, CYLINDER = 'type="capsule" size="0.02 0.1"', 'type="cylinder" size="0.05 0.05"'


def _quaternion_from_z(direction) -> np.ndarray:
    """The unit quaternion turning the z axis onto ``direction``."""
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    axis = np.cross([0.0, 0.0, 1.0], d)
    if np.linalg.norm(axis) < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0]) if d[2] > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    angle = np.arccos(np.clip(d[2], -1.0, 1.0))
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)])


def _capsule_along(tmp_path, centre, direction):
    """``(tree, qpos)``: a capsule (radius 0.02, half-length 0.1) centred at ``centre`` with its
    axis along ``direction``, and an upright cylinder (radius 0.05, half-height 0.05) at the origin."""
    tree = _two_bodies(tmp_path, CAPSULE, CYLINDER)
    qpos = np.zeros(14)
    qpos[:3], qpos[3:7], qpos[10] = centre, _quaternion_from_z(direction), 1.0
    return tree, torch.as_tensor(qpos).unsqueeze(0)


def _capsule_beside_cylinder(tmp_path, centre, angle=0.0):
    """`_capsule_along` with the capsule's axis along y turned by ``angle`` about x."""
    return _capsule_along(tmp_path, centre, [0.0, np.cos(angle), np.sin(angle)])


@pytest.mark.filterwarnings("ignore")
def test_capsule_cylinder_contact_hand_computed(tmp_path):
    """Capsule against cylinder where the answer is known by hand: beside the side (the normal is
    -x, the distance the gap between the surfaces) and across the rim (the normal along the
    diagonal to the rim point), in float64."""
    tree, qpos = _capsule_beside_cylinder(tmp_path, [0.072, 0.0, 0.01])
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    assert c.dist[0, 0].item() == pytest.approx(0.072 - 0.05 - 0.02, abs=1e-14) and c.active[0, 0]
    torch.testing.assert_close(c.frame[0, 0, 0], torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-14, rtol=0)
    torch.testing.assert_close(c.pos[0, 0], torch.tensor([(0.052 + 0.05) / 2, 0.0, 0.01], dtype=torch.float64),
                               atol=1e-14, rtol=0)
    tree, qpos = _capsule_beside_cylinder(tmp_path, [0.066, 0.0, 0.066])  # over the rim point (0.05, 0, 0.05)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    gap = 0.016 * np.sqrt(2)
    assert c.dist[0, 0].item() == pytest.approx(gap - 0.02, abs=1e-14) and c.active[0, 0]
    torch.testing.assert_close(c.frame[0, 0, 0], torch.tensor([-1.0, 0.0, -1.0], dtype=torch.float64) / np.sqrt(2),
                               atol=1e-12, rtol=0)
    middle = 0.05 + (gap - 0.02) / 2 / np.sqrt(2)
    torch.testing.assert_close(c.pos[0, 0], torch.tensor([middle, 0.0, middle], dtype=torch.float64), atol=1e-12, rtol=0)
    # upright, its lower end 1 cm inside the cap: the minimal translation is 3 cm straight up
    tree, qpos = _capsule_beside_cylinder(tmp_path, [0.0, 0.0, 0.14], angle=np.pi / 2)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    assert c.dist[0, 0].item() == pytest.approx(-0.03, abs=1e-14)
    torch.testing.assert_close(c.frame[0, 0, 0], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), atol=1e-14, rtol=0)
    torch.testing.assert_close(c.pos[0, 0], torch.tensor([0.0, 0.0, 0.035], dtype=torch.float64), atol=1e-14, rtol=0)


@pytest.mark.filterwarnings("ignore")
def test_capsule_cylinder_contact_gradcheck(tmp_path):
    """The distance, position and normal of a tilted capsule's contact on the cylinder's side and
    near its rim (the minimiser along the capsule's axis by its implicit derivative), and with
    its axis inside the cylinder (an end against the rim, an end under the cap), against finite
    differences in float64."""
    for centre, angle in (([0.069, 0.01, 0.02], 0.4), ([0.06, 0.0, 0.071], 0.3), ([0.06, 0.0, 0.1], 1.2),
                          ([0.03, 0.0, 0.06], 0.2)):
        tree, qpos = _capsule_beside_cylinder(tmp_path, centre, angle)

        def contact(position):
            q = torch.cat([position, qpos[:, 3:]], dim=-1)
            c = collide(tree.contact_slots, forward_kinematics(tree, q))
            return c.dist[0, 0], c.pos[0, 0], c.frame[0, 0, 0]

        assert collide(tree.contact_slots, forward_kinematics(tree, qpos)).active[:, 0].all()
        torch.autograd.gradcheck(contact, (qpos[:, :3].clone().requires_grad_(True),))


@pytest.mark.filterwarnings("ignore")
def test_capsule_cylinder_gradient_where_the_capsule_edge_meets_the_rim(tmp_path):
    """Deep in the cylinder with the capsule's side against a rim (the minimiser found on the
    great circle across the capsule's axis): distance, position and normal against finite
    differences in the capsule's position and its direction (float64)."""
    centre, direction = np.array([0.045, 0.003, 0.046]), np.array([0.068, 0.01, -0.072])
    tree, qpos = _capsule_along(tmp_path, centre, direction)
    c = collide(tree.contact_slots, forward_kinematics(tree, qpos))
    assert c.active[:, 0].all() and c.dist[0, 0] < -0.02  # the axis inside
    u = c.frame[0, 0, 0]
    assert abs(float(u @ torch.as_tensor(direction / np.linalg.norm(direction)))) < 1e-9  # across the axis
    assert 0.1 < abs(float(u[2])) < 0.99  # neither a cap nor the side

    def contact(position, turn):
        quaternion = qpos[:, 3:7] + turn
        q = torch.cat([position, quaternion / quaternion.norm(dim=-1, keepdim=True), qpos[:, 7:]], dim=-1)
        cc = collide(tree.contact_slots, forward_kinematics(tree, q))
        return cc.dist[0, 0], cc.pos[0, 0], cc.frame[0, 0, 0]

    torch.autograd.gradcheck(contact, (qpos[:, :3].clone().requires_grad_(True),
                                       torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_capsule_cylinder_gradients_stay_finite_for_a_capsule_along_the_axis(dtype):
    """A capsule standing on the cap, its axis along the cylinder's to 1e-3 ... 1e-30 (its shadow
    on the cap shrinking to a point): every output's gradient is finite in both slots (a NaN in one
    env's contact would poison a batch's shared parameters)."""
    from torchrl_diffenvs.articulated.capsule_cylinder import capsule_cylinder

    for exponent in (3, 8, 13, 16, 20, 30):
        start = torch.tensor([[[0.01, 0.0, 0.119]]], dtype=dtype, requires_grad=True)
        axis = torch.tensor([[[0.05 * 10.0 ** -exponent, 0.05 * 10.0 ** -exponent, 0.05]]], dtype=dtype,
                            requires_grad=True)
        dist, pos, normal, _ = capsule_cylinder(start, axis, torch.tensor([0.02], dtype=dtype),
                                                torch.zeros(1, 1, 3, dtype=dtype), torch.eye(3, dtype=dtype).view(1, 1, 3, 3),
                                                torch.tensor([[0.05, 0.05, 0.0]], dtype=dtype),
                                                torch.tensor([0.004], dtype=dtype))
        assert dist[0, 0, 0] < 0.004  # touching the cap
        gradients = torch.autograd.grad(dist.sum() + pos.sum() + normal.sum(), (start, axis))
        assert all(torch.isfinite(g).all() for g in gradients), exponent


def _capsule_cylinder_gaps(c, data, k):
    """Our contacts of pose ``k`` (the pair's two slots) against mjData's, matched as sets (MuJoCo's
    order of two clipped points is a floating-point tie): ``[(|ddist|, |dnormal|, |dpos|, dist)]``,
    or ``None`` where the counts differ."""
    ours = [(c.dist[k, j].item(), c.frame[k, j, 0].double().numpy(), c.pos[k, j].double().numpy())
            for j in np.flatnonzero(c.active[k].numpy())]
    theirs = [(data.contact.dist[j], data.contact.frame[j][:3], data.contact.pos[j]) for j in range(data.ncon)]
    if len(ours) != len(theirs):
        return None
    best = None
    for order in ([0, 1], [1, 0]) if len(ours) == 2 else ([0],)[:len(ours)]:
        gaps = [(abs(ours[i][0] - theirs[j][0]), np.abs(ours[i][1] - theirs[j][1]).max(),
                 np.abs(ours[i][2] - theirs[j][2]).max(), theirs[j][0]) for i, j in enumerate(order)]
        if best is None or max(g[2] for g in gaps) < max(g[2] for g in best):
            best = gaps
    return best or []


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_capsule_cylinder_matches_mujocos_converged_convex_collision(tmp_path, dtype):
    """At random poses, outside and deep inside: MuJoCo's own capsule-cylinder contacts with its
    convex collision run to 1e-11, against ours: the same contacts (one, or two where the capsule
    lies along a cap), distance, normal and position (measured, float64: 2e-9, 2e-5, 5e-7; the
    distance's worst where a sunk capsule's two contacts follow EPA's direction).
    Float32, the envs' default: to its rounding."""
    tree = _two_bodies(tmp_path, CAPSULE, CYLINDER, dtype)
    converged = 'gravity="0 0 0" ccd_tolerance="1e-11" ccd_iterations="1000"'
    mm = mujoco.MjModel.from_xml_string((tmp_path / "pair.xml").read_text().replace('gravity="0 0 0"', converged))
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(0)
    poses = np.zeros((800, 14))
    poses[:, :3] = rng.uniform(-0.09, 0.09, (800, 3))
    poses[:, 3:7] = rng.normal(size=(800, 4))
    poses[:, 3:7] /= np.linalg.norm(poses[:, 3:7], axis=1, keepdims=True)
    poses[:, 10] = 1.0
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses, dtype=dtype)))
    errors = []
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        gaps = _capsule_cylinder_gaps(c, data, k)
        assert gaps is not None, (k, data.ncon)
        errors += gaps
    errors = np.array(errors)
    compared, deep = len(errors), int((errors[:, 3] < -0.02).sum())
    worst = errors[:, :3].max(0)
    if dtype == torch.float64:
        assert worst[0] < 1e-8 and worst[1] < 1e-4 and worst[2] < 1e-5, worst
    else:  # a shallow minimum's normal moves with float32's rounding (measured: 4 of 566 above 1e-3)
        assert worst[0] < 5e-6 and worst[2] < 1e-3 and worst[1] < 5e-2, worst
        assert np.quantile(errors[:, 1], 0.99) < 2e-3
    assert compared > 400 and deep > 150


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_capsule_along_a_cylinders_cap_gets_mujocos_two_contacts(tmp_path, dtype):
    """MuJoCo 4's multi-contact: a capsule within 5.09 degrees of a cap's plane (MuJoCo's
    mjEDGE_TOL 0.0888), above it, sunk into it and across its rim, on either cap: its edge clipped
    against the cap's 16-gon, each contact with the cap's normal and its own depth, as mjData's
    (count exact; values to MuJoCo's convex-collision tolerance, run to 1e-11 here). Tilts on
    either side of the threshold switch between the two contacts and the single one. Float32, the
    envs' default: the same counts, values to its rounding."""
    tree = _two_bodies(tmp_path, CAPSULE, CYLINDER, dtype)
    converged = 'gravity="0 0 0" ccd_tolerance="1e-11" ccd_iterations="1000"'
    mm = mujoco.MjModel.from_xml_string((tmp_path / "pair.xml").read_text().replace('gravity="0 0 0"', converged))
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(1)
    n = 400
    side = rng.choice([1.0, -1.0], n)
    tilt = np.where(np.arange(n) < 40, np.arcsin(0.0888) + rng.choice([-1e-4, 1e-4], n),  # either side of it
                    rng.uniform(-0.1, 0.1, n))
    yaw = rng.uniform(0, 2 * np.pi, n)
    axis = np.stack([np.cos(yaw) * np.cos(tilt), np.sin(yaw) * np.cos(tilt), np.sin(tilt)], 1)
    reach = 0.07 * np.sqrt(rng.uniform(0, 1, n))  # the centre over the cap, or beyond its rim (0.05)
    turn = rng.uniform(0, 2 * np.pi, n)
    height = 0.05 + 0.02 + rng.uniform(-0.03, 0.004, n)  # cap + radius: touching within the margin, or sunk
    centre = np.stack([reach * np.cos(turn), reach * np.sin(turn), side * height], 1)
    poses = np.zeros((n, 14))
    poses[:, :3], poses[:, 10] = centre, 1.0
    # the capsule's z axis along `axis`: the rotation taking z to it
    half = np.arccos(np.clip(axis[:, 2], -1, 1)) / 2
    pivot = np.cross(np.array([0.0, 0.0, 1.0]), axis)
    pivot /= np.linalg.norm(pivot, axis=1, keepdims=True)
    poses[:, 3:7] = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * pivot], 1)
    c = collide(tree.contact_slots, forward_kinematics(tree, torch.as_tensor(poses, dtype=dtype)))
    errors, counts = [], {1: 0, 2: 0}
    for k, pose in enumerate(poses):
        data.qpos[:] = pose
        mujoco.mj_forward(mm, data)
        gaps = _capsule_cylinder_gaps(c, data, k)
        assert gaps is not None, (k, data.ncon, int(c.active[k].sum()))
        if data.ncon:
            counts[data.ncon] += 1
        errors += gaps
    errors = np.array(errors)
    assert counts[2] > 150 and counts[1] > 20  # both paths taken
    within = errors[:, 3] > -0.02 - 0.002  # the axis outside the inflated cylinder
    worst = errors[within, :3].max(0)
    # distance, normal, position; float64 measured 2e-8, 1.2e-5 (a sunk single contact: EPA's
    # direction, as in the test above), 2e-7; float32 5e-6, 2e-3, 6e-5
    assert (worst < ([1e-7, 1e-4, 1e-6] if dtype == torch.float64 else [2e-5, 5e-2, 1e-3])).all(), worst
    # the axis inside the cylinder: MuJoCo's EPA direction against the exact one
    assert (~within).sum() > 20 and errors[~within, :3].max() < (1e-4 if dtype == torch.float64 else 1e-3)
    if dtype == torch.float32:
        return

    # both contacts' distance and position carry the gradient (float64 against finite differences):
    # a capsule tilted 2 degrees, one end over the cap and the other beyond its rim
    lying = torch.tensor([[0.03, 0.01, 0.0695, np.cos(0.5 * (np.pi / 2 - 0.035)), 0.0,
                           np.sin(0.5 * (np.pi / 2 - 0.035)), 0.0, 0, 0, 0, 1.0, 0, 0, 0]], dtype=torch.float64)

    def both(position):
        q = torch.cat([position, lying[:, 3:]], dim=-1)
        cc = collide(tree.contact_slots, forward_kinematics(tree, q))
        return cc.dist[0], cc.pos[0]

    cc = collide(tree.contact_slots, forward_kinematics(tree, lying))
    assert cc.active.all() and (cc.dist[0, 0] - cc.dist[0, 1]).abs() > 1e-4  # two contacts, each its own depth
    torch.autograd.gradcheck(both, (lying[:, :3].clone().requires_grad_(True),))


@pytest.mark.filterwarnings("ignore")
def test_pusher_contacts_and_step_match_mujoco_while_pushing():
    """The Pusher's wrist pushing the object (MuJoCo's own trajectories): the contacts per geom
    pair as mj_collision's (table contacts exactly; the wrist's on the object to the tolerance of
    MuJoCo's EPA, which stops at the file's ccd_tolerance, two where a wrist capsule lies along the
    object's cap), and one physics step from MuJoCo's state as mj_step's: exact without the wrist
    on the object, within EPA's residual with it (measured: 2e-5 in qvel; the smooth model lands
    ~6 m/s away)."""
    model, mm, data, tree, params = setup("pusher_v5.xml")
    starts, ends, depth, multi = CONTACT_MODEL.pushing_trajectory(mm, episodes=6, steps=200, seed=0)
    touching = np.flatnonzero(np.isfinite(depth))
    free = np.flatnonzero(~np.isfinite(depth))
    assert len(touching) > 60 and (depth[touching] < -0.02).sum() > 10 and len(free) > 300 and multi.sum() > 10
    slots, compared = tree.contact_slots, 0
    for i in touching:
        q, v, u = starts[i]
        forward(mm, data, q, v, u)
        c = collide(slots, forward_kinematics(tree, torch.as_tensor(q).unsqueeze(0)))
        ours, theirs = {}, {}
        for k in np.flatnonzero(c.active[0].numpy()):
            ours.setdefault(tuple(slots.geom[k].tolist()), []).append(k)
        for j in range(data.ncon):
            theirs.setdefault(tuple(map(int, data.contact.geom[j])), []).append(j)
        assert {g: len(x) for g, x in ours.items()} == {g: len(x) for g, x in theirs.items()}
        for geoms, ks in ours.items():
            js = theirs[geoms]
            if mm.geom_type[geoms[0]] == mujoco.mjtGeom.mjGEOM_PLANE:
                for k, j in zip(ks, js):
                    assert c.dist[0, k].item() == pytest.approx(data.contact.dist[j], abs=1e-12)
                    np.testing.assert_allclose(c.pos[0, k].numpy(), data.contact.pos[j], atol=1e-12)
                    np.testing.assert_allclose(c.frame[0, k].numpy().ravel(), data.contact.frame[j], atol=1e-12)
                continue
            # two contacts of one pair: MuJoCo's order of two clipped points is a floating-point tie
            pairs = min(([list(zip(ks, js)), list(zip(ks, js[::-1]))] if len(ks) == 2 else [list(zip(ks, js))]),
                        key=lambda m: max(np.abs(c.pos[0, k].numpy() - data.contact.pos[j]).max() for k, j in m))
            for k, j in pairs:
                deep = data.contact.dist[j] < -0.02
                assert c.dist[0, k].item() == pytest.approx(data.contact.dist[j], abs=1e-5 if deep else 2e-6)
                np.testing.assert_allclose(c.frame[0, k, 0].numpy(), data.contact.frame[j][:3], atol=1e-2)
                # EPA stops at the file's ccd_tolerance: farther from the exact answer when deep
                np.testing.assert_allclose(c.pos[0, k].numpy(), data.contact.pos[j], atol=5e-4 if deep else 2e-5)
                compared += 1
    assert compared > 80

    def qvel_gaps(index):
        qpos, qvel, ctrl = (torch.as_tensor(np.stack([starts[i][k] for i in index])) for k in range(3))
        batch = {k: v.expand(len(index), *v.shape[1:]) for k, v in params.items()}
        result = step(tree, qpos, qvel, ctrl, batch, mm.opt.timestep, model.integrator, invweight0(tree, batch))
        return np.abs(result.qvel.numpy() - np.stack([ends[i][1] for i in index])).max(-1)

    assert qvel_gaps(free).max() < 1e-10
    shallow = touching[depth[touching] >= -0.02]
    assert qvel_gaps(shallow).max() < 3e-5  # measured 2e-7
    # the axis inside the object: EPA's residual (measured 2e-5)
    assert qvel_gaps(touching[depth[touching] < -0.02]).max() < 1e-4


def test_line_search_returns_the_minimiser_along_the_direction():
    """The exact line search against bisection on the slope ``f'(alpha) = s + alpha c + sum_i w_i
    jd_i min(0, jar_i + alpha jd_i)`` (increasing), with rows on the boundary (``jar = 0``) that
    move in, move out or stay, and rows that do not exist (``w = 0``)."""
    g = torch.Generator().manual_seed(0)
    n, r = 256, 12
    jar = torch.randn(n, r, dtype=torch.float64, generator=g)
    jar[torch.rand(n, r, generator=g) < 0.2] = 0.0  # on the boundary
    jd = torch.randn(n, r, dtype=torch.float64, generator=g)
    jd[torch.rand(n, r, generator=g) < 0.1] = 0.0
    w = torch.rand(n, r, dtype=torch.float64, generator=g) * (torch.rand(n, r, generator=g) < 0.8)
    s0, c0 = torch.randn(n, dtype=torch.float64, generator=g), torch.rand(n, dtype=torch.float64, generator=g) + 0.01

    def slope(alpha):
        return s0 + alpha * c0 + (w * jd * (jar + alpha.unsqueeze(-1) * jd).clamp_max(0)).sum(-1)

    low, high = torch.zeros(n, dtype=torch.float64), torch.full((n,), 1e3, dtype=torch.float64)
    assert (slope(high) > 0).all()
    for _ in range(200):  # bisection to the root (or 0 where the cost rises from the start)
        mid = (low + high) / 2
        uphill = slope(mid) >= 0
        low, high = torch.where(uphill, low, mid), torch.where(uphill, mid, high)
    expected = torch.where(slope(torch.zeros(n, dtype=torch.float64)) >= 0, 0.0, high)
    torch.testing.assert_close(line_search(jar, jd, w, s0, c0), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("filename", ["half_cheetah.xml", "hopper.xml", "ant.xml"])
def test_solver_convergence_report_follows_mujocos_termination(filename):
    """``accelerations(..., with_contact_force=True)`` reports whether the constraint solve converged:
    as MuJoCo's solver decides at the model file's iterations (every state converges), and in (almost)
    every state when both are cut to 1-5 iterations (the two Newton iterates differ in rounding, so a
    state right at the tolerance may fall either side)."""
    import dataclasses

    model, mm, data, tree, params = setup(filename)
    states = trajectory_states(mm, data, 300, seed=3, every=15)
    agree, total = 0, 0
    for iterations in (1, 2, 3, 5, model.iterations):
        tree.model = dataclasses.replace(model, iterations=iterations)
        mm.opt.iterations = iterations
        for qpos, qvel, ctrl in states:
            forward(mm, data, qpos, qvel, ctrl)
            if data.solver_niter[0] == 0:  # no constraint active: nothing to solve
                continue
            _, report = accelerations(tree, *t64(qpos, qvel, ctrl), params, with_contact_force=True)
            ours, theirs = bool(report.solver_converged[0]), mujoco_converged(mm, data)
            if iterations == model.iterations:
                assert ours and theirs
            agree, total = agree + (ours == theirs), total + 1
    assert total > 40 and agree >= 0.9 * total, f"{agree} of {total} verdicts agree"


@pytest.mark.filterwarnings("ignore")
def test_env_flags_the_envs_whose_solve_did_not_converge():
    import dataclasses

    env = make_env("HalfCheetah-v5", num_envs=8, dtype=torch.float64, seed=0)
    td = env.rollout(30)
    assert not td["next", "state", "solver_unconverged"].any()  # MuJoCo's 100 iterations suffice
    env.tree.model = dataclasses.replace(env.tree.model, iterations=1)
    td = env.rollout(30)
    flags = td["next", "state", "solver_unconverged"]
    assert flags.dtype == torch.bool and flags.any() and not td["state", "solver_unconverged"][:, 0].any()
    assert torch.isfinite(td["next", "state", "qvel"]).all()  # the last iterate is taken: flagged, not raised
    from torchrl_diffenvs.objectives.windows import window_solver_unconverged

    assert window_solver_unconverged(td) == pytest.approx(flags.sum().item() / flags.numel())  # what the learners log
    assert "solver_unconverged" not in make_env("HalfCheetah-v5", contact="smooth").reset()["state"].keys()


def test_regulariser_scales_follow_params_changed_between_steps():
    """An env keeps MuJoCo's invweight0 (the regularisers' scales, constants of the params) from
    step to step: a param changed in place, or replaced, must reach the next step as it reaches a
    fresh env's (which computes them anew)."""
    env = make_env("HalfCheetah-v5", num_envs=2, seed=0, dtype=torch.float64)
    td = env.reset()
    for _ in range(20):  # into contact, where the scales matter
        td["action"] = torch.full((2, 6), 0.5, dtype=torch.float64)
        td = env.step_mdp(env.step(td))
    for change in ("in place", "replaced"):
        if change == "in place":
            td["params", "body_mass"].mul_(3.0)
        else:
            td["params", "body_inertia"] = td["params", "body_inertia"] * 3.0
        td["action"] = torch.full((2, 6), 0.5, dtype=torch.float64)
        fresh = make_env("HalfCheetah-v5", num_envs=2, seed=0, dtype=torch.float64).step(td.clone())
        stepped = env.step(td)
        assert torch.equal(stepped["next", "observation"], fresh["next", "observation"]), change
        td = env.step_mdp(stepped)
    with torch.inference_mode():  # params made there are inference tensors, without a version counter
        inferred = make_env("HalfCheetah-v5", num_envs=2, seed=0, dtype=torch.float64).rollout(3)
    assert torch.isfinite(inferred["next", "observation"]).all()


@pytest.mark.parametrize("mode, integrator", [("exact", "rk4"), ("penalty", "rk4"), ("cfd", "euler"),
                                              ("exact", "implicit")])
def test_the_steps_solved_contacts_give_the_wrench_of_a_fresh_solve(mode, integrator):
    """``cfrc_ext`` read from the contact problem the step solved at the state it evaluated last (RK4's
    last stage, Euler's start) is the wrench a fresh forward at that state gives: values and
    gradient w.r.t. the action; the env's transition reads it."""
    env = make_env("Ant-v5", num_envs=2, dtype=torch.float64, seed=0, contact_gradient=mode, integrator=integrator)
    td = env.reset()
    for _ in range(10):  # onto the floor
        td["action"] = torch.zeros(2, 8, dtype=torch.float64)
        td = env.step(td)["next"].clone()
    state, params = dict(td["state"].items()), env.params
    action = (0.3 * torch.ones(2, 8, dtype=torch.float64)).requires_grad_()
    result = env.simulate(state, action, params)
    assert result.solved_contacts is not None
    reused = env.contact_wrenches(result.eval_qpos, result.eval_qvel, action, params, result.solved_contacts)
    fresh = env.contact_wrenches(result.eval_qpos, result.eval_qvel, action, params)
    assert fresh.abs().max() > 1.0  # the feet carry the Ant
    torch.testing.assert_close(reused, fresh, rtol=0, atol=0)
    weights = torch.randn_like(fresh)
    grads = [torch.autograd.grad((w * weights).sum(), action, retain_graph=True)[0] for w in (reused, fresh)]
    assert grads[1].abs().max() > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)
    stepped = env.transition(state, action, params)[0]["cfrc_ext"]  # with grad, as above: the same slots in use
    torch.testing.assert_close(stepped, fresh, rtol=0, atol=0)
