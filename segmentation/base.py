"""The segmenter interface: parameters, input handling, direction, finalisation.

A concrete segmenter subclasses ``Segmenter``, declares its parameters as a
frozen dataclass deriving from ``CommonParams`` and implements
``_raw_labels(points_xy, thresholds_scale)`` on the valid points in scan
order. Everything else is shared here: building a ``Scanline`` from the
input, the noise model, forward/backward/combined runs for sequential
methods, depth-jump splitting, ``min_len``, renumbering and the line fits.

Noise model (every threshold-based segmenter): a point at range ``r`` has
range noise ``sigma(r) = point_sigma + noise_slope * r``; a method's
thresholds, stated for the constant noise ``point_sigma``, are scaled per
point by ``sigma(r) / point_sigma``. With ``noise_slope = 0`` (the default)
thresholds are constant, as in the paper.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from segmentation.labels import combine_runs, finalize_runs
from segmentation.lines import fit_segments
from segmentation.result import Segmentation
from segmentation.scanline import Scanline

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Direction = Literal["forward", "backward", "combined"]


@dataclass(frozen=True)
class CommonParams:
    """Parameters every segmenter has.

    min_len: fewest points in a kept segment.
    max_gap: consecutive points farther apart than this (m) never share a segment.
    point_sigma: range noise (m) used for the line covariances and as sigma0 of the noise model.
    noise_slope: k of sigma(r) = point_sigma + k * r (m per m); 0 = constant noise.
    """

    min_len: int = 10
    max_gap: float = 0.2
    point_sigma: float = 0.003
    noise_slope: float = 0.0

    def validate(self) -> None:
        """Raise ValueError naming the first parameter out of range."""
        _check(self.min_len >= 2, "min_len", self.min_len, ">= 2")
        _check(self.max_gap > 0, "max_gap", self.max_gap, "> 0")
        _check(self.point_sigma > 0, "point_sigma", self.point_sigma, "> 0")
        _check(self.noise_slope >= 0, "noise_slope", self.noise_slope, ">= 0")


@dataclass(frozen=True)
class SequentialParams(CommonParams):
    """Parameters of a segmenter that walks the scanline in order.

    direction: ``forward`` (scan order), ``backward`` (reverse order), or
    ``combined`` (both, merged by the paper's section 2.2 rule).
    """

    direction: Direction = "forward"

    def validate(self) -> None:
        super().validate()
        _check(self.direction in ("forward", "backward", "combined"), "direction", self.direction,
               "one of forward, backward, combined")


def _check(ok: bool, name: str, value: Any, rule: str) -> None:
    if not ok:
        raise ValueError(f"parameter {name}={value!r} is invalid: must be {rule}")


def _coerce(name: str, value: Any, tp: Any) -> Any:
    """Convert a parameter value (possibly a string from the CLI or YAML) to its declared type."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        choices = typing.get_args(tp)
        if value not in choices:
            raise ValueError(f"parameter {name}={value!r} is invalid: must be one of {', '.join(map(str, choices))}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() == "none"):
            return None
        return _coerce(name, value, args[0])
    try:
        if tp is bool:
            if isinstance(value, str):
                if value.lower() in ("1", "true", "yes", "on"):
                    return True
                if value.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            return bool(value)
        if tp is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            if isinstance(value, bool):
                raise ValueError
            return int(float(value)) if isinstance(value, str) else int(value)
        if tp is float:
            if isinstance(value, bool):
                raise ValueError
            v = float(value)
            if not np.isfinite(v):
                raise ValueError
            return v
        if tp is str:
            return str(value)
    except (TypeError, ValueError):
        raise ValueError(f"parameter {name}={value!r} is invalid: expected {getattr(tp, '__name__', tp)}") from None
    return value


class Segmenter(ABC):
    """Base class: ``segment(points_or_scanline) -> Segmentation``.

    Subclasses set ``name``, ``Params`` and implement ``_raw_labels``. Set
    ``sequential = True`` (with ``Params`` deriving from ``SequentialParams``)
    to get forward/backward/combined runs for free.
    """

    name: ClassVar[str] = ""
    Params: ClassVar[type[CommonParams]] = CommonParams
    sequential: ClassVar[bool] = False

    def __init__(self, **params: Any) -> None:
        self.params = self.make_params(**params)

    @classmethod
    def param_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls.Params)]

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        return dataclasses.asdict(cls.Params())

    @classmethod
    def make_params(cls, **params: Any) -> CommonParams:
        """Validated parameters; unknown names or bad values raise ValueError listing the valid ones."""
        hints = typing.get_type_hints(cls.Params)
        names = cls.param_names()
        unknown = sorted(set(params) - set(names))
        if unknown:
            raise ValueError(
                f"unknown parameter {', '.join(unknown)} for segmenter '{cls.name}'; valid: {', '.join(names)}"
            )
        values = {k: _coerce(k, v, hints[k]) for k, v in params.items()}
        p = cls.Params(**values)
        p.validate()
        return p

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params})"

    # ---- the method-specific part -------------------------------------------------------------
    @abstractmethod
    def _raw_labels(self, points_xy: FloatArray, scale: FloatArray) -> IntArray:
        """Raw labels (-1 or segment ids, runs = segments) of the valid points in scan order.

        ``points_xy`` is (m, 2) C-contiguous float64 in the scanner frame;
        ``scale[i] = sigma(r_i) / point_sigma`` (all ones with constant noise)
        multiplies every metric threshold of point i.
        """

    # ---- shared machinery ---------------------------------------------------------------------
    def segment(self, data: Scanline | ArrayLike) -> Segmentation:
        """Segment a ``Scanline`` or an (n, 2) array of points (scanner frame, scan order)."""
        line = as_scanline(data)
        pts = line.points_xy
        p = self.params
        if pts.shape[0] == 0:
            raise ValueError("empty input: the scanline has no valid points")
        if not np.all(np.isfinite(pts)):
            raise ValueError("input has NaN or inf coordinates among its valid points")
        r = np.hypot(pts[:, 0], pts[:, 1])
        sigma_pts = p.point_sigma + p.noise_slope * r
        scale = sigma_pts / p.point_sigma
        raw = self._directional_labels(pts, scale)
        lab, first, last = finalize_runs(raw, pts, p.max_gap, p.min_len)
        return build_segmentation(line, lab, first, last, sigma_pts, self.name, dataclasses.asdict(p))

    def _directional_labels(self, pts: FloatArray, scale: FloatArray) -> IntArray:
        p = self.params
        if not self.sequential:
            return self._raw_labels(pts, scale)
        direction = getattr(p, "direction", "forward")
        if direction == "forward":
            return self._raw_labels(pts, scale)
        rev = self._run_reversed(pts, scale)
        if direction == "backward":
            return rev
        fwd, _, _ = finalize_runs(self._raw_labels(pts, scale), pts, p.max_gap, p.min_len)
        bwd, _, _ = finalize_runs(rev, pts, p.max_gap, p.min_len)
        return combine_runs(fwd, bwd)

    def _run_reversed(self, pts: FloatArray, scale: FloatArray) -> IntArray:
        rpts = np.ascontiguousarray(pts[::-1])
        rscale = np.ascontiguousarray(scale[::-1])
        raw = self._raw_labels(rpts, rscale)
        # finalise in the reversed order (so runs and min_len match a true backward pass), then flip
        lab, _, _ = finalize_runs(raw, rpts, self.params.max_gap, self.params.min_len)
        return np.ascontiguousarray(lab[::-1])


def as_scanline(data: Scanline | ArrayLike) -> Scanline:
    """Accept a ``Scanline`` or an (n, 2) array of points."""
    if isinstance(data, Scanline):
        return data
    arr = np.asarray(data, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"input must be a Scanline or an (n, 2) array of points, got shape {arr.shape}")
    if arr.shape[0] and not np.all(np.isfinite(arr)):
        raise ValueError("input has NaN or inf coordinates")
    return Scanline.from_points(arr)


def build_segmentation(
    line: Scanline,
    point_labels: IntArray,
    first: IntArray,
    last: IntArray,
    sigma_pts: FloatArray,
    method: str,
    params: dict[str, Any],
) -> Segmentation:
    """Map point-level segments back to beams and fit their lines."""
    labels = np.full(line.n_beams, -1, dtype=np.int64)
    idx = line.valid_index
    labels[idx] = point_labels
    normal, offset, centroid, direction, endpoints, rms, cov = fit_segments(line.points_xy, first, last, sigma_pts)
    return Segmentation(
        labels=labels,
        first_beam=idx[first].astype(np.int64),
        last_beam=idx[last].astype(np.int64),
        n_points=(last - first + 1).astype(np.int64),
        normal=normal,
        offset=offset,
        centroid=centroid,
        direction=direction,
        endpoints=endpoints,
        rms=rms,
        cov=cov,
        method=method,
        params=params,
    )
