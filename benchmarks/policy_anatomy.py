"""What saved policies do on a locomotion task: the parts of their reward and why their episodes end.

For each checkpoint (``checkpoints=[LABEL=PATH, ...]``, e.g. a run's
``checkpoints/ckpt_000000040960.pt``), its deterministic policy plays one episode on each of
``num_envs`` fresh envs of the checkpoint's own task and options, and the table reports, over
the steps before each env's first episode end:

* ``ctrl cost / step``: ``ctrl_cost_weight x |a|^2`` per step, and the fraction of saturated
  actions (``|a| > 0.95``);
* ``vx``: the torso's forward velocity (``qvel[0]``, m/s);
* ``reward / step`` and ``return`` (the checkpoint's reward: Gymnasium's unless its run changed
  the reward's parameters);
* ``ended``: the fraction of envs whose episode terminated, and why: the torso's height above
  ``healthy_z_high`` (a jump), below ``healthy_z_low`` (a fall), or another health bound.

    python benchmarks/policy_anatomy.py checkpoints=[s0=outputs/.../checkpoints/last.pt] data=none
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C  # noqa: E402

from torchrl_diffenvs import checks  # noqa: E402
from torchrl_diffenvs.checks import checked, parse_cli  # noqa: E402


@dataclass(frozen=True)
class PolicyAnatomySettings(C.BenchmarkSettings):
    checkpoints: list[str] | None = None  # LABEL=PATH of each checkpoint (required)
    num_envs: int = checked(16, checks.positive_int)  # episodes per checkpoint (one per env)
    seed: int = 123  # of the envs' start states
    steps: int | None = None  # episode length (default: the task's time limit)


def anatomy(path: str, args) -> dict:
    import torch
    from omegaconf import OmegaConf
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from torchrl_diffenvs.evaluation import first_episode_ends
    from torchrl_diffenvs.learners import LEARNERS
    from torchrl_diffenvs.training.checkpoint import load_checkpoint
    from torchrl_diffenvs.training.config import make_env_from_config

    ckpt = load_checkpoint(path)
    cfg = OmegaConf.create(ckpt["config"])
    env = make_env_from_config(cfg, args.num_envs, seed=args.seed)
    policy = LEARNERS[cfg.loss.name].policy_from_config(cfg.loss, env)
    policy.load_state_dict(ckpt["policy"])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(args.steps or env.max_episode_steps, policy, break_when_any_done=False)
    length, ended = first_episode_ends(td)
    lived = (torch.arange(td.shape[1], device=length.device)[None] < length[:, None]).to(td["action"].dtype)

    def per_step(values):  # [N, T] -> mean over the steps lived
        return float((values * lived).sum() / lived.sum())

    params = env.params
    action = td["action"]
    qpos, qvel = td["next", "state", "qpos"], td["next", "state", "qvel"]
    reward = td["next", "reward"][..., 0]
    last = (length - 1).clamp(min=0)
    height = qpos[torch.arange(len(length)), last, getattr(env, "height_coordinate", 1)]
    causes = {"jump": 0, "fall": 0, "other": 0}
    if "healthy_z_high" in params.keys():
        high, low = float(params["healthy_z_high"].flatten()[0]), float(params["healthy_z_low"].flatten()[0])
        for h, end in zip(height.tolist(), ended.tolist()):
            if end:
                causes["jump" if h > high else "fall" if h < low else "other"] += 1
    else:
        causes["other"] = int(ended.sum())
    return {
        "env": cfg.env.name, "loss": cfg.loss.name, "env_steps": ckpt.get("progress", {}).get("env_steps"),
        "ctrl_per_step": per_step(params["ctrl_cost_weight"].flatten()[0] * (action ** 2).sum(-1)),
        "saturated": per_step((action.abs() > 0.95).to(action.dtype).mean(-1)),
        "vx": per_step(qvel[..., 0]), "reward_per_step": per_step(reward),
        "return": float((reward * lived).sum(-1).mean()), "episode_length": float(length.float().mean()),
        "ended": float(ended.float().mean()), "causes": causes,
    }


def main(argv=None) -> list[dict]:
    args = parse_cli(PolicyAnatomySettings, argv, __doc__)
    C.setup_threads(args.threads)
    if not args.checkpoints or any("=" not in item for item in args.checkpoints):
        raise SystemExit(f"checkpoints={args.checkpoints}: expected [LABEL=PATH, ...], the checkpoint files to look at")
    rows = []
    for item in args.checkpoints:
        label, path = item.split("=", 1)
        if not Path(path).is_file():
            raise SystemExit(f"checkpoints: {label}={path}: no such file")
        rows.append({"label": label, "path": path, **anatomy(path, args)})
        print(rows[-1], flush=True)

    def cause_cell(r):
        found = [f"{count} {cause}" for cause, count in r["causes"].items() if count]
        return f"{r['ended']:.0%}" + (f" ({', '.join(found)})" if found else "")

    table = C.data_table(
        "Deterministic policies of saved checkpoints: per-step parts of the reward, over the steps before each "
        "env's first episode end, and why episodes ended",
        ["checkpoint", "env steps", "ctrl cost / step", "actions saturated (> 0.95)", "vx (m/s)", "reward / step", "return", "ended"],
        [[r["label"], f"{r['env_steps']:,}" if r["env_steps"] is not None else "-", f"{r['ctrl_per_step']:.2f}",
          f"{r['saturated']:.1%}", f"{r['vx']:.3f}", f"{r['reward_per_step']:.2f}", f"{r['return']:.0f}",
          cause_cell(r)] for r in rows])
    C.print_table(table["columns"], table["rows"])
    C.write_data(args, "policy_anatomy", {"anatomy": table})
    C.write_json("policy_anatomy", {"benchmark": "policy_anatomy", "rows": rows}, args.out)
    return rows


if __name__ == "__main__":
    main()
