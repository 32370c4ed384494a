"""The gradient learners on envs that are not ours: TorchRL's own PendulumEnv (batch-unlocked,
batched through its parameters at reset, as in TorchRL's pendulum tutorial) and an EnvBase written
by a user with TorchRL's API; and the errors for envs they cannot work with."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import CatTensors, EnvBase, TransformedEnv, UnsqueezeTransform
from torchrl.envs import PendulumEnv as TorchRLPendulumEnv

from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner, SHACConfig, SHACLearner
from torchrl_diffenvs.modules import env_dims, make_actor, make_critic


def torchrl_tutorial_pendulum():
    """TorchRL's PendulumEnv with transforms as in its tutorial: observation = (th, thdot)."""
    env = TransformedEnv(
        TorchRLPendulumEnv(),
        UnsqueezeTransform(dim=-1, in_keys=["th", "thdot"], in_keys_inv=["th", "thdot"]),
    )
    env.append_transform(CatTensors(in_keys=["th", "thdot"], out_key="observation", del_keys=False))
    return env


class DoubleIntegrator(EnvBase):
    """A user's differentiable EnvBase: x'' = a, reward -(x^2 + 0.1 v^2), 20-step episodes."""

    def __init__(self, num_envs: int, detach_outputs: bool = False):
        super().__init__(batch_size=[num_envs])
        self.detach_outputs = detach_outputs
        self.observation_spec = Composite(observation=Unbounded((num_envs, 2)), step=Unbounded((num_envs,), dtype=torch.int64),
                                          shape=(num_envs,))
        self.action_spec = Bounded(-1.0, 1.0, (num_envs, 1))
        self.reward_spec = Unbounded((num_envs, 1))

    def _reset(self, tensordict):
        x = torch.rand(self.batch_size[0], 1) * 2 - 1
        obs = torch.cat([x, torch.zeros_like(x)], -1)
        return TensorDict({"observation": obs, "step": torch.zeros(self.batch_size, dtype=torch.int64),
                           "done": torch.zeros(*self.batch_size, 1, dtype=torch.bool),
                           "terminated": torch.zeros(*self.batch_size, 1, dtype=torch.bool)}, self.batch_size)

    def _step(self, tensordict):
        obs, action = tensordict["observation"], tensordict["action"]
        x, v = obs[..., :1], obs[..., 1:]
        v = v + 0.1 * action
        x = x + 0.1 * v
        reward = -(x**2 + 0.1 * v**2)
        obs = torch.cat([x, v], -1)
        if self.detach_outputs:
            obs, reward = obs.detach(), reward.detach()
        step = tensordict["step"] + 1
        done = (step >= 20).unsqueeze(-1)
        return TensorDict({"observation": obs, "reward": reward, "step": step, "done": done,
                           "terminated": torch.zeros_like(done)}, self.batch_size)

    def _set_seed(self, seed):
        torch.manual_seed(seed)


def window_return(learner, reset_input=None, steps=20):
    env = learner.env
    td = env.reset(reset_input(), set_state=False) if reset_input is not None else env.reset()
    with torch.no_grad():
        rollout = env.rollout(steps, learner.policy, tensordict=td, auto_reset=False)
    return rollout["next", "reward"].sum(-2).mean().item()


@pytest.mark.parametrize("algorithm", ["bptt", "shac"])
def test_torchrl_pendulum_env_trains(algorithm):
    torch.manual_seed(0)
    env = torchrl_tutorial_pendulum()
    assert env.batch_size == torch.Size([]) and not env.batch_locked
    assert env_dims(env) == (2, 1, torch.float32)  # read from the specs
    reset_input = lambda: env.gen_params(batch_size=[32])  # noqa: E731 (as in TorchRL's tutorial)
    actor = make_actor(env, hidden=(32, 32))
    if algorithm == "bptt":
        learner = BPTTLearner(env, actor, BPTTConfig(horizon=10, actor_lr=5e-3, obs_norm=False), 32 * 10 * 40,
                              reset_input=reset_input)
    else:
        learner = SHACLearner(env, actor, make_critic(env, hidden=(32, 32)),
                              SHACConfig(horizon=10, actor_lr=5e-3, obs_norm=False), 32 * 10 * 40,
                              reset_input=reset_input)
    assert learner.num_envs == 32 and learner.env_steps_per_iteration == 320
    before = [p.detach().clone() for p in actor.parameters()]
    for _ in range(3):
        metrics = learner.train_iteration()
        assert torch.isfinite(torch.tensor(metrics["loss_actor"])) and metrics["grad_norm_actor"] > 0
    assert metrics["skipped_actor"] == 0
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, actor.parameters()))
    # the collector carries TorchRL's pendulum state (th, thdot, params) across windows
    assert learner.collector._carried.batch_size == torch.Size([32])
    assert torch.isfinite(torch.tensor(window_return(learner, reset_input)))


@pytest.mark.parametrize("algorithm", ["bptt", "shac"])
def test_a_user_written_envbase_learns(algorithm):
    """The gradient learners improve a user's EnvBase policy: return of 20-step episodes from the
    same start states, before and after 40 iterations."""
    torch.manual_seed(0)
    env = DoubleIntegrator(64)
    actor = make_actor(env, hidden=(32,))
    if algorithm == "bptt":
        learner = BPTTLearner(env, actor, BPTTConfig(horizon=20, actor_lr=1e-2, obs_norm=False), 64 * 20 * 40)
    else:
        learner = SHACLearner(env, actor, make_critic(env, hidden=(32,)),
                              SHACConfig(horizon=10, actor_lr=1e-2, obs_norm=False), 64 * 10 * 40)
    torch.manual_seed(1)
    before = window_return(learner)
    for _ in range(40):
        learner.train_iteration()
    torch.manual_seed(1)
    after = window_return(learner)
    assert after > before + 0.3 * abs(before), (before, after)


def test_an_env_without_batch_dimension_is_refused_with_the_fix():
    env = torchrl_tutorial_pendulum()
    with pytest.raises(ValueError, match=r"batch size \[N\], got \(\).*reset_input=lambda: env.gen_params"):
        BPTTLearner(env, make_actor(env), BPTTConfig(horizon=4), 1000)


def test_an_env_without_gradients_is_refused_with_what_is_missing():
    env = DoubleIntegrator(8, detach_outputs=True)
    learner = BPTTLearner(env, make_actor(env, hidden=(8,)), BPTTConfig(horizon=4, obs_norm=False), 1000)
    with pytest.raises(RuntimeError, match="without gradient w.r.t. the actions.*need a differentiable env"):
        learner.train_iteration()


def test_an_env_without_the_observation_entry_is_refused():
    with pytest.raises(ValueError, match="the networks read 'observation'.*CatTensors"):
        make_actor(TorchRLPendulumEnv())
