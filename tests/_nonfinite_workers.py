"""What runs inside the processes of tests/learners/test_nonfinite_envs.py's data-parallel test (gloo)."""
from __future__ import annotations

import warnings
from pathlib import Path

import torch
import torch.distributed as dist
from _distributed_workers import ENV_SEEDS, join, loss_config

from torchrl_diffenvs import make_env
from torchrl_diffenvs.learners import make_learner

SETTINGS = {
    "bptt": {"horizon": 4},
    "shac": {"horizon": 4},
    "ppo": {"rollout_len": 4, "minibatch_size": 8, "epochs": 2},
    "sac": {"rollout_len": 2, "init_random_frames": 0, "batch_size": 8, "buffer_size": 256},
}


def train_with_a_nan_env_on_rank_1(rank, size, store, out, losses, iterations):
    """Rank 1's env 2 has a NaN mass; every rank trains each loss of ``losses`` in turn (one
    process group: starting the processes costs more than the training) for ``iterations``
    iterations and saves its metrics and actor weights (which data parallelism keeps identical
    on every rank) to ``rank<r>_<loss>.pt``."""
    world = join(rank, size, store)
    for loss in losses:
        torch.manual_seed(0)  # the same networks on every rank
        env = make_env("pendulum", num_envs=4, seed=ENV_SEEDS[rank])
        if rank == 1:
            env.params["mass"][2] = float("nan")
        learner = make_learner(loss_config(loss, **SETTINGS[loss]), env, 10**6, world)
        torch.manual_seed(100 + rank)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            metrics = [learner.train_iteration() for _ in range(iterations)]
        torch.save({"metrics": metrics, "actor": [p.detach().clone() for p in learner.actor.parameters()]},
                   Path(out) / f"rank{rank}_{loss}.pt")
    dist.destroy_process_group()
