"""Run-through demo (Ivy Gym's run_through): random actions in any env, written to a GIF.

    python sota_scripts/run_through.py env=swimmer
    python sota_scripts/run_through.py env=reacher steps=100 num_envs=4 out=outputs/reacher.gif seed=1

Arguments (key=value, all optional): env (default cartpole), steps (250), num_envs (1; several
envs are drawn as a grid of at most ``show`` envs, default 16), out (default
outputs/run_through/<env>.gif), seed (0), fps (25), size (pixels of one env's picture; 256 for
one env, 128 per cell in a grid). Actions are uniform in the action spec; episodes that end
(truncation after max_episode_steps, or termination) are reset automatically, as in a rollout.
"""
from __future__ import annotations

import sys
import time

import torch

from torchrl_diffenvs import list_envs, make_env
from torchrl_diffenvs.rendering import save_gif

DEFAULTS = {"env": "cartpole", "steps": 250, "num_envs": 1, "out": None, "seed": 0, "fps": 25, "size": None, "show": 16}
INTS = {"steps", "num_envs", "seed", "fps", "size", "show"}


def parse_args(argv: list[str]) -> dict:
    """``key=value`` pairs -> options; raises ``SystemExit(2)`` with a message on bad input."""
    options = dict(DEFAULTS)
    for arg in argv:
        key, sep, value = arg.partition("=")
        if not sep or key not in DEFAULTS:
            raise SystemExit(f"run_through: expected key=value with key in {sorted(DEFAULTS)}, got {arg!r}")
        if key in INTS:
            try:
                value = int(value)
            except ValueError:
                raise SystemExit(f"run_through: {key} must be an integer, got {value!r}") from None
            if value < (0 if key == "seed" else 1):
                raise SystemExit(f"run_through: {key} must be {'>= 0' if key == 'seed' else '>= 1'}, got {value}")
        options[key] = value
    if options["env"] not in list_envs():
        raise SystemExit(f"run_through: unknown env {options['env']!r}; valid names: {', '.join(list_envs())}")
    return options


def run_through(env: str, steps: int, num_envs: int, out: str | None, seed: int, fps: int, size: int | None, show: int):
    """Runs ``steps`` random steps and writes one frame per step; returns (gif path, frames, mean reward)."""
    torch.manual_seed(seed)
    environment = make_env(env, num_envs=num_envs, seed=seed)
    shown = list(range(min(num_envs, show)))
    env_index = 0 if num_envs == 1 else shown
    size = size or (256 if num_envs == 1 else 128)
    spec = environment.action_spec
    low, high = spec.space.low, spec.space.high
    generator = torch.Generator().manual_seed(seed)

    frames, rewards = [], []
    with torch.no_grad():
        td = environment.reset()
        for _ in range(steps):
            u = torch.rand(spec.shape, generator=generator, dtype=environment.float_dtype)
            td["action"] = low + (high - low) * u
            td, td_next = environment.step_and_maybe_reset(td)
            frames.append(environment.render(td["next"], env_index=env_index, size=size))  # before any reset
            rewards.append(td["next", "reward"].mean().item())
            td = td_next
    path = save_gif(frames, out or f"outputs/run_through/{env}.gif", fps=fps)
    return path, frames, sum(rewards) / len(rewards)


def main(argv: list[str] | None = None) -> int:
    options = parse_args(sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    path, frames, mean_reward = run_through(**options)
    seconds = time.perf_counter() - start
    height, width = frames[0].shape[:2]
    print(
        f"{options['env']}: {len(frames)} random steps x {options['num_envs']} env(s), mean reward "
        f"{mean_reward:.3f}; wrote {path} ({len(frames)} frames, {width}x{height}) in {seconds:.1f} s"
    )
    print("End of Run Through Demo!")
    return 0


if __name__ == "__main__":
    sys.exit(main())
