"""Contacts with torsional and rolling friction (``condim`` 4 and 6), with MuJoCo's default
pyramidal cones and with elliptic ones, against MuJoCo itself.

Oracles: the installed ``mujoco``'s ``mj_forward`` (``efc_J``, ``efc_pos``, ``efc_aref``,
``efc_R``, ``efc_force``, ``qfrc_constraint``, ``qacc``), ``mj_contactForce`` and ``cfrc_ext``
(``mj_rnePostConstraint``) at the same states, with contacts of every condim (1, 3, 4, 6) on a
floor and between bodies; ``mj_step`` from MuJoCo's own states along a ball rolling and spinning
and a box spinning; ``torch.autograd.gradcheck`` (finite differences, float64) for a step's
gradient.
"""
import dataclasses

import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from torchrl_diffenvs.articulated import MJCFError, RigidBodyTree, default_params, forward_kinematics, load_mjcf, step  # noqa: E402
from torchrl_diffenvs.articulated.collision import collide  # noqa: E402
from torchrl_diffenvs.articulated.constraint import (constraint_rows, contact_frame_forces,  # noqa: E402
                                                     contact_row_blocks, solve)
from torchrl_diffenvs.articulated.elliptic import _cone_state  # noqa: E402
from torchrl_diffenvs.articulated.inertia import mass_matrix_and_bias  # noqa: E402
from torchrl_diffenvs.articulated.pipeline import accelerations, body_contact_wrenches, invweight0  # noqa: E402

from _mujoco_steps import gaps_to_mj_step, mujoco_converged  # noqa: E402

# a frictionless floor (its condim 1 leaves each pair the other geom's), a ball with torsional and
# rolling friction (6) pressed against a box with torsional friction (4), a capsule with sliding
# friction (3) touching a frictionless bead (1): pairs of every condim, on the floor and between bodies
MIXED = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="5 5 0.1" condim="1" friction="0.5 0.001 0.00001"/>
  <body name="ball" pos="0 0 0.0995"><freejoint/>
    <geom name="ball" type="sphere" size="0.1" condim="6" friction="1 0.02 0.01"/></body>
  <body name="block" pos="0.179 0 0.0495"><freejoint/>
    <geom name="block" type="box" size="0.08 0.06 0.05" condim="4" friction="0.7 0.03 0.001"/></body>
  <body name="pill" pos="-0.5 0 0.0395"><freejoint/>
    <geom name="pill" type="capsule" size="0.04 0.1" euler="0 90 0" condim="3"/></body>
  <body name="bead" pos="-0.5 0.089 0.0495"><freejoint/>
    <geom name="bead" type="sphere" size="0.05" condim="1"/></body>
</worldbody></mujoco>"""

# a ball rolling and spinning on the floor (condim 6), a box spinning on it (condim 4)
ROLLING = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="5 5 0.1"/>
  <body name="ball" pos="0 0 0.1"><freejoint/>
    <geom name="ball" type="sphere" size="0.1" condim="6" friction="1 0.01 0.01"/></body>
  <body name="block" pos="0.6 0 0.05"><freejoint/>
    <geom name="block" type="box" size="0.08 0.06 0.05" condim="4" friction="0.7 0.03 0.001"/></body>
</worldbody></mujoco>"""


def _load(tmp_path, text, name="model.xml"):
    path = tmp_path / name
    path.write_text(text)
    model = load_mjcf(str(path))
    mm = mujoco.MjModel.from_xml_path(str(path))
    return model, RigidBodyTree.from_model(model), mm, mujoco.MjData(mm)


def _params(tree, n=1):
    params = {k: v.expand(n, *v.shape) for k, v in default_params(tree.model).items()}
    params["contact_friction"] = torch.as_tensor(tree.contact_pair_friction).expand(n, -1)
    return params


def _mixed_states(mm, data):
    """``[S, nq]``, ``[S, nv]``: every 10th state of a trajectory of MuJoCo's own (the ball pushing
    the box, all turning), then the start poses turned a little about random axes with random
    velocities (the ball against the box in each)."""
    rng = np.random.default_rng(0)
    qpos, qvel = [], []
    mujoco.mj_resetData(mm, data)
    data.qvel[:] = rng.normal(0.0, 1.0, mm.nv)
    data.qvel[0], data.qvel[5] = 1.0, 15.0  # the ball rolls into the box, spinning
    for t in range(300):
        mujoco.mj_step(mm, data)
        if t % 10 == 0:
            qpos.append(data.qpos.copy())
            qvel.append(data.qvel.copy())
    for _ in range(20):
        q = mm.qpos0.copy()
        for body in range(4):
            turn = np.r_[1.0, rng.normal(0.0, 0.05, 3)]
            mujoco.mju_mulQuat(q[7 * body + 3:7 * body + 7], turn / np.linalg.norm(turn), q[7 * body + 3:7 * body + 7].copy())
        qpos.append(q)
        qvel.append(rng.normal(0.0, 0.5, mm.nv) + np.tile([0, 0, 0, 0, 0, 5.0], 4))  # all spinning about z
    return np.array(qpos), np.array(qvel)


def _forward_at_mixed_states(tmp_path, text):
    """MuJoCo's ``mj_forward`` at the states of `_mixed_states` of the model ``text`` (Newton run to
    1e-14: at its default 1e-8 its forces stop ~1e-8 short of the minimiser; each contact's efc rows,
    its first row's state, MuJoCo's own residual ``M (qacc - qacc_smooth) - qfrc_constraint``), and
    ours at all of them as one batch: the rows, the solve (to the same tolerance) and the contact forces."""
    model, tree, mm, data = _load(tmp_path, text)
    mm.opt.tolerance = 1e-14
    qpos_np, qvel_np = _mixed_states(mm, data)
    elliptic = mm.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    theirs = []
    for q, v in zip(qpos_np, qvel_np):
        data.qpos[:], data.qvel[:], data.qacc_warmstart[:] = q, v, 0.0
        mujoco.mj_forward(mm, data)
        mujoco.mj_rnePostConstraint(mm, data)
        inertial = np.zeros(mm.nv)
        mujoco.mj_mulM(mm, data, inertial, data.qacc - data.qacc_smooth)
        contacts = []
        for j in range(data.ncon):
            con = data.contact[j]
            force = np.zeros(6)
            mujoco.mj_contactForce(mm, data, j, force)
            a, k = con.efc_address, (int(con.dim) if elliptic or con.dim == 1 else 2 * (con.dim - 1))
            contacts.append(dict(geom=tuple(map(int, con.geom)), point=con.pos.copy(), dim=int(con.dim), force6=force,
                                 state=int(data.efc_state[a]), J=data.efc_J.reshape(data.nefc, mm.nv)[a:a + k].copy(),
                                 **{f: getattr(data, "efc_" + f)[a:a + k].copy() for f in ("pos", "aref", "R", "force")}))
        theirs.append(dict(contacts=contacts, qfrc=data.qfrc_constraint.copy(), qacc=data.qacc.copy(),
                           qacc_smooth=data.qacc_smooth.copy(), residual=np.abs(inertial - data.qfrc_constraint).max(),
                           cfrc_ext=data.cfrc_ext.copy(), com=data.subtree_com.copy()))
    params = _params(tree, len(theirs))
    weights = invweight0(tree, params)
    qpos, qvel = torch.as_tensor(qpos_np), torch.as_tensor(qvel_np)
    kin = forward_kinematics(tree, qpos)
    contacts = collide(tree.contact_slots, kin)
    rows = constraint_rows(tree, tree.contact_slots, kin, contacts, qpos, qvel, params, weights.dof, weights.body)
    mass, _ = mass_matrix_and_bias(tree, kin, qvel, params)
    qacc_smooth = torch.as_tensor(np.array([t["qacc_smooth"] for t in theirs]))
    solution = solve(mass, qacc_smooth, rows, mm.opt.iterations, mm.opt.tolerance)
    return dict(model=model, tree=tree, mm=mm, theirs=theirs, qpos=qpos, qvel=qvel, params=params, weights=weights,
                contacts=contacts, rows=rows, mass=mass, qacc_smooth=qacc_smooth, solution=solution)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """`_forward_at_mixed_states` with MuJoCo's default pyramidal cones."""
    return _forward_at_mixed_states(tmp_path_factory.mktemp("condim"), MIXED)


def _matched(mixed):
    """Our rows matched to MuJoCo's contacts: ``(state, slot, our rows, MuJoCo's contact)`` for
    every contact of every state, by geom pair and position (the same contacts, each once), with
    pyramidal or elliptic cones."""
    tree, contacts, rows = mixed["tree"], mixed["contacts"], mixed["rows"]
    slots = tree.contact_slots
    out = []
    for k, state in enumerate(mixed["theirs"]):
        ours = {}
        for condim, index, start in contact_row_blocks(slots, rows):
            edges = condim if condim == 1 or slots.cone == "elliptic" else 2 * (condim - 1)
            for n, s in enumerate(index.tolist()):
                if contacts.active[k, s]:
                    key = (tuple(slots.geom[s].tolist()), tuple(np.round(contacts.pos[k, s].numpy(), 9)))
                    ours[key] = (s, slice(start + edges * n, start + edges * (n + 1)))
        assert len(ours) == len(state["contacts"])
        for con in state["contacts"]:
            s, index = ours.pop((con["geom"], tuple(np.round(con["point"], 9))))
            assert slots.condim[s] == con["dim"]
            out.append((k, s, index, con))
    return out


@pytest.mark.filterwarnings("ignore")
def test_condim_4_and_6_rows_force_and_qacc_match_mjdata(mixed):
    """efc_J, efc_pos, efc_aref, efc_R, efc_force per contact of each condim, qfrc_constraint and
    qacc at every state (measured: 7e-16, 1e-16, 2e-13, 6e-14 relative, 4e-12, 3e-12, 3e-11), the ball's
    condim-6 contacts on the floor and against the box among them."""
    rows, solution = mixed["rows"], mixed["solution"]
    worst = dict(J=0.0, pos=0.0, aref=0.0, R=0.0, force=0.0)
    condims = {}
    for k, s, index, con in _matched(mixed):
        condims[con["dim"]] = condims.get(con["dim"], 0) + 1
        for name, ours in (("J", rows.jacobian[k, index]), ("pos", rows.pos[k, index]), ("aref", rows.aref[k, index]),
                           ("force", solution.force[k, index])):
            worst[name] = max(worst[name], np.abs(ours.numpy() - con[name]).max())
        worst["R"] = max(worst["R"], (np.abs(rows.regulariser[k, index].numpy() - con["R"]) / con["R"]).max())
    assert worst["J"] < 1e-12 and worst["pos"] < 1e-12 and worst["aref"] < 1e-9 and worst["R"] < 1e-10, worst
    assert worst["force"] < 1e-9, worst
    assert condims.get(4, 0) > 50 and condims.get(6, 0) > 30 and condims.get(3, 0) > 30 and condims.get(1, 0) > 30
    assert sum(con["geom"] == (1, 2) for *_, con in _matched(mixed)) > 5  # ball against box: both sides turn
    theirs = mixed["theirs"]
    constraint = (rows.jacobian.transpose(-1, -2) @ solution.force.unsqueeze(-1)).squeeze(-1)
    np.testing.assert_allclose(constraint.numpy(), np.array([t["qfrc"] for t in theirs]), rtol=0, atol=1e-9)
    tree, params = mixed["tree"], mixed["params"]
    ctrl = torch.zeros(len(theirs), 0, dtype=torch.float64)
    qacc = accelerations(tree, mixed["qpos"], mixed["qvel"], ctrl, params, invweight0=mixed["weights"])
    np.testing.assert_allclose(qacc.numpy(), np.array([t["qacc"] for t in theirs]), rtol=0, atol=1e-9)


@pytest.mark.filterwarnings("ignore")
def test_contact_force_and_torque_match_mj_contactforce_and_cfrc_ext(mixed):
    """`contact_frame_forces`: each contact's force and torque in its frame as mj_contactForce's 6
    numbers (the torsional torque of condim 4 and 6, the rolling torques of 6); the bodies'
    contact wrenches as cfrc_ext (each free body's about its own centre of mass). Measured: 4e-12
    and 3e-12."""
    tree, rows, solution, params = mixed["tree"], mixed["rows"], mixed["solution"], mixed["params"]
    slots = tree.contact_slots
    local = contact_frame_forces(slots, rows, solution.force, params["contact_friction"][:, slots.friction_slot])
    worst, torque = 0.0, 0.0
    for k, s, _, con in _matched(mixed):
        worst = max(worst, np.abs(local[k, s].numpy() - con["force6"]).max())
        torque = max(torque, np.abs(con["force6"][3:]).max())
    assert worst < 1e-9 and torque > 1e-2, (worst, torque)
    theirs = mixed["theirs"]
    n = len(theirs)
    ctrl = torch.zeros(n, 0, dtype=torch.float64)
    for body in range(1, tree.nbody):  # each free body is its own root: cfrc_ext about its own centre of mass
        about = torch.as_tensor(np.array([t["com"][body] for t in theirs]))
        ours = body_contact_wrenches(tree, mixed["qpos"], mixed["qvel"], ctrl, params, about, mixed["weights"])
        np.testing.assert_allclose(ours[:, body].numpy(), np.array([t["cfrc_ext"][body] for t in theirs]),
                                   rtol=0, atol=1e-9)


def _rolling_start(mm, data):
    """Ball and box settled on the floor (100 steps at rest), then the ball rolling at 1 m/s
    without slipping and spinning at 20 rad/s about the vertical, the box spinning at 10 rad/s."""
    mujoco.mj_resetData(mm, data)
    for _ in range(100):
        mujoco.mj_step(mm, data)
    data.qvel[:] = [1.0, 0.0, 0.0, 0.0, 10.0, 20.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0]


def _sliding_only(text):
    return text.replace('condim="6"', 'condim="3"').replace('condim="4"', 'condim="3"')


@pytest.mark.filterwarnings("ignore")
def test_rolling_and_spinning_steps_match_mj_step(tmp_path):
    """200 steps of the ball rolling and spinning and the box spinning to a stop: one step of ours
    from each of MuJoCo's states lands on mj_step's (measured: 1e-14). The torsional and rolling
    friction act: along MuJoCo's trajectory the ball's spin and roll decay, where with condim 3
    they keep; ours, one step from a state of the condim-3 trajectory, slows them as much, and
    with condim 3 keeps them."""
    model, tree, mm, data = _load(tmp_path, ROLLING)
    spins = []
    _rolling_start(mm, data)
    gaps = gaps_to_mj_step(tree, mm, data, 200, lambda d: spins.append(d.qvel[[4, 5]].copy()))
    assert max(gaps) < 1e-9, max(gaps)
    roll, spin = spins[-1]
    assert spin < 0.8 * 20.0 and roll < 0.9 * 10.0, spins[-1]  # condim 6: spin and roll decay
    sliding_mm = mujoco.MjModel.from_xml_string(_sliding_only(ROLLING))
    sliding = mujoco.MjData(sliding_mm)
    _rolling_start(sliding_mm, sliding)
    for _ in range(200):
        mujoco.mj_step(sliding_mm, sliding)
    assert np.abs(sliding.qvel[[4, 5]] - [10.0, 20.0]).max() < 0.05, sliding.qvel  # condim 3: they keep
    # ours from that state, with condim 6 and with condim 3: as mj_step of each, the spin and roll slowed by condim 6
    sliding_tree = RigidBodyTree.from_model(load_mjcf(_write(tmp_path, "sliding.xml", _sliding_only(ROLLING))))
    qpos, qvel = torch.as_tensor(sliding.qpos).unsqueeze(0), torch.as_tensor(sliding.qvel).unsqueeze(0)
    rates = []
    for t, m, d in ((tree, mm, data), (sliding_tree, sliding_mm, sliding)):
        d.qpos[:], d.qvel[:] = qpos[0].numpy(), qvel[0].numpy()
        mujoco.mj_step(m, d)
        params = _params(t)
        result = step(t, qpos, qvel, torch.zeros(1, 0, dtype=torch.float64), params, mm.opt.timestep,
                      model.integrator, invweight0(t, params))
        np.testing.assert_allclose(result.qvel[0].numpy(), d.qvel, rtol=0, atol=1e-9)
        rates.append((result.qvel - qvel)[0, [4, 5]].numpy() / mm.opt.timestep)  # the ball's roll and spin rates
    assert rates[0][0] < -10.0 and rates[0][1] < -10.0 and np.abs(rates[1]).max() < 0.1, rates


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def _with_cone(text, cone):
    return text if cone == "pyramidal" else text.replace("<worldbody>", f'<option cone="{cone}"/><worldbody>', 1)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_one_step_gradcheck_with_condim_6_contacts(tmp_path, cone):
    """One Euler step's qpos and qvel against finite differences (float64) in qvel and in the
    pairs' sliding friction (``params["contact_friction"]``), with the rolling, spinning ball's
    condim-6 contact and the box's condim-4 contacts active; with elliptic cones every one in
    the cone's middle zone, where the solve is not a fixed-weight one."""
    model, tree, mm, data = _load(tmp_path, _with_cone(ROLLING, cone))
    _rolling_start(mm, data)
    qpos, qvel = torch.as_tensor(data.qpos).unsqueeze(0), torch.as_tensor(data.qvel).unsqueeze(0)
    active = collide(tree.contact_slots, forward_kinematics(tree, qpos)).active[0]
    assert [tree.contact_slots.condim[s] for s in np.flatnonzero(active.numpy())] == [6, 4, 4, 4, 4]
    if cone == "elliptic":
        mujoco.mj_forward(mm, data)
        assert (data.efc_state[:data.nefc] == mujoco.mjtConstraintState.mjCNSTRSTATE_CONE).all()
    params = _params(tree)
    weights = invweight0(tree, params)
    friction = params["contact_friction"].clone().requires_grad_(True)

    def one_step(qvel, friction):
        result = step(tree, qpos, qvel, torch.zeros(1, 0, dtype=torch.float64), {**params, "contact_friction": friction},
                      mm.opt.timestep, model.integrator, weights)
        return result.qpos, result.qvel

    assert torch.autograd.gradcheck(one_step, (qvel.clone().requires_grad_(True), friction), eps=1e-6, atol=1e-5,
                                    rtol=1e-4)


def test_invalid_cones_and_condims_are_refused(tmp_path):
    """A cone MuJoCo has not is refused when the file is read and by the contact model for a model
    built with one; so is a condim MuJoCo has not (2, 5), naming the geoms."""
    with pytest.raises(MJCFError, match="cone 'round' is invalid; valid: 'pyramidal' .*'elliptic'"):
        load_mjcf(_write(tmp_path, "round.xml", ROLLING.replace("<worldbody>", '<option cone="round"/><worldbody>')))
    model = load_mjcf(_write(tmp_path, "rolling.xml", ROLLING))
    with pytest.raises(ValueError, match="friction cone 'round' is invalid; valid: 'pyramidal', 'elliptic'"):
        RigidBodyTree.from_model(dataclasses.replace(model, cone="round"))
    with pytest.raises(MJCFError, match="condim '5' is invalid; valid: 1, 3, 4, 6"):
        load_mjcf(_write(tmp_path, "five.xml", ROLLING.replace('condim="4"', 'condim="5"')))
    condim = model.geom_condim.copy()
    condim[2] = 5
    with pytest.raises(ValueError, match="geoms 'floor' and 'block': condim 5 is not supported .*supported: 1 "
                                         r"\(frictionless\), 3 \(sliding friction\), 4 \(and torsional\) and 6"):
        RigidBodyTree.from_model(dataclasses.replace(model, geom_condim=condim))


# MIXED with elliptic cones, and impratio 3 (the friction rows' R is the normal's over it)
ELLIPTIC = MIXED.replace("<worldbody>", '<option cone="elliptic" impratio="3"/><worldbody>', 1)


@pytest.fixture(scope="module")
def elliptic(tmp_path_factory):
    """`_forward_at_mixed_states` with elliptic cones."""
    return _forward_at_mixed_states(tmp_path_factory.mktemp("elliptic"), ELLIPTIC)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_solver_verdict_against_mujocos_at_the_files_and_at_cut_iteration_counts(request, cone):
    """The solve's convergence verdict (what ``solver_unconverged`` flags) at the mixed states,
    against MuJoCo's own (`mujoco_converged`: its scaled improvement or gradient under the
    tolerance), both at the default tolerance 1e-8: at the file's 100 iterations every state
    converges in both; cut to 1-5 iterations, ours is the stricter test (the cost's gradient
    relative to the size of its terms): where MuJoCo's says unconverged, ours does too at >= 90%
    of the states (measured: all but 2 of 121, elliptic; all but 5 of 73, pyramidal)."""
    forward = request.getfixturevalue("mixed" if cone == "pyramidal" else "elliptic")
    mm, data = forward["mm"], mujoco.MjData(forward["mm"])
    tolerance, saved = 1e-8, (mm.opt.iterations, mm.opt.tolerance)
    mm.opt.tolerance = tolerance
    flagged_by_both, flagged_by_mujoco = 0, 0
    try:
        for iterations in (1, 2, 3, 5, 100):
            mm.opt.iterations = iterations
            ours = solve(forward["mass"], forward["qacc_smooth"], forward["rows"], iterations, tolerance).converged
            for k, (q, v) in enumerate(zip(forward["qpos"].numpy(), forward["qvel"].numpy())):
                data.qpos[:], data.qvel[:], data.qacc_warmstart[:] = q, v, 0.0
                mujoco.mj_forward(mm, data)
                theirs = mujoco_converged(mm, data)
                if iterations == 100:
                    assert theirs and bool(ours[k]), f"state {k} unconverged after 100 iterations"
                flagged_by_mujoco += not theirs
                flagged_by_both += not theirs and not bool(ours[k])
    finally:
        mm.opt.iterations, mm.opt.tolerance = saved
    assert flagged_by_mujoco > 20 and flagged_by_both >= 0.9 * flagged_by_mujoco, (flagged_by_both, flagged_by_mujoco)


@pytest.mark.filterwarnings("ignore")
def test_elliptic_rows_and_cone_force_law_match_mjdata(elliptic):
    """Elliptic cones: efc_J, efc_pos, efc_aref and efc_R of every contact (condim rows each: the
    friction rows' R from the normal's over impratio) as mjData's (measured: 2e-15, 0, 2e-12, 7e-14
    relative), and the cone's force law (`_cone_state`, mj_constraintUpdate's top, bottom and middle
    zones) at MuJoCo's own qacc gives its efc_force (measured: 4e-12), with contacts in each zone."""
    rows = elliptic["rows"]
    qacc = torch.as_tensor(np.array([t["qacc"] for t in elliptic["theirs"]]))
    jar = (rows.jacobian @ qacc.unsqueeze(-1)).squeeze(-1) - rows.aref
    force, _, _ = _cone_state(jar, rows.weight, rows.exists, rows.cones)
    worst = dict(J=0.0, pos=0.0, aref=0.0, R=0.0, force=0.0)
    zones, condims = {}, {}
    for k, s, index, con in _matched(elliptic):
        zones[con["state"]] = zones.get(con["state"], 0) + 1
        condims[con["dim"]] = condims.get(con["dim"], 0) + 1
        for name, ours in (("J", rows.jacobian[k, index]), ("pos", rows.pos[k, index]), ("aref", rows.aref[k, index]),
                           ("force", force[k, index])):
            worst[name] = max(worst[name], np.abs(ours.numpy() - con[name]).max())
        worst["R"] = max(worst["R"], (np.abs(rows.regulariser[k, index].numpy() - con["R"]) / con["R"]).max())
    assert worst["J"] < 1e-12 and worst["pos"] < 1e-12 and worst["aref"] < 1e-9 and worst["R"] < 1e-10, worst
    assert worst["force"] < 1e-9, worst
    state = mujoco.mjtConstraintState
    assert min(zones.get(int(z), 0) for z in (state.mjCNSTRSTATE_SATISFIED, state.mjCNSTRSTATE_QUADRATIC,
                                               state.mjCNSTRSTATE_CONE)) > 5, zones
    assert condims.get(4, 0) > 50 and condims.get(6, 0) > 30 and condims.get(3, 0) > 30 and condims.get(1, 0) > 30


@pytest.mark.filterwarnings("ignore")
def test_elliptic_solve_is_the_minimiser_mujocos_newton_approaches(elliptic):
    """Our solve with elliptic cones meets the optimality condition M (qacc - qacc_smooth) =
    J' f(J qacc - aref) to 1e-9 at every state; MuJoCo's Newton, even at tolerance 1e-14, stops up
    to 3e-6 short of it in its own terms (M (qacc - qacc_smooth) - qfrc_constraint from mjData:
    measured 2.8e-6) and its qacc, efc_force and mj_contactForce lie within that of ours (measured
    1.2e-6, 2.5e-6), as the bodies' contact wrenches and cfrc_ext."""
    rows, solution, mass = elliptic["rows"], elliptic["solution"], elliptic["mass"]
    assert bool(solution.converged.all())
    inertial = (mass @ (solution.qacc - elliptic["qacc_smooth"]).unsqueeze(-1)).squeeze(-1)
    constraint = (rows.jacobian.transpose(-1, -2) @ solution.force.unsqueeze(-1)).squeeze(-1)
    assert (inertial - constraint).abs().max() < 1e-9
    theirs = elliptic["theirs"]
    assert max(t["residual"] for t in theirs) < 1e-5
    np.testing.assert_allclose(solution.qacc.numpy(), np.array([t["qacc"] for t in theirs]), rtol=0, atol=1e-5)
    tree, params = elliptic["tree"], elliptic["params"]
    slots = tree.contact_slots
    local = contact_frame_forces(slots, rows, solution.force, params["contact_friction"][:, slots.friction_slot])
    for k, s, index, con in _matched(elliptic):
        np.testing.assert_allclose(solution.force[k, index].numpy(), con["force"], rtol=0, atol=1e-5)
        np.testing.assert_allclose(local[k, s, :con["dim"]].numpy(), con["force6"][:con["dim"]], rtol=0, atol=1e-5)
    n = len(theirs)
    ctrl = torch.zeros(n, 0, dtype=torch.float64)
    for body in range(1, tree.nbody):  # the bodies' contact wrenches as cfrc_ext, within MuJoCo's residual
        about = torch.as_tensor(np.array([t["com"][body] for t in theirs]))
        ours = body_contact_wrenches(tree, elliptic["qpos"], elliptic["qvel"], ctrl, params, about, elliptic["weights"])
        np.testing.assert_allclose(ours[:, body].numpy(), np.array([t["cfrc_ext"][body] for t in theirs]),
                                   rtol=0, atol=1e-4)
    # the simulator's own path (the file's tolerance, 1e-8) to the same minimiser
    qacc = accelerations(tree, elliptic["qpos"], elliptic["qvel"], ctrl, params, invweight0=elliptic["weights"])
    np.testing.assert_allclose(qacc.numpy(), solution.qacc.numpy(), rtol=0, atol=1e-9)


@pytest.mark.filterwarnings("ignore")
def test_elliptic_rolling_and_spinning_steps_match_mj_step(tmp_path):
    """200 steps of the ball rolling and spinning and the box spinning on the floor with elliptic
    cones: one step of ours from each of MuJoCo's states lands on mj_step's within its solver's
    residual (measured: 4e-7 at worst, 7e-16 median; the cones' middle zone in 18% of the rows)."""
    model, tree, mm, data = _load(tmp_path, _with_cone(ROLLING, "elliptic"))
    _rolling_start(mm, data)
    states = []
    gaps = gaps_to_mj_step(tree, mm, data, 200, lambda d: states.append(d.efc_state[:d.nefc].copy()))
    assert max(gaps) < 1e-6, max(gaps)
    assert np.mean(np.concatenate(states) == mujoco.mjtConstraintState.mjCNSTRSTATE_CONE) > 0.1


@pytest.mark.filterwarnings("ignore")
def test_elliptic_zero_friction_and_gradient_modes(tmp_path):
    """Elliptic cones: a zero friction is MuJoCo's minimum (mjMINMU), as mj_step's (50 steps of
    the ball and the box rolling and spinning on a frictionless floor; measured: 5e-14) with a
    finite gradient. The solve-shaping gradient modes refuse an elliptic model, naming the valid
    ones; the penalty mode keeps the elliptic forward and shapes the backward only (a ball alone:
    the smooth model has no box)."""
    frictionless = _with_cone(ROLLING, "elliptic").replace('size="5 5 0.1"/>', 'size="5 5 0.1" friction="0 0 0"/>')
    frictionless = frictionless.replace('friction="1 0.01 0.01"', 'friction="0 0 0"').replace(
        'friction="0.7 0.03 0.001"', 'friction="0 0 0"')
    model, tree, mm, data = _load(tmp_path, frictionless)
    _rolling_start(mm, data)
    qpos, qvel = torch.as_tensor(data.qpos).unsqueeze(0), torch.as_tensor(data.qvel).unsqueeze(0)
    gaps = gaps_to_mj_step(tree, mm, data, 50)
    assert max(gaps) < 1e-9, max(gaps)
    params = _params(tree)
    weights = invweight0(tree, params)
    assert (params["contact_friction"] == 0).all()
    friction = params["contact_friction"].clone().requires_grad_(True)
    result = step(tree, qpos, qvel, torch.zeros(1, 0, dtype=torch.float64), {**params, "contact_friction": friction},
                  mm.opt.timestep, model.integrator, weights)
    (gradient,) = torch.autograd.grad(result.qvel.sum(), friction)
    assert torch.isfinite(result.qvel).all() and torch.isfinite(gradient).all()
    for mode in ("cfd", "smooth"):
        with pytest.raises(ValueError, match=f"contact_gradient='{mode}' .*elliptic \\(valid there: 'exact', 'penalty'\\)"):
            RigidBodyTree.from_model(model).use_contact_gradient(mode)
    # the penalty mode (outside the solve) keeps the elliptic forward, and shapes the backward only
    from torchrl_diffenvs.envs.mujoco.base import CONTACT_DEFAULTS

    ball = load_mjcf(_write(tmp_path, "ball.xml", _with_cone(ROLLING, "elliptic").split('  <body name="block"')[0]
                            + "</worldbody></mujoco>"))
    ball_params = {**_params(RigidBodyTree.from_model(ball)),
                   **{k: torch.full((1,), float(v), dtype=torch.float64) for k, v in CONTACT_DEFAULTS.items()}}
    start = torch.tensor([[0.0, 0.0, 0.099, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    results = {}
    for mode in ("exact", "penalty"):
        tree_mode = RigidBodyTree.from_model(ball).use_contact_gradient(mode)
        spin = torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 5.0]], dtype=torch.float64, requires_grad=True)
        result = step(tree_mode, start, spin, torch.zeros(1, 0, dtype=torch.float64), ball_params, mm.opt.timestep,
                      ball.integrator, invweight0(tree_mode, ball_params))
        results[mode] = (result.qvel.detach(), torch.autograd.grad(result.qvel.sum(), spin)[0])
    torch.testing.assert_close(results["penalty"][0], results["exact"][0], rtol=0, atol=0)
    assert torch.isfinite(results["penalty"][1]).all() and not torch.allclose(results["penalty"][1], results["exact"][1])


@pytest.mark.filterwarnings("ignore")
def test_elliptic_contact_step_compiles_into_one_graph(tmp_path):
    """A physics step with elliptic cones in their middle zone traces into one graph
    (``fullgraph=True``: the Newton rounds, with their line search, are one ``torch.while_loop``)
    and gives eager's next state."""
    if not hasattr(torch, "while_loop"):
        pytest.skip("this torch has no torch.while_loop: the Newton solve is a graph break")
    model, tree, mm, data = _load(tmp_path, _with_cone(ROLLING, "elliptic"))
    _rolling_start(mm, data)
    qpos, qvel = torch.as_tensor(data.qpos).unsqueeze(0), torch.as_tensor(data.qvel).unsqueeze(0)
    params = _params(tree)
    weights = invweight0(tree, params)

    def one(qpos, qvel):
        return step(tree, qpos, qvel, torch.zeros(1, 0, dtype=torch.float64), params, mm.opt.timestep,
                    model.integrator, weights)

    eager = one(qpos, qvel)
    traced = torch.compile(one, fullgraph=True, backend="aot_eager")(qpos, qvel)
    torch.testing.assert_close(traced.qvel, eager.qvel, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(traced.qpos, eager.qpos, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_leaving_out_the_slots_no_env_uses_changes_nothing(tmp_path, monkeypatch, cone):
    """Eagerly on the CPU the constraint stage builds the rows of the contact slots some env uses
    only; on a GPU and under torch.compile it builds them all. With contacts of every condim and
    both cones, the implicit integrator's acceleration, the largest contact force, ``cfrc_ext`` and
    the gradients (state and friction) must not depend on it; a batch entirely in the air keeps
    the friction's gradient (zeros)."""
    from torchrl_diffenvs.articulated import convergence, pipeline

    # 15 solver iterations: every slot and row as on a GPU runs all of them (no early stop on the CPU)
    option = '<option iterations="15"/>' if cone == "pyramidal" else '<option cone="elliptic" impratio="3" iterations="15"/>'
    _, tree, _, _ = _load(tmp_path, MIXED.replace("<worldbody>", option + "<worldbody>", 1))
    assert tree.contact_slots.cone == cone
    n = 4
    start = tree.qpos0.expand(n, -1).clone()
    qvel = torch.randn(n, tree.nv, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.5
    start[1, 2::7] += 0.0005  # every body lifted a little
    start[2, 0] += 0.003
    start[3, 2::7] += 0.5  # every body in the air
    airborne = start.clone()  # every body in the air, apart from the others
    airborne[:, 2::7] += 0.5
    airborne[:, 0::7] += 2.0 * torch.arange(4, dtype=torch.float64)
    weights = torch.randn(n, tree.nv + tree.nbody * 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    used = []
    slots_in_use = pipeline._slots_in_use
    monkeypatch.setattr(pipeline, "_slots_in_use", lambda *a: (lambda r: used.append(r[0].count) or r)(slots_in_use(*a)))
    for qpos in (start, airborne):
        out = []
        for reads_data in (True, False):  # the CPU's compacted problem, then every slot and row (a GPU's)
            monkeypatch.setattr(convergence, "reads_data_freely", lambda device, reads_data=reads_data: reads_data)
            params = _params(tree, n)
            friction = params["contact_friction"] = params["contact_friction"].clone().requires_grad_(True)
            q, v = qpos.clone().requires_grad_(True), qvel.clone().requires_grad_(True)
            qacc, report = accelerations(tree, q, v, torch.zeros(n, tree.model.nu, dtype=torch.float64), params,
                                         implicit_damping_dt=0.01, implicit_bias=True,
                                         invweight0=invweight0(tree, params), with_contact_force=True)
            wrench = body_contact_wrenches(tree, q, v, torch.zeros(n, tree.model.nu, dtype=torch.float64), params,
                                           about=q.new_zeros(n, 3))
            loss = (torch.cat([qacc, wrench.flatten(1)], 1) * weights).sum()
            out.append((qacc.detach(), report.contact_force, wrench.detach(), *torch.autograd.grad(loss, (q, v, friction))))
        for compacted, every_slot in zip(*out):
            torch.testing.assert_close(compacted, every_slot, rtol=1e-9, atol=1e-9)
    assert 1 <= used[0] < tree.contact_slots.count and used[2] == 1  # in the air: one slot, for the graph
    assert out[0][0].abs().sum() > 0 and torch.equal(out[0][-1], torch.zeros_like(out[0][-1]))
