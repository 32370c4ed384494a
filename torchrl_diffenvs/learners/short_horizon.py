"""The SHAC family's training iteration, written once: SHAC, AHAC and SAPO fill in its hooks.

One iteration of [`ShortHorizonLearner`][torchrl_diffenvs.learners.ShortHorizonLearner]:

1. collect a window ``[N, H]`` with the autograd graph on (the env state carried over and
   detached at the window start); ``_check_window`` may refuse it before anything is updated;
2. actor step: backpropagate the loss's bootstrapped return over the finite envs (envs with
   NaN/inf rewards or observations are left out of the actor and critic steps, counted in
   ``"nonfinite_envs"`` and named in a warning), one guarded step on the gradient averaged
   over the ranks; ``_after_actor_step`` adds its own update and metrics (SAPO's temperature);
3. critic targets: those the loss wrote into the detached window (``_critic_targets`` may
   recompute them: SAPO, with the new temperature);
4. critic passes over minibatches of the finite envs' steps (``critic_minibatches``, ordered by
   ``critic_shuffle``; ``_critic_pass_count`` says how many passes, and whether to stop when
   the pass losses plateau: AHAC), gradients averaged over the ranks; then
   ``_after_critic_fit`` (SHAC's target critic);
5. update the observation normaliser (shared by actor and critic) from the window, all ranks'
   (and a privileged critic's own input normaliser);
6. ``_after_window`` adds its own update and metrics (AHAC's horizon);
7. step the learning-rate schedules.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import torch

from ..collectors import DiffWindowCollector
from ..distributed import SINGLE_PROCESS, World
from ..envs.multi_agent import policy_keys
from ..modules import (
    ObservationNormalizer,
    critic_from_config,
    observation_key_of,
    orthogonal_init_,
    update_privileged_statistics,
)
from ..objectives import GradientGuard, NonFiniteEnvMonitor, TwinCritic
from ..objectives.windows import window_contact_force, window_solver_unconverged
from .base import ActorCriticCheckpoint, Learner, LearnerConfig, lr_scheduler

__all__ = ["CRITIC_SHUFFLES", "ShortHorizonLearner", "TwinCriticLearner", "twin_critic_from_config"]

# how the critic's minibatches are drawn from the window: in_order: contiguous blocks of the window in
# time order, [t0, t1) x all envs (the references: DiffRL and mineral build their critic datasets unshuffled);
# once_per_window: one random split, visited in the same order by every pass; every_pass: a new one per pass
CRITIC_SHUFFLES = ("in_order", "once_per_window", "every_pass")


class ShortHorizonLearner(ActorCriticCheckpoint, Learner):
    """SHAC's window loop (collect, actor step, critic fit, normalisers, schedules) with hooks.

    Subclasses build the loss and override the hooks where their algorithm differs:
    ``_check_window``, ``_after_actor_step``, ``_critic_targets``, ``_critic_pass_count``,
    ``_after_critic_fit``, ``_critic_metrics`` and ``_after_window`` (each a no-op or SHAC's
    behaviour here).

    Args:
        env: a batched differentiable env (this rank's batch).
        actor: the policy to train, writing ``"action"``.
        loss: the window loss ([`SHACLoss`][torchrl_diffenvs.objectives.SHACLoss] or a subclass),
            holding the critics; its reward and value keys are set to the env's here.
        config: the learner's settings (``actor_lr``, ``critic_lr``, ``betas``, ``lr_schedule``,
            ``min_lr``, ``lr_decay``, ``critic_passes``, ``critic_minibatches``,
            ``critic_shuffle``, ``max_grad_norm``, ``skip_above`` are read here).
        total_env_steps: the budget the learning-rate schedules run over.
        horizon: the first window's length.
        normalizer: the observation normaliser shared by actor and critics, updated after every window.
        reset_input: for a batch-unlocked env (TorchRL's ``PendulumEnv``), what to reset it with
            (see [`DiffWindowCollector`][torchrl_diffenvs.collectors.DiffWindowCollector]).
        world: the ranks training together (`torchrl_diffenvs.distributed`).
        optimizer: the optimiser class of actor and critics (``torch.optim.Adam`` or ``AdamW``).
        optimizer_kwargs: its extra arguments (e.g. ``weight_decay``).
        critic_max_grad_norm: the critics' gradient-norm clip (``None``: no clipping).
    """

    def __init__(self, env, actor, loss, config: LearnerConfig, total_env_steps: int, *, horizon: int,
                 normalizer: ObservationNormalizer | None = None, reset_input=None, world: World = SINGLE_PROCESS,
                 optimizer: type[torch.optim.Optimizer] = torch.optim.Adam, optimizer_kwargs: Mapping | None = None,
                 critic_max_grad_norm: float | None = None):
        super().__init__(env, config, total_env_steps, reset_input=reset_input, world=world)
        c = config
        self.keys = policy_keys(env)
        if self.keys.num_agents is not None and not self.supports_multi_agent:
            raise ValueError(f"{type(self).__name__}: single-agent envs only; {type(env).__name__} is multi-agent "
                             "(train it with bptt, shac or ppo)")
        self.actor = self.policy = actor
        self.normalizer = normalizer
        self.collector = DiffWindowCollector(env, actor, horizon=int(horizon), reset_input=reset_input)
        self._last_window_steps = int(horizon)
        self.loss = loss
        self.loss.set_keys(reward=self.keys.reward, value=self.keys.value)  # ("agents", ...) on a multi-agent env
        self.actor_params = [p for p in actor.parameters() if p.requires_grad]
        self.critic_params = [p for p in self.loss.critic_network.parameters() if p.requires_grad]
        # foreach: one kernel per optimiser operation for all tensors (about 2x faster for small nets on CPU)
        kwargs = dict(optimizer_kwargs or {})
        self.actor_optim = optimizer(self.actor_params, lr=c.actor_lr, betas=c.betas, foreach=True, **kwargs)
        self.critic_optim = optimizer(self.critic_params, lr=c.critic_lr, betas=c.betas, foreach=True, **kwargs)
        self.nonfinite = NonFiniteEnvMonitor(type(self).__name__)
        self.actor_guard = GradientGuard(max_norm=c.max_grad_norm, skip_above=c.skip_above)
        self.critic_guard = GradientGuard(max_norm=critic_max_grad_norm, skip_above=c.skip_above)
        self.schedules = [
            lr_scheduler(optim, c.lr_schedule, lambda: self.total_iterations, min_lr=c.min_lr, decay=c.lr_decay)
            for optim in (self.actor_optim, self.critic_optim)
        ]

    @property
    def steps_per_env(self) -> int:
        """Length of the window the last `train_iteration` collected (the next one's before any)."""
        return self._last_window_steps

    # ------------------------------------------------------------------ hooks
    def _check_window(self, window) -> None:
        """Right after the rollout: raise if the window lacks an entry the learner needs."""

    def _after_actor_step(self, window, out) -> dict[str, float]:
        """After the actor's step, before the window is detached: extra updates and metrics."""
        return {}

    def _critic_targets(self, data) -> None:
        """The critic targets of the detached window: those the loss wrote (override to recompute)."""

    def _critic_pass_count(self) -> tuple[int, bool]:
        """``(most passes, stop early when the pass losses plateau)``."""
        return self.config.critic_passes, False

    def _after_critic_fit(self) -> None:
        """Right after the critic passes, before the normalisers move (SHAC: the target critic)."""

    def _critic_metrics(self, pass_losses: list[list[float]]) -> dict[str, float]:
        """The critic's metrics from the minibatch losses of each pass (none when every env was
        non-finite): ``"loss_critic"``, the mean over every minibatch of every pass."""
        losses = [loss for one_pass in pass_losses for loss in one_pass]
        return {"loss_critic": sum(losses) / len(losses) if losses else float("nan")}

    def _after_window(self, data, keep) -> dict[str, float]:
        """After the critic and normaliser updates, before the schedules step: extra updates and
        metrics (``keep [N]``: the finite envs)."""
        return {}

    # ------------------------------------------------------------------ one iteration
    def train_iteration(self) -> dict[str, float]:
        # 1. a window with the graph on
        window = self.collector.rollout()
        self._last_window_steps = window.shape[1]
        self._check_window(window)
        # 2. actor step on the bootstrapped return over the finite envs (the collector cut the others'
        # gradient); the loss also writes the critic targets
        out = self.loss(window)
        keep = self.loss.finite_envs(window)
        nonfinite = self.nonfinite.update(~keep, self.iteration)
        self.actor_optim.zero_grad(set_to_none=True)
        if out["loss_actor"].requires_grad:  # False when nothing depends on the actions
            out["loss_actor"].backward()
        self.world.average_gradients(self.actor_params)
        actor_info = self.actor_guard.step(self.actor_optim, self.actor_params, loss=out["loss_actor"],
                                           context=self.nonfinite.describe)
        metrics = {key: out[key].item() for key in ("loss_actor", "reward_mean", "value_mean")}
        metrics["nonfinite_envs"] = nonfinite
        metrics.update(self._after_actor_step(window, out))
        # 3. the critic targets of the detached window
        data = window.detach()
        del window, out  # the graph is spent
        self._critic_targets(data)
        # 4. the critic fits the finite envs' targets
        pass_losses = self._fit_critic(data, keep)
        self._after_critic_fit()
        # 5. observation (and privileged-input) statistics, frozen during the window, move after it
        if self.normalizer is not None:
            self.normalizer.update(self.world.gather(data.get(observation_key_of(self.actor, self.keys.observation))))
        update_privileged_statistics(self.loss.critic_network, data, self.world.gather)
        metrics.update({
            "reward": metrics.pop("reward_mean"),
            "value": metrics.pop("value_mean"),
            **self._critic_metrics(pass_losses),
            "grad_norm_actor": actor_info["grad_norm"],
            "skipped_actor": self.actor_guard.skipped,
            "skipped_critic": self.critic_guard.skipped,
            "lr_actor": self.actor_optim.param_groups[0]["lr"],
        })
        force = window_contact_force(data)  # envs with contacts report their largest normal force
        if force is not None:
            metrics["contact_force_max"] = force.max().item()
        unconverged = window_solver_unconverged(data)  # MuJoCo's contact: solves cut at the model's iterations
        if unconverged is not None:
            metrics["solver_unconverged"] = unconverged
        # 6. the learner's own end-of-window update
        metrics.update(self._after_window(data, keep))
        if self.collector.finished_returns:
            metrics["return"] = sum(self.collector.finished_returns) / len(self.collector.finished_returns)
        # 7. learning-rate schedules
        for schedule in self.schedules:
            schedule.step()
        self.iteration += 1
        return metrics

    def _fit_critic(self, data, keep) -> list[list[float]]:
        """Critic passes over minibatches of the finite envs' steps of the detached window
        ``data [N, H]``; returns each pass's minibatch losses. None when every env is non-finite
        (the env zeroes their rewards: there is nothing true to fit): each planned step is
        counted as skipped."""
        c = self.config
        most, until_plateau = self._critic_pass_count()
        if not keep.any():
            for _ in range(most * c.critic_minibatches):
                self.critic_guard.skip(context=self.nonfinite.describe)
            return []
        window = data.select(*self.loss.critic_network.in_keys, self.loss.tensor_keys.value_target)[keep]
        flat = window.reshape(-1)
        pass_losses: list[list[float]] = []
        recent: deque[float] = deque(maxlen=5)
        for critic_pass in range(most):
            if critic_pass == 0 and c.critic_shuffle == "in_order":
                n, h = window.batch_size
                split = torch.arange(n * h).reshape(n, h).t().reshape(-1).chunk(c.critic_minibatches)
            elif critic_pass == 0 or c.critic_shuffle == "every_pass":
                split = torch.randperm(flat.shape[0]).chunk(c.critic_minibatches)
            losses = [self._critic_step(flat[batch]) for batch in split]
            pass_losses.append(losses)
            if until_plateau:  # the reference's early stop: the mean change over the previous 5 pass losses
                if len(recent) == 5 and abs((recent[-1] - recent[0]) / 4) < c.critic_plateau:
                    break
                recent.append(sum(losses) / len(losses))
        return pass_losses

    def _critic_step(self, batch) -> float:
        """One guarded step of the critics on a minibatch, the gradient averaged over the ranks."""
        critic_loss = self.loss.critic_loss(batch)["loss_critic"]
        self.critic_optim.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.world.average_gradients(self.critic_params)
        self.critic_guard.step(self.critic_optim, self.critic_params, loss=critic_loss,
                               context=self.nonfinite.describe)
        return critic_loss.item()


def twin_critic_from_config(section: Mapping, env, normalizer: ObservationNormalizer | None,
                            orthogonal_gain: float | None = None) -> TwinCritic:
    """Two critics from one ``loss.critic`` section (separate weights, the actor's normaliser
    shared); ``orthogonal_gain``: the gain of an ``init: orthogonal`` section (the builder's own
    is ``sqrt(2)``)."""
    critics = [critic_from_config(section, env, normalizer) for _ in range(2)]
    if orthogonal_gain is not None and section.get("init") == "orthogonal":
        for critic in critics:
            orthogonal_init_(critic, orthogonal_gain)
    return TwinCritic(*critics)


class TwinCriticLearner(ShortHorizonLearner):
    """The SHAC-family skeleton with twin critics and no target critic: what AHAC and SAPO share.

    Single-agent; its metrics give the last critic pass's mean loss (``"loss_critic"``) and the
    number of passes (``"critic_passes"``); its checkpoints keep the last window's length (AHAC
    changes it between iterations). Arguments as
    [`ShortHorizonLearner`][torchrl_diffenvs.learners.ShortHorizonLearner]'s.
    """

    supports_multi_agent = False  # one actor, one value per env: the multi-agent keys are SHAC's and PPO's

    def _critic_metrics(self, pass_losses: list[list[float]]) -> dict[str, float]:
        last = pass_losses[-1] if pass_losses else []
        return {"loss_critic": sum(last) / len(last) if last else float("nan"), "critic_passes": len(pass_losses)}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "last_window_steps": self._last_window_steps}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)  # actor, both critics (normaliser included), optimisers, ...
        self._last_window_steps = int(state["last_window_steps"])
