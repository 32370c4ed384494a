"""The training loop: build the run, then evaluate, checkpoint and train until the budget is spent.

`run` is what ``sota_scripts/train.py`` calls with a composed configuration; it trains
(`train`) or evaluates a checkpoint (``mode=eval``, `evaluate_checkpoint`).
The loop itself is `Trainer.fit`, readable top to bottom:

1. at every ``eval.interval`` env steps (and at step 0): evaluate the deterministic policy on
   separate envs (rank 0), keep ``best.pt`` and stop early at ``train.score_to_win``;
2. at every ``train.checkpoint_interval`` env steps: write a checkpoint (all ranks' state);
3. one learner iteration (``learner.train_iteration()``), its metrics logged;
4. at the end: a last evaluation and checkpoint, the video, the learning curve and
   ``final_metrics.json``.

What differs between learners (their settings, networks, how they collect data) is the
learner's business (`torchrl_diffenvs.learners`); this loop only drives
`Learner`'s interface.

Under ``torchrun`` every rank runs the same loop: each simulates ``env.num_envs`` envs of its own,
the learners average gradients over the ranks, and rank 0 alone evaluates, logs and writes the run
directory and its checkpoints.

Stopping: SIGTERM (a cluster's preemption) or Ctrl-C (SIGINT) lets the current iteration finish,
writes a checkpoint and raises `TrainingInterrupted` with the ``resume=`` command in its
message; a second Ctrl-C stops at once (the last checkpoint written stays the one to resume).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
import random
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from tqdm.auto import tqdm

from ..distributed import SINGLE_PROCESS, World, parameters_checksum, rank_seed
from ..envs.rollout import compile_report
from ..envs.gymnasium_backend import GymnasiumBackedEnv
from ..evaluation import evaluate, evaluate_random
from ..learners import make_learner
from .checkpoint import (
    CheckpointError,
    atomic_copy,
    capture_rng_state,
    load_checkpoint,
    remove_stale_temp_files,
    restore_rng_state,
    save_checkpoint,
)
from .config import (
    ConfigError,
    check_resume_compatible,
    make_env_from_config,
    resolve_device,
    validate_config,
)
from .eval_mode import chunk_length, evaluate_checkpoint, gymnasium_scores, json_report, write_video
from .interrupts import StopRequests, TrainingInterrupted
from .run_logger import RunLogger, plot_learning_curve, read_history
from .selfplay import SelfPlay
from .settings import RunSettings

__all__ = ["Trainer", "TrainingInterrupted", "run", "seed_everything", "train"]

log = logging.getLogger("train")  # Hydra sends it to the console and <run dir>/train.log

# overrides of the command line that a checkpoint does not carry on to a resumed run
_PER_INVOCATION = ("resume=", "mode=", "checkpoint=")
# what evaluate_in_gymnasium reports (eval/gymnasium_<key>)
GYMNASIUM_SCORES = ("return", "return_std", "return_min", "return_max", "episode_length", "terminated")


def memory_in_use(device) -> dict:
    """The process's resident memory (``memory/rss_mib``, Linux) and on CUDA the tensors' memory
    (``memory/cuda_allocated_mib``): a training row's record, so that a leak shows as a slope over
    iterations (``benchmarks/memory_growth.py``). Host-side counters: no synchronisation."""
    out = {}
    try:
        with open("/proc/self/statm") as statm:
            out["memory/rss_mib"] = int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):  # not Linux
        pass
    if torch.device(device).type == "cuda":
        out["memory/cuda_allocated_mib"] = torch.cuda.memory_allocated(device) / 2**20
    return out


def run(cfg: DictConfig, run_dir: str | Path, overrides: Sequence[str] = ()) -> dict:
    """Checks ``cfg`` and trains, or evaluates a checkpoint (``mode=eval``, on rank 0 only), in the
    ranks ``torchrun`` started (one process without it). ``overrides`` are the command line's
    (saved in checkpoints so that ``resume=`` alone continues the run). Returns the final metrics
    (rank 0's, on every rank).

    Raises:
        ConfigError: the configuration cannot run (every problem listed).
        CheckpointError: ``resume=`` / ``checkpoint=`` is not a checkpoint this loop can use.
        TrainingInterrupted: SIGTERM or Ctrl-C stopped training (a checkpoint was written first).
    """
    validate_config(cfg)
    world = join_world(cfg)
    try:
        if RunSettings.from_config(cfg).mode == "eval":
            result = evaluate_checkpoint(cfg, Path(run_dir), overrides) if world.is_main else None
            return world.broadcast_object(result)
        return train(cfg, Path(run_dir), overrides, world)
    finally:
        world.close()


def join_world(cfg: DictConfig) -> World:
    """The ranks torchrun started (``WORLD_SIZE`` etc.), or one process."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    in_multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and in_multirun:
        raise ConfigError("a multirun (-m) cannot run under torchrun: launch one torchrun per configuration, or "
                          "sweep single-process runs with a launcher (hydra/launcher=joblib or submitit_local)")
    run = RunSettings.from_config(cfg)
    return World.from_environment(resolve_device(run.device), timeout_s=run.distributed.timeout_s)


def seed_everything(seed: int) -> None:
    """Seeds Python's, numpy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(cfg: DictConfig, run_dir: str | Path, overrides: Sequence[str] = (), world: World = SINGLE_PROCESS) -> dict:
    """Trains as ``cfg`` says (resuming ``cfg.resume`` if set); returns the final metrics."""
    trainer = Trainer(cfg, Path(run_dir), overrides, world)
    try:
        return trainer.fit()
    finally:
        trainer.close()


class Trainer:
    """One training run: its envs, learner, logger and counters, and the loop (`fit`).

    Args:
        cfg: the composed configuration (already checked by `validate_config`).
        run_dir: where rank 0 writes metrics, checkpoints, the video and the learning curve.
        overrides: the command line's overrides (kept in checkpoints for ``resume=``).
        world: the ranks training together.
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, overrides: Sequence[str] = (), world: World = SINGLE_PROCESS):
        world.check_same(OmegaConf.to_yaml(cfg, resolve=True), "configuration")
        # what this loop reads, typed; cuda -> cuda:<local rank>
        run = RunSettings.from_config(cfg)
        self.settings = run = dataclasses.replace(run, device=str(world.device(resolve_device(run.device))))
        cfg = cfg.copy()
        with open_dict(cfg):  # recorded in the checkpoints' config and the logger's hyperparameters
            cfg.distributed.world_size, cfg.distributed.backend = world.size, world.backend
            cfg.device = run.device
        self.cfg, self.run_dir, self.world = cfg, Path(run_dir), world
        self.env_options = run.env_options  # eval.gymnasium
        self.overrides = [o for o in overrides if not o.startswith(_PER_INVOCATION)]
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.logger: RunLogger | None = None

        # ------------------------------------------------------------ envs, learner, opponents
        seed_everything(run.seed)  # the same networks on every rank
        self.env = make_env_from_config(cfg, run.env_num_envs, seed=rank_seed(run.seed, world.rank))
        self.learner = make_learner(cfg.loss, self.env, run.train.total_env_steps, world)
        world.check_same(parameters_checksum(self.learner.policy.state_dict().values()), "initial policy")
        if not world.is_main:  # its own exploration noise and minibatch order (rank 0 goes on as one process would)
            seed_everything(rank_seed(run.seed, world.rank))
        self.selfplay = None
        if run.selfplay.refresh_interval is not None:  # the opponent: snapshots of the policy (rl_games' self-play)
            self.selfplay = SelfPlay(self.env, self.learner.policy, run.selfplay.refresh_interval,
                                     run.selfplay.pool_size, seed=run.seed)
        self.eval_env = make_env_from_config(cfg, run.eval.num_envs, seed=run.eval.seed) if world.is_main else None
        self.eval_steps = run.eval.max_steps or (self.eval_env or self.env).max_episode_steps
        if run.compile:
            self._compile()
        self.total = run.train.total_env_steps
        if world.size > 1:
            log.info(f"data parallel: {world.size} ranks ({world.backend}), env.num_envs={run.env_num_envs} per rank "
                     f"({run.env_num_envs * world.size} in all), "
                     f"{self.learner.env_steps_per_iteration:,} env steps per iteration")

        # ------------------------------------------------------------ counters (saved in checkpoints)
        # wall_time_s: the run's time to its last iteration, its evaluations included, of which
        # eval_time_s was spent evaluating (the final evaluation, after the last iteration, in neither)
        self.progress = {"iteration": 0, "env_steps": 0, "wall_time_s": 0.0, "eval_time_s": 0.0, "next_eval": 0,
                         "next_checkpoint": run.train.checkpoint_interval, "logged_rows": 0,
                         "last": {"eval/return": math.nan, "train/return": math.nan}}
        history, wandb_run_id = [], None
        if world.is_main:
            remove_stale_temp_files(self.ckpt_dir)
        if run.resume:
            try:
                history, wandb_run_id = self._resume(Path(run.resume))
            except BaseException:
                self.learner.close()  # its collector, if any, before the error leaves
                raise
        if world.is_main:  # rank 0 alone writes the run directory
            self.logger = RunLogger(run.logger, self.run_dir, history, wandb_run_id,
                                    hyperparameters=OmegaConf.to_container(cfg, resolve=True))

    # ------------------------------------------------------------------ the loop
    def fit(self) -> dict:
        """Trains until the budget is spent (or ``train.score_to_win`` is reached); returns the
        final metrics."""
        run, progress, last = self.settings, self.progress, self.progress["last"]
        bar = tqdm(total=self.total, initial=min(progress["env_steps"], self.total), unit="step", unit_scale=True,
                   dynamic_ncols=True, disable=not (run.train.progress_bar and self.world.is_main),
                   desc=f"{run.env_name} {run.loss_name}")
        start = time.perf_counter() - progress["wall_time_s"]
        evaluating = 0.0  # the latest evaluation's seconds, counted once an iteration follows it
        with StopRequests() as stop, bar:
            try:
                while True:
                    if progress["env_steps"] >= progress["next_eval"]:
                        tic = time.perf_counter()
                        self.evaluate()
                        evaluating = time.perf_counter() - tic
                        while progress["next_eval"] <= progress["env_steps"]:
                            progress["next_eval"] += run.eval.interval
                    if progress["env_steps"] >= progress["next_checkpoint"]:
                        while progress["next_checkpoint"] <= progress["env_steps"]:
                            progress["next_checkpoint"] += run.train.checkpoint_interval
                        self.checkpoint()
                    if progress["env_steps"] >= self.total or progress.get("won"):
                        break
                    if self.world.mean(float(stop.requested is not None)) > 0:  # every rank stops together
                        self._stop(stop.requested or "a signal on another rank")

                    tic = time.perf_counter()
                    metrics, logging_now = self.iteration()
                    progress["wall_time_s"] = time.perf_counter() - start
                    progress["eval_time_s"] = progress.get("eval_time_s", 0.0) + evaluating
                    evaluating = 0.0
                    if "return" in metrics:
                        last["train/return"] = metrics["return"]
                    if self.world.is_main and logging_now:
                        row = {f"train/{k}": v for k, v in metrics.items()}
                        row.update({"time/iteration": progress["iteration"], "time/wall_s": progress["wall_time_s"],
                                    "time/eval_s": progress["eval_time_s"],
                                    "time/steps_per_s": self.learner.env_steps_per_iteration
                                    / (time.perf_counter() - tic), **memory_in_use(self.env.device)})
                        self.log(row)
                    bar.update(self.learner.env_steps_per_iteration)
                    shown = last.get("eval/gymnasium_return", math.nan) if run.eval.only_gymnasium \
                        else last["eval/return"]
                    bar.set_postfix({"return": f"{last['train/return']:.3g}", "eval": f"{shown:.3g}"}, refresh=False)
            except KeyboardInterrupt as err:
                if isinstance(err, TrainingInterrupted):
                    raise
                self._interrupted_mid_iteration()
        return self.finish()

    def iteration(self) -> tuple[dict[str, float], bool]:
        """One learner iteration (the self-play schedule before it); returns its metrics (means
        over the ranks when a row is logged) and whether this iteration logs a row."""
        progress = self.progress
        tic = time.perf_counter()
        if self.selfplay is not None:
            self.selfplay.step(progress["env_steps"])
        metrics = self.learner.train_iteration()
        if self.selfplay is not None:
            metrics.update(self.selfplay.metrics())
        progress["iteration"] += 1
        progress["env_steps"] += self.learner.env_steps_per_iteration  # all ranks'
        logging_now = progress["iteration"] % self.settings.train.log_interval == 0
        if logging_now:  # a collective: only when a row is logged
            metrics = self.world.mean_metrics(metrics)
        if self.settings.compile and progress["iteration"] == 1 and self.world.is_main:
            self._report_compile(time.perf_counter() - tic)
        return metrics, logging_now

    def log(self, row: dict) -> None:
        self.logger.log(row, self.progress["env_steps"])
        self.progress["logged_rows"] = len(self.logger.rows)

    def evaluate(self) -> None:
        """Rank 0 evaluates; every rank learns its verdicts (best so far? won?) and acts on them."""
        run, progress, last = self.settings, self.progress, self.progress["last"]
        score = None
        if self.world.is_main:
            in_gymnasium_backend = isinstance(self.eval_env, GymnasiumBackedEnv)
            here = not run.eval.only_gymnasium or in_gymnasium_backend
            if here and "eval/random_return" not in last:
                last["eval/random_return"] = evaluate_random(self.eval_env, self.eval_steps, run.eval.seed)
                self.log({"eval/random_return": last["eval/random_return"]})
            if here:
                scores = evaluate(self.eval_env, self.learner.policy, self.eval_steps, run.eval.seed)
                score = last["eval/return"] = scores["return"]
                last["eval/episode_length"], last["eval/terminated"] = scores["episode_length"], scores["terminated"]
                self.log({f"eval/{k}": v for k, v in scores.items()})
            if run.eval.gymnasium and in_gymnasium_backend:
                # env.backend=gymnasium: the evaluation just played is Gymnasium's own env, from the
                # seeds evaluate_in_gymnasium uses (env i from eval.seed + i): the same scores
                theirs = {f"eval/gymnasium_{k}": v for k, v in scores.items() if k in GYMNASIUM_SCORES}
            elif run.eval.gymnasium:  # the same policy in Gymnasium's own env (MuJoCo's forward)
                theirs = gymnasium_scores(run, self.env_options, self.learner.policy, self.eval_steps)
            if run.eval.gymnasium:
                last["eval/gymnasium_return"] = theirs["eval/gymnasium_return"]
                self.log(theirs)
            if not here:
                score = last["eval/gymnasium_return"]
        score = self.world.broadcast_object(score)
        progress["last_eval"] = progress["env_steps"]
        best_after = run.train.save_best_after
        if best_after is not None and progress["env_steps"] >= best_after and \
                score > progress.get("best_eval_return", -math.inf):
            progress["best_eval_return"] = score  # set first: best.pt records itself as the best
            self.checkpoint("best.pt")
        win = run.train.score_to_win
        if win is not None and score >= win and not progress.get("won"):
            progress["won"] = True
            log.info(f"evaluation return {score:.4g} >= train.score_to_win={win}: stopping at env step "
                     f"{progress['env_steps']:,}")

    def checkpoint(self, name: str | None = None) -> Path | None:
        """Writes a numbered checkpoint (and ``last.pt``), or the one called ``name``
        (``best.pt``), with every rank's state; every rank calls it, rank 0 writes.

        The logged history is not in it: it is the run directory's ``metrics.jsonl``, of which
        the checkpoint records how many rows belong to it (``progress["logged_rows"]``).
        """
        world, learner = self.world, self.learner
        ranks = world.gather_object({
            "learner": learner.state_dict(), "rng": capture_rng_state({"env": self.env.rng}),
            "selfplay": self.selfplay.state_dict() if self.selfplay is not None else None,
            # env.backend=gymnasium: the simulator state the collector's TensorDict does not hold
            "env": self.env.simulator_state() if isinstance(self.env, GymnasiumBackedEnv) else None,
        })
        if not world.is_main:
            return None
        state = {
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "overrides": self.overrides,
            **ranks[0],  # rank 0's learner and random streams
            "other_ranks": ranks[1:],
            "world_size": world.size,
            "policy": learner.policy.state_dict(),
            "progress": dict(self.progress),
            "run_dir": str(self.run_dir),
            "wandb_run_id": self.logger.wandb_run_id,
        }
        if name is not None:
            return save_checkpoint(state, self.ckpt_dir / name)
        path = save_checkpoint(state, self.ckpt_dir / f"ckpt_{self.progress['env_steps']:012d}.pt")
        atomic_copy(path, self.ckpt_dir / "last.pt")
        numbered = sorted(self.ckpt_dir.glob("ckpt_*.pt"))
        for old in numbered[: len(numbered) - self.settings.train.keep_checkpoints]:  # the newest keep_checkpoints stay
            old.unlink()
        self.logger.write_csv()
        return path

    def finish(self) -> dict:
        """The last evaluation and checkpoint, the video, the learning curve and
        ``final_metrics.json``; returns the final metrics (rank 0's, on every rank)."""
        run, progress, last, world = self.settings, self.progress, self.progress["last"], self.world
        if progress.get("last_eval") != progress["env_steps"]:
            self.evaluate()
        self.checkpoint()
        if not world.is_main:
            return world.broadcast_object(None)
        files = {}
        if run.eval.gif:
            files["final_gif"] = write_video(run.eval, self.eval_env, self.learner.policy, self.eval_steps,
                                             self.run_dir / "final")
        curve = None
        if run.eval.learning_curve:
            curve = plot_learning_curve(self.logger.rows, self.run_dir / "learning_curve.png",
                                        title=f"{run.env_name} - {run.loss_name} - seed {run.seed}")
        self.logger.log_files(images={"learning_curve": curve} if curve else {},
                              gifs={"final_gif": files["final_gif"]} if files.get("final_gif") else {})
        result = {
            "env": run.env_name, "loss": run.loss_name, "seed": run.seed, "world_size": world.size,
            "env_steps": progress["env_steps"], "iterations": progress["iteration"],
            "wall_time_s": progress["wall_time_s"], "eval_time_s": progress.get("eval_time_s"),
            "steps_per_s": progress["env_steps"] / max(progress["wall_time_s"], 1e-9),
            "eval/return": last["eval/return"], "eval/random_return": last.get("eval/random_return"),
            "eval/episode_length": last.get("eval/episode_length"), "eval/terminated": last.get("eval/terminated"),
            "train/return": last["train/return"], "checkpoint": str(self.ckpt_dir / "last.pt"),
            **({"eval/gymnasium_return": last["eval/gymnasium_return"]} if "eval/gymnasium_return" in last else {}),
            "run_dir": str(self.run_dir),
            "wandb_dir": str(self.logger.wandb_dir) if self.logger.wandb_dir else None,
        }
        reasons = {"train/return": "no training episode finished (the episodes are longer than the run, or the "
                                   "returns diverged)"}
        if run.eval.only_gymnasium and not math.isfinite(result["eval/return"]):
            reasons["eval/return"] = ("eval.only_gymnasium=true: this library's own evaluation is not played "
                                      "(eval/gymnasium_return is the score)")
        (self.run_dir / "final_metrics.json").write_text(json_report(result, reasons=reasons))
        in_gymnasium = (f", in Gymnasium's own env {result['eval/gymnasium_return']:.4g}"
                        if "eval/gymnasium_return" in result else "")
        log.info(f"{run.env_name} {run.loss_name}: eval return {result['eval/return']:.4g} "
                 f"(random policy {math.nan if result['eval/random_return'] is None else result['eval/random_return']:.4g})"
                 f"{in_gymnasium} after {progress['env_steps']:,} env steps "
                 f"in {progress['wall_time_s']:.0f} s; outputs in {self.run_dir}")
        return world.broadcast_object(result)

    def close(self) -> None:
        if self.logger is not None:
            self.logger.close()
        self.learner.close()

    # ------------------------------------------------------------------ resuming and stopping
    def _resume(self, path: Path) -> tuple[list[dict], str | None]:
        """Restores a checkpoint's state into the learner, the opponents and the counters;
        returns the rows logged before it and its W&B run id."""
        cfg, world = self.cfg, self.world
        ckpt = load_checkpoint(path, map_location=self.env.device)
        check_resume_compatible(OmegaConf.create(ckpt["config"]), cfg)
        if ckpt.get("world_size", 1) != world.size:
            raise CheckpointError(
                f"resume={str(path)!r} was written by {ckpt.get('world_size', 1)} rank(s) and holds each rank's env "
                f"state, replay buffer and random streams; resume it with as many ranks "
                f"(torchrun --nproc_per_node={ckpt.get('world_size', 1)}), not {world.size}")
        mine = ckpt if world.is_main else ckpt["other_ranks"][world.rank - 1]
        self.learner.load_state_dict(mine["learner"])
        if isinstance(self.env, GymnasiumBackedEnv):  # after the learner: its collector reset the envs when built
            try:
                self.env.load_simulator_state(mine.get("env"))
            except ValueError as err:
                raise CheckpointError(f"resume={str(path)!r}: {err}") from None
        if self.selfplay is not None:
            self.selfplay.load_state_dict(mine["selfplay"])
        self.progress.update(ckpt["progress"])
        if "eval_time_s" not in ckpt["progress"]:  # a checkpoint that did not count it: unknown before the resume
            self.progress["eval_time_s"] = math.nan
        self.progress.pop("won", None)  # a resumed run trains on, even past an earlier score_to_win
        restore_rng_state(mine["rng"], {"env": self.env.rng})  # last: building the learner drew numbers
        history = []
        if world.is_main:
            remove_stale_temp_files(path.parent)
            history = read_history(ckpt, path)
            for row in history:  # what the progress bar and the final metrics show (checkpoints before "last")
                self.progress["last"].update({k: v for k, v in row.items()
                                              if k in ("eval/return", "train/return", "eval/random_return",
                                                       "eval/episode_length", "eval/terminated")})
        log.info(f"resumed {path} at env step {self.progress['env_steps']:,}")
        return history, ckpt.get("wandb_run_id")

    def _stop(self, reason: str) -> None:
        """A stop request between iterations: writes a checkpoint, then raises
        `TrainingInterrupted` with the command that continues the run."""
        self.checkpoint()
        last = self.ckpt_dir / "last.pt"
        message = (f"stopped by {reason} at env step {self.progress['env_steps']:,}; checkpoint written: continue "
                   f"with resume={last}")
        if self.world.is_main:
            log.warning(message)
        raise TrainingInterrupted(message, checkpoint=last, reason=reason)

    def _interrupted_mid_iteration(self) -> None:
        """A second Ctrl-C (or a ``KeyboardInterrupt`` from inside an iteration): the learner's
        state may be half-updated, so no checkpoint is written; the last one is the resume point."""
        saved = self.ckpt_dir / "last.pt"
        at = None
        if self.world.is_main and saved.exists():
            try:
                at = load_checkpoint(saved)["progress"]["env_steps"]
            except (CheckpointError, FileNotFoundError):
                at = None
        if at is not None:
            message = (f"interrupted at env step {self.progress['env_steps']:,}; continue from env step {at:,} "
                       f"with resume={saved}")
        else:
            message = f"interrupted at env step {self.progress['env_steps']:,}, before the first checkpoint"
        if self.world.is_main:
            log.warning(message)
        raise TrainingInterrupted(message, checkpoint=saved if at is not None else None, reason="Ctrl-C")

    # ------------------------------------------------------------------ compile=true
    def _compile(self) -> None:
        """``compile=true``: the learner's differentiable windows (when it collects through the
        env's rollout) and the evaluation rollouts run in compiled chunks."""
        from .. import compile_physics

        windows = self.learner.compiles_windows
        if windows:
            compile_physics(self.env, steps_per_chunk=chunk_length(self.learner.steps_per_env))
        if self.eval_env is not None:
            compile_physics(self.eval_env, steps_per_chunk=chunk_length(self.eval_steps))
        log.info("compile=true: rollouts run in compiled chunks of policy + physics "
                 f"({'training windows, ' if windows else ''}evaluations); the first of each kind compiles")

    def _report_compile(self, first_iteration_s: float) -> None:
        report = compile_report(self.env)
        if report is None:
            return
        calls = ", ".join(f"{what} {seconds:.1f} s" for what, seconds in report["first_call_seconds"].items())
        log.info(f"compile: first iteration {first_iteration_s:.1f} s (compiling forward and backward included); "
                 f"first calls: {calls or 'none'}" + (f"; fell back to eager: {report['fallback_reason']}"
                                                      if report["fallback_reason"] else ""))

