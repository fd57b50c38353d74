"""A scan's own work before the front end: segmentation, lifting into the body frame, deskew.

``ScanPreparer.prepare`` turns one ``Scanline`` (scanner frame) into a ``PreparedScan``: its
segments from the configured segmenter, lifted into the body frame at their beams' times
(``frontend.observations.scan_segments``) and, with an IMU, moved by the gyro's rotation between
knots (``slam.trajectory.deskew``). It depends on the scan, the rig, the configuration and the IMU only, never
on the trajectory estimate, so it can run ahead of the front end in another process
(``slam.prefetch``) and give the same numbers bit for bit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.rig import Rig
from segmentation import Scanline
from segmentation.steps import split_at_steps
from slam import params
from slam.config import SlamConfig
from slam.frontend import edge_kernels
from slam.frontend.edges import EdgeParams, recess_beyond, segment_end
from slam.frontend.observations import ScanSegments, scan_segments
from slam.imu_feed import ImuSamples
from slam.trajectory.deskew import DeskewTable, deskew_table


@dataclass(frozen=True)
class PreparedScan:
    """One scan ready for the front end.

    ``scanner`` indexes the rig's scanners, ``scan_index`` counts that scanner's scans from 0,
    ``stamp`` is the scan's first-beam time (s). ``segs`` is None for a scan that is skipped
    (``skipped``: fewer than two valid beams, before the first scan's stamp, or refused by the
    segmenter) and for a scan without segments. ``seconds`` are the segmentation's and the
    lifting's (with the deskew and the edge tests) times spent on it. ``edge_tests`` holds
    :func:`scan_edge_tests` (empty with ``edges.use`` off). The stream's first scan carries
    the preparer's deskew table (``deskew``; None without an IMU or deskewing).
    """

    scanner: int
    scan_index: int
    stamp: float
    skipped: bool
    segs: ScanSegments | None
    seconds_segmentation: float
    seconds_lift: float
    edge_tests: dict[tuple[int, int], Any] = field(default_factory=dict)
    deskew: DeskewTable | None = None  # the stream's first scan: the preparer's deskew table (None without one)


class ScanPreparer:
    """Prepares the scans of one time-ordered stream (see the module docstring).

    Each scanner has its own segmenter and point noise, from its noise level
    (``slam.params.noise_levels``: the configuration's rule). The first scan's stamp is the
    trajectory's origin ``t0``: the deskew table is built on the
    knot grid from it (``knot_rate``), as ``SlamRunner`` builds its own."""

    def __init__(self, rig: Rig, cfg: SlamConfig, imu: ImuSamples | None = None) -> None:
        self.cfg = cfg
        self.imu = imu
        self.scanner_names = [s.name for s in rig.scanners]
        self._index = {n: i for i, n in enumerate(self.scanner_names)}
        self._T_body_scanner = [s.T_body_scanner.matrix() for s in rig.scanners]
        levels = params.noise_levels(rig, cfg)
        self._range_sigma = list(levels.sigma)
        # one segmenter per scanner: each follows its scanner's noise (slam.params.segmenter)
        self.segmenters = [params.segmenter(cfg, rig, levels, i) for i in range(len(rig.scanners))]
        scaled = params.noise_scaled(cfg, levels.shared)
        self._edges = params.edge_params(scaled) if cfg.edges.use else None
        self._counter = [0] * len(self.scanner_names)
        self.t0: float | None = None
        self.deskew: DeskewTable | None = None

    def scanner_index(self, line: Scanline) -> int:
        """The rig's index of the scan's scanner; a ValueError for a scanner the rig lacks."""
        s = self._index.get(line.scanner_id)
        if s is None:
            raise ValueError(f"scan from unknown scanner '{line.scanner_id}' (rig has {', '.join(self.scanner_names)})")
        return s

    def prepare(self, line: Scanline) -> PreparedScan:
        """The scan's segments in the body frame (see :class:`PreparedScan`)."""
        t_start = time.perf_counter()
        s = self.scanner_index(line)
        scan_index = self._counter[s]
        self._counter[s] += 1
        table = None  # handed on with the stream's first scan (a runner in another process need not build it again)
        if self.t0 is None:
            self.t0 = line.stamp
            self.deskew = table = knot_deskew(self.cfg, self.imu, line.stamp)
        if line.n_valid < 2 or line.stamp < self.t0:
            return PreparedScan(s, scan_index, line.stamp, True, None, 0.0, 0.0, deskew=table)
        try:
            seg = self.segmenters[s].segment(line)
        except ValueError:
            return PreparedScan(s, scan_index, line.stamp, True, None, time.perf_counter() - t_start, 0.0,
                                deskew=table)
        sc = self.cfg.segmenter
        if sc.split_steps:
            seg = split_at_steps(line, seg, self._range_sigma[s], sc.step_chi2, sc.step_min,
                                 max(2, self.segmenters[s].params.min_len))
        t_seg = time.perf_counter()
        segs = scan_segments(line, seg, self._T_body_scanner[s], s, scan_index, self._range_sigma[s],
                             self.cfg.frontend.model_sigma)
        if self.deskew is not None and segs.n_segments:
            # in place: the arrays are this scan's own
            segs.points_body[:] = self.deskew.apply(segs.points_body, segs.times)
            segs.virtual_body[:] = self.deskew.apply(
                segs.virtual_body.reshape(-1, 3), segs.virtual_times.ravel()).reshape(segs.virtual_body.shape)
        tests = scan_edge_tests(segs, self._edges, self._range_sigma[s]) if self._edges is not None and segs.n_segments else {}
        t_end = time.perf_counter()
        return PreparedScan(s, scan_index, line.stamp, False, segs if segs.n_segments else None,
                            t_seg - t_start, t_end - t_seg, tests, table)


def scan_edge_tests(segs: ScanSegments, ep: EdgeParams, range_sigma: float) -> dict[tuple[int, int], Any]:
    """The door-edge tests that depend on the scan alone, for every segment that may turn out to be
    a wall's (the front end asks them of wall segments only, once it knows which those are):
    ``(j, +-1)``: ``frontend.edges.recess_beyond`` past the segment's end in that direction, where
    no other segment starts within three beams (``frontend.edges.next_to_segment``); ``(j, 0)``:
    ``frontend.edges.steps_within`` of ``frontend.edges.segment_returns``, with ``inline``.
    Segments shorter than the front end's limits are left out: the front end takes a missing test
    for a failed one. One compiled pass over the segments (``frontend.edge_kernels.scan_edge_tests``,
    bit for bit the per-segment functions: tests/test_edge_kernels.py)."""
    status, ends, median, has_inline, start, step_index, step_offset = edge_kernels.scan_edge_tests(
        segs.first_beam, segs.last_beam, segs.n_points, segs.beam_angles, segs.beam_ranges, segs.beam_valid,
        np.cos(segs.beam_angles), np.sin(segs.beam_angles), segs.line_centroid, segs.line_direction,
        ep.min_segment_points, ep.inline, ep.inline_window, ep.min_step, ep.max_step, ep.max_gap, range_sigma,
        ep.inline_z)
    st, en, med, inl = status.tolist(), ends.tolist(), median.tolist(), has_inline.tolist()
    bounds, idx, off = start.tolist(), step_index.tolist(), step_offset.tolist()
    out: dict[tuple[int, int], Any] = {}
    for j in range(segs.n_segments):
        for col, direction in ((0, 1), (1, -1)):
            s = st[j][col]
            if s == 1:
                out[(j, direction)] = (en[j][col][0], en[j][col][1], med[j][col])
            elif s == 0:
                out[(j, direction)] = None
            elif s == 2:  # the gap lies within rounding of max_gap: Python's math.hypot decides
                out[(j, direction)] = recess_beyond(
                    segment_end(segs, j, direction), direction, segs.beam_angles, segs.beam_ranges,
                    segs.beam_valid, segs.line_centroid[j], segs.line_direction[j], ep.min_step, ep.max_step,
                    ep.max_gap)
        if inl[j]:
            out[(j, 0)] = sorted(zip(idx[bounds[j] : bounds[j + 1]], off[bounds[j] : bounds[j + 1]], strict=True))
    return out


def knot_deskew(cfg: SlamConfig, imu: ImuSamples | None, t0: float) -> DeskewTable | None:
    """The deskew table (``slam.trajectory.deskew``) on the knot grid that starts at ``t0`` (s); None without
    an IMU or with ``trajectory.imu_deskew`` off."""
    if imu is None or not cfg.trajectory.imu_deskew:
        return None
    dt = 1.0 / cfg.trajectory.knot_rate
    n = int(np.ceil((imu.times[-1] - t0) / dt)) + 1
    return deskew_table(imu.times, imu.gyro, imu.instantaneous, t0 + dt * np.arange(n, dtype=np.float64))
