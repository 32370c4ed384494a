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
from torchrl_diffenvs.envs.rollout import compile_report
from _env_helpers import with_smooth_contact  # noqa: E402

# written for the smooth contact option (MuJoCo's own: tests/simulator/test_mujoco_contact.py)
make_env = with_smooth_contact(make_env)


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


def eager_and_compiled_windows(env, steps: int, chunk: int):
    """The same ``steps``-step window (values, gradients) eager and then compiled in chunks of
    ``chunk`` through ``aot_eager``, and the compile report; the env is eager again afterwards."""
    net, policy = deterministic_policy(env)
    net.to(env.float_dtype)
    start = env.reset()
    eager = window(env, net, policy, start, steps)
    compile_physics(env, steps_per_chunk=chunk, backend="aot_eager")
    try:
        compiled = window(env, net, policy, start, steps)
        report = compile_report(env)
    finally:
        eager_physics(env)
    return eager, compiled, report


def test_articulated_tasks_compile_one_physics_step_with_values_and_gradients_of_eager():
    """A window through ``aot_eager`` in chunks, on the Hopper (joint limits and contact) with the
    implicit integrator (Euler's step plus the bias forces' velocity Jacobian: one compile covers
    both): the report names the compiled physics step of the integrator (forward with grad),
    nothing fell back, the values and gradients (policy and body masses) are eager's; afterwards
    ``step`` is eager again. In float64, where it is the same math to 1e-10: in float32 the
    reordered backward's rounding grows through the contact steps (about 2e-5 relative with Euler
    on the Hopper, 1e-2 with the implicit integrator on HalfCheetah) and depends on the CPU's
    vector instructions."""
    integrator = "implicit"
    env = make_env("Hopper-v5", num_envs=3, seed=0, integrator=integrator, dtype=torch.float64)
    eager, compiled, report = eager_and_compiled_windows(env, steps=8, chunk=4)
    assert report["fallback_reason"] is None, report
    assert f"physics step ({integrator}), with grad" in report["first_call_seconds"], report
    assert integrators.physics_stepper(env.tree) is None, "the compiled step must be active only inside a chunk"
    for key in ("observation", "reward"):
        torch.testing.assert_close(compiled[0]["next", key], eager[0]["next", key], rtol=1e-10, atol=1e-10)
    for got, want in zip(compiled[1], eager[1]):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_inductor_compiled_physics_step_matches_eager():
    """The default backend (inductor: C++ kernels, tens of seconds to compile on one core): a
    no-grad rollout of InvertedPendulum-v5 with the Euler integrator (a slider and a hinge: the
    articulated dynamics, without contact or RK4's four evaluations, whose graphs compile in a
    fraction of a contact task's time) matches eager. Contact steps compile through ``aot_eager``
    above."""
    env = make_env("InvertedPendulum-v5", num_envs=2, seed=0, integrator="euler")
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


def test_the_compiled_step_is_held_by_the_tree_and_the_env():
    """``stepping_with`` sets the tree's own stepper for its block and restores the enclosing
    one; ``compile_physics`` gives the env its compiled physics, which a wrapper of the env does
    not share and ``eager_physics`` takes away."""
    from torchrl.envs import StepCounter, TransformedEnv

    env = make_env("Hopper-v5", num_envs=2, seed=0)
    state = env.initial_state(env.params, 2)
    calls = []

    def counting(name):
        def stepper(tree, *args):
            calls.append(name)
            return integrators.eager_step(tree, *args)
        return stepper

    def one_step():
        return integrators.step(env.tree, state["qpos"], state["qvel"], torch.zeros(2, 3), env.params, 0.002,
                                "euler")

    assert integrators.physics_stepper(env.tree) is None
    with integrators.stepping_with(env.tree, counting("outer")):
        with integrators.stepping_with(env.tree, counting("inner")):
            inner = one_step()
        outer = one_step()
    assert calls == ["inner", "outer"] and integrators.physics_stepper(env.tree) is None
    torch.testing.assert_close(inner.qvel, one_step().qvel, rtol=0, atol=0)
    torch.testing.assert_close(outer.qvel, one_step().qvel, rtol=0, atol=0)

    assert compile_report(env) is None
    compile_physics(env, steps_per_chunk=2)
    assert compile_report(env)["steps_per_chunk"] == 2
    assert compile_report(TransformedEnv(env, StepCounter())) is None  # forwarded attributes are the env's
    eager_physics(env)
    assert compile_report(env) is None
    eager_physics(env)  # again: nothing to undo


def test_mujocos_contact_step_compiles_into_one_graph():
    """MuJoCo's contact model (the default): a physics step with contacts, joint limits and the
    Newton solve traces into one graph (``fullgraph=True``: no graph break, the solve is one
    ``torch.while_loop``), and the traced step gives eager's next state."""
    from torchrl_diffenvs import make_env as make_mujoco_env
    from torchrl_diffenvs.articulated.pipeline import invweight0

    if not hasattr(torch, "while_loop"):
        pytest.skip("this torch has no torch.while_loop: the Newton solve is a graph break")
    env = make_mujoco_env("HalfCheetah-v5", num_envs=4, seed=0, dtype=torch.float64)
    state = env.rollout(20)[:, -1]["next", "state"]  # fallen onto the floor: contacts active
    params, weights = dict(env.params.items()), None
    weights = invweight0(env.tree, params)
    ctrl = torch.linspace(-1, 1, 4 * env.action_dim, dtype=torch.float64).reshape(4, -1)

    def one(qpos, qvel, ctrl):
        return integrators.step(env.tree, qpos, qvel, ctrl, params, env.model.timestep, env.integrator, weights)

    eager = one(state["qpos"], state["qvel"], ctrl)
    assert eager.solver_converged.all()
    traced = torch.compile(one, fullgraph=True, backend="aot_eager")(state["qpos"], state["qvel"], ctrl)
    torch.testing.assert_close(traced.qvel, eager.qvel, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(traced.qpos, eager.qpos, rtol=1e-12, atol=1e-12)


def test_a_plain_callable_policy_runs_the_compiled_physics_step():
    """``compile_physics`` with a plain callable policy (no TensorDict module): the articulated
    task still runs its compiled physics step (the policy is called eagerly around it), with
    eager's values and gradients; a task compiled by the chunk reports why it ran eagerly."""
    from torchrl_diffenvs import make_env as make_mujoco_env

    # the smallest articulated task: what is checked is the policy's path around the compiled step
    env = make_mujoco_env("InvertedPendulum-v5", num_envs=2, seed=0, integrator="euler", dtype=torch.float64)
    torch.manual_seed(0)
    net = torch.nn.Linear(env.observation_dim, env.action_dim).double()

    def policy(td):
        return td.set("action", torch.tanh(net(td["observation"])))

    start = env.reset()

    def window():
        out = env.rollout(4, policy, auto_reset=False, tensordict=start.clone())
        loss = out["next", "observation"].square().sum()  # its reward is 1 per step whatever the action
        return out.detach(), torch.autograd.grad(loss, list(net.parameters()))

    eager = window()
    compile_physics(env, steps_per_chunk=2, backend="aot_eager")
    try:
        compiled = window()
        report = compile_report(env)
    finally:
        eager_physics(env)
    assert report["fallback_reason"] is None and report["eager_reason"] is None, report
    assert "physics step (euler), with grad" in report["first_call_seconds"], report
    torch.testing.assert_close(compiled[0]["next", "observation"], eager[0]["next", "observation"],
                               rtol=1e-10, atol=1e-10)
    for got, want in zip(compiled[1], eager[1]):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)

    class Slotted:  # a callable that cannot be weakly referenced
        __slots__ = ()

        def __call__(self, td):
            return policy(td)

    compile_physics(env, steps_per_chunk=2, backend="aot_eager")
    try:
        with torch.no_grad():
            slotted = env.rollout(4, Slotted(), auto_reset=False, tensordict=start.clone())
        assert compile_report(env)["eager_reason"] is None
        torch.testing.assert_close(slotted["next", "observation"], eager[0]["next", "observation"],
                                   rtol=1e-10, atol=1e-10)

        def overwriting(td):  # writes the env's own entry: the chunk would drop it, so the steps run eagerly
            return policy(td).set("observation", td["observation"] * 0 + 7)

        with torch.no_grad():
            compiled_out = env.rollout(4, overwriting, auto_reset=False, tensordict=start.clone())
        assert "changed the env's own entries" in compile_report(env)["eager_reason"]
    finally:
        eager_physics(env)
    with torch.no_grad():
        eager_out = env.rollout(4, overwriting, auto_reset=False, tensordict=start.clone())
    torch.testing.assert_close(compiled_out["observation"], eager_out["observation"], rtol=0, atol=0)
    assert (compiled_out["observation"][:, 1:] == 7).all()

    pendulum = make_mujoco_env("pendulum", num_envs=2, seed=0)
    compile_physics(pendulum, steps_per_chunk=2)
    pendulum.rollout(2, lambda td: td.set("action", torch.zeros(2, 1)))
    assert "not a TensorDict module" in compile_report(pendulum)["eager_reason"]
    assert compile_report(pendulum)["first_call_seconds"] == {}
