"""Core of the segmentation package: Scanline, TLS fits and covariances, label kernels, registry."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import segmentation
from segmentation import Scanline
from segmentation.labels import combine_runs, finalize_runs
from segmentation.lines import fit_line, fit_segments


# ---- Scanline ---------------------------------------------------------------------------------
def test_from_ranges_masks_invalid_returns() -> None:
    angles = np.linspace(-1.0, 1.0, 7)
    ranges = np.array([1.0, 0.0, np.nan, np.inf, 0.05, 40.0, 2.0])
    line = Scanline.from_ranges(ranges, angles, 10.0, range_min=0.1, range_max=30.0, time_increment=0.01)
    assert line.valid.tolist() == [True, False, False, False, False, False, True]
    assert line.valid_index.tolist() == [0, 6]
    assert np.allclose(line.points_xy, [[np.cos(-1.0), np.sin(-1.0)], [2 * np.cos(1.0), 2 * np.sin(1.0)]])
    assert np.allclose(line.times, 10.0 + 0.01 * np.arange(7))
    assert line.n_beams == 7 and line.n_valid == 2


def test_points_are_the_valid_beams_cosines_and_sines_whatever_was_seen_before() -> None:
    """The cosines and sines kept per angle array give the points numpy's own trig of the valid
    beams gives, bit for bit, for angles seen before, changed in place, or in float32."""
    rng = np.random.default_rng(2)
    base = -2.35 + 0.0043633 * np.arange(1081)
    for trial in range(60):
        angles = base.copy() if trial % 3 else rng.uniform(-3.0, 3.0, int(rng.integers(1, 1200)))
        if trial % 7 == 0:
            angles = angles.astype(np.float32)
        if trial % 5 == 0:
            angles[len(angles) // 2] += 1e-3  # the same length and ends as a kept array, not the same angles
        ranges = rng.uniform(0.1, 20.0, angles.shape[0])
        ranges[rng.random(angles.shape[0]) < 0.3] = np.nan
        line = Scanline(angles, ranges, np.zeros(angles.shape[0]), np.isfinite(ranges))
        a, r = angles[line.valid_index], ranges[line.valid_index]
        assert np.array_equal(line.points_xy, np.column_stack((r * np.cos(a), r * np.sin(a))))


def test_from_laserscan_record() -> None:
    msg = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=5, nanosec=500_000_000), frame_id="laser_top"),
        angle_min=-2.356194, angle_increment=np.deg2rad(0.25), time_increment=1.0 / 40 / 1440,
        range_min=0.1, range_max=30.0, ranges=np.array([1.0, 2.0, 0.0, 31.0, np.nan], dtype=np.float32),
    )
    line = Scanline.from_laserscan(msg)
    assert line.scanner_id == "laser_top"
    assert line.stamp == pytest.approx(5.5)
    assert np.allclose(line.angles, -2.356194 + np.deg2rad(0.25) * np.arange(5))
    assert np.allclose(line.times[4] - line.times[0], 4 * msg.time_increment)
    assert line.valid.tolist() == [True, True, False, False, False]


def test_from_points_keeps_coordinates_and_masks_nonfinite_rows() -> None:
    pts = np.array([[1.0, 2.0], [np.nan, 1.0], [0.0, 0.0], [3.0, -1.0]])
    line = Scanline.from_points(pts)
    assert line.valid.tolist() == [True, False, False, True]
    assert np.array_equal(line.points_xy, pts[[0, 3]])


def test_scanline_rejects_valid_nonfinite_beam() -> None:
    with pytest.raises(ValueError, match="NaN or inf"):
        Scanline(np.zeros(2), np.array([1.0, np.nan]), np.zeros(2), np.array([True, True]))


def test_reversed_scanline() -> None:
    line = Scanline.from_ranges([1.0, 0.0, 3.0], [0.0, 0.1, 0.2])
    rev = line.reversed()
    assert np.array_equal(rev.points_xy, line.points_xy[::-1])
    assert rev.valid.tolist() == [True, False, True]


# ---- line fits --------------------------------------------------------------------------------
def test_fit_line_exact_and_oriented() -> None:
    # the line y = 2 - x seen from the origin: normal (1, 1)/sqrt(2), offset sqrt(2)
    x = np.linspace(-1.0, 3.0, 20)
    n, off, rms = fit_line(np.column_stack((x, 2.0 - x)))
    assert np.allclose(n, [2**-0.5, 2**-0.5]) and off == pytest.approx(2**0.5) and rms < 1e-12
    # far from the scanner, nearly along x: no precision loss
    x = np.linspace(1000.0, 1000.5, 50)
    n, off, rms = fit_line(np.column_stack((x, 0.3 * np.ones_like(x))))
    assert np.allclose(n, [0.0, 1.0], atol=1e-9) and off == pytest.approx(0.3, abs=1e-9)


def test_fit_segments_fields() -> None:
    pts = np.array([[2.0, -1.0], [2.0, 0.0], [2.0, 1.0], [0.0, 3.0], [1.0, 3.0], [2.0, 3.0]])
    normal, offset, centroid, direction, endpoints, rms, cov = fit_segments(
        pts, np.array([0, 3]), np.array([2, 5]), np.full(6, 0.01))
    assert np.allclose(normal, [[1, 0], [0, 1]]) and np.allclose(offset, [2, 3])
    assert np.allclose(centroid, [[2, 0], [1, 3]])
    assert np.allclose(direction, [[0, 1], [1, 0]])  # first -> last point
    assert np.allclose(endpoints[0], [[2, -1], [2, 1]]) and np.allclose(rms, 0)
    assert np.allclose(cov, np.transpose(cov, (0, 2, 1))) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_angle_offset_covariance_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    sigma, n, trials = 0.01, 40, 4000
    t = np.linspace(-1.0, 1.5, n)
    # a wall at 4 m with normal at 30 deg, points along it (offset from the foot point)
    a0 = np.deg2rad(30.0)
    nrm = np.array([np.cos(a0), np.sin(a0)])
    dirv = np.array([-nrm[1], nrm[0]])
    base = 4.0 * nrm + t[:, None] * dirv
    pts = (base[None] + sigma * rng.standard_normal((trials, n, 2))).reshape(-1, 2)
    first = np.arange(trials) * n
    normal, offset, _, _, _, _, cov = fit_segments(np.ascontiguousarray(pts), first, first + n - 1,
                                                    np.full(trials * n, sigma))
    samples = np.column_stack((np.arctan2(normal[:, 1], normal[:, 0]), offset))
    emp = np.cov(samples.T)
    pred = cov.mean(axis=0)
    assert np.allclose(samples.mean(axis=0), [a0, 4.0], atol=3 * np.sqrt(np.diag(pred) / trials) + 1e-12)
    assert np.allclose(np.diag(emp), np.diag(pred), rtol=0.1)
    corr_emp = emp[0, 1] / np.sqrt(emp[0, 0] * emp[1, 1])
    corr_pred = pred[0, 1] / np.sqrt(pred[0, 0] * pred[1, 1])
    assert corr_emp == pytest.approx(corr_pred, abs=0.05)
    assert abs(corr_pred) > 0.3  # the offset and angle are correlated here: the test can see it


# ---- label kernels ----------------------------------------------------------------------------
def test_combine_runs_hand_made() -> None:
    fwd = np.array([0, 0, 0, 0, 1, 1, 1, -1, 2, 2], dtype=np.int64)
    bwd = np.array([5, 5, 6, 6, 6, 6, 6, 6, 6, -1], dtype=np.int64)
    out = combine_runs(fwd, bwd)
    # unsegmented in either -> -1; a boundary in either (after 1, after 3) -> a new id
    assert out.tolist() == [0, 0, 1, 1, 2, 2, 2, -1, 3, -1]


def test_finalize_runs_splits_gaps_and_drops_short() -> None:
    pts = np.column_stack((np.r_[np.arange(6) * 0.1, 5 + np.arange(4) * 0.1], np.zeros(10)))
    raw = np.array([7, 7, 7, 7, 7, 7, 7, 7, 7, 7], dtype=np.int64)
    lab, first, last = finalize_runs(raw, pts, 0.2, 5)
    assert lab.tolist() == [0] * 6 + [-1] * 4
    assert first.tolist() == [0] and last.tolist() == [5]
    raw2 = np.array([3, 3, 3, 1, 1, 1, 1, 1, 1, 1], dtype=np.int64)
    lab, first, last = finalize_runs(raw2, pts[:10] * 0 + np.column_stack((np.arange(10) * 0.1, np.zeros(10))), 0.2, 3)
    assert lab.tolist() == [0, 0, 0, 1, 1, 1, 1, 1, 1, 1] and last.tolist() == [2, 9]


# ---- registry and parameters ------------------------------------------------------------------
def test_registry_lists_names_and_params() -> None:
    names = segmentation.available()
    assert "ror" in names and "line_tracking" in names and names == sorted(names)
    with pytest.raises(ValueError, match=r"unknown segmenter 'nope'; available: .*ror"):
        segmentation.get("nope")
    with pytest.raises(ValueError, match=r"unknown parameter sigmaa .*valid: .*n_init.*sigma.*percentage"):
        segmentation.get("ror", sigmaa=0.01)
    with pytest.raises(ValueError, match="percentage"):
        segmentation.get("ror", percentage=1.5)
    with pytest.raises(ValueError, match="direction"):
        segmentation.get("ror", direction="sideways")


def test_parameter_coercion_from_strings() -> None:
    seg = segmentation.get("ror", sigma="0.011", min_len="20", direction="forward", stride="2",
                           statistic="signed")
    p = seg.params
    assert p.sigma == 0.011 and p.min_len == 20 and p.direction == "forward"  # type: ignore[attr-defined]
    assert p.stride == 2 and p.statistic == "signed"  # type: ignore[attr-defined]
    for bad in ({"min_len": "2.5"}, {"sigma": "abc"}, {"sigma": "nan"}, {"n_init": True}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            segmentation.get("ror", **bad)


def test_get_and_segment_agree() -> None:
    x = np.linspace(-2, 2, 200)
    pts = np.column_stack((x, np.full_like(x, 2.0)))
    a = segmentation.segment(pts, method="ror", sigma=0.01)
    b = segmentation.get("ror", sigma=0.01).segment(pts)
    assert np.array_equal(a.labels, b.labels) and a.params == b.params and a.method == "ror"
    assert a.n_segments == 1 and a.segments[0].n_points == 200
