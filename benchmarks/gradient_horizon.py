"""How far the analytic gradient can be trusted: per task and window length, the action gradient of
a window's return against the zeroth-order (smoothed) gradient of the same window.

Gradient learners differentiate a window of ``H`` steps. Through stiff, switching contact the
exact gradient of a long window describes an infinitesimal neighbourhood that no update step
stays in (Suh et al., 2022, "Do differentiable simulators give better policy gradients?"): it
grows with ``H`` and stops pointing where the return improves. This measures where that starts.

For each task: ``starts`` envs settle for ``warmup`` steps under small random actions; from each
settled state an open-loop window of actions ``a`` ``[H, A]`` (``N(0, action_scale^2)``, clipped
to the control range by the physics) gives the window's return ``J(a) = sum_t r_t`` (the task's
reward, Gymnasium's; rewards after an env's first termination are dropped). Reported per ``H``
(medians over the start states):

* ``|grad|``: the norm of the analytic gradient ``dJ/da`` (float64);
* ``cos``: its cosine with the smoothed gradient ``grad E[J(a + sigma e)]``, estimated from
  ``samples`` antithetic Gaussian perturbations of scale ``sigma`` (the exploration scale of a
  stochastic policy); ``ceiling``: the cosine of two independent halves of that estimate, the
  most a perfect gradient would score against it at this sample size;
* ``local``: the gain ``J(a + eps g/|g|) - J(a)`` over the first-order prediction ``eps |g|``,
  ``eps = 1e-3``: 1 where the linearisation holds at all;
* ``gain``: the return's gain from a step of norm 1 along the analytic gradient, over the gain
  from the same step along the smoothed gradient (1: as good as the smoothed gradient for this
  update; below 0: the gradient points downhill at the scale of an update). The ratio is only
  read where the smoothed step gains (its gain is clamped at 1e-12): a start state where it
  loses gives a large or negative ratio, which is why the table shows the median over start states.

    OMP_NUM_THREADS=1 python benchmarks/gradient_horizon.py
    OMP_NUM_THREADS=1 python benchmarks/gradient_horizon.py tasks=[Ant-v5] horizons=[4,8,16] data=none
    OMP_NUM_THREADS=1 python benchmarks/gradient_horizon.py tasks=[Hopper-v5] modes=[exact,cfd] data=none

It writes ``docs/data/gradient_modes.json`` (``contact=smooth``: ``gradient_horizon.json``) unless
``data=`` names another file. Each row is one contact gradient mode (``contact_gradient``: ``exact``, ``cfd``, ``smooth``, ``penalty``; see
the simulator docs): the forward, hence the window's returns and the smoothed gradient, is the
same in every mode, so the modes are compared against one smoothed estimate.
"""
from __future__ import annotations

import statistics
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks, make_env  # noqa: E402
from torchrl_diffenvs.articulated.contact_gradient import GRADIENT_MODES  # noqa: E402
from torchrl_diffenvs.checks import checked, each, one_of, parse_cli  # noqa: E402

TASKS = ["Ant-v5", "HalfCheetah-v5", "Hopper-v5", "Walker2d-v5"]


@dataclass(frozen=True)
class GradientHorizonSettings(C.BenchmarkSettings):
    """tasks=[..] horizons=[2,4,8,12,16,24,32] starts=8 samples=256 sigma=0.1"""

    tasks: tuple = checked(tuple(TASKS), each(one_of(TASKS)))
    horizons: tuple = checked((2, 4, 8, 12, 16, 24, 32), each(checks.positive_int))
    starts: int = checked(8, checks.positive_int)  # settled start states (envs)
    samples: int = checked(256, checks.positive_int)  # perturbations per start state (even: antithetic pairs)
    sigma: float = checked(0.1, checks.positive)  # the perturbations' scale (per action)
    action_scale: float = checked(0.3, checks.positive)  # the window's open-loop actions: N(0, scale^2)
    warmup: int = checked(30, checks.nonnegative_int)
    seed: int = 0
    params: list[str] | None = None  # NAME=VALUE physical parameter overrides, e.g. [body_mass=...]
    modes: tuple = checked(GRADIENT_MODES, each(one_of(GRADIENT_MODES)))
    contact: str = checked("mujoco", one_of(("mujoco", "smooth")))  # the smooth option: modes=[exact] only


def window_return(env, state: dict, actions: torch.Tensor) -> torch.Tensor:
    """``[n]``: the sum of the rewards of ``actions [H, n, A]`` from ``state``, up to each env's
    first termination (pure physics: :meth:`transition`, no resets)."""
    total, alive = 0.0, torch.ones(actions.shape[1], dtype=torch.bool)
    for action in actions:
        state, reward, terminated = env.transition(state, action, env.params)
        total = total + reward * alive
        if terminated is not None:
            alive = alive & ~terminated
    return total


def physical_params(s: GradientHorizonSettings) -> dict:
    """``params=[NAME=VALUE, ...]`` as the env's ``params`` argument (checked by the env)."""
    out = {}
    for item in s.params or []:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"gradient_horizon: params expects NAME=VALUE items, got {item!r}")
        try:
            out[name] = float(value)
        except ValueError:
            raise SystemExit(f"gradient_horizon: params: {name}={value!r} is not a number") from None
    return out


def make(task: str, n: int, s: GradientHorizonSettings, mode: str = "exact"):
    return make_env(task, num_envs=n, seed=s.seed, dtype=torch.float64, params=physical_params(s),
                    contact=s.contact, contact_gradient=mode)


def settled_states(task: str, s: GradientHorizonSettings) -> dict:
    env = make(task, s.starts, s)
    generator = torch.Generator().manual_seed(s.seed)
    td = env.reset()
    with torch.no_grad():
        for _ in range(s.warmup):
            td["action"] = 0.1 * (2 * torch.rand(s.starts, env.action_dim, generator=generator, dtype=torch.float64) - 1)
            td = env.step_mdp(env.step(td))
    return {key: value.clone() for key, value in td["state"].items()}


def measure(task: str, horizon: int, s: GradientHorizonSettings) -> dict:
    """The columns of one (task, H) cell for each contact gradient mode: ``{mode: {column: list over
    the start states}}``."""
    B, M = s.starts, s.samples - s.samples % 2
    env, big = make(task, B, s), make(task, B * M, s)
    state = settled_states(task, s)
    generator = torch.Generator().manual_seed(s.seed + horizon)
    A = env.action_dim
    base = s.action_scale * torch.randn(horizon, B, A, generator=generator, dtype=torch.float64)

    half = torch.randn(B, M // 2, horizon * A, generator=generator, dtype=torch.float64)
    noise = torch.cat([half, -half], 1)  # antithetic pairs: (i, i + M/2)
    with torch.no_grad():
        start = window_return(env, state, base)
        perturbed = base.transpose(0, 1).flatten(1)[:, None] + s.sigma * noise  # [B, M, H * A]
        many = {key: value.repeat_interleave(M, 0) for key, value in state.items()}
        returns = window_return(big, many, perturbed.reshape(B * M, horizon, A).transpose(0, 1)).reshape(B, M)
        pair = (returns[:, :M // 2] - returns[:, M // 2:]) / (2 * s.sigma)  # [B, M/2]
        smoothed = (pair[..., None] * half).mean(1)
        q = M // 4
        first, second = (pair[:, :q, None] * half[:, :q]).mean(1), (pair[:, q:, None] * half[:, q:]).mean(1)

    def gain(direction, size):
        with torch.no_grad():
            step = size * direction / direction.norm(dim=1, keepdim=True)
            moved = (base.transpose(0, 1).flatten(1) + step).reshape(B, horizon, A).transpose(0, 1)
            return window_return(env, state, moved) - start

    cos = torch.nn.functional.cosine_similarity
    ceiling = cos(first, second, dim=1).tolist()
    smoothed_gain = gain(smoothed, 1.0).clamp(min=1e-12)
    out = {}
    for mode in s.modes:
        actions = base.clone().requires_grad_(True)
        grad, = torch.autograd.grad(window_return(make(task, B, s, mode), state, actions).sum(), actions)
        grad = grad.transpose(0, 1).flatten(1)  # [B, H * A]
        norm = grad.norm(dim=1)
        out[mode] = {"norm": norm.tolist(), "cos": cos(grad, smoothed, dim=1).tolist(), "ceiling": ceiling,
                     "local": (gain(grad, 1e-3) / (1e-3 * norm)).tolist(),
                     "gain": (gain(grad, 1.0) / smoothed_gain).tolist()}
    return out


def main(argv=None):
    s = parse_cli(GradientHorizonSettings, argv, __doc__)
    if s.contact == "smooth" and set(s.modes) != {"exact"}:
        raise SystemExit("gradient_horizon: contact=smooth has no constraint solve to shape: pass modes=[exact]")
    C.setup_threads(s.threads)
    warnings.filterwarnings("ignore")
    if s.quick:
        s = GradientHorizonSettings(**{**s.__dict__, "tasks": s.tasks[:1], "horizons": (2, 4), "starts": 2,
                                       "samples": 16, "warmup": 2})
    headers = ["task", "H", "contact gradient", "|grad|", "cos with smoothed gradient", "ceiling", "local",
               "gain along it"]
    rows = []
    for task in s.tasks:
        for horizon in s.horizons:
            for mode, m in measure(task, horizon, s).items():
                med = {k: statistics.median(v) for k, v in m.items()}
                row = [task, str(horizon), mode, f"{med['norm']:.3g}",
                       f"{med['cos']:.2f} [{min(m['cos']):.2f}, {max(m['cos']):.2f}]",
                       f"{med['ceiling']:.2f}", f"{med['local']:.2f}", f"{med['gain']:.2f}"]
                rows.append(row)
                print(" | ".join(row), flush=True)
            C.write_data(s, "gradient_modes" if s.contact == "mujoco" else "gradient_horizon", {"horizon": C.data_table(
                f"The window's analytic action gradient against its smoothed gradient ({s.contact} contact, sigma {s.sigma}, "
                f"{s.samples} perturbations; median over {s.starts} settled start states, float64"
                + (f"; params {', '.join(s.params)}" if s.params else "") + ")", headers, rows)})
    C.print_table(headers, rows)
    return rows


if __name__ == "__main__":
    main()
