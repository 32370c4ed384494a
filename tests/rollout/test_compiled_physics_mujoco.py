"""``compile_physics`` on the articulated (MuJoCo) tasks: one compiled physics step, reused for
every physics step of a chunk, gives the eager path's values and gradients in float32.

Tolerances: float32 (eps 1.2e-7). With ``aot_eager`` (dynamo and AOTAutograd, no code
generation) the compiled step runs the same aten ops as eager, so values and gradients agree to
a few ulps; inductor's fused kernels reorder sums and products, and the difference grows
through the contact dynamics (measured on Hopper-v5, 8 steps: values 5e-7 apart, the policy
gradient 1.2e-7 relative; HalfCheetah-v5 reaches 1e-3 after 16 steps of chaotic contact), so the
inductor test keeps the horizon short and allows 1e-4 relative, 1e-5 absolute.
"""
import pytest
import torch
from tensordict.nn import TensorDictModule

from torchrl_diffenvs import compile_physics, eager_physics, make_env
from torchrl_diffenvs.articulated import integrators
from torchrl_diffenvs.envs.fast_rollout import compile_report


@pytest.fixture(autouse=True)
def fresh_compiler():
    torch.compiler.reset()
    yield
    torch.compiler.reset()


def deterministic_policy(env, seed=0):
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(env.observation_dim, 16), torch.nn.Tanh(),
                              torch.nn.Linear(16, env.action_dim), torch.nn.Tanh())
    return net, TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def window(env, net, policy, start, steps):
    """A BPTT window: values, and gradients w.r.t. the policy and a physical parameter."""
    td0 = start.clone()
    mass = td0["params", "body_mass"].clone().requires_grad_(True)
    td0["params", "body_mass"] = mass
    out = env.rollout(steps, policy, auto_reset=False, tensordict=td0)
    loss = out["next", "reward"].sum() + out["next", "observation"].square().sum()
    grads = torch.autograd.grad(loss, [*net.parameters(), mass])
    return out.detach(), grads


def test_articulated_tasks_compile_one_physics_step_with_values_and_gradients_of_eager():
    """Hopper-v5 (Euler, joint limits, contact), 8 steps in chunks of 4 through ``aot_eager``:
    the report names the compiled physics step (forward with grad), nothing fell back, the
    values and gradients (policy and body masses) are eager's; afterwards ``step`` is eager again."""
    env = make_env("Hopper-v5", num_envs=3, seed=0)
    net, policy = deterministic_policy(env)
    start = env.reset()
    eager = window(env, net, policy, start, 8)
    compile_physics(env, steps_per_chunk=4, backend="aot_eager")
    try:
        compiled = window(env, net, policy, start, 8)
        report = compile_report(env)
    finally:
        eager_physics(env)
    assert report["fallback_reason"] is None, report
    assert "physics step (euler), with grad" in report["first_call_seconds"], report
    assert not integrators._STEPPERS, "the compiled step must be active only inside a chunk"
    for key in ("observation", "reward"):
        torch.testing.assert_close(compiled[0]["next", key], eager[0]["next", key], rtol=1e-6, atol=1e-6)
    for got, want in zip(compiled[1], eager[1]):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_inductor_compiled_physics_step_matches_eager():
    """The default backend (inductor: C++ kernels, tens of seconds to compile on one core): a
    no-grad rollout of HalfCheetah-v5 (12 joint-limit rows, 16 contact pairs) matches eager."""
    env = make_env("HalfCheetah-v5", num_envs=2, seed=0)
    start = env.reset()

    def rollout():
        torch.manual_seed(1)
        with torch.no_grad():
            return env.rollout(4, auto_reset=False, tensordict=start.clone())

    eager = rollout()
    compile_physics(env, steps_per_chunk=4)
    try:
        compiled = rollout()
        report = compile_report(env)
    finally:
        eager_physics(env)
    if report["fallback_reason"] is not None and "compile" in report["fallback_reason"]:
        pytest.skip(f"torch.compile is unavailable here: {report['fallback_reason']}")
    assert "physics step (euler), without grad" in report["first_call_seconds"], report
    torch.testing.assert_close(compiled["action"], eager["action"], rtol=0, atol=0)
    for key in ("observation", "reward"):
        torch.testing.assert_close(compiled["next", key], eager["next", key], rtol=1e-4, atol=1e-5)


def test_implicit_integrator_compiles_with_values_and_gradients_of_eager():
    """MuJoCo's implicit integrator (the Ant's default; here on HalfCheetah-v5, whose smaller tree
    compiles sooner): the compiled step is the implicit one, and 6 steps in chunks of 3 through
    ``aot_eager`` give eager's values and gradients (policy and body masses). In float64: the
    same math to 1e-10; in float32 the reordered backward's rounding grows through the contact
    steps to about 1e-2 relative on this task (1e-5 with Euler), so the comparison is in float64."""
    env = make_env("HalfCheetah-v5", num_envs=2, seed=0, integrator="implicit", dtype=torch.float64)
    net, policy = deterministic_policy(env)
    net.to(torch.float64)
    start = env.reset()
    eager = window(env, net, policy, start, 6)
    compile_physics(env, steps_per_chunk=3, backend="aot_eager")
    try:
        compiled = window(env, net, policy, start, 6)
        report = compile_report(env)
    finally:
        eager_physics(env)
    assert report["fallback_reason"] is None, report
    assert "physics step (implicit), with grad" in report["first_call_seconds"], report
    for key in ("observation", "reward"):
        torch.testing.assert_close(compiled[0]["next", key], eager[0]["next", key], rtol=1e-10, atol=1e-10)
    for got, want in zip(compiled[1], eager[1]):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
