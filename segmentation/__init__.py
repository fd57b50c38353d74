"""Line segmentation of 2D laser scanlines: range of residuals (RoR) and classic baselines.

Public API::

    segmentation.available()                      # registered method names
    segmentation.segment(points_or_scanline, method="ror", **params) -> Segmentation
    segmentation.get(method, **params).segment(points_or_scanline)

This package imports nothing else of backpack-slam.
"""

from segmentation import methods as _methods  # noqa: F401  (registers the segmenters)
from segmentation.base import CommonParams, Segmenter, SequentialParams
from segmentation.registry import available, get, register, segment, segmenter_class
from segmentation.result import Segment, Segmentation
from segmentation.scanline import Scanline, validity_mask

__all__ = [
    "CommonParams",
    "Scanline",
    "Segment",
    "Segmentation",
    "Segmenter",
    "SequentialParams",
    "available",
    "get",
    "register",
    "segment",
    "segmenter_class",
    "validity_mask",
]
