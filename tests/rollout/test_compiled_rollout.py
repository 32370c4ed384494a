"""``compile_physics`` with a policy: compiled chunks of policy + physics + resets (and their
backward) give the eager path's rollout, gradients and episode counts.

The reference is the eager lean path on the same env from the same generator states (itself
checked bit for bit against TorchRL's ``EnvBase.rollout`` in tests/rollout/test_fast_rollout.py), in
float64. Inductor draws random numbers with its own generator; ``fallback_random`` makes it
draw torch's, so that a stochastic policy samples the same actions on both paths.
"""
import logging

import pytest
import torch
import torch._inductor.config as inductor_config  # fallback_random: see the module docstring
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_diffenvs import compile_physics, eager_physics, make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.envs.rollout import compile_report
from torchrl_diffenvs.envs.rollout.compiled import compiled_physics
from torchrl_diffenvs.modules import make_actor

from _env_helpers import assert_same_tensordict


# Tests of the loop's bookkeeping (resets, episode counts, windows) trace with dynamo and
# AOTAutograd but skip inductor's code generation (seconds instead of tens of seconds); the tests
# of values and gradients under fused kernels use inductor, the default.
BOOKKEEPING = "aot_eager"


@pytest.fixture(autouse=True)
def fresh_compiler():
    """Each test compiles from scratch (dynamo's per-function recompile limit is shared)."""
    torch.compiler.reset()
    with inductor_config.patch(fallback_random=True):
        yield
    torch.compiler.reset()


def staggered_start(env, limit):
    """A start whose envs reach the time limit at different steps of the first chunks."""
    td = env.reset()
    td.set("episode_step", (limit - 1 - torch.arange(env.num_envs) % limit).to(td["episode_step"].dtype))
    return td


def rollout_and_grads(env, actor, steps, start, exploration=ExplorationType.RANDOM, params_grad=False, **kwargs):
    """One rollout from ``start`` (cloned) with torch's generator seeded; its gradients w.r.t. the
    actor's parameters (and the start's physical parameters), torch's generator state and the
    env's episode counts (which start states its envs draw next) after."""
    torch.manual_seed(0)
    env.set_seed(1)
    td0 = start.clone()
    inputs = list(actor.parameters())
    if params_grad:
        for key, value in td0["params"].items():
            td0["params"].set(key, value.clone().requires_grad_(True))
        inputs += list(td0["params"].values())
    with set_exploration_type(exploration):
        out = env.rollout(steps, actor, auto_reset=False, tensordict=td0, **kwargs)
    loss = (out["next", "reward"] ** 2).sum() + out["next", "observation"].sum() + out["action"].sum()
    grads = torch.autograd.grad(loss, inputs, allow_unused=True)
    return out.detach(), grads, td0.exclude("next").detach(), (torch.get_rng_state(), env.episodes.clone())


def parameters_of(actor, start):
    return [*actor.parameters(), *start["params"].values()]


def compare_paths(env, actor, steps, start, chunk=4, backend="inductor", **kwargs):
    eager = rollout_and_grads(env, actor, steps, start, **kwargs)
    compile_physics(env, steps_per_chunk=chunk, backend=backend)
    try:
        compiled = rollout_and_grads(env, actor, steps, start, **kwargs)
        report = compile_report(env)
    finally:
        eager_physics(env)
    assert_same_tensordict(compiled[0], eager[0], exact=False)
    for got, want, value in zip(compiled[1], eager[1], parameters_of(actor, start)):
        # a physical parameter unused between resets has no gradient eagerly and a zero one
        # compiled (the chunk's reset merge reads it at every step)
        zeros = torch.zeros_like(value)
        torch.testing.assert_close(zeros if got is None else got, zeros if want is None else want,
                                   rtol=1e-10, atol=1e-12)
    assert_same_tensordict(compiled[2], eager[2], exact=False)  # the input tensordict's side effects
    assert torch.equal(compiled[3][1], eager[3][1]), "every env must have drawn as many start states as eagerly"
    assert report["fallback_reason"] is None
    assert any(name.startswith("policy + physics") for name in report["first_call_seconds"]), report
    return eager[0]


def test_policy_chunks_match_eager_with_resets_inside_chunks():
    """Inductor's kernels: truncations at different steps inside 3-step chunks (several resets per
    chunk), the last two steps of 11 eager; values, gradients w.r.t. the policy and episode counts
    as eagerly."""
    env = make_env("pendulum", num_envs=6, seed=0, max_episode_steps=4, dtype=torch.float64)
    actor = make_actor(env, hidden=(8,)).double()
    out = compare_paths(env, actor, 11, staggered_start(env, 4), chunk=3, break_when_any_done=False)
    done_steps = out["next", "done"][..., 0].any(0).nonzero().flatten().tolist()
    assert len([t for t in done_steps if t < 2]) >= 2, f"want several resets inside the first chunk: {done_steps}"


def test_a_chunk_reaching_the_time_limit_draws_start_states_ahead():
    """The first chunk has no reset; the second reaches the envs' time limit before its last
    step, so it runs with start states drawn ahead (the same as the eager path's)."""
    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=6, dtype=torch.float64)
    actor = make_actor(env, hidden=(16,)).double()
    out = compare_paths(env, actor, 12, env.reset(), backend=BOOKKEEPING, break_when_any_done=False)
    assert out["next", "done"][:, 5].all() and not out["next", "done"][:, :5].any()


def test_policy_chunks_match_eager_with_termination_and_parameter_gradients():
    """A task that terminates (CartPole-v1), physical parameters with gradient (merged at resets
    inside the chunk rather than kept), deterministic actions."""
    env = make_env("CartPole-v1", num_envs=8, seed=0, max_episode_steps=6, dtype=torch.float64)
    actor = make_actor(env, hidden=(16, 16)).double()
    start = staggered_start(env, 6)
    start["state"].apply_(lambda x: x * 8)  # far off balance: terminations within a few steps
    out = compare_paths(env, actor, 12, start, chunk=4, backend=BOOKKEEPING, params_grad=True,
                        break_when_any_done=False, exploration=ExplorationType.DETERMINISTIC)
    assert out["next", "terminated"].any() and out["next", "truncated"].any()


def test_a_chunk_with_an_unexpected_termination_is_cut_after_it():
    """A chunk run without start states drawn ahead (none expected: no time limit near, the last
    chunk had no reset) in which CartPole-v1 terminates before the chunk's last step: the steps
    up to the termination are kept, the env is reset eagerly and the rollout goes on; the result
    is the eager path's (deterministic actions: the cut chunk's later steps are dropped)."""
    env = make_env("CartPole-v1", num_envs=4, seed=0, max_episode_steps=100, dtype=torch.float64)
    actor = make_actor(env, hidden=(8,)).double()
    start = env.reset()
    start["state"].apply_(lambda x: x * 8)  # far off balance: terminations within a few steps

    def rollout():
        torch.manual_seed(0)
        env.set_seed(1)
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return env.rollout(16, actor, auto_reset=False, tensordict=start.clone(),
                               break_when_any_done=False).detach(), env.episodes.clone()

    eager, eager_episodes = rollout()
    compile_physics(env, steps_per_chunk=4, backend=BOOKKEEPING)
    compiled_physics(env).expect_resets = False  # the first chunk runs without start states
    try:
        compiled, compiled_episodes = rollout()
    finally:
        eager_physics(env)
    first_done = int(eager["next", "terminated"][..., 0].any(0).nonzero()[0])
    assert first_done < 3, "the first chunk should see a termination before its last step"
    assert_same_tensordict(compiled, eager, exact=False)
    assert torch.equal(compiled_episodes, eager_episodes)


def test_policy_chunks_match_eager_when_breaking_at_the_first_done():
    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=7, dtype=torch.float64)
    actor = make_actor(env, hidden=(16, 16)).double()
    out = compare_paths(env, actor, 12, staggered_start(env, 7), chunk=4, backend=BOOKKEEPING,
                        break_when_any_done=True)
    assert out.shape == (4, 1)  # env 0 starts one step before its time limit


def test_collector_windows_match_eager():
    """Three DiffWindowCollector windows (state carried between them). (No-grad evaluations run
    compiled in test_train_with_compile_true_is_the_eager_run.)"""
    results = []
    for compiled in (False, True):
        env = make_env("pendulum", num_envs=5, seed=3, max_episode_steps=6, dtype=torch.float64)
        actor = make_actor(env, hidden=(16, 16)).double()
        torch.manual_seed(0)
        actor.load_state_dict(make_actor(env, hidden=(16, 16)).double().state_dict())
        if compiled:
            compile_physics(env, steps_per_chunk=4, backend=BOOKKEEPING)
        torch.manual_seed(0)
        collector = DiffWindowCollector(env, actor, horizon=4, total_windows=3)
        windows, grads = [], []
        for window in collector:
            grads.append(torch.autograd.grad(window["next", "reward"].sum(), list(actor.parameters())))
            windows.append(window.detach())
        results.append((windows, grads))
        if compiled:
            assert list(compile_report(env)["first_call_seconds"]) == ["policy + physics, 4 steps, with grad"]
    (windows_e, grads_e), (windows_c, grads_c) = results
    assert any(w["next", "done"].any() for w in windows_e)
    for got, want in zip(windows_c, windows_e):
        assert_same_tensordict(got, want, exact=False)
    for got, want in zip(grads_c, grads_e):
        for g, w in zip(got, want):
            torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("break_when_any_done", [False, True])
def test_random_action_chunks_match_eager_with_resets_inside_chunks(break_when_any_done):
    """Without a policy (random actions from torch's generator, drawn eagerly): CartPole-v1
    terminating and truncating inside 4-step chunks; torch's generator and the episode counts end
    where eagerly."""
    env = make_env("CartPole-v1", num_envs=8, seed=0, max_episode_steps=5, dtype=torch.float64)
    results = []
    for compiled in (False, True):
        compile_physics(env, steps_per_chunk=4, backend=BOOKKEEPING) if compiled else eager_physics(env)
        torch.manual_seed(0)
        env.set_seed(1)
        start = staggered_start(env, 5)
        out = env.rollout(14, auto_reset=False, tensordict=start, break_when_any_done=break_when_any_done)
        results.append((out, start.exclude("next"), torch.get_rng_state(), env.episodes.clone()))
    report = compile_report(env)
    eager_physics(env)
    (out_e, start_e, global_e, env_e), (out_c, start_c, global_c, env_c) = results
    assert_same_tensordict(out_c, out_e, exact=False)
    assert_same_tensordict(start_c, start_e, exact=False)
    assert torch.equal(global_c, global_e) and torch.equal(env_c, env_e)
    assert list(report["first_call_seconds"]) == ["physics, 4 steps, with grad"]
    if not break_when_any_done:
        assert out_e["next", "done"][:, :3].any(0).sum() >= 2  # several resets inside the first chunk


def test_policy_chunk_is_one_graph():
    """The whole chunk (policy, physics, resets) is one graph: no graph break per step. Both
    chunks here run with resets inside (the first expects them, the second reaches the time
    limit), so one graph."""
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=5)
    actor = make_actor(env, hidden=(8,))
    compile_physics(env, steps_per_chunk=4, backend=counting_backend)
    with set_exploration_type(ExplorationType.RANDOM):
        env.rollout(8, actor, break_when_any_done=False)
    assert len(graphs) == 1  # a graph break would add graphs
    assert compile_report(env)["fallback_reason"] is None


def test_collector_windows_do_not_recompile():
    """A window starts from slices of the previous window (strided) and detached tensors: the
    chunks take them contiguous and differentiable, so every window reuses the same graphs (one
    with resets inside the chunk, one without)."""
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    env = make_env("pendulum", num_envs=4, seed=0, max_episode_steps=6)
    compile_physics(env, steps_per_chunk=4, backend=counting_backend)
    actor = make_actor(env, hidden=(8,))
    for window in DiffWindowCollector(env, actor, horizon=4, total_windows=6):
        window["next", "reward"].sum().backward()
    assert len(graphs) <= 2, f"{len(graphs)} graphs: the windows recompiled"


def test_many_envs_in_one_process_all_run_compiled():
    """torch.compile allows 8 recompilations per code object: each env's chunk functions need
    their own, or the ninth compiled variant in a process (tests, benchmarks, sweeps) would
    silently run eagerly."""
    graphs = []

    def counting_backend(graph_module, example_inputs):
        graphs.append(graph_module)
        return graph_module.forward

    for i in range(3):
        env = make_env("pendulum", num_envs=3 + i, seed=0, max_episode_steps=5)
        compile_physics(env, steps_per_chunk=4, backend=counting_backend)
        with set_exploration_type(ExplorationType.RANDOM):
            env.rollout(4, make_actor(env, hidden=(8,)), break_when_any_done=False)
    assert len(graphs) == 3  # one per env (see test_policy_chunk_is_one_graph)


def test_compile_failure_falls_back_to_eager_with_the_reason(caplog):
    def broken_backend(graph_module, example_inputs):
        raise RuntimeError("no compiler here")

    env = make_env("pendulum", num_envs=3, seed=0, max_episode_steps=5, dtype=torch.float64)
    actor = make_actor(env, hidden=(8,)).double()
    start = staggered_start(env, 5)
    eager = rollout_and_grads(env, actor, 8, start, break_when_any_done=False)
    compile_physics(env, steps_per_chunk=4, backend=broken_backend)
    with caplog.at_level(logging.WARNING):
        fallback = rollout_and_grads(env, actor, 8, start, break_when_any_done=False)
    reason = compile_report(env)["fallback_reason"]
    assert "torch.compile failed" in reason and "no compiler here" in reason
    assert "running eagerly" in caplog.text and "no compiler here" in caplog.text
    assert_same_tensordict(fallback[0], eager[0])  # the eager path, bit for bit
    assert torch.equal(fallback[3][1], eager[3][1])
    # later rollouts go straight to eager, without trying again
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        rollout_and_grads(env, actor, 8, start, break_when_any_done=False)
    assert caplog.text == ""


def test_plain_callable_policies_run_eagerly_with_compile_physics():
    env = make_env("pendulum", num_envs=3, seed=0)
    compile_physics(env, steps_per_chunk=4)

    def policy(td):
        return td.set("action", torch.zeros(3, 1))

    out = env.rollout(8, policy)
    assert out.shape == (3, 8)
    assert compile_report(env)["first_call_seconds"] == {}  # nothing compiled


def test_train_with_compile_true_is_the_eager_run(tmp_path, caplog, monkeypatch):
    """``compile=true`` in train.py: SHAC windows and evaluations compiled, the same run as eagerly
    (float64; fallback_random makes the sampled actions equal), compile time logged. The wiring is
    what is tested here, so the chunks compile through ``aot_eager`` (inductor's code generation
    takes minutes on one core); inductor's kernels are checked against eager above."""
    from functools import partial

    import torchrl_diffenvs
    from _train_helpers import tiny_cfg, train_script

    monkeypatch.setattr(torchrl_diffenvs, "compile_physics", partial(compile_physics, backend=BOOKKEEPING))
    results = {}
    for compiled in (False, True):
        cfg = tiny_cfg("pendulum", "shac", 2, "dtype=float64", "eval.max_steps=4", f"compile={str(compiled).lower()}")
        with caplog.at_level(logging.INFO):
            results[compiled] = train_script.run(cfg, tmp_path / str(compiled))
    assert "compile: first iteration" in caplog.text and "fell back" not in caplog.text
    assert "policy + physics, 4 steps, with grad" in caplog.text  # the windows ran compiled
    eager, compiled = (torch.load(results[c]["checkpoint"], weights_only=False) for c in (False, True))
    for key, value in eager["policy"].items():
        torch.testing.assert_close(compiled["policy"][key], value, rtol=1e-9, atol=1e-11)
    assert results[True]["eval/return"] == pytest.approx(results[False]["eval/return"], rel=1e-9)


def test_train_rejects_a_non_boolean_compile():
    from _train_helpers import tiny_cfg

    from torchrl_diffenvs.training import ConfigError, validate_config

    with pytest.raises(ConfigError, match="compile='yes': expected true or false"):
        validate_config(tiny_cfg("pendulum", "shac", 2, "compile=yes"))


def test_cuda_graph_modes_are_recognised_and_turned_off_for_windows_with_gradient():
    """Which ``torch.compile`` settings replay CUDA graphs (rollouts without gradient copy their
    outputs out of them), and the settings a window with gradient compiles with instead."""
    from torchrl_diffenvs.envs.rollout.compiled import uses_cudagraphs, without_cudagraphs

    assert uses_cudagraphs({"mode": "reduce-overhead"}) and uses_cudagraphs({"mode": "max-autotune"})
    assert uses_cudagraphs({"options": {"triton.cudagraphs": True}})
    assert not uses_cudagraphs({"dynamic": False}) and not uses_cudagraphs({"mode": "max-autotune-no-cudagraphs"})
    assert without_cudagraphs({"mode": "reduce-overhead", "dynamic": False}) == {"dynamic": False}
    assert without_cudagraphs({"mode": "max-autotune"}) == {"mode": "max-autotune-no-cudagraphs"}
    assert without_cudagraphs({"options": {"triton.cudagraphs": True, "x": 1}}) == {
        "options": {"triton.cudagraphs": False, "x": 1}}


def test_a_cuda_graph_mode_keeps_the_eager_rollout_and_gradient():
    """``mode="reduce-overhead"`` goes through the CUDA-graph wrapper (a new graph step and copied
    outputs without gradient, a second compilation with gradient); on the CPU inductor runs the
    graphs without CUDA graphs, so the values must be the eager path's to rounding (float64).
    tests/project/test_gpu.py checks the same on CUDA."""
    envs = [make_env("pendulum", num_envs=4, seed=0, dtype=torch.float64) for _ in range(2)]
    compile_physics(envs[1], steps_per_chunk=2, mode="reduce-overhead")
    outs, grads = [], []
    for env in envs:
        torch.manual_seed(0)
        with torch.no_grad():
            outs.append(env.rollout(4, break_when_any_done=False))
        torch.manual_seed(0)
        actor = make_actor(env, hidden=(8,)).double()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            window = env.rollout(4, actor, auto_reset=False, tensordict=env.reset(), break_when_any_done=False)
        grads.append(torch.autograd.grad(window["next", "reward"].sum(), list(actor.parameters())[:2]))
    assert compile_report(envs[1])["fallback_reason"] is None
    assert set(compile_report(envs[1])["first_call_seconds"]) == {"physics, 2 steps, without grad",
                                                                  "policy + physics, 2 steps, with grad"}
    torch.testing.assert_close(outs[1]["next", "observation"], outs[0]["next", "observation"], rtol=1e-10, atol=1e-12)
    for got, want in zip(*reversed(grads)):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_a_window_with_its_policy_traces_into_one_graph():
    """A 4-step chunk of the pendulum with a TensorDict-module policy (what compile_physics compiles
    for a BPTT window): dynamo traces it without a graph break, and the traced chunk's rewards
    are eager's."""
    from torchrl_diffenvs.envs.rollout.compiled import chunk_inputs, chunk_steps

    env = make_env("pendulum", num_envs=4, seed=0)
    actor = make_actor(env, hidden=(16,))
    td = env.reset()
    root = chunk_inputs({"observation": td["observation"], "state": dict(td["state"].items()),
                         "params": dict(td["params"].items()), "episode_step": td["episode_step"]})

    def window(root):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            steps, _ = chunk_steps(env, actor, 4, root, {}, None, None)
        return torch.stack([nxt["reward"] for _, nxt, _ in steps])

    explanation = torch._dynamo.explain(window)(root)
    assert explanation.graph_break_count == 0 and explanation.graph_count == 1, explanation.break_reasons
    traced = torch.compile(window, fullgraph=True, backend="eager")(root)
    torch.testing.assert_close(traced, window(root), rtol=0, atol=0)
