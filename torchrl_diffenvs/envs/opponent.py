"""Two-player tasks seen from one side: the opponent's policy is part of the env's dynamics.

A [`TwoPlayerDiffEnv`][torchrl_diffenvs.envs.TwoPlayerDiffEnv] is an ordinary single-agent [`DiffEnv`][torchrl_diffenvs.DiffEnv] for the learner: its
``"observation"``, ``"action"`` and ``"reward"`` are player 0's. Each step the opponent (player 1)
acts from its own observation, computed by the same ``observe`` function with the players
swapped, so that a snapshot of the learner's policy can play the other side (self-play, as
rl_games does it: ``sota_scripts/train.py selfplay.refresh_interval=...``, see
`torchrl_diffenvs.training.selfplay`). By default the opponent is the task's scripted
controller. Gradients flow through the opponent's response into player 0's earlier actions
(the opponent's own weights are frozen).
"""
from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from torch import nn

from .base import DiffEnv

__all__ = ["TwoPlayerDiffEnv", "opponent_from_actor"]


class _FrozenActor(nn.Module):
    """The deterministic action of a (copied, frozen) actor from an observation tensor."""

    def __init__(self, actor: nn.Module):
        super().__init__()
        actor = copy.deepcopy(actor)
        for parameter in actor.parameters():
            parameter.requires_grad_(False)
        self.actor = actor
        # make_actor's TanhNormalActor plays its mean action; its deterministic variant is a
        # LeanModule, whose module maps the observation to the action
        self.act = actor.mean_action if hasattr(actor, "mean_action") else actor.module

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.act(observation)


def opponent_from_actor(actor: nn.Module) -> Callable[[torch.Tensor], torch.Tensor]:
    """A frozen copy of ``actor`` as an opponent:
    ``observation [N, obs_dim] -> action [N, action_dim]``, its deterministic (mean) action.

    Args:
        actor: an actor from [`make_actor`][torchrl_diffenvs.modules.make_actor].
    """
    return _FrozenActor(actor)


class TwoPlayerDiffEnv(DiffEnv):
    """A [`DiffEnv`][torchrl_diffenvs.DiffEnv] whose player 1 is played by [`opponent`][torchrl_diffenvs.envs.TwoPlayerDiffEnv.opponent].

    A subclass defines ``initial_state`` as usual and

    * ``observe(state, params, player) -> [N, obs_dim]``: what player 0 or 1 sees (the same layout
      for both, so that one policy can play either side);
    * ``play(state, actions, params) -> (next_state, reward, terminated)``: the step from both
      players' actions ``[N, 2, action_dim]``; ``reward`` is player 0's;
    * ``scripted_action(state, params) -> [N, action_dim]``: the default opponent's action;
    * optionally ``player_wins(state, params) -> [N] bool``: whether player 0 won (evaluations
      report the win rate at the end of the first episode).
    """

    def observe(self, state, params, player: int) -> torch.Tensor:
        """What ``player`` (0 or 1) sees: ``[N, obs_dim]``, the same layout for both players, so
        that one policy can play either side (a task writes this)."""
        raise NotImplementedError

    def play(self, state, actions, params):
        """One step from both players' actions ``[N, 2, action_dim]`` (player 0's first):
        ``(next_state, reward, terminated)``, ``reward`` ``[N]`` being player 0's (a task writes this)."""
        raise NotImplementedError

    def scripted_action(self, state, params) -> torch.Tensor:
        """The default opponent's action ``[N, action_dim]`` for player 1 (a task writes this)."""
        raise NotImplementedError

    _opponent_policy = None  # None: the scripted opponent

    def set_opponent(self, policy=None) -> None:
        """Plays player 1 with ``policy`` from now on: an actor of this env (``make_actor(env)``,
        copied and frozen, its mean action), a callable ``observation -> action``, or ``None`` for
        the task's scripted opponent."""
        if policy is not None and isinstance(policy, nn.Module) and hasattr(policy, "module"):
            policy = opponent_from_actor(policy)
        if policy is not None and not callable(policy):
            raise TypeError(f"{self.name}: set_opponent expects an actor, a callable or None, got {type(policy).__name__}")
        self.__dict__["_opponent_policy"] = policy  # not a submodule: its weights are not the env's

    @property
    def opponent(self):
        """What plays player 1: ``None`` for the scripted opponent, else the policy."""
        return self._opponent_policy

    def opponent_action(self, state, params) -> torch.Tensor:
        """Player 1's action ``[N, action_dim]``: the scripted one, or the opponent policy's on
        player 1's observation, clamped to the action bounds."""
        if self._opponent_policy is None:
            return self.scripted_action(state, params)
        return self._opponent_policy(self.observe(state, params, 1)).clamp(self.action_low, self.action_high)

    def transition(self, state, action, params):
        actions = torch.stack([action, self.opponent_action(state, params)], dim=-2)
        return self.play(state, actions, params)

    def observation(self, state, params) -> torch.Tensor:
        return self.observe(state, params, 0)
