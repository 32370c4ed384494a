"""Gymnasium parity: our "CartPole-v1", "Pendulum-v1" and "MountainCarContinuous-v0" against gymnasium's own.

The oracle is gymnasium itself: ``gymnasium.make(id)`` (its TimeLimit wrapper included, so it also
decides ``truncated``), one gymnasium env per entry of our batch. Both start from the same state
(gymnasium's ``env.unwrapped.state`` is set to ours after reset) and get the same actions; every step
compares the next observation, the reward, ``terminated`` and ``truncated``, and the full internal
state. Our envs run in float64; gymnasium's observations are float32, hence the tolerances.

Two ways of driving them:

* free-running: the two envs are synchronised once, at the start, and each then follows its own
  trajectory (catches anything that accumulates);
* resync: gymnasium's state is set to ours before every step, so every step is a one-step
  comparison from the same state, with tight tolerances. Gymnasium's own float32 arithmetic
  (Pendulum's float32 action term, MountainCar's float32 state) drifts a free run away (Pendulum:
  1e-6 to 5e-5 in 200 steps, it is chaotic once it spins; MountainCar: ~2e-7); an upright CartPole
  amplifies any last-bit difference between numpy's and torch's sin/cos (here they agree bit for
  bit, but no platform promises that).

``python tests/envs/test_gymnasium_parity.py`` prints the largest differences seen (README table).
"""
import math
from functools import partial

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs import EnvBase
from torchrl.envs.utils import step_mdp

from torchrl_diffenvs import list_envs, make_env

GYM_IDS = ["CartPole-v1", "Pendulum-v1", "MountainCarContinuous-v0"]
# our state keys, in the order of gymnasium's env.unwrapped.state
STATE_KEYS = {
    "CartPole-v1": ("x", "xd", "th", "thd"),
    "Pendulum-v1": ("th", "thd"),
    "MountainCarContinuous-v0": ("x", "xd"),
}
# Absolute tolerances. Gymnasium's observations are float32 (atol 1e-6 plus rtol 1e-6 on them).
# Its CartPole state is float64 throughout; Pendulum multiplies the float32 action in float32
# (~1e-9 per step); MountainCar rounds its whole state to float32 after each step (~1e-8).
TOL = {
    "CartPole-v1": dict(state=1e-10, obs=1e-6, reward=1e-12),
    "Pendulum-v1": dict(state=1e-7, obs=1e-6, reward=1e-6),
    "MountainCarContinuous-v0": dict(state=1e-6, obs=1e-6, reward=1e-12),
}


def _gym_step(gym_env, name, a, continuous_cartpole):
    """One gymnasium step with our scalar action ``a`` (a float32 value)."""
    if name == "CartPole-v1":
        if continuous_cartpole:
            # Gymnasium pushes with +-force_mag; |a| * 10 N in the direction of a is our force 10 a
            gym_env.unwrapped.force_mag = 10.0 * abs(float(a))
        else:
            assert a in (-1.0, 1.0), a
        return gym_env.step(int(a > 0))
    return gym_env.step(np.array([a], dtype=np.float32))


def _check_close(what, ours, gym, rtol, atol):
    """``|ours - gym| <= atol + rtol |gym|`` elementwise (np.testing.assert_allclose is too slow
    per step); returns the largest absolute difference."""
    gym = np.asarray(gym, dtype=np.float64)
    err = np.abs(ours - gym)
    bad = ~(err <= atol + rtol * np.abs(gym))
    if bad.any():
        raise AssertionError(f"{what}: ours {ours[bad]} vs gymnasium {gym[bad]} (atol {atol}, rtol {rtol})")
    return float(err.max())


def _check_equal(what, ours, gym):
    if not np.array_equal(ours, gym):
        raise AssertionError(f"{what}: ours {ours.tolist()} vs gymnasium {gym.tolist()}")


def side_by_side(name, policy, steps, *, num_envs, seed, resync, start=None, continuous_cartpole=False,
                 max_episode_steps=None, gym_kwargs=None, params=None, tol=None, dtype=torch.float64):
    """Steps our batched env and one gymnasium env per batch entry in lockstep, comparing every step.

    ``policy(t, state) -> np.float32 [num_envs]`` sees our current state (a dict of float64 numpy
    arrays). Each gymnasium env stops at its first terminated or truncated step; the run stops when
    all have. Returns per-step records of ours (reward, terminated, truncated, state, active mask).
    ``tol`` overrides entries of ``TOL[name]`` (``rtol``, default 0, applies to states and rewards).
    """
    keys = STATE_KEYS[name]
    tol = {"rtol": 0.0, **TOL[name], **(tol or {})}
    env_kwargs = {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}
    env = make_env(name, num_envs=num_envs, dtype=dtype, seed=seed, params=params, **env_kwargs)
    td = env.reset()
    if start is not None:
        for k in keys:
            td["state", k] = torch.as_tensor(start[k], dtype=dtype).expand(num_envs).clone()
        td = env.reset(td, set_state=True)
    gym_envs = [gymnasium.make(name, **(gym_kwargs or {}), **env_kwargs) for _ in range(num_envs)]
    for i, g in enumerate(gym_envs):
        g.reset(seed=seed + i)

    def our_state(t):
        return np.stack([t["state", k].numpy() for k in keys], axis=-1).astype(np.float64)  # [N, state_dim]

    for i, g in enumerate(gym_envs):
        g.unwrapped.state = our_state(td)[i].copy()
    active = np.ones(num_envs, dtype=bool)
    records = []
    for t in range(steps):
        state_now = our_state(td)
        if resync:
            for i in np.flatnonzero(active):
                gym_envs[i].unwrapped.state = state_now[i].copy()
        a = np.asarray(policy(t, {k: td["state", k].numpy() for k in keys}), dtype=np.float32)
        td["action"] = torch.as_tensor(a, dtype=dtype).unsqueeze(-1)
        td = env.step(td)
        nxt = td["next"]
        ours = {
            "obs": nxt["observation"].numpy().astype(np.float64),
            "reward": nxt["reward"][:, 0].numpy().astype(np.float64),
            "terminated": nxt["terminated"][:, 0].numpy(),
            "truncated": nxt["truncated"][:, 0].numpy(),
            "done": nxt["done"][:, 0].numpy(),
            "state": our_state(nxt),
            "active": active.copy(),
            "action": a,
        }
        idx = np.flatnonzero(active)
        gym = [_gym_step(gym_envs[i], name, a[i], continuous_cartpole) for i in idx]
        gym_state = np.stack([np.asarray(gym_envs[i].unwrapped.state, dtype=np.float64) for i in idx])
        g_terminated = np.array([out[2] for out in gym])
        g_truncated = np.array([out[3] for out in gym])
        where = f"{name}, step {t + 1}, envs {idx.tolist()}"
        ours["max_err"] = {
            "obs": _check_close(f"observation, {where}", ours["obs"][idx], np.stack([out[0] for out in gym]),
                                1e-6, tol["obs"]),
            "state": _check_close(f"state, {where}", ours["state"][idx], gym_state, tol["rtol"], tol["state"]),
            "reward": _check_close(f"reward, {where}", ours["reward"][idx], np.array([out[1] for out in gym]),
                                   tol["rtol"], tol["reward"]),
        }
        _check_equal(f"terminated, {where}", ours["terminated"][idx], g_terminated)
        _check_equal(f"truncated, {where}", ours["truncated"][idx], g_truncated)
        _check_equal(f"done, {where}", ours["done"][idx], g_terminated | g_truncated)
        active[idx[g_terminated | g_truncated]] = False
        records.append(ours)
        td = step_mdp(td)
        if not active.any():
            break
    for g in gym_envs:
        g.close()
    return records


def _stack(records, key):
    return np.stack([r[key] for r in records])  # [T, N, ...]


def _compared_steps(records):
    return int(_stack(records, "active").sum(0).min())  # steps compared for the shortest episode


# --------------------------------------------------------------------------- registration, specs
@pytest.mark.parametrize("name", GYM_IDS)
def test_registered_with_gymnasium_spaces_and_limits(name):
    assert name in list_envs()
    env = make_env(name, num_envs=2, seed=0)
    gym_env = gymnasium.make(name)
    assert env.observation_dim == gym_env.observation_space.shape[0]
    assert env.max_episode_steps == gymnasium.spec(name).max_episode_steps
    if name == "CartPole-v1":  # the deliberate deviation: Box(-1, 1) instead of Discrete(2)
        low, high = -1.0, 1.0
    else:
        low, high = float(gym_env.action_space.low[0]), float(gym_env.action_space.high[0])
    assert env.action_spec.space.low.flatten().tolist() == [low, low]
    assert env.action_spec.space.high.flatten().tolist() == [high, high]


# --------------------------------------------------------------------------- CartPole-v1
def test_cartpole_plus_minus_one_are_gymnasium_actions_1_and_0():
    rng = np.random.default_rng(0)
    env = make_env("CartPole-v1", num_envs=2, dtype=torch.float64, seed=0)
    gym_env = gymnasium.make("CartPole-v1").unwrapped
    for _ in range(20):
        state = rng.uniform(-0.2, 0.2, size=4)
        td = env.reset()
        for k, v in zip(STATE_KEYS["CartPole-v1"], state):
            td["state", k] = torch.full((2,), float(v), dtype=torch.float64)
        td = env.reset(td, set_state=True)
        td["action"] = torch.tensor([[1.0], [-1.0]], dtype=torch.float64)
        out = env.step(td)["next", "observation"].numpy()
        for row, gym_action in ((0, 1), (1, 0)):
            gym_env.reset(seed=0)
            gym_env.state = state.copy()
            gym_env.step(gym_action)
            np.testing.assert_allclose(out[row], gym_env.state, rtol=0, atol=1e-14)


def test_cartpole_random_discrete_actions_until_the_pole_falls():
    # random +-1 from near-upright starts: every episode terminates within ~100 steps
    rng = np.random.default_rng(1)
    recs = side_by_side("CartPole-v1", lambda t, s: rng.choice([-1.0, 1.0], size=16), 500,
                        num_envs=16, seed=1, resync=False)
    terminated = _stack(recs, "terminated") & _stack(recs, "active")
    assert terminated.any(0).all()  # all 16 fell, and gymnasium agreed at the same step
    assert np.abs(_stack(recs, "state")[..., 2][terminated]).max() > 12 * 2 * math.pi / 360


def test_cartpole_balanced_for_500_steps_is_truncated_like_timelimit():
    # a bang-bang balancing controller keeps the pole up: gymnasium's TimeLimit truncates at 500
    gains = np.array([0.1, 0.2, 1.0, 0.2])

    def policy(t, s):
        u = gains[0] * s["x"] + gains[1] * s["xd"] + gains[2] * s["th"] + gains[3] * s["thd"]
        return np.where(u > 0, 1.0, -1.0)

    recs = side_by_side("CartPole-v1", policy, 500, num_envs=4, seed=2, resync=True)
    assert len(recs) == 500 and _compared_steps(recs) == 500
    assert _stack(recs, "truncated")[-1].all() and not _stack(recs, "truncated")[:-1].any()
    assert not _stack(recs, "terminated").any()


def _noisy_balancer(rng):
    """A continuous CartPole policy that keeps the pole up: a = clip(K s + N(0, 0.3^2), -1, 1)."""
    gains = np.array([0.5, 1.0, 10.0, 2.0])

    def policy(t, s):
        u = gains[0] * s["x"] + gains[1] * s["xd"] + gains[2] * s["th"] + gains[3] * s["thd"]
        return np.clip(u + rng.normal(0.0, 0.3, size=u.shape), -1.0, 1.0)

    return policy


def test_cartpole_continuous_force_matches_gymnasium_with_scaled_force_mag():
    # ours pushes with 10 a; gymnasium with force_mag = |10 a| in the direction of a
    policy = _noisy_balancer(np.random.default_rng(3))
    recs = side_by_side("CartPole-v1", policy, 150, num_envs=4, seed=3, resync=True, continuous_cartpole=True)
    actions = _stack(recs, "action")
    assert _compared_steps(recs) >= 100
    assert ((np.abs(actions) > 0.05) & (np.abs(actions) < 0.95)).mean() > 0.5  # really continuous


def test_cartpole_cart_leaving_the_track_terminates():
    # the pole is balanced but the cart runs off the right end (x > 2.4)
    gains = np.array([0.0, 0.0, 1.0, 0.2])

    def policy(t, s):
        u = gains[2] * s["th"] + gains[3] * s["thd"]
        return np.where(u > 0, 1.0, -1.0)

    start = {"x": 2.0, "xd": 1.0, "th": 0.0, "thd": 0.0}
    recs = side_by_side("CartPole-v1", policy, 100, num_envs=2, seed=4, resync=False, start=start)
    last = recs[-1]
    assert last["terminated"].all() and (last["state"][:, 0] > 2.4).all()
    assert (np.abs(last["state"][:, 2]) < 12 * 2 * math.pi / 360).all()  # not the angle


def test_cartpole_termination_on_the_last_step_is_also_truncated_like_timelimit():
    # find the step k at which a run from this state falls, then limit episodes to exactly k steps
    start = {"x": 0.0, "xd": 0.0, "th": 0.1, "thd": 0.0}
    recs = side_by_side("CartPole-v1", lambda t, s: np.ones(1), 100, num_envs=1, seed=5, resync=False, start=start)
    k = len(recs)
    assert recs[-1]["terminated"].all() and 1 < k < 100
    recs = side_by_side("CartPole-v1", lambda t, s: np.ones(1), 100, num_envs=1, seed=5, resync=False,
                        start=start, max_episode_steps=k)
    assert len(recs) == k and recs[-1]["terminated"].all() and recs[-1]["truncated"].all()
    # env.rollout (DiffEnv's lean loop) and TorchRL's EnvBase.rollout flag that step the same way
    env = make_env("CartPole-v1", num_envs=1, dtype=torch.float64, seed=5, max_episode_steps=k)
    td0 = env.reset()
    for key, value in start.items():
        td0["state", key] = torch.full((1,), value, dtype=torch.float64)
    actions = [torch.ones(1, 1, dtype=torch.float64)] * (k + 5)
    for rollout in (env.rollout, partial(EnvBase.rollout, env)):
        traj = rollout(k + 5, actions=actions, tensordict=env.reset(td0.clone(), set_state=True), auto_reset=False)
        assert traj.shape == (1, k)
        assert traj["next", "terminated"][0, -1].item() and traj["next", "truncated"][0, -1].item()
        assert not traj["next", "done"][0, :-1].any()


# --------------------------------------------------------------------------- Pendulum-v1
@pytest.mark.parametrize("resync", [True, False])
def test_pendulum_200_steps_with_clipped_torques_and_speeds(resync):
    # half the envs get random torques in [-3, 3] (beyond the +-2 clip); half pump energy with
    # a = 2.5 sign(thd), which spins the pendulum up to the +-8 rad/s speed clip. Free-running,
    # gymnasium's float32 torque term drifts the trajectories apart (1.5e-6 in this run).
    rng = np.random.default_rng(6)
    tol = None if resync else dict(state=1e-4, obs=1e-4, reward=1e-3)

    def policy(t, s):
        pump = np.where(s["thd"] >= 0, 2.5, -2.5)
        return np.concatenate([rng.uniform(-3.0, 3.0, size=4), pump[4:]])

    recs = side_by_side("Pendulum-v1", policy, 200, num_envs=8, seed=6, resync=resync, tol=tol)
    assert len(recs) == 200 and _compared_steps(recs) == 200
    assert _stack(recs, "truncated")[-1].all() and not _stack(recs, "truncated")[:-1].any()
    states = _stack(recs, "state")
    assert (np.abs(states[..., 1]) == 8.0).any()  # the speed clip was active
    assert (np.abs(states[..., 0]) > 2 * math.pi).any()  # angles were wrapped by angle_normalize
    assert (np.abs(_stack(recs, "action")) > 2.0).any()  # the torque clip was active


# --------------------------------------------------------------------------- MountainCarContinuous-v0
def test_mountaincar_bang_bang_hits_the_left_wall_then_the_goal():
    # push in the direction of motion: the car swings back, hits the left wall, then reaches the flag
    def policy(t, s):
        return np.where(s["xd"] >= 0, 1.0, -1.0)

    recs = side_by_side("MountainCarContinuous-v0", policy, 999, num_envs=4, seed=7, resync=True)
    states, active = _stack(recs, "state"), _stack(recs, "active")
    terminated = _stack(recs, "terminated") & active
    assert terminated.any(0).all() and _compared_steps(recs) >= 100
    assert (states[..., 0][terminated] >= 0.45).all()
    assert (_stack(recs, "reward")[terminated] == pytest.approx(100.0 - 0.1))
    on_wall = (states[..., 0] == -1.2) & active
    assert on_wall.any() and (states[..., 1][on_wall] == 0.0).all()  # stopped by the wall


@pytest.mark.parametrize("goal_velocity", [0.0, 0.03, 0.07])
def test_mountaincar_goal_velocity_option(goal_velocity):
    # coasting over the flag at ~0.02 ends the episode only when goal_velocity <= that speed;
    # otherwise the car rolls on to the right wall (x = 0.6, where its speed is not reset), speeds
    # up to the 0.07 cap, and ends there: v = 0.07 >= goal_velocity = 0.07 holds exactly.
    # (gymnasium.make's goal_velocity argument is our "goal_velocity" parameter.)
    start = {"x": 0.40, "xd": 0.02}
    recs = side_by_side("MountainCarContinuous-v0", lambda t, s: np.zeros(1), 200, num_envs=1, seed=12,
                        resync=True, start=start, gym_kwargs={"goal_velocity": goal_velocity},
                        params={"goal_velocity": goal_velocity})
    states, terminated = _stack(recs, "state")[:, 0], _stack(recs, "terminated")[:, 0]
    first_over = int(np.argmax(states[:, 0] >= 0.45))
    assert states[first_over, 0] >= 0.45 and 0.0 < states[first_over, 1] < 0.03
    assert terminated[first_over] == (goal_velocity == 0.0)
    assert terminated[-1] and states[-1, 1] >= goal_velocity
    if goal_velocity == 0.07:
        assert states[-1, 0] == 0.6 and states[-1, 1] == 0.07


def test_mountaincar_out_of_range_actions_pay_the_raw_action_cost():
    # actions in [-3, 3]: gymnasium clips the force but charges 0.1 a^2 on the raw action
    rng = np.random.default_rng(8)
    recs = side_by_side("MountainCarContinuous-v0", lambda t, s: rng.uniform(-3.0, 3.0, size=4), 150,
                        num_envs=4, seed=8, resync=True)
    assert _compared_steps(recs) == 150
    actions, rewards = _stack(recs, "action"), _stack(recs, "reward")
    big = np.abs(actions) > 1.0
    assert big.any()
    np.testing.assert_allclose(rewards[big], -0.1 * actions[big].astype(np.float64) ** 2, rtol=1e-12)


def test_mountaincar_truncated_at_999_steps_like_timelimit():
    recs = side_by_side("MountainCarContinuous-v0", lambda t, s: np.zeros(2), 999, num_envs=2, seed=9, resync=True)
    assert len(recs) == 999
    assert _stack(recs, "truncated")[-1].all() and not _stack(recs, "truncated")[:-1].any()


def test_mountaincar_free_running_stays_within_float32_drift():
    # without resync, gymnasium's float32 state rounding accumulates (~2e-7 here) but stays far
    # below any modelling error (a wrong power or gravity constant differs by >1e-4 per step)
    def policy(t, s):
        return np.where(s["xd"] >= 0, 0.8, -0.8)

    recs = side_by_side("MountainCarContinuous-v0", policy, 300, num_envs=2, seed=10, resync=False,
                        tol=dict(state=1e-5, obs=1e-5))
    assert _compared_steps(recs) >= 100


# --------------------------------------------------------------------------- float32
@pytest.mark.parametrize("name", GYM_IDS)
def test_float32_envs_match_gymnasium_to_float32_precision(name):
    # one-step comparisons (resync) over 100 steps of in-range actions
    rng = np.random.default_rng(13)
    if name == "CartPole-v1":
        policy, kwargs = _noisy_balancer(rng), {"continuous_cartpole": True}
    else:
        high = 2.0 if name == "Pendulum-v1" else 1.0
        policy, kwargs = (lambda t, s: rng.uniform(-high, high, size=4)), {}
    recs = side_by_side(name, policy, 100, num_envs=4, seed=13, resync=True, dtype=torch.float32,
                        tol=dict(state=1e-5, obs=1e-5, reward=1e-5, rtol=1e-5), **kwargs)
    assert len(recs) == 100


# --------------------------------------------------------------------------- resets
RESET_RANGES = {  # Gymnasium 1.4's documented reset ranges, per state entry
    "CartPole-v1": [(-0.05, 0.05)] * 4,
    "Pendulum-v1": [(-math.pi, math.pi), (-1.0, 1.0)],
    "MountainCarContinuous-v0": [(-0.6, -0.4), (0.0, 0.0)],
}


@pytest.mark.parametrize("name", GYM_IDS)
def test_reset_distribution_ranges_match_gymnasium(name):
    gym_env = gymnasium.make(name).unwrapped
    gym_states = []
    for seed in range(1000):
        gym_env.reset(seed=seed)
        gym_states.append(np.array(gym_env.state, dtype=np.float64))
    gym_states = np.stack(gym_states)
    env = make_env(name, num_envs=4096, dtype=torch.float64, seed=11)
    td = env.reset()
    ours = np.stack([td["state", k].numpy() for k in STATE_KEYS[name]], axis=-1)
    for j, (low, high) in enumerate(RESET_RANGES[name]):
        slack = 0.02 * (high - low)  # both samples must fill the range: min/max within 2% of the ends
        for label, sample in (("gymnasium", gym_states[:, j]), ("ours", ours[:, j])):
            assert low <= sample.min() <= low + slack, (name, label, j, sample.min())
            assert high - slack <= sample.max() <= high, (name, label, j, sample.max())
        # same mean and spread as gymnasium's samples (uniform: sd = width / sqrt 12)
        assert abs(ours[:, j].mean() - gym_states[:, j].mean()) < 0.1 * (high - low) + 1e-12
        assert abs(ours[:, j].std() - gym_states[:, j].std()) < 0.1 * (high - low) + 1e-12


# --------------------------------------------------------------------------- parity report
def parity_report():
    """Prints the largest differences from gymnasium in the runs above (the README quotes them)."""
    balancer = np.array([0.1, 0.2, 1.0, 0.2])

    def bang_bang_cartpole(t, s):
        return np.where(balancer @ np.stack([s["x"], s["xd"], s["th"], s["thd"]]) > 0, 1.0, -1.0)

    rng = np.random.default_rng(0)
    runs = [
        ("CartPole-v1", "random +-1 until every pole falls", False, 16,
         lambda t, s: rng.choice([-1.0, 1.0], size=16), 500, {}),
        ("CartPole-v1", "bang-bang balancer, 500 steps", False, 4, bang_bang_cartpole, 500, {}),
        ("CartPole-v1", "continuous noisy balancer, 150 steps", True, 4, _noisy_balancer(rng), 150,
         {"continuous_cartpole": True}),
        ("Pendulum-v1", "random torques in [-3, 3], 200 steps", False, 4,
         lambda t, s: rng.uniform(-3.0, 3.0, size=4), 200, {"tol": dict(state=1e-4, obs=1e-4, reward=1e-3)}),
        ("Pendulum-v1", "random torques in [-3, 3], 200 steps", True, 4,
         lambda t, s: rng.uniform(-3.0, 3.0, size=4), 200, {}),
        ("MountainCarContinuous-v0", "bang-bang to the goal", False, 4,
         lambda t, s: np.where(s["xd"] >= 0, 1.0, -1.0), 999, {"tol": dict(state=1e-5, obs=1e-5)}),
        ("MountainCarContinuous-v0", "bang-bang to the goal", True, 4,
         lambda t, s: np.where(s["xd"] >= 0, 1.0, -1.0), 999, {}),
    ]
    print("| env | run | mode | steps | max abs diff: state | observation | reward |")
    print("|---|---|---|---|---|---|---|")
    for name, what, resync, n, policy, steps, kwargs in runs:
        recs = side_by_side(name, policy, steps, num_envs=n, seed=0, resync=resync, **kwargs)
        errs = {k: max(r["max_err"][k] for r in recs) for k in ("state", "obs", "reward")}
        mode = "resync" if resync else "free"
        cells = ["0" if errs[k] == 0 else f"{errs[k]:.1e}" for k in ("state", "obs", "reward")]
        print(f"| {name} | {what} | {mode} | {len(recs)} | {' | '.join(cells)} |")


if __name__ == "__main__":
    parity_report()
