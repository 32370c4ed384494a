"""The MuJoCo-model tasks against gymnasium's own MuJoCo envs: contact fidelity.

Fidelity (float64): the torso height after 2 s at zero action (a dropped robot coming to rest),
the gap after 1 s of the same random actions from the same start (no reset noise), and the
return of a still robot: the task's own episode (reset noise, termination, at most 1000 steps) at
zero action, mean over 5 starts: what a learner that only learned to keep still scores.
Speed is measured by ``benchmarks/mujoco_throughput.py``. Needs ``pip install "torchrl_diffenvs[mujoco]"``.

    OMP_NUM_THREADS=1 python benchmarks/contact_fidelity.py
"""
from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import make_env  # noqa: E402
from torchrl_diffenvs.checks import Settings, checked, each, one_of, parse_cli  # noqa: E402

CONTACT_TASKS = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "HumanoidStandup-v5",
                 "Pusher-v5"]
# where each task keeps its torso's forward position, height and orientation in qpos, and its first joint angle:
# the planar runners a hinge angle; the Ant and the humanoids a free joint's quaternion; the Pusher
# (no gravity, no torso) its object's x slide and its arm's joints
PLANAR = {"x": 0, "z": 1, "angle": 2, "joints": 3}
FREE = {"x": 0, "z": 2, "quaternion": 3, "joints": 7}
LAYOUT = {"Ant-v5": FREE, "Humanoid-v5": FREE, "HumanoidStandup-v5": FREE, "Pusher-v5": {"x": 8, "joints": 0, "joints_end": 7}}
NO_HEALTH = ("HalfCheetah-v5", "HumanoidStandup-v5", "Pusher-v5")  # no terminate_when_unhealthy option


def _tilt_gap(task, theirs, ours):
    """Per step, the torso orientation gap (rad): a hinge angle difference, or a quaternion's rotation angle."""
    layout = LAYOUT.get(task, PLANAR)
    if "angle" not in layout and "quaternion" not in layout:
        return np.zeros(len(theirs))
    if "angle" in layout:
        return np.abs(theirs[:, layout["angle"]] - ours[:, layout["angle"]])
    q = layout["quaternion"]
    a, b = theirs[:, q:q + 4], ours[:, q:q + 4]
    cos_half = np.abs((a * b).sum(-1)) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return 2 * np.arccos(np.clip(cos_half, -1.0, 1.0))


def _gym(task):
    import gymnasium as gym

    kwargs = {} if task in NO_HEALTH else {"terminate_when_unhealthy": False}
    if task != "Pusher-v5":  # (its start noise is not an option)
        kwargs["reset_noise_scale"] = 0.0
    env = gym.make(task, **kwargs)
    env.reset(seed=0)
    return env


def _ours(task, **options):
    env = make_env(task, num_envs=1, dtype=torch.float64, seed=0, max_episode_steps=None, **options,
                   params={**({} if task == "Pusher-v5" else {"reset_noise_scale": 0.0}),
                           **({} if task in NO_HEALTH else {"terminate_when_unhealthy": 0.0})})
    return env, env.reset()


def fidelity(task, seconds_rest=2.0, seconds_open_loop=1.0, **options):
    """Rest height and open-loop gaps of ``task`` built with ``options`` (e.g. ``integrator``, ``substeps``)."""
    genv, (env, td) = _gym(task), _ours(task, **options)
    _same_start(task, genv, env, td)
    for _ in range(int(round(seconds_rest / env.dt))):
        genv.step(np.zeros(env.action_dim))
        td["action"] = torch.zeros(1, env.action_dim, dtype=torch.float64)
        td = env.step(td)["next"].clone()
    layout = LAYOUT.get(task, PLANAR)
    rest = (genv.unwrapped.data.qpos[layout["z"]], td["state", "qpos"][0, layout["z"]].item()) if "z" in layout \
        else (float("nan"), float("nan"))
    genv, (env, td) = _gym(task), _ours(task, **options)
    td = _same_start(task, genv, env, td)
    rng, theirs, ours = np.random.default_rng(0), [], []
    for _ in range(int(round(seconds_open_loop / env.dt))):
        action = rng.uniform(env.action_low, env.action_high, env.action_dim)
        genv.step(action)
        td["action"] = torch.tensor(action[None])
        td = env.step(td)["next"].clone()
        theirs.append(genv.unwrapped.data.qpos.copy())
        ours.append(td["state", "qpos"][0].numpy().copy())
    theirs, ours = np.array(theirs), np.array(ours)
    return {
        "rest_z_mujoco": rest[0], "rest_z_ours": rest[1],
        "x_gap": abs(theirs[-1, layout["x"]] - ours[-1, layout["x"]]),
        "z_gap_max": np.abs(theirs[:, layout["z"]] - ours[:, layout["z"]]).max() if "z" in layout else 0.0,
        "angle_gap_max": _tilt_gap(task, theirs, ours).max(),
        "joint_rms_gap": float(np.sqrt(((theirs - ours)[:, layout["joints"]:layout.get("joints_end")] ** 2).mean())),
    }


def still_return(task, episodes: int = 5, steps: int = 1000) -> tuple[float, float]:
    """Mean return of ``episodes`` zero-action episodes of the task as shipped (reset noise and
    termination on): gymnasium's (seeds 0..episodes-1) and ours (``episodes`` envs, float64)."""
    import gymnasium as gym

    genv, theirs = gym.make(task), []
    for seed in range(episodes):
        genv.reset(seed=seed)
        total = 0.0
        for _ in range(steps):
            _, reward, terminated, truncated, _ = genv.step(np.zeros(genv.action_space.shape))
            total += reward
            if terminated or truncated:
                break
        theirs.append(total)
    env = make_env(task, num_envs=episodes, dtype=torch.float64, seed=0)
    td, total = env.reset(), torch.zeros(episodes, dtype=torch.float64)
    running = torch.ones(episodes, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(steps):
            td["action"] = torch.zeros(episodes, env.action_dim, dtype=torch.float64)
            out = env.step(td)
            total += torch.where(running, out["next", "reward"].reshape(-1), 0.0)
            running &= ~out["next", "done"].reshape(-1)
            if not running.any():
                break
            td = env.step_mdp(out)
    return float(np.mean(theirs)), float(total.mean())


def _same_start(task, genv, env, td):
    """The Pusher's start is random in both (its object's place): ours starts from gymnasium's."""
    if task != "Pusher-v5":
        return td
    qpos = torch.tensor(genv.unwrapped.data.qpos[None].copy())
    td["state", "qpos"], td["state", "qvel"] = qpos, torch.tensor(genv.unwrapped.data.qvel[None].copy())
    td["state", "body_points"] = env.body_points(qpos)
    return env.reset(td, set_state=True)


@dataclass(frozen=True)
class ContactFidelitySettings(Settings):
    """tasks=[HalfCheetah-v5,Ant-v5]: which contact tasks (all by default)."""

    tasks: tuple = checked(tuple(CONTACT_TASKS), each(one_of(CONTACT_TASKS)))
    # the documentation's data file: docs/data/<data>.json (default contact_fidelity); none: write none
    data: str | None = None


def main(argv=None):
    settings = parse_cli(ContactFidelitySettings, argv, __doc__)
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    rows = []
    for task in settings.tasks:
        result = fidelity(task)
        still = "{:.4g} / {:.4g}".format(*still_return(task))
        print(task, {k: round(float(v), 4) for k, v in result.items()}, "still return", still, flush=True)
        if task == "Pusher-v5":  # no gravity: nothing comes to rest
            rows.append([task, "(no gravity)", f"object x {result['x_gap']:.3g} m, "
                         f"joints {result['joint_rms_gap']:.3g} rad rms", still])
            continue
        rows.append([task, f"{result['rest_z_mujoco']:.3f} m / {result['rest_z_ours']:.3f} m",
                     f"root x {result['x_gap']:.3g} m, height up to {result['z_gap_max']:.3g} m, "
                     f"angle up to {result['angle_gap_max']:.3g} rad, joints {result['joint_rms_gap']:.3g} rad rms",
                     still])
    C.write_data(settings, "contact_fidelity", {"fidelity": C.data_table(
        "Smooth contact against MuJoCo (same model, float64)",
        ["task", "rest height of the torso after 2 s, zero action (MuJoCo / ours)",
         "gap after 1 s of the same random actions",
         "return of a still robot: zero action, the task's episode (MuJoCo / ours)"], rows)})


if __name__ == "__main__":
    main()
