"""Successive edge following (SEF) segmentation, with an optional corner criterion.

The literature's part (Siadat et al. 1997, as summarised by the seed paper,
section 1.1): SEF works on the polar measurements; walking the scan, a point
joins the current segment while the difference between its range and the
previous point's range, ``d_i = r_i - r_{i-1}``, stays within ``threshold``;
a larger difference (an "edge", a depth jump) starts a new segment. That
criterion has no linearity test: it separates objects at range
discontinuities but never splits a corner between two walls, whose ranges are
continuous. ``corner_threshold=0`` gives exactly this classic SEF.

Our addition (on by default): successive edge following applied once more,
to the range *differences*. A corner is a kink in the range profile: the range
is continuous there but its slope ``d_i`` changes. The kink statistic at
point ``i`` is the change between the range differences on either side,
taken over ``h = corner_span`` beams::

    K_i = (r_{i+h} - r_i) - (r_i - r_{i-h})

(``h = 1``: the discrete second difference ``d_{i+1} - d_i``; ``h > 1``: the
change between the sums of ``h`` successive differences). Point ``i`` is a
corner when ``|K_i|`` exceeds ``corner_threshold`` and is the largest within
``i - h .. i + h`` (ties: all of them). The corner point is the vertex shared
by both faces, so it is left unsegmented: the segments end at ``i - 1`` and
start at ``i + 1``. Both tests are symmetric, so forward, backward and
combined runs coincide. ``K`` is not evaluated where a range jump lies within
``i - h .. i + h`` (the classic criterion already cuts there).

Default corner threshold: ``K_i`` combines three independent ranges with
weights 1, -2, 1, so for range noise sigma its standard deviation is
``sqrt(6) sigma`` for every ``h``; the default ``3 sqrt(6) point_sigma``
(22 mm for 3 mm) is a 3-sigma test. The signal grows with ``h``: a corner
whose walls turn by ``tau`` changes the range difference by at least
``2 r dtheta tan(tau / 2)`` (about 15 mm at 3 m for 60 deg, 0.25 deg beams),
and ``K`` reaches about ``h`` times that. With ``h = 1`` a corner falling
between two beams splits its kink over two second differences and corners
like that are missed; hence the default ``h = 2``. The price is the
curvature of a flat wall's range profile, ``h^2 r (1 + sin^2 a) / cos^2 a
dtheta^2`` at incidence ``a`` (about 11 mm at 5 m and 75 deg with h = 2),
which limits ``h`` (grazing walls are cut for large ``h``). Shallower, nearer
or noisier corners are missed: this is still an edge follower, not a line fitter.

Both thresholds are scaled per point by the noise model (the largest scale of
the points involved); the base class additionally cuts at point distances
over ``max_gap`` and drops runs shorter than ``min_len``. Sequential, so
``direction`` is accepted; both criteria are symmetric, so forward, backward
and combined runs coincide. Default jump threshold: 10 cm, which keeps walls
seen up to about 80 deg incidence at 4 m (range step r * 0.25 deg *
tan(incidence)) in one piece on a UTM-30LX while 3 mm noise (4 mm on
differences) is far below it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np

from segmentation.base import (
    FloatArray,
    IntArray,
    Segmenter,
    SequentialParams,
    _check,
)
from segmentation.noise import REFERENCE_ANGLE_STEP, NoiseModel
from segmentation.registry import register

#: default corner threshold in units of the point noise: 3 standard deviations of a second difference
CORNER_SIGMAS = 3.0 * math.sqrt(6.0)
#: noise-derived jump threshold, at least: 8 standard deviations of a range difference
JUMP_SIGMAS = 8.0 * math.sqrt(2.0)


@dataclass(frozen=True)
class SEFParams(SequentialParams):
    """threshold: largest range difference (m) between successive points of a segment.
    corner_threshold: largest change (m) between the range differences before and after a point
    (over ``corner_span`` beams) inside a segment; ``None`` = ``3 sqrt(6) point_sigma``; 0 = no corner
    criterion (the classic SEF).
    corner_span: h, the number of beams each side of the kink statistic spans (1 = second difference)."""

    threshold: float = 0.1
    corner_threshold: float | None = None
    corner_span: int = 2

    def validate(self) -> None:
        super().validate()
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")
        if self.corner_threshold is not None:
            _check(self.corner_threshold >= 0, "corner_threshold", self.corner_threshold, ">= 0 (0 = off)")
        _check(self.corner_span >= 1, "corner_span", self.corner_span, ">= 1")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values; the jump ``threshold`` follows the beam spacing (a grazing wall's range
        step grows with the angular step) and stays ``JUMP_SIGMAS`` noise widths of a range
        difference; ``corner_span`` shrinks at coarse steps (a flat wall's range curvature grows
        with the step squared)."""
        d = cls()
        step_ratio = model.angle_step / REFERENCE_ANGLE_STEP
        return {**super().from_noise(model),
                "threshold": max(d.threshold * step_ratio, JUMP_SIGMAS * model.sigma0),
                "corner_span": max(1, math.floor(d.corner_span / step_ratio + 0.5))}

    @property
    def corner(self) -> float:
        """The corner threshold in metres (0 = off)."""
        return CORNER_SIGMAS * self.point_sigma if self.corner_threshold is None else self.corner_threshold


@nb.njit(cache=True)
def sef_labels(points: FloatArray, scale: FloatArray, threshold: float, corner: float, span: int) -> IntArray:
    """Raw labels: a new segment starts at every range jump over ``threshold``; with
    ``corner > 0`` every kink point (see the module docstring) is unsegmented."""
    m = points.shape[0]
    r = np.empty(m)
    for i in range(m):
        r[i] = math.hypot(points[i, 0], points[i, 1])
    # jump[i]: a range jump between points i - 1 and i; njump: prefix count of jumps
    jump = np.zeros(m, dtype=np.bool_)
    njump = np.zeros(m + 1, dtype=np.int64)
    for i in range(1, m):
        jump[i] = abs(r[i] - r[i - 1]) > threshold * max(scale[i], scale[i - 1])
        njump[i + 1] = njump[i] + jump[i]
    kink = np.zeros(m, dtype=np.bool_)
    if corner > 0.0 and m > 2 * span:
        h = span
        # excess[i] = |(r[i+h] - r[i]) - (r[i] - r[i-h])| / scale over threshold (<= 0: no kink)
        excess = np.zeros(m)
        for i in range(h, m - h):
            if njump[i + h + 1] - njump[i - h + 1] > 0:
                continue  # a jump inside i-h .. i+h: the classic criterion cuts there
            s = max(scale[i - h], max(scale[i], scale[i + h]))
            excess[i] = abs(r[i + h] - 2.0 * r[i] + r[i - h]) - corner * s
        for i in range(h, m - h):
            if excess[i] <= 0.0:
                continue
            peak = True
            for q in range(i - h, i + h + 1):
                if excess[q] > excess[i]:
                    peak = False
                    break
            kink[i] = peak
    labels = np.empty(m, dtype=np.int64)
    seg = 0
    for i in range(m):
        if kink[i]:
            labels[i] = -1
            seg += 1
            continue
        if i > 0 and jump[i]:
            seg += 1
        labels[i] = seg
    return labels


@register("sef")
class SEF(Segmenter):
    """Successive edge following on ranges and (by default) on range differences; see the module docstring."""

    Params = SEFParams
    sequential = True

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, SEFParams)
        return sef_labels(points_xy, scale, p.threshold, p.corner, p.corner_span)
