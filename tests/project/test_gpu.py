"""The GPU path, end to end: every task, the collector, the compiled chunks, train.py with every
loss, checkpoints moved between CUDA and CPU, rendering from CUDA tensors.

Each test compares against the same computation on the CPU (float64), the reference the rest of
the suite checks against gymnasium, MuJoCo and finite differences. Skipped without a CUDA device:
run ``python -m pytest -q tests/project/test_gpu.py`` on a GPU machine.
"""
import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_diffenvs import compile_physics, list_envs, make_env
from torchrl_diffenvs.collectors import DiffWindowCollector
from torchrl_diffenvs.envs.rollout import compile_report
from torchrl_diffenvs.modules import make_actor

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")]

N, STEPS = 4, 12


def window_on(device: str, name: str):
    """A 12-step rollout with a deterministic policy, from the same start and weights on any
    device; the rollout and the gradient of its rewards and observations (every agent's, on a
    multi-agent env; a constant reward such as CartPole's has none) w.r.t. the policy's parameters, on the CPU (``None`` for the standard deviation, which a
    deterministic action does not use)."""
    env = make_env(name, num_envs=N, seed=0, dtype=torch.float64, device=device)
    torch.manual_seed(0)
    actor = make_actor(env, hidden=(16,)).double().to(device)
    start = make_env(name, num_envs=N, seed=0, dtype=torch.float64).reset().to(device)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = env.rollout(STEPS, actor, auto_reset=False, tensordict=start, break_when_any_done=False)
    outputs = [out["next", key] for key in out["next"].keys(True, True)
               if (key[-1] if isinstance(key, tuple) else key) in ("reward", "observation")]
    grads = torch.autograd.grad(sum(o.sum() for o in outputs), list(actor.parameters()), allow_unused=True)
    return out.detach().cpu(), [None if g is None else g.cpu() for g in grads]


@pytest.mark.parametrize("name", list_envs())
def test_every_task_rolls_out_and_differentiates_on_cuda_as_on_cpu(name):
    (cuda_out, cuda_grads), (cpu_out, cpu_grads) = window_on("cuda", name), window_on("cpu", name)
    for key in cpu_out.keys(True, True):
        torch.testing.assert_close(cuda_out[key], cpu_out[key], rtol=1e-7, atol=1e-8, msg=str(key))
    assert any(g is not None and g.abs().sum() > 0 for g in cpu_grads)  # the outputs depend on the policy
    for got, want in zip(cuda_grads, cpu_grads):
        assert (got is None) == (want is None)
        if want is not None:
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-8)


def test_collector_and_compiled_chunks_on_cuda():
    env = make_env("pendulum", num_envs=8, seed=0, max_episode_steps=6, device="cuda")
    actor = make_actor(env, hidden=(16,)).to("cuda")
    compile_physics(env, steps_per_chunk=4)
    collector = DiffWindowCollector(env, actor, horizon=8, total_windows=2)
    for window in collector:
        assert window.device.type == "cuda" and window["next", "reward"].requires_grad
        window["next", "reward"].sum().backward()
    report = compile_report(env)
    assert report["fallback_reason"] is None and report["first_call_seconds"]


@pytest.mark.parametrize("name", ["pendulum", "HalfCheetah-v5"])
def test_cuda_graphs_rollout_matches_eager(name):
    """``compile_physics(mode="reduce-overhead")``: inductor's CUDA graphs, for a whole chunk (the
    pendulum) and for the articulated tasks' physics step replayed at every step; the same
    rollout as eager from the same generator state (float64: fused kernels round differently)."""
    envs = [make_env(name, num_envs=64, seed=0, dtype=torch.float64, device="cuda") for _ in range(2)]
    compile_physics(envs[1], steps_per_chunk=4, mode="reduce-overhead")
    outs = []
    for env in envs:
        torch.manual_seed(0)
        with torch.no_grad():
            outs.append(env.rollout(12, break_when_any_done=False).cpu())
    assert compile_report(envs[1])["fallback_reason"] is None
    for key in ("observation", "reward"):
        torch.testing.assert_close(outs[1]["next", key], outs[0]["next", key], rtol=1e-7, atol=1e-9)
    grads = []  # a window with gradient: the compiled graphs without CUDA graphs
    start = make_env(name, num_envs=64, seed=1, dtype=torch.float64, device="cuda").reset()
    for env in envs:
        torch.manual_seed(0)
        actor = make_actor(env, hidden=(16,)).double().to("cuda")
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            out = env.rollout(8, actor, auto_reset=False, tensordict=start.clone(), break_when_any_done=False)
        grads.append(torch.autograd.grad(out["next", "reward"].sum(), list(actor.parameters()), allow_unused=True))
    for got, want, param in zip(*reversed(grads), actor.parameters()):  # unused: None eagerly, zeros compiled
        zeros = torch.zeros_like(param)
        torch.testing.assert_close(zeros if got is None else got, zeros if want is None else want,
                                   rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("loss", ["bptt", "shac", "ppo", "sac"])
def test_train_on_cuda_resume_on_cpu_and_back(loss, tmp_path):
    from _train_helpers import STEPS_PER_ITER, tiny_cfg, train_script

    from torchrl_diffenvs.training import load_checkpoint

    steps = STEPS_PER_ITER[loss]
    first = train_script.run(tiny_cfg("pendulum", loss, 2, "device=cuda"), tmp_path / "cuda")
    saved = load_checkpoint(first["checkpoint"], map_location=None)  # where the run kept its tensors
    assert all(value.device.type == "cuda" and value.isfinite().all() for value in saved["policy"].values())
    on_cpu = train_script.run(tiny_cfg("pendulum", loss, 4, "device=cpu", f"resume={first['checkpoint']}"),
                              tmp_path / "cpu")
    assert on_cpu["env_steps"] == 4 * steps
    back = train_script.run(tiny_cfg("pendulum", loss, 6, "device=cuda", f"resume={on_cpu['checkpoint']}"),
                            tmp_path / "back")
    assert back["env_steps"] == 6 * steps


def test_rendering_from_cuda_tensors():
    """A CUDA rollout's frame is the frame of the same states copied to the CPU (rendering the two
    devices' own rollouts would compare their rounding: a pixel at an edge may differ)."""
    env = make_env("HalfCheetah-v5", num_envs=2, seed=0, device="cuda")
    last = env.rollout(3)[:, -1]
    on_cuda = env.render(last, size=64)
    on_cpu = make_env("HalfCheetah-v5", num_envs=2, seed=0).render(last.cpu(), size=64)
    assert on_cuda.shape == (64, 64, 3) and on_cuda.std() > 0  # a drawn scene, not a blank frame
    assert (on_cuda == on_cpu).all()


def _sync_sites(fn) -> list[str]:
    """The Python lines that synchronised host and device while ``fn`` ran."""
    import warnings
    from pathlib import Path

    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return [f"{'/'.join(Path(w.filename).parts[-3:])}:{w.lineno}" for w in caught
            if "synchronizing" in str(w.message) and "prototype" not in str(w.message)
            and "torchrl_diffenvs" in w.filename]  # ours (TorchRL's own reset bookkeeping is not)


@pytest.mark.parametrize("name,contact", [*((name, None) for name in list_envs() if name.endswith("-v5")),
                                          ("HalfCheetah-v5", "smooth"), ("pendulum", None)])
def test_an_env_step_and_a_partial_reset_never_synchronise_host_and_device(name, contact):
    """The step (physics, contacts and constraint solve, reward, termination) and the reset of some
    envs run without a host-device synchronisation in this library's code: masks, not
    data-dependent branches; every MuJoCo task with its own contact model."""
    env = make_env(name, num_envs=64, seed=0, device="cuda", **({"contact": contact} if contact else {}))
    td = env.rand_step(env.reset())  # warm-up: caches, lazily built buffers
    td = env.rand_action(td.get("next").exclude("reward", "done", "terminated", "truncated"))
    with torch.no_grad():
        assert _sync_sites(lambda: env.step(td)) == []
        partial = td.select(*env.state_spec.keys(True, True)).set(
            "_reset", torch.arange(64, device="cuda").remainder(2).bool().unsqueeze(-1))
        assert _sync_sites(lambda: env.reset(partial)) == []


def test_the_cuda_solve_stops_once_the_host_sees_every_env_converged(monkeypatch):
    """MuJoCo's Newton solve on CUDA: the host stops issuing rounds a few rounds after every env
    converged (read without waiting), with the result of all the model's rounds."""
    from torchrl_diffenvs.articulated import newton

    env = make_env("HalfCheetah-v5", num_envs=256, seed=0, dtype=torch.float64, device="cuda")
    state = env.rollout(20)[:, -1]["next", "state"]  # on the floor: contacts active
    rounds = []
    original = newton.newton_round

    def counted(*args):
        rounds.append(1)
        return original(*args)

    monkeypatch.setattr(newton, "newton_round", counted)

    def one_step():
        from torchrl_diffenvs.articulated import step

        rounds.clear()
        ctrl = torch.zeros(256, env.action_dim, dtype=torch.float64, device="cuda")
        with torch.no_grad():
            result = step(env.tree, state["qpos"], state["qvel"], ctrl, dict(env.params.items()), env.model.timestep,
                          env.integrator)
        return result, len(rounds)

    watched, watched_rounds = one_step()
    monkeypatch.setattr(newton.ConvergenceWatch, "for_device", classmethod(lambda cls, device: None))
    fixed, fixed_rounds = one_step()
    assert fixed_rounds == env.tree.model.iterations and watched_rounds < fixed_rounds / 4, (watched_rounds,
                                                                                             fixed_rounds)
    assert watched.solver_converged.all()
    torch.testing.assert_close(watched.qvel, fixed.qvel, rtol=0, atol=0)


BOXES = """<mujoco><option timestep="0.005"/><worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="box1" pos="0 0 0.035"><freejoint/><geom type="box" size="0.1 0.06 0.04"/></body>
    <body name="box2" pos="0.02 0.01 0.11"><freejoint/><geom type="box" size="0.05 0.05 0.04"/></body>
    <body name="capsule" pos="0.05 0 0.165" euler="0 90 0"><freejoint/><geom type="capsule" size="0.02 0.1"/></body>
    </worldbody></mujoco>"""


def test_box_contacts_step_without_synchronising(tmp_path):
    """The box pairs (plane-box, box-box, capsule-box; no registered task has them) step on CUDA
    without a host-device synchronisation, as on the CPU."""
    from torchrl_diffenvs.articulated import RigidBodyTree, load_mjcf, step
    from torchrl_diffenvs.articulated.dynamics import default_params
    from torchrl_diffenvs.articulated.pipeline import invweight0

    path = tmp_path / "boxes.xml"
    path.write_text(BOXES)
    model = load_mjcf(str(path))
    outs = {}
    for device in ("cpu", "cuda"):
        tree = RigidBodyTree.from_model(model, device=device)
        assert tree.contact_model == "mujoco"
        params = {k: v.unsqueeze(0).expand(4, *v.shape).to(device) for k, v in default_params(model).items()}
        params["contact_friction"] = torch.as_tensor(tree.contact_pair_friction, device=device).expand(4, -1)
        qpos = torch.as_tensor(model.qpos0, dtype=torch.float64, device=device).expand(4, -1).clone()
        qvel = torch.zeros(4, model.nv, dtype=torch.float64, device=device)
        ctrl = torch.zeros(4, 0, dtype=torch.float64, device=device)
        weights = invweight0(tree, params)

        def one():
            return step(tree, qpos, qvel, ctrl, params, model.timestep, "euler", weights)
        one()  # warm-up
        if device == "cuda":
            assert _sync_sites(one) == []
        outs[device] = one()
    torch.testing.assert_close(outs["cuda"].qvel.cpu(), outs["cpu"].qvel, rtol=1e-9, atol=1e-9)
