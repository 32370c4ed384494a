"""DiffWindowCollector: layout, carried state, graph cuts at window starts and auto-resets,
episode bookkeeping, checkpoint resume."""
import pytest
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_diffenvs import make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.modules import make_actor


class LeafPolicy(TensorDictModuleBase):
    """action = 0.5 tanh(obs[0]) + leaf_t, with a fresh leaf tensor per call: the gradient of any
    later quantity w.r.t. leaf_t tells exactly which earlier actions it depends on."""

    def __init__(self, env):
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action"]
        self.env = env
        self.leaves = []

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        leaf = torch.zeros(self.env.num_envs, self.env.action_dim, dtype=self.env.float_dtype, requires_grad=True)
        self.leaves.append(leaf)
        td.set("action", 0.5 * torch.tanh(td.get("observation")[:, :1]) + leaf)
        return td


def grad_rows(output, leaf):
    """Per-env |d output / d leaf| (zeros where no path exists)."""
    (g,) = torch.autograd.grad(output, leaf, retain_graph=True, allow_unused=True)
    return torch.zeros(leaf.shape[0]) if g is None else g.abs().sum(-1)


def test_window_layout_matches_env_rollout():
    env = make_env("pendulum", num_envs=4, seed=0)
    actor = make_actor(env)
    window = DiffWindowCollector(env, actor, horizon=5).rollout()
    assert window.batch_size == torch.Size([4, 5])
    reference = env.rollout(5, actor, break_when_any_done=False)
    expected = set(reference.keys(True, True)) | {("next", "episode_reward"), "isolated"}
    assert set(window.keys(True, True)) == expected
    assert window["next", "reward"].requires_grad  # the graph is on
    assert window["action"].shape == (4, 5, 1)


def test_state_is_carried_and_detached_between_windows():
    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=100)
    policy = LeafPolicy(env)
    collector = DiffWindowCollector(env, policy, horizon=4, total_windows=2)
    first, second = list(collector)
    assert collector.windows == 2 and collector.frames == 2 * 3 * 4
    # episodes continue: the second window starts where the first stopped
    torch.testing.assert_close(second["state", "th"][:, 0], first["next", "state", "th"][:, -1].detach())
    assert second["episode_step"][:, 0].tolist() == [4, 4, 4]
    # ... but no gradient crosses the window start
    late_reward = second["next", "reward"].sum()
    for leaf in policy.leaves[:4]:  # the first window's actions
        assert grad_rows(late_reward, leaf).eq(0).all()
        assert grad_rows(second["observation"].sum(), leaf).eq(0).all()
    assert grad_rows(first["next", "observation"][:, -1].sum(), policy.leaves[3]).gt(0).all()
    assert grad_rows(late_reward, policy.leaves[4]).gt(0).all()


def test_auto_reset_cuts_the_graph_per_env_and_keeps_the_pre_reset_observation():
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=3)
    policy = LeafPolicy(env)
    collector = DiffWindowCollector(env, policy, horizon=4)
    collector.reset()
    state = collector.state_dict()
    state["carried"]["episode_step"] = torch.tensor([2, 0, 2, 0])  # envs 0 and 2 truncate after step 0
    collector.load_state_dict(state)
    window = collector.rollout()

    truncated = window["next", "truncated"].squeeze(-1)
    assert truncated[:, 0].tolist() == [True, False, True, False]
    assert truncated[:, 2].tolist() == [False, True, False, True]
    assert window["episode_step"][:, 1].tolist() == [0, 1, 0, 1]  # envs 0 and 2 were reset

    # ("next", "observation") at a truncation is the pre-reset one, recomputed from the pre-reset state
    nxt = window["next"][:, 0]
    torch.testing.assert_close(nxt["observation"], env.observation(nxt["state"], nxt["params"]))
    assert not torch.allclose(nxt["observation"][[0, 2]], window["observation"][[0, 2], 1])

    reward_after = window["next", "reward"][:, 1].sum()  # step 1: after the reset for envs 0 and 2
    assert grad_rows(reward_after, policy.leaves[0]).tolist()[0] == 0
    assert grad_rows(reward_after, policy.leaves[0]).tolist()[2] == 0
    assert (grad_rows(reward_after, policy.leaves[0])[[1, 3]] > 0).all()  # envs 1, 3: same episode
    # the pre-reset observation still depends on the actions of its episode (bootstrapping needs it)
    assert grad_rows(nxt["observation"].sum(), policy.leaves[0]).gt(0).all()


def test_episode_returns_match_an_independent_sum():
    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=5)
    actor = make_actor(env)
    collector = DiffWindowCollector(env, actor, horizon=4, total_windows=4)
    rewards, dones, finished = [], [], []
    for window in collector:
        rewards.append(window["next", "reward"].detach().squeeze(-1))
        dones.append(window["next", "done"].squeeze(-1))
        finished.extend(collector.finished_returns)  # the episodes that ended in this window
        # the entry at a done step is that episode's return so far
    rewards, dones = torch.cat(rewards, 1), torch.cat(dones, 1)
    expected = []
    for t in range(rewards.shape[1]):  # episodes end at the same steps here: all start together
        for i in range(3):
            if dones[i, t]:
                start = t - 4  # 5-step episodes
                expected.append(rewards[i, start : t + 1].double().sum().item())
    assert len(expected) == 9  # 16 steps: 3 episodes of 5 steps per env
    assert sorted(finished) == pytest.approx(sorted(expected))
    assert window["next", "episode_reward"][:, -1, 0].tolist() == pytest.approx(rewards[:, 15].tolist())


def test_state_dict_resumes_exactly():
    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=6)
    actor = make_actor(env)
    collector = DiffWindowCollector(env, actor, horizon=4)
    collector.rollout()
    state = collector.state_dict()
    torch.manual_seed(5)
    a, b = collector.rollout(), collector.rollout()  # b crosses a reset: the env's RNG matters

    other = DiffWindowCollector(make_env("pendulum", num_envs=3, seed=99, max_episode_steps=6), actor, horizon=4)
    other.load_state_dict(state)
    torch.manual_seed(5)
    a2, b2 = other.rollout(), other.rollout()
    torch.testing.assert_close(a2["next", "reward"], a["next", "reward"])
    torch.testing.assert_close(b2["next", "reward"], b["next", "reward"])
    assert other.windows == collector.windows


def test_reset_from_a_given_state():
    env = make_env("pendulum", num_envs=2, seed=0)
    collector = DiffWindowCollector(env, make_actor(env), horizon=3)
    td = env.reset()
    td["state", "th"] = torch.tensor([0.1, -0.2])
    collector.reset(td, set_state=True)
    window = collector.rollout()
    torch.testing.assert_close(window["state", "th"][:, 0], torch.tensor([0.1, -0.2]))


def test_argument_validation():
    env = make_env("pendulum", num_envs=2, seed=0)
    with pytest.raises(ValueError, match="horizon"):
        DiffWindowCollector(env, make_actor(env), horizon=0)
    with pytest.raises(ValueError, match="total_windows"):
        DiffWindowCollector(env, make_actor(env), horizon=2, total_windows=-1)
    with pytest.raises(TypeError, match="total_windows is None"):
        len(DiffWindowCollector(env, make_actor(env), horizon=2))
