"""Train any torchrl_diffenvs env with BPTT, SHAC, PPO or SAC, or evaluate a saved policy.

    python sota_scripts/train.py env=swimmer loss=bptt
    python sota_scripts/train.py env=Pendulum-v1 loss=sac logger=csv train.total_env_steps=50000
    python sota_scripts/train.py -m env=pendulum,cartpole loss=shac,ppo seed=0,1,2
    python sota_scripts/train.py resume=outputs/<run>/checkpoints/last.pt
    python sota_scripts/train.py mode=eval checkpoint=outputs/<run>/checkpoints/last.pt
    torchrun --nproc_per_node=2 sota_scripts/train.py env=pendulum loss=shac   # data parallel

Configuration: configs/ (Hydra; config groups loss/, logger/, per-pair tuning in tuned/; env=<name> from
the task registrations).
Everything a run writes goes to its Hydra run directory: metrics.jsonl / metrics.csv,
final_metrics.json, checkpoints/ (last.pt and numbered ones), learning_curve.png, final.gif and,
with the default logger, the offline W&B run in wandb/.

Under torchrun every rank runs this script: each simulates env.num_envs envs of its own, the
gradients are averaged over the ranks (torchrl_diffenvs.distributed), and rank 0 alone evaluates,
logs and writes the run directory and its checkpoints.
"""
from __future__ import annotations

import json
import logging
import math
import os
import random
import sys
import time
import warnings
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from torchrl_diffenvs.training import (
    CheckpointError,
    ConfigError,
    RunLogger,
    capture_rng_state,
    load_checkpoint,
    make_env_from_config,
    plot_learning_curve,
    resolve_device,
    restore_rng_state,
    save_checkpoint,
    validate_config,
)
from torchrl_diffenvs import compile_physics
from torchrl_diffenvs.distributed import SINGLE_PROCESS, DistributedError, World, parameters_checksum, rank_seed
from torchrl_diffenvs.envs.fast_rollout import compile_report
from torchrl_diffenvs.evaluation import episode_returns, evaluate, evaluate_random, record_video
from torchrl_diffenvs.learners import make_learner
from torchrl_diffenvs.modules import actor_from_config
from torchrl_diffenvs.training.checkpoint import atomic_copy
from torchrl_diffenvs.training.config import check_resume_compatible, merge_overrides
from torchrl_diffenvs.training.selfplay import SelfPlay

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")
log = logging.getLogger("train")  # Hydra sends it to the console and <run dir>/train.log


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    overrides = list(HydraConfig.get().overrides.task)
    try:
        if cfg.mode == "train" and cfg.get("resume"):
            # continue the run as it was configured: its own overrides, then today's (which win)
            overrides = merge_overrides(load_checkpoint(cfg.resume).get("overrides", []), overrides)
            cfg = hydra.compose(config_name="config", overrides=overrides)
        result = run(cfg, Path(HydraConfig.get().runtime.output_dir), overrides)
    except (ConfigError, CheckpointError, DistributedError) as err:  # a clear message instead of a traceback
        raise SystemExit(f"error: {err}") from None
    return result["eval/return"]  # a sweeper can maximise it


def run(cfg: DictConfig, run_dir: Path, overrides: list[str] = ()) -> dict:
    """Checks ``cfg`` and trains, or evaluates a checkpoint (``mode=eval``, on rank 0 only), in
    the ranks torchrun started (one process without torchrun). Returns the final metrics (rank
    0's, on every rank)."""
    validate_config(cfg)
    world = join_world(cfg)
    try:
        if cfg.mode == "eval":
            return world.broadcast_object(evaluate_checkpoint(cfg, Path(run_dir)) if world.is_main else None)
        return train(cfg, Path(run_dir), list(overrides), world)
    finally:
        world.close()


def join_world(cfg: DictConfig) -> World:
    """The ranks torchrun started (``WORLD_SIZE`` etc.), or one process."""
    in_multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and in_multirun:
        raise ConfigError("a multirun (-m) cannot run under torchrun: launch one torchrun per configuration, or "
                          "sweep single-process runs with a launcher (hydra/launcher=joblib or submitit_local)")
    return World.from_environment(resolve_device(cfg.device), timeout_s=float(cfg.distributed.timeout_s))


def chunk_length(steps: int, longest: int = 8) -> int:
    """The longest chunk of at most ``longest`` steps that divides ``steps`` (no eager remainder)."""
    return max(k for k in range(1, longest + 1) if steps % k == 0)


def compile_envs(learner, env, eval_env, eval_steps: int) -> None:
    """``compile=true``: BPTT/SHAC windows and evaluation rollouts in compiled chunks."""
    horizon = getattr(learner.config, "horizon", None)  # PPO and SAC collect through TorchRL's Collector
    if horizon is not None:
        compile_physics(env, steps_per_chunk=chunk_length(horizon))
    if eval_env is not None:
        compile_physics(eval_env, steps_per_chunk=chunk_length(eval_steps))
    log.info("compile=true: rollouts run in compiled chunks of policy + physics "
             f"({'training windows, ' if horizon is not None else ''}evaluations); the first of each kind compiles")


def report_compile(env, first_iteration_s: float) -> None:
    report = compile_report(env)
    if report is None:
        return
    calls = ", ".join(f"{what} {seconds:.1f} s" for what, seconds in report["first_call_seconds"].items())
    log.info(f"compile: first iteration {first_iteration_s:.1f} s (compiling forward and backward included); "
             f"first calls: {calls or 'none'}" + (f"; fell back to eager: {report['fallback_reason']}"
                                                  if report["fallback_reason"] else ""))


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(cfg: DictConfig, run_dir: Path, overrides: list[str] = (), world: World = SINGLE_PROCESS) -> dict:
    # ------------------------------------------------------------------ build everything
    world.check_same(OmegaConf.to_yaml(cfg, resolve=True), "configuration")
    cfg = cfg.copy()
    with open_dict(cfg):  # recorded in the checkpoints' config and the logger's hyperparameters
        cfg.distributed.world_size, cfg.distributed.backend = world.size, world.backend
        cfg.device = str(world.device(resolve_device(cfg.device)))  # cuda -> cuda:<local rank>
    seed_everything(cfg.seed)  # the same networks on every rank
    env = make_env_from_config(cfg, cfg.env.num_envs, seed=rank_seed(cfg.seed, world.rank))
    learner = make_learner(cfg.loss, env, cfg.train.total_env_steps, world)
    world.check_same(parameters_checksum(learner.policy.state_dict().values()), "initial policy")
    if not world.is_main:  # its own exploration noise and minibatch order (rank 0 goes on as one process would)
        seed_everything(rank_seed(cfg.seed, world.rank))
    selfplay = None
    if cfg.selfplay.refresh_interval is not None:  # the opponent: snapshots of the policy (rl_games' self-play)
        selfplay = SelfPlay(env, learner.policy, cfg.selfplay.refresh_interval, cfg.selfplay.pool_size, seed=cfg.seed)
    eval_env = make_env_from_config(cfg, cfg.eval.num_envs, seed=cfg.eval.seed) if world.is_main else None
    eval_steps = cfg.eval.max_steps or (eval_env or env).max_episode_steps
    if cfg.get("compile"):
        compile_envs(learner, env, eval_env, eval_steps)
    total = int(cfg.train.total_env_steps)
    if world.size > 1:
        log.info(f"data parallel: {world.size} ranks ({world.backend}), env.num_envs={cfg.env.num_envs} per rank "
                 f"({cfg.env.num_envs * world.size} in all), {learner.env_steps_per_iteration:,} env steps per iteration")
    # the counters a checkpoint carries, so that a resumed run continues its schedules
    progress = {"iteration": 0, "env_steps": 0, "wall_time_s": 0.0, "next_eval": 0,
                "next_checkpoint": int(cfg.train.checkpoint_interval)}
    history, wandb_run_id = [], None
    if cfg.get("resume"):
        ckpt = load_checkpoint(cfg.resume, map_location=env.device)
        check_resume_compatible(OmegaConf.create(ckpt["config"]), cfg)
        if ckpt.get("world_size", 1) != world.size:
            raise CheckpointError(
                f"resume={cfg.resume!r} was written by {ckpt.get('world_size', 1)} rank(s) and holds each rank's env "
                f"state, replay buffer and random streams; resume it with as many ranks "
                f"(torchrun --nproc_per_node={ckpt.get('world_size', 1)}), not {world.size}")
        mine = ckpt if world.is_main else ckpt["other_ranks"][world.rank - 1]
        learner.load_state_dict(mine["learner"])
        if selfplay is not None:
            selfplay.load_state_dict(mine["selfplay"])
        progress, history, wandb_run_id = ckpt["progress"], ckpt["history"], ckpt.get("wandb_run_id")
        progress.pop("won", None)  # a resumed run trains on, even past an earlier score_to_win
        restore_rng_state(mine["rng"], {"env": env.rng})  # last: building the learner drew numbers
        log.info(f"resumed {cfg.resume} at env step {progress['env_steps']:,}")
    # rank 0 alone writes the run directory
    logger = RunLogger(cfg, run_dir, history, wandb_run_id) if world.is_main else None
    ckpt_dir = run_dir / "checkpoints"
    last = {"eval/return": float("nan"), "train/return": float("nan")}
    for row in history:  # what the progress bar and the final metrics show after a resume
        last.update({k: v for k, v in row.items() if k in last or k == "eval/random_return"})

    def checkpoint(name: str | None = None) -> Path | None:
        """Writes a numbered checkpoint (and last.pt), or the one called ``name`` (best.pt), with
        every rank's state; every rank calls it, rank 0 writes."""
        ranks = world.gather_object({"learner": learner.state_dict(), "rng": capture_rng_state({"env": env.rng}),
                                     "selfplay": selfplay.state_dict() if selfplay is not None else None})
        if not world.is_main:
            return None
        state = {
            "config": OmegaConf.to_container(cfg, resolve=True),
            "overrides": [o for o in overrides if not o.startswith(("resume=", "mode=", "checkpoint="))],
            **ranks[0],  # rank 0's learner and random streams
            "other_ranks": ranks[1:],
            "world_size": world.size,
            "policy": learner.policy.state_dict(),
            "progress": dict(progress),
            "history": logger.rows,
            "wandb_run_id": logger.wandb_run_id,
        }
        if name is not None:
            return save_checkpoint(state, ckpt_dir / name)
        path = save_checkpoint(state, ckpt_dir / f"ckpt_{progress['env_steps']:012d}.pt")
        atomic_copy(path, ckpt_dir / "last.pt")
        numbered = sorted(ckpt_dir.glob("ckpt_*.pt"))
        for old in numbered[: len(numbered) - cfg.train.keep_checkpoints]:  # the newest keep_checkpoints stay
            old.unlink()
        logger.write_csv()
        return path

    def evaluation() -> None:
        """Rank 0 evaluates; every rank learns its verdicts (best so far? won?) and acts on them."""
        score = None
        if world.is_main:
            if "eval/random_return" not in last:
                last["eval/random_return"] = evaluate_random(eval_env, eval_steps, cfg.eval.seed)
                logger.log({"eval/random_return": last["eval/random_return"]}, progress["env_steps"])
            scores = evaluate(eval_env, learner.policy, eval_steps, cfg.eval.seed)
            score = last["eval/return"] = scores["return"]
            logger.log({f"eval/{k}": v for k, v in scores.items()}, progress["env_steps"])
        score = world.broadcast_object(score)
        progress["last_eval"] = progress["env_steps"]
        best_after = cfg.train.get("save_best_after")
        if best_after is not None and progress["env_steps"] >= best_after and \
                score > progress.get("best_eval_return", -math.inf):
            progress["best_eval_return"] = score  # set first: best.pt records itself as the best
            checkpoint("best.pt")
        win = cfg.train.get("score_to_win")
        if win is not None and score >= win and not progress.get("won"):
            progress["won"] = True
            log.info(f"evaluation return {score:.4g} >= train.score_to_win={win}: stopping at env step "
                     f"{progress['env_steps']:,}")

    # ------------------------------------------------------------------ the loop
    bar = tqdm(total=total, initial=min(progress["env_steps"], total), unit="step", unit_scale=True,
               dynamic_ncols=True, disable=not (cfg.train.progress_bar and world.is_main),
               desc=f"{cfg.env.name} {cfg.loss.name}")
    start = time.perf_counter() - progress["wall_time_s"]
    compile_reported = False
    try:
        while True:
            if progress["env_steps"] >= progress["next_eval"]:
                evaluation()
                while progress["next_eval"] <= progress["env_steps"]:
                    progress["next_eval"] += int(cfg.eval.interval)
            if progress["env_steps"] >= progress["next_checkpoint"]:
                while progress["next_checkpoint"] <= progress["env_steps"]:
                    progress["next_checkpoint"] += int(cfg.train.checkpoint_interval)
                checkpoint()
            if progress["env_steps"] >= total or progress.get("won"):
                break

            tic = time.perf_counter()
            if selfplay is not None:
                selfplay.step(progress["env_steps"])
            metrics = learner.train_iteration()
            if selfplay is not None:
                metrics.update(selfplay.metrics())
            steps = learner.env_steps_per_iteration  # all ranks'
            progress["iteration"] += 1
            logging_now = progress["iteration"] % cfg.train.log_interval == 0
            if logging_now:  # means over the ranks (a collective: only when a row is logged)
                metrics = world.mean_metrics(metrics)
            progress["env_steps"] += steps
            progress["wall_time_s"] = time.perf_counter() - start
            if "return" in metrics:
                last["train/return"] = metrics["return"]
            if cfg.get("compile") and not compile_reported and world.is_main:  # this process's first iteration
                report_compile(env, time.perf_counter() - tic)
                compile_reported = True
            if world.is_main and logging_now:
                row = {f"train/{k}": v for k, v in metrics.items()}
                row.update({"time/iteration": progress["iteration"], "time/wall_s": progress["wall_time_s"],
                            "time/steps_per_s": steps / (time.perf_counter() - tic)})
                logger.log(row, progress["env_steps"])
            bar.update(steps)
            bar.set_postfix({"return": f"{last['train/return']:.3g}", "eval": f"{last['eval/return']:.3g}"},
                            refresh=False)
        bar.close()

        # ------------------------------------------------------------------ the end
        if progress.get("last_eval") != progress["env_steps"]:
            evaluation()
        checkpoint()
        if not world.is_main:
            return world.broadcast_object(None)
        files = {}
        if cfg.eval.gif:
            files["final_gif"] = write_video(cfg, eval_env, learner.policy, eval_steps, run_dir / "final")
        curve = plot_learning_curve(logger.rows, run_dir / "learning_curve.png",
                                    title=f"{cfg.env.name} - {cfg.loss.name} - seed {cfg.seed}")
        logger.log_files(images={"learning_curve": curve} if curve else {},
                         gifs={"final_gif": files["final_gif"]} if files.get("final_gif") else {})
        result = {
            "env": cfg.env.name, "loss": cfg.loss.name, "seed": cfg.seed, "world_size": world.size,
            "env_steps": progress["env_steps"], "iterations": progress["iteration"],
            "wall_time_s": progress["wall_time_s"],
            "steps_per_s": progress["env_steps"] / max(progress["wall_time_s"], 1e-9),
            "eval/return": last["eval/return"], "eval/random_return": last.get("eval/random_return"),
            "train/return": last["train/return"], "checkpoint": str(ckpt_dir / "last.pt"),
            "run_dir": str(run_dir), "wandb_dir": str(logger.wandb_dir) if logger.wandb_dir else None,
        }
        (run_dir / "final_metrics.json").write_text(json.dumps(result, indent=2) + "\n")
        log.info(f"{cfg.env.name} {cfg.loss.name}: eval return {result['eval/return']:.4g} "
              f"(random policy {result['eval/random_return']:.4g}) after {progress['env_steps']:,} env steps "
              f"in {progress['wall_time_s']:.0f} s; outputs in {run_dir}")
        return world.broadcast_object(result)
    except KeyboardInterrupt:
        bar.close()
        saved = ckpt_dir / "last.pt"
        if not world.is_main:
            raise
        if saved.exists():
            at = load_checkpoint(saved)["progress"]["env_steps"]
            log.warning(f"interrupted at env step {progress['env_steps']:,}; continue from env step {at:,} with "
                  f"resume={saved}")
        else:
            log.warning(f"interrupted at env step {progress['env_steps']:,}, before the first checkpoint")
        raise
    finally:
        if logger is not None:
            logger.close()
        learner.close()


def write_video(cfg: DictConfig, env, policy, steps: int, stem: Path) -> Path | None:
    """The policy's video, ``<stem>.gif`` or ``<stem>.mp4`` (``eval.video_format``; MP4 falls back to
    GIF with a warning when imageio-ffmpeg is missing); a failure to draw (e.g. Pillow missing)
    warns instead of losing the run."""
    from torchrl_diffenvs.rendering import mp4_available  # lazy: Pillow is an optional extra

    video_format = cfg.eval.get("video_format", "gif")
    if video_format == "mp4" and not mp4_available():
        warnings.warn('eval.video_format=mp4 needs imageio-ffmpeg (pip install "torchrl_diffenvs[video]"); '
                      "writing a GIF instead", stacklevel=2)
        video_format = "gif"
    try:
        return record_video(env, policy, steps, cfg.eval.seed, stem.with_suffix(f".{video_format}"),
                            env_index=cfg.eval.gif_env_index, fps=cfg.eval.gif_fps, size=cfg.eval.gif_size,
                            exploration_type=exploration_of(cfg))
    except (ImportError, ValueError, KeyError) as err:
        warnings.warn(f"no video written ({type(err).__name__}: {err})", stacklevel=2)
        return None


def exploration_of(cfg: DictConfig) -> ExplorationType:
    """``eval.deterministic``: the mean action (default) or sampled actions."""
    return ExplorationType.DETERMINISTIC if cfg.eval.get("deterministic", True) else ExplorationType.RANDOM


def evaluate_checkpoint(cfg: DictConfig, run_dir: Path) -> dict:
    """``mode=eval``: scores the policy of ``cfg.checkpoint`` on fresh envs and writes its GIF.

    The env, the loss (network shapes) and the dtype come from the checkpoint; ``eval.*`` and
    ``device`` from the command line.
    """
    ckpt = load_checkpoint(cfg.checkpoint)
    trained = OmegaConf.create(ckpt["config"])
    cfg = cfg.copy()
    with open_dict(cfg):  # whole sections replaced, not merged: the trained env may have other options
        cfg.env, cfg.loss, cfg.dtype = trained.env, trained.loss, trained.dtype
    env = make_env_from_config(cfg, cfg.eval.num_envs, seed=cfg.eval.seed)
    steps = cfg.eval.max_steps or env.max_episode_steps
    policy, _ = actor_from_config(cfg.loss, env, return_log_prob=cfg.loss.name == "ppo")
    policy.load_state_dict(ckpt["policy"])
    if cfg.get("compile"):
        compile_physics(env, steps_per_chunk=chunk_length(steps))
    # rl_games' player: eval.games_num episodes, played eval.num_envs at a time from successive seeds
    games = int(cfg.eval.get("games_num") or cfg.eval.num_envs)
    returns = []
    for round_index in range(-(-games // cfg.eval.num_envs)):
        env.set_seed(cfg.eval.seed + round_index)
        with torch.no_grad(), set_exploration_type(exploration_of(cfg)):
            rollout = env.rollout(steps, policy, break_when_any_done=False)
        returns.extend(episode_returns(rollout, env.reward_key).double().tolist())
    returns = torch.tensor(returns[:games], dtype=torch.float64)
    scores = {"return": returns.mean().item(), "return_std": returns.std(unbiased=False).item(),
              "return_min": returns.min().item(), "return_max": returns.max().item()}
    result = {"env": cfg.env.name, "loss": cfg.loss.name, "checkpoint": str(cfg.checkpoint),
              "trained_env_steps": ckpt["progress"]["env_steps"], "eval_steps": steps, "games": games,
              "returns": returns.tolist(),
              "deterministic": bool(cfg.eval.get("deterministic", True)),
              "eval/random_return": evaluate_random(env, steps, cfg.eval.seed),
              **{f"eval/{k}": v for k, v in scores.items()}}
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.eval.gif:
        video = write_video(cfg, env, policy, steps, run_dir / "eval")
        result["video"] = str(video) if video else None
    (run_dir / "eval_metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    log.info(f"{cfg.env.name} {cfg.loss.name} ({cfg.checkpoint}): eval return {scores['return']:.4g} "
          f"+- {scores['return_std']:.3g} over {games} games (random policy "
          f"{result['eval/random_return']:.4g}); outputs in {run_dir}")
    return result


if __name__ == "__main__":
    if int(os.environ.get("RANK", "0")) > 0:
        # under torchrun only rank 0 has a run directory: the other ranks keep Hydra from creating
        # theirs (no .hydra/ copy, no log file; their warnings and errors still reach stderr)
        sys.argv += ["hydra.output_subdir=null", "hydra.run.dir=.", "hydra/job_logging=none", "hydra/hydra_logging=none"]
    main()
