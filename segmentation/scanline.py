"""One 2D scanline of one scanner, in the scanner frame.

Frame ``scanner_i``: x along the 0-rad beam, y at +90 deg, scan plane z = 0.
Beam ``i`` has angle ``angles[i]`` (rad, counter-clockwise from x), range
``ranges[i]`` (m) and its own timestamp ``times[i]`` (s). Returns that are
NaN, inf, 0, below ``range_min`` or above ``range_max`` are invalid: they are
masked by ``valid`` and never turned into points. ``intensities`` holds each beam's return
intensity (float32, the sensor's units; NaN where a beam has none) when the source carries them,
else None.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

MAX_SCAN_SPAN = 1.0  # s: beams of one 2D scan spread over longer than this are a corrupt time_increment

FloatArray = NDArray[np.float64]


def validity_mask(ranges: ArrayLike, range_min: float = 0.0, range_max: float = np.inf) -> NDArray[np.bool_]:
    """True where a range is a usable return: finite, > 0 and within [range_min, range_max]."""
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(r) & (r > 0.0) & (r >= range_min) & (r <= range_max)


_TRIG_KEEP = 16  # distinct angle arrays whose cosines and sines are kept (a rig's scanners repeat theirs)
_trig: dict[tuple[int, str, float, float], tuple[NDArray[Any], NDArray[Any], NDArray[Any]]] = {}


def beam_cos_sin(angles: NDArray[Any]) -> tuple[NDArray[Any], NDArray[Any]]:
    """``np.cos(angles)``, ``np.sin(angles)``, kept for the last few distinct angle arrays: a
    scanner's angles are the same every scan. Each element is what numpy gives for any subset of
    the angles (its loops compute element by element), so ``c[idx]`` is ``np.cos(angles[idx])``."""
    n = angles.shape[0]
    if n == 0:
        return angles, angles
    key = (n, angles.dtype.str, float(angles[0]), float(angles[-1]))
    hit = _trig.get(key)
    if hit is None or not (hit[0] is angles or np.array_equal(hit[0], angles)):
        if len(_trig) >= _TRIG_KEEP:  # (clearing is safe where threads share the cache; popping one may not be)
            _trig.clear()
        hit = (angles.copy(), np.cos(angles), np.sin(angles))
        _trig[key] = hit
    return hit[1], hit[2]


def _beam_intensities(msg: Any, n: int) -> NDArray[np.float32] | None:
    """A LaserScan-like record's intensities (float32), one per beam, or None."""
    raw = getattr(msg, "intensities", None)
    if raw is None or n == 0 or len(raw) != n:
        return None
    with np.errstate(invalid="ignore"):
        return np.asarray(raw, dtype=np.float32).ravel()


@dataclass(frozen=True, eq=False)
class Scanline:
    """A scanline: per-beam angles, ranges, times and validity, plus its scanner's id.

    ``points_xy`` holds only the valid returns, (m, 2) in the scanner frame, in
    beam order; ``valid_index`` maps each of them back to its beam index.
    """

    angles: FloatArray
    ranges: FloatArray
    times: FloatArray
    valid: NDArray[np.bool_]
    scanner_id: str = "scanner"
    range_min: float = 0.0
    range_max: float = float("inf")
    intensities: NDArray[np.float32] | None = field(default=None, repr=False)
    points_xy: FloatArray = field(init=False, repr=False)
    valid_index: NDArray[np.intp] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = self.angles.shape[0]
        for name in ("ranges", "times", "valid", "intensities"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != (n,):
                raise ValueError(f"Scanline.{name} has shape {arr.shape}, expected ({n},) like angles")
        idx = np.flatnonzero(self.valid)
        r = self.ranges[idx]
        if idx.size:
            c, s = beam_cos_sin(np.asarray(self.angles))
            pts = np.column_stack((r * c[idx], r * s[idx]))
        else:
            pts = np.empty((0, 2))
        if idx.size and not np.isfinite(pts).all():
            raise ValueError("Scanline: a beam marked valid has a NaN or inf range or angle")
        object.__setattr__(self, "points_xy", np.ascontiguousarray(pts, dtype=np.float64))
        object.__setattr__(self, "valid_index", idx.astype(np.intp))

    @property
    def n_beams(self) -> int:
        return int(self.angles.shape[0])

    @property
    def n_valid(self) -> int:
        return int(self.valid_index.shape[0])

    @property
    def stamp(self) -> float:
        """Time of the first beam (s)."""
        return float(self.times[0]) if self.n_beams else 0.0

    @classmethod
    def from_ranges(
        cls,
        ranges: ArrayLike,
        angles: ArrayLike,
        times: ArrayLike | float | None = None,
        *,
        scanner_id: str = "scanner",
        range_min: float = 0.0,
        range_max: float = float("inf"),
        time_increment: float = 0.0,
        intensities: ArrayLike | None = None,
    ) -> Scanline:
        """Build from ranges and beam angles; ``times`` per beam, or a start time plus ``time_increment``;
        ``intensities`` per beam, or None."""
        r = np.asarray(ranges, dtype=np.float64).ravel()
        a = np.asarray(angles, dtype=np.float64).ravel()
        if r.shape != a.shape:
            raise ValueError(f"ranges ({r.size}) and angles ({a.size}) differ in length")
        if times is None or np.ndim(times) == 0:
            t0 = 0.0 if times is None else float(times)  # type: ignore[arg-type]
            t = t0 + time_increment * np.arange(r.size, dtype=np.float64)
        else:
            t = np.asarray(times, dtype=np.float64).ravel()
        valid = validity_mask(r, range_min, range_max)
        inten = None if intensities is None else np.asarray(intensities, dtype=np.float32).ravel()
        return cls(a, r, t, valid, scanner_id, float(range_min), float(range_max), inten)

    @classmethod
    def from_laserscan(cls, msg: Any, stamp: float | None = None, scanner_id: str | None = None) -> Scanline:
        """Build from a ``sensor_msgs/LaserScan``-like record (attribute access).

        The header stamp is the time of the first beam; beam i is taken at
        ``stamp + i * time_increment`` (a non-finite ``time_increment`` is a ValueError). The
        message's ``intensities`` are kept when there is one per beam (ROS leaves the list empty
        for a sensor without them; a list of another length is taken as none).
        """
        if not np.isfinite(float(msg.time_increment)):
            raise ValueError(f"time_increment {float(msg.time_increment)} is not finite")
        with np.errstate(invalid="ignore"):  # a signalling NaN (a corrupt message) is a NaN like any other
            ranges = np.asarray(msg.ranges, dtype=np.float64)
        n = ranges.size
        span = abs(float(msg.time_increment)) * max(n - 1, 0)
        if span > MAX_SCAN_SPAN:
            raise ValueError(f"time_increment {float(msg.time_increment):g} s makes the {n} beams span {span:g} s "
                             f"(a 2D scanner's sweep lasts under {MAX_SCAN_SPAN:g} s)")
        angles = float(msg.angle_min) + float(msg.angle_increment) * np.arange(n, dtype=np.float64)
        if stamp is None:
            st = msg.header.stamp
            stamp = float(st.sec) + 1e-9 * float(st.nanosec) if hasattr(st, "sec") else float(st)
        sid = scanner_id if scanner_id is not None else str(getattr(msg.header, "frame_id", "scanner"))
        return cls.from_ranges(
            ranges,
            angles,
            stamp,
            scanner_id=sid,
            range_min=float(msg.range_min),
            range_max=float(msg.range_max),
            time_increment=float(msg.time_increment),
            intensities=_beam_intensities(msg, n),
        )

    @classmethod
    def from_points(cls, points_xy: ArrayLike, times: ArrayLike | None = None, *, scanner_id: str = "scanner") -> Scanline:
        """Build from an (n, 2) array of points in the scanner frame, in scan order.

        Rows with a NaN or inf coordinate, or at the origin, are invalid.
        """
        p = np.asarray(points_xy, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must have shape (n, 2), got {p.shape}")
        with np.errstate(invalid="ignore"):
            r = np.hypot(p[:, 0], p[:, 1])
        a = np.arctan2(p[:, 1], p[:, 0])
        a = np.where(np.isfinite(a), a, 0.0)
        t = np.zeros(p.shape[0]) if times is None else np.asarray(times, dtype=np.float64).ravel()
        valid = validity_mask(r)
        line = cls(a, np.where(valid, r, np.nan), t, valid, scanner_id)
        # keep the caller's exact coordinates rather than the polar round trip
        object.__setattr__(line, "points_xy", np.ascontiguousarray(p[valid], dtype=np.float64))
        return line

    def reversed(self) -> Scanline:
        """The same scanline with its beams in reverse order."""
        line = Scanline(
            self.angles[::-1].copy(),
            self.ranges[::-1].copy(),
            self.times[::-1].copy(),
            self.valid[::-1].copy(),
            self.scanner_id,
            self.range_min,
            self.range_max,
            None if self.intensities is None else self.intensities[::-1].copy(),
        )
        object.__setattr__(line, "points_xy", np.ascontiguousarray(self.points_xy[::-1]))
        return line
