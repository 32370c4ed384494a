"""The articulated simulator stays finite and accurate where learned policies take it.

Learned runners travel far along the track. With every spatial quantity taken about the world
origin, a HalfCheetah 100 m down the track carried lever arms of 100 m into its inertias and
contact moments; float32 cancellation then made ``M + h C`` (mass matrix plus the implicit
contact damping) indefinite and velocities grew to 1e21 within a few steps. The references here
are the same computation in float64 at the origin (the dynamics do not depend on where the robot
is) and MuJoCo-independent hand checks.
"""
from __future__ import annotations

import pytest
import torch

from torchrl_diffenvs import make_env
from torchrl_diffenvs.articulated import forward_kinematics
from torchrl_diffenvs.articulated.dynamics import accelerations, dof_invweight0, step

CONTACT_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5"]


def touching_states(env, n: int, seed: int = 0, depth: float = 0.005):
    """``n`` states near ``qpos0`` (joints mid-range, random velocities) lowered until the lowest
    contact point is ``depth`` into the floor; float64."""
    tree, model = env.tree, env.model
    gen = torch.Generator().manual_seed(seed)
    qpos = tree.qpos0.to(torch.float64).expand(n, -1).clone()
    for j in range(model.njnt):
        if model.limited[j]:
            a = int(model.joint_qposadr[j])
            low, high = (float(x) for x in model.joint_range[j])
            qpos[:, a] = low + (high - low) * (0.3 + 0.4 * torch.rand(n, generator=gen, dtype=torch.float64))
    qvel = 2.0 * torch.randn(n, tree.nv, generator=gen, dtype=torch.float64)
    kin = forward_kinematics(tree, qpos)
    centre = kin.body_pos[:, tree.contact_body] + (
        kin.body_rot[:, tree.contact_body] @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    lowest = (centre[..., 2] - tree.contact_radius).min(dim=1).values
    z = 2 if env.model.joint_type[0] == "free" else 1  # the free joint's z, or the planar runners' rootz
    qpos[:, z] -= lowest + depth
    return qpos, qvel


def float_params(env, dtype):
    return {k: v.to(dtype) for k, v in env.params.items()}


@pytest.mark.parametrize("name", CONTACT_TASKS)
@pytest.mark.parametrize("distance", [100.0, 1000.0])
def test_float32_accelerations_do_not_depend_on_how_far_the_robot_has_travelled(name, distance):
    """qacc (contact, joint limits, implicit contact damping) of float32 states ``distance`` metres
    down the track equals float64's at the origin; before the spatial quantities moved to a
    reference point on the robot, float32 lost every digit at 1 km."""
    env32 = make_env(name, num_envs=8, seed=0)
    env64 = make_env(name, num_envs=8, seed=0, dtype=torch.float64)
    qpos, qvel = touching_states(env64, 8)
    ctrl = torch.rand(8, env64.tree.ctrl_low.shape[-1], generator=torch.Generator().manual_seed(1),
                      dtype=torch.float64) * 2 - 1
    dt = env64.model.timestep
    p64 = float_params(env64, torch.float64)
    expected = accelerations(env64.tree, qpos, qvel, ctrl, p64, implicit_damping_dt=dt)
    far = qpos.clone()
    far[:, 0] += distance  # rootx, or the free joint's x
    p32 = float_params(env32, torch.float32)
    got = accelerations(env32.tree, far.float(), qvel.float(), ctrl.float(), p32, implicit_damping_dt=dt)
    scale = expected.abs().amax(dim=-1, keepdim=True).clamp(min=1.0)
    assert expected.abs().max() > 10.0  # the floor pushes
    assert ((got.double() - expected).abs() / scale).max() < 2e-3


def test_the_diverging_halfcheetah_stays_with_float64():
    """The state a learned policy reached 101 m down the track and the four actions that drove its
    velocities to 830, 3530 and NaN in float32: float32 now follows float64's trajectory."""
    qpos = [101.22035217285156, -0.10095739364624023, 0.014691382646560669, 0.42356187105178833,
            -0.29433783888816833, 0.6488616466522217, 0.7463669776916504, -0.1198229119181633, -0.2261779010295868]
    qvel = [1.471632719039917, -0.5514013171195984, 1.2782227993011475, -8.734984397888184, 6.162042617797852,
            2.468674659729004, -1.5564022064208984, -9.706231117248535, -1.0812969207763672]
    actions = [[-1.0, -0.17994, -0.23419, 1.0, -0.85488, 0.38761], [-0.11856, -0.03990, 0.33904, 1.0, 0.50671, 0.76869],
               [0.31928, -0.78885, 0.81182, 1.0, 0.61840, 0.34189], [1.0, -1.0, 1.0, 0.05362, -0.47622, -1.0]]
    trajectories = {}
    for dtype in (torch.float32, torch.float64):
        env = make_env("HalfCheetah-v5", num_envs=1, seed=0, dtype=dtype)
        params = float_params(env, dtype)
        w0 = dof_invweight0(env.tree, params)
        q, v = torch.tensor([qpos], dtype=dtype), torch.tensor([qvel], dtype=dtype)
        speeds = []
        for a in actions:
            for _ in range(env.frame_skip):
                result = step(env.tree, q, v, torch.tensor([a], dtype=dtype), params, env.model.timestep, "euler", w0)
                q, v = result.qpos, result.qvel
            speeds.append(v.abs().max().item())
        trajectories[dtype] = (q, v, speeds)
    q32, v32, speeds32 = trajectories[torch.float32]
    q64, v64, speeds64 = trajectories[torch.float64]
    assert max(speeds64) < 20.0 and max(speeds32) < 20.0
    torch.testing.assert_close(v32.double(), v64, atol=0.05, rtol=0.01)
    torch.testing.assert_close(q32.double(), q64, atol=1e-3, rtol=1e-5)


@pytest.mark.parametrize("name", CONTACT_TASKS)
def test_a_singular_env_does_not_raise_or_touch_the_others(name):
    """An env whose mass matrix is singular (massless bodies: torch.linalg.inv raised on it) gives
    meaningless values for itself only: nothing raises, and the other envs' values are
    bit-identical to a batch without it. (Which values it gets depends on the LAPACK build:
    non-finite, huge, or finite and wrong, as on some AMD CPUs.)"""
    env = make_env(name, num_envs=4, seed=0, dtype=torch.float64)
    qpos, qvel = touching_states(env, 4)
    ctrl = torch.zeros(4, env.tree.ctrl_low.shape[-1], dtype=torch.float64)
    params = float_params(env, torch.float64)
    broken = dict(params)
    broken["body_mass"] = params["body_mass"].clone()
    broken["body_inertia"] = params["body_inertia"].clone()
    broken["armature"] = params["armature"].clone()
    broken["body_mass"][2] = 0.0
    broken["body_inertia"][2] = 0.0
    broken["armature"][2] = 0.0
    w0 = dof_invweight0(env.tree, params)
    healthy = step(env.tree, qpos, qvel, ctrl, params, env.model.timestep, env.model.integrator, w0)
    mixed = step(env.tree, qpos, qvel, ctrl, broken, env.model.timestep, env.model.integrator, w0)
    assert not torch.equal(mixed.qvel[2], healthy.qvel[2])  # the massless bodies did change env 2
    keep = [0, 1, 3]
    assert torch.equal(mixed.qvel[keep], healthy.qvel[keep]) and torch.equal(mixed.qpos[keep], healthy.qpos[keep])


def test_the_spinning_ant_that_euler_blew_up_stays_bounded_with_the_implicit_integrator():
    """An Ant thrown 1.9 m up by resonant full-range square waves (benchmarks/stress.py), its torso
    spinning at 30 rad/s, and the 25 actions that followed: semi-implicit Euler, whose Coriolis and
    centrifugal forces are explicit, pumps energy into the spin until the velocities overflow (in
    float64 too: not rounding); MuJoCo's ``implicit`` integrator, which treats those forces'
    velocity derivative implicitly, keeps them where RK4 keeps them (below 60)."""
    qpos = [-2.0663311, 16.86693, 1.9135766, 0.4845021, -0.1109707, -0.1489101, 0.8548503, -0.1655935, 1.2516888,
            0.2655221, -0.7576232, 0.5347204, -1.0503043, 0.2834452, 0.3754466]
    qvel = [-3.996383, 7.009945, 7.816287, -11.043701, 27.222462, -9.238519, 10.396386, -0.908741, -9.36648,
            -8.19788, -0.279348, 8.212225, -8.762749, -14.933318]
    signs = ("-++---++ ++--++-+ ++-+++-- +-+++++- --++--++ " * 5).split()
    actions = torch.tensor([[1.0 if c == "+" else -1.0 for c in row] for row in signs], dtype=torch.float64)
    peak = {}
    for integrator in ("euler", "implicit", "rk4"):
        env = make_env("Ant-v5", num_envs=1, seed=0, dtype=torch.float64, integrator=integrator)
        params = float_params(env, torch.float64)
        w0 = dof_invweight0(env.tree, params)
        q, v = torch.tensor([qpos], dtype=torch.float64), torch.tensor([qvel], dtype=torch.float64)
        q[:, 3:7] /= q[:, 3:7].norm()
        speeds = []
        for a in actions:
            for _ in range(env.frame_skip):
                result = step(env.tree, q, v, a[None], params, env.model.timestep, integrator, w0)
                q, v = result.qpos, result.qvel
            speeds.append(v.abs().max().item() if torch.isfinite(v).all() else float("inf"))
        peak[integrator] = max(speeds)
    assert peak["euler"] > 1e6, peak  # the instability this integrator removes
    assert peak["implicit"] < 60.0 and peak["rk4"] < 60.0, peak
