"""Opt-in ``torch.compile`` of rollouts: [`compile_physics`][torchrl_diffenvs.compile_physics] runs ``K``-step chunks of the
lean loop (policy, `physics_step`, `merge_reset`) as one compiled function."""
from __future__ import annotations

import itertools
import time
import types
import weakref
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from ...articulated.integrators import eager_step, stepping_with
from ...articulated.tree import RigidBodyTree
from .step import ENV_KEYS, FLAG_KEYS, merge_reset, physics_step
from .support import fast_rollout_unsupported

__all__ = ["CompiledPhysics", "PolicyWritesEnvEntries", "chunk_inputs", "chunk_steps", "compile_physics", "compile_report", "compiled_physics",
           "eager_physics"]


def chunk_steps(env: EnvBase, policy, chunk: int, root: dict, extras: dict, actions: list | None,
                fresh: dict | None) -> tuple[list[tuple], torch.Tensor | None]:
    """``K`` steps of the lean loop on plain tensors: what ``torch.compile`` traces.

    Each step: the action (from ``policy``, a TensorDict module called on the step's entries, or
    the given ``actions[j]``), `physics_step`, and, when ``fresh`` start states are
    given, `merge_reset` of the envs that are done before the chunk's last step
    (the merge at the last step is the caller's). ``fresh`` holds ``K - 1`` start states per env
    (``[K - 1, N, ...]``, those of its next ``K - 1`` episodes) and env ``i``'s ``r``-th reset in
    the chunk takes the ``r``-th: the start states of the eager loop.

    Returns ``[(policy outputs, "next" entries, (merged root, extras) or None), ...]`` and the number of
    resets of each env inside the chunk (``None`` without ``fresh``).
    """
    steps = []
    episode_step = root["episode_step"]
    false = torch.zeros(episode_step.shape, dtype=torch.bool, device=episode_step.device)
    flags = {key: false.unsqueeze(-1) for key in FLAG_KEYS}  # the TorchRL layout: [N, 1]
    resets = envs = None
    if fresh is not None:
        resets = torch.zeros_like(episode_step)
        envs = torch.arange(episode_step.shape[0], device=episode_step.device)
    for j in range(chunk):
        if policy is None:
            out = {"action": actions[j]}
        else:
            entries = {key: value for key, value in root.items() if key not in FLAG_KEYS}
            td = policy(TensorDict({**entries, **flags, **extras}, batch_size=false.shape, device=false.device))
            if not isinstance(policy, TensorDictModuleBase) and not _env_entries_kept(td, entries):
                # (a TensorDict module's out_keys were checked before the chunk)
                raise PolicyWritesEnvEntries("the policy (a plain callable) changed the env's own entries "
                                             "(observation, state, params): its steps run eagerly")
            out = {key: td.get(key) for key in td.keys() if key not in ENV_KEYS}
        nxt = physics_step(env, root["state"], root["params"], root["episode_step"], out["action"])
        merged = None
        if fresh is not None and j < chunk - 1:
            start = {"observation": fresh["observation"][resets, envs],
                     "state": {key: value[resets, envs] for key, value in fresh["state"].items()}}
            merged, extras = merge_reset(nxt["done"], nxt, start, out, root["params"], fresh.get("params"))
            resets = resets + nxt["done"].to(resets.dtype)
            root = merged
        else:
            root = {"observation": nxt["observation"], "state": nxt["state"], "params": root["params"],
                    "episode_step": nxt["episode_step"]}
            extras = out
        steps.append((out, nxt, None if merged is None else (merged, extras)))
    return steps, resets


class PolicyWritesEnvEntries(RuntimeError):
    """A plain callable policy changed the env's own entries inside a compiled chunk, which keeps
    only the policy's other outputs: the rollout goes on eagerly, as `EnvBase.rollout` would run it."""


def _env_entries_kept(td: TensorDictBase, entries: dict) -> bool:
    """Whether ``td`` still holds the very tensors of ``entries`` (nested one level, as the state)."""
    for key, value in entries.items():
        if isinstance(value, dict):
            if any(td.get((key, name), None) is not tensor for name, tensor in value.items()):
                return False
        elif td.get(key, None) is not value:
            return False
    return True


def chunk_inputs(root: dict) -> dict:
    """The root entries a compiled chunk takes: no done flags (all ``False`` at a chunk's start),
    every tensor contiguous, and with grad on, the floating-point state and observation as
    tensors that require grad.

    Compiled code is specialised on strides and ``requires_grad``: a window continues from
    slices of the previous window's output (strided) and from detached tensors, while its later
    chunks get contiguous, differentiable ones; without this every window would alternate
    between two compiled functions. A detached input becomes a fresh leaf with the same values
    (its gradient is computed and dropped: an ``[N, d]`` tensor per chunk).
    """
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


def physics_step_tree(env: EnvBase) -> RigidBodyTree | None:
    """The articulated model of an env whose physics runs through
    [`step`][torchrl_diffenvs.articulated.step] (the MuJoCo tasks), else ``None``."""
    tree = getattr(env, "tree", None)
    return tree if isinstance(tree, RigidBodyTree) else None


class CompiledPhysics:
    """The ``torch.compile``'d chunk functions of one env and what its rollouts learned.

    Two granularities: ``"chunk"`` compiles the whole ``K``-step chunk (policy, physics, reward,
    resets) as one function; ``"physics step"`` (the articulated tasks) runs the chunk's Python
    eagerly and compiles one physics step of [`step`][torchrl_diffenvs.articulated.step],
    reused for every one of the chunk's ``K x frame_skip`` physics steps.
    """

    def __init__(self, env: EnvBase, steps_per_chunk: int, compile_kwargs: dict):
        self.steps_per_chunk = steps_per_chunk
        self.compile_kwargs = {"dynamic": False, **compile_kwargs}
        self.cudagraphs = uses_cudagraphs(self.compile_kwargs)
        self.env_ref = weakref.ref(env)  # the env holds this object: no reference cycle
        self.tree = physics_step_tree(env)
        self.granularity = "chunk" if self.tree is None else "physics step"
        self.step_functions: dict = {}  # (dt, integrator) -> the compiled physics step
        # policy -> {with_resets: compiled chunk}; without a policy: self.functions
        self.policy_functions: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.functions: dict = {}
        self.fallback_reason: str | None = None  # why compiled chunks were given up (then eager)
        self.eager_reason: str | None = None  # why the last rollout's steps ran eagerly (None: compiled)
        self.first_call_seconds: dict[str, float] = {}  # first call (tracing + compiling + running)
        self.expect_resets = True  # the last chunk saw an env done before its last step

    def note_first_call(self, what: str, seconds: float) -> None:
        """Records the duration of the first call of each compiled function (mostly compiling)."""
        what = f"{what}, {'with' if torch.is_grad_enabled() else 'without'} grad"
        self.first_call_seconds.setdefault(what, seconds)

    def chunk_function(self, policy, with_resets: bool) -> Callable:
        """The compiled `chunk_steps` for ``policy`` (one per policy object, or ``None``)."""
        try:
            functions = self.functions if policy is None else self.policy_functions.setdefault(policy, {})
            policy_ref = (lambda: None) if policy is None else weakref.ref(policy)
        except TypeError:  # a callable that cannot be weakly referenced
            if self.granularity != "physics step":
                raise
            functions, policy_ref = {}, (lambda: policy)  # nothing of the policy is compiled: no cache needed
        fn = functions.get(with_resets)
        if fn is None:
            env_ref, steps = self.env_ref, self.steps_per_chunk

            def chunk(root, extras, actions, fresh):
                return chunk_steps(env_ref(), policy_ref(), steps, root, extras, actions, fresh)

            if self.granularity == "physics step":
                tree, stepper = self.tree, self.physics_step

                def fn(root, extras, actions, fresh):
                    with stepping_with(tree, stepper):
                        return chunk(root, extras, actions, fresh)

                functions[with_resets] = fn
            else:
                fn = functions[with_resets] = self.compiled(chunk)
        return fn

    def compiled(self, function: Callable) -> Callable:
        """``torch.compile(function)``. With CUDA graphs, calls without gradient each start a new
        graph step and return copies of the outputs (the graph's own output buffers are overwritten
        by its next replay, while a rollout keeps every step's outputs and the next physics step
        reads them); calls with gradient go to a second ``torch.compile`` of ``function`` without
        CUDA graphs (compiled at its own first call): a window's tensors saved for its backward
        must outlive many replays."""
        fn = torch.compile(_own_code(function), **self.compile_kwargs)
        if not self.cudagraphs:
            return fn
        with_grad = torch.compile(_own_code(function), **without_cudagraphs(self.compile_kwargs))

        def run(*args):
            if torch.is_grad_enabled():
                return with_grad(*args)
            torch.compiler.cudagraph_mark_step_begin()
            return _copied(fn(*args))
        return run

    def physics_step(self, tree, qpos, qvel, ctrl, params, dt, integrator, invweight0):
        """[`step`][torchrl_diffenvs.articulated.step] through ``torch.compile``: one
        compiled function per step size and integrator (the tree and both are constants of its
        graph), reused at every physics step; its first call per grad mode is timed."""
        fn = self.step_functions.get((dt, integrator))
        if fn is None:
            def one_step(qpos, qvel, ctrl, params, invweight0):
                # a graph returns tensors: the solved contact problem (Python objects) stays behind
                return eager_step(tree, qpos, qvel, ctrl, params, dt, integrator, invweight0)._replace(
                    solved_contacts=None)

            fn = self.step_functions[(dt, integrator)] = self.compiled(one_step)
        what = f"physics step ({integrator}), {'with' if torch.is_grad_enabled() else 'without'} grad"
        if what in self.first_call_seconds:
            return fn(qpos, qvel, ctrl, params, invweight0)
        started = time.perf_counter()
        result = fn(qpos, qvel, ctrl, params, invweight0)
        self.first_call_seconds[what] = time.perf_counter() - started
        return result


_CHUNK_FUNCTIONS = itertools.count()


def uses_cudagraphs(compile_kwargs: dict) -> bool:
    """Whether ``torch.compile(**compile_kwargs)`` runs its graphs as CUDA graphs (inductor's
    ``mode="reduce-overhead"`` and ``"max-autotune"``, or the ``triton.cudagraphs`` option)."""
    options = compile_kwargs.get("options") or {}
    return compile_kwargs.get("mode") in ("reduce-overhead", "max-autotune") or bool(options.get("triton.cudagraphs"))


def without_cudagraphs(compile_kwargs: dict) -> dict:
    """``compile_kwargs`` with inductor's CUDA graphs turned off (the rest of the mode kept)."""
    kwargs = dict(compile_kwargs)
    mode = kwargs.pop("mode", None)
    if mode == "max-autotune":
        kwargs["mode"] = "max-autotune-no-cudagraphs"
    elif mode not in (None, "reduce-overhead"):
        kwargs["mode"] = mode
    if kwargs.get("options"):
        kwargs["options"] = {**kwargs["options"], "triton.cudagraphs": False}
    return kwargs


def _copied(value):
    """``value`` (tensors in tuples, lists, dicts and named tuples) with every tensor cloned."""
    if isinstance(value, (torch.Tensor, TensorDictBase)):
        return value.clone()
    if isinstance(value, dict):
        return {key: _copied(item) for key, item in value.items()}
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(_copied(item) for item in value))
    if isinstance(value, (list, tuple)):
        return type(value)(_copied(item) for item in value)
    return value


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

    * With a policy (a TensorDict module such as [`make_actor`][torchrl_diffenvs.modules.make_actor]'s,
      as BPTT, SHAC and evaluation call it; on the articulated tasks any callable that takes and
      returns a TensorDict, see below): one compiled function per ``K``-step chunk covers
      the policy forward, the physics, the reward, the done flags and the auto-resets of envs
      whose episode ends inside the chunk; its backward is compiled too (AOTAutograd), so
      ``DiffWindowCollector`` windows and their gradients run compiled.
    * Without a policy (random actions, or ``actions=``): the same chunk function steps the
      given actions (drawn eagerly, as the eager path draws them), resets included.
    * Resets inside a chunk use start states drawn ahead (each env's next ``K - 1`` episodes of
      its own stream, so they are the eager path's). Drawing them costs about a physics step per
      step, so they are drawn only when an env may reach its time limit inside the chunk or the
      previous chunk had a reset; a chunk in which an env is done unexpectedly is cut after that
      step (the eager loop resets the env and goes on).
    * Steps beyond whole chunks (``max_steps`` not a multiple of ``K``) run eagerly: choose
      ``K`` dividing the window length.
    * The articulated tasks (the MuJoCo models: an env step is ``frame_skip`` physics steps of
      a few forward-dynamics passes each) compile one physics step instead
      ([`step`][torchrl_diffenvs.articulated.step], ``dynamic=False``): the chunk's
      policy, reward and resets run eagerly and call the same compiled step ``K x frame_skip``
      times. A whole chunk of HalfCheetah-v5 was a graph of 40 physics steps that did not finish
      compiling in 15 minutes on one CPU thread; one step compiles in about a minute, its
      backward too (benchmarks/compile_physics.py). With MuJoCo's contact model the step is one
      graph (the constraint solve is a ``torch.while_loop``; on CUDA the solve runs eagerly
      between two graphs, stopping without a synchronisation); the smooth model's joint-limit
      solve runs eagerly inside it (a graph break, see `limit_force`). Since the chunk's Python
      is eager here, the policy may be any callable.

    The result is that of the eager path up to floating-point rounding (fused kernels may round
    differently), gradients included, with one exception: random numbers drawn inside compiled
    code (a stochastic policy's noise) come from inductor's own generator, seeded from torch's
    global one, so sampled actions differ from the eager path's draws (same distribution), and
    a cut chunk has drawn noise for steps it did not keep. Compare the two paths with given
    actions or a deterministic policy.

    Compiling happens at first use and takes seconds to a minute per function on a CPU (one per
    policy object, grad mode and exploration mode, and again for the backward pass); it pays off
    for repeated rollouts, mostly at small and medium batch sizes. `compile_report` says
    how long the first calls took. If ``torch.compile`` fails (no C++ compiler for inductor, an
    operation it cannot trace), the rollout logs the reason and runs eagerly from there on.
    Undo with [`eager_physics`][torchrl_diffenvs.eager_physics]. ``EnvBase.rollout`` and ``env.step``
    are not affected.

    Args:
        env: the env whose ``env.rollout`` to compile; its rollouts must be able to take the lean
            rollout loop that the compiled chunks replace.
        steps_per_chunk: ``K``, the number of env steps each compiled chunk covers (a positive integer).
        **compile_kwargs: go to ``torch.compile`` (default ``dynamic=False``). On CUDA,
            ``mode="reduce-overhead"`` replays each compiled graph as a CUDA graph (inductor's CUDA graph
            trees), to save the kernel-launch overhead of an eager GPU step: rollouts without gradient
            use them (each call's outputs are copied out of the graph's buffers); windows with gradient
            use a second compilation without CUDA graphs (its own compile time at its first call).

    Returns:
        ``env``, its rollouts now compiled.
    """
    if isinstance(steps_per_chunk, bool) or not isinstance(steps_per_chunk, int) or steps_per_chunk < 1:
        raise ValueError(f"compile_physics: steps_per_chunk must be a positive integer, got {steps_per_chunk!r}")
    why_not = fast_rollout_unsupported(env, None, {})
    if why_not is not None:  # the compiled chunks replace the lean loop: without it nothing would compile
        raise ValueError(f"compile_physics: {type(env).__name__}'s rollouts cannot take the lean path that the "
                         f"compiled chunks replace ({why_not}); multi-agent envs roll out through EnvBase.rollout")
    env._compiled_physics = CompiledPhysics(env, steps_per_chunk, compile_kwargs)
    return env


def compiled_physics(env: EnvBase) -> CompiledPhysics | None:
    """The `CompiledPhysics` that [`compile_physics`][torchrl_diffenvs.compile_physics] gave ``env`` (its ``_compiled_physics``
    attribute), or ``None``: its rollouts run eagerly. A wrapper that forwards attributes to the
    env it wraps (``TransformedEnv``) has none of its own."""
    compiled = getattr(env, "_compiled_physics", None)
    return compiled if compiled is not None and compiled.env_ref() is env else None


def compile_report(env: EnvBase) -> dict | None:
    """What [`compile_physics`][torchrl_diffenvs.compile_physics] did on ``env`` so far; ``None`` if it is not compiled.

    ``{"steps_per_chunk": K, "granularity": "chunk" or "physics step", "first_call_seconds":
    {function: seconds}, "fallback_reason": str or None, "eager_reason": str or None}``: the first call of each compiled
    function (tracing and compiling included: for the articulated tasks the compiled physics
    step's own entry, ``"physics step (<integrator>), with/without grad"``, and the first chunk
    that called it; the backward's compilation happens in the first ``backward()`` instead),
    why compiled chunks were given up, if they were, and ``"eager_reason"``: why the last
    rollout through the lean loop could not take compiled chunks (e.g. a plain callable policy on
    a task compiled by the chunk, whose compiled chunk needs a TensorDict module, or one that
    changes the env's own entries; ``None``: it could, for its whole chunks).
    """
    compiled = compiled_physics(env)
    if compiled is None:
        return None
    return {"steps_per_chunk": compiled.steps_per_chunk, "granularity": compiled.granularity,
            "first_call_seconds": dict(compiled.first_call_seconds),
            "fallback_reason": compiled.fallback_reason, "eager_reason": compiled.eager_reason}


def eager_physics(env: EnvBase) -> EnvBase:
    """Undoes [`compile_physics`][torchrl_diffenvs.compile_physics]; returns ``env``.

    Args:
        env: the env whose compiled rollouts to drop (nothing happens if it has none).

    Returns:
        ``env``, its rollouts eager again.
    """
    if compiled_physics(env) is not None:
        del env._compiled_physics
    return env
