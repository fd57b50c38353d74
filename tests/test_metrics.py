"""The paper's section-3 metrics on hand-made labellings of a known scanline."""

from __future__ import annotations

import numpy as np
import pytest

from segmentation import Scanline, Segmentation
from segmentation.metrics import boundary_scores, compare, segment_bounds, separates
from simulation.scanline import figure1


@pytest.fixture(scope="module")
def fig1():  # type: ignore[no-untyped-def]
    s = figure1(noise_sigma=0.0)
    line = Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min, range_max=s.range_max)
    return s, line


def _segmentation(labels: np.ndarray, normals: np.ndarray) -> Segmentation:
    first, last = segment_bounds(labels)
    k = first.size
    z2 = np.zeros((k, 2))
    return Segmentation(
        labels=labels, first_beam=first, last_beam=last, n_points=last - first + 1,
        normal=normals, offset=np.zeros(k), centroid=z2, direction=z2, endpoints=np.zeros((k, 2, 2)),
        rms=np.zeros(k), cov=np.zeros((k, 2, 2)),
    )


def test_perfect_result(fig1) -> None:  # type: ignore[no-untyped-def]
    s, line = fig1
    sc = compare(s.gt_labels, s.gt_labels, line, s.gt_normals)
    np.testing.assert_allclose(sc.overlap1, 1.0)
    np.testing.assert_allclose(sc.overlap2, 1.0)
    np.testing.assert_array_equal(sc.n_assigned, 1)
    assert sc.mean_overlap1 == sc.mean_overlap2 == sc.segments_per_gt == 1.0
    assert sc.median_angle_deg == pytest.approx(0.0, abs=1e-6)
    assert sc.boundary_precision == sc.boundary_recall == 1.0
    assert sc.n_unassigned == 0 and sc.n_result == sc.n_gt == s.n_segments


def test_merged_door_is_undersegmentation(fig1) -> None:  # type: ignore[no-untyped-def]
    s, line = fig1
    door, before, after = (s.label_of(n) for n in ("door", "wall_before_door", "wall_after_door"))
    gt = s.gt_labels
    merged = gt.copy()
    span = np.flatnonzero(np.isin(gt, [door, before, after]))
    merged[span[0]:span[-1] + 1] = before  # one segment over wall + frame + door + wall
    merged[gt > after] -= 2
    sc = compare(merged, gt, line, s.gt_normals)
    assert sc.n_assigned[door] == 0 and sc.overlap1[door] == 0.0 and np.isnan(sc.angle_deg[door])
    assert sc.segments_per_gt < 1.0
    assert sc.n_overlapping[door] == 1
    # the merged line is tilted towards the door: a visibly non-zero angle for the wall it is assigned to
    assert sc.angle_deg[after] > 0.05
    assert sc.boundary_recall < 1.0 and sc.boundary_precision == 1.0
    assert not separates(merged, gt, door)
    assert separates(gt, gt, door)


def test_split_wall_is_oversegmentation(fig1) -> None:  # type: ignore[no-untyped-def]
    s, line = fig1
    gt = s.gt_labels
    wall = s.label_of("right_wall")
    idx = np.flatnonzero(gt == wall)
    split = gt.copy()
    split[gt > wall] += 2
    split[idx[100:]] = wall + 1
    split[idx[200:]] = wall + 2
    split[idx[99]] = -1  # one unsegmented point between the first two parts
    sc = compare(split, gt, line, s.gt_normals)
    assert sc.n_assigned[wall] == 3
    assert sc.overlap1[wall] == pytest.approx(100 / idx.size)
    assert sc.overlap2[wall] == pytest.approx((idx.size - 1) / idx.size)
    assert sc.segments_per_gt == pytest.approx((s.n_segments + 2) / s.n_segments)
    assert sc.boundary_recall == 1.0 and sc.boundary_precision < 1.0


def test_tilted_line_gives_its_angle(fig1) -> None:  # type: ignore[no-untyped-def]
    s, line = fig1
    tilt = np.deg2rad(3.0)
    rot = np.array([[np.cos(tilt), -np.sin(tilt)], [np.sin(tilt), np.cos(tilt)]])
    normals = s.gt_normals.copy()
    normals[3] = rot @ normals[3]
    sc = compare(_segmentation(s.gt_labels, normals), s.gt_labels, line, s.gt_normals)
    assert sc.angle_deg[3] == pytest.approx(3.0)
    np.testing.assert_allclose(np.delete(sc.angle_deg, 3), 0.0, atol=1e-6)
    assert sc.median_angle_deg == pytest.approx(0.0, abs=1e-6)
    # without true normals the GT line is the TLS fit of the (noise-free) GT points: same answer
    sc2 = compare(_segmentation(s.gt_labels, normals), s.gt_labels, line)
    assert sc2.angle_deg[3] == pytest.approx(3.0, abs=1e-6)


def test_boundary_tolerance_and_unassigned_segment() -> None:
    gt = np.array([0] * 10 + [-1] * 5 + [1] * 10)
    res = np.array([0] * 12 + [1] * 3 + [2] * 10)  # end of 0 two beams late; 1 lies on GT-unsegmented beams
    pts = np.column_stack((np.arange(25.0), np.where(np.arange(25) < 12, 1.0, 2.0)))
    sc = compare(res, gt, pts)
    assert sc.assigned_gt.tolist() == [0, -1, 1] and sc.n_unassigned == 1
    p, r = boundary_scores(res, gt, tolerance=2)
    assert r == 1.0 and p == pytest.approx(4 / 6)
    _, r1 = boundary_scores(res, gt, tolerance=1)
    assert r1 == pytest.approx(3 / 4)


def test_mismatched_lengths_are_an_error() -> None:
    with pytest.raises(ValueError, match="equal length"):
        compare(np.zeros(3, dtype=int), np.zeros(4, dtype=int), np.zeros((4, 2)))
