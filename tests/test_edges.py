"""Door/board edges (slam.frontend.edges): break pairs, incidence, clustering, association, merges."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from slam.config import SlamConfig
from slam.frontend.edges import (
    EDGE_ID_BASE,
    Break,
    EdgeMap,
    EdgeParams,
    along_wall,
    bracket_point,
    break_pairs,
    break_sigma,
    is_flat,
    ray_on_line,
    recess_beyond,
    steep_enough,
    step_of,
    steps_within,
    surface_end,
)
from slam.params import edge_params

WALL_N = np.array([0.0, 1.0, 0.0])  # a wall y = 0 facing +y; along it: x


def _params(**changes: Any) -> EdgeParams:
    """The default configuration's edge parameters with ``changes``."""
    return replace(edge_params(SlamConfig()), **changes)


def _break(u: float, serial: int, z: float = 1.5, host: int = 1, step: int = -1, side: int = 1) -> Break:
    p = np.array([u * along_wall(WALL_N)[0], 0.0, z])
    return Break(host, step, side, float(along_wall(WALL_N) @ p), p, p, float(serial) * 0.025, 0.004, serial)


def test_along_wall_is_horizontal_and_in_the_wall() -> None:
    for n in (WALL_N, np.array([0.6, -0.8, 0.0]), np.array([0.6, -0.79, 0.01])):
        e = along_wall(n)
        assert abs(float(np.linalg.norm(e)) - 1.0) < 1e-12
        assert abs(e[2]) < 1e-12 and abs(float(e @ n)) < 1e-12


def test_break_pairs_join_a_wall_and_its_neighbours() -> None:
    # beam order: wall 1 (60 pts), door plane 2 (40), short slope segment (8), wall 1 (50),
    # unassociated (30), wall 7 (20)
    first = np.array([0, 60, 100, 108, 158, 188])
    n_pts = np.array([60, 40, 8, 50, 30, 20])
    ids = np.array([1, 2, -1, 1, -1, 7])
    walls = {1, 7}
    pairs = break_pairs(first, n_pts, ids, walls.__contains__, max_skipped_points=15)
    assert set(pairs) == {(0, 1), (3, 2), (3, 1), (3, 4), (5, 4)}
    # the same segments listed out of beam order give the same pairs
    perm = np.array([3, 0, 5, 1, 4, 2])
    got = break_pairs(first[perm], n_pts[perm], ids[perm], walls.__contains__, max_skipped_points=15)
    assert {(int(perm[a]), int(perm[b])) for a, b in got} == set(pairs)
    # a long segment in between is not skipped
    assert (3, 1) not in break_pairs(first, np.array([60, 40, 30, 50, 30, 20]), ids, walls.__contains__, 15)
    assert break_pairs(first, n_pts, ids, lambda pid: False, 15) == []
    # a door that passed the wall's gates (same id): both orders, the caller picks by distance
    same = break_pairs(np.array([0, 60]), np.array([60, 40]), np.array([1, 1]), walls.__contains__, 15)
    assert set(same) == {(0, 1), (1, 0)}


def test_step_cancels_a_common_offset() -> None:
    wall = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.2]])
    door = np.array([[1.2, -0.015, 1.0], [2.0, -0.015, 1.1]])
    s1, s2 = step_of(WALL_N, wall, door)
    assert abs(s1 + 0.015) < 1e-12 and abs(s2 + 0.015) < 1e-12
    shift = np.array([0.0, 0.02, 0.0])  # the pose 2 cm off across the wall
    assert np.allclose(step_of(WALL_N, wall + shift, door + shift), (s1, s2))


def test_break_sigma_and_incidence() -> None:
    assert abs(break_sigma(0.0, 0.003) - 0.003) < 1e-12
    assert abs(break_sigma(0.12, 0.0) - 0.12 / np.sqrt(12.0)) < 1e-12
    origin = np.array([0.0, 1.0, 1.5])
    assert steep_enough(origin, np.array([0.5, 0.0, 1.5]), WALL_N, 40.0)  # 63 deg from grazing
    assert not steep_enough(origin, np.array([3.0, 0.0, 1.5]), WALL_N, 40.0)  # 18 deg


def test_vertical_edge_clusters_and_top_edge_does_not() -> None:
    em = EdgeMap(_params(min_points=6, min_scans=4, cluster_width=0.02), resolve=lambda i: i)
    rng = np.random.default_rng(0)
    # a jamb at u = 2.0: breaks of 8 scans within +-5 mm, at several heights
    for s in range(8):
        em.pending.append(_break(2.0 + rng.uniform(-0.005, 0.005), s, z=0.5 + 0.2 * s))
    # the door's top edge: breaks spread along the wall at one height
    for s in range(8):
        em.pending.append(_break(3.0 + 0.1 * s, 20 + s, z=2.05, side=-1))
    found = em.cluster()
    assert len(found) == 1
    members, u = found[0]
    assert len(members) == 8 and abs(u - 2.0) < 0.005
    assert len(em.pending) == 8  # the top-edge breaks are left to expire
    em.expire(now=20 * 0.025 + 10.0)
    assert em.pending == []


def test_breaks_at_one_height_cluster_only_from_flat_scanlines() -> None:
    """A tilted scanline nearly parallel to a board's bottom edge puts its breaks close together at
    one height: not a vertical edge. The horizontal scanner's breaks are all at one height too, but
    its scanlines cross the wall flat and can only cross vertical edges."""
    em = EdgeMap(_params(min_points=4, min_scans=3), resolve=lambda i: i)
    for s in range(6):
        em.pending.append(_break(5.0 + 0.002 * s, s, z=0.9))
    assert em.cluster() == []
    em.pending = [replace(b, flat=True) for b in em.pending]
    assert len(em.cluster()) == 1
    assert is_flat(np.array([1.0, 0.0, 0.1]), WALL_N, 0.3)
    assert not is_flat(np.array([1.0, 0.0, 0.7]), WALL_N, 0.3)
    assert not is_flat(np.array([0.0, 1.0, 0.0]), WALL_N, 0.3)  # runs into the wall, not across it


def test_too_few_scans_make_no_edge() -> None:
    em = EdgeMap(_params(min_points=6, min_scans=4), resolve=lambda i: i)
    for k in range(9):
        em.pending.append(_break(2.0, serial=k % 3))  # 9 breaks but 3 scans
    assert em.cluster() == []


def test_match_respects_key_side_and_gate() -> None:
    em = EdgeMap(_params(gate=0.03), resolve=lambda i: {5: 1}.get(i, i))
    e = em.add(1, -1, 1, along_wall(WALL_N), u=2.0, time=0.0)
    assert e.id == EDGE_ID_BASE
    assert em.match(_break(2.01, 0)) is e
    assert em.match(_break(2.01, 0, host=5)) is e  # wall 5 was merged into wall 1
    assert em.match(_break(2.05, 0)) is None  # outside the gate
    assert em.match(_break(2.0, 0, side=-1)) is None  # the door's other edge
    assert em.match(_break(2.0, 0, step=1)) is None  # a board's edge, not a door's
    assert em.match(_break(2.0, 0, host=3)) is None  # another wall


def test_match_with_an_index_follows_merges_and_new_edges() -> None:
    merged: dict[int, int] = {}
    gen = [0]
    em = EdgeMap(_params(gate=0.03), resolve=lambda i: merged.get(i, i), generation=lambda: gen[0])
    e = em.add(1, -1, 1, along_wall(WALL_N), u=2.0, time=0.0)
    assert em.match(_break(2.01, 0)) is e
    assert em.match(_break(2.01, 0, host=5)) is None  # wall 5 is another wall ...
    merged[5] = 1
    gen[0] += 1
    assert em.match(_break(2.01, 0, host=5)) is e  # ... until it is merged into wall 1
    f = em.add(5, -1, 1, along_wall(WALL_N), u=3.0, time=1.0)
    assert em.match(_break(3.01, 0)) is f  # a new edge is found at once
    f.merged_into = e.id
    assert em.match(_break(3.01, 0)) is None  # a merged edge is not matched


def test_the_index_matches_what_testing_every_edge_matches() -> None:
    """Edges added one by one (the index extended), edges merged (left in it, passed over) and
    walls merged (the index rebuilt without the merged edges): every break matches the edge an
    index-free map finds, in a random sequence of them."""
    rng = np.random.default_rng(8)
    merged: dict[int, int] = {}
    gen = [0]
    indexed = EdgeMap(_params(gate=0.05), resolve=lambda i: merged.get(i, i), generation=lambda: gen[0])
    plain = EdgeMap(_params(gate=0.05), resolve=lambda i: merged.get(i, i))
    for step in range(400):
        action = rng.random()
        if action < 0.3:
            host, st, side, u = int(rng.integers(1, 6)), int(rng.choice([-1, 1])), int(rng.choice([-1, 1])), rng.uniform(0, 4)
            for em in (indexed, plain):
                em.add(host, st, side, along_wall(WALL_N), u=float(u), time=float(step))
        elif action < 0.4 and len(indexed.edges) > 1:
            drop, keep = (int(x) for x in rng.choice(list(indexed.edges), 2, replace=False))
            for em in (indexed, plain):
                em.edges[drop].merged_into = keep
        elif action < 0.45:
            a, b = (int(x) for x in rng.choice(np.arange(1, 6), 2, replace=False))
            merged[a] = merged.get(b, b)
            gen[0] += 1
        b = _break(float(rng.uniform(0, 4)), step, host=int(rng.integers(1, 6)), step=int(rng.choice([-1, 1])),
                   side=int(rng.choice([-1, 1])))
        got, want = indexed.match(b), plain.match(b)
        assert (got and got.id) == (want and want.id)


def test_match_keeps_to_the_heights_the_edge_was_seen_at() -> None:
    em = EdgeMap(_params(gate=0.15, height_margin=0.1), resolve=lambda i: i)
    e = em.add(1, -1, 1, along_wall(WALL_N), u=2.0, time=0.0, z_range=(0.5, 1.8))
    assert em.match(_break(2.1, 0, z=1.85)) is e
    top = _break(2.1, 0, z=2.05)  # a break on the door's top edge, 10 cm along it
    assert em.match(top) is None
    top = replace(top, flat=True)  # a flat scanline cannot cross the top edge: it is on the jamb
    assert em.match(top) is e


def test_duplicates_pair_the_same_edge_made_twice() -> None:
    merged: dict[int, int] = {}
    em = EdgeMap(_params(merge_distance=0.25), resolve=lambda i: merged.get(i, i))
    a = em.add(1, -1, 1, along_wall(WALL_N), u=2.0, time=0.0)
    a.n_obs = 40
    b = em.add(3, -1, 1, along_wall(WALL_N), u=2.12, time=5.0)  # the same wall, a second plane
    b.n_obs = 6
    em.add(3, -1, -1, along_wall(WALL_N), u=1.1, time=5.0)  # the door's other side: never paired
    em.add(3, -1, 1, along_wall(WALL_N), u=4.0, time=5.0)  # another door on that wall
    assert em.duplicates() == []  # walls 1 and 3 not merged yet
    merged[3] = 1
    assert em.duplicates() == [(a, b)]
    b.merged_into = a.id
    assert em.root(b.id) == a.id and em.duplicates() == []


def test_ray_on_line_meets_the_line_in_front_only() -> None:
    c, u = np.array([2.0, 1.0]), np.array([1.0, 0.0])  # the line y = 1 (scanner frame)
    q = ray_on_line(np.pi / 4, c, u)
    assert q is not None and np.allclose(q, [1.0, 1.0])
    assert ray_on_line(-np.pi / 4, c, u) is None  # meets it behind the scanner
    assert ray_on_line(0.0, c, u) is None  # parallel


def test_bracket_point_is_unbiased_where_the_last_sample_is_not() -> None:
    """A wall y = 1 ending at x = e, seen by 0.25-degree beams from the origin: the midpoint of the
    last beam's and the next beam's crossings is within half a spacing of the edge and unbiased;
    the last sample itself lies half a spacing short on average."""
    rng = np.random.default_rng(0)
    step = np.radians(0.25)
    c, u = np.array([0.0, 1.0]), np.array([1.0, 0.0])
    err_bracket, err_last, spacings = [], [], []
    for e in rng.uniform(0.8, 2.0, 400):  # the edge ahead at 27-51 deg from grazing
        phase = rng.uniform(0.0, step)
        angles = np.arange(np.pi / 2 - phase, 0.2, -step)  # sweeping from +y towards +x
        x_hit = 1.0 / np.tan(angles)
        k_end = int(np.flatnonzero(x_hit <= e)[-1])
        got = bracket_point(float(angles[k_end]), float(angles[k_end + 1]), c, u)
        assert got is not None
        mid, spacing = got
        assert abs(mid[1] - 1.0) < 1e-12
        assert abs(mid[0] - e) <= 0.5 * spacing + 1e-12
        err_bracket.append(mid[0] - e)
        err_last.append(x_hit[k_end] - e)
        spacings.append(spacing)
    half = 0.5 * float(np.mean(spacings))
    assert abs(float(np.mean(err_bracket))) < 0.1 * half
    assert abs(float(np.mean(err_last)) + half) < 0.1 * half


def test_surface_end_walks_over_beams_still_on_the_surface() -> None:
    """A board y = 1 (scanner frame) ending at x = 1.2, a wall 5 mm behind it: a segment that
    stopped three beams short of the board's edge is extended to its last beam, not onto the wall."""
    angles = np.radians(np.arange(90.0, 30.0, -0.25))
    x_edge = 1.2
    hit_board = 1.0 / np.tan(angles) <= x_edge
    ranges = np.where(hit_board, 1.0 / np.sin(angles), 1.005 / np.sin(angles))
    valid = np.ones(angles.size, dtype=bool)
    last_board = int(np.flatnonzero(hit_board)[-1])
    c, u = np.array([0.5, 1.0]), np.array([1.0, 0.0])
    assert surface_end(last_board - 3, 1, angles, ranges, valid, c, u, 0.0025) == last_board
    assert surface_end(last_board - 3, 1, angles, ranges, valid, c, u, 0.0025, max_beams=2) == last_board - 1
    valid[last_board - 1] = False  # an invalid return ends the walk
    assert surface_end(last_board - 3, 1, angles, ranges, valid, c, u, 0.0025) == last_board - 2


def test_recess_beyond_finds_a_door_left_unsegmented() -> None:
    """A wall y = 1 (scanner frame) up to x = 1.2, a door leaf 12 mm behind it beyond: returns
    past the wall segment's end lie in the recess; a wall that simply goes on, or a corner far
    behind, is no recess."""
    rng = np.random.default_rng(3)
    angles = np.radians(np.arange(90.0, 30.0, -0.25))
    x = 1.0 / np.tan(angles)
    c, u = np.array([0.5, 1.0]), np.array([1.0, 0.0])
    valid = np.ones(angles.size, dtype=bool)
    k_end = int(np.flatnonzero(x <= 1.2)[-1])
    noise = rng.normal(0.0, 0.001, angles.size)
    door = np.where(x <= 1.2, 1.0, 1.012) / np.sin(angles) + noise
    got = recess_beyond(k_end, 1, angles, door, valid, c, u, 0.004, 0.04, 0.08)
    assert got is not None and got[0] == k_end + 1 and abs(got[2] - 0.012) < 0.003
    flat = 1.0 / np.sin(angles) + noise
    assert recess_beyond(k_end, 1, angles, flat, valid, c, u, 0.004, 0.04, 0.08) is None
    deep = np.where(x <= 1.2, 1.0, 1.3) / np.sin(angles)  # a corner 30 cm behind: no door
    assert recess_beyond(k_end, 1, angles, deep, valid, c, u, 0.004, 0.04, 0.5) is None
    valid[k_end + 1 : k_end + 9] = False  # nothing valid beyond: no recess
    assert recess_beyond(k_end, 1, angles, door, valid, c, u, 0.004, 0.04, 0.08) is None


def _wall_scan(rng: np.random.Generator, proud: float, x0: float, x1: float) -> np.ndarray:
    """Returns (scanner frame, beam order) of a wall y = 1.1 with a poster ``proud`` in front of it
    from x0 to x1, 3 mm range noise."""
    angles = np.radians(np.arange(30.0, 150.0, 0.25))
    x = 1.1 / np.tan(angles)
    y = np.where((x > x0) & (x < x1), 1.1 - proud, 1.1)
    r = y / np.sin(angles) + rng.normal(0.0, 0.003, angles.size)
    return np.column_stack((r * np.cos(angles), r * np.sin(angles)))


def test_steps_within_find_a_5_mm_poster_inside_a_wall_segment() -> None:
    """Both edges of a 0.6 m poster 5 mm proud are found, three in four within 2 points (6.5 mm
    along the wall here) of the truth, with the step's sign along the line normal; a plain wall gives no step in 200 noisy scans (false
    alarms), and a 6 cm step is outside the bounds."""
    rng = np.random.default_rng(11)
    u = np.array([-1.0, 0.0])  # beam order runs towards -x
    hits = 0
    for _ in range(100):
        xy = _wall_scan(rng, 0.005, -0.9, -0.3)
        x = xy[:, 0]
        on = (x > -0.9) & (x < -0.3)
        truth = np.flatnonzero(np.diff(on.astype(int)))
        got = steps_within(xy, xy.mean(axis=0), u, 0.003, 25, 0.004, 0.04, 5.0)
        normal = np.array([-u[1], u[0]])  # (0, -1): towards the scanner
        assert all(abs(d) < 0.008 for _, d in got)
        for k, d in got:
            t = truth[np.argmin(np.abs(truth - k))]
            assert abs(k - t) <= 10  # no step away from the poster's edges
            assert (d * normal[1] < 0.0) == bool(on[t + 1])  # onto the poster: nearer the scanner
            hits += int(abs(k - t) <= 2)
    assert hits >= 150  # of 200 edges within 2 points (measured: 9 in 10 found, 8 in 10 within 2 points)
    false = sum(len(steps_within(xy, xy.mean(axis=0), u, 0.003, 25, 0.004, 0.04, 5.0))
                for xy in (_wall_scan(rng, 0.0, 0.0, 0.0) for _ in range(200)))
    assert false <= 2
    big = _wall_scan(rng, 0.06, -0.9, -0.3)
    assert steps_within(big, big.mean(axis=0), u, 0.003, 25, 0.004, 0.04, 5.0) == []
    assert steps_within(big[:40], big[:40].mean(axis=0), u, 0.003, 25, 0.004, 0.04, 5.0) == []
    # a step 30 points from the segment's start: the split keeps half a window on either side
    near = _wall_scan(rng, 0.005, -0.9, -0.3)[270:]
    for k, _ in steps_within(near, near.mean(axis=0), u, 0.003, 25, 0.004, 0.04, 5.0):
        assert k + 1 >= 12 and near.shape[0] - k - 1 >= 12


def test_host_ties_never_make_the_bigger_tied_plane_a_door() -> None:
    """Merges can tie a wall and its door either way round (wall 0 -> door 1 via a merged child
    and door 1 -> wall 0): the plane with more segments stays the wall, so its breaks count; a
    wall's other face is a tie but no child."""
    from slam.frontend.edge_finder import wall_test
    from slam.frontend.map_builder import HostTies, TieKind
    from slam.frontend.planemap import KIND_WALL, PlaneMap

    pmap = PlaneMap(cell_size=0.25)
    n = np.array([0.0, 1.0, 0.0])
    wall = pmap.add(n, -5.0, KIND_WALL, 0.0, 0.0)
    door = pmap.add(n, -4.99, KIND_WALL, 0.0, 0.0)
    other = pmap.add(n, -5.0, KIND_WALL, 0.0, 0.0)
    face = pmap.add(-n, 5.2, KIND_WALL, 0.0, 0.0)
    wall.n_segments, door.n_segments, other.n_segments, face.n_segments = 900, 60, 10, 80
    ties = HostTies(pmap)
    ties.tie(door.id, wall.id, TieKind.DOOR)
    ties.tie(other.id, door.id, TieKind.BOARD)
    ties.tie(face.id, wall.id, TieKind.FACE)
    assert ties.children() == {door.id: wall.id, other.id: door.id}
    pmap.merge(wall.id, other.id)  # a plane once tied to the door is now the wall
    hosts = ties.children()
    assert hosts == {door.id: wall.id}
    assert wall_test(pmap, hosts)(wall.id) and not wall_test(pmap, hosts)(door.id)
    assert wall_test(pmap, hosts)(face.id) and ties.kind_of(face.id) is TieKind.FACE
    assert ties.kind_of(wall.id) is None
