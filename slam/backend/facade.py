"""The SLAM back end: body poses at knots + world planes in one gtsam factor graph.

Inputs are plain numpy (independent of the front end's records)::

    be = Backend(config)                              # a BackendConfig (every field given)
    i = be.add_pose(t, T_world_body_guess)            # knots in time order
    be.add_plane(7, normal_world, offset)             # n . x + offset = 0, world frame
    b = be.add_observations(i - 1, 7, points_body, alphas, sigmas)   # one block
    be.step()                                         # the incremental solver, while reading
    be.batch_optimize()                               # final batch (damped Gauss-Newton)
    be.poses(); be.planes(); be.T_world_body(times); be.plane_covariance(7)

The parts, each in its module: the variables and factor records (:mod:`slam.backend.graph`),
the knots with their motion, datum and IMU factors (:mod:`slam.backend.knots`), the observation
blocks (:mod:`slam.backend.blocks`), planes with their priors, ties and merges
(:mod:`slam.backend.ties`), the incremental solver, a fixed-lag window or iSAM2
(:mod:`slam.backend.incremental`), and the batch solves and trim (:mod:`slam.backend.batch`).

An observation block is the set of points seen on one plane during one knot interval
``[t_i, t_i+1]`` (``alphas`` the beam times' fractions of that interval; all zero or None gives a
single-pose factor on ``X(i)``), with per-point point-to-plane sigmas, all in one batched
factor (:mod:`slam.backend.factors`) with per-point robust kernels, points in the body frame at
their beam times.
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P, X
from numpy.typing import ArrayLike, NDArray

from slam.backend.batch import BatchSolver
from slam.backend.blocks import BlockStore, ObservationBlock
from slam.backend.config import BackendConfig, OptimizeSummary, StepReport
from slam.backend.factors import RobustKernel, robust_weights
from slam.backend.graph import FactorGraph
from slam.backend.incremental import IncrementalSolver, make_incremental
from slam.backend.knots import Knots, is_imu_keys
from slam.backend.marginals import eliminated_marginals, root_marginals
from slam.backend.sections import SectionedBatch
from slam.backend.ties import PlaneTies
from slam.trajectory.interpolation import interpolate_trajectory

FloatArray = NDArray[np.float64]


class Backend:
    """Factor graph of knots and planes (and with an IMU velocities and biases); see module doc."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.graph = FactorGraph()
        self.knots = Knots(self.graph, config)
        self.blocks = BlockStore(self.graph, config.kernel, config.coalesce_blocks)
        self.ties = PlaneTies(self.graph, self.blocks, config.horizontal_sigma, config.vertical_sigma)
        self.batch = BatchSolver(self.graph, self.blocks, config)
        self.incremental: IncrementalSolver = make_incremental(config, self.graph, self.blocks, self.batch)
        self.sections = SectionedBatch(self.graph, self.blocks, config)
        self._marginals: tuple[int, gtsam.Marginals | None] | None = None  # (graph version, marginals; None: indeterminate)
        self._section_covariances: tuple[int, dict[int, FloatArray]] | None = None  # (graph version, by plane)

    # ----------------------------------------------------------------- variables
    def add_pose(self, time: float, T_world_body: ArrayLike, velocity_world: ArrayLike | None = None) -> int:
        """Add the next knot at ``time`` [s] (strictly after the last) with an initial guess
        (4, 4); returns its index. With an IMU, ``velocity_world`` (3,) [m/s] is its velocity
        guess (default: from the previous knots, or zero)."""
        return self.knots.add_pose(time, T_world_body, velocity_world)

    def add_velocity_prior(self, knot: int, velocity_world: ArrayLike, sigma: float) -> None:
        """A prior (3,) [m/s] on a knot's velocity, e.g. zero while the operator stands still
        (IMU configurations only)."""
        self.knots.add_velocity_prior(knot, velocity_world, sigma)

    def add_imu(self, knot: int, accel_imu: ArrayLike, gyro_imu: ArrayLike, dt: ArrayLike) -> None:
        """IMU samples of interval [knot, knot+1] (IMU frame; see :func:`slam.motion.preintegrate`)
        as one ImuFactor. Needs ``BackendConfig.imu``."""
        self.knots.add_imu(knot, accel_imu, gyro_imu, dt)

    def add_plane(self, plane_id: int, normal_world: ArrayLike, offset: float, horizontal: bool = False,
                  vertical: bool = False, anchor: ArrayLike | None = None) -> None:
        """Add plane ``plane_id`` (int >= 0): ``normal_world . x + offset = 0`` (the normal is
        normalised). ``horizontal`` adds a prior keeping it a floor/ceiling, ``vertical`` one
        keeping it a wall (its normal horizontal: ``n_z = 0``).

        ``anchor`` (3,), a world point near the plane's observed patch: the variable is the plane
        expressed about it (``n . (x - anchor) + d_local = 0``). A plane seen far from the world
        origin is otherwise badly conditioned (turning the normal about the origin and shifting
        the offset nearly cancel at the patch: condition numbers of 1e7-1e9 at 20 m). Estimates
        and inputs stay in the world frame; :meth:`plane_covariance` is about the anchor."""
        self.ties.add_plane(plane_id, normal_world, offset, horizontal, vertical, anchor)

    # ----------------------------------------------------------------- observations
    def add_observations(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
                         sigmas: ArrayLike) -> int:
        """Add a block: points (N, 3) [m] in the body frame at their beam times, seen on plane
        ``plane_id`` during interval [knot, knot+1] at fractions ``alphas`` (N,) (None or all 0:
        at the knot itself), with point-to-plane sigmas (N,) or scalar [m]. Returns the block
        id (with ``config.coalesce_blocks`` possibly that of the block it joined)."""
        return self.blocks.add(knot, plane_id, points, alphas, sigmas)

    def remove_observations(self, block_id: int) -> None:
        """Remove an observation block."""
        self.blocks.remove(block_id)

    def blocks_of_plane(self, plane_id: int) -> list[int]:
        """Ids of the observation blocks on a plane."""
        return self.blocks.of_plane(plane_id)

    def block(self, block_id: int) -> ObservationBlock:
        """The data of an observation block."""
        return self.blocks.get(block_id)

    def block_residuals(self, block_id: int) -> tuple[FloatArray, FloatArray]:
        """Whitened signed point-to-plane residuals (N,) at the current estimate and the robust
        (IRLS) weights (N,) in [0, 1] the kernel gives them (small = treated as outlier)."""
        return self.blocks.residuals(block_id)

    def trim_observations(self, max_whitened: float, min_distance: float) -> tuple[int, int]:
        """Detach the points that do not fit their plane at the current estimate: those whose
        point-to-plane residual exceeds both ``max_whitened`` sigmas and ``min_distance`` [m]
        (a wall's segment on the plane of its door or board, 1-2 cm off, or the other way
        round). Blocks keep their other points; a block left empty is removed. Returns (points
        detached, blocks changed)."""
        return self.batch.trim(max_whitened, min_distance)

    # ----------------------------------------------------------------- planes
    def merge_planes(self, keep_id: int, drop_id: int) -> int:
        """Merge plane ``drop_id`` into ``keep_id``: its blocks are re-keyed onto ``keep_id`` (same
        block ids), its horizontality or verticality prior moves over if ``keep_id`` has none, its
        ties follow, and the variable is removed. ``keep_id`` keeps its current estimate.
        Returns the number of moved blocks."""
        return self.ties.merge(keep_id, drop_id)

    def link_planes(self, keep_id: int, drop_id: int, sigma_angle: float, sigma_offset: float) -> int:
        """Tie plane ``drop_id`` to ``keep_id`` with a tight equality factor: the incremental way to
        merge (the solvers go on incrementally); :meth:`fold_links` merges them for good later.
        Returns the factor id. The residual is ``(B_keep^T n_drop, d_drop - d_keep)`` with the
        normals oriented alike, ``B_keep`` the tangent basis of ``keep``'s normal."""
        return self.ties.link(keep_id, drop_id, sigma_angle, sigma_offset)

    def add_parallel(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        """Keep plane ``plane_id`` parallel to ``host_id`` (same facing), offsets free: a door set
        into its wall, a board on it. Survives merges (re-keyed onto the surviving plane).
        Returns the factor id."""
        return self.ties.tie(host_id, plane_id, sigma_angle, perpendicular=False)

    def add_perpendicular(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        """Keep plane ``plane_id`` perpendicular to ``host_id`` (one residual: the dot product of
        the unit normals, sigma ``sigma_angle`` [rad]): the plane through a door's edge across its
        wall. Survives merges like :meth:`add_parallel`. Returns the factor id."""
        return self.ties.tie(host_id, plane_id, sigma_angle, perpendicular=True)

    def fold_links(self) -> dict[int, int]:
        """Turn every :meth:`link_planes` tie into a real merge (blocks re-keyed onto the surviving
        plane, linked variables removed). Returns dropped id -> surviving id; a dropped id given
        to any method afterwards means the surviving plane. Made at the end of a run, before the
        batch, and with ``config.fold_links_in_window`` at every :meth:`step`."""
        return self.ties.fold_links()

    def remove_plane(self, plane_id: int) -> None:
        """Remove a plane with all its observation blocks, priors and ties."""
        self.ties.remove_plane(plane_id)

    # ----------------------------------------------------------------- solving
    def step(self) -> StepReport:
        """The configured incremental solver's step (``config.solver``: a fixed-lag window
        solve, or an iSAM2 update with its rebuild and batch fallback) over everything added or
        removed since the last step; nothing before the second knot. With
        ``config.fold_links_in_window`` the planes linked since the last step are merged first
        (:meth:`fold_links`): a window then carries one plane per surface, not a link to every
        earlier copy of a wall walked past again (whose number, and cost, grew with the walk)."""
        if self.config.fold_links_in_window and self.ties.links:
            self.ties.fold_links()
        self.graph.keep_rebuilt(False)  # a batch solved mid-walk keeps nothing for the window
        return self.incremental.step()

    def batch_optimize(self, max_iterations: int | None = None, graduated: bool = True,
                       kernel: RobustKernel | None = None) -> OptimizeSummary:
        """A batch solve over every factor from the current estimate; with ``graduated`` (and a
        robust kernel) first with the kernel threshold scaled by each ``config.robust_schedule``
        multiplier, then nominal. ``max_iterations`` per stage (None: ``config.lm_max_iterations``);
        ``kernel``: the observation blocks' kernel for this solve (None: ``config.kernel``). The
        window's summaries are dropped and iSAM2 is rebuilt at its next step. A walk of more than
        ``config.batch_section_knots`` knots is solved in sections (:mod:`slam.backend.sections`)."""
        if self.sections.needed():
            return self.sections.optimize(max_iterations, graduated, kernel)
        if self.graph.rebuilt is None:  # the solves after it (trims) and the covariances reuse them
            self.graph.keep_rebuilt(True)
        return self.batch.optimize(max_iterations, graduated, kernel)

    def error(self) -> float:
        """Total graph error (0.5 sum of whitened squares, robust losses) at the current estimate."""
        return self.sections.total_error() if self.sections.needed() else self.batch.error()

    @property
    def singular_systems(self) -> list[str]:
        """The singular linear systems the solves met (each retried with more damping)."""
        return self.batch.singular_systems

    # ----------------------------------------------------------------- estimates
    @property
    def num_knots(self) -> int:
        return len(self.graph.times)

    def knot_times(self) -> FloatArray:
        """Knot times (K,) [s]."""
        return np.asarray(self.graph.times, dtype=float)

    def poses(self) -> FloatArray:
        """Current ``T_world_body`` of every knot, (K, 4, 4)."""
        return self.knots.poses()

    def pose(self, knot: int) -> FloatArray:
        """Current ``T_world_body`` (4, 4) of one knot."""
        return self.knots.pose(knot)

    def velocities(self) -> FloatArray:
        """World-frame velocities (K, 3) [m/s] of the knots (IMU configurations only)."""
        return self.knots.velocities()

    def velocity(self, knot: int) -> FloatArray:
        """World-frame velocity (3,) [m/s] of one knot (IMU configurations only)."""
        return self.knots.velocity(knot)

    def bias(self, knot: int) -> FloatArray:
        """IMU bias (6,) of one knot: accelerometer (m/s^2) then gyroscope (rad/s)."""
        return self.knots.bias(knot)

    def plane_ids(self) -> list[int]:
        return self.blocks.plane_ids()

    def planes(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Plane ids (P,), unit normals (P, 3) and offsets (P,) in the world frame (n.x + d = 0)."""
        ids = self.plane_ids()
        world = [self.plane(j) for j in ids]
        normals = np.array([w[0] for w in world]).reshape(-1, 3)
        return (np.asarray(ids, dtype=np.int64), normals, np.array([w[1] for w in world], dtype=float))

    def plane(self, plane_id: int) -> tuple[FloatArray, float]:
        """Unit normal (3,) and offset of one plane (world frame)."""
        j = self.blocks.check_plane(plane_id)
        p = self.graph.values.atOrientedPlane3(P(j))
        n = np.asarray(p.normal().point3())
        return n, float(p.distance()) - float(n @ self.graph.anchors.get(j, np.zeros(3)))

    def T_world_body(self, times: ArrayLike) -> FloatArray:
        """Interpolated ``T_world_body`` (M, 4, 4) at times (M,) within the knots, exactly as the
        factors place points."""
        return interpolate_trajectory(self.graph.times, self.poses(), np.atleast_1d(times))

    def predict_pose(self, time: float) -> FloatArray:
        """Constant-velocity extrapolation (4, 4) of the trajectory to ``time`` >= the last knot
        (initial guess of the next knot, deskewing of the newest scan)."""
        return self.knots.predict_pose(time)

    # ----------------------------------------------------------------- covariances
    def pose_covariance(self, knot: int) -> FloatArray:
        """Marginal covariance (6, 6) of a knot's pose in gtsam's tangent order (rotation [rad],
        then translation [m], both in the body frame); a ValueError when the system is indeterminate."""
        return self._covariance(X(self.graph.check_knot(knot)))

    def plane_covariance(self, plane_id: int) -> FloatArray:
        """Marginal covariance (3, 3) of a plane in its retract coordinates: normal direction in
        the ``Unit3.basis()`` tangent (2, rad) and offset (m), about its anchor; a ValueError when
        the system leaves it indeterminate."""
        return self._covariance(P(self.blocks.check_plane(plane_id)))

    def plane_covariances(self, plane_ids: Sequence[int]) -> dict[int, FloatArray]:
        """:meth:`plane_covariance` of each of ``plane_ids``, a plane without one (an
        indeterminate system; a variance over 1e6, a direction the elimination passed with a
        rounding-sized pivot) left out, all from one elimination: with the planes ordered last
        (:func:`slam.backend.marginals.root_marginals`), or a sectioned walk's (the other planes
        that one section alone sees eliminated with it); plane by plane where neither can."""
        ids: dict[int, int] = {}
        for j in plane_ids:
            try:
                ids[int(j)] = self.blocks.check_plane(int(j))
            except ValueError:  # no such plane: no covariance
                continue
        if self.sections.needed():
            got = self.sections.plane_covariances(sorted(set(ids.values())))
            return _determined({j: got[i] for j, i in ids.items() if i in got})
        if ids and self.incremental.marginal_covariance(P(next(iter(ids.values())))) is None:
            graph = self.blocks.whole_graph()
            joint = root_marginals(graph, self.graph.used_values(graph), sorted({P(i) for i in ids.values()}),
                                   self.blocks.planes)
            if joint is not None:
                return _determined({j: joint[P(i)] for j, i in ids.items()})
            # singular (a plane left indeterminate) or in pieces: the planes' dense system
            part = eliminated_marginals(graph, self.graph.used_values(graph), sorted({P(i) for i in ids.values()}),
                                        self.blocks.planes)
            if part is not None:
                return _determined({j: part[P(i)] for j, i in ids.items() if P(i) in part})
        out: dict[int, FloatArray] = {}
        for j in ids:
            try:
                out[j] = self.plane_covariance(j)
            except (ValueError, RuntimeError):
                continue
        return _determined(out)

    def _covariance(self, key: int) -> FloatArray:
        """From the incremental solver if it holds the current graph, else from the whole graph
        (kept until the graph or the estimate changes); a plane's of a sectioned walk from its
        section (:meth:`SectionedBatch.plane_covariances`, all planes at once)."""
        cov = self.incremental.marginal_covariance(key)
        if cov is not None:
            return cov
        if self.sections.needed() and chr(gtsam.Symbol(key).chr()) == "p":
            if self._section_covariances is None or self._section_covariances[0] != self.graph.version:
                self._section_covariances = (self.graph.version, self.sections.plane_covariances())
            j = int(gtsam.Symbol(key).index())
            if j not in self._section_covariances[1]:
                raise ValueError(f"plane {j}: no marginal covariance (indeterminate in its section)")
            return self._section_covariances[1][j]
        if self._marginals is None or self._marginals[0] != self.graph.version:
            graph = self.blocks.whole_graph()
            try:
                marg: gtsam.Marginals | None = gtsam.Marginals(graph, self.graph.used_values(graph))
            except RuntimeError:  # indeterminate: not tried again until the graph or estimate changes
                marg = None
            self._marginals = (self.graph.version, marg)
        if self._marginals[1] is None:
            raise ValueError(f"{gtsam.DefaultKeyFormatter(key)}: no marginal covariance (the system is indeterminate)")
        return np.asarray(self._marginals[1].marginalCovariance(key))

    def release(self) -> None:
        """Let go of what the solves keep for their next call (the whole graph's marginals, the
        interval factors the final batch built); the estimates stay, and anything let go is
        built again if asked for. Meant for the end of a run, before the export."""
        self._marginals = None
        self._section_covariances = None
        self.blocks.drop_group_factors()
        self.graph.keep_rebuilt(False)

    # ----------------------------------------------------------------- statistics
    def residual_statistics(self) -> dict[str, float]:
        """Counts, RMS of whitened residuals and the share of down-weighted points (w < 0.5);
        with IMU factors also their count and whitened RMS (``imu_factors``, ``imu_rms_whitened``:
        how far the trajectory is from what the IMU measured, in units of its noise)."""
        e = self.blocks.whitened_rows()[1]
        w = robust_weights(e, self.config.kernel)
        out = {
            "blocks": float(len(self.blocks.blocks)),
            "points": float(e.size),
            "rms_whitened": float(np.sqrt(np.mean(e**2))) if e.size else 0.0,
            "outlier_fraction": float(np.mean(w < 0.5)) if e.size else 0.0,
        }
        # the IMU factors, those the window has let go built again one at a time
        imu = [fid for fid, r in self.graph.records.items()
               if isinstance(r.factor, gtsam.ImuFactor) or (r.factor is None and is_imu_keys(r.keys))]
        if imu:
            values = self.graph.values
            chi2 = sum(2.0 * self.graph.factor(fid).error(values) for fid in imu)  # error(): half the whitened square
            out["imu_factors"] = float(len(imu))
            out["imu_rms_whitened"] = float(np.sqrt(chi2 / (9.0 * len(imu))))
        return out


# a variance over this (a sigma over 1,000 rad or m) marks a direction the system leaves
# undetermined that an elimination passed with a pivot of rounding size
_UNDETERMINED_VARIANCE = 1e6


def _determined(covs: dict[int, FloatArray]) -> dict[int, FloatArray]:
    """The covariances whose every variance is finite and under ``_UNDETERMINED_VARIANCE``."""
    return {j: c for j, c in covs.items()
            if np.all(np.isfinite(c)) and float(np.max(np.diag(c))) < _UNDETERMINED_VARIANCE}

