"""Gradient health through contact: the closed-loop actor gradient at initialisation, per
integrator option, beside each option's fidelity to MuJoCo and its cost.

For each contact task and each physics option (``integrator`` x ``substeps``; the Ant also with
and without its ``cfrc_ext`` observation features), a freshly initialised actor (the learners'
default: 64-64 tanh MLP, deterministic mean) drives ``num_envs`` envs for ``warmup`` steps
without gradient (the robot lands and starts to move), then for one window of ``horizon`` steps
with the graph on; the window's loss is SHAC's actor loss without the critic term,
``-mean_envs sum_t gamma^t r_t / horizon``. Reported per option, over ``seeds``: the actor's
gradient norm (median and max), the largest contact normal force seen in the window, the
fidelity gaps of ``benchmarks/contact_fidelity.py`` (float64, against gymnasium's MuJoCo env)
and the CPU time of one env step relative to the task's default option.

With ``mode=learners`` it measures instead each gradient learner's shipped settings (the
``env=<task> loss=<learner>`` configuration of the training script, tuned files included): its
pre-clip actor gradient norm at every iteration of its first ``env_steps`` env steps (median and
max over iterations and seeds) and its skipped updates.

    OMP_NUM_THREADS=1 python benchmarks/gradient_health.py
    OMP_NUM_THREADS=1 python benchmarks/gradient_health.py tasks=[Ant-v5] seeds=5 fidelity=false
    OMP_NUM_THREADS=1 python benchmarks/gradient_health.py mode=learners learners=[shac,ahac] env_steps=20000
    OMP_NUM_THREADS=1 python benchmarks/gradient_health.py mode=contact_gradients tasks=[HalfCheetah-v5,Hopper-v5]

With ``mode=contact_gradients`` the rows are the contact gradient modes (``contact_gradient``:
``exact``, ``cfd``, ``smooth``, ``penalty``; ``modes=`` picks them) on MuJoCo's forward with the model file's integrator: the same
forward, so only the gradient columns differ (no fidelity columns).
"""
from __future__ import annotations

import statistics
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402
from _common import BenchmarkSettings, print_table  # noqa: E402

from torchrl_diffenvs import make_env  # noqa: E402
from torchrl_diffenvs.articulated.contact_gradient import GRADIENT_MODES  # noqa: E402
from torchrl_diffenvs.checks import checked, each, one_of, parse_cli  # noqa: E402

CONTACT_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5"]
# (integrator, substeps): the model file's own first, then the alternatives
OPTIONS = [("model", 1), ("euler", 1), ("implicit", 1), ("rk4", 1), ("euler", 2), ("rk4", 2)]


@dataclass(frozen=True)
class GradientHealthSettings(BenchmarkSettings):
    """tasks=[..] seeds=3 num_envs=32 horizon=16 warmup=100 fidelity=true"""

    tasks: tuple = checked(tuple(CONTACT_TASKS), each(one_of(CONTACT_TASKS)))
    seeds: int = 3
    num_envs: int = 32
    horizon: int = 16
    warmup: int = 100
    gamma: float = 0.99
    fidelity: bool = True
    mode: str = checked("options", one_of(("options", "learners", "contact_gradients")))
    learners: tuple = checked(("bptt", "shac", "ahac", "sapo"), each(one_of(("bptt", "shac", "ahac", "sapo"))))
    env_steps: int = 20_000  # mode=learners: the budget measured (the first env steps of a run)
    modes: tuple = checked(GRADIENT_MODES, each(one_of(GRADIENT_MODES)))  # mode=contact_gradients: the rows


def actor_for(env, seed: int) -> nn.Module:
    torch.manual_seed(seed)
    obs = env.observation_spec["observation"].shape[-1]
    return nn.Sequential(nn.Linear(obs, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(),
                         nn.Linear(64, env.action_dim), nn.Tanh())


def window_gradient(task: str, options: dict, seed: int, s: GradientHealthSettings) -> dict:
    """The actor's gradient norm over one window after ``warmup`` steps, and the window's largest
    contact normal force."""
    env = make_env(task, num_envs=s.num_envs, seed=seed, **options)
    actor = actor_for(env, seed)
    td = env.reset()
    with torch.no_grad():
        for _ in range(s.warmup):
            td["action"] = actor(td["observation"])
            td = env.step_mdp(env.step(td))
    state = td.exclude("next").clone()
    loss, largest = 0.0, 0.0
    start = time.process_time()
    for t in range(s.horizon):
        state["action"] = actor(state["observation"])
        out = env.step(state)
        loss = loss - (s.gamma ** t) * out["next", "reward"].reshape(-1)
        largest = max(largest, float(out["next", "state", "contact_force"].max()))  # the step's, as AHAC reads it
        state = env.step_mdp(out)
    forward_seconds = (time.process_time() - start) / s.horizon
    actor.zero_grad()
    (loss.mean() / s.horizon).backward()
    norm = torch.sqrt(sum((p.grad.double() ** 2).sum() for p in actor.parameters())).item()
    return {"norm": norm, "force": largest, "step_seconds": forward_seconds}


def option_label(integrator: str, substeps: int, env_name: str) -> str:
    model = make_env(env_name, num_envs=1).model.integrator
    name = f"{model} (file)" if integrator == "model" else integrator
    return name + (f" x{substeps}" if substeps > 1 else "")


def learner_gradients(task: str, loss: str, seed: int, env_steps: int) -> dict:
    """The pre-clip actor gradient norms and skipped updates of ``loss``'s shipped settings on
    ``task`` (the training script's configuration) over its first ``env_steps`` env steps."""
    from hydra import compose, initialize_config_dir

    from torchrl_diffenvs.learners import make_learner
    from torchrl_diffenvs.training.config import make_env_from_config

    configs = Path(__file__).resolve().parent.parent / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"env={task}", f"loss={loss}", f"seed={seed}"])
    torch.manual_seed(seed)
    env = make_env_from_config(cfg, cfg.env.num_envs, seed=seed)
    learner = make_learner(cfg.loss, env, cfg.train.total_env_steps)
    norms, steps, metrics = [], 0, {}
    while steps < env_steps:
        metrics = learner.train_iteration()
        norms.append(metrics["grad_norm_actor"])
        steps += learner.env_steps_per_iteration
    return {"norms": norms, "skipped": metrics.get("skipped_actor", 0), "steps": steps}


def learners_table(settings) -> list[list[str]]:
    rows = []
    for task in settings.tasks:
        for loss in settings.learners:
            runs = [learner_gradients(task, loss, seed, settings.env_steps) for seed in range(settings.seeds)]
            norms = [n for r in runs for n in r["norms"]]
            finite = [n for n in norms if n == n and n != float("inf")]
            row = [task, loss, f"{runs[0]['steps']:,}", f"{statistics.median(finite):.3g}" if finite else "nan",
                   f"{max(finite):.3g}" if finite else "nan", str(sum(int(r["skipped"]) for r in runs)),
                   str(len(norms) - len(finite))]
            rows.append(row)
            print(" | ".join(row), flush=True)
            headers = ["task", "learner", "env steps per seed", "pre-clip actor grad norm (median)", "max",
                       "skipped updates (all seeds)", "non-finite norms"]
            C.write_data(settings, "gradient_health_learners", source="gradient_health", tables={"learners": C.data_table(
                f"Shipped settings: the actor's pre-clip gradient norm over the first {settings.env_steps:,} env steps "
                f"({settings.seeds} seeds, every iteration)", headers, rows)})
    return rows


def contact_gradients_table(settings) -> list[list[str]]:
    """The closed-loop actor gradient of each contact gradient mode (same forward, same windows)."""
    headers = ["task", "contact gradient", "actor grad norm (median)", "max", "largest normal force (N)",
               "step cost"]
    rows = []
    for task in settings.tasks:
        # seed by seed, every mode in turn: the step costs are compared under the same load
        runs = {mode: [] for mode in settings.modes}
        for seed in range(settings.seeds):
            for mode in settings.modes:
                runs[mode].append(window_gradient(task, {"contact_gradient": mode}, seed, settings))
        base_cost = statistics.median(r["step_seconds"] for r in runs[settings.modes[0]])
        for mode in settings.modes:
            norms = [r["norm"] for r in runs[mode]]
            cost = statistics.median(r["step_seconds"] for r in runs[mode])
            rows.append([task, mode, f"{statistics.median(norms):.3g}", f"{max(norms):.3g}",
                         f"{max(r['force'] for r in runs[mode]):.3g}", f"{cost / base_cost:.2f}"])
            print(" | ".join(rows[-1]), flush=True)
            C.write_data(settings, "gradient_health_modes", source="gradient_health", tables={"modes": C.data_table(
                f"Closed-loop actor gradient at initialisation on MuJoCo's forward, per contact gradient mode "
                f"({settings.seeds} seeds, {settings.num_envs} envs, {settings.horizon}-step window after "
                f"{settings.warmup} steps)", headers, rows)})
    print_table(headers, rows)
    return rows


def main(argv=None):
    settings = parse_cli(GradientHealthSettings, argv, __doc__)
    torch.set_num_threads(settings.threads)
    warnings.filterwarnings("ignore")
    if settings.mode == "learners":
        if settings.quick:
            settings = GradientHealthSettings(**{**settings.__dict__, "seeds": 1, "env_steps": 1, "learners": ("shac",),
                                                 "tasks": settings.tasks[:1]})
        return learners_table(settings)
    if settings.quick:
        settings = GradientHealthSettings(**{**settings.__dict__, "seeds": 1, "num_envs": 4, "horizon": 4,
                                             "warmup": 5, "fidelity": False, "tasks": settings.tasks[:1]})
    if settings.mode == "contact_gradients":
        return contact_gradients_table(settings)
    rows = []
    for task in settings.tasks:
        variants = [({"integrator": i, "substeps": k}, option_label(i, k, task)) for i, k in OPTIONS]
        model = make_env(task, num_envs=1).model.integrator
        # "model" already covers the file's own integrator at one substep
        variants = [v for v in variants if (v[0]["integrator"], v[0]["substeps"]) != (model, 1)]
        if task == "Ant-v5":
            variants += [({**o, "include_cfrc_ext_in_observation": False}, label + ", no cfrc_ext")
                         for o, label in list(variants)]
        base_cost = None
        for options, label in variants:
            runs = [window_gradient(task, options, seed, settings) for seed in range(settings.seeds)]
            norms = [r["norm"] for r in runs]
            cost = statistics.median(r["step_seconds"] for r in runs)
            base_cost = base_cost or cost
            row = [task, label, f"{statistics.median(norms):.3g}", f"{max(norms):.3g}",
                   f"{max(r['force'] for r in runs):.3g}", f"{cost / base_cost:.2f}"]
            if settings.fidelity:
                from contact_fidelity import fidelity

                physics = {k: v for k, v in options.items() if k in ("integrator", "substeps")}
                gaps = fidelity(task, **physics)
                row += [f"{gaps['rest_z_ours'] - gaps['rest_z_mujoco']:+.3f}", f"{gaps['x_gap']:.3f}",
                        f"{gaps['joint_rms_gap']:.3f}"]
            rows.append(row)
            print(" | ".join(row), flush=True)
    headers = ["task", "physics", "actor grad norm (median)", "max", "largest normal force (N)", "step cost"]
    if settings.fidelity:
        headers += ["rest height - MuJoCo's (m)", "x gap after 1 s (m)", "joint RMS gap (rad)"]
    print_table(headers, rows)
    C.write_data(settings, "gradient_health", {"gradient_health": C.data_table(
        f"Closed-loop actor gradient at initialisation ({settings.seeds} seeds, {settings.num_envs} envs, "
        f"{settings.horizon}-step window after {settings.warmup} steps), per physics option", headers, rows)})
    return rows


if __name__ == "__main__":
    main()
