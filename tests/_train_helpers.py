"""The tiny training runs every area's tests compose (sota_scripts/train.py in-process): the
configurations, the script as a module and a few readers. Not a test module."""
from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from _env_helpers import load_script

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
SCRIPT = ROOT / "sota_scripts" / "train.py"


train_script = load_script("train_script", SCRIPT)
results_table = load_script("results_table", ROOT / "sota_scripts" / "results_table.py")

# Tiny runs: 4 envs, 12-step episodes (so episodes finish inside the run), small networks, no figures (drawing the
# learning curve cost a quarter of a tiny run; the tests of the run's outputs turn it on).
COMMON = [
    "logger=none", "train.progress_bar=false", "eval.gif=false", "eval.learning_curve=false", "env.num_envs=4",
    "env.max_episode_steps=12",
    "eval.num_envs=2", "eval.interval=1000000",
]
TINY = {
    "bptt": ["loss.horizon=4", "loss.actor.hidden=[16]"],
    "shac": ["loss.horizon=4", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]", "loss.critic_passes=2",
             "loss.critic_minibatches=2"],
    "ppo": ["loss.rollout_len=4", "loss.epochs=2", "loss.minibatch_size=8", "loss.actor.hidden=[16]",
            "loss.critic.hidden=[16]"],
    "sac": ["loss.rollout_len=2", "loss.init_random_frames=8", "loss.batch_size=8", "loss.buffer_size=256",
            "loss.utd_ratio=0.25", "loss.actor.hidden=[16]", "loss.qvalue.hidden=[16]"],
}
TINY.update(mappo=TINY["ppo"], ippo=TINY["ppo"])
TINY["sapo"] = ["loss.horizon=4", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]", "loss.critic_passes=2",
                "loss.critic_minibatches=2"]
# AHAC's window held at 4 steps (the horizon's own rule is tested in test_ahac_sapo.py)
TINY["ahac"] = ["loss.min_horizon=4", "loss.max_horizon=5", "loss.horizon_lr=1e-9", "loss.actor.hidden=[16]",
                "loss.critic.hidden=[16]", "loss.critic_passes=2", "loss.critic_minibatches=2"]
STEPS_PER_ITER = {"bptt": 16, "shac": 16, "ppo": 16, "sac": 8, "mappo": 16, "ippo": 16, "sapo": 16,
                  "ahac": 16}  # num_envs x horizon / rollout_len
CONTACT_ENVS = ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "HumanoidStandup-v5",
                "Pusher-v5")  # they report contact forces (AHAC's signal)


_composing = False  # inside `composing()`: Hydra is initialised on CONFIGS


@contextmanager
def composing():
    """One Hydra initialisation on the project's configs for the `make_cfg` calls inside the block
    (re-entrant): each call outside one initialises Hydra on the config tree again (a third of a
    compose's time)."""
    global _composing
    if _composing and GlobalHydra.instance().is_initialized():
        yield
        return
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        _composing = True
        try:
            yield
        finally:
            _composing = False


def make_cfg(*overrides: str):
    with composing():
        return compose(config_name="config", overrides=list(overrides))


def tiny_cfg(env: str, loss: str, iterations: int = 2, *extra: str):
    steps = iterations * STEPS_PER_ITER[loss]
    return make_cfg(f"env={env}", f"loss={loss}", *COMMON, *TINY[loss], f"train.total_env_steps={steps}",
                    f"train.checkpoint_interval={steps}", *extra)


def without_measurements(rows: list[dict]) -> list[dict]:
    """The rows without what measures the machine (``time/``: timings, ``memory/``: memory in
    use), which differs between two runs of the same training: everything else must not."""
    return [{k: v for k, v in r.items() if not k.startswith(("time/", "memory/"))} for r in rows]


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _cli(*args: str, cwd: Path, monkeypatch):
    """Runs ``python sota_scripts/train.py *args`` in this process (Hydra's own argument parsing
    and launcher; a subprocess would spend most of its time importing torch)."""
    from hydra.core.global_hydra import GlobalHydra

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    try:
        return train_script.main()
    finally:
        GlobalHydra.instance().clear()
