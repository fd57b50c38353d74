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

Defaults from a scanner's noise (``segmentation.noise.NoiseModel``): the fixed
defaults are stated for a UTM-30LX indoors (``noise.REFERENCE``: 3 mm, 0.25 deg
steps). ``Segmenter(noise=model)`` (``segmentation.get(name, noise=model)``)
takes every parameter not given explicitly from ``Params.from_noise(model)``:
``point_sigma`` and ``noise_slope`` are the model's effective noise, metric
thresholds scale with the noise (``scaled_threshold``), point counts follow the
angular step (``scaled_count``: the same metric length at ``RANGE_REF`` spans
fewer beams at coarser steps, with a floor of ``MIN_SEGMENT_POINTS``) and
``max_gap`` follows the beam spacing. ``from_noise(noise.REFERENCE)`` gives the
fixed defaults exactly; without a model nothing changes.

Input errors (ValueError, one line): empty input, all beams invalid, fewer
valid points than ``Segmenter.min_points`` (``max(2, n_init)``), NaN/inf
coordinates in an (n, 2) array input. Duplicate points and a single straight
line are ordinary input.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from segmentation.labels import combine_directions, finalize_runs, reverse_labels
from segmentation.lines import fit_segments
from segmentation.noise import REFERENCE_ANGLE_STEP, REFERENCE_SIGMA, NoiseModel
from segmentation.result import Segmentation
from segmentation.scanline import Scanline

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Direction = Literal["forward", "backward", "combined"]

#: range (m) at which a segment's fewest points are turned into a metric length
RANGE_REF = 5.0
#: fewest points a noise-derived ``min_len`` (or other count) goes down to at coarse angular steps
MIN_SEGMENT_POINTS = 8
#: a noise-derived ``max_gap`` is at least this many times the noise at the typical range
GAP_SIGMAS = 10.0


def noise_ratio(model: NoiseModel) -> float:
    """The model's noise (at r = 0: ``point_sigma``) over the noise the fixed defaults assume."""
    return model.sigma0 / REFERENCE_SIGMA


#: beam-to-beam over lagged noise at or above which the noise counts as white: the two estimates
#: of white noise scatter by up to about 15 % on a single scan (1 cm quantisation, 2.5 cm noise: 0.86)
WHITE_SHARE = 0.8


def independent_share(model: NoiseModel) -> float:
    """The share of the model's noise that is independent from beam to beam: ``beam_sigma`` over
    ``sigma_ref`` relative to ``WHITE_SHARE``, at most 1 (1 when the model has no beam-to-beam
    estimate).

    White noise gives 1 (both estimates agree within their scatter). Real scanners' range errors
    are often correlated along the scan (segmentation.noise, "Lag"): neighbouring points then
    share most of their error, and a test that compares consecutive points' residuals sees only
    the independent part.
    """
    if not model.beam_sigma > 0:
        return 1.0
    return min(1.0, model.beam_sigma / model.sigma_ref / WHITE_SHARE)


def scaled_threshold(default: float, model: NoiseModel) -> float:
    """A metric threshold stated for the reference noise, scaled to the model's noise."""
    return default * noise_ratio(model)


def scaled_count(default: int, model: NoiseModel) -> int:
    """A point count stated for the reference angular step, for the model's step.

    ``default - 1`` beam spacings at the reference step and ``RANGE_REF`` are a
    metric length (RoR's 15 points: 0.31 m at 5 m); the count is the beams that
    length spans at the model's step, at least ``MIN_SEGMENT_POINTS`` (or
    ``default``, if smaller).
    """
    n = 1 + math.floor((default - 1) * REFERENCE_ANGLE_STEP / model.angle_step + 0.5)
    return max(n, min(default, MIN_SEGMENT_POINTS))


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

    @classmethod
    def from_noise(cls, model: NoiseModel) -> dict[str, Any]:
        """Parameter values derived from a scanner's noise model (module docstring); subclasses
        add their thresholds. ``max_gap`` follows the beam spacing, and stays 10 noise widths."""
        d = cls()
        step_ratio = model.angle_step / REFERENCE_ANGLE_STEP
        return {
            "point_sigma": model.sigma0,
            "noise_slope": model.slope,
            "min_len": scaled_count(d.min_len, model),
            "max_gap": max(d.max_gap * step_ratio, GAP_SIGMAS * model.sigma_ref),
        }


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
            if isinstance(value, str):
                v = float(value)
                if not v.is_integer():
                    raise ValueError
                return int(v)
            return int(value)
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

    def __init__(self, noise: NoiseModel | None = None, **params: Any) -> None:
        self.noise = noise
        self.params = self.make_params(noise, **params)
        self._params_dict: dict[str, Any] = dataclasses.asdict(self.params)
        self._const_noise: dict[int, tuple[FloatArray, FloatArray]] = {}

    @classmethod
    def param_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls.Params)]

    @classmethod
    def defaults(cls, noise: NoiseModel | None = None) -> dict[str, Any]:
        """The default parameters: fixed, or derived from the noise model ``noise``."""
        if noise is None:
            return dataclasses.asdict(cls.Params())
        return dataclasses.asdict(cls.make_params(noise))

    @classmethod
    def make_params(cls, noise: NoiseModel | None = None, **params: Any) -> CommonParams:
        """Validated parameters; unknown names or bad values raise ValueError listing the valid ones.

        With a noise model, every parameter not in ``params`` takes its value from
        ``Params.from_noise(noise)`` (explicit parameters win).
        """
        if noise is not None:
            if not isinstance(noise, NoiseModel):
                raise ValueError(f"noise={noise!r} is invalid: expected a segmentation.noise.NoiseModel")
            params = {**cls.Params.from_noise(noise), **params}
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
    @property
    def min_points(self) -> int:
        """Fewest valid points this segmenter accepts: ``max(2, n_init)``."""
        return max(2, int(getattr(self.params, "n_init", 2)))

    def segment(self, data: Scanline | ArrayLike) -> Segmentation:
        """Segment a ``Scanline`` or an (n, 2) array of points (scanner frame, scan order).

        Raises ValueError on empty input, all-invalid input, fewer valid points
        than ``min_points`` and NaN/inf coordinates in an array input.
        """
        line = data if type(data) is Scanline else as_scanline(data)
        pts = line.points_xy
        m = pts.shape[0]
        if m < self.min_points:
            if line.n_beams == 0:
                raise ValueError("empty input: the scanline has no beams")
            if m == 0:
                raise ValueError(f"all {line.n_beams} beams of the input are invalid")
            raise ValueError(f"input has {m} valid points, fewer than the {self.min_points} "
                             f"segmenter '{self.name}' needs")
        scale, sigma_pts = self._noise(pts)
        lab, first, last = self._final_labels(pts, scale)
        return build_segmentation(line, lab, first, last, sigma_pts, self.name, dict(self._params_dict))

    def _noise(self, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Per-point threshold scale ``sigma(r) / point_sigma`` and noise ``sigma(r)`` (m)."""
        p = self.params
        m = pts.shape[0]
        if p.noise_slope == 0.0:
            cached = self._const_noise.get(m)
            if cached is None:
                cached = (np.ones(m), np.full(m, p.point_sigma))
                if len(self._const_noise) > 8:
                    self._const_noise.clear()
                self._const_noise[m] = cached
            return cached
        r = np.hypot(pts[:, 0], pts[:, 1])
        sigma_pts = p.point_sigma + p.noise_slope * r
        return sigma_pts / p.point_sigma, sigma_pts

    def _final_labels(self, pts: FloatArray, scale: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        """Final point labels and each segment's first and last point, for the configured direction."""
        p = self.params
        direction = getattr(p, "direction", "forward") if self.sequential else "forward"
        if direction == "forward":
            return finalize_runs(self._raw_labels(pts, scale), pts, p.max_gap, p.min_len)  # type: ignore[no-any-return]
        # the backward run is the forward pass on the reversed points
        rscale = scale if self._is_const_noise(scale) else np.ascontiguousarray(scale[::-1])
        raw_bwd = self._raw_labels(reverse_rows(pts), rscale)
        if direction == "backward":
            return finalize_runs(reverse_labels(raw_bwd), pts, p.max_gap, p.min_len)  # type: ignore[no-any-return]
        raw_fwd = self._raw_labels(pts, scale)
        return self._combine(raw_fwd, raw_bwd, pts, scale)

    def _combine(self, raw_fwd: IntArray, raw_bwd: IntArray, pts: FloatArray,
                 scale: FloatArray) -> tuple[IntArray, IntArray, IntArray]:
        """Final labels of a combined run from the raw forward labels and the raw labels of the
        backward pass in its own (reversed) order: the paper's section 2.2 rule."""
        p = self.params
        return combine_directions(raw_fwd, raw_bwd, pts, p.max_gap, p.min_len)  # type: ignore[no-any-return]

    def _is_const_noise(self, scale: FloatArray) -> bool:
        cached = self._const_noise.get(scale.shape[0])
        return cached is not None and cached[0] is scale


@nb.njit(cache=True)
def reverse_rows(a: FloatArray) -> FloatArray:
    """A C-contiguous copy of an (m, 2) array with its rows in reverse order."""
    m = a.shape[0]
    out = np.empty((m, 2))
    for i in range(m):
        out[i, 0] = a[m - 1 - i, 0]
        out[i, 1] = a[m - 1 - i, 1]
    return out


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
    idx = line.valid_index
    if idx.shape[0] == line.n_beams:
        labels = point_labels
    else:
        labels = np.full(line.n_beams, -1, dtype=np.int64)
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
