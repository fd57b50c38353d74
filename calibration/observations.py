"""Calibration observations: the SLAM run's associated segments, in the scanner frame.

While SLAM runs, :class:`SegmentLog` keeps from every prepared scan
(:class:`slam.frontend.scan_prep.PreparedScan`) what the calibration needs of its segments: scanner,
scan index, beam range, number of points and the two moment-matched virtual points of
:mod:`slam.frontend.observations` in the *scanner* frame with their beam times. These do not depend
on the extrinsics (nor on a deskew, which moves only the body-frame points), so the recording is
read once. After SLAM, every segment it associated with a plane (``SlamResult.segment_rows``)
becomes two point observations, with the rig's current ``time_offset`` of its scanner added to
their times and a point-to-plane sigma from the scanner's range noise. The extrinsics are then
free to move in the calibration graph.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig
from slam.frontend.scan_prep import PreparedScan

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_SCAN_BITS = 32  # segment key: (scanner, scan index, first beam) in one int64
_BEAM_BITS = 20


@dataclass(frozen=True)
class PointObservations:
    """Points (M, 3) in their scanner's frame on known planes, one row per (virtual) point.

    ``scanner`` (M,) scanner index in the rig, ``plane_id`` (M,), ``times`` (M,) [s] beam times on
    the trajectory's clock, ``sigmas`` (M,) point-to-plane standard deviations [m].
    """

    scanner: IntArray
    plane_id: IntArray
    points_scanner: FloatArray
    times: FloatArray
    sigmas: FloatArray

    def __post_init__(self) -> None:
        m = self.scanner.shape[0]
        for name in ("plane_id", "times", "sigmas"):
            if getattr(self, name).shape != (m,):
                raise ValueError(f"{name}: expected shape ({m},), got {getattr(self, name).shape}")
        if self.points_scanner.shape != (m, 3):
            raise ValueError(f"points_scanner: expected shape ({m}, 3), got {self.points_scanner.shape}")

    def __len__(self) -> int:
        return int(self.scanner.shape[0])

    def select(self, mask: NDArray[np.bool_]) -> PointObservations:
        return PointObservations(self.scanner[mask], self.plane_id[mask], self.points_scanner[mask],
                                 self.times[mask], self.sigmas[mask])

    @staticmethod
    def concatenate(parts: list[PointObservations]) -> PointObservations:
        if not parts:
            z = np.zeros(0, dtype=np.int64)
            return PointObservations(z, z.copy(), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        return PointObservations(
            np.concatenate([p.scanner for p in parts]),
            np.concatenate([p.plane_id for p in parts]),
            np.concatenate([p.points_scanner for p in parts]),
            np.concatenate([p.times for p in parts]),
            np.concatenate([p.sigmas for p in parts]),
        )


def _segment_key(scanner: NDArray[Any], scan_index: NDArray[Any], first_beam: NDArray[Any]) -> IntArray:
    """One int64 per segment, ordered as (scanner, scan index, first beam); a ValueError if one
    does not fit."""
    s, i, b = (np.asarray(a, dtype=np.int64) for a in (scanner, scan_index, first_beam))
    if s.size and (s.min() < 0 or s.max() >= 1 << (63 - _SCAN_BITS - _BEAM_BITS) or i.min() < 0
                   or i.max() >= 1 << _SCAN_BITS or b.min() < 0 or b.max() >= 1 << _BEAM_BITS):
        raise ValueError("segment rows: scanner, scan index or beam index out of range")
    return (s << (_SCAN_BITS + _BEAM_BITS)) | (i << _BEAM_BITS) | b


class SegmentLog:
    """Every segment of the prepared scans of one SLAM run, in stream order, column-wise: scanner,
    scan index, first and last beam, number of points (int32), the two virtual points in the
    scanner frame (their x, y; z = 0) and their times [s]. Grown in chunks of ``chunk`` scans."""

    _COLUMNS = ("scanner", "scan_index", "first_beam", "last_beam", "n_points", "virtual_xy", "virtual_times")

    def __init__(self, chunk: int = 512) -> None:
        self._chunk = chunk
        self._pending: list[tuple[NDArray[Any], ...]] = []
        self._chunks: list[tuple[NDArray[Any], ...]] = []

    def add(self, scan: PreparedScan) -> None:
        """Keep ``scan``'s segments (copies: the scan goes on to the front end)."""
        segs = scan.segs
        if segs is None or segs.n_segments == 0:
            return
        k = segs.n_segments
        self._pending.append((
            np.full(k, scan.scanner, dtype=np.int32),
            np.full(k, scan.scan_index, dtype=np.int32),
            segs.first_beam.astype(np.int32),
            segs.last_beam.astype(np.int32),
            segs.n_points.astype(np.int32),
            segs.virtual_scanner[:, :, :2].copy(),
            segs.virtual_times.copy(),
        ))
        if len(self._pending) >= self._chunk:
            self._flush()

    def _flush(self) -> None:
        if self._pending:
            self._chunks.append(tuple(np.concatenate(c) for c in zip(*self._pending, strict=True)))
            self._pending = []

    def columns(self) -> dict[str, NDArray[Any]]:
        """The log's columns (see the class docstring), one row per segment."""
        self._flush()
        if not self._chunks:
            z = np.zeros(0, dtype=np.int32)
            return {"scanner": z, "scan_index": z, "first_beam": z, "last_beam": z, "n_points": z,
                    "virtual_xy": np.zeros((0, 2, 2)), "virtual_times": np.zeros((0, 2))}
        if len(self._chunks) > 1:
            self._chunks = [tuple(np.concatenate(c) for c in zip(*self._chunks, strict=True))]
        return dict(zip(self._COLUMNS, self._chunks[0], strict=True))

    def __len__(self) -> int:
        return int(self.columns()["scanner"].shape[0])

    def observations(self, rig: Rig, segment_rows: dict[str, NDArray[Any]], point_sigma: float | None = None,
                     min_points: int = 10) -> PointObservations:
        """Two virtual points of every segment SLAM associated (``segment_rows['plane_id'] >= 0``)
        with at least ``min_points`` points, in stream order.

        ``segment_rows`` must come from the run these scans were prepared for (a ValueError names
        an associated row the log lacks). A virtual point's sigma is ``sigma / sqrt(n / 2)`` with
        ``sigma`` = ``point_sigma`` [m], by default its scanner model's ``range_sigma`` (at least
        0.1 mm), and ``n`` its segment's points. Times get the rig's ``time_offset`` of their
        scanner added.
        """
        c = self.columns()
        rows = segment_rows
        pid = np.asarray(rows["plane_id"], dtype=np.int64)
        assoc = np.flatnonzero(pid >= 0)
        key_log = _segment_key(c["scanner"], c["scan_index"], c["first_beam"])
        by_key = np.argsort(key_log, kind="stable")
        key_sorted = key_log[by_key]
        key_rows = _segment_key(rows["scanner"][assoc], rows["scan_index"][assoc], rows["first_beam"][assoc])
        pos = np.minimum(np.searchsorted(key_sorted, key_rows), max(key_sorted.size - 1, 0))
        hit = key_sorted[pos] == key_rows if key_sorted.size else np.zeros(assoc.size, dtype=bool)
        if not hit.all():
            r = assoc[np.flatnonzero(~hit)[0]]
            raise ValueError(f"segment_rows: segment of scanner {int(rows['scanner'][r])}, scan "
                             f"{int(rows['scan_index'][r])}, beams {int(rows['first_beam'][r])}.."
                             f"{int(rows['last_beam'][r])} is not among the prepared scans' segments")
        seg = by_key[pos]  # the log's row of every associated segment
        stream = np.argsort(seg, kind="stable")
        seg, row = seg[stream], assoc[stream]
        if np.any(np.asarray(rows["last_beam"])[row] != c["last_beam"][seg]):
            raise ValueError("segment_rows: a segment's last beam differs from the prepared scans'")
        n = c["n_points"][seg]
        keep = n >= min_points
        idx, row = seg[keep], row[keep]
        n = n[keep].astype(np.float64)
        scanner = c["scanner"][idx].astype(np.int64)
        if point_sigma is None:
            sigma_of = np.array([max(s.scanner_model.range_sigma, 1e-4) for s in rig.scanners])
        else:
            sigma_of = np.full(len(rig.scanners), max(point_sigma, 1e-4))
        sigma = sigma_of[scanner]
        offset = np.array([s.time_offset for s in rig.scanners], dtype=np.float64)[scanner]
        m = idx.size
        points = np.zeros((m, 2, 3))
        points[:, :, :2] = c["virtual_xy"][idx]
        return PointObservations(
            np.repeat(scanner, 2),
            np.repeat(pid[row], 2),
            points.reshape(-1, 3),
            (c["virtual_times"][idx] + offset[:, None]).ravel(),
            np.repeat(np.sqrt(sigma**2 / (np.maximum(n, 2.0) / 2.0)), 2),
        )
