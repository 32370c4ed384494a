"""The lean loop's shortcuts give EnvBase.rollout's results.

* resets merge start states from a table of each env's next episodes (``_StartTable``), which
  deepens while the envs reset at different steps;
* without a policy and without breaking, the steps skip the per-step finiteness check and the
  output is checked once: a non-finite value makes the loop step the same actions again with
  checks (and the env checks every step from then on).
"""
import torch
from torchrl.envs import EnvBase

from _env_helpers import assert_same_tensordict

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs.rollout import loop as loop_module

F64 = torch.float64


def both_paths(env, steps, seed=0, **kwargs):
    """(lean loop, EnvBase.rollout) from identical generator states, and the states they leave."""
    results, after = [], []
    for path in (env.rollout, lambda *a, **k: EnvBase.rollout(env, *a, **k)):
        torch.manual_seed(seed)
        env.set_seed(seed + 1)
        results.append(path(steps, break_when_any_done=False, **kwargs))
        after.append((torch.rand(4), env.episodes.clone()))
    assert all(torch.equal(a, b) for a, b in zip(*after))
    return results


def test_start_table_deepens_and_matches_envbase(monkeypatch):
    depths = []
    draw = loop_module._StartTable.draw

    def recording_draw(self, episodes):
        draw(self, episodes)
        depths.append(self.depth)

    monkeypatch.setattr(loop_module._StartTable, "draw", recording_draw)
    env = make_env("CartPole-v1", num_envs=32, seed=0, dtype=F64)  # random actions: short, unequal episodes
    got, ref = both_paths(env, 150)
    assert ref["next", "done"].sum() > 100
    assert max(depths) > 1
    assert_same_tensordict(got, ref)


def test_start_table_gradients_wrt_params_match_envbase():
    """A physical parameter with gradient (the resets merge env.params, not the input's): the
    values and the gradient through the steps after the resets are EnvBase's."""
    def run(path):
        env = make_env("MountainCarContinuous-v0", num_envs=8, seed=0, dtype=F64, max_episode_steps=3)
        power = env.params["power"].clone().requires_grad_(True)
        env.params["power"] = power
        actions = torch.rand(40, 8, 1, dtype=F64, generator=torch.Generator().manual_seed(0)) * 2 - 1
        out = path(env)(40, actions=list(actions), break_when_any_done=False)
        (grad,) = torch.autograd.grad(out["next", "observation"].sum() + out["next", "reward"].sum(), power)
        return out, grad

    got, got_grad = run(lambda env: env.rollout)
    ref, ref_grad = run(lambda env: (lambda *a, **k: EnvBase.rollout(env, *a, **k)))
    assert_same_tensordict(got, ref)
    assert torch.equal(got_grad, ref_grad)


def nan_mass_env(seed=3):
    probe = make_env("pendulum", num_envs=4, seed=0, dtype=F64)
    mass = probe.params["mass"].clone()
    mass[2] = float("nan")
    return make_env("pendulum", num_envs=4, seed=seed, dtype=F64, max_episode_steps=5, params={"mass": mass})


def test_random_actions_with_a_nan_env_match_envbase():
    env = nan_mass_env()
    assert not getattr(env, "_nonfinite_seen", False)
    got, ref = both_paths(env, 12)
    assert ref["next", "nonfinite"].any()
    assert getattr(env, "_nonfinite_seen", False)  # found by the output check, stepped again with checks
    nan_keys = [("params", "mass"), ("next", "params", "mass"), *[("next", "state", k) for k in ("th", "thd")]]
    assert_same_tensordict(got.exclude(*nan_keys), ref.exclude(*nan_keys))
    for key in nan_keys:
        torch.testing.assert_close(got[key], ref[key], equal_nan=True, rtol=0, atol=0)
    # from then on every step is checked: the same again
    again, ref_again = both_paths(env, 12, seed=5)
    assert_same_tensordict(again.exclude(*nan_keys), ref_again.exclude(*nan_keys))


def test_finite_rollouts_skip_the_step_check(monkeypatch):
    from torchrl_diffenvs.envs.rollout import step as step_module

    calls = []
    check = step_module._all_finite
    monkeypatch.setattr(step_module, "_all_finite", lambda values: calls.append(1) or check(values))
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=5)
    with torch.no_grad():
        env.rollout(12, break_when_any_done=False)
    assert not calls
    env.rollout(12, break_when_any_done=True)  # a break needs each step's flags before the next step
    assert calls
