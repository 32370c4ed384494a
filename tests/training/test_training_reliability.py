"""Run reliability of the training loop: checkpoints that cannot be silently altered and do not
grow with the run, clean stops on SIGTERM / Ctrl-C, one-line errors for bad inputs, strict JSON,
a learning-rate schedule without a jump on resume, and finite physical parameters.

Each test drives ``sota_scripts/train.py`` the way a user does (its ``run`` / ``main``), on tiny
runs (4 envs, 12-step episodes).
"""
from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path

import pytest
import torch

from _train_helpers import COMMON, STEPS_PER_ITER, TINY, _cli, make_cfg, read_jsonl, tiny_cfg, train_script, without_measurements
from torchrl_diffenvs.learners import BPTTLearner
from torchrl_diffenvs.learners.base import load_lr_scheduler, lr_scheduler
from torchrl_diffenvs.training import (
    CheckpointError,
    ConfigError,
    TrainingInterrupted,
    load_checkpoint,
    save_checkpoint,
)

STEPS = STEPS_PER_ITER["bptt"]  # 16 env steps per iteration


def _strict_json(path: Path) -> dict:
    """Parses ``path`` as strict JSON: NaN / Infinity are not JSON."""
    def refuse(constant):
        raise ValueError(f"{path.name} holds {constant}, which is not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


# ---------------------------------------------------------------------- checkpoints: checksum
def _flip_inside_a_tensor(path: Path, tensor: torch.Tensor) -> None:
    """Flips one byte in the middle of ``tensor``'s data inside the checkpoint file (the zip
    container stays readable: its records are stored, not compressed)."""
    data = bytearray(path.read_bytes())
    raw = tensor.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes()
    at = data.find(raw)
    assert at >= 0, "the tensor's bytes are stored as they are"
    data[at + len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def test_a_checkpoint_with_a_flipped_byte_inside_a_tensor_is_refused_on_resume_and_eval(tmp_path):
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "a")
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    weight = next(v for k, v in load_checkpoint(last)["policy"].items() if v.numel() >= 16)
    _flip_inside_a_tensor(last, weight)
    # torch itself loads the altered file without complaint: only the checksum notices
    assert torch.load(last, weights_only=True)["format"]
    with pytest.raises(CheckpointError, match="is corrupt: its content does not match the checksum"):
        load_checkpoint(last)
    with pytest.raises(CheckpointError, match="is corrupt"):
        train_script.run(tiny_cfg("pendulum", "bptt", 2, f"resume={last}"), tmp_path / "b")
    with pytest.raises(CheckpointError, match="is corrupt"):
        train_script.run(make_cfg("mode=eval", f"checkpoint={last}", "logger=none", "eval.gif=false"), tmp_path / "c")


def test_checksum_covers_every_value_and_ignores_the_device(tmp_path):
    state = {"w": torch.arange(6.0).reshape(2, 3), "n": 3, "nested": {"t": torch.ones(2, dtype=torch.uint8)}}
    path = save_checkpoint(state, tmp_path / "x.pt")
    assert torch.equal(load_checkpoint(path)["w"], state["w"])
    raw = torch.load(path, weights_only=True)
    raw["n"] = 4  # a changed number (not a tensor) is caught too
    torch.save(raw, path)
    with pytest.raises(CheckpointError, match="is corrupt"):
        load_checkpoint(path)


# ---------------------------------------------------------------------- checkpoints: temp files, size
def test_temp_files_of_interrupted_writes_are_removed_at_the_next_start(tmp_path):
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "a")
    ckpt_dir = tmp_path / "a" / "checkpoints"
    dead_pid = 2**22 + 12345  # above Linux's pid_max default: no such process
    stale = [ckpt_dir / f".last.pt.tmp-{dead_pid}", ckpt_dir / f".ckpt_000000000016.pt.tmp-{dead_pid}"]
    for path in stale:
        path.write_bytes(b"half a checkpoint")
    alive = ckpt_dir / f".last.pt.tmp-{os.getppid()}"  # a live writer's file stays
    alive.write_bytes(b"being written")
    train_script.run(tiny_cfg("pendulum", "bptt", 2, f"resume={ckpt_dir / 'last.pt'}"), tmp_path / "b")
    assert not any(path.exists() for path in stale) and alive.exists()
    # a fresh start in a run directory with leftovers cleans it too
    (tmp_path / "c" / "checkpoints").mkdir(parents=True)
    leftover = tmp_path / "c" / "checkpoints" / f".last.pt.tmp-{dead_pid}"
    leftover.write_bytes(b"x")
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "c")
    assert not leftover.exists()


def test_checkpoint_size_does_not_grow_with_the_run_and_resume_keeps_the_history(tmp_path):
    """The logged history lives in the run directory's metrics.jsonl, not in every checkpoint."""
    cfg = tiny_cfg("pendulum", "bptt", 40, f"train.checkpoint_interval={2 * STEPS}", "train.keep_checkpoints=100",
                   "eval.interval=32")
    train_script.run(cfg, tmp_path / "a")
    ckpt_dir = tmp_path / "a" / "checkpoints"
    early, late = ckpt_dir / f"ckpt_{2 * STEPS:012d}.pt", ckpt_dir / f"ckpt_{40 * STEPS:012d}.pt"
    assert "history" not in load_checkpoint(late)
    # 38 more iterations logged 38 more rows of ~6 metrics: with the rows inside, the file grew by kilobytes
    assert abs(late.stat().st_size - early.stat().st_size) < 512, (early.stat().st_size, late.stat().st_size)
    # a resumed run's metrics.jsonl still starts with the rows before the checkpoint
    middle = ckpt_dir / f"ckpt_{20 * STEPS:012d}.pt"
    train_script.run(tiny_cfg("pendulum", "bptt", 40, f"train.checkpoint_interval={2 * STEPS}", "eval.interval=32",
                              f"resume={middle}"), tmp_path / "b")

    rows_a, rows_b = read_jsonl(tmp_path / "a" / "metrics.jsonl"), read_jsonl(tmp_path / "b" / "metrics.jsonl")
    assert without_measurements(rows_b) == without_measurements(rows_a)


# ---------------------------------------------------------------------- SIGTERM and Ctrl-C
def _signal_at_iteration(monkeypatch, n: int, signum: int) -> None:
    calls = {"n": 0}
    original = BPTTLearner.train_iteration

    def iteration(self):
        calls["n"] += 1
        metrics = original(self)
        if calls["n"] == n:
            os.kill(os.getpid(), signum)  # arrives while the iteration is still running
        return metrics

    monkeypatch.setattr(BPTTLearner, "train_iteration", iteration)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_ctrl_c_write_a_checkpoint_and_the_resumed_run_ends_as_an_uninterrupted_one(
        tmp_path, monkeypatch, caplog, signum):
    full = train_script.run(tiny_cfg("pendulum", "bptt", 6), tmp_path / "full")
    _signal_at_iteration(monkeypatch, 3, signum)
    with pytest.raises(TrainingInterrupted) as err:
        train_script.run(tiny_cfg("pendulum", "bptt", 6), tmp_path / "a")
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    assert load_checkpoint(last)["progress"]["env_steps"] == 3 * STEPS  # written after the signal's iteration
    assert f"resume={last}" in str(err.value) and f"resume={last}" in caplog.text
    assert err.value.exit_code == 128 + signum
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the handlers are given back
    monkeypatch.undo()
    resumed = train_script.run(tiny_cfg("pendulum", "bptt", 6, f"resume={last}"), tmp_path / "b")
    assert resumed["eval/return"] == full["eval/return"] and resumed["env_steps"] == 6 * STEPS


def test_sigterm_on_the_command_line_exits_with_the_hint_and_no_traceback(tmp_path, monkeypatch, caplog):
    _signal_at_iteration(monkeypatch, 2, signal.SIGTERM)
    steps = 4 * STEPS
    with pytest.raises(SystemExit) as exit_info:
        _cli("env=pendulum", "loss=bptt", *COMMON, *TINY["bptt"], f"train.total_env_steps={steps}",
             f"train.checkpoint_interval={steps}", f"hydra.run.dir={tmp_path / 'a'}", cwd=tmp_path,
             monkeypatch=monkeypatch)
    assert exit_info.value.code == 128 + signal.SIGTERM  # a plain exit status: Python prints no traceback
    (log_file,) = (tmp_path / "a").glob("*.log")  # Hydra's copy of the console
    assert f"continue with resume={tmp_path / 'a' / 'checkpoints' / 'last.pt'}" in log_file.read_text()
    assert load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")["progress"]["env_steps"] == 2 * STEPS


# ---------------------------------------------------------------------- bad inputs: one-line errors
def test_resume_of_a_missing_file_or_a_directory_is_a_one_line_error(tmp_path, monkeypatch):
    with pytest.raises(SystemExit) as missing:
        _cli(f"resume={tmp_path / 'nope.pt'}", cwd=tmp_path, monkeypatch=monkeypatch)
    message = str(missing.value.code)
    assert message.startswith("error: resume=") and "no such checkpoint file; valid:" in message
    assert "\n" not in message
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "run")
    with pytest.raises(SystemExit) as directory:
        _cli(f"resume={tmp_path / 'run'}", cwd=tmp_path, monkeypatch=monkeypatch)
    message = str(directory.value.code)
    assert "is a directory; valid: a checkpoint file" in message
    assert f"resume={tmp_path / 'run' / 'checkpoints' / 'last.pt'}" in message and "\n" not in message
    with pytest.raises(CheckpointError, match="is a directory, not a checkpoint file"):
        load_checkpoint(tmp_path / "run")


def test_an_unknown_tuned_choice_is_an_error_not_the_defaults(tmp_path, monkeypatch):
    with pytest.raises(SystemExit) as err:
        _cli("env=pendulum", "loss=shac", "tuned=pendulum_shac_fast", cwd=tmp_path, monkeypatch=monkeypatch)
    message = str(err.value.code)
    assert message.startswith("error: tuned='pendulum_shac_fast': no such tuned config; valid: ")
    assert "pendulum_shac" in message and "Hopper-v5_ppo" in message
    assert not list(tmp_path.rglob("checkpoints"))


def test_eval_of_a_checkpoint_on_another_env_is_refused(tmp_path, monkeypatch):
    train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path / "train")
    last = tmp_path / "train" / "checkpoints" / "last.pt"
    overrides = ["mode=eval", f"checkpoint={last}", "env=cartpole", "logger=none", "eval.gif=false"]
    with pytest.raises(ConfigError, match="holds a policy trained on env=pendulum, not env=cartpole"):
        train_script.run(make_cfg(*overrides), tmp_path / "eval", overrides)
    with pytest.raises(SystemExit) as err:
        _cli(*overrides, cwd=tmp_path, monkeypatch=monkeypatch)
    assert "trained on env=pendulum, not env=cartpole; drop env=" in str(err.value.code)
    # naming the checkpoint's own env is fine, and env.<key>= changes the checkpoint's env (not the default env's)
    same = ["mode=eval", f"checkpoint={last}", "env=pendulum", "logger=none", "eval.gif=false", "eval.num_envs=2"]
    plain = train_script.run(make_cfg(*same), tmp_path / "same", same)
    heavier = [*same, "+env.params.mass=3.0"]
    changed = train_script.run(make_cfg(*heavier), tmp_path / "heavier", heavier)
    assert plain["env"] == changed["env"] == "pendulum" and plain["env_overrides"] == {}
    assert changed["env_overrides"] == {"env.params.mass": 3.0} and changed["eval/return"] != plain["eval/return"]
    bogus = ["mode=eval", f"checkpoint={last}", "logger=none", "eval.gif=false", "env.max_episode_steps=0"]
    with pytest.raises(ConfigError, match="env.max_episode_steps=0: expected an integer >= 1"):
        train_script.run(make_cfg(*bogus), tmp_path / "bogus", bogus)


@pytest.mark.parametrize("override, shown", [("+env.params.mass=nan", "nan"), ("+env.params.g=inf", "inf"),
                                             ("+env.params.length=-inf", "-inf")])
def test_non_finite_physical_parameters_are_refused_at_configuration_time(override, shown):
    with pytest.raises(ConfigError) as err:
        train_script.validate_config(make_cfg("env=pendulum", override))
    key = override.split("=")[0].lstrip("+")
    assert f"{key}={shown}: physical parameters must be finite numbers (not nan or inf)" in str(err.value)
    train_script.validate_config(make_cfg("env=pendulum", "+env.params.mass=2.0"))  # finite values pass


# ---------------------------------------------------------------------- final_metrics.json
def test_final_metrics_json_is_strict_json_when_the_evaluation_is_nan(tmp_path, monkeypatch):
    from torchrl_diffenvs.training import loop

    real = loop.evaluate
    monkeypatch.setattr(loop, "evaluate", lambda *a, **k: {**real(*a, **k), "return": math.nan})
    result = train_script.run(tiny_cfg("pendulum", "bptt", 1), tmp_path)
    assert math.isnan(result["eval/return"])  # the Python result keeps the float
    saved = _strict_json(tmp_path / "final_metrics.json")
    assert saved["eval/return"] is None and saved["non_finite"]["eval/return"].startswith("nan: ")
    # no training episode finished in 4 steps of 12-step episodes: said so, not a bare NaN
    assert saved["train/return"] is None and "no training episode finished" in saved["non_finite"]["train/return"]
    assert saved["env_steps"] == STEPS


# ---------------------------------------------------------------------- learning rate across a resume
def _schedule(total: int, min_lr: float = 1e-3):
    param = torch.nn.Parameter(torch.zeros(1))
    optim = torch.optim.Adam([param], lr=1e-1)
    box = {"total": total}
    return optim, lr_scheduler(optim, "linear", lambda: box["total"], min_lr=min_lr), box


def test_linear_schedule_resumed_with_a_larger_budget_continues_from_its_rate_to_min_lr():
    optim, schedule, _ = _schedule(total=10)
    for _ in range(4):
        schedule.step()
    before = optim.param_groups[0]["lr"]
    assert before == pytest.approx(0.1 - 4 / 10 * (0.1 - 1e-3))  # hand-computed: 4 of 10 steps down the line
    state = {"optim": optim.state_dict(), "schedule": schedule.state_dict()}

    optim2, schedule2, _ = _schedule(total=20)  # the same run, resumed with twice the budget
    optim2.load_state_dict(state["optim"])
    load_lr_scheduler(schedule2, state["schedule"])
    assert optim2.param_groups[0]["lr"] == pytest.approx(before, rel=1e-12)  # no jump
    lrs = []
    for _ in range(20):
        schedule2.step()
        lrs.append(optim2.param_groups[0]["lr"])
    # from `before` at iteration 4 straight to min_lr at iteration 20, then held
    expected = [before + (1e-3 - before) * min((i - 4) / 16, 1.0) for i in range(5, 25)]
    assert lrs == pytest.approx(expected, rel=1e-12)
    # a second resume keeps the new line
    state2 = schedule2.state_dict()
    optim3, schedule3, _ = _schedule(total=20)
    optim3.load_state_dict(optim2.state_dict())
    load_lr_scheduler(schedule3, state2)
    assert optim3.param_groups[0]["lr"] == pytest.approx(lrs[-1], rel=1e-12)


def test_resume_with_the_same_budget_keeps_the_schedule_exactly():
    optim, schedule, _ = _schedule(total=10)
    for _ in range(3):
        schedule.step()
    optim2, schedule2, _ = _schedule(total=10)
    optim2.load_state_dict(optim.state_dict())
    load_lr_scheduler(schedule2, schedule.state_dict())
    for _ in range(9):
        schedule.step()
        schedule2.step()
        assert optim2.param_groups[0]["lr"] == optim.param_groups[0]["lr"]  # bit-identical


def test_a_run_resumed_with_a_larger_budget_has_no_learning_rate_jump(tmp_path):
    train_script.run(tiny_cfg("pendulum", "bptt", 4, f"train.checkpoint_interval={2 * STEPS}",
                              "train.keep_checkpoints=5"), tmp_path / "a")
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * STEPS:012d}.pt"
    before = load_checkpoint(stopped)["learner"]["actor_optimizer"]["param_groups"][0]["lr"]
    train_script.run(tiny_cfg("pendulum", "bptt", 8, f"resume={stopped}"), tmp_path / "b")
    rows = [r for r in read_jsonl(tmp_path / "b" / "metrics.jsonl") if "train/lr_actor" in r]
    after = [r["train/lr_actor"] for r in rows if r["env_steps"] > 2 * STEPS]
    assert after[0] == pytest.approx(before, rel=1e-6)  # the first iteration after the resume
    assert all(b < a for a, b in zip(after, after[1:]))  # and down from there
