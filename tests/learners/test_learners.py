"""The BPTT and SHAC learners: NaN safety end to end, exact checkpoint resume, schedules that
follow the budget, settings checks; and the evaluation they are scored with."""
import io

import pytest
import torch
from tensordict import TensorDict

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs import PendulumEnv
from torchrl_diffenvs.evaluation import evaluate
from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner, SHACConfig, SHACLearner
from torchrl_diffenvs.modules import ObservationNormalizer, make_actor, make_critic


class PoisonedPendulum(PendulumEnv):
    """Pendulum whose rewards are NaN while ``poisoned`` is set."""

    poisoned = False

    def transition(self, state, action, params):
        next_state, reward, terminated = super().transition(state, action, params)
        if self.poisoned:
            reward = reward + float("nan")
        return next_state, reward, terminated


def make_learner(loss_name, env=None, seed=0, total_env_steps=20 * 8 * 6):
    torch.manual_seed(seed)
    env = env if env is not None else make_env("pendulum", num_envs=8, seed=seed, max_episode_steps=10)
    normalizer = ObservationNormalizer(env.observation_dim)
    actor = make_actor(env, hidden=(16,), normalizer=normalizer)
    if loss_name == "shac":
        critic = make_critic(env, hidden=(16,), normalizer=normalizer)
        settings = SHACConfig(horizon=6, actor_lr=1e-2, critic_passes=2, critic_minibatches=2)
        return SHACLearner(env, actor, critic, settings, total_env_steps, normalizer=normalizer)
    return BPTTLearner(env, actor, BPTTConfig(horizon=6, actor_lr=1e-2), total_env_steps, normalizer=normalizer)


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_nan_rewards_skip_every_update(loss_name):
    env = PoisonedPendulum(num_envs=8, seed=0, max_episode_steps=10)
    learner = make_learner(loss_name, env)
    learner.train_iteration()  # a healthy step first: optimiser state exists
    weights = dict(learner.loss.named_parameters())  # actor and critic weights (not the target's)
    before = {k: v.detach().clone() for k, v in weights.items()}
    env.poisoned = True
    metrics = learner.train_iteration()
    assert metrics["skipped_actor"] == 1
    if loss_name == "shac":
        assert metrics["skipped_critic"] == 2 * 2  # every critic minibatch step
    assert len(before) == (13 if loss_name == "shac" else 7)  # the critic's weights are included
    for key, value in before.items():
        torch.testing.assert_close(weights[key].detach(), value, rtol=0, atol=0, msg=key)
    env.poisoned = False
    assert learner.train_iteration()["skipped_actor"] == 1  # training goes on


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_checkpoint_resume_is_exact(loss_name):
    learner = make_learner(loss_name)
    for _ in range(3):
        learner.train_iteration()
    buffer = io.BytesIO()
    torch.save(learner.state_dict(), buffer)
    torch.manual_seed(123)
    expected = [learner.train_iteration()["loss_actor"] for _ in range(3)]

    resumed = make_learner(loss_name, seed=7)  # other initial weights and env seed
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    torch.manual_seed(123)
    assert [resumed.train_iteration()["loss_actor"] for _ in range(3)] == pytest.approx(expected, rel=1e-6)
    for (k, a), b in zip(learner.loss.state_dict().items(), resumed.loss.state_dict().values()):
        torch.testing.assert_close(a, b, msg=k)
    assert resumed.iteration == learner.iteration == 6


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_resuming_with_a_larger_budget_goes_on_from_the_learning_rate_reached(loss_name):
    """A run resumed with twice the budget keeps the learning rate it had reached (no jump) and
    decays it linearly from there to min_lr at the end of the new budget: started with 20
    iterations, stopped after 5, resumed with 40."""
    short = make_learner(loss_name, total_env_steps=20 * 8 * 6)
    for _ in range(5):
        short.train_iteration()
    longer = make_learner(loss_name, total_env_steps=40 * 8 * 6)
    longer.load_state_dict(short.state_dict())
    lrs = [longer.train_iteration()["lr_actor"] for _ in range(10)]
    # the lr used at iteration i (before that iteration's schedule step): from lr_5 of the 20-iteration
    # line, straight to 1e-5 at iteration 40
    lr_5 = 1e-2 - (1e-2 - 1e-5) * 5 / 20
    expected = [lr_5 + (1e-5 - lr_5) * (i - 5) / 35 for i in range(5, 15)]
    assert lrs == pytest.approx(expected, rel=1e-9)
    if loss_name == "shac":  # the critic's schedule too: 1e-3 -> 1e-5, now after 15 steps
        c_5 = 1e-3 - (1e-3 - 1e-5) * 5 / 20
        assert longer.critic_optim.param_groups[0]["lr"] == pytest.approx(c_5 + (1e-5 - c_5) * 10 / 35, rel=1e-9)


def test_settings_are_checked_with_a_clear_message():
    with pytest.raises(ValueError, match=r"lr_schedule='cosine': valid: linear, exponential, constant"):
        BPTTConfig(lr_schedule="cosine")
    with pytest.raises(ValueError, match=r"horizon=0: expected an integer >= 1"):
        SHACConfig(horizon=0)
    with pytest.raises(ValueError, match=r"unknown setting of SHACConfig.*valid: horizon"):
        SHACConfig.from_mapping({"horizn": 8})
    env = make_env("pendulum", num_envs=2, seed=0)
    with pytest.raises(TypeError, match="config must be a BPTTConfig"):
        BPTTLearner(env, make_actor(env), SHACConfig())


def test_evaluate_reports_returns_and_rewards():
    learner = make_learner("bptt")
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=10)
    result = evaluate(env, learner.policy)
    assert set(result) == {"return", "return_std", "return_min", "return_max", "reward_mean", "tail_reward_mean",
                           "episode_length", "terminated"}
    assert result["return"] == pytest.approx(10 * result["reward_mean"], rel=1e-5)
    assert result["episode_length"] == 10 and result["terminated"] == 0  # the pendulum only truncates
    assert result["return_min"] <= result["return"] <= result["return_max"]


def test_evaluate_counts_only_the_first_episode():
    """CartPole-v1 pays +1 per step, so each env's return is the length of its first episode; an
    episode shorter than the limit ended by a fall (termination), one of 60 steps by truncation."""
    from torchrl.envs.utils import RandomPolicy

    env = make_env("CartPole-v1", num_envs=8, dtype=torch.float64, seed=3, max_episode_steps=60)
    torch.manual_seed(0)
    stats = evaluate(env, RandomPolicy(env.action_spec))
    torch.manual_seed(0)
    env.set_seed(3)
    done = env.rollout(60, RandomPolicy(env.action_spec), break_when_any_done=False)["next", "done"]
    lengths = []
    for row in done.squeeze(-1).tolist():  # hand count: steps up to the first done
        lengths.append(row.index(True) + 1 if True in row else len(row))
    assert min(lengths) < 60  # random actions do make some pole fall before the limit
    assert stats["return"] == pytest.approx(sum(lengths) / len(lengths))
    assert stats["reward_mean"] == pytest.approx(1.0)
    assert stats["episode_length"] == pytest.approx(sum(lengths) / len(lengths))
    assert stats["terminated"] == pytest.approx(sum(n < 60 for n in lengths) / len(lengths))


# ---------------------------------------------------------------------------- fidelity knobs
def test_elementwise_clip_clamps_each_element_and_norm_clip_keeps_the_direction():
    from torchrl_diffenvs.objectives import GradientGuard

    for clip, expected in (("elementwise", [1.0, -0.5, -1.0]), ("norm", [3 / 3.640055, -0.5 / 3.640055, -2 / 3.640055])):
        weight = torch.zeros(3, requires_grad=True)
        optim = torch.optim.SGD([weight], lr=1.0)
        weight.grad = torch.tensor([3.0, -0.5, -2.0])  # norm 3.640055
        info = GradientGuard(max_norm=1.0, clip=clip).step(optim, [weight])
        assert info["grad_norm"] == pytest.approx(3.640055, rel=1e-6)
        torch.testing.assert_close(weight.detach(), -torch.tensor(expected), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="clip must be one of"):
        GradientGuard(clip="value")


def test_network_layer_order_and_orthogonal_init():
    from torch import nn

    from torchrl_diffenvs.modules import make_mlp

    pre = [type(m) for m in make_mlp(3, 1, (8,), nn.ELU, True)]
    post = [type(m) for m in make_mlp(3, 1, (8,), nn.ELU, True, norm_after_activation=True)]
    assert pre == [nn.Linear, nn.LayerNorm, nn.ELU, nn.Linear]
    assert post == [nn.Linear, nn.ELU, nn.LayerNorm, nn.Linear]  # DiffRL's order
    net = make_mlp(16, 4, (32,), nn.ELU, False, dtype=torch.float64, init="orthogonal")
    first, last = net[0].weight.detach(), net[-1].weight.detach()
    torch.testing.assert_close(first.T @ first, 2.0 * torch.eye(16, dtype=torch.float64))  # 32x16: orthonormal columns x gain^2
    torch.testing.assert_close(last @ last.T, 2.0 * torch.eye(4, dtype=torch.float64))
    assert not net[0].bias.any() and not net[-1].bias.any()


@pytest.mark.parametrize("shuffle, distinct_splits", [("every_pass", 3), ("once_per_window", 1)])
def test_critic_minibatch_order(shuffle, distinct_splits):
    """DiffRL visits one split of the window in the same order on every pass; ours re-draws it per pass."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=8, seed=0, max_episode_steps=10)
    settings = SHACConfig(horizon=4, critic_passes=3, critic_minibatches=2, critic_shuffle=shuffle)
    learner = SHACLearner(env, make_actor(env, hidden=(8,)), make_critic(env, hidden=(8,)), settings, 1000)
    seen = []
    original = learner.loss.critic_loss

    def recording(batch):
        seen.append(tuple(batch.get("value_target").flatten().tolist()))
        return original(batch)

    learner.loss.critic_loss = recording
    learner.train_iteration()
    passes = [tuple(seen[i:i + 2]) for i in range(0, len(seen), 2)]
    assert len(passes) == 3 and len(set(passes)) == distinct_splits


def test_bptt_reference_knobs_reach_the_learner():
    env = make_env("pendulum", num_envs=16, seed=0, max_episode_steps=50)
    settings = BPTTConfig(horizon=4, grad_clip="elementwise", stagger_episodes=True)
    learner = BPTTLearner(env, make_actor(env, hidden=(8,)), settings, 1000)
    assert learner.actor_guard.clip == "elementwise"
    learner.train_iteration()
    phases = learner.collector._carried.get("episode_step")
    assert len(set(phases.tolist())) > 4  # the envs no longer share one episode phase


# ---------------------------------------------------------------------------- rl_games' PPO knobs
def make_ppo(**settings):
    from torchrl_diffenvs.learners import PPOConfig, PPOLearner

    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=10)
    actor = make_actor(env, hidden=(8,), return_log_prob=True)
    base = dict(rollout_len=4, epochs=2, minibatch_size=8)
    return PPOLearner(env, actor, make_critic(env, hidden=(8,)), PPOConfig(**{**base, **settings}), 1000)


def test_adaptive_lr_follows_the_kl_as_rl_games():
    learner = make_ppo(lr_schedule="adaptive", lr=1e-3, kl_threshold=0.01, min_lr=5e-4, max_lr=2e-3)
    lr = lambda: learner.optim.param_groups[0]["lr"]  # noqa: E731
    learner._adapt_lr(0.05)  # > 2 x threshold
    assert lr() == pytest.approx(1e-3 / 1.5)
    learner._adapt_lr(0.05)
    assert lr() == pytest.approx(5e-4)  # clamped at min_lr
    learner._adapt_lr(0.01)  # within [threshold / 2, 2 x threshold]: unchanged
    assert lr() == pytest.approx(5e-4)
    for _ in range(4):  # 5e-4 x 1.5^4 = 2.5e-3
        learner._adapt_lr(0.001)  # < threshold / 2
    assert lr() == pytest.approx(2e-3)  # clamped at max_lr
    learner.train_iteration()  # the schedule does not reset the adapted lr
    assert lr() != pytest.approx(1e-3)
    adapted = lr()
    resumed = make_ppo(lr_schedule="adaptive", lr=1e-3, kl_threshold=0.01, min_lr=5e-4, max_lr=2e-3)
    resumed.load_state_dict(learner.state_dict())
    assert resumed.optim.param_groups[0]["lr"] == pytest.approx(adapted)
    with pytest.raises(ValueError, match=r"lr=0.1 must lie in \[min_lr, max_lr\]"):
        make_ppo(lr_schedule="adaptive", lr=0.1)


def test_bounds_loss_hand_computed():
    learner = make_ppo(bounds_loss_coef=1e-4)
    loc = torch.tensor([[1.5], [-2.0], [0.5]])

    class FixedLoc(torch.nn.Module):
        in_keys = ["observation"]

        def forward(self, td):
            return td.set("loc", loc)

    learner.actor.module[0] = FixedLoc()
    batch = TensorDict({"observation": torch.zeros(3, 3)}, batch_size=[3])
    assert learner.bounds_loss(batch).item() == pytest.approx((0.4**2 + 0.9**2 + 0.0) / 3)
    regularised = make_ppo(bounds_loss_coef=1e-4, bound_loss_type="regularisation")
    regularised.actor.module[0] = FixedLoc()
    assert regularised.bounds_loss(batch).item() == pytest.approx((2.25 + 4.0 + 0.25) / 3)


def test_bounds_loss_reaches_the_policy_and_value_clipping_reaches_torchrls_loss():
    learner = make_ppo(bounds_loss_coef=1.0, clip_value=True)
    assert learner.loss.clip_value  # TorchRL's ClipPPOLoss clips the value update to +-clip_epsilon
    batch = next(learner._batches).reshape(-1)
    with torch.no_grad():  # push the means out of the soft bounds so that the loss has a gradient
        last = [m for m in learner.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
        last.bias.fill_(3.0)
    learner.bounds_loss(batch).backward()
    assert last.bias.grad is not None and last.bias.grad.abs().sum() > 0
    assert any(p is last.bias for p in learner.params), "the optimiser steps the parameter the bounds loss moves"
    metrics = learner.train_iteration()
    assert metrics["loss_bounds"] > 0


def test_value_normalization_standardises_the_critic_loss():
    """With rl_games' normalize_value the critic loss is computed on standardised targets and
    predictions: on the first batch (running stats = that batch's targets), the plain loss divided
    by the targets' (population) variance."""
    plain, normalised = make_ppo(), make_ppo(value_normalization=True)
    normalised.loss.load_state_dict(plain.loss.state_dict(), strict=False)  # same networks
    batch = next(plain._batches)
    with torch.no_grad():
        plain.loss.value_estimator(batch, params=plain.loss.critic_network_params,
                                   target_params=plain.loss.target_critic_network_params)
    flat = batch.reshape(-1)
    expected = plain.loss(flat.clone())["loss_critic"].item() / flat["value_target"].var(unbiased=False).item()
    assert normalised.loss(flat.clone())["loss_critic"].item() == pytest.approx(expected, rel=1e-4)
    assert "value_norm.mean" in {k for k in normalised.loss.state_dict()}  # checkpointed with the loss
    normalised.train_iteration()
