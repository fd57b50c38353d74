"""Line segments of one scan as SLAM observations, in the body frame at their beams' own times.

Each segment found by a segmenter (2D, scanner frame) becomes a ``SegmentObs``:
its points lifted to 3D (``z = 0`` in the scanner frame) and mapped into the
body frame by ``T_body_scanner``, each with its own beam time. Because the rig
moves during a scan, ``points_body[i]`` is expressed in the body frame *at
time* ``times[i]``: placing it in the world needs ``T_world_body(times[i])``.

For the back end a segment is summarised by two *virtual points* that match
the first and second moments of its points along the line: with centroid
``c``, line direction ``u`` and ``var_s`` the variance of the points'
coordinates ``s_i`` along ``u``, ``v = c +- sqrt(var_s) u``, each standing for
``n / 2`` points. For any plane, the sum of squared point-to-plane distances
of the ``n`` points equals that of the two virtual points weighted ``n / 2``,
up to the (parameter-independent, noise-sized) scatter across the line. Their
times follow the points' times the same way (``t = t_mean +- beta
sqrt(var_s)`` with ``beta`` the slope of time over ``s``), so motion during
the segment is honoured to first order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segmentation import Scanline, Segmentation
from slam.frontend.batch_kernels import lift_segments

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ScanSegments:
    """The segments of one scan of one scanner, column-wise (k segments).

    ``virtual_scanner`` (k, 2, 3) are the virtual points in the scanner frame,
    ``virtual_body`` (k, 2, 3) the same in the body frame, ``virtual_times``
    (k, 2) their times (s) and ``virtual_sigma`` (k,) the standard deviation
    of one virtual point's distance (m): point noise / sqrt(n / 2).
    ``points_body``/``times`` hold every point, ``offsets`` (k + 1,) slice them.
    ``line_centroid``/``line_direction`` (k, 2) are each segment's fitted line in the scanner
    frame, ``beam_angles`` every beam's angle (rad, scanner frame, invalid beams included),
    ``beam_ranges`` its range (m) and ``beam_valid`` whether it is a valid return.
    """

    scanner: int
    scan_index: int
    stamp: float
    first_beam: NDArray[np.int64]
    last_beam: NDArray[np.int64]
    n_points: NDArray[np.int64]
    offsets: NDArray[np.int64]
    points_body: FloatArray
    times: FloatArray
    virtual_scanner: FloatArray
    virtual_body: FloatArray
    virtual_times: FloatArray
    virtual_sigma: FloatArray
    rms: FloatArray
    line_centroid: FloatArray
    line_direction: FloatArray
    beam_angles: FloatArray
    beam_ranges: FloatArray
    beam_valid: NDArray[np.bool_]

    @property
    def n_segments(self) -> int:
        return int(self.first_beam.shape[0])

    def points_of(self, k: int) -> FloatArray:
        return self.points_body[self.offsets[k] : self.offsets[k + 1]]

    def times_of(self, k: int) -> FloatArray:
        return self.times[self.offsets[k] : self.offsets[k + 1]]


def scan_segments(
    line: Scanline,
    seg: Segmentation,
    T_body_scanner: FloatArray,
    scanner: int,
    scan_index: int,
    point_sigma: float,
    model_sigma: float = 0.0,
) -> ScanSegments:
    """Lift the segments of ``seg`` (on ``line``) into the body frame; see the module docstring.

    ``model_sigma`` (m) is added in quadrature to each virtual point's noise: errors that do not
    average out over a segment's points (the trajectory between knots, calibration, surface
    flatness). Without it a long segment's virtual points claim a fraction of a millimetre.
    One compiled pass (``frontend.batch_kernels.lift_segments``), bit for bit :func:`scan_segments_numpy`.
    """
    k = seg.n_segments
    c2 = np.asarray(seg.centroid, dtype=np.float64)  # (k, 2) scanner frame
    u2 = np.asarray(seg.direction, dtype=np.float64)  # (k, 2)
    R = np.ascontiguousarray(T_body_scanner[:3, :3], dtype=np.float64)
    t = np.ascontiguousarray(T_body_scanner[:3, 3], dtype=np.float64)
    counts, offsets, pts_body, tms, v_scanner, v_body, v_times, v_sigma = lift_segments(
        np.asarray(seg.labels, dtype=np.int64), np.asarray(line.valid_index, dtype=np.int64), line.points_xy,
        line.times, k, R, t, c2, u2, point_sigma**2, model_sigma**2)
    if pts_body.shape[0] == 1:  # numpy's product of one row is no gemm: its own code
        return scan_segments_numpy(line, seg, T_body_scanner, scanner, scan_index, point_sigma, model_sigma)
    return _assemble(line, seg, scanner, scan_index, counts, offsets, pts_body, tms, v_scanner, v_body, v_times,
                     v_sigma, c2, u2)


def scan_segments_numpy(
    line: Scanline,
    seg: Segmentation,
    T_body_scanner: FloatArray,
    scanner: int,
    scan_index: int,
    point_sigma: float,
    model_sigma: float = 0.0,
) -> ScanSegments:
    """:func:`scan_segments` in numpy, the code the compiled pass (``frontend.batch_kernels.lift_segments``)
    reproduces bit for bit (tests/test_batch_kernels.py); it serves a scan with one labelled return."""
    k = seg.n_segments
    labels_valid = seg.labels[line.valid_index]
    keep = labels_valid >= 0
    pts2 = line.points_xy[keep]
    tms = line.times[line.valid_index][keep]
    lab = labels_valid[keep]
    counts = np.bincount(lab, minlength=k).astype(np.int64)
    offsets = np.zeros(k + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    pts_scanner = np.column_stack((pts2, np.zeros(pts2.shape[0])))
    R = T_body_scanner[:3, :3]
    t = T_body_scanner[:3, 3]
    pts_body = pts_scanner @ R.T + t

    n = counts.astype(np.float64)
    c2 = seg.centroid  # (k, 2) scanner frame
    u2 = seg.direction  # (k, 2)
    # coordinates along the line and the time slope, per segment (vectorised over points)
    s = np.einsum("ij,ij->i", pts2 - c2[lab], u2[lab])
    var_s = np.bincount(lab, weights=s * s, minlength=k) / np.maximum(n, 1.0)
    t_mean = np.bincount(lab, weights=tms, minlength=k) / np.maximum(n, 1.0)
    cov_ts = np.bincount(lab, weights=(tms - t_mean[lab]) * s, minlength=k) / np.maximum(n, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(var_s > 0, cov_ts / var_s, 0.0)
    h = np.sqrt(var_s)
    v2 = np.stack((c2 - h[:, None] * u2, c2 + h[:, None] * u2), axis=1)  # (k, 2, 2)
    v_scanner = np.concatenate((v2, np.zeros((k, 2, 1))), axis=2)
    v_body = v_scanner @ R.T + t
    v_times = np.stack((t_mean - beta * h, t_mean + beta * h), axis=1)
    v_sigma = np.sqrt(point_sigma**2 / (np.maximum(n, 2.0) / 2.0) + model_sigma**2)
    return _assemble(line, seg, scanner, scan_index, counts, offsets, pts_body, tms, v_scanner, v_body, v_times,
                     v_sigma, c2, u2)


def _assemble(line: Scanline, seg: Segmentation, scanner: int, scan_index: int, counts: NDArray[np.int64],
              offsets: NDArray[np.int64], pts_body: FloatArray, tms: FloatArray, v_scanner: FloatArray,
              v_body: FloatArray, v_times: FloatArray, v_sigma: FloatArray, c2: FloatArray,
              u2: FloatArray) -> ScanSegments:
    return ScanSegments(
        scanner=scanner,
        scan_index=scan_index,
        stamp=line.stamp,
        first_beam=seg.first_beam,
        last_beam=seg.last_beam,
        n_points=counts,
        offsets=offsets,
        points_body=pts_body,
        times=tms,
        virtual_scanner=v_scanner,
        virtual_body=v_body,
        virtual_times=v_times,
        virtual_sigma=v_sigma,
        rms=seg.rms,
        line_centroid=np.asarray(c2, dtype=np.float64),
        line_direction=np.asarray(u2, dtype=np.float64),
        beam_angles=line.angles,
        beam_ranges=line.ranges,
        beam_valid=line.valid,
    )
