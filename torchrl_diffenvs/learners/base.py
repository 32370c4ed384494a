"""What every learner shares: its settings' checks, the interface the training script drives and
the learning-rate schedules."""
from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from types import MappingProxyType

import torch
from tensordict.nn import TensorDictModuleBase

from .. import checks
from ..checks import Settings, checked
from ..collectors import batch_size_of
from ..distributed import SINGLE_PROCESS, World
from ..modules import ACTIVATIONS, DISTRIBUTIONS, NETWORK_INITS, actor_from_config

__all__ = [  # checked: re-exported for the learner files
    "ActorCriticCheckpoint", "ActorNetworkConfig", "LR_SCHEDULES", "Learner", "LearnerConfig", "NetworkConfig", "checked",
    "load_lr_scheduler", "lr_scheduler",
]

LR_SCHEDULES = ("linear", "exponential", "constant")
"""The valid ``loss.lr_schedule`` values."""


class LearnerConfig(Settings):
    """Base of a learner's settings: a frozen dataclass whose fields carry their checks
    (`checked`).

    The fields are the keys of the training script's ``loss`` section (besides ``name`` and the
    network sections, `Learner.networks`), and their defaults are the section's defaults:
    the configuration is generated from this class, so the training script and Python code build
    learners alike.
    """


def _layer_widths(value) -> str | None:
    ok = (isinstance(value, (list, tuple)) and not isinstance(value, str) and len(value) > 0
          and all(checks.is_int(h) and h >= 1 for h in value))
    return None if ok else "expected a list of positive layer widths, e.g. [64, 64]"


def _finite_number(value) -> str | None:
    return None if checks.is_number(value) else "expected a finite number"


@dataclasses.dataclass(frozen=True)
class NetworkConfig(Settings):
    """A network section of a learner's settings (``loss.critic``, ``loss.qvalue``): the MLP that
    [`make_critic`][torchrl_diffenvs.modules.make_critic] / ``make_qvalue`` build."""

    hidden: tuple = checked((64, 64), _layer_widths)  # layer widths
    activation: str = checked("elu", checks.one_of(tuple(ACTIVATIONS)))
    layer_norm: bool = checked(True, checks.boolean)
    norm_after_activation: bool = checked(False, checks.boolean)  # Linear-LayerNorm-act; true: Linear-act-LayerNorm
    init: str = checked("default", checks.one_of(NETWORK_INITS))  # default (PyTorch's) | orthogonal (gain sqrt 2)


@dataclasses.dataclass(frozen=True)
class ActorNetworkConfig(NetworkConfig):
    """``loss.actor``: the policy network ([`make_actor`][torchrl_diffenvs.modules.make_actor])."""

    init_log_std: float = checked(-1.0, _finite_number)  # the policy's initial log standard deviation
    distribution: str = checked("tanh_normal", checks.one_of(DISTRIBUTIONS))  # tanh_normal | deterministic


def _plain(value):
    """Dataclass defaults and configuration nodes as plain values: sequences become lists,
    mappings dicts (OmegaConf's ListConfig / DictConfig included)."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)):
        return [_plain(v) for v in value]
    return value


def _show(value) -> str:
    """A value as it is written on the command line (``true``, not ``True``)."""
    return str(value).lower() if isinstance(value, bool) else repr(value)


def lr_scheduler(optimizer: torch.optim.Optimizer, kind: str, total_iterations: Callable[[], int], *,
                 min_lr: float = 0.0, decay: float = 1.0) -> torch.optim.lr_scheduler.LambdaLR:
    """A learning-rate schedule that follows the budget as it is *now*.

    A run resumed with another budget (`load_lr_scheduler`) continues without a jump: the
    linear schedule goes on from the learning rate it had reached, straight to ``min_lr`` at the
    end of the new budget (from the iteration ``r`` and factor ``f_r`` of the resume,
    ``f(i) = f_r + (end - f_r) (i - r) / (total - r)``), and holds ``min_lr`` after it. A
    schedule that had already reached ``min_lr`` stays there. The anchor ``(r, f_r)`` is saved
    in the scheduler's state.

    Args:
        optimizer: the optimiser whose learning rates are scheduled (every group's by the same factor,
            which ends at ``min_lr`` over the first group's learning rate).
        kind: ``"linear"`` decays from the optimiser's learning rate to ``min_lr`` over
            ``total_iterations()`` iterations, then stays there; ``"exponential"`` multiplies it by
            ``decay`` every iteration; ``"constant"`` keeps it.
        total_iterations: returns the budget in iterations; read at every step.
        min_lr: where the linear schedule ends.
        decay: the exponential schedule's factor per iteration.
    """
    if kind not in LR_SCHEDULES:
        raise ValueError(f"unknown lr_schedule {kind!r}; valid: {', '.join(LR_SCHEDULES)}")
    end = min(1.0, min_lr / optimizer.param_groups[0]["lr"])
    anchor = {"iteration": 0, "factor": 1.0}  # where the current line starts (moved by a resume)
    if kind == "linear":
        def factor(i: int) -> float:
            start, at = anchor["iteration"], anchor["factor"]
            if start == 0:  # a fresh run: from 1 to end over the budget
                return 1.0 - (1.0 - end) * min(i / max(1, total_iterations()), 1.0)
            return at + (end - at) * min(max(i - start, 0) / max(1, total_iterations() - start), 1.0)
    elif kind == "exponential":
        def factor(i: int) -> float:
            return decay**i
    else:
        def factor(i: int) -> float:
            return 1.0
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    schedule.anchor = anchor  # in the scheduler's __dict__: saved and restored with its state
    return schedule


def load_lr_scheduler(schedule: torch.optim.lr_scheduler.LambdaLR, state: dict) -> None:
    """Restores a [`lr_scheduler`][torchrl_diffenvs.learners.lr_scheduler] so that the learning rate goes on from the saved one.

    With the budget it was saved with, the schedule continues exactly. With another budget the
    saved learning rate no longer lies on the schedule's line: the schedule is re-anchored at the
    saved iteration and rate (see [`lr_scheduler`][torchrl_diffenvs.learners.lr_scheduler]), so the rate right after the resume is
    the rate right before it, and it then decays to ``min_lr`` over the remaining budget.
    """
    anchor = getattr(schedule, "anchor", None)
    schedule.load_state_dict(state)
    if anchor is not None:  # the closure reads this dict: copy the loaded values into it
        anchor.update(getattr(schedule, "anchor", anchor))
        schedule.anchor = anchor
    saved = state.get("_last_lr")
    i = schedule.last_epoch
    for k, (group, base_lr, factor) in enumerate(zip(schedule.optimizer.param_groups, schedule.base_lrs,
                                                     schedule.lr_lambdas)):
        lr = base_lr * factor(i)
        if saved is not None and anchor is not None and lr != saved[k] and base_lr > 0:
            anchor.update(iteration=i, factor=saved[k] / base_lr)  # the budget changed: go on from here
            lr = base_lr * factor(i)
        group["lr"] = lr


class Learner(ABC):
    """One learning algorithm behind one interface, used alike by ``sota_scripts/train.py``, the
    demos, the benchmarks and the tests.

    A learner owns its networks, optimisers, schedules and data collection on the training env.
    Each [`train_iteration`][torchrl_diffenvs.learners.Learner.train_iteration] collects [`env_steps_per_iteration`][torchrl_diffenvs.learners.Learner.env_steps_per_iteration] env steps and updates
    the networks; `policy` is the actor that evaluation runs in deterministic mode.
    [`from_config`][torchrl_diffenvs.learners.Learner.from_config] builds one from a ``loss`` configuration section.

    Args:
        env: the training env: any TorchRL ``EnvBase`` with a batch dimension ``[N]`` (BPTT and
            SHAC also take a batch-unlocked one with ``reset_input``); BPTT and SHAC need its
            rewards or observations to carry gradients w.r.t. the actions.
        config: the learner's settings (its [`LearnerConfig`][torchrl_diffenvs.learners.LearnerConfig] subclass).
        total_env_steps: the training budget (global: all ranks together); the learning-rate
            schedules run over it, and it can be changed later (a resumed run with a larger budget).
        world: the ranks training together (`World`; default
            one process). Every gradient is averaged over them before the optimiser step, and
            [`env_steps_per_iteration`][torchrl_diffenvs.learners.Learner.env_steps_per_iteration] counts the env steps of all of them.
    """

    # ------------------------------------------------------------------ what differs between learners
    #: the ``loss=<name>`` of the training script (and of [`register_learner`][torchrl_diffenvs.learners.register_learner])
    name: str = ""
    #: its settings: a frozen dataclass whose field defaults are the ``loss`` section's defaults
    config_class: type[LearnerConfig] = LearnerConfig
    #: its network sections (``loss.actor``, ``loss.critic``, ...) with their defaults
    networks: Mapping[str, NetworkConfig] = MappingProxyType({"actor": ActorNetworkConfig()})
    #: what the learner changes in the run's other sections (its budget; SAC: fewer envs), merged
    #: over ``configs/config.yaml`` when ``loss=<name>`` is chosen
    run_defaults: Mapping[str, Mapping] = MappingProxyType({})
    #: settings other learners have and this one refuses, with the reason (``loss.<key>=...``)
    unsupported_settings: Mapping[str, str] = MappingProxyType({})
    #: the policy must sample actions (``loss.actor.distribution=tanh_normal``): PPO, SAC
    needs_stochastic_policy: bool = False
    #: the policy writes its log-probability (PPO's ratio): the evaluated policy is built so too
    policy_log_prob: bool = False
    #: trains on multi-agent envs (``("agents", ...)`` keys)
    supports_multi_agent: bool = True
    #: the ``loss=`` choices to suggest for a multi-agent env (PPO: its presets mappo and ippo);
    #: empty: ``(name,)``
    multi_agent_choices: tuple[str, ...] = ()
    #: collects differentiable windows through the env's own rollout (BPTT, SHAC), which
    #: ``compile=true`` ([`compile_physics`][torchrl_diffenvs.compile_physics]) runs in compiled chunks
    compiles_windows: bool = False

    policy: TensorDictModuleBase

    @classmethod
    def env_problems(cls, env) -> list[str]:
        """What this learner cannot train on ``env`` (one line each; the training script reports
        them with the other configuration problems). AHAC: an env that reports no contact force."""
        return []

    def __init__(self, env, config: LearnerConfig, total_env_steps: int, *, reset_input=None,
                 world: World = SINGLE_PROCESS):
        if not isinstance(config, self.config_class):
            raise TypeError(f"{type(self).__name__}: config must be a {self.config_class.__name__}, "
                            f"got {type(config).__name__}")
        self._num_envs = batch_size_of(env, reset_input, type(self).__name__)
        self.env = env
        self.config = config
        self.total_env_steps = int(total_env_steps)
        self.world = world
        self.iteration = 0

    @classmethod
    @abstractmethod
    def from_config(cls, loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> Learner:
        """Builds the learner and its networks from a ``loss`` section ([`default_config`][torchrl_diffenvs.learners.Learner.default_config] and overrides)."""

    @classmethod
    def default_config(cls) -> dict:
        """The configuration ``loss=<name>`` selects, generated from the class (the only place
        the defaults are written): ``{"loss": {"name", <settings>, <network sections>}, **run_defaults}``."""
        section = {"name": cls.name, **_plain(cls.config_class.defaults())}
        section.update({key: _plain(dataclasses.asdict(net)) for key, net in cls.networks.items()})
        return {"loss": section, **_plain(dict(cls.run_defaults))}

    @classmethod
    def config_problems(cls, loss_cfg: Mapping, where: str = "loss.") -> list[str]:
        """Every problem of a ``loss`` section for this learner (unknown keys, values failing
        their checks, settings this learner refuses), each naming the key and what is valid."""
        problems = []
        settings = {}
        loss_cfg = _plain(loss_cfg)
        for key, value in loss_cfg.items():
            if key == "name":
                continue
            if key in cls.unsupported_settings:
                if value:  # false / null: the setting is off, as the learner works anyway
                    problems.append(f"{where}{key}={_show(value)} is not supported by loss={cls.name} "
                                    f"({cls.unsupported_settings[key]})")
            elif key in cls.networks:
                if isinstance(value, Mapping):
                    problems.extend(type(cls.networks[key]).problems(value, f"{where}{key}."))
                else:
                    problems.append(f"{where}{key}={value!r}: expected a network section, e.g. {{hidden: [64, 64]}}")
            else:
                settings[key] = value
        problems.extend(cls.config_class.problems(settings, where))
        actor = loss_cfg.get("actor")
        if cls.needs_stochastic_policy and isinstance(actor, Mapping) and \
                actor.get("distribution", "tanh_normal") != "tanh_normal":
            problems.append(f"{where}actor.distribution={actor.get('distribution')!r}: loss={cls.name} needs a "
                            "stochastic policy; valid: tanh_normal")
        return problems

    @classmethod
    def settings_from(cls, loss_cfg: Mapping) -> LearnerConfig:
        """The [`config_class`][torchrl_diffenvs.learners.LearnerConfig] of a ``loss`` section: every key but ``name``, the network
        sections and the (off) settings this learner does not support."""
        skipped = {"name", *cls.networks, *cls.unsupported_settings}
        return cls.config_class.from_mapping({k: v for k, v in loss_cfg.items() if k not in skipped})

    @classmethod
    def policy_from_config(cls, loss_cfg: Mapping, env) -> TensorDictModuleBase:
        """The policy network alone, shaped as [`from_config`][torchrl_diffenvs.learners.Learner.from_config] builds it (``mode=eval`` loads a
        checkpoint's ``"policy"`` weights into it)."""
        return actor_from_config(loss_cfg, env, return_log_prob=cls.policy_log_prob)[0]

    @property
    def num_envs(self) -> int:
        """The number of envs the learner trains on (this rank's)."""
        return self._num_envs

    @property
    @abstractmethod
    def steps_per_env(self) -> int:
        """Steps each env takes in one [`train_iteration`][torchrl_diffenvs.learners.Learner.train_iteration] (the window or rollout length)."""

    @property
    def env_steps_per_iteration(self) -> int:
        """Env steps collected by one [`train_iteration`][torchrl_diffenvs.learners.Learner.train_iteration], on all ranks together."""
        return self.num_envs * self.steps_per_env * self.world.size

    @property
    def total_iterations(self) -> int:
        """Training iterations in the run: ``total_env_steps`` over the env steps of one iteration, at least 1."""
        return max(1, math.ceil(self.total_env_steps / self.env_steps_per_iteration))

    @abstractmethod
    def train_iteration(self) -> dict[str, float]:
        """Collects data and updates the networks once.

        Returns scalar metrics without a prefix: ``"reward"`` (mean per-step reward of the
        collected data), ``"return"`` (mean return of the episodes that finished, when any did),
        losses, pre-clip gradient norms (``"grad_norm*"``), cumulative skipped steps
        (``"skipped*"``) and learning rates.
        """

    @abstractmethod
    def state_dict(self) -> dict:
        """Everything needed to continue exactly: networks, optimisers, schedules, normalisers,
        the env state being collected from, replay buffers. Plain tensors and containers only."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        """Restores [`state_dict`][torchrl_diffenvs.learners.Learner.state_dict] into a learner built from the same configuration."""

    def close(self) -> None:
        """Releases collectors (override when there is anything to release)."""


class ActorCriticCheckpoint:
    """Mixin: the checkpoint state of a window learner with an actor and a critic optimiser
    (SHAC, AHAC, SAPO): ``iteration``, ``loss`` (every network, normaliser included), the two
    optimisers, the schedules, the two gradient guards and the window collector. Subclasses add
    their own entries around ``super()``."""

    def state_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "loss": self.loss.state_dict(),
            "optimizers": [self.actor_optim.state_dict(), self.critic_optim.state_dict()],
            "schedules": [s.state_dict() for s in self.schedules],
            "guards": [self.actor_guard.state_dict(), self.critic_guard.state_dict()],
            "collector": self.collector.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.iteration = int(state["iteration"])
        self.loss.load_state_dict(state["loss"])
        for optim, saved in zip((self.actor_optim, self.critic_optim), state["optimizers"], strict=True):
            optim.load_state_dict(saved)
        for schedule, saved in zip(self.schedules, state["schedules"], strict=True):
            load_lr_scheduler(schedule, saved)
        for guard, saved in zip((self.actor_guard, self.critic_guard), state["guards"], strict=True):
            guard.load_state_dict(saved)
        self.collector.load_state_dict(state["collector"])
