"""Step entries <-> TensorDicts, and the rollout output: every entry stacked once along time.

A step is a dict of entries (see `step`); the done flags
and the reward are kept ``[N]`` and get their trailing ``1`` only in TensorDicts (fewer ops per
step, and the same tensor object can be recognised from step to step, see `stack_time`).
"""
from __future__ import annotations

import torch
from tensordict import LazyStackedTensorDict, TensorDict, TensorDictBase

from ..._compat import unchecked_tensordict
from .step import FLAG_KEYS, NESTED_ENV_KEYS

__all__ = ["as_tensordict", "build_output", "entries_of", "set_truncated_last_step", "stack_time"]

_TRAILING_ONE = (*FLAG_KEYS, "reward")  # [N] here, [N, 1] in TensorDicts


def entries_of(td: TensorDictBase, n: int, views: dict | None = None) -> dict:
    """A step TensorDict's root entries in the internal layout.

    ``views``: the ``{key: ([N, 1] view, [N] flag)}`` that `as_tensordict` made for ``td``;
    a flag the policy left untouched maps back to the loop's own tensor.
    """
    entries = dict(td.items())
    for key in NESTED_ENV_KEYS:
        entries[key] = dict(entries[key].items())
    for key in FLAG_KEYS:
        flag = entries[key]
        made = views.get(key) if views else None
        entries[key] = made[1] if made is not None and made[0] is flag else flag.reshape(n)
    return entries


def as_tensordict(entries: dict, batch_size: torch.Size, device, views: dict | None = None) -> TensorDict:
    """A ``[N]`` TensorDict of one step's entries (the TorchRL layout); see `entries_of`."""
    source = {}
    for key, value in entries.items():
        if key in _TRAILING_ONE:
            view = value.unsqueeze(-1)
            if views is not None:
                views[key] = (view, value)
            value = view
        source[key] = value  # "state" / "params" dicts become nested TensorDicts
    # every entry already has the right batch size and device: skip TensorDict's checks
    # (about 15 us per TensorDict; the public constructor validates the final output)
    return unchecked_tensordict(source, batch_size, device)


def build_output(roots: list[dict], nexts: list[dict], return_contiguous: bool, batch_size: torch.Size,
                 device) -> TensorDictBase:
    """Stacks every entry along a new time dim 1: ``[N, T, ...]``, as EnvBase.rollout does."""
    if any(r.keys() != roots[0].keys() for r in roots):
        # a policy that writes different keys at different steps: let TensorDict decide, as EnvBase does
        steps = [as_tensordict({**r, "next": as_tensordict(x, batch_size, device)}, batch_size, device)
                 for r, x in zip(roots, nexts)]
        if return_contiguous:
            return torch.stack(steps, len(batch_size))
        return LazyStackedTensorDict.maybe_dense_stack(steps, len(batch_size))
    out_size = torch.Size([batch_size[0], len(roots)])
    memo: dict = {}  # entries made of the very same tensors (e.g. "truncated" and "done") stack once

    def stack_once(values):
        ids = tuple(map(id, values))
        if ids in memo:
            return memo[ids].clone()
        memo[ids] = result = stack_time(values)
        return result

    def stacked(key, sub=None):
        pick = (lambda d: d[key]) if sub is None else (lambda d: d[key][sub])
        next_values = [pick(x) for x in nexts] if key in nexts[0] else None
        next_stack = None if next_values is None else stack_once(next_values)
        return _stack_root([pick(r) for r in roots], next_values, next_stack), next_stack

    out, out_next = {}, {}
    for key in roots[0]:
        if key in NESTED_ENV_KEYS:
            leaves = {sub: stacked(key, sub) for sub in roots[0][key]}
            out[key] = TensorDict({k: v[0] for k, v in leaves.items()}, batch_size=out_size, device=device)
            out_next[key] = TensorDict({k: v[1] for k, v in leaves.items()}, batch_size=out_size, device=device)
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
        for key in _TRAILING_ONE:
            if key in entries:
                entries[key] = entries[key].unsqueeze(-1)
    out["next"] = TensorDict(out_next, batch_size=out_size, device=device)
    return TensorDict(out, batch_size=out_size, device=device)


def stack_time(values: list[torch.Tensor]) -> torch.Tensor:
    """``torch.stack(values, dim=1)``, with runs of one repeated tensor copied in one go.

    Entries that do not change between resets (the physical parameters, a goal position) appear
    as the same tensor object at many steps; expanding it is the same data and the same
    gradient as stacking it.
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


def _stack_root(root_values: list[torch.Tensor], next_values: list[torch.Tensor] | None,
                next_stack: torch.Tensor | None) -> torch.Tensor:
    """Stacks a root entry; where it is the previous step's ``"next"`` entry, copies that slice.

    Between resets the root entry of step ``t + 1`` *is* the ``"next"`` entry of step ``t`` (the
    same tensor, as ``step_mdp`` makes it): one contiguous copy of the stacked ``"next"`` entry
    replaces a second strided stack. Reset steps contribute their own (merged) tensor.
    """
    if next_values is None or 4 * len(_runs(root_values)) <= len(root_values):
        return stack_time(root_values)  # e.g. unchanged physical parameters: expand, no read-back
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


def set_truncated_last_step(out_td: TensorDictBase) -> None:
    """EnvBase.rollout(set_truncated=True): the last step is marked truncated (and done)."""
    val = out_td.get(("next", "truncated"))
    done = out_td.get(("next", "done"))
    val[(slice(None),) * (out_td.ndim - 1) + (-1,)] = True
    out_td.set(("next", "truncated"), val)
    out_td.set(("next", "done"), val | done)
