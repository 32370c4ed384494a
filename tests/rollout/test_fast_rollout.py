"""The lean rollout path returns exactly what TorchRL's ``EnvBase.rollout`` returns.

The reference is TorchRL's own implementation, called as ``EnvBase.rollout(env, ...)`` on the
same env with the same seeds (torch's global generator for random actions and policy samples, the
env's per-env start-state streams for resets). Compared: TensorDict types, batch sizes, names, devices, key sets,
dtypes, values (bitwise) and gradients.
"""

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs import EnvBase, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal

from _env_helpers import assert_same_tensordict, single_agent_envs

from torchrl_diffenvs import make_env
from torchrl_diffenvs.envs.rollout import (
    compile_physics,
    compile_report,
    eager_physics,
    fast_rollout,
    fast_rollout_unsupported,
)

N = 5
STEPS = 6  # past the time limit: every env resets inside the rollout and steps on from its new start
MAX_EPISODE_STEPS = 4  # short episodes: auto-resets happen inside the rollouts


def both_paths(env, *args, seed=0, prepare=None, **kwargs):
    """(fast path, EnvBase.rollout) from identical generator states; ``prepare()`` builds fresh inputs."""
    results, after = [], []
    for path in (fast_rollout, EnvBase.rollout):
        torch.manual_seed(seed)
        env.set_seed(seed + 1)
        extra = prepare() if prepare is not None else {}
        results.append(path(env, *args, **kwargs, **extra))
        # both leave torch's generator, the env's and its start-state streams in the same state
        after.append((torch.rand(4), env.uniform(0, 1, 4), env.episodes.clone()))
    assert all(torch.equal(a, b) for a, b in zip(*after))
    return results


def make_fast_env(name, **kwargs):
    env = make_env(name, num_envs=N, seed=0, max_episode_steps=MAX_EPISODE_STEPS, **kwargs)
    reason = fast_rollout_unsupported(env, None, {})
    assert reason is None, f"{name}: env.rollout would not take the fast path: {reason}"
    return env


def tanh_normal_actor(env, hidden=16):
    net = nn.Sequential(
        nn.Linear(env.observation_dim, hidden), nn.Tanh(), nn.Linear(hidden, 2 * env.action_dim), NormalParamExtractor()
    ).to(env.float_dtype)
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    spec = env.action_spec
    return ProbabilisticActor(
        module, in_keys=["loc", "scale"], distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low[0], "high": spec.space.high[0]},
        return_log_prob=True, spec=spec,
    )


# ---------------------------------------------------------------------------- every env, no policy
@pytest.mark.parametrize("name", single_agent_envs())
def test_every_env_takes_the_fast_path(name):
    env = make_env(name, num_envs=2, seed=0)
    assert fast_rollout_unsupported(env, None, {}) is None
    assert fast_rollout_unsupported(env, None, {"break_when_any_done": False, "tensordict": env.reset()}) is None


# HumanoidStandup is the Humanoid's model and code path at twice the cost
LIGHTER = [name for name in single_agent_envs() if name != "HumanoidStandup-v5"]


# the Humanoid runs to its first fall only: the auto-resets after it are every other task's (its steps cost 5x)
@pytest.mark.parametrize("name,break_when_any_done", [(name, stop) for name in LIGHTER for stop in (True, False)
                                                      if not (name == "Humanoid-v5" and not stop)])
def test_random_actions_match_envbase(name, break_when_any_done):
    env = make_fast_env(name)
    got, ref = both_paths(env, STEPS, break_when_any_done=break_when_any_done)
    expected_steps = STEPS if not break_when_any_done else min(STEPS, MAX_EPISODE_STEPS)
    assert ref.shape[1] <= expected_steps
    if not break_when_any_done:  # the comparison covers auto-resets inside the rollout
        assert ref.shape[1] == STEPS and ref["next", "done"].any()
    assert_same_tensordict(got, ref)
    # the env remembers the same latest output for rendering
    assert_same_render_source(env._render_source, _render_source_after(EnvBase.rollout, env, break_when_any_done))


def _render_source_after(rollout, env, break_when_any_done):
    torch.manual_seed(0)
    env.set_seed(1)
    rollout(env, STEPS, break_when_any_done=break_when_any_done)
    return env._render_source


def assert_same_render_source(got, expected):
    if isinstance(expected, tuple):  # a partial reset: (before, fresh, mask)
        assert isinstance(got, tuple)
        for a, b in zip(got[:2], expected[:2]):
            assert_same_render_source(a, b)
        torch.testing.assert_close(got[2], expected[2], rtol=0, atol=0)
        return
    assert not isinstance(got, tuple) and got["num_envs"] == expected["num_envs"]
    for part in ("state", "params"):
        assert got[part].keys() == expected[part].keys()
        for key in expected[part]:
            torch.testing.assert_close(got[part][key], expected[part][key], rtol=0, atol=0)
    torch.testing.assert_close(got["reward"], expected["reward"], rtol=0, atol=0)


def test_terminations_and_partial_resets_match_envbase():
    """CartPole-v1 terminates at different steps in different envs: partial auto-resets."""
    env = make_env("CartPole-v1", num_envs=16, seed=0)
    got, ref = both_paths(env, 60, break_when_any_done=False)
    terminated = ref["next", "terminated"].squeeze(-1)
    assert terminated.any() and (terminated.any(0) & ~terminated.all(0)).any(), "expected partial resets"
    assert_same_tensordict(got, ref)


# the Humanoid's values are compared above; its gradient through this generic loop adds 30-50 s, not coverage
@pytest.mark.parametrize("name", [name for name in LIGHTER if name != "Humanoid-v5"])
def test_policy_values_and_gradients_match_envbase(name):
    """A TanhNormal actor sampling with rsample; gradients of the return w.r.t. its weights."""
    env = make_fast_env(name, dtype=torch.float64)
    actor = tanh_normal_actor(env)
    grads = []
    outputs = []
    for path in (fast_rollout, EnvBase.rollout):
        torch.manual_seed(0)
        env.set_seed(1)
        actor.zero_grad()
        with set_exploration_type(ExplorationType.RANDOM):
            td = path(env, STEPS, actor, break_when_any_done=False)
        # observations too: CartPole-v1's reward (+1 per step) carries no gradient
        (td["next", "reward"].sum() + td["next", "observation"].sum()).backward()
        grads.append([p.grad.clone() for p in actor.parameters()])
        outputs.append(td.detach())
    assert outputs[1]["next", "done"].any(), "the rollout should contain auto-resets"
    assert {"loc", "scale", "action_log_prob"} <= set(outputs[1].keys())
    assert_same_tensordict(*outputs)
    for g_fast, g_ref in zip(*grads):
        assert g_ref.abs().sum() > 0
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("break_when_any_done", [True, False])
def test_gradients_wrt_actions_and_start_state_match_envbase(break_when_any_done):
    """actions= (leaf tensors) and a start state given through tensordict=, set_state=True."""
    env = make_fast_env("reacher", dtype=torch.float64)
    torch.manual_seed(5)
    base_actions = torch.randn(STEPS, N, env.action_dim, dtype=torch.float64)
    start = env.reset()
    grads = []
    outputs = []
    for path in (fast_rollout, EnvBase.rollout):
        env.set_seed(1)
        actions = [a.clone().requires_grad_(True) for a in base_actions]
        th = start["state", "th"].clone().requires_grad_(True)
        td_in = start.clone()
        td_in["state", "th"] = th
        td = path(env, STEPS, actions=actions, tensordict=td_in, set_state=True,
                  break_when_any_done=break_when_any_done)
        (td["next", "reward"] * torch.linspace(1, 2, td.shape[1], dtype=torch.float64)).sum().backward()
        grads.append([a.grad for a in actions] + [th.grad])
        outputs.append(td.detach())
    assert_same_tensordict(*outputs)
    used = outputs[1].shape[1]
    for i, (g_fast, g_ref) in enumerate(zip(*grads)):
        if g_ref is None:  # actions after an early stop are never used
            assert g_fast is None and i >= used
            continue
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-10, atol=1e-12)
    # the gradient reaches the start state, and is cut at the first auto-reset
    assert grads[1][-1].abs().sum() > 0


def test_gradients_wrt_physical_params_match_envbase():
    env = make_fast_env("pendulum", dtype=torch.float64)
    grads = []
    for path in (fast_rollout, EnvBase.rollout):
        torch.manual_seed(0)
        env.set_seed(1)
        g = torch.full((N,), 9.0, dtype=torch.float64, requires_grad=True)
        td_in = env.reset()
        td_in["params", "g"] = g
        td = path(env, STEPS, tensordict=td_in, auto_reset=False, break_when_any_done=False)
        td["next", "reward"].sum().backward()
        grads.append(g.grad)
    assert grads[1].abs().sum() > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------------- arguments
def test_continuing_rollouts_with_auto_reset_false():
    """The TorchRL data-collection idiom: feed step_mdp(last step) back with auto_reset=False."""
    env = make_fast_env("cartpole")
    got, ref = both_paths(env, 3, break_when_any_done=False)
    for _ in range(3):  # crosses episode ends (4 steps) at window boundaries
        start_got, start_ref = env.step_mdp(got[:, -1]), env.step_mdp(ref[:, -1])
        assert_same_tensordict(start_got, start_ref)
        torch.manual_seed(7)
        env.set_seed(8)
        got = env.rollout(3, tensordict=start_got, auto_reset=False, break_when_any_done=False)
        torch.manual_seed(7)
        env.set_seed(8)
        ref = EnvBase.rollout(env, 3, tensordict=start_ref, auto_reset=False, break_when_any_done=False)
        assert_same_tensordict(got, ref)
        # EnvBase leaves step 0's action and "next" in the input tensordict: so does the fast path
        assert_same_tensordict(start_got, start_ref)


@pytest.mark.parametrize("return_contiguous", [True, False, None])
@pytest.mark.parametrize("set_truncated", [True, False])
def test_return_contiguous_and_set_truncated(return_contiguous, set_truncated):
    env = make_fast_env("swimmer")
    got, ref = both_paths(
        env, 6, break_when_any_done=False, return_contiguous=return_contiguous, set_truncated=set_truncated
    )
    assert_same_tensordict(got, ref)
    assert bool(got["next", "truncated"][:, -1].all()) == set_truncated


def test_user_entries_are_carried_and_zeroed_at_partial_resets():
    """Extra root entries travel with the env entries; TorchRL zeroes them where an env resets."""
    env = make_env("pendulum", num_envs=N, seed=0, max_episode_steps=3)

    def prepare():
        td = env.reset()
        td["episode_step"] = torch.tensor([0, 1, 2, 0, 1])  # staggered episodes: partial resets
        td["user_flag"] = torch.arange(N, dtype=torch.float32) + 1
        return {"tensordict": td}

    got, ref = both_paths(env, 8, break_when_any_done=False, auto_reset=False, prepare=prepare)
    assert (ref["user_flag"] == 0).any() and (ref["user_flag"] != 0).any()
    assert_same_tensordict(got, ref)


def test_plain_module_policy_and_trust_policy():
    """A policy that is not a TensorDict module is wrapped exactly as EnvBase wraps it."""
    env = make_fast_env("mountaincar")

    class Policy(nn.Module):
        # TorchRL wraps a plain module with every observation-spec entry as an argument
        def forward(self, observation, state, params, episode_step, nonfinite):
            return torch.tanh(observation.sum(-1, keepdim=True) + episode_step.unsqueeze(-1))

    got, ref = both_paths(env, 7, Policy(), break_when_any_done=False)
    assert_same_tensordict(got, ref)

    def td_policy(td):
        td["action"] = torch.sin(td["observation"][..., :1])
        return td

    got, ref = both_paths(env, 7, td_policy, break_when_any_done=False, trust_policy=True)
    assert_same_tensordict(got, ref)


def test_policy_writing_changing_keys_gives_the_same_lazy_stack():
    env = make_fast_env("pendulum")

    def policy(td):
        td["action"] = torch.zeros(N, 1)
        if int(td["episode_step"][0]) == 1:
            td["extra"] = torch.ones(N)
        return td

    got, ref = both_paths(env, 3, policy, break_when_any_done=False, return_contiguous=False, trust_policy=True)
    assert type(got) is type(ref)
    assert got.shape == ref.shape
    assert_same_tensordict(got.tensordicts[1], ref.tensordicts[1])


def test_errors_match_envbase():
    env = make_fast_env("pendulum")
    with pytest.raises(ValueError, match=r"expected an action of shape \(5, 1\)"):
        env.rollout(3, actions=[torch.zeros(5, 2)])
    with pytest.raises(RuntimeError, match="tensordict must be provided when auto_reset is False"):
        env.rollout(3, auto_reset=False)
    with pytest.raises(ValueError, match="Cannot pass both `policy` and `actions`"):
        env.rollout(3, lambda td: td, actions=[torch.zeros(5, 1)])
    with pytest.raises(KeyError, match="the policy wrote no 'action' entry"):
        env.rollout(3, lambda td: td, trust_policy=True)
    with pytest.raises(ValueError, match=r"max_steps >= 1 \(and actions, if given\), got 0"):
        env.rollout(3, actions=[])
    with pytest.raises(TypeError, match="max_steps must be an integer, got 2.5"):
        env.rollout(2.5)


def test_unsupported_arguments_fall_back_to_envbase():
    env = make_fast_env("pendulum")
    assert "callback" in fast_rollout_unsupported(env, print, {})
    assert "break_when_all_done" in fast_rollout_unsupported(env, None, {"break_when_all_done": True})
    assert "unknown keyword" in fast_rollout_unsupported(env, None, {"bogus": 1})
    calls = []
    td = env.rollout(5, callback=lambda e, t: calls.append(t), break_when_any_done=False)
    assert len(calls) == 4 and td.shape == (N, 5)
    torch.manual_seed(0)
    env.set_seed(1)
    td = env.rollout(9, break_when_all_done=True)
    torch.manual_seed(0)
    env.set_seed(1)
    assert_same_tensordict(td, EnvBase.rollout(env, 9, break_when_all_done=True))
    env.use_fast_rollout = False
    assert "use_fast_rollout" in fast_rollout_unsupported(env, None, {})
    with pytest.raises(ValueError, match="fast_rollout cannot reproduce"):
        fast_rollout(env, 3)


def test_transformed_env_steps_the_base_env_itself():
    """TransformedEnv does not call DiffEnv.rollout; its rollout is TorchRL's, over our _step."""
    env = make_env("pendulum", num_envs=N, seed=0)
    called = []
    env.rollout = lambda *a, **k: called.append(1)  # would be hit if TransformedEnv delegated
    td = TransformedEnv(env, StepCounter()).rollout(4)
    assert not called and td.shape == (N, 4) and "step_count" in td.keys()


# ---------------------------------------------------------------------------- torch.compile
def test_compiled_physics_matches_eager_values_and_gradients():
    """Compiled 2-step chunks with auto-resets inside them, against the eager path (float64)."""
    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=3, dtype=torch.float64)
    base_actions = torch.randn(8, 3, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    results = []
    for compiled in (False, True):
        compile_physics(env, steps_per_chunk=2) if compiled else eager_physics(env)
        env.set_seed(1)
        actions = [a.clone().requires_grad_(True) for a in base_actions]
        td = env.rollout(8, actions=actions, break_when_any_done=False)
        (td["next", "reward"].sum() + td["next", "observation"].sum()).backward()
        results.append((td.detach(), [a.grad for a in actions]))
    assert list(compile_report(env)["first_call_seconds"]) == ["physics, 2 steps, with grad"]  # chunks ran compiled
    eager_physics(env)
    (td_eager, grads_eager), (td_compiled, grads_compiled) = results
    assert td_eager["next", "done"][:, :-1].any(), "the rollout should reset envs inside chunks"
    assert_same_tensordict(td_compiled, td_eager, exact=False)
    for g_compiled, g_eager in zip(grads_compiled, grads_eager):
        torch.testing.assert_close(g_compiled, g_eager, rtol=1e-10, atol=1e-12)


def test_compile_physics_rejects_bad_chunks():
    env = make_env("pendulum", num_envs=2, seed=0)
    with pytest.raises(ValueError, match="steps_per_chunk must be a positive integer, got 0"):
        compile_physics(env, steps_per_chunk=0)
