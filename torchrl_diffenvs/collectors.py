"""A collector of gradient-carrying rollout windows for BPTT and SHAC, and the tracker of
finished-episode returns that every learner reports.

TorchRL's own collectors run under ``torch.no_grad`` (they feed replay buffers); the
gradient-based learners need the opposite: rollouts whose rewards and observations are
differentiable w.r.t. the policy parameters. [`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector] owns that.
"""
from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Composite
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from .envs.multi_agent import policy_keys, reward_per_env
from .objectives.nonfinite import ISOLATED_KEY, next_key, nonfinite_envs, now_and_next

__all__ = ["DiffWindowCollector", "EpisodeReturnTracker", "IsolatingPolicy", "batch_size_of", "detach_transform_state"]


def batch_size_of(env, reset_input=None, who: str = "") -> int:
    """``N``: the env's batch size ``[N]``, or for a batch-unlocked env (``batch_size`` ``[]``, like
    TorchRL's ``PendulumEnv``) the batch size of what ``reset_input()`` returns.

    Args:
        env: the env, batched (``batch_size`` ``[N]``) or batch-unlocked (``batch_size`` ``[]``).
        reset_input: for a batch-unlocked env only: a callable returning the TensorDict of batch size
            ``[N]`` that ``reset`` receives (e.g. ``lambda: env.gen_params(batch_size=[N])``).
        who: the caller's name, which the error messages begin with.

    Raises:
        ValueError: for any other env (naming ``who`` and the fix), or when ``reset_input`` is given
            for a batched env or returns a batch size other than ``[N]``.
    """
    if reset_input is not None:
        if len(env.batch_size) != 0:
            raise ValueError(f"{who}: reset_input is for batch-unlocked envs (batch_size []); this env is "
                             f"batched already, batch_size={tuple(env.batch_size)}")
        batch = reset_input().batch_size
        if len(batch) != 1:
            raise ValueError(f"{who}: reset_input() must return a TensorDict of batch size [N], got {tuple(batch)}")
        return batch[0]
    if len(env.batch_size) == 1:
        return env.batch_size[0]
    hint = (" For a batch-unlocked env (batched through what reset receives, like TorchRL's PendulumEnv), "
            "pass reset_input=lambda: env.gen_params(batch_size=[N]) (BPTT and SHAC)." if len(env.batch_size) == 0
            else "")
    raise ValueError(f"{who}: expected a batched env with batch size [N], got {tuple(env.batch_size)} "
                     f"({type(env).__name__}).{hint}")


@torch.no_grad()
def detach_transform_state(env) -> None:
    """Cuts the autograd graph out of the state that ``env``'s transforms keep between steps
    (``CatFrames``' frame buffer, ...): every buffer that carries a graph is replaced by a
    detached copy (a copy, so that a window collected earlier keeps its own graph intact).
    A no-op for an env without transforms.

    Args:
        env: the env; its ``TransformedEnv`` layers, if any, are walked down to the base env.
    """
    while isinstance(env, TransformedEnv):
        for module in env.transform.modules():
            for name, buffer in list(module.named_buffers(recurse=False)):
                if buffer.requires_grad:
                    setattr(module, name, buffer.detach().clone())
        env = env.base_env


class _Gate:
    """The envs whose gradient passes (``keep``, ``[N]`` bool), read when the backward pass runs:
    the non-finite envs of a window are known only after it has been collected."""

    def __init__(self, keep: torch.Tensor):
        self.keep = keep

    def __call__(self, grad: torch.Tensor | None) -> torch.Tensor | None:
        if grad is None:  # no gradient reached this output
            return None
        keep = self.keep.reshape(-1, *([1] * (grad.ndim - 1)))
        # where, not a product: a NaN gradient of an isolated env becomes exactly 0
        return torch.where(keep, grad, torch.zeros((), dtype=grad.dtype, device=grad.device))


class IsolatingPolicy(TensorDictModuleBase):
    """Calls ``policy`` so that non-finite envs cannot spoil the gradient of the others.

    Averaging the gradient over a batch does not isolate a non-finite env: the zero weight a
    loss gives it meets the NaN derivatives of its simulation (``0 * nan = nan``) and the NaN
    reaches the shared weights. So, on every step, the policy reads its inputs with non-finite
    values replaced by 0 (the recorded observations stay as the env produced them), and the
    actions it writes (``action_keys``) get a gradient hook that replaces the gradient of every
    env not in ``gate.keep`` by 0. [`open_gate`][torchrl_diffenvs.collectors.IsolatingPolicy.open_gate] starts a rollout with every env passing and
    returns the gate, whose ``keep`` (``[N]`` bool) is set after the rollout, before the backward
    pass: that is when the non-finite envs are known.

    Inside the compiled chunks of ``compile_physics`` no hook is registered (a traced hook would
    read the mask as it was when the chunk ran, and an eager one would split every chunk at every
    step): there a non-finite env still makes the window's gradient NaN, and the learner skips
    that update (counted, warned about, and an error after too many in a row).
    """

    def __init__(self, policy, action_keys=("action",)):
        super().__init__()
        self.policy = policy
        self.in_keys = list(policy.in_keys)
        self.out_keys = list(policy.out_keys)
        self.action_keys = list(action_keys)
        self.gate: _Gate | None = None

    def open_gate(self, num_envs: int, device) -> _Gate:
        """A new gate (every env passing) for the outputs of the next calls."""
        self.gate = _Gate(torch.ones(num_envs, dtype=torch.bool, device=device))
        return self.gate

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raw = {}
        for key in self.in_keys:
            value = tensordict.get(key, None)
            if isinstance(value, torch.Tensor) and value.dtype.is_floating_point:
                raw[key] = value
        for key, value in raw.items():  # nan_to_num's gradient is grad * isfinite: 0, never NaN, there
            tensordict.set(key, torch.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0))
        tensordict = self.policy(tensordict)
        for key, value in raw.items():  # the record keeps what the env produced
            tensordict.set(key, value)
        if not torch.compiler.is_compiling() and self.gate is not None:
            for key in self.action_keys:
                action = tensordict.get(key, None)
                if action is not None and action.requires_grad:
                    action.register_hook(self.gate)
        return tensordict


class EpisodeReturnTracker:
    """Undiscounted returns of the episodes that finish inside each batch ``[N, T]``.

    Keeps each env's running sum across batches (episodes span iterations); its state is saved
    in checkpoints so that a resumed run reports the same returns.
    """

    def __init__(self, num_envs: int, device: torch.device | str = "cpu", reward_key: NestedKey = "reward"):
        self.running = torch.zeros(num_envs, dtype=torch.float64, device=device)
        self.reward_key = reward_key

    def update(self, batch: TensorDictBase) -> tuple[list[float], torch.Tensor]:
        """Adds a ``[N, T]`` batch (``("next", reward_key)``, ``("next", "done")``).

        Returns the returns of the episodes that ended in it and the running return at every step
        ``[N, T]`` (float64; at a done step, the finished episode's return). A multi-agent reward
        (``("agents", "reward")``) counts as the mean over the agents.
        """
        reward = reward_per_env(batch, self.reward_key).detach().to(torch.float64)
        done = batch.get(("next", "done")).reshape(batch.shape)
        running = self.running
        per_step = torch.empty_like(reward)
        finished: list[float] = []
        for t in range(reward.shape[-1]):
            running = running + reward[:, t]
            per_step[:, t] = running
            if done[:, t].any():
                finished.extend(running[done[:, t]].tolist())
                running = torch.where(done[:, t], torch.zeros_like(running), running)
        self.running = running
        return finished, per_step

    def state_dict(self) -> dict:
        """The running returns of the episodes in progress (for a checkpoint)."""
        return {"running": self.running.clone()}

    def load_state_dict(self, state: dict) -> None:
        """Restores `state_dict`'s running returns."""
        self.running = state["running"].to(self.running)


class DiffWindowCollector:
    """Yields rollout windows ``[N, H]`` with the autograd graph on.

    Each window continues where the previous one stopped: the env TensorDict is carried over,
    *detached* at the window start (the gradient of a window never reaches into the previous
    one), and episodes are not reset at window boundaries. Envs whose episode ends inside a window
    are reset inside ``env.rollout(..., break_when_any_done=False)`` (the rollout's auto-reset:
    ``maybe_reset`` between steps, or the lean loop's equivalent merge), which cuts the graph for
    those envs only; an env done at the window's last step is reset when the next window starts.

    A window has the layout of ``env.rollout(H, policy, break_when_any_done=False)``: root
    entries at step ``t`` (``"observation"``, ``("state", ...)``, ``"episode_step"``, the policy
    outputs such as ``"action"``, ``"loc"``, ``"scale"``), and under ``"next"`` the entries
    after the step *before any reset*: ``("next", "observation")`` of a truncated step is the
    pre-reset observation, which is what a critic must bootstrap from. The collector adds
    ``("next", "episode_reward")``: the undiscounted return of the episode so far, detached
    (at a done step it is the finished episode's return), from an [`EpisodeReturnTracker`][torchrl_diffenvs.collectors.EpisodeReturnTracker].

    Actions are drawn under ``exploration_type`` (default ``ExplorationType.RANDOM``, so a
    ``ProbabilisticActor`` with a ``TanhNormal`` uses ``rsample``: reparameterised, gradients
    reach the distribution parameters).

    Args:
        env: a batched differentiable env (a [`DiffEnv`][torchrl_diffenvs.DiffEnv], possibly
            wrapped in a ``TransformedEnv`` whose transforms keep gradients).
        policy: a TensorDict module that writes ``"action"``.
        horizon: window length ``H``.
        total_windows: iteration stops after this many windows; ``None`` iterates forever.
        exploration_type: exploration mode for the policy.
        start_state: if given, every window starts from this TensorDict's ``"state"``
            (``env.reset(start_state, set_state=True)``) instead of continuing the previous
            one: fixed-start trajectory optimisation.
        stagger_episodes: after the first reset, give every env a random ``"episode_step"`` in
            ``[0, max_episode_steps)`` so that the envs' episodes end at different times
            instead of all together (their first episodes are shorter). This decorrelates the
            batch; it needs an env with ``max_episode_steps``.
        generator: torch generator for ``stagger_episodes`` (seeding).
        reset_input: for a batch-unlocked env (``batch_size`` ``[]``, batched by what ``reset``
            receives, like TorchRL's ``PendulumEnv``): a function returning the TensorDict to
            reset with, e.g. ``lambda: env.gen_params(batch_size=[64])``; its batch size is ``N``.
        isolate_nonfinite: (default) envs with a NaN/inf reward or observation in a window (or
            a ``("next", "nonfinite")`` flag) are marked ``"isolated"`` ``[N, H]`` in it, which
            the losses leave out, and their gradient is cut at the policy's outputs
            ([`IsolatingPolicy`][torchrl_diffenvs.collectors.IsolatingPolicy]), so that they cannot make the others' gradient NaN.

    Attributes:
        finished_returns: the undiscounted returns of the episodes that ended in the last window.
        nonfinite: ``[N]`` bool, the envs isolated in the last window.
        windows: windows collected so far.
        frames: env steps collected so far (``windows * N * H``).

    For example:

    ```python
    env = make_env("pendulum", num_envs=64, seed=0)
    actor = make_actor(env)
    collector = DiffWindowCollector(env, actor, horizon=32, total_windows=100)
    for window in collector:          # TensorDict [64, 32], graph on
        loss = BPTTLoss(actor)(window)["loss_actor"]
        ...
    ```
    """

    def __init__(
        self,
        env: EnvBase,
        policy,
        horizon: int,
        total_windows: int | None = None,
        *,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
        start_state: TensorDictBase | None = None,
        stagger_episodes: bool = False,
        generator: torch.Generator | None = None,
        reset_input=None,
        isolate_nonfinite: bool = True,
    ):
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"DiffWindowCollector: horizon must be a positive integer, got {horizon!r}")
        if total_windows is not None and (not isinstance(total_windows, int) or total_windows < 0):
            raise ValueError(f"DiffWindowCollector: total_windows must be None or an integer >= 0, got {total_windows!r}")
        self.reset_input = reset_input
        self._num_envs = batch_size_of(env, reset_input, "DiffWindowCollector")
        self.env = env
        self.policy = policy
        self._isolating_policy = None
        if isolate_nonfinite and policy is not None:
            self._isolating_policy = IsolatingPolicy(policy, env.action_keys)
        self.horizon = horizon
        self.total_windows = total_windows
        self.exploration_type = exploration_type
        self.start_state = start_state
        self.stagger_episodes = stagger_episodes
        self.generator = generator
        if stagger_episodes and getattr(env, "max_episode_steps", None) is None:
            raise ValueError("DiffWindowCollector: stagger_episodes needs an env with max_episode_steps")
        self.finished_returns: list[float] = []
        self.nonfinite: torch.Tensor | None = None
        self.windows = 0
        # what the env needs to continue: its observation/state entries and the done flags
        self._carry_keys = list(env.observation_spec.keys(True, True)) + list(env.done_keys)  # leaves: not a group's reward
        self._carried: TensorDictBase | None = None
        self.tracker = EpisodeReturnTracker(self.num_envs, env.device, env.reward_key)

    @property
    def num_envs(self) -> int:
        """The number of envs the collector steps in parallel."""
        return self._num_envs

    @property
    def frames(self) -> int:
        """Env steps collected so far: windows x ``num_envs`` x ``horizon``."""
        return self.windows * self.num_envs * self.horizon

    # ------------------------------------------------------------------ state
    def reset(self, tensordict: TensorDictBase | None = None, **reset_kwargs) -> TensorDictBase:
        """Resets every env (``env.reset(tensordict, **reset_kwargs)``) and forgets running returns.

        ``collector.reset(td, set_state=True)`` starts the next window from ``td["state"]`` (a
        fixed start state, as in trajectory optimisation).
        """
        if tensordict is None and self.reset_input is not None:
            tensordict = self.reset_input()
            reset_kwargs.setdefault("set_state", False)  # it carries the batch (e.g. parameters), not a state
        td = self.env.reset(tensordict, **reset_kwargs) if tensordict is not None else self.env.reset(**reset_kwargs)
        self._carried = td.select(*self._carry_keys, strict=False).detach()
        if self.stagger_episodes:
            step = self._carried.get("episode_step")
            offset = torch.randint(self.env.max_episode_steps, step.shape, generator=self.generator, device="cpu")
            self._carried.set("episode_step", step + offset.to(step.device))
        self.tracker = EpisodeReturnTracker(self.num_envs, self.env.device, self.env.reward_key)
        return self._carried

    def state_dict(self) -> dict:
        """The carried env TensorDict (as a plain nested dict of tensors), running returns, the
        env's random generator state and counters: everything needed to resume mid-episode.
        Loadable with ``torch.load(..., weights_only=True)``."""
        rng = getattr(self.env, "rng", None)
        return {
            "carried": None if self._carried is None else self._carried.to_dict(),
            "tracker": self.tracker.state_dict(),
            "finished_returns": list(self.finished_returns),
            "windows": self.windows,
            "env_rng": rng.get_state() if isinstance(rng, torch.Generator) else None,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restores [`state_dict`][torchrl_diffenvs.collectors.DiffWindowCollector.state_dict] (same env class and ``num_envs``)."""
        carried = state["carried"]
        self._carried = None if carried is None else self._from_dict(carried)
        self.tracker.load_state_dict(state["tracker"])
        self.finished_returns = list(state["finished_returns"])
        self.windows = int(state["windows"])
        if state.get("env_rng") is not None and isinstance(getattr(self.env, "rng", None), torch.Generator):
            self.env.rng.set_state(state["env_rng"].cpu())  # generator states are CPU byte tensors, also for CUDA

    def _from_dict(self, carried: dict) -> TensorDictBase:
        """The carried TensorDict from its plain nested dict: batch ``[N]``, and a group's own
        batch size where the env's spec has one (``"agents"``: ``[N, A]``)."""
        td = TensorDict(carried, batch_size=[self.num_envs], device=self.env.device)
        for key, spec in self.env.full_observation_spec.items(True):
            if isinstance(spec, Composite) and len(spec.shape) > td.batch_dims and key in td.keys(True):
                td.get(key).batch_size = spec.shape
        return td

    # ------------------------------------------------------------------ collection
    def rollout(self) -> TensorDictBase:
        """Collects and returns the next window ``[N, H]`` (graph on)."""
        if self.start_state is not None:
            self.reset(self.start_state, set_state=True)
        elif self._carried is None:
            self.reset()
        # a transform's state (CatFrames' frames) is env state too: detached at the window start
        detach_transform_state(self.env)
        policy = self.policy
        gate = None
        if self._isolating_policy is not None:
            policy = self._isolating_policy
            # every env's gradient passes until the window shows which envs to isolate
            gate = policy.open_gate(self.num_envs, self.env.device)
        with torch.enable_grad(), set_exploration_type(self.exploration_type):
            # the carried TensorDict is detached: the graph starts here
            window = self.env.rollout(
                self.horizon,
                policy,
                auto_reset=False,
                tensordict=self._carried,
                break_when_any_done=False,
                return_contiguous=True,
            )
        if self.windows == 0:
            self._check_differentiable(window)
        self._isolate_nonfinite(window, gate)
        self._track_returns(window)
        # where the next window starts: the last step's "next" entries, done envs reset
        last = window[:, -1].get("next").select(*self._carry_keys, strict=False).detach()
        self._carried = self.env.maybe_reset(last).select(*self._carry_keys, strict=False).detach()
        self.windows += 1
        return window

    def _check_differentiable(self, window: TensorDictBase) -> None:
        """A window whose actions carry gradients must give rewards or observations that do."""
        keys = policy_keys(self.env)
        action = window.get(keys.action, None)
        if action is None or not action.requires_grad:
            return  # nothing to differentiate (e.g. a policy without parameters)
        nxt = window.get("next")
        outputs = [nxt.get(key, None) for key in (keys.reward, keys.observation)]
        if not any(value is not None and value.requires_grad for value in outputs):
            raise RuntimeError(
                f"DiffWindowCollector: {type(self.env).__name__} returned rewards and observations without "
                "gradient w.r.t. the actions, so BPTT and SHAC cannot learn through it. They need a differentiable "
                f"env: its step must compute ('next', {keys.reward!r}) and ('next', {keys.observation!r}) from the "
                "action with "
                "differentiable torch operations (no .detach(), .item(), numpy or torch.no_grad inside _step)."
            )

    @torch.no_grad()
    def _isolate_nonfinite(self, window: TensorDictBase, gate: _Gate | None) -> None:
        """Finds the envs with a NaN/inf reward or observation (or a ``("next", "nonfinite")``
        flag) in ``window``, marks them ``"isolated"`` ``[N, H]`` for the losses, cuts their
        gradient at the policy's outputs and keeps their mask in `nonfinite`."""
        keys = policy_keys(self.env)
        observed = [key for key in getattr(self.policy, "in_keys", ()) if key != "episode_step"]
        bad = nonfinite_envs(window, [next_key(keys.reward), *now_and_next(observed or [keys.observation])])
        self.nonfinite = bad
        if gate is not None:
            gate.keep = ~bad
        window.set(ISOLATED_KEY, bad.unsqueeze(-1).expand(window.batch_size))

    @torch.no_grad()
    def _track_returns(self, window: TensorDictBase) -> None:
        """Writes ``("next", "episode_reward")`` and records the returns of finished episodes
        (those of non-finite envs left out)."""
        finished, running = self.tracker.update(window)
        self.finished_returns = [value for value in finished if math.isfinite(value)]
        dtype = window.get(("next", self.env.reward_key)).dtype
        window.set(("next", "episode_reward"), running.to(dtype).unsqueeze(-1))  # [N, H, 1], the team's for agents

    def __iter__(self) -> Iterator[TensorDictBase]:
        while self.total_windows is None or self.windows < self.total_windows:
            yield self.rollout()

    def __len__(self) -> int:
        if self.total_windows is None:
            raise TypeError("DiffWindowCollector: len() is undefined when total_windows is None")
        return self.total_windows

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_envs={self.num_envs}, horizon={self.horizon}, "
            f"total_windows={self.total_windows}, windows={self.windows})"
        )
