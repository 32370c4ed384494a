"""Every learner on a ``TransformedEnv`` whose transforms change the observation's size or dtype.

Reference: the transformed env's own specs. The networks and the observation normaliser must be
built for what the transforms output (``CatFrames`` and ``CatTensors`` change the size,
``DoubleToFloat`` the dtype, ``ObservationNorm`` neither), never for the base env, whose
attributes (``observation_dim``, ``float_dtype``) a ``TransformedEnv`` forwards unchanged.
"""

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn
from torchrl.envs import (
    CatFrames,
    CatTensors,
    Compose,
    DoubleToFloat,
    ObservationNorm,
    TransformedEnv,
)

from torchrl_diffenvs import make_env
from torchrl_diffenvs.learners import LEARNERS, make_learner
from torchrl_diffenvs.modules import env_dims, make_actor

BASE_DIM = 16  # the swimmer's observation


def _cat_state(out_key="observation"):
    # the observation and the velocity, concatenated into the observation the networks read
    return CatTensors(in_keys=["observation", ("state", "vel")], out_key=out_key, del_keys=False)


# name -> (base env dtype, transform factory, expected observation size, expected network dtype)
TRANSFORMS = {
    "catframes": (torch.float32, lambda: CatFrames(N=2, in_keys=["observation"], dim=-1), 2 * BASE_DIM,
                  torch.float32),
    "double_to_float": (torch.float64, lambda: DoubleToFloat(), BASE_DIM, torch.float32),
    "cattensors": (torch.float32, _cat_state, BASE_DIM + 2, torch.float32),
    "observation_norm": (torch.float64, lambda: ObservationNorm(
        loc=torch.linspace(-1, 1, BASE_DIM, dtype=torch.float64), scale=torch.full((BASE_DIM,), 2.0, dtype=torch.float64),
        in_keys=["observation"]), BASE_DIM, torch.float64),
    "compose": (torch.float64, lambda: Compose(
        _cat_state(),
        DoubleToFloat(in_keys=["observation", "reward"], in_keys_inv=["action"]),
        CatFrames(N=3, in_keys=["observation"], dim=-1),
        ObservationNorm(loc=torch.zeros(3 * (BASE_DIM + 2)), scale=torch.full((3 * (BASE_DIM + 2),), 0.5),
                        in_keys=["observation"])), 3 * (BASE_DIM + 2), torch.float32),
}

SMALL = {
    "bptt": {"horizon": 4, "obs_norm": True},
    "shac": {"horizon": 4, "obs_norm": True},
    "ppo": {"rollout_len": 4, "minibatch_size": 16, "epochs": 1, "obs_norm": True},
    "sac": {"rollout_len": 2, "init_random_frames": 0, "batch_size": 8, "buffer_size": 64},
    "sapo": {"horizon": 4, "critic_passes": 2, "critic_minibatches": 2, "obs_norm": True},
}
# AHAC builds its actor and critics with SHAC's builders (covered by "shac" here) and needs an env
# that reports contact forces, which the swimmer these transforms wrap does not
NOT_COVERED = {"ahac"}


def loss_section(name: str):
    cfg = OmegaConf.create(LEARNERS[name].default_config()["loss"])
    for network in ("actor", "critic", "qvalue"):
        if network in cfg:
            cfg[network].hidden = [16]
    return OmegaConf.merge(cfg, SMALL[name])


def transformed(kind: str, num_envs: int = 8):
    dtype, transform, _, _ = TRANSFORMS[kind]
    return TransformedEnv(make_env("swimmer", num_envs=num_envs, seed=0, dtype=dtype), transform())


def first_linear(module: nn.Module) -> nn.Linear:
    return next(m for m in module.modules() if isinstance(m, nn.Linear))


def test_every_registered_learner_is_covered():
    assert sorted(SMALL) == sorted(set(LEARNERS) - NOT_COVERED)


@pytest.mark.parametrize("kind", sorted(TRANSFORMS))
def test_env_dims_reads_the_transformed_specs(kind):
    env = transformed(kind, num_envs=2)
    _, _, size, dtype = TRANSFORMS[kind]
    assert env_dims(env) == (size, 2, dtype)
    assert env.observation_spec["observation"].shape[-1] == size  # the reference the learners must follow
    if size != BASE_DIM or dtype != env.base_env.float_dtype:
        # the attributes forwarded from the base env are what the learners used to read: wrong here
        assert (env.observation_dim, env.float_dtype) != (size, dtype)


@pytest.mark.parametrize("kind", sorted(TRANSFORMS))
@pytest.mark.parametrize("loss", sorted(SMALL))
def test_learners_build_from_the_transformed_specs_and_train(loss, kind):
    torch.manual_seed(0)
    env = transformed(kind)
    _, _, size, dtype = TRANSFORMS[kind]
    spec = env.observation_spec["observation"]
    assert (spec.shape[-1], spec.dtype) == (size, dtype)
    learner = make_learner(loss_section(loss), env, 10_000)
    actor_in = first_linear(learner.actor)
    assert actor_in.in_features == size and actor_in.weight.dtype == dtype
    if loss == "sac":
        assert first_linear(learner.loss.qvalue_network).in_features == size + 2  # Q(observation, action)
    else:
        if loss != "bptt":
            critic = learner.loss.critic_network
            assert first_linear(critic).in_features == size and first_linear(critic).weight.dtype == dtype
        assert learner.normalizer.mean.shape == (size,) and learner.normalizer.mean.dtype == dtype
    params = list(learner.actor.parameters())
    before = [p.detach().clone() for p in params]
    for _ in range(3):
        metrics = learner.train_iteration()
    losses = {k: v for k, v in metrics.items() if k.startswith("loss")}
    assert losses and all(torch.isfinite(torch.tensor(v)) for v in losses.values()), metrics
    assert any(not torch.equal(a, b) for a, b in zip(before, params))  # the actor learned
    if loss != "sac":
        assert learner.normalizer.count > 0  # its statistics follow the transformed observations


def test_actor_reads_a_key_added_by_a_transform():
    """``CatTensors`` into a new key: the actor reads that key, sized from its spec; the learner
    updates the normaliser from the key the actor reads."""
    from torchrl_diffenvs.learners import BPTTConfig, BPTTLearner
    from torchrl_diffenvs.modules import ObservationNormalizer

    torch.manual_seed(0)
    env = TransformedEnv(make_env("swimmer", num_envs=8, seed=0), _cat_state("obs_full"))
    normalizer = ObservationNormalizer(env_dims(env, "obs_full")[0])
    actor = make_actor(env, hidden=(16,), normalizer=normalizer, in_key="obs_full")
    assert first_linear(actor).in_features == BASE_DIM + 2
    learner = BPTTLearner(env, actor, BPTTConfig(horizon=4), 10_000, normalizer=normalizer)
    assert torch.isfinite(torch.tensor(learner.train_iteration()["loss_actor"]))
    assert normalizer.count == 8 * 4


def test_mismatched_observation_and_action_dtypes_are_refused_with_the_fix():
    env = TransformedEnv(make_env("swimmer", num_envs=2, dtype=torch.float64), DoubleToFloat(in_keys=["observation"]))
    with pytest.raises(ValueError, match=r"torch.float32 but the action is torch.float64.*in_keys_inv=\['action'\]"):
        make_actor(env)
