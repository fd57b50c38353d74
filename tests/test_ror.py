"""Range-of-residuals segmentation on hand-made scanlines."""

from __future__ import annotations

import numpy as np
import pytest

import segmentation
from segmentation import Scanline
from tests.seg_scenes import UTM_ANGLES, office_scanline, raycast


def step_wall(step: float = 0.02, noise: float = 0.003, seed: int = 0) -> tuple[Scanline, np.ndarray]:
    """A wall 2 m ahead (y = 2) with its middle metre ``step`` closer; (scanline, face per beam)."""
    faces = [((-4.0, 2.0), (-0.5, 2.0)), ((-0.5, 2.0 - step), (0.5, 2.0 - step)), ((0.5, 2.0), (4.0, 2.0)),
             ((-0.5, 2.0), (-0.5, 2.0 - step)), ((0.5, 2.0 - step), (0.5, 2.0))]
    angles = UTM_ANGLES[(UTM_ANGLES > 0.5) & (UTM_ANGLES < 2.6)]
    r, face = raycast(faces, angles)
    r = r + noise * np.random.default_rng(seed).standard_normal(r.shape[0])
    return Scanline.from_ranges(r, angles, range_min=0.1, range_max=30.0), face


def separated(res: segmentation.Segmentation, face: np.ndarray, f: int) -> bool:
    """Some segment covers most of face f and is made (almost) only of it."""
    total = int((face == f).sum())
    for a, b in zip(res.first_beam, res.last_beam, strict=True):
        on = int((face[a:b + 1] == f).sum())
        if on >= 0.5 * total and on >= 0.9 * (b - a + 1):
            return True
    return False


@pytest.mark.parametrize("statistic", ["abs", "signed"])
def test_two_cm_step_is_separated(statistic: str) -> None:
    for seed in range(5):
        line, face = step_wall(seed=seed)
        res = segmentation.segment(line, "ror", statistic=statistic)
        assert separated(res, face, 1), f"seed {seed}: {list(zip(res.first_beam, res.last_beam, strict=True))}"
        assert separated(res, face, 0) and separated(res, face, 2)


def test_large_sigma_merges_the_step() -> None:
    # the check above can fail: with a loose sigma the 2 cm step joins its wall
    line, face = step_wall()
    res = segmentation.segment(line, "ror", sigma=0.03)
    assert not separated(res, face, 1)


def test_office_door_and_board_at_defaults() -> None:
    for seed in range(5):
        line, face = office_scanline(seed=seed)
        res = segmentation.segment(line, "ror")
        assert separated(res, face, 1) and separated(res, face, 4), seed


@pytest.mark.parametrize("kw", [{}, {"statistic": "signed"}, {"stride": 3}, {"noise_slope": 0.002}])
def test_forward_equals_backward_on_reversed(kw: dict) -> None:
    line, _ = office_scanline(seed=1)
    fwd = segmentation.segment(line, "ror", direction="forward", **kw)
    bwd = segmentation.segment(line.reversed(), "ror", direction="backward", **kw)
    assert np.array_equal(fwd.labels >= 0, bwd.labels[::-1] >= 0)
    # same segments (as beam sets), numbered in each scan order
    fs = {(int(a), int(b)) for a, b in zip(fwd.first_beam, fwd.last_beam, strict=True)}
    n = line.n_beams
    bs = {(n - 1 - int(b), n - 1 - int(a)) for a, b in zip(bwd.first_beam, bwd.last_beam, strict=True)}
    assert fs == bs


def test_combined_rule() -> None:
    line, _ = office_scanline(seed=2, noise=0.004)
    p = {"sigma": 0.008, "min_len": 15}
    f = segmentation.segment(line, "ror", direction="forward", **p).labels
    b = segmentation.segment(line, "ror", direction="backward", **p).labels
    c = segmentation.segment(line, "ror", direction="combined", **p).labels
    # expected: unsegmented in either -> unsegmented; boundary in either -> boundary; then min_len
    raw = np.full(f.shape[0], -1)
    k = -1
    for i in range(f.shape[0]):
        if f[i] < 0 or b[i] < 0:
            continue
        if i == 0 or raw[i - 1] < 0 or f[i] != f[i - 1] or b[i] != b[i - 1]:
            k += 1
        raw[i] = k
    ids, counts = np.unique(raw[raw >= 0], return_counts=True)
    keep = ids[counts >= 15]
    expected = np.where(np.isin(raw, keep), raw, -1)
    assert np.array_equal(c >= 0, expected >= 0)
    assert np.array_equal(np.diff(c) != 0, np.diff(expected) != 0)
    assert not np.array_equal(f, b)  # the two runs differ here, so the rule is exercised


def test_stride_one_is_the_default_and_stride_changes_little() -> None:
    line, face = office_scanline(seed=3)
    a = segmentation.segment(line, "ror")
    b = segmentation.segment(line, "ror", stride=1)
    assert np.array_equal(a.labels, b.labels)
    c = segmentation.segment(line, "ror", stride=4)
    assert separated(c, face, 1)
    assert np.mean(a.labels == c.labels) > 0.9


def test_percentage_and_n_init_matter() -> None:
    line, _ = office_scanline(seed=4)
    base = segmentation.segment(line, "ror").labels
    assert not np.array_equal(base, segmentation.segment(line, "ror", percentage=0.6, sigma=0.006).labels)


def test_range_dependent_noise_scales_thresholds() -> None:
    line, face = step_wall()
    assert separated(segmentation.segment(line, "ror"), face, 1)
    # sigma(r) = 3 mm + 0.01 r: at about 2.1 m every threshold grows 8x: the step merges
    res = segmentation.segment(line, "ror", noise_slope=0.01)
    assert not separated(res, face, 1)
    # equivalence on a scanline at one range: scaling sigma by sigma(r0)/point_sigma is the same
    ang = np.linspace(-0.4, 0.4, 400)
    rng = np.random.default_rng(0)
    r0 = 3.0
    pts = r0 * np.column_stack((np.cos(ang), np.sin(ang)))  # an arc: every range is r0
    pts += 0.002 * rng.standard_normal(pts.shape)
    pts *= r0 / np.hypot(pts[:, 0], pts[:, 1])[:, None]
    scale = (0.003 + 0.002 * r0) / 0.003
    a = segmentation.segment(pts, "ror", sigma=0.004, noise_slope=0.002, statistic="signed")
    b = segmentation.segment(pts, "ror", sigma=0.004 * scale, statistic="signed")
    assert np.array_equal(a.labels, b.labels)
    assert not np.array_equal(a.labels, segmentation.segment(pts, "ror", sigma=0.004, statistic="signed").labels)


def test_result_lines_are_consistent() -> None:
    line, _ = office_scanline(seed=0, noise=0.0)
    res = segmentation.segment(line, "ror")
    for s in res.segments:
        pts = line.points_xy[np.searchsorted(line.valid_index, s.first_beam):
                             np.searchsorted(line.valid_index, s.last_beam) + 1]
        assert np.allclose(pts @ s.normal, s.offset, atol=1e-6)
        assert s.n_points >= 15 and s.rms < 1e-6 and s.offset > 0
    assert np.all(np.diff(res.labels[res.labels >= 0]) >= 0)


# ---- parent_check (our addition to the combination; module docstring) ---------------------------

from hypothesis import given  # noqa: E402

from tests.test_segmentation_properties import SETTINGS, check_labels, scanlines  # noqa: E402


def _bounds(res: segmentation.Segmentation) -> set[tuple[int, int]]:
    return {(int(a), int(b)) for a, b in zip(res.first_beam, res.last_beam, strict=True)}


@SETTINGS
@given(line=scanlines())
def test_parent_check_only_drops_combined_segments(line: Scanline) -> None:
    try:
        checked = segmentation.segment(line, "ror")
    except ValueError:
        return
    paper = segmentation.segment(line, "ror", parent_check=False)
    check_labels(checked, line, 15)
    # every kept segment is a segment of the paper's combination, unchanged
    assert _bounds(checked) <= _bounds(paper)
    assert np.all(paper.labels[checked.labels >= 0] >= 0)
    # single runs do not depend on it
    for d in ("forward", "backward"):
        assert np.array_equal(segmentation.segment(line, "ror", direction=d).labels,
                              segmentation.segment(line, "ror", direction=d, parent_check=False).labels)


@SETTINGS
@given(line=scanlines())
def test_checked_combination_is_symmetric_under_reversal(line: Scanline) -> None:
    try:
        a = segmentation.segment(line, "ror")
    except ValueError:
        return
    b = segmentation.segment(line.reversed(), "ror")
    n = line.n_beams
    assert _bounds(a) == {(n - 1 - y, n - 1 - x) for x, y in _bounds(b)}


def test_parent_check_drops_the_door_transition_piece() -> None:
    """Figure-1 seed 1: the paper's rule keeps a 17-point piece of wall, sloped frame and door
    between the wall and the door; the check drops exactly that piece."""
    from segmentation.metrics import separates
    from simulation.scanline import figure1

    s = figure1(noise_sigma=0.003, seed=1)
    line = Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min, range_max=s.range_max)
    door = s.label_of("door")
    paper = segmentation.segment(line, "ror", parent_check=False)
    checked = segmentation.segment(line, "ror")
    assert not separates(paper, s.gt_labels, door)
    assert separates(checked, s.gt_labels, door)
    dropped = _bounds(paper) - _bounds(checked)
    assert len(dropped) == 1
    a, b = dropped.pop()
    faces = set(s.gt_labels[a:b + 1].tolist())
    assert {door, s.label_of("wall_before_door"), -1} == faces and b - a + 1 < 20
