"""Ray casting: analytic ranges in a box room, plane ids and kinds, door recess, board relief."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from simulation.raycast import Raycaster
from simulation.world import KINDS, World, load_world


def box_world(tmp_path: Path, x0: float = 0.0, y0: float = 0.0, **extra: Any) -> World:
    """A 6 m x 4 m x 2.5 m room with its south-west corner at (x0, y0)."""
    spec: dict[str, Any] = {
        "name": "box",
        "floor_z": 0.0,
        "ceiling_z": 2.5,
        "spaces": [{"name": "room", "rect": [x0, y0, x0 + 6.0, y0 + 4.0]}],
        "walk": {"waypoints": [[x0 + 1.0, y0 + 1.0], [x0 + 5.0, y0 + 3.0]]},
    }
    spec.update(extra)
    path = tmp_path / "box.yaml"
    path.write_text(yaml.safe_dump(spec))
    return load_world(path)


def rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def analytic_box(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exit distance from inside an axis-aligned box, the axis and side (+1: hi face) hit."""
    with np.errstate(divide="ignore"):
        t_hi = (hi - origin) / dirs
        t_lo = (lo - origin) / dirs
    t = np.where(dirs > 0, t_hi, np.where(dirs < 0, t_lo, np.inf))
    axis = np.argmin(t, axis=1)
    rows = np.arange(len(dirs))
    return t[rows, axis], axis, np.where(dirs[rows, axis] > 0, 1, -1)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (4000.0, -2500.0)])
def test_box_room_analytic_ranges_plane_ids_and_kinds(
    tmp_path: Path, offset: tuple[float, float]
) -> None:
    x0, y0 = offset
    w = box_world(tmp_path, x0, y0)
    rc = Raycaster(w)
    # a scanner at a known pose: tilted, its scan plane z = 0, 1081 beams over 270 deg
    T_world_scanner_R = rot(0.3, -0.5, 0.7)
    origin = np.array([x0 + 2.3, y0 + 1.7, 1.2])
    beam = np.radians(-135.0 + 0.25 * np.arange(1081))
    dirs_scanner = np.stack([np.cos(beam), np.sin(beam), np.zeros_like(beam)], axis=1)
    dirs = dirs_scanner @ T_world_scanner_R.T
    hits = rc.cast(np.tile(origin, (len(dirs), 1)), dirs)
    lo, hi = np.array([x0, y0, 0.0]), np.array([x0 + 6.0, y0 + 4.0, 2.5])
    t, axis, side = analytic_box(origin, dirs, lo, hi)
    assert hits.hit.all()
    assert np.abs(hits.range - t).max() < 1e-6
    # the plane hit: its normal points back into the room along the hit axis
    normals = w.plane_normals[hits.plane_id]
    rows = np.arange(len(dirs))
    assert np.array_equal(normals[rows, axis], -side.astype(np.float64))
    expect_kind = np.where(
        axis < 2, KINDS["wall"], np.where(side > 0, KINDS["ceiling"], KINDS["floor"])
    )
    assert np.array_equal(hits.kind, expect_kind)
    np.testing.assert_allclose(hits.cos_incidence, np.abs(dirs[rows, axis]), atol=1e-12)
    # hit points lie on their planes
    pts = origin + hits.range[:, None] * dirs
    assert np.abs(np.einsum("ij,ij->i", pts, normals) + w.plane_d[hits.plane_id]).max() < 1e-9


def test_misses_are_inf_and_minus_one(tmp_path: Path) -> None:
    rc = Raycaster(box_world(tmp_path))
    hits = rc.cast(
        np.array([[10.0, 2.0, 1.0], [3.0, 2.0, 1.0]]), np.array([[1.0, 0, 0], [1.0, 0, 0]])
    )
    assert hits.range[0] == np.inf and hits.plane_id[0] == -1 and hits.kind[0] == -1
    assert hits.cos_incidence[0] == 0.0
    assert hits.range[1] == pytest.approx(3.0, abs=1e-12) and hits.hit[1]
    with pytest.raises(ValueError, match="differ in shape"):
        rc.cast(np.zeros((2, 3)), np.ones((3, 3)))


def test_door_is_recessed_and_board_proud_by_their_configured_depths(tmp_path: Path) -> None:
    recess, frame, thickness = 0.017, 0.05, 0.013
    w = box_world(
        tmp_path,
        doors=[
            {
                "space": "room",
                "side": "north",
                "at": 2.0,
                "width": 0.9,
                "height": 2.05,
                "recess": recess,
                "frame_width": frame,
            }
        ],
        boards=[
            {
                "type": "whiteboard",
                "space": "room",
                "side": "north",
                "at": 4.5,
                "z": 0.9,
                "width": 1.5,
                "height": 1.0,
                "thickness": thickness,
            }
        ],
    )
    rc = Raycaster(w)
    y = 2.0  # the scanner stands 2 m in front of the north wall (y = 4)
    xs = np.array(
        [
            2.0,
            1.8,
            2.4,  # door leaf
            2.0 - 0.45 - frame / 2,  # middle of the left frame slope
            0.5,
            3.2,  # bare wall
            4.5,
            4.0,
            5.1,  # board
        ]
    )
    o = np.column_stack([xs, np.full(len(xs), y), np.full(len(xs), 1.2)])
    d = np.tile([0.0, 1.0, 0.0], (len(xs), 1))
    hits = rc.cast(o, d)
    names = [w.planes[i].kind for i in hits.plane_id]
    assert names == ["door"] * 3 + ["door_frame"] + ["wall"] * 2 + ["board"] * 3
    np.testing.assert_allclose(hits.range[:3], 2.0 + recess, atol=1e-9)
    np.testing.assert_allclose(hits.range[3], 2.0 + recess / 2, atol=1e-9)
    np.testing.assert_allclose(hits.range[4:6], 2.0, atol=1e-9)
    np.testing.assert_allclose(hits.range[6:], 2.0 - thickness, atol=1e-9)
    # the door's top frame and the board's steep edges, seen from below
    up = rc.cast(
        np.array([[2.0, 4.0 + recess / 2 - 1e-4, 1.0], [4.5, 4.0 - thickness / 2, 0.5]]),
        np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
    )
    assert [w.planes[i].kind for i in up.plane_id] == ["door_frame", "board_edge"]
    np.testing.assert_allclose(up.range[1], 0.4, atol=1e-9)  # board bottom edge at z = 0.9


def test_rays_towards_the_door_foot_hit_the_floor_in_the_recess(tmp_path: Path) -> None:
    w = box_world(tmp_path, doors=[{"space": "room", "side": "north", "at": 3.0, "recess": 0.02}])
    rc = Raycaster(w)
    # aim steeply down into the recess strip between the wall plane and the leaf
    target = np.array([[3.0, 4.01, 0.0], [2.7, 4.005, 0.0]])
    o = np.array([[3.0, 3.5, 1.5], [2.7, 3.5, 1.5]])
    d = target - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    hits = rc.cast(o, d)
    assert [w.planes[i].kind for i in hits.plane_id] == ["floor", "floor"]
    np.testing.assert_allclose(o + hits.range[:, None] * d, target, atol=1e-9)
