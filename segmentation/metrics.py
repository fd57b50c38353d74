"""Comparison of a segmentation with ground-truth labels: the seed paper's section 3 metrics.

Everything is counted in beams of one scanline (labels: one int per beam,
-1 = unsegmented). A *GT segment* is a ground-truth label >= 0, a *result
segment* a label >= 0 of the ``Segmentation``.

Reading of the paper's definitions (section 3, steps 1-4):

1. **Assignment.** Each result segment is assigned to the GT segment with
   which it shares the most beams (ties: the lower GT id). A result segment
   sharing no beam with any GT segment (it lies on unsegmented ground truth)
   is *unassigned*; it counts in ``n_unassigned`` but in no per-GT metric.
2. **overlap1** of a GT segment = the largest number of beams any single
   assigned result segment shares with it, divided by the GT segment's
   size. 1 means one result segment covers the whole GT segment (no
   oversegmentation, nothing missed).
3. **overlap2** = the beams of the GT segment covered by *all* its assigned
   result segments together, divided by its size. 1 means every point was
   found, possibly by several segments. Beams a result segment shares with a
   GT segment it is *not* assigned to do not count for that GT segment.
4. **Over/undersegmentation** = the number of result segments assigned to a
   GT segment; its average over GT segments is the paper's "average number of
   resulting segments per ground truth segment": 1 ideal, > 1
   oversegmentation, < 1 undersegmentation. A GT segment swallowed by a
   result segment assigned elsewhere (a door merged into its wall) has 0
   assigned segments, which is how undersegmentation shows. (The raw count of
   result segments merely *touching* a GT segment is ``n_overlapping``.)
5. **Angle** between a result segment's line and its GT segment's line, in
   degrees in [0, 90]. The GT line is the true face if ``gt_normals`` is
   given, else the total-least-squares fit of the GT segment's points. Every
   assigned result segment has an angle; ``median_angle_deg`` is the median
   over all of them (the paper's median angle). Per GT segment, ``angle_deg``
   is the angle of the segment that defines overlap1.
6. **Unassigned GT segments** (no result segment assigned) count with
   overlap1 = overlap2 = 0 and 0 assigned segments in the averages, and have
   no angle (NaN).

Added here (not in the paper): boundary precision and recall. The
boundaries of a labelling are the first and the last beam of each of its
segments; result starts are matched one-to-one to GT starts, and ends to
ends, when they lie within ``tolerance`` beams (default 2), maximising the
number of matches. Precision = matched / result boundaries, recall =
matched / GT boundaries.

``separates`` is the criterion the figure scripts and tests use to say that
a narrow object (door, board) is separated from its wall.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from segmentation.lines import fit_line
from segmentation.result import Segmentation
from segmentation.scanline import Scanline

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class SegmentScore:
    """Per-GT-segment arrays (index = GT id) and per-result-segment arrays, plus the averages.

    Per GT segment: ``gt_size``, ``overlap1``, ``overlap2``, ``n_assigned``,
    ``n_overlapping``, ``angle_deg`` (NaN if unassigned). Per result segment:
    ``assigned_gt`` (-1 if unassigned) and ``result_angle_deg`` (NaN if unassigned).
    """

    gt_size: IntArray
    overlap1: FloatArray
    overlap2: FloatArray
    n_assigned: IntArray
    n_overlapping: IntArray
    angle_deg: FloatArray
    assigned_gt: IntArray
    result_angle_deg: FloatArray
    mean_overlap1: float
    mean_overlap2: float
    segments_per_gt: float
    median_angle_deg: float
    boundary_precision: float
    boundary_recall: float
    n_gt: int
    n_result: int
    n_unassigned: int

    def summary(self) -> dict[str, float]:
        """The scalar metrics, e.g. for a CSV row."""
        d = asdict(self)
        return {k: float(v) for k, v in d.items() if np.ndim(v) == 0}


def compare(
    result: Segmentation | ArrayLike,
    gt_labels: ArrayLike,
    points: Scanline | ArrayLike,
    gt_normals: ArrayLike | None = None,
    tolerance: int = 2,
) -> SegmentScore:
    """Score ``result`` against ``gt_labels`` (one int per beam) following the paper's section 3.

    ``result`` is a ``Segmentation`` or its per-beam labels. ``points`` are
    the beams' points in the scanner frame: a ``Scanline`` or an
    (n_beams, 2) array (rows of invalid beams are ignored). ``gt_normals``
    (n_gt, 2), if given, are the true line normals of the GT segments.
    """
    res = _labels_of(result)
    gt = np.asarray(gt_labels, dtype=np.int64)
    if res.shape != gt.shape or gt.ndim != 1:
        raise ValueError(f"result labels {res.shape} and gt_labels {gt.shape} must be 1-D of equal length")
    pts = _beam_points(points, gt.shape[0])
    n_gt = int(gt.max()) + 1 if gt.size and gt.max() >= 0 else 0
    n_res = int(res.max()) + 1 if res.size and res.max() >= 0 else 0

    # contingency table of beams: result segment x GT segment
    both = (res >= 0) & (gt >= 0)
    table = np.zeros((n_res, n_gt), dtype=np.int64)
    np.add.at(table, (res[both], gt[both]), 1)
    gt_size = np.bincount(gt[gt >= 0], minlength=n_gt).astype(np.int64)

    assigned = np.where(table.sum(axis=1) > 0, np.argmax(table, axis=1) if n_gt else -1, -1).astype(np.int64)
    mine = np.zeros_like(table)
    rows = np.flatnonzero(assigned >= 0)
    mine[rows, assigned[rows]] = table[rows, assigned[rows]]

    with np.errstate(invalid="ignore", divide="ignore"):
        overlap1 = np.where(gt_size > 0, mine.max(axis=0, initial=0) / gt_size, 0.0)
        overlap2 = np.where(gt_size > 0, mine.sum(axis=0) / gt_size, 0.0)
    n_assigned = np.bincount(assigned[assigned >= 0], minlength=n_gt).astype(np.int64)
    n_overlapping = (table > 0).sum(axis=0).astype(np.int64)

    gt_dirs = _gt_normals(gt, pts, n_gt, gt_normals)
    res_dirs = _result_normals(result, res, pts, n_res)
    res_angle = np.full(n_res, np.nan)
    for r in rows:
        res_angle[r] = _line_angle_deg(res_dirs[r], gt_dirs[assigned[r]])
    angle = np.full(n_gt, np.nan)
    for g in np.flatnonzero(n_assigned > 0):
        best = rows[assigned[rows] == g][np.argmax(table[rows[assigned[rows] == g], g])]
        angle[g] = res_angle[best]

    precision, recall = boundary_scores(res, gt, tolerance)
    finite = res_angle[np.isfinite(res_angle)]
    return SegmentScore(
        gt_size=gt_size,
        overlap1=overlap1.astype(np.float64),
        overlap2=overlap2.astype(np.float64),
        n_assigned=n_assigned,
        n_overlapping=n_overlapping,
        angle_deg=angle,
        assigned_gt=assigned,
        result_angle_deg=res_angle,
        mean_overlap1=float(np.mean(overlap1)) if n_gt else float("nan"),
        mean_overlap2=float(np.mean(overlap2)) if n_gt else float("nan"),
        segments_per_gt=float(np.mean(n_assigned)) if n_gt else float("nan"),
        median_angle_deg=float(np.median(finite)) if finite.size else float("nan"),
        boundary_precision=precision,
        boundary_recall=recall,
        n_gt=n_gt,
        n_result=n_res,
        n_unassigned=int(np.sum(assigned < 0)),
    )


def segment_bounds(labels: ArrayLike) -> tuple[IntArray, IntArray]:
    """First and last beam of every maximal run of equal labels >= 0, in beam order."""
    lab = np.asarray(labels, dtype=np.int64)
    if lab.size == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    change = np.flatnonzero(np.diff(lab) != 0) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [lab.size])) - 1
    keep = lab[starts] >= 0
    return starts[keep].astype(np.int64), ends[keep].astype(np.int64)


def boundary_scores(result_labels: ArrayLike, gt_labels: ArrayLike, tolerance: int = 2) -> tuple[float, float]:
    """(precision, recall) of segment starts and ends matched one-to-one within ``tolerance`` beams."""
    rs, re = segment_bounds(result_labels)
    gs, ge = segment_bounds(gt_labels)
    matched = _match_1d(rs, gs, tolerance) + _match_1d(re, ge, tolerance)
    n_res = rs.size + re.size
    n_gt = gs.size + ge.size
    precision = matched / n_res if n_res else 1.0
    recall = matched / n_gt if n_gt else 1.0
    return float(precision), float(recall)


def separates(
    result: Segmentation | ArrayLike,
    gt_labels: ArrayLike,
    target: int,
    min_overlap: float = 0.5,
    tolerance: int = 3,
) -> bool:
    """Whether GT segment ``target`` (e.g. a door) is separated from its neighbours (its walls).

    True when (a) one result segment covers at least ``min_overlap`` of the
    target's beams and (b) no result segment holds more than ``tolerance``
    beams of the target and more than ``tolerance`` beams of any other single
    GT segment (no segment spans door + wall; a boundary bleeding a few beams
    is tolerated, as in the +-2 beam boundary metric).
    """
    res = _labels_of(result)
    gt = np.asarray(gt_labels, dtype=np.int64)
    on_target = gt == target
    size = int(on_target.sum())
    if size == 0:
        raise ValueError(f"target GT segment {target} has no beams")
    found = False
    for r in np.unique(res[on_target & (res >= 0)]):
        in_r = res == r
        n_t = int(np.sum(in_r & on_target))
        if n_t >= min_overlap * size:
            found = True
        others = gt[in_r & (gt >= 0) & ~on_target]
        if n_t > tolerance and others.size and np.bincount(others).max() > tolerance:
            return False
    return found


# ---- helpers -------------------------------------------------------------------------------------


def _labels_of(result: Segmentation | ArrayLike) -> IntArray:
    if isinstance(result, Segmentation):
        return np.asarray(result.labels, dtype=np.int64)
    return np.asarray(result, dtype=np.int64)


def _beam_points(points: Scanline | ArrayLike, n: int) -> FloatArray:
    """(n, 2) per-beam points, NaN for invalid beams."""
    if isinstance(points, Scanline):
        out = np.full((points.n_beams, 2), np.nan)
        out[points.valid_index] = points.points_xy
    else:
        out = np.asarray(points, dtype=np.float64)
    if out.shape != (n, 2):
        raise ValueError(f"points must be (n_beams, 2) = ({n}, 2) to match the labels, got {out.shape}")
    return out


def _fit_normal(p: FloatArray) -> FloatArray:
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] < 2:
        return np.array([np.nan, np.nan])
    normal, _, _ = fit_line(p)
    return np.asarray(normal, dtype=np.float64)


def _gt_normals(gt: IntArray, pts: FloatArray, n_gt: int, given: ArrayLike | None) -> FloatArray:
    if given is not None:
        g = np.asarray(given, dtype=np.float64)
        if g.shape != (n_gt, 2):
            raise ValueError(f"gt_normals must have shape ({n_gt}, 2), got {g.shape}")
        return g
    return np.array([_fit_normal(pts[gt == k]) for k in range(n_gt)]).reshape(n_gt, 2)


def _result_normals(result: Segmentation | ArrayLike, res: IntArray, pts: FloatArray, n_res: int) -> FloatArray:
    if isinstance(result, Segmentation) and result.n_segments == n_res:
        return np.asarray(result.normal, dtype=np.float64).reshape(n_res, 2)
    return np.array([_fit_normal(pts[res == k]) for k in range(n_res)]).reshape(n_res, 2)


def _line_angle_deg(n1: FloatArray, n2: FloatArray) -> float:
    """Acute angle (deg) between two lines given by their normals."""
    norms = float(np.linalg.norm(n1) * np.linalg.norm(n2))
    if not np.isfinite(norms) or norms == 0.0:
        return float("nan")
    return float(np.degrees(np.arccos(min(1.0, abs(float(n1 @ n2)) / norms))))


def _match_1d(a: IntArray, b: IntArray, tol: int) -> int:
    """Maximum number of one-to-one pairs (x in a, y in b) with |x - y| <= tol (greedy sweep)."""
    a = np.sort(a)
    b = np.sort(b)
    i = j = n = 0
    while i < a.size and j < b.size:
        if a[i] < b[j] - tol:
            i += 1
        elif b[j] < a[i] - tol:
            j += 1
        else:
            n += 1
            i += 1
            j += 1
    return n
