"""BPTTLoss, SHACLoss and GradientGuard against hand-computed values, an independent
lambda-return computation and float64 central finite differences."""
import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_diffenvs import make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.modules import LeanModule, make_actor, make_critic
from torchrl_diffenvs.objectives import BPTTLoss, GradientGuard, SHACLoss

F, T = False, True


def hand_window(rewards, done, terminated=None, obs=None, next_obs=None):
    """A [N, H] window with the entries the losses read (observations have 2 features: [x, 0])."""
    rewards = torch.tensor(rewards, dtype=torch.float64)
    n, h = rewards.shape
    done = torch.tensor(done)
    terminated = torch.zeros_like(done) if terminated is None else torch.tensor(terminated)

    def as_obs(x):
        x = torch.zeros(n, h) if x is None else torch.tensor(x, dtype=torch.float64)
        return torch.stack([x, torch.zeros_like(x)], -1).double()

    return TensorDict(
        {
            "observation": as_obs(obs),
            "next": {
                "observation": as_obs(next_obs),
                "reward": rewards.unsqueeze(-1),
                "done": done.unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
                "truncated": (done & ~terminated).unsqueeze(-1),
            },
        },
        batch_size=[n, h],
    )


def first_feature_critic():
    """V(obs) = obs[..., 0], exactly."""
    linear = nn.Linear(2, 1, dtype=torch.float64)
    with torch.no_grad():
        linear.weight.copy_(torch.tensor([[1.0, 0.0]]))
        linear.bias.zero_()
    return LeanModule(linear, in_keys=["observation"], out_keys=["state_value"])


def dummy_actor():
    return LeanModule(nn.Linear(2, 1, dtype=torch.float64), in_keys=["observation"], out_keys=["action"])


# ---------------------------------------------------------------------------- hand-computed values
def test_bptt_loss_hand_computed():
    # env 0: one sub-trajectory, 1 + .5*2 + .25*3 = 2.75
    # env 1: done after step 1 -> (4 + .5*5) + 6 = 12.5 (the discount restarts with the episode)
    window = hand_window([[1, 2, 3], [4, 5, 6]], [[F, F, F], [F, T, F]])
    out = BPTTLoss(dummy_actor(), gamma=0.5)(window)
    assert out["loss_actor"].item() == pytest.approx(-(2.75 + 12.5) / 6)
    assert out["reward_mean"].item() == pytest.approx(3.5)


def test_bptt_loss_undiscounted_default_is_mean_reward():
    rewards = torch.rand(3, 7).tolist()
    out = BPTTLoss(dummy_actor())(hand_window(rewards, [[F] * 7] * 3))
    assert out["loss_actor"].item() == pytest.approx(-torch.tensor(rewards).mean().item())


def shac_hand_window():
    # env 0: no episode end; env 1: truncated after step 1 (next obs 50 is the pre-reset one),
    # terminated after step 2
    return hand_window(
        rewards=[[1, 2, 3], [4, 5, 6]],
        done=[[F, F, F], [F, T, T]],
        terminated=[[F, F, F], [F, F, T]],
        obs=[[0, 10, 20], [1, 40, 2]],
        next_obs=[[10, 20, 30], [40, 50, 60]],
    )


def test_shac_actor_loss_hand_computed():
    loss = SHACLoss(dummy_actor(), first_feature_critic(), gamma=0.5, lmbda=0.5)
    loss.make_target_updater()
    out = loss(shac_hand_window())
    # env 0: 1 + .5*2 + .25*3 + .125*V(30) = 6.5
    # env 1: (4 + .5*5 + .25*V(50)) + (6 + 0: terminated) = 19 + 6 = 25
    assert out["loss_actor"].item() == pytest.approx(-(6.5 + 25) / 6)


def test_shac_critic_targets_and_loss_hand_computed():
    loss = SHACLoss(dummy_actor(), first_feature_critic(), gamma=0.5, lmbda=0.5)
    loss.make_target_updater()
    window = shac_hand_window()
    out = loss(window)
    # G_t = r_t + g[(1-l) V(s_t+1) + l G_t+1]; G = r + g V(s') at a done step / the window end
    # env 0: G2 = 3 + .5*30 = 18; G1 = 2 + .5(.5*20 + .5*18) = 11.5; G0 = 1 + .5(.5*10 + .5*11.5) = 6.375
    # env 1: G2 = 6 (terminated); G1 = 5 + .5*50 = 30 (truncated); G0 = 4 + .5(.5*40 + .5*30) = 21.5
    expected = torch.tensor([[6.375, 11.5, 18.0], [21.5, 30.0, 6.0]], dtype=torch.float64)
    torch.testing.assert_close(window["value_target"].squeeze(-1), expected)
    values = torch.tensor([[0, 10, 20], [1, 40, 2]], dtype=torch.float64)
    assert set(out.keys()) == {"loss_actor", "reward_mean", "value_mean", "nonfinite_envs"}  # only what a learner uses
    assert out["nonfinite_envs"] == 0
    assert loss.critic_loss(window)["loss_critic"].item() == pytest.approx(((values - expected) ** 2).mean().item())
    # critic_loss on a flattened minibatch agrees
    flat = window.reshape(-1)
    assert loss.critic_loss(flat[[0, 4]])["loss_critic"].item() == pytest.approx((6.375**2 + 10**2) / 2)


def lambda_return_forward_view(rewards, next_values, done, terminated, gamma, lmbda):
    """Independent truncated TD(lambda) targets by the forward view: a (1-l)-weighted mix of the
    n-step returns inside the sub-trajectory, the longest one taking the remaining weight."""
    n_envs, h = len(rewards), len(rewards[0])
    targets = [[0.0] * h for _ in range(n_envs)]
    for i in range(n_envs):
        for t in range(h):
            end = t  # last step of t's sub-trajectory (episode end or window end)
            while not done[i][end] and end < h - 1:
                end += 1
            horizon = end - t + 1

            def n_step(n):
                ret = sum(gamma**k * rewards[i][t + k] for k in range(n))
                last = t + n - 1
                bootstrap = 0.0 if terminated[i][last] else next_values[i][last]
                return ret + gamma**n * bootstrap

            mix = sum((1 - lmbda) * lmbda ** (n - 1) * n_step(n) for n in range(1, horizon))
            targets[i][t] = mix + lmbda ** (horizon - 1) * n_step(horizon)
    return targets


def test_shac_critic_targets_match_independent_lambda_returns():
    gen = torch.Generator().manual_seed(0)
    n, h = 5, 9
    done = torch.rand(n, h, generator=gen) < 0.2
    terminated = done & (torch.rand(n, h, generator=gen) < 0.5)  # some ends are time limits
    done[0, 3] = True  # make sure both kinds occur
    terminated[0, 3] = False
    done[1, 5] = terminated[1, 5] = True
    window = hand_window(
        torch.randn(n, h, generator=gen).tolist(), done.tolist(), terminated.tolist(),
        next_obs=torch.randn(n, h, generator=gen).tolist(),
    )
    gamma, lmbda = 0.9, 0.7
    loss = SHACLoss(dummy_actor(), first_feature_critic(), gamma=gamma, lmbda=lmbda)
    loss.make_target_updater()
    targets = loss.compute_value_targets(window)
    expected = lambda_return_forward_view(
        window["next", "reward"].squeeze(-1).tolist(), window["next", "observation"][..., 0].tolist(),
        done.tolist(), terminated.tolist(), gamma, lmbda,
    )
    torch.testing.assert_close(targets.squeeze(-1), torch.tensor(expected, dtype=torch.float64))
    assert not targets.requires_grad


def test_shac_target_critic_lags_and_soft_update_convention():
    critic = first_feature_critic()
    loss = SHACLoss(dummy_actor(), critic, gamma=0.5, lmbda=0.5)
    updater = loss.make_target_updater(tau=0.8)
    window = shac_hand_window()
    with torch.no_grad():
        critic.module.weight.copy_(torch.tensor([[2.0, 0.0]]))  # the live critic moves, the target not yet
    torch.testing.assert_close(loss.compute_value_targets(window)[0, 2, 0], torch.tensor(3 + 0.5 * 30.0, dtype=torch.float64))
    updater.step()  # target weight = 0.2 * 1 + 0.8 * 2 = 1.8
    torch.testing.assert_close(loss.compute_value_targets(window)[0, 2, 0], torch.tensor(3 + 0.5 * 1.8 * 30, dtype=torch.float64))


def test_shac_actor_loss_gives_no_gradient_to_the_critic():
    critic = first_feature_critic()
    loss = SHACLoss(dummy_actor(), critic)
    loss.make_target_updater()
    window = shac_hand_window()
    window["next", "observation"].requires_grad_(True)
    loss(window)["loss_actor"].backward()
    assert critic.module.weight.grad is None
    # ... but it reaches the observation the target critic evaluates (gamma^K at window end)
    assert window["next", "observation"].grad[0, 2, 0].item() == pytest.approx(-(0.99**3) / 6)


def test_loss_input_validation():
    loss = BPTTLoss(dummy_actor())
    with pytest.raises(ValueError, match=r"batch size \[N, H\]"):
        loss(hand_window([[1.0, 2.0]], [[F, F]])[0])
    with pytest.raises(KeyError, match="reward"):
        loss(TensorDict({"next": {"done": torch.zeros(2, 3, 1, dtype=torch.bool)}}, [2, 3]))
    with pytest.raises(ValueError, match="gamma"):
        BPTTLoss(dummy_actor(), gamma=0.0)
    shac = SHACLoss(dummy_actor(), first_feature_critic())
    with pytest.raises(KeyError, match="compute_value_targets"):
        shac.critic_loss(TensorDict({"observation": torch.zeros(4, 2, dtype=torch.float64)}, [4]))


# ---------------------------------------------------------------------------- finite differences
def _window_objective(loss, collector, state, seed):
    """Loss of one window collected from a fixed carried state with fixed sampling noise."""
    collector.load_state_dict(state)
    torch.manual_seed(seed)
    window = collector.rollout()
    return loss(window)["loss_actor"], window


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_actor_gradient_matches_finite_differences(loss_name):
    """d loss_actor / d actor parameters through a pendulum window (float64) that crosses an
    auto-reset (max_episode_steps=4, H=6), against central differences of the same objective."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=3, dtype=torch.float64, seed=1, max_episode_steps=4)
    actor = make_actor(env, hidden=(8,))
    if loss_name == "shac":
        critic = make_critic(env, hidden=(8,))
        loss = SHACLoss(actor, critic, gamma=0.9, lmbda=0.8)
        loss.make_target_updater()
    else:
        loss = BPTTLoss(actor, gamma=0.9)
    collector = DiffWindowCollector(env, actor, horizon=6)
    collector.rollout()  # start the measured window mid-episode
    state = collector.state_dict()
    params = list(actor.parameters())
    objective, window = _window_objective(loss, collector, state, seed=7)
    objective.backward()
    assert window["next", "truncated"].any()  # the window crosses an auto-reset

    gen = torch.Generator().manual_seed(3)
    eps = 1e-6
    for p in params:
        for _ in range(2):
            idx = tuple(torch.randint(s, (1,), generator=gen).item() for s in p.shape)
            with torch.no_grad():
                orig = p[idx].item()
                p[idx] = orig + eps
                plus = _window_objective(loss, collector, state, seed=7)[0].item()
                p[idx] = orig - eps
                minus = _window_objective(loss, collector, state, seed=7)[0].item()
                p[idx] = orig
            fd = (plus - minus) / (2 * eps)
            assert p.grad[idx].item() == pytest.approx(fd, rel=1e-5, abs=1e-8), (p.shape, idx)


# ---------------------------------------------------------------------------- gradient safety
def test_nan_reward_skips_the_step_and_leaves_parameters_unchanged():
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=4, seed=0)
    actor = make_actor(env)
    loss = BPTTLoss(actor)
    optimizer = torch.optim.Adam(actor.parameters(), lr=0.1)
    guard = GradientGuard(max_norm=1.0)
    window = DiffWindowCollector(env, actor, horizon=5).rollout()
    reward = window["next", "reward"]
    window["next", "reward"] = reward * torch.where(torch.arange(5).view(1, 5, 1) == 2, float("nan"), 1.0)
    before = [p.detach().clone() for p in actor.parameters()]
    optimizer.zero_grad()
    loss(window)["loss_actor"].backward()
    info = guard.step(optimizer, actor.parameters())
    assert info["skipped"] and guard.skipped == 1
    assert not torch.isfinite(torch.tensor(info["grad_norm"]))
    for b, p in zip(before, actor.parameters()):
        torch.testing.assert_close(p, b, rtol=0, atol=0)
    assert len(optimizer.state) == 0  # Adam never stepped: no moments were touched


def test_gradient_guard_clips_and_skips_huge_norms():
    p = nn.Parameter(torch.zeros(2, dtype=torch.float64))
    optimizer = torch.optim.SGD([p], lr=1.0)
    guard = GradientGuard(max_norm=1.0, skip_above=100.0)
    p.grad = torch.tensor([3.0, 4.0], dtype=torch.float64)  # norm 5 -> clipped to 1
    assert guard.step(optimizer) == {"grad_norm": pytest.approx(5.0), "skipped": False}
    torch.testing.assert_close(p.detach(), torch.tensor([-0.6, -0.8], dtype=torch.float64), atol=1e-6, rtol=0)
    p.grad = torch.tensor([300.0, 400.0], dtype=torch.float64)  # norm 500 > skip_above
    assert guard.step(optimizer)["skipped"]
    torch.testing.assert_close(p.detach(), torch.tensor([-0.6, -0.8], dtype=torch.float64), atol=1e-6, rtol=0)
    assert guard.state_dict() == {"skipped": 1, "steps": 2, "nonfinite_in_a_row": 0}  # a huge finite norm is no NaN
    with pytest.raises(ValueError, match="max_norm"):
        GradientGuard(max_norm=0.0)
