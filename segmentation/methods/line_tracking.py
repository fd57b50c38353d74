"""Line tracking (incremental) segmentation.

Starting from ``n_init`` points whose TLS line fits within ``threshold``, the
next point joins the segment while its distance to a line stays within
``threshold`` (scaled by the noise model). Two variants, as the seed paper
describes them:

* ``variant="refit"`` (Siadat et al. 1997): the line is refitted with the
  candidate point included and the candidate's distance to that line is tested.
* ``variant="segment"`` (Vosselman 2014): the candidate's distance to the line
  of the segment's points only (without it) is tested.

A rejected point (or one beyond ``max_gap`` from its predecessor) closes the
segment and starts a new one from itself.
Sequential: ``direction`` gives forward, backward or combined runs.
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
    scaled_threshold,
)
from segmentation.methods._incremental import (
    gaps_ok,
    moments_add,
    moments_line,
    moments_of,
    point_line_distance,
)
from segmentation.noise import NoiseModel
from segmentation.registry import register


@dataclass(frozen=True)
class LineTrackingParams(SequentialParams):
    """threshold: point-to-line distance limit (m), the paper's best was 3 mm for 3 mm noise.
    n_init: points of a new segment's initial line. variant: ``refit`` or ``segment``."""

    threshold: float = 0.009
    n_init: int = 3
    variant: Literal["refit", "segment"] = "segment"
    min_len: int = 10

    def validate(self) -> None:
        super().validate()
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")
        _check(self.n_init >= 2, "n_init", self.n_init, ">= 2")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values plus ``threshold`` scaled to the model's noise."""
        return {**super().from_noise(model), "threshold": scaled_threshold(cls().threshold, model)}


@nb.njit(cache=True)
def _init_ok(points: FloatArray, i0: int, i1: int, thr: FloatArray) -> bool:
    m = moments_of(points, i0, i1)
    cx, cy, nx, ny = moments_line(m)
    for i in range(i0, i1 + 1):
        if point_line_distance(points[i, 0], points[i, 1], cx, cy, nx, ny) > thr[i]:
            return False
    return True


@nb.njit(cache=True)
def line_tracking_labels(points: FloatArray, thr: FloatArray, n_init: int, refit: bool, max_gap: float) -> IntArray:
    """Raw labels of the line-tracking pass over points in the given order.

    A point farther than ``max_gap`` from its predecessor never joins its segment.
    """
    m_pts = points.shape[0]
    labels = np.full(m_pts, -1, dtype=np.int64)
    near = gaps_ok(points, max_gap)
    seg = 0
    i = 0
    while i + n_init <= m_pts:
        i_end = i + n_init - 1
        gap = False
        for q in range(i + 1, i_end + 1):
            if not near[q]:
                gap = True
        if gap or not _init_ok(points, i, i_end, thr):
            i += 1
            continue
        mom = moments_of(points, i, i_end)
        for q in range(i, i_end + 1):
            labels[q] = seg
        j = i_end + 1
        while j < m_pts and near[j]:
            x = points[j, 0]
            y = points[j, 1]
            if refit:
                moments_add(mom, x, y, 1.0)
                cx, cy, nx, ny = moments_line(mom)
                if point_line_distance(x, y, cx, cy, nx, ny) > thr[j]:
                    moments_add(mom, x, y, -1.0)
                    break
            else:
                cx, cy, nx, ny = moments_line(mom)
                if point_line_distance(x, y, cx, cy, nx, ny) > thr[j]:
                    break
                moments_add(mom, x, y, 1.0)
            labels[j] = seg
            j += 1
        seg += 1
        i = j
    return labels


@register("line_tracking")
class LineTracking(Segmenter):
    """Line tracking (incremental); see the module docstring."""

    Params = LineTrackingParams
    sequential = True

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, LineTrackingParams)
        thr = np.ascontiguousarray(p.threshold * scale)
        return line_tracking_labels(points_xy, thr, p.n_init, p.variant == "refit", p.max_gap)
