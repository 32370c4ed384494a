"""The two-player race and rl_games-style self-play.

* ``swimmer_race``: a hand-computed step (the scripted opponent's action and the zero-sum
  reward), the players' symmetric views, ``gradcheck`` of a step and a 10-step rollout against
  central finite differences with a policy snapshot as the opponent (the gradient flows through
  its responses), its weights frozen and copied;
* :class:`SelfPlay`: the refresh schedule, the pool, the seeded draw and exact restore;
* the training script: a self-play run resumes bit for bit, evaluations report the win rate
  against the scripted opponent, and bad settings are refused.
"""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from torchrl_diffenvs import make_env
from torchrl_diffenvs.evaluation import evaluate
from torchrl_diffenvs.modules import make_actor
from torchrl_diffenvs.training.selfplay import SelfPlay

F64 = torch.float64
EPS = 1e-6


def race(num_envs=2, **kwargs):
    kwargs.setdefault("dtype", F64)
    kwargs.setdefault("seed", 0)
    return make_env("swimmer_race", num_envs=num_envs, **kwargs)


def tiny_actor(env, seed=0):
    torch.manual_seed(seed)
    return make_actor(env, hidden=(8,))


def test_specs_and_start_states():
    env = race(num_envs=64, dtype=torch.float32)
    check_env_specs(env)
    state = env.reset()["state"]
    to_goal = (state["pos"] - state["goal"].unsqueeze(1)).norm(dim=-1)
    torch.testing.assert_close(to_goal[:, 0], to_goal[:, 1])  # the same distance: a fair start
    assert to_goal.min() >= 0.7 - 1e-6 and to_goal.max() <= 1.0 + 1e-6
    anchors = torch.cat([state["pos"], state["goal"].unsqueeze(1)], dim=1)
    assert (state["urchins"].unsqueeze(-2) - anchors.unsqueeze(-3)).norm(dim=-1).min() >= 0.25


def placed(env):
    state = {"pos": torch.tensor([[[0.0, 0.0], [0.6, 0.2]]], dtype=F64),
             "vel": torch.tensor([[[0.1, 0.0], [0.0, -0.2]]], dtype=F64),
             "goal": torch.tensor([[0.3, 0.1]], dtype=F64),
             "urchins": torch.tensor([[[0.5, -0.5]]], dtype=F64),
             "steps_to_goal": torch.zeros(1, 2, dtype=F64), "arrived": torch.zeros(1, 2, dtype=F64)}
    return env.reset(TensorDict({"state": state}, batch_size=[1]), set_state=True)


def test_a_step_against_the_scripted_opponent_equals_hand_computed_values():
    env = race(num_envs=1, num_urchins=1)
    td = placed(env)
    out = env.step(td.set("action", torch.tensor([[1.0, -0.5]], dtype=F64)))["next"]
    dt = 0.05
    opponent = [math.tanh(2 * (0.3 - 0.6) - 2 * 0.0), math.tanh(2 * (0.1 - 0.2) - 2 * -0.2)]
    v0, v1 = (0.1 + dt * 1.0, 0.0 - dt * 0.5), (dt * opponent[0], -0.2 + dt * opponent[1])
    p0, p1 = (dt * v0[0], dt * v0[1]), (0.6 + dt * v1[0], 0.2 + dt * v1[1])

    def closeness(p):
        return math.exp(-0.5 * ((p[0] - 0.3) ** 2 + (p[1] - 0.1) ** 2)) * (
            1 - math.exp(-30 * ((p[0] - 0.5) ** 2 + (p[1] + 0.5) ** 2)))

    torch.testing.assert_close(out["reward"], torch.tensor([[closeness(p0) - closeness(p1)]], dtype=F64))
    torch.testing.assert_close(out["state", "pos"], torch.tensor([[p0, p1]], dtype=F64))
    # player 0's view: urchins, p0, v0, goal, p1 - p0, v1
    expected = [0.5, -0.5, *p0, *v0, 0.3, 0.1, p1[0] - p0[0], p1[1] - p0[1], *v1]
    torch.testing.assert_close(out["observation"], torch.tensor([expected], dtype=F64))


def test_the_players_see_the_same_layout():
    env = race(num_envs=3)
    state = dict(env.reset()["state"].items())
    swapped = {key: value.flip(1) if key in ("pos", "vel") else value for key, value in state.items()}
    torch.testing.assert_close(env.observe(state, env.params, 1), env.observe(swapped, env.params, 0))


def test_gradcheck_of_a_step_through_a_snapshot_opponent():
    env = race(num_envs=2)
    env.set_opponent(tiny_actor(env).double())
    td0 = env.reset()
    keys = sorted(td0["state"].keys())
    state = [td0["state", k].clone().requires_grad_() for k in keys]
    action = (torch.rand(2, 2, dtype=F64, generator=torch.Generator().manual_seed(0)) - 0.5).requires_grad_()
    accel = td0["params", "max_accel"].clone().requires_grad_()

    def step(action, accel, *tensors):
        params = dict(td0["params"].items(), max_accel=accel)
        td = TensorDict({"action": action, "state": dict(zip(keys, tensors)), "params": params,
                         "episode_step": td0["episode_step"]}, batch_size=[2])
        nxt = env.step(td)["next"]
        return nxt["reward"] + 0 * action.sum(), nxt["observation"] + 0 * action.sum()

    assert torch.autograd.gradcheck(step, (action, accel, *state), eps=EPS, atol=1e-7, rtol=1e-5)
    # the opponent's response depends on player 0's state: d(reward) / d(p0) includes its path
    grads = torch.autograd.grad(step(action, accel, *state)[0].sum(), state[keys.index("pos")])
    assert grads[0][:, 1].abs().sum() > 0  # and on its own position


def test_rollout_gradient_through_the_opponents_responses_equals_finite_differences():
    env = race(num_envs=2, max_episode_steps=None)
    env.set_opponent(tiny_actor(env).double())
    start = env.reset()
    actions = 0.6 * (torch.rand(2, 10, 2, dtype=F64, generator=torch.Generator().manual_seed(1)) * 2 - 1)

    def total(a):
        steps = iter(range(a.shape[1]))
        out = env.rollout(a.shape[1], lambda td: td.set("action", a[:, next(steps)]), tensordict=start.clone(),
                          auto_reset=False)
        return out["next", "reward"].sum()

    a = actions.clone().requires_grad_()
    (grad,) = torch.autograd.grad(total(a), a)
    flat = actions.reshape(-1)
    numeric = torch.zeros_like(flat)
    for i in range(flat.numel()):
        plus, minus = flat.clone(), flat.clone()
        plus[i] += EPS
        minus[i] -= EPS
        numeric[i] = (total(plus.reshape(actions.shape)) - total(minus.reshape(actions.shape))) / (2 * EPS)
    torch.testing.assert_close(grad.reshape(-1), numeric, rtol=1e-5, atol=1e-8)


def test_the_opponent_is_a_frozen_copy():
    env = race(num_envs=4)
    actor = tiny_actor(env).double()
    env.set_opponent(actor)
    td = env.reset()
    before = env.opponent_action(td["state"], td["params"])
    with torch.no_grad():
        for parameter in actor.parameters():
            parameter.add_(1.0)  # training the learner later does not move the opponent
    torch.testing.assert_close(env.opponent_action(td["state"], td["params"]), before, rtol=0, atol=0)
    assert not any(p.requires_grad for p in env.opponent.parameters())
    assert not list(env.parameters())  # the opponent's weights are not the env's
    env.set_opponent(None)  # back to the scripted opponent
    torch.testing.assert_close(env.opponent_action(td["state"], td["params"]),
                               env.scripted_action(td["state"], td["params"]))
    with pytest.raises(TypeError, match="set_opponent expects an actor, a callable or None"):
        env.set_opponent(3)


def scripted_player(td):
    """Player 0 driven by the scripted opponent's rule (from its own side) with a gain from 0.5 to 4
    across the envs: some beat the opponent's 2, some lose."""
    state = td["state"]
    gain = torch.linspace(0.5, 4.0, td.shape[0], dtype=F64).unsqueeze(-1)
    return td.set("action", torch.tanh(gain * (state["goal"] - state["pos"][:, 0]) - 2.0 * state["vel"][:, 0]))


def test_the_first_fish_at_the_goal_wins():
    env = race(num_envs=64, max_episode_steps=100)
    with torch.no_grad():
        rollout = env.rollout(100, scripted_player)
    # by hand: the first step each fish is within 0.1 of the goal
    distance = (rollout["next", "state", "pos"] - rollout["next", "state", "goal"].unsqueeze(2)).norm(dim=-1)
    inside = distance < 0.1  # [N, T, 2]
    first = torch.where(inside.any(1), inside.float().argmax(1), torch.full_like(inside[:, 0], 10**6, dtype=torch.long))
    wins = first[:, 0] < first[:, 1]
    end = rollout["next", "state"][:, -1]
    assert 0 < wins.sum() < 64  # some races won, some lost or tied
    assert torch.equal(env.player_wins(end, None), wins)
    arrived = inside.any(1)
    torch.testing.assert_close(end["arrived"], arrived.to(F64))
    torch.testing.assert_close(end["steps_to_goal"][arrived], (first + 1)[arrived].to(F64))


def test_win_rate_counts_the_first_episode_ends():
    env = race(num_envs=16, max_episode_steps=60)
    scores = evaluate(env, scripted_player, steps=80, seed=5)
    env.set_seed(5)
    with torch.no_grad():
        rollout = env.rollout(80, scripted_player, break_when_any_done=False)
    end = rollout["next", "state"][:, 59]  # the first episode's last step
    assert scores["win_rate"] == pytest.approx(env.player_wins(end, None).double().mean().item())
    assert 0 < scores["win_rate"] < 1


# ---------------------------------------------------------------------------- the schedule
def test_selfplay_refreshes_on_schedule_from_a_bounded_pool():
    env = race(num_envs=2)
    actor = tiny_actor(env).double()
    selfplay = SelfPlay(env, actor, refresh_interval=100, pool_size=2, seed=0)
    assert selfplay.step(0) and env.opponent is not None and len(selfplay.pool) == 1
    assert not selfplay.step(99)
    snapshots = []
    for steps in (100, 250, 300):
        with torch.no_grad():
            next(actor.parameters()).add_(1.0)  # the policy trains
        assert selfplay.step(steps)
        snapshots.append(next(iter(selfplay.pool[-1].values())).clone())
    assert len(selfplay.pool) == 2 and selfplay.next_refresh == 400
    torch.testing.assert_close(next(iter(selfplay.pool[0].values())), snapshots[1])  # the oldest left
    # the playing opponent is the drawn snapshot's policy
    td = env.reset()
    played = env.opponent_action(td["state"], td["params"])
    rebuilt = race(num_envs=2)
    restored = SelfPlay(rebuilt, tiny_actor(rebuilt, seed=9).double(), refresh_interval=100, pool_size=2)
    restored.load_state_dict(selfplay.state_dict())
    torch.testing.assert_close(rebuilt.opponent_action(td["state"], td["params"]), played, rtol=0, atol=0)
    # and the draws continue identically
    assert selfplay.step(400) and restored.step(400) and selfplay.current == restored.current


def test_selfplay_needs_a_two_player_env():
    env = make_env("pendulum")
    with pytest.raises(ValueError, match="self-play needs a two-player env"):
        SelfPlay(env, make_actor(env), refresh_interval=10)


# ---------------------------------------------------------------------------- the training script
def test_selfplay_run_resumes_exactly_and_reports_the_win_rate(tmp_path):
    from _train_helpers import STEPS_PER_ITER, read_jsonl, tiny_cfg, train_script, without_measurements

    from torchrl_diffenvs.training import load_checkpoint

    steps = STEPS_PER_ITER["shac"]
    extra = [f"train.checkpoint_interval={2 * steps}", "eval.interval=16", f"selfplay.refresh_interval={steps}",
             "selfplay.pool_size=2"]
    result_a = train_script.run(tiny_cfg("swimmer_race", "shac", 4, *extra), tmp_path / "a")
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * steps:012d}.pt"
    assert len(load_checkpoint(stopped)["selfplay"]["pool"]) == 2
    result_b = train_script.run(tiny_cfg("swimmer_race", "shac", 4, *extra, f"resume={stopped}"), tmp_path / "b")
    final_a, final_b = (load_checkpoint(tmp_path / run / "checkpoints" / "last.pt") for run in "ab")
    for key, value in final_a["policy"].items():
        assert torch.equal(value, final_b["policy"][key]), key
    rows = [read_jsonl(tmp_path / run / "metrics.jsonl") for run in "ab"]
    strip = [without_measurements(run) for run in rows]
    assert strip[0] == strip[1] and result_a["eval/return"] == result_b["eval/return"]
    assert any("eval/win_rate" in r for r in rows[0]) and any("train/opponent_age" in r for r in rows[0])


@pytest.mark.parametrize("overrides, message", [
    (["env=pendulum", "selfplay.refresh_interval=100"], "self-play needs a two-player env"),
    (["env=swimmer_race", "selfplay.refresh_interval=0"], r"selfplay.refresh_interval=0: expected an integer >= 1"),
    (["env=swimmer_race", "selfplay.refresh_interval=10", "selfplay.pool_size=0"], "selfplay.pool_size=0"),
])
def test_bad_selfplay_settings_are_refused(overrides, message):
    from _train_helpers import make_cfg, train_script

    from torchrl_diffenvs.training import ConfigError

    with pytest.raises(ConfigError, match=message):
        train_script.validate_config(make_cfg(*overrides, "loss=shac"))


@pytest.mark.parametrize("distribution", ["tanh_normal", "deterministic"])
def test_a_snapshot_plays_the_actors_mean_action_from_its_own_side(distribution):
    env = race(num_envs=3)
    torch.manual_seed(0)
    actor = make_actor(env, hidden=(8,), distribution=distribution).double()
    env.set_opponent(actor)
    td = env.reset()
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    seen_by_player_1 = td.clone().set("observation", env.observe(td["state"], td["params"], 1))
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(seen_by_player_1)["action"]
    torch.testing.assert_close(env.opponent_action(td["state"], td["params"]), expected)
