"""Front end pieces: plane creation tolerances and degeneracy-aware tracking (world frame)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from slam.config import SlamConfig
from slam.frontend.plane_init import PlaneInitParams, PooledSegment, SegmentPool, on_plane
from slam.frontend.planemap import PlaneMap, is_other_face, merge_tolerance
from slam.frontend.tracking import freeze_unobserved, orthonormalize, refine_window
from slam.params import plane_init_params
from slam.trajectory.interpolation import (
    interpolate_poses,
    interpolate_trajectory,
    knot_fractions,
    se3_exp,
    se3_inverse,
    se3_log,
)
from slam.trajectory.placement import interval_poses, place_points


def _init_params(**changes: Any) -> PlaneInitParams:
    """The default configuration's plane creation (samples within 15 mm) with ``changes``."""
    return replace(plane_init_params(SlamConfig()), **{"sample_distance": 0.015, **changes})


def _segment(serial: int, y: float, z0: float, x0: float, x1: float, rng: np.random.Generator,
             sigma: float = 0.003, rise: float = 0.5) -> PooledSegment:
    """A slanted line on the wall plane y = const (points scattered by ``sigma`` across it)."""
    s = np.linspace(0.0, 1.0, 12)
    pts = np.column_stack((x0 + (x1 - x0) * s, np.full(12, y), z0 + rise * s))
    pts[:, 1] += rng.normal(0.0, sigma, 12)
    c = pts.mean(axis=0)
    d = pts[-1] - pts[0]
    line = np.array([c - 0.3 * d, c + 0.3 * d])
    line[:, 1] = y  # the fitted line: its offset is known far better than one point's
    return PooledSegment(
        ref=(serial, 0), time=0.01 * serial, scan_serial=serial, centroid=c,
        direction=d / np.linalg.norm(d), endpoints=pts[[0, -1]], samples=pts, line=line,
        scan_normal=np.array([1.0, 0.0, 0.0]), origin=np.array([c[0], 0.0, 1.5]))


def test_a_door_recessed_13_mm_does_not_join_its_wall() -> None:
    rng = np.random.default_rng(3)
    p = _init_params(min_support=4, min_scans=3)
    # the two tilted scanners' lines slant opposite ways across the wall
    wall = [_segment(i, 2.0, 0.2 + 0.1 * i, 0.1 * i, 0.1 * i + 0.8, rng, rise=0.5 if i % 2 else -0.5)
            for i in range(6)]
    door = _segment(9, 2.013, 0.5, 0.3, 1.0, rng)
    n, d = np.array([0.0, -1.0, 0.0]), 2.0
    assert all(on_plane(s, n, d, p) for s in wall)
    assert not on_plane(door, n, d, p)
    pool = SegmentPool(p)
    for s in [*wall, door]:
        pool.add(s)
    planes = pool.create_planes()
    assert len(planes) == 1
    assert door not in planes[0].members and len(planes[0].members) == 6
    assert abs(abs(planes[0].d) - 2.0) < 0.002


def test_tracking_leaves_an_unobserved_direction_to_the_prediction() -> None:
    """A corridor along x: walls (normals +-y), floor and a wall tilted 0.5 deg (its heading
    slightly wrong). Points say the rig sits 5 cm further along x than predicted through that
    tilt only; with the freeze the window stays at the prediction along x."""
    W = 4
    T = np.repeat(np.eye(4)[None], W, axis=0)
    for k in range(W):
        T[k, 0, 3] = 0.05 * k
    tilt = np.radians(0.5)
    planes = [(np.array([0.0, 1.0, 0.0]), -1.1), (np.array([0.0, -1.0, 0.0]), -1.1),
              (np.array([0.0, 0.0, 1.0]), 1.9), (np.array([np.sin(tilt), np.cos(tilt), 0.0]), -1.1)]
    rng = np.random.default_rng(1)
    pts, nrm, off, kis, al = [], [], [], [], []
    for k in range(W - 1):
        for n, d in planes:
            for _ in range(20):
                a = rng.uniform()
                x = 0.05 * (k + a) + rng.uniform(-2.0, 2.0)
                # a point on the plane in the world, seen 5 cm "ahead" for the tilted plane
                p_w = np.array([x, 0.0, 0.0]) + rng.uniform(-0.5, 0.5, 3)
                p_w = p_w - (n @ p_w + d) * n
                p_b = p_w - np.array([0.05 * (k + a), 0.0, 0.0])
                if n[0] != 0.0:
                    p_b[0] -= 0.05
                pts.append(p_b)
                nrm.append(n)
                off.append(d)
                kis.append(k)
                al.append(a)
    args = (np.array(kis), np.array(al), np.array(pts), np.array(nrm), np.array(off),
            np.full(len(pts), 0.001), np.array([np.radians(0.2)] * 3 + [0.01] * 3),
            np.array([0.006] * 3 + [0.002] * 3))
    inc = np.array([np.radians(0.05)] * 3 + [0.001] * 3)
    free = refine_window(T, *args, increment_sigmas=inc)
    frozen = refine_window(T, *args, increment_sigmas=inc, degenerate_ratio=float(np.sin(np.radians(3.0)) ** 2))
    assert np.abs(free[:, 0, 3] - T[:, 0, 3]).max() > 0.005  # the tilt drags the window along x
    assert np.abs(frozen[:, 0, 3] - T[:, 0, 3]).max() < 1e-3


def _refine_window_loops(T_knots: np.ndarray, knot_index: np.ndarray, alphas: np.ndarray, points_body: np.ndarray,
                         normals: np.ndarray, offsets: np.ndarray, sigmas: np.ndarray, first_prior_sigmas: np.ndarray,
                         cv_sigmas: np.ndarray, iterations: int = 3, huber_k: float = 2.0,
                         increment_sigmas: np.ndarray | None = None,
                         degenerate_ratio: float | None = None, freeze_sigma: float = 1e-4) -> np.ndarray:
    """refine_window as it was written before its normal equations were vectorised: one
    logarithm per knot and a Python loop per motion-prior block (the reference of the test below)."""
    W = T_knots.shape[0]
    T = T_knots.copy()
    T_first = T[0].copy()
    w_first = 1.0 / first_prior_sigmas**2
    w_cv = 1.0 / cv_sigmas**2
    T_given = T.copy()
    w_stay = 1.0 / np.array([np.radians(1.0)] * 3 + [0.03] * 3) ** 2
    n = 6 * W
    for _ in range(iterations):
        Tk = interpolate_poses(T[knot_index], T[knot_index + 1], alphas)
        R = Tk[:, :3, :3]
        pw = np.einsum("mij,mj->mi", R, points_body) + Tk[:, :3, 3]
        r = (np.einsum("mi,mi->m", normals, pw) + offsets) / sigmas
        Rtn = np.einsum("mji,mj->mi", R, normals)
        g = np.concatenate((np.cross(points_body, Rtn), Rtn), axis=1) / sigmas[:, None]
        a = np.abs(r)
        w = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
        J = np.zeros((r.shape[0], n))
        rows = np.arange(r.shape[0])[:, None]
        cols = 6 * knot_index[:, None] + np.arange(6)[None, :]
        J[rows, cols] = g * (1.0 - alphas)[:, None]
        J[rows, cols + 6] = g * alphas[:, None]
        A = (J * w[:, None]).T @ J
        b = (J * w[:, None]).T @ r
        for k in range(1, W):
            A[6 * k : 6 * k + 6, 6 * k : 6 * k + 6] += np.diag(w_stay)
            b[6 * k : 6 * k + 6] += w_stay * se3_log(se3_inverse(T_given[k]) @ T[k])
        if degenerate_ratio is not None:  # unchanged: shared
            freeze_unobserved(A, b, T, T_given, normals, w / sigmas**2, degenerate_ratio, freeze_sigma)
        e0 = se3_log(se3_inverse(T_first) @ T[0])
        A[:6, :6] += np.diag(w_first)
        b[:6] += w_first * e0
        terms = []
        if increment_sigmas is not None:
            w_inc = 1.0 / increment_sigmas**2
            for k in range(1, W):
                e = se3_log(se3_inverse(se3_inverse(T_given[k - 1]) @ T_given[k]) @ (se3_inverse(T[k - 1]) @ T[k]))
                terms.append((e, (k - 1, k), (-1.0, 1.0), w_inc))
        else:
            for k in range(1, W - 1):
                e = se3_log(se3_inverse(T[k]) @ T[k + 1]) - se3_log(se3_inverse(T[k - 1]) @ T[k])
                terms.append((e, (k - 1, k, k + 1), (1.0, -2.0, 1.0), w_cv))
        for e, idx, coefs, wt in terms:
            for i, ci in zip(idx, coefs, strict=True):
                b[6 * i : 6 * i + 6] += ci * wt * e
                for j, cj in zip(idx, coefs, strict=True):
                    A[6 * i : 6 * i + 6, 6 * j : 6 * j + 6] += ci * cj * np.diag(wt)
        delta = -np.linalg.solve(A + 1e-9 * np.eye(n), b)
        T = T @ se3_exp(delta.reshape(W, 6))
        if np.abs(delta).max() < 1e-7:
            break
    return np.array([orthonormalize(t) for t in T])


def test_refine_window_matches_the_per_knot_loops() -> None:
    """The compiled normal equations, batched logarithms and block updates of refine_window add
    the same terms as the dense Jacobian and per-knot loops they replaced (in another order):
    the same windows to rounding (1e-12 m / rad), with either motion prior."""
    rng = np.random.default_rng(7)
    W, m = 7, 300
    T = np.repeat(np.eye(4)[None], W, axis=0)
    for k in range(W):
        T[k] = se3_exp(np.concatenate((rng.normal(0.0, 0.02, 3), [0.06 * k, 0.01 * k, 0.0])))
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    kis = rng.integers(0, W - 1, m)
    al = rng.uniform(0.0, 1.0, m)
    pts = rng.uniform(-3.0, 3.0, (m, 3))
    # offsets that put the points 0-2 cm off their planes, a few of them 10 cm (Huber)
    Tk = interpolate_poses(T[kis], T[kis + 1], al)
    pw = np.einsum("mij,mj->mi", Tk[:, :3, :3], pts) + Tk[:, :3, 3]
    off = -np.einsum("mi,mi->m", normals, pw) + rng.normal(0.0, 0.01, m)
    off[:10] += 0.1
    args = (kis, al, pts, normals, off, np.full(m, 0.004), np.array([np.radians(0.2)] * 3 + [0.01] * 3),
            np.array([0.006] * 3 + [0.002] * 3))
    inc = np.array([np.radians(0.05)] * 3 + [0.001] * 3)
    for kw in ({}, {"increment_sigmas": inc}, {"increment_sigmas": inc, "degenerate_ratio": 0.5}):
        np.testing.assert_allclose(refine_window(T, *args, **kw), _refine_window_loops(T, *args, **kw),  # type: ignore[arg-type]
                                   rtol=0.0, atol=1e-12)


def test_extending_a_plane_adds_each_cell_once() -> None:
    pmap = PlaneMap(cell_size=0.25)
    pid = pmap.add(np.array([0.0, 1.0, 0.0]), -2.0, 1, 0.0, 0.0).id
    pts = np.random.default_rng(3).uniform(-1.0, 1.0, (200, 3))
    pmap.extend(pid, pts)
    expected = {tuple(c) for c in np.unique(pmap.cells_of(pid, pts), axis=0).tolist()}
    assert pmap.planes[pid].cells == expected
    assert all(type(v) is int for c in pmap.planes[pid].cells for v in c)
    assert pmap.overlaps(pid, pts[:1], 0) and not pmap.overlaps(pid, pts[:1] + 10.0, 2)


def test_drift_between_sightings_counts_only_the_gap_between_observation_spans() -> None:
    pmap = PlaneMap()
    wall = pmap.add(np.array([0.0, 1.0, 0.0]), -2.0, 1, 0.0, 0.0)
    door = pmap.add(np.array([0.0, 1.0, 0.0]), -1.98, 1, 5.0, 12.0)
    wall.last_seen_odometer = 30.0  # the wall is still being seen while the door is passed
    door.last_seen_odometer = 18.0
    assert pmap.unseen_between(wall.id, door.id) == 0.0
    again = pmap.add(np.array([0.0, 1.0, 0.0]), -2.01, 1, 60.0, 95.0)  # the door's place seen again
    assert pmap.unseen_between(door.id, again.id) == 95.0 - 18.0
    assert pmap.unseen_between(again.id, door.id) == 95.0 - 18.0
    pmap.merge(door.id, again.id)
    assert (door.first_seen_odometer, door.last_seen_odometer) == (12.0, 95.0)


def test_planes_seen_together_merge_only_within_the_coobserved_limit() -> None:
    pmap = PlaneMap(bucket=0.5)
    wall = pmap.add(np.array([1.0, 0.0, 0.0]), -33.075, 1, 100.0, 50.0)
    cabinet = pmap.add(np.array([1.0, 0.0, 0.0]), -33.675, 1, 104.9, 55.0)  # 0.6 m before the wall
    assert not pmap.coobserved(wall.id, cabinet.id)
    pmap.seen(wall.id, 105.1, 55.2)  # the next bucket: [105.0, 105.5) against the cabinet's [104.5, 105.0)
    assert not pmap.coobserved(wall.id, cabinet.id)
    pmap.seen(wall.id, 104.7, 55.1)
    assert pmap.coobserved(wall.id, cabinet.id) and pmap.coobserved(cabinet.id, wall.id)
    assert wall.last_seen_time == 104.7 and wall.last_seen_odometer == 55.1
    # the cabinet seen again 200 m later as a new plane: it merges into the old cabinet (never seen
    # with it, the drift allowance holds) and the survivor stays "seen with the wall"
    again = pmap.add(np.array([1.0, 0.0, 0.0]), -33.70, 1, 320.0, 255.0)
    assert not pmap.coobserved(again.id, wall.id)
    pmap.merge(cabinet.id, again.id)
    assert pmap.coobserved(cabinet.id, wall.id)
    walked = 200.0
    assert merge_tolerance(0.008, 0.003, walked, False, 0.05) == 0.008 + 0.003 * walked
    assert merge_tolerance(0.008, 0.003, walked, True, 0.05) == 0.05  # 0.6 m apart: not merged
    assert merge_tolerance(0.008, 0.003, 1.0, True, 0.05) == 0.008 + 0.003  # below the limit: as before
    assert merge_tolerance(0.008, 0.003, walked, True, 0.001) == 0.008  # never below merge_distance


def test_a_board_seen_beside_its_wall_in_one_scan_is_not_merged_into_it() -> None:
    """The demo's whiteboard (issue 26, session 20): made a plane before its wall had the segments
    to host it (so untied), 18 mm proud; 37 s later the drift-grown merge tolerance (seen together,
    up to merge_coobserved_max) passed 18 mm and the board was folded into the wall with its 1,107
    segments. Once one scan's segments have taken both, they are two surfaces and merge only
    within child_merge_distance; a duplicate of the wall seen instead of it still merges."""
    from types import SimpleNamespace

    from slam.frontend.map_builder import MapBuilder
    from slam.params import map_params

    def scene() -> tuple[MapBuilder, list[tuple[int, int]], int, int]:
        pmap = PlaneMap(bucket=0.5)
        n = np.array([0.0, -1.0, 0.0])
        wall = pmap.add(n, 7.25, 1, 1.0, 0.0)
        board = pmap.add(n, 7.232, 1, 3.0, 2.0)
        xs, zs = np.meshgrid(np.linspace(0.0, 8.0, 40), np.linspace(0.2, 2.6, 12))
        pmap.extend(wall.id, np.column_stack((xs.ravel(), np.full(xs.size, 7.25), zs.ravel())))
        xb, zb = np.meshgrid(np.linspace(2.5, 4.5, 10), np.linspace(0.9, 2.1, 6))
        pmap.extend(board.id, np.column_stack((xb.ravel(), np.full(xb.size, 7.232), zb.ravel())))
        for pl in (wall, board):
            pl.n_segments = 1000
            pmap.seen(pl.id, 37.8, 40.0)
        links: list[tuple[int, int]] = []
        sink = SimpleNamespace(link_planes=lambda keep, drop, *a: links.append((keep, drop)))
        builder = MapBuilder(map_params(SlamConfig()), pmap, None, SimpleNamespace(odometer=45.0), sink,  # type: ignore[arg-type]
                             SimpleNamespace(planes_merged=0))  # type: ignore[arg-type]
        return builder, links, wall.id, board.id

    builder, links, wall, board = scene()
    builder.merge(38.0)  # 45 m walked since the board was made: the tolerance passes 18 mm
    assert links == [(wall, board)] or links == [(board, wall)]
    builder, links, wall, board = scene()
    builder._note_distinct({wall, board})  # one scan's segments on both
    builder.merge(38.0)
    assert links == []
    assert not builder.pmap.planes[board].merged_into >= 0


def test_a_board_grown_along_its_wall_within_a_centimetre_is_merged_as_a_layer_of_it() -> None:
    """The hour's corridor (issue 27, session 25): a plane tied to its wall as a board, 8 mm in front
    of it and grown along the corridor, took the wall's segments, so the door edges along the
    corridor were no longer found and the walk slid 1 m. A tied plane longer than child_max_length
    (6 m) and within layer_merge_distance (12 mm) of its wall is merged into the wall (the wall
    kept); a board 1.8 or 5 m long 8 mm proud, or a long one 2 cm proud, stays; with
    layer_merge_distance 0 none is."""
    from types import SimpleNamespace

    from slam.frontend.map_builder import MapBuilder, TieKind
    from slam.params import map_params

    def scene(offset: float, x1: float, cfg: SlamConfig) -> tuple[MapBuilder, list[tuple[int, int]], int, int, Any]:
        pmap = PlaneMap(bucket=0.5)
        n = np.array([0.0, -1.0, 0.0])
        wall = pmap.add(n, 7.25, 1, 1.0, 0.0)
        layer = pmap.add(n, 7.25 - offset, 1, 3.0, 2.0)
        xs, zs = np.meshgrid(np.linspace(0.0, 12.0, 60), np.linspace(0.2, 2.6, 12))
        pmap.extend(wall.id, np.column_stack((xs.ravel(), np.full(xs.size, 7.25), zs.ravel())))
        xb, zb = np.meshgrid(np.linspace(2.0, x1, 30), np.linspace(0.9, 2.1, 6))
        pmap.extend(layer.id, np.column_stack((xb.ravel(), np.full(xb.size, 7.25 - offset), zb.ravel())))
        for pl in (wall, layer):
            pl.n_segments = 1000
            pmap.seen(pl.id, 37.8, 40.0)
        layer.n_segments = 800  # fewer than its wall (else the tie is read the other way round)
        links: list[tuple[int, int]] = []
        sink = SimpleNamespace(link_planes=lambda keep, drop, *a: links.append((keep, drop)))
        stats = SimpleNamespace(planes_merged=0, wall_layers_merged=0)
        builder = MapBuilder(map_params(cfg), pmap, None, SimpleNamespace(odometer=45.0), sink,  # type: ignore[arg-type]
                             stats)  # type: ignore[arg-type]
        builder.ties.tie(layer.id, wall.id, TieKind.BOARD)
        return builder, links, wall.id, layer.id, stats

    cfg = SlamConfig()
    builder, links, wall, layer, stats = scene(0.008, 10.0, cfg)  # 8 m long, 8 mm proud
    builder.merge(38.0)
    assert links == [(wall, layer)]  # the wall is kept
    assert builder.pmap.planes[layer].merged_into == wall
    assert stats.wall_layers_merged == 1 and stats.planes_merged == 1
    for offset, x1 in ((0.008, 3.8), (0.008, 7.0), (0.02, 10.0)):  # a board; a 5 m board; a long one 2 cm proud
        builder, links, wall, layer, stats = scene(offset, x1, cfg)
        builder.merge(38.0)
        assert links == [] and stats.wall_layers_merged == 0
    off = cfg.model_copy(update={"frontend": cfg.frontend.model_copy(update={"layer_merge_distance": 0.0})})
    builder, links, wall, layer, stats = scene(0.008, 10.0, off)
    builder.merge(38.0)
    assert links == []


def test_the_other_face_of_a_wall_faces_away_and_lies_its_thickness_behind() -> None:
    # the corridor's face of a partition: y = 6.15, seen from the corridor (normal +y)
    wall_n, wall_d = np.array([0.0, 1.0, 0.0]), -6.15
    rng = np.random.default_rng(0)
    room_face = np.column_stack((rng.uniform(15.0, 21.0, 50), np.full(50, 6.0), rng.uniform(0.0, 2.8, 50)))
    facing_room = np.array([0.0, -1.0, 0.0])
    cos_min, thick = np.cos(np.radians(6.0)), (0.05, 0.3)
    assert is_other_face(wall_n, wall_d, facing_room, room_face, cos_min, thick)
    # the same points seen from the corridor side: a door or board, not the other face
    assert not is_other_face(wall_n, wall_d, wall_n, room_face, cos_min, thick)
    # a cabinet's back 0.5 m behind: too far for a wall
    assert not is_other_face(wall_n, wall_d, facing_room, room_face - np.array([0.0, 0.5, 0.0]), cos_min, thick)
    # a door leaf's two faces (4 cm): too thin
    assert not is_other_face(wall_n, wall_d, facing_room, room_face + np.array([0.0, 0.11, 0.0]), cos_min, thick)
    # 10 degrees off opposite
    tilted = np.array([np.sin(np.radians(10.0)), -np.cos(np.radians(10.0)), 0.0])
    assert not is_other_face(wall_n, wall_d, tilted, room_face, cos_min, thick)


def test_placing_points_per_knot_interval_matches_interpolate_trajectory() -> None:
    """slam.trajectory.placement takes one rotation logarithm per knot interval (compiled): the same world
    points and poses as interpolate_trajectory's pose per point, to rounding (1e-12 m)."""
    rng = np.random.default_rng(5)
    kt = 10.0 + 0.05 * np.arange(12)
    T = np.array([se3_exp(np.concatenate((rng.normal(0.0, 0.3, 3), rng.normal(0.0, 1.0, 3)))) for _ in kt])
    times = np.sort(rng.uniform(kt[0], kt[-1], 500))
    times[-1] = kt[-1]
    pts = rng.uniform(-5.0, 5.0, (500, 3))
    Tw = interpolate_trajectory(kt, T, times)
    expected = np.einsum("mij,mj->mi", Tw[:, :3, :3], pts) + Tw[:, :3, 3]
    np.testing.assert_allclose(place_points(kt, T, times, pts), expected, rtol=0.0, atol=1e-12)
    idx, alpha = knot_fractions(kt, times)
    R, t = interval_poses(T, idx, alpha)
    np.testing.assert_allclose(R, Tw[:, :3, :3], rtol=0.0, atol=1e-14)
    np.testing.assert_allclose(t, Tw[:, :3, 3], rtol=0.0, atol=1e-12)
    # a point's world position does not depend on the batch it is placed with
    np.testing.assert_array_equal(place_points(kt, T, times[7:9], pts[7:9]), place_points(kt, T, times, pts)[7:9])


def test_plane_map_rows_follow_estimates_merges_and_sightings() -> None:
    """The association's plane rows are cached, yet always those of the current map."""
    from slam.frontend.planemap import KIND_FLOOR, KIND_WALL, PlaneMap

    pm = PlaneMap()
    a = pm.add(np.array([1.0, 0.0, 0.0]), -2.0, KIND_WALL, 0.0, 0.0)
    b = pm.add(np.array([0.0, 0.0, 1.0]), 0.0, KIND_FLOOR, 0.0, 0.0)
    rows, horizontal = pm.active_rows()
    assert rows.shape == (2, 12) and horizontal.tolist() == [False, True]
    np.testing.assert_allclose(rows[0, :4], [1.0, 0.0, 0.0, -2.0])
    pm.set_estimate(a.id, np.array([1.0, 0.01, 0.0]), -2.1)
    a.last_seen_odometer = 7.5
    rows, _ = pm.active_rows()
    np.testing.assert_allclose(rows[0, 3], -2.1)
    assert rows[0, 5] == 7.5 and rows[0, 1] > 0.0
    c = pm.add(np.array([1.0, 0.0, 0.0]), -2.11, KIND_WALL, 1.0, 1.0)
    assert pm.active_rows()[0].shape == (3, 12)
    pm.merge(a.id, c.id)
    rows, horizontal = pm.active_rows()
    assert [p.id for p in pm.active_planes()] == [a.id, b.id] and rows.shape == (2, 12)
    assert horizontal.tolist() == [False, True]


def _level_line(serial: int, z: float, scan_normal: np.ndarray, rng: np.random.Generator) -> PooledSegment:
    """A level line along (1, -1, 0)/sqrt 2 at height ``z`` through (0, 2, z), as a scanner whose
    scan plane has ``scan_normal`` sees it (points scattered by 3 mm within the line's plane)."""
    u = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    s = np.linspace(-0.4, 0.4, 15)
    pts = np.array([0.0, 2.0, z]) + s[:, None] * u
    pts[:, 2] += rng.normal(0.0, 0.003, s.size) * 0.1
    c = pts.mean(axis=0)
    return PooledSegment(
        ref=(serial, 0), time=0.01 * serial, scan_serial=serial, centroid=c, direction=u,
        endpoints=pts[[0, -1]], samples=pts, line=np.array([c - 0.3 * u, c + 0.3 * u]),
        scan_normal=scan_normal / np.linalg.norm(scan_normal), origin=np.array([-1.0, 0.0, 1.5]))


def test_the_wall_hypothesis_takes_level_scan_planes_only() -> None:
    """Standing still, a tilted scanner sees one level line on a table top again and again: it
    lies on the table as much as on the vertical plane through it, so it makes no wall. The
    level scanner's repeated lines on a wall it faces do (kept vertical by a prior)."""
    rng = np.random.default_rng(4)
    p = _init_params(min_support=4, min_scans=3)
    tilted = np.array([0.66, 0.66, 0.34])  # 20 deg from vertical, its level direction along (1, -1, 0)
    table = SegmentPool(p)
    for i in range(8):
        table.add(_level_line(i, 0.75, tilted, rng))
    assert table.create_planes() == []
    wall = SegmentPool(p)
    for i in range(8):
        wall.add(_level_line(i, 1.9, np.array([0.0, 0.0, 1.0]), rng))
    planes = wall.create_planes()
    assert len(planes) == 1 and planes[0].vertical_hypothesis
    np.testing.assert_allclose(np.abs(planes[0].normal), [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-3)


def _scan(scan_index: int, stamp: float, first: list[int], t_end: float) -> Any:
    """A stand-in for ``ScanSegments`` with what the queues read (scanner 0, beams from ``stamp`` to ``t_end``)."""
    from types import SimpleNamespace

    k = len(first)
    return SimpleNamespace(scanner=0, scan_index=scan_index, stamp=stamp, n_segments=k,
                           first_beam=np.array(first), last_beam=np.array(first) + 5,
                           times=np.linspace(stamp, t_end, 2))


def test_scan_queues_hand_scans_on_and_keep_their_rows() -> None:
    """Pending scans become ready once their last beam is past; compacted scans keep their
    segment rows, reported sorted with plane ids resolved through the merges."""
    from slam.frontend.pending import ScanQueues

    q = ScanQueues()
    q.add(_scan(1, 0.1, [50, 10], 0.2), {})
    q.add(_scan(0, 0.0, [30], 0.35), {(0, 1): None})
    assert q.last_end() == 0.35
    ready = q.take_ready(0.3)
    assert [p.serial for p in ready] == [0] and [p.serial for p in q.pending] == [1]
    assert q.pending[0].edge_tests == {(0, 1): None}
    ready[0].plane_ids[:] = (7, -1)
    q.done.extend(ready)
    assert q.track(ready, 0.15) == ready and q.track([], 0.25) == []
    q.compact(horizon=0.25)
    assert q.done == [] and q.by_serial() == {}
    rows = q.segment_rows(lambda pid: {7: 3}.get(pid, pid))
    np.testing.assert_array_equal(rows["scan_index"], [0, 1, 1])
    np.testing.assert_array_equal(rows["first_beam"], [30, 10, 50])
    np.testing.assert_array_equal(rows["plane_id"], [-1, -1, 3])


def test_knot_mirror_grows_holds_a_prediction_and_walks() -> None:
    from slam.frontend.knots import KnotMirror

    m = KnotMirror(0.05)
    m.start(10.0, None)
    for k in range(1100):  # past the first allocation
        T = np.eye(4)
        T[0, 3] = 0.01 * k
        assert m.append(T) == k
    assert m.n == 1100 and m.time(1100) == pytest.approx(65.0)
    assert m.odometer == pytest.approx(10.99)
    np.testing.assert_array_equal(m.V[:1100], 0.0)
    T_pred = np.eye(4)
    T_pred[0, 3] = 11.0
    m.hold(T_pred)
    assert m.n == 1101 and m.pose_at(m.time(1100))[0, 3] == pytest.approx(11.0)
    m.release()
    assert m.n == 1100 and m.odometer == pytest.approx(10.99)
    np.testing.assert_allclose(m.place(np.zeros((2, 3)), np.array([10.0, 10.025])), [[0, 0, 0], [0.005, 0, 0]],
                               atol=1e-12)
    pts = np.ones((3, 3))
    assert m.deskewed(pts, np.zeros(3)) is pts  # no deskew table


def test_optional_features_share_their_interfaces() -> None:
    """The runner holds either object of each pair without asking which."""
    from slam.frontend.edge_tracker import EdgeTracker, NoEdges
    from slam.frontend.motion_model import ConstantVelocity
    from slam.imu_feed import ImuMotion

    def public(cls: type) -> set[str]:
        return {n for n in dir(cls) if not n.startswith("_") and callable(getattr(cls, n))}

    assert public(EdgeTracker) == public(NoEdges)
    assert public(ImuMotion) == public(ConstantVelocity)
    assert {"predict", "initial_pose", "add_factors", "refresh", "velocity"} <= public(ConstantVelocity)
