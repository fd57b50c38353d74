"""The choice between parallel planes from the segments' own lines (slam.frontend.parallel_choice)."""

from __future__ import annotations

import numpy as np

from slam.frontend.parallel_choice import HELD, NONE, ChoiceParams, choose, families

WALL, BOARD, FLOOR = 0, 1, 2
# a wall facing -y, a board 2 cm proud of it (nearer the scanner), a floor
NORMALS = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
GAP = 0.02


def _params(sigma_pose: float = 0.004) -> ChoiceParams:
    return ChoiceParams(relative_sigma=0.0015, gate=4.0, ratio=100.0, sigma_pose=sigma_pose, sigma_lever=0.0,
                        walls_only=False, veto=False)


def _scan(on: list[int], offset: float, rng: np.random.Generator) -> tuple[list[list[int]], np.ndarray, np.ndarray]:
    """Segments on the planes ``on`` of one scan whose pose puts them ``offset`` off along the
    wall's normal: every one a candidate of both the wall and the board (the gates widened by the
    pose's uncertainty), their signed distances to both, and their centroid sigmas."""
    k = len(on)
    dist = np.zeros((k, 3))
    for i, p in enumerate(on):
        true_wall = 0.0 if p == WALL else GAP  # the board's points lie 2 cm before the wall (towards the scanner)
        r = true_wall + offset + rng.normal(0.0, 0.0003)
        dist[i, WALL], dist[i, BOARD] = r, r - GAP
    # the nearer plane first (the gates' m2 order)
    cands = [[WALL, BOARD] if abs(d[WALL]) <= abs(d[BOARD]) else [BOARD, WALL] for d in dist]
    return cands, dist, np.full(k, 0.0004)


def test_families_group_parallel_planes_of_one_facing() -> None:
    normals = np.vstack((NORMALS, [[0.0, 1.0, 0.0]], [[np.sin(0.01), -np.cos(0.01), 0.0]]))
    assert families(normals, [0, 1, 2, 3, 4]) == {0: 0, 1: 0, 2: 2, 3: 3, 4: 0}


def test_a_common_pose_offset_beyond_half_the_gap_does_not_swap_wall_and_board() -> None:
    """1.2 cm of pose error along the normal puts the wall's segments nearer the board's plane
    (what the nearest candidate under the gates takes); the scan's segments agree on the offset,
    and each takes its own plane."""
    rng = np.random.default_rng(1)
    on = [WALL, WALL, WALL, BOARD, BOARD]
    cands, dist, sig = _scan(on, 0.012, rng)
    assert all(c[0] == BOARD for c, p in zip(cands, on, strict=True) if p == WALL)  # the old choice: wrong
    ch = choose(cands, dist, sig, np.full(len(on), 100.0), NORMALS, _params())
    np.testing.assert_array_equal(ch.column, on)
    assert ch.grows.all()


def test_a_door_segment_without_its_plane_is_left_to_the_pool() -> None:
    """The door's plane is not made yet: its segment 1.5 cm behind the wall passes the wall's
    gate, but the wall's segments of the scan put the scan's offset at 0: it goes to the pool.
    Alone in its scan it is not taken either (no offset is a hypothesis too)."""
    rng = np.random.default_rng(2)
    k = 4
    dist = np.zeros((k, 3))
    dist[:, WALL] = rng.normal(0.0, 0.0003, k)
    dist[3, WALL] = 0.015
    cands = [[WALL]] * k
    ch = choose(cands, dist, np.full(k, 0.0004), np.full(k, 80.0), NORMALS, _params())
    np.testing.assert_array_equal(ch.column, [WALL, WALL, WALL, NONE])
    alone = choose([[WALL]], dist[3:], np.full(1, 0.0004), np.full(1, 80.0), NORMALS, _params())
    assert alone.column[0] == NONE


def test_a_segment_between_two_near_surfaces_is_held_back() -> None:
    """A poster 6 mm proud of its wall and a segment half way: neither likelihood wins by 100:1;
    the segments on the wall and on the poster are told apart."""
    dist = np.array([[0.0, -0.006, 0.0], [0.003, -0.003, 0.0], [0.006, 0.0, 0.0]])
    cands = [[WALL, BOARD], [WALL, BOARD], [BOARD, WALL]]
    ch = choose(cands, dist, np.full(3, 0.0002), np.full(3, 50.0), NORMALS, _params())
    assert ch.column[1] == HELD and not ch.grows[1]
    assert ch.column[0] == WALL and ch.column[2] == BOARD


def test_families_are_chosen_apart_and_a_lone_candidate_grows() -> None:
    """The floor's segment is its family's only one: taken, and it grows the floor's extent; the
    wall's segments beside the board grow the wall only because the others confirmed the offset."""
    rng = np.random.default_rng(3)
    cands, dist, sig = _scan([WALL, WALL], 0.001, rng)
    cands.append([FLOOR])
    dist = np.vstack((dist, [[0.0, 0.0, 0.0008]]))
    sig = np.append(sig, 0.0004)
    ch = choose(cands, dist, sig, np.full(3, 60.0), NORMALS, _params())
    np.testing.assert_array_equal(ch.column, [WALL, WALL, FLOOR])
    assert ch.grows.all()
    one = choose(cands[:1], dist[:1], sig[:1], np.full(1, 60.0), NORMALS, _params())
    assert one.column[0] == WALL and not one.grows[0]  # the offset rests on this segment alone
