"""MuJoCo's contact dynamics (``contact="mujoco"``, the default) against the smooth penalty model
(``contact="smooth"``): parity with ``mj_step``, speed, ops per step and the compiled step.

* **parity** (float64): one physics step from MuJoCo's own state along a random-action trajectory
  of ``steps`` steps, against ``mj_step``'s next state: the worst ``|dqpos|`` and ``|dqvel|`` of
  each contact model (with each its default integrator), and the share of steps with contact.
  The humanoids' files (50 PGS iterations, unconverged by design) are also compared with
  ``mj_step`` of the same file with a converged Newton solve (the same minimiser): what is left
  of the gap there is the residual of MuJoCo's unconverged PGS solve. The Pusher's trajectory
  drives its fingertip at the object (random actions never touch it), through the states where
  MuJoCo 4's multi-contact gives a wrist capsule lying along the object's cap two contacts.
* **speed** (one thread, interleaved rounds, CPU time): env-steps/s at ``N`` envs of the env step
  (no gradient) and of a 4-step BPTT window (forward + backward), and the ratio mujoco / smooth;
  each model with its default integrator, and ``TASK:INTEGRATOR`` both with that one.
* **ops**: aten ops per env step (``torch.profiler`` on the CPU, no gradient), the CPU proxy of
  CUDA kernels per step; and whether ``torch.compile(fullgraph=True)`` of one physics step
  succeeds (traced by dynamo; a graph break: the data-dependent parts, reported with their reason).

Needs ``pip install "torchrl_diffenvs[mujoco]"``. The data file holds the parts measured:
``parity_tasks=[]`` or ``speed_tasks=[]`` with ``data=<name>`` measures one part into its own file.

    OMP_NUM_THREADS=1 python benchmarks/contact_model.py
    OMP_NUM_THREADS=1 python benchmarks/contact_model.py "parity_tasks=[]" data=contact_model_speed
"""
from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import make_env  # noqa: E402
from torchrl_diffenvs.articulated import step  # noqa: E402
from torchrl_diffenvs.articulated.pipeline import invweight0  # noqa: E402

PARITY_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "HumanoidStandup-v5", "Pusher-v5"]
# the Ant's file steps RK4 (four constraint solves per physics step), the smooth option's default is implicit
# Euler (one evaluation): "Ant-v5:implicit" times both models with one evaluation per physics step
SPEED_TASKS = ["HalfCheetah-v5", "Ant-v5", "Ant-v5:implicit", "Humanoid-v5", "Pusher-v5"]


def _trajectory(mm, steps: int, seed: int, warmstart: bool = True):
    """MuJoCo's own random-action trajectory: ``(qpos, qvel, ctrl)`` starts and mj_step's next states."""
    import mujoco

    data = mujoco.MjData(mm)
    if not warmstart:
        mm.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_WARMSTART
    rng = np.random.default_rng(seed)
    data.qpos[:] += rng.uniform(-0.1, 0.1, mm.nq)
    mujoco.mj_normalizeQuat(mm, data.qpos)
    starts, ends, touching = [], [], 0
    for _ in range(steps):
        data.ctrl[:] = rng.uniform(mm.actuator_ctrlrange[:, 0], mm.actuator_ctrlrange[:, 1])
        starts.append((data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()))
        mujoco.mj_step(mm, data)
        touching += data.ncon > 0
        ends.append((data.qpos.copy(), data.qvel.copy()))
    return starts, ends, touching / steps


def pushing_trajectory(mm, episodes: int, steps: int, seed: int):
    """MuJoCo's own Pusher trajectories with the fingertip driven at the object (random actions
    never reach it): ``(starts, ends, wrist_depth, multi)``, and per start state its deepest
    capsule-cylinder contact (``inf``: none) and whether MuJoCo's multi-CCD added contacts to a
    wrist-object pair."""
    import mujoco

    data = mujoco.MjData(mm)
    rng = np.random.default_rng(seed)
    tip, obj = mm.body("tips_arm").id, mm.body("object").id
    jac = np.zeros((3, mm.nv))
    starts, ends, depth, extra = [], [], [], []
    for _ in range(episodes):
        mujoco.mj_resetData(mm, data)
        data.qpos[-4:-2] = rng.uniform(-0.3, 0.3, 2)
        for t in range(steps):
            if t % 5 == 0:  # Jacobian transpose towards the object, with noise
                mujoco.mj_jacBody(mm, data, jac, None, tip)
                pull = jac[:, :7].T @ (data.xpos[obj] - data.xpos[tip])
                data.ctrl[:] = np.clip(20 * pull - 0.5 * data.qvel[:7] + rng.normal(0, 0.5, 7), -2, 2)
            starts.append((data.qpos.copy(), data.qvel.copy(), data.ctrl.copy()))
            mujoco.mj_step(mm, data)
            # mj_step's contacts are those of the state it started from
            wrist = [(c.dist, c.geom1) for c in data.contact[:data.ncon]
                     if mm.geom_type[c.geom2] == mujoco.mjtGeom.mjGEOM_CYLINDER
                     and mm.geom_type[c.geom1] == mujoco.mjtGeom.mjGEOM_CAPSULE]
            depth.append(min((d for d, _ in wrist), default=np.inf))
            extra.append(len(wrist) > len({g for _, g in wrist}))
            ends.append((data.qpos.copy(), data.qvel.copy()))
    return starts, ends, np.array(depth), np.array(extra)


def _steps_with_newton(mm, starts):
    """``mj_step`` from each start with the file's solver swapped for a converged Newton solve."""
    import mujoco

    mm.opt.solver, mm.opt.iterations = mujoco.mjtSolver.mjSOL_NEWTON, 100
    data, out = mujoco.MjData(mm), []
    for q, v, u in starts:
        data.qpos[:], data.qvel[:], data.ctrl[:], data.qacc_warmstart[:] = q, v, u, 0.0
        mujoco.mj_step(mm, data)
        out.append((data.qpos.copy(), data.qvel.copy()))
    return out


def _one_step_gap(env, starts, ends):
    """Worst ``(|dqpos|, |dqvel|)`` of one physics step of ``env``'s simulator from each start."""
    n = len(starts)
    qpos, qvel, ctrl = (torch.as_tensor(np.stack([s[i] for s in starts])) for i in range(3))
    params = {k: v[:1].expand(n, *v.shape[1:]) for k, v in env.params.items()}
    result = step(env.tree, qpos, qvel, ctrl, params, env.model.timestep, env.integrator, invweight0(env.tree, params))
    return (float(np.abs(result.qpos.numpy() - np.stack([e[0] for e in ends])).max()),
            float(np.abs(result.qvel.numpy() - np.stack([e[1] for e in ends])).max()))


def parity(task: str, steps: int) -> dict:
    import mujoco

    env = make_env(task, num_envs=1, dtype=torch.float64)
    mm = mujoco.MjModel.from_xml_path(env.model.path)
    out = {"task": task, "steps": steps, "integrator": env.integrator, "solver": env.model.solver}
    if task == "Pusher-v5":  # random actions never reach the object: the fingertip is driven at it
        starts, ends, depth, multi = pushing_trajectory(mm, episodes=max(1, steps // 100), steps=100, seed=0)
        out["contact_share"] = float(np.isfinite(depth).mean())  # the wrist on the object
        out["trajectory"] = "pushing"
        out["deep_share"] = float((depth < -0.02).mean())  # the wrist's axis inside the object
        out["multi_contact_share"] = float(multi.mean())  # a wrist capsule along the object's cap: two contacts
    else:
        starts, ends, out["contact_share"] = _trajectory(mm, steps, seed=0)
    out["mujoco"] = _one_step_gap(env, starts, ends)
    out["smooth"] = _one_step_gap(make_env(task, num_envs=1, dtype=torch.float64, contact="smooth"), starts, ends)
    if env.model.solver == "pgs":
        out["mujoco_vs_newton"] = _one_step_gap(env, starts,
                                                _steps_with_newton(mujoco.MjModel.from_xml_path(env.model.path), starts))
    return out


def _aten_ops_per_step(env, td) -> int:
    with torch.no_grad():
        return C.aten_ops(lambda: env.step(td))


def _compiles_fullgraph(env) -> str:
    """``"yes"`` or the first line of the reason ``torch.compile(fullgraph=True)`` of one physics step
    fails. Traced by dynamo only (``backend="eager"``): a graph break is dynamo's verdict, and
    inductor's code generation for the Ant's RK4 step takes longer than the rest of the benchmark."""
    tree, params = env.tree, {k: v for k, v in env.params.items()}
    weights = invweight0(tree, params)
    state = env.reset()["state"]
    action = torch.zeros(env.batch_size[0], env.action_dim, dtype=env.float_dtype)

    def one(qpos, qvel, ctrl):
        return step(tree, qpos, qvel, ctrl, params, env.model.timestep, env.integrator, weights).qvel

    try:
        torch._dynamo.reset()
        torch.compile(one, fullgraph=True, dynamic=False, backend="eager")(state["qpos"], state["qvel"], action)
        return "yes"
    except Exception as error:  # a graph break: report why
        return f"no: {str(error).strip().splitlines()[0][:160]}"


def _yes_no(outcome: str | None) -> str:
    """A table cell for a compile outcome (the reason stays in the raw JSON)."""
    return "-" if outcome is None else ("yes" if outcome == "yes" else "no (graph break)")


def speed(spec: str, n: int, rounds: int) -> dict:
    """``spec``: a task (each contact model with its default integrator), or ``TASK:INTEGRATOR``
    (both with that one: the cost of one evaluation of each, where the defaults differ)."""
    task, _, integrator = spec.partition(":")
    options = {"integrator": integrator} if integrator else {}
    envs = {contact: make_env(task, num_envs=n, contact=contact, **options) for contact in ("mujoco", "smooth")}
    tds = {contact: env.reset() for contact, env in envs.items()}
    gen = torch.Generator().manual_seed(0)
    actions = (torch.rand(8, n, envs["mujoco"].action_dim, generator=gen) * 2 - 1)
    for contact, env in envs.items():  # into contact before timing
        for a in actions:
            tds[contact] = env.step(tds[contact].set("action", a))["next"]

    def forward(contact):
        def run():
            td = tds[contact]
            with torch.no_grad():
                for a in actions[:2]:
                    td = envs[contact].step(td.set("action", a))["next"]
        return run

    def window(contact):
        def run():
            td, total = tds[contact].clone(), 0.0
            for a in actions[:4]:
                td = envs[contact].step(td.set("action", a.clone().requires_grad_(True)))["next"]
                total = total + td["reward"].sum()
            total.backward()
        return run

    fns = {f"{c} {kind}": (forward(c) if kind == "step" else window(c)) for c in envs for kind in ("step", "window")}
    times = C.interleaved(fns, rounds)
    steps = {"step": 2 * n, "window": 4 * n}
    rates = {name: C.spread([steps[name.split()[1]] / c for c in t["cpu"]]) for name, t in times.items()}
    ratio = {kind: C.median_ratio([c / steps[kind] for c in times[f"smooth {kind}"]["cpu"]],
                                  [c / steps[kind] for c in times[f"mujoco {kind}"]["cpu"]]) for kind in steps}
    ops = {c: _aten_ops_per_step(env, tds[c].set("action", actions[0])) for c, env in envs.items()}
    return {"task": spec, "N": n, "rates_cpu": rates, "ratio_mujoco_over_smooth": ratio, "aten_ops_per_env_step": ops,
            "integrators": {c: env.integrator for c, env in envs.items()}}


@dataclass(frozen=True)
class ContactModelSettings(C.BenchmarkSettings):
    parity_tasks: list[str] = field(default_factory=lambda: list(PARITY_TASKS))
    # TASK, or TASK:INTEGRATOR for both contact models with that integrator
    speed_tasks: list[str] = field(default_factory=lambda: list(SPEED_TASKS))
    steps: int = 1000  # trajectory length of the parity check
    size: int = 1024  # N of the speed check
    compile: bool = True  # also try torch.compile(fullgraph=True) of one physics step


def main(argv=None) -> dict:
    from torchrl_diffenvs.checks import parse_cli

    args = parse_cli(ContactModelSettings, argv, __doc__)
    if (not args.parity_tasks or not args.speed_tasks) and args.data is None and not args.quick:
        raise SystemExit("contact_model: a run that leaves out a part (parity_tasks=[] or speed_tasks=[]) writes its own "
                         "data file: name it with data=<name> (docs/data/contact_model.json holds both parts)")
    C.setup_threads(args.threads)
    warnings.filterwarnings("ignore")
    steps = 50 if args.quick else args.steps
    n = 16 if args.quick else args.size
    rounds = args.repeats or (2 if args.quick else 3)
    info = C.versions()
    C.print_header("MuJoCo's contact model against the smooth model", info)
    g = C.fmt_error
    parity_rows, parities = [], []
    for task in args.parity_tasks:
        p = parity(task, steps)
        parities.append(p)
        apart = p.get("mujoco_vs_newton")
        label = f"{task} (pushing)" if p.get("trajectory") == "pushing" else task
        parity_rows.append([label, f"{p['integrator']}, {p['solver']}", f"{100 * p['contact_share']:.0f}%",
                            g(p["mujoco"][0]), g(p["mujoco"][1]), "-" if apart is None else g(apart[1]),
                            g(p["smooth"][0]), g(p["smooth"][1])])
        print(f"# {task}: {parity_rows[-1]}", flush=True)
    parity_headers = ["task", "integrator, file's solver", "steps in contact", "mujoco |dqpos|", "mujoco |dqvel|",
                      "mujoco |dqvel| without the known residual", "smooth |dqpos|", "smooth |dqvel|"]
    C.print_table(parity_headers, parity_rows)
    speed_rows, speeds = [], []
    for task in args.speed_tasks:
        s = speed(task, n, rounds)
        if args.compile:
            name, _, integrator = task.partition(":")
            options = {"integrator": integrator} if integrator else {}
            s["fullgraph_compile"] = {c: _compiles_fullgraph(make_env(name, num_envs=8, contact=c, **options))
                                      for c in ("mujoco", "smooth")}
        speeds.append(s)
        r, ops = s["rates_cpu"], s["aten_ops_per_env_step"]
        compiled = s.get("fullgraph_compile", {})
        speed_rows.append([task, n, f"{s['integrators']['mujoco']} / {s['integrators']['smooth']}",
                           C.fmt_rate(r["mujoco step"]["median"]), C.fmt_rate(r["smooth step"]["median"]),
                           C.fmt_ratio(s["ratio_mujoco_over_smooth"]["step"]),
                           C.fmt_rate(r["mujoco window"]["median"]), C.fmt_rate(r["smooth window"]["median"]),
                           C.fmt_ratio(s["ratio_mujoco_over_smooth"]["window"]), f"{ops['mujoco']} / {ops['smooth']}",
                           " / ".join(_yes_no(compiled.get(c)) for c in ("mujoco", "smooth"))])
        print(f"# {task}: {speed_rows[-1]}", flush=True)
    speed_headers = ["task", "N", "integrator (mujoco / smooth)", "mujoco step/s", "smooth step/s", "mujoco / smooth",
                     "mujoco fwd+bwd", "smooth fwd+bwd", "mujoco / smooth (fwd+bwd)", "aten ops per env step",
                     "fullgraph compile"]
    C.print_table(speed_headers, speed_rows)
    payload = {"benchmark": "contact_model", "info": info, "parity": parities, "speed": speeds}
    C.write_json("contact_model", payload, args.out)
    tables = {}  # only the parts measured (parity_tasks=[] or speed_tasks=[] leaves one out)
    if parity_rows:
        tables["parity"] = C.data_table(
            f"One physics step from MuJoCo's state against mj_step, float64, worst over a {steps}-step random-action "
            f"trajectory (the Pusher: {steps} steps of a controller pushing the object; steps in contact: the wrist "
            "on the object). Without the known residual: the PGS files against mj_step with a converged Newton solve",
            parity_headers, parity_rows)
    if speed_rows:
        tables["speed"] = C.data_table(f"Env-steps/s at N={n}, one thread, from CPU time (fwd+bwd: a 4-step BPTT "
                                       "window)", speed_headers, speed_rows)
    C.write_data(args, "contact_model", tables)
    return payload


if __name__ == "__main__":
    main()
