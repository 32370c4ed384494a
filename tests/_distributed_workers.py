"""What runs inside the processes that tests/training/test_distributed.py starts (gloo, one thread each).

Each worker joins a process group through a file store, does its part and writes what the test
compares to ``<out>/rank<r>.pt``.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import torch
import torch.distributed as dist
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_diffenvs import make_env
from torchrl_diffenvs.distributed import SINGLE_PROCESS, DistributedError, World
from torchrl_diffenvs.learners import make_learner

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ENV_SEEDS = (11, 22)  # rank r's envs; the single-process reference starts from the same states
SMALL_NETS = {"hidden": [16, 16]}


def loss_config(name: str, **settings):
    """The ``loss=<name>`` section (the learner's defaults) with small networks and ``settings`` on top."""
    from torchrl_diffenvs.learners import LEARNERS

    cfg = OmegaConf.create(LEARNERS[name].default_config()["loss"])
    for network in ("actor", "critic", "qvalue"):
        if network in cfg:
            cfg[network].hidden = SMALL_NETS["hidden"]
    return OmegaConf.merge(cfg, settings)


def build(loss: str, num_envs: int, env_seed: int, world: World = SINGLE_PROCESS, **settings):
    """A float64 pendulum learner; the same networks in every process (seeded before building)."""
    torch.manual_seed(0)
    env = make_env("pendulum", num_envs=num_envs, seed=env_seed, dtype=torch.float64)
    return make_learner(loss_config(loss, **settings), env, 10**6, world)


def join(rank: int, size: int, store: str, timeout_s: float = 60.0) -> World:
    import datetime

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=size,
                            timeout=datetime.timedelta(seconds=timeout_s))
    return World(size=size, rank=rank, backend="gloo")


def without_action_noise() -> None:
    """Sampled actions become the distributions' means (zero standard-normal noise), so that a
    loss is a deterministic function of its batch, whichever process draws."""
    import torch.distributions.normal

    import torchrl_diffenvs.modules.actors

    def zeros(shape, dtype, device):
        return torch.zeros(shape, dtype=dtype, device=device)

    torch.distributions.normal._standard_normal = zeros
    torchrl_diffenvs.modules.actors.standard_normal = zeros  # where the policies draw their noise


# ---------------------------------------------------------------------- workers
def train_rank(rank, size, store, out, cases, num_envs, iterations):
    """For each ``{loss: settings}`` of ``cases`` in turn (one process group: starting the
    processes costs more than the training), ``iterations`` training iterations on this rank's
    envs; saves ``{loss: the learner's state}``."""
    world = join(rank, size, store)
    states = {}
    for loss, settings in cases.items():
        learner = build(loss, num_envs, ENV_SEEDS[rank], world, **settings)
        torch.manual_seed(100 + rank)  # each rank's own streams (minibatch order)
        for _ in range(iterations):
            learner.train_iteration()
        states[loss] = learner.state_dict()
    torch.save(states, Path(out) / f"rank{rank}.pt")
    dist.destroy_process_group()


def gradient_rank(rank, size, store, out, cases, batch_size):
    """For each ``{loss: settings}`` of ``cases`` in turn, one ``gradient_step`` on this rank's
    share of a fixed batch; saves ``{loss: the gradients it stepped with, the parameters after
    the step}``."""
    without_action_noise()
    world = join(rank, size, store)
    results = {}
    for loss, settings in cases.items():
        learner = build(loss, 4, ENV_SEEDS[rank], world, **settings)
        batch = fixed_batch(learner, loss, size * batch_size)
        params = step_parameters(learner, loss)
        stats = learner.gradient_step(batch[rank * batch_size:(rank + 1) * batch_size])
        results[loss] = {"grads": [p.grad.clone() for p in params], "params": [p.detach().clone() for p in params],
                         "stats": stats, "lr": lr_of(learner, loss)}
    torch.save(results, Path(out) / f"rank{rank}.pt")
    dist.destroy_process_group()


def lost_rank(rank, size, store, out):
    """Rank 1 dies right after joining; rank 0's next exchange must fail with a clear error."""
    world = join(rank, size, store, timeout_s=10.0)
    if rank == 1:
        os._exit(0)
    start = time.perf_counter()
    param = torch.zeros(3, requires_grad=True)
    param.grad = torch.ones(3)
    try:
        world.average_gradients([param])
        message = None
    except DistributedError as err:
        message = str(err)
    torch.save({"message": message, "seconds": time.perf_counter() - start}, Path(out) / "rank0.pt")
    # leave without tearing down: with its peer gone, destroying gloo's process group can abort the process
    # ("terminate called without an active exception") after the result above is saved
    os._exit(0)


# ---------------------------------------------------------------------- shared by workers and tests
def fixed_batch(learner, loss: str, size: int) -> TensorDict:
    """A batch of ``size`` transitions with everything the loss reads, the same in every process."""
    g = torch.Generator().manual_seed(5)
    f64 = torch.float64

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=f64)

    obs = torch.randn(size, 3, generator=g, dtype=f64)
    action = 3.8 * rand(size, 1) - 1.9  # inside the pendulum's [-2, 2]
    if loss == "sac":
        return TensorDict({
            "observation": obs, "action": action,
            "next": {"observation": torch.randn(size, 3, generator=g, dtype=f64), "reward": rand(size, 1) - 1,
                     "done": torch.zeros(size, 1, dtype=torch.bool), "terminated": torch.zeros(size, 1, dtype=torch.bool)},
        }, [size])
    batch = TensorDict({"observation": obs, "action": action}, [size])
    log_prob_key = learner.loss.tensor_keys.sample_log_prob
    with torch.no_grad():
        dist_ = learner.actor.get_dist(batch.clone())
        old_log_prob = dist_.log_prob(action) - 0.3 * rand(size)  # the data's policy was another one
    batch.set(log_prob_key, old_log_prob.reshape(size))
    batch.set("advantage", torch.randn(size, 1, generator=g, dtype=f64))
    batch.set("value_target", torch.randn(size, 1, generator=g, dtype=f64))
    batch.set("state_value", torch.randn(size, 1, generator=g, dtype=f64))
    return batch


def step_parameters(learner, loss: str) -> list[torch.Tensor]:
    """The parameters one ``gradient_step`` updates."""
    if loss == "sac":
        return learner.actor_params + learner.qvalue_params + [learner.loss.log_alpha]
    return learner.params


def lr_of(learner, loss: str) -> float:
    optim = learner.actor_optim if loss == "sac" else learner.optim
    return optim.param_groups[0]["lr"]
