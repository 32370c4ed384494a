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

from torchrl_diffenvs import make_env  # noqa: E402
from torchrl_diffenvs.evaluation import evaluate, evaluate_in_gymnasium, gymnasium_kwargs, start_states  # noqa: E402
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


def test_paired_start_states_play_the_same_episodes_in_both_envs():
    # Hopper in float64: MuJoCo's forward here, so from the same start both envs play the same episode
    env = make_env("Hopper-v5", num_envs=2, dtype=torch.float64, seed=0)
    policy = _linear_policy(11, 3, seed=2)
    policy.module[0].weight.data *= 3  # a policy whose hopper falls after about 20 steps
    qpos, qvel = start_states(env, seed=11)
    assert qpos.shape == (2, 6) and qvel.shape == (2, 6) and qpos.dtype == torch.float64
    ours = evaluate(env, policy, 30, seed=11, per_env=True)
    paired = evaluate_in_gymnasium(policy, "Hopper-v5", 2, seed=11, steps=30, dtype=torch.float64,
                                   start_states=(qpos, qvel))
    assert paired["lengths"] == ours["lengths"] and min(ours["lengths"]) < 30  # a fall, at the same step
    assert paired["returns"] == pytest.approx(ours["returns"], rel=1e-9)
    # ... which Gymnasium's own start states are not: the pairing is what makes them equal
    own = evaluate_in_gymnasium(policy, "Hopper-v5", 2, seed=11, steps=30, dtype=torch.float64)
    assert max(abs(a - b) for a, b in zip(own["returns"], ours["returns"])) > 1e-3
    # a hand-run loop that sets each start state after its reset, as Gymnasium's reset_model does
    for i in range(2):
        gym_env = gym.make("Hopper-v5", max_episode_steps=30)
        gym_env.reset(seed=11 + i)
        gym_env.unwrapped.set_state(qpos[i].numpy(), qvel[i].numpy())
        obs, total, done = gym_env.unwrapped._get_obs(), 0.0, False
        while not done:
            with torch.no_grad():
                action = policy.module(torch.as_tensor(obs, dtype=torch.float64)).numpy()
            obs, reward, terminated, truncated, _ = gym_env.step(action)
            total, done = total + reward, terminated or truncated
        assert paired["returns"][i] == pytest.approx(total, rel=1e-12)


def test_paired_start_states_refuse_what_is_not_a_mujoco_state():
    policy = _linear_policy(11, 3)
    with pytest.raises(ValueError, match=r"start_states of Hopper-v5 for 2 episodes are qpos \(2, 6\) and qvel "
                                         r"\(2, 6\), got \(3, 6\) and \(3, 6\)"):
        evaluate_in_gymnasium(policy, "Hopper-v5", 2, steps=5, start_states=(np.zeros((3, 6)), np.zeros((3, 6))))
    with pytest.raises(ValueError, match="Pendulum-v1 is not a MuJoCo env"):
        evaluate_in_gymnasium(_linear_policy(3, 1), "Pendulum-v1", 1, steps=5,
                              start_states=(np.zeros((1, 1)), np.zeros((1, 1))))
    with pytest.raises(ValueError, match="not MuJoCo's qpos and qvel"):
        start_states(make_env("Pendulum-v1", num_envs=2, seed=0), seed=0)


def test_transfer_rows_of_paired_episodes_give_the_per_episode_ratios():
    transfer = load_script("transfer_bench", REPO / "benchmarks" / "transfer.py")
    cfg = make_cfg("env=Hopper-v5", "loss=shac")
    ours = {"return": 200.0, "return_min": 100.0, "return_max": 300.0, "episode_length": 50.0, "returns": [100.0, 300.0]}
    theirs = {"return": 190.0, "return_min": 80.0, "return_max": 300.0, "episode_length": 48.0,
              "returns": [80.0, 300.0]}
    row = transfer.row(cfg, 1000, {"ours": ours, "gymnasium": theirs, "ratio": 0.95, "contact": "mujoco",
                                   "paired": True})
    assert len(row) == len(transfer.PAIRED_HEADERS)
    # per episode 0.8 and 1.0: median (torch's, the lower middle) 0.8; the largest gap 20
    assert row[6:] == ["0.95", "50", "48", "0.80 [0.80, 1.00]", "20"]


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
