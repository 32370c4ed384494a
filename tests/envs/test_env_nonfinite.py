"""Non-finite envs: a NaN/inf state or reward never raises out of a step and never stays.

The base class flags the env (``"nonfinite"``), marks it terminated (so an auto-reset restarts
it) and zeroes the non-finite elements of its observation and reward. References: the same
batch with the env finite (the other envs bit-identical, their gradients equal), TorchRL's own
``EnvBase.rollout`` on the same env (the lean loop equal to it), TorchRL's ``check_env_specs``.
"""
import pytest
import torch
from torchrl.envs import EnvBase
from torchrl.envs.utils import check_env_specs

from torchrl_diffenvs import compile_physics, eager_physics, make_env

from _env_helpers import assert_same_tensordict

F64 = torch.float64


def nan_state_start(env, index):
    """A reset TensorDict whose env ``index`` has a NaN state (every entry)."""
    td = env.reset()
    state = td["state"].clone()
    for key, value in state.items():
        value[index] = float("nan")
        state.set(key, value)
    return env.reset(td.set("state", state), set_state=True)


@pytest.mark.parametrize("name", ["CartPole-v1", "Hopper-v5", "cartpole", "pendulum", "InvertedPendulum-v5"])
def test_a_nan_state_is_flagged_terminated_and_reset(name):
    """NaN comparisons are false: without the flag a NaN CartPole-v1 or Hopper never terminates."""
    env = make_env(name, num_envs=3, seed=0, dtype=F64)
    td = nan_state_start(env, 1)
    step = env.step(td.clone().set("action", torch.zeros(3, env.action_dim, dtype=F64)))["next"]
    assert step["nonfinite"].squeeze(-1).tolist() == [False, True, False]
    assert step["terminated"][1].item() and step["done"][1].item()
    assert torch.isfinite(step["observation"]).all() and torch.isfinite(step["reward"]).all()
    # a rollout restarts it: from its next step on, env 1 is a fresh, finite episode
    out = env.rollout(4, actions=[torch.zeros(3, env.action_dim, dtype=F64)] * 4, auto_reset=False,
                      tensordict=td, break_when_any_done=False)
    assert out["next", "nonfinite"][1, 0].item() and not out["next", "nonfinite"][:, 1:].any()
    assert out["episode_step"][1, 1].item() == 0
    for key, value in out["state"].items():
        assert torch.isfinite(value[:, 1:]).all(), key


def assert_same_with_nan(got, ref, exact):
    """:func:`assert_same_tensordict` where the entries that hold the NaN (the NaN env's
    parameters and its next states) are compared with NaN equal to NaN."""
    nan_keys = [("params", "mass"), ("next", "params", "mass"),
                *[("next", "state", key) for key in ref["next", "state"].keys()]]
    assert_same_tensordict(got.exclude(*nan_keys), ref.exclude(*nan_keys), exact=exact)
    tol = dict(rtol=0, atol=0) if exact else dict(rtol=1e-10, atol=1e-12)
    for key in nan_keys:
        torch.testing.assert_close(got[key], ref[key], equal_nan=True, **tol)


def rollout_with_mass(name, mass_key, bad_value, actions, fast=True, compiled=False):
    """A rollout of 4 envs where env 2's mass entry is ``bad_value``, with gradients w.r.t. ``actions``."""
    probe = make_env(name, num_envs=4, seed=0, dtype=F64)
    mass = probe.params[mass_key].clone()
    mass[2] = bad_value
    env = make_env(name, num_envs=4, seed=3, dtype=F64, max_episode_steps=4, params={mass_key: mass})
    if compiled:
        compile_physics(env, steps_per_chunk=2, backend="aot_eager")
    actions = actions.clone().requires_grad_(True)
    path = env.rollout if fast else (lambda *a, **k: EnvBase.rollout(env, *a, **k))
    out = path(actions.shape[0], actions=list(actions), break_when_any_done=False)
    eager_physics(env)
    return out, actions


@pytest.mark.parametrize("name, mass_key", [("pendulum", "mass"), ("cartpole", "pole_mass"),
                                            ("InvertedPendulum-v5", "body_mass")])
def test_one_env_at_nan_mass_leaves_the_others_bit_identical(name, mass_key):
    actions = torch.rand(9, 4, 1, dtype=F64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    dirty, dirty_actions = rollout_with_mass(name, mass_key, float("nan"), actions)
    clean, clean_actions = rollout_with_mass(name, mass_key, 1.0, actions)
    others = [0, 1, 3]
    assert_same_tensordict(dirty[others].exclude("params", ("next", "params")),
                           clean[others].exclude("params", ("next", "params")))
    assert dirty["next", "nonfinite"][2].all() and not dirty["next", "nonfinite"][others].any()
    assert dirty["next", "terminated"][2].all()
    for key in ("observation", "reward"):
        assert torch.isfinite(dirty["next", key]).all(), key
    # the finite envs' gradients are those of the run without the NaN env
    w = torch.linspace(0.5, 1.5, dirty["next", "observation"].shape[-1], dtype=F64)
    (dirty_grad,) = torch.autograd.grad((dirty[others]["next", "observation"] * w).sum()
                                        + dirty[others]["next", "reward"].sum(), dirty_actions)
    (clean_grad,) = torch.autograd.grad((clean[others]["next", "observation"] * w).sum()
                                        + clean[others]["next", "reward"].sum(), clean_actions)
    assert torch.isfinite(dirty_grad[:, others]).all() and (dirty_grad[:, others] != 0).any()
    assert torch.equal(dirty_grad[:, others], clean_grad[:, others])


def test_the_lean_loop_equals_envbase_rollout_with_a_nan_env():
    actions = torch.rand(9, 4, 1, dtype=F64, generator=torch.Generator().manual_seed(1)) * 2 - 1
    fast, _ = rollout_with_mass("pendulum", "mass", float("nan"), actions, fast=True)
    ref, _ = rollout_with_mass("pendulum", "mass", float("nan"), actions, fast=False)
    assert ref["next", "nonfinite"].any()
    assert_same_with_nan(fast, ref, exact=True)


def test_compiled_chunks_flag_and_reset_a_nan_env_as_eagerly():
    actions = torch.rand(8, 4, 1, dtype=F64, generator=torch.Generator().manual_seed(2)) * 2 - 1
    eager, _ = rollout_with_mass("pendulum", "mass", float("nan"), actions)
    compiled, _ = rollout_with_mass("pendulum", "mass", float("nan"), actions, compiled=True)
    assert eager["next", "nonfinite"][2].all()
    assert_same_with_nan(compiled, eager, exact=False)


@pytest.mark.parametrize("name", ["pendulum", "CartPole-v1", "Hopper-v5", "multi_swimmer"])
def test_the_flag_is_in_the_specs(name):
    env = make_env(name, num_envs=2, seed=0)
    check_env_specs(env)
    assert env.observation_spec["nonfinite"].dtype == torch.bool
    assert env.reset()["nonfinite"].shape == (2, 1)
