"""The choice between parallel planes from the segments' own lines (slam.frontend.parallel_choice)."""

from __future__ import annotations

import numpy as np

from slam.frontend.parallel_choice import HELD, NONE, ChoiceParams, choose, families

WALL, BOARD, FLOOR = 0, 1, 2
# a wall facing -y, a board 2 cm proud of it (nearer the scanner), a floor
NORMALS = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
GAP = 0.02
# the configuration's host-test defaults (slam.config: host_sigma, host_lever_deg, host_test)
HOST_OFF = {"host_sigma": 0.0004, "host_lever": float(np.radians(0.015)), "host_test": False, "model": False,
            "hold_past_child": False, "local_reach": 0.0, "local_gate": 3.0, "local_sigma": 0.001, "local_lever": 0.0}


def _params(sigma_pose: float = 0.004) -> ChoiceParams:
    return ChoiceParams(relative_sigma=0.0015, gate=4.0, ratio=100.0, sigma_pose=sigma_pose, sigma_lever=0.0,
                        walls_only=False, veto=False, **HOST_OFF)


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


def _office_params() -> ChoiceParams:
    """The defaults (``slam.params.gates``): the pose-widened relative sigma with its 0.05 deg lever."""
    return ChoiceParams(relative_sigma=0.0015, gate=4.0, ratio=100.0, sigma_pose=0.002,
                        sigma_lever=float(np.radians(0.05)), walls_only=False, veto=False, **HOST_OFF)


def test_a_wall_does_not_take_the_segments_of_a_door_it_has_no_plane_for() -> None:
    """The office walk's mechanism (issue 26): a door 10 mm behind its wall, its plane not a
    candidate (not made yet, or the segment runs past its extent across the door's edge). The
    scan's wall segments fix its offset at 0; at 3 m the relative gate (4 sigmas of the lever-
    widened sigma: 12 mm) takes the door's segment 10 mm off, and the one straddling the door's
    edge 6 mm off, onto the wall. The host test of the wall holds both back; the wall's own far
    segment 1 mm off stays; a floor (not a host) keeps its old gate."""
    rng = np.random.default_rng(4)
    k = 6
    dist = np.zeros((k, 3))
    dist[:4, WALL] = rng.normal(0.0, 0.0003, 4)
    dist[3, WALL] = 0.001
    dist[4, WALL] = -0.010  # the door's segment
    dist[5, WALL] = -0.006  # across the door's edge: two thirds on the door, a third on the wall
    cands = [[WALL]] * k
    sig = np.full(k, 0.0008)
    ranges = np.full(k, 3.0)
    old = choose(cands, dist, sig, np.full(k, 80.0), NORMALS, _office_params(), ranges)
    np.testing.assert_array_equal(old.column, [WALL] * k)  # without the host test: the wall takes all
    hosts = np.array([True, False, False])
    ch = choose(cands, dist, sig, np.full(k, 80.0), NORMALS, _office_params(), ranges, hosts)
    np.testing.assert_array_equal(ch.column, [WALL, WALL, WALL, WALL, HELD, HELD])
    assert not ch.grows[4:].any()
    floor_dist = np.zeros((k, 3))
    floor_dist[:, FLOOR] = dist[:, WALL]
    fl = choose([[FLOOR]] * k, floor_dist, sig, np.full(k, 80.0), NORMALS, _office_params(), ranges, hosts)
    assert (fl.column == FLOOR).all()


def test_the_host_test_leaves_the_choice_between_a_wall_and_its_board_alone() -> None:
    """With the board's plane a candidate the likelihood ratio decides as before: the host test
    only refuses the wall a segment its own line puts off it."""
    rng = np.random.default_rng(5)
    on = [WALL, WALL, WALL, BOARD, BOARD]
    cands, dist, sig = _scan(on, 0.003, rng)
    ch = choose(cands, dist, sig, np.full(len(on), 100.0), NORMALS, _office_params(), np.full(len(on), 2.0),
                np.array([True, False, False]))
    np.testing.assert_array_equal(ch.column, on)


def _model_params() -> ChoiceParams:
    """The office parameters with the leave-one-out model (``frontend.choice_lever_model``)."""
    p = _office_params()
    return ChoiceParams(**{**p.__dict__, "model": True})


def test_a_lone_segment_does_not_set_the_offset_it_is_judged_by() -> None:
    """The small room (issue 26, session 20): a wall's segment at 5.7 m, alone in its family in
    its scan, 10.6 mm off its wall and 9.4 mm off the board in front. Its own distance became the
    scan's offset, so it looked certain to be the board's; judged by the others (none: the prior)
    it fits both and is held back."""
    dist = np.array([[0.0106, -0.0094, 0.0]])
    cands = [[WALL, BOARD]]
    sig, rng_ = np.full(1, 0.0008), np.full(1, 5.74)
    old = choose(cands, dist, sig, np.full(1, 59.0), NORMALS, _office_params(), rng_)
    assert old.column[0] == BOARD
    arm = np.array([[2.0, 5.38, 0.0]])
    for a in (None, arm):
        assert choose(cands, dist, sig, np.full(1, 59.0), NORMALS, _model_params(), rng_, arm=a).column[0] == HELD


def test_a_board_beside_its_placed_wall_is_not_the_wall_at_range() -> None:
    """A board 19 mm proud at 5.3 m, its plane not made yet, beside three wall segments the scan
    has placed on the wall. The rotation's lever added to every segment's sigma (0.05 deg: 4.6 mm
    at 5.3 m) lets the wall take it; modelled across the scan, the rotation moves segments a metre
    apart by under a millimetre relative to each other, so the board's segment fits no plane and
    goes to the pool, where it makes the board's plane. The wall's segments stay."""
    dist = np.array([[-0.0004, 0.0, 0.0], [0.0003, 0.0, 0.0], [-0.0001, 0.0, 0.0], [0.0191, 0.0, 0.0]])
    cands = [[WALL]] * 4
    sig = np.full(4, 0.0008)
    arm = np.array([[1.5, 5.3, 0.0], [2.5, 5.3, 0.0], [-1.5, 5.3, 0.0], [0.5, 5.28, 0.0]])
    ranges = np.linalg.norm(arm, axis=1)
    w = np.full(4, 69.0)
    old = choose(cands, dist, sig, w, NORMALS, _office_params(), ranges)
    np.testing.assert_array_equal(old.column, [WALL] * 4)
    ch = choose(cands, dist, sig, w, NORMALS, _model_params(), ranges, arm=arm)
    np.testing.assert_array_equal(ch.column, [WALL, WALL, WALL, NONE])
    # without positions the lever stays in each sigma: the wall takes it as before
    np.testing.assert_array_equal(choose(cands, dist, sig, w, NORMALS, _model_params(), ranges).column, [WALL] * 4)


def test_a_door_segment_past_the_doors_extent_is_held_not_given_to_the_wall() -> None:
    """The small room's door (issue 26, session 20): a door segment 12.5 mm behind the wall and
    1.5 mm off the door's plane, running past the extent the door's plane has so far. Without the
    door as a candidate the wall took it (its rotation-widened gate at 3.6 m); as a shadow
    candidate (``frontend.hold_past_child_extent``) the choice puts it on the door and so holds it
    back: neither the wall's nor growing the door past what it has seen."""
    from slam.frontend.parallel_choice import choose_pairs

    door = BOARD  # a column parallel to the wall, 14 mm behind it here
    dist = np.array([[0.0, -0.014, 0.0], [0.0003, -0.0141, 0.0], [-0.0002, -0.0139, 0.0], [-0.0125, 0.0015, 0.0]])
    start = np.array([0, 2, 4, 6, 8])
    cols = np.array([WALL, door] * 4)
    sig, ranges = np.full(4, 0.0009), np.full(4, 3.6)
    keep_extent = np.array([True, False] * 4)  # no segment lies within the door's young extent
    without = choose_pairs(start, cols, keep_extent, dist, sig, np.full(4, 30.0), NORMALS, _office_params(), ranges)
    np.testing.assert_array_equal(without.column, [WALL, WALL, WALL, WALL])
    shadow = ~keep_extent
    held = choose_pairs(start, cols, np.ones(8, dtype=bool), dist, sig, np.full(4, 30.0), NORMALS, _office_params(),
                        ranges, shadow=shadow)
    np.testing.assert_array_equal(held.column, [WALL, WALL, WALL, HELD])
    assert not held.grows[3]
    # kept as a plain candidate it would be the door's, and grow it
    kept = choose_pairs(start, cols, np.ones(8, dtype=bool), dist, sig, np.full(4, 30.0), NORMALS, _office_params(),
                        ranges)
    assert kept.column[3] == door
