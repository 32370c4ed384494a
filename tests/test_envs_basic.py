"""Construction, specs and registry of every env."""
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from torchrl_diffenvs import list_envs, make_env

IVY_TASKS = ["cartpole", "pendulum", "mountaincar", "reacher", "swimmer"]


def test_list_envs_contains_ivy_tasks():
    assert set(IVY_TASKS) <= set(list_envs())


@pytest.mark.parametrize("name", list_envs())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_check_env_specs(name, dtype):
    env = make_env(name, num_envs=3, dtype=dtype, seed=0)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].dtype == dtype
    assert td["observation"].shape == (3, env.observation_dim)


def test_unknown_env_lists_valid_names():
    with pytest.raises(ValueError, match="unknown env 'nope'.*pendulum"):
        make_env("nope")
