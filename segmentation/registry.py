"""The one registry of segmenters, keyed by name."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Literal, TypeVar

from numpy.typing import ArrayLike

from segmentation.base import Segmenter, as_scanline
from segmentation.noise import NoiseModel, estimate
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


def get(method: str = "ror", noise: NoiseModel | None = None, **params: Any) -> Segmenter:
    """A reusable segmenter; ``get(m, **p).segment(x)`` equals ``segment(x, m, **p)``.

    With a noise model (``segmentation.noise``), parameters not given take their
    noise-derived values; without one, the fixed defaults.
    """
    return segmenter_class(method)(noise, **params)


def segment(data: Scanline | ArrayLike, method: str = "ror", noise: NoiseModel | Literal["auto"] | None = None,
            **params: Any) -> Segmentation:
    """Segment one scanline (a ``Scanline`` or an (n, 2) array of points) with the named method.

    ``noise``: a noise model to derive the defaults from, ``"auto"`` to estimate
    it from this scanline alone, or None for the fixed defaults.
    """
    if isinstance(noise, str):
        if noise != "auto":
            raise ValueError(f"noise={noise!r} is invalid: expected a NoiseModel, 'auto' or None")
        line = as_scanline(data)
        return get(method, estimate(line), **params).segment(line)
    return get(method, noise, **params).segment(data)


def auto(scanlines: Scanline | Iterable[Scanline], method: str = "ror", **params: Any) -> Segmenter:
    """A segmenter whose defaults come from the noise model estimated from ``scanlines``
    (one scanner's; ``segmentation.noise.estimate``); explicit ``params`` win. The model
    is the segmenter's ``noise`` attribute."""
    return get(method, estimate(scanlines), **params)
