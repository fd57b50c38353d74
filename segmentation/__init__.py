"""Line segmentation of 2D laser scanlines: range of residuals (RoR) and classic baselines.

Public API::

    segmentation.available()                      # registered method names
    segmentation.segment(points_or_scanline, method="ror", **params) -> Segmentation
    segmentation.get(method, **params).segment(points_or_scanline)

    model = segmentation.noise.estimate(scanlines)  # one scanner's noise, from its scans
    segmentation.get(method, noise=model, **params)  # defaults derived from it; explicit params win
    segmentation.auto(scanlines, method, **params)  # the same, estimating the model
    segmentation.segment(points_or_scanline, method, noise="auto")  # model from this scan alone

Without a noise model every segmenter keeps its fixed defaults (stated for a
UTM-30LX: 3 mm range noise, 0.25 deg steps).

This package imports nothing else of backpack-slam.
"""

from segmentation import methods as _methods  # noqa: F401  (registers the segmenters)
from segmentation import noise
from segmentation.base import CommonParams, Segmenter, SequentialParams
from segmentation.noise import NoiseModel
from segmentation.registry import auto, available, get, register, segment, segmenter_class
from segmentation.result import Segment, Segmentation
from segmentation.scanline import Scanline, validity_mask

__all__ = [
    "CommonParams",
    "NoiseModel",
    "Scanline",
    "Segment",
    "Segmentation",
    "Segmenter",
    "SequentialParams",
    "auto",
    "available",
    "get",
    "noise",
    "register",
    "segment",
    "segmenter_class",
    "validity_mask",
]
