"""GradientTrainer: NaN safety end to end, exact checkpoint resume, argument checks."""
import io

import pytest
import torch

from torchrl_diffenvs import make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.envs import PendulumEnv
from torchrl_diffenvs.modules import ObservationNormalizer, make_actor, make_critic
from torchrl_diffenvs.objectives import BPTTLoss, SHACLoss
from torchrl_diffenvs.trainers import GradientTrainer, evaluate_policy


class PoisonedPendulum(PendulumEnv):
    """Pendulum whose rewards are NaN while ``poisoned`` is set."""

    poisoned = False

    def transition(self, state, action, params):
        next_state, reward, terminated = super().transition(state, action, params)
        if self.poisoned:
            reward = reward + float("nan")
        return next_state, reward, terminated


def make_trainer(loss_name, env=None, seed=0):
    torch.manual_seed(seed)
    env = env if env is not None else make_env("pendulum", num_envs=8, seed=seed, max_episode_steps=10)
    normalizer = ObservationNormalizer(env.observation_dim)
    actor = make_actor(env, hidden=(16,), normalizer=normalizer)
    if loss_name == "shac":
        loss = SHACLoss(actor, make_critic(env, hidden=(16,), normalizer=normalizer))
    else:
        loss = BPTTLoss(actor)
    collector = DiffWindowCollector(env, actor, horizon=6)
    return GradientTrainer(collector, loss, actor_lr=1e-2, critic_passes=2, critic_minibatches=2,
                           total_iterations=20, normalizer=normalizer)


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_nan_rewards_skip_every_update(loss_name):
    env = PoisonedPendulum(num_envs=8, seed=0, max_episode_steps=10)
    trainer = make_trainer(loss_name, env)
    trainer.step()  # a healthy step first: optimiser state exists
    weights = dict(trainer.loss.named_parameters())  # actor and critic weights (not the target's)
    before = {k: v.detach().clone() for k, v in weights.items()}
    env.poisoned = True
    metrics = trainer.step()
    assert metrics["actor_skipped"] == 1
    if loss_name == "shac":
        assert metrics["critic_skipped"] == 2 * 2  # every critic minibatch step
    assert len(before) == (13 if loss_name == "shac" else 7)  # the critic's weights are included
    for key, value in before.items():
        torch.testing.assert_close(weights[key].detach(), value, rtol=0, atol=0, msg=key)
    env.poisoned = False
    assert trainer.step()["actor_skipped"] == 1  # training goes on


@pytest.mark.parametrize("loss_name", ["bptt", "shac"])
def test_checkpoint_resume_is_exact(loss_name):
    trainer = make_trainer(loss_name)
    for _ in range(3):
        trainer.step()
    buffer = io.BytesIO()
    torch.save(trainer.state_dict(), buffer)
    torch.manual_seed(123)
    expected = [trainer.step()["loss_actor"] for _ in range(3)]

    resumed = make_trainer(loss_name, seed=7)  # other initial weights and env seed
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    torch.manual_seed(123)
    assert [resumed.step()["loss_actor"] for _ in range(3)] == pytest.approx(expected, rel=1e-6)
    for (k, a), b in zip(trainer.loss.state_dict().items(), resumed.loss.state_dict().values()):
        torch.testing.assert_close(a, b, msg=k)
    assert resumed.iteration == trainer.iteration == 6


def test_evaluate_policy_and_argument_checks():
    trainer = make_trainer("bptt")
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=10)
    result = evaluate_policy(env, trainer.loss.actor_network)
    assert set(result) == {"reward_mean", "return_mean", "tail_reward_mean"}
    assert result["return_mean"] == pytest.approx(10 * result["reward_mean"], rel=1e-5)
    with pytest.raises(ValueError, match="lr_schedule"):
        GradientTrainer(trainer.collector, trainer.loss, lr_schedule="cosine")
    with pytest.raises(TypeError, match="BPTTLoss or SHACLoss"):
        GradientTrainer(trainer.collector, torch.nn.Linear(1, 1))


def test_evaluate_policy_counts_only_the_first_episode():
    """CartPole-v1 pays +1 per step, so each env's return is the length of its first episode."""
    from torchrl.envs.utils import RandomPolicy

    env = make_env("CartPole-v1", num_envs=8, dtype=torch.float64, seed=3, max_episode_steps=60)
    torch.manual_seed(0)
    stats = evaluate_policy(env, RandomPolicy(env.action_spec))
    torch.manual_seed(0)
    env.set_seed(3)
    done = env.rollout(60, RandomPolicy(env.action_spec), break_when_any_done=False)["next", "done"]
    lengths = []
    for row in done.squeeze(-1).tolist():  # hand count: steps up to the first done
        lengths.append(row.index(True) + 1 if True in row else len(row))
    assert min(lengths) < 60  # random actions do make some pole fall before the limit
    assert stats["return_mean"] == pytest.approx(sum(lengths) / len(lengths))
    assert stats["reward_mean"] == pytest.approx(1.0)
