"""``env.backend=gymnasium``: PPO and SAC trained on Gymnasium's own env (the baseline a user would
otherwise run). The adapter equals a hand-run ``gymnasium.make`` loop step for step; training
writes its final metrics; its evaluations are Gymnasium's own returns; a resumed run continues
exactly; gradient learners and unknown backends are refused with what is valid."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from _train_helpers import STEPS_PER_ITER, make_cfg, read_jsonl, tiny_cfg, train_script, without_measurements  # noqa: E402

from torchrl_diffenvs.envs.gymnasium_backend import GymnasiumBackedEnv  # noqa: E402
from torchrl_diffenvs.evaluation import evaluate_in_gymnasium  # noqa: E402
from torchrl_diffenvs.training import load_checkpoint  # noqa: E402
from torchrl_diffenvs.training.config import ConfigError  # noqa: E402

GYMNASIUM = ("env.backend=gymnasium",)


def test_the_env_equals_gymnasiums_own_env_step_for_step():
    # 12-step episodes inside a 30-step rollout: TorchRL's partial resets restart each env as
    # gymnasium's own reset() does (the env's random stream continues)
    num_envs, steps, seed = 3, 30, 7
    env = GymnasiumBackedEnv("HalfCheetah-v5", num_envs, seed=seed, max_episode_steps=12, dtype=torch.float64)
    # float32 numbers (Gymnasium's action space) played by a float64 policy
    actions = (torch.rand(num_envs, steps, 6, generator=torch.Generator().manual_seed(0)) * 2 - 1).double()
    t = iter(range(steps))

    def policy(td):
        return td.set("action", actions[:, next(t)])

    rollout = env.rollout(steps, policy, break_when_any_done=False)
    assert rollout["next", "done"].sum().item() == 2 * num_envs
    for i in range(num_envs):
        theirs = gym.make("HalfCheetah-v5", max_episode_steps=12)
        obs, _ = theirs.reset(seed=seed + i)
        for k in range(steps):
            assert np.array_equal(rollout["observation"][i, k].numpy(), obs), (i, k)
            # Gymnasium's env gets float32 actions (its action space's dtype), as a float32 policy writes
            obs, reward, terminated, truncated, _ = theirs.step(actions[i, k].float().numpy())
            assert np.array_equal(rollout["next", "observation"][i, k].numpy(), obs), (i, k)
            assert rollout["next", "reward"][i, k].item() == pytest.approx(reward, rel=1e-7, abs=1e-9)  # TorchRL's float32
            assert rollout["next", "terminated"][i, k].item() == terminated
            assert rollout["next", "truncated"][i, k].item() == truncated
            if terminated or truncated:
                obs, _ = theirs.reset()
        theirs.close()
    # set_seed restarts the same start states (an evaluation's contract)
    env.set_seed(seed)
    assert torch.equal(env.reset()["observation"], rollout["observation"][:, 0])
    env.close()


def test_ppo_trains_on_gymnasium_and_its_evaluation_is_gymnasiums_return(tmp_path):
    steps = 300  # a few hundred env steps: 16 per iteration
    cfg = tiny_cfg("HalfCheetah-v5", "ppo", steps // STEPS_PER_ITER["ppo"] + 1, *GYMNASIUM, "eval.gymnasium=true",
                   "eval.max_steps=40")
    result = train_script.run(cfg, tmp_path)
    final = json.loads((tmp_path / "final_metrics.json").read_text())
    assert final["env_steps"] >= steps and final["steps_per_s"] > 0
    assert final["eval/return"] == result["eval/return"] and np.isfinite(final["eval/return"])
    assert final["train/return"] is not None  # 12-step episodes finished during training
    # eval.gymnasium=true is this evaluation itself, not a second one
    assert final["eval/gymnasium_return"] == final["eval/return"]
    # ... and it is what evaluate_in_gymnasium scores (env i from eval.seed + i)
    from torchrl_diffenvs.learners import LEARNERS

    env = GymnasiumBackedEnv("HalfCheetah-v5", 1, max_episode_steps=12)
    policy = LEARNERS["ppo"].policy_from_config(cfg.loss, env)
    policy.load_state_dict(load_checkpoint(tmp_path / "checkpoints" / "last.pt")["policy"])
    theirs = evaluate_in_gymnasium(policy, "HalfCheetah-v5", cfg.eval.num_envs, cfg.eval.seed, 12)  # episodes of 12
    assert final["eval/return"] == pytest.approx(theirs["return"], rel=1e-5)  # TorchRL's float32 rewards
    # mode=eval plays the checkpoint in Gymnasium's env again (the backend is in its env section)
    replay = train_script.run(make_cfg("mode=eval", f"checkpoint={tmp_path / 'checkpoints' / 'last.pt'}",
                                       "logger=none", "eval.gif=false", "eval.num_envs=2", "eval.max_steps=40",
                                       "eval.gymnasium=true"), tmp_path / "eval")
    assert replay["eval/return"] == replay["eval/gymnasium_return"]
    assert replay["eval/return"] == pytest.approx(final["eval/return"], rel=1e-6)  # summed in float32 there


def test_a_resumed_run_continues_exactly(tmp_path):
    steps = STEPS_PER_ITER["ppo"]
    extra = (*GYMNASIUM, f"train.checkpoint_interval={2 * steps}", "eval.interval=32", "env.max_episode_steps=6")
    result_a = train_script.run(tiny_cfg("HalfCheetah-v5", "ppo", 4, *extra), tmp_path / "a")
    stopped = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * steps:012d}.pt"
    result_b = train_script.run(tiny_cfg("HalfCheetah-v5", "ppo", 4, *extra, f"resume={stopped}"), tmp_path / "b")
    final_a = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.pt")
    final_b = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.pt")
    for key, value in final_a["policy"].items():
        assert torch.equal(value, final_b["policy"][key]), key

    assert without_measurements(read_jsonl(tmp_path / "b" / "metrics.jsonl")) == \
        without_measurements(read_jsonl(tmp_path / "a" / "metrics.jsonl"))
    assert result_b["eval/return"] == result_a["eval/return"]


@pytest.mark.parametrize("loss", ["shac", "bptt"])
def test_a_gradient_learner_is_refused(loss):
    with pytest.raises(ConfigError, match=f"loss={loss} needs a differentiable env .* train loss=ppo or loss=sac"):
        train_script.validate_config(tiny_cfg("HalfCheetah-v5", loss, 1, *GYMNASIUM))


def test_sac_is_accepted():
    train_script.validate_config(tiny_cfg("HalfCheetah-v5", "sac", 1, *GYMNASIUM))


@pytest.mark.parametrize(("overrides", "message"), [
    (["env.backend=mujoco"], r"env.backend='mujoco': unknown backend; valid: torchrl_diffenvs .*, gymnasium"),
    ([*GYMNASIUM, "+env.params.mass=2"], "env.backend=gymnasium: env.params=.* drop env.params"),
    ([*GYMNASIUM, "compile=true"], "compile=true: env.backend=gymnasium .* drop compile=true"),
])
def test_bad_backend_settings_are_clear_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        train_script.validate_config(tiny_cfg("HalfCheetah-v5", "ppo", 1, *overrides))


def test_a_task_gymnasium_does_not_have_is_refused():
    with pytest.raises(ConfigError, match="env 'swimmer' is not one of Gymnasium's registered envs"):
        train_script.validate_config(tiny_cfg("swimmer", "ppo", 1, *GYMNASIUM))
    with pytest.raises(ConfigError, match="Gymnasium's 'CartPole-v1' takes Discrete.* continuous actions"):
        train_script.validate_config(tiny_cfg("CartPole-v1", "ppo", 1, *GYMNASIUM))
