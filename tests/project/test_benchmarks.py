"""Every benchmark script runs in --quick mode and writes a well-formed JSON result.

The benchmarks measure (benchmarks/, docs/performance.md); this only checks that
they run end to end and report what they claim, in seconds, in-process.
"""
import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
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


def test_gpu_throughput_on_the_cpu_quick(tmp_path):
    """The GPU benchmark's smoke run on the CPU: eager cells with positive rates, the CUDA-graph
    cells refused with a reason, a bad mode refused, the budget skipping what is left."""
    bench = load("gpu_throughput")
    out = bench.main(["quick=true", "device=cpu", "tasks=[pendulum]", "modes=[eager,cudagraphs]",
                      f"out={tmp_path / 'gpu.json'}", f"data={tmp_path / 'gpu_data.json'}"])
    cells = {(r["mode"], r["kind"]): r for r in out["results"]}
    assert cells["eager", "rollout"]["env_steps_per_s"] > 0 and cells["eager", "bptt"]["env_steps_per_s"] > 0
    assert cells["eager", "bptt"]["saved_kib_per_env_step"] > 0
    assert cells["cudagraphs", "rollout"]["error"] == "CUDA graphs need device=cuda"
    assert json.loads((tmp_path / "gpu_data.json").read_text())["tables"]["rollout"]["rows"][0][:2] == ["pendulum", "4"]
    with pytest.raises(SystemExit, match="valid values"):
        bench.main(["quick=true", "device=cpu", "modes=[graphs]", f"out={tmp_path / 'x.json'}", "data=none"])
    with pytest.raises(SystemExit, match="unknown task option 'soft' in 'Hopper-v5:soft'; valid: "):
        bench.make_task_env("Hopper-v5:soft", 1, "cpu")
    skipped = bench.main(["quick=true", "device=cpu", "tasks=[pendulum]", "modes=[eager]", "budget_s=1e-9",
                          f"out={tmp_path / 'y.json'}", "data=none"])
    assert {r.get("error") for r in skipped["results"]} == {"skipped (budget)"}


def test_gpu_throughput_hotspots_name_the_library_lines_of_a_step():
    """``hotspots=K``: the K library lines whose torch calls take the most time in one env step
    (CPU time here), by decreasing time, each with its share and its calls; the docs table lists them."""
    bench = load("gpu_throughput")
    every = bench.step_hotspots("HalfCheetah-v5", 2, "cpu", 1000)
    hot = every[:5]
    assert all(h["site"].split(":")[0].endswith(".py") and h["site"].split(":")[1].isdigit() for h in hot)
    assert [h["ms"] for h in hot] == sorted((h["ms"] for h in hot), reverse=True) and hot[-1]["ms"] > 0
    assert 0 < sum(h["share"] for h in hot) < 1 and sum(h["share"] for h in every) == pytest.approx(1)
    assert all(sum(h["calls"].values()) > 0 for h in hot)
    assert any(h["site"].startswith("articulated/") for h in hot)  # the physics, not the env's bookkeeping
    # the algebra helpers' calls count at their callers' lines
    assert not any(h["site"].startswith(bench.HELPER_MODULES) for h in every)
    tables = bench.docs_tables([], {"HalfCheetah-v5": {"N": 2, "hotspots": hot}}, "cpu")
    assert [row[2] for row in tables["hotspots"]["rows"]] == [f"`{h['site']}`" for h in hot]


def test_batched_products_quick(tmp_path):
    """Both forms of every product at the simulator's shapes (checked equal inside), the solves, and
    the data table with one row per product."""
    bench = load("batched_products")
    out = bench.main(["quick=true", "device=cpu", f"out={tmp_path / 'bp.json'}", f"data={tmp_path / 'bp_data.json'}"])
    products = [r for r in out["rows"] if "matmul_us" in r]
    assert [r["op"] for r in products] == [name for name, _, _ in bench.SHAPES]
    assert all(r["matmul_us"] > 0 and r["broadcast_us"] > 0 for r in products)
    assert {"solve_ex_us", "cholesky_us"} <= set(out["rows"][-2]) and out["rows"][-1]["argsort_us"] > 0
    table = json.loads((tmp_path / "bp_data.json").read_text())["tables"]["products"]
    assert len(table["rows"]) == len(bench.SHAPES) and "N = 64" in table["title"]


def test_gpu_throughput_data_file_from_several_runs(tmp_path):
    """``from_results`` renders several runs of one machine in one data file, in the order given,
    without rows for cells the budget skipped; runs of two machines are refused."""
    bench = load("gpu_throughput")

    def raw(name, machine, results, diagnostics):
        path = tmp_path / name
        path.write_text(json.dumps({"date": "2026-01-02", "info": {"machine": machine, "command": f"x.py {name}"},
                                    "results": results, "diagnostics": diagnostics}))
        return path

    cell = {"mode": "eager", "kind": "bptt", "steps": 16, "env_steps_per_s": 5e4, "first_call_s": 1.0,
            "peak_memory_gib": 10.9, "saved_kib_per_env_step": 0.68}
    first = raw("a.json", "GPU", [{**cell, "task": "A", "N": 8}], {"A": {"N": 8, "kernels_per_step": 10}})
    second = raw("b.json", "GPU", [{**cell, "task": "B", "N": 8},
                                   {"task": "C", "N": 8, "mode": "eager", "kind": "bptt", "error": "skipped (budget)"}],
                 {"B": {"N": 8, "kernels_per_step": 20}})
    target = tmp_path / "data.json"
    bench.main([f"from_results=[{first},{second}]", f"data={target}"])
    data = json.loads(target.read_text())
    assert [row[0] for row in data["tables"]["bptt"]["rows"]] == ["A", "B"]  # C was skipped: no row
    assert data["tables"]["bptt"]["rows"][1][-3:] == ["16", "10.9", "0.7"]  # window, peak GiB, saved KiB
    assert [row[0] for row in data["tables"]["diagnostics"]["rows"]] == ["A", "B"]
    other = raw("c.json", "another GPU", [{**cell, "task": "D", "N": 8}], {})
    with pytest.raises(SystemExit, match="measured on different machines"):
        bench.main([f"from_results=[{first},{other}]", "data=none"])


def test_gpu_training_time_to_the_cpu_race_ppo_return(tmp_path):
    """The target is the median of the CPU race's PPO final MuJoCo returns; a learner reaches it at
    its first evaluation at or above it (env steps and the wall clock logged then)."""
    bench = load("gpu_training")
    race = tmp_path / "race"
    race.mkdir()
    for seed, final in enumerate([900.0, 1500.0, 400.0]):
        (race / f"HalfCheetah-v5_s{seed}_ppo.json").write_text(json.dumps(
            {"summary": [{"mujoco_return": {"median": final}}]}))
    metrics = tmp_path / "metrics.jsonl"
    rows = [{"env_steps": 0, "eval/gymnasium_return": -90.0},
            {"env_steps": 1000, "time/wall_s": 5.0, "time/steps_per_s": 200.0},
            {"env_steps": 1000, "eval/gymnasium_return": 850.0},
            {"env_steps": 2000, "time/wall_s": 11.0, "time/steps_per_s": 180.0},
            {"env_steps": 2000, "eval/gymnasium_return": 950.0},
            {"env_steps": 3000, "time/wall_s": 16.0, "time/steps_per_s": 190.0},
            {"env_steps": 3000, "eval/gymnasium_return": 920.0}]
    metrics.write_text("\n".join(json.dumps(r) for r in rows) + '\n{"env_steps": 31')  # cut off by the run's end
    out = bench.main([f"from_metrics=[ahac={metrics}]", f"race={race}", "gpu=a GPU", f"out={tmp_path / 'o.json'}",
                      f"data={tmp_path / 'd.json'}"])
    assert out["target"] == 900.0
    (result,) = out["results"]
    assert (result["reached_steps"], result["reached_wall_s"]) == (2000, 11.0)
    assert (result["best_return"], result["last_return"], result["training_env_steps_per_s"]) == (950.0, 920.0, 190.0)
    assert result["evaluated_every"] == 1000
    assert "exited with 1" in bench.summarise("ahac", metrics, 900.0, exit_code=1)["error"]
    assert bench.summarise("ahac", metrics, 900.0, exit_code=143)["reached_steps"] == 2000  # SIGTERM: a clean end
    with pytest.raises(SystemExit, match="seconds: 'sac' is not a learner of this run; valid: \\['ppo', 'ahac'\\]"):
        bench.main(["seconds=[sac=5]", "device=cpu", f"race={race}", "data=none"])
    data = json.loads((tmp_path / "d.json").read_text())
    assert data["machine"] == "a GPU" and data["tables"]["time_to_ppo"]["rows"][0][2] == "11 s"
    with pytest.raises(SystemExit, match=r"no Hopper-v5_s\*_ppo.json results there"):
        bench.main(["env=Hopper-v5", f"from_metrics=[ahac={metrics}]", f"race={race}", "data=none"])


def test_memory_growth_reads_the_slope_after_the_warm_up(tmp_path):
    """The slope is a least-squares line through the rows after the first tenth of the iterations,
    in MiB per 1000 iterations: flat memory gives 0, a steady leak its rate, the warm-up is left out."""
    bench = load("memory_growth")
    assert bench.slope_per_1000([(0, 5.0), (1000, 7.0), (2000, 9.0)]) == pytest.approx(2.0)
    rows = [{"time/iteration": i, "memory/rss_mib": 100.0 if i < 100 else 300.0 + 0.01 * i} for i in range(10, 1001, 10)]
    metrics = tmp_path / "metrics.jsonl"
    metrics.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = bench.summarise("x:y", metrics)["memory/rss_mib"]
    assert out["slope_per_1000"] == pytest.approx(10.0) and out["iterations"] == 1000
    assert (out["after_warmup"], out["end"], out["peak"]) == (301.0, 310.0, 310.0)
    metrics.write_text(json.dumps({"time/iteration": 1}))
    assert "no memory rows" in bench.summarise("x:y", metrics)["error"]
    with pytest.raises(SystemExit, match="runs: expected ENV:LOSS, got 'pendulum'"):
        bench.main(["runs=[pendulum]", "data=none", f"out={tmp_path / 'o.json'}"])


def test_policy_anatomy_of_a_saved_hopper(tmp_path):
    """The return is the first episode's (as ``evaluation.episode_returns`` computes it for the same
    policy and start states) and an episode ended by the torso above ``healthy_z_high`` counts as a
    jump: with the bound set under the Hopper's start height (1.25) every episode ends at its first
    step, by a jump."""
    from omegaconf import OmegaConf
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from _train_helpers import tiny_cfg, train_script
    from torchrl_diffenvs.evaluation import episode_returns
    from torchrl_diffenvs.learners import LEARNERS
    from torchrl_diffenvs.training import load_checkpoint, save_checkpoint
    from torchrl_diffenvs.training.config import make_env_from_config

    bench = load("policy_anatomy")
    run = train_script.run(tiny_cfg("Hopper-v5", "bptt", 1), tmp_path / "run")
    row = bench.main([f"checkpoints=[hopper={run['checkpoint']}]", "num_envs=4", "steps=12", "data=none",
                      f"out={tmp_path / 'a.json'}"])[0]
    ckpt = load_checkpoint(run["checkpoint"])
    cfg = OmegaConf.create(ckpt["config"])
    env = make_env_from_config(cfg, 4, seed=123)  # the benchmark's default start states
    policy = LEARNERS["bptt"].policy_from_config(cfg.loss, env)
    policy.load_state_dict(ckpt["policy"])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = episode_returns(env.rollout(12, policy, break_when_any_done=False)).mean()
    assert row["return"] == pytest.approx(float(expected), rel=1e-6)
    assert row["ctrl_per_step"] > 0 and 0 <= row["saturated"] <= 1
    assert sum(row["causes"].values()) == round(row["ended"] * 4)
    # the same policy, its config's bound edited (what training with +env.params.healthy_z_high=1.0 saves)
    ckpt["config"].setdefault("env", {}).setdefault("params", {})["healthy_z_high"] = 1.0
    low = save_checkpoint({k: v for k, v in ckpt.items() if k not in ("format", "checksum")}, tmp_path / "low.pt")
    row = bench.main([f"checkpoints=[low={low}]", "num_envs=4", "steps=12", "data=none",
                      f"out={tmp_path / 'b.json'}"])[0]
    assert row["ended"] == 1 and row["causes"] == {"jump": 4, "fall": 0, "other": 0} and row["episode_length"] == 1
    with pytest.raises(SystemExit, match="expected \\[LABEL=PATH"):
        bench.main([f"checkpoints=[{run['checkpoint']}]", "data=none"])


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


def test_time_to_solve_reports_the_return_in_gymnasiums_env():
    """Runs with ``eval.gymnasium=true`` carry their final policy's return in Gymnasium's env:
    the summary gives it and the share kept there, per loss (hand-computed)."""
    tts = load("time_to_solve")

    def run(loss, seed, ours, theirs=None):
        r = {"env": "Hopper-v5", "loss": loss, "seed": seed, "eval/return": ours, "eval/random_return": 10.0,
             "wall_time_s": 100.0, "env_steps": 1000, "curve": [(0, 0.0, 10.0), (1000, 100.0, ours)]}
        return r if theirs is None else {**r, "eval/gymnasium_return": theirs}

    runs = [run("ppo", s, 1000.0) for s in range(3)]
    runs += [run("ahac", 0, 2000.0, 1000.0), run("ahac", 1, 2000.0, 2000.0), run("ahac", 2, 1000.0, 900.0)]
    summary, table = tts.summarise(runs, ["Hopper-v5"], ["ppo", "ahac"])
    ppo, ahac = summary
    assert "mujoco_return" not in ppo  # not scored there: a dash, not a number
    assert ahac["mujoco_return"] == {"min": 900.0, "median": 1000.0, "max": 2000.0}
    assert ahac["transfer"] == {"min": 0.5, "median": 0.9, "max": 1.0}
    assert "in Gymnasium's env" in table and "0.90 [0.50, 1.00]" in table


def test_time_to_solve_reports_how_much_of_the_wall_time_the_evaluations_took():
    """Runs that counted their evaluations (``eval_time_s``) get its spread in the column "of
    which evaluating s"; a loss with a run that did not (an older run, or one resumed from such a
    checkpoint: NaN) gets a dash."""
    tts = load("time_to_solve")

    def run(loss, seed, evaluating):
        r = {"env": "Hopper-v5", "loss": loss, "seed": seed, "eval/return": 100.0, "eval/random_return": 10.0,
             "wall_time_s": 1000.0, "env_steps": 1000, "curve": [(0, 0.0, 10.0), (1000, 1000.0, 100.0)]}
        return r if evaluating is None else {**r, "eval_time_s": evaluating}

    runs = [run("ppo", 0, 300.0), run("ppo", 1, 100.0), run("ppo", 2, 200.0),
            run("shac", 0, 250.0), run("shac", 1, math.nan), run("sapo", 0, None)]
    summary, table = tts.summarise(runs, ["Hopper-v5"], ["ppo", "shac", "sapo"])
    assert summary[0]["eval_s"] == {"min": 100.0, "median": 200.0, "max": 300.0}
    assert "eval_s" not in summary[1] and "eval_s" not in summary[2]
    assert "of which evaluating s" in table and "200 [100, 300]" in table
    # runs none of which counted it: no column
    assert "of which evaluating s" not in tts.summarise([run("ppo", 0, None)], ["Hopper-v5"], ["ppo"])[1]


def test_time_to_solve_reports_each_runs_actor_gradient_health(tmp_path):
    """A gradient learner's whole run: the median and largest pre-clip actor norm of its logged
    updates and the updates its guard skipped (the cumulative count at the end), from
    ``metrics.jsonl`` (hand-written); the summary gives their spread over seeds, PPO a dash."""
    tts = load("time_to_solve")
    rows = [{"env_steps": 0, "eval/return": 1.0}, {"env_steps": 10, "train/grad_norm_actor": 3.0, "train/skipped_actor": 0},
            {"env_steps": 20, "train/grad_norm_actor": 1e9, "train/skipped_actor": 1},
            {"env_steps": 30, "train/grad_norm_actor": 5.0, "train/skipped_actor": 1},
            {"env_steps": 40, "train/grad_norm_actor": 4.0, "train/skipped_actor": 2}]
    (tmp_path / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows))
    health = tts.gradient_health(tmp_path)
    assert health == {"actor_grad_norm_median": 4.5, "actor_grad_norm_max": 1e9, "logged_updates": 4,
                      "skipped_actor_updates": 2}
    (tmp_path / "metrics.jsonl").write_text(json.dumps({"env_steps": 10, "train/grad_norm": 2.0}))
    assert tts.gradient_health(tmp_path) is None  # PPO logs no actor norm

    def run(loss, seed, healthy):
        r = {"env": "Walker2d-v5", "loss": loss, "seed": seed, "eval/return": 500.0, "eval/random_return": 1.0,
             "wall_time_s": 100.0, "env_steps": 1000, "curve": [(0, 0.0, 1.0), (1000, 100.0, 500.0)],
             "gradient_health": healthy}
        return r

    runs = [run("ppo", s, None) for s in range(2)]
    runs += [run("sapo", s, {"actor_grad_norm_median": 10.0 ** s, "actor_grad_norm_max": 1e9, "logged_updates": 4,
                             "skipped_actor_updates": 2 * s}) for s in range(3)]
    summary, table = tts.summarise(runs, ["Walker2d-v5"], ["ppo", "sapo"])
    ppo, sapo = summary
    assert "gradient_health" not in ppo
    assert sapo["gradient_health"]["actor_grad_norm_median"] == {"min": 1.0, "median": 10.0, "max": 100.0}
    assert sapo["gradient_health"]["skipped_actor_updates"] == {"min": 0, "median": 2, "max": 4}
    assert "skipped actor updates" in table and "10 [1, 100]" in table and "2 [0, 4]" in table


def test_a_ppo_final_below_ppos_untrained_policy_gets_no_speed_up():
    """PPO's runs end below their first evaluation (the untrained policy): their final level is met
    at the start, so no learner gets a speed-up against it (a 0 s reference), and the cell says why."""
    tts = load("time_to_solve")

    def run(loss, seed, curve):
        return {"env": "Ant-v5", "loss": loss, "seed": seed, "eval/return": curve[-1][2], "eval/random_return": -50.0,
                "wall_time_s": curve[-1][1], "env_steps": curve[-1][0], "curve": curve}

    runs = [run("ppo", s, [(0, 0.0, 940.0), (1000, 100.0, 420.0 + s)]) for s in range(3)]
    runs += [run("shac", s, [(0, 0.0, 390.0), (1000, 80.0, 990.0)]) for s in range(3)]
    summary, table = tts.summarise(runs, ["Ant-v5"], ["ppo", "shac"])
    shac = summary[1]["levels"][1.0]
    assert shac["time_s"] == 80.0 and shac["ppo_at_start"] and shac["speedup_vs_ppo"] is None
    assert "80 s, 1k steps (3/3, PPO's start is above it)" in table
    assert tts.overview_table(summary)["rows"][1][-1] == "- (PPO ends below its start)"  # the glance: no race


def test_time_to_solve_resumes_kept_runs_from_their_checkpoints(tmp_path):
    """A race split across sittings: a kept run stopped at its 32-env-step checkpoint (the
    uninterrupted run's directory with that checkpoint as its last), continued with
    ``resume=true``, ends as the uninterrupted run did: the same evaluations (exact resume), the
    stopped part's own wall times kept, and the result says where it resumed. A kept run is never
    overwritten without ``resume=true``, nor continued by a command with other overrides."""
    tts = load("time_to_solve")
    common = ["quick=true", "losses=[bptt]", "steps=[bptt=64]",
              "override=[train.checkpoint_interval=16,train.keep_checkpoints=8]"]
    whole = tts.main([*common, f"keep_runs={tmp_path / 'whole'}", f"out={tmp_path / 'a.json'}"])["runs"][0]
    shutil.copytree(tmp_path / "whole", tmp_path / "stopped")
    checkpoints = tmp_path / "stopped" / "pendulum_bptt_seed0" / "checkpoints"
    shutil.copy(checkpoints / "ckpt_000000000032.pt", checkpoints / "last.pt")
    resumed = tts.main([*common, f"keep_runs={tmp_path / 'stopped'}", "resume=true",
                        f"out={tmp_path / 'b.json'}"])["runs"][0]
    assert whole["resumed_from_env_steps"] is None and resumed["resumed_from_env_steps"] == 32
    # the records name the run by its place among the kept runs, not by this machine's path
    assert (resumed["run_dir"], resumed["checkpoint"]) == ("pendulum_bptt_seed0", "pendulum_bptt_seed0/checkpoints/last.pt")
    assert [(steps, value) for steps, _, value in resumed["curve"]] == [(steps, value) for steps, _, value in whole["curve"]]
    assert resumed["eval/return"] == whole["eval/return"] and resumed["env_steps"] == whole["env_steps"] == 64
    # before the checkpoint: the stopped run's rows as they were (a fresh run would measure other times)
    before = [point for point in whole["curve"] if point[0] < 32]
    assert len(before) >= 2 and resumed["curve"][:len(before)] == before
    with pytest.raises(SystemExit, match="holds a run with checkpoints .* resume=true continues it"):
        tts.main([*common, f"keep_runs={tmp_path / 'stopped'}", f"out={tmp_path / 'c.json'}"])
    with pytest.raises(SystemExit, match="was started with other overrides"):
        tts.main(["quick=true", "losses=[bptt]", "steps=[bptt=64]", f"keep_runs={tmp_path / 'stopped'}",
                  "resume=true", f"out={tmp_path / 'c.json'}"])
    with pytest.raises(SystemExit, match="resume=true continues the runs kept in keep_runs=DIR"):
        tts.main(["quick=true", "losses=[bptt]", "resume=true", f"out={tmp_path / 'c.json'}"])


def test_recorded_commands_hold_no_local_paths(tmp_path):
    """A command as the data files record it: scratch files and directories outside the repository
    dropped (with the ``resume=true`` of a scratch ``keep_runs``), paths inside it relative."""
    common = load("_common")
    inside = common.REPO_ROOT / "docs" / "data" / "runs" / "x.json"
    args = ["envs=[Hopper-v5]", f"keep_runs={tmp_path}", "resume=true", f"out={tmp_path / 'a.json'}",
            f"data={tmp_path / 'race.json'}"]
    assert common.portable_args(args) == ["envs=[Hopper-v5]", "data=race"]
    assert common.portable_args(["keep_runs=runs/ant", "resume=true", f"out={inside}"]) == [
        "keep_runs=runs/ant", "resume=true", "out=docs/data/runs/x.json"]
    # list items: scratch files by name, files inside relative; a pattern quoted for the shell
    assert common.portable_args([f"summarise=[{tmp_path / 'a.json'},{inside}]", f"summarise=[{inside.parent}/*.json]"]) == [
        "summarise=[a.json,docs/data/runs/x.json]", '"summarise=[docs/data/runs/*.json]"']
    run = {"run_dir": str(tmp_path / "elsewhere" / "r"), "checkpoint": str(tmp_path / "elsewhere" / "r" / "checkpoints" / "last.pt")}
    assert common.portable_run(run, tmp_path / "runs") == {"run_dir": "r", "checkpoint": "r/checkpoints/last.pt"}


def test_the_data_files_hold_no_local_paths():
    """What the docs render and link (docs/data: results, raw run files, logs) names no directory of
    the machine that measured it."""
    data = Path(__file__).resolve().parents[2] / "docs" / "data"
    local = ("/tmp/", "/home/", "/root/", "/work/", str(data.parents[1]))
    texts = [path for path in sorted(data.rglob("*")) if path.suffix in (".json", ".jsonl", ".txt", ".csv", ".md")]
    assert len(texts) > 100
    found = [f"{path.relative_to(data)}: {prefix}" for path in texts for prefix in local if prefix in path.read_text()]
    assert not found, found


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


def test_time_to_solve_checks_every_run_before_the_first(tmp_path, monkeypatch):
    """A variant whose override does not compose stops the benchmark before any run starts (the
    runs before it would otherwise take hours and be lost), naming the run and the override."""
    tts = load("time_to_solve")
    tts.load_train_script()  # the real script registers the loss configs that composing needs
    started = []
    monkeypatch.setattr(tts, "load_train_script", lambda: SimpleNamespace(run=lambda *a: started.append(a)))
    with pytest.raises(SystemExit, match=r"Hopper-v5 shac bad seed 0 does not compose .*no_such_option"):
        tts.main(["quick=true", "envs=[Hopper-v5]", "losses=[shac]", 'variant=["ok=","bad=env.options.no_such_option=1"]',
                  f"out={tmp_path / 'tts.json'}"])
    with pytest.raises(SystemExit, match="eval.only_gymnasium=true leaves the runs without this library's evaluation"):
        tts.main(["quick=true", "envs=[Hopper-v5]", "losses=[shac]",
                  "override=[eval.gymnasium=true,eval.only_gymnasium=true]", f"out={tmp_path / 'tts.json'}"])
    assert started == []


def _run(env, loss, seed, curve):
    """A result file's run as time_to_solve writes it: ``curve`` = [(env steps, wall s, return), ...]."""
    steps, wall, value = curve[-1]
    return {"env": env, "loss": loss, "seed": seed, "variant": "", "curve": [list(p) for p in curve],
            "eval/return": value, "eval/random_return": 0.0, "wall_time_s": wall, "env_steps": steps}


def test_time_to_solve_merges_result_files(tmp_path):
    """Runs from several result files (one per seed, run side by side) are summarised together:
    PPO's final median, and each learner's wall time and env steps to it, by hand."""
    tts = load("time_to_solve")
    ppo = [[(0, 0, 0), (100_000, 50, 40), (200_000, 100, 90)], [(0, 0, 0), (100_000, 60, 80), (200_000, 120, 100)],
           [(0, 0, 0), (100_000, 55, 70), (200_000, 110, 110)]]  # finals 90, 100, 110: PPO's final median 100
    shac = [[(0, 0, 0), (50_000, 20, 101), (100_000, 40, 60)], [(0, 0, 0), (50_000, 30, 50), (100_000, 45, 120)],
            [(0, 0, 0), (50_000, 25, 10), (100_000, 50, 20)]]  # reach 100: 20 s / 50k steps, 45 s / 100k, never
    files = []
    for seed in range(3):
        path = tmp_path / f"seed{seed}.json"
        path.write_text(json.dumps({"benchmark": "time_to_solve", "info": {"torch_threads": 1}, "runs": [
            _run("task", "ppo", seed, ppo[seed]), _run("task", "shac", seed, shac[seed])]}))
        files.append(str(path))
    out = tmp_path / "merged.json"
    payload = tts.main([f"summarise=[{','.join(files)}]", f"out={out}", f"data={tmp_path / 'data.json'}"])
    rows = {r["loss"]: r for r in payload["summary"]}
    assert rows["ppo"]["final_return"]["median"] == 100
    assert rows["ppo"]["levels"][1.0]["time_s"] == 120  # seeds 0, 1, 2 reach 100 at: never, 120 s, 110 s
    shac_level = rows["shac"]["levels"][1.0]
    assert shac_level["return"] == 100 and shac_level["reached"] == "2/3" and shac_level["seeds_reached"] == [0, 1]
    assert shac_level["time_s"] == 45 and shac_level["env_steps"] == 100_000  # medians of (20, 45, inf), (50k, 100k, inf)
    assert shac_level["speedup_vs_ppo"] == pytest.approx(120 / 45)
    assert json.loads(out.read_text())["merged_from"] == [Path(f).name for f in files]  # scratch files: names
    data = json.loads((tmp_path / "data.json").read_text())
    assert "45 s, 100k steps (2/3, 2.67x)" in json.dumps(data["tables"]["levels"]["rows"])
    # the caption names the runs' threads (not the summarising process's) and the title their seeds
    assert data["machine"].endswith("1 torch thread") and "(3 seeds;" in data["tables"]["levels"]["title"]
    # the race at a glance: one row per learner, its seeds counted, the time to PPO's final (minutes from 2)
    assert data["tables"]["overview"]["rows"] == [["task", "ppo (3)", "100 [90, 110]", "-", "2 min (2/3, 1x)"],
                                                  ["task", "shac (3)", "60 [20, 120]", "-", "45 s (2/3, 2.67x)"]]
    # a pattern stands for the files it matches
    pattern = tts.main([f"summarise=[{tmp_path / 'seed*.json'}]", f"out={tmp_path / 'p.json'}"])
    assert pattern["summary"] == payload["summary"]
    with pytest.raises(SystemExit, match="no result file matches"):
        tts.main([f"summarise=[{tmp_path / 'none*.json'}]"])
    extra = tmp_path / "sapo.json"
    extra.write_text(json.dumps({"benchmark": "time_to_solve", "info": {"torch_threads": 1},
                                 "runs": [_run("task", "sapo", 0, shac[0])]}))
    tts.main([f"summarise=[{','.join(files)},{extra}]", f"out={out}", f"data={tmp_path / 'data.json'}"])
    title = json.loads((tmp_path / "data.json").read_text())["tables"]["levels"]["title"]
    assert "(seeds: ppo 3, shac 3, sapo 1;" in title
    with pytest.raises(SystemExit, match=r"appear more than once: \[\('task', 'ppo', 0\)"):
        tts.main([f"summarise=[{files[0]},{files[0]}]", f"out={out}"])
    with pytest.raises(SystemExit, match="no result file"):
        tts.main([f"summarise=[{tmp_path / 'missing.json'}]"])


def test_time_to_solve_takes_ppo_on_gymnasiums_env_where_an_env_has_no_ppo_run_here():
    """An env raced against PPO on Gymnasium's own env only (``ppo:gymnasium``): its levels are
    that PPO's (final median 100, reached never, at 110 s and at 120 s: 120 s, by hand); an env
    with a PPO run here keeps it; the headers say which PPO."""
    tts = load("time_to_solve")

    def run(env, loss, seed, curve, variant=""):
        return {**_run(env, loss, seed, curve), "variant": variant}

    gym_ppo = [[(0, 0, 0), (100_000, 60, 90)], [(0, 0, 0), (100_000, 110, 100)], [(0, 0, 0), (100_000, 120, 110)]]
    runs = [run("w", "ppo", s, c, "gymnasium") for s, c in enumerate(gym_ppo)]
    runs.append(run("w", "ahac", 0, [(0, 0, 0), (20_000, 11, 105), (40_000, 22, 50)]))
    summary, table = tts.summarise(runs, ["w"], ["ppo", "ahac"])
    rows = {r["loss"]: r for r in summary}
    assert rows["ahac"]["reference"] == "ppo:gymnasium"
    level = rows["ahac"]["levels"][1.0]
    assert level["return"] == 100 and level["time_s"] == 11 and level["env_steps"] == 20_000
    assert level["speedup_vs_ppo"] == pytest.approx(120 / 11)
    assert "PPO on Gymnasium's env final = 100" in table
    here = [run("h", "ppo", 0, [(0, 0, 0), (100_000, 50, 40)])]
    summary, table = tts.summarise(runs + here, ["h", "w"], ["ppo", "ahac"])
    assert {r["env"]: r["reference"] for r in summary} == {"h": "ppo", "w": "ppo:gymnasium"}
    assert "(the env's own; on Gymnasium's env where it has no PPO run here)" in table


def test_time_to_solve_summary_names_the_cpus_its_runs_recorded(tmp_path):
    """A summary of result files from two machines names both CPU models (a file written before
    benchmarks recorded the model adds none; files that all lack it say so); every benchmark
    records it."""
    tts = load("time_to_solve")
    infos = [{"torch_threads": 1, "cpu_model": "Model A"}, {"torch_threads": 1, "cpu_model": "Model B"},
             {"torch_threads": 1}]
    paths = []
    for i, info in enumerate(infos):
        paths.append(tmp_path / f"runs{i}.json")
        paths[-1].write_text(json.dumps({"benchmark": "time_to_solve", "info": info, "runs": [
            _run("a", "sapo", i, [(0, 0, 0), (50_000, 20, 101)])]}))
    tts.main([f"summarise=[{','.join(map(str, paths))}]", f"out={tmp_path / 'out.json'}",
              f"data={tmp_path / 'data.json'}"])
    machine = json.loads((tmp_path / "data.json").read_text())["machine"]
    assert "Model A / Model B (" in machine and machine.endswith("1 torch thread")
    tts.main([f"summarise=[{paths[2]}]", f"out={tmp_path / 'out.json'}", f"data={tmp_path / 'data.json'}"])
    assert "CPU not recorded" in json.loads((tmp_path / "data.json").read_text())["machine"]
    assert load("_common").versions()["cpu_model"]


def test_time_to_solve_env_levels_apply_to_their_env_only(tmp_path):
    """``env_levels=[ENV=RETURN]``: a fixed level in that env's table only (another race's PPO
    final when PPO's runs are not among the files); wall time and env steps to it by hand."""
    tts = load("time_to_solve")
    curves = {"a": [(0, 0, 0), (50_000, 20, 101), (100_000, 40, 60)], "b": [(0, 0, 0), (50_000, 30, 5), (100_000, 45, 7)]}
    path = tmp_path / "runs.json"
    path.write_text(json.dumps({"benchmark": "time_to_solve", "info": {}, "runs": [
        _run(env, "sapo", 0, curve) for env, curve in curves.items()]}))
    payload = tts.main([f"summarise=[{path}]", "env_levels=[a=100,b=6]", f"out={tmp_path / 'out.json'}",
                        f"data={tmp_path / 'data.json'}"])
    tables = json.loads((tmp_path / "data.json").read_text())["tables"]
    assert tables["a"]["columns"][-1] == "return >= 100" and tables["b"]["columns"][-1] == "return >= 6"
    assert tables["a"]["rows"][0][-1] == "20.0 s, 50k steps (1/1: 20.0)"  # a passes 100 at its first evaluation
    assert tables["b"]["rows"][0][-1] == "45.0 s, 100k steps (1/1: 45.0)"
    assert not any(c.startswith("return >=") for c in tables["levels"]["columns"])  # not in the combined table
    assert payload["summary"][0]["fixed_levels"] == {}
    with pytest.raises(SystemExit, match="names 'c', which no summarised run has; valid: a, b"):
        tts.main([f"summarise=[{path}]", "env_levels=[c=1]", f"out={tmp_path / 'out.json'}"])
    with pytest.raises(SystemExit, match="expected ENV=RETURN"):
        tts.main([f"summarise=[{path}]", "env_levels=[100]", f"out={tmp_path / 'out.json'}"])


def test_benchmark_arguments_are_checked_like_the_training_scripts():
    tts = load("time_to_solve")
    with pytest.raises(SystemExit, match=r"losses=\['dqn'\]: element 'dqn': valid: shac, bptt, ppo, sac"):
        tts.main(["losses=[dqn]"])
    with pytest.raises(SystemExit, match="unknown argument '--quick'"):
        tts.main(["--quick"])
    with pytest.raises(SystemExit, match="threads=3: valid: 1, 2"):
        load("env_throughput").main(["threads=3"])


def test_mujoco_throughput_quick(tmp_path):
    """Every column but MJX's (each N compiles MJX for a minute or more: `test_mjx_rollout_runs`);
    the BPTT window up to ``window_max_n`` only."""
    pytest.importorskip("mujoco")
    bench = load("mujoco_throughput")
    payload = bench.main(["quick=true", "tasks=[Hopper-v5]", "mjx_max_n=0", "window_max_n=1",
                          f"out={tmp_path / 'mj.json'}"])
    assert [(r["task"], r["N"]) for r in payload["results"]] == [("Hopper-v5", 1), ("Hopper-v5", 4)]
    for row in payload["results"]:
        positive_rates(row["candidates"])
        assert row["mjx"] == "not timed: N > mjx_max_n=0"
        window = {"ours fwd+bwd"} if row["N"] == 1 else set()
        assert {"ours", "gymnasium", "mj_step (C)", "gymnasium SyncVectorEnv"} | window == set(row["candidates"])
        assert ("window" in row) == (row["N"] == 4)
        assert set(row["ratios_cpu"]) == {f"ours / {name}" for name in row["candidates"] if name != "ours"}
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in payload["table"].splitlines()[2:]]
    assert [row[3] != "-" for row in rows] == [True, False]  # the window's column: timed at N = 1 only
    with pytest.raises(SystemExit, match="window_max_n=-1: expected an integer >= 0"):
        bench.main(["window_max_n=-1"])
    # a run stopped after its first row goes on from its raw file: that row kept as it was, the rest measured
    stopped = tmp_path / "stopped.json"
    stopped.write_text(json.dumps({"results": payload["results"][:1]}))
    resumed = bench.main(["quick=true", "tasks=[Hopper-v5]", "mjx_max_n=0", "window_max_n=1", f"resume={stopped}",
                          f"out={tmp_path / 'resumed.json'}"])
    assert resumed["results"][0] == payload["results"][0]
    assert resumed["results"][1]["N"] == 4 and resumed["results"][1] != payload["results"][1]  # timed again
    assert resumed["table"].splitlines()[2] == payload["table"].splitlines()[2]
    with pytest.raises(SystemExit, match="no such file; expected the raw JSON an earlier run wrote"):
        bench.main(["quick=true", f"resume={tmp_path / 'missing.json'}"])


def test_mjx_rollout_runs():
    """The MJX column's rollout (with the bench extra): compiled, then a timed call that moves the
    envs (finite, away from the start)."""
    pytest.importorskip("mujoco.mjx")
    import mujoco
    from torchrl_diffenvs.articulated import gymnasium_asset

    bench = load("mujoco_throughput")
    # the smallest model: MJX compiles Hopper's step for minutes on a loaded CPU
    model = mujoco.MjModel.from_xml_path(str(gymnasium_asset("inverted_pendulum.xml")))
    run, compile_s = bench.mjx_rollout(model, frame_skip=2, n=2, steps=2)
    assert compile_s > 0
    qpos = np.asarray(run())
    assert qpos.shape == (2, model.nq) and np.isfinite(qpos).all()
    assert np.abs(qpos - np.asarray(run.start_qpos)).max() > 1e-4


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


def test_stress_quick(tmp_path, monkeypatch):
    rows = load("stress").main(["quick=true", "tasks=[Ant-v5]", "integrator=implicit", "policies=[resonant,greedy]",
                                f"out={tmp_path / 's.json'}", "data=none"])
    assert [r[:4] for r in rows] == [["Ant-v5", "mujoco", "implicit", "resonant"], ["Ant-v5", "mujoco", "implicit", "greedy"]]
    assert all(r[5] == "0" for r in rows)  # 8 envs x 20 steps: nothing diverges
    assert all(r[6] == "0" for r in rows)  # and every constraint solve converged within the file's iterations


def test_stress_runs_a_fixed_base_task_without_a_track(tmp_path):
    """The Pusher's arm is fixed to the world: no ``far`` row (no track to go down) and no travel."""
    rows = load("stress").main(["quick=true", "tasks=[Pusher-v5]", "policies=[random,far,greedy]",
                                f"out={tmp_path / 's.json'}", "data=none"])
    assert [r[3] for r in rows] == ["random", "greedy"]
    assert all(r[5] == "0" and r[8] == "-" for r in rows)


def test_stress_counts_the_env_steps_whose_solve_stopped_short(monkeypatch, tmp_path):
    """With one Newton iteration allowed, the env flags unconverged solves (``solver_unconverged``)
    and stress counts them; the smooth option has no solve to count: a dash, not a 0."""
    import dataclasses

    stress = load("stress")
    make = stress.make_env

    def one_iteration(*args, **kwargs):
        env = make(*args, **kwargs)
        env.tree.model = dataclasses.replace(env.tree.model, iterations=1)
        return env

    monkeypatch.setattr(stress, "make_env", one_iteration)
    settings = stress.StressSettings(quick=True, tasks=("HalfCheetah-v5",), num_envs=8, steps=20)
    flagged = stress.stress("HalfCheetah-v5", "random", settings)["unconverged"]
    assert 0 < flagged <= 8 * 20
    monkeypatch.setattr(stress, "make_env", make)
    assert stress.stress("HalfCheetah-v5", "random", settings)["unconverged"] == 0
    monkeypatch.setattr(stress, "make_env", lambda *args, **kwargs: make(*args, contact="smooth", **kwargs))
    assert stress.stress("HalfCheetah-v5", "random", settings)["unconverged"] is None
    with pytest.raises(SystemExit, match="integrator='verlet': valid: model, euler, implicit, rk4"):
        load("stress").main(["quick=true", "integrator=verlet"])


def test_stress_resume_keeps_the_data_files_rows_and_runs_only_the_missing_pairs(monkeypatch, tmp_path):
    stress = load("stress")
    ran = []

    def fake(task, kind, settings, partial=None):
        ran.append((task, kind))
        return {"nonfinite": 0, "unconverged": 0, "max_qvel": 1.0, "travel": 2.0, "contact": "mujoco",
                "integrator": "euler"}

    monkeypatch.setattr(stress, "stress", fake)
    data = tmp_path / "stress_cheetah.json"
    args = ["tasks=[HalfCheetah-v5]", "steps=20", f"out={tmp_path / 's.json'}", f"data={data}"]
    first = stress.main([*args, "policies=[random]"])
    assert ran == [("HalfCheetah-v5", "random")]
    kept = json.loads(data.read_text())
    kept["command"], kept["machine"] = "python benchmarks/stress.py an earlier sitting", "an earlier machine"
    data.write_text(json.dumps(kept))
    rows = stress.main([*args, "policies=[random,greedy]", "resume=true"])
    assert ran == [("HalfCheetah-v5", "random"), ("HalfCheetah-v5", "greedy")]  # random was in the file
    assert rows[0] == first[0] and [r[3] for r in rows] == ["random", "greedy"]
    written = json.loads(data.read_text())
    assert written["tables"]["stress"]["rows"] == rows
    # the rows of both sittings: both commands and machines, the newest date
    assert written["command"].startswith("python benchmarks/stress.py an earlier sitting; python benchmarks/")
    assert written["machine"].startswith("an earlier machine; ")
    stress.main([*args, "policies=[random,greedy]", "resume=true", "num_envs=4"])  # another size: both run again
    assert ran[2:] == [("HalfCheetah-v5", "random"), ("HalfCheetah-v5", "greedy")]
    ran.clear()  # the kept rows stepped with HalfCheetah's Euler: another integrator runs them again
    stress.main([*args, "policies=[random]", "resume=true", "integrator=implicit"])
    assert ran == [("HalfCheetah-v5", "random")]
    with pytest.raises(SystemExit, match="resume=true: no data file"):
        stress.main(["quick=true", "resume=true", "data=none"])
    data.write_text("{}")
    with pytest.raises(SystemExit, match="is not a stress data file"):
        stress.main([*args, "resume=true"])


def test_stress_row_stopped_midway_resumes_to_the_result_of_one_sitting(monkeypatch, tmp_path, capsys):
    """A row killed after its last save continues there with resume=true (the envs, their random
    streams, the policy's state and the counters), to the same numbers and the same last state,
    bit for bit, as a row run in one go; the partial row is removed once the row is written."""
    stress = load("stress")
    monkeypatch.setattr(stress, "PARTIAL_DIR", tmp_path / "partial")
    data = tmp_path / "stress_hopper.json"
    settings = stress.StressSettings(tasks=("Hopper-v5",), num_envs=6, steps=24, checkpoint_every=8, data=str(data),
                                     resume=True)
    keys = ("nonfinite", "unconverged", "max_qvel", "travel")
    make_policy = stress.make_policy

    def stopping(kind_, env, gen):  # the sitting ends (a kill) at step 19: the save at step 16 is kept
        policy, state = make_policy(kind_, env, gen)

        def stopped(td, t):
            if t == 19:
                raise KeyboardInterrupt
            return policy(td, t)
        return stopped, state

    for kind in ("random", "bang-bang", "resonant", "far", "greedy"):
        whole = stress.stress("Hopper-v5", kind, settings)
        path = stress.partial_path(settings, "Hopper-v5", kind)
        monkeypatch.setattr(stress, "make_policy", stopping)
        with pytest.raises(KeyboardInterrupt):
            stress.stress("Hopper-v5", kind, settings, path)
        assert torch.load(path, weights_only=False)["t"] == 16
        monkeypatch.setattr(stress, "make_policy", make_policy)
        resumed = stress.stress("Hopper-v5", kind, settings, path)
        assert {k: resumed[k] for k in keys} == {k: whole[k] for k in keys}, kind
        for key in ("qpos", "qvel"):
            assert torch.equal(resumed["state"][key], whole["state"][key]), (kind, key)
    # through the script: a partial row is continued, and removed once its row is in the data file
    monkeypatch.setattr(stress, "make_policy", stopping)
    args = ["tasks=[Hopper-v5]", "policies=[bang-bang]", "num_envs=6", "steps=24", "checkpoint_every=8",
            f"data={data}", f"out={tmp_path / 's.json'}"]
    with pytest.raises(KeyboardInterrupt):
        stress.main(args)
    path = stress.partial_path(settings, "Hopper-v5", "bang-bang")
    assert path.exists() and not data.exists()
    monkeypatch.setattr(stress, "make_policy", make_policy)
    rows = stress.main([*args, "resume=true"])
    assert "continuing a partial row from step 16" in capsys.readouterr().out
    assert not path.exists() and json.loads(data.read_text())["tables"]["stress"]["rows"] == rows
    # without resume=true a partial row starts over, and says so
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"row": {"task": "Ant-v5"}}, path)
    stress.main([*args, "policies=[bang-bang]"])
    assert "discarding the partial row" in capsys.readouterr().out and not path.exists()
    torch.save({"row": {"task": "Ant-v5"}}, path)
    with pytest.raises(SystemExit, match="is a partial row of .*Ant-v5.*remove it"):
        stress.stress("Hopper-v5", "bang-bang", settings, path)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit, match="is not a partial stress row"):
        stress.stress("Hopper-v5", "bang-bang", settings, path)
    with pytest.raises(SystemExit, match="checkpoint_every"):
        stress.main(["quick=true", "checkpoint_every=0"])


def test_gradient_health_quick(tmp_path):
    rows = load("gradient_health").main(["quick=true", "tasks=[Hopper-v5]", f"out={tmp_path / 'g.json'}", "data=none"])
    labels = [r[1] for r in rows]
    assert labels == ["rk4 (file)", "euler", "implicit", "euler x2", "rk4 x2"]
    assert all(float(r[2]) > 0 for r in rows)  # a finite, non-zero actor gradient for every option


def test_gradient_health_reports_each_contact_gradient_mode(tmp_path):
    rows = load("gradient_health").main(["quick=true", "mode=contact_gradients", "tasks=[HalfCheetah-v5]",
                                         f"out={tmp_path / 'g.json'}", "data=none"])
    assert [r[1] for r in rows] == ["exact", "cfd", "smooth", "penalty"]
    assert all(0 < float(r[2]) < float("inf") for r in rows)
    assert len({r[4] for r in rows}) == 1  # the same forward: the same largest contact force in every mode


def test_contact_fidelity_still_return_matches_gymnasium():
    """A still Hopper (zero action, the task's own reset noise) earns gymnasium's healthy bonus of 1 per
    step and almost nothing else, in MuJoCo and here: about 20 over 20 steps."""
    theirs, ours = load("contact_fidelity").still_return("Hopper-v5", episodes=2, steps=20)
    assert theirs == pytest.approx(20, abs=1.0) and ours == pytest.approx(theirs, abs=0.5)


def test_gradient_horizon_agrees_with_finite_differences_on_a_short_window(tmp_path):
    # over two Hopper steps the analytic gradient is the local slope (a directional finite
    # difference along it gives |grad|) and points where the smoothed return rises
    rows = load("gradient_horizon").main(["tasks=[Hopper-v5]", "horizons=[2]", "starts=2", "samples=64", "warmup=5",
                                          "modes=[exact]", f"out={tmp_path / 'h.json'}", "data=none"])
    (task, horizon, mode, norm, cos, _ceiling, local, _gain), = rows
    assert (task, horizon, mode) == ("Hopper-v5", "2", "exact") and float(norm) > 0
    assert abs(float(local) - 1.0) < 0.05
    assert float(cos.split()[0]) > 0.5


def test_compile_physics_renders_one_data_file_from_earlier_runs(tmp_path):
    """Rows of several raw result files (e.g. float32 and float64) in the given order, the machine
    and date they were measured on, and their commands without the local out=/data= paths."""
    def raw(name, command, rows, date):
        path = tmp_path / name
        path.write_text(json.dumps({"benchmark": "compile_physics", "date": date,
                                    "info": {"machine": "2-vCPU Test CPU (x86_64), 1 torch thread",
                                             "command": command}, "results": rows}))
        return str(path)

    row = {"task": "Ant-v5", "N": 64, "mode": "bptt", "eager_steps_per_s": 400.0, "compiled_steps_per_s": 720.0,
           "ratio": 1.8, "compile_s": 160.0, "granularity": "physics step", "max_abs_diff_first_step": 3.6e-15,
           "max_abs_diff": 2.8e-11, "grad_rel_diff": 9.1e-12, "grad_rel_diff_rounding": 0.091, "dtype": "float64",
           "aten_ops_per_env_step": {"eager": 30961.7, "compiled": 2076.4}}
    failed = {"task": "HalfCheetah-v5", "N": 1024, "mode": "rollout", "error": "still compiling after 5 s"}
    first = raw("f32.json", "compile_physics.py tasks=[HalfCheetah-v5] data=none out=/tmp/x/f32.json", [failed],
                "2026-01-01")
    second = raw("f64.json", "compile_physics.py tasks=[Ant-v5] dtype=float64 out=/tmp/x/f64.json", [row], "2026-01-02")
    target = tmp_path / "data.json"
    load("compile_physics").main([f"from_results=[{first},{second}]", f"data={target}"])
    data = json.loads(target.read_text())
    assert data["measured"] == "2026-01-02"
    assert data["machine"] == "2-vCPU Test CPU (x86_64), 1 torch thread"
    assert data["command"] == ("python benchmarks/compile_physics.py tasks=[HalfCheetah-v5]; "
                               "python benchmarks/compile_physics.py tasks=[Ant-v5] dtype=float64")
    rows = data["tables"]["compile_physics"]["rows"]
    assert [r[0] for r in rows] == ["HalfCheetah-v5", "Ant-v5"]
    assert rows[0][-3] == "still compiling after 5 s"
    assert rows[1][3:7] == ["float64", "400", "720", "1.8x"]
    assert rows[1][-2:] == ["9.1e-12 / 0.091", "30962 / 2076"]


@pytest.mark.parametrize("ops_steps", [3, 0, -8])
def test_compile_physics_counts_ops_over_whole_chunks_only(ops_steps):
    """Steps beyond whole chunks run eagerly, so an op count over them would be eager's."""
    with pytest.raises(SystemExit, match=rf"ops_steps={ops_steps}: expected a multiple of chunk=8"):
        load("compile_physics").main([f"ops_steps={ops_steps}"])


def test_gymnasium_baseline_quick_trains_on_both_backends(tmp_path):
    """Tuned PPO on our env and on Gymnasium's own, back to back: the gymnasium-backed run's
    evaluation is Gymnasium's return, so its ``eval/gymnasium_return`` is its ``eval/return``."""
    payload = load("gymnasium_baseline").main(["quick=true", f"out={tmp_path / 'gb.json'}"])
    runs = {r["backend"]: r for r in payload["runs"]}
    assert set(runs) == {"torchrl_diffenvs", "gymnasium"}
    for run in runs.values():
        assert run["env_steps"] == 64 and run["steps_per_s"] > 0
    assert runs["gymnasium"]["eval/gymnasium_return"] == runs["gymnasium"]["eval/return"]


def test_contact_model_writes_the_parts_it_measured(tmp_path, monkeypatch):
    """The speed part alone (``parity_tasks=[]``) writes a data file with the speed table only: a
    part not measured leaves no empty table behind (the measurement itself is the benchmark's run:
    here a canned one)."""
    pytest.importorskip("mujoco")
    bench = load("contact_model")
    rates = {key: {"median": rate} for key, rate in (("mujoco step", 400.0), ("smooth step", 1000.0),
                                                     ("mujoco window", 100.0), ("smooth window", 300.0))}
    monkeypatch.setattr(bench, "speed", lambda task, n, rounds: {
        "task": task, "N": n, "rates_cpu": rates, "ratio_mujoco_over_smooth": {"step": 0.4, "window": 1 / 3},
        "aten_ops_per_env_step": {"mujoco": 300, "smooth": 100}, "integrators": {"mujoco": "rk4", "smooth": "implicit"}})
    payload = bench.main(["quick=true", "parity_tasks=[]", "speed_tasks=[Ant-v5]", "compile=false",
                          f"out={tmp_path / 'cm.json'}", f"data={tmp_path / 'cm_data.json'}"])
    tables = json.loads((tmp_path / "cm_data.json").read_text())["tables"]
    assert list(tables) == ["speed"] and payload["parity"] == []
    assert tables["speed"]["rows"] == [["Ant-v5", "16", "rk4 / implicit", "400", "1k", "0.4x", "100", "300", "0.333x",
                                        "300 / 100", "- / -"]]
    with pytest.raises(SystemExit, match="name it with data=<name>"):
        bench.main(["parity_tasks=[]", f"out={tmp_path / 'x.json'}"])


def test_contact_model_speed_times_both_models_with_the_integrator_a_task_names():
    pytest.importorskip("mujoco")
    measured = load("contact_model").speed("HalfCheetah-v5:implicit", 2, 1)
    assert measured["task"] == "HalfCheetah-v5:implicit"
    assert measured["integrators"] == {"mujoco": "implicit", "smooth": "implicit"}  # the file's is Euler
    assert all(rate["median"] > 0 for rate in measured["rates_cpu"].values())
