"""Stress: do the contact tasks stay finite under the policies that break simulators?

Each contact task runs ``num_envs`` envs (float32, as training does) for ``steps`` steps with no
truncation, under each policy:

* ``random``: uniform actions in the control range, new each step;
* ``bang-bang``: +-1 per motor, switched at random every 1-20 steps;
* ``resonant``: every motor a full-range square wave, each env its own period (2-40 steps), the
  gait that pumps energy into the legs;
* ``greedy``: an adversary that uses the simulator's own gradient: each step it plays
  ``sign(d qvel_0 / d action)`` at full range (the runners' forward velocity: it runs as far and
  as fast as the physics allows, and learned runners travel hundreds of metres, where float32
  used to fail; the Pusher's shoulder: it swings the arm as fast as it goes);
* ``far``: random actions from start states 10 km down the track (the tasks whose first joint
  moves the root along the track; the Pusher's arm is fixed to the world: no row).

Reported per task and policy: envs that became non-finite, the env steps in which some constraint
solve used all its iterations (MuJoCo's contact; the env flags them in ``("state",
"solver_unconverged")`` and steps on), the largest ``|qvel|`` and the torso's largest travel
(``-`` for the Pusher). Episodes do not end on a fall (``terminate_when_unhealthy=0`` where a task
has it). A healthy simulator has 0 non-finite envs everywhere.

A task and policy take minutes to hours at 1024 envs; the data file is rewritten after each row, and
``resume=true`` keeps its rows and runs only the (task, contact, integrator, policy, size) rows it
does not hold yet. A row longer than a sitting is resumable too: every ``checkpoint_every`` steps
it saves where it is (the envs' tensordict and random streams, the policy's state, the counters)
under ``benchmarks/stress_partial/<data file>/`` (commit it to continue from another checkout),
and ``resume=true`` continues it from there, to the same result as a row run in one go; the file
is removed once the row is in the data file.

    OMP_NUM_THREADS=1 python benchmarks/stress.py
    OMP_NUM_THREADS=1 python benchmarks/stress.py tasks=[HalfCheetah-v5] num_envs=1024 steps=1000
"""
from __future__ import annotations

import json
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from _common import BenchmarkSettings, print_table  # noqa: E402

from torchrl_diffenvs import make_env  # noqa: E402
from torchrl_diffenvs.envs.mujoco.base import MuJoCoModelEnv  # noqa: E402
from torchrl_diffenvs.checks import boolean, checked, each, one_of, parse_cli, positive_int  # noqa: E402

CONTACT_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "HumanoidStandup-v5", "Pusher-v5"]
POLICIES = ["random", "bang-bang", "resonant", "greedy", "far"]
HEADERS = ["task", "contact", "integrator", "policy", "envs x steps", "non-finite envs", "unconverged env-steps",
           "max |qvel|", "max travel (m)"]


@dataclass(frozen=True)
class StressSettings(BenchmarkSettings):
    """tasks=[..] policies=[..] num_envs=1024 steps=1000"""

    tasks: tuple = checked(tuple(CONTACT_TASKS), each(one_of(CONTACT_TASKS)))
    policies: tuple = checked(tuple(POLICIES), each(one_of(POLICIES)))
    num_envs: int = 1024
    steps: int = 1000
    seed: int = 0
    resume: bool = checked(False, boolean)  # keep the data file's rows (and partial rows); run only the missing ones
    checkpoint_every: int = checked(50, positive_int)  # steps between a partial row's saves
    # None: each task's default
    integrator: str | None = checked(None, lambda v: None if v is None else one_of(MuJoCoModelEnv.INTEGRATORS)(v))


PARTIAL_DIR = Path(__file__).resolve().parent / "stress_partial"


def make_policy(kind: str, env, gen: torch.Generator):
    """``(policy(td, t) -> action, state)``: ``state`` is the dict of tensors the policy keeps
    between steps (saved with a partial row, and loaded back into the same dict)."""
    n, m = env.batch_size[0], env.action_dim
    if kind in ("random", "far"):
        return (lambda td, t: torch.rand(n, m, generator=gen) * 2 - 1), {}
    if kind == "bang-bang":
        state = {"action": torch.sign(torch.rand(n, m, generator=gen) - 0.5),
                 "switch": torch.randint(1, 21, (n, m), generator=gen)}

        def bang(td, t):
            flip = (t % state["switch"]) == 0
            state["action"] = torch.where(flip, torch.sign(torch.rand(n, m, generator=gen) - 0.5), state["action"])
            return state["action"]
        return bang, state
    if kind == "resonant":
        state = {"period": torch.randint(2, 41, (n, 1), generator=gen),
                 "phase": torch.randint(0, 40, (n, m), generator=gen)}
        return (lambda td, t: torch.where(((t + state["phase"]) % state["period"]) < state["period"] / 2, 1.0, -1.0),
                state)

    def greedy(td, t):  # sign of d(forward velocity)/d(action), through one env step
        action = torch.zeros(n, m, requires_grad=True)
        probe = td.clone()
        probe["action"] = action
        qvel = env.step(probe)["next", "state", "qvel"]
        (grad,) = torch.autograd.grad(qvel[:, 0].sum(), action)
        return torch.where(grad >= 0, 1.0, -1.0)
    return greedy, {}


def travels(env) -> bool:
    """Whether the env's first coordinate moves its root along the track (a free or slide joint),
    what ``far`` shifts and the travel column measures."""
    return env.tree.joint_type[0] in ("free", "slide")


def stress(task: str, kind: str, s: StressSettings, partial: Path | None = None) -> dict:
    """One row: ``task`` under the policy ``kind``. ``partial``: where the row saves itself every
    ``s.checkpoint_every`` steps and, if the file is there, what it continues from (`main`
    removes it once the row is in the data file); None: it runs in one go. Returns the row's
    numbers and the envs' last ``state``."""
    options = {"integrator": s.integrator} if s.integrator else {}
    falls = "terminate_when_unhealthy" in make_env(task, num_envs=1, **options).params.keys()
    env = make_env(task, num_envs=s.num_envs, seed=s.seed, max_episode_steps=None,
                   params={"terminate_when_unhealthy": 0.0} if falls else {}, **options)
    gen = torch.Generator().manual_seed(s.seed)
    td = env.reset()
    if kind == "far":
        state = td["state"].clone()
        state["qpos"][:, 0] += 1e4
        td.set("state", state)
        td = env.reset(td, set_state=True)
    start_x = td["state", "qpos"][:, 0].clone()
    policy, policy_state = make_policy(kind, env, gen)
    bad = torch.zeros(s.num_envs, dtype=torch.bool)
    # MuJoCo's contact flags the env steps whose constraint solve stopped short; the smooth option has no solve
    unconverged = 0 if "solver_unconverged" in td["state"].keys() else None
    speed, travel, first, elapsed = 0.0, 0.0, 0, 0.0
    row = {"task": task, "policy": kind, "num_envs": s.num_envs, "steps": s.steps, "seed": s.seed,
           "contact": env.contact, "integrator": env.integrator}
    if partial is not None and partial.exists():
        try:
            saved = torch.load(partial, weights_only=False)
            saved_row = saved.get("row")
        except Exception as error:  # a truncated or foreign file
            raise SystemExit(f"stress: {partial} is not a partial stress row ({error!r}); remove it to run this "
                             "row from its start") from None
        if saved_row != row:
            raise SystemExit(f"stress: {partial} is a partial row of {saved_row}, not of {row}; remove it (or run "
                             "without resume=true) to run this row from its start")
        td = td.update(saved["td"])  # the params are the reset's (the row never changes them)
        start_x, bad, unconverged = saved["start_x"], saved["bad"], saved["unconverged"]
        speed, travel, first, elapsed = saved["speed"], saved["travel"], saved["t"], saved["elapsed"]
        env.rng.set_state(saved["env_rng"])
        gen.set_state(saved["gen"])
        policy_state.update(saved["policy_state"])
        print(f"# {task} {kind}: continuing a partial row from step {first} of {s.steps}", flush=True)
    began = time.perf_counter() - elapsed
    for t in range(first, s.steps):
        if partial is not None and t > first and t % s.checkpoint_every == 0:
            partial.parent.mkdir(parents=True, exist_ok=True)
            written = partial.with_suffix(".tmp")  # then renamed: a kill mid-write leaves the last good file
            with open(written, "wb") as file:  # without the params, the reset's: a smaller file
                torch.save({"row": row, "t": t, "td": td.exclude("params"), "start_x": start_x, "bad": bad,
                            "unconverged": unconverged, "speed": speed, "travel": travel,
                            "elapsed": time.perf_counter() - began, "env_rng": env.rng.get_state(),
                            "gen": gen.get_state(), "policy_state": dict(policy_state)}, file)
                file.flush()
                os.fsync(file.fileno())
            written.replace(partial)
        with torch.no_grad() if kind != "greedy" else torch.enable_grad():
            action = policy(td, t)
        with torch.no_grad():
            td["action"] = action.to(td["observation"].dtype)
            td = env.step_mdp(env.step(td))
            qvel = td["state", "qvel"]
            finite = torch.isfinite(qvel).all(-1) & torch.isfinite(td["state", "qpos"]).all(-1)
            bad |= ~finite
            if unconverged is not None:
                unconverged += int(td["state", "solver_unconverged"].sum())
            if finite.any():
                speed = max(speed, float(qvel[finite].abs().max()))
                travel = max(travel, float((td["state", "qpos"][finite, 0] - start_x[finite]).abs().max()))
    return {"nonfinite": int(bad.sum()), "unconverged": unconverged, "max_qvel": speed,
            "travel": travel if travels(env) else None,
            "contact": env.contact, "integrator": env.integrator,
            "env_steps_per_s": s.num_envs * s.steps / (time.perf_counter() - began), "state": td["state"]}


def resumed(settings: StressSettings) -> tuple[list[list[str]], dict | None]:
    """With ``resume=true``, the rows of the data file this run rewrites and its provenance merged
    with this sitting's (``measured=`` of `write_data`: the newest date, every machine and
    command); without, no rows and ``None``."""
    path = C.data_path(settings, "stress")
    if not settings.resume:
        return [], None
    if path is None:
        raise SystemExit("resume=true: no data file to resume (data=none, or a quick run without data=)")
    if not path.exists():
        return [], None
    try:
        kept = json.loads(path.read_text())
        table = kept["tables"]["stress"]
        columns, rows = table["columns"], [list(row) for row in table["rows"]]
    except (ValueError, KeyError, TypeError) as error:
        raise SystemExit(f"resume=true: {path} is not a stress data file ({error!r})") from None
    if columns != HEADERS:
        raise SystemExit(f"resume=true: {path} has columns {columns}, expected {HEADERS}")
    merged = {"date": C.today(),
              "machine": "; ".join(dict.fromkeys([*kept["machine"].split("; "), C.machine_name()])),
              "command": "; ".join(dict.fromkeys([*kept["command"].split("; "), C.command_line("stress")]))}
    return rows, merged


def partial_path(settings: StressSettings, task: str, kind: str) -> Path | None:
    """Where a row of this data file saves its progress (None: no data file, nothing to resume
    into)."""
    data = C.data_path(settings, "stress")
    if data is None:
        return None
    return PARTIAL_DIR / data.stem / (f"{task}_{kind}_{settings.integrator or 'default'}_"
                                      f"{settings.num_envs}x{settings.steps}_seed{settings.seed}.pt")


def physics_of(task: str, s: StressSettings) -> tuple[str, str, bool]:
    """The ``(contact, integrator)`` a row of ``task`` steps with under these settings, and whether
    its root travels (`travels`)."""
    env = make_env(task, num_envs=1, seed=s.seed, **({"integrator": s.integrator} if s.integrator else {}))
    return env.contact, env.integrator, travels(env)


def main(argv=None):
    settings = parse_cli(StressSettings, argv, __doc__)
    torch.set_num_threads(settings.threads)
    warnings.filterwarnings("ignore")
    if settings.quick:
        settings = StressSettings(**{**settings.__dict__, "num_envs": 8, "steps": 20})
    rows, measured = resumed(settings)
    done = {tuple(row[:5]) for row in rows}  # task, contact, integrator, policy, size
    size = f"{settings.num_envs} x {settings.steps}"
    for task in settings.tasks:
        *physics, rooted = physics_of(task, settings)
        for kind in settings.policies:
            if (task, *physics, kind, size) in done:
                continue
            if kind == "far" and not rooted:
                print(f"# {task}: no far row (its base is fixed to the world: no track to go down)", flush=True)
                continue
            partial = partial_path(settings, task, kind)
            if partial is not None and partial.exists() and not settings.resume:
                print(f"# {task} {kind}: starting over, discarding the partial row {partial} (resume=true "
                      "continues it)", flush=True)
                partial.unlink()
            r = stress(task, kind, settings, partial)
            unconverged = "-" if r["unconverged"] is None else str(r["unconverged"])  # "-": no solve to count
            travel = "-" if r["travel"] is None else f"{r['travel']:.3g}"  # "-": a fixed base
            row = [task, r["contact"], r["integrator"], kind, size,
                   str(r["nonfinite"]), unconverged, f"{r['max_qvel']:.3g}", travel]
            rows.append(row)
            print(" | ".join(row), flush=True)
            # rewritten after every row: a long run that is stopped still leaves what it measured
            C.write_data(settings, "stress", {"stress": C.data_table(
                "Long episodes under the policies that break simulators (float32)", HEADERS, rows)}, measured=measured)
            if partial is not None:  # the row is in the data file: nothing left to resume
                partial.unlink(missing_ok=True)
    print_table(HEADERS, rows)
    return rows


if __name__ == "__main__":
    main()
