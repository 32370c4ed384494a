"""Train any torchrl_diffenvs env with BPTT, SHAC, AHAC, SAPO, PPO or SAC, or evaluate a saved policy.

    python sota_scripts/train.py env=swimmer loss=bptt
    python sota_scripts/train.py env=Pendulum-v1 loss=sac logger=csv train.total_env_steps=50000
    python sota_scripts/train.py -m env=pendulum,cartpole loss=shac,ppo seed=0,1,2
    python sota_scripts/train.py resume=outputs/<run>/checkpoints/last.pt
    python sota_scripts/train.py mode=eval checkpoint=outputs/<run>/checkpoints/last.pt
    torchrun --nproc_per_node=2 sota_scripts/train.py env=pendulum loss=shac   # data parallel

This file is only the command line: Hydra composes the configuration (configs/config.yaml; the
``loss=<name>`` sections are generated from the learners' settings dataclasses, configs/loss/ holds
presets, configs/tuned/ per-pair tuning; ``env=<name>`` from the task registrations) and
:func:`torchrl_diffenvs.training.run` trains or evaluates. Everything a run writes goes to its Hydra
run directory: metrics.jsonl / metrics.csv, final_metrics.json, checkpoints/ (last.pt and numbered
ones), learning_curve.png, final.gif and, with the default logger, the offline W&B run in wandb/.

A bad configuration, checkpoint or ``tuned=`` choice stops with a one-line-per-problem error (exit
status 1). SIGTERM or Ctrl-C writes a checkpoint and prints the ``resume=`` command (exit status
128 + the signal's number).
"""
from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import hydra
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from torchrl_diffenvs.distributed import DistributedError
from torchrl_diffenvs.training import (
    CheckpointError,
    ConfigError,
    load_checkpoint,
    merge_overrides,
    run,
    validate_config,
)
from torchrl_diffenvs.training.config import check_checkpoint_path, check_group_choice

__all__ = ["main", "run", "validate_config"]

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")
log = logging.getLogger("train")  # Hydra sends it to the console and <run dir>/train.log


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    overrides = list(HydraConfig.get().overrides.task)
    try:
        # a choice the command line names must exist (the "tuned" group is optional: a missing
        # file would otherwise be skipped without a word)
        check_group_choice("tuned", overrides, GlobalHydra.instance().config_loader().get_group_options("tuned"))
        if cfg.mode == "train" and cfg.get("resume"):
            # continue the run as it was configured: its own overrides, then today's (which win)
            check_checkpoint_path(cfg.resume, "resume")
            overrides = merge_overrides(load_checkpoint(cfg.resume).get("overrides", []), overrides)
            cfg = hydra.compose(config_name="config", overrides=overrides)
        result = run(cfg, Path(HydraConfig.get().runtime.output_dir), overrides)
    except (ConfigError, CheckpointError, DistributedError) as err:  # a clear message instead of a traceback
        raise SystemExit(f"error: {err}") from None
    except KeyboardInterrupt as err:  # SIGTERM / Ctrl-C: the resume hint is logged; no traceback
        raise SystemExit(getattr(err, "exit_code", 130)) from None
    # a sweeper can maximise it: the return the run is judged by (Gymnasium's with eval.only_gymnasium)
    return result["eval/gymnasium_return"] if cfg.eval.get("only_gymnasium") else result["eval/return"]


if __name__ == "__main__":
    if int(os.environ.get("RANK", "0")) > 0:
        # under torchrun only rank 0 has a run directory: the other ranks keep Hydra from creating
        # theirs (no .hydra/ copy, no log file; their warnings and errors still reach stderr)
        sys.argv += ["hydra.output_subdir=null", "hydra.run.dir=.", "hydra/job_logging=none", "hydra/hydra_logging=none"]
    main()
