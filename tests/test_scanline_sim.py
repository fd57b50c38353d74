"""The synthetic scanline ray caster: geometry, labels, timing and seeding."""

from __future__ import annotations

import numpy as np
import pytest

from simulation.scanline import ScannerSpec, World2D, figure1, random_room, run_labels, scan


def _square_room(half: float = 4.0) -> World2D:
    c = [(-half, -half), (half, -half), (half, half), (-half, half)]
    return World2D.from_pieces([(f"wall_{i}", [c[i], c[(i + 1) % 4]]) for i in range(4)])


def test_noise_free_ranges_match_analytic_wall_distances() -> None:
    half = 4.0
    x0, y0, heading = 0.7, -1.2, 0.3
    s = scan(_square_room(half), (x0, y0, heading), ScannerSpec(noise_sigma=0.0))
    a = s.angles + heading
    c, sn = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (half - x0) / c, np.where(c < 0, (-half - x0) / c, np.inf))
        ty = np.where(sn > 0, (half - y0) / sn, np.where(sn < 0, (-half - y0) / sn, np.inf))
    np.testing.assert_allclose(s.ranges, np.minimum(tx, ty), rtol=0, atol=1e-9)
    np.testing.assert_allclose(s.true_ranges, s.ranges, atol=0)


def test_scanner_geometry_and_per_beam_times() -> None:
    s = scan(_square_room(), t0=12.5)
    assert s.n_beams == 1081
    assert np.isclose(s.angles[0], np.deg2rad(-135.0)) and np.isclose(s.angles[-1], np.deg2rad(135.0))
    np.testing.assert_allclose(np.diff(s.times), 0.025 / 1440)
    assert s.times[0] == 12.5
    assert (s.range_min, s.range_max) == (0.1, 30.0)


def test_noise_level_and_quantisation() -> None:
    s = scan(_square_room(), scanner=ScannerSpec(noise_sigma=0.003), seed=3)
    err = s.ranges - s.true_ranges
    assert 0.0027 < np.std(err) < 0.0033
    q = scan(_square_room(), scanner=ScannerSpec(noise_sigma=0.003, quantization=0.001), seed=3)
    np.testing.assert_allclose(q.ranges * 1000, np.round(q.ranges * 1000), atol=1e-6)


def test_misses_beyond_range_max_are_inf_and_unlabelled() -> None:
    world = World2D.from_pieces([("far", [(40.0, -50.0), (40.0, 50.0)]), ("near", [(5.0, 1.0), (5.0, 3.0)])])
    s = scan(world, scanner=ScannerSpec(noise_sigma=0.0))
    assert np.all(np.isinf(s.ranges[s.face_ids < 0]))
    assert np.all(s.gt_labels[s.face_ids < 0] == -1)
    assert s.gt_names == ("near",)
    hit = s.gt_labels == 0
    np.testing.assert_allclose(s.ranges[hit] * np.cos(s.angles[hit]), 5.0, atol=1e-9)


def test_seeding_is_deterministic() -> None:
    a, b, c = figure1(seed=7), figure1(seed=7), figure1(seed=8)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    assert not np.array_equal(a.ranges, c.ranges)
    r1, r2 = random_room(11), random_room(11)
    np.testing.assert_array_equal(r1.ranges, r2.ranges)
    np.testing.assert_array_equal(r1.gt_labels, r2.gt_labels)
    assert r1.pose == r2.pose and r1.noise_sigma == r2.noise_sigma
    assert random_room(12).pose != r1.pose


def test_figure1_labels_in_scan_order_with_transitions_unlabelled() -> None:
    s = figure1(noise_sigma=0.0)
    assert s.gt_names[2:] == (
        "wall_left_of_board", "whiteboard", "wall_right_of_board",
        "wall_before_door", "door", "wall_after_door",
    )
    lab = s.gt_labels
    seen = lab[lab >= 0]
    assert np.all(np.diff(seen) >= 0) and set(seen) == set(range(s.n_segments))
    door = np.flatnonzero(lab == s.label_of("door"))
    before = np.flatnonzero(lab == s.label_of("wall_before_door"))
    after = np.flatnonzero(lab == s.label_of("wall_after_door"))
    # sloped frames (4 cm at ~2 m) leave a few unlabelled beams either side of the door
    assert 3 <= door[0] - before[-1] - 1 <= 8 and 3 <= after[0] - door[-1] - 1 <= 8
    assert door.size > 80 and np.sum(lab == s.label_of("whiteboard")) > 80
    # the true lines: door 1.5 cm behind its wall, board 2 cm proud of its wall
    off = dict(zip(s.gt_names, s.gt_offsets, strict=True))
    assert off["door"] - off["wall_before_door"] == pytest.approx(0.015)
    assert off["wall_left_of_board"] - off["whiteboard"] == pytest.approx(0.02)
    # every labelled noise-free point lies on its true line
    p = s.points_xy
    for k in range(s.n_segments):
        on = lab == k
        np.testing.assert_allclose(p[on] @ s.gt_normals[k], s.gt_offsets[k], atol=1e-9)


def test_random_room_points_lie_on_their_faces() -> None:
    for seed in range(5):
        s = random_room(seed, noise_sigma=0.0)
        assert s.n_segments >= 4
        p = s.points_xy
        for k in range(s.n_segments):
            on = s.gt_labels == k
            np.testing.assert_allclose(p[on] @ s.gt_normals[k], s.gt_offsets[k], atol=1e-8)


def test_run_labels() -> None:
    lab, faces = run_labels([-1, 2, 2, 5, 5, 5, -1, 2, 7], min_run=2)
    np.testing.assert_array_equal(lab, [-1, 0, 0, 1, 1, 1, -1, -1, -1])
    np.testing.assert_array_equal(faces, [2, 5])


def test_bad_world_piece_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="planar face is one straight edge"):
        World2D.from_pieces([("bent", [(0, 0), (1, 0), (1, 1)])])
    with pytest.raises(ValueError, match="noise_sigma"):
        ScannerSpec(noise_sigma=-1.0)
