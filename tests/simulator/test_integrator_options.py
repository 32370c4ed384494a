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
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)

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
    ({"integrator": "implicitfast"}, "unknown integrator 'implicitfast'; valid: 'model', 'euler', 'implicit', 'rk4'"),
    ({"substeps": 0}, "substeps must be an integer >= 1"),
    ({"substeps": 2.5}, "substeps must be an integer >= 1"),
    ({"recompute_in_backward": "yes"}, "recompute_in_backward must be True or False, got 'yes'"),
])
def test_bad_options_are_refused_with_what_is_valid(kwargs, expected):
    with pytest.raises(ValueError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        make_env("Hopper-v5", num_envs=1, **kwargs)


def test_defaults_and_the_model_files_integrator():
    """The planar contact tasks step by semi-implicit Euler unless told otherwise, the Ant by MuJoCo's
    implicit integrator; "model" is the file's."""
    for name in ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5"):
        assert make_env(name, num_envs=1).integrator == "euler"
    assert make_env("Ant-v5", num_envs=1).integrator == "implicit"  # Euler diverged under resonant actions (stress)
    assert make_env("Hopper-v5", num_envs=1, integrator="model").integrator == "rk4"
    assert make_env("Ant-v5", num_envs=1, integrator="model").integrator == "rk4"
    assert make_env("HalfCheetah-v5", num_envs=1, integrator="model").integrator == "euler"
    assert make_env("InvertedDoublePendulum-v5", num_envs=1).integrator == "rk4"  # contact-free: the file's


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


def test_swimmers_fluid_refuses_the_implicit_integrator():
    with pytest.raises(ValueError, match="integrator 'implicit' is not available for a model with fluid forces"):
        make_env("Swimmer-v5", num_envs=1, integrator="implicit")


@pytest.mark.parametrize("name,integrator", [("Hopper-v5", "euler"), ("Walker2d-v5", "euler"),
                                             ("HalfCheetah-v5", "rk4"), ("HalfCheetah-v5", "implicit"),
                                             ("Ant-v5", "implicit"), ("Humanoid-v5", "implicit")])
def test_other_integrator_matches_mujoco_run_with_it_in_the_air(name, integrator):
    """Lifted 3 m, the robot falls freely for 0.3 s (joint limits and motors active): the states
    equal MuJoCo's with ``opt.integrator`` set to the same integrator (the free-floating ones
    spinning at 10 rad/s, where ``implicit``'s Coriolis derivative matters)."""
    env = make_env(name, num_envs=1, dtype=torch.float64, seed=0, integrator=integrator)
    mm = mujoco.MjModel.from_xml_path(str(gymnasium_asset(env.model_file)))
    mm.opt.integrator = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
                         "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT}[integrator]
    data = mujoco.MjData(mm)
    rng = np.random.default_rng(0)
    free = env.model.joint_type[0] == "free"
    data.qpos[:] = mm.qpos0 + 0.1 * rng.normal(size=mm.nq)
    data.qpos[2 if free else 1] += 3.0
    data.qvel[:] = rng.normal(size=mm.nv)
    if free:
        data.qvel[3:6] = 10.0 * rng.normal(size=3) / np.sqrt(3)
    q, v = torch.tensor(data.qpos[None]), torch.tensor(data.qvel[None])
    w0 = dof_invweight0(env.tree, env.params)
    # the spinning humanoid's limits are solved by MuJoCo to its solver's tolerance: 1e-9 after 0.1 s,
    # 1e-6 after 0.3 s (Euler's too)
    for _ in range(int((0.1 if name == "Humanoid-v5" else 0.3) / mm.opt.timestep)):
        ctrl = rng.uniform(-1, 1, mm.nu)
        data.ctrl[:] = ctrl
        mujoco.mj_step(mm, data)
        r = step(env.tree, q, v, torch.tensor(ctrl[None]), env.params, mm.opt.timestep, integrator, w0)
        q, v = r.qpos, r.qvel
    assert data.qpos[2 if free else 1] > 1.5  # still in the air
    np.testing.assert_allclose(q[0].numpy(), data.qpos, atol=1e-7)
    np.testing.assert_allclose(v[0].numpy(), data.qvel, atol=1e-6)


@pytest.mark.parametrize("name,options", [
    ("Hopper-v5", {"integrator": "rk4"}),
    ("Hopper-v5", {"substeps": 2}),
    ("Walker2d-v5", {"integrator": "rk4"}),
    ("Ant-v5", {"integrator": "euler"}),
    ("HalfCheetah-v5", {"integrator": "implicit"}),
    ("Hopper-v5", {"integrator": "implicit"}),
])  # each task's default: tests/simulator/test_mujoco_gradients.py; RK4 through MuJoCo's contact (the
#     Ant's file integrator): tests/simulator/test_mujoco_contact.py
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


def _one_step(env, qpos, qvel, action):
    extras = {k: v for k, v in env.initial_state(env.params, qpos.shape[0]).items() if k not in ("qpos", "qvel")}
    return env.transition({**extras, "qpos": qpos, "qvel": qvel}, action, env.params)


@pytest.mark.parametrize("name", ["Hopper-v5", "Walker2d-v5", "Ant-v5"])
def test_posture_gradient_keeps_gymnasiums_rewards_and_adds_the_posture_terms_gradient(name):
    """posture_gradient_scale=k: the reward values are unchanged; d reward / d action gains exactly
    k x the gradient of the hand-written posture terms at the next state."""
    plain = make_env(name, num_envs=3, dtype=torch.float64, seed=0)
    shaped = make_env(name, num_envs=3, dtype=torch.float64, seed=0, posture_gradient_scale=2.0)
    qpos, qvel = lowered_onto_floor(plain, 3, depth=0.003)
    action = torch.full((3, plain.action_dim), 0.3, dtype=torch.float64, requires_grad=True)
    _, r_plain, _ = _one_step(plain, qpos, qvel, action)
    next_state, r_shaped, _ = _one_step(shaped, qpos, qvel, action)
    torch.testing.assert_close(r_shaped, r_plain, rtol=0, atol=0)
    q = next_state["qpos"]
    z = q[:, shaped.height_coordinate] - shaped.params["healthy_z_low"]
    h = torch.clamp(z, -1.0, 0.3)
    hand = torch.where(h < 0, -200 * h * h, h)
    if name == "Ant-v5":
        quat = q[:, 3:7] / q[:, 3:7].norm(dim=-1, keepdim=True)
        hand = hand + 0.1 * (1 - 2 * (quat[:, 1] ** 2 + quat[:, 2] ** 2))
    else:
        hand = hand + 1 - (q[:, 2] / shaped.params["healthy_angle_high"]) ** 2
    (g_plain,) = torch.autograd.grad(r_plain.sum(), action)
    (g_shaped,) = torch.autograd.grad(r_shaped.sum(), action, retain_graph=True)
    (g_hand,) = torch.autograd.grad(hand.sum(), action)
    assert g_hand.abs().max() > 1e-5  # the posture terms do move with the action (the Ant: 2e-4)
    torch.testing.assert_close(g_shaped, g_plain + 2.0 * g_hand)


def test_ant_cfrc_ext_gradient_option_keeps_values_and_stops_their_gradient():
    on = make_env("Ant-v5", num_envs=2, dtype=torch.float64, seed=0)
    off = make_env("Ant-v5", num_envs=2, dtype=torch.float64, seed=0, cfrc_ext_gradient=False)
    qpos, qvel = lowered_onto_floor(on, 2, depth=0.003)
    action = torch.full((2, on.action_dim), 0.3, dtype=torch.float64, requires_grad=True)
    obs_on = on.observation(_one_step(on, qpos, qvel, action)[0], on.params)
    obs_off = off.observation(_one_step(off, qpos, qvel, action)[0], off.params)
    torch.testing.assert_close(obs_on, obs_off, rtol=0, atol=0)
    forces = slice(27, 105)  # the 78 cfrc_ext features
    assert obs_on[:, forces].abs().max() > 0
    (g_on,) = torch.autograd.grad(obs_on[:, forces].sum(), action, retain_graph=True)
    assert g_on.abs().max() > 0
    (g_off,) = torch.autograd.grad(obs_off[:, forces].sum(), action, retain_graph=True)
    assert torch.equal(g_off, torch.zeros_like(g_off))
    (g_off_rest,) = torch.autograd.grad(obs_off[:, :27].sum(), action)
    (g_on_rest,) = torch.autograd.grad(obs_on[:, :27].sum(), action)  # the graph kept by retain_graph above
    torch.testing.assert_close(g_off_rest, g_on_rest)
    with pytest.raises(ValueError, match="cfrc_ext_gradient must be true or false"):
        make_env("Ant-v5", num_envs=1, cfrc_ext_gradient="no")


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_step_reports_the_largest_contact_normal_force_at_the_evaluated_state(integrator):
    """StepResult.contact_force is max over the contact points of the normal force at the state
    the step evaluated last (Euler: the start; RK4: the fourth stage), recomputed here by hand from
    the penetration depth and normal velocity."""
    import torch.nn.functional as F

    from torchrl_diffenvs.articulated.dynamics import body_velocities

    env = make_env("Hopper-v5", num_envs=3, dtype=torch.float64, seed=0, integrator=integrator)
    tree, params = env.tree, env.params
    qpos, qvel = lowered_onto_floor(env, 3, depth=0.004)
    r = step(tree, qpos, qvel, torch.zeros(3, env.action_dim, dtype=torch.float64), params, env.model.timestep,
             integrator, dof_invweight0(tree, params))
    kin = forward_kinematics(tree, r.eval_qpos)
    rot = kin.body_rot[:, tree.contact_body]
    centre = kin.body_pos[:, tree.contact_body] + (rot @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    depth_signed = centre[..., 2] - tree.contact_radius  # the floor is z = 0
    point = centre.clone()
    point[..., 2] -= tree.contact_radius
    vel = body_velocities(tree, kin, r.eval_qvel)[:, tree.contact_body]
    v_point = vel[..., 3:] + torch.linalg.cross(vel[..., :3], point - kin.origin.unsqueeze(1))
    w = params["contact_width"].unsqueeze(-1)
    normal = params["contact_stiffness"].unsqueeze(-1) * F.softplus(-depth_signed / w) * w \
        - params["contact_damping"].unsqueeze(-1) * torch.sigmoid(-depth_signed / w) * v_point[..., 2]
    expected = normal.clamp(min=0).amax(-1)
    assert expected.max() > 100.0  # pushing (an env whose foot moves up may already be free)
    torch.testing.assert_close(r.contact_force, expected)
    swimmer = make_env("Swimmer-v5", num_envs=1)  # no contacts: no force reported
    start = {"qpos": swimmer.tree.qpos0[None], "qvel": torch.zeros(1, swimmer.tree.nv)}
    assert swimmer.simulate(start, torch.zeros(1, 2), swimmer.params).contact_force is None


@pytest.mark.parametrize("name", ["Ant-v5", "Humanoid-v5", "HalfCheetah-v5", "Pusher-v5"])
def test_bias_velocity_jacobian_equals_autograd_of_the_bias(name):
    """``d qfrc_bias / d qvel`` (what the implicit integrator adds to ``M + h D``), analytic, against
    reverse-mode autograd of the bias itself at random states and velocities, float64."""
    from torchrl_diffenvs.articulated.inertia import bias_velocity_jacobian, mass_matrix_and_bias

    env = make_env(name, num_envs=3, dtype=torch.float64, seed=0)
    tree, params = env.tree, env.params
    gen = torch.Generator().manual_seed(1)
    qpos = tree.qpos0.expand(3, -1) + 0.3 * torch.randn(3, tree.nq, generator=gen, dtype=torch.float64)
    if env.model.joint_type[0] == "free":
        qpos[:, 3:7] = qpos[:, 3:7] / qpos[:, 3:7].norm(dim=-1, keepdim=True)
    qvel = 3.0 * torch.randn(3, tree.nv, generator=gen, dtype=torch.float64)
    kin = forward_kinematics(tree, qpos)
    analytic = bias_velocity_jacobian(tree, kin, qvel, params)
    reference = torch.autograd.functional.jacobian(
        lambda v: mass_matrix_and_bias(tree, kin, v, params)[1].sum(0), qvel).permute(1, 0, 2)
    assert reference.abs().max() > 1.0
    torch.testing.assert_close(analytic, reference, rtol=1e-10, atol=1e-10)


def test_recompute_in_backward_keeps_values_and_gradients_and_saves_less():
    """MuJoCo's HalfCheetah (contacts, joint limits, the Newton solve), a 3-step window in float64:
    with ``recompute_in_backward`` the rollout, the policy gradient and the gradient w.r.t. the
    body masses are the same, and the graph holds a small share of the bytes (each env step's
    physics runs again in the backward)."""
    from torchrl_diffenvs import make_env as make_mujoco_env

    def window(recompute: bool):
        env = make_mujoco_env("HalfCheetah-v5", num_envs=4, seed=0, dtype=torch.float64,
                              recompute_in_backward=recompute)
        torch.manual_seed(0)
        net = torch.nn.Linear(env.observation_dim, env.action_dim).double()
        td0 = env.rollout(15)[:, -1]["next"].exclude("reward")  # touching the floor
        mass = td0["params", "body_mass"].clone().requires_grad_(True)
        td0["params", "body_mass"] = mass
        storages = {}

        def pack(tensor):
            storage = tensor.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
            return tensor

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
            out = env.rollout(3, lambda td: td.set("action", torch.tanh(net(td["observation"]))),
                              auto_reset=False, tensordict=td0)
        grads = torch.autograd.grad(out["next", "reward"].sum(), [*net.parameters(), mass])
        return out.detach(), grads, sum(storages.values())

    (out, grads, saved), (out_r, grads_r, saved_r) = window(False), window(True)
    torch.testing.assert_close(out_r["next", "observation"], out["next", "observation"], rtol=0, atol=0)
    assert grads[-1].abs().sum() > 0
    for got, want in zip(grads_r, grads):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert saved_r < saved / 10, (saved_r, saved)


def test_recompute_in_backward_under_compile_physics_recomputes_the_compiled_step():
    """With ``compile_physics`` the forward runs the compiled physics step: the backward's
    recomputation takes the same step (not the eager one), and the gradient is eager's."""
    from torchrl_diffenvs import compile_physics, eager_physics
    from torchrl_diffenvs import make_env as make_mujoco_env
    from torchrl_diffenvs.envs.rollout import compile_report

    grads = []
    for compiled in (False, True):
        # Euler: one stage to trace with grad, where the file's RK4 unrolls four (about 4x the compile)
        env = make_mujoco_env("InvertedPendulum-v5", num_envs=2, seed=0, dtype=torch.float64,
                              recompute_in_backward=True, integrator="euler")
        torch.manual_seed(0)
        net = torch.nn.Linear(env.observation_dim, env.action_dim).double()
        if compiled:
            compile_physics(env, steps_per_chunk=2, backend="aot_eager")
        out = env.rollout(2, lambda td: td.set("action", torch.tanh(net(td["observation"]))), auto_reset=False,
                          tensordict=env.reset())
        grads.append(torch.autograd.grad(out["next", "reward"].sum() + out["next", "observation"].sum(),
                                         list(net.parameters())))
        if compiled:
            report = compile_report(env)
            assert report["eager_reason"] is None and any("with grad" in k for k in report["first_call_seconds"]), report
            eager_physics(env)
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
