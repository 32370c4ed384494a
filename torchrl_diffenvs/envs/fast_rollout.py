"""A lean implementation of ``EnvBase.rollout`` for :class:`~torchrl_diffenvs.DiffEnv`.

TorchRL's generic rollout builds, validates, copies and merges several TensorDicts per step
(``step``, ``step_mdp``, ``maybe_reset``, the random-action TensorDict): on CPU that machinery
costs several times the physics of our tasks. Because a DiffEnv's physics are pure tensor
functions (``initial_state`` / ``transition`` / ``observation``), a rollout can instead loop
over plain tensors, call the policy on one light TensorDict per step (only when there is a
policy), stack each entry once at the end and build the output TensorDict once.

:func:`fast_rollout` returns exactly what ``EnvBase.rollout`` returns for the arguments it
supports (same keys, shapes, dtypes, values for the same seeds, gradients, auto-reset and
``break_when_any_done`` semantics, side effects on the input ``tensordict``); tests/
test_fast_rollout.py compares the two. ``DiffEnv.rollout`` takes this path automatically when
:func:`fast_rollout_unsupported` finds nothing in the way and falls back to
``EnvBase.rollout`` otherwise, so users get the speed without changing their code.

What the lean loop reproduces, step by step (``EnvBase._rollout_nonstop`` /
``_rollout_stop_early``, torchrl 0.14):

* random actions (no policy) come from ``action_spec.rand()``, i.e. torch's *global* generator,
  drawn in the same order and with the same arithmetic, so a seeded run gives equal values;
* the step is ``DiffEnv._step``: optional clipping, ``transition``, ``episode_step + 1``, the
  done flags of ``DiffEnv._truncated``, ``observation`` of the new state;
* with ``break_when_any_done`` the loop stops after the first step where any env is done;
  otherwise done envs are reset between steps as ``maybe_reset`` does: a full-batch
  ``initial_state`` draw (so the env's generator advances exactly as in TorchRL) merged with
  ``torch.where(~reset, old, fresh)``; the merge cuts the graph for the reset envs only;
* the root entries of step ``t + 1`` are the ``"next"`` entries of step ``t`` (the same
  tensors, as ``step_mdp`` makes them), reset envs excepted.
"""
from __future__ import annotations

import itertools
import logging
import operator
import time
import types
import weakref
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from .._compat import (
    COMPILE_ERRORS,
    ENVBASE_STEP_METHODS,
    has_dynamic_specs,
    make_compatible_policy,
    rollout_machinery_in_use,
    unchecked_tensordict,
)


__all__ = [
    "fast_rollout", "fast_rollout_unsupported", "compile_physics", "eager_physics", "compile_report",
    "FAST_ROLLOUT_KWARGS",
]

_logger = logging.getLogger(__name__)

# Entries that the env owns at the root of a step TensorDict (everything else at the root, such as
# "action" or a policy's "loc"/"scale", belongs to the policy or to the user).
_ENV_KEYS = ("observation", "state", "params", "episode_step", "terminated", "truncated", "done")
_NESTED_ENV_KEYS = ("state", "params")
_FLAG_KEYS = ("terminated", "truncated", "done")

# Keyword arguments of EnvBase.rollout that the lean path implements, with the values it accepts
# (``None`` = any value). Anything else sends the call to EnvBase.rollout.
FAST_ROLLOUT_KWARGS: dict[str, tuple | None] = {
    "auto_reset": None,
    "break_when_any_done": None,
    "break_when_all_done": (None, False),
    "return_contiguous": None,
    "tensordict": None,
    "set_truncated": None,
    "trust_policy": None,
    "set_state": None,
    "actions": None,
    "auto_cast_to_device": (False,),
    "storing_device": (None,),
    "out": (None,),
}

# Methods whose TorchRL / DiffEnv versions the lean loop reimplements: a subclass that overrides
# one of them gets EnvBase.rollout, which calls the override.
_REIMPLEMENTED_METHODS = (
    "_step", "_reset", "step", "reset", "maybe_reset", "step_and_maybe_reset", "rand_action", "any_done", "_output",
    *ENVBASE_STEP_METHODS,
)


def fast_rollout_unsupported(env: EnvBase, callback: Callable | None, kwargs: Mapping[str, Any]) -> str | None:
    """Why ``env.rollout(..., callback=callback, **kwargs)`` must take ``EnvBase.rollout``.

    Returns ``None`` when the lean path reproduces the call exactly, else a short reason
    (useful when debugging a slow rollout: ``fast_rollout_unsupported(env, None, kwargs)``).
    """
    if not getattr(env, "use_fast_rollout", True):
        return "env.use_fast_rollout is False"
    if callback is not None:
        return "a callback is given"
    for key, value in kwargs.items():
        if key not in FAST_ROLLOUT_KWARGS:
            return f"unknown keyword argument {key!r}"
        allowed = FAST_ROLLOUT_KWARGS[key]
        if allowed is not None and not any(value is a or (a is not None and value == a) for a in allowed):
            return f"{key}={value!r}"
    # (a task with its own truncation rule overrides DiffEnv._truncated, which the loop calls)
    overridden = type(env).overridden_methods(_REIMPLEMENTED_METHODS)
    if overridden:
        return f"{type(env).__name__} overrides {overridden[0]}"
    machinery = rollout_machinery_in_use(env)
    if machinery is not None:
        return machinery
    if env.run_type_checks:
        return "run_type_checks"
    if env.action_keys != ["action"] or env.reward_keys != ["reward"] or sorted(env.done_keys) != sorted(_FLAG_KEYS):
        return "non-default action/reward/done keys"
    td = kwargs.get("tensordict")
    if td is not None and (not isinstance(td, TensorDict) or "next" in td.keys() or "_step" in td.keys()):
        return "the input tensordict is not a plain TensorDict without 'next'/'_step' entries"
    return None


def fast_rollout(
    env: EnvBase,
    max_steps: int,
    policy: Callable[[TensorDictBase], TensorDictBase] | None = None,
    *,
    auto_reset: bool = True,
    break_when_any_done: bool | None = None,
    break_when_all_done: bool | None = None,
    return_contiguous: bool | None = False,
    tensordict: TensorDictBase | None = None,
    set_truncated: bool = False,
    trust_policy: bool = False,
    set_state: bool | None = None,
    actions: Iterable[torch.Tensor] | None = None,
    auto_cast_to_device: bool = False,
    storing_device=None,
    out=None,
) -> TensorDictBase:
    """``EnvBase.rollout(env, ...)`` through a lean loop (same arguments, same result).

    Call it through ``env.rollout``, which checks :func:`fast_rollout_unsupported` first; calling
    it directly with an unsupported argument raises ``ValueError``.
    """
    reason = fast_rollout_unsupported(
        env, None,
        dict(break_when_all_done=break_when_all_done, auto_cast_to_device=auto_cast_to_device,
             storing_device=storing_device, out=out, tensordict=tensordict),
    )
    if reason is not None:
        raise ValueError(f"fast_rollout cannot reproduce EnvBase.rollout here ({reason}); call env.rollout")
    if break_when_any_done is None:  # EnvBase's defaults
        break_when_any_done = not break_when_all_done
    if return_contiguous is None:
        return_contiguous = not has_dynamic_specs(env)
    try:
        max_steps = operator.index(max_steps)
    except TypeError:
        raise TypeError(f"{env.name}: rollout max_steps must be an integer, got {max_steps!r}") from None

    action_source = None
    if actions is not None:
        if policy is not None:
            raise ValueError("Cannot pass both `policy` and `actions` to rollout().")
        action_source = iter(actions)
        if hasattr(actions, "__len__"):
            max_steps = min(max_steps, len(actions))
    elif policy is not None:
        policy = make_compatible_policy(policy, env, trust_policy)

    # The first TensorDict comes from TorchRL itself: same reset, same warnings, same in-place
    # update of a user-given ``tensordict``.
    if auto_reset:
        td0 = env.reset(tensordict, set_state=set_state)
    elif tensordict is None:
        raise RuntimeError("tensordict must be provided when auto_reset is False")
    else:
        td0 = env.maybe_reset(tensordict)
    if max_steps < 1:  # EnvBase.rollout fails later, stacking an empty list
        raise ValueError(f"{env.name}: rollout needs max_steps >= 1 (and actions, if given), got {max_steps}")
    loop = _Loop(env, policy, action_source, max_steps)
    return loop.run(td0, max_steps, break_when_any_done, return_contiguous, set_truncated)


def _physics_steps(env: EnvBase, plain_truncation: bool, state: dict, params: dict, episode_step: torch.Tensor,
                   actions: list[torch.Tensor]) -> list[dict]:
    """``DiffEnv._step`` on plain tensors, once per action: the ``"next"`` entries of each step.

    Pure tensor code (``torch.compile`` traces it, see :func:`compile_physics`). Flags that need
    no computation come back as ``None`` and :class:`_Physics` fills them in: ``"terminated"`` of
    a task without termination, ``"done"`` when it equals ``"truncated"``, both when there is no
    time limit either. The ``"params"`` entry is added by the caller (the input, unchanged).
    """
    out = []
    for action in actions:
        if env.clip_actions:
            action = action.clamp(env.action_low, env.action_high)
        state, reward, terminated = env.transition(state, action, params)
        episode_step = episode_step + 1
        if terminated is None and plain_truncation:
            # DiffEnv._truncated with nothing terminated: one comparison, and done == truncated
            truncated = None if env.max_episode_steps is None else episode_step >= env.max_episode_steps
            done = None
        else:
            flags = terminated if terminated is not None else torch.zeros_like(episode_step, dtype=torch.bool)
            truncated = env._truncated(episode_step, flags)
            done = flags | truncated
        out.append({
            "observation": env.observation(state, params),
            "state": state,
            "episode_step": episode_step,
            "terminated": terminated,
            "truncated": truncated,
            "done": done,
            "reward": reward,
        })
    return out


def _chunk_steps(env: EnvBase, policy, plain_truncation: bool, merge_params: bool, chunk: int, root: dict,
                 extras: dict, actions: list | None, fresh: dict | None, all_false: torch.Tensor) -> list[tuple]:
    """``K`` steps of policy + physics + auto-reset on plain tensors (``torch.compile`` traces it).

    The actions come from ``policy`` (a TensorDict module called on each step's entries) or,
    without one, from ``actions`` (random or given; then ``extras`` is empty).

    What the lean loop does step by step, with the resets inside: where some env is done after
    step ``j < K - 1``, its entries are replaced by the ``c``-th of the ``K - 1`` full-batch start
    states drawn ahead in ``fresh`` (``c`` counts the steps with a reset so far, so the draws are
    used in the order the eager loop would draw them), the other envs keep theirs (the graph is
    cut for the reset envs only), and the entries that are not the env's are zeroed for them.

    Args:
        root: the env entries at the chunk's first step but the done flags (all False there).
        extras: the other root entries (the previous step's policy outputs).
        actions: the ``K`` actions without a policy, else ``None``.
        fresh: ``{"observation": [K-1, N, ...], "state": {...}}`` (plus ``"params"``, env.params,
            when ``merge_params``), or ``None``: no resets inside the chunk (the caller knows none
            is needed, or checks afterwards that none was).

    Returns ``(policy outputs, "next" entries, merged root or None)`` per step; the merged root
    (observation, state, episode step, and parameters when ``merge_params``) is that of the next
    step when some env was done, computed at every step but the last when ``fresh`` is given (the
    loop uses it only then).
    """
    steps = []
    resets = torch.zeros(1, dtype=torch.int64, device=all_false.device)  # resets so far in this chunk
    zero = torch.zeros((), dtype=root["episode_step"].dtype, device=all_false.device)
    flags = {key: all_false.unsqueeze(-1) for key in _FLAG_KEYS}  # the TorchRL layout: [N, 1]
    for j in range(chunk):
        if policy is None:
            out = {"action": actions[j]}
        else:
            td = policy(TensorDict({**root, **flags, **extras}, batch_size=all_false.shape, device=all_false.device))
            out = {key: td.get(key) for key in td.keys() if key not in _ENV_KEYS}
        nxt = _physics_steps(env, plain_truncation, root["state"], root["params"], root["episode_step"],
                             [out["action"]])[0]
        merged = None
        if j < chunk - 1 and fresh is not None:
            done = nxt["done"] if nxt["done"] is not None else nxt["truncated"]
            done = all_false if done is None else done
            keep = ~done

            def merge(old, new, keep=keep):
                return torch.where(keep.reshape(keep.shape + (1,) * (old.ndim - 1)), old, new)

            def drawn(stacked):  # the start states of draw number `resets` (index_select: no .item())
                return stacked.index_select(0, resets).squeeze(0)

            merged = {"observation": merge(nxt["observation"], drawn(fresh["observation"])),
                      "state": {key: merge(value, drawn(fresh["state"][key])) for key, value in nxt["state"].items()},
                      "episode_step": merge(nxt["episode_step"], zero)}
            if merge_params:
                merged["params"] = {key: merge(value, fresh["params"][key]) for key, value in root["params"].items()}
            # a reset of every env leaves the other entries as they are (TorchRL replaces the env's only)
            keep_extras = keep | done.all()
            extras = {key: merge(value, torch.zeros((), dtype=value.dtype, device=value.device), keep=keep_extras)
                      for key, value in out.items()}
            resets = resets + done.any().to(resets.dtype)
            root = {**merged, "params": merged.get("params", root["params"])}
        else:
            root = {"observation": nxt["observation"], "state": nxt["state"], "params": root["params"],
                    "episode_step": nxt["episode_step"]}
            extras = out
        steps.append((out, nxt, merged))
    return steps


class _Physics:
    """Runs :func:`_physics_steps` eagerly; knows whether :func:`compile_physics` applies."""

    def __init__(self, env: EnvBase, all_false: torch.Tensor):
        self.env = env
        self.all_false = all_false
        self.plain_truncation = not type(env).overridden_methods(("_truncated",))
        self.compiled = env.__dict__.get("_compiled_physics")
        self.chunk = 1 if self.compiled is None else self.compiled.steps_per_chunk

    def steps(self, state: dict, params: dict, episode_step: torch.Tensor, actions: list[torch.Tensor]) -> list[dict]:
        """Eager steps (compiled chunks go through :meth:`_Loop.run_chunk`)."""
        for action in actions:
            self.env._check_action(action)
        out = _physics_steps(self.env, self.plain_truncation, state, params, episode_step, actions)
        return [self.complete(nxt, params) for nxt in out]

    def complete(self, nxt: dict, params: dict) -> dict:
        """Fills in the flags that came back as ``None`` and the ``"params"`` entry."""
        nxt["params"] = params
        if nxt["terminated"] is None:
            nxt["terminated"] = self.all_false
        if nxt["truncated"] is None:
            nxt["truncated"] = self.all_false
        if nxt["done"] is None:
            nxt["done"] = nxt["truncated"]
        return nxt


class _CompiledPhysics:
    """The ``torch.compile``'d chunk functions of one env (:func:`_chunk_steps`) and what the
    rollouts learned about them."""

    def __init__(self, env: EnvBase, steps_per_chunk: int, compile_kwargs: dict):
        self.steps_per_chunk = steps_per_chunk
        self.compile_kwargs = {"dynamic": False, **compile_kwargs}
        self.env_ref = weakref.ref(env)  # the env holds this object: no reference cycle
        # policy -> {(plain_truncation, merge_params): compiled chunk}; without a policy: self.functions
        self.policy_functions: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.functions: dict[tuple[bool, bool], Callable] = {}
        self.fallback_reason: str | None = None  # why compiled chunks were given up (then eager)
        self.first_call_seconds: dict[str, float] = {}  # first call (tracing + compiling + running)
        self.cannot_terminate = False  # learned from the first chunk: the task returns no "terminated"
        self.expect_resets = True  # the last chunk that could reset did: draw start states ahead

    def note_first_call(self, what: str, seconds: float) -> None:
        """Records the duration of the first call of each compiled function (mostly compiling)."""
        what = f"{what}, {'with' if torch.is_grad_enabled() else 'without'} grad"
        self.first_call_seconds.setdefault(what, seconds)

    def chunk_function(self, policy, plain_truncation: bool, merge_params: bool, with_resets: bool) -> Callable:
        """The compiled :func:`_chunk_steps` for ``policy`` (one per policy object, or ``None``)."""
        functions = self.functions if policy is None else self.policy_functions.setdefault(policy, {})
        key = (plain_truncation, merge_params, with_resets)
        fn = functions.get(key)
        if fn is None:
            env_ref, steps = self.env_ref, self.steps_per_chunk
            policy_ref = (lambda: None) if policy is None else weakref.ref(policy)

            def chunk(root, extras, actions, fresh, all_false):
                return _chunk_steps(env_ref(), policy_ref(), plain_truncation, merge_params, steps, root, extras,
                                    actions, fresh, all_false)

            fn = functions[key] = torch.compile(_own_code(chunk), **self.compile_kwargs)
        return fn


_CHUNK_FUNCTIONS = itertools.count()


def _own_code(function: Callable) -> Callable:
    """``function`` with a code object of its own.

    ``torch.compile`` keeps compiled code, and its limit of 8 recompilations, per code object;
    every env's chunk function is the same closure code, so a process with many envs (a test
    suite, a benchmark, a sweep of runs) would reach the limit and silently run the rest eagerly.
    """
    code = function.__code__.replace(co_name=f"{function.__name__}_{next(_CHUNK_FUNCTIONS)}")
    return types.FunctionType(code, function.__globals__, code.co_name, function.__defaults__, function.__closure__)


def compile_physics(env: EnvBase, steps_per_chunk: int = 8, **compile_kwargs) -> EnvBase:
    """Opt-in: ``env.rollout`` runs through ``torch.compile`` in chunks of ``K`` steps; returns ``env``.

    * With a policy (a TensorDict module such as :func:`~torchrl_diffenvs.modules.make_actor`'s,
      as BPTT, SHAC and evaluation call it): one compiled function per ``K``-step chunk covers
      the policy forward, the physics, the reward, the done flags and the auto-resets of envs
      whose episode ends inside the chunk; its backward is compiled too (AOTAutograd), so
      ``DiffWindowCollector`` windows and their gradients run compiled. Resets do not cut chunks:
      the ``K - 1`` full-batch start states that a chunk's resets may need are drawn ahead from
      ``env.rng`` and the generator is then set as if only the resets that happened had drawn,
      so the start states are those of the eager path. Drawing and merging costs about a physics
      step per step, so a chunk that cannot reset (no termination, far from the time limit, or
      ``break_when_any_done``) skips it, and one that probably will not (the previous one did not)
      first runs without it and runs again with it (the same policy noise) if some env was done.
    * Without a policy (random actions, or ``actions=``): the same chunk function steps the
      given actions (drawn eagerly, so the random stream is the eager path's), resets included.
    * Steps beyond whole chunks (``max_steps`` not a multiple of ``K``) run eagerly: choose
      ``K`` dividing the window length.

    The result is that of the eager path up to floating-point rounding (fused kernels may round
    differently), gradients included, with one exception: random numbers drawn inside compiled
    code (a stochastic policy's noise) come from inductor's own generator, seeded from torch's
    global one, so sampled actions differ from the eager path's draws (same distribution);
    ``torch._inductor.config.fallback_random = True`` makes them equal (tests use it).

    Compiling happens at first use and takes seconds to a minute per function on a CPU (one per
    policy object, grad mode and exploration mode, and again for the backward pass); it pays off
    for repeated rollouts, mostly at small and medium batch sizes (README, Performance).
    :func:`compile_report` says how long the first calls took. If ``torch.compile`` fails (no
    C++ compiler for inductor, an operation it cannot trace), the rollout logs the reason and
    runs eagerly from there on. ``compile_kwargs`` go to ``torch.compile`` (default
    ``dynamic=False``). Undo with :func:`eager_physics`. ``EnvBase.rollout`` and ``env.step``
    are not affected.
    """
    if isinstance(steps_per_chunk, bool) or not isinstance(steps_per_chunk, int) or steps_per_chunk < 1:
        raise ValueError(f"compile_physics: steps_per_chunk must be a positive integer, got {steps_per_chunk!r}")
    why_not = fast_rollout_unsupported(env, None, {})
    if why_not is not None:  # the compiled chunks replace the lean loop: without it nothing would compile
        raise ValueError(f"compile_physics: {type(env).__name__}'s rollouts cannot take the lean path that the "
                         f"compiled chunks replace ({why_not}); multi-agent envs roll out through EnvBase.rollout")
    env.__dict__["_compiled_physics"] = _CompiledPhysics(env, steps_per_chunk, compile_kwargs)
    return env


def compile_report(env: EnvBase) -> dict | None:
    """What :func:`compile_physics` did on ``env`` so far; ``None`` if it is not compiled.

    ``{"steps_per_chunk": K, "first_call_seconds": {function: seconds}, "fallback_reason": str
    or None}``: the first call of each compiled function (tracing and compiling included; the
    backward's compilation happens in the first ``backward()`` instead), and why compiled policy
    chunks were given up, if they were.
    """
    compiled = env.__dict__.get("_compiled_physics")
    if compiled is None:
        return None
    return {"steps_per_chunk": compiled.steps_per_chunk, "first_call_seconds": dict(compiled.first_call_seconds),
            "fallback_reason": compiled.fallback_reason}


def eager_physics(env: EnvBase) -> EnvBase:
    """Undoes :func:`compile_physics`; returns ``env``."""
    env.__dict__.pop("_compiled_physics", None)
    return env


class _RandomActions:
    """The random actions of ``EnvBase.rollout`` without a policy: ``action_spec.rand()`` per step.

    ``Bounded.rand()`` (torchrl 0.14) draws ``uniform_`` from torch's global generator, scales
    it to the bounds and sets values that rounding pushed past a bound to that bound. Here the
    same arithmetic runs on a block of steps at once: on CPU, ``uniform_`` fills a tensor from
    the generator element after element, so one draw of ``K`` steps gives the values of ``K``
    one-step draws, bitwise (tests/rollout/test_fast_rollout.py checks it against EnvBase.rollout).
    :meth:`close` rewinds the generator to the end of the last action actually used, so the
    global random stream continues exactly where TorchRL's rollout would leave it. (This relies
    on the physics being pure: a task draws its random start states from ``env.rng``, never from
    torch's global generator.)
    """

    BLOCK_ELEMENTS = 1 << 18  # about 1 MB of float32 per block

    def __init__(self, env: EnvBase, max_steps: int):
        space = env.action_spec.space
        self.low, self.high = space.low, space.high
        self.span = self.high - self.low
        self.shape = (env.num_envs, env.action_dim)
        self.dtype, self.device = env.float_dtype, env.device
        # other devices have counter-based generators whose block draws differ from step draws
        self.block_steps = 1
        if self.device.type == "cpu":
            self.block_steps = min(max_steps, max(1, self.BLOCK_ELEMENTS // (self.shape[0] * self.shape[1])))
        self.remaining = max_steps
        self.block: list[torch.Tensor] = []
        self.used = 0  # actions handed out from the current block
        self.state_before_block = None

    def __iter__(self):
        return self

    def __next__(self) -> torch.Tensor:
        if self.used == len(self.block):
            if self.block_steps > 1:
                self.state_before_block = torch.get_rng_state()
            steps = min(self.block_steps, self.remaining)
            self.remaining -= steps
            raw = torch.rand((steps, *self.shape), dtype=self.dtype, device=self.device)
            self.block = list(torch.clamp(raw * self.span + self.low, self.low, self.high).unbind(0))
            self.used = 0
        self.used += 1
        return self.block[self.used - 1]

    def close(self, unused: int = 0) -> None:
        """Leaves the global generator as if only the used actions had been drawn; ``unused``:
        the last actions handed out that the rollout did not use (a compiled chunk cut short by
        ``break_when_any_done``; rewound within the current block on CPU only)."""
        used = self.used - unused
        if self.block_steps > 1 and 0 <= used < len(self.block):
            torch.set_rng_state(self.state_before_block)
            torch.rand((used, *self.shape), dtype=self.dtype, device=self.device)
        self.block = []


class _Loop:
    """One rollout: per-step tensors in lists, stacked along the time dim at the end.

    Internally a step is a dict of entries ("observation", "state" and "params" as dicts of
    tensors, "episode_step", "action", ...); the done flags and the reward are kept ``[N]`` and
    get their trailing ``1`` only in TensorDicts (fewer ops per step, and the same tensor object
    can be recognised from step to step, see :func:`_stack_time`).
    """

    def __init__(self, env: EnvBase, policy, action_source, max_steps: int):
        self.env = env
        self.policy = policy
        if action_source is None and policy is None:
            action_source = _RandomActions(env, max_steps)
        self.action_source = action_source
        self.pending: list[torch.Tensor] = []  # actions drawn for a chunk that then ran eagerly
        self.n = env.num_envs
        self.bs = env.batch_size
        self.device = env.device
        self.all_false = torch.zeros(self.n, dtype=torch.bool, device=self.device)
        self.physics = _Physics(env, self.all_false)

    # ------------------------------------------------------------------ main loop
    def run(self, td0: TensorDictBase, max_steps: int, break_when_any_done: bool, return_contiguous: bool,
            set_truncated: bool) -> TensorDictBase:
        root = self.entries_of(td0)
        # root entries that are not the env's (a user's extra entries) travel along, as step_mdp does
        extras = {key: value for key, value in root.items() if key not in _ENV_KEYS}
        root = {key: root[key] for key in _ENV_KEYS}
        # Physical parameters equal to env.params, without gradient: a reset merges them with
        # env.params, which leaves them as they are (and the same tensors from step to step).
        env_params = self.env.params
        self.params_are_env_params = root["params"].keys() == set(env_params.keys()) and all(
            not value.requires_grad and not env_params[key].requires_grad and torch.equal(value, env_params[key])
            for key, value in root["params"].items()
        )
        roots: list[dict] = []
        nexts: list[dict] = []
        t, finished = 0, False
        chunked = self.chunks_unsupported(extras) is None
        while not finished:
            if chunked and max_steps - t >= self.physics.chunk:
                actions = None if self.policy is not None else [self.next_action() for _ in range(self.physics.chunk)]
                result = self.run_chunk(td0, root, extras, actions, t, max_steps, break_when_any_done, roots, nexts)
                if result is not None:
                    t, finished, root, extras = result
                    continue
                chunked = False  # compiling failed (logged): eager from here on
                self.pending = actions or []
            if self.policy is not None:
                # step 0 runs on the input TensorDict itself, as in EnvBase
                views: dict = {}
                td = td0 if t == 0 else self.as_tensordict({**root, **extras}, views)
                root_t = self.call_policy(td, views)  # what the policy leaves at the root is what TorchRL stores
                action = root_t["action"]
            else:
                action = self.next_action()
                if t == 0:  # EnvBase writes step 0's action into the input tensordict
                    td0.set("action", self.first_action(action))
                root_t = {**root, **extras, "action": action}
            nxt = self.physics.steps(root_t["state"], root_t["params"], root_t["episode_step"], [action])[0]
            roots.append(root_t)
            nexts.append(nxt)
            t += 1
            any_done = bool(nxt["done"].any())
            if t == max_steps or (break_when_any_done and any_done):
                break
            # step_mdp: the next root is the "next" entries plus whatever else was at the root
            root = {key: nxt[key] for key in _ENV_KEYS}
            extras = {key: value for key, value in root_t.items() if key not in _ENV_KEYS}
            if any_done:  # only without break_when_any_done
                root, extras = self.reset_done(nxt["done"], root, extras)

        if isinstance(self.action_source, _RandomActions):
            self.action_source.close(unused=len(self.pending))
        out_td = self.build_output(roots, nexts, return_contiguous)
        # EnvBase leaves step 0's "next" in the input tensordict; rendering wants the last output
        td0.set("next", self.as_tensordict(nexts[0]))
        remember = getattr(self.env, "_remember_for_render", None)
        if remember is not None:
            remember(self.as_tensordict(nexts[-1]))
        if set_truncated:
            _set_truncated_last_step(out_td)
        out_td.refine_names(..., "time")
        return out_td

    def call_policy(self, td: TensorDictBase, views: dict) -> dict:
        """Runs the policy on a step TensorDict; returns the root entries it leaves."""
        td.update(self.policy(td))
        entries = self.entries_of(td, views)
        if "action" not in entries:
            raise KeyError(f"{self.env.name}: the policy wrote no 'action' entry (keys: {sorted(entries)})")
        return entries

    def next_action(self) -> torch.Tensor:
        """The next random or given action (without a policy)."""
        return self.pending.pop(0) if self.pending else next(self.action_source)

    def first_action(self, action: torch.Tensor) -> torch.Tensor:
        """What EnvBase leaves as the input tensordict's ``"action"`` without a policy."""
        return action.clone() if isinstance(self.action_source, _RandomActions) else action

    # ------------------------------------------------------------------ compiled chunks
    def chunks_unsupported(self, extras: dict) -> str | None:
        """Why the steps cannot run in compiled chunks (:func:`compile_physics`), or ``None``."""
        compiled = self.physics.compiled
        if compiled is None:
            return "no compile_physics"
        if compiled.fallback_reason is not None:
            return compiled.fallback_reason
        if self.policy is None:
            # the eager loop carries other root entries along (zeroed at resets): not in chunks
            return None if set(extras) <= {"action"} else "the input tensordict has entries besides the env's"
        out_keys = getattr(self.policy, "out_keys", None)
        if not isinstance(self.policy, TensorDictModuleBase) or out_keys is None:
            return "the policy is not a TensorDict module"
        if any(not isinstance(key, str) or key in _ENV_KEYS for key in out_keys):
            return f"the policy writes nested keys or the env's own entries ({out_keys})"
        if any(not isinstance(value, torch.Tensor) for value in extras.values()):
            return "the input tensordict holds nested entries besides the env's"
        return None

    def run_chunk(self, td0: TensorDictBase, root: dict, extras: dict, actions: list | None, t: int, max_steps: int,
                  break_when_any_done: bool, roots: list, nexts: list) -> tuple | None:
        """Runs ``K`` policy + physics steps (or physics steps of the ``K`` given actions) in one
        compiled call and books them as the eager loop would (same entries, same tensors reused
        between steps, same draws from ``env.rng``).

        Returns ``(t, finished, root, extras)`` after the chunk, or ``None`` when compiling
        failed: the reason is logged and kept (``compile_report(env)``), nothing was consumed and
        the rollout goes on eagerly.
        """
        env, compiled = self.env, self.physics.compiled
        merge_params = not self.params_are_env_params
        # The previous step's outputs (the only extras, usually) are overwritten by the policy and
        # not read by it: leave them out, so that every chunk has the first chunk's inputs (one compile).
        policy_keys = set() if self.policy is None else set(self.policy.out_keys) - set(self.policy.in_keys)
        extras_in = {} if set(extras) <= policy_keys or self.policy is None else {
            key: value.contiguous() for key, value in extras.items()}
        if actions is not None:
            for action in actions:
                env._check_action(action)
            actions_in = [action.contiguous() for action in actions]
        else:
            actions_in = None
        inputs = _chunk_inputs(root)

        def run(with_resets: bool):
            fresh, rng_states = self.fresh_starts(merge_params) if with_resets else (None, None)
            function = compiled.chunk_function(self.policy, self.physics.plain_truncation, merge_params, with_resets)
            try:
                return function(inputs, extras_in, actions_in, fresh, self.all_false), rng_states
            except COMPILE_ERRORS:
                if rng_states is not None:
                    env.rng.set_state(rng_states[0])
                raise

        # Drawing start states ahead and merging them costs about a physics step per step: a chunk
        # that cannot reset (break_when_any_done, or no termination and far from the time limit)
        # skips it, and one that probably will not (the last one did not) runs without and is run
        # again with resets if some env was done before its last step.
        with_resets = self.physics.chunk > 1 and not (break_when_any_done or self.no_reset_possible(root))
        speculate = with_resets and not compiled.expect_resets
        random_state = _global_random_state(env.device) if speculate else None
        started = time.perf_counter()
        try:
            steps, rng_states = run(with_resets and not speculate)
            if speculate and any(_any_done(nxt) for _, nxt, _ in steps[:-1]):
                _set_global_random_state(env.device, random_state)  # the policy's noise, as the first time
                steps, rng_states = run(True)
        except COMPILE_ERRORS as err:
            if random_state is not None:
                _set_global_random_state(env.device, random_state)
            message = " ".join(line.strip() for line in str(err).splitlines()[:3] if line.strip())
            compiled.fallback_reason = f"torch.compile failed ({type(err).__name__}: {message})"
            _logger.warning("%s: compiled rollout chunks disabled, running eagerly: %s", env.name,
                            compiled.fallback_reason)
            return None
        what = "physics" if self.policy is None else "policy + physics"
        compiled.note_first_call(f"{what}, {len(steps)} steps", time.perf_counter() - started)
        compiled.cannot_terminate = all(nxt["terminated"] is None for _, nxt, _ in steps)
        if actions is not None:  # the actions as given (the same tensors as the eager loop stores)
            steps = [({"action": action}, nxt, merged) for action, (_, nxt, merged) in zip(actions, steps)]
        env._check_action(steps[0][0]["action"])
        if t == 0 and actions is not None:  # EnvBase writes step 0's action into the input tensordict
            td0.set("action", self.first_action(actions[0]))
        elif t == 0:  # EnvBase runs step 0's policy on the input tensordict itself
            for key, value in steps[0][0].items():
                td0.set(key, value)
        finished, resets, nxt = False, 0, None
        for j, (out, nxt, merged) in enumerate(steps):
            nxt = self.physics.complete(nxt, root["params"])
            roots.append({**root, **out})
            nexts.append(nxt)
            t += 1
            any_done = bool(nxt["done"].any())
            if t == max_steps or (break_when_any_done and any_done):
                finished = True
                if actions is not None:
                    self.pending = actions[j + 1:]  # drawn, not used: the generator is rewound past them
                break
            if j < len(steps) - 1 and any_done:  # reset inside the chunk
                resets += 1
                root = {**merged, "params": merged.get("params", root["params"]),
                        **{key: self.all_false for key in _FLAG_KEYS}}
            else:
                root = {key: nxt[key] for key in _ENV_KEYS}
                extras = out
        if rng_states is not None:  # as if only the resets that happened had drawn
            env.rng.set_state(rng_states[resets])
            compiled.expect_resets = resets > 0
        elif with_resets:  # speculated right: no reset
            compiled.expect_resets = False
        if not finished and bool(nxt["done"].any()):  # done at the chunk's last step
            root, extras = self.reset_done(nxt["done"], root, extras)
        return t, finished, root, extras

    def no_reset_possible(self, root: dict) -> bool:
        """No env can be done before a chunk's last step: the task has no termination (learned
        from the first chunk) and every env is more than a chunk away from its time limit."""
        env, compiled = self.env, self.physics.compiled
        if not (compiled.cannot_terminate and self.physics.plain_truncation):
            return False
        limit = env.max_episode_steps
        return limit is None or int(root["episode_step"].max()) + self.physics.chunk - 1 < limit

    def fresh_starts(self, merge_params: bool) -> tuple[dict, list]:
        """The ``K - 1`` full-batch start states a chunk may reset to, drawn ahead from ``env.rng``,
        with the generator's state before each draw and after the last, so that the loop can leave
        ``env.rng`` as if only the resets that happened had drawn."""
        env = self.env
        states, observations, starts = [env.rng.get_state()], [], []
        for _ in range(self.physics.chunk - 1):
            start = env.initial_state(env.params, self.n)
            observations.append(env.observation(start, env.params))
            starts.append(start)
            states.append(env.rng.get_state())
        fresh = {"observation": torch.stack(observations),
                 "state": {key: torch.stack([start[key] for start in starts]) for key in starts[0]}}
        if merge_params:
            fresh["params"] = dict(env.params.items())
        return fresh, states

    def reset_done(self, done: torch.Tensor, root: dict, extras: dict) -> tuple[dict, dict]:
        """``maybe_reset``: fresh start states for the done envs, the graph cut there only.

        TorchRL calls ``DiffEnv._reset`` for the whole batch (so the env's generator advances by
        a full-batch draw) and merges with ``torch.where(~done, old, fresh)``. Two merges are
        known without computing them: the done flags (an env that is not done has no flag set:
        ``done = terminated | truncated``), and the physical parameters when they are
        ``env.params`` themselves, without gradient (see :meth:`run`).
        """
        env = self.env
        # DiffEnv._reset passes a clone of env.params; initial_state is pure, so env.params will do
        state = env.initial_state(env.params, self.n)
        observation = env.observation(state, env.params)
        params = root["params"] if self.params_are_env_params else dict(env.params.clone().items())
        flags = {key: self.all_false for key in _FLAG_KEYS}
        if bool(done.all()):
            # TorchRL then replaces the env entries and leaves the others untouched
            zeros = torch.zeros(self.n, dtype=torch.int64, device=self.device)
            return {"observation": observation, "state": dict(state), "params": params, "episode_step": zeros,
                    **flags}, extras
        keep = ~done
        masks = {1: keep}  # keep, shaped for entries of each number of dims

        def merge(old: torch.Tensor, new) -> torch.Tensor:
            mask = masks.get(old.ndim)
            if mask is None:
                mask = masks[old.ndim] = keep.reshape(keep.shape + (1,) * (old.ndim - 1))
            return torch.where(mask, old, new)

        merged = {"observation": merge(root["observation"], observation),
                  "state": {k: merge(v, state[k]) for k, v in root["state"].items()},
                  "params": params if self.params_are_env_params else
                  {k: merge(v, params[k]) for k, v in root["params"].items()},
                  "episode_step": merge(root["episode_step"], 0),
                  **flags}
        # entries the reset does not produce (action, policy outputs, user extras) are zeroed;
        # without a policy the action is replaced before anyone sees it
        extras = {key: value if key == "action" and self.policy is None else _zero_where(done, value)
                  for key, value in extras.items()}
        return merged, extras

    # ------------------------------------------------------------------ TensorDict <-> entries
    def entries_of(self, td: TensorDictBase, views: dict | None = None) -> dict:
        """A step TensorDict's root entries in the internal layout.

        ``views``: the ``{key: ([N, 1] view, [N] flag)}`` that :meth:`as_tensordict` made for
        ``td``; a flag the policy left untouched maps back to the loop's own tensor.
        """
        entries = dict(td.items())
        for key in _NESTED_ENV_KEYS:
            entries[key] = dict(entries[key].items())
        for key in _FLAG_KEYS:
            flag = entries[key]
            made = views.get(key) if views else None
            entries[key] = made[1] if made is not None and made[0] is flag else flag.reshape(self.n)
        return entries

    def as_tensordict(self, entries: dict, views: dict | None = None) -> TensorDict:
        """A ``[N]`` TensorDict of one step's entries (the TorchRL layout); see :meth:`entries_of`."""
        source = {}
        for key, value in entries.items():
            if key in _FLAG_KEYS or key == "reward":
                view = value.unsqueeze(-1)
                if views is not None:
                    views[key] = (view, value)
                value = view
            source[key] = value  # "state" / "params" dicts become nested TensorDicts
        # every entry already has the right batch size and device: skip TensorDict's checks
        # (about 15 us per TensorDict; the public constructor validates the final output)
        return unchecked_tensordict(source, self.bs, self.device)

    # ------------------------------------------------------------------ output
    def build_output(self, roots: list[dict], nexts: list[dict], return_contiguous: bool) -> TensorDictBase:
        """Stacks every entry along a new time dim 1: ``[N, T, ...]``, as EnvBase.rollout does."""
        if any(r.keys() != roots[0].keys() for r in roots):
            # a policy that writes different keys at different steps: let TensorDict decide, as EnvBase does
            steps = [self.as_tensordict({**r, "next": self.as_tensordict(x)}) for r, x in zip(roots, nexts)]
            if return_contiguous:
                return torch.stack(steps, len(self.bs))
            return LazyStackedTensorDict.maybe_dense_stack(steps, len(self.bs))
        batch_size = torch.Size([self.n, len(roots)])

        memo: dict = {}  # entries made of the very same tensors (e.g. "truncated" and "done") stack once

        def stack_once(values):
            ids = tuple(map(id, values))
            if ids in memo:
                return memo[ids].clone()
            memo[ids] = result = _stack_time(values)
            return result

        def stacked(key, sub=None):
            pick = (lambda d: d[key]) if sub is None else (lambda d: d[key][sub])
            next_values = [pick(x) for x in nexts] if key in nexts[0] else None
            next_stack = None if next_values is None else stack_once(next_values)
            return _stack_root([pick(r) for r in roots], next_values, next_stack), next_stack

        out, out_next = {}, {}
        for key in roots[0]:
            if key in _NESTED_ENV_KEYS:
                leaves = {sub: stacked(key, sub) for sub in roots[0][key]}
                out[key] = TensorDict({k: v[0] for k, v in leaves.items()}, batch_size=batch_size, device=self.device)
                out_next[key] = TensorDict({k: v[1] for k, v in leaves.items()}, batch_size=batch_size,
                                           device=self.device)
            elif isinstance(roots[0][key], torch.Tensor):
                out[key], next_stack = stacked(key)
                if next_stack is not None:
                    out_next[key] = next_stack
            else:  # a policy's nested TensorDict
                out[key] = torch.stack([r[key] for r in roots], dim=1)
        for key in nexts[0]:
            if key not in out_next:  # "reward"
                out_next[key] = stack_once([x[key] for x in nexts])
        for entries in (out, out_next):  # [N, T] -> [N, T, 1], TorchRL's layout
            for key in (*_FLAG_KEYS, "reward"):
                if key in entries:
                    entries[key] = entries[key].unsqueeze(-1)
        out["next"] = TensorDict(out_next, batch_size=batch_size, device=self.device)
        return TensorDict(out, batch_size=batch_size, device=self.device)


def _stack_time(values: list[torch.Tensor]) -> torch.Tensor:
    """``torch.stack(values, dim=1)``, with runs of one repeated tensor copied in one go.

    Entries that do not change between resets (the physical parameters, a goal position, the
    ``terminated`` flag of a task without termination) appear as the same tensor object at many
    steps; expanding it is the same data and the same gradient as stacking it.
    """
    runs = _runs(values)
    if 4 * len(runs) > len(values):
        return torch.stack(values, dim=1)
    pieces = [v.unsqueeze(1).expand(v.shape[0], count, *v.shape[1:]) for v, count in runs]
    return torch.cat(pieces, dim=1) if len(pieces) > 1 else pieces[0].clone()


def _runs(values: list[torch.Tensor]) -> list[list]:
    """``[[tensor, count], ...]``: consecutive repeats of the same tensor object."""
    runs: list[list] = []
    for value in values:
        if runs and runs[-1][0] is value:
            runs[-1][1] += 1
        else:
            runs.append([value, 1])
    return runs


def _few_runs(values: list[torch.Tensor]) -> bool:
    return 4 * len(_runs(values)) <= len(values)


def _stack_root(root_values: list[torch.Tensor], next_values: list[torch.Tensor] | None,
                next_stack: torch.Tensor | None) -> torch.Tensor:
    """Stacks a root entry; where it is the previous step's ``"next"`` entry, copies that slice.

    Between resets the root entry of step ``t + 1`` *is* the ``"next"`` entry of step ``t`` (the
    same tensor, as ``step_mdp`` makes it): one contiguous copy of the stacked ``"next"`` entry
    replaces a second strided stack. Reset steps contribute their own (merged) tensor.
    """
    if next_values is None or _few_runs(root_values):
        return _stack_time(root_values)  # e.g. unchanged physical parameters: expand, no read-back
    pieces = [root_values[0].unsqueeze(1)]
    start = None  # first step of the current run of steps that reuse "next" entries
    for t in range(1, len(root_values)):
        if root_values[t] is next_values[t - 1]:
            if start is None:
                start = t
            continue
        if start is not None:
            pieces.append(next_stack[:, start - 1:t - 1])
            start = None
        pieces.append(root_values[t].unsqueeze(1))
    if start is not None:
        pieces.append(next_stack[:, start - 1:len(root_values) - 1])
    return torch.cat(pieces, dim=1)


def _any_done(nxt: dict) -> bool:
    done = nxt["done"] if nxt["done"] is not None else nxt["truncated"]
    return done is not None and bool(done.any())


def _global_random_state(device: torch.device) -> tuple:
    """Torch's global generator (and the device's): what a policy's noise is drawn from."""
    cuda = torch.cuda.get_rng_state(device) if device.type == "cuda" else None
    return torch.get_rng_state(), cuda


def _set_global_random_state(device: torch.device, state: tuple) -> None:
    torch.set_rng_state(state[0])
    if state[1] is not None:
        torch.cuda.set_rng_state(state[1], device)


def _chunk_inputs(root: dict) -> dict:
    """The root entries a compiled chunk takes: no done flags, every tensor contiguous, and with
    grad on, the floating-point state and observation as tensors that require grad.

    Compiled code is specialised on strides and ``requires_grad``: a window continues from slices
    of the previous window's output (strided) and from detached tensors, while its later chunks
    get contiguous, differentiable ones; without this every window would alternate between two
    compiled functions (and compile both). A detached input becomes a fresh leaf with the same
    values (its gradient is computed and dropped: an ``[N, d]`` tensor per chunk).
    """
    # The done flags at a chunk's start are always all False (a done env has been reset), and
    # passing them would specialise the compiled code on which of them are the same tensor.
    grad = torch.is_grad_enabled()

    def prepared(value, differentiable: bool):
        value = value.contiguous()
        if grad and differentiable and value.is_floating_point() and not value.requires_grad:
            value = value.detach().requires_grad_(True)
        return value

    return {"observation": prepared(root["observation"], True),
            "state": {key: prepared(value, True) for key, value in root["state"].items()},
            "params": {key: prepared(value, False) for key, value in root["params"].items()},
            "episode_step": root["episode_step"].contiguous()}


def _zero_where(reset: torch.Tensor, value):
    """``TensorDict.where(~reset, other=<nothing>, pad=0)`` for one entry."""
    if isinstance(value, torch.Tensor):
        keep = (~reset).reshape(reset.shape + (1,) * (value.ndim - 1))
        return torch.where(keep, value, torch.tensor(0, dtype=value.dtype, device=value.device))
    return value.where(~reset, other=value.empty(), pad=0)


def _set_truncated_last_step(out_td: TensorDictBase) -> None:
    """EnvBase.rollout(set_truncated=True): the last step is marked truncated (and done)."""
    val = out_td.get(("next", "truncated"))
    done = out_td.get(("next", "done"))
    val[(slice(None),) * (out_td.ndim - 1) + (-1,)] = True
    out_td.set(("next", "truncated"), val)
    out_td.set(("next", "done"), val | done)
