"""The planes' outlines from the final map (slam.plane_extents): the cells a plane's segments
cross, counted, with stray and off-plane segments left out."""

from __future__ import annotations

import numpy as np
import pytest

from slam import plane_extents
from slam.evaluate import extent_errors, face_region
from slam.frontend.planemap import plane_basis
from slam.plane_extents import (
    ExtentRule,
    cell_table,
    final_extents,
    rectangle,
    region_boxes,
    segment_runs,
    union_box,
)

RULE = ExtentRule(cell=0.05, min_segments=3, gate=0.009, rms=0.006)


def test_a_segments_runs_are_its_cells_in_order_with_its_samples_bounds() -> None:
    a, b = np.array([[0.01, 0.02]]), np.array([[0.23, 0.02]])
    cells, seg, box = segment_runs(a, b, 0.1)
    assert cells.tolist() == [[0, 0], [1, 0], [2, 0]] and seg.tolist() == [0, 0, 0]
    assert box[0, 0] == 0.01 and box[-1, 1] == 0.23  # the end points are samples
    assert np.all(box[:, 2] == 0.02) and np.all(box[:, 3] == 0.02)
    assert box[1, 0] >= 0.1 and box[1, 1] < 0.2
    # a diagonal crosses each cell once, in order; a point-like segment is one run
    cells, seg, _ = segment_runs(np.array([[0.0, 0.0], [0.5, 0.5]]), np.array([[0.29, 0.29], [0.5, 0.5]]), 0.1)
    assert seg.tolist().count(1) == 1
    first = cells[seg == 0]
    assert first[0].tolist() == [0, 0] and first[-1].tolist() == [2, 2]
    assert len({tuple(c) for c in first.tolist()}) == first.shape[0]


def _door_segments(rng: np.random.Generator, u: tuple[float, float], v: tuple[float, float], n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` scan lines across a face [u0, u1] x [v0, v1]: horizontal ones at random heights and
    slanted ones (tilted scanners), each from one edge to the other."""
    hv = rng.uniform(*v, size=n)
    a = np.column_stack((np.full(n, u[0]), hv))
    b = np.column_stack((np.full(n, u[1]), np.clip(hv + rng.uniform(-0.6, 0.6, size=n), *v)))
    return a, b


def test_the_box_is_the_face_and_two_stray_segments_do_not_stretch_it() -> None:
    rng = np.random.default_rng(3)
    a, b = _door_segments(rng, (2.0, 2.9), (0.0, 2.05), 400)
    stray_a, stray_b = np.array([[0.5, 0.02], [0.8, 1.0]]), np.array([[2.5, 0.03], [2.4, 1.0]])
    box = union_box(region_boxes(np.vstack((a, stray_a)), np.vstack((b, stray_b)), 0.05, 3, 0.0))
    np.testing.assert_allclose(box, [[2.0, 0.0], [2.9, 2.05]], atol=0.03)
    # counted once each, the strays are the outline's left edge: the count is what keeps them out
    loose = union_box(region_boxes(np.vstack((a, stray_a)), np.vstack((b, stray_b)), 0.05, 1, 0.0))
    assert loose[0, 0] == pytest.approx(0.5)
    # fewer segments than the count: no outline
    assert region_boxes(a[:2], b[:2], 0.05, 3, 0.0) == []


def _lift(uv: np.ndarray, normal: np.ndarray, d: float, off: float = 0.0) -> np.ndarray:
    u, v = plane_basis(normal)
    return uv[:, :1] * u + uv[:, 1:] * v - (d + off) * normal


def test_final_extents_leave_out_segments_off_the_plane_or_not_on_it() -> None:
    rng = np.random.default_rng(5)
    n = np.array([0.0, 1.0, 0.0])
    d = -0.015  # a door 1.5 cm behind the wall y = 0, seen from y < 0
    a, b = _door_segments(rng, (2.0, 2.9), (0.0, 2.05), 300)
    ends = [np.stack((_lift(a, n, d), _lift(b, n, d)), axis=1)]
    rms = [np.full(a.shape[0], 0.003)]
    # the wall beside the door, 1.5 cm in front of the door's plane, wrongly given to it 20 times
    wa, wb = _door_segments(rng, (0.0, 2.0), (0.5, 1.5), 20)
    ends.append(np.stack((_lift(wa, n, d, 0.015), _lift(wb, n, d, 0.015)), axis=1))
    rms.append(np.full(20, 0.015))
    # segments run across the door's edge onto the wall: their ends on the door's plane, their
    # points half on the wall (RMS 11 mm)
    ma, mb = _door_segments(rng, (1.0, 2.5), (0.4, 0.6), 20)
    ends.append(np.stack((_lift(ma, n, d), _lift(mb, n, d)), axis=1))
    rms.append(np.full(20, 0.011))
    e = np.concatenate(ends)
    pid = np.full(e.shape[0], 7)
    planes = [(7, n, d), (8, n, 0.0)]  # plane 8 has no segment: left out
    out = final_extents(e, pid, planes, RULE, np.concatenate(rms))
    assert sorted(out) == [7]
    u, v = plane_basis(n)
    poly = out[7].polygon
    assert len(out[7].regions) == 1 and np.array_equal(out[7].regions[0], poly)
    assert poly.shape == (5, 3) and np.allclose(poly[0], poly[-1])
    np.testing.assert_allclose(poly @ n + d, 0.0, atol=1e-12)  # on the plane
    uv = np.column_stack((poly @ u, poly @ v))
    np.testing.assert_allclose([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()],
                               [2.0, 2.9, 0.0, 2.05], atol=0.03)
    # without the RMS test the segments across the edge stretch the door onto its wall
    loose = final_extents(e, pid, planes, ExtentRule(0.05, 3, 0.009), np.concatenate(rms))
    assert float((loose[7].polygon @ u).min()) < 1.1
    np.testing.assert_allclose(rectangle(n, d, np.array([[2.0, 0.0], [2.9, 2.05]])), poly, atol=0.03)


def test_two_doors_on_one_plane_are_two_regions_each_on_its_face() -> None:
    """Two doors at one depth 3.6 m apart on one plane: the outline spans both, its regions are
    one per door (the larger first), and the evaluation measures each door by its own region."""
    rng = np.random.default_rng(7)
    a1, b1 = _door_segments(rng, (7.55, 8.45), (0.0, 2.05), 300)
    a2, b2 = _door_segments(rng, (12.05, 12.95), (0.0, 2.05), 200)
    boxes = region_boxes(np.vstack((a1, a2)), np.vstack((b1, b2)), 0.05, 3, 0.25)
    assert len(boxes) == 2
    np.testing.assert_allclose(boxes[0], [[7.55, 0.0], [8.45, 2.05]], atol=0.03)
    np.testing.assert_allclose(boxes[1], [[12.05, 0.0], [12.95, 2.05]], atol=0.03)
    # a gap wider than the scan lines' spacing within a face does not split it; one wider than
    # ``gap`` between two faces does
    assert len(region_boxes(a1, b1, 0.05, 3, 0.25)) == 1
    assert len(region_boxes(np.vstack((a1, a2)), np.vstack((b1, b2)), 0.05, 3, 4.0)) == 1
    n, d = np.array([0.0, 1.0, 0.0]), -0.015
    e = np.concatenate((np.stack((_lift(a1, n, d), _lift(b1, n, d)), axis=1),
                        np.stack((_lift(a2, n, d), _lift(b2, n, d)), axis=1)))
    out = final_extents(e, np.full(e.shape[0], 3), [(3, n, d)], RULE, np.full(e.shape[0], 0.003))[3]
    assert len(out.regions) == 2
    face2 = rectangle(n, d, np.array([[12.05, 0.0], [12.95, 2.05]]))
    whole, _ = extent_errors(out.polygon, face2, n)
    own, excess = extent_errors(face_region(out.regions, face2, n), face2, n)
    assert whole > 4.0 and own < 0.03 and excess < 0.03
    # a door seen as two bands (its middle given to the wall): both bands are on its face
    bands = (rectangle(n, d, np.array([[7.55, 0.0], [8.45, 0.4]])), rectangle(n, d, np.array([[7.55, 1.66], [8.45, 2.05]])))
    face1 = rectangle(n, d, np.array([[7.55, 0.0], [8.45, 2.05]]))
    assert extent_errors(face_region(bands, face1, n), face1, n)[0] < 1e-9
    assert extent_errors(bands[1], face1, n)[0] > 1.6


@pytest.mark.parametrize("bad", [dict(cell=0.0), dict(min_segments=0), dict(gate=-1.0), dict(rms=0.0), dict(gap=-0.1)])
def test_a_rule_out_of_range_is_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="extent rule"):
        ExtentRule(**{"cell": 0.05, "min_segments": 3, "gate": 0.009, "rms": 0.006, **bad})  # type: ignore[arg-type]


def test_the_cell_table_in_chunks_is_the_grids() -> None:
    rng = np.random.default_rng(11)
    a, b = _door_segments(rng, (-1.5, 1.5), (-1.0, 1.0), 500)  # cells of both signs
    whole = cell_table(a, b, 0.05, chunk=10_000)
    with pytest.MonkeyPatch.context() as mp:  # the chunked reduction instead of the grid
        mp.setattr(plane_extents, "_GRID_CELLS", 0)
        cut = cell_table(a, b, 0.05, chunk=37)
    for x, y in zip(whole, cut, strict=True):
        np.testing.assert_array_equal(x, y)
    # every segment counted once in each cell it crosses; the cells as the runs have them
    cells, _, _ = segment_runs(a, b, 0.05)
    assert int(whole[1].sum()) == cells.shape[0]
    np.testing.assert_array_equal(whole[0], np.unique(cells, axis=0))
    assert whole[0].min() < 0 < whole[0].max()
