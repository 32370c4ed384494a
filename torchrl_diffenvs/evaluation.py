"""Evaluation of a policy (deterministic by default) on separate envs, the random-policy
baseline, and the policy's GIF: the one evaluation module of the training script, the demos, the
benchmarks and the tests.

Given a ``seed``, every evaluation restarts the evaluation envs from it, so successive
evaluations (and runs with different training seeds) are scored on the same start states. Each
env plays one episode of ``steps`` steps; the score of an env is the undiscounted sum of rewards
up to and including the step where its first episode ends (termination or truncation): later
episodes, started by the auto-reset, are not counted. On a multi-agent env the score is the mean
over its agents of their returns.
"""
from __future__ import annotations

import inspect
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, set_exploration_type

from .envs.multi_agent import reward_per_env

__all__ = [
    "episode_returns", "evaluate", "evaluate_in_gymnasium", "evaluate_random", "first_episode_ends", "first_episode_mask",
    "gymnasium_kwargs", "record_video", "start_states", "uniform_random_policy",
]

#: Options of our tasks that choose how the physics is simulated or how the backward is shaped, not
#: what the task is: Gymnasium's env has none of them (it is MuJoCo's own forward, without gradients).
NOT_TASK_OPTIONS = frozenset({"contact", "integrator", "substeps", "contact_gradient", "cfrc_ext_gradient",
                              "healthy_gradient_width", "healthy_gradient_scale", "posture_gradient_scale",
                              "recompute_in_backward", "gradient_outlier_clip"})


def first_episode_mask(rollout: TensorDictBase) -> torch.Tensor:
    """``[N, T]`` float mask of the steps of each env's *first* episode in a rollout (up to and
    including its first ``("next", "done")``).

    Args:
        rollout: a ``[N, T]`` rollout (``env.rollout`` output) with ``("next", "done")``.
    """
    done = rollout.get(("next", "done"))[..., 0].to(torch.int64)
    ended_before = torch.cumsum(done, dim=-1) - done  # dones strictly before t
    return (ended_before == 0).to(torch.float64)


def first_episode_ends(rollout: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """``(length [N], terminated [N])`` of each env's *first* episode in a ``[N, T]`` rollout: its
    number of steps (``T`` if it did not end), and whether it ended by termination (a fall, a
    goal) rather than by truncation or the rollout's end.

    Args:
        rollout: a ``[N, T]`` rollout with ``("next", "done")`` and ``("next", "terminated")``.
    """
    in_first = first_episode_mask(rollout)
    length = in_first.sum(-1).long()
    last = (length - 1).clamp(max=rollout.shape[-1] - 1)
    terminated = rollout.get(("next", "terminated"))[..., 0].bool()
    return length, terminated[torch.arange(rollout.shape[0]), last]


def episode_returns(rollout: TensorDictBase, reward_key: NestedKey = "reward") -> torch.Tensor:
    """Per-env return of the *first* episode of a ``[N, T]`` rollout (later episodes ignored).

    Args:
        rollout: a ``[N, T]`` rollout.
        reward_key: the reward's key under ``"next"``; a multi-agent env's
            (``reward_key=("agents", "reward")``) return is the mean over its agents.
    """
    reward = reward_per_env(rollout, reward_key)
    return (reward * first_episode_mask(rollout).to(reward.dtype)).sum(-1)


def uniform_random_policy(env):
    """A policy writing uniformly random actions within the action spec, drawn from ``env.rng``
    (so it neither consumes nor disturbs torch's global generator).

    Args:
        env: the env whose bounded action spec (at ``env.action_key``) and ``rng`` the policy uses.
    """
    space = env.full_action_spec[env.action_key].space
    low, high = space.low, space.high

    def policy(td: TensorDictBase) -> TensorDictBase:
        u = torch.rand(low.shape, generator=env.rng, device=low.device, dtype=low.dtype)
        return td.set(env.action_key, low + (high - low) * u)

    return policy


def _rollout(env, policy, steps: int | None, seed: int | None, exploration: ExplorationType) -> TensorDictBase:
    steps = steps or env.max_episode_steps
    if steps is None:
        raise ValueError(f"evaluation: env {env!r} never truncates its episodes; pass steps=")
    if seed is not None:
        env.set_seed(seed)  # same start states at every evaluation
    with torch.no_grad(), set_exploration_type(exploration):
        return env.rollout(steps, policy, break_when_any_done=False)


def evaluate(env, policy, steps: int | None = None, seed: int | None = None, *, tail_steps: int = 20,
             exploration_type: ExplorationType = ExplorationType.DETERMINISTIC, per_env: bool = False) -> dict:
    """Scores ``policy`` on every env of ``env`` for one episode of ``steps`` steps (default: the
    env's ``max_episode_steps``), in deterministic mode (the mean action) by default.

    Args:
        env: the (batched) evaluation env.
        policy: the policy to score, as ``env.rollout`` takes it.
        steps: the rollout's length (default: the env's ``max_episode_steps``).
        seed: if given, the envs are reseeded with it first, so every evaluation starts from the same
            start states.
        tail_steps: the number of last steps ``tail_reward_mean`` averages over.
        exploration_type: the exploration mode the policy runs in (default: deterministic, the mean action).
        per_env: also return each env's ``returns`` and ``lengths`` (lists, env order).

    Returns:
        ``return`` (mean over envs of the first episode's return), ``return_std``,
        ``return_min``, ``return_max``, ``reward_mean`` (mean per-step reward over the steps of
        the first episodes) and ``tail_reward_mean`` (mean per-step reward of the last ``tail_steps``
        steps: how well a task is held once reached, e.g. a pendulum kept upright), ``episode_length``
        (the first episodes' mean length) and ``terminated`` (the fraction of them that ended by
        termination); on a two-player env (``player_wins``) also ``win_rate``: the fraction of first
        episodes the policy won against the env's opponent.
    """
    rollout = _rollout(env, policy, steps, seed, exploration_type)
    reward = reward_per_env(rollout, env.reward_key).double()  # the agents' mean on a multi-agent env
    in_first = first_episode_mask(rollout)
    returns = (reward * in_first).sum(-1)
    scores = {
        "return": returns.mean().item(),
        "return_std": returns.std(unbiased=False).item(),
        "return_min": returns.min().item(),
        "return_max": returns.max().item(),
        "reward_mean": (returns.sum() / in_first.sum()).item(),
        "tail_reward_mean": reward[:, -tail_steps:].mean().item(),
    }
    length, terminated = first_episode_ends(rollout)
    scores["episode_length"] = length.double().mean().item()
    scores["terminated"] = terminated.double().mean().item()
    if per_env:
        scores["returns"], scores["lengths"] = returns.tolist(), length.tolist()
    if hasattr(env, "player_wins"):  # a two-player env: did the policy beat the opponent in its first episode?
        last = in_first.sum(-1).long() - 1  # each env's last step of its first episode
        end = rollout.get("next")[torch.arange(rollout.shape[0]), last]
        scores["win_rate"] = env.player_wins(end.get("state"), end.get("params")).double().mean().item()
    return scores


def gymnasium_kwargs(env_id: str, options: dict | None = None) -> dict:
    """The keyword arguments of ``gymnasium.make(env_id, ...)`` that give Gymnasium's env the task
    of our env made with ``options``: the options Gymnasium's env class takes, by name. The
    options of the simulator and of the backward (``NOT_TASK_OPTIONS``: ``contact``,
    ``integrator``, ``contact_gradient``, the ``*_gradient*`` shaping options...) are dropped:
    Gymnasium's env is MuJoCo's forward.

    Args:
        env_id: the Gymnasium env id, e.g. ``"HalfCheetah-v5"``.
        options: our env's task options.

    Raises:
        ValueError: any other option (one Gymnasium's env class does not take), naming those it takes.
    """
    import gymnasium

    from gymnasium.envs.registration import load_env_creator

    entry = gymnasium.spec(env_id).entry_point
    entry = load_env_creator(entry) if isinstance(entry, str) else entry
    accepted = set(inspect.signature(entry.__init__).parameters) - {"self", "kwargs"}
    out = {}
    for key, value in (options or {}).items():
        if key in NOT_TASK_OPTIONS:
            continue
        if key not in accepted:
            raise ValueError(f"{env_id}: option {key!r} has no counterpart in Gymnasium's env, which takes "
                             f"{sorted(accepted)}; drop it to score the policy in Gymnasium's own task")
        out[key] = value
    return out


def start_states(env, seed: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(qpos [E, nq], qvel [E, nv])``, float64 on the CPU: the start states that
    [`evaluate`][torchrl_diffenvs.evaluation.evaluate] plays ``env``'s ``E`` episodes from with this
    ``seed``, for [`evaluate_in_gymnasium`][torchrl_diffenvs.evaluation.evaluate_in_gymnasium]'s
    ``start_states``: both envs then play every episode from the same state.

    Args:
        env: a MuJoCo task's (batched) evaluation env: its state holds ``qpos`` and ``qvel``.
        seed: the seed `evaluate` is given (it reseeds the env with it before its reset); ``None``
            takes the env's next reset as it stands (and consumes it).

    Raises:
        ValueError: ``env``'s state has no ``qpos`` and ``qvel`` (not a MuJoCo task).
    """
    if seed is not None:
        env.set_seed(seed)
    state = env.reset().get("state")
    if "qpos" not in state.keys() or "qvel" not in state.keys():
        raise ValueError(f"start_states: {type(env).__name__}'s state holds {sorted(state.keys())}, not MuJoCo's "
                         "qpos and qvel: the same start states can be set in Gymnasium's MuJoCo envs only")
    return state.get("qpos").detach().double().cpu(), state.get("qvel").detach().double().cpu()


def _start_from(env, qpos, qvel):
    """Gymnasium's MuJoCo env ``env`` (just reset) moved to ``(qpos, qvel)``: its observation there.
    ``_get_obs`` is the observation every Gymnasium MuJoCo env's ``reset_model`` returns after its
    own ``set_state``."""
    model = env.unwrapped
    model.set_state(qpos, qvel)
    return model._get_obs()


def evaluate_in_gymnasium(policy, env_id: str, episodes: int = 16, seed: int = 0, steps: int | None = None, *,
                          options: dict | None = None, dtype: torch.dtype = torch.float32, device="cpu",
                          observation_key: NestedKey = "observation", action_key: NestedKey = "action",
                          exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
                          start_states: tuple | None = None) -> dict:
    """Scores ``policy`` in Gymnasium's own env ``env_id`` (for a MuJoCo task: MuJoCo itself; needs
    the ``mujoco`` extra): ``episodes`` full episodes, episode ``i`` reset with seed ``seed + i``
    (or started from ``start_states``), each played to its termination or to its time limit
    (``steps``, else the env's).

    Args:
        policy: the policy; it reads ``observation_key`` from a TensorDict of the still-running
            episodes and writes ``action_key``, as it does on our env.
        env_id: Gymnasium's env id, e.g. ``"HalfCheetah-v5"``.
        episodes: the number of episodes (an integer >= 1).
        seed: episode ``i`` is reset with seed ``seed + i``.
        steps: the time limit of an episode (default: the env's).
        options: our env's task options ([`gymnasium_kwargs`][torchrl_diffenvs.evaluation.gymnasium_kwargs]).
        dtype: the observations are converted to it for the policy.
        device: the observations are put on it for the policy.
        observation_key: where the policy reads the observation.
        action_key: where the policy writes the action.
        exploration_type: the exploration mode the policy runs in (default: deterministic, the mean action).
        start_states: ``(qpos [episodes, nq], qvel [episodes, nv])``: episode ``i`` starts from
            state ``i`` (set after its reset, as Gymnasium's own reset sets its random start) instead
            of Gymnasium's random start: with [`start_states`][torchrl_diffenvs.evaluation.start_states]
            of our env, both envs play the same episodes, and the returns differ by the dynamics
            only, not by the draw of start states. MuJoCo tasks only.

    Returns:
        [`evaluate`][torchrl_diffenvs.evaluation.evaluate]'s ``return``, ``return_std``, ``return_min``,
        ``return_max``, ``episode_length`` and ``terminated``, and the per-episode ``returns`` and ``lengths``.
    """
    import gymnasium
    import numpy as np
    from tensordict import TensorDict

    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"evaluate_in_gymnasium: episodes must be an integer >= 1, got {episodes!r}")
    kwargs = gymnasium_kwargs(env_id, options)
    if steps is not None:
        kwargs["max_episode_steps"] = steps
    envs = [gymnasium.make(env_id, **kwargs) for _ in range(episodes)]
    if not isinstance(envs[0].action_space, gymnasium.spaces.Box):
        for env in envs:
            env.close()
        raise ValueError(f"{env_id}: Gymnasium's env takes {envs[0].action_space} actions, not continuous ones "
                         "like this library's task of the same name: its policy cannot be played there")
    try:
        observations = [env.reset(seed=seed + i)[0] for i, env in enumerate(envs)]
        if start_states is not None:
            qpos, qvel = (np.asarray(torch.as_tensor(x, dtype=torch.float64).cpu()) for x in start_states)
            model = envs[0].unwrapped
            if not hasattr(model, "set_state"):
                raise ValueError(f"evaluate_in_gymnasium: start_states are MuJoCo's qpos and qvel, and {env_id} is not "
                                 "a MuJoCo env")
            expected = ((episodes, model.model.nq), (episodes, model.model.nv))
            if (qpos.shape, qvel.shape) != expected:
                raise ValueError(f"evaluate_in_gymnasium: start_states of {env_id} for {episodes} episodes are qpos "
                                 f"{expected[0]} and qvel {expected[1]}, got {qpos.shape} and {qvel.shape}")
            observations = [_start_from(env, qpos[i], qvel[i]) for i, env in enumerate(envs)]
        returns, lengths = np.zeros(episodes), np.zeros(episodes, dtype=np.int64)
        terminated = np.zeros(episodes, dtype=bool)
        running = list(range(episodes))
        while running:
            obs = torch.as_tensor(np.stack([observations[i] for i in running]), dtype=dtype, device=device)
            with torch.no_grad(), set_exploration_type(exploration_type):
                action = policy(TensorDict({observation_key: obs}, batch_size=[len(running)], device=device))
            action = action.get(action_key).detach().cpu().double().numpy()
            still = []
            for row, i in enumerate(running):
                observations[i], reward, term, trunc, _ = envs[i].step(action[row])
                returns[i] += reward
                lengths[i] += 1
                if term or trunc:
                    terminated[i] = term
                else:
                    still.append(i)
            running = still
    finally:
        for env in envs:
            env.close()
    return {"return": float(returns.mean()), "return_std": float(returns.std()), "return_min": float(returns.min()),
            "return_max": float(returns.max()), "episode_length": float(lengths.mean()),
            "terminated": float(terminated.mean()), "returns": returns.tolist(), "lengths": lengths.tolist()}


def evaluate_random(env, steps: int | None = None, seed: int | None = None) -> float:
    """Mean return of uniformly random actions on the same start states as
    [`evaluate`][torchrl_diffenvs.evaluation.evaluate].

    Args:
        env: the (batched) evaluation env.
        steps: the rollout's length (default: the env's ``max_episode_steps``).
        seed: if given, the envs are reseeded with it first (the same start states as
            [`evaluate`][torchrl_diffenvs.evaluation.evaluate] with this seed).
    """
    rollout = _rollout(env, uniform_random_policy(env), steps, seed, ExplorationType.RANDOM)
    return episode_returns(rollout, env.reward_key).double().mean().item()


def record_video(env, policy, steps: int, seed: int, path: str | Path, env_index: int = 0, fps: int = 30,
                 size: int = 256, exploration_type: ExplorationType = ExplorationType.DETERMINISTIC) -> Path:
    """Writes a GIF or MP4 (by the suffix of ``path``) of ``policy`` playing env ``env_index`` of
    ``env`` for ``steps`` steps.

    Needs Pillow (``pip install "torchrl_diffenvs[render]"``), and for MP4 imageio-ffmpeg (the
    ``video`` extra).

    Args:
        env: the env to roll out (its task must have a drawer).
        policy: the policy that plays, as ``env.rollout`` takes it.
        steps: the number of steps recorded.
        seed: the envs are reseeded with it first (``None``: not reseeded).
        path: the file to write: ``.gif`` or ``.mp4``.
        env_index: which env of the batch is drawn.
        fps: frames per second of the video.
        size: pixels of a frame, each way.
        exploration_type: the exploration mode the policy runs in (default: deterministic, the mean action).

    Returns:
        The path of the written file.
    """
    from .rendering import rollout_frames, save_video  # Pillow is an optional extra

    rollout = _rollout(env, policy, steps, seed, exploration_type)
    frames = rollout_frames(env, rollout, env_index=env_index, size=size)
    return save_video(frames, path, fps=fps)
