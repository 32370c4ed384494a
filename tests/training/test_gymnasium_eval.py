"""Scoring in Gymnasium's own env: ``evaluate_in_gymnasium`` against a hand-run gymnasium loop,
``benchmarks/transfer.py`` on a checkpoint, and ``eval.gymnasium=true`` in the training script."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

gym = pytest.importorskip("gymnasium")
pytest.importorskip("mujoco")

from _env_helpers import REPO, load_script  # noqa: E402
from _train_helpers import make_cfg, results_table, tiny_cfg, train_script  # noqa: E402

from torchrl_diffenvs.evaluation import evaluate_in_gymnasium, gymnasium_kwargs  # noqa: E402
from torchrl_diffenvs.training.config import ConfigError  # noqa: E402


def _linear_policy(obs_dim: int, act_dim: int, seed: int = 0) -> TensorDictModule:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(obs_dim, act_dim), nn.Tanh()).double()
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def _hand_run(policy, env_id: str, episodes: int, seed: int, steps: int):
    returns, lengths = [], []
    for i in range(episodes):
        env = gym.make(env_id, max_episode_steps=steps)
        obs, _ = env.reset(seed=seed + i)
        total, length, done = 0.0, 0, False
        while not done:
            with torch.no_grad():
                action = policy.module(torch.as_tensor(obs, dtype=torch.float64)).numpy()
            obs, reward, terminated, truncated, _ = env.step(action)
            total, length, done = total + reward, length + 1, terminated or truncated
        returns.append(total)
        lengths.append(length)
    return returns, lengths


def test_evaluate_in_gymnasium_matches_a_hand_run_gymnasium_loop():
    # Hopper: some episodes end by a fall before the time limit, so the batch shrinks as they end
    policy = _linear_policy(11, 3)
    scores = evaluate_in_gymnasium(policy, "Hopper-v5", episodes=3, seed=7, steps=120, dtype=torch.float64)
    returns, lengths = _hand_run(policy, "Hopper-v5", 3, 7, 120)
    # the batched policy rounds as the one-at-a-time one up to a last bit
    assert scores["returns"] == pytest.approx(returns, rel=1e-12) and scores["lengths"] == lengths
    assert scores["return"] == pytest.approx(np.mean(returns), rel=1e-12)
    assert min(lengths) < 120 and scores["terminated"] > 0


def test_gymnasium_kwargs_keep_the_task_options_and_refuse_unknown_ones():
    assert gymnasium_kwargs("Ant-v5", {"include_cfrc_ext_in_observation": False, "contact": "mujoco",
                                       "contact_gradient": "cfd", "healthy_gradient_width": 0.1}) == \
        {"include_cfrc_ext_in_observation": False}
    with pytest.raises(ValueError, match="option 'wobble' has no counterpart in Gymnasium's env, which takes"):
        gymnasium_kwargs("Hopper-v5", {"wobble": 1})


# The training-script tests below run HalfCheetah (5 Euler evaluations per env step, against Hopper's
# 16 of RK4): what they check does not depend on the task; the falls are checked above
def test_transfer_benchmark_and_training_evaluation_in_gymnasium(tmp_path):
    result = train_script.run(tiny_cfg("HalfCheetah-v5", "shac", 1, "eval.gymnasium=true", "eval.num_envs=2",
                                       "eval.max_steps=20"), tmp_path / "run")
    assert np.isfinite(result["eval/gymnasium_return"])
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    logged = [r["eval/gymnasium_return"] for r in rows if "eval/gymnasium_return" in r]
    assert logged and logged[-1] == result["eval/gymnasium_return"]

    # the transfer benchmark plays the checkpoint's policy in both envs, as evaluate_in_gymnasium does
    transfer = load_script("transfer_bench", REPO / "benchmarks" / "transfer.py")
    policy, cfg, _ = transfer.policy_and_config(str(tmp_path / "run" / "checkpoints" / "last.pt"))
    out = transfer.transfer(policy, cfg, episodes=2, seed=5)
    direct = evaluate_in_gymnasium(policy, "HalfCheetah-v5", 2, 5, cfg.env.max_episode_steps)
    assert out["gymnasium"]["returns"] == direct["returns"] and out["contact"] == "mujoco"

    # mode=eval scores the checkpoint in Gymnasium's env too, on eval.num_envs episodes from eval.seed
    played = train_script.run(make_cfg("mode=eval", f"checkpoint={tmp_path / 'run' / 'checkpoints' / 'last.pt'}",
                                       "eval.num_envs=2", "eval.gif=false", "logger=none", "eval.gymnasium=true",
                                       "eval.seed=5"), tmp_path / "eval")
    assert played["eval/gymnasium_return"] == pytest.approx(direct["return"], rel=1e-12)
    saved = json.loads((tmp_path / "eval" / "eval_metrics.json").read_text())
    assert saved["eval/gymnasium_return"] == pytest.approx(direct["return"], rel=1e-12)


def test_only_gymnasium_scores_there_alone_and_picks_the_best_checkpoint_by_it(tmp_path):
    result = train_script.run(tiny_cfg("HalfCheetah-v5", "shac", 1, "eval.gymnasium=true", "eval.only_gymnasium=true",
                                       "eval.num_envs=2", "eval.max_steps=20", "train.save_best_after=0"),
                              tmp_path / "run")
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert not any("eval/return" in r or "eval/random_return" in r for r in rows)  # no evaluation of ours
    logged = [r["eval/gymnasium_return"] for r in rows if "eval/gymnasium_return" in r]
    assert len(logged) >= 2 and logged[-1] == result["eval/gymnasium_return"] and np.isnan(result["eval/return"])
    # the Gymnasium return decides the best checkpoint: best.pt holds the best of the logged ones
    best = torch.load(tmp_path / "run" / "checkpoints" / "best.pt", weights_only=False)
    assert best["progress"]["best_eval_return"] == max(logged)
    final = json.loads((tmp_path / "run" / "final_metrics.json").read_text())
    assert final["eval/return"] is None and "eval.only_gymnasium=true" in final["non_finite"]["eval/return"]
    table = results_table.main([f"dirs=[{tmp_path / 'run'}]", f"output={tmp_path / 'table.md'}"])
    assert f"{result['eval/gymnasium_return']:.4g}" in table  # the table reads the Gymnasium return there
    # ... and train.score_to_win: a bar any evaluation clears stops the run at its first one
    won = train_script.run(tiny_cfg("HalfCheetah-v5", "shac", 3, "eval.gymnasium=true", "eval.only_gymnasium=true",
                                    "eval.num_envs=2", "eval.max_steps=20", "train.score_to_win=-1e9"),
                           tmp_path / "won")
    assert won["env_steps"] == 0


def test_gymnasium_evaluation_config_errors():
    with pytest.raises(ConfigError, match="eval.only_gymnasium=true scores the policy only in Gymnasium's own env: "
                                          "it needs eval.gymnasium=true"):
        train_script.run(make_cfg("env=Hopper-v5", "loss=shac", "eval.only_gymnasium=true", "logger=none"),
                         "/tmp/unused")
    # Gymnasium's CartPole-v1 takes discrete actions, ours continuous ones
    with pytest.raises(ConfigError, match="Gymnasium's 'CartPole-v1' has actions Discrete\\(2\\)"):
        train_script.run(make_cfg("env=CartPole-v1", "loss=shac", "eval.gymnasium=true", "logger=none"), "/tmp/unused")
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        evaluate_in_gymnasium(_linear_policy(11, 3), "Hopper-v5", episodes=0)
    with pytest.raises(ConfigError, match="env 'swimmer' is not one of Gymnasium's registered envs"):
        train_script.run(make_cfg("env=swimmer", "loss=shac", "eval.gymnasium=true", "logger=none"), "/tmp/unused")
    with pytest.raises(ConfigError, match="env.params=.*change the physics"):
        train_script.run(make_cfg("env=Hopper-v5", "loss=shac", "eval.gymnasium=true", "logger=none",
                                  "+env.params.gravity=[0,0,-5]"), "/tmp/unused")
