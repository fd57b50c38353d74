"""Object kinds: one small integer code per kind of surface, stored per triangle and per plane."""

from __future__ import annotations

from types import MappingProxyType
from typing import Final

#: Kind name -> int8 code. ``-1`` is reserved for "no hit" in ray casting results.
KINDS: Final = MappingProxyType(
    {
        "wall": 0,
        "floor": 1,
        "ceiling": 2,
        "lintel": 3,  # underside of an opening's lintel (horizontal, facing down)
        "door": 4,  # door leaf, recessed into the wall
        "door_frame": 5,  # sloped transition between the wall plane and the door leaf
        "board": 6,  # front face of a whiteboard, poster or pin board
        "board_edge": 7,  # the steep edge faces of a board
        "pillar": 8,
        "furniture": 9,
        "clutter": 10,
        "person": 11,  # people in the scene (simulation.people), never part of the mesh
    }
)

#: Code -> kind name.
KIND_NAMES: Final = MappingProxyType({v: k for k, v in KINDS.items()})

NO_HIT: Final = -1


def kind_code(name: str) -> int:
    """The code of a kind name; a ValueError names the unknown kind."""
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"unknown object kind {name!r} (known: {', '.join(KINDS)})") from None
