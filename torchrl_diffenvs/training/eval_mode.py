"""``mode=eval``: score a saved policy on fresh envs and write its video (rl_games' player), and the
pieces the training loop shares with it (videos, JSON reports, compiled chunk lengths)."""
from __future__ import annotations

import json
import logging
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ..envs.gymnasium_backend import GymnasiumBackedEnv
from ..evaluation import episode_returns, evaluate_in_gymnasium, evaluate_random, first_episode_ends, record_video
from ..learners import LEARNERS
from .checkpoint import load_checkpoint
from .config import ConfigError, check_gymnasium_eval, env_backend, make_env_from_config
from .settings import EvalSettings, RunSettings

__all__ = ["chunk_length", "evaluate_checkpoint", "exploration_of", "gymnasium_scores", "json_report", "write_video"]

log = logging.getLogger("train")


def chunk_length(steps: int, longest: int = 8) -> int:
    """The longest chunk of at most ``longest`` steps that divides ``steps`` (no eager remainder)."""
    return max(k for k in range(1, longest + 1) if steps % k == 0)


def exploration_of(settings: EvalSettings) -> ExplorationType:
    """``eval.deterministic``: the mean action (default) or sampled actions."""
    return ExplorationType.DETERMINISTIC if settings.deterministic else ExplorationType.RANDOM


def gymnasium_scores(run: RunSettings, env_options: Mapping, policy, steps: int, episodes: int | None = None) -> dict:
    """``eval.gymnasium=true``: ``policy`` played in Gymnasium's own env of the run's task with its
    ``env.options`` (for a MuJoCo task, MuJoCo's forward), ``episodes`` (default ``eval.num_envs``)
    full episodes from seeds ``eval.seed + i``: ``{"eval/gymnasium_return": ...,
    "eval/gymnasium_return_std": ..., ...}``."""
    scores = evaluate_in_gymnasium(policy, run.env_name, episodes or run.eval.num_envs, run.eval.seed, steps,
                                   options=dict(env_options), dtype=run.torch_dtype, device=run.device,
                                   exploration_type=exploration_of(run.eval))
    return {f"eval/gymnasium_{k}": v for k, v in scores.items() if k not in ("returns", "lengths")}


def _diff(old: DictConfig, new: DictConfig, where: str = "env.") -> dict:
    """``{"env.params.mass": new value}`` for every leaf of ``new`` that differs from ``old``."""
    out = {}
    for key, value in new.items():
        before = old.get(key) if key in old else None
        if isinstance(value, DictConfig):
            out.update(_diff(before if isinstance(before, DictConfig) else OmegaConf.create({}), value,
                             f"{where}{key}."))
        elif value != before:
            out[f"{where}{key}"] = value
    return out


def json_report(result: Mapping, reasons: Mapping[str, str] | None = None) -> str:
    """``result`` as strict JSON (``final_metrics.json``, ``eval_metrics.json``): a NaN or infinite
    number becomes ``null``, and ``"non_finite"`` says for each such key what it was and why
    (``reasons[key]``, else: the policy or the env diverged), so every JSON reader can parse the
    file."""
    reasons = dict(reasons or {})
    clean, non_finite = {}, {}
    for key, value in result.items():
        if isinstance(value, float) and not math.isfinite(value):
            clean[key] = None
            non_finite[key] = f"{value}: " + reasons.get(key, "not a finite number (a diverged policy or env)")
        elif isinstance(value, list) and any(isinstance(v, float) and not math.isfinite(v) for v in value):
            clean[key] = [None if isinstance(v, float) and not math.isfinite(v) else v for v in value]
            non_finite[key] = "null elements: not finite numbers (a diverged policy or env)"
        else:
            clean[key] = value
    if non_finite:
        clean["non_finite"] = non_finite
    return json.dumps(clean, indent=2, allow_nan=False) + "\n"


def write_video(settings: EvalSettings, env, policy, steps: int, stem: Path) -> Path | None:
    """The policy's video, ``<stem>.gif`` or ``<stem>.mp4`` (``eval.video_format``; MP4 falls back to
    GIF with a warning when imageio-ffmpeg is missing); a failure to draw (e.g. Pillow missing)
    warns instead of losing the run."""
    from ..rendering import mp4_available  # lazy: Pillow is an optional extra

    video_format = settings.video_format
    if video_format == "mp4" and not mp4_available():
        warnings.warn('eval.video_format=mp4 needs imageio-ffmpeg (pip install "torchrl_diffenvs[video]"); '
                      "writing a GIF instead", stacklevel=2)
        video_format = "gif"
    video = dict(env_index=settings.gif_env_index, fps=settings.gif_fps, size=settings.gif_size,
                 exploration_type=exploration_of(settings))
    if isinstance(env, GymnasiumBackedEnv):  # drawn by Gymnasium's own renderer (MuJoCo's needs OpenGL)
        try:
            return env.record_video(policy, steps, settings.seed, stem.with_suffix(f".{video_format}"), **video)
        except Exception as err:  # noqa: BLE001 - MuJoCo's renderer fails in many ways without a display
            warnings.warn(f"no video written: Gymnasium's renderer failed ({type(err).__name__}: {err}); on a "
                          "machine without a display set MUJOCO_GL=egl (or osmesa), or pass eval.gif=false",
                          stacklevel=2)
            return None
    try:
        return record_video(env, policy, steps, settings.seed, stem.with_suffix(f".{video_format}"), **video)
    except (ImportError, ValueError, KeyError) as err:
        warnings.warn(f"no video written ({type(err).__name__}: {err})", stacklevel=2)
        return None


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def _env_of_checkpoint(cfg: DictConfig, asked: RunSettings, trained: DictConfig, overrides: Sequence[str]) -> DictConfig:
    """The checkpoint's ``env`` section, with the command line's ``env.<key>=...`` on top (e.g.
    ``env.params.mass=2``: the trained policy under other physics). An ``env=<name>`` /
    ``env.name=<name>`` (``asked``: the command line's settings) must name the checkpoint's env:
    the policy's networks are shaped for it."""
    keys = [_override_key(o) for o in overrides if _override_key(o) == "env" or _override_key(o).startswith("env.")]
    if any(key in ("env", "env.name") for key in keys) and asked.env_name != trained.env.name:
        raise ConfigError(f"checkpoint={asked.checkpoint!r} holds a policy trained on env={trained.env.name}, "
                          f"not env={asked.env_name}; drop env= (mode=eval takes the env from the checkpoint) or "
                          f"evaluate a checkpoint of an env={asked.env_name} run")
    env = trained.env.copy()
    with open_dict(env):
        for key in keys:
            if key not in ("env", "env.name"):
                OmegaConf.update(env, key[len("env."):], OmegaConf.select(cfg, key), merge=False)
    return env


def evaluate_checkpoint(cfg: DictConfig, run_dir: Path, overrides: Sequence[str] = ()) -> dict:
    """``mode=eval``: scores the policy of ``cfg.checkpoint`` on fresh envs and writes its video
    and ``eval_metrics.json`` into ``run_dir``.

    The env, the loss (network shapes) and the dtype come from the checkpoint; ``eval.*`` and
    ``device`` from the command line. An ``env=`` on the command line (``overrides``) must name
    the checkpoint's env (the policy's networks are shaped for it); ``env.<key>=...`` overrides
    change the checkpoint's env section (e.g. ``env.params.mass=2`` evaluates the policy with
    another mass) and are recorded in ``eval_metrics.json``.
    """
    from .. import compile_physics

    asked = RunSettings.from_config(cfg)
    ckpt = load_checkpoint(asked.checkpoint)
    trained = OmegaConf.create(ckpt["config"])
    env_section = _env_of_checkpoint(cfg, asked, trained, overrides)
    changed = {key: OmegaConf.to_container(value) if isinstance(value, (DictConfig, ListConfig)) else value
               for key, value in _diff(trained.env, env_section).items()}
    cfg = cfg.copy()
    with open_dict(cfg):  # whole sections replaced, not merged: the trained env may have other options
        cfg.env, cfg.loss, cfg.dtype = env_section, trained.loss, trained.dtype
    run = RunSettings.from_config(cfg)
    evaluation = run.eval
    in_gymnasium = env_backend(cfg.env) == "gymnasium"  # the env below is Gymnasium's own already
    if evaluation.gymnasium and not in_gymnasium:
        problems: list[str] = []
        check_gymnasium_eval(cfg.env, problems)
        if problems:
            raise ConfigError(f"checkpoint={run.checkpoint!r}: " + "; ".join(problems))
    try:
        env = make_env_from_config(cfg, evaluation.num_envs, seed=evaluation.seed)
    except (ValueError, TypeError, KeyError) as err:
        raise ConfigError(f"env overrides {changed} rejected by env {run.env_name!r} of checkpoint="
                          f"{run.checkpoint!r}: {err}") from None
    steps = evaluation.max_steps or env.max_episode_steps
    policy = LEARNERS[run.loss_name].policy_from_config(cfg.loss, env)
    policy.load_state_dict(ckpt["policy"])
    if run.compile:
        compile_physics(env, steps_per_chunk=chunk_length(steps))
    # rl_games' player: eval.games_num episodes, played eval.num_envs at a time from successive seeds
    games = evaluation.games_num or evaluation.num_envs
    returns, lengths, terminated = [], [], []
    for round_index in range(-(-games // evaluation.num_envs)):
        env.set_seed(evaluation.seed + round_index)
        with torch.no_grad(), set_exploration_type(exploration_of(evaluation)):
            rollout = env.rollout(steps, policy, break_when_any_done=False)
        returns.extend(episode_returns(rollout, env.reward_key).double().tolist())
        length, ended = first_episode_ends(rollout)
        lengths.extend(length.tolist())
        terminated.extend(ended.tolist())
    returns = torch.tensor(returns[:games], dtype=torch.float64)
    scores = {"return": returns.mean().item(), "return_std": returns.std(unbiased=False).item(),
              "return_min": returns.min().item(), "return_max": returns.max().item(),
              "episode_length": sum(lengths[:games]) / games, "terminated": sum(terminated[:games]) / games}
    result = {"env": run.env_name, "loss": run.loss_name, "checkpoint": run.checkpoint,
              "trained_env_steps": ckpt["progress"]["env_steps"], "eval_steps": steps, "games": games,
              "env_overrides": changed,
              "returns": returns.tolist(), "episode_lengths": lengths[:games],
              "deterministic": evaluation.deterministic,
              "eval/random_return": evaluate_random(env, steps, evaluation.seed),
              **{f"eval/{k}": v for k, v in scores.items()}}
    if evaluation.gymnasium and in_gymnasium:  # the scores above are Gymnasium's own env's
        result.update({f"eval/gymnasium_{k}": v for k, v in scores.items()})
    elif evaluation.gymnasium:
        result.update(gymnasium_scores(run, run.env_options, policy, steps, games))
    run_dir.mkdir(parents=True, exist_ok=True)
    if evaluation.gif:
        video = write_video(evaluation, env, policy, steps, run_dir / "eval")
        result["video"] = str(video) if video else None
    (run_dir / "eval_metrics.json").write_text(json_report(result))
    in_gymnasium = (f"; in Gymnasium's own env {result['eval/gymnasium_return']:.4g}"
                    if "eval/gymnasium_return" in result else "")
    log.info(f"{run.env_name} {run.loss_name} ({run.checkpoint}): eval return {scores['return']:.4g} "
             f"+- {scores['return_std']:.3g} over {games} games (random policy "
             f"{result['eval/random_return']:.4g}){in_gymnasium}; outputs in {run_dir}")
    return result
