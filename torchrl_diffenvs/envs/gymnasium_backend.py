"""Gymnasium's own env behind the surface the training loop expects of this library's envs.

``python sota_scripts/train.py env=HalfCheetah-v5 loss=ppo env.backend=gymnasium`` trains on
Gymnasium's env itself (for a MuJoCo task: MuJoCo's forward, no gradients): the baseline a user
would otherwise run, on the same machine, with the same learner, networks and settings.
`GymnasiumBackedEnv` is the one adapter that makes it fit the loop:

* the batch is Gymnasium's ``SyncVectorEnv`` of ``num_envs`` envs, each exactly
  ``gymnasium.make(env_id)``, wrapped by TorchRL's ``GymWrapper`` (``torchrl.envs.libs.gym``) with
  Gymnasium's auto-reset disabled: TorchRL resets the envs that are done (``reset_mask``), so
  ``("next", "observation")`` of a done step is its true last observation. TorchRL's
  ``GymEnv(num_envs=N)`` builds an ``AsyncVectorEnv`` (one process per env) and
  ``ParallelEnv`` one process per worker: on one or two cores both are several times slower
  than the in-process vector env (numbers in ``docs/training/index.md``);
* observations (Gymnasium's float64) and actions are cast to the run's ``dtype``; the reward is
  Gymnasium's, as TorchRL's float32;
* `set_seed` seeds the *next* full reset: env ``i`` then starts as
  ``gymnasium.make(env_id).reset(seed=seed + i)`` does, and later episodes continue its own
  random stream (as Gymnasium's vector env does); ``rng`` is a torch generator for the loop's
  random-action baseline;
* ``max_episode_steps`` is the Gymnasium registration's (or the override);
* `simulator_state` / `load_simulator_state` capture the simulator state the
  TensorDicts do not hold (MuJoCo's integration state, the time limits' counters, each env's
  random stream), so that a resumed run continues exactly;
* `record_video` films an episode with Gymnasium's own renderer (MuJoCo needs an OpenGL
  backend: ``MUJOCO_GL=egl`` on a headless machine).

Only gradient-free learners can train on it (`GRADIENT_FREE_LOSSES`): the others
differentiate through the simulation, which Gymnasium's env cannot.
"""
from __future__ import annotations

import copy
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torchrl.envs import Compose, DTypeCastTransform, TransformedEnv
from torchrl.envs.libs.gym import GymWrapper
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["ENV_BACKENDS", "GRADIENT_FREE_LOSSES", "GymnasiumBackedEnv", "gymnasium_env_problems"]

#: ``env.backend`` of the training script: this library's differentiable env, or Gymnasium's own
ENV_BACKENDS = ("torchrl_diffenvs", "gymnasium")
#: the learners that need no gradient through the env, so can train on ``env.backend=gymnasium``
GRADIENT_FREE_LOSSES = ("ppo", "sac")


def gymnasium_env_problems(env_id: str, options: Mapping | None = None) -> list[str]:
    """Why Gymnasium's env ``env_id`` with this library's task ``options`` cannot be the training
    env (one line each; empty when it can): not registered in Gymnasium, MuJoCo missing, an option
    Gymnasium's env lacks, or actions that are not continuous (``CartPole-v1``).

    Args:
        env_id: a Gymnasium id, e.g. ``"HalfCheetah-v5"``.
        options: this library's ``env.options`` (simulator and gradient options are dropped).
    """
    import importlib.util

    from ..evaluation import gymnasium_kwargs

    try:
        import gymnasium

        gymnasium.spec(env_id)
    except ImportError:
        return ["env.backend=gymnasium needs Gymnasium: pip install gymnasium (and \"torchrl_diffenvs[mujoco]\" for "
                "the MuJoCo tasks)"]
    except Exception:  # gymnasium's NameNotFound / VersionNotFound
        return [f"env.backend=gymnasium: env {env_id!r} is not one of Gymnasium's registered envs (the MuJoCo and "
                "classic-control tasks are, e.g. HalfCheetah-v5)"]
    if env_id.endswith("-v5") and importlib.util.find_spec("mujoco") is None:
        return [f"env.backend=gymnasium: Gymnasium's {env_id!r} needs MuJoCo: pip install \"torchrl_diffenvs[mujoco]\""]
    try:
        kwargs = gymnasium_kwargs(env_id, dict(options or {}))
    except ValueError as err:
        return [f"env.backend=gymnasium: {err}"]
    env = gymnasium.make(env_id, **kwargs)
    space = env.action_space
    env.close()
    if not isinstance(space, gymnasium.spaces.Box):
        return [f"env.backend=gymnasium: Gymnasium's {env_id!r} takes {space} actions; the learners' policies write "
                "continuous actions (a Box action space)"]
    return []


def _wrapper(env, cls):
    """The first wrapper of class ``cls`` around a Gymnasium env (``None`` if none)."""
    while env is not None:
        if isinstance(env, cls):
            return env
        env = getattr(env, "env", None)
    return None


class GymnasiumBackedEnv(TransformedEnv):
    """A batch of Gymnasium's own env ``env_id`` as a TorchRL env with this library's env surface.

    Args:
        env_id: a Gymnasium id with continuous actions, e.g. ``"HalfCheetah-v5"``.
        num_envs: envs in the batch (Gymnasium's ``SyncVectorEnv``, in this process).
        device: where the TensorDicts live (the simulation runs on the CPU).
        dtype: ``torch.float32`` or ``torch.float64``: of the observations and actions the policy sees.
        seed: seeds the first reset (env ``i`` with ``seed + i``) and `rng`; ``None`` draws one
            from torch's global generator.
        max_episode_steps: Gymnasium's time limit; ``None``: its registration's.
        options: this library's task options (``env.options``); those Gymnasium's env takes are
            passed to ``gymnasium.make``, the simulator's and the backward's are dropped
            (`gymnasium_kwargs`).

    Raises:
        ValueError: ``env_id`` cannot be trained in Gymnasium (`gymnasium_env_problems`).
    """

    def __init__(self, env_id: str, num_envs: int = 1, *, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32, seed: int | None = None, max_episode_steps: int | None = None,
                 options: Mapping | None = None):
        import gymnasium

        from ..evaluation import gymnasium_kwargs

        problems = gymnasium_env_problems(env_id, options)
        if problems:
            raise ValueError("; ".join(problems))
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"{env_id}: num_envs must be an integer >= 1, got {num_envs!r}")
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"{env_id}: dtype must be torch.float32 or torch.float64, got {dtype}")
        kwargs = gymnasium_kwargs(env_id, dict(options or {}))
        if max_episode_steps is not None:
            kwargs["max_episode_steps"] = int(max_episode_steps)

        def make():
            return gymnasium.make(env_id, **kwargs)

        vector = gymnasium.vector.SyncVectorEnv([make] * num_envs,
                                                autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED)
        base = GymWrapper(vector, device=device)
        casts = []
        observation = base.observation_spec["observation"]
        if observation.dtype != dtype:
            casts.append(DTypeCastTransform(observation.dtype, dtype, in_keys=["observation"]))
        action = base.full_action_spec[base.action_key]
        if action.dtype != dtype:  # the policy writes the run's dtype; Gymnasium gets its own
            casts.append(DTypeCastTransform(action.dtype, dtype, in_keys_inv=[base.action_key]))
        super().__init__(base, Compose(*casts))
        self.env_id = env_id
        self.vector_env = vector
        self.num_envs = num_envs
        self.float_dtype = dtype
        self.max_episode_steps = vector.envs[0].spec.max_episode_steps
        self.gymnasium_kwargs = kwargs
        self.rng = torch.Generator(device=self.device)
        if seed is None:
            seed = int(torch.randint(0, 2**62, (), dtype=torch.int64).item())
        self._pending_seed: int | None = None
        self.set_seed(seed)

    # ------------------------------------------------------------------ seeding and resets
    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """The next full reset starts env ``i`` from ``seed + i`` (not at once: TorchRL's
        ``GymWrapper`` would reset now, and the rollout's own reset would then start other
        episodes); `rng` restarts from ``seed``. Torch's global generator is untouched.

        Args:
            seed: the seed; ``None`` changes nothing.
            static_seed: unused (TorchRL's signature).

        Returns:
            ``seed``.
        """
        if seed is not None:
            self._pending_seed = int(seed)
            self.rng.manual_seed(int(seed))
        return seed

    def _reset(self, tensordict=None, **kwargs):
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if self._pending_seed is not None and (reset is None or bool(reset.all())):
            kwargs["seed"], self._pending_seed = self._pending_seed, None
            if tensordict is not None:  # a full reset: Gymnasium's reset(seed=...) without a mask
                tensordict = tensordict.exclude("_reset")
        return super()._reset(tensordict, **kwargs)

    # ------------------------------------------------------------------ resuming exactly
    def simulator_state(self) -> dict:
        """What a checkpoint needs beyond the TensorDicts to continue these envs exactly: each
        env's simulator state (MuJoCo's integration state: positions, velocities, activations,
        warm start, time), its time limit's step count, its reset flag and its random stream,
        plus `rng` and a pending seed. For an env that is not a MuJoCo env, ``"envs"`` is
        ``None`` and ``"unsupported"`` says why (`load_simulator_state` then refuses)."""
        import mujoco
        from gymnasium.envs.mujoco import MujocoEnv
        from gymnasium.wrappers import OrderEnforcing, TimeLimit

        out = {"envs": [], "rng": self.rng.get_state(), "pending_seed": self._pending_seed}
        for env in self.vector_env.envs:
            sim = env.unwrapped
            if not isinstance(sim, MujocoEnv):
                return {**out, "envs": None, "unsupported": f"the state of Gymnasium's {self.env_id!r} "
                        f"({type(sim).__name__}, not a MuJoCo env) is not saved in checkpoints"}
            kind = mujoco.mjtState.mjSTATE_INTEGRATION
            state = np.empty(mujoco.mj_stateSize(sim.model, kind))
            mujoco.mj_getState(sim.model, sim.data, state, kind)
            limit, order = _wrapper(env, TimeLimit), _wrapper(env, OrderEnforcing)
            out["envs"].append({
                "mujoco": torch.from_numpy(state),
                "elapsed_steps": None if limit is None else limit._elapsed_steps,
                "has_reset": None if order is None else order._has_reset,
                "np_random": copy.deepcopy(sim.np_random.bit_generator.state),
            })
        return out

    def load_simulator_state(self, state: Mapping) -> None:
        """Restores `simulator_state` into envs built with the same ``env_id`` and ``num_envs``.

        Args:
            state: what `simulator_state` returned.

        Raises:
            ValueError: ``state`` holds no simulator state (a non-MuJoCo env, or a checkpoint
                written without it) or another number of envs.
        """
        import mujoco
        from gymnasium.wrappers import OrderEnforcing, TimeLimit

        if state is None or state.get("envs") is None:
            why = (state or {}).get("unsupported", "the checkpoint holds no Gymnasium simulator state")
            raise ValueError(f"env.backend=gymnasium cannot resume exactly: {why}; start a new run instead")
        if len(state["envs"]) != self.num_envs:
            raise ValueError(f"env.backend=gymnasium: the saved state holds {len(state['envs'])} envs, this batch "
                             f"{self.num_envs}; resume with env.num_envs={len(state['envs'])}")
        kind = mujoco.mjtState.mjSTATE_INTEGRATION
        for env, saved in zip(self.vector_env.envs, state["envs"], strict=True):
            sim = env.unwrapped
            mujoco.mj_setState(sim.model, sim.data, saved["mujoco"].cpu().numpy(), kind)
            limit, order = _wrapper(env, TimeLimit), _wrapper(env, OrderEnforcing)
            if limit is not None:
                limit._elapsed_steps = saved["elapsed_steps"]
            if order is not None:
                order._has_reset = saved["has_reset"]
            sim.np_random.bit_generator.state = saved["np_random"]
        self.rng.set_state(state["rng"].cpu())
        self._pending_seed = state["pending_seed"]

    # ------------------------------------------------------------------ video
    def record_video(self, policy, steps: int, seed: int, path: str | Path, env_index: int = 0, fps: int = 30,
                     size: int = 256, exploration_type: ExplorationType = ExplorationType.DETERMINISTIC) -> Path:
        """Films ``policy`` playing one episode (at most ``steps`` steps) of Gymnasium's env from
        ``seed + env_index`` (the start state of env ``env_index`` after ``set_seed(seed)``), drawn
        by Gymnasium's own renderer, and writes it to ``path`` (``.gif`` or ``.mp4``).

        Needs Pillow (the ``render`` extra) and, for a MuJoCo env, an OpenGL backend
        (``MUJOCO_GL=egl`` on a machine without a display).
        """
        import gymnasium
        from tensordict import TensorDict

        from ..rendering import save_video

        env = gymnasium.make(self.env_id, render_mode="rgb_array", width=size, height=size, **self.gymnasium_kwargs)
        try:
            observation, _ = env.reset(seed=seed + env_index)
            frames = [env.render()]
            for _ in range(steps):
                td = TensorDict({"observation": torch.as_tensor(observation, dtype=self.float_dtype,
                                                                device=self.device).unsqueeze(0)},
                                batch_size=[1], device=self.device)
                with torch.no_grad(), set_exploration_type(exploration_type):
                    action = policy(td).get(self.action_key)[0].detach().cpu().double().numpy()
                observation, _, terminated, truncated, _ = env.step(action)
                frames.append(env.render())
                if terminated or truncated:
                    break
        finally:
            env.close()
        return save_video(frames, path, fps=fps)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.env_id!r}, num_envs={self.num_envs}, dtype={self.float_dtype}, "
                f"max_episode_steps={self.max_episode_steps})")
