"""Small helpers shared by the test files: env lists and builders, the repository root and a
loader for the scripts under ``sota_scripts/`` and ``benchmarks/``.

Not a test module (the leading underscore keeps pytest from collecting it); ``tests/`` is on
``sys.path`` (see ``tests/conftest.py``), so the test files import it as ``_env_helpers``.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs.utils import step_mdp

from torchrl_diffenvs import list_envs, make_env

F64 = torch.float64
REPO = Path(__file__).resolve().parent.parent


def load_script(name: str, path: Path):
    """A script file (``sota_scripts/*.py``, ``benchmarks/*.py``) imported as the module ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


def multi_agent_envs() -> list[str]:
    """The registered tasks with TorchRL's ``("agents", ...)`` layout (tests/envs/test_multi_agent.py)."""
    from torchrl_diffenvs.envs import MultiAgentDiffEnv, env_class

    return [name for name in list_envs() if issubclass(env_class(name), MultiAgentDiffEnv)]


def single_agent_envs() -> list[str]:
    """Every registered env whose policy reads ``"observation"`` and writes ``"action"``."""
    multi = set(multi_agent_envs())
    return [name for name in list_envs() if name not in multi]


def classic_envs() -> list[str]:
    """Every single-agent env but the MuJoCo-model tasks.

    The table-driven suites (behaviour, composition, gradients, rendering) describe these tasks
    one by one; the MuJoCo-model tasks have their own suites (test_mujoco_parity.py,
    test_mujoco_gradients.py, test_rendering_mujoco.py) with MuJoCo and Gymnasium as the
    references, and the multi-agent tasks theirs (test_multi_agent.py).
    """
    from torchrl_diffenvs.envs.mujoco import MUJOCO_TASKS

    mujoco_names = {cls.name for cls in MUJOCO_TASKS}
    return [name for name in single_agent_envs() if name not in mujoco_names]


def is_gymnasium_variant(name: str) -> bool:
    """Gymnasium ids carry a version suffix ("CartPole-v1"); the Ivy-style names do not."""
    return "-v" in name


def make(name: str, num_envs: int, dtype=F64, seed: int = 0, **kwargs):
    """``make_env`` with float64 and a fixed seed as test defaults."""
    return make_env(name, num_envs=num_envs, dtype=dtype, seed=seed, **kwargs)


def in_spec_actions(env, *shape: int, fraction: float = 0.5, seed: int = 0) -> torch.Tensor:
    """Deterministic actions of shape ``[*shape, action_dim]`` strictly inside the action spec.

    ``fraction`` < 1 keeps them away from the bounds, where clipped variants have kinks.
    """
    gen = torch.Generator().manual_seed(seed)
    unit = torch.rand(*shape, env.action_dim, generator=gen, dtype=env.float_dtype) * 2 - 1
    mid = (env.action_high + env.action_low) / 2
    half = (env.action_high - env.action_low) / 2
    return mid + fraction * half * unit


def obs_weights(env, seed: int = 1) -> torch.Tensor:
    """Fixed random weights ``[obs_dim]`` for the test signal ``reward + w . next_obs``.

    CartPole-v1's reward is a constant ``+1``, so a gradient check of the reward alone could
    never fail there; adding a fixed linear function of the next observation makes every env's
    signal depend on its actions, state and parameters.
    """
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(env.observation_dim, generator=gen, dtype=env.float_dtype) + 0.5


def signal(traj: TensorDict, w: torch.Tensor) -> torch.Tensor:
    """Per step test signal ``reward + w . next_observation``; ``[N, T]`` for a rollout."""
    return traj["next", "reward"][..., 0] + (traj["next", "observation"] * w).sum(-1)


def start_td(env, state: dict, params: dict) -> TensorDict:
    """``env.reset(set_state=True)`` from the given state and per-env params (graph kept)."""
    td = TensorDict({"state": dict(state), "params": dict(params)}, batch_size=[env.num_envs])
    return env.reset(td, set_state=True)


def run_steps(env, td: TensorDict, actions: torch.Tensor) -> TensorDict:
    """Steps ``env`` with ``actions[:, t]`` for every ``t`` with plain ``env.step`` (no resets).

    Returns the stacked ``[N, T]`` trajectory, like ``env.rollout`` would.
    """
    out = []
    for t in range(actions.shape[1]):
        td = td.clone(False)
        td["action"] = actions[:, t]
        td = env.step(td)
        out.append(td)
        td = step_mdp(td)
    return torch.stack(out, dim=1)


def use_rollout_path(env, fast: bool):
    """Selects DiffEnv's lean rollout loop (``fast``) or TorchRL's ``EnvBase.rollout``."""
    assert hasattr(env, "use_fast_rollout"), "DiffEnv.use_fast_rollout is gone: update the tests"
    env.use_fast_rollout = fast
    return env


class ReplayPolicy:
    """A policy that plays a fixed action sequence ``[N, T, act_dim]``, one column per call."""

    def __init__(self, actions: torch.Tensor):
        self.actions = actions
        self.t = 0

    def __call__(self, td: TensorDict) -> TensorDict:
        td["action"] = self.actions[:, self.t]
        self.t += 1
        return td


def assert_same_tensordict(got, ref, path="root", exact=True):
    """Same structure, dtypes and values (bitwise when ``exact``, else to float64 rounding)."""
    assert type(got) is type(ref), f"{path}: {type(got).__name__} != {type(ref).__name__}"
    assert got.batch_size == ref.batch_size, f"{path}: batch size {got.batch_size} != {ref.batch_size}"
    assert got.names == ref.names, f"{path}: names {got.names} != {ref.names}"
    assert got.device == ref.device, f"{path}: device {got.device} != {ref.device}"
    assert set(got.keys()) == set(ref.keys()), f"{path}: keys differ by {set(got.keys()) ^ set(ref.keys())}"
    for key in ref.keys():
        x, y = got.get(key), ref.get(key)
        where = f"{path}/{key}"
        if isinstance(y, torch.Tensor):
            assert x.shape == y.shape and x.dtype == y.dtype, f"{where}: {x.shape} {x.dtype} != {y.shape} {y.dtype}"
            assert x.is_contiguous() == y.is_contiguous(), f"{where}: contiguity differs"
            if exact:
                assert torch.equal(x, y), f"{where}: values differ, max |diff| {(x.double() - y.double()).abs().max()}"
            else:
                torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-12, msg=where)
        else:
            assert_same_tensordict(x, y, where, exact)


def with_smooth_contact(make):
    """``make_env`` for the tests written for the smooth contact option: MuJoCo tasks get
    ``contact="smooth"`` unless a test names a contact model (MuJoCo's own is tested in
    tests/simulator/test_mujoco_contact.py)."""
    from torchrl_diffenvs.envs.mujoco.base import MuJoCoModelEnv
    from torchrl_diffenvs.envs.registry import env_class

    def build(name, *args, **kwargs):
        if issubclass(env_class(name), MuJoCoModelEnv):
            kwargs.setdefault("contact", "smooth")
        return make(name, *args, **kwargs)

    return build
