"""Behaviour of every env against independent references.

* physics: one step of each Ivy task against its equations written out again here in plain
  Python ``math`` (from the task table of the design notes), for default and non-default params;
* reset distributions inside the documented ranges (and filling them);
* batching: a batch of N envs equals N single envs; per-env params only touch their env;
* seeding, truncation, input validation, non-finite and out-of-spec actions;
* task options: reacher ``num_links`` / ``goal_sampling``, swimmer ``num_urchins`` /
  ``urchin_clearance``.
"""
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from _env_helpers import (
    classic_envs,
    F64, ReplayPolicy, in_spec_actions, is_gymnasium_variant, make, obs_weights, run_steps, signal, start_td,
    use_rollout_path,
)
from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs import TwoPlayerDiffEnv, env_class, env_options

ALL_ENVS = classic_envs()
# Ivy Gym's tasks (the two-player race has its hand-computed step in test_selfplay.py)
IVY_TASKS = [n for n in ALL_ENVS if not is_gymnasium_variant(n) and not issubclass(env_class(n), TwoPlayerDiffEnv)]


# ============================================================================ hand-computed physics
# Each function maps (state, action, params) given as python floats / lists to
# (next_state, observation, reward), with the equations of the task table.
def cartpole_step(s, a, p):
    g, mc, mp, l, dt = p["g"], p["cart_mass"], p["pole_mass"], p["half_length"], p["dt"]
    force = p["max_force"] * a[0]
    m = mc + mp
    sin, cos = math.sin(s["th"]), math.cos(s["th"])
    tmp = (force + mp * l * s["thd"] ** 2 * sin) / m
    thdd = (g * sin - cos * tmp) / (l * (4.0 / 3.0 - mp * cos**2 / m))
    xdd = tmp - mp * l * thdd * cos / m
    xd = s["xd"] + dt * xdd  # semi-implicit Euler: velocities first
    thd = s["thd"] + dt * thdd
    x = s["x"] + dt * xd
    th = s["th"] + dt * thd
    reward = math.exp(-(x**2)) * (math.cos(th) + 1) / 2
    return dict(x=x, xd=xd, th=th, thd=thd), [x, xd, math.cos(th), math.sin(th), thd], reward


def pendulum_step(s, a, p):
    g, m, l, dt = p["g"], p["mass"], p["length"], p["dt"]
    thdd = 3 * g / (2 * l) * math.sin(s["th"]) + 3 / (m * l**2) * p["max_torque"] * a[0]
    thd = s["thd"] + dt * thdd
    th = s["th"] + dt * thd
    return dict(th=th, thd=thd), [math.cos(th), math.sin(th), thd], (math.cos(th) + 1) / 2


def mountaincar_step(s, a, p):
    dt = p["dt"]
    xd = s["xd"] + dt * (p["max_force"] * a[0] - p["g"] * math.cos(3 * s["x"]))
    x = s["x"] + dt * xd
    return dict(x=x, xd=xd), [x, xd], math.exp(-5 * (x - p["goal"]) ** 2)


def reacher_step(s, a, p):
    dt, ll = p["dt"], p["link_length"]
    thd = [w + dt * p["max_accel"] * u for w, u in zip(s["thd"], a)]
    th = [t + dt * w for t, w in zip(s["th"], thd)]
    tip_x = sum(ll * math.cos(t) for t in th)
    tip_y = sum(ll * math.sin(t) for t in th)
    gx, gy = s["goal"]
    reward = math.exp(-((tip_x - gx) ** 2 + (tip_y - gy) ** 2))
    obs = [math.cos(t) for t in th] + [math.sin(t) for t in th] + thd + [gx, gy]
    return dict(th=th, thd=thd, goal=[gx, gy]), obs, reward


def swimmer_step(s, a, p):
    dt = p["dt"]
    vel = [v + dt * p["max_accel"] * u for v, u in zip(s["vel"], a)]
    pos = [q + dt * v for q, v in zip(s["pos"], vel)]
    gx, gy = s["goal"]
    reward = math.exp(-0.5 * ((pos[0] - gx) ** 2 + (pos[1] - gy) ** 2))
    for ux, uy in s["urchins"]:
        reward *= 1 - math.exp(-p["urchin_sharpness"] * ((pos[0] - ux) ** 2 + (pos[1] - uy) ** 2))
    obs = [c for u in s["urchins"] for c in u] + pos + vel + [gx, gy]
    return dict(pos=pos, vel=vel, goal=[gx, gy], urchins=s["urchins"]), obs, reward


# (task, options, start state, action, non-default params)
HAND_CASES = {
    "cartpole": (cartpole_step, {}, dict(x=0.3, xd=-0.2, th=2.5, thd=0.7), [0.4],
                 dict(g=9.0, cart_mass=1.5, pole_mass=0.3, half_length=0.7, max_force=8.0, dt=0.03)),
    "pendulum": (pendulum_step, {}, dict(th=-2.0, thd=0.5), [-0.6],
                 dict(g=5.0, mass=2.0, length=0.5, max_torque=2.0, dt=0.1)),
    "mountaincar": (mountaincar_step, {}, dict(x=-0.5, xd=0.1), [0.8],
                    dict(g=9.0, max_force=2.0, goal=0.3, dt=0.04)),
    "reacher": (reacher_step, {}, dict(th=[0.4, -1.3], thd=[0.2, -0.5], goal=[0.7, -1.1]), [0.9, -0.3],
                dict(link_length=0.8, max_accel=2.0, dt=0.1)),
    "reacher-1link": (reacher_step, {"num_links": 1}, dict(th=[2.0], thd=[-0.3], goal=[0.2, 0.5]), [0.5],
                      dict(link_length=1.5, max_accel=0.5, dt=0.02)),
    "reacher-3links": (reacher_step, {"num_links": 3},
                       dict(th=[0.1, 1.2, -2.2], thd=[0.3, 0.0, -0.9], goal=[-1.0, 1.4]), [0.2, -0.7, 1.0],
                       dict(link_length=0.6, max_accel=1.5, dt=0.05)),
    "swimmer": (swimmer_step, {"num_urchins": 2},
                dict(pos=[0.1, -0.2], vel=[0.3, 0.1], goal=[0.5, 0.6], urchins=[[0.2, -0.15], [-0.7, 0.4]]),
                [0.5, -0.9], dict(max_accel=2.0, urchin_sharpness=10.0, dt=0.1)),
    "swimmer-0urchins": (swimmer_step, {"num_urchins": 0},
                         dict(pos=[-0.4, 0.9], vel=[0.0, -0.2], goal=[0.0, 0.0], urchins=[]), [1.0, 0.2],
                         dict(max_accel=0.5, urchin_sharpness=30.0, dt=0.05)),
}


def _task_of(case: str) -> str:
    return case.split("-")[0]


def test_hand_cases_cover_every_ivy_task():
    assert {_task_of(c) for c in HAND_CASES} == set(IVY_TASKS)


@pytest.mark.parametrize("use_default_params", [True, False], ids=["default-params", "custom-params"])
@pytest.mark.parametrize("case", sorted(HAND_CASES))
def test_single_step_matches_hand_computed_physics(case, use_default_params):
    """One env.step from a known state equals the task equations evaluated in plain python."""
    step_fn, options, state, action, custom = HAND_CASES[case]
    env = make(_task_of(case), 1, **options, params=None if use_default_params else custom)
    params = {k: v.item() for k, v in env.params[0].items()}
    if not use_default_params:
        assert params == pytest.approx(custom)
    expected_state, expected_obs, expected_reward = step_fn(state, action, params)

    state_t = {k: torch.tensor([v], dtype=F64) for k, v in state.items()}
    if "urchins" in state_t:  # [1, K, 2], also for K = 0
        state_t["urchins"] = state_t["urchins"].reshape(1, -1, 2)
    td = start_td(env, state_t, env.params.clone())
    td["action"] = torch.tensor([action], dtype=F64)
    nxt = env.step(td)["next"]
    close = dict(rtol=1e-12, atol=1e-12)
    for k, v in expected_state.items():
        expected = torch.tensor(v, dtype=F64)
        expected = expected.reshape(-1, 2) if k == "urchins" else expected
        torch.testing.assert_close(nxt["state", k][0], expected, **close, msg=k)
    torch.testing.assert_close(nxt["observation"][0], torch.tensor(expected_obs, dtype=F64), **close)
    torch.testing.assert_close(nxt["reward"][0, 0].item(), expected_reward, **close)
    assert not nxt["terminated"].any() and not nxt["truncated"].any()


def test_ivy_default_params_are_the_documented_constants():
    documented = {
        "cartpole": dict(g=9.8, cart_mass=1.0, pole_mass=0.1, half_length=0.5, max_force=10.0, dt=0.02),
        "pendulum": dict(g=9.8, mass=1.0, length=1.0, max_torque=1.0, dt=0.05),
        "mountaincar": dict(g=9.8, max_force=3.0, goal=0.45, dt=0.02),
        "reacher": dict(link_length=1.0, max_accel=1.0, dt=0.05),
        "swimmer": dict(max_accel=1.0, urchin_sharpness=30.0, dt=0.05),
    }
    assert set(documented) == set(IVY_TASKS)
    for name, constants in documented.items():
        env = make(name, 2)
        assert {k: v[0].item() for k, v in env.params.items()} == pytest.approx(constants), name
        assert env.max_episode_steps == 100, name  # Ivy's demos use 100-step episodes
        assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all(), name


@pytest.mark.parametrize("name", IVY_TASKS)
def test_ivy_observation_dims_and_reward_range(name):
    """Documented observation sizes; rewards lie in [0, 1] and nothing terminates."""
    dims = {"cartpole": 5, "pendulum": 3, "mountaincar": 2, "reacher": 8, "swimmer": 16}
    env = make(name, 8, seed=2)
    assert env.observation_dim == dims[name] and env.action_dim == (2 if name in ("reacher", "swimmer") else 1)
    traj = env.rollout(50, ReplayPolicy(in_spec_actions(env, 8, 50, fraction=1.0)))
    reward = traj["next", "reward"]
    assert (reward >= 0).all() and (reward <= 1).all() and reward.std() > 0
    assert not traj["next", "terminated"].any()


# ============================================================================ resets
def _uniform(lo, hi):
    return ("uniform", lo, hi)


ZERO = ("zero",)
PI = math.pi
# documented reset distribution of every state entry (per component)
RESET_RANGES = {
    "cartpole": dict(x=_uniform(-1, 1), xd=_uniform(-0.3, 0.3), th=_uniform(-PI, PI), thd=_uniform(-0.3, 0.3)),
    "pendulum": dict(th=_uniform(-PI, PI), thd=_uniform(-1, 1)),
    "mountaincar": dict(x=_uniform(-0.9, -0.2), xd=ZERO),
    "reacher": dict(th=_uniform(-PI, PI), thd=_uniform(-1, 1)),  # goal: see the goal_sampling tests
    # urchins are resampled away from start and goal: checked in test_swimmer_urchin_clearance
    "swimmer": dict(pos=_uniform(-1, 1), goal=_uniform(-1, 1), vel=ZERO),
    # the two fish start mirrored about the goal: checked in test_selfplay.py::test_specs_and_start_states
    "swimmer_race": dict(goal=_uniform(-0.5, 0.5), vel=ZERO),
    "CartPole-v1": {k: _uniform(-0.05, 0.05) for k in ("x", "xd", "th", "thd")},
    "Pendulum-v1": dict(th=_uniform(-PI, PI), thd=_uniform(-1, 1)),
    "MountainCarContinuous-v0": dict(x=_uniform(-0.6, -0.4), xd=ZERO),
}


@pytest.mark.parametrize("name", ALL_ENVS)
def test_reset_distribution_within_documented_ranges(name):
    if name not in RESET_RANGES:
        pytest.fail(f"{name} has no documented reset distribution in RESET_RANGES: add it")
    n = 4000
    state = make(name, n, seed=7).reset()["state"]
    for key, dist in RESET_RANGES[name].items():
        values = state[key].reshape(n, -1)
        if dist == ZERO:
            assert (values == 0).all(), key
            continue
        _, lo, hi = dist
        width = hi - lo
        assert values.min() >= lo and values.max() <= hi, f"{key} leaves [{lo}, {hi}]"
        # fills the range (not a narrower one) with a uniform's mean and spread
        assert values.min() < lo + 0.01 * width and values.max() > hi - 0.01 * width, key
        se = width / math.sqrt(12 * n)
        assert (values.mean(0) - (lo + hi) / 2).abs().max() < 5 * se, key
        std = values.std(0)
        torch.testing.assert_close(std, torch.full_like(std, width / math.sqrt(12)), rtol=0.05, atol=0)


def test_reset_starts_episodes_at_step_zero_not_done():
    for name in ALL_ENVS:
        td = make(name, 3).reset()
        assert (td["episode_step"] == 0).all(), name
        assert not td["done"].any() and not td["terminated"].any() and not td["truncated"].any(), name


# ============================================================================ batching
@pytest.mark.parametrize("name", ALL_ENVS)
def test_batch_equals_envs_run_one_by_one(name):
    """Env i of a batch of 4 follows the same transitions as a single env from the same start."""
    n, steps = 4, 5
    env = make(name, n, seed=1, max_episode_steps=None)
    start = env.reset()
    actions = in_spec_actions(env, n, steps, fraction=1.0, seed=2)
    batch = run_steps(env, start, actions)
    for i in range(n):
        single = make(name, 1, seed=100 + i, max_episode_steps=None)
        td = start_td(single, start["state"][i : i + 1].to_dict(), start["params"][i : i + 1].to_dict())
        torch.testing.assert_close(td["observation"], start["observation"][i : i + 1], rtol=1e-12, atol=1e-12)
        one = run_steps(single, td, actions[i : i + 1])
        state_keys = [("next", "state", k) for k in start["state"].keys()]
        for key in [("next", "observation"), ("next", "reward"), *state_keys]:
            torch.testing.assert_close(one[key][0], batch[key][i], rtol=1e-12, atol=1e-12, msg=f"env {i} {key}")
        for key in ("terminated", "truncated", "done"):
            assert torch.equal(one["next", key][0], batch["next", key][i]), (i, key)


@pytest.mark.parametrize("name", ALL_ENVS)
def test_per_env_params_change_only_their_env(name):
    """Domain randomisation: a params tensor [N] changes exactly the env whose value differs."""
    n = 3
    # a parameter that acts on every step (MountainCarContinuous-v0 has no dt)
    key = next(k for k in ("dt", "gravity") if k in make(name, 1).params.keys())
    base = make(name, n, seed=5)
    values = base.params[key].clone()
    values[1] = values[1] * 1.5
    varied = make(name, n, seed=5, params={key: values})
    assert torch.equal(varied.params[key], values)
    actions = in_spec_actions(base, n, 4, seed=3)
    a = base.rollout(4, ReplayPolicy(actions), break_when_any_done=False)
    b = varied.rollout(4, ReplayPolicy(actions), break_when_any_done=False)
    for k in [("next", "observation"), ("next", "reward")]:
        assert torch.equal(a[k][[0, 2]], b[k][[0, 2]]), k
    assert not torch.equal(a["next", "observation"][1], b["next", "observation"][1])
    assert torch.equal(b["next", "params", key][:, -1], values)


def test_reset_takes_params_from_the_tensordict_auto_reset_from_env_params():
    """Documented in DiffEnv._reset: reset(td) uses td["params"]; an auto-reset (TorchRL passes
    only the "_reset" mask) gives the reset envs env.params."""
    env = make("pendulum", 2, max_episode_steps=2)
    td = env.reset()
    td["params", "g"] = torch.tensor([5.0, 6.0], dtype=F64)
    td = env.reset(td, set_state=False)
    assert td["params", "g"].tolist() == [5.0, 6.0]
    traj = env.rollout(4, tensordict=td, auto_reset=False, break_when_any_done=False)
    assert traj["params", "g"].tolist() == [[5.0, 5.0, 9.8, 9.8], [6.0, 6.0, 9.8, 9.8]]


def test_per_env_params_survive_auto_reset():
    """Auto-resets take the env's params (env.params), so per-env values stay with their env."""
    dt = torch.tensor([0.01, 0.02, 0.04], dtype=F64)
    env = make("pendulum", 3, max_episode_steps=2, params={"dt": dt})
    traj = env.rollout(5, break_when_any_done=False)
    assert traj["next", "done"][:, 1].all()  # reset after step 2
    assert torch.equal(traj["params", "dt"], dt[:, None].expand(3, 5))


# ============================================================================ seeding
@pytest.mark.parametrize("name", ALL_ENVS)
def test_same_seed_same_rollout_different_seed_differs(name):
    """Seeded envs reproduce resets (auto-resets included); other seeds give other starts."""
    def rollout(seed):
        env = make(name, 3, seed=seed, max_episode_steps=2)
        return env.rollout(5, ReplayPolicy(in_spec_actions(env, 3, 5)), break_when_any_done=False)

    a, b, c = rollout(11), rollout(11), rollout(12)
    assert (a == b).all(), "same seed gave a different rollout"
    assert not torch.equal(a["observation"][:, 0], c["observation"][:, 0])
    assert not torch.equal(a["observation"][:, 2], c["observation"][:, 2])  # after the auto-reset


def test_set_seed_restarts_the_reset_sequence():
    env = make("reacher", 3, seed=0)
    env.set_seed(42)
    first = env.reset()["state"].clone()
    env.reset()
    env.set_seed(42)
    assert (env.reset()["state"] == first).all()


def test_set_seed_none_draws_a_seed_from_torch():
    """EnvBase.set_seed(None) is valid TorchRL API: like seed=None at construction, the env's
    generator is then seeded from torch's global RNG (this used to raise a TypeError)."""
    env = make("pendulum", 2)
    torch.manual_seed(5)
    env.set_seed(None)
    a = env.reset()["state"].clone()
    torch.manual_seed(5)
    env.set_seed()
    assert (env.reset()["state"] == a).all()
    torch.manual_seed(6)
    env.set_seed(None)
    assert not (env.reset()["state"] == a).all()


def test_random_action_rollouts_need_torch_seed_too():
    """env.rollout() without a policy draws actions from action_spec.rand(), i.e. torch's global
    RNG (TorchRL's rule); with both seeds fixed a random rollout is reproducible."""
    def run():
        torch.manual_seed(0)
        return make("swimmer", 2, seed=1, max_episode_steps=3).rollout(6, break_when_any_done=False)

    assert (run() == run()).all()


def test_seed_none_follows_torch_global_seed():
    torch.manual_seed(3)
    a = make_env("swimmer", num_envs=2, seed=None).reset()
    torch.manual_seed(3)
    b = make_env("swimmer", num_envs=2, seed=None).reset()
    assert torch.equal(a["observation"], b["observation"])


# ============================================================================ truncation
DEFAULT_MAX_STEPS = {"CartPole-v1": 500, "Pendulum-v1": 200, "MountainCarContinuous-v0": 999}


@pytest.mark.parametrize("name", ALL_ENVS)
def test_truncation_at_max_episode_steps(name):
    env = make(name, 2, max_episode_steps=3)
    traj = run_steps(env, env.reset(), in_spec_actions(env, 2, 3, fraction=0.2))
    assert torch.equal(traj["next", "episode_step"], torch.tensor([[1, 2, 3]] * 2))
    truncated = traj["next", "truncated"][..., 0]
    assert torch.equal(truncated, torch.tensor([[False, False, True]] * 2))
    assert not traj["next", "terminated"].any()
    assert torch.equal(traj["next", "done"], traj["next", "truncated"])
    # env.rollout resets after a truncation and counts again from 0
    roll = env.rollout(7, ReplayPolicy(in_spec_actions(env, 2, 7, fraction=0.2)), break_when_any_done=False)
    assert torch.equal(roll["episode_step"][0], torch.tensor([0, 1, 2, 0, 1, 2, 0]))
    assert torch.equal(roll["next", "truncated"][0, :, 0], torch.tensor([0, 0, 1, 0, 0, 1, 0], dtype=torch.bool))


@pytest.mark.parametrize("name", ALL_ENVS)
def test_default_and_disabled_truncation(name):
    default = DEFAULT_MAX_STEPS.get(name, 100)
    env = make(name, 1)
    assert env.max_episode_steps == default

    def step_from(env, episode_step):
        td = env.reset()
        td["episode_step"] = torch.tensor([episode_step])
        td["action"] = in_spec_actions(env, 1, fraction=0.0)
        return env.step(td)["next"]

    assert step_from(env, default - 2)["truncated"].item() is False
    assert step_from(env, default - 1)["truncated"].item() is True
    never = make(name, 1, max_episode_steps=None)
    assert never.max_episode_steps is None
    assert step_from(never, 10**9)["truncated"].item() is False


# ============================================================================ bad input
def test_bad_actions_are_rejected_with_what_was_expected():
    env = make("reacher", 3, dtype=torch.float32)
    td = env.reset()
    with pytest.raises(ValueError, match=r"expected an action of shape \(3, 2\).*got \(3, 3\)"):
        env.step(td.clone().set("action", torch.zeros(3, 3)))
    with pytest.raises(ValueError, match=r"expected an action of shape \(3, 2\).*got \(3,\)"):
        env.step(td.clone().set("action", torch.zeros(3)))
    with pytest.raises(TypeError, match=r"expected an action of dtype torch.float32, got torch.float64"):
        env.step(td.clone().set("action", torch.zeros(3, 2, dtype=F64)))
    with pytest.raises(TypeError, match=r"expected an action of dtype torch.float32, got torch.int64"):
        env.step(td.clone().set("action", torch.zeros(3, 2, dtype=torch.int64)))
    with pytest.raises(KeyError, match=r"no 'action' entry \(expected shape \(3, 2\)\)"):
        env.step(td.clone())


def test_wrong_tensordict_batch_size_is_rejected():
    env = make("pendulum", 3)
    td = env.reset()
    small = td[:2].clone().set("action", torch.zeros(2, 1, dtype=F64))
    with pytest.raises(ValueError, match=r"batch size \(3,\) \(num_envs\), got \(2,\)"):
        env.step(small)
    with pytest.raises(ValueError, match=r"batch size \(3,\) \(num_envs\), got \(2,\)"):
        env.reset(td[:2].clone(), set_state=True)


def test_step_without_the_env_entries_says_what_is_needed():
    """A hand-built TensorDict lacking "state"/"params"/"episode_step" gets an error naming them
    (it used to fail inside the physics with "'NoneType' object is not subscriptable")."""
    env = make("pendulum", 2)
    for missing in ("state", "params", "episode_step"):
        td = env.reset().exclude(missing).set("action", torch.zeros(2, 1, dtype=F64))
        with pytest.raises(KeyError, match=r"needs the 'state', 'params' and 'episode_step' entries"):
            env.step(td)


def test_reset_set_state_validates_the_state():
    """reset(td, set_state=True) checks td["state"] against the state spec: every entry present,
    with the env's dtype and shape (a float64 state used to turn a float32 env's observations
    into float64, and a reacher "th" of shape [N] used to broadcast silently)."""
    env = make("reacher", 2, dtype=torch.float32)
    good = env.reset()["state"]
    with pytest.raises(KeyError, match=r"needs a 'state' entry"):
        env.reset(set_state=True)
    with pytest.raises(KeyError, match=r"state entries \['goal', 'th', 'thd'\].*missing \['goal'\]"):
        env.reset(TensorDict({"state": good.exclude("goal")}, [2]), set_state=True)
    with pytest.raises(TypeError, match=r"state entry 'th' must have dtype torch.float32, got torch.float64"):
        env.reset(TensorDict({"state": good.clone().set("th", good["th"].double())}, [2]), set_state=True)
    with pytest.raises(ValueError, match=r"state entry 'th' must have shape \(2, 2\), got \(2,\)"):
        env.reset(TensorDict({"state": good.clone().set("th", good["th"][:, 0])}, [2]), set_state=True)
    out = env.reset(TensorDict({"state": good.clone()}, [2]), set_state=True)
    assert (out["state"] == good).all()


def test_unknown_env_name_lists_every_valid_name():
    with pytest.raises(ValueError, match="unknown env 'Swimmer'") as info:
        make_env("Swimmer")
    for name in ALL_ENVS:
        assert name in str(info.value)


@pytest.mark.parametrize("num_envs", [0, -2, 2.0, True, "4", None])
def test_bad_num_envs(num_envs):
    with pytest.raises(ValueError, match=r"num_envs must be an integer >= 1, got"):
        make_env("pendulum", num_envs=num_envs)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.int32, "float32"])
def test_bad_dtype(dtype):
    with pytest.raises(TypeError, match=r"dtype must be torch.float32 or torch.float64"):
        make_env("pendulum", dtype=dtype)


def test_bad_params_are_rejected_with_what_is_valid():
    with pytest.raises(KeyError, match=r"unknown physical parameter\(s\) \['gravity'\]; valid: \['dt', 'g',"):
        make_env("pendulum", params={"gravity": 9.8})
    with pytest.raises(ValueError, match=r"'g' must be a scalar .* per-env tensor of shape \(3,\), got \(4,\)"):
        make_env("pendulum", num_envs=3, params={"g": torch.ones(4)})
    with pytest.raises(ValueError, match=r"per-env tensor of shape \(3,\), got \(3, 1\)"):
        make_env("pendulum", num_envs=3, params={"g": torch.ones(3, 1)})


@pytest.mark.parametrize("value", ["abc", None, {"a": 1}])
def test_non_numeric_param_value_names_the_parameter(value):
    with pytest.raises(TypeError, match=r"pendulum: parameter 'g' must be a number or a tensor .*shape \(3,\)\), got"):
        make_env("pendulum", num_envs=3, params={"g": value})


@pytest.mark.parametrize("max_steps", [0, -1, 2.5, True])
def test_bad_max_episode_steps(max_steps):
    with pytest.raises(ValueError, match=r"max_episode_steps must be a positive integer or None"):
        make_env("pendulum", max_episode_steps=max_steps)


def test_bad_task_options():
    with pytest.raises(ValueError, match=r"num_links must be an integer >= 1, got 0"):
        make_env("reacher", num_links=0)
    with pytest.raises(ValueError, match=r"goal_sampling must be one of \('reachable', 'square'\), got 'disc'"):
        make_env("reacher", goal_sampling="disc")
    with pytest.raises(ValueError, match=r"num_urchins must be an integer >= 0, got -1"):
        make_env("swimmer", num_urchins=-1)
    with pytest.raises(ValueError, match=r"urchin_clearance must lie in \[0, 1\), got 1.0"):
        make_env("swimmer", urchin_clearance=1.0)
    # a misspelt option is not silently ignored: the error lists the task's options
    with pytest.raises(TypeError, match=r"reacher: unknown option\(s\) \['num_link'\]; valid: \[.*'num_links'"):
        make_env("reacher", num_link=3)
    with pytest.raises(TypeError, match=r"HalfCheetah-v5: unknown option\(s\) \['frame_skip'\]; valid: \[.*'contact'"):
        make_env("HalfCheetah-v5", frame_skip=2)
    assert {"device", "dtype", "seed", "max_episode_steps", "params", "contact", "integrator",
            "contact_gradient"} <= set(env_options("HalfCheetah-v5"))
    for name in ALL_ENVS:  # every option make_env accepts is one the class's constructor takes
        assert {"device", "dtype", "seed", "params"} <= set(env_options(name)), name


@pytest.mark.parametrize("seed", ["a", 2.5, [1]])
def test_bad_seed_says_what_a_seed_is(seed):
    with pytest.raises(TypeError, match=r"pendulum: seed must be an integer or None, got"):
        make_env("pendulum", seed=seed)
    env = make_env("pendulum", seed=np.int64(3))  # any integer type is a seed
    torch.testing.assert_close(env.reset()["observation"], make_env("pendulum", seed=3).reset()["observation"])


# ============================================================================ special actions
@pytest.mark.parametrize("fast", [True, False], ids=["fast_rollout", "EnvBase.rollout"])
@pytest.mark.parametrize("name", ALL_ENVS)
def test_nan_action_touches_only_its_env(name, fast):
    """base.py: a NaN action makes only that env non-finite; it is flagged, terminated (so
    reset), its observation and reward zeroed; the others are bit-identical."""
    n, steps = 3, 5

    def make_env_(seed=4):
        env = make(name, n, seed=seed, max_episode_steps=2)
        use_rollout_path(env, fast)
        return env

    env = make_env_()
    actions = in_spec_actions(env, n, steps, seed=8)
    poisoned = actions.clone().requires_grad_()
    clean = make_env_().rollout(steps, ReplayPolicy(actions), break_when_any_done=False)
    nan_mask = torch.zeros_like(actions, dtype=torch.bool)
    nan_mask[1, 0] = True
    with_nan = torch.where(nan_mask, float("nan"), poisoned)
    dirty = env.rollout(steps, ReplayPolicy(with_nan), break_when_any_done=False)
    others = [0, 2]
    assert (dirty[others] == clean[others]).all(), "a NaN action changed another env"
    # the NaN action's step: env 1's state is NaN, it is flagged and terminated
    assert any(not torch.isfinite(value[1, 0]).all() for value in dirty["next", "state"].values())
    assert dirty["next", "nonfinite"][1, 0].item() and dirty["next", "terminated"][1, 0].item()
    assert not dirty["next", "nonfinite"][others].any() and not clean["next", "nonfinite"].any()
    # what a learner averages stays finite: the non-finite elements are zeroed
    assert torch.isfinite(dirty["next", "observation"]).all() and torch.isfinite(dirty["next", "reward"]).all()
    # the auto-reset restarts it from a finite start state; its own later steps stay finite
    assert dirty["episode_step"][1, 1].item() == 0
    for key, value in dirty["state"].items():
        assert torch.isfinite(value[1, 1:]).all(), f"the reset should clear the NaN in state {key!r}"
    expected_done = clean["next", "done"].clone()
    expected_done[1, 0] = True
    assert torch.equal(dirty["next", "done"][1, :1], expected_done[1, :1])
    assert torch.equal(dirty["next", "done"][others], clean["next", "done"][others])
    # gradients of the other envs stay finite and equal to the clean run's
    w = obs_weights(env)
    (grad,) = torch.autograd.grad(signal(dirty[others], w).sum(), poisoned)
    clean_actions = actions.clone().requires_grad_()
    clean2 = make_env_().rollout(steps, ReplayPolicy(clean_actions), break_when_any_done=False)
    (clean_grad,) = torch.autograd.grad(signal(clean2[others], w).sum(), clean_actions)
    assert torch.isfinite(grad[others]).all() and (grad[others] != 0).any()
    assert torch.equal(grad[others], clean_grad[others])


# the parameter that scales the action in each Ivy task (force = param * action)
# swimmer_race: max_accel scales the opponent's acceleration too, so 3u is no rescaled u there;
# only "unclipped, with its gradient" is checked
ACTION_SCALE = {"cartpole": "max_force", "pendulum": "max_torque", "mountaincar": "max_force",
                "reacher": "max_accel", "swimmer": "max_accel", "swimmer_race": None}


@pytest.mark.parametrize("name", ALL_ENVS)
def test_actions_outside_the_spec(name):
    """Ivy tasks apply out-of-spec actions unclipped (gradient included); Gymnasium variants clip.

    Ivy: action ``3u`` must act exactly like action ``u`` with the action-scaling parameter
    tripled. Gymnasium variants: ``3 * high`` acts like ``high`` with zero gradient, except
    MountainCarContinuous-v0, whose reward ``-0.1 a^2`` sees the raw action (as Gymnasium's).
    """
    n = 2
    env = make(name, n, seed=9)
    td = env.reset()
    low, high = env.action_low, env.action_high
    if not is_gymnasium_variant(name):
        assert env.clip_actions is False
        u = torch.full((n, env.action_dim), 0.9, dtype=F64)
        u[1] = -0.7
        big = (3 * u).requires_grad_()
        out = env.step(td.clone().set("action", big))["next"]
        assert (big.abs() > high).all()
        if name not in ACTION_SCALE:
            pytest.fail(f"{name}: add the parameter that scales its action to ACTION_SCALE")
        scale = ACTION_SCALE[name]
        if scale is None:
            clipped = env.step(td.clone().set("action", big.detach().clamp(low, high)))["next"]
            assert not torch.equal(out["state", "vel"], clipped["state", "vel"])
            (grad,) = torch.autograd.grad(out["observation"].sum(), big)
            assert (grad != 0).any(), "out-of-spec actions must keep their gradient"
            return
        scaled = make(name, n, seed=9, params={scale: 3 * env.params[scale]})
        ref_td = td.clone()
        ref_td["params"] = scaled.params.clone()
        ref = scaled.step(ref_td.set("action", u))["next"]
        torch.testing.assert_close(out["observation"], ref["observation"], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out["reward"], ref["reward"], rtol=1e-12, atol=1e-12)
        (grad,) = torch.autograd.grad(out["observation"].sum(), big)
        assert (grad != 0).any(), "out-of-spec actions must keep their gradient"
        return
    outside = torch.tensor([[3 * high], [3 * low]], dtype=F64).expand(n, env.action_dim).clone().requires_grad_()
    edge = torch.tensor([[high], [low]], dtype=F64).expand(n, env.action_dim)
    out = env.step(td.clone().set("action", outside))["next"]
    ref = env.step(td.clone().set("action", edge))["next"]
    for key in td["state"].keys():
        assert torch.equal(out["state", key], ref["state", key]), key
    (grad,) = torch.autograd.grad(out["observation"].sum(), outside)
    assert (grad == 0).all(), "a clipped action has no gradient"
    if name == "MountainCarContinuous-v0":
        torch.testing.assert_close(out["reward"], -0.1 * outside.detach() ** 2, rtol=1e-12, atol=1e-12)
    else:
        assert torch.equal(out["reward"], ref["reward"])


# ============================================================================ task options
@pytest.mark.parametrize("num_links", [1, 2, 3])
def test_reacher_num_links(num_links):
    env = make("reacher", 4, num_links=num_links, dtype=torch.float32)
    assert env.action_dim == num_links and env.observation_dim == 3 * num_links + 2
    check_env_specs(env)
    traj = env.rollout(5)
    assert traj["next", "observation"].shape == (4, 5, 3 * num_links + 2)
    assert traj["next", "state", "th"].shape == (4, 5, num_links)


@pytest.mark.parametrize("num_urchins", [0, 1, 5, 7])
def test_swimmer_num_urchins(num_urchins):
    env = make("swimmer", 4, num_urchins=num_urchins, dtype=torch.float32)
    assert env.observation_dim == 2 * num_urchins + 6
    check_env_specs(env)
    traj = env.rollout(5)
    assert traj["next", "observation"].shape == (4, 5, 2 * num_urchins + 6)
    assert traj["next", "state", "urchins"].shape == (4, 5, num_urchins, 2)


@pytest.mark.parametrize("num_links,link_length", [(1, 1.0), (2, 1.0), (3, 0.5)])
def test_reacher_reachable_goals_fill_the_reachable_disc(num_links, link_length):
    n = 4000
    goal = make("reacher", n, num_links=num_links, params={"link_length": link_length}).reset()["state", "goal"]
    reach = num_links * link_length
    radius = goal.norm(dim=-1)
    assert radius.max() <= reach * (1 + 1e-12)
    assert radius.max() > 0.99 * reach
    # uniform over the disc: P(r < reach / 2) = 1/4 (a standard error is ~0.007 here)
    assert abs((radius < reach / 2).double().mean().item() - 0.25) < 0.03


@pytest.mark.parametrize("num_links", [1, 2, 3])
def test_reacher_square_goals_match_ivy(num_links):
    """Ivy Gym samples goals from U[-R, R]^2 with R the arm's reach; ~21% lie out of reach."""
    n = 4000
    goal = make("reacher", n, num_links=num_links, goal_sampling="square").reset()["state", "goal"]
    reach = float(num_links)
    assert goal.abs().max() <= reach
    assert (goal.min(0).values < -0.99 * reach).all() and (goal.max(0).values > 0.99 * reach).all()
    unreachable = (goal.norm(dim=-1) > reach).double().mean().item()
    assert abs(unreachable - (1 - math.pi / 4)) < 0.03


@pytest.mark.parametrize("clearance", [0.0, 0.25, 0.5])
def test_swimmer_urchin_clearance(clearance):
    n = 2000
    state = make("swimmer", n, num_urchins=5, urchin_clearance=clearance).reset()["state"]
    urchins = state["urchins"]
    assert urchins.abs().max() <= 1.0
    closest = torch.minimum(
        (urchins - state["pos"][:, None]).norm(dim=-1), (urchins - state["goal"][:, None]).norm(dim=-1)
    ).min(-1).values
    if clearance == 0.0:
        # Ivy Gym's original sampling: some episodes start or end close to an urchin
        assert (closest < 0.25).double().mean() > 0.05
    else:
        assert (closest >= clearance).all()
