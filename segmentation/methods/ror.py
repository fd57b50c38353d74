"""Range-of-residuals (RoR) line segmentation (the seed paper, section 2).

A candidate point joins the current segment when, for every window size
``k = 1 .. K``, the mean residual of the candidate and the ``k - 1`` segment
points before it, measured against the segment's line, stays below
``3 sigma / sqrt(k)``: the expected mean of ``k`` residuals shrinks as
``sigma / sqrt(k)``, so a run of points that drifts off the line a little
(a door 1.5 cm behind its wall) is caught by the longer windows although
each single point is within ``3 sigma``.

Reading of Algorithm 1
----------------------
Algorithm 1 in the paper is garbled by the text conversion; the prose of
section 2 is the specification. Every ambiguous step, as implemented here:

* **Initial line: N + 1 points.** The prose says "the current point together
  with the N next points", and the listing advances ``pt += N + 1`` after an
  accepted start, so a segment starts from ``N + 1`` points (4 for N = 3).
  They are fitted by total least squares (orthogonal residuals, the same fit
  used for the segment's line afterwards).
* **Initial acceptance: mean of absolute residuals < sigma** (strict, as both
  the prose and the listing write ``<``). The absolute value is used for both
  statistics: the signed residuals of a least-squares fit average to exactly
  zero, so a signed test would accept everything. Every point of the start
  must also be within ``max_gap`` of its predecessor. A rejected start labels
  its first point unsegmented and the start moves on by one point.
* **Line of the test: the segment's line without the candidate.** The prose
  says the point "is added to the segment and the line parameters are
  recomputed" only *after* all checks pass, so the residuals are taken
  against the line of the segment's current points. (Refitting with the
  candidate would let an outlier pull the line towards itself: exactly the
  weakness of line tracking's "refit" variant the paper discusses.)
* **Window of size j: the candidate plus the last j - 1 segment points**,
  i.e. ``points[pt - j + 1 .. pt]``: the listing's inner loop runs ``j`` from
  ``pt`` down, and the prose lists "the next point itself, then the next point
  and the last point contained in the segment, and so forth".
* **Window count K = round(percentage * len(segment)), at least 1.** The
  listing's ``endpt = pt - round(percentage * len(segment))`` with
  ``j > endpt`` gives exactly ``round(...)`` windows. ``len(segment)`` counts
  the segment's points without the candidate. Rounding is half away from zero
  (C/Matlab ``round``, not Python's banker's rounding). K is at least 1 so the
  candidate alone is always tested against ``3 sigma`` (the first residual
  the prose names); with N = 3 and 15 %, the first candidates of a new
  segment (4 points) are tested with K = round(0.6) = 1.
* **Comparisons are strict:** window k passes when its mean residual is
  ``< 3 sigma / sqrt(k)``. A point is added only if all K windows pass.
* **Statistic.** ``statistic="abs"`` (default) averages absolute residuals:
  this is what the paper's values imply (sigma = 9.5 mm for 3 mm noise: with
  absolute residuals, whose mean stays near 0.8 x the noise for any k, a
  small sigma oversegments, as fig. 7 shows for sigma < 8 mm; with signed
  residuals the threshold would sit 3 sigma / noise = 9.5 standard deviations
  away for every k and small sigma could not oversegment).
  ``statistic="signed"`` averages signed residuals and compares their absolute
  mean: the statistically exact reading of "the expected average of n
  residuals is sigma / sqrt(n)", where sigma is then the point noise.
* **min_len: segments with >= min_len points are kept.** The prose says
  "greater than minLen"; the library's convention for every segmenter is
  ">= min_len" (so min_len is the fewest points of a kept segment). Set
  ``min_len = 16`` for the paper's strict reading of 15.
* **The rejected point starts the next segment** together with its N next
  points ("the point is used to initiate a new segment (together with the
  next N points)"); it is not dropped. If that start is rejected, it becomes
  unsegmented and the start moves on by one point.
* **Depth jumps:** a candidate farther than ``max_gap`` from its predecessor
  is rejected like a failed test (not in the paper; the library's common
  guarantee that points across a jump never share a segment).

Checked against the paper's behaviour (sigma swept from 4 to 16 mm, 3 mm
noise, percentage 15 %). On a hand-made figure-1-like room with steep door
edges (``tests/seg_scenes.py``, 20 seeds, ``tests/test_ror.py``'s criterion)
combined RoR separates the door for sigma = 4-13 mm and the board for 4-16 mm,
with or without the parent check below. On the synthetic figure-1 scanline
with the sloped door frame (``simulation.scanline.figure1``, 50 seeds,
``segmentation.metrics.separates`` in >= 95 % of seeds, ``scripts/
paper_figures.py``) it separates the door for sigma = 4.0-10.0 mm and the board
for 4.0-12.5 mm; with the paper's combination rule only the door range shrinks
to 4.0-8.5 mm (the default 9.5 mm separates the door in 66 % of the seeds, 100 % with the check).
Walls oversegment below about 5 mm (the absolute mean residual, about 2.4 mm
plus fit error, crosses 3 sigma / sqrt(k) in the long windows of long walls)
and the door merges above (about (3 sigma / 1.5 cm)^2 door points must enter
the windows before the split, and the line tilts into the door first). The
paper reports 8-11 mm (door) and 7-14 mm (board) on real data, whose walls are
not perfectly flat: the same shape, with the default sigma = 9.5 mm inside both
ranges. Forward alone loses the door earlier (the paper's "upper edge" problem
that the combination fixes).

Our addition: ``parent_check`` (default on; only acts with ``direction =
"combined"``; ``parent_check=False`` is the paper's section 2.2 rule exactly).
On figure-1-like scenes the combination can keep a transition piece: the
forward run overshoots the wall into the sloped door frame and door leaf (its
windows use few door points), the backward run overshoots the door into the
frame and wall, and the paper's rule turns the overlap of the two overshoots
into a 15-17 point piece of wall, frame and door that passes ``min_len`` and
gives a tilted line. The check applies the paper's own threshold rule to each
combined piece as one window: the forward run reached the piece with the line
of its forward parent segment's points *before* the piece, the backward run
with the line of its backward parent's points *after* it; the piece's mean
signed residual against each of these lines (the residual of its centroid)
must stay below ``3 sigma / sqrt(n)`` for its ``n`` points, widened in
quadrature by that line's own error at the piece (offset and slope error of a
TLS line of the rest's points with the range noise ``point_sigma``:
``3 sqrt(sigma^2 / n + point_sigma^2 (1 / n_rest + t^2 / S_rest))``, ``t``
the distance along the line from the rest's centroid, ``S_rest`` its scatter
along the line). A rest shorter than ``n_init + 1`` points is not tested.
Signed, not absolute, residuals: the mean absolute residual of ``n`` noisy
points does not shrink with ``n`` and would reject every long piece. A piece
that fails either test is dropped (unsegmented), which is how the combination
treats disagreement everywhere else. Pieces that are whole parents in both
runs are never tested (no rest); a wall half that one run wrongly merged with
a door is tested against the door's line and dropped if it does not fit it.
On the synthetic figure-1 scanline (3 mm noise, defaults) the door is
separated in 99 of 100 seeds with the check and 68 of 100 without.

Extensions (issue 2): ``direction`` (forward / backward / combined by the
paper's section 2.2 rule, done by the base class), ``stride`` (test only
window sizes 1, 1 + s, 1 + 2 s, ... and always the full window K: the
paper's future-work idea; 1 = the paper), and the range-dependent noise model
of the base class: with ``sigma(r) = point_sigma + noise_slope * r`` and
``scale_i = sigma(r_i) / point_sigma``, window k's threshold becomes
``3 sigma * mean(scale over the window) / sqrt(k)`` and the start's threshold
``sigma * mean(scale over the start)``. With ``noise_slope = 0`` (default)
every scale is 1 and the thresholds are the paper's.

Cost: each window's mean is accumulated from the previous one, so a point
costs O(K) and a segment of L points O(percentage * L^2 / 2). A combined run
does both passes, the combination and the check in one compiled call; the
check costs O(points) per piece.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numba as nb
import numpy as np

from segmentation.base import (
    FloatArray,
    IntArray,
    Segmenter,
    SequentialParams,
    _check,
    independent_share,
    reverse_rows,
    scaled_threshold,
)
from segmentation.labels import combine_runs, finalize_runs, reverse_labels
from segmentation.methods._incremental import gaps_ok, line_from_sums
from segmentation.noise import NoiseModel
from segmentation.registry import register

Statistic = Literal["abs", "signed"]


@dataclass(frozen=True)
class RoRParams(SequentialParams):
    """Parameters of the range-of-residuals segmenter (names as in the paper).

    n_init: N, a segment starts from N + 1 points.
    sigma: the metric threshold sigma (m) of the start test and of 3 sigma / sqrt(k).
    percentage: fraction of the segment's points tested as windows (K = round(p * len)).
    statistic: ``abs`` (mean of absolute residuals) or ``signed`` (|mean of signed residuals|).
    stride: test window sizes 1, 1 + stride, ... and the full window only.
    parent_check: with ``direction="combined"``, drop combined pieces that do not fit the lines
    their runs reached them with (module docstring; our addition); False = the paper's rule.
    """

    n_init: int = 3
    sigma: float = 0.0095
    percentage: float = 0.15
    min_len: int = 15
    direction: Literal["forward", "backward", "combined"] = "combined"
    statistic: Statistic = "abs"
    stride: int = 1
    parent_check: bool = True

    def validate(self) -> None:
        super().validate()
        _check(self.n_init >= 2, "n_init", self.n_init, ">= 2")
        _check(self.sigma > 0, "sigma", self.sigma, "> 0")
        _check(0 < self.percentage <= 1, "percentage", self.percentage, "in (0, 1]")
        _check(self.stride >= 1, "stride", self.stride, ">= 1")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values plus ``sigma`` scaled to the model's noise (the paper's 9.5 mm for 3 mm),
        times the noise's independent share (``independent_share``): RoR's start test and windows
        judge consecutive points' residuals against a line the neighbouring points fixed, so a
        correlated error moves line and point together and only the beam-to-beam part is noise
        to them; with the full, correlated noise the thresholds let segments follow the error's
        slow bends (the URG bag's /front_scan: median residual 1.70 times the noise, 1.1 with it).
        White noise: a share of 1, the paper's ratio."""
        sigma = scaled_threshold(cls().sigma, model) * independent_share(model)
        return {**super().from_noise(model), "sigma": sigma}


@nb.njit(cache=True, inline="always")
def _windows_fast(x: FloatArray, y: FloatArray, j: int, kk: int, nx: float, ny: float, c0: float,
                  tk: FloatArray) -> bool:
    """All windows 1..kk pass: abs statistic, constant noise, stride 1 (the paper's case).

    Window k holds points j, j-1, .., j-k+1 and passes when sum |r| < tk[k] = 3 sigma sqrt(k).
    Unrolled by four with the partial sums formed first, so the running sum's
    dependency chain advances once per four windows.
    """
    acc = 0.0
    k = 1
    while k + 3 <= kk:
        i = j - k + 1
        r1 = abs(nx * x[i] + ny * y[i] - c0)
        r2 = abs(nx * x[i - 1] + ny * y[i - 1] - c0)
        r3 = abs(nx * x[i - 2] + ny * y[i - 2] - c0)
        r4 = abs(nx * x[i - 3] + ny * y[i - 3] - c0)
        s12 = r1 + r2
        s1234 = s12 + (r3 + r4)
        if not ((acc + r1 < tk[k]) & (acc + s12 < tk[k + 1]) & (acc + (s12 + r3) < tk[k + 2])
                & (acc + s1234 < tk[k + 3])):
            return False
        acc += s1234
        k += 4
    while k <= kk:
        i = j - k + 1
        acc += abs(nx * x[i] + ny * y[i] - c0)
        if not acc < tk[k]:
            return False
        k += 1
    return True


@nb.njit(cache=True)  # not inlined: inlining it next to the fast path slows the fast path down
def _windows_general(x: FloatArray, y: FloatArray, j: int, kk: int, nx: float, ny: float, c0: float,
                     ps: FloatArray, sqrt_k: FloatArray, thr3: float, stride: int, signed: bool) -> bool:
    """All tested windows pass, for any statistic, stride and noise scale.

    Window k passes when |mean residual| < 3 sigma mean(scale) / sqrt(k), i.e.
    |sum r| sqrt(k) < 3 sigma sum(scale); tested are k = 1, 1 + stride, ... and kk.
    """
    t_end = ps[j + 1]
    acc = 0.0
    next_test = 1
    for k in range(1, kk + 1):
        i = j - k + 1
        r = nx * x[i] + ny * y[i] - c0
        acc += r if signed else abs(r)
        if k == next_test or k == kk:
            next_test += stride
            if not abs(acc) * sqrt_k[k] < thr3 * (t_end - ps[i]):
                return False
    return True


@nb.njit(cache=True)
def ror_labels(
    points: FloatArray,
    scale: FloatArray,
    n_init: int,
    sigma: float,
    percentage: float,
    stride: int,
    signed: bool,
    max_gap: float,
) -> IntArray:
    """Raw labels (-1 or segment ids) of one RoR pass over ``points`` in the given order.

    ``points`` (m, 2) in the scanner frame; ``scale[i]`` multiplies point i's
    thresholds (see the module docstring).
    """
    m = points.shape[0]
    labels = np.full(m, -1, dtype=np.int64)
    x = np.ascontiguousarray(points[:, 0])
    y = np.ascontiguousarray(points[:, 1])
    near = gaps_ok(points, max_gap)
    # prefix sums of the scales: sum over points a..b-1 = ps[b] - ps[a]
    ps = np.zeros(m + 1)
    constant = True
    for i in range(m):
        ps[i + 1] = ps[i] + scale[i]
        constant &= scale[i] == 1.0
    fast = constant and stride == 1 and not signed
    sqrt_k = np.sqrt(np.arange(m + 2, dtype=np.float64))
    thr3 = 3.0 * sigma
    tk = thr3 * sqrt_k
    seg = 0
    pt = 0
    while pt + n_init < m:
        # ---- start: points pt .. pt + N, no depth jump, mean |residual| < sigma mean(scale)
        i_end = pt + n_init
        gap = False
        for i in range(pt + 1, i_end + 1):
            gap |= not near[i]
        if gap:
            pt += 1
            continue
        # sums about the start's first point (no cancellation far from the scanner)
        ox = x[pt]
        oy = y[pt]
        n = 0.0
        su = 0.0
        sv = 0.0
        suu = 0.0
        svv = 0.0
        suv = 0.0
        for i in range(pt, i_end + 1):
            u = x[i] - ox
            v = y[i] - oy
            n += 1.0
            su += u
            sv += v
            suu += u * u
            svv += v * v
            suv += u * v
        mu, mv, nx, ny = line_from_sums(n, su, sv, suu, svv, suv)
        c0 = nx * (mu + ox) + ny * (mv + oy)
        acc = 0.0
        for i in range(pt, i_end + 1):
            acc += abs(nx * x[i] + ny * y[i] - c0)
        if not acc < sigma * (ps[i_end + 1] - ps[pt]):
            pt += 1
            continue
        for i in range(pt, i_end + 1):
            labels[i] = seg
        j = i_end + 1
        # ---- growth: candidate j against the line of the segment's points (without j)
        while j < m and near[j]:
            # the line with j included, computed before the test (independent of its outcome,
            # so it overlaps with the windows) and used only if j is accepted
            u = x[j] - ox
            v = y[j] - oy
            n2 = n + 1.0
            su2 = su + u
            sv2 = sv + v
            suu2 = suu + u * u
            svv2 = svv + v * v
            suv2 = suv + u * v
            mu2, mv2, nx2, ny2 = line_from_sums(n2, su2, sv2, suu2, svv2, suv2)
            # K = round(percentage * len(segment)), half up, at least 1
            kk = max(int(percentage * n + 0.5), 1)
            if fast:
                ok = _windows_fast(x, y, j, kk, nx, ny, c0, tk)
            else:
                ok = _windows_general(x, y, j, kk, nx, ny, c0, ps, sqrt_k, thr3, stride, signed)
            if not ok:
                break
            n, su, sv, suu, svv, suv = n2, su2, sv2, suu2, svv2, suv2
            nx = nx2
            ny = ny2
            c0 = nx * (mu2 + ox) + ny * (mv2 + oy)
            labels[j] = seg
            j += 1
        seg += 1
        pt = j
    return labels


@nb.njit(cache=True)
def _piece_vs_rest(points: FloatArray, p0: int, p1: int, cx: float, cy: float) -> tuple[float, float]:
    """The piece's centroid (cx, cy) against the TLS line of points ``p0 .. p1`` (the rest).

    Returns (|signed residual of the centroid|, v) where ``v = 1 / n_rest + t^2 / S`` is the
    variance of the rest line's position at the centroid in units of the point variance: its
    offset error and its slope error carried over the distance ``t`` along the line from the
    rest's centroid (``S``: the rest's scatter along its line).
    """
    ox = points[p0, 0]
    oy = points[p0, 1]
    n = 0.0
    su = 0.0
    sv = 0.0
    suu = 0.0
    svv = 0.0
    suv = 0.0
    for i in range(p0, p1 + 1):
        u = points[i, 0] - ox
        v = points[i, 1] - oy
        n += 1.0
        su += u
        sv += v
        suu += u * u
        svv += v * v
        suv += u * v
    mu, mv, nx, ny = line_from_sums(n, su, sv, suu, svv, suv)
    du = cx - ox - mu
    dv = cy - oy - mv
    sxx = suu - mu * su
    syy = svv - mv * sv
    sxy = suv - mu * sv
    # scatter along the line = trace - scatter across it
    along = (sxx + syy) - (nx * nx * sxx + 2.0 * nx * ny * sxy + ny * ny * syy)
    t = -ny * du + nx * dv
    v = 1.0 / n + (t * t / along if along > 0.0 else np.inf)
    return abs(nx * du + ny * dv), v


@nb.njit(cache=True)
def combine_checked(
    raw_fwd: IntArray,
    raw_bwd_reversed: IntArray,
    points: FloatArray,
    scale: FloatArray,
    sigma: float,
    point_sigma: float,
    n_init: int,
    max_gap: float,
    min_len: int,
    check: bool,
) -> tuple[IntArray, IntArray, IntArray]:
    """Forward and backward runs combined (section 2.2) and, with ``check``, each combined
    piece tested against the rest of its forward and backward parent segments (module docstring).

    Returns final labels and each segment's first and last point, as ``finalize_runs``.
    """
    fwd, f_first, _ = finalize_runs(raw_fwd, points, max_gap, min_len)
    bwd, _, b_last = finalize_runs(reverse_labels(raw_bwd_reversed), points, max_gap, min_len)
    comb, first, last = finalize_runs(combine_runs(fwd, bwd), points, max_gap, min_len)
    if not check or first.shape[0] == 0:
        return comb, first, last
    keep = np.ones(first.shape[0], dtype=np.bool_)
    min_rest = n_init + 1
    for k in range(first.shape[0]):
        i0 = first[k]
        i1 = last[k]
        f = fwd[i0]
        b = bwd[i0]
        n = i1 - i0 + 1
        cx = 0.0
        cy = 0.0
        ssum = 0.0
        for i in range(i0, i1 + 1):
            cx += points[i, 0]
            cy += points[i, 1]
            ssum += scale[i]
        cx /= n
        cy /= n
        mscale = ssum / n
        # the paper's threshold 3 sigma / sqrt(n) for the mean of the piece's n residuals, widened by
        # the error of the rest's line at the piece (point_sigma: the range noise of the line covariances)
        t_mean = (sigma * mscale) ** 2 / n
        t_line = (point_sigma * mscale) ** 2
        # the forward run reached the piece with the line of its parent's points before it,
        # the backward run with the line of its parent's points after it
        if i0 - f_first[f] >= min_rest:
            dev, v = _piece_vs_rest(points, f_first[f], i0 - 1, cx, cy)
            keep[k] &= dev * dev < 9.0 * (t_mean + t_line * v)
        if b_last[b] - i1 >= min_rest:
            dev, v = _piece_vs_rest(points, i1 + 1, b_last[b], cx, cy)
            keep[k] &= dev * dev < 9.0 * (t_mean + t_line * v)
    if np.all(keep):
        return comb, first, last
    out = np.full(comb.shape[0], -1, dtype=np.int64)
    for k in range(first.shape[0]):
        if keep[k]:
            for i in range(first[k], last[k] + 1):
                out[i] = k
    return finalize_runs(out, points, max_gap, min_len)


@nb.njit(cache=True)
def ror_combined(
    points: FloatArray,
    scale: FloatArray,
    n_init: int,
    sigma: float,
    percentage: float,
    stride: int,
    signed: bool,
    max_gap: float,
    point_sigma: float,
    min_len: int,
    check: bool,
) -> tuple[IntArray, IntArray, IntArray]:
    """The forward pass, the backward pass (the forward pass on the reversed points) and their
    combination in one compiled call; returns final labels, first and last point per segment."""
    raw_fwd = ror_labels(points, scale, n_init, sigma, percentage, stride, signed, max_gap)
    m = points.shape[0]
    rscale = np.empty(m)
    for i in range(m):
        rscale[i] = scale[m - 1 - i]
    raw_bwd = ror_labels(reverse_rows(points), rscale, n_init, sigma, percentage, stride, signed, max_gap)
    return combine_checked(raw_fwd, raw_bwd, points, scale, sigma, point_sigma, n_init, max_gap, min_len, check)


@register("ror")
class RangeOfResiduals(Segmenter):
    """Range-of-residuals segmentation; see the module docstring for the reading of Algorithm 1."""

    Params = RoRParams
    sequential = True

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, RoRParams)
        return ror_labels(
            points_xy, scale, p.n_init, p.sigma, p.percentage, p.stride, p.statistic == "signed", p.max_gap
        )

    def _final_labels(self, pts: FloatArray, scale: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        p = self.params
        assert isinstance(p, RoRParams)
        if p.direction != "combined":
            return super()._final_labels(pts, scale)
        # both passes and the combination in one compiled call (no per-call dispatch in between)
        return ror_combined(pts, scale, p.n_init, p.sigma, p.percentage, p.stride,  # type: ignore[no-any-return]
                            p.statistic == "signed", p.max_gap, p.point_sigma, p.min_len, p.parent_check)
