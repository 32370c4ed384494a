"""Data-parallel training: 2 gloo processes on this machine against one process.

* bptt and shac: 2 ranks x N envs take exactly the steps of one process with 2N envs started
  from the same states (float64);
* ppo and sac: the gradient a rank steps with (averaged over the ranks) is the single-process
  gradient on the concatenated batch; PPO's advantage standardisation, value normaliser and
  adaptive learning rate included;
* a lost rank fails the others with a clear error instead of a hang;
* ``torchrun ... sota_scripts/train.py``: trains PPO, SAC and SHAC, only rank 0 writes, a checkpoint holds
  every rank and resumes exactly; a killed rank stops the run, which then resumes.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

import _distributed_workers as workers
from torchrl_diffenvs.distributed import SINGLE_PROCESS, World, rank_seed
from torchrl_diffenvs.training import CheckpointError, load_checkpoint

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "sota_scripts" / "train.py"
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]

pytestmark = pytest.mark.skipif(not torch.distributed.is_available(), reason="torch.distributed is not available")


def spawn(worker, tmp_path: Path, *args, nprocs: int = 2) -> list[dict]:
    """Runs ``worker(rank, nprocs, store, out, *args)`` in ``nprocs`` fresh processes; returns what each saved."""
    store, out = tmp_path / "store", tmp_path / "out"
    out.mkdir(exist_ok=True)
    mp.spawn(worker, args=(nprocs, str(store), str(out), *args), nprocs=nprocs, join=True)
    return [torch.load(path, weights_only=False) for path in sorted(out.glob("rank*.pt"))]


def assert_same_tree(a, b, **tol):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_same_tree(a[key], b[key], **tol)
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_same_tree(x, y, **tol)
    elif isinstance(a, torch.Tensor):
        if tol:
            torch.testing.assert_close(a, b, **tol)
        else:
            assert torch.equal(a, b)
    else:
        assert a == b or (tol and isinstance(a, float) and abs(a - b) <= 1e-9 * max(1.0, abs(b))), (a, b)


# ---------------------------------------------------------------------- the World itself
def test_one_process_world_passes_everything_through():
    world = World()
    assert world is not SINGLE_PROCESS and world == SINGLE_PROCESS and world.is_main
    p = torch.ones(2, requires_grad=True)
    p.grad = torch.tensor([1.0, 2.0])
    world.average_gradients([p])
    assert torch.equal(p.grad, torch.tensor([1.0, 2.0]))
    x = torch.arange(6.0).reshape(3, 2)
    assert world.gather(x) is x and world.mean(2.5) == 2.5 and world.broadcast_object({"a": 1}) == {"a": 1}
    assert world.mean_metrics({"a": 1.0}) == {"a": 1.0} and world.gather_object(3) == [3]
    world.check_same("anything", "configuration")  # one rank always agrees with itself
    assert rank_seed(7, 0) == 7 and len({rank_seed(7, r) for r in range(4)} | {rank_seed(8, r) for r in range(4)}) == 8


# ---------------------------------------------------------------------- exactness
EXACT = {
    "bptt": {"horizon": 8, "actor": {"distribution": "deterministic"}},
    # one critic minibatch: each rank's random split is then a mere reordering (see the module doc)
    "shac": {"horizon": 8, "critic_minibatches": 1, "critic_passes": 2, "actor": {"distribution": "deterministic"}},
}


def test_two_ranks_take_the_steps_of_one_process_with_all_their_envs(tmp_path):
    """BPTT and SHAC (in one pair of processes), deterministic policies (no action noise to split
    between processes) and windows shorter than an episode (no resets drawn from the envs'
    generators): the only randomness is each rank's start states, which the reference is given."""
    n, iterations = 4, 3
    ranks = spawn(workers.train_rank, tmp_path, EXACT, n, iterations)
    for loss, settings in EXACT.items():
        reference = workers.build(loss, 2 * n, 0, **settings)
        starts = [workers.make_env("pendulum", num_envs=n, seed=seed, dtype=torch.float64).reset()
                  for seed in workers.ENV_SEEDS]
        reference.collector.reset(torch.cat(starts, 0), set_state=True)
        for _ in range(iterations):
            reference.train_iteration()
        expected = reference.state_dict()
        states = [rank[loss] for rank in ranks]

        networks = ("actor", "actor_optimizer") if loss == "bptt" else ("loss", "optimizers")
        for key in networks:
            assert_same_tree(states[0][key], states[1][key])  # identical on every rank, bit for bit
            assert_same_tree(states[0][key], expected[key], rtol=1e-9, atol=1e-12)
        # the observation normaliser saw every rank's observations
        counts = {k: v.item() for k, v in states[0][networks[0]].items() if k.endswith("count")}
        assert counts and 2 * n * settings["horizon"] * iterations in counts.values(), (loss, counts)
        # each rank carries its own envs on: the reference's are theirs, side by side
        carried = torch.cat([torch.as_tensor(s["collector"]["carried"]["state"]["th"]) for s in states])
        torch.testing.assert_close(carried, torch.as_tensor(expected["collector"]["carried"]["state"]["th"]),
                                   rtol=1e-9, atol=1e-12)


GRADIENT_CASES = {
    "ppo": {"normalize_advantage": True, "value_normalization": True, "clip_value": True,
            "lr_schedule": "adaptive", "bounds_loss_coef": 0.1},
    "sac": {},
}


def test_the_averaged_gradient_is_the_gradient_of_the_concatenated_batch(tmp_path, monkeypatch):
    """PPO and SAC (in one pair of processes): each rank's step on its half of a fixed batch takes
    the gradient and the step of one process on the whole batch."""
    batch_size = 8
    ranks = spawn(workers.gradient_rank, tmp_path, GRADIENT_CASES, batch_size)

    monkeypatch.setattr(torch.distributions.normal, "_standard_normal", lambda shape, dtype, device:
                        torch.zeros(shape, dtype=dtype, device=device))
    import torchrl_diffenvs.modules.actors
    monkeypatch.setattr(torchrl_diffenvs.modules.actors, "standard_normal", lambda shape, dtype, device:
                        torch.zeros(shape, dtype=dtype, device=device))
    for loss, settings in GRADIENT_CASES.items():
        reference = workers.build(loss, 4, 0, **settings)
        params = workers.step_parameters(reference, loss)
        reference.gradient_step(workers.fixed_batch(reference, loss, 2 * batch_size))

        expected_grads = [p.grad for p in params]
        assert any(g.abs().max() > 1e-3 for g in expected_grads), loss  # a gradient that says something
        results = [rank[loss] for rank in ranks]
        for result in results:
            assert_same_tree(result["grads"], results[0]["grads"])
            assert_same_tree(result["params"], results[0]["params"])
            assert_same_tree(result["grads"], expected_grads, rtol=1e-9, atol=1e-12)
            assert_same_tree(result["params"], [p.detach() for p in params], rtol=1e-9, atol=1e-12)
            assert result["lr"] == pytest.approx(workers.lr_of(reference, loss), rel=1e-12)


def test_a_lost_rank_fails_the_others_with_a_clear_error(tmp_path):
    (rank0,) = spawn(workers.lost_rank, tmp_path)
    assert rank0["message"] is not None, "the exchange with a dead rank did not fail"
    assert "a rank died or stalled" in rank0["message"] and "resume=" in rank0["message"]
    assert rank0["seconds"] < 30  # the 10 s timeout, not a hang


# ---------------------------------------------------------------------- torchrun + train.py
RUN = ["env=pendulum", "env.num_envs=4", "env.max_episode_steps=12", "eval.num_envs=2", "eval.gif=false",
       "logger=none", "train.progress_bar=false", "eval.interval=1000000"]
TINY = {
    "bptt": ["loss.horizon=4", "loss.actor.hidden=[16]"],
    "shac": ["loss.horizon=4", "loss.actor.hidden=[16]", "loss.critic.hidden=[16]"],
    "ppo": ["loss.rollout_len=4", "loss.epochs=2", "loss.minibatch_size=8", "loss.actor.hidden=[16]",
            "loss.critic.hidden=[16]", "loss.value_normalization=true", "loss.lr_schedule=adaptive"],
    "sac": ["loss.rollout_len=2", "loss.init_random_frames=16", "loss.batch_size=8", "loss.buffer_size=256",
            "loss.actor.hidden=[16]", "loss.qvalue.hidden=[16]"],
}
GLOBAL_STEPS_PER_ITERATION = {"bptt": 32, "shac": 32, "ppo": 32, "sac": 16}  # 2 ranks x 4 envs x length


def torchrun(cwd: Path, *overrides: str, timeout: float = 240, env_extra: dict | None = None):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), **(env_extra or {})}
    return subprocess.run([*TORCHRUN, str(SCRIPT), *overrides], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


def assert_two_rank_run(tmp_path: Path, run_dir: Path, loss: str) -> None:
    """A finished 4-iteration two-rank run: only rank 0 wrote, the checkpoint holds both ranks,
    the networks are the same on both ranks and each rank's envs are its own."""
    steps = GLOBAL_STEPS_PER_ITERATION[loss]
    assert sorted(p.name for p in tmp_path.iterdir()) == [run_dir.name]  # rank 1 wrote nothing (no Hydra dir either)
    result = json.loads((run_dir / "final_metrics.json").read_text())
    assert result["world_size"] == 2 and result["env_steps"] == 4 * steps and result["iterations"] == 4
    ckpt = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert ckpt["world_size"] == 2 and len(ckpt["other_ranks"]) == 1
    assert ckpt["config"]["distributed"]["world_size"] == 2 and ckpt["config"]["distributed"]["backend"] == "gloo"
    assert "data parallel: 2 ranks (gloo)" in (run_dir / "train.log").read_text()
    mine, other = ckpt["learner"], ckpt["other_ranks"][0]["learner"]
    network = "actor" if loss == "bptt" else "loss"
    assert_same_tree(mine[network], other[network])
    if loss in ("bptt", "shac"):
        assert not torch.equal(mine["collector"]["carried"]["observation"], other["collector"]["carried"]["observation"])
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [row["env_steps"] for row in rows if "train/reward" in row] == [steps * i for i in (1, 2, 3, 4)]


# BPTT's run is SHAC's actor without the critic (its data-parallel step is checked exactly above);
# SHAC's run is the first run of the resume test below
@pytest.mark.parametrize("loss", ["ppo", "sac"])
def test_torchrun_trains_with_two_ranks_and_only_rank_zero_writes(loss, tmp_path):
    steps = GLOBAL_STEPS_PER_ITERATION[loss]
    run_dir = tmp_path / "run"
    done = torchrun(tmp_path, *RUN, f"loss={loss}", *TINY[loss], f"train.total_env_steps={4 * steps}",
                    f"train.checkpoint_interval={2 * steps}", f"hydra.run.dir={run_dir}")
    assert done.returncode == 0, done.stderr[-3000:]
    assert_two_rank_run(tmp_path, run_dir, loss)


def test_a_two_rank_run_resumes_exactly_and_only_with_two_ranks(tmp_path):
    """SHAC trained with two ranks (checked as the other losses above), then resumed from its
    middle checkpoint: the same networks and envs as the run that went through."""
    steps = GLOBAL_STEPS_PER_ITERATION["shac"]
    common = [*RUN, "loss=shac", *TINY["shac"], f"train.total_env_steps={4 * steps}",
              f"train.checkpoint_interval={2 * steps}", "train.keep_checkpoints=4"]
    whole = torchrun(tmp_path, *common, f"hydra.run.dir={tmp_path / 'a'}")
    assert whole.returncode == 0, whole.stderr[-3000:]
    assert_two_rank_run(tmp_path, tmp_path / "a", "shac")
    middle = tmp_path / "a" / "checkpoints" / f"ckpt_{2 * steps:012d}.pt"
    resumed = torchrun(tmp_path, *common, f"resume={middle}", f"hydra.run.dir={tmp_path / 'b'}")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a, b = (load_checkpoint(tmp_path / run / "checkpoints" / "last.pt") for run in ("a", "b"))
    assert_same_tree(a["learner"]["loss"], b["learner"]["loss"])
    assert_same_tree(a["other_ranks"][0]["learner"]["collector"], b["other_ranks"][0]["learner"]["collector"])

    # one process cannot continue two ranks' envs and streams: a clear error, nothing written
    sys.path.insert(0, str(ROOT / "tests"))
    from _train_helpers import make_cfg, train_script

    cfg = make_cfg(*common, f"resume={middle}")
    with pytest.raises(CheckpointError, match=r"written by 2 rank\(s\).*nproc_per_node=2"):
        train_script.run(cfg, tmp_path / "c")
    assert not (tmp_path / "c" / "checkpoints").exists()


def _workers_of(parent: int) -> dict[int, int]:
    """{rank: pid} of torchrun's worker processes: its children with a ``RANK`` (their own helper
    processes inherit the variable, but not the parent)."""
    found = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            environ = dict(item.split("=", 1) for item in (proc / "environ").read_text().split("\0") if "=" in item)
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and "RANK" in environ:
            found[int(environ["RANK"])] = int(proc.name)
    return found


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="finds the ranks' processes through /proc")
def test_a_killed_rank_stops_the_run_and_it_resumes_from_the_last_checkpoint(tmp_path):
    steps = GLOBAL_STEPS_PER_ITERATION["shac"]
    common = [*RUN, "loss=shac", *TINY["shac"], f"train.checkpoint_interval={2 * steps}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([*TORCHRUN, str(SCRIPT), *common, "train.total_env_steps=100000000",
                             f"hydra.run.dir={tmp_path / 'a'}"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    try:
        deadline = time.time() + 120
        while not last.exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert last.exists(), "no checkpoint was written"
        ranks = _workers_of(proc.pid)
        assert sorted(ranks) == [0, 1], ranks
        os.kill(ranks[1], signal.SIGKILL)
        killed_at = time.time()
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # leave no rank behind, whatever failed
            for pid in _workers_of(proc.pid).values():
                os.kill(pid, signal.SIGKILL)
            proc.kill()
    assert proc.returncode != 0
    assert time.time() - killed_at < 60  # torchrun stops rank 0 instead of leaving it waiting
    assert "rank      : 1" in output and "SIGKILL" in output, output[-3000:]

    at = load_checkpoint(last)["progress"]["env_steps"]
    resumed = torchrun(tmp_path, *common, f"resume={last}", f"train.total_env_steps={at + 2 * steps}",
                       f"hydra.run.dir={tmp_path / 'b'}")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    result = json.loads((tmp_path / "b" / "final_metrics.json").read_text())
    assert result["env_steps"] == at + 2 * steps and result["world_size"] == 2


def test_a_multirun_under_torchrun_is_refused(tmp_path):
    env = {**os.environ, "WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(SCRIPT), "-m", *RUN, "loss=bptt", "seed=0,1",
                           f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode != 0
    assert "cannot run under torchrun" in done.stderr + done.stdout
