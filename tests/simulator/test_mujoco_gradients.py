"""Gradients of the MuJoCo-model tasks: gradcheck of one step (contact active), 15-step rollouts
against central finite differences through contact, finite gradients at deep penetration, at rest
and at touch-down (float64)."""
import numpy as np
import pytest
import torch

from torchrl_diffenvs.envs import make_env
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)

MUJOCO_TASKS = ["InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Reacher-v5", "Swimmer-v5", "HalfCheetah-v5",
                "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "HumanoidStandup-v5", "Pusher-v5"]
CONTACT_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5"]


def height_coordinate(env) -> int:
    """The qpos (and qvel) entry that moves the whole robot up: a planar runner's rootz slide, the Ant's free z."""
    return 2 if env.model.joint_type[0] == "free" else 1


def standing_state(env, n, depth=0.0, mid_range=False):
    """Start states with the robot lowered onto the floor until its lowest contact point is ``depth`` deep.

    ``depth = 0``: exactly at touch-down; ``> 0``: penetrating. ``mid_range``: limited joints start
    in the middle of their range, away from MuJoCo's joint-limit constraint, whose force switches on
    with a jump (a discontinuity no finite difference can follow).
    """
    from torchrl_diffenvs.articulated import forward_kinematics

    state = env.initial_state(env.params, n)
    if mid_range:
        state = limits_mid_range(env, state)
    kin = forward_kinematics(env.tree, state["qpos"])
    tree = env.tree
    centre = kin.body_pos[:, tree.contact_body] + (kin.body_rot[:, tree.contact_body] @ tree.contact_local.unsqueeze(-1)).squeeze(-1)
    lowest = (centre[..., 2] - tree.contact_radius).min(dim=1).values
    qpos = state["qpos"].clone()
    z = height_coordinate(env)
    qpos[:, z] = qpos[:, z] - lowest - depth  # rootz (the free joint's z) moves the whole robot
    state["qpos"] = qpos
    return state


def limits_mid_range(env, state):
    """``state`` with every limited joint moved to the middle of its range (the Pusher's arm
    starts with two joints exactly at a range end, where the limit force has a kink)."""
    model = env.model
    qpos = state["qpos"].clone()
    for j in range(model.njnt):
        if model.limited[j] and np.isfinite(model.joint_range[j]).all() and model.joint_range[j, 1] - model.joint_range[j, 0] < 5:
            a = int(model.joint_qposadr[j])
            qpos[:, a] = float(model.joint_range[j].mean()) + 0.01 * qpos[:, a]
    return {**state, "qpos": qpos}


def step_fn(env, state_keys, param_key=None):
    """One env step as a function of (action, qpos, qvel[, param]) -> (reward, next qpos, next qvel)."""
    base_params = env.params.clone()

    def fn(action, qpos, qvel, *param):
        params = base_params.clone()
        if param_key is not None:
            params[param_key] = param[0]
        state = {"qpos": qpos, "qvel": qvel}
        for k in state_keys:
            if k not in state:
                state[k] = fixed_extras[k]
        next_state, reward, _ = env.transition(state, action, params)
        return reward, next_state["qpos"], next_state["qvel"]

    fixed_extras = {}
    return fn, fixed_extras


# HumanoidStandup's model is the Humanoid's, lying down: its gradcheck adds time, not coverage
@pytest.mark.parametrize("name", [t for t in MUJOCO_TASKS if t != "HumanoidStandup-v5"])
def test_gradcheck_one_step(name):
    # many contacts (the Ant, the Humanoid) or golden-section searches (the Pusher's capsule-cylinder
    # pairs): the slowest, one env; the others check with two envs that no gradient crosses envs
    n = 1 if name in ("Ant-v5", "Humanoid-v5", "HumanoidStandup-v5", "Pusher-v5") else 2
    env = make_env(name, num_envs=n, dtype=torch.float64, seed=0)
    # contact active; joints mid-range: a limit's active set (which rows push, jointly solved) has
    # kinks in the state (as MuJoCo's), see test_coupled_joint_limits_gradcheck for the limits
    state = standing_state(env, n, depth=0.01, mid_range=True) if name in CONTACT_TASKS else \
        limits_mid_range(env, env.initial_state(env.params, n)) if name == "Pusher-v5" else env.initial_state(env.params, n)
    fn, extras = step_fn(env, list(state.keys()), param_key="body_mass")
    extras.update({k: v for k, v in state.items() if k not in ("qpos", "qvel")})
    action = (0.3 * torch.randn(n, env.action_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))
    inputs = (action.requires_grad_(), state["qpos"].clone().requires_grad_(), state["qvel"].clone().requires_grad_(),
              env.params["body_mass"].clone().requires_grad_())
    # the Humanoid (78 inputs, 48 outputs): gradcheck's fast mode, a random directional derivative
    # of a random projection of the outputs against its finite difference (the full Jacobian: 40 s)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=name == "Humanoid-v5")


def rollout_return(env, state, actions, params):
    total = 0.0
    for t in range(actions.shape[1]):
        state, reward, _ = env.transition(state, actions[:, t], params)
        total = total + reward.sum()
    return total


# the Humanoid's free body and capsule feet are the Ant's and the runners' cases, at 3x their cost;
# Walker2d's feet and self-contacts are Hopper's, twice
@pytest.mark.parametrize("name", [t for t in CONTACT_TASKS if t not in ("Humanoid-v5", "Walker2d-v5")])
def test_15_step_rollout_matches_finite_differences_through_contact(name):
    """Directional derivatives of a 15-step return w.r.t. actions, the start state and params.

    The robot starts 5 mm inside the floor and bounces: the return is stiff (directional
    derivatives up to ~1e4), hence the extrapolated differences.
    """
    env = make_env(name, num_envs=2, dtype=torch.float64, seed=0)
    state0 = standing_state(env, 2, depth=0.005, mid_range=True)
    g = torch.Generator().manual_seed(1)
    actions = 0.5 * torch.randn(2, 15, env.action_dim, dtype=torch.float64, generator=g)
    params0 = env.params.clone()

    def total(actions, qpos, qvel, stiffness, friction):
        params = params0.clone()
        params["contact_stiffness"] = stiffness
        params["contact_friction"] = friction
        return rollout_return(env, {**state0, "qpos": qpos, "qvel": qvel}, actions, params)

    inputs = [actions, state0["qpos"], state0["qvel"], params0["contact_stiffness"], params0["contact_friction"]]
    inputs = [x.clone().requires_grad_() for x in inputs]
    value = total(*inputs)
    grads = torch.autograd.grad(value, inputs)
    assert all(torch.isfinite(gr).all() for gr in grads)
    for i, x in enumerate(inputs):
        direction = torch.randn(x.shape, dtype=torch.float64, generator=g)
        direction = direction / direction.norm() * (1.0 if i != 3 else 100.0)
        with torch.no_grad():  # Richardson-extrapolated central differences: error O(eps^4)
            def central(eps):
                plus = [y + (eps * direction if j == i else 0) for j, y in enumerate(inputs)]
                minus = [y - (eps * direction if j == i else 0) for j, y in enumerate(inputs)]
                return (total(*plus) - total(*minus)) / (2 * eps)

            fd = (4 * central(5e-7) - central(1e-6)) / 3
        analytic = (grads[i] * direction).sum()
        assert analytic.item() == pytest.approx(fd.item(), rel=1e-4, abs=1e-6), f"input {i}"


@pytest.mark.parametrize("name", CONTACT_TASKS)
@pytest.mark.parametrize("depth", [-0.001, 0.0, 0.05, 0.5])
def test_gradients_finite_at_touchdown_rest_and_deep_penetration(name, depth):
    """Above the floor, at touch-down, resting in contact, and half a metre inside the floor."""
    env = make_env(name, num_envs=3, dtype=torch.float32, seed=0)
    state = standing_state(env, 3, depth=depth)
    state["qvel"] = torch.zeros_like(state["qvel"])
    z = height_coordinate(env)
    state["qvel"][:, z] = -1.0  # moving into the floor
    action = torch.zeros(3, env.action_dim, requires_grad=True)
    qpos = state["qpos"].clone().requires_grad_()
    next_state, reward, _ = env.transition({**state, "qpos": qpos, "qvel": state["qvel"]}, action, env.params)
    (reward.sum() + next_state["qpos"].sum() + next_state["qvel"].sum()).backward()
    assert torch.isfinite(next_state["qvel"]).all()
    assert torch.isfinite(action.grad).all() and torch.isfinite(qpos.grad).all()
    if depth > 0:  # the floor pushes back: the torso accelerates upwards
        assert (next_state["qvel"][:, z] > state["qvel"][:, z]).all()


@pytest.mark.parametrize("name", CONTACT_TASKS)
def test_long_random_rollouts_stay_finite(name):
    """Random actions in float32 never produce NaN: 200 HalfCheetah steps (it never resets), 150 steps
    of Hopper and Walker2d (they fall and reset), 80 of the Ant (20 force evaluations per step) and
    of the Humanoid (falls and resets). The stress benchmark runs 1000 steps of harder actions."""
    env = make_env(name, num_envs=16, seed=0, max_episode_steps=1000)
    with torch.no_grad():
        td = env.rollout({"HalfCheetah-v5": 200, "Ant-v5": 80, "Humanoid-v5": 80}.get(name, 150),
                         break_when_any_done=False)
    assert torch.isfinite(td["next", "observation"]).all()
    assert torch.isfinite(td["next", "reward"]).all()
    assert td["next", "done"].any() == (name != "HalfCheetah-v5")  # the others fall and reset


def test_gradient_is_zero_across_an_auto_reset():
    """Hopper with random actions falls and resets: rewards after the reset do not depend on earlier actions."""
    env = make_env("Hopper-v5", num_envs=4, dtype=torch.float64, seed=0, params={"healthy_angle_high": 0.02,
                                                                                    "healthy_angle_low": -0.02})
    g = torch.Generator().manual_seed(0)
    actions = torch.randn(4, 40, env.action_dim, dtype=torch.float64, generator=g).requires_grad_()
    td = env.rollout(40, policy=_OpenLoop(actions), break_when_any_done=False)
    done = td["next", "done"][..., 0]
    env_i, t_done = [int(v) for v in done.nonzero()[0]]
    assert t_done < 38
    later = td["next", "reward"][env_i, t_done + 1:].sum()
    (grad,) = torch.autograd.grad(later, actions)
    assert grad[env_i, : t_done + 1].abs().max() == 0
    assert grad[env_i, t_done + 1:].abs().max() > 0


class _OpenLoop(torch.nn.Module):
    def __init__(self, actions):
        super().__init__()
        self.actions, self.t = actions, 0

    def forward(self, td):
        td["action"] = self.actions[:, self.t]
        self.t += 1
        return td


def test_coupled_joint_limits_gradcheck():
    """Swimmer-v5 with both motor joints pushed past their limits at once (two rows solved jointly,
    each pushing): one step's gradient w.r.t. the state, the action and the masses."""
    from torchrl_diffenvs.articulated.limits import _complementary_forces

    env = make_env("Swimmer-v5", num_envs=2, dtype=torch.float64, seed=0)
    state = env.initial_state(env.params, 2)
    qpos = state["qpos"].clone()
    qpos[:, 3:] = torch.tensor([[1.76, 1.77], [-1.77, -1.76]], dtype=torch.float64)  # past +-100 degrees
    qvel = state["qvel"].clone()
    qvel[:, 3:] = torch.tensor([[1.0, 2.0], [-2.0, -1.0]], dtype=torch.float64)  # pressing on
    fn, _ = step_fn(env, ["qpos", "qvel"], param_key="body_mass")
    action = torch.tensor([[0.5, 0.8], [-0.6, -0.9]], dtype=torch.float64)
    calls = []
    import torchrl_diffenvs.articulated.limits as dynamics  # the module whose limit_force calls it

    def spy(offset, allowed, diagonal, matrix_of):
        force = _complementary_forces(offset, allowed, diagonal, matrix_of)
        calls.append(((force > 1.0).sum(-1) == 2).all().item())
        return force

    dynamics._complementary_forces, original = spy, dynamics._complementary_forces
    try:
        inputs = (action.requires_grad_(), qpos.requires_grad_(), qvel.requires_grad_(),
                  env.params["body_mass"].clone().requires_grad_())
        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)
    finally:
        dynamics._complementary_forces = original
    assert calls and all(calls)  # every physics step had both limits pushing


@pytest.mark.parametrize("name", ["HalfCheetah-v5", "Ant-v5"])
def test_contact_damping_matrix_is_built_from_the_point_jacobians(name):
    """The implicit Euler's contact damping ``C`` equals ``sum_p J_p^T (a n n^T + b (I - n n^T)) J_p``
    with each contact point's velocity Jacobian ``J_p`` taken by autograd through the forward
    kinematics (of the position reached by moving with qvel ``v`` for unit time, at ``v = 0``; the
    Ant's free joint turns in 3D), ``a`` the normal damping while pushing, ``b = mu f_n / slip``;
    C is symmetric positive semi-definite."""
    from torchrl_diffenvs.articulated.contact import _contact_points_and_forces
    from torchrl_diffenvs.articulated.dynamics import contact_force, forward_kinematics, integrate_position

    env = make_env(name, num_envs=3, dtype=torch.float64, seed=0)
    tree, params = env.tree, env.params
    state = standing_state(env, 3, depth=0.01, mid_range=True)
    qpos = state["qpos"]
    qvel = torch.randn(state["qvel"].shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    kin = forward_kinematics(tree, qpos)
    _, damping = contact_force(tree, kin, qvel, params, with_damping=True)
    c = _contact_points_and_forces(tree, kin, qvel, params)

    # each force acts at the sphere's lowest point: the body point there, fixed in its body frame
    rot0 = kin.body_rot[:, tree.contact_body]
    lowest = tree.contact_local - (rot0.transpose(-1, -2) @ (tree.contact_radius.unsqueeze(-1) * c.normal)
                                   .unsqueeze(-1)).squeeze(-1)

    def points(q):
        k = forward_kinematics(tree, q)
        rot = k.body_rot[:, tree.contact_body]
        return k.body_pos[:, tree.contact_body] + (rot @ lowest.unsqueeze(-1)).squeeze(-1)

    torch.testing.assert_close(points(qpos), c.point)
    move = lambda v: points(integrate_position(tree, qpos, v, 1.0)).sum(0)  # noqa: E731  (envs independent)
    jac = torch.autograd.functional.jacobian(move, torch.zeros_like(qvel)).permute(2, 0, 1, 3)  # [N, P, 3, nv]
    n = c.normal  # [P, 3]
    nn = n.unsqueeze(-1) * n.unsqueeze(-2)
    a = c.damping * c.touching * (c.normal_force > 0)
    b = c.mu * c.normal_force / c.slip
    rate = a[..., None, None] * nn + b[..., None, None] * (torch.eye(3, dtype=torch.float64) - nn)
    expected = (jac.transpose(-1, -2) @ rate @ jac).sum(1)
    assert (c.normal_force > 0).any() and expected.abs().max() > 1.0
    torch.testing.assert_close(damping, expected, rtol=1e-10, atol=1e-9)
    assert torch.linalg.eigvalsh(damping).min() > -1e-9


def hand_soft_healthy(qpos, qvel, z_low, angle_low, angle_high, width, z_high=None, state_bound=None):
    """The surrogate by hand: a product of logistic functions of each finite bound's margin."""
    s = lambda m: 1.0 / (1.0 + torch.exp(-m / width))  # noqa: E731
    out = s(qpos[:, 1] - z_low) * s(qpos[:, 2] - angle_low) * s(angle_high - qpos[:, 2])
    if z_high is not None:
        out = out * s(z_high - qpos[:, 1])
    if state_bound is not None:
        rest = torch.cat([qpos, qvel], -1)[:, 2:]
        out = out * (s(rest + state_bound) * s(state_bound - rest)).prod(-1)
    return out


@pytest.mark.parametrize("name,scale", [("Hopper-v5", 1.0), ("Walker2d-v5", 30.0)])
def test_healthy_gradient_width_keeps_rewards_and_gives_the_surrogate_gradient(name, scale):
    width = 0.05
    exact = make_env(name, num_envs=6, dtype=torch.float64, seed=0)
    smooth = make_env(name, num_envs=6, dtype=torch.float64, seed=0, healthy_gradient_width=width,
                      healthy_gradient_scale=scale)
    params = exact.params
    state = exact.initial_state(params, 6)
    # torso heights and angles on both sides of each healthy bound, within a few widths of it
    z_low, a_high = float(params["healthy_z_low"][0]), float(params["healthy_angle_high"][0])
    qpos = state["qpos"].clone()
    qpos[:, 1] = z_low + torch.tensor([0.3, 0.02, -0.01, 0.05, 0.2, 0.04], dtype=torch.float64)
    qpos[:, 2] = a_high + torch.tensor([-0.5, -0.03, -0.1, 0.01, -0.02, -a_high], dtype=torch.float64)
    action = 0.3 * torch.ones(6, exact.action_dim, dtype=torch.float64)

    def reward_of(env, qpos):
        return env.transition({"qpos": qpos, "qvel": state["qvel"]}, action, params)[1]

    q_exact = qpos.clone().requires_grad_()
    q_smooth = qpos.clone().requires_grad_()
    r_exact, r_smooth = reward_of(exact, q_exact), reward_of(smooth, q_smooth)
    torch.testing.assert_close(r_smooth, r_exact, rtol=0, atol=0)  # values stay Gymnasium's
    g_exact, = torch.autograd.grad(r_exact.sum(), q_exact)
    g_smooth, = torch.autograd.grad(r_smooth.sum(), q_smooth)

    # the difference is the healthy bonus's surrogate gradient at the *next* state
    next_state, _, _ = exact.transition({"qpos": q_exact, "qvel": state["qvel"]}, action, params)
    hand = hand_soft_healthy(
        next_state["qpos"], next_state["qvel"], z_low, float(params["healthy_angle_low"][0]), a_high, width,
        z_high=float(params["healthy_z_high"][0]) if name == "Walker2d-v5" else None,
        state_bound=100.0 if name == "Hopper-v5" else None)
    g_hand, = torch.autograd.grad(scale * float(params["healthy_reward"][0]) * hand.sum(), q_exact)
    torch.testing.assert_close(g_smooth - g_exact, g_hand, rtol=1e-7, atol=1e-10)
    assert (g_hand[:, 1:3].abs() > 1e-3).any()  # the envs near a bound do feel it
    torch.testing.assert_close(smooth.soft_healthy(next_state["qpos"], next_state["qvel"], params), hand)


def test_ant_healthy_gradient_width_keeps_rewards_and_gives_the_surrogate_gradient():
    """The Ant's bonus (torso height in [0.2, 1]): same rewards; the gradient gains the surrogate's."""
    width, scale = 0.05, 10.0
    exact = make_env("Ant-v5", num_envs=4, dtype=torch.float64, seed=0)
    smooth = make_env("Ant-v5", num_envs=4, dtype=torch.float64, seed=0, healthy_gradient_width=width,
                      healthy_gradient_scale=scale)
    params = exact.params
    state = exact.initial_state(params, 4)
    qpos = state["qpos"].clone()
    qpos[:, 2] = torch.tensor([0.22, 0.5, 0.98, 1.01], dtype=torch.float64)  # near each bound, and between
    qvel = torch.zeros_like(state["qvel"])
    action = 0.3 * torch.ones(4, exact.action_dim, dtype=torch.float64)

    def reward_of(env, q):
        return env.transition({**state, "qpos": q, "qvel": qvel}, action, params)[1]

    q_exact, q_smooth = qpos.clone().requires_grad_(), qpos.clone().requires_grad_()
    r_exact, r_smooth = reward_of(exact, q_exact), reward_of(smooth, q_smooth)
    torch.testing.assert_close(r_smooth, r_exact, rtol=0, atol=0)
    g_exact, = torch.autograd.grad(r_exact.sum(), q_exact)
    g_smooth, = torch.autograd.grad(r_smooth.sum(), q_smooth)
    next_qpos = exact.transition({**state, "qpos": q_exact, "qvel": qvel}, action, params)[0]["qpos"]
    z = next_qpos[:, 2]
    hand = torch.sigmoid((z - 0.2) / width) * torch.sigmoid((1.0 - z) / width)
    g_hand, = torch.autograd.grad(scale * hand.sum(), q_exact)
    torch.testing.assert_close(g_smooth - g_exact, g_hand, rtol=1e-7, atol=1e-10)
    assert (g_hand[[0, 2, 3]].abs().amax(-1) > 0.1).all()  # the envs near a bound do feel it


@pytest.mark.parametrize("option", ["healthy_gradient_width", "healthy_gradient_scale"])
@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf"), True, "0.1"])
def test_healthy_gradient_options_reject_bad_values(option, value):
    with pytest.raises(ValueError, match=f"{option} must be a finite number >= 0"):
        make_env("Hopper-v5", num_envs=1, **{option: value})


def test_healthy_gradient_width_needs_a_healthy_bonus():
    with pytest.raises(ValueError, match="HalfCheetah-v5 has none"):
        make_env("HalfCheetah-v5", num_envs=1, healthy_gradient_width=0.1)
