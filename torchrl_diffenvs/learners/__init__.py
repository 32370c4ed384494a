"""One learner per algorithm, each in one file that reads like its algorithm.

``bptt``, ``shac``, ``ahac`` and ``sapo`` backpropagate through the differentiable env; ``ppo``
and ``sac`` are TorchRL's own losses and collectors. All share [`Learner`][torchrl_diffenvs.learners.Learner]'s interface, used alike by
the training loop (`torchrl_diffenvs.training`), the demos, the benchmarks and the tests:

```python
learner = SHACLearner(env, make_actor(env), make_critic(env), SHACConfig(horizon=8))
for _ in range(100):
    metrics = learner.train_iteration()
```

Adding a learner
----------------
One file plus its import and registration here:

1. ``torchrl_diffenvs/learners/<name>.py``: a frozen settings dataclass (a [`LearnerConfig`][torchrl_diffenvs.learners.LearnerConfig]
   whose fields are ``checked(default, check)``: the defaults live there and nowhere else) and a
   [`Learner`][torchrl_diffenvs.learners.Learner] subclass that implements ``from_config``, ``steps_per_env``,
   ``train_iteration``, ``state_dict`` and ``load_state_dict``, and says in class attributes what
   the training loop needs to know about it: ``name`` (the ``loss=<name>`` choice),
   ``config_class``, ``networks`` (its network sections and their defaults), ``run_defaults``
   (its budget: ``train.total_env_steps`` etc.), and where it differs from the defaults
   ``needs_stochastic_policy``, ``policy_log_prob``, ``supports_multi_agent``,
   ``compiles_windows``, ``unsupported_settings``;
2. its import in this file, and ``MyLearner`` in the tuple of the registration loop at its end
   (``register_learner``: the training script knows the learners this module registers).

A learner of SHAC's family (a differentiable window, an actor step, critic passes) subclasses
[`ShortHorizonLearner`][torchrl_diffenvs.learners.ShortHorizonLearner] and fills in its hooks, as
SHAC, AHAC and SAPO do.

``python sota_scripts/train.py loss=<name>`` then works: the ``loss`` configuration group gets
``<name>`` (generated from the class, [`Learner.default_config`][torchrl_diffenvs.learners.Learner.default_config]), the settings are checked
with the project's one-line errors ([`Learner.config_problems`][torchrl_diffenvs.learners.Learner.config_problems]), and the training loop,
checkpoints, resume and ``mode=eval`` drive it through the interface. Presets (other settings of
the same learner, e.g. ``loss=shac_reference``) are YAML files in ``configs/loss/`` whose defaults
list starts with the learner's name.
"""
from __future__ import annotations

from collections.abc import Mapping

from ..distributed import SINGLE_PROCESS, World

from .ahac import AHACConfig, AHACLearner
from .base import LR_SCHEDULES, ActorNetworkConfig, Learner, LearnerConfig, NetworkConfig, lr_scheduler
from .bptt import BPTTConfig, BPTTLearner
from .ppo import PPOConfig, PPOLearner
from .sac import SACConfig, SACLearner
from .sapo import SAPOConfig, SAPOLearner
from .shac import SHACConfig, SHACLearner
from .short_horizon import ShortHorizonLearner, TwinCriticLearner

LEARNERS: dict[str, type[Learner]] = {}
"""Every learner class by its ``loss=`` name (filled by `register_learner`)."""


def register_learner(learner: type[Learner]) -> type[Learner]:
    """Makes ``learner`` available as ``loss=<learner.name>`` ([`make_learner`][torchrl_diffenvs.learners.make_learner]
    and the training script's ``loss`` configuration group).

    Args:
        learner: a [`Learner`][torchrl_diffenvs.learners.Learner] subclass with a ``name``.

    Returns:
        ``learner``, so it can decorate the class.
    """
    if not (isinstance(learner, type) and issubclass(learner, Learner)) or not learner.name:
        raise TypeError(f"register_learner needs a Learner subclass with a name, got {learner!r}")
    LEARNERS[learner.name] = learner
    try:  # the training script's configuration group (Hydra is a dependency, but keep learners importable without)
        from hydra.core.config_store import ConfigStore
    except ImportError:  # pragma: no cover
        return learner
    ConfigStore.instance().store(group="loss", name=learner.name, node=learner.default_config(), package="_global_")
    return learner


def make_learner(loss_cfg: Mapping, env, total_env_steps: int, world: World = SINGLE_PROCESS) -> Learner:
    """Builds the learner named by ``loss_cfg.name`` on ``env``.

    Args:
        loss_cfg: the training script's ``loss`` section; its ``name`` picks the learner.
        env: the env to train on (this rank's envs when ``world`` has several ranks).
        total_env_steps: the training budget in env steps (global: all ranks together).
        world: the ranks training together (default: one process).
    """
    name = loss_cfg.get("name")
    if name not in LEARNERS:
        raise ValueError(f"unknown loss {name!r}; valid: {', '.join(LEARNERS)}")
    return LEARNERS[name].from_config(loss_cfg, env, total_env_steps, world)


for _learner in (BPTTLearner, SHACLearner, PPOLearner, SACLearner, AHACLearner, SAPOLearner):
    register_learner(_learner)

__all__ = [
    "ActorNetworkConfig", "AHACConfig", "AHACLearner", "BPTTConfig", "BPTTLearner", "LEARNERS", "LR_SCHEDULES",
    "Learner", "LearnerConfig", "NetworkConfig", "PPOConfig", "PPOLearner", "SACConfig", "SACLearner", "SAPOConfig",
    "SAPOLearner", "SHACConfig", "SHACLearner", "ShortHorizonLearner", "TwinCriticLearner", "lr_scheduler",
    "make_learner", "register_learner",
]
