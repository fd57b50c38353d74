"""The local step test of the association (``assoc_kernels.local_steps``, issue 26): a segment a
wall took that lies a step off the wall's neighbouring segments of the same scan goes to the pool."""

from __future__ import annotations

import numpy as np

from slam.frontend.assoc_kernels import local_steps
from slam.frontend.parallel_choice import NONE, ChoiceParams, local_scalars

WALL, DOOR = 7, 9  # plane ids; columns 0 and 1
IDS = np.array([WALL, DOOR], dtype=np.int64)
WALLS = np.array([True, False])
NORMALS = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
SAME = float(np.cos(np.radians(2.0)))


def _scan(spans: list[tuple[float, float, float]], plane: list[int]) -> tuple[np.ndarray, ...]:
    """Segments along a wall y = 0 (world frame), each ``(x0, x1, distance)`` from the wall's plane
    (m), given to ``plane``: the association's output, distances, end points, centroids."""
    k = len(spans)
    ends = np.zeros((k, 2, 3))
    dist = np.zeros((k, 2))
    for s, (x0, x1, d) in enumerate(spans):
        ends[s, 0] = (x0, d, 1.0)
        ends[s, 1] = (x1, d, 1.0)
        dist[s, 0] = d
        dist[s, 1] = d + 0.012  # the door's plane, 12 mm behind the wall
    return np.array(plane, dtype=np.int64), dist, ends, ends.mean(axis=1)


def _run(out: np.ndarray, dist: np.ndarray, ends: np.ndarray, cen: np.ndarray, reach: float = 0.5,
         sigma: float = 0.0003) -> tuple[np.ndarray, np.ndarray, int]:
    out = out.copy()
    grows = np.ones(out.shape[0], dtype=bool)
    k = out.shape[0]
    n = local_steps(out, grows, dist, IDS, WALLS, NORMALS, SAME, ends, cen, np.full(k, sigma), np.full(k, 60.0), reach, 3.0,
                    0.001**2, float(np.radians(0.02)))
    return out, grows, n


def test_a_door_between_wall_segments_goes_to_the_pool_and_the_wall_keeps_its_own() -> None:
    # wall, wall, the door 12 mm behind (no plane yet: the wall took it), wall; the scan 2 mm off
    out, dist, ends, cen = _scan([(0.0, 1.0, 0.002), (1.1, 2.0, 0.0025), (2.1, 3.0, 0.014), (3.1, 4.5, 0.0018)],
                                 [WALL] * 4)
    got, grows, n = _run(out, dist, ends, cen)
    np.testing.assert_array_equal(got, [WALL, WALL, NONE, WALL])
    assert n == 1 and not grows[2] and grows[[0, 1, 3]].all()


def test_a_poster_five_millimetres_proud_is_told_from_its_wall() -> None:
    out, dist, ends, cen = _scan([(0.0, 1.2, 0.0), (1.25, 1.85, -0.005), (1.9, 3.0, 0.0003)], [WALL] * 3)
    got, _, n = _run(out, dist, ends, cen)
    np.testing.assert_array_equal(got, [WALL, NONE, WALL])
    assert n == 1


def test_a_door_holding_most_of_the_scans_points_does_not_send_the_wall_away() -> None:
    # one short wall segment beside a long door segment: the door sets the scan's median, the
    # wall's plane says the wall segment is the wall's
    out, dist, ends, cen = _scan([(0.0, 0.4, 0.001), (0.5, 1.4, 0.013)], [WALL, WALL])
    weight = np.array([20.0, 90.0])
    got = out.copy()
    grows = np.ones(2, dtype=bool)
    n = local_steps(got, grows, dist, IDS, WALLS, NORMALS, SAME, ends, cen, np.full(2, 0.0003), weight, 0.5, 3.0, 0.001**2, 0.0)
    np.testing.assert_array_equal(got, [WALL, WALL])
    assert n == 0


def test_a_step_beyond_the_reach_or_within_the_sigmas_is_left_alone() -> None:
    # the same door, but its nearest wall segment ends 2 m away
    out, dist, ends, cen = _scan([(0.0, 1.0, 0.002), (3.0, 4.0, 0.014)], [WALL, WALL])
    got, _, n = _run(out, dist, ends, cen)
    np.testing.assert_array_equal(got, [WALL, WALL])
    assert n == 0
    # a 2 mm difference is the lines' noise and the wall's flatness
    out, dist, ends, cen = _scan([(0.0, 1.0, 0.0), (1.1, 2.0, 0.002)], [WALL, WALL])
    assert _run(out, dist, ends, cen)[2] == 0


def test_a_rotation_error_along_a_long_wall_is_no_step() -> None:
    # 0.05 deg of heading error: the wall's segments drift off its plane by 0.9 mm per metre
    slope = float(np.tan(np.radians(0.05)))
    spans = [(x, x + 0.9, slope * (x + 0.45)) for x in np.arange(0.0, 12.0, 1.0)]
    out, dist, ends, cen = _scan(spans, [WALL] * len(spans))
    assert _run(out, dist, ends, cen)[2] == 0


def test_segments_on_a_door_or_unassociated_are_not_tested() -> None:
    out, dist, ends, cen = _scan([(0.0, 1.0, 0.0), (1.1, 2.0, 0.012), (2.1, 3.0, 0.012)], [WALL, DOOR, NONE])
    got, _, n = _run(out, dist, ends, cen)
    np.testing.assert_array_equal(got, [WALL, DOOR, NONE])
    assert n == 0


def test_the_test_is_off_without_a_reach_and_in_the_trackings_veto() -> None:
    p = ChoiceParams(relative_sigma=0.0015, gate=4.0, ratio=100.0, sigma_pose=0.002, sigma_lever=0.0, walls_only=False,
                     veto=False, host_sigma=0.0004, host_lever=0.0, host_test=False, model=False,
                     hold_past_child=False, local_reach=0.5, local_gate=3.0, local_sigma=0.002, local_lever=0.0)
    assert local_scalars(p) == (0.5, 3.0, 0.002**2, 0.0)
    assert local_scalars(ChoiceParams(**{**p.__dict__, "veto": True}))[0] == 0.0
    assert local_scalars(ChoiceParams(**{**p.__dict__, "local_reach": 0.0}))[0] == 0.0
    assert local_scalars(None)[0] == 0.0


def test_a_young_duplicate_of_the_wall_counts_as_the_wall() -> None:
    # the first lap of a corridor: the wall's segments on plane 7, its young duplicate 11 (1 mm
    # off, awaiting its merge) took the door's segment; a wall 3 m behind (13) is no neighbour
    ids = np.array([WALL, 11, 13], dtype=np.int64)
    walls = np.array([True, True, True])
    normals = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    out, d, ends, cen = _scan([(0.0, 1.0, 0.001), (1.1, 2.0, 0.013), (2.1, 3.0, 0.0015)], [WALL, 11, WALL])
    dist = np.stack([d[:, 0], d[:, 0] - 0.001, d[:, 0] - 3.0], axis=1)
    grows = np.ones(3, dtype=bool)
    n = local_steps(out, grows, dist, ids, walls, normals, SAME, ends, cen, np.full(3, 0.0003), np.full(3, 60.0), 0.5,
                    3.0, 0.001**2, 0.0)
    np.testing.assert_array_equal(out, [WALL, NONE, WALL])
    assert n == 1
    # a perpendicular wall is not the same wall
    out, d, ends, cen = _scan([(0.0, 1.0, 0.001), (1.1, 2.0, 0.013)], [WALL, 11])
    normals[1] = (1.0, 0.0, 0.0)
    n = local_steps(out, np.ones(2, dtype=bool), np.stack([d[:, 0], d[:, 0], d[:, 0]], axis=1), ids, walls, normals,
                    SAME, ends, cen, np.full(2, 0.0003), np.full(2, 60.0), 0.5, 3.0, 0.001**2, 0.0)
    assert n == 0
