"""Self-play as rl_games does it: the opponent is a frozen snapshot of a past policy, refreshed on
a schedule, drawn from a pool of the latest snapshots.

The training script's ``selfplay`` section drives it on a two-player env
(`TwoPlayerDiffEnv`, e.g. ``swimmer_race``):

```text
python sota_scripts/train.py env=swimmer_race loss=shac selfplay.refresh_interval=20000 selfplay.pool_size=4
```

Every ``refresh_interval`` env steps (from step 0) the current policy is copied into the pool
(the oldest snapshot leaves when it holds ``pool_size``) and the training envs' opponent becomes a
snapshot drawn uniformly from the pool (with ``pool_size=1``: always the latest). Evaluations keep
the task's scripted opponent, a fixed yardstick. The pool, the draw generator and the schedule are
saved in checkpoints, so a resumed run plays the same opponents.
"""
from __future__ import annotations

import copy

import torch

__all__ = ["SelfPlay"]


class SelfPlay:
    """The snapshot pool and its schedule for one training env.

    Args:
        env: the training env (a `TwoPlayerDiffEnv`).
        policy: the learner's policy (``learner.policy``); snapshots are copies of it.
        refresh_interval: env steps between refreshes (all ranks' steps, like every interval).
        pool_size: snapshots kept.
        seed: seed of the generator that draws the opponent from the pool (the same on every rank).
    """

    def __init__(self, env, policy, refresh_interval: int, pool_size: int = 1, seed: int = 0):
        if not hasattr(env, "set_opponent"):
            raise ValueError(f"self-play needs a two-player env (one with set_opponent, e.g. swimmer_race); "
                             f"{type(env).__name__} has no opponent")
        if refresh_interval < 1 or pool_size < 1:
            raise ValueError(f"self-play: refresh_interval and pool_size must be >= 1, got {refresh_interval}, {pool_size}")
        self.env, self.policy = env, policy
        self.refresh_interval, self.pool_size = int(refresh_interval), int(pool_size)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.pool: list[dict] = []  # policy state_dicts, oldest first
        self.current: int | None = None  # index in the pool of the opponent now playing
        self.next_refresh = 0
        self.refreshes = 0
        self._holder = None

    def step(self, env_steps: int) -> bool:
        """Refreshes the opponent if ``env_steps`` reached the schedule; returns whether it did."""
        if env_steps < self.next_refresh:
            return False
        self.pool.append({key: value.detach().clone() for key, value in self.policy.state_dict().items()})
        del self.pool[: len(self.pool) - self.pool_size]
        self.current = int(torch.randint(len(self.pool), (), generator=self.generator))
        self._play(self.pool[self.current])
        while self.next_refresh <= env_steps:
            self.next_refresh += self.refresh_interval
        self.refreshes += 1
        return True

    def _play(self, snapshot: dict) -> None:
        if self._holder is None:  # a policy-shaped module to load snapshots into (made once)
            self._holder = copy.deepcopy(self.policy)
        self._holder.load_state_dict(snapshot)
        self.env.set_opponent(self._holder)  # copies and freezes it

    def metrics(self) -> dict[str, float]:
        """``opponent_age``: refreshes since the playing snapshot was taken (0: the latest)."""
        return {"opponent_age": float(len(self.pool) - 1 - self.current) if self.current is not None else float("nan")}

    def state_dict(self) -> dict:
        return {"pool": self.pool, "current": self.current, "next_refresh": self.next_refresh,
                "refreshes": self.refreshes, "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.pool = [dict(snapshot) for snapshot in state["pool"]]
        self.current, self.next_refresh = state["current"], int(state["next_refresh"])
        self.refreshes = int(state["refreshes"])
        self.generator.set_state(state["generator"].cpu())
        if self.current is not None:
            self._play(self.pool[self.current])
