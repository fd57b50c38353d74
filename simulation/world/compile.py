"""Compile a :class:`WorldSpec` into a :class:`World` mesh (world frame, metres).

Walls, floors, ceilings and opening reveals come from the boundary of the free space
(``grid``); doors, boards and boxes are added as separate parts (``parts``). Every
problem is a ConfigError naming the file and the key.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from common.config import ConfigError
from simulation.world import grid as g
from simulation.world.clearance import (
    PlanObstacles,
    check_walk,
    inside_convex,
    point_segment_distance,
    polygon_segments,
    walk_samples,
)
from simulation.world.kinds import KINDS
from simulation.world.mesh import MeshBuilder
from simulation.world.model import World
from simulation.world.parts import OVERLAP, WallFrame, add_board, add_box, add_door, box_footprint
from simulation.world.spec import Board, Door, Space, WorldSpec

#: Attempts per clutter object before giving up.
CLUTTER_ATTEMPTS = 500


def wall_of(space: Space, side: str) -> WallFrame:
    """The wall surface on ``side`` of a space, facing into the space."""
    x0, y0, x1, y1 = space.rect
    return {
        "west": WallFrame(axis=0, coord=x0, sign=+1),
        "east": WallFrame(axis=0, coord=x1, sign=-1),
        "south": WallFrame(axis=1, coord=y0, sign=+1),
        "north": WallFrame(axis=1, coord=y1, sign=-1),
    }[side]


def _wall_view(mask: NDArray[np.bool_], axis: int) -> NDArray[np.bool_]:
    """View of a vertical face mask indexed (along-wall, z); writes go through."""
    return mask if axis == 0 else mask.T  # UV_AXES: axis 0 -> (y, z), axis 1 -> (z, x)


def _cells_overlapping(coords: NDArray[np.float64], lo: float, hi: float) -> tuple[int, int]:
    """Cell index range [i0, i1) of cells that overlap the open interval (lo, hi)."""
    i0 = int(np.searchsorted(coords, lo, side="right")) - 1
    i1 = int(np.searchsorted(coords, hi, side="left"))
    return max(i0, 0), min(i1, len(coords) - 1)


def _door_hole(door: Door, floor_z: float) -> tuple[float, float, float]:
    """Hole in the wall surface: along-wall [lo, hi] and top z (shrunk by OVERLAP)."""
    half = door.width / 2 + door.frame_width - OVERLAP
    return door.at - half, door.at + half, floor_z + door.height + door.frame_width - OVERLAP


def _check_references(spec: WorldSpec, source: str) -> list[float]:
    """Cross-field checks pydantic cannot do; returns the ceiling z per space."""
    names = [s.name for s in spec.spaces]
    seen: set[str] = set()
    for i, n in enumerate(names):
        if n in seen:
            raise ConfigError(f"{source}: key 'spaces.{i}.name': duplicate space name {n!r}")
        seen.add(n)
    ceilings = []
    for i, s in enumerate(spec.spaces):
        c = spec.ceiling_z if s.ceiling_z is None else s.ceiling_z
        if c <= spec.floor_z + 1.5:
            key = "ceiling_z" if s.ceiling_z is None else f"spaces.{i}.ceiling_z"
            raise ConfigError(f"{source}: key '{key}': ceiling {c} m must be > floor_z + 1.5 m")
        ceilings.append(c)
    groups: list[tuple[str, list[Door] | list[Board]]] = [
        ("doors", spec.doors),
        ("boards", spec.boards),
    ]
    for key, items in groups:
        for i, it in enumerate(items):
            if it.space not in seen:
                raise ConfigError(f"{source}: key '{key}.{i}.space': unknown space {it.space!r}")
    if spec.clutter is not None:
        for i, n in enumerate(spec.clutter.spaces or []):
            if n not in seen:
                raise ConfigError(f"{source}: key 'clutter.spaces.{i}': unknown space {n!r}")
    return ceilings


def compile_world(spec: WorldSpec, source: str) -> World:
    """Build the mesh, planes and plan obstacles of ``spec``; validate the walk."""
    fz = spec.floor_z
    ceilings = _check_references(spec, source)
    space_by_name = {s.name: s for s in spec.spaces}

    boxes = [[*s.rect[:2], fz, *s.rect[2:], c] for s, c in zip(spec.spaces, ceilings, strict=True)]
    boxes += [[*o.rect[:2], fz, *o.rect[2:], fz + o.height] for o in spec.openings]
    extra: tuple[list[float], list[float], list[float]] = ([], [], [])
    door_walls = [wall_of(space_by_name[d.space], d.side) for d in spec.doors]
    for d, w in zip(spec.doors, door_walls, strict=True):
        lo, hi, top = _door_hole(d, fz)
        extra[w.h_axis].extend([lo, hi])
        extra[2].append(top)
    grid = g.build_grid(np.asarray(boxes, dtype=np.float64), extra)
    slices = {(fs.axis, fs.index, fs.sign): fs for fs in g.boundary_slices(grid)}

    def wall_slice(w: WallFrame, key: str) -> g.FaceSlice:
        fs = slices.get((w.axis, grid.index(w.axis, w.coord), w.sign))
        if fs is None:
            raise ConfigError(f"{source}: key '{key}': that side of the space has no wall")
        return fs

    # doors: cut holes in the wall surfaces
    for i, (d, w) in enumerate(zip(spec.doors, door_walls, strict=True)):
        key = f"doors.{i}"
        lo, hi, top = _door_hole(d, fz)
        if top > ceilings[spec.spaces.index(space_by_name[d.space])] - 0.01:
            raise ConfigError(f"{source}: key '{key}.height': door and frame reach the ceiling")
        view = _wall_view(wall_slice(w, f"{key}.side").mask, w.axis)
        h0, h1 = grid.cell_range(w.h_axis, lo, hi)
        z0, z1 = grid.cell_range(2, fz, top)
        if not view[h0:h1, z0:z1].all():
            raise ConfigError(
                f"{source}: key '{key}.at': door at {d.at} on the {d.side} wall of {d.space!r} is "
                "not entirely on the wall (it overlaps an opening, another door, a corner or the "
                "wall's end)"
            )
        view[h0:h1, z0:z1] = False
        behind = np.stack(
            [
                w.point(h, fz + zz, d.recess + 1e-3)
                for h in np.linspace(lo, hi, 5)
                for zz in (0.05, d.height / 2, d.height - 0.05)
            ]
        )
        if grid.is_free(behind).any():
            raise ConfigError(
                f"{source}: key '{key}.recess': the wall behind the door is thinner than the "
                f"recess ({d.recess} m)"
            )

    # boards must sit on wall
    board_walls = [wall_of(space_by_name[b.space], b.side) for b in spec.boards]
    for i, (b, w) in enumerate(zip(spec.boards, board_walls, strict=True)):
        key = f"boards.{i}"
        view = _wall_view(wall_slice(w, f"{key}.side").mask, w.axis)
        h0, h1 = _cells_overlapping(grid.coords[w.h_axis], b.at - b.width / 2, b.at + b.width / 2)
        z0, z1 = _cells_overlapping(grid.coords[2], fz + b.z, fz + b.z + b.height)
        if h1 <= h0 or z1 <= z0 or not view[h0:h1, z0:z1].all():
            raise ConfigError(
                f"{source}: key '{key}.at': board at {b.at} on the {b.side} wall of {b.space!r} "
                "is not entirely on the wall (it overlaps an opening, a door, a corner, the "
                "ceiling or the wall's end)"
            )

    mb = MeshBuilder()
    ceiling_set = {round(c, g.DECIMALS) for c in ceilings}
    component_plane: dict[tuple[int, int, int], tuple[np.ndarray, dict[int, int]]] = {}
    for skey, fs in slices.items():
        labels, n = g.label_components(fs.mask)
        if n == 0:
            continue
        if fs.axis == 2:
            if fs.sign > 0:
                kind = "floor"
            else:
                kind = "ceiling" if round(fs.coord, g.DECIMALS) in ceiling_set else "lintel"
        else:
            kind = "wall"
        normal = np.zeros(3)
        normal[fs.axis] = fs.sign
        ids: dict[int, int] = {}
        u_ax, v_ax = g.UV_AXES[fs.axis]
        for c in range(1, n + 1):
            cells = labels == c
            loop = g.outer_loop(cells)
            poly = np.zeros((len(loop), 3))
            poly[:, fs.axis] = fs.coord
            poly[:, u_ax] = grid.coords[u_ax][loop[:, 0]]
            poly[:, v_ax] = grid.coords[v_ax][loop[:, 1]]
            if fs.sign < 0:
                poly = poly[::-1]
            pid = mb.add_plane(normal, poly[0], kind, poly)
            tris = g.slice_quads(grid, fs, cells)
            uniq, inv = np.unique(tris, return_inverse=True)
            mb.add_triangles(g.grid_points(grid, uniq), inv.reshape(-1, 3), pid)
            ids[c] = pid
        component_plane[skey] = (labels, ids)

    floor_key = (2, grid.index(2, fz), +1)

    def floor_plane_at(x: float, y: float) -> int:
        labels, ids = component_plane[floor_key]
        i = int(np.searchsorted(grid.coords[0], x, side="right")) - 1
        j = int(np.searchsorted(grid.coords[1], y, side="right")) - 1
        return ids[int(labels[i, j])]

    for d, w in zip(spec.doors, door_walls, strict=True):
        front = w.point(d.at, fz, -0.05)
        add_door(
            mb,
            w,
            d.at,
            d.width,
            d.height,
            d.recess,
            d.frame_width,
            fz,
            floor_plane_at(front[0], front[1]),
        )

    footprints: list[NDArray[np.float64]] = []
    keepouts: list[tuple[NDArray[np.float64], float]] = []  # (centre, radius) for clutter
    for d, w in zip(spec.doors, door_walls, strict=True):
        keepouts.append((w.point(d.at, fz, 0.0)[:2], d.width / 2 + d.frame_width + 0.8))
    for b, w in zip(spec.boards, board_walls, strict=True):
        add_board(mb, w, b.at, fz + b.z, b.width, b.height, b.thickness)
        p0, p1 = (
            w.point(b.at - b.width / 2, 0, 0)[:2],
            w.point(b.at + b.width / 2, 0, -b.thickness)[:2],
        )
        bl, tr = np.minimum(p0, p1), np.maximum(p0, p1)
        footprints.append(
            np.array([[bl[0], bl[1]], [tr[0], bl[1]], [tr[0], tr[1]], [bl[0], tr[1]]])
        )
        keepouts.append(((bl + tr) / 2, b.width / 2 + 0.3))

    def column_top(xy: NDArray[np.float64]) -> float:
        i = int(np.searchsorted(grid.coords[0], xy[0], side="right")) - 1
        j = int(np.searchsorted(grid.coords[1], xy[1], side="right")) - 1
        k = np.flatnonzero(grid.free[i, j, :])
        return float(grid.coords[2][k.max() + 1])

    plan = PlanObstacles.from_grid(grid, fz)

    def check_inside(fp: NDArray[np.float64], key: str) -> None:
        centre = fp.mean(axis=0)
        shrunk = centre + (fp - centre) * (
            1 - 1e-3 / max(np.linalg.norm(fp - centre, axis=1).max(), 1e-9)
        )
        if not plan.is_free(np.vstack([shrunk, centre])).all():
            raise ConfigError(f"{source}: key '{key}': the object is not inside free space")

    for i, p in enumerate(spec.pillars):
        fp = box_footprint(p.center, p.size, p.yaw_deg)
        check_inside(fp, f"pillars.{i}.center")
        add_box(
            mb,
            fp,
            fz - OVERLAP,
            column_top(fp.mean(axis=0)) + OVERLAP,
            "pillar",
            bottom=False,
            top=False,
        )
        footprints.append(fp)
        keepouts.append((fp.mean(axis=0), float(np.linalg.norm(fp[0] - fp[2]) / 2)))
    for i, f in enumerate(spec.furniture):
        fp = box_footprint(f.center, f.size[:2], f.yaw_deg)
        check_inside(fp, f"furniture.{i}.center")
        h = f.size[2]
        if fz + h > column_top(fp.mean(axis=0)) - 0.01:
            raise ConfigError(f"{source}: key 'furniture.{i}.size': taller than the room")
        if f.type == "table":
            if f.top_thickness >= h or 2 * f.leg_size >= min(f.size[:2]):
                raise ConfigError(f"{source}: key 'furniture.{i}': table top or legs too large")
            add_box(mb, fp, fz + h - f.top_thickness, fz + h, "furniture")
            inset = np.array([f.size[0] / 2 - f.leg_size / 2, f.size[1] / 2 - f.leg_size / 2])
            cy, sy_ = math.cos(math.radians(f.yaw_deg)), math.sin(math.radians(f.yaw_deg))
            for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                lx, ly = sx * inset[0], sy * inset[1]
                centre = [f.center[0] + cy * lx - sy_ * ly, f.center[1] + sy_ * lx + cy * ly]
                leg = box_footprint(centre, [f.leg_size, f.leg_size], f.yaw_deg)
                add_box(
                    mb,
                    leg,
                    fz - OVERLAP,
                    fz + h - f.top_thickness + OVERLAP,
                    "furniture",
                    bottom=False,
                    top=False,
                )
        else:
            add_box(mb, fp, fz - OVERLAP, fz + h, "furniture", bottom=False)
        footprints.append(fp)
        keepouts.append((fp.mean(axis=0), float(np.linalg.norm(fp[0] - fp[2]) / 2)))

    if spec.clutter is not None and spec.clutter.count > 0:
        for fp, h in _place_clutter(spec, source, keepouts):
            add_box(mb, fp, fz - OVERLAP, fz + h, "clutter", bottom=False)
            footprints.append(fp)

    obstacles = plan.with_footprints(footprints)
    check_walk(spec.walk, obstacles, source)

    vertices, triangles, tri_plane = mb.build()
    kinds = np.array([KINDS[p.kind] for p in mb.planes], dtype=np.int8)
    return World(
        name=spec.name,
        vertices=vertices,
        triangles=triangles,
        tri_plane=tri_plane,
        tri_kind=kinds[tri_plane],
        planes=mb.planes,
        walk=spec.walk,
        floor_z=fz,
        ceiling_z=spec.ceiling_z,
        bounds=np.stack([vertices.min(axis=0), vertices.max(axis=0)]),
        spec=spec,
        obstacles=obstacles,
    )


def _place_clutter(
    spec: WorldSpec, source: str, keepouts: list[tuple[NDArray[np.float64], float]]
) -> list[tuple[NDArray[np.float64], float]]:
    """Seeded random boxes (footprint, height) clear of the walk, objects, doors and boards."""
    cl = spec.clutter
    assert cl is not None
    rng = np.random.default_rng(cl.seed)
    spaces = [s for s in spec.spaces if cl.spaces is None or s.name in cl.spaces]
    path, _ = walk_samples(spec.walk)
    need = spec.walk.clearance + 0.05
    smin, smax = np.asarray(cl.size_min), np.asarray(cl.size_max)
    circles = list(keepouts)
    out: list[tuple[NDArray[np.float64], float]] = []
    for n in range(cl.count):
        for _ in range(CLUTTER_ATTEMPTS):
            sp = spaces[int(rng.integers(len(spaces)))]
            size = rng.uniform(smin, smax)
            yaw = float(rng.uniform(0.0, 180.0))
            r = float(np.hypot(size[0], size[1]) / 2)
            x0, y0, x1, y1 = sp.rect
            m = r + 0.02
            if x1 - x0 <= 2 * m or y1 - y0 <= 2 * m:
                continue
            centre = rng.uniform([x0 + m, y0 + m], [x1 - m, y1 - m])
            if any(np.linalg.norm(centre - c) < r + rc + 0.05 for c, rc in circles):
                continue
            fp = box_footprint(list(centre), list(size[:2]), yaw)
            near = np.linalg.norm(path - centre, axis=1) < r + need
            if near.any():
                pts = path[near]
                if inside_convex(pts, fp).any():
                    continue
                if point_segment_distance(pts, polygon_segments(fp)).min() < need:
                    continue
            circles.append((centre, r))
            out.append((fp, float(size[2])))
            break
        else:
            raise ConfigError(
                f"{source}: key 'clutter.count': placed only {n} of {cl.count} clutter objects "
                "clear of the walk, doors, boards and other objects; lower the count or sizes"
            )
    return out
