"""The one registry of segmenters, keyed by name."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from numpy.typing import ArrayLike

from segmentation.base import Segmenter
from segmentation.result import Segmentation
from segmentation.scanline import Scanline

_REGISTRY: dict[str, type[Segmenter]] = {}
S = TypeVar("S", bound=type[Segmenter])


def register(name: str) -> Callable[[S], S]:
    """Class decorator: make a segmenter available under ``name``."""

    def deco(cls: S) -> S:
        if name in _REGISTRY:
            raise ValueError(f"segmenter '{name}' is registered twice")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def available() -> list[str]:
    """Names of every registered segmenter, sorted."""
    return sorted(_REGISTRY)


def segmenter_class(method: str) -> type[Segmenter]:
    try:
        return _REGISTRY[method]
    except KeyError:
        raise ValueError(f"unknown segmenter '{method}'; available: {', '.join(available())}") from None


def get(method: str = "ror", **params: Any) -> Segmenter:
    """A reusable segmenter; ``get(m, **p).segment(x)`` equals ``segment(x, m, **p)``."""
    return segmenter_class(method)(**params)


def segment(data: Scanline | ArrayLike, method: str = "ror", **params: Any) -> Segmentation:
    """Segment one scanline (a ``Scanline`` or an (n, 2) array of points) with the named method."""
    return get(method, **params).segment(data)
