"""World descriptions: schema errors, compilation, plane labelling, exports, ready worlds."""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from common.config import ConfigError
from simulation.raycast import Raycaster
from simulation.world import (
    KINDS,
    World,
    load_world,
    read_mesh,
    read_planes,
    world_names,
)

READY = ["office", "hall", "corridor", "demo", "calibration", "small_room"]


def room_spec(**extra: Any) -> dict[str, Any]:
    """A 6 m x 4 m box room, 2.5 m high, with a closed walk."""
    spec: dict[str, Any] = {
        "name": "box",
        "floor_z": 0.0,
        "ceiling_z": 2.5,
        "spaces": [{"name": "room", "rect": [0.0, 0.0, 6.0, 4.0]}],
        "walk": {"waypoints": [[1.0, 1.0], [5.0, 1.0], [5.0, 3.0]], "closed": True},
    }
    spec.update(extra)
    return spec


def write(tmp_path: Path, spec: dict[str, Any], name: str = "w.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(spec))
    return p


@cache
def ready(name: str) -> World:
    return load_world(name)


# --- schema and reference errors name the file and the key ------------------------------


@pytest.mark.parametrize(
    ("mutate", "key"),
    [
        (lambda s: s["spaces"][0].update(colour="red"), "spaces.0.colour"),
        (lambda s: s["walk"].update(speed=3.0), "walk.speed"),
        (lambda s: s["spaces"][0].update(rect=[5.0, 0.0, 1.0, 4.0]), "spaces.0.rect"),
        (
            lambda s: s.update(doors=[{"space": "lobby", "side": "north", "at": 3.0}]),
            "doors.0.space",
        ),
        (lambda s: s.update(doors=[{"space": "room", "side": "up", "at": 3.0}]), "doors.0.side"),
        (
            lambda s: s.update(
                boards=[{"space": "room", "side": "north", "at": 3.0, "thickness": 0.1}]
            ),
            "boards.0.thickness",
        ),
        (lambda s: s["walk"].update(stops=[{"waypoint": 9, "duration": 1.0}]), "walk"),
        (lambda s: s.update(ceiling_z=1.0), "ceiling_z"),
        (lambda s: s["walk"]["waypoints"].append([1.0, 1.0]), "walk"),
    ],
)
def test_schema_errors_name_file_and_key(tmp_path: Path, mutate: Any, key: str) -> None:
    spec = room_spec()
    mutate(spec)
    path = write(tmp_path, spec)
    with pytest.raises(ConfigError) as e:
        load_world(path)
    msg = str(e.value)
    assert str(path) in msg and f"'{key}" in msg and "\n" not in msg


def test_walk_clearance_error_names_the_waypoint(tmp_path: Path) -> None:
    spec = room_spec()
    spec["walk"]["waypoints"] = [[1.0, 1.0], [5.7, 1.0], [5.0, 3.0]]  # 0.3 m from the east wall
    with pytest.raises(ConfigError, match=r"'walk\.waypoints\.1'.*0\.30 m"):
        load_world(write(tmp_path, spec))
    spec["walk"]["waypoints"] = [[1.0, 1.0], [5.0, 1.0], [5.0, 3.0]]
    spec["pillars"] = [{"center": [3.0, 1.1], "size": [0.4, 0.4]}]  # on the leg 0 -> 1
    with pytest.raises(ConfigError, match=r"leg from waypoint 0 to 1 leaves free space"):
        load_world(write(tmp_path, spec))
    spec["pillars"] = [{"center": [3.0, 1.5], "size": [0.4, 0.4]}]  # 0.3 m beside the leg
    with pytest.raises(ConfigError, match=r"leg from waypoint 0 to 1 passes 0\.30 m"):
        load_world(write(tmp_path, spec))
    spec["pillars"] = []
    spec["walk"]["waypoints"] = [[1.0, 1.0], [8.0, 1.0], [5.0, 3.0]]  # outside the building
    with pytest.raises(ConfigError, match=r"'walk\.waypoints\.1'.*outside free space"):
        load_world(write(tmp_path, spec))


def test_door_must_lie_on_a_wall(tmp_path: Path) -> None:
    spec = room_spec(doors=[{"space": "room", "side": "north", "at": 5.8, "width": 0.9}])
    with pytest.raises(ConfigError, match=r"'doors\.0\.at'.*not entirely on the wall"):
        load_world(write(tmp_path, spec))


def test_door_recess_deeper_than_the_wall_is_an_error(tmp_path: Path) -> None:
    spec = room_spec(
        spaces=[
            {"name": "room", "rect": [0.0, 0.0, 6.0, 4.0]},
            {"name": "next", "rect": [0.0, 4.01, 6.0, 8.0]},  # a 1 cm wall
        ],
        doors=[{"space": "room", "side": "north", "at": 3.0, "recess": 0.02}],
    )
    with pytest.raises(ConfigError, match=r"'doors\.0\.recess'"):
        load_world(write(tmp_path, spec))


def test_world_by_name_uses_the_configs_env_override(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "worlds").mkdir()
    write(tmp_path / "worlds", room_spec(name="mine"), "mine.yaml")
    monkeypatch.setenv("BACKPACK_SLAM_CONFIGS", str(tmp_path))
    assert load_world("mine").name == "mine"
    with pytest.raises(ConfigError, match="known worlds: mine"):
        load_world("nope")


# --- compilation and plane labelling ------------------------------------------------------


def assert_planes_consistent(w: World) -> None:
    assert [p.id for p in w.planes] == list(range(len(w.planes)))
    assert np.allclose(np.linalg.norm(w.plane_normals, axis=1), 1.0, atol=1e-12)
    tri_pts = w.vertices[w.triangles]  # (T, 3, 3)
    dist = (
        np.einsum("tkj,tj->tk", tri_pts, w.plane_normals[w.tri_plane])
        + w.plane_d[w.tri_plane, None]
    )
    assert np.abs(dist).max() < 1e-9
    # every triangle faces along its plane's normal (wound counter-clockwise from the front)
    e1, e2 = tri_pts[:, 1] - tri_pts[:, 0], tri_pts[:, 2] - tri_pts[:, 0]
    area_n = np.cross(e1, e2)
    assert np.all(np.einsum("tj,tj->t", area_n, w.plane_normals[w.tri_plane]) > 0)
    for p in w.planes:
        assert np.abs(p.distance(p.polygon)).max() < 1e-9
    assert set(np.unique(w.tri_plane)) == set(range(len(w.planes)))  # no empty plane
    assert np.array_equal(w.tri_kind, w.plane_kind[w.tri_plane])


def test_box_room_planes(tmp_path: Path) -> None:
    w = load_world(write(tmp_path, room_spec()))
    assert_planes_consistent(w)
    kinds = sorted(p.kind for p in w.planes)
    assert kinds == ["ceiling", "floor", "wall", "wall", "wall", "wall"]
    np.testing.assert_allclose(w.bounds, np.array([[0.0, 0.0, 0.0], [6.0, 4.0, 2.5]]))


def test_a_wall_split_around_a_door_is_one_plane(tmp_path: Path) -> None:
    spec = room_spec(
        doors=[{"space": "room", "side": "north", "at": 3.0}],
        boards=[{"space": "room", "side": "south", "at": 3.0}],
    )
    w = load_world(write(tmp_path, spec))
    assert_planes_consistent(w)
    north = [p for p in w.planes if p.kind == "wall" and p.normal[1] == -1.0]
    assert len(north) == 1 and np.isclose(north[0].d, 4.0)
    assert sum(p.kind == "door" for p in w.planes) == 1
    assert sum(p.kind == "door_frame" for p in w.planes) == 3
    assert sum(p.kind == "board" for p in w.planes) == 1
    assert sum(p.kind == "board_edge" for p in w.planes) == 4
    assert sum(p.kind == "floor" for p in w.planes) == 1
    # the wall keeps its outline; its triangles leave a hole where the door is
    np.testing.assert_allclose(np.ptp(north[0].polygon, axis=0), np.array([6.0, 0.0, 2.5]))
    cent = w.vertices[w.triangles[w.tri_plane == north[0].id]].mean(axis=1)
    assert not np.any((np.abs(cent[:, 0] - 3.0) < 0.45) & (cent[:, 2] < 2.0))


def test_rooms_joined_by_an_opening_share_the_floor(tmp_path: Path) -> None:
    spec = room_spec(
        spaces=[
            {"name": "room", "rect": [0.0, 0.0, 6.0, 4.0]},
            {"name": "next", "rect": [0.0, 4.2, 6.0, 8.0]},
        ],
        openings=[{"rect": [2.0, 4.0, 3.4, 4.2], "height": 2.1}],
    )
    spec["walk"]["waypoints"] = [[2.7, 2.0], [2.7, 6.0]]
    spec["walk"]["closed"] = False
    w = load_world(write(tmp_path, spec))
    assert_planes_consistent(w)
    assert sum(p.kind == "floor" for p in w.planes) == 1
    assert sum(p.kind == "ceiling" for p in w.planes) == 2
    assert sum(p.kind == "lintel" for p in w.planes) == 1
    # the two reveals of the passage and the walls either side of it
    walls = [p for p in w.planes if p.kind == "wall"]
    assert len(walls) == 2 * 4 + 2


def test_clutter_is_seeded(tmp_path: Path) -> None:
    clutter = {"seed": 5, "count": 4, "size_min": [0.2, 0.2, 0.2], "size_max": [0.5, 0.5, 0.8]}
    spec = room_spec(clutter=clutter)
    a = load_world(write(tmp_path, spec, "a.yaml"))
    b = load_world(write(tmp_path, spec, "b.yaml"))
    spec["clutter"] = {**clutter, "seed": 6}
    c = load_world(write(tmp_path, spec, "c.yaml"))
    assert sum(p.kind == "clutter" for p in a.planes) == 4 * 5
    assert np.array_equal(a.vertices, b.vertices)
    assert not np.array_equal(a.vertices, c.vertices)
    assert_planes_consistent(a)
    spec["clutter"] = {**clutter, "count": 500}
    with pytest.raises(ConfigError, match=r"'clutter\.count'"):
        load_world(write(tmp_path, spec, "d.yaml"))


# --- exports -------------------------------------------------------------------------------


def test_planes_json_round_trip(tmp_path: Path) -> None:
    w = ready("demo")
    path = tmp_path / "gt" / "planes.json"
    w.write_planes(path)
    back = read_planes(path)
    assert len(back) == len(w.planes)
    for a, b in zip(w.planes, back, strict=True):
        assert (a.id, a.kind, a.d) == (b.id, b.kind, b.d)
        assert np.array_equal(a.normal, b.normal) and np.array_equal(a.polygon, b.polygon)
    assert list(path.parent.iterdir()) == [path]  # no temporary left behind
    path.write_text('{"planes": []}')
    with pytest.raises(ValueError, match="not a planes file"):
        read_planes(path)


def test_mesh_ply_round_trip(tmp_path: Path) -> None:
    w = ready("demo")
    path = tmp_path / "mesh.ply"
    w.write_mesh(path)
    m = read_mesh(path)
    assert len(m.triangles) == len(w.triangles)

    def keyed(vertices: np.ndarray, triangles: np.ndarray, plane: np.ndarray) -> np.ndarray:
        tri = np.sort(vertices[triangles].reshape(len(triangles), 9), axis=1)
        rows = np.column_stack([tri, plane])
        return rows[np.lexsort(rows.T[::-1])]

    assert np.array_equal(
        keyed(w.vertices, w.triangles, w.tri_plane), keyed(m.vertices, m.triangles, m.tri_plane)
    )


# --- ready worlds --------------------------------------------------------------------------


def test_ready_worlds_are_listed() -> None:
    assert set(READY) <= set(world_names())


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


@pytest.mark.parametrize("name", READY)
def test_ready_world_is_closed_and_walkable(name: str) -> None:
    w = ready(name)
    assert w.name == name
    assert_planes_consistent(w)
    assert {"wall", "floor", "ceiling"} <= {p.kind for p in w.planes}
    wp = np.asarray(w.walk.waypoints, dtype=np.float64)
    assert w.obstacles is not None
    assert np.all(w.obstacles.clearance(wp) >= 0.5)
    # every horizontal and vertical direction from every waypoint hits something
    ang = np.linspace(0.0, 2 * np.pi, 1440, endpoint=False)
    horiz = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
    a = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    vert = np.concatenate(
        [
            np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], 1),
            np.stack([np.zeros_like(a), np.cos(a), np.sin(a)], 1),
        ]
    )
    dirs = np.concatenate([horiz, vert, fibonacci_sphere(2000)])
    rc = Raycaster(w)
    diag = float(np.linalg.norm(w.bounds[1] - w.bounds[0]))
    for height in (0.3, 1.2, 1.9):
        origins = np.column_stack([wp, np.full(len(wp), w.floor_z + height)])
        o = np.repeat(origins, len(dirs), axis=0)
        d = np.tile(dirs, (len(wp), 1))
        hits = rc.cast(o, d)
        assert hits.hit.all(), f"{name}: {np.count_nonzero(~hits.hit)} rays escaped"
        assert np.all((hits.range > 0) & (hits.range < diag))
        assert set(np.unique(hits.kind)) <= set(KINDS.values())


def test_office_walk_is_a_ten_minute_loop() -> None:
    w = ready("office")
    wp = np.asarray(w.walk.waypoints)
    assert w.walk.closed
    length = float(np.linalg.norm(np.diff(np.vstack([wp, wp[:1]]), axis=0), axis=1).sum())
    minutes = (length / w.walk.speed + sum(s.duration for s in w.walk.stops)) / 60
    assert 8.5 < minutes < 11.0
    assert sum(p.kind == "door" for p in w.planes) >= 20
    assert sum(p.kind == "board" for p in w.planes) >= 20


def test_demo_walk_is_about_a_minute() -> None:
    w = ready("demo")
    wp = np.asarray(w.walk.waypoints)
    length = float(np.linalg.norm(np.diff(np.vstack([wp, wp[:1]]), axis=0), axis=1).sum())
    assert 45 < length / w.walk.speed + sum(s.duration for s in w.walk.stops) < 75
