"""segmentation.steps: segments split where their points switch between two parallel lines."""

from __future__ import annotations

import numpy as np
import pytest

import segmentation
from segmentation.scanline import Scanline
from segmentation.steps import _best_step, split_at_steps


def _wall_with_recess(depth: float, seed: int, noise: float = 0.003, dist: float = 3.0) -> tuple[Scanline, np.ndarray]:
    """A wall 3 m ahead (scanner frame x = 3), seen over +-30 deg at 0.25 deg steps, with the
    part at y in [-0.4, 0.4] set ``depth`` deeper (a door); range noise ``noise``. Returns the
    scanline and, per beam, whether it hits the recessed part."""
    angles = np.radians(np.arange(-30.0, 30.0, 0.25))
    y = dist * np.tan(angles)
    door = np.abs(y) <= 0.4
    x = np.where(door, dist + depth, dist)
    ranges = x / np.cos(angles) + np.random.default_rng(seed).normal(0.0, noise, angles.shape[0])
    return Scanline.from_ranges(ranges, angles), door


def _missed(line: Scanline) -> segmentation.Segmentation:
    """A segmentation that missed the step: RoR at 5 cm keeps the wall and its door in one segment."""
    seg = segmentation.segment(line, "ror", sigma=0.05)
    assert seg.n_segments == 1
    return seg


@pytest.mark.parametrize("dist", [3.0, 7.0])
def test_a_door_one_centimetre_deep_is_split_off_its_wall(dist: float) -> None:
    for seed in range(5):
        line, door = _wall_with_recess(0.010, seed, dist=dist)
        out = split_at_steps(line, _missed(line), 0.003)
        assert out.n_segments == 3
        # every segment of the result lies on one face but for a few beams at its ends
        for a, b in zip(out.first_beam, out.last_beam, strict=True):
            on_door = door[a:b + 1]
            assert min(on_door.sum(), (~on_door).sum()) <= 6, (seed, a, b)
        # the door's edges are segment ends within six beams (1 cm in 3 mm noise: a few beams of play)
        edges = np.flatnonzero(np.diff(door.astype(int)))
        ends = np.concatenate((out.first_beam, out.last_beam + 1))
        for e in edges + 1:
            assert np.abs(ends - e).min() <= 6, (seed, e, out.first_beam, out.last_beam)


def test_a_straight_wall_stays_whole() -> None:
    split = 0
    for seed in range(40):
        line, _ = _wall_with_recess(0.0, seed, dist=3.0 + seed / 10.0)
        split += split_at_steps(line, _missed(line), 0.003).n_segments - 1
    assert split == 0


def test_a_step_below_min_step_is_not_split() -> None:
    line, _ = _wall_with_recess(0.010, 0)
    seg = _missed(line)
    assert split_at_steps(line, seg, 0.003, min_step=0.004).n_segments == 3
    assert split_at_steps(line, seg, 0.003, min_step=0.02).n_segments == 1


def test_gain_and_step_equal_a_least_squares_fit_of_two_parallel_lines() -> None:
    rng = np.random.default_rng(3)
    n, j_true = 60, 23
    s = np.linspace(0.0, 1.2, n)
    e = rng.normal(0.0, 0.003, n) + np.where(np.arange(n) >= j_true, 0.01, 0.0)
    theta = 0.4  # the line's direction in the plane
    u, nrm = np.array([np.cos(theta), np.sin(theta)]), np.array([-np.sin(theta), np.cos(theta)])
    xy = np.array([1.0, 2.0]) + s[:, None] * u + e[:, None] * nrm
    w = 1.0 / rng.uniform(0.002, 0.004, n) ** 2
    j, gain, step = _best_step(xy, w, 10)
    # brute force: weighted least squares of the offsets from the fitted line on [1, s, h_j]
    c = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - c)
    ss, ee = (xy - c) @ vt[0], (xy - c) @ vt[1]
    sw = np.sqrt(w)

    def sse(X: np.ndarray) -> tuple[float, np.ndarray]:
        coef, *_ = np.linalg.lstsq(X * sw[:, None], ee * sw, rcond=None)
        r = (ee - X @ coef) * sw
        return float(r @ r), coef

    base, _ = sse(np.c_[np.ones(n), ss])
    gains = {}
    for jj in range(10, n - 9):
        val, coef = sse(np.c_[np.ones(n), ss, (np.arange(n) >= jj).astype(float)])
        gains[jj] = (base - val, coef[2])
    j_ref = max(gains, key=lambda k: gains[k][0])
    assert j == j_ref
    assert gain == pytest.approx(gains[j_ref][0], rel=1e-6)
    # the step's sign follows the fitted normal's; its size is the fitted one
    assert abs(step) == pytest.approx(abs(gains[j_ref][1]), rel=1e-6)
    assert abs(abs(step) - 0.01) < 0.003


def test_bad_parameters_and_empty_segmentations() -> None:
    line, _ = _wall_with_recess(0.01, 0)
    seg = segmentation.segment(line, "ror", sigma=0.006)
    with pytest.raises(ValueError, match="chi2"):
        split_at_steps(line, seg, 0.003, chi2=0.0)
    with pytest.raises(ValueError, match="min_len"):
        split_at_steps(line, seg, 0.003, min_len=1)
    empty = segmentation.segment(line, "ror", sigma=0.006, min_len=10_000)
    assert split_at_steps(line, empty, 0.003) is empty
