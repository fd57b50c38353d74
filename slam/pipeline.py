"""The SLAM pipeline: scans in, trajectory and planes out (the orchestration).

Per scan: segment with the configured segmenter, lift the segments into the body frame at their
beams' times and run the scan-only edge tests (``frontend.scan_prep``, possibly ahead in another
process). Knots of the trajectory lie on a fixed grid at ``knot_rate``
(``frontend.knots.KnotMirror``); knot ``k+1`` is processed once every segment whose beams end
before ``t_{k+1}`` has arrived (``frontend.pending``):

1. predict ``T_world_body(t_{k+1})`` with the motion model (``frontend.motion_model``: constant
   velocity, or the IMU with ``slam.imu_feed.ImuMotion``);
2. place the ready segments in the world with the current trajectory (deskewed: every point at
   its own beam time), associate them with loose gates and refine the newest knots by
   Gauss-Newton against the fixed planes (``frontend.window_tracker``);
3. associate again with the tight gates (``frontend.association``): each associated segment
   becomes observations of its plane in the back end (two moment-matched virtual points, each in
   its own knot interval; ``frontend.blocks``), each door/board break of its edge plane
   (``frontend.edge_tracker``, when edges are on);
4. unassociated segments wait in a pool from which new planes are created; planes that converge
   onto the same surface are merged (``frontend.map_builder``; this is also how a loop closes:
   after the walk returns, segments associate with the old planes again through gates that grow
   with the distance walked since a plane was last seen, and duplicates merge);
5. every ``update_every`` knots the back end takes a step (a window solve or iSAM2) and the front
   end copies the new estimates in (with ``backend.pipelined`` the back end runs in its own
   process and the front end copies in the step before's, ``slam.backend_process``).

At the end a batch solve over everything gives the final trajectory and planes
(``slam.result.SlamResult``). Every component's parameters come from ``slam.params``.
"""

from __future__ import annotations

import time as _time
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig
from segmentation import Scanline
from slam import params
from slam.backend import RobustKernel, StepReport
from slam.backend_process import BackendProcess, make_backend
from slam.config import SlamConfig
from slam.frontend.association import ScanAssociator
from slam.frontend.blocks import ObservationBlocks
from slam.frontend.edge_tracker import edge_feature
from slam.frontend.edges import EDGE_ID_BASE
from slam.frontend.initial_motion import estimate as estimate_initial_motion
from slam.frontend.knots import KnotMirror
from slam.frontend.map_builder import MapBuilder
from slam.frontend.observations import ScanSegments
from slam.frontend.pending import PendingScan, ScanQueues
from slam.frontend.plane_init import SegmentPool
from slam.frontend.planemap import KIND_NAMES, PlaneMap
from slam.frontend.scan_prep import PreparedScan, ScanPreparer, knot_deskew
from slam.frontend.transients import TRANSIENT, TransientFilter
from slam.frontend.window_tracker import WindowTracker
from slam.health import trajectory_departure
from slam.imu_feed import ImuSamples, motion_model
from slam.result import BatchStats, RunStats, SlamResult, StageTimer

FloatArray = NDArray[np.float64]


class SlamRunner:
    """Online front end + incremental back end over a time-ordered stream of scanlines, with
    the IMU's samples (``imu``, body frame) when there are any."""

    def __init__(self, rig: Rig, cfg: SlamConfig, imu: ImuSamples | None = None) -> None:
        self.noise = params.noise_levels(rig, cfg)
        self.preparer = ScanPreparer(rig, cfg, imu)
        # the run's values at its scanners' noise (``slam.config.NoiseSection``'s rule)
        cfg = params.noise_scaled(cfg, self.noise.shared)
        self.cfg = cfg
        self.imu = imu
        self.rig = rig
        self.scanner_names = [s.name for s in rig.scanners]
        T_body_scanner = [s.T_body_scanner.matrix() for s in rig.scanners]
        range_sigma = list(self.noise.sigma)
        self._T_body_scanner = T_body_scanner
        self._scan_span = max(s.scanner_model.time_increment * (s.scanner_model.n_beams - 1) for s in rig.scanners)
        with_imu = imu is not None
        self.params = params.components(cfg, with_imu)
        self.gates = self.params.gates
        self.dt = 1.0 / cfg.trajectory.knot_rate
        self.knots = KnotMirror(self.dt)
        # in its own process (one update behind) with ``backend.pipelined``
        self.backend = make_backend(self.params.backend, cfg.backend.pipelined, self.knots,
                                    4 * cfg.backend.update_every)
        self.stats = RunStats(imu_used=int(with_imu))
        self._timer = StageTimer()
        self.queues = ScanQueues()
        self.pmap = PlaneMap(cell_size=cfg.frontend.extent_cell,
                             samples_until=cfg.frontend.transient_probation if cfg.frontend.transient_check else 0)
        self.pool = SegmentPool(self.params.plane_init)
        self.maps = MapBuilder(self.params.map, self.pmap, self.pool, self.knots, self.backend, self.stats)
        # the optional features: the IMU's motion model or constant velocity, edges or none
        self.motion = motion_model(imu, self.params.imu, self.params.imu_motion, self.backend)
        self.edges = edge_feature(self.params.edges, self.pmap, self.knots, T_body_scanner, range_sigma, self.backend,
                                  self.stats)
        children = self.maps.ties.children
        self.associator = ScanAssociator(self.pmap, self.knots, T_body_scanner, cfg.frontend.point_sigma,
                                         cfg.frontend.min_segment_points, children,
                                         line_direction=self.noise.shared > 1.0)
        def fixed() -> set[int]:  # merged with another or a host of ties: not taken out alone
            return self.pmap.merge_hosts() | set(children().values())

        self.transients = TransientFilter(self.params.transients, self.pmap, self.knots, T_body_scanner, fixed)
        self.tracker = WindowTracker(self.params.tracking, self.params.tracking_gates, self.knots, self.pmap,
                                     self.queues, self.associator, self.edges, self.motion, children)
        self._since_update = 0
        # knots at rest in a row up to the newest (the IMU's zero-velocity test or the tracked poses;
        # counted for frontend.rest_observe_every only)
        self._rest_run = 0
        # the first scans, held (and no knot processed) until the start's motion is known
        self._start_scans: list[ScanSegments] | None = None

    # ------------------------------------------------------------------ knots
    def _append_knot(self, T: FloatArray, v: FloatArray | None = None) -> int:
        """Add the next knot (pose, velocity) to the mirror and the back end, with what the
        motion model adds about it."""
        k = self.knots.append(T, v)
        self.backend.add_pose(self.knots.time(k), T, velocity_world=self.motion.velocity(self.knots, k))
        zupt = self.motion.add_factors(self.knots, k)
        self.stats.zero_velocity_updates += zupt
        if self.cfg.frontend.rest_observe_every > 1:
            self._rest_run = self._rest_run + 1 if (zupt or self._still(k)) else 0
        return k

    def _still(self, k: int) -> bool:
        """Whether the tracked poses say the rig stood still over the half second up to knot ``k``
        (less than 1 cm and 0.5 deg from the knot half a second before)."""
        j = k - max(1, round(0.5 / self.dt))
        if j < 0:
            return False
        A, B = self.knots.T[j], self.knots.T[k]
        if float(np.linalg.norm(B[:3, 3] - A[:3, 3])) > 0.01:
            return False
        c = (float(np.trace(A[:3, :3].T @ B[:3, :3])) - 1.0) / 2.0
        return c > np.cos(np.radians(0.5))

    # ------------------------------------------------------------------ input
    def add_scan(self, line: Scanline) -> None:
        """Feed the next scanline (time order); knots are processed as soon as they are complete."""
        self.add_prepared(self.preparer.prepare(line))

    def add_prepared(self, scan: PreparedScan) -> None:
        """Feed the next scan as prepared by a ``ScanPreparer`` over the same stream (time order;
        possibly in another process, ``slam.prefetch``); knots are processed as soon as they are
        complete."""
        t_start = _time.perf_counter()
        self.stats.scans += 1
        if self.knots.t0 is None:
            # the deskew table the preparer built for this stream (the runner's own, or one in
            # another process, which hands it on with the first scan), else the same one built here
            own = self.preparer.t0 == scan.stamp
            table = self.preparer.deskew if own else scan.deskew
            if table is None and not own:
                table = knot_deskew(self.cfg, self.imu, scan.stamp)
            self.knots.start(scan.stamp, table)
            self._start_scans = []
        self._timer.add_seconds("segmentation", scan.seconds_segmentation)
        self._timer.add_seconds("frontend", scan.seconds_lift)
        if scan.skipped:
            self.stats.skipped_scans += 1
            return
        segs = scan.segs
        if segs is not None:
            self.stats.segments += segs.n_segments
            self.queues.add(segs, scan.edge_tests)  # the scan is handed over: its tests are the queue's
            if self._start_scans is not None:
                self._start_scans.append(segs)
        self._timer.add("frontend", t_start)
        if self._start_scans is not None:
            if scan.stamp <= self.knots.time(0) + self.params.initial_motion.window:
                return
            self._begin()
        # a knot is complete once no later scan can have beams before it
        while self.knots.time(self.knots.n) + self._scan_span < scan.stamp:
            self._process_knot()

    def finish(self) -> None:
        """Process the remaining knots (up to the last beam) and take a last back-end step."""
        if self._start_scans is not None:
            self._begin()
        last = self.queues.last_end()
        if last is not None:
            while self.knots.time(self.knots.n - 1) < last:
                self._process_knot()
        self._update()
        if isinstance(self.backend, BackendProcess):  # the last step's result, one update behind
            self._apply(self.backend.collect())

    def _begin(self) -> None:
        """The first knot, once the first scans tell how the walk starts (at rest, or moving:
        ``frontend.initial_motion``, which then gives the motion model its start and the first
        knot its velocity)."""
        t_start = _time.perf_counter()
        assert self._start_scans is not None
        scans, self._start_scans = self._start_scans, None
        t0 = self.knots.time(0)
        start = estimate_initial_motion(scans, self._T_body_scanner, t0, self.dt, self.params.initial_motion,
                                        list(self.noise.sigma))
        self.stats.initial_motion = start.as_dict()
        T0 = self.motion.initial_pose(t0)
        v0 = None
        if start.increments:  # moving, or at rest with initial_motion_rest_odometry
            self.motion.start_moving(start.increments, start.increment_sigmas)
        if start.moving:
            v0 = T0[:3, :3] @ start.twist_body[3:]
        self._append_knot(T0, v0)
        self._timer.add("initial_motion", t_start)

    # ------------------------------------------------------------------ one knot
    def _process_knot(self) -> None:
        t_start = _time.perf_counter()
        k_new = self.knots.n
        t_new = self.knots.time(k_new)
        T_pred, v_pred = self.motion.predict(self.knots)
        self.knots.hold(T_pred)
        ready = self.queues.take_ready(t_new)
        T_new = self.tracker.track(ready, k_new, T_pred)
        self.knots.release()
        t = self._timer.add("tracking", t_start)
        self._append_knot(T_new, v_pred)
        self._associate_and_observe(ready)
        t = self._timer.add("association", t)
        # drop the point data of scans the pool can no longer use, keeping their segment rows
        self.queues.compact(t_new - self.pool.params.window - 1.0)
        self.maps.create_planes(t_new, self.queues)
        self.edges.create(t_new)
        t = self._timer.add("plane_creation", t)
        self._since_update += 1
        be = self.cfg.backend
        if self._since_update >= be.update_every:
            self._update()
            self._timer.add("backend", t)
        elif self._since_update == be.pipelined_collect_after and isinstance(self.backend, BackendProcess):
            # the outstanding step's result taken at a fixed knot (the same input gives the same
            # output), sooner than the next step: the front end lags the back end by this many knots
            self._apply(self.backend.collect())
            self._timer.add("backend", t)

    def _associate_and_observe(self, ready: list[PendingScan]) -> None:
        """Associate the ready scans with the tight gates; their segments and breaks observe the
        map (the rest goes to the pool)."""
        for pid in self.transients.check(ready):
            self.backend.remove_plane(pid)
            self.pmap.remove_transient(pid)
            self.stats.planes_transient += 1
        blocks = ObservationBlocks(self.knots, self.stats)
        now = self.knots.time(self.knots.n - 1)
        hosts = self.maps.ties.children()
        idle = self._rest_run > 1 and self._rest_run % self.cfg.frontend.rest_observe_every != 0
        for p, summary in zip(ready, self.associator.summaries(ready), strict=True):
            a = self.associator.associate(p, self.gates, summary)
            if idle:  # a standing rig's repeated view: neither associated nor pooled
                a = replace(a, ids=np.full_like(a.ids, -2), grows=np.zeros_like(a.grows))
                self.stats.rest_idle_scans += 1
            ids = np.maximum(a.ids, -1)  # held back (-2) or not: unassociated
            p.plane_ids = ids
            segs = p.segs
            self.edges.observe(p, ids, hosts, now, blocks)
            self.maps.observe(p, a.ids, summary[0], summary[1], self._T_body_scanner[segs.scanner], now, blocks,
                              a.grows)
            self.queues.done.append(p)
        blocks.flush(self.backend)

    def _update(self) -> None:
        self._since_update = 0
        self._apply(self.backend.step())

    def _apply(self, report: StepReport) -> None:
        """A back-end step's outcome into the statistics and, if it solved, the front end."""
        if not report.solved:
            return
        self.stats.isam2_rebuilds += report.rebuilds
        self.stats.isam2_fallbacks += report.fallbacks
        self._after_update()

    def _after_update(self) -> None:
        self.stats.updates += 1
        # refresh the recent knots and the recently seen planes
        k0 = max(0, self.knots.n - 4 * self.cfg.backend.update_every)
        for k in range(k0, self.knots.n):
            self.knots.T[k] = self.backend.pose(k)
        self.motion.refresh(self.knots, k0)  # velocities and bias with an IMU
        now = self.knots.time(self.knots.n - 1)
        self.maps.refresh(now)
        self.maps.merge(now)
        self.edges.refresh(now)

    # ------------------------------------------------------------------ results
    def result(self, batch: bool = True, covariances: bool = True) -> SlamResult:
        """The final estimates: after a batch solve over everything (``batch``, with the final
        trims), else the current ones; with the planes' marginal covariances unless
        ``covariances`` is off (they take a factorisation of the whole graph)."""
        t = _time.perf_counter()
        summary = None
        self.backend.fold_links()
        online = None  # the window's poses, kept until the batch is done
        if batch and self.knots.n >= 2:
            online = self.backend.poses()
            be = self.cfg.backend
            final = None if be.final_robust == "same" else RobustKernel(be.final_robust, be.robust_k)
            summary = self.backend.batch_optimize(be.batch_iterations, graduated=False, kernel=final)
            first_round = 0
            for _ in range(be.final_trim_rounds if be.final_trim_sigmas > 0 else 0):
                n_pts, n_blk = self.backend.trim_observations(be.final_trim_sigmas, be.final_trim_distance)
                self.stats.trimmed_points += n_pts
                self.stats.trimmed_blocks += n_blk
                if not n_pts or n_pts < be.final_trim_min_fraction * first_round:
                    break  # nothing, or too little to move the estimate: not solved again
                first_round = first_round or n_pts
                summary = self.backend.batch_optimize(be.final_trim_iterations, graduated=False, kernel=final)
        self._timer.add("batch", t)
        poses = self.backend.poses()
        departure = (0.0, 0.0)
        if online is not None:
            departure = trajectory_departure(self.backend.knot_times(), online, poses, self.cfg.health.departure_window)
        ids, normals, offsets = self.backend.planes()
        real = ids < EDGE_ID_BASE  # edge planes are observations' helpers, not surfaces
        ids, normals, offsets = ids[real], normals[real], offsets[real]
        for pid, n, d in zip(ids, normals, offsets, strict=True):
            self.pmap.set_estimate(int(pid), n, float(d))
        rows = self.queues.segment_rows(self._resolve)
        stats = replace(
            self.stats,
            knots=self.knots.n,
            planes=len(ids),
            edges=self.edges.count(),
            pool_dropped=self.pool.dropped,
            singular_systems=list(self.backend.singular_systems),
            batch=None if summary is None else BatchStats(summary.initial_error, summary.final_error,
                                                          summary.iterations, summary.seconds, *departure),
            residuals=self.backend.residual_statistics(),
        )
        # a plane without a marginal (an indeterminate system) is left out
        cov = self.backend.plane_covariances([int(p) for p in ids]) if covariances else {}
        self.backend.release()  # the marginals and the batch's factors: the export needs the memory
        return SlamResult(
            knot_times=self.backend.knot_times(),
            T_world_body=poses,
            plane_ids=ids,
            plane_normals=normals,
            plane_offsets=offsets,
            plane_covariances=cov,
            plane_map=self.pmap,
            scanner_names=self.scanner_names,
            segment_rows=rows,
            stats=stats,
            timings=dict(self._timer.t),
            deskew=self.knots.deskew,
            T_world_body_online=online,
        )

    def close(self) -> None:
        """Stop the back-end process, if the back end runs in one (``backend.pipelined``): its
        estimates are no longer needed."""
        if isinstance(self.backend, BackendProcess):
            self.backend.close()

    def _resolve(self, pid: int) -> int:
        """A segment's plane id at the end: followed through the merges, ``TRANSIENT`` for a
        plane taken out as a thing that moved."""
        j = self.pmap.resolve(pid)
        return TRANSIENT if self.pmap.planes[j].transient else j

    def kind_name(self, pid: int) -> str:
        """The kind (wall, floor, ceiling, other) of map plane ``pid``."""
        return KIND_NAMES[self.pmap.planes[pid].kind]
