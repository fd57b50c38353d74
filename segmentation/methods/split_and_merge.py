"""Split-and-merge segmentation: least-squares split, chi-square merge of collinear neighbours.

Split (Pavlidis and Horowitz 1974; Nguyen et al. 2005): fit the total-least-
squares line of an interval; while its farthest point lies more than
``threshold`` (scaled per point by the noise model) from that line, split
there and recurse. When the farthest point is within two points of an end a
split there would peel points off one at a time: an outlying end point
(its neighbour fits) is split off alone, otherwise the interval is split at
the farthest point from its chord (the IEPF rule, which finds the corner
when a short second wall at the end pulls the fit).

Merge (as in ROS ``laser_line_extraction``): walking the kept intervals
(>= ``min_len`` points) in scan order, two consecutive ones in the same
chunk (no depth jump between them) with fewer than ``min_len`` points of
dropped intervals between them (which then join the merged segment, as an
outlier does that caused a split) are merged when their lines agree: the
(angle, offset) difference ``d`` of
the two TLS lines, with covariances ``C1``, ``C2`` propagated from the point
noise by ``segmentation.lines.fit_segments``, passes the chi-square test
``d' (C1 + C2)^-1 d <= chi2_2(1 - merge_alpha) = -2 ln(merge_alpha)``. The
merged line is refitted and compared with the next interval. ``merge=False``
gives the split step alone.

Depth jumps over ``max_gap`` cut the scanline before splitting; split points
go to the neighbour whose line they fit (``segmentation.methods._split``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np

from segmentation.base import (
    CommonParams,
    FloatArray,
    IntArray,
    Segmenter,
    _check,
    scaled_threshold,
)
from segmentation.lines import fit_segments
from segmentation.methods._split import assign_labels, split_intervals
from segmentation.noise import NoiseModel
from segmentation.registry import register


@dataclass(frozen=True)
class SplitAndMergeParams(CommonParams):
    """threshold: largest accepted point-to-line distance (m) at the noise ``point_sigma``.
    merge: run the merge step. merge_alpha: significance of the chi-square collinearity test
    (smaller = merges more readily)."""

    threshold: float = 0.011
    merge: bool = True
    merge_alpha: float = 0.05

    def validate(self) -> None:
        super().validate()
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")
        _check(0.0 < self.merge_alpha < 1.0, "merge_alpha", self.merge_alpha, "in (0, 1)")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values plus ``threshold`` scaled to the model's noise."""
        return {**super().from_noise(model), "threshold": scaled_threshold(cls().threshold, model)}


@nb.njit(cache=True)
def line_chi2(n1: FloatArray, r1: float, c1: FloatArray, n2: FloatArray, r2: float, c2: FloatArray) -> float:
    """Mahalanobis distance^2 between two lines given as (unit normal, offset, 2x2 (angle, offset) cov)."""
    dot = n1[0] * n2[0] + n1[1] * n2[1]
    s01 = c2[0, 1]
    if dot < 0.0:
        # same line with the opposite normal: (angle + pi, -offset); the correlation changes sign
        dot = -dot
        r2 = -r2
        s01 = -s01
        cross = -(n1[0] * n2[1] - n1[1] * n2[0])
    else:
        cross = n1[0] * n2[1] - n1[1] * n2[0]
    da = np.arctan2(cross, dot)
    dr = r2 - r1
    a = c1[0, 0] + c2[0, 0]
    b = c1[0, 1] + s01
    d = c1[1, 1] + c2[1, 1]
    det = a * d - b * b
    if not det > 0.0:
        return np.inf
    return (d * da * da - 2.0 * b * da * dr + a * dr * dr) / det


@nb.njit(cache=True)
def _fit(points: FloatArray, a: int, b: int, sigma_pts: FloatArray) -> tuple[FloatArray, float, FloatArray]:
    """(normal, offset, (angle, offset) covariance) of the TLS line of points a..b."""
    fa = np.full(1, a, dtype=np.int64)
    fb = np.full(1, b, dtype=np.int64)
    nm, of, _, _, _, _, cv = fit_segments(points, fa, fb, sigma_pts)
    return nm[0].copy(), of[0], cv[0].copy()


@nb.njit(cache=True)
def merge_collinear(points: FloatArray, first: IntArray, last: IntArray, sigma_pts: FloatArray,
                    min_len: int, crit: float) -> tuple[IntArray, IntArray]:
    """Greedy scan-order merge of kept intervals whose lines pass the chi-square test.

    Two kept intervals (>= ``min_len`` points) merge when they are consecutive
    among the kept ones, linked by shared boundary points (same chunk), fewer
    than ``min_len`` points of dropped short intervals lie between them (those
    join the merged interval), and their lines agree. The lines compared leave
    out the boundary points the intervals share: a split point is the one the
    split found farthest from a line, and at the end of a fit its leverage
    biases both lines against each other.
    """
    q = first.shape[0]
    out_a = np.empty(q, dtype=np.int64)
    out_b = np.empty(q, dtype=np.int64)
    n_out = 0
    nxt = 0  # first leaf neither emitted nor absorbed
    cur_a = -1
    cur_b = -1
    cur_ta = -1
    cur_leaf = -1
    cur_n = np.zeros(2)
    cur_r = 0.0
    cur_c = np.zeros((2, 2))
    for j in range(q):
        if last[j] - first[j] + 1 < min_len:
            continue
        ta = first[j] + 1 if j > 0 and last[j - 1] == first[j] else first[j]
        tb = last[j] - 1 if j + 1 < q and first[j + 1] == last[j] else last[j]
        if tb - ta < 1:  # too short to leave its boundary points out (min_len 2 or 3)
            ta = first[j]
            tb = last[j]
        if cur_a >= 0:
            chained = first[j] - cur_b - 1 < min_len
            for t in range(cur_leaf + 1, j + 1):
                if last[t - 1] != first[t]:
                    chained = False
            if chained:
                nj, rj, cj = _fit(points, ta, tb, sigma_pts)
                if line_chi2(cur_n, cur_r, cur_c, nj, rj, cj) <= crit:
                    cur_b = last[j]
                    cur_leaf = j
                    nxt = j + 1
                    cur_n, cur_r, cur_c = _fit(points, cur_ta, tb, sigma_pts)
                    continue
            out_a[n_out] = cur_a
            out_b[n_out] = cur_b
            n_out += 1
        for t in range(nxt, j):
            out_a[n_out] = first[t]
            out_b[n_out] = last[t]
            n_out += 1
        cur_a = first[j]
        cur_b = last[j]
        cur_ta = ta
        cur_leaf = j
        nxt = j + 1
        cur_n, cur_r, cur_c = _fit(points, ta, tb, sigma_pts)
    if cur_a >= 0:
        out_a[n_out] = cur_a
        out_b[n_out] = cur_b
        n_out += 1
    for t in range(nxt, q):
        out_a[n_out] = first[t]
        out_b[n_out] = last[t]
        n_out += 1
    return out_a[:n_out].copy(), out_b[:n_out].copy()


@register("split_and_merge")
class SplitAndMerge(Segmenter):
    """Split-and-merge; see the module docstring."""

    Params = SplitAndMergeParams

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, SplitAndMergeParams)
        thr = np.ascontiguousarray(p.threshold * scale)
        first, last = split_intervals(points_xy, thr, p.max_gap, p.min_len, True)
        if p.merge:
            sigma = np.ascontiguousarray(p.point_sigma * scale)
            crit = -2.0 * np.log(p.merge_alpha)
            first, last = merge_collinear(points_xy, first, last, sigma, p.min_len, crit)
        return assign_labels(points_xy, thr, first, last, p.min_len)
