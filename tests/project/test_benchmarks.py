"""Every benchmark script runs in --quick mode and writes a well-formed JSON result.

The benchmarks measure (benchmarks/, docs/performance.md); this only checks that
they run end to end and report what they claim, in seconds, in-process.
"""
import json
import math
from pathlib import Path

import pytest
import torch
from _env_helpers import load_script

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def load(name: str):
    return load_script(f"benchmark_{name}", BENCHMARKS / f"{name}.py")


@pytest.fixture(autouse=True)
def keep_torch_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def positive_rates(candidates: dict) -> None:
    for name, c in candidates.items():
        spread = c["env_steps_per_s_cpu"]
        assert 0 < spread["min"] <= spread["median"] <= spread["max"] < math.inf, name


def test_env_throughput_quick(tmp_path):
    out = tmp_path / "env.json"
    payload = load("env_throughput").main(["quick=true", f"out={out}"])
    assert json.loads(out.read_text())["benchmark"] == "env_throughput"
    assert payload["info"]["torch_threads"] == 1
    rows = {row["task"]: row for row in payload["results"]}
    assert set(rows) == {"pendulum", "Pendulum-v1", "CartPole-v1"}
    assert {"ours", "EnvBase.rollout", "raw", "raw + resets", "raw by hand", "torchrl PendulumEnv"} <= set(
        rows["pendulum"]["candidates"])
    assert {"gymnasium SyncVectorEnv", "gymnasium vectorised CartPole"} <= set(rows["CartPole-v1"]["candidates"])
    for row in payload["results"]:
        positive_rates(row["candidates"])
        assert set(row["ratios_cpu"]) == {f"ours / {name}" for name in row["candidates"] if name != "ours"}


def test_env_throughput_with_a_policy_quick(tmp_path):
    payload = load("env_throughput").main(["quick=true", "tasks=[pendulum]", "gym=false", "policy=true",
                                           f"out={tmp_path / 'env.json'}"])
    (row,) = payload["results"]
    assert {"ours + policy", "raw + policy"} <= set(row["candidates"])
    assert row["ratios_cpu"]["ours + policy / raw + policy"] > 0
    assert payload["info"]["device"] == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_benchmarks_refuse_cuda_without_a_gpu(tmp_path):
    with pytest.raises(SystemExit, match=r"device='cuda': torch.cuda.is_available\(\) is False"):
        load("env_throughput").main(["quick=true", "device=cuda", f"out={tmp_path / 'env.json'}"])
    with pytest.raises(SystemExit, match="device='tpu': expected cpu, cuda or cuda:<index>"):
        load("jax_comparison").main(["quick=true", "device=tpu", f"out={tmp_path / 'jax.json'}"])


def test_gradient_throughput_quick(tmp_path):
    payload = load("gradient_throughput").main(["quick=true", f"out={tmp_path / 'grad.json'}"])
    assert [(r["mode"], r["H"], r["N"]) for r in payload["results"]] == [("policy", 4, 2), ("open-loop", 4, 2)]
    for row in payload["results"]:
        positive_rates(row["candidates"])
        memory = row["memory"]
        # the rollouts keep at least what the raw loop keeps, plus their TensorDict
        assert memory["ours"]["held_bytes_per_env_step"] > memory["raw"]["saved_bytes_per_env_step"] > 0
        assert memory["ours"]["held_bytes_per_env_step"] >= memory["ours"]["saved_bytes_per_env_step"]


def test_time_to_solve_quick(tmp_path):
    payload = load("time_to_solve").main(["quick=true", f"out={tmp_path / 'tts.json'}"])
    assert [(r["env"], r["loss"]) for r in payload["summary"]] == [("pendulum", l) for l in ("shac", "bptt", "ppo", "sac")]
    for run in payload["runs"]:
        assert run["env_steps"] >= 32 and run["curve"], run["loss"]
        assert run["curve"][0][0] == 0  # evaluated before training
    ppo = next(r for r in payload["summary"] if r["loss"] == "ppo")
    assert set(ppo["levels"]) == {1.0, 0.95, 0.9}
    assert ppo["levels"][1.0]["reached"] == "1/1" and ppo["levels"][1.0]["time_s"] <= ppo["wall_s"]["max"]
    # each level is that fraction of the way from the random policy's return to PPO's final one
    # (a 32-step run may end below the random policy: the levels then fall the other way)
    random_return, final = ppo["random_return"], ppo["final_return"]["median"]
    for fraction in (1.0, 0.95, 0.9):
        assert ppo["levels"][fraction]["return"] == pytest.approx(random_return + fraction * (final - random_return))


def test_time_to_solve_variants_and_fixed_levels(tmp_path):
    tts = load("time_to_solve")
    payload = tts.main(["quick=true", "losses=[shac]", 'variant=["default=","fast=loss.actor_lr=2e-2"]',
                        "levels=[0,1e9]", f"out={tmp_path / 'tts.json'}"])
    assert [r["loss"] for r in payload["summary"]] == ["shac:default", "shac:fast"]
    assert [r["variant"] for r in payload["runs"]] == ["default", "fast"]
    assert "loss.actor_lr=2e-2" in payload["runs"][1]["overrides"]
    assert "loss.actor_lr=2e-2" not in payload["runs"][0]["overrides"]
    for row in payload["summary"]:
        assert row["levels"] == {}  # no PPO run: no PPO-relative levels
        assert row["fixed_levels"][0.0]["reached"] == "1/1" and row["fixed_levels"][0.0]["time_s"] == 0.0  # rewards >= 0
        assert row["fixed_levels"][1e9]["reached"] == "0/1" and math.isinf(row["fixed_levels"][1e9]["time_s"])
    with pytest.raises(SystemExit, match="LABEL=OVERRIDES"):
        tts.parse_variants(["no-label"])
    with pytest.raises(SystemExit, match="must be distinct"):
        tts.parse_variants(["a=x=1", "a=y=2"])


def test_benchmark_arguments_are_checked_like_the_training_scripts():
    tts = load("time_to_solve")
    with pytest.raises(SystemExit, match=r"losses=\['dqn'\]: element 'dqn': valid: shac, bptt, ppo, sac"):
        tts.main(["losses=[dqn]"])
    with pytest.raises(SystemExit, match="unknown argument '--quick'"):
        tts.main(["--quick"])
    with pytest.raises(SystemExit, match="threads=3: valid: 1, 2"):
        load("env_throughput").main(["threads=3"])


def test_mujoco_throughput_quick(tmp_path):
    pytest.importorskip("mujoco")
    payload = load("mujoco_throughput").main(["quick=true", "tasks=[Hopper-v5]", f"out={tmp_path / 'mj.json'}"])
    assert [(r["task"], r["N"]) for r in payload["results"]] == [("Hopper-v5", 1), ("Hopper-v5", 4)]
    for row in payload["results"]:
        positive_rates(row["candidates"])
        assert {"ours", "ours fwd+bwd", "gymnasium", "mj_step (C)", "gymnasium SyncVectorEnv"} == set(row["candidates"])
        assert set(row["ratios_cpu"]) == {f"ours / {name}" for name in row["candidates"] if name != "ours"}


def test_jax_comparison_quick(tmp_path):
    """Runs with or without the bench extra: without jax/gymnax the JAX columns are skipped, with a note."""
    bench = load("jax_comparison")
    payload = bench.main(["quick=true", "tasks=[Pendulum-v1,swimmer]", f"out={tmp_path / 'jax.json'}"])
    kinds = [(r["kind"], r["task"]) for r in payload["results"]]
    assert kinds == [("forward", "Pendulum-v1"), ("forward", "swimmer"), ("BPTT", "Pendulum-v1")]
    pendulum = payload["results"][0]["candidates"]
    assert {"ours", "raw torch"} <= set(pendulum)
    if bench.jax_available() is None:
        assert payload["jax_skipped"] is None
        assert {"gymnax", "raw JAX"} <= set(pendulum)
        assert "JAX value_and_grad" in payload["results"][2]["candidates"]
    else:
        assert "pip install" in payload["jax_skipped"] and "gymnax" not in pendulum
    for result in payload["results"]:
        positive_rates(result["candidates"])
