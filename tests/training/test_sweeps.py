"""Sweeps on Hydra's launcher and sweeper plugins (configs/launcher/, configs/optuna/): parallel
local jobs (joblib), submitit (its local executor; the Slurm preset composes), and an Optuna study
in SQLite that a second launch resumes. Each runs ``sota_scripts/train.py -m`` in a subprocess, as
a user would (joblib and submitit pickle the task for their own worker processes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from torchrl_diffenvs.training.config import register_env_configs

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "sota_scripts" / "train.py"
TINY = ["env=pendulum", "env.num_envs=4", "env.max_episode_steps=12", "eval.num_envs=2", "eval.gif=false",
        "logger=none", "train.progress_bar=false", "train.total_env_steps=96", "train.checkpoint_interval=96",
        "loss.actor.hidden=[16]"]


def multirun(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(SCRIPT), "-m", *overrides], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def finished_runs(sweep_dir: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in sorted(sweep_dir.glob("*/final_metrics.json"))}


def test_parallel_launcher_runs_the_jobs_in_worker_processes(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason='pip install -e ".[parallel]"')
    done = multirun(tmp_path, "launcher=parallel", "loss=bptt", "loss.horizon=4", "seed=0,1", *TINY,
                    f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert "Joblib.Parallel(n_jobs=2" in done.stderr + done.stdout
    runs = finished_runs(tmp_path / "sweep")
    assert sorted(runs) == ["0_pendulum_bptt_seed0", "1_pendulum_bptt_seed1"]
    assert {run["seed"] for run in runs.values()} == {0, 1} and all(run["env_steps"] == 96 for run in runs.values())


def test_submitit_local_executor_runs_the_sweep_as_slurm_would(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason='pip install -e ".[slurm]"')
    multirun(tmp_path, "launcher=submitit_local", "loss=bptt", "loss.horizon=4", "seed=0,1", *TINY,
             f"hydra.sweep.dir={tmp_path / 'sweep'}")
    runs = finished_runs(tmp_path / "sweep")
    assert sorted(runs) == ["0_pendulum_bptt_seed0", "1_pendulum_bptt_seed1"]
    assert list((tmp_path / "sweep" / ".submitit").glob("*/*_result.pkl"))  # submitit's own job records


def test_slurm_preset_configures_the_submitit_slurm_launcher():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason='pip install -e ".[slurm]"')
    register_env_configs()  # env=<name> sections, as train.py registers them
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["launcher=slurm", "hydra.launcher.partition=gpu",
                                                       "hydra.launcher.gpus_per_node=1"], return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert (launcher.partition, launcher.gpus_per_node, launcher.cpus_per_task) == ("gpu", 1, 2)
    assert launcher.submitit_folder.endswith(".submitit/%j")


def test_optuna_study_tunes_shac_and_a_second_launch_resumes_it(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason='pip install -e ".[optuna]"')
    optuna = pytest.importorskip("optuna")
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    common = ["optuna=shac_pendulum", "hydra.sweeper.n_trials=1", f"hydra.sweeper.storage={storage}", *TINY,
              "loss.critic.hidden=[16]"]
    multirun(tmp_path, *common, f"hydra.sweep.dir={tmp_path / 'first'}")
    multirun(tmp_path, *common, f"hydra.sweep.dir={tmp_path / 'second'}")

    study = optuna.load_study(study_name="shac_pendulum", storage=storage)
    trials = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(trials) == 2  # the second launch added to the first one's study
    assert {"loss.actor_lr", "loss.critic_lr", "loss.horizon", "loss.target_tau"} == set(trials[0].params)
    runs = [*finished_runs(tmp_path / "first").values(), *finished_runs(tmp_path / "second").values()]
    assert all((run["env"], run["loss"]) == ("pendulum", "shac") for run in runs)
    # each trial's value is its run's final evaluation return, and the study maximises it
    assert sorted(t.value for t in trials) == pytest.approx(sorted(run["eval/return"] for run in runs))
    best = yaml.safe_load((tmp_path / "second" / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(max(t.value for t in trials))
