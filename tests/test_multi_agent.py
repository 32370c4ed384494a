"""The multi-agent layout and the multi_swimmer task, against independent references.

* one agent is the single swimmer, bit for bit (same seed, same actions);
* rewards and observations of a hand-placed pond equal hand-computed values;
* gradients: ``gradcheck`` of one step w.r.t. every agent's action, the state and the
  parameters (float64), a 15-step ``env.rollout`` against central finite differences, the
  coupling between agents (a fish's reward depends on another fish's earlier actions through
  the collision factor), and exactly zero across auto-resets;
* TorchRL's layout (``check_env_specs``, ``("agents", ...)`` keys, shared done flags) and clear
  errors for bad input, with a NaN action confined to its env.
"""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs, step_mdp

from _env_helpers import F64, multi_agent_envs

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs import is_multi_agent

EPS = 1e-6


def make(num_envs=2, num_agents=3, **kwargs):
    kwargs.setdefault("dtype", F64)
    kwargs.setdefault("seed", 0)
    return make_env("multi_swimmer", num_envs=num_envs, num_agents=num_agents, **kwargs)


def actions(n, t, a, seed=0, scale=0.8):
    gen = torch.Generator().manual_seed(seed)
    return scale * (torch.rand(n, t, a, 2, generator=gen, dtype=F64) * 2 - 1)


def test_registered_as_multi_agent_with_torchrl_layout():
    assert multi_agent_envs() == ["multi_swimmer"]
    env = make(num_envs=4, num_agents=3, dtype=torch.float32)
    check_env_specs(env)
    assert is_multi_agent(env) and not is_multi_agent(make_env("swimmer"))
    assert env.action_key == ("agents", "action") and env.reward_key == ("agents", "reward")
    assert sorted(env.done_keys) == ["done", "terminated", "truncated"]  # one shared episode
    td = env.rollout(3)
    assert td["agents"].batch_size == (4, 3, 3)
    assert td["agents", "observation"].shape == (4, 3, 3, 10 + 6 + 8)
    assert td["next", "agents", "reward"].shape == (4, 3, 3, 1)
    assert td["next", "done"].shape == (4, 3, 1)


def test_one_agent_is_the_swimmer_bit_for_bit():
    single = make_env("swimmer", num_envs=5, seed=7, dtype=F64)
    multi = make(num_envs=5, num_agents=1, seed=7)
    a = actions(5, 30, 1)
    ts, tm = single.reset(), multi.reset()
    torch.testing.assert_close(tm["agents", "observation"][:, 0], ts["observation"], rtol=0, atol=0)
    for t in range(30):
        ts = single.step(ts.set("action", a[:, t, 0]))
        tm = multi.step(tm.set(("agents", "action"), a[:, t]))
        torch.testing.assert_close(tm["next", "agents", "reward"][:, 0], ts["next", "reward"], rtol=0, atol=0)
        torch.testing.assert_close(tm["next", "agents", "observation"][:, 0], ts["next", "observation"], rtol=0, atol=0)
        ts, tm = step_mdp(ts), step_mdp(tm)


def placed_pond(env):
    """Two fish, one urchin, at hand-chosen places (env of 1 pond)."""
    state = {
        "pos": torch.tensor([[[0.0, 0.0], [0.3, 0.4]]], dtype=F64),
        "vel": torch.tensor([[[0.1, 0.0], [0.0, -0.2]]], dtype=F64),
        "goal": torch.tensor([[[1.0, 1.0], [-0.5, 0.5]]], dtype=F64),
        "urchins": torch.tensor([[[0.5, -0.5]]], dtype=F64),
    }
    return env.reset(TensorDict({"state": state}, batch_size=[1]), set_state=True)


def test_reward_and_observation_equal_hand_computed_values():
    env = make(num_envs=1, num_agents=2, num_urchins=1)
    td = placed_pond(env)
    a = torch.tensor([[[1.0, -1.0], [0.5, 0.5]]], dtype=F64)
    out = env.step(td.set(("agents", "action"), a))["next"]
    dt = 0.05
    # semi-implicit Euler, by hand
    v0, v1 = (0.1 + dt * 1.0, 0.0 - dt * 1.0), (0.0 + dt * 0.5, -0.2 + dt * 0.5)
    p0, p1 = (dt * v0[0], dt * v0[1]), (0.3 + dt * v1[0], 0.4 + dt * v1[1])

    def reward(p, g, other):
        goal = math.exp(-0.5 * ((p[0] - g[0]) ** 2 + (p[1] - g[1]) ** 2))
        urchin = 1 - math.exp(-30 * ((p[0] - 0.5) ** 2 + (p[1] + 0.5) ** 2))
        fish = 1 - math.exp(-30 * ((p[0] - other[0]) ** 2 + (p[1] - other[1]) ** 2))
        return goal * urchin * fish

    expected = torch.tensor([reward(p0, (1, 1), p1), reward(p1, (-0.5, 0.5), p0)], dtype=F64)
    torch.testing.assert_close(out["agents", "reward"][0, :, 0], expected, rtol=1e-12, atol=1e-12)
    # observation of fish 0 and fish 1: urchins, p, v, goal, others' relative p, others' v
    obs0 = [0.5, -0.5, *p0, *v0, 1, 1, p1[0] - p0[0], p1[1] - p0[1], *v1]
    obs1 = [0.5, -0.5, *p1, *v1, -0.5, 0.5, p0[0] - p1[0], p0[1] - p1[1], *v0]
    torch.testing.assert_close(out["agents", "observation"][0], torch.tensor([obs0, obs1], dtype=F64),
                               rtol=1e-12, atol=1e-12)


def test_observe_urchins_false_hides_them():
    env = make(num_agents=2, observe_urchins=False)
    assert env.observation_dim == 6 + 4
    full = make(num_agents=2)
    torch.testing.assert_close(env.reset()["agents", "observation"], full.reset()["agents", "observation"][..., 10:])


def test_start_states_keep_clear_of_each_other():
    env = make(num_envs=256, num_agents=4, clearance=0.25)
    state = env.reset()["state"]
    pos, goal, urchins = state["pos"], state["goal"], state["urchins"]
    fish_gap = (pos.unsqueeze(-2) - pos.unsqueeze(-3)).norm(dim=-1) + torch.eye(4, dtype=F64) * 10
    assert fish_gap.min() >= 0.25
    anchors = torch.cat([pos, goal], dim=1)
    assert (urchins.unsqueeze(-2) - anchors.unsqueeze(-3)).norm(dim=-1).min() >= 0.25
    # the draws come from the env's seed
    torch.testing.assert_close(make(num_envs=256, num_agents=4).reset()["state", "pos"], pos, rtol=0, atol=0)


# ---------------------------------------------------------------------------- gradients
def one_step_fn(env, td0):
    state_keys, param_keys = sorted(td0["state"].keys()), sorted(td0["params"].keys())

    def step(action, *tensors):
        td = TensorDict({
            ("agents", "action"): action,
            "state": dict(zip(state_keys, tensors[: len(state_keys)])),
            "params": dict(zip(param_keys, tensors[len(state_keys):])),
            "episode_step": td0["episode_step"],
        }, batch_size=[td0.batch_size[0]])
        nxt = env.step(td)["next"]
        anchor = 0.0 * action.sum()  # gradcheck skips outputs without grad: keep every one in
        return tuple(o + anchor for o in (nxt["agents", "observation"], nxt["agents", "reward"],
                                          *(nxt["state", k] for k in state_keys)))

    return step, state_keys, param_keys


def test_one_step_gradcheck_wrt_actions_state_and_params():
    env = make(num_envs=2, num_agents=3)
    td0 = env.reset()
    step, state_keys, param_keys = one_step_fn(env, td0)
    action = actions(2, 1, 3)[:, 0].requires_grad_()
    state = [td0["state", k].clone().requires_grad_() for k in state_keys]
    params = [td0["params", k].clone().requires_grad_() for k in param_keys]
    assert torch.autograd.gradcheck(step, (action, *state, *params), eps=EPS, atol=1e-7, rtol=1e-5)
    # meaningful only if each input moves the step
    grads = torch.autograd.grad(sum(o.sum() for o in step(action, *state, *params)), (action, *state, *params))
    assert all(g.abs().sum() > 0 for g in grads)


T_FD = 15


def rollout_return(env, start, a, params=None):
    """Sum over steps and agents of the rewards of ``env.rollout`` from ``start`` with actions ``a``."""
    td = start.clone()
    if params is not None:
        td.set("params", TensorDict(params, batch_size=td.batch_size))
    step = iter(range(a.shape[1]))

    def policy(td):
        return td.set(("agents", "action"), a[:, next(step)])

    traj = env.rollout(a.shape[1], policy, tensordict=td, auto_reset=False, break_when_any_done=False)
    return traj["next", "agents", "reward"].sum((1, 2, 3))


def central_differences(f, x, eps=EPS):
    flat = x.detach().reshape(-1).clone()
    grad = torch.zeros_like(flat)
    for i in range(flat.numel()):
        plus, minus = flat.clone(), flat.clone()
        plus[i] += eps
        minus[i] -= eps
        grad[i] = (f(plus.reshape(x.shape)).sum() - f(minus.reshape(x.shape)).sum()) / (2 * eps)
    return grad.reshape(x.shape)


def test_rollout_gradients_equal_finite_differences():
    """d(return) / d(every agent's actions, start positions, max_accel and fish_sharpness) over 15 steps."""
    env = make(num_envs=2, num_agents=2, num_urchins=2, max_episode_steps=None)
    start = env.reset()
    # the fish start close together, so that the collision factor (and fish_sharpness) matters
    close = start["state", "pos"][:, :1] + torch.tensor([[0.0, 0.0], [0.15, 0.1]], dtype=F64)
    a = actions(2, T_FD, 2, scale=0.6).requires_grad_()
    pos = close.clone().requires_grad_()
    accel = start["params", "max_accel"].clone().requires_grad_()
    fish = start["params", "fish_sharpness"].clone().requires_grad_()

    def objective(a=a, pos=pos, accel=accel, fish=fish):
        td = start.clone()
        td.set(("state", "pos"), pos)
        params = dict(start["params"].items())
        params.update(max_accel=accel, fish_sharpness=fish)
        return rollout_return(env, td, a, params)

    grads = torch.autograd.grad(objective().sum(), (a, pos, accel, fish))
    for name, got, x in zip(("actions", "pos", "max_accel", "fish_sharpness"), grads, (a, pos, accel, fish)):
        want = central_differences(lambda v, name=name: objective(**{
            {"actions": "a", "pos": "pos", "max_accel": "accel", "fish_sharpness": "fish"}[name]: v}), x)
        assert want.abs().max() > 1e-6, name
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7, msg=name)


def test_a_fishs_reward_depends_on_the_other_fishs_actions():
    """Coupling: two fish close together; fish 0's reward at step 3 depends on fish 1's action at step 0."""
    env = make(num_envs=1, num_agents=2, num_urchins=1, clearance=0.0)
    start = placed_pond(env)
    start.set(("state", "pos"), torch.tensor([[[0.0, 0.0], [0.1, 0.05]]], dtype=F64))
    a = actions(1, 4, 2).requires_grad_()
    step = iter(range(4))
    traj = env.rollout(4, lambda td: td.set(("agents", "action"), a[:, next(step)]), tensordict=start,
                       auto_reset=False)
    (grad,) = torch.autograd.grad(traj["next", "agents", "reward"][0, 3, 0, 0], a)
    assert grad[0, 0, 1].abs().sum() > 1e-4  # fish 1's first action
    # and it is the collision factor that couples them: without it the gradient is exactly zero
    start.set(("params", "fish_sharpness"), torch.zeros(1, dtype=F64))
    step = iter(range(4))
    traj = env.rollout(4, lambda td: td.set(("agents", "action"), a[:, next(step)]), tensordict=start,
                       auto_reset=False)
    (grad,) = torch.autograd.grad(traj["next", "agents", "reward"][0, 3, 0, 0], a, allow_unused=True)
    assert grad is None or grad[0, :, 1].abs().max() == 0


def test_gradients_are_exactly_zero_across_resets():
    env = make(num_envs=3, num_agents=2, max_episode_steps=4)
    a = actions(3, 10, 2).requires_grad_()
    step = iter(range(10))
    traj = env.rollout(10, lambda td: td.set(("agents", "action"), a[:, next(step)]), break_when_any_done=False)
    assert traj["next", "truncated"][:, 3].all()
    late = traj["next", "agents", "reward"][:, 4:].sum() + traj["next", "agents", "observation"][:, 4:].sum()
    (grad,) = torch.autograd.grad(late, a)
    assert grad[:, :4].abs().max() == 0 and grad[:, 4:].abs().max() > 0


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("num_agents", [0, -1, 1.5, True, "2"])
def test_bad_num_agents_is_rejected(num_agents):
    with pytest.raises(ValueError, match="num_agents must be an integer >= 1"):
        make(num_agents=num_agents)


@pytest.mark.parametrize("kwargs, message", [
    ({"num_urchins": -1}, "num_urchins must be an integer >= 0"),
    ({"clearance": 1.0}, r"clearance must lie in \[0, 1\)"),
    ({"observe_urchins": "yes"}, "observe_urchins must be true or false"),
])
def test_bad_options_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make(**kwargs)


def test_wrong_action_shapes_name_the_layout():
    env = make(num_envs=2, num_agents=3)
    td = env.reset()
    with pytest.raises(ValueError, match=r"\(2, 3, 2\) \(\[num_envs, num_agents, action_dim\]\), got \(2, 3, 3\)"):
        env.step(td.clone().set(("agents", "action"), torch.zeros(2, 3, 3, dtype=F64)))
    with pytest.raises(KeyError, match=r"no \('agents', 'action'\) entry"):
        env._step(td.clone())


def test_a_nan_action_stays_in_its_env():
    env = make(num_envs=3, num_agents=2)
    td = env.reset()
    a = actions(3, 1, 2)[:, 0]
    a[1, 0, 0] = float("nan")
    out = env.step(td.set(("agents", "action"), a))["next"]
    finite = torch.isfinite(out["agents", "reward"]).reshape(3, -1).all(-1)
    assert finite.tolist() == [True, False, True]


def test_render_draws_every_fish():
    pytest.importorskip("PIL")
    env = make(num_envs=2, num_agents=4, dtype=torch.float32)
    td = env.rollout(3)
    frame = env.render(td[:, -1]["next"], size=96)
    assert frame.shape == (96, 96, 3)
    one = make(num_envs=2, num_agents=1, dtype=torch.float32)
    assert (frame != one.render(one.rollout(3)[:, -1]["next"], size=96)).any()
