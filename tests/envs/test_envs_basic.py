"""Construction, specs and registry of every env."""
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from torchrl_diffenvs import list_envs, make_env
from torchrl_diffenvs.envs import is_multi_agent

IVY_TASKS = ["cartpole", "pendulum", "mountaincar", "reacher", "swimmer"]


def test_list_envs_contains_ivy_tasks():
    assert set(IVY_TASKS) <= set(list_envs())


@pytest.mark.parametrize("name", list_envs())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_check_env_specs(name, dtype):
    env = make_env(name, num_envs=3, dtype=dtype, seed=0)
    check_env_specs(env)
    td = env.reset()
    if is_multi_agent(env):
        observation, shape = td["agents", "observation"], (3, env.num_agents, env.observation_dim)
    else:
        observation, shape = td["observation"], (3, env.observation_dim)
    assert observation.dtype == dtype
    assert observation.shape == shape


def test_unknown_env_lists_valid_names():
    with pytest.raises(ValueError, match="unknown env 'nope'.*pendulum"):
        make_env("nope")


def test_a_new_task_needs_only_physics():
    """The README's 'Writing a new task' example: a double integrator in a few lines."""
    from torchrl_diffenvs import DiffEnv

    class DoubleIntegratorEnv(DiffEnv):
        name = "double_integrator_test"
        action_dim = 1
        default_params = {"dt": 0.05}

        def initial_state(self, params, n):
            return {"x": self.uniform(-1, 1, n), "v": torch.zeros_like(params["dt"])}

        def transition(self, state, action, params):
            v = state["v"] + params["dt"] * action[..., 0]
            x = state["x"] + params["dt"] * v
            return {"x": x, "v": v}, torch.exp(-(x**2)), None

        def observation(self, state, params):
            return torch.stack([state["x"], state["v"]], -1)

    env = DoubleIntegratorEnv(4, dtype=torch.float64, seed=0)
    check_env_specs(env)
    td = env.reset()
    x0 = td["state", "x"].clone()
    action = torch.full((4, 1), 2.0, dtype=torch.float64, requires_grad=True)
    out = env.step(td.set("action", action))["next"]
    # hand-computed semi-implicit Euler step from rest: v = dt * a, x = x0 + dt * v
    torch.testing.assert_close(out["state", "x"], x0 + 0.05 * 0.05 * 2.0)
    torch.testing.assert_close(out["reward"].squeeze(-1), torch.exp(-(x0 + 0.005) ** 2))
    (grad,) = torch.autograd.grad(out["reward"].sum(), action)
    torch.testing.assert_close(grad.squeeze(-1), -2 * (x0 + 0.005) * torch.exp(-(x0 + 0.005) ** 2) * 0.05**2)
