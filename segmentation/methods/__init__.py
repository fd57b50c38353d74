"""Every segmenter module; importing this package registers them all."""

from segmentation.methods import line_tracking as line_tracking

__all__ = ["line_tracking"]
