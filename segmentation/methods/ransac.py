"""Sequential RANSAC line extraction (as compared by Nguyen et al. 2005).

Repeat on the points not yet taken: draw ``n_iter`` random point pairs
(seeded: ``seed``, a numpy ``Generator``, so the same input and seed give the
same output), keep the pair's line with the most inliers (points within
``threshold``, scaled per point by the noise model; ties go to the earlier
draw), refit it by total least squares on its inliers (twice), and take
every run of at least ``min_len`` consecutive inliers as a segment (see
``segmentation.methods._consensus``). Stop when fewer than ``min_len``
points remain or the best line has fewer than ``min_len`` inliers. If a best
line has enough inliers but no run long enough (scattered clutter), its
inliers are discarded (left unsegmented) so the search moves on. It also
stops as soon as no ``min_len`` alive, gap-free consecutive points are left:
no run could be taken any more, so the labels are final.

Speed without changing the result: the alive points are kept packed in scan
order (pairs are drawn by packed index, as before), so the inlier count of a
pair is one vectorised pass, and each line's ``2 * n_iter`` indices are drawn
in one batch (the same stream as one draw at a time).

RANSAC ignores scan order while fitting, so collinear but separate faces (a
wall either side of a door recessed by less than ``threshold``) share a
line: the classic extractors were found less reliable for this reason.
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
from segmentation.methods._consensus import (
    can_take_more,
    discard_inliers,
    mark_inliers,
    pack_alive,
    refine_line,
    take_runs,
)
from segmentation.methods._incremental import gaps_ok
from segmentation.noise import NoiseModel
from segmentation.registry import register


@dataclass(frozen=True)
class RansacParams(CommonParams):
    """threshold: inlier distance (m) at the noise ``point_sigma``. n_iter: pairs drawn per line.
    seed: seed of the random pairs."""

    threshold: float = 0.01
    n_iter: int = 100
    seed: int = 0

    def validate(self) -> None:
        super().validate()
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")
        _check(self.n_iter >= 1, "n_iter", self.n_iter, ">= 1")
        _check(self.seed >= 0, "seed", self.seed, ">= 0")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values plus ``threshold`` scaled to the model's noise."""
        return {**super().from_noise(model), "threshold": scaled_threshold(cls().threshold, model)}


@nb.njit(cache=True)
def _count_line(xs: FloatArray, ys: FloatArray, ts: FloatArray, q: int, ax: float, ay: float, nx: float,
                ny: float) -> int:
    """Points among the first ``q`` of (xs, ys) within ``ts`` of the line through (ax, ay) with normal (nx, ny)."""
    count = 0
    for t in range(q):
        count += abs((xs[t] - ax) * nx + (ys[t] - ay) * ny) <= ts[t]
    return count


@nb.njit(cache=True)
def ransac_labels(points: FloatArray, thr: FloatArray, n_iter: int, min_len: int, max_gap: float,
                  rng: np.random.Generator) -> IntArray:
    """Raw labels of sequential RANSAC over the points (scan order)."""
    m = points.shape[0]
    labels = np.full(m, -1, dtype=np.int64)
    alive = np.ones(m, dtype=np.bool_)
    step_ok = gaps_ok(points, max_gap)
    # the alive points packed in scan order (pairs are drawn among them by packed index)
    xs = np.empty(m)
    ys = np.empty(m)
    ts = np.empty(m)
    idx = np.empty(m, dtype=np.int64)
    inl = np.zeros(m, dtype=np.bool_)
    q = pack_alive(points, thr, alive, xs, ys, ts, idx)
    seg = 0
    while q >= min_len and can_take_more(alive, step_ok, min_len):
        best = -1
        best_a = 0
        best_b = 0
        draws = rng.integers(0, q, size=2 * n_iter)  # one batch: the stream of 2 * n_iter scalar draws
        for j in range(n_iter):
            a = draws[2 * j]
            b = draws[2 * j + 1]
            if a == b or (xs[a] == xs[b] and ys[a] == ys[b]):
                continue
            ex = xs[b] - xs[a]
            ey = ys[b] - ys[a]
            ln = np.sqrt(ex * ex + ey * ey)
            c = _count_line(xs, ys, ts, q, xs[a], ys[a], -ey / ln, ex / ln)
            if c > best:
                best = c
                best_a = a
                best_b = b
        if best < min_len:
            break
        ax = xs[best_a]
        ay = ys[best_a]
        ex = xs[best_b] - ax
        ey = ys[best_b] - ay
        ln = np.sqrt(ex * ex + ey * ey)
        mark_inliers(xs, ys, ts, q, ax, ay, -ey / ln, ex / ln, inl)
        refine_line(xs, ys, ts, q, inl, 2)
        seg, taken = take_runs(xs, ys, idx, q, inl, alive, labels, seg, min_len, max_gap)
        if taken == 0 and discard_inliers(idx, q, inl, alive) == 0:
            break
        q = pack_alive(points, thr, alive, xs, ys, ts, idx)
    return labels


@register("ransac")
class Ransac(Segmenter):
    """Sequential RANSAC; see the module docstring."""

    Params = RansacParams

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, RansacParams)
        thr = np.ascontiguousarray(p.threshold * scale)
        rng = np.random.default_rng(p.seed)
        return ransac_labels(points_xy, thr, p.n_iter, p.min_len, p.max_gap, rng)
