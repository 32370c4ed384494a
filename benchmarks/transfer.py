"""Transfer: a trained policy's return here and in Gymnasium's own env (for a MuJoCo task, MuJoCo
itself), on many start states.

For each checkpoint written by ``sota_scripts/train.py`` the policy plays, deterministically
(its mean action), ``episodes`` full episodes in our env as it was trained (the checkpoint's env
section: its options, e.g. the contact model) and ``episodes`` full episodes in Gymnasium's env
of the same name (``gymnasium.make``, episode ``i`` reset with seed ``seed + i``). Reported: both
mean returns with their spread, the transfer ratio (MuJoCo's return over ours) and the episode
lengths (a policy that falls over in MuJoCo ends its episodes early there).

``starts=paired`` starts Gymnasium's episode ``i`` from our episode ``i``'s start state
(``qpos``, ``qvel``; MuJoCo tasks): both envs then play the same episodes, so the ratio measures
the dynamics alone, without the draw of start states (with the default ``starts=own`` each env
draws its own), and the rows also give the median of the per-episode ratios and the largest
per-episode gap of the returns.

    OMP_NUM_THREADS=1 python benchmarks/transfer.py checkpoints=[a.pt] starts=paired episodes=32

    OMP_NUM_THREADS=1 python benchmarks/transfer.py checkpoints=[outputs/.../checkpoints/last.pt]
    OMP_NUM_THREADS=1 python benchmarks/transfer.py checkpoints=[a.pt,b.pt] episodes=32 data=transfer_race
    OMP_NUM_THREADS=1 python benchmarks/transfer.py checkpoints=[old.pt] options=[contact=smooth]

``options=[KEY=VALUE,...]`` sets env options on every checkpoint's env, e.g. ``contact=smooth``
for a checkpoint trained on the smooth contact before the option existed (its env section names
no contact model, which now means MuJoCo's). ``contacts=[smooth,mujoco]`` scores each checkpoint
here once per contact model (a row each; default: the checkpoint's own).

    OMP_NUM_THREADS=1 python benchmarks/transfer.py checkpoints=[old.pt] contacts=[smooth,mujoco]
"""
from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402
from torchrl_diffenvs.evaluation import evaluate, evaluate_in_gymnasium, start_states  # noqa: E402

HEADERS = ["env", "learner", "trained env steps", "contact here", "return here", "return in MuJoCo", "ratio",
           "episode length here", "in MuJoCo"]
PAIRED_HEADERS = [*HEADERS, "per-episode ratio (median [min, max])", "largest per-episode gap"]


@dataclass(frozen=True)
class TransferSettings(C.BenchmarkSettings):
    """checkpoints=[..] episodes=16 seed=1000003"""

    checkpoints: tuple = ()  # checkpoint files written by sota_scripts/train.py
    episodes: int = checked(16, checks.positive_int)  # full episodes in each env (start states)
    seed: int = checked(1_000_003, checks.nonnegative_int)  # eval.seed's default: the training's evaluation starts
    options: tuple = ()  # KEY=VALUE env options set on each checkpoint's env (e.g. contact=smooth)
    contacts: tuple = checked((), checks.each(checks.one_of(("mujoco", "smooth"))))  # a row per contact model here
    # own: each env draws its start states; paired: Gymnasium's episodes start from ours (MuJoCo tasks)
    starts: str = checked("own", checks.one_of(("own", "paired")))


def policy_and_config(path: str, options=()):
    """The policy of a checkpoint, with its weights, and the run's configuration (``options``:
    ``KEY=VALUE`` env options set on it)."""
    from torchrl_diffenvs.learners import LEARNERS
    from torchrl_diffenvs.training.checkpoint import load_checkpoint
    from torchrl_diffenvs.training.config import make_env_from_config

    ckpt = load_checkpoint(path)
    cfg = OmegaConf.create(ckpt["config"])
    cfg.device = "cpu"
    if options:
        cfg.env.options = OmegaConf.merge(cfg.env.get("options") or {}, OmegaConf.from_dotlist(list(options)))
    env = make_env_from_config(cfg, 1, seed=0)
    policy = LEARNERS[cfg.loss.name].policy_from_config(cfg.loss, env)
    policy.load_state_dict(ckpt["policy"])
    return policy, cfg, ckpt["progress"]["env_steps"]


def transfer(policy, cfg, episodes: int, seed: int, paired: bool = False) -> dict:
    """``policy`` on ``episodes`` start states of our env of ``cfg`` and of Gymnasium's env of the
    same name: both scores (:func:`~torchrl_diffenvs.evaluation.evaluate`,
    :func:`~torchrl_diffenvs.evaluation.evaluate_in_gymnasium`) and the ratio of the returns.
    ``paired``: Gymnasium's episodes start from our start states
    (:func:`~torchrl_diffenvs.evaluation.start_states`), and ``ours`` also holds the per-episode
    ``returns``."""
    from torchrl_diffenvs.training.config import make_env_from_config

    env = make_env_from_config(cfg, episodes, seed=seed)
    starts = start_states(env, seed) if paired else None
    ours = evaluate(env, policy, env.max_episode_steps, seed, per_env=paired)
    options = OmegaConf.to_container(cfg.env.options, resolve=True) if cfg.env.get("options") else {}
    theirs = evaluate_in_gymnasium(policy, cfg.env.name, episodes, seed, env.max_episode_steps, options=options,
                                   dtype=env.float_dtype, start_states=starts)
    return {"ours": ours, "gymnasium": theirs, "ratio": theirs["return"] / ours["return"] if ours["return"] else None,
            "contact": getattr(env, "contact", "-"), "paired": paired}


def row(cfg, env_steps: int, result: dict) -> list[str]:
    ours, theirs = result["ours"], result["gymnasium"]
    ratio = "-" if result["ratio"] is None else f"{result['ratio']:.2f}"
    out = [cfg.env.name, cfg.loss.name, f"{env_steps:,}", result["contact"],
           f"{ours['return']:.0f} [{ours['return_min']:.0f}, {ours['return_max']:.0f}]",
           f"{theirs['return']:.0f} [{theirs['return_min']:.0f}, {theirs['return_max']:.0f}]", ratio,
           f"{ours['episode_length']:.0f}", f"{theirs['episode_length']:.0f}"]
    if result.get("paired"):
        here, there = torch.tensor(ours["returns"], dtype=torch.float64), torch.tensor(theirs["returns"],
                                                                                       dtype=torch.float64)
        ratios = there[here != 0] / here[here != 0]
        spread = "-" if not ratios.numel() else \
            f"{ratios.median():.2f} [{ratios.min():.2f}, {ratios.max():.2f}]"
        out += [spread, f"{(there - here).abs().max():.0f}"]
    return out


def main(argv=None):
    s = parse_cli(TransferSettings, argv, __doc__)
    C.setup_threads(s.threads)
    warnings.filterwarnings("ignore")
    if not s.checkpoints:
        raise SystemExit("transfer: name the checkpoints to score: checkpoints=[<run dir>/checkpoints/last.pt,...]")
    rows, headers = [], PAIRED_HEADERS if s.starts == "paired" else HEADERS
    runs = [(path, [*s.options, f"contact={contact}"]) for path in s.checkpoints for contact in s.contacts] or \
        [(path, list(s.options)) for path in s.checkpoints]
    for path, options in runs:
        policy, cfg, env_steps = policy_and_config(path, options)
        with torch.no_grad():
            result = transfer(policy, cfg, 2 if s.quick else s.episodes, s.seed, paired=s.starts == "paired")
        rows.append(row(cfg, env_steps, result))
        print(" | ".join(rows[-1]), flush=True)
        starts = ", Gymnasium's from ours" if s.starts == "paired" else ", each env's own start states"
        C.write_data(s, "transfer", {"transfer": C.data_table(
            f"Policies played here and in Gymnasium's own env (deterministic, {s.episodes} full episodes each"
            f"{starts}; mean [min, max])", headers, rows)})
    C.print_table(headers, rows)
    return rows


if __name__ == "__main__":
    main()
