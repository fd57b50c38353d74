"""The world description schema (``configs/worlds/<name>.yaml``), validated with pydantic.

All coordinates are in the world frame, metres, z up; plan coordinates ``[x, y]``.
Heights given as ``z``/``height`` are measured from ``floor_z`` unless said otherwise.

Free space is the union of ``spaces`` (floor to ceiling) and ``openings`` (floor to
their height); everything else is solid, so the gap between two spaces is a wall of
that thickness and an opening's rectangle spanning the gap is a passage through it.
A wall is addressed as the ``side`` of a space: ``west``/``east`` are the walls at the
space's x-min/x-max, ``south``/``north`` at its y-min/y-max; ``at`` is the coordinate
along that wall (y for west/east, x for south/north).
"""

from __future__ import annotations

from itertools import pairwise
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from common.config import StrictModel

Side = Literal["west", "east", "south", "north"]
Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Rect = Annotated[list[float], Field(min_length=4, max_length=4)]


def _check_rect(v: list[float]) -> list[float]:
    x0, y0, x1, y1 = v
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"rect must be [x0, y0, x1, y1] with x1 > x0 and y1 > y0, got {v}")
    return v


class Space(StrictModel):
    """A room or corridor: an axis-aligned free rectangle from the floor to its ceiling."""

    name: str
    rect: Rect
    ceiling_z: float | None = Field(None, description="overrides the world's ceiling_z (m)")

    _rect = field_validator("rect")(_check_rect)


class Opening(StrictModel):
    """A passage without a door leaf: a free box from the floor to ``height``."""

    rect: Rect
    height: float = Field(2.1, gt=0.5)

    _rect = field_validator("rect")(_check_rect)


class WallPlacement(StrictModel):
    """Common fields of things placed on a wall of a space."""

    space: str
    side: Side
    at: float = Field(description="centre coordinate along the wall (m)")


class Door(WallPlacement):
    """A closed door: the leaf recessed into the wall, with sloped frame transitions."""

    width: float = Field(0.9, ge=0.5, le=2.5)
    height: float = Field(2.05, ge=1.5, le=3.0)
    recess: float = Field(0.015, ge=0.003, le=0.05, description="leaf depth behind the wall (m)")
    frame_width: float = Field(
        0.04, ge=0.01, le=0.15, description="width of the sloped transition (m)"
    )


class Board(WallPlacement):
    """A whiteboard, poster or pin board standing proud of the wall, with steep edges."""

    type: Literal["whiteboard", "poster", "pinboard"] = "whiteboard"
    z: float = Field(0.9, ge=0.0, description="bottom edge above the floor (m)")
    width: float = Field(1.5, gt=0.05)
    height: float = Field(1.0, gt=0.05)
    thickness: float = Field(0.015, ge=0.003, le=0.03, description="proud of the wall (m)")


class Pillar(StrictModel):
    """A floor-to-ceiling box pillar."""

    center: Vec2
    size: Vec2
    yaw_deg: float = 0.0

    @field_validator("size")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if min(v) <= 0:
            raise ValueError(f"sizes must be > 0, got {v}")
        return v


class Furniture(StrictModel):
    """A cupboard or box (a solid box on the floor) or a table (top slab on four legs)."""

    type: Literal["cupboard", "table", "box"]
    center: Vec2
    size: Vec3 = Field(description="[length x, width y, height z] before yaw (m)")
    yaw_deg: float = 0.0
    top_thickness: float = Field(0.03, gt=0, description="table top (m)")
    leg_size: float = Field(0.05, gt=0, description="square table legs (m)")

    @field_validator("size")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if min(v) <= 0:
            raise ValueError(f"sizes must be > 0, got {v}")
        return v


class Clutter(StrictModel):
    """Seeded random boxes on the floor, kept clear of the walk, doors and boards."""

    seed: int
    count: int = Field(ge=0)
    size_min: Vec3 = Field(default_factory=lambda: [0.2, 0.2, 0.2])
    size_max: Vec3 = Field(default_factory=lambda: [0.8, 0.6, 1.2])
    spaces: list[str] | None = Field(None, description="names of spaces to fill (default all)")

    @model_validator(mode="after")
    def _sizes(self) -> Clutter:
        if min(self.size_min) <= 0 or any(
            a > b for a, b in zip(self.size_min, self.size_max, strict=True)
        ):
            raise ValueError("need 0 < size_min <= size_max")
        return self


class Stop(StrictModel):
    waypoint: int = Field(ge=0)
    duration: float = Field(gt=0, description="s")


class Walk(StrictModel):
    """The operator's walk: waypoints at floor level (world frame), speed, stops."""

    waypoints: list[Vec2] = Field(min_length=2)
    speed: float = Field(1.2, ge=1.0, le=1.5, description="m/s")
    stops: list[Stop] = Field(default_factory=list)
    closed: bool = Field(False, description="return to the first waypoint at the end")
    clearance: float = Field(0.5, ge=0.5, description="min distance to walls and objects (m)")

    @model_validator(mode="after")
    def _stops(self) -> Walk:
        wp = self.waypoints
        pairs = list(pairwise(wp))
        if self.closed:
            pairs.append((wp[-1], wp[0]))
        for i, (a, b) in enumerate(pairs):
            if a == b:
                raise ValueError(
                    f"waypoints.{(i + 1) % len(wp)}: same point as the one before it {a} "
                    "(closed walks return to the start by themselves)"
                )
        for i, s in enumerate(self.stops):
            if s.waypoint >= len(self.waypoints):
                raise ValueError(
                    f"stops.{i}.waypoint: {s.waypoint} out of range "
                    f"(there are {len(self.waypoints)} waypoints)"
                )
        return self


class WorldSpec(StrictModel):
    """A building: floor plan, heights, openings, doors, boards, objects and a walk."""

    name: str
    description: str = ""
    floor_z: float = 0.0
    ceiling_z: float = Field(2.8, description="default ceiling height (world z, m)")
    spaces: list[Space] = Field(min_length=1)
    openings: list[Opening] = Field(default_factory=list)
    doors: list[Door] = Field(default_factory=list)
    boards: list[Board] = Field(default_factory=list)
    pillars: list[Pillar] = Field(default_factory=list)
    furniture: list[Furniture] = Field(default_factory=list)
    clutter: Clutter | None = None
    walk: Walk
