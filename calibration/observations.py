"""Calibration observations: the SLAM run's associated segments, re-read in the scanner frame.

For each segment that SLAM associated with a plane (``SlamResult.segment_rows``), the scan is
read again from the bag and the segment's valid beams ``first_beam..last_beam`` are refitted and
summarised by the two moment-matched virtual points of :mod:`slam.frontend.observations`, here
in the *scanner* frame (``T_body_scanner = I``), with their beam times (plus the rig's current
``time_offset`` of the scanner) and point-to-plane sigma. The extrinsics are then free to move
in the calibration graph: nothing here depends on them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig
from segmentation import Scanline
from segmentation.base import build_segmentation
from slam.frontend.observations import scan_segments

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


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


def segment_virtual_points(line: Scanline, first_beam: IntArray, last_beam: IntArray,
                           scanner: int, point_sigma: float
                           ) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
    """Two moment-matched virtual points per segment ``first_beam..last_beam`` of ``line``.

    Returns virtual points (k, 2, 3) in the scanner frame (z = 0), their times (k, 2) [s], the
    sigma (k,) of one virtual point and the number of valid points (k,) per segment. Segments with
    fewer than two valid beams get zero points (and should be skipped).
    """
    vi = line.valid_index
    first = np.searchsorted(vi, first_beam, side="left").astype(np.int64)
    last = (np.searchsorted(vi, last_beam, side="right") - 1).astype(np.int64)
    n_pts = np.maximum(last - first + 1, 0)
    ok = n_pts >= 2
    k = first.shape[0]
    v = np.zeros((k, 2, 3))
    t = np.zeros((k, 2))
    sg = np.full(k, np.inf)
    if not ok.any():
        return v, t, sg, n_pts
    f, la = first[ok], last[ok]
    labels = np.full(vi.shape[0], -1, dtype=np.int64)
    for j, (a, b) in enumerate(zip(f, la, strict=True)):
        labels[a:b + 1] = j
    sigma_pts = np.full(vi.shape[0], point_sigma)
    seg = build_segmentation(line, labels, f, la, sigma_pts, "calibration", {})
    segs = scan_segments(line, seg, np.eye(4), scanner, 0, point_sigma)
    v[ok], t[ok], sg[ok] = segs.virtual_scanner, segs.virtual_times, segs.virtual_sigma
    return v, t, sg, n_pts


def collect_observations(scans: Iterable[Scanline], rig: Rig, segment_rows: dict[str, NDArray[Any]],
                         point_sigma: float | None = None, min_points: int = 10) -> PointObservations:
    """Virtual points of every associated segment (``segment_rows['plane_id'] >= 0``).

    ``scans`` is the same time-ordered stream SLAM read (scan indices count per scanner from 0);
    ``point_sigma`` [m] defaults to each scanner model's ``range_sigma``. Times get the rig's
    ``time_offset`` of their scanner added.
    """
    names = [s.name for s in rig.scanners]
    index = {n: i for i, n in enumerate(names)}
    rows = segment_rows
    assoc = np.flatnonzero(np.asarray(rows["plane_id"]) >= 0)
    key = rows["scanner"][assoc].astype(np.int64) * (1 << 40) + rows["scan_index"][assoc].astype(np.int64)
    order = np.argsort(key, kind="stable")
    key_sorted, rows_sorted = key[order], assoc[order]
    counters = [0] * len(names)
    parts: list[PointObservations] = []
    for line in scans:
        s = index.get(line.scanner_id)
        if s is None:
            raise ValueError(f"scan from unknown scanner '{line.scanner_id}' (rig has {', '.join(names)})")
        si = counters[s]
        counters[s] += 1
        k = s * (1 << 40) + si
        lo, hi = np.searchsorted(key_sorted, [k, k + 1])
        if lo == hi or line.n_valid < 2:
            continue
        r = rows_sorted[lo:hi]
        cfg = rig.scanners[s]
        sigma = cfg.scanner_model.range_sigma if point_sigma is None else point_sigma
        v, t, sg, n = segment_virtual_points(line, rows["first_beam"][r], rows["last_beam"][r], s,
                                             max(sigma, 1e-4))
        keep = n >= min_points
        if not keep.any():
            continue
        m = int(keep.sum())
        parts.append(PointObservations(
            np.full(2 * m, s, dtype=np.int64),
            np.repeat(rows["plane_id"][r][keep].astype(np.int64), 2),
            v[keep].reshape(-1, 3),
            t[keep].ravel() + cfg.time_offset,
            np.repeat(sg[keep], 2),
        ))
    return PointObservations.concatenate(parts)
