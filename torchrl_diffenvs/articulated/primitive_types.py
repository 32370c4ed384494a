"""The types every collision primitive takes and returns (see
[`primitives`][torchrl_diffenvs.articulated.primitives]): the geoms of one type posed in the
world, a pair's candidate contacts, a table entry, and a box's corners."""
from __future__ import annotations

from typing import Callable, NamedTuple

import torch

__all__ = ["PairContacts", "PosedGeoms", "Primitive", "box_corners", "one_contact"]


class PosedGeoms(NamedTuple):
    """``P`` geoms of one type in ``N`` configurations: world ``pos [N, P, 3]`` and ``rot [N, P, 3, 3]``
    (MuJoCo's geom_xpos, geom_xmat), and ``size [P, 3]`` (MuJoCo's geom_size)."""

    pos: torch.Tensor
    rot: torch.Tensor
    size: torch.Tensor


class PairContacts(NamedTuple):
    """The ``K`` candidate contacts of each of ``P`` pairs: ``dist [N, P, K]`` (negative:
    penetrating), ``pos [N, P, K, 3]`` (midway between the surfaces), ``normal [N, P, K, 3]`` (from
    geom 1 to geom 2), ``tangent [N, P, K, 3]`` (the frame's first tangent before it is made
    orthogonal; zero: MuJoCo's default), ``found [N, P, K]`` (the contact's points exist, mostly at
    any distance: capsule-capsule's second exists only where the axes are parallel,
    capsule-cylinder's second only where MuJoCo's multi-contact makes it, in touch)."""

    dist: torch.Tensor
    pos: torch.Tensor
    normal: torch.Tensor
    tangent: torch.Tensor
    found: torch.Tensor


class Primitive(NamedTuple):
    """One geom-pair type's collision function and the contacts it gives a pair at most."""

    contacts: int  # K, the contacts each pair gives at most
    collide: Callable[[PosedGeoms, PosedGeoms, torch.Tensor], PairContacts]  # (geom1, geom2, margin [P])


def one_contact(dist, pos, normal) -> PairContacts:
    """A primitive's single contact per pair, with MuJoCo's default tangent.

    Args:
        dist: ``[N, P]`` the signed distances (negative: penetrating).
        pos: ``[N, P, 3]`` the contact points.
        normal: ``[N, P, 3]`` the normals, from geom 1 to geom 2.

    Returns:
        [`PairContacts`][torchrl_diffenvs.articulated.primitive_types.PairContacts] with ``K = 1``, ``found``
        everywhere.
    """
    return PairContacts(dist[..., None], pos[..., None, :], normal[..., None, :], torch.zeros_like(pos)[..., None, :],
                        torch.ones_like(dist, dtype=torch.bool)[..., None])


def box_corners(like: torch.Tensor) -> torch.Tensor:
    """The signs ``[8, 3]`` of a box's corners in MuJoCo's order (corner ``i``: + along axis ``k``
    where bit ``k`` of ``i`` is set), made on ``like``'s device (a tensor built from Python
    numbers is a host-to-device copy, a synchronisation on CUDA).

    Args:
        like: a tensor whose device and dtype the signs take.
    """
    corner, axis = torch.arange(8, device=like.device).unsqueeze(-1), torch.arange(3, device=like.device)
    return (2 * torch.bitwise_and(torch.bitwise_right_shift(corner, axis), 1) - 1).to(like.dtype)
