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
    # env 1 alone is flagged and terminated; its non-finite rewards are zeroed (the batch stays finite)
    assert out["nonfinite"].reshape(3).tolist() == [False, True, False]
    assert out["terminated"].reshape(3).tolist() == [False, True, False]
    assert torch.isfinite(out["agents", "reward"]).all() and (out["agents", "reward"][1] == 0).any()


def test_render_draws_every_fish():
    pytest.importorskip("PIL")
    env = make(num_envs=2, num_agents=4, dtype=torch.float32)
    td = env.rollout(3)
    frame = env.render(td[:, -1]["next"], size=96)
    assert frame.shape == (96, 96, 3)
    one = make(num_envs=2, num_agents=1, dtype=torch.float32)
    assert (frame != one.render(one.rollout(3)[:, -1]["next"], size=96)).any()


# ---------------------------------------------------------------------------- learners
def window_of(env, horizon=6, seed=0):
    """A multi-agent window with the graph on, from a parameter-shared actor."""
    from torchrl_diffenvs.collectors import DiffWindowCollector
    from torchrl_diffenvs.modules import make_actor

    torch.manual_seed(seed)
    actor = make_actor(env, hidden=(16,))
    return actor, DiffWindowCollector(env, actor, horizon=horizon).rollout()


def agent_slice(window, i):
    """Agent ``i``'s part of a multi-agent window, laid out as a single-agent window."""
    out = window.exclude("agents", ("next", "agents"))
    out.set("observation", window["agents", "observation"][:, :, i])
    out.set(("next", "observation"), window["next", "agents", "observation"][:, :, i])
    out.set(("next", "reward"), window["next", "agents", "reward"][:, :, i])
    return out


def test_bptt_loss_is_the_mean_of_the_agents_returns():
    from torchrl_diffenvs.objectives import BPTTLoss

    env = make(num_envs=3, num_agents=2, max_episode_steps=4)  # an episode ends inside the window
    actor, window = window_of(env)
    loss = BPTTLoss(actor, gamma=0.9)
    loss.set_keys(reward=("agents", "reward"))
    per_agent = [BPTTLoss(actor, gamma=0.9)(agent_slice(window, i))["loss_actor"] for i in range(2)]
    torch.testing.assert_close(loss(window)["loss_actor"], sum(per_agent) / 2)


def test_shac_loss_and_targets_are_each_agents_own():
    """Per agent, the multi-agent SHAC loss and critic targets equal the single-agent ones on that
    agent's slice of the window (its rewards, its values; the episode ends are shared)."""
    from torchrl_diffenvs.modules import make_critic
    from torchrl_diffenvs.objectives import SHACLoss

    env = make(num_envs=3, num_agents=2, max_episode_steps=4)
    actor, window = window_of(env)
    torch.manual_seed(1)
    critic = make_critic(env, hidden=(16,))  # decentralised: each agent's value from its own observation
    loss = SHACLoss(actor, critic, gamma=0.9, lmbda=0.8)
    loss.set_keys(reward=("agents", "reward"), value=("agents", "state_value"))
    out = loss(window)
    # the same network as a single-agent critic V(o) (parameter sharing: one MLP for every agent)
    from torchrl_diffenvs.modules import LeanModule

    class OneAgent(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, observation):
            return self.net(observation.unsqueeze(-2).expand(*observation.shape[:-1], 2, -1))[..., 0, :]

    single_critic = LeanModule(OneAgent(critic.module), in_keys=["observation"], out_keys=["state_value"])
    reference = SHACLoss(actor, single_critic, gamma=0.9, lmbda=0.8)
    reference.load_state_dict(loss.state_dict())  # the same target weights
    slices = [agent_slice(window, i).exclude("value_target") for i in range(2)]
    per_agent = [reference(piece) for piece in slices]
    torch.testing.assert_close(out["loss_actor"], sum(o["loss_actor"] for o in per_agent) / 2)
    assert window["next", "done"].any()  # the shared episode end is inside the window
    for i, piece in enumerate(slices):
        torch.testing.assert_close(window["value_target"][:, :, i], piece["value_target"])


@pytest.mark.parametrize("loss", ["bptt", "shac", "mappo", "ippo"])
def test_train_script_trains_and_resumes_exactly_on_multi_swimmer(loss, tmp_path):
    from _train_helpers import STEPS_PER_ITER, read_jsonl, tiny_cfg, train_script, without_measurements

    from torchrl_diffenvs.training import load_checkpoint

    steps = STEPS_PER_ITER[loss]
    extra = [f"train.checkpoint_interval={2 * steps}", "eval.interval=16", "env.options.num_agents=2"]
    result_a = train_script.run(tiny_cfg("multi_swimmer", loss, 4, *extra), tmp_path / "a")
    assert math.isfinite(result_a["eval/return"])
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * steps:012d}.pt"
    result_b = train_script.run(tiny_cfg("multi_swimmer", loss, 4, *extra, f"resume={stopped}"), tmp_path / "b")
    final_a, final_b = (load_checkpoint(tmp_path / run / "checkpoints" / "last.pt") for run in "ab")
    for key, value in final_a["policy"].items():
        assert torch.equal(value, final_b["policy"][key]), key
    rows = [without_measurements(read_jsonl(tmp_path / run / "metrics.jsonl")) for run in "ab"]
    assert rows[0] == rows[1] and result_b["eval/return"] == result_a["eval/return"]


def test_mappo_uses_a_centralised_critic_and_ippo_a_decentralised_one():
    """MAPPO: each fish's value from every fish's observation; IPPO: from its own."""
    from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss
    from torchrl.objectives.value import MultiAgentGAE

    from _train_helpers import make_cfg
    from torchrl_diffenvs.learners import make_learner

    env = make(num_envs=4, num_agents=3, dtype=torch.float32)
    td = env.reset()
    for preset, loss_class in (("mappo", MAPPOLoss), ("ippo", IPPOLoss)):
        cfg = make_cfg("env=multi_swimmer", f"loss={preset}")
        learner = make_learner(cfg.loss, env, 10_000)
        assert type(learner.loss) is loss_class and isinstance(learner.loss.value_estimator, MultiAgentGAE)
        values = learner.critic(td.clone())["agents", "state_value"]
        assert values.shape == (4, 3, 1)
        # moving agent 1's observation changes agent 0's value only with a centralised critic
        moved = td.clone()
        moved["agents", "observation"][:, 1] += 1.0
        changed = (learner.critic(moved)["agents", "state_value"][:, 0] != values[:, 0]).any()
        assert bool(changed) == (preset == "mappo")
        # either way each fish gets its own value (its own reward): MAPPO's critic is one network per agent
        assert (values[:, 0] != values[:, 1]).all()
        learner.close()


@pytest.mark.parametrize("overrides, message", [
    (["env=multi_swimmer", "loss=sac"], "is multi-agent; train it with bptt, shac, mappo or ippo"),
    (["env=multi_swimmer", "loss=shac", "loss.critic_input=state"], "its critic reads the agents' observations"),
    (["env=pendulum", "loss=mappo"], "centralised_critic=true: env 'pendulum' has a single agent"),
    (["env=multi_swimmer", "loss=ppo", "env.options.num_agents=0"], "num_agents must be an integer >= 1"),
    (["env=multi_swimmer", "loss=shac", "compile=true"], "compile=true: env 'multi_swimmer' is multi-agent"),
])
def test_train_script_rejects_what_a_multi_agent_env_cannot_do(overrides, message):
    from _train_helpers import make_cfg, train_script

    from torchrl_diffenvs.training import ConfigError

    with pytest.raises(ConfigError, match=message):
        train_script.validate_config(make_cfg(*overrides))


def test_advantages_across_ranks_are_standardised_per_agent():
    """What the PPO learner does with several ranks: TorchRL's per-agent standardisation (the agent
    dim excluded), here on one rank against the formula by hand."""
    from torchrl_diffenvs.distributed import SINGLE_PROCESS
    from torchrl_diffenvs.learners.ppo import standardize_advantage

    advantage = torch.randn(40, 3, 1, generator=torch.Generator().manual_seed(0), dtype=F64)
    advantage[:, 1] = advantage[:, 1] * 10 + 5  # one agent on another scale
    out = standardize_advantage(advantage, SINGLE_PROCESS, (-2,))
    for i in range(3):
        a = advantage[:, i]
        torch.testing.assert_close(out[:, i], (a - a.mean()) / a.std())
    whole = standardize_advantage(advantage, SINGLE_PROCESS)
    torch.testing.assert_close(whole, (advantage - advantage.mean()) / advantage.std())


def test_compile_physics_refuses_a_multi_agent_env_instead_of_doing_nothing():
    from torchrl_diffenvs import compile_physics

    with pytest.raises(ValueError, match="compile_physics: MultiSwimmerEnv's rollouts cannot take the lean path"):
        compile_physics(make(num_envs=2))
