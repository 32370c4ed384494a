"""The base class that turns a task's pure physics into a batched, differentiable TorchRL env.

A task subclass only supplies physics (see [`DiffEnv`][torchrl_diffenvs.DiffEnv]); everything TorchRL needs (specs,
batch size, device, dtype, seeding, partial resets, truncation, input validation) lives here.

TensorDict layout (``N = num_envs``):

```text
"observation"            [N, obs_dim]   what a policy sees (computed from the state)
("state", <name>)        [N, ...]       the physical state; never the same tensor as "observation"
("params", <name>)       [N, ...]       physical parameters, per env (randomise or differentiate)
"episode_step"           [N] int64      steps since the last reset (drives truncation)
"action"                 [N, act_dim]
("next", "reward")       [N, 1]
("next", "terminated" | "truncated" | "done")   [N, 1] bool
"nonfinite"              [N, 1] bool    the step left this env's state or reward NaN/inf
```

Keeping the state apart from the observation matters: an ObservationNorm (or any transform) on
"observation" can never feed its output back into the dynamics. A multi-agent task
([`MultiAgentDiffEnv`][torchrl_diffenvs.envs.MultiAgentDiffEnv]) moves "observation", "action" and
"reward" into an "agents" group ``[N, A]`` (`DiffEnv._policy_specs` is the one place that
lays them out).
"""
from __future__ import annotations

import contextlib
import math
import operator
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .rollout import fast_rollout, fast_rollout_unsupported
from .rollout.step import physics_step
from .streams import EnvGenerator, StartDraw, env_index_keys

__all__ = ["DiffEnv"]

_FLOAT_DTYPES = (torch.float32, torch.float64)


class DiffEnv(EnvBase):
    """Batched differentiable environment. Subclass it with physics only.

    A subclass defines:

    * ``name`` (str), ``action_dim`` (int) and ``default_params`` (dict of floats or lists);
    * ``initial_state(params, n) -> dict[str, Tensor]``: samples ``n`` start states with
      [`uniform`][torchrl_diffenvs.DiffEnv.uniform] / [`normal`][torchrl_diffenvs.DiffEnv.normal] (so seeding works: see "Start states" below);
    * ``transition(state, action, params) -> (next_state, reward, terminated)``: one step, pure
      tensor code; ``reward`` is ``[N]``, ``terminated`` a ``[N]`` bool tensor or ``None``;
    * ``observation(state, params) -> Tensor [N, obs_dim]``.

    Optional class attributes: ``default_max_episode_steps`` (``None`` disables truncation),
    ``action_low`` / ``action_high`` (the action spec) and ``clip_actions``.

    Actions outside ``[action_low, action_high]``: when ``clip_actions`` is ``False`` (the
    Ivy-style tasks) the physics is applied to the action as given, gradients included; the
    spec bounds are what a policy should produce (e.g. with a tanh). When ``True`` (the
    Gymnasium-compatible tasks) the action is clipped as Gymnasium does, which zeroes the
    gradient outside the bounds.

    Start states: when the env resets, every number [`uniform`][torchrl_diffenvs.DiffEnv.uniform] and [`normal`][torchrl_diffenvs.DiffEnv.normal] return
    inside ``initial_state`` comes from env ``i``'s own random stream, a hash of (seed, ``i``,
    ``i``'s episode count, draw number): env ``i``'s start states are the same whatever the batch
    size and however often the other envs reset (`streams`).
    [`episodes`][torchrl_diffenvs.DiffEnv.episodes] holds the counts (saved and restored with ``env.rng``'s state);
    `set_seed` sets them back to zero.

    Non-finite envs: every operation is elementwise over the batch, so a NaN/inf action or
    parameter of env ``i`` can only make env ``i``'s values non-finite. After each step the base
    class flags such an env in ``"nonfinite"`` (``[N, 1]`` bool), marks it ``terminated`` (an
    auto-reset restarts it; a NaN state never stays) and replaces the non-finite elements of its
    ``"observation"`` and ``"reward"`` by ``0`` so that batch means stay finite; its ``"state"``
    keeps the NaN/inf values (see `physics_step`). The
    other envs' values and gradients are unchanged; the flagged env's own gradients may be NaN,
    so learners mask flagged envs out of their losses.

    Args:
        num_envs: number of environments simulated in one batch (``>= 1``).
        device: torch device of every tensor.
        dtype: ``torch.float32`` (default) or ``torch.float64`` (for gradient checks).
        seed: seed of the env's own random generator; ``None`` draws one from torch's global RNG.
        max_episode_steps: episodes are truncated after this many steps; ``None`` never truncates.
        params: overrides of ``default_params``; each value a float or a tensor of shape
            ``[num_envs, ...]`` for per-env values (domain randomisation).
    """

    name: str = ""
    action_dim: int = 1
    default_params: Mapping[str, float | list[float]] = {}
    default_max_episode_steps: int | None = 100
    action_low: float = -1.0
    action_high: float = 1.0
    clip_actions: bool = False

    batch_locked = True
    _supports_set_state = True
    reading_state_keys: tuple[str, ...] = ()
    """State entries that are readings of the last step (as a MuJoCo task's contact force), not
    inputs of the next: ``reset(td, set_state=True)`` starts a missing one at 0."""
    # the compiled chunks of this env's lean rollouts, set by compile_physics (None: eager)
    _compiled_physics = None
    # whether a lean rollout that deferred its finiteness checks met a non-finite value: this
    # env's lean rollouts check every step from then on
    _nonfinite_seen: bool = False

    def derived_state(self, state, params) -> dict:
        """State entries that follow from others (e.g. positions MuJoCo derives from ``qpos``):
        ``reset(td, set_state=True)`` computes those missing from ``td["state"]``. None here."""
        return {}
    _USE_DEFAULT = object()

    # ------------------------------------------------------------------ physics (subclasses)
    def initial_state(self, params: Mapping[str, torch.Tensor], n: int) -> dict[str, torch.Tensor]:
        """Start states of ``n`` envs (a task writes this).

        Args:
            params: the physical parameters of these envs, each ``[n, ...]``.
            n: how many start states to sample.

        Returns:
            The state entries, each ``[n, ...]``; random draws come from each env's own stream
                (see the class docstring), so that a reset of some envs leaves the others' draws as they were.
        """
        raise NotImplementedError

    def transition(self, state, action, params):
        """One step of the task's physics, pure tensor code that autograd differentiates (a task
        writes this).

        Args:
            state: the state entries, each ``[N, ...]``.
            action: ``[N, action_dim]``, clamped to the action bounds when ``clip_actions`` is set.
            params: the physical parameters, each ``[N, ...]``.

        Returns:
            ``(next_state, reward, terminated)``: a dict like ``state``, the reward ``[N]`` and a
                ``[N]`` bool tensor, or ``None`` for a task that never terminates.
        """
        raise NotImplementedError

    def observation(self, state, params) -> torch.Tensor:
        """What the policy sees of ``state`` (a task writes this).

        Args:
            state: the state entries, each ``[N, ...]``.
            params: the physical parameters, each ``[N, ...]``.

        Returns:
            ``[N, obs_dim]``.
        """
        raise NotImplementedError

    # ------------------------------------------------------------------ construction
    def __init__(
        self,
        num_envs: int = 1,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        seed: int | None = None,
        max_episode_steps: int | None = _USE_DEFAULT,  # type: ignore[assignment]
        params: Mapping[str, float | torch.Tensor] | None = None,
    ):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"{self.name}: num_envs must be an integer >= 1, got {num_envs!r}")
        if dtype not in _FLOAT_DTYPES:
            raise TypeError(f"{self.name}: dtype must be torch.float32 or torch.float64, got {dtype}")
        if max_episode_steps is DiffEnv._USE_DEFAULT:
            max_episode_steps = self.default_max_episode_steps
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1
        ):
            raise ValueError(
                f"{self.name}: max_episode_steps must be a positive integer or None, got {max_episode_steps!r}"
            )
        super().__init__(device=device if device is not None else "cpu", batch_size=torch.Size([num_envs]))
        self.num_envs = num_envs
        self.float_dtype = dtype
        self.max_episode_steps = max_episode_steps
        # a throwaway generator for building specs; set_seed below installs the real one
        self.rng = torch.Generator(device=self.device).manual_seed(0)
        self.params = self._build_params(params or {})
        self._make_specs()
        if seed is None:
            seed = int(torch.randint(0, 2**62, (), dtype=torch.int64).item())
        self.set_seed(seed)

    def _build_params(self, overrides: Mapping[str, float | torch.Tensor]) -> TensorDict:
        unknown = sorted(set(overrides) - set(self.default_params))
        if unknown:
            raise KeyError(
                f"{self.name}: unknown physical parameter(s) {unknown}; valid: {sorted(self.default_params)}"
            )
        n = self.num_envs
        values = {}
        for key, default in self.default_params.items():
            default_t = torch.as_tensor(default, dtype=self.float_dtype, device=self.device)
            raw = overrides.get(key, default_t)
            try:
                value = torch.as_tensor(raw, dtype=self.float_dtype, device=self.device)
            except (TypeError, ValueError, RuntimeError) as err:
                raise TypeError(
                    f"{self.name}: parameter {key!r} must be a number or a tensor (one value per env: shape "
                    f"({n},)), got {type(raw).__name__} {raw!r}"
                ) from err
            if value.shape == default_t.shape:
                value = value.expand(n, *default_t.shape)
            elif value.shape != (n, *default_t.shape):
                raise ValueError(
                    f"{self.name}: parameter {key!r} must be a scalar shaped like its default "
                    f"{tuple(default_t.shape)} or a per-env tensor of shape {(n, *default_t.shape)}, "
                    f"got {tuple(value.shape)}"
                )
            values[key] = value.clone()
        return TensorDict(values, batch_size=[n], device=self.device)

    def _make_specs(self) -> None:
        n = self.num_envs
        state = self.initial_state(self.params, n)
        obs = self.observation(state, self.params)
        self.observation_dim = obs.shape[-1]

        def unbounded_like(td: Mapping[str, torch.Tensor]) -> Composite:
            return Composite(
                {k: Unbounded(shape=v.shape, dtype=v.dtype, device=self.device) for k, v in td.items()},
                shape=(n,),
                device=self.device,
            )

        carried = dict(
            state=unbounded_like(state),
            params=unbounded_like(self.params),
            episode_step=Unbounded(shape=(n,), dtype=torch.int64, device=self.device),
        )
        observation, action, reward = self._policy_specs()
        # "nonfinite": the step left the env's state or reward NaN/inf (see physics_step)
        nonfinite = Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.observation_spec = Composite(**observation, **carried, nonfinite=nonfinite, shape=(n,),
                                          device=self.device)
        # The env is stateless: everything needed to step it travels in the TensorDict.
        self.state_spec = Composite(carried, shape=(n,), device=self.device).clone()
        self.action_spec = action
        self.reward_spec = reward
        self._action_key, self._reward_key = self.action_key, self.reward_key  # cached: read every step
        done = Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=done, terminated=done.clone(), truncated=done.clone(), shape=(n,), device=self.device
        )

    @property
    def action_shape(self) -> tuple[int, ...]:
        """One env's action shape: ``(action_dim,)`` (a multi-agent env: ``(num_agents, action_dim)``)."""
        return (self.action_dim,)

    def _policy_specs(self) -> tuple[dict, object, object]:
        """The specs of what a policy reads and writes: ``({"observation": spec}, action_spec,
        reward_spec)``; the multi-agent base moves them into an ``"agents"`` group."""
        n, dtype = self.num_envs, self.float_dtype
        observation = Unbounded(shape=(n, self.observation_dim), dtype=dtype, device=self.device)
        action = Bounded(low=self.action_low, high=self.action_high, shape=(n, self.action_dim), dtype=dtype,
                         device=self.device)
        return {"observation": observation}, action, Unbounded(shape=(n, 1), dtype=dtype, device=self.device)

    def _policy_entries(self, observation: torch.Tensor, reward: torch.Tensor | None) -> dict:
        """The output entries a policy reads (and the reward), laid out as `_policy_specs` says."""
        out = {"observation": observation}
        if reward is not None:
            out["reward"] = reward.unsqueeze(-1)
        return out

    # ------------------------------------------------------------------ helpers for tasks
    def uniform(self, low: float, high: float, *shape: int) -> torch.Tensor:
        """``U[low, high)`` samples of shape ``shape`` (``[n, ...]``) for ``initial_state``.

        During a reset ([`start_states`][torchrl_diffenvs.DiffEnv.start_states]) row ``i`` comes from env ``i``'s own random stream;
        called anywhere else (e.g. ``initial_state`` called directly), from the seeded
        generator `rng`.
        """
        draw = self.__dict__.get("_start_draw")
        if draw is None:
            sample = torch.rand(shape, generator=self.rng, device=self.device, dtype=self.float_dtype)
        else:
            sample = draw.uniform(shape, self.float_dtype)
        return sample * (high - low) + low

    def normal(self, *shape: int) -> torch.Tensor:
        """Standard normal samples of shape ``shape`` (``[n, ...]``), from the same streams as [`uniform`][torchrl_diffenvs.DiffEnv.uniform]."""
        draw = self.__dict__.get("_start_draw")
        if draw is None:
            return torch.randn(shape, generator=self.rng, device=self.device, dtype=self.float_dtype)
        return draw.normal(shape, self.float_dtype)

    @contextlib.contextmanager
    def redraws(self):
        """Wraps a rejection-sampling loop in ``initial_state``: its draws come from numbers of
        their own, so the draws after the loop are the same whatever number of rounds the batch
        needed (an env's own rounds use its own stream):

        ```python
        goal = self.uniform(-0.2, 0.2, n, 2)
        with self.redraws():
            while (reject := goal.norm(dim=-1) >= 0.2).any():
                goal = torch.where(reject.unsqueeze(-1), self.uniform(-0.2, 0.2, n, 2), goal)
        ```
        """
        draw = self.__dict__.get("_start_draw")
        if draw is None:
            yield
            return
        main = draw.calls
        draw.calls = (main + 1) << 20  # a range of stream positions no main draw reaches
        try:
            yield
        finally:
            draw.calls = main

    @property
    def episodes(self) -> torch.Tensor:
        """``[N]`` int64: how many start states each env has drawn since the last `set_seed`
        (env ``i``'s next start state is the one of episode ``episodes[i]`` of its stream)."""
        return self.rng.episodes

    @episodes.setter
    def episodes(self, value: torch.Tensor) -> None:
        value = torch.as_tensor(value, dtype=torch.int64, device=self.device)
        if value.shape != (self.num_envs,) or bool((value < 0).any()):
            raise ValueError(f"{self.name}: episodes must be {self.num_envs} non-negative integers, got {value}")
        self.rng.episodes = value.clone()

    def start_states(self, params, episodes: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """``initial_state`` for every env, env ``i`` at episode ``episodes[i]`` of its own stream
        (default: [`episodes`][torchrl_diffenvs.DiffEnv.episodes], the next ones). Pure: advances no counter (``_reset`` does)."""
        episodes = self.episodes if episodes is None else episodes
        # hash as many words up front as the last call used (one numpy hash instead of one per draw)
        key = self.rng.key
        cached = self.__dict__.get("_index_keys")
        if cached is None or cached[0] != key or cached[1] is not self._env_index:
            cached = self.__dict__["_index_keys"] = (key, self._env_index, env_index_keys(key, self._env_index))
        draw = StartDraw(key, self._env_index, episodes, self.__dict__.get("_start_words", 0), cached[2])
        self.__dict__["_start_draw"] = draw
        try:
            return self.initial_state(params, self.num_envs)
        finally:
            self.__dict__["_start_draw"] = None
            self.__dict__["_start_words"] = draw.used

    def _set_seed(self, seed: int | None) -> None:
        # EnvBase.set_seed(seed=None) is valid TorchRL API: like the constructor's seed=None,
        # draw a seed from torch's global RNG (int(None) used to raise a TypeError here).
        if seed is None:
            seed = int(torch.randint(0, 2**62, (), dtype=torch.int64).item())
        try:
            seed = operator.index(seed)  # an integer of any kind (Python, NumPy, a 0-dim integer tensor)
        except TypeError:
            raise TypeError(f"{self.name}: seed must be an integer or None, got {seed!r}") from None
        # env.rng also holds the episode counts of the start states' per-env streams (see EnvGenerator)
        self.rng = EnvGenerator(self.device, self.num_envs, seed)
        self.__dict__["_env_index"] = torch.arange(self.num_envs, dtype=torch.int64, device=self.device)

    # ------------------------------------------------------------------ TorchRL plumbing
    def _check_action(self, action: torch.Tensor | None) -> None:
        expected = (self.num_envs, *self.action_shape)
        if action is None:
            raise KeyError(
                f"{self.name}: the input TensorDict has no {self._action_key!r} entry (expected shape {expected})"
            )
        if tuple(action.shape) != expected:
            layout = "[num_envs, action_dim]" if len(expected) == 2 else "[num_envs, num_agents, action_dim]"
            raise ValueError(f"{self.name}: expected an action of shape {expected} ({layout}), got {tuple(action.shape)}")
        if action.dtype != self.float_dtype:
            raise TypeError(f"{self.name}: expected an action of dtype {self.float_dtype}, got {action.dtype}")

    def _check_state(self, state: TensorDictBase) -> None:
        """``reset(td, set_state=True)``: ``td["state"]`` must match the state spec entry by entry.

        Without this, a float64 state silently turns a float32 env's outputs into float64 and a
        wrongly shaped entry can broadcast through the physics.
        """
        spec = self.state_spec["state"]
        expected = sorted(spec.keys())
        missing = sorted(set(expected) - set(state.keys()))
        if missing:
            raise KeyError(f"{self.name}: reset(set_state=True) needs the state entries {expected}, missing {missing}")
        for key in expected:
            value, want = state.get(key), spec[key]
            if value.dtype != want.dtype:
                raise TypeError(f"{self.name}: state entry {key!r} must have dtype {want.dtype}, got {value.dtype}")
            if value.shape != want.shape:
                raise ValueError(
                    f"{self.name}: state entry {key!r} must have shape {tuple(want.shape)}, got {tuple(value.shape)}"
                )

    def _assert_tensordict_shape(self, tensordict: TensorDictBase) -> None:
        if tensordict.batch_size != self.batch_size:
            raise ValueError(
                f"{self.name}: expected a TensorDict with batch size {tuple(self.batch_size)} (num_envs), "
                f"got {tuple(tensordict.batch_size)}"
            )

    def _truncated(self, episode_step: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
        """``[N]`` bool time-limit flag: ``episode_step >= max_episode_steps`` unless terminated.

        The one place the truncation rule lives (``_step``, ``_reset`` and the fast rollout path
        all use it); a task with another rule (e.g. Gymnasium's ``TimeLimit``) overrides this.
        """
        if self.max_episode_steps is None:
            return torch.zeros_like(terminated)
        return (episode_step >= self.max_episode_steps) & ~terminated

    # the rollout's step compares episode steps directly while a task keeps this rule
    _truncated.time_limit_rule = True

    def _output(self, state, params, episode_step, reward=None, terminated=None, nonfinite=None,
                observation=None) -> TensorDict:
        n = self.num_envs
        if terminated is None:
            terminated = torch.zeros(n, dtype=torch.bool, device=self.device)
        if nonfinite is None:
            nonfinite = torch.zeros(n, dtype=torch.bool, device=self.device)
        truncated = self._truncated(episode_step, terminated)
        out = {
            **self._policy_entries(self.observation(state, params) if observation is None else observation,
                                   reward),
            "state": TensorDict(dict(state), batch_size=[n]),
            "params": params,
            "episode_step": episode_step,
            "terminated": terminated.unsqueeze(-1),
            "truncated": truncated.unsqueeze(-1),
            "done": (terminated | truncated).unsqueeze(-1),
            "nonfinite": nonfinite.unsqueeze(-1),
        }
        return TensorDict(out, batch_size=[n], device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self._action_key, None)
        self._check_action(action)
        if self.clip_actions:
            action = action.clamp(self.action_low, self.action_high)
        params, state, episode_step = (tensordict.get(k, None) for k in ("params", "state", "episode_step"))
        if params is None or state is None or episode_step is None:
            # a hand-built TensorDict would otherwise fail inside the physics on a None
            raise KeyError(
                f"{self.name}: env.step needs the 'state', 'params' and 'episode_step' entries (as "
                f"returned by env.reset() or a previous step); got keys {sorted(tensordict.keys())}"
            )
        nxt = physics_step(self, state, params, episode_step, action)
        out = self._output(nxt["state"], params, nxt["episode_step"], nxt["reward"], nxt["terminated"],
                           nxt["nonfinite"], nxt["observation"])
        self._remember_for_render(out)
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """Fresh start states; ``reset(td, set_state=True)`` starts from ``td["state"]`` instead.

        Params come from ``td["params"]`` when given, else from ``env.params``. During auto-resets
        TorchRL passes only the ``"_reset"`` mask, so reset envs take ``env.params``. Start states
        are drawn for every env (TorchRL keeps those of the envs in ``"_reset"``); only the reset
        envs' episode counts advance, so the others' streams are untouched.
        """
        given = tensordict if tensordict is not None else TensorDict(batch_size=self.batch_size)
        params = given.get("params", None)
        params = self.params.clone() if params is None else params
        if kwargs.get("set_state"):
            if "state" not in given.keys():
                raise KeyError(f"{self.name}: reset(set_state=True) needs a 'state' entry in the TensorDict")
            state = given.get("state").copy()
            for key in self.reading_state_keys:  # readings of the last step, not inputs: 0 when not given
                if key not in state.keys():
                    spec = self.state_spec["state", key]
                    state.set(key, torch.zeros(spec.shape, dtype=spec.dtype, device=self.device))
            for key, value in self.derived_state(state, params).items():  # derived from the given ones
                if key not in state.keys():
                    state.set(key, value)
            self._check_state(state)
        else:
            state = self.start_states(params)
            reset = given.get("_reset", None)
            advance = 1 if reset is None else reset.reshape(self.num_envs).to(torch.int64)
            self.rng.episodes = self.episodes + advance
        episode_step = torch.zeros(self.num_envs, dtype=torch.int64, device=self.device)
        out = self._output(state, params, episode_step)
        self._remember_for_render(out, reset_mask=given.get("_reset", None))
        return out

    # ------------------------------------------------------------------ fast rollout
    use_fast_rollout: bool = True  # False: always use EnvBase.rollout (e.g. to compare)

    @classmethod
    def overridden_methods(cls, names) -> list[str]:
        """Those of ``names`` that ``cls`` defines differently from [`DiffEnv`][torchrl_diffenvs.DiffEnv] (the lean
        rollout reproduces DiffEnv's and TorchRL's versions only)."""
        return [name for name in names if getattr(cls, name) is not getattr(DiffEnv, name)]

    def rollout(self, max_steps: int, policy=None, callback=None, **kwargs) -> TensorDictBase:
        """``EnvBase.rollout`` (same arguments, same result), through a lean loop when possible.

        The lean loop (`torchrl_diffenvs.envs.rollout`) steps the pure physics on plain
        tensors and builds the output TensorDict once; it is taken unless a ``callback`` or an
        argument it does not reproduce is given (see ``fast_rollout_unsupported``).
        ``TransformedEnv`` never calls this method: it steps the base env itself.
        """
        if fast_rollout_unsupported(self, callback, kwargs) is None:
            return fast_rollout(self, max_steps, policy, **kwargs)
        return super().rollout(max_steps, policy, callback, **kwargs)

    # ------------------------------------------------------------------ conveniences
    _render_source = None  # see _remember_for_render

    def _remember_for_render(self, tensordict: TensorDictBase, reset_mask: torch.Tensor | None = None) -> None:
        """Keeps what [`render`][torchrl_diffenvs.DiffEnv.render] draws of the latest ``[N]`` output: its ``"state"``,
        ``"params"`` and ``"reward"``, *detached* (views, no copies: about 3 us), so that the env
        never holds a rollout's autograd graph alive.

        ``_step`` and ``_reset`` call it; a rollout path that bypasses them calls it with the last
        TensorDict it produced. A partial reset (``reset_mask``) only replaces the masked envs, as
        TorchRL does; the merge is left to render time. Written into ``__dict__`` directly
        because ``nn.Module.__setattr__`` costs about 7 us per call, a tenth of a ``_step``.
        """
        params = tensordict.get("params", None)
        reward = tensordict.get(self._reward_key, None)
        source = {
            "state": {key: value.detach() for key, value in tensordict.get("state").items()},
            "params": None if params is None else {key: value.detach() for key, value in params.items()},
            "reward": None if reward is None else reward.detach(),
            "num_envs": tensordict.batch_size[0],
        }
        if reset_mask is not None and self._render_source is not None:
            source = (self._render_source, source, reset_mask)
        self.__dict__["_render_source"] = source

    def render(self, tensordict: TensorDictBase | None = None, env_index=0, size=256, **kwargs):
        """Draws envs as an RGB frame, ``np.ndarray`` uint8 ``[H, W, 3]``, without a display.

        Args:
            tensordict: a ``[N]`` TensorDict holding ``"state"`` (and ``"reward"`` to colour the
                body, ``"params"`` else ``env.params``), e.g. ``td["next"]`` of a step; default:
                the latest output of ``step`` / ``reset``.
            env_index: an env index, a list of indices, or ``"all"``; several envs are tiled
                into one grid frame.
            size: pixels of one env's picture, ``int`` (square) or ``(height, width)``.
            **kwargs: passed to [`torchrl_diffenvs.rendering.render_frame`][torchrl_diffenvs.rendering.render_frame].

        Needs Pillow (``pip install "torchrl_diffenvs[render]"``); see
        [`torchrl_diffenvs.rendering`][torchrl_diffenvs.rendering] for the drawings and GIF export.
        """
        from ..rendering import render_frame  # lazy: Pillow is an optional extra

        return render_frame(self, tensordict, env_index=env_index, size=size, **kwargs)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, num_envs={self.num_envs}, "
            f"action_dim={self.action_dim}, observation_dim={self.observation_dim}, "
            f"dtype={self.float_dtype}, device={self.device}, max_episode_steps={self.max_episode_steps})"
        )


def angle_normalize(angle: torch.Tensor) -> torch.Tensor:
    """Maps an angle to ``[-pi, pi)`` (gradient 1 almost everywhere)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi
