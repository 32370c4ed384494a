"""The lean rollout loop: ``EnvBase.rollout`` on plain tensors, eager or in compiled chunks.

Each step is the policy (or a random or given action), `physics_step` and, where
an env is done, `merge_reset` with fresh start states; a compiled chunk
(`compiled`) runs the same functions for ``K`` steps. The per-step entries are kept in
lists and stacked once at the end (`output`).
"""
from __future__ import annotations

import logging
import math
import operator
import time
from collections.abc import Callable, Iterable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from ..._compat import (
    COMPILE_ERRORS,
    has_dynamic_specs,
    make_compatible_policy,
)
from .actions import RandomActions
from .compiled import PolicyWritesEnvEntries, chunk_inputs, compiled_physics
from .output import as_tensordict, build_output, entries_of, set_truncated_last_step
from .step import ENV_KEYS, merge_reset, physics_step
from .support import FAST_ROLLOUT_KWARGS, fast_rollout_unsupported  # noqa: F401  (re-exported)

__all__ = ["fast_rollout"]

_logger = logging.getLogger(__name__)

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
    """``EnvBase.rollout(env, ...)`` through the lean loop (same arguments, same result).

    Same keys, shapes, dtypes, values and gradients as ``EnvBase.rollout`` for the same env seed
    and the same actions; random actions (no policy) are drawn from torch's global generator as
    TorchRL draws them. Call it through ``env.rollout``, which checks
    `fast_rollout_unsupported` first; calling it directly with an unsupported argument
    raises ``ValueError``.
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


class _Loop:
    """One rollout: per-step entries in lists, stacked along the time dim at the end."""

    def __init__(self, env: EnvBase, policy, action_source, max_steps: int):
        self.env = env
        self.policy = policy
        if action_source is None and policy is None:
            action_source = RandomActions(env, max_steps)
        self.action_source = action_source
        self.pending: list[torch.Tensor] = []  # actions drawn for a chunk but not stepped yet
        self.n = env.num_envs
        self.bs = env.batch_size
        self.device = env.device
        self.all_false = torch.zeros(self.n, dtype=torch.bool, device=self.device)
        self.compiled = compiled_physics(env)
        self.chunk = 1 if self.compiled is None else self.compiled.steps_per_chunk
        self.check_actions = not isinstance(action_source, RandomActions) or policy is not None  # (ours are valid)
        self.start_table = _StartTable(self)
        self.replay = None  # the actions of a rollout stepped again with finiteness checks

    # ------------------------------------------------------------------ main loop
    def run(self, td0: TensorDictBase, max_steps: int, break_when_any_done: bool, return_contiguous: bool,
            set_truncated: bool) -> TensorDictBase:
        root = entries_of(td0, self.n)
        # root entries that are not the env's (a user's extra entries) travel along, as step_mdp does
        extras = {key: value for key, value in root.items() if key not in ENV_KEYS}
        root = {key: root[key] for key in ENV_KEYS}
        # Physical parameters equal to env.params, without gradient: a reset merges them with
        # env.params, which leaves them as they are (and the same tensors from step to step).
        env_params = self.env.params
        self.params_are_env_params = root["params"].keys() == set(env_params.keys()) and all(
            not value.requires_grad and not env_params[key].requires_grad and torch.equal(value, env_params[key])
            for key, value in root["params"].items()
        )
        # Without a policy and without breaking, the eager steps may skip the per-step finiteness
        # check: the output is checked at the end (one sum per stacked entry), and only if some
        # value is not finite are the same actions stepped again from the start, with checks (an
        # env that did that once checks every step from then on).
        deferred = (self.policy is None and not break_when_any_done and self.compiled is None
                    and not self.env._nonfinite_seen)
        episodes = self.env.episodes
        roots, nexts = self.steps(td0, root, extras, max_steps, break_when_any_done, check=not deferred)
        out_td = build_output(roots, nexts, return_contiguous, self.bs, self.device)
        if deferred and not _output_finite(out_td):
            self.env._nonfinite_seen = True  # the env's own flag: it checks every step from now on
            self.env.rng.episodes = episodes
            self.start_table = _StartTable(self)
            self.replay = iter([r["action"] for r in roots])
            roots, nexts = self.steps(td0, root, extras, max_steps, break_when_any_done, check=True)
            out_td = build_output(roots, nexts, return_contiguous, self.bs, self.device)

        if isinstance(self.action_source, RandomActions):
            self.action_source.close(unused=len(self.pending))
        # EnvBase leaves step 0's "next" in the input tensordict; rendering wants the last output
        td0.set("next", as_tensordict(nexts[0], self.bs, self.device))
        remember = getattr(self.env, "_remember_for_render", None)
        if remember is not None:
            remember(as_tensordict(nexts[-1], self.bs, self.device))
        if set_truncated:
            set_truncated_last_step(out_td)
        out_td.refine_names(..., "time")
        return out_td

    def steps(self, td0: TensorDictBase, root: dict, extras: dict, max_steps: int, break_when_any_done: bool,
              check: bool) -> tuple[list[dict], list[dict]]:
        """The rollout's steps: the root entries and the ``"next"`` entries of each."""
        roots: list[dict] = []
        nexts: list[dict] = []
        t, finished = 0, False
        eager_reason = self.chunks_unsupported(extras)
        if self.compiled is not None:
            self.compiled.eager_reason = eager_reason
        chunked = eager_reason is None
        while not finished:
            if chunked and max_steps - t >= self.chunk:
                actions = None if self.policy is not None else [self.next_action() for _ in range(self.chunk)]
                result = self.run_chunk(td0, root, extras, actions, t, max_steps, break_when_any_done, roots, nexts)
                if result is not None:
                    t, finished, root, extras = result
                    continue
                chunked = False  # compiling failed (logged): eager from here on
                self.pending = actions or []
            if self.policy is not None:
                # step 0 runs on the input TensorDict itself, as in EnvBase
                views: dict = {}
                td = td0 if t == 0 else as_tensordict({**root, **extras}, self.bs, self.device, views)
                root_t = self.call_policy(td, views)  # what the policy leaves at the root is what TorchRL stores
                action = root_t["action"]
            else:
                action = self.next_action()
                if t == 0 and self.replay is None:  # EnvBase writes step 0's action into the input tensordict
                    td0.set("action", self.first_action(action))
                root_t = {**root, **extras, "action": action}
            if self.check_actions:
                self.env._check_action(action)
            nxt = physics_step(self.env, root_t["state"], root_t["params"], root_t["episode_step"], action,
                               self.all_false, check)
            nxt["params"] = root_t["params"]
            roots.append(root_t)
            nexts.append(nxt)
            t += 1
            any_done = bool(nxt["done"].any())
            if t == max_steps or (break_when_any_done and any_done):
                break
            # step_mdp: the next root is the "next" entries plus whatever else was at the root
            root = {key: nxt[key] for key in ENV_KEYS}
            extras = {key: value for key, value in root_t.items() if key not in ENV_KEYS}
            if any_done:  # only without break_when_any_done
                root, extras = self.reset_done(nxt, extras)
        return roots, nexts

    def call_policy(self, td: TensorDictBase, views: dict) -> dict:
        """Runs the policy on a step TensorDict; returns the root entries it leaves."""
        td.update(self.policy(td))
        entries = entries_of(td, self.n, views)
        if "action" not in entries:
            raise KeyError(f"{self.env.name}: the policy wrote no 'action' entry (keys: {sorted(entries)})")
        return entries

    def next_action(self) -> torch.Tensor:
        """The next random or given action (without a policy)."""
        if self.replay is not None:
            return next(self.replay)
        return self.pending.pop(0) if self.pending else next(self.action_source)

    def first_action(self, action: torch.Tensor) -> torch.Tensor:
        """What EnvBase leaves as the input tensordict's ``"action"`` without a policy."""
        return action.clone() if isinstance(self.action_source, RandomActions) else action

    # ------------------------------------------------------------------ resets
    def starts(self, episodes: torch.Tensor | None = None) -> dict:
        """Start states of every env (env ``i`` at ``episodes[i]``, default its next episode)."""
        env = self.env
        # DiffEnv._reset passes a clone of env.params; initial_state is pure, so env.params will do
        state = env.start_states(env.params, episodes)
        return {"observation": env.observation(state, env.params), "state": state}

    def reset_params(self) -> dict | None:
        """The parameters a reset env takes: ``None`` when they are the ones it has (env.params)."""
        return None if self.params_are_env_params else dict(self.env.params.items())

    def reset_done(self, nxt: dict, extras: dict) -> tuple[dict, dict]:
        """``maybe_reset``: the done envs restart from their next start states (`merge_reset`)."""
        done = nxt["done"]
        # without a policy the action is replaced before anyone sees it: no need to zero it
        keep = {"action": extras["action"]} if self.policy is None and "action" in extras else {}
        zeroable = {key: value for key, value in extras.items() if key not in keep}
        root, extras = merge_reset(done, nxt, self.start_table.starts(done), zeroable, nxt["params"],
                                   self.reset_params())
        self.env.rng.episodes = self.env.episodes + done.to(torch.int64)
        return root, {**extras, **keep}

    # ------------------------------------------------------------------ compiled chunks
    def chunks_unsupported(self, extras: dict) -> str | None:
        """Why the steps cannot run in compiled chunks (``compile_physics``), or ``None``."""
        compiled = self.compiled
        if compiled is None:
            return "no compile_physics"
        if compiled.fallback_reason is not None:
            return compiled.fallback_reason
        if self.policy is None:
            # the eager loop carries other root entries along (zeroed at resets): not in chunks
            return None if set(extras) <= {"action"} else "the input tensordict has entries besides the env's"
        out_keys = getattr(self.policy, "out_keys", None)
        if not isinstance(self.policy, TensorDictModuleBase) or out_keys is None:
            # compiled physics steps leave the chunk's Python, the policy's call included, eager
            return None if compiled.granularity == "physics step" else (
                "the policy is not a TensorDict module (a compiled chunk traces the policy with its out_keys)")
        if any(not isinstance(key, str) or key in ENV_KEYS for key in out_keys):
            return f"the policy writes nested keys or the env's own entries ({out_keys})"
        if any(not isinstance(value, torch.Tensor) for value in extras.values()):
            return "the input tensordict holds nested entries besides the env's"
        return None

    def fresh_starts(self) -> dict:
        """The start states of each env's next ``K - 1`` episodes, ``[K - 1, N, ...]``."""
        starts = [self.starts(self.env.episodes + r) for r in range(self.chunk - 1)]
        fresh = {"observation": torch.stack([s["observation"] for s in starts]),
                 "state": {key: torch.stack([s["state"][key] for s in starts]) for key in starts[0]["state"]}}
        params = self.reset_params()
        if params is not None:
            fresh["params"] = params
        return fresh

    def limit_within_chunk(self, root: dict) -> bool:
        """Whether an env may reach its time limit before the chunk's last step."""
        limit = self.env.max_episode_steps
        return limit is not None and int(root["episode_step"].max()) + self.chunk - 1 >= limit

    def run_chunk(self, td0: TensorDictBase, root: dict, extras: dict, actions: list | None, t: int, max_steps: int,
                  break_when_any_done: bool, roots: list, nexts: list) -> tuple | None:
        """Runs ``K`` steps in one compiled call and books them as the eager loop would.

        Returns ``(t, finished, root, extras)`` after the chunk, or ``None`` when compiling
        failed: the reason is logged and kept (``compile_report(env)``), nothing was consumed and
        the rollout goes on eagerly.
        """
        env, compiled = self.env, self.compiled
        # The previous step's outputs (the only extras, usually) are overwritten by the policy and
        # not read by it: leave them out, so that every chunk has the first chunk's inputs (one compile).
        policy_keys = (set(self.policy.out_keys) - set(self.policy.in_keys)
                       if isinstance(self.policy, TensorDictModuleBase) else set())
        extras_in = {} if set(extras) <= policy_keys or self.policy is None else {
            key: value.contiguous() for key, value in extras.items()}
        if actions is not None:
            for action in actions:
                env._check_action(action)
        actions_in = None if actions is None else [action.contiguous() for action in actions]
        with_resets = self.chunk > 1 and not break_when_any_done and (
            compiled.expect_resets or self.limit_within_chunk(root))
        fresh = self.fresh_starts() if with_resets else None
        function = compiled.chunk_function(self.policy, with_resets)
        started = time.perf_counter()
        try:
            steps, resets = function(chunk_inputs(root), extras_in, actions_in, fresh)
        except PolicyWritesEnvEntries as err:  # this rollout's policy only: later rollouts may compile
            compiled.eager_reason = str(err)
            return None
        except COMPILE_ERRORS as err:
            message = " ".join(line.strip() for line in str(err).splitlines()[:3] if line.strip())
            compiled.fallback_reason = f"torch.compile failed ({type(err).__name__}: {message})"
            _logger.warning("%s: compiled rollout chunks disabled, running eagerly: %s", env.name,
                            compiled.fallback_reason)
            return None
        what = "physics" if self.policy is None else "policy + physics"
        compiled.note_first_call(f"{what}, {len(steps)} steps", time.perf_counter() - started)
        if resets is not None:
            env.rng.episodes = env.episodes + resets
        if actions is not None:  # the actions as given (the same tensors as the eager loop stores)
            steps = [({"action": action}, nxt, merged) for action, (_, nxt, merged) in zip(actions, steps)]
        env._check_action(steps[0][0]["action"])
        if t == 0 and actions is not None:  # EnvBase writes step 0's action into the input tensordict
            td0.set("action", self.first_action(actions[0]))
        elif t == 0:  # EnvBase runs step 0's policy on the input tensordict itself
            for key, value in steps[0][0].items():
                td0.set(key, value)
        finished, reset_inside = False, False
        for j, (out, nxt, merged) in enumerate(steps):
            nxt["params"] = root["params"]
            roots.append({**root, **extras, **out})
            nexts.append(nxt)
            t += 1
            any_done = bool(nxt["done"].any())
            if t == max_steps or (break_when_any_done and any_done):
                finished = True
                if actions is not None:
                    self.pending = actions[j + 1:]  # drawn, not stepped
                break
            if any_done and merged is not None:  # reset inside the chunk
                root, extras = merged
                reset_inside = True
                continue
            root = {key: nxt[key] for key in ENV_KEYS}
            extras = {**extras, **out}
            if any_done:  # at the chunk's last step, or not expected: the chunk ends here
                root, extras = self.reset_done(nxt, extras)
                if j < len(steps) - 1:
                    reset_inside = True
                    if actions is not None:
                        self.pending = actions[j + 1:]
                    break
        compiled.expect_resets = reset_inside
        return t, finished, root, extras


def _output_finite(out_td: TensorDictBase) -> bool:
    """Whether every ``"next"`` state and reward of a rollout output is finite (one sum of each)."""
    nxt = out_td.get("next")
    with torch.no_grad():
        sums = [value.sum() for value in (*nxt.get("state").values(True, True), nxt.get("reward"))]
        return math.isfinite(torch.stack(sums).sum().item())


class _StartTable:
    """The start states a reset merges, served from a table of each env's next episodes.

    Env ``i``'s start state at episode ``e`` depends on ``(seed, i, e)`` only (per-env streams),
    and a reset takes it for the done envs only; the other envs' rows of a full-batch draw are
    thrown away, and drawn again, identical, at the next reset. The table holds the start states
    of episodes ``base_i ... base_i + depth - 1`` of every env (``depth`` full-batch draws); a
    reset picks row ``episodes_i - base_i`` of each done env (one ``index_select`` per entry)
    and draws a new table only when a done env has used up its rows. ``depth`` starts at 1
    (a draw per reset, as before, when all envs reset together) and doubles while a table serves
    more reset steps than it has rows (envs that reset at different steps). Same values and
    gradients as drawing at each reset: the rows of the envs not done are not merged.
    """

    MAX_DEPTH = 16
    MAX_ELEMENTS = 1 << 22  # of a table, all entries together

    def __init__(self, loop: _Loop):
        self.loop = loop
        self.n = loop.n
        self.depth = 1
        self.table: dict | None = None  # {"observation": [depth * N, ...], "state": {key: [depth * N, ...]}}
        self.base: torch.Tensor | None = None  # env.episodes at the draw
        self.served = 0  # reset steps served by the current table
        self.rows: torch.Tensor | None = None  # arange(N)
        self.rng = self.key = None  # the env's generator and seed key at the draw

    def starts(self, done: torch.Tensor) -> dict:
        """``{"observation", "state"}`` of every env, right (``env.episodes``) for the ``done`` envs."""
        rng = self.loop.env.rng
        episodes = rng.episodes
        pick = None
        if self.table is not None and rng is self.rng and rng.key == self.key:  # (not reseeded meanwhile)
            pick = torch.where(done, episodes - self.base, 0)
            if int(pick.max()) >= self.depth:
                pick = None
        if pick is None:
            self.draw(episodes)
            if self.depth == 1:
                self.served = 1
                return self.table
            pick = torch.zeros_like(episodes)
        self.served += 1
        if self.depth == 1:
            return self.table
        index = pick * self.n + self.rows
        table = self.table
        return {"observation": table["observation"].index_select(0, index),
                "state": {key: value.index_select(0, index) for key, value in table["state"].items()}}

    def draw(self, episodes: torch.Tensor) -> None:
        """A new table from ``episodes`` on, deeper if the last one served more reset steps than it had rows."""
        if self.table is not None and self.served > self.depth:
            per_env = self.table["observation"][0].numel() + sum(v[0].numel() for v in self.table["state"].values())
            self.depth = max(self.depth, min(2 * self.depth, self.MAX_DEPTH,
                                             self.MAX_ELEMENTS // max(1, per_env * self.n)))
        self.base, self.served = episodes, 0
        self.rng, self.key = self.loop.env.rng, self.loop.env.rng.key
        if self.depth == 1:
            self.table = self.loop.starts(episodes)
            return
        if self.rows is None:
            self.rows = torch.arange(self.n, device=episodes.device)
        starts = [self.loop.starts(episodes + r) for r in range(self.depth)]
        self.table = {"observation": torch.cat([s["observation"] for s in starts]),
                      "state": {key: torch.cat([s["state"][key] for s in starts]) for key in starts[0]["state"]}}
