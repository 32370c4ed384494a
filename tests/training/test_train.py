"""sota_scripts/train.py: every env x loss trains a few iterations, logging, checkpoints, resume,
eval mode, sweeps and configuration errors.

Runs are composed in-process (Hydra's compose API, as TorchRL's own sota scripts are smoke-tested
with tiny overrides); a few tests go through the command line in a subprocess.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf
from hydra.errors import MissingConfigException

from _env_helpers import classic_envs, multi_agent_envs
from torchrl_diffenvs import list_envs
from torchrl_diffenvs.envs import env_config
from torchrl_diffenvs.evaluation import episode_returns
from torchrl_diffenvs.training import (
    CheckpointError,
    ConfigError,
    load_checkpoint,
    save_checkpoint,
)
from torchrl_diffenvs.training.config import LOSSES, make_env_from_config, merge_overrides

from _train_helpers import (  # noqa: F401  (shared with the other areas' training tests)
    COMMON, CONFIGS, CONTACT_ENVS, ROOT, SCRIPT, STEPS_PER_ITER, TINY, _cli, composing, make_cfg, read_jsonl,
    results_table,
    tiny_cfg, train_script, without_measurements,
)


# ---------------------------------------------------------------------- configuration
# configs/loss/<preset>.yaml: a learner with other settings (its loss.name is the learner's)
PRESETS = {"bptt_reference": "bptt", "shac_reference": "shac", "mappo": "ppo", "ippo": "ppo"}
REFERENCE_LOSSES = ("bptt_reference", "shac_reference")


def test_every_registered_env_and_loss_has_a_config():
    # the learners' sections are generated from their classes; configs/loss/ holds presets only
    loss_files = {p.stem for p in (CONFIGS / "loss").glob("*.yaml")}
    assert loss_files == set(PRESETS)
    assert not (CONFIGS / "env").exists(), "env sections come from the task registrations"
    for name in list_envs():
        cfg = make_cfg(f"env={name}", "loss=shac", "~tuned")  # (a tuned file may set env options)
        assert OmegaConf.to_container(cfg.env) == env_config(name)
    # a tuned file only for a pair that exists
    for path in (CONFIGS / "tuned").glob("*.yaml"):
        env, _, loss = path.stem.rpartition("_")
        assert env in list_envs() and loss in LOSSES, path.name


@pytest.mark.parametrize("env", list_envs())
def test_default_config_of_every_pair_is_valid(env):
    multi_agent = env in multi_agent_envs()
    with composing():
        configs = {loss: make_cfg(f"env={env}", f"loss={loss}") for loss in (*LOSSES, *PRESETS)}
    for loss, cfg in configs.items():
        assert cfg.env.name == env and cfg.loss.name == PRESETS.get(loss, loss)
        if loss == "ahac" and env not in CONTACT_ENVS:
            with pytest.raises(ConfigError, match=f"loss=ahac: env '{env}' reports no contact force"):
                train_script.validate_config(cfg)
        elif multi_agent and loss in ("sac", "sapo"):
            with pytest.raises(ConfigError, match="is multi-agent; train it with bptt, shac, mappo or ippo"):
                train_script.validate_config(cfg)
        elif not multi_agent and loss == "mappo":
            with pytest.raises(ConfigError, match="centralised_critic=true: env .* has a single agent"):
                train_script.validate_config(cfg)
        else:
            train_script.validate_config(cfg)  # raises on any problem


def test_a_newly_registered_task_is_trainable_without_a_config_file():
    from torchrl_diffenvs.envs import PendulumEnv, register_env
    from torchrl_diffenvs.envs.registry import _REGISTRY
    from torchrl_diffenvs.training.config import register_env_configs

    class LongPendulum(PendulumEnv):
        name = "long_pendulum_test"

    register_env(LongPendulum, num_envs=16)
    try:
        register_env_configs()
        cfg = make_cfg("env=long_pendulum_test", "loss=bptt")
        assert cfg.env.num_envs == 16 and cfg.env.name == "long_pendulum_test"
        train_script.validate_config(cfg)
    finally:
        _REGISTRY.pop("long_pendulum_test")


def test_a_new_learner_is_one_class_and_its_registration(tmp_path):
    """The extension story of torchrl_diffenvs.learners: a Learner subclass with its settings
    dataclass, registered with register_learner, is loss=<name> with its defaults, its checks,
    its budget, training, checkpoints and mode=eval, with no configuration file."""
    from hydra.core.config_store import ConfigStore

    from torchrl_diffenvs import checks
    from torchrl_diffenvs.learners import LEARNERS, BPTTConfig, BPTTLearner, register_learner
    from torchrl_diffenvs.learners.base import checked

    @dataclasses.dataclass(frozen=True)
    class CautiousBPTTConfig(BPTTConfig):
        actor_lr: float = checked(1e-3, checks.learning_rate)  # its own default
        horizon: int = checked(4, checks.positive_int)

    class CautiousBPTT(BPTTLearner):
        name = "cautious_bptt"
        config_class = CautiousBPTTConfig
        run_defaults = {"train": {"total_env_steps": 32, "checkpoint_interval": 32}}

    register_learner(CautiousBPTT)
    try:
        cfg = make_cfg("env=pendulum", "loss=cautious_bptt")
        assert (cfg.loss.name, cfg.loss.actor_lr, cfg.loss.horizon, cfg.train.total_env_steps) == \
            ("cautious_bptt", 1e-3, 4, 32)
        with pytest.raises(ConfigError, match="loss.actor_lr=0: a learning rate must be a number > 0"):
            train_script.validate_config(make_cfg("env=pendulum", "loss=cautious_bptt", "loss.actor_lr=0"))
        tiny = [*COMMON, "loss.actor.hidden=[8]"]
        result = train_script.run(make_cfg("env=pendulum", "loss=cautious_bptt", *tiny), tmp_path / "train")
        assert result["loss"] == "cautious_bptt" and result["env_steps"] == 32
        ckpt = tmp_path / "train" / "checkpoints" / "last.pt"
        played = train_script.run(make_cfg("mode=eval", f"checkpoint={ckpt}", "logger=none", "eval.gif=false",
                                           "eval.num_envs=2"), tmp_path / "eval")
        assert played["loss"] == "cautious_bptt" and math.isfinite(played["eval/return"])
    finally:
        LEARNERS.pop("cautious_bptt")
        ConfigStore.instance().repo["loss"].pop("cautious_bptt.yaml")


@pytest.mark.parametrize("choice, name", [("bptt_reference", "bptt"), ("shac_reference", "shac")])
def test_reference_configs_are_the_learner_with_the_references_settings(tmp_path, choice, name):
    cfg = make_cfg("env=pendulum", f"loss={choice}")
    assert cfg.loss.name == name and cfg.loss.horizon == 32
    train_script.validate_config(cfg)
    if name == "shac":  # DiffRL
        assert (cfg.loss.critic_passes, cfg.loss.critic_minibatches, cfg.loss.critic_shuffle) == (16, 4, "once_per_window")
        assert cfg.loss.critic.init == "orthogonal" and cfg.loss.actor.norm_after_activation
    else:  # Brax APG
        assert (cfg.loss.grad_clip, cfg.loss.stagger_episodes, cfg.loss.lr_schedule) == ("elementwise", True, "exponential")
    overrides = ["env.num_envs=4", "env.max_episode_steps=12", "eval.num_envs=2", "eval.interval=64", "loss.horizon=4",
                 "loss.actor.hidden=[8]", "train.total_env_steps=32", "train.checkpoint_interval=32", "logger=none",
                 "eval.gif=false", "train.progress_bar=false"]
    if name == "shac":
        overrides += ["loss.critic.hidden=[8]", "loss.critic_passes=2"]
    result = train_script.run(make_cfg("env=pendulum", f"loss={choice}", *overrides), tmp_path)
    assert result["env_steps"] == 32 and math.isfinite(result["eval/return"])


@pytest.mark.parametrize("loss, budget", [("bptt", 600_000), ("shac", 400_000), ("ppo", 500_000), ("sac", 15_000)])
def test_each_loss_carries_its_budget(loss, budget):
    cfg = make_cfg("env=swimmer", f"loss={loss}")
    assert cfg.train.total_env_steps == budget
    assert cfg.env.num_envs == (8 if loss == "sac" else 64)  # SAC: few envs, many updates per env step


def test_a_tuned_file_sets_env_options_of_the_training_envs():
    """configs/tuned/Hopper-v5_shac.yaml turns on the healthy bonus's surrogate gradient; the
    command line still wins."""
    from torchrl_diffenvs.training.config import make_env_from_config

    env = make_env_from_config(make_cfg("env=Hopper-v5", "loss=shac"), num_envs=2, seed=0)
    assert (env.healthy_gradient_width, env.healthy_gradient_scale) == (0.1, 30.0)
    env = make_env_from_config(make_cfg("env=Hopper-v5", "loss=shac", "env.options.healthy_gradient_scale=1"),
                               num_envs=2, seed=0)
    assert env.healthy_gradient_scale == 1.0
    assert make_env_from_config(make_cfg("env=Hopper-v5", "loss=ppo"), num_envs=2, seed=0).healthy_gradient_width == 0


def test_tuned_defaults_override_the_loss_defaults_but_not_the_command_line():
    from torchrl_diffenvs.learners import SHACConfig

    tuned = yaml.safe_load((CONFIGS / "tuned" / "pendulum_shac.yaml").read_text())
    horizon = tuned["loss"]["horizon"]
    assert horizon != SHACConfig().horizon
    assert make_cfg("env=pendulum", "loss=shac").loss.horizon == horizon
    assert make_cfg("env=pendulum", "loss=shac", "loss.horizon=3").loss.horizon == 3
    assert make_cfg("env=CartPole-v1", "loss=bptt").train.total_env_steps == 200_000  # a per-pair budget
    assert make_cfg("env=CartPole-v1", "loss=bptt", "train.total_env_steps=123").train.total_env_steps == 123


def test_unknown_env_or_loss_lists_the_valid_choices():
    with pytest.raises(MissingConfigException) as err:
        make_cfg("env=atari")
    assert all(name in str(err.value) for name in list_envs())
    with pytest.raises(MissingConfigException) as err:
        make_cfg("loss=dqn")
    assert all(name in str(err.value) for name in LOSSES)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["loss=bptt", "loss.actor_lr=-0.001"], "loss.actor_lr=-0.001: a learning rate must be a number > 0"),
        (["loss=ppo", "loss.lr=0"], "loss.lr=0: a learning rate must be a number > 0"),
        (["loss=shac", "loss.horizon=0"], "loss.horizon=0: expected an integer >= 1"),
        (["env.num_envs=0"], "env.num_envs=0: expected an integer >= 1"),
        (["loss=shac", "loss.gamma=1.5"], "loss.gamma=1.5: expected a number in (0.0, 1.0]"),
        (["env.name=atari"], "env.name='atari': unknown env; valid: " + ", ".join(list_envs())),
        (["mode=eval"], "mode=eval needs checkpoint="),
        (["mode=eval", "checkpoint=/nonexistent/last.pt"], "checkpoint='/nonexistent/last.pt': no such checkpoint"),
        (["resume=/nonexistent/last.pt"], "resume='/nonexistent/last.pt': no such checkpoint file"),
        (["logger.mode=sometimes"], "logger.mode='sometimes': valid: offline, online, disabled"),
        (["env=reacher", "env.options.num_links=0"], "num_links must be an integer >= 1"),
        (["env=pendulum", "+env.params.gravity=3"], "unknown physical parameter(s) ['gravity']"),
        (["device=tpu"], "device='tpu'"),
        (["loss=ppo", "loss.actor.distribution=deterministic"], "loss=ppo needs a stochastic policy"),
        (["loss=sac", "loss.actor.distribution=deterministic"], "loss=sac needs a stochastic policy"),
        (["loss=sac", "+loss.obs_norm=true"], "loss.obs_norm=true is not supported by loss=sac"),
        (["loss=sac", "loss.buffer_size=10", "loss.batch_size=64"], "loss.buffer_size=10 is smaller than"),
        (["loss=shac", "loss.critic.init=xavier"], "loss.critic.init='xavier': valid: default, orthogonal"),
        (["loss=shac", "loss.critic_shuffle=never"], "loss.critic_shuffle='never': valid: every_pass, once_per_window"),
        (["loss=bptt", "loss.grad_clip=value"], "loss.grad_clip='value': valid: norm, elementwise"),
        (["loss=bptt", "+loss.actor.widths=[3]"], "loss.actor.widths: unknown setting of ActorNetworkConfig; valid: hidden,"),
        (["loss=ppo", "loss.critic.hidden=[0]"], "loss.critic.hidden=[0]: expected a list of positive layer widths"),
        (["loss=shac", "loss.actor.activation=gelu"], "loss.actor.activation='gelu': valid: tanh, elu, relu"),
        (["+train.total_env_step=5"], "train.total_env_step: unknown setting of TrainSettings; valid: total_env_steps,"),
        (["eval.num_envs=2", "eval.gif_env_index=2"], "eval.gif_env_index=2: expected an integer in [0, eval.num_envs)"),
        (["distributed.timeout_s=0"], "distributed.timeout_s=0: expected a number > 0"),
    ],
)
def test_bad_configs_stop_before_training_with_a_clear_message(overrides, message):
    with pytest.raises(ConfigError) as err:
        train_script.validate_config(make_cfg(*overrides))
    assert message in str(err.value)


def test_all_problems_are_reported_at_once():
    cfg = make_cfg("loss=shac", "loss.actor_lr=-1", "loss.horizon=0", "env.num_envs=0")
    with pytest.raises(ConfigError, match=r"3 problems") as err:
        train_script.validate_config(cfg)
    assert "loss.actor_lr" in str(err.value) and "loss.horizon" in str(err.value) and "env.num_envs" in str(err.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_without_a_gpu_is_a_clear_error():
    with pytest.raises(ConfigError, match="torch.cuda.is_available.. is False"):
        train_script.validate_config(make_cfg("device=cuda"))


def test_merge_overrides_keeps_the_saved_run_and_lets_today_win():
    saved = ["env=swimmer", "loss=bptt", "loss.horizon=16", "resume=old.pt", "hydra.run.dir=x"]
    current = ["resume=new.pt", "train.total_env_steps=100", "loss.horizon=8"]
    assert merge_overrides(saved, current) == [
        "env=swimmer", "loss=bptt", "resume=new.pt", "train.total_env_steps=100", "loss.horizon=8",
    ]


# ---------------------------------------------------------------------- every env x loss trains
# every learner on every classic env and on HalfCheetah; the other MuJoCo tasks (their runs cost
# 10-40 s each) with a gradient learner and AHAC (which reads the contact force) through Hopper's
# falls, the Humanoid's and the Pusher's models, the Pusher with a TorchRL learner too: the learners'
# code paths are the same on every MuJoCo task
MUJOCO_LOSSES = {"HalfCheetah-v5": LOSSES, "Hopper-v5": ("shac", "ahac"), "Humanoid-v5": ("shac",),
                 "Pusher-v5": ("shac", "ahac", "ppo")}


@pytest.mark.parametrize("env,loss", [(env, loss) for env in classic_envs() for loss in LOSSES]
                         + [(env, loss) for env, losses in MUJOCO_LOSSES.items() for loss in losses])
def test_every_env_and_loss_trains_a_few_iterations(env, loss, tmp_path):
    if loss == "ahac" and env not in CONTACT_ENVS:
        with pytest.raises(ConfigError, match=f"loss=ahac: env '{env}' reports no contact force"):
            train_script.run(tiny_cfg(env, loss), tmp_path)
        return
    # the Humanoid's evaluations (its step costs 5x the others') on 6-step episodes
    extra = ["env.max_episode_steps=6"] if env == "Humanoid-v5" else []
    result = train_script.run(tiny_cfg(env, loss, 2, *extra), tmp_path)
    assert result["env_steps"] == 2 * STEPS_PER_ITER[loss] and result["iterations"] == 2
    assert math.isfinite(result["eval/return"]) and math.isfinite(result["eval/random_return"])
    rows = read_jsonl(tmp_path / "metrics.jsonl")
    train_rows = [r for r in rows if "train/reward" in r]
    assert [r["env_steps"] for r in train_rows] == [STEPS_PER_ITER[loss], 2 * STEPS_PER_ITER[loss]]
    assert all(math.isfinite(r["train/reward"]) and r["time/steps_per_s"] > 0 for r in train_rows)
    if loss != "sac":  # SAC's first updates wait for init_random_frames
        assert any(k.startswith("train/grad_norm") for k in train_rows[-1])
    assert (tmp_path / "checkpoints" / "last.pt").is_file()
    assert json.loads((tmp_path / "final_metrics.json").read_text())["eval/return"] == result["eval/return"]


def test_a_physical_parameter_override_is_saved_with_the_checkpoint(tmp_path):
    """``+env.params.X=v`` trains on the edited physics and the checkpoint's config keeps it: what
    evaluation, resume and the benchmarks that read a checkpoint (policy_anatomy) rebuild its env from."""
    run = train_script.run(tiny_cfg("pendulum", "bptt", 1, "+env.params.mass=2.5"), tmp_path)
    config = load_checkpoint(run["checkpoint"])["config"]
    assert config["env"]["params"] == {"mass": 2.5}
    env = make_env_from_config(OmegaConf.create(config), 2, seed=0)
    assert torch.all(env.params["mass"] == 2.5)


# ---------------------------------------------------------------------- logging
def read_wandb_history(run_file: Path) -> dict[str, list]:
    """Every logged value per key in an offline W&B run file (``run-<id>.wandb``).

    The file is W&B's 7-byte header followed by a LevelDB-style log (32 KiB blocks of records
    with a 7-byte header: crc32 (4), length (2), type (1: full, 2: first, 3: middle, 4: last)),
    each record one ``wandb_internal_pb2.Record`` protobuf.
    """
    from google.protobuf.message import DecodeError

    # W&B's service process may still be writing the file's tail after wandb.finish() returns (seen
    # once in CI under load: a half-written record): read again until the run's exit record is in
    deadline = time.monotonic() + 30
    while True:
        try:
            history, complete = _parse_wandb_log(run_file.read_bytes())
        except DecodeError:
            history, complete = None, False
        if complete or time.monotonic() > deadline:
            assert complete, f"{run_file} has no complete exit record after 30 s"
            return history
        time.sleep(0.5)


def _parse_wandb_log(data: bytes) -> tuple[dict[str, list], bool]:
    """``(history, whether the exit record was read)`` of a W&B run file's bytes."""
    from wandb.proto import wandb_internal_pb2

    assert data[:4] == b":W&B"
    block, pos, pending, history, complete = 32768, 7, b"", {}, False
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # the block's tail is padding
            pos += block - pos % block
            continue
        length, kind = int.from_bytes(data[pos + 4 : pos + 6], "little"), data[pos + 6]
        chunk, pos = data[pos + 7 : pos + 7 + length], pos + 7 + length
        if kind in (2, 3):
            pending = (pending if kind == 3 else b"") + chunk
            continue
        record = wandb_internal_pb2.Record()
        record.ParseFromString(pending + chunk if kind == 4 else chunk)
        record_type = record.WhichOneof("record_type")
        complete = complete or record_type == "exit"
        if record_type == "history":
            for item in record.history.item:
                key = item.key or "/".join(item.nested_key)
                history.setdefault(key, []).append(json.loads(item.value_json))
    return history, complete


def test_offline_wandb_run_writes_its_run_directory_with_the_metrics(tmp_path):
    cfg = tiny_cfg("pendulum", "bptt", 2, "logger=wandb", "eval.gif=true", "eval.learning_curve=true", "eval.gif_size=32")
    result = train_script.run(cfg, tmp_path)
    wandb_dir = Path(result["wandb_dir"])
    assert wandb_dir.parent == tmp_path / "wandb" and wandb_dir.name.startswith("offline-run-")
    (record_file,) = wandb_dir.glob("run-*.wandb")
    history = read_wandb_history(record_file)
    for _ in range(60):  # W&B's writer process may still be flushing when finish() returns on a busy machine
        if "eval/return" in history and len(history.get("train/loss_actor", [])) == 2:
            break
        time.sleep(0.5)
        history = read_wandb_history(record_file)
    assert history["eval/return"][-1] == pytest.approx(result["eval/return"])
    assert history["eval/step"][-1] == result["env_steps"]
    assert len(history["train/loss_actor"]) == 2 and "train/grad_norm_actor" in history
    assert any(wandb_dir.joinpath("files", "media", "videos").glob("final_gif_*.gif"))
    assert any(wandb_dir.joinpath("files", "media", "images").glob("learning_curve_*.png"))


def test_csv_logger_and_run_directory_outputs(tmp_path):
    pytest.importorskip("matplotlib")
    pytest.importorskip("PIL")
    from PIL import Image

    cfg = tiny_cfg("swimmer", "ppo", 2, "logger=csv", "eval.gif=true", "eval.learning_curve=true", "eval.gif_size=32", "eval.interval=16")
    result = train_script.run(cfg, tmp_path)
    scalars = tmp_path / "csv" / "swimmer_ppo_seed0" / "scalars"
    eval_rows = (scalars / "eval" / "return.csv").read_text().splitlines()
    assert [int(r.split(",")[0]) for r in eval_rows] == [0, 16, 32]  # at the start, every 16 steps, the end
    assert float(eval_rows[-1].split(",")[1]) == pytest.approx(result["eval/return"])
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"env_steps", "train/loss_objective", "train/grad_norm", "eval/return", "time/wall_s"} <= set(header)
    rows = read_jsonl(tmp_path / "metrics.jsonl")
    rss = [r["memory/rss_mib"] for r in rows if "train/loss_objective" in r]
    if sys.platform.startswith("linux"):  # the process's resident memory, from /proc
        import resource

        peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        assert rss and all(50 < m <= peak_mib + 1 for m in rss)
    with Image.open(tmp_path / "final.gif") as gif:
        assert gif.size == (32, 32) and gif.n_frames > 1
    assert (tmp_path / "learning_curve.png").stat().st_size > 0


def test_episode_returns_counts_only_the_first_episode():
    from tensordict import TensorDict

    reward = torch.tensor([[1.0, 2.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0]]).unsqueeze(-1)
    done = torch.tensor([[False, True, False, True], [False, False, False, False]]).unsqueeze(-1)
    rollout = TensorDict({"next": {"reward": reward, "done": done}}, batch_size=[2, 4])
    assert episode_returns(rollout).tolist() == [3.0, 4.0]


# ---------------------------------------------------------------------- checkpoints and resume
@pytest.mark.parametrize("loss", LOSSES)
def test_resumed_run_continues_exactly_where_the_stopped_run_was(loss, tmp_path):
    """Run A trains 4 iterations (checkpoints after 2 and 4); run B resumes A's 2-iteration
    checkpoint. B must end bit-identical to A: same step, same weights, same metrics, i.e. the
    same env states and random streams were restored."""
    steps = STEPS_PER_ITER[loss]
    extra = [f"train.checkpoint_interval={2 * steps}", f"eval.interval={2 * steps}"]
    env = "HalfCheetah-v5" if loss == "ahac" else "pendulum"  # AHAC needs an env that reports contact forces
    cfg = tiny_cfg(env, loss, 4, *extra)
    result_a = train_script.run(cfg, tmp_path / "a")
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * steps:012d}.pt"
    assert load_checkpoint(stopped)["progress"]["env_steps"] == 2 * steps

    result_b = train_script.run(tiny_cfg(env, loss, 4, *extra, f"resume={stopped}"), tmp_path / "b")
    assert result_b["env_steps"] == result_a["env_steps"] == 4 * steps
    assert result_b["iterations"] == 4
    final_a = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")
    final_b = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    for key, value in final_a["policy"].items():
        assert torch.equal(value, final_b["policy"][key]), key

    assert without_measurements(read_jsonl(tmp_path / "b" / "metrics.jsonl")) == \
        without_measurements(read_jsonl(tmp_path / "a" / "metrics.jsonl"))
    assert result_b["eval/return"] == result_a["eval/return"]


def test_the_wall_time_says_how_much_of_it_the_evaluations_took(tmp_path, monkeypatch):
    """Evaluations at env steps 0, 32 and 64 (the last after the final iteration, outside the wall
    time), each made 0.3 s slower: the two inside the wall time count, the final one does not."""
    from torchrl_diffenvs.training import loop

    original = loop.Trainer.evaluate

    def slow(self):
        time.sleep(0.3)
        return original(self)

    monkeypatch.setattr(loop.Trainer, "evaluate", slow)
    result = train_script.run(tiny_cfg("pendulum", "bptt", 4, "eval.interval=32", "train.log_interval=1",
                                       "train.checkpoint_interval=32"),
                              tmp_path / "a")
    assert 0.6 <= result["eval_time_s"] < result["wall_time_s"]
    rows = [r for r in read_jsonl(tmp_path / "a" / "metrics.jsonl") if "time/eval_s" in r]
    counted = [r["time/eval_s"] for r in rows]
    # after iterations 1-2 the evaluation at step 0 counts, from iteration 3 on also the one at 32
    assert [r["env_steps"] for r in rows] == [16, 32, 48, 64] and counted[0] == counted[1] < counted[2] == counted[3]
    assert 0.3 <= counted[0] < 0.6 <= counted[2] == result["eval_time_s"]
    # a resume from a checkpoint that did not count the evaluations: unknown, not zero
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{32:012d}.pt"
    state = load_checkpoint(stopped)
    del state["progress"]["eval_time_s"]
    torch.save(state, tmp_path / "old.pt")
    monkeypatch.setattr(loop, "load_checkpoint", lambda path, **kw: state)
    resumed = train_script.run(tiny_cfg("pendulum", "bptt", 4, "eval.interval=32", f"resume={tmp_path / 'old.pt'}"),
                               tmp_path / "b")
    assert math.isnan(resumed["eval_time_s"]) and resumed["env_steps"] == 64


def test_ctrl_c_keeps_the_last_checkpoint_and_closes_the_run(tmp_path, monkeypatch, caplog):
    from torchrl_diffenvs.learners import BPTTLearner

    calls = {"n": 0}
    original = BPTTLearner.train_iteration

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(BPTTLearner, "train_iteration", interrupted)
    cfg = tiny_cfg("pendulum", "bptt", 4, "train.checkpoint_interval=16")
    with pytest.raises(KeyboardInterrupt):
        train_script.run(cfg, tmp_path)
    last = tmp_path / "checkpoints" / "last.pt"
    assert load_checkpoint(last)["progress"]["env_steps"] == 32  # after iteration 2
    assert f"continue from env step 32 with resume={last}" in caplog.text
    assert (tmp_path / "metrics.csv").is_file()  # the logger was closed


def test_resume_with_a_different_env_or_learner_is_refused(tmp_path):
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "a")
    ckpt = tmp_path / "a" / "checkpoints" / "last.pt"
    with pytest.raises(ConfigError, match=r"loss.horizon: checkpoint 4, now 8"):
        train_script.run(tiny_cfg("pendulum", "bptt", 1, "loss.horizon=8", f"resume={ckpt}"), tmp_path / "b")


def test_eval_mode_loads_a_checkpoint_and_reproduces_the_final_evaluation(tmp_path):
    pytest.importorskip("PIL")
    from PIL import Image

    result = train_script.run(tiny_cfg("reacher", "shac", 2), tmp_path / "train")
    ckpt = tmp_path / "train" / "checkpoints" / "last.pt"
    # no env/loss overrides: both come from the checkpoint
    cfg = make_cfg("mode=eval", f"checkpoint={ckpt}", "eval.num_envs=2", "eval.gif_size=32", "logger=none")
    evaluation = train_script.run(cfg, tmp_path / "eval")
    assert evaluation["env"] == "reacher" and evaluation["loss"] == "shac"
    assert evaluation["eval/return"] == pytest.approx(result["eval/return"], rel=1e-6)
    assert evaluation["episode_lengths"] == [12, 12] and evaluation["eval/terminated"] == 0  # reacher only truncates
    assert result["eval/episode_length"] == 12 and result["eval/terminated"] == 0
    with Image.open(tmp_path / "eval" / "eval.gif") as gif:
        assert gif.n_frames > 1
    assert json.loads((tmp_path / "eval" / "eval_metrics.json").read_text())["eval_steps"] == 12


def test_a_failed_checkpoint_write_never_replaces_a_good_one(tmp_path, monkeypatch):
    path = tmp_path / "last.pt"
    save_checkpoint({"value": torch.tensor([1.0])}, path)

    def broken_save(obj, f, *args, **kwargs):
        f.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint({"value": torch.tensor([2.0])}, path)
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(path)["value"], torch.tensor([1.0]))
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]  # no temporary file left behind


def test_corrupt_truncated_or_foreign_checkpoints_give_clear_errors(tmp_path):
    good = save_checkpoint({"value": torch.arange(1000)}, tmp_path / "good.pt")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {}}, foreign)
    with pytest.raises(CheckpointError, match="not a checkpoint of sota_scripts/train.py"):
        load_checkpoint(foreign)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")


# ---------------------------------------------------------------------- command line, sweeps
def test_command_line_config_error_is_a_message_not_a_traceback(tmp_path, monkeypatch):
    with pytest.raises(SystemExit) as exit_info:
        _cli("loss=shac", "loss.horizon=0", "loss.actor_lr=-1", cwd=tmp_path, monkeypatch=monkeypatch)
    message = str(exit_info.value.code)
    assert message.startswith("error: invalid configuration (2 problems)")
    assert "loss.horizon=0" in message and "loss.actor_lr=-1" in message
    assert not list(tmp_path.rglob("checkpoints"))  # stopped before training


def test_command_line_resume_needs_only_the_checkpoint(tmp_path, monkeypatch):
    """``resume=<path>`` alone continues the run with the overrides it was started with."""
    steps = STEPS_PER_ITER["shac"]
    started = ["env=swimmer", "loss=shac", *COMMON, *TINY["shac"], f"train.total_env_steps={2 * steps}",
               f"train.checkpoint_interval={steps}", "train.keep_checkpoints=5"]
    _cli(*started, f"hydra.run.dir={tmp_path / 'a'}", cwd=tmp_path, monkeypatch=monkeypatch)
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{steps:012d}.pt"
    _cli(f"resume={stopped}", "train.total_env_steps=48", f"hydra.run.dir={tmp_path / 'b'}", cwd=tmp_path,
         monkeypatch=monkeypatch)
    result = json.loads((tmp_path / "b" / "final_metrics.json").read_text())
    assert (result["env"], result["loss"], result["env_steps"]) == ("swimmer", "shac", 48)  # today's budget wins
    assert load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")["config"]["loss"]["horizon"] == 4


def test_hydra_multirun_sweep_and_results_table(tmp_path, monkeypatch):
    sweep_dir = tmp_path / "sweep"
    tiny = COMMON + TINY["bptt"] + ["train.total_env_steps=32", "train.checkpoint_interval=32"]
    _cli("-m", "env=pendulum,cartpole", "loss=bptt", "seed=0,1", *tiny, f"hydra.sweep.dir={sweep_dir}",
         cwd=tmp_path, monkeypatch=monkeypatch)
    runs = sorted(sweep_dir.glob("*/final_metrics.json"))
    assert [p.parent.name for p in runs] == [
        "0_pendulum_bptt_seed0", "1_pendulum_bptt_seed1", "2_cartpole_bptt_seed0", "3_cartpole_bptt_seed1",
    ]
    table = results_table.main([f"dirs=[{sweep_dir}]", f"output={tmp_path / 'table.md'}"])
    assert (tmp_path / "table.md").read_text() == table
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line for line in table.splitlines()[2:]}
    assert len(rows) == len(list_envs()) * len(LOSSES)
    assert "| 2 | 32 |" in rows[("pendulum", "bptt")] and "| 2 | 32 |" in rows[("cartpole", "bptt")]
    assert "not run" in rows[("swimmer", "sac")]
    returns = [json.loads(p.read_text())["eval/return"] for p in runs if "pendulum" in p.parent.name]
    assert f"{sum(returns) / 2:.4g} +- " in rows[("pendulum", "bptt")]


@pytest.mark.parametrize("sweep_file", sorted((CONFIGS / "sweep").glob("*.yaml")), ids=lambda p: p.name)
def test_wandb_sweep_file_drives_the_same_script_through_hydra_overrides(sweep_file):
    sweep = yaml.safe_load(sweep_file.read_text())
    assert sweep["program"] == "sota_scripts/train.py"
    assert "${args_no_hyphens}" in sweep["command"]
    # what the W&B agent passes: one key=value per parameter
    overrides = []
    for key, spec in sweep["parameters"].items():
        value = spec["value"] if "value" in spec else spec["values"][0] if "values" in spec else spec["min"]
        overrides.append(f"{key}={value}")
    cfg = make_cfg(*overrides)
    train_script.validate_config(cfg)
    assert cfg.logger.mode == "online" and cfg.logger.backend == "wandb"
    assert sweep["metric"]["name"] == "eval/return"


@pytest.mark.parametrize("loss", LOSSES)
def test_composing_a_loss_gives_its_dataclass_defaults(loss):
    """``loss=<name>`` (no tuned file) is the learner's settings dataclass with its defaults, its
    network sections' defaults and its budget: the class is the one source of every default."""
    from torchrl_diffenvs.learners import LEARNERS

    learner = LEARNERS[loss]
    section = make_cfg("env=swimmer", f"loss={loss}", "~tuned").loss
    settings = {k: v for k, v in section.items() if k != "name" and k not in learner.networks}
    assert section.name == loss
    assert learner.config_class.from_mapping(settings) == learner.config_class()  # every field, its default
    assert set(settings) == {f.name for f in dataclasses.fields(learner.config_class)}
    for key, network in learner.networks.items():
        assert type(network).from_mapping(section[key]) == network
    cfg = make_cfg("env=swimmer", f"loss={loss}", "~tuned")
    for group, values in learner.run_defaults.items():
        for key, value in values.items():
            assert cfg[group][key] == value


def test_the_run_sections_are_their_dataclasses_defaults():
    """train / eval / selfplay / distributed come from torchrl_diffenvs.training.settings (the
    learner then sets its budget)."""
    from torchrl_diffenvs.learners import LEARNERS
    from torchrl_diffenvs.training.settings import RUN_SECTIONS

    cfg = make_cfg("env=swimmer", "loss=bptt", "~tuned")
    budget = LEARNERS["bptt"].run_defaults
    for section, settings in RUN_SECTIONS.items():
        expected = {**settings.defaults(), **budget.get(section, {})}
        assert OmegaConf.to_container(cfg[section]) == expected, section
        assert settings.from_mapping(expected) is not None  # the defaults pass their own checks
    assert not {"train", "eval", "selfplay", "distributed"} & set(OmegaConf.load(CONFIGS / "config.yaml"))


def test_tuned_files_hold_only_what_differs_from_the_defaults():
    """A tuned file that repeats a default is a second copy of it: each of its values must differ
    from what env=<env> loss=<loss> gives without it."""
    for path in sorted((CONFIGS / "tuned").glob("*.yaml")):
        env, _, loss = path.stem.rpartition("_")
        untuned = OmegaConf.to_container(make_cfg(f"env={env}", f"loss={loss}", "~tuned"))

        def walk(node, where):
            for key, value in node.items():
                if isinstance(value, dict):
                    walk(value, [*where, key])
                else:
                    default = untuned
                    for part in [*where, key]:
                        default = default.get(part) if isinstance(default, dict) else None
                    assert value != default, f"{path.name}: {'.'.join([*where, key])}={value} is the default"

        walk(yaml.safe_load(path.read_text()), [])


def test_score_to_win_stops_training_and_best_checkpoint_keeps_the_best_evaluation(tmp_path, caplog):
    """rl_games' score_to_win and save_best_after: the run stops at the first evaluation that reaches
    the score; checkpoints/best.pt holds the policy of the best evaluation so far."""
    caplog.set_level("INFO", logger="train")
    cfg = tiny_cfg("pendulum", "bptt", 8, "eval.interval=16", "train.save_best_after=0")
    result = train_script.run(cfg, tmp_path / "full")
    evals = [row["eval/return"] for row in read_jsonl(tmp_path / "full" / "metrics.jsonl") if "eval/return" in row]
    best = load_checkpoint(tmp_path / "full" / "checkpoints" / "best.pt")
    assert best["progress"]["best_eval_return"] == pytest.approx(max(evals))
    assert best["progress"]["env_steps"] == 16 * evals.index(max(evals))  # saved at that evaluation
    # a score reached at the second evaluation (env step 16) ends the run there
    target = evals[1] if evals[1] >= evals[0] else evals[0]
    stopped = train_script.run(tiny_cfg("pendulum", "bptt", 8, "eval.interval=16", f"train.score_to_win={target}"),
                               tmp_path / "won")
    assert stopped["env_steps"] == 16 * next(i for i, e in enumerate(evals) if e >= target) < result["env_steps"]
    assert "train.score_to_win" in caplog.text
    with pytest.raises(ConfigError, match="train.save_best_after=-1: expected an integer >= 0"):
        train_script.validate_config(make_cfg("train.save_best_after=-1"))
    with pytest.raises(ConfigError, match="train.score_to_win='high': expected a number"):
        train_script.validate_config(make_cfg("train.score_to_win=high"))


def test_player_mode_games_stochastic_actions_and_mp4(tmp_path, monkeypatch):
    """rl_games' player: mode=eval plays eval.games_num episodes (eval.num_envs at a time), with the
    mean action or sampled actions, and writes an MP4 (or a GIF when imageio-ffmpeg is missing)."""
    pytest.importorskip("PIL")
    from torchrl_diffenvs import rendering

    train_script.run(tiny_cfg("pendulum", "shac", 2), tmp_path / "train")
    ckpt = tmp_path / "train" / "checkpoints" / "last.pt"
    play = ["mode=eval", f"checkpoint={ckpt}", "eval.num_envs=2", "eval.gif_size=32", "logger=none"]
    five = train_script.run(make_cfg(*play, "eval.games_num=5", "eval.gif=false"), tmp_path / "five")
    two = train_script.run(make_cfg(*play, "eval.gif=false"), tmp_path / "two")
    assert five["games"] == 5 and two["games"] == 2
    # the first two of the five games are the two of a default evaluation (same seed, same envs)
    assert len(five["returns"]) == 5 and five["returns"][:2] == pytest.approx(two["returns"])
    assert five["eval/return"] == pytest.approx(sum(five["returns"]) / 5)
    sampled = train_script.run(make_cfg(*play, "eval.deterministic=false", "eval.gif=false"), tmp_path / "sampled")
    assert sampled["deterministic"] is False and sampled["eval/return"] != pytest.approx(two["eval/return"], abs=1e-9)
    if rendering.mp4_available():
        video = train_script.run(make_cfg(*play, "eval.video_format=mp4"), tmp_path / "mp4")["video"]
        assert video.endswith("eval.mp4") and b"ftyp" in Path(video).read_bytes()[:12]
    monkeypatch.setattr(rendering, "mp4_available", lambda: False)
    with pytest.warns(UserWarning, match="needs imageio-ffmpeg"):
        fallback = train_script.run(make_cfg(*play, "eval.video_format=mp4"), tmp_path / "fallback")["video"]
    assert fallback.endswith("eval.gif")
    with pytest.raises(ConfigError, match="eval.video_format='avi': valid: gif, mp4"):
        train_script.validate_config(make_cfg("eval.video_format=avi"))
    with pytest.raises(ConfigError, match="eval.games_num=0: expected an integer >= 1"):
        train_script.validate_config(make_cfg("eval.games_num=0"))
