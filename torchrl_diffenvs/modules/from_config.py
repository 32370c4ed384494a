"""The network builders driven by a learner's ``loss`` configuration section (its network settings)."""
from __future__ import annotations

from collections.abc import Mapping

from torchrl.modules import ValueOperator

from ..envs.multi_agent import policy_keys
from ..normalization import ObservationNormalizer
from .actors import make_actor
from .critics import make_critic, make_qvalue
from .networks import ACTIVATIONS, LeanModule, env_dims

__all__ = ["actor_from_config", "critic_from_config", "network_kwargs", "qvalue_from_config"]


def network_kwargs(section: Mapping) -> dict:
    """``hidden`` / ``activation`` / ``layer_norm`` (/ ``norm_after_activation``, ``init``,
    ``init_log_std``) of a network section as keyword arguments of the builders.

    Args:
        section: a network section (``loss.actor``, ``loss.critic``, ``loss.qvalue``); ``activation``
            is a name of [`ACTIVATIONS`][torchrl_diffenvs.modules.ACTIVATIONS] (default ``"elu"``).
    """
    activation = section.get("activation", "elu")
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation={activation!r}: valid: {', '.join(ACTIVATIONS)}")
    kwargs = {
        "hidden": tuple(int(h) for h in section["hidden"]),
        "activation": ACTIVATIONS[activation],
        "layer_norm": bool(section.get("layer_norm", True)),
    }
    if "init_log_std" in section:
        kwargs["init_log_std"] = float(section["init_log_std"])
    for key, cast in (("norm_after_activation", bool), ("init", str)):
        if key in section:
            kwargs[key] = cast(section[key])
    return kwargs


def actor_from_config(loss_cfg: Mapping, env, return_log_prob: bool = False):
    """The actor a learner trains, from ``loss_cfg.actor`` and ``loss_cfg.obs_norm``.

    Args:
        loss_cfg: the training script's ``loss`` section.
        env: the training env.
        return_log_prob: the actor stores the log-probability of the sampled action (needed by PPO).

    Returns:
        ``(actor, normalizer)``; the normaliser (or ``None``) is the actor's first layer, so
        the actor's ``state_dict`` carries its statistics; pass it on to the critic.
    """
    normalizer = None
    if loss_cfg.get("obs_norm", False):
        observation_dim, _, dtype = env_dims(env, policy_keys(env).observation)
        normalizer = ObservationNormalizer(observation_dim, dtype=dtype).to(env.device)
    actor_cfg = loss_cfg["actor"]
    actor = make_actor(env, **network_kwargs(actor_cfg), distribution=actor_cfg.get("distribution", "tanh_normal"),
                       normalizer=normalizer, return_log_prob=return_log_prob)
    return actor.to(env.device), normalizer


def critic_from_config(section: Mapping, env, normalizer: ObservationNormalizer | None = None,
                       critic_input: str = "observation", centralised: bool = False) -> LeanModule:
    """[`make_critic`][torchrl_diffenvs.modules.make_critic] from a ``loss.critic`` section, sharing the
    actor's normaliser.

    Args:
        section: the ``loss.critic`` section.
        env: the training env.
        normalizer: the actor's normaliser ([`actor_from_config`][torchrl_diffenvs.modules.actor_from_config]'s),
            or ``None``.
        critic_input: ``"observation"`` or ``"state"``, as in [`make_critic`][torchrl_diffenvs.modules.make_critic].
        centralised: a multi-agent critic from every agent's observation (MAPPO), as in
            [`make_critic`][torchrl_diffenvs.modules.make_critic].
    """
    return make_critic(env, **network_kwargs(section), normalizer=normalizer, critic_input=critic_input,
                       centralised=centralised).to(env.device)


def qvalue_from_config(section: Mapping, env, critic_input: str = "observation") -> ValueOperator:
    """[`make_qvalue`][torchrl_diffenvs.modules.make_qvalue] from a ``loss.qvalue`` section.

    Args:
        section: the ``loss.qvalue`` section.
        env: the training env.
        critic_input: ``"observation"`` or ``"state"``, as in [`make_qvalue`][torchrl_diffenvs.modules.make_qvalue].
    """
    return make_qvalue(env, **network_kwargs(section), critic_input=critic_input).to(env.device)
