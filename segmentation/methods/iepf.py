"""Iterative end point fit (IEPF) segmentation.

The classic recursive split (Duda and Hart 1973; Siadat et al. 1997): the
line of an interval is the *chord* joining its first and last points; the
interval is split at the point farthest from the chord while that distance
exceeds ``threshold`` (scaled per point by the noise model), recursively.
Pure IEPF: there is no merge step (see ``split_and_merge`` for the
least-squares variant with a merge of collinear neighbours).

Before splitting, the scanline is cut at depth jumps larger than ``max_gap``;
the split point is shared by both halves during the recursion and finally
given to the neighbour whose fitted line it is nearer to (details in
``segmentation.methods._split``). Intervals with fewer than ``min_len``
points are unsegmented. Default threshold 15 mm (5 sigma of a UTM-30LX's 3 mm
indoor noise): the chord runs through two noisy points, so IEPF needs a wider
margin than a least-squares fit. The seed paper's best IEPF threshold on its
figure-1 scanline was 11 mm; on a synthetic 1081-beam office scanline with
3 mm noise, 11 mm cuts 8 faces into about 22 segments, 15 mm into about 10.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from segmentation.base import (
    CommonParams,
    FloatArray,
    IntArray,
    Segmenter,
    _check,
    scaled_threshold,
)
from segmentation.methods._split import assign_labels, split_intervals
from segmentation.noise import NoiseModel
from segmentation.registry import register


@dataclass(frozen=True)
class IEPFParams(CommonParams):
    """threshold: largest accepted point-to-chord distance (m) at the noise ``point_sigma``."""

    threshold: float = 0.015

    def validate(self) -> None:
        super().validate()
        _check(self.threshold > 0, "threshold", self.threshold, "> 0")

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """The common values plus ``threshold`` scaled to the model's noise."""
        return {**super().from_noise(model), "threshold": scaled_threshold(cls().threshold, model)}


@register("iepf")
class IEPF(Segmenter):
    """Iterative end point fit; see the module docstring."""

    Params = IEPFParams

    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        assert isinstance(p, IEPFParams)
        thr = np.ascontiguousarray(p.threshold * scale)
        first, last = split_intervals(points_xy, thr, p.max_gap, p.min_len, False)
        return assign_labels(points_xy, thr, first, last, p.min_len)
