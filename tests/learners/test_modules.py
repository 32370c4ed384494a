"""make_actor's TanhNormalActor: its direct forward path against ProbabilisticActor.forward, bit for bit."""
import pytest
import torch
from tensordict.nn import InteractionType, set_interaction_type
from torchrl.modules import ProbabilisticActor

from torchrl_diffenvs import make_env
from torchrl_diffenvs.modules import ObservationNormalizer, TanhNormalActor, make_actor


def _forward_and_grads(actor, forward, td, seed):
    """Runs ``forward(td)`` from ``seed``; returns the outputs, the gradients of a fixed
    function of the action w.r.t. every actor parameter and the observation, and the RNG state."""
    td = td.clone()
    obs = td["observation"].detach().requires_grad_(True)
    td.set("observation", obs)
    torch.manual_seed(seed)
    out = forward(td)
    weights = torch.linspace(-1.0, 2.0, out["action"].numel(), dtype=out["action"].dtype).reshape(out["action"].shape)
    objective = (out["action"] * weights).sum() + out["action"].pow(2).sum()
    params = [p for p in actor.parameters() if p.requires_grad]
    grads = torch.autograd.grad(objective, [*params, obs], allow_unused=True)
    values = {key: out[key].detach().clone() for key in ("loc", "scale", "action")}
    return values, grads, torch.get_rng_state()


@pytest.mark.parametrize("env_name", ["pendulum", "cartpole", "reacher", "Pendulum-v1"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mode", [InteractionType.RANDOM, InteractionType.DETERMINISTIC, None])
def test_direct_forward_equals_probabilistic_actor_forward(env_name, dtype, mode):
    env = make_env(env_name, num_envs=7, dtype=dtype, seed=3)
    normalizer = ObservationNormalizer(env.observation_dim, dtype=dtype)
    normalizer.update(torch.randn(50, env.observation_dim, dtype=dtype) * 3 + 1)
    torch.manual_seed(0)
    actor = make_actor(env, normalizer=normalizer, init_log_std=0.5)  # wide: some actions near the bounds
    assert isinstance(actor, TanhNormalActor)
    td = env.reset()
    if mode is None:  # no interaction type set: ProbabilisticActor's default (DETERMINISTIC)
        ours = _forward_and_grads(actor, actor, td, seed=11)
        ref = _forward_and_grads(actor, lambda t: ProbabilisticActor.forward(actor, t), td, seed=11)
    else:
        with set_interaction_type(mode):
            ours = _forward_and_grads(actor, actor, td, seed=11)
            ref = _forward_and_grads(actor, lambda t: ProbabilisticActor.forward(actor, t), td, seed=11)
    for key in ("loc", "scale", "action"):
        assert torch.equal(ours[0][key], ref[0][key]), key
    low, high = env.action_spec_unbatched.space.low, env.action_spec_unbatched.space.high
    assert (ours[0]["action"] > low).all() and (ours[0]["action"] < high).all()
    for mine, theirs in zip(ours[1], ref[1]):
        assert (mine is None) == (theirs is None)
        if mine is not None:
            assert torch.equal(mine, theirs)
    assert torch.equal(ours[2], ref[2])  # the same draws from torch's global stream
    sampled = mode is InteractionType.RANDOM
    loc_action = ours[0]["loc"].tanh() * (high - low) / 2 + (high + low) / 2
    assert torch.allclose(ours[0]["action"], loc_action.to(dtype), atol=1e-6) != sampled


def test_calls_the_direct_path_does_not_cover_use_probabilistic_actor():
    env = make_env("pendulum", num_envs=4, seed=0)
    actor = make_actor(env, return_log_prob=True)
    td = env.reset()
    with set_interaction_type(InteractionType.RANDOM):
        torch.manual_seed(1)
        out = actor(td.clone())
        torch.manual_seed(1)
        ref = ProbabilisticActor.forward(actor, td.clone())
    assert torch.equal(out["action"], ref["action"])
    assert torch.equal(out["action_log_prob"], ref["action_log_prob"])
    # the log-probability is TanhNormal's, of that action
    assert torch.allclose(out["action_log_prob"], actor.get_dist(out).log_prob(out["action"]), atol=1e-5)
    # MEAN is not a direct mode: ProbabilisticActor estimates it from many samples
    plain = make_actor(env)
    with set_interaction_type(InteractionType.MEAN):
        torch.manual_seed(2)
        mean = plain(td.clone())["action"]
        torch.manual_seed(2)
        ref_mean = ProbabilisticActor.forward(plain, td.clone())["action"]
    assert torch.equal(mean, ref_mean)
    with set_interaction_type(InteractionType.DETERMINISTIC):
        squashed_loc = plain(td.clone())["action"]
    assert not torch.equal(mean, squashed_loc)  # an empirical mean, not the direct path's squashed loc


def test_normalizer_does_not_amplify_a_nearly_constant_feature_beyond_min_std():
    """A feature with std 1e-4 (a contact force while in the air) is divided by min_std (1e-2 by
    default), not by its own std; a feature with std 3 by its own: both against hand values."""
    norm = ObservationNormalizer(2, dtype=torch.float64)
    data = torch.stack([1.0 + 1e-4 * torch.randn(4000, dtype=torch.float64),
                        3.0 * torch.randn(4000, dtype=torch.float64)], dim=-1)
    norm.update(data)
    x = torch.tensor([[1.5, 6.0]], dtype=torch.float64, requires_grad=True)
    out = norm(x)
    mean, std = data.mean(0), data.std(0, unbiased=False)
    expected = torch.stack([(1.5 - mean[0]) / 1e-2, (6.0 - mean[1]) / torch.sqrt(std[1] ** 2 + 1e-5)])
    torch.testing.assert_close(out[0], expected)
    (grad,) = torch.autograd.grad(out.sum(), x)
    torch.testing.assert_close(grad[0, 0], torch.tensor(100.0, dtype=torch.float64))
    with pytest.raises(ValueError, match="min_std must be a finite number >= 0"):
        ObservationNormalizer(2, min_std=-1.0)
