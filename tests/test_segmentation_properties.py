"""Properties every registered segmenter must have (hypothesis), including methods added later."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import segmentation
from segmentation import Scanline, Segmentation
from tests.seg_scenes import raycast

METHODS = segmentation.available()
SEQUENTIAL = [m for m in METHODS if segmentation.segmenter_class(m).sequential]
SETTINGS = settings(max_examples=30, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@st.composite
def scanlines(draw: st.DrawFn) -> Scanline:
    """A random room (rectangle with a proud or recessed panel) seen from inside, with noise and dropouts."""
    w = draw(st.floats(2.0, 12.0))
    h = draw(st.floats(2.0, 12.0))
    sx = draw(st.floats(0.2, 0.8)) * w
    sy = draw(st.floats(0.2, 0.8)) * h
    step = draw(st.floats(-0.03, 0.03))
    p0 = draw(st.floats(0.1, 0.6)) * w
    p1 = p0 + draw(st.floats(0.2, 0.35)) * w
    corners = [(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)]
    faces = [((0.0, 0.0), (p0, 0.0)), ((p0, step), (p1, step)), ((p1, 0.0), (w, 0.0)),
             ((p0, 0.0), (p0, step)), ((p1, step), (p1, 0.0))]
    faces += [(corners[i], corners[(i + 1) % 4]) for i in (1, 2, 3)]
    faces = [((a[0] - sx, a[1] - sy), (b[0] - sx, b[1] - sy)) for a, b in faces]
    n = draw(st.integers(30, 500))
    fov = draw(st.floats(0.5, 4.7))
    start = draw(st.floats(-np.pi, np.pi))
    angles = start + np.linspace(0.0, fov, n)
    r, _ = raycast(faces, angles)
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    noise = draw(st.sampled_from([0.0, 0.001, 0.003, 0.01]))
    r = r + noise * rng.standard_normal(n)
    drop = draw(st.floats(0.0, 0.3))
    r[rng.random(n) < drop] = draw(st.sampled_from([0.0, np.nan, np.inf, 100.0]))
    return Scanline.from_ranges(r, angles, range_min=0.1, range_max=30.0)


def segment_or_documented_error(data: object, method: str, **params: object) -> Segmentation | None:
    try:
        return segmentation.segment(data, method, **params)  # type: ignore[arg-type]
    except ValueError as e:
        msg = str(e)
        assert any(k in msg for k in ("empty input", "invalid", "fewer than", "NaN or inf")), msg
        return None


def check_labels(res: Segmentation, line: Scanline, min_len: int) -> None:
    lab = res.labels
    assert lab.shape == (line.n_beams,) and lab.dtype == np.int64
    assert np.all(lab[~line.valid] == -1)
    seg = lab[lab >= 0]
    assert np.all(lab >= -1)
    if seg.size:
        # ids consecutive from 0 in scan order
        assert seg[0] == 0 and np.all(np.diff(seg) >= 0) and np.all(np.diff(seg) <= 1)
    assert res.n_segments == (int(seg.max()) + 1 if seg.size else 0)
    for k in range(res.n_segments):
        beams = np.flatnonzero(lab == k)
        assert beams[0] == res.first_beam[k] and beams[-1] == res.last_beam[k]
        # contiguous over the valid beams
        valid_between = np.flatnonzero(line.valid[beams[0]:beams[-1] + 1]) + beams[0]
        assert np.array_equal(beams, valid_between)
        assert res.n_points[k] == beams.size >= min_len
    assert np.all(np.isfinite(res.normal)) and np.all(np.isfinite(res.offset))


@pytest.mark.parametrize("method", METHODS)
@SETTINGS
@given(line=scanlines())
def test_labels_contiguous_min_len_deterministic(method: str, line: Scanline) -> None:
    res = segment_or_documented_error(line, method)
    if res is None:
        assert line.n_valid < 5
        return
    check_labels(res, line, segmentation.get(method).params.min_len)
    again = segmentation.get(method).segment(line)
    assert np.array_equal(res.labels, again.labels) and np.array_equal(res.offset, again.offset)
    # depth jumps: consecutive points of one segment are never farther apart than max_gap
    max_gap = segmentation.get(method).params.max_gap
    pts = line.points_xy
    plab = res.labels[line.valid_index]
    same = (plab[1:] == plab[:-1]) & (plab[1:] >= 0)
    assert np.all(np.hypot(*(pts[1:] - pts[:-1]).T)[same] <= max_gap + 1e-12)


@pytest.mark.parametrize("method", SEQUENTIAL)
@SETTINGS
@given(line=scanlines())
def test_backward_is_forward_on_reversed(method: str, line: Scanline) -> None:
    fwd = segment_or_documented_error(line.reversed(), method, direction="forward")
    bwd = segment_or_documented_error(line, method, direction="backward")
    assert (fwd is None) == (bwd is None)
    if fwd is None or bwd is None:
        return
    assert np.array_equal(bwd.labels >= 0, fwd.labels[::-1] >= 0)
    assert np.array_equal(np.diff(bwd.labels) != 0, np.diff(fwd.labels[::-1]) != 0)
    check_labels(segmentation.segment(line, method, direction="combined"), line,
                 segmentation.get(method).params.min_len)


@pytest.mark.parametrize("method", METHODS)
def test_documented_errors(method: str) -> None:
    seg = segmentation.get(method)
    with pytest.raises(ValueError, match="empty input"):
        seg.segment(np.empty((0, 2)))
    with pytest.raises(ValueError, match="invalid"):
        seg.segment(Scanline.from_ranges([np.nan, 0.0, np.inf], [0.0, 0.1, 0.2]))
    with pytest.raises(ValueError, match="NaN or inf"):
        seg.segment(np.array([[1.0, 2.0], [np.nan, 1.0], [1.0, 3.0]]))
    with pytest.raises(ValueError, match="NaN or inf"):
        seg.segment(np.array([[1.0, 2.0], [np.inf, 1.0], [1.0, 3.0]]))
    with pytest.raises(ValueError, match="fewer than"):
        seg.segment(np.array([[1.0, 2.0]]))
    n_init = getattr(seg.params, "n_init", None)
    if n_init is not None:
        with pytest.raises(ValueError, match="fewer than"):
            seg.segment(np.column_stack((np.ones(n_init - 1), np.arange(n_init - 1.0))))
    with pytest.raises(ValueError, match="shape"):
        seg.segment(np.ones((5, 3)))


@pytest.mark.parametrize("method", METHODS)
def test_duplicates_and_single_line_segment_normally(method: str) -> None:
    seg = segmentation.get(method)
    x = np.linspace(-2.0, 2.0, 300)
    line = np.column_stack((x, np.full_like(x, 3.0)))
    res = seg.segment(line)
    assert res.n_segments >= 1 and np.mean(res.labels >= 0) > 0.8
    assert np.allclose(np.abs(res.normal[:, 1]), 1.0, atol=1e-9)
    for pts in (np.repeat(line, 2, axis=0), np.tile([[1.0, 2.0]], (50, 1)),
                np.r_[line[:100], np.tile(line[100], (40, 1)), line[100:]]):
        res = seg.segment(pts)
        check_labels(res, Scanline.from_points(pts), seg.params.min_len)
    # a few points, as many as the method needs: no crash
    k = seg.min_points
    res = seg.segment(np.column_stack((np.arange(k, dtype=float), np.full(k, 2.0))))
    assert res.labels.shape == (k,)
