"""Hough transform line extraction (as compared by Nguyen et al. 2005).

Every point votes, for each of the ``round(pi / theta_res)`` normal directions
``theta`` in [0, pi), for the cell of ``rho = x cos(theta) + y sin(theta)``
(scanner frame, cells ``rho_res`` wide). Peaks are taken one at a time: the
highest cell (ties: lowest theta, then lowest rho) with at least
``min_votes`` votes gives the points that voted for it, whose total-least-
squares line is refitted on its inliers (points within ``threshold``, scaled
per point by the noise model) twice; every run of at least ``min_len``
consecutive inliers becomes a segment (``segmentation.methods._consensus``)
and its points withdraw their votes. A peak that yields no such run is
suppressed and the next one is tried. Deterministic by construction.

Like RANSAC, Hough ignores scan order while voting: collinear but separate
faces share a peak, and the resolution trades accuracy against split votes.
Defaults: 1 deg x 5 cm cells (a 5 m wall misaligned by half a bin spreads
over 2.2 cm of rho) and a 1 cm inlier threshold for 3 mm noise.

Implementation (same peaks, same labels as the plain accumulator): each theta
row spans only the rho cells its points reach (a sparse 80 m scan does not pay
for twice its farthest range in every direction); every row's highest cell is
kept, so a peak is a scan of the row maxima; votes are withdrawn lazily: after
a take, a row is recounted from the alive points only when its (now upper
bound) maximum could be the next peak; the extraction stops as soon as no
``min_len`` alive, gap-free consecutive points are left, since no run could
be taken any more.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.base import (
    CommonParams,
    FloatArray,
    IntArray,
    Segmenter,
    _check,
    scaled_count,
    scaled_threshold,
)
from segmentation.methods._consensus import can_take_more, pack_alive, refine_line, take_runs
from segmentation.methods._incremental import gaps_ok
from segmentation.noise import NoiseModel
from segmentation.registry import register

Cells = NDArray[np.int32]


@dataclass(frozen=True)
class HoughParams(CommonParams):
    """theta_res: angular cell size (rad). rho_res: distance cell size (m).
    threshold: inlier distance (m) at the noise ``point_sigma``. min_votes: smallest peak."""

    theta_res: float = float(np.deg2rad(1.0))
    rho_res: float = 0.05
    threshold: float = 0.01
    min_votes: int = 10

    def validate(self) -> None:
        super().validate()
        _check(0 < self.theta_res <= np.pi / 2, "theta_res", self.theta_res, "in (0, pi/2]")
        _check(self.rho_res > 0, "rho_res", self.rho_res, "> 0")
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")
        _check(self.min_votes >= 2, "min_votes", self.min_votes, ">= 2")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values, ``threshold`` scaled to the model's noise, ``rho_res`` at least twice
        that threshold (a wall's votes stay in about one cell) and ``min_votes`` following the
        angular step like ``min_len``."""
        d = cls()
        thr = scaled_threshold(d.threshold, model)
        return {**super().from_noise(model), "threshold": thr, "rho_res": max(d.rho_res, 2.0 * thr),
                "min_votes": scaled_count(d.min_votes, model)}


@nb.njit(cache=True)
def _rho_bins(x: FloatArray, y: FloatArray, ct: FloatArray, st: FloatArray, r_max: float,
              inv_res: float) -> Cells:
    """``bins[k, i]``: the rho cell point i votes for in theta row k (cells ``rho_res`` wide from -r_max)."""
    n_t = ct.shape[0]
    m = x.shape[0]
    bins = np.empty((n_t, m), dtype=np.int32)
    for k in range(n_t):
        c = ct[k]
        s = st[k]
        for i in range(m):
            bins[k, i] = np.int32((x[i] * c + y[i] * s + r_max) * inv_res)
    return bins


@nb.njit(cache=True)
def _row_extent(bins: Cells) -> tuple[IntArray, IntArray, IntArray]:
    """Accumulator layout: row k holds only the rho cells its points reach.

    Returns (row_base, row_lo, row_len): cell (k, b) is ``votes[row_base[k] + b]``, row k
    spans bins row_lo[k] .. row_lo[k] + row_len[k] - 1. Long-range scans make few votes
    over a wide rho range: the rows follow the data, not twice the farthest range.
    """
    n_t, m = bins.shape
    row_base = np.empty(n_t, dtype=np.int64)
    row_lo = np.empty(n_t, dtype=np.int64)
    row_len = np.empty(n_t, dtype=np.int64)
    total = 0
    for k in range(n_t):
        lo = bins[k, 0]
        hi = bins[k, 0]
        for i in range(1, m):
            lo = min(lo, bins[k, i])
            hi = max(hi, bins[k, i])
        row_lo[k] = lo
        row_len[k] = hi - lo + 1
        row_base[k] = total - lo
        total += hi - lo + 1
    return row_base, row_lo, row_len


@nb.njit(cache=True)
def _first_max(a: IntArray | Cells, first: int, length: int) -> tuple[int, int]:
    """Largest of ``a[first:first + length]`` and the offset of its first occurrence."""
    row = a[first:first + length]
    best = row[0]
    for c in range(1, length):
        v = row[c]
        best = v if v > best else best  # (this form vectorises; max() does not)
    for c in range(length):
        if row[c] == best:
            return int(best), c
    return int(best), 0


@nb.njit(cache=True)
def _count_row(bins: Cells, k: int, alive_idx: IntArray, n_alive: int, votes: Cells, base: int, lo: int,
               length: int, suppressed: IntArray, n_suppressed: int) -> tuple[int, int]:
    """Recount row k's votes (cells ``votes[base + lo]`` on) from the alive points, hold the
    suppressed cells (flat indices) at -1; the row's highest cell (ties: lowest rho) as
    (votes, offset in the row)."""
    first = base + lo
    votes[first:first + length] = 0
    row = bins[k]
    # two interleaved halves: consecutive points of a wall share a cell, and back-to-back
    # increments of one cell would wait on each other
    half = n_alive // 2
    for t in range(half):
        votes[base + row[alive_idx[t]]] += 1
        votes[base + row[alive_idx[t + half]]] += 1
    if n_alive % 2:
        votes[base + row[alive_idx[n_alive - 1]]] += 1
    for j in range(n_suppressed):
        if first <= suppressed[j] < first + length:
            votes[suppressed[j]] = -1
    return _first_max(votes, first, length)


@nb.njit(cache=True)
def hough_labels(points: FloatArray, thr: FloatArray, theta_res: float, rho_res: float,
                 min_votes: int, min_len: int, max_gap: float) -> IntArray:
    """Raw labels of sequential Hough peak extraction over the points (scan order)."""
    m = points.shape[0]
    n_t = max(1, round(np.pi / theta_res))
    theta = np.arange(n_t) * (np.pi / n_t)
    ct = np.cos(theta)
    st = np.sin(theta)
    r_max = 0.0
    for i in range(m):
        r_max = max(r_max, np.hypot(points[i, 0], points[i, 1]))
    r_max += rho_res
    bins = _rho_bins(np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1]), ct, st, r_max,
                     1.0 / rho_res)
    row_base, row_lo, row_len = _row_extent(bins)
    votes = np.empty(row_base[n_t - 1] + row_lo[n_t - 1] + row_len[n_t - 1], dtype=np.int32)
    suppressed = np.empty(votes.shape[0], dtype=np.int64)  # flat indices of suppressed cells
    n_suppressed = 0
    alive_idx = np.arange(m)
    n_alive = m
    # Votes are withdrawn lazily: after a take, a stale row's counts (and row_max[k]) are
    # upper bounds until the row is recounted from the alive points.
    row_max = np.empty(n_t, dtype=np.int64)
    row_arg = np.empty(n_t, dtype=np.int64)
    fresh = np.ones(n_t, dtype=np.bool_)
    for k in range(n_t):
        row_max[k], row_arg[k] = _count_row(bins, k, alive_idx, n_alive, votes, row_base[k], row_lo[k],
                                            row_len[k], suppressed, n_suppressed)
    step_ok = gaps_ok(points, max_gap)
    labels = np.full(m, -1, dtype=np.int64)
    alive = np.ones(m, dtype=np.bool_)
    xs = np.empty(m)
    ys = np.empty(m)
    ts = np.empty(m)
    inl = np.zeros(m, dtype=np.bool_)
    n_alive = pack_alive(points, thr, alive, xs, ys, ts, alive_idx)
    seg = 0
    more = can_take_more(alive, step_ok, min_len)
    while more:
        # highest peak, ties: lowest theta (then lowest rho: row_arg); a fresh winner beats
        # every other row's upper bound, so it is the exact peak
        while True:
            best, kb = _first_max(row_max, 0, n_t)
            if fresh[kb]:
                break
            row_max[kb], row_arg[kb] = _count_row(bins, kb, alive_idx, n_alive, votes, row_base[kb], row_lo[kb],
                                                  row_len[kb], suppressed, n_suppressed)
            fresh[kb] = True
        if best < min_votes:
            break
        bb = row_lo[kb] + row_arg[kb]
        row = bins[kb]
        for t in range(n_alive):
            inl[t] = row[alive_idx[t]] == bb
        refine_line(xs, ys, ts, n_alive, inl, 2)
        seg, taken = take_runs(xs, ys, alive_idx, n_alive, inl, alive, labels, seg, min_len, max_gap)
        if taken == 0:  # never a peak again; row kb is fresh, so only its maximum moves
            suppressed[n_suppressed] = row_base[kb] + bb
            n_suppressed += 1
            votes[row_base[kb] + bb] = -1
            row_max[kb], row_arg[kb] = _first_max(votes, row_base[kb] + row_lo[kb], row_len[kb])
            continue
        n_alive = pack_alive(points, thr, alive, xs, ys, ts, alive_idx)
        fresh[:] = False
        more = can_take_more(alive, step_ok, min_len)
    return labels


@register("hough")
class Hough(Segmenter):
    """Hough transform line extraction; see the module docstring."""

    Params = HoughParams

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, HoughParams)
        thr = np.ascontiguousarray(p.threshold * scale)
        return hough_labels(points_xy, thr, p.theta_res, p.rho_res, p.min_votes, p.min_len, p.max_gap)
