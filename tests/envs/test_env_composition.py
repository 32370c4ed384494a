"""The envs composed with TorchRL: transforms, probabilistic actors, collectors, partial resets.

References: the bare env (a transform must not change the physics), finite differences (the
gradient through a sampled TanhNormal policy), and the episode structure (a reset cuts the
gradient of exactly the envs that reset). ``check_env_specs`` in both dtypes is in
test_envs_basic.py.
"""
import warnings

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import (
    Compose, DoubleToFloat, InitTracker, ObservationNorm, RewardSum, StepCounter, TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type, step_mdp
from torchrl.modules import ProbabilisticActor, TanhNormal

from _env_helpers import classic_envs, F64, ReplayPolicy, in_spec_actions, make, obs_weights, signal, use_rollout_path

ALL_ENVS = classic_envs()


def _norm_params(env, dtype=None):
    """Fixed, non-trivial ObservationNorm loc / scale ``[obs_dim]`` (default: the env's dtype)."""
    d, dtype = env.observation_dim, dtype or env.float_dtype
    return torch.linspace(-1.0, 1.0, d, dtype=dtype), torch.linspace(0.5, 2.0, d, dtype=dtype)


def _transformed(name, n, seed, max_steps, with_double_to_float=False):
    env = make(name, n, seed=seed, max_episode_steps=max_steps)
    # after a DoubleToFloat the observation is float32, and so must be loc / scale
    loc, scale = _norm_params(env, torch.float32 if with_double_to_float else None)
    transforms = [StepCounter(), RewardSum(), InitTracker(),
                  ObservationNorm(loc=loc, scale=scale, in_keys=["observation"])]
    if with_double_to_float:
        # casting only what the policy sees keeps the physics in float64 (see test below)
        transforms.insert(0, DoubleToFloat(in_keys=["observation", "reward"], in_keys_inv=["action"]))
    return TransformedEnv(env, Compose(*transforms))


# ---------------------------------------------------------------------------- transforms
@pytest.mark.parametrize("name", ALL_ENVS)
def test_transforms_leave_the_physics_alone(name):
    """StepCounter, RewardSum, InitTracker, ObservationNorm: state and dynamics are the bare env's,
    the observation is normalised, and the transforms count and sum correctly across resets."""
    n, steps = 3, 7
    bare = make(name, n, seed=2, max_episode_steps=3)
    env = _transformed(name, n, seed=2, max_steps=3)
    actions = in_spec_actions(bare, n, steps)
    ref = bare.rollout(steps, ReplayPolicy(actions), break_when_any_done=False)
    out = env.rollout(steps, ReplayPolicy(actions), break_when_any_done=False)

    for key in ref["next", "state"].keys():
        assert torch.equal(out["next", "state", key], ref["next", "state", key]), key
    assert torch.equal(out["next", "reward"], ref["next", "reward"])
    loc, scale = _norm_params(bare)
    # ObservationNorm (standard_normal=False) computes obs * scale + loc
    torch.testing.assert_close(out["next", "observation"], ref["next", "observation"] * scale + loc)
    assert not torch.equal(out["next", "observation"], ref["next", "observation"])
    # the state the dynamics read is never the normalised observation
    first_state_key = sorted(ref["state"].keys())[0]
    assert not torch.equal(out["next", "observation"][..., 0], out["next", "state", first_state_key])
    # StepCounter mirrors episode_step, InitTracker flags the first step of each episode
    assert torch.equal(out["next", "step_count"][..., 0], ref["next", "episode_step"])
    assert torch.equal(out["is_init"][..., 0], ref["episode_step"] == 0)
    # RewardSum accumulates within an episode and restarts after the reset
    expected = torch.cat([ref["next", "reward"][:, :3].cumsum(1), ref["next", "reward"][:, 3:6].cumsum(1),
                          ref["next", "reward"][:, 6:].cumsum(1)], dim=1)
    torch.testing.assert_close(out["next", "episode_reward"], expected)


@pytest.mark.parametrize("name", ALL_ENVS)
def test_gradients_flow_through_transformed_env(name):
    """Through TransformedEnv.rollout, d(sum of signal)/d(actions) equals the bare env's gradient."""
    n, steps = 2, 6
    bare = make(name, n, seed=3, max_episode_steps=None)
    env = _transformed(name, n, seed=3, max_steps=None)
    a_bare = in_spec_actions(bare, n, steps).requires_grad_()
    a_env = a_bare.detach().clone().requires_grad_()
    w = obs_weights(bare)
    loc, scale = _norm_params(bare)
    ref = bare.rollout(steps, ReplayPolicy(a_bare), break_when_any_done=False)
    out = env.rollout(steps, ReplayPolicy(a_env), break_when_any_done=False)
    # same signal, computed from the normalised observation
    bare_signal = signal(ref, w).sum()
    env_signal = (out["next", "reward"][..., 0] + (((out["next", "observation"] - loc) / scale) * w).sum(-1)).sum()
    (g_bare,) = torch.autograd.grad(bare_signal, a_bare)
    (g_env,) = torch.autograd.grad(env_signal, a_env)
    assert g_bare.abs().sum() > 0
    torch.testing.assert_close(g_env, g_bare, rtol=1e-10, atol=1e-12)


def test_double_to_float_on_a_float64_env():
    """DoubleToFloat on the policy-facing keys: float32 observations/actions, float64 physics
    identical to the bare env's, gradients reaching the float32 actions."""
    n, steps = 3, 6
    bare = make("cartpole", n, seed=4, max_episode_steps=4)
    env = _transformed("cartpole", n, seed=4, max_steps=4, with_double_to_float=True)
    assert env.action_spec.dtype == torch.float32
    assert env.observation_spec["observation"].dtype == torch.float32
    actions32 = in_spec_actions(bare, n, steps).float().requires_grad_()
    out = env.rollout(steps, ReplayPolicy(actions32), break_when_any_done=False)
    ref = bare.rollout(steps, ReplayPolicy(actions32.detach().double()), break_when_any_done=False)
    assert out["next", "observation"].dtype == torch.float32 and out["next", "reward"].dtype == torch.float32
    assert out["next", "state", "th"].dtype == F64
    for key in ref["next", "state"].keys():
        assert torch.equal(out["next", "state", key], ref["next", "state", key]), key
    (grad,) = torch.autograd.grad(out["next", "reward"].sum(), actions32)
    assert grad.dtype == torch.float32 and grad[:, :3].abs().sum() > 0
    check_env_specs(env)  # last: it resets the env (and so advances its generator)


def test_double_to_float_default_keys_round_the_state():
    """DoubleToFloat() without keys also casts "state" and "params" (they are in the observation
    spec) to float32 between steps: rollouts and gradients work, but the physics then runs on
    float32-rounded states. Documented here so that the difference is a known one."""
    n, steps = 2, 5
    bare = make("pendulum", n, seed=4, max_episode_steps=None)
    env = TransformedEnv(make("pendulum", n, seed=4, max_episode_steps=None), DoubleToFloat())
    actions32 = in_spec_actions(bare, n, steps).float().requires_grad_()
    out = env.rollout(steps, ReplayPolicy(actions32), break_when_any_done=False)
    ref = bare.rollout(steps, ReplayPolicy(actions32.detach().double()), break_when_any_done=False)
    assert out["next", "state", "th"].dtype == torch.float32
    diff = (out["next", "state", "th"].double() - ref["next", "state", "th"]).abs().max()
    assert 0 < diff < 1e-5
    (grad,) = torch.autograd.grad(out["next", "reward"].sum(), actions32)
    assert grad.abs().sum() > 0


# ---------------------------------------------------------------------------- policies
def _tanh_normal_actor(env, seed=0):
    torch.manual_seed(seed)
    dtype = env.float_dtype
    net = torch.nn.Sequential(
        torch.nn.Linear(env.observation_dim, 32, dtype=dtype), torch.nn.Tanh(),
        torch.nn.Linear(32, 2 * env.action_dim, dtype=dtype), NormalParamExtractor(),
    )
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    spec = env.action_spec
    return ProbabilisticActor(
        module, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low[0], "high": spec.space.high[0]},
    )


@pytest.mark.parametrize("transformed", [False, True], ids=["bare", "transformed"])
def test_tanh_normal_actor_gradients_match_finite_differences(transformed):
    """ProbabilisticActor(TanhNormal) sampled with rsample (ExplorationType.RANDOM): the
    gradient of the rollout's return w.r.t. a policy weight equals central differences when
    the sampling noise is held fixed (same torch seed for every evaluation)."""
    n, steps = 4, 12
    env = _transformed("reacher", n, seed=0, max_steps=None) if transformed else make("reacher", n, seed=0)
    actor = _tanh_normal_actor(env)
    start = env.reset()

    def objective():
        torch.manual_seed(123)  # fixed noise: the return is a smooth function of the weights
        with set_exploration_type(ExplorationType.RANDOM):
            td = env.rollout(steps, actor, tensordict=start.clone(), auto_reset=False)
        return td["next", "reward"].sum(), td["action"]

    ret, actions = objective()
    assert actions.abs().max() < 1  # TanhNormal keeps the actions inside the spec
    params = dict(actor.named_parameters())
    grads = torch.autograd.grad(ret, list(params.values()))
    for (pname, _), g in zip(params.items(), grads):
        assert torch.isfinite(g).all() and g.abs().sum() > 0, pname
    # the sample is random: another seed gives other actions
    with set_exploration_type(ExplorationType.RANDOM):
        other = env.rollout(steps, actor, tensordict=start.clone(), auto_reset=False)["action"]
    assert not torch.equal(other, actions.detach())

    weight = actor.module[0].module[0].weight
    (grad,) = torch.autograd.grad(objective()[0], weight)
    eps = 1e-6
    with torch.no_grad():
        for idx in [(0, 0), (7, 3), (20, 7)]:
            orig = weight[idx].item()
            weight[idx] = orig + eps
            plus = objective()[0]
            weight[idx] = orig - eps
            minus = objective()[0]
            weight[idx] = orig
            torch.testing.assert_close(grad[idx], (plus - minus) / (2 * eps), rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("name", ["swimmer", "CartPole-v1"])
def test_collector_yields_batches_of_the_right_shape(name):
    """torchrl.collectors.Collector runs our env and a TanhNormal policy (under no_grad)."""
    n, frames_per_env = 4, 8
    env = make(name, n, dtype=torch.float32, max_episode_steps=5)
    actor = _tanh_normal_actor(env)
    collector = Collector(env, actor, frames_per_batch=n * frames_per_env, total_frames=2 * n * frames_per_env,
                          auto_register_policy_transforms=False)  # a feed-forward policy needs no InitTracker
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch.batch_size == (n, frames_per_env)
        assert batch["action"].shape == (n, frames_per_env, env.action_dim)
        assert batch["next", "observation"].shape == (n, frames_per_env, env.observation_dim)
        assert batch["next", "reward"].shape == (n, frames_per_env, 1)
        assert not batch["next", "reward"].requires_grad  # collectors run under no_grad
        assert (batch["action"].abs() <= env.action_high).all()
    # episodes of 5 steps continue across batches: the collector auto-resets the done envs
    steps = torch.cat([b["next", "episode_step"] for b in batches], dim=1)
    assert torch.equal(steps[0], torch.tensor([1, 2, 3, 4, 5] * 3 + [1]))


# ---------------------------------------------------------------------------- partial resets
@pytest.mark.parametrize("name", ALL_ENVS)
def test_partial_reset_resets_only_the_masked_envs(name):
    n = 4
    env = make(name, n, seed=6)
    td = env.reset()
    td["action"] = in_spec_actions(env, n)
    td = step_mdp(env.step(td))
    before = td.clone()
    mask = torch.tensor([True, False, True, False])
    td["_reset"] = mask.unsqueeze(-1)
    after = env.reset(td, set_state=False)
    keep = ~mask
    for key in ["observation", "episode_step", *(("state", k) for k in before["state"].keys()),
                *(("params", k) for k in before["params"].keys())]:
        assert torch.equal(after[key][keep], before[key][keep]), key
    assert (after["episode_step"][mask] == 0).all() and (before["episode_step"] == 1).all()
    assert not torch.equal(after["observation"][mask], before["observation"][mask])
    assert not after["done"].any()


def test_partial_reset_with_set_state_restarts_from_the_given_state():
    """reset(td with "_reset", set_state=True): masked envs restart (episode_step 0) from the
    state in td; TorchRL's default (set_state unspecified) does the same, with a FutureWarning."""
    env = make("pendulum", 3, seed=0)
    td = env.reset()
    td["action"] = in_spec_actions(env, 3)
    td = step_mdp(env.step(td))
    td["state", "th"] = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    td["_reset"] = torch.tensor([[True], [False], [False]])
    out = env.reset(td.clone(), set_state=True)
    torch.testing.assert_close(out["state", "th"], torch.tensor([0.1, 0.2, 0.3], dtype=F64))
    assert out["episode_step"].tolist() == [0, 1, 1]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        implicit = env.reset(td.clone())
    assert any(issubclass(w.category, FutureWarning) for w in caught)
    assert torch.equal(implicit["state", "th"], out["state", "th"])


def _staggered_start(env):
    """A TensorDict whose envs are at episode steps [n-1, ..., 1, 0] (by partial resets)."""
    td = env.reset()
    n = env.num_envs
    for k in range(1, n):
        td["action"] = in_spec_actions(env, n, seed=k)
        td = step_mdp(env.step(td))
        td["_reset"] = (torch.arange(n) >= k).unsqueeze(-1)  # envs k.. start again
        td = env.reset(td, set_state=False)
    return td.detach()


@pytest.mark.parametrize("fast", [True, False], ids=["fast_rollout", "EnvBase.rollout"])
@pytest.mark.parametrize("name", ALL_ENVS)
def test_auto_reset_cuts_the_gradient_only_for_the_envs_that_reset(name, fast):
    """Envs at different episode steps reset at different times inside one rollout; the
    gradient of each env's signal is cut exactly at its own resets and nowhere else."""
    n, steps, max_steps = 3, 7, 3
    env = make(name, n, seed=8, max_episode_steps=max_steps)
    use_rollout_path(env, fast)
    start = _staggered_start(env)
    assert start["episode_step"].tolist() == [2, 1, 0]
    actions = in_spec_actions(env, n, steps).requires_grad_()
    traj = env.rollout(steps, ReplayPolicy(actions), tensordict=start, auto_reset=False,
                       break_when_any_done=False)
    done = traj["next", "done"][..., 0]
    # env i is done whenever its episode step reaches 3
    assert done.tolist() == [[True, False, False, True, False, False, True],
                             [False, True, False, False, True, False, False],
                             [False, False, True, False, False, True, False]]
    sig = signal(traj, obs_weights(env))
    episode = torch.cat([torch.zeros(n, 1, dtype=torch.long), done[:, :-1].long().cumsum(1)], dim=1)
    for t in range(steps):
        (grad,) = torch.autograd.grad(sig[:, t].sum(), actions, retain_graph=True)
        per_step = grad.abs().sum(-1)
        same_episode = (episode == episode[:, t : t + 1]) & (torch.arange(steps) <= t)
        assert (per_step[~same_episode] == 0).all(), f"step {t}: gradient leaks across a reset"
        assert (per_step[same_episode] > 0).all(), f"step {t}: gradient lost inside an episode"
