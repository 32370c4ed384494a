"""Asymmetric (privileged) critics: ``loss.critic_input=state`` for shac, ppo and sac, and the
partially observed pendulum (``observe_velocity=False``) that shows what they are for."""
from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs import PendulumEnv as TorchRLPendulumEnv

from torchrl_diffenvs import make_env
from torchrl_diffenvs.learners import make_learner
from torchrl_diffenvs.modules import make_critic, make_qvalue, privileged_inputs, update_privileged_statistics
from torchrl_diffenvs.training import ConfigError, validate_config

from _train_helpers import make_cfg


# ---------------------------------------------------------------------- the partially observed pendulum
def test_pendulum_without_velocity_observes_the_angle_only():
    full = make_env("pendulum", num_envs=5, seed=3, dtype=torch.float64)
    partial = make_env("pendulum", num_envs=5, seed=3, dtype=torch.float64, observe_velocity=False)
    assert (full.observation_dim, partial.observation_dim) == (3, 2)
    action = torch.full((5, 4, 1), 0.3, dtype=torch.float64)
    a, b = full.reset(), partial.reset()
    for t in range(4):
        a = full.step(a.set("action", action[:, t]))["next"]
        b = partial.step(b.set("action", action[:, t]))["next"]
        torch.testing.assert_close(b["observation"], a["observation"][:, :2], rtol=0, atol=0)
        torch.testing.assert_close(b["state", "thd"], a["state", "thd"], rtol=0, atol=0)
    th = b["state", "th"]
    torch.testing.assert_close(b["observation"], torch.stack([th.cos(), th.sin()], -1))
    with pytest.raises(ValueError, match="observe_velocity must be true or false"):
        make_env("pendulum", num_envs=2, observe_velocity="no")


def test_swimmer_without_urchins_observes_position_velocity_and_goal():
    full = make_env("swimmer", num_envs=4, seed=2, dtype=torch.float64)
    partial = make_env("swimmer", num_envs=4, seed=2, dtype=torch.float64, observe_urchins=False)
    assert (full.observation_dim, partial.observation_dim) == (16, 6)
    a, b = full.reset(), partial.reset()
    for _ in range(3):
        a = full.step(a.set("action", torch.full((4, 2), 0.5, dtype=torch.float64)))["next"]
        b = partial.step(b.set("action", torch.full((4, 2), 0.5, dtype=torch.float64)))["next"]
        torch.testing.assert_close(b["observation"], a["observation"][:, 10:], rtol=0, atol=0)
        torch.testing.assert_close(b["reward"], a["reward"], rtol=0, atol=0)  # the urchins still sting
    with pytest.raises(ValueError, match="observe_urchins must be true or false"):
        make_env("swimmer", num_envs=2, observe_urchins=1)


def test_partial_pendulum_step_gradcheck():
    env = make_env("pendulum", num_envs=3, seed=0, dtype=torch.float64, observe_velocity=False)
    start = env.reset()

    def step(action, thd):
        td = start.clone()
        td.set(("state", "thd"), thd)
        td.set("action", action)
        out = env.step(td)["next"]
        return out["observation"], out["reward"]

    action = torch.tensor([[0.2], [-0.5], [0.9]], dtype=torch.float64, requires_grad=True)
    thd = start["state", "thd"].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(step, (action, thd))


# ---------------------------------------------------------------------- the networks
def test_privileged_critic_reads_observation_state_and_params_in_spec_order():
    env = make_env("pendulum", num_envs=4, seed=1, dtype=torch.float64, observe_velocity=False)
    keys = [key for key, _ in privileged_inputs(env)]
    assert keys == [("state", "th"), ("state", "thd"), ("params", "g"), ("params", "mass"), ("params", "length"),
                    ("params", "max_torque"), ("params", "dt")]
    torch.manual_seed(0)
    critic = make_critic(env, hidden=(8,), critic_input="state")
    assert critic.in_keys == ["observation", *keys]
    td = env.reset()
    privileged = torch.cat([td[key].unsqueeze(-1) for key in keys], -1)  # 7 inputs
    # their own running normaliser: identity (up to eps) before any update
    by_hand = torch.cat([td["observation"], privileged / math.sqrt(1 + 1e-5)], -1)
    assert by_hand.shape == (4, 9)
    torch.testing.assert_close(critic(td.clone())["state_value"], critic.module.net(by_hand))
    # after an update: standardised by the statistics of what it saw
    rollout = env.rollout(20)
    update_privileged_statistics(critic, rollout)
    seen = torch.cat([rollout[key].reshape(-1, 1) for key in keys], -1)
    mean, var = seen.mean(0), seen.var(0, unbiased=False)
    standardised = (privileged - mean) / torch.sqrt(var + 1e-5)
    torch.testing.assert_close(critic(td.clone())["state_value"],
                               critic.module.net(torch.cat([td["observation"], standardised], -1)))
    raw = make_critic(env, hidden=(8,), critic_input="state", privileged_norm=False)
    assert raw.module.privileged_normalizer is None
    # the value sees the velocity the observation hides
    faster = td.clone()
    faster.set(("state", "thd"), td["state", "thd"] + 1.0)
    assert not torch.allclose(critic(faster)["state_value"], critic(td.clone())["state_value"])


def test_privileged_inputs_flatten_multi_dimensional_entries():
    env = make_env("HalfCheetah-v5", num_envs=2, seed=0)
    sizes = dict(privileged_inputs(env))
    assert sizes[("state", "qpos")] == 9 and sizes[("state", "qvel")] == 9
    inertia_shape = env.observation_spec["params", "body_inertia"].shape[1:]  # per body, a 3 x 3 matrix
    assert len(inertia_shape) == 3 and sizes[("params", "body_inertia")] == math.prod(inertia_shape)
    qvalue = make_qvalue(env, hidden=(8,), critic_input="state")
    td = env.reset()
    td.set("action", torch.zeros(2, env.action_dim))
    assert qvalue(td)["state_action_value"].shape == (2, 1)
    assert qvalue.module.net[0].in_features == env.observation_dim + sum(sizes.values()) + env.action_dim


def test_an_env_without_state_entries_is_refused_with_the_fix():
    with pytest.raises(ValueError, match=r"no \('state', \.\.\.\) entries.*critic_input='observation'"):
        privileged_inputs(TorchRLPendulumEnv())


# ---------------------------------------------------------------------- the learners
def loss_section(name: str, **settings):
    from torchrl_diffenvs.learners import LEARNERS

    cfg = OmegaConf.create(LEARNERS[name].default_config()["loss"])  # the loss=<name> section
    for network in ("actor", "critic", "qvalue"):
        if network in cfg:
            cfg[network].hidden = [16]
    return OmegaConf.merge(cfg, settings)


SMALL = {
    "shac": {"horizon": 4},
    "ppo": {"rollout_len": 4, "minibatch_size": 16, "epochs": 1},
    "sac": {"rollout_len": 2, "init_random_frames": 0, "batch_size": 8, "buffer_size": 64},
}


@pytest.mark.parametrize("loss", sorted(SMALL))
def test_learners_train_a_privileged_critic_on_the_partial_pendulum(loss):
    env = make_env("pendulum", num_envs=8, seed=0, observe_velocity=False)
    learner = make_learner(loss_section(loss, critic_input="state", **SMALL[loss]), env, 10_000)
    critic = learner.loss.qvalue_network if loss == "sac" else learner.loss.critic_network
    assert ("state", "thd") in critic.in_keys and ("params", "g") in critic.in_keys
    assert "observation" in learner.actor.in_keys and ("state", "thd") not in learner.actor.in_keys
    # SACLoss trains its own (functional) copies of the Q-networks' parameters
    params = learner.qvalue_params if loss == "sac" else list(critic.parameters())
    before = [p.detach().clone() for p in params]
    for _ in range(2):
        metrics = learner.train_iteration()
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
    assert any(not torch.equal(a, b) for a, b in zip(before, params))  # the critic learned
    if loss == "sac":
        assert ("next", "state", "thd") in learner.buffer.sample(4).keys(True, True)
    else:
        # the privileged inputs' statistics moved, and the loss's critic (TorchRL's functional copy
        # of its parameters and buffers) scores with them
        norm = critic.module.privileged_normalizer
        assert norm.count == 2 * learner.env_steps_per_iteration and norm.mean.abs().sum() > 0
        loss_buffers = dict(learner.loss.critic_network_params.items(True, True))
        torch.testing.assert_close(loss_buffers[("module", "privileged_normalizer", "mean")], norm.mean)


def test_config_checks_critic_input():
    cfg = make_cfg("env=pendulum", "loss=ppo", "loss.critic_input=privileged")
    with pytest.raises(ConfigError, match=r"loss.critic_input='privileged'.*observation.*state"):
        validate_config(cfg)
    validate_config(make_cfg("env=pendulum", "loss=sac", "loss.critic_input=state",
                             "env.options.observe_velocity=false"))


# ---------------------------------------------------------------------- env.randomize
def test_randomized_physical_parameters_are_per_env_seeded_and_in_range():
    from torchrl_diffenvs.training import make_env_from_config

    cfg = make_cfg("env=pendulum", "loss=shac", "+env.randomize.mass=[0.5,1.5]", "+env.randomize.length=[0.7,1.3]")
    env = make_env_from_config(cfg, 64, seed=3)
    mass, length = env.params["mass"], env.params["length"]
    assert mass.shape == (64,) and 0.5 <= mass.min() < mass.max() <= 1.5
    assert 0.7 <= length.min() < length.max() <= 1.3
    assert (env.params["g"] == 9.8).all()  # the others stay at their defaults
    again, other = make_env_from_config(cfg, 64, seed=3), make_env_from_config(cfg, 64, seed=4)
    assert torch.equal(again.params["mass"], mass) and not torch.equal(other.params["mass"], mass)
    # the critic's privileged inputs see each env's own values
    from torchrl_diffenvs.modules import privileged_inputs

    assert (("params", "mass"), 1) in privileged_inputs(env)


@pytest.mark.parametrize("override, message", [
    ("+env.randomize.mass=[1.5,0.5]", "env.randomize.mass=[1.5, 0.5]: expected [low, high] with low <= high"),
    ("+env.randomize.mass=2", "env.randomize.mass=2: expected [low, high]"),
    ("+env.randomize.bogus=[0,1]", "unknown physical parameter(s) ['bogus']"),
    ("+env.params.mass=2", "env.randomize.mass and env.params.mass are both set: keep one"),
])
def test_bad_randomize_values_are_rejected(override, message):
    from torchrl_diffenvs.training import ConfigError, validate_config

    extra = ["+env.randomize.mass=[0.5,1.5]"] if override.startswith("+env.params") else []
    with pytest.raises(ConfigError) as err:
        validate_config(make_cfg("env=pendulum", "loss=shac", *extra, override))
    assert message in str(err.value)
