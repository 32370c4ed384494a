"""System identification through the differentiable model: recover the masses and joint damping
that were changed in a MuJoCo model file, from trajectories of gymnasium's own MuJoCo env.

1. The model: gymnasium's ``inverted_double_pendulum.xml`` with the three bodies' masses and the
   three joints' damping edited in the XML (``mass`` on each body's geom, ``damping`` on each
   joint), written to ``out_dir/edited_model.xml``. Our code is not touched.
2. The data: gymnasium's ``InvertedDoublePendulum-v5`` built from that file (``xml_file=...``,
   MuJoCo does the simulation) is started from ``trajectories`` random states and driven by random
   actions for ``steps`` steps; every ``qpos``/``qvel`` is recorded (plus ``noise``, if asked).
3. The fit: our ``InvertedDoublePendulum-v5`` (default model, float64) is started from the
   recorded states at the beginning of every ``segment``-step piece and replays the recorded
   actions; the squared error between its predicted and the recorded ``qpos``/``qvel`` (scaled per
   coordinate) is minimised over the log-masses and log-damping by L-BFGS, the gradients taken
   through the whole segment by autograd. Short segments keep the fit near-convex: predicted
   over 0.5 s, this chaotic system's error surface has local minima far from the truth. A geom's inertia scales with its mass (MuJoCo's
   inertia-from-geom at fixed shape), so the inertia follows the fitted mass.

This task has no contact, so our dynamics equal MuJoCo's and the true values are recoverable to
the precision of the optimiser (the contact tasks' smooth contact would bias a fit like this one).

Usage::

    python sota_scripts/system_identification.py out_dir=outputs/sysid
    python sota_scripts/system_identification.py true_mass=8,3,5 true_damping=0.6,0.25,0.1

Writes ``summary.json`` (true, initial and recovered values, the loss per iteration) and
``loss.png`` to ``out_dir``. Needs ``gymnasium[mujoco]`` (the ``test`` extra).
"""
from __future__ import annotations

import json
import math
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from demo_utils import plot_curve, start_demo
from torchrl_diffenvs import checks, make_env
from torchrl_diffenvs.articulated import gymnasium_asset
from torchrl_diffenvs.checks import Settings, checked

TASK = "InvertedDoublePendulum-v5"
BODIES = ("cart", "pole", "pole2")  # one geom each: its mass is the body's
JOINTS = ("slider", "hinge", "hinge2")
SEARCH_RANGE = 4.0  # the fit searches e^-4 to e^4 times the unedited file's values

def three_positive_numbers(text) -> str | None:
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        return "expected 3 comma-separated numbers"
    ok = len(values) == 3 and all(v > 0 and math.isfinite(v) for v in values)
    return None if ok else "expected 3 positive comma-separated numbers"


@dataclass(frozen=True)
class IdentificationSettings(Settings):
    """The demo's arguments (``key=value``)."""

    true_mass: str = checked("8.0,3.0,5.0", three_positive_numbers)  # kg: cart, pole, pole2 (the file's: 10.47, 4.19, 4.19)
    true_damping: str = checked("0.6,0.25,0.1", three_positive_numbers)  # slider, hinge, hinge2 (the file's: 0.05 each)
    trajectories: int = checked(8, checks.positive_int)
    steps: int = checked(40, checks.positive_int)  # env steps per recorded trajectory (0.05 s each)
    segment: int = checked(2, checks.positive_int)  # env steps predicted from each recorded state (short: near-convex)
    action_scale: float = checked(0.3, checks.positive)  # random actions U(-scale, scale) (the motor's gear is 500 N)
    noise: float = checked(0.0, checks.nonnegative)  # std of Gaussian noise added to the recorded qpos/qvel
    iterations: int = checked(10, checks.positive_int)  # L-BFGS iterations (each up to 10 function evaluations)
    seed: int = checked(0, checks.nonnegative_int)
    out_dir: str = "outputs/system_identification"
    progress: bool = checked(True, checks.boolean)

    @classmethod
    def relation_problems(cls, values, where: str = "") -> list[str]:
        if values["steps"] < values["segment"]:
            return [f"need steps >= segment, got steps={values['steps']}, segment={values['segment']}"]
        return []


def parse_values(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]  # checked by three_positive_numbers


def edit_model(masses: list[float], damping: list[float], path) -> None:
    """Writes gymnasium's model file with the given geom masses and joint damping."""
    tree = ET.parse(gymnasium_asset("inverted_double_pendulum.xml"))
    for name, mass in zip(BODIES, masses):
        tree.find(f".//body[@name='{name}']/geom").set("mass", repr(mass))
    for name, value in zip(JOINTS, damping):
        tree.find(f".//joint[@name='{name}']").set("damping", repr(value))
    tree.write(path)


def record(xml_file, trajectories: int, steps: int, action_scale: float, seed: int) -> dict[str, np.ndarray]:
    """qpos/qvel ``[K, steps + 1, 3]`` and actions ``[K, steps, 1]`` from gymnasium's MuJoCo env."""
    try:
        import gymnasium as gym

        env = gym.make(TASK, xml_file=str(xml_file)).unwrapped
    except (ImportError, gym.error.DependencyNotInstalled) as err:
        raise SystemExit(f"recording needs gymnasium's MuJoCo envs: pip install 'gymnasium[mujoco]' ({err})") from None
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    qpos = np.zeros((trajectories, steps + 1, env.model.nq))
    qvel = np.zeros((trajectories, steps + 1, env.model.nv))
    actions = rng.uniform(-action_scale, action_scale, (trajectories, steps, 1))
    for k in range(trajectories):
        # anywhere on the rail, poles at any angle: the data must excite every mass and damper
        env.set_state(rng.uniform([-0.5, -math.pi, -math.pi], [0.5, math.pi, math.pi]), rng.normal(0.0, 1.0, 3))
        qpos[k, 0], qvel[k, 0] = env.data.qpos, env.data.qvel
        for t in range(steps):
            env.step(actions[k, t])  # the unwrapped env never stops: termination is only reported
            qpos[k, t + 1], qvel[k, t + 1] = env.data.qpos, env.data.qvel
    env.close()
    return {"qpos": qpos, "qvel": qvel, "actions": actions}


class SegmentModel:
    """Our env predicting every ``segment``-step piece of the recordings at once (one env per piece)."""

    def __init__(self, data: dict[str, np.ndarray], segment: int):
        k, steps = data["actions"].shape[:2]
        starts = range(0, steps - segment + 1, segment)
        as_tensor = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
        qpos, qvel, actions = (as_tensor(data[key]) for key in ("qpos", "qvel", "actions"))
        self.start_qpos = torch.cat([qpos[:, s] for s in starts])  # [pieces, nq]
        self.start_qvel = torch.cat([qvel[:, s] for s in starts])
        self.actions = torch.cat([actions[:, s:s + segment] for s in starts])  # [pieces, segment, 1]
        self.target = torch.cat([torch.cat([qpos[:, s + 1:s + segment + 1], qvel[:, s + 1:s + segment + 1]], -1)
                                 for s in starts])  # [pieces, segment, nq + nv]
        self.scale = self.target.flatten(0, 1).std(0)  # every coordinate counts alike
        self.env = make_env(TASK, num_envs=len(self.start_qpos), dtype=torch.float64)
        self.segment = segment
        params = self.env.params
        self.body = torch.tensor([self.env.model.body_index(b) for b in BODIES])
        self.default_mass = params["body_mass"][0, self.body].clone()
        self.default_damping = params["damping"][0].clone()

    def predict(self, mass: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
        """``[pieces, segment, nq + nv]`` predicted by our env with these masses and damping."""
        td = self.env.reset()
        td["state", "qpos"], td["state", "qvel"] = self.start_qpos, self.start_qvel
        params = td["params"]
        ratio = torch.ones_like(params["body_mass"][0]).index_put((self.body,), mass / self.default_mass)
        # the geometry is known, the mass is not: the inertia scales with the mass
        params["body_mass"] = params["body_mass"] * ratio
        params["body_inertia"] = params["body_inertia"] * ratio[:, None, None]
        params["damping"] = damping.expand_as(params["damping"])
        predicted = []
        for t in range(self.segment):
            td["action"] = self.actions[:, t]
            td = self.env.step(td)["next"]
            predicted.append(torch.cat([td["state", "qpos"], td["state", "qvel"]], -1))
        return torch.stack(predicted, 1)

    def loss(self, mass: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
        return (((self.predict(mass, damping) - self.target) / self.scale) ** 2).mean()


def main(argv: list[str] | None = None) -> dict:
    args, out_dir = start_demo(IdentificationSettings, argv, usage=__doc__)
    true_mass, true_damping = parse_values(args.true_mass), parse_values(args.true_damping)

    edited = out_dir / "edited_model.xml"
    edit_model(true_mass, true_damping, edited)
    data = record(edited, args.trajectories, args.steps, args.action_scale, args.seed)
    if args.noise > 0:
        rng = np.random.default_rng(args.seed + 1)
        for key in ("qpos", "qvel"):
            data[key] = data[key] + rng.normal(0.0, args.noise, data[key].shape)
    model = SegmentModel(data, args.segment)

    # the unknowns: log-ratios to the unedited file's values, kept smooth and bounded (e^-4 to e^4
    # times the file's value) so that no line-search step makes a body massless
    z_mass = torch.zeros_like(model.default_mass, requires_grad=True)
    z_damping = torch.zeros_like(model.default_damping, requires_grad=True)

    def values():
        bounded = lambda z: torch.exp(SEARCH_RANGE * torch.tanh(z / SEARCH_RANGE))  # noqa: E731
        return model.default_mass * bounded(z_mass), model.default_damping * bounded(z_damping)

    # the loss falls by orders of magnitude: LBFGS's default tolerances (1e-7 on the gradient) stop it early
    optimizer = torch.optim.LBFGS([z_mass, z_damping], lr=1.0, max_iter=10, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-14, tolerance_change=1e-20)

    def closure():
        optimizer.zero_grad()
        loss = model.loss(*values())
        loss.backward()
        return loss

    with torch.no_grad():
        losses = [model.loss(*values()).item()]
    start = time.perf_counter()
    bar = tqdm(range(args.iterations), desc="system identification", disable=not args.progress)
    for _ in bar:
        optimizer.step(closure)
        with torch.no_grad():
            losses.append(model.loss(*values()).item())
        bar.set_postfix(loss=f"{losses[-1]:.2e}")
    seconds = time.perf_counter() - start

    recovered_mass, recovered_damping = (v.tolist() for v in values())
    rows = [(f"mass {b}", t, i, r) for b, t, i, r in zip(BODIES, true_mass, model.default_mass.tolist(), recovered_mass)]
    rows += [(f"damping {j}", t, i, r) for j, t, i, r in zip(JOINTS, true_damping, model.default_damping.tolist(),
                                                              recovered_damping)]
    summary = {
        "task": TASK, "pieces": len(model.start_qpos), "segment": args.segment, "noise": args.noise,
        "iterations": args.iterations,
        "seconds": round(seconds, 2), "loss": losses,
        "parameters": [{"name": n, "true": t, "initial": i, "recovered": r, "relative_error": abs(r - t) / t}
                       for n, t, i, r in rows],
    }
    plot_curve(out_dir / "loss.png", {"scaled squared error": (list(range(len(losses))), losses)},
               "L-BFGS iteration", "loss", f"system identification: {TASK}")
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{'parameter':<16} {'true':>9} {'initial':>9} {'recovered':>10} {'rel. error':>10}")
    for p in summary["parameters"]:
        print(f"{p['name']:<16} {p['true']:>9.4f} {p['initial']:>9.4f} {p['recovered']:>10.4f} {p['relative_error']:>10.1e}")
    print(f"{len(model.start_qpos)} pieces of {args.segment} steps, {args.iterations} L-BFGS iterations, "
          f"{seconds:.1f} s")
    return summary


if __name__ == "__main__":
    main()
