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

import dataclasses
import sys
import time
from dataclasses import dataclass

import torch

from torchrl_diffenvs import checks, list_envs, make_env
from torchrl_diffenvs.checks import Settings, checked, parse_cli
from torchrl_diffenvs.rendering import save_gif

def optional_positive_int(value) -> str | None:
    return None if value is None else checks.positive_int(value)


@dataclass(frozen=True)
class RunThroughSettings(Settings):
    """The demo's arguments (``key=value``)."""

    env: str = checked("cartpole", checks.one_of(list_envs()))
    steps: int = checked(250, checks.positive_int)
    num_envs: int = checked(1, checks.positive_int)
    out: str | None = None  # default outputs/run_through/<env>.gif
    seed: int = checked(0, checks.nonnegative_int)
    fps: int = checked(25, checks.positive_int)
    size: int | None = checked(None, optional_positive_int)  # pixels of one env's picture
    show: int = checked(16, checks.positive_int)  # envs drawn in the grid, at most


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
    options = dataclasses.asdict(parse_cli(RunThroughSettings, argv, usage=__doc__))
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
