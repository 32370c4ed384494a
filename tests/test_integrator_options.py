"""The contact tasks' ``integrator`` and ``substeps`` options: what they compute (against MuJoCo
run with the same integrator, and against hand-written loops of physics steps), their gradients
through contact (gradcheck, float64) and their refusals."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchrl_diffenvs import make_env
from torchrl_diffenvs.articulated import forward_kinematics, gymnasium_asset
from torchrl_diffenvs.articulated.dynamics import dof_invweight0, step

mujoco = pytest.importorskip("mujoco")


def lowered_onto_floor(env, n, depth, seed=0):
    """States near qpos0 (limited joints mid-range) with the lowest contact point ``depth`` deep."""
    tree, model = env.tree, env.model
    gen = torch.Generator().manual_seed(seed)
    qpos = tree.qpos0.expand(n, -1).clone() + 0.01 * torch.randn(n, tree.nq, generator=gen, dtype=torch.float64)
    for j in range(model.njnt):
        if model.limited[j]:
            qpos[:, int(model.joint_qposadr[j])] = float(model.joint_range[j].mean())
    if model.joint_type[0] == "free":
        qpos[:, 3:7] = qpos[:, 3:7] / qpos[:, 3:7].norm(dim=-1, keepdim=True)
    qvel = 0.5 * torch.randn(n, tree.nv, generator=gen, dtype=torch.float64)
    kin = forward_kinematics(tree, qpos)
    centre = kin.body_pos[:, tree.contact_body] + (
        kin.body_rot[:, tree.contact_body] @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    lowest = (centre[..., 2] - tree.contact_radius).min(dim=1).values
    qpos[:, 2 if model.joint_type[0] == "free" else 1] -= lowest + depth
    return qpos, qvel


@pytest.mark.parametrize("kwargs,expected", [
    ({"integrator": "implicit"}, "unknown integrator 'implicit'; valid: 'model', 'euler', 'rk4'"),
    ({"substeps": 0}, "substeps must be an integer >= 1"),
    ({"substeps": 2.5}, "substeps must be an integer >= 1"),
])
def test_bad_options_are_refused_with_what_is_valid(kwargs, expected):
    with pytest.raises(ValueError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        make_env("Hopper-v5", num_envs=1, **kwargs)


def test_model_is_the_files_integrator():
    assert make_env("Hopper-v5", num_envs=1).integrator == "rk4"
    assert make_env("HalfCheetah-v5", num_envs=1).integrator == "euler"
    assert make_env("Hopper-v5", num_envs=1, integrator="euler").integrator == "euler"


@pytest.mark.parametrize("name,integrator,substeps", [("Hopper-v5", "euler", 3), ("HalfCheetah-v5", "rk4", 2)])
def test_substeps_are_k_physics_steps_of_timestep_over_k(name, integrator, substeps):
    """One env step equals frame_skip * k calls of the physics step at timestep / k, in contact."""
    env = make_env(name, num_envs=2, dtype=torch.float64, seed=0, integrator=integrator, substeps=substeps)
    qpos, qvel = lowered_onto_floor(env, 2, depth=0.005)
    action = torch.full((2, env.action_dim), 0.4, dtype=torch.float64)
    params = env.params
    state = env.initial_state(params, 2)
    state.update(qpos=qpos, qvel=qvel)
    next_state, _, _ = env.transition(state, action, params)
    q, v = qpos, qvel
    w0 = dof_invweight0(env.tree, params)
    for _ in range(env.frame_skip * substeps):
        r = step(env.tree, q, v, action, params, env.model.timestep / substeps, integrator, w0)
        q, v = r.qpos, r.qvel
    torch.testing.assert_close(next_state["qpos"], q, rtol=0, atol=0)
    torch.testing.assert_close(next_state["qvel"], v, rtol=0, atol=0)


@pytest.mark.parametrize("name,integrator", [("Hopper-v5", "euler"), ("Walker2d-v5", "euler"),
                                             ("HalfCheetah-v5", "rk4")])
def test_other_integrator_matches_mujoco_run_with_it_in_the_air(name, integrator):
    """Lifted 3 m, the robot falls freely for 0.3 s (joint limits and motors active): the states
    equal MuJoCo's with ``opt.integrator`` set to the same integrator."""
    env = make_env(name, num_envs=1, dtype=torch.float64, seed=0, integrator=integrator)
    mm = mujoco.MjModel.from_xml_path(str(gymnasium_asset(env.model_file)))
    mm.opt.integrator = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4}[integrator]
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(0)
    data.qpos[:] = mm.qpos0 + 0.1 * rng.normal(size=mm.nq)
    data.qpos[1] += 3.0
    data.qvel[:] = rng.normal(size=mm.nv)
    q, v = torch.tensor(data.qpos[None]), torch.tensor(data.qvel[None])
    w0 = dof_invweight0(env.tree, env.params)
    for _ in range(int(0.3 / mm.opt.timestep)):
        ctrl = rng.uniform(-1, 1, mm.nu)
        data.ctrl[:] = ctrl
        mujoco.mj_step(mm, data)
        r = step(env.tree, q, v, torch.tensor(ctrl[None]), env.params, mm.opt.timestep, integrator, w0)
        q, v = r.qpos, r.qvel
    assert data.qpos[1] > 1.5  # still in the air
    np.testing.assert_allclose(q[0].numpy(), data.qpos, atol=1e-7)
    np.testing.assert_allclose(v[0].numpy(), data.qvel, atol=1e-6)


@pytest.mark.parametrize("name,options", [
    ("Hopper-v5", {"integrator": "euler"}),
    ("Hopper-v5", {"integrator": "euler", "substeps": 2}),
    ("Walker2d-v5", {"integrator": "euler"}),
    ("HalfCheetah-v5", {"integrator": "rk4"}),
    ("Ant-v5", {"integrator": "euler"}),
])
def test_gradcheck_one_step_through_contact(name, options):
    """One env step, 5 mm into the floor: gradients w.r.t. the action, the state and the masses."""
    n = 1
    env = make_env(name, num_envs=n, dtype=torch.float64, seed=0, **options)
    qpos, qvel = lowered_onto_floor(env, n, depth=0.005)
    extras = {k: v for k, v in env.initial_state(env.params, n).items() if k not in ("qpos", "qvel")}
    base = env.params.clone()

    def fn(action, qpos, qvel, mass):
        params = base.clone()
        params["body_mass"] = mass
        next_state, reward, _ = env.transition({**extras, "qpos": qpos, "qvel": qvel}, action, params)
        return reward, next_state["qpos"], next_state["qvel"]

    action = 0.3 * torch.randn(n, env.action_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    inputs = (action.requires_grad_(), qpos.requires_grad_(), qvel.requires_grad_(),
              base["body_mass"].clone().requires_grad_())
    reward, _, _ = fn(*inputs)
    assert torch.isfinite(reward).all()
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)
