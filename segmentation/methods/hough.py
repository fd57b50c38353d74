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
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.base import CommonParams, FloatArray, IntArray, Segmenter, _check
from segmentation.methods._consensus import BoolArray, refine_line, take_runs
from segmentation.registry import register

Votes = NDArray[np.int32]


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


@nb.njit(cache=True)
def _vote(acc: Votes, ct: FloatArray, st: FloatArray, x: float, y: float, r_max: float,
          inv_res: float, w: int) -> None:
    for k in range(ct.shape[0]):
        acc[k, int((x * ct[k] + y * st[k] + r_max) * inv_res)] += w


@nb.njit(cache=True)
def _peak(acc: Votes, suppressed: BoolArray, row_bound: IntArray) -> tuple[int, int, int]:
    """Highest unsuppressed cell (ties: lowest theta, then lowest rho) as (votes, theta bin, rho bin).

    ``row_bound[k]`` is an upper bound of row k's highest count (votes only
    ever decrease); rows are rescanned in decreasing bound order until no
    bound can beat the best found, so few rows are read per peak.
    """
    order = np.argsort(-row_bound, kind="mergesort")
    best = -1
    kb = 0
    bb = 0
    for k in order:
        if row_bound[k] < best or (row_bound[k] == best and k > kb):
            break
        row_best = -1
        row_arg = 0
        for b in range(acc.shape[1]):
            if acc[k, b] > row_best and not suppressed[k, b]:
                row_best = acc[k, b]
                row_arg = b
        row_bound[k] = row_best
        if row_best > best or (row_best == best and k < kb):
            best = row_best
            kb = k
            bb = row_arg
    return best, kb, bb


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
    n_r = int(2.0 * r_max / rho_res) + 2
    inv_res = 1.0 / rho_res
    acc = np.zeros((n_t, n_r), dtype=np.int32)
    suppressed = np.zeros((n_t, n_r), dtype=np.bool_)
    for i in range(m):
        _vote(acc, ct, st, points[i, 0], points[i, 1], r_max, inv_res, 1)
    row_bound = np.full(n_t, m, dtype=np.int64)
    labels = np.full(m, -1, dtype=np.int64)
    alive = np.ones(m, dtype=np.bool_)
    inl = np.zeros(m, dtype=np.bool_)
    seg = 0
    while True:
        best, kb, bb = _peak(acc, suppressed, row_bound)
        if best < min_votes:
            break
        for i in range(m):
            inl[i] = alive[i] and int((points[i, 0] * ct[kb] + points[i, 1] * st[kb] + r_max) * inv_res) == bb
        refine_line(points, thr, alive, inl, 2)
        seg0 = seg
        seg, taken = take_runs(points, inl, alive, labels, seg, min_len, max_gap)
        if taken == 0:
            suppressed[kb, bb] = True
            continue
        for i in range(m):
            if labels[i] >= seg0:
                _vote(acc, ct, st, points[i, 0], points[i, 1], r_max, inv_res, -1)
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
