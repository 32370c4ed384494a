"""The network building blocks: MLPs (single- and multi-agent), the lean TensorDict module that
runs them, and the sizes and dtype the networks take from an env's specs."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.modules import MLP, MultiAgentMLP

__all__ = ["ACTIVATIONS", "NETWORK_INITS", "LeanModule", "env_dims", "make_agent_mlp", "make_mlp", "observation_key_of",
           "orthogonal_init_"]

ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "elu": nn.ELU, "relu": nn.ReLU, "silu": nn.SiLU}
"""The valid ``activation`` names of the networks and their modules."""
NETWORK_INITS = ("default", "orthogonal")
"""The valid ``init`` names of the networks: the layers' own initialisation, or orthogonal."""


class LeanModule(TensorDictModuleBase):
    """Reads ``in_keys``, calls ``module`` on those tensors and writes its output(s) to ``out_keys``.

    What ``tensordict.nn.TensorDictModule`` does for plain tensor outputs, without its
    per-output conversion step, which in tensordict 0.14.3 probes the filesystem for an
    optional package (about 80 us per output tensor, more than a pendulum step costs).
    """

    def __init__(self, module: nn.Module, in_keys: Sequence, out_keys: Sequence):
        super().__init__()
        self.module = module
        self.in_keys = list(in_keys)
        self.out_keys = list(out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        outputs = self.module(*(tensordict.get(key) for key in self.in_keys))
        if isinstance(outputs, torch.Tensor):
            outputs = (outputs,)
        if len(outputs) != len(self.out_keys):
            raise RuntimeError(f"LeanModule: {len(outputs)} outputs for out_keys {self.out_keys}")
        for key, value in zip(self.out_keys, outputs):
            tensordict.set(key, value)
        return tensordict


def orthogonal_init_(module: nn.Module, gain: float) -> None:
    """Every ``nn.Linear`` in ``module`` (nested ones included) gets orthogonal weights of
    ``gain`` and zero biases, in place.

    Args:
        module: the module whose ``nn.Linear`` layers are initialised.
        gain: the orthogonal weights' gain.
    """
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain=gain)
            nn.init.zeros_(layer.bias)


def make_mlp(
    in_dim: int,
    out_dim: int,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    dtype: torch.dtype = torch.float32,
    norm_after_activation: bool = False,
    init: str = "default",
) -> nn.Sequential:
    """``[Linear -> (LayerNorm) -> activation] * len(hidden) -> Linear``: TorchRL's ``MLP``.

    Args:
        in_dim: the input size.
        out_dim: the output size.
        hidden: the hidden layers' widths.
        activation: the hidden layers' activation class.
        layer_norm: a LayerNorm in each hidden layer.
        dtype: the dtype the parameters are created in (float64 networks for gradient checks).
        norm_after_activation: ``True`` gives ``Linear -> activation -> LayerNorm`` per hidden layer
            (the order of DiffRL's SHAC networks), which TorchRL's ``MLP`` cannot build: then a plain
            ``nn.Sequential`` of the same layers.
        init: ``"orthogonal"`` initialises every Linear with orthogonal weights of gain sqrt(2) and
            zero biases (DiffRL's critic); ``"default"`` keeps PyTorch's.
    """
    if init not in NETWORK_INITS:
        raise ValueError(f"make_mlp: init must be one of {NETWORK_INITS}, got {init!r}")
    hidden = [int(width) for width in hidden]
    if not norm_after_activation:
        net = MLP(in_features=in_dim, out_features=out_dim, **_torchrl_mlp_layers(hidden, activation, layer_norm, dtype))
    else:
        layers: list[nn.Module] = []
        for width in hidden:
            layers.append(nn.Linear(in_dim, width, dtype=dtype))
            layers.extend([activation(), nn.LayerNorm(width, dtype=dtype)] if layer_norm else [activation()])
            in_dim = width
        layers.append(nn.Linear(in_dim, out_dim, dtype=dtype))
        net = nn.Sequential(*layers)
    if init == "orthogonal":
        orthogonal_init_(net, math.sqrt(2))
    return net


def _torchrl_mlp_layers(hidden, activation, layer_norm: bool, dtype) -> dict:
    """The hidden-layer arguments of TorchRL's ``MLP`` (and ``MultiAgentMLP``): Linear-(LayerNorm)-activation."""
    norm = {}
    if layer_norm:
        norm = {"norm_class": nn.LayerNorm, "norm_kwargs": [{"normalized_shape": int(w), "dtype": dtype} for w in hidden]}
    return {"num_cells": [int(w) for w in hidden], "activation_class": activation, "layer_kwargs": {"dtype": dtype},
            **norm}


def make_agent_mlp(
    in_dim: int,
    out_dim: int,
    num_agents: int,
    hidden: Sequence[int] = (64, 64),
    activation: type[nn.Module] = nn.ELU,
    layer_norm: bool = True,
    dtype: torch.dtype = torch.float32,
    norm_after_activation: bool = False,
    init: str = "default",
    centralised: bool = False,
) -> MultiAgentMLP:
    """The networks of a multi-agent env: TorchRL's ``MultiAgentMLP`` on ``[..., num_agents, in_dim]``.

    Args:
        in_dim: one agent's input size.
        out_dim: one agent's output size.
        num_agents: the number of agents.
        hidden: the hidden layers' widths.
        activation: the hidden layers' activation class.
        layer_norm: a LayerNorm in each hidden layer (before the activation).
        dtype: the dtype the parameters are created in.
        norm_after_activation: must be ``False``: ``MultiAgentMLP`` is Linear-LayerNorm-activation.
        init: must be ``"default"``: ``MultiAgentMLP`` keeps PyTorch's initialisation.
        centralised: ``False``: each agent's output from its own input, one network shared by the
            agents (a decentralised policy or critic: [`make_mlp`][torchrl_diffenvs.modules.make_mlp] applied
            to every agent). ``True``: each agent's output from every agent's input (MAPPO's centralised
            critic), with one network per agent: a shared one would give every agent the same value,
            which per-agent rewards (``multi_swimmer``'s) do not have.
    """
    if norm_after_activation or init != "default":
        raise ValueError("the multi-agent networks (TorchRL's MultiAgentMLP) are Linear-LayerNorm-activation with "
                         "PyTorch's initialisation: set norm_after_activation=false and init=default")
    return MultiAgentMLP(in_dim, out_dim, num_agents, centralized=centralised, share_params=not centralised,
                         **_torchrl_mlp_layers(hidden, activation, layer_norm, dtype))


def env_dims(env, in_key="observation") -> tuple[int, int, torch.dtype]:
    """``(observation size, action size, float dtype)`` of any TorchRL env the networks are built for.

    Always read from the env's specs: the last dimension and dtype of ``in_key`` in its
    observation spec, and the last dimension of its action spec. For a ``TransformedEnv`` these
    are the *transformed* specs (``CatFrames``, ``CatTensors``, ``DoubleToFloat``,
    ``ObservationNorm``, ...), which is what the networks receive; attributes of a DiffEnv such as
    ``observation_dim`` describe the base env and are forwarded unchanged through a transform.

    Args:
        env: any TorchRL env.
        in_key: the observation entry the networks read.

    Raises:
        ValueError: ``in_key`` is missing or not floating point, or the action dtype differs from
            the observation dtype (the networks compute in one dtype).
    """
    observation = env.observation_spec.get(in_key, None)
    if observation is None:
        raise ValueError(
            f"{type(env).__name__}: the networks read {in_key!r}, which its observation spec lacks (it has "
            f"{sorted(map(str, env.observation_spec.keys()))}); add one with a transform, e.g. "
            f"TransformedEnv(env, CatTensors(in_keys=[...], out_key={in_key!r}, del_keys=False))"
        )
    if not observation.dtype.is_floating_point:
        raise ValueError(f"{type(env).__name__}: {in_key!r} must be floating point, got {observation.dtype}")
    action = env.full_action_spec[env.action_key]
    if action.dtype.is_floating_point and action.dtype != observation.dtype:
        raise ValueError(
            f"{type(env).__name__}: the observation {in_key!r} is {observation.dtype} but the action is "
            f"{action.dtype}; the networks compute in one dtype: cast both, e.g. "
            f"DoubleToFloat(in_keys=[{in_key!r}, 'reward'], in_keys_inv=['action'])"
        )
    return int(observation.shape[-1]), int(action.shape[-1]), observation.dtype


def observation_key_of(policy, default="observation"):
    """The observation entry ``policy`` reads (its only in-key), else ``default``: what a learner
    updates the policy's [`ObservationNormalizer`][torchrl_diffenvs.modules.ObservationNormalizer] from
    (e.g. a key a ``CatTensors`` added).

    Args:
        policy: a TensorDict module (its ``in_keys`` are read), or anything else.
        default: the key returned when ``policy`` has not exactly one in-key.
    """
    in_keys = list(getattr(policy, "in_keys", ()))
    return in_keys[0] if len(in_keys) == 1 else default
