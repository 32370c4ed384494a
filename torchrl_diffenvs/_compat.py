"""Every use of TorchRL's and tensordict's private names, in one fenced module.

The rest of the package touches only public APIs; what it needs beyond them is here, with why.
Checked against the versions in :data:`CHECKED_VERSIONS`; ``tests/test_compat.py`` exercises
each assumption and fails loudly on a version where one breaks.
"""
from __future__ import annotations

from tensordict import TensorDict

__all__ = ["CHECKED_VERSIONS", "collector_carrier_state", "load_collector_carrier"]

CHECKED_VERSIONS = {"torchrl": "0.14.1", "tensordict": "0.14.3"}


# ---------------------------------------------------------------------- collector state
def collector_carrier_state(collector) -> dict | None:
    """The env TensorDict a TorchRL ``Collector`` will step from next, as plain tensors.

    TorchRL's ``Collector.state_dict`` leaves out the in-flight env state ("not generally
    serializable"); our envs keep their whole state in that TensorDict, so saving it lets a
    resumed run continue the same episodes. It lives in the private ``_carrier`` attribute;
    ``None`` (resume then starts fresh episodes) if a future TorchRL renames it.
    """
    carrier = getattr(collector, "_carrier", None)
    if carrier is None:
        return None
    carrier = carrier.exclude("collector")
    return {"batch_size": list(carrier.batch_size), "data": carrier.to_dict()}


def load_collector_carrier(collector, state: dict | None) -> None:
    """Restores :func:`collector_carrier_state` (no-op for ``None``)."""
    carrier = getattr(collector, "_carrier", None)
    if state is not None and carrier is not None:
        carrier.update(TensorDict(state["data"], batch_size=state["batch_size"], device=carrier.device))
