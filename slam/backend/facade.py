"""The SLAM back end: body poses at knots + world planes in one gtsam factor graph.

Inputs are plain numpy (independent of the front end's records)::

    be = Backend(BackendConfig())
    i = be.add_pose(t, T_world_body_guess)            # knots in time order (40 Hz scans)
    be.add_plane(7, normal_world, offset)             # n . x + offset = 0, world frame
    b = be.add_observations(i - 1, 7, points_body, alphas, sigmas)   # one block
    be.update()                                       # iSAM2 step(s) while reading
    be.batch_optimize()                               # final batch (damped Gauss-Newton)
    be.poses(); be.planes(); be.T_world_body(times); be.plane_covariance(7)

Variables (gtsam keys): ``X(i)`` body pose ``T_world_body`` at knot i, ``P(j)`` plane with id j
(``OrientedPlane3``), ``E(s)`` ``T_body_scanner`` of scanner s (only if added, for calibration),
``V(i)``/``B(i)`` world velocity and IMU bias per knot (only with an IMU).

Factors added automatically: a datum prior on the first knot (the whole pose by default, or
position and heading when floor/ceiling priors define the vertical: ``datum="position_yaw"``),
a weak prior on the first interval's motion (without an IMU), a constant-velocity prior on every three
consecutive knots (:mod:`slam.motion`), and with an IMU the ImuFactor/bias random walk of each
interval given by :meth:`Backend.add_imu` plus priors on the first velocity and bias.

An observation block is the set of points seen on one plane during one knot interval
``[t_i, t_i+1]`` (``alphas`` the beam times' fractions of that interval; all zero or None gives a
single-pose factor on ``X(i)``), with per-point point-to-plane sigmas, all in one batched
factor (:mod:`slam.backend.factors`) with per-point robust kernels. Points are in the body frame at their
beam times, or in the scanner frame when ``scanner=s`` is given and ``E(s)`` was added.

Incremental estimation: ``update()`` hands new factors and variables to gtsam.ISAM2 and runs one
iSAM2 step (more with ``iterations``). A variable enters iSAM2 with its first factor, so add a
plane with enough observations to fix it (two non-parallel lines) before calling ``update()``.
Removing observation blocks uses iSAM2's factor removal; merging planes or a batch
optimisation rebuilds iSAM2 from the current estimate at the next ``update()``.
"""

from __future__ import annotations

import time as _time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, E, P, V, X
from numpy.typing import ArrayLike, NDArray

from slam.backend.factors import (
    RobustKernel,
    check_block,
    point_plane_factor,
    point_plane_terms,
    point_planes_factor,
    robust_weights,
    scanner_point_plane_factor,
)
from slam.backend.plane_summary import plane_summary_factor, scatter, shift_anchor
from slam.backend.solver import Solution, solve
from slam.motion import (
    ImuConfig,
    MotionPriorConfig,
    bias_random_walk_factor,
    constant_velocity_factor,
    datum_prior,
    horizontal_plane_prior,
    initial_velocity_factor,
    preintegrate,
)
from slam.trajectory.interpolation import interpolate_trajectory, knot_fractions, se3_exp, se3_log
from slam.trajectory.placement import interval_poses

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BackendConfig:
    """Back-end settings (validated on construction; a bad value is a ValueError naming it).

    kernel: per-point robust kernel of the observation blocks.
    motion: constant-velocity prior densities; ``use_motion_prior`` switches it off.
    initial_velocity_sigmas: (rad/s, m/s) of the weak prior on the first interval's motion.
    datum: ``"pose"`` fixes the first knot; ``"position_yaw"`` fixes its position and rotation
        about the body z axis only (with horizontal-plane priors giving the vertical).
    datum_sigma: sigma (rad and m) of the datum prior.
    datum_tilt_sigma: sigma (rad) on the first knot's roll and pitch with ``position_yaw``: loose, so
        the horizontal-plane priors level the map, yet finite so the system stays well conditioned.
    horizontal_sigma: sigma [rad] of the floor/ceiling horizontality priors.
    relinearize_threshold, relinearize_skip: iSAM2 relinearisation settings.
    plane_relinearize_factor: iSAM2 relinearisation threshold of planes, as a multiple of
        ``relinearize_threshold`` (the poses').
    lm_max_iterations, lm_relative_tolerance: the final batch's iterations and stopping rule
        (relative error decrease), per stage.
    robust_schedule: kernel-threshold multipliers of the stages that precede the nominal one in
        :meth:`Backend.batch_optimize` (graduated robustness: a redescending kernel at 3 sigma
        from an initial guess that is centimetres off would treat every point as an outlier).
    imu: IMU noise and mounting; None without an IMU.
    coalesce_blocks: a block added on the (knot, plane, scanner) of a block not yet summarised
        joins it (one factor instead of two: the per-factor cost dominates small blocks); the
        returned block id is then the joint block's and the earlier id is gone.
    """

    kernel: RobustKernel = field(default_factory=RobustKernel)
    motion: MotionPriorConfig = field(default_factory=MotionPriorConfig)
    use_motion_prior: bool = True
    initial_velocity_sigmas: tuple[float, float] = (3.0, 3.0)
    datum: Literal["pose", "position_yaw"] = "pose"
    datum_sigma: float = 1e-6
    datum_tilt_sigma: float = 0.1
    vertical_sigma: float = 1e-3
    horizontal_sigma: float = 1e-3
    relinearize_threshold: float = 1e-3
    relinearize_skip: int = 1
    plane_relinearize_factor: float = 10.0
    lm_max_iterations: int = 50
    lm_relative_tolerance: float = 1e-10
    robust_schedule: tuple[float, ...] = (30.0, 10.0, 3.0)
    imu: ImuConfig | None = None
    coalesce_blocks: bool = False

    def __post_init__(self) -> None:
        if self.datum not in ("pose", "position_yaw"):
            raise ValueError(f"datum: expected 'pose' or 'position_yaw', got {self.datum!r}")
        for name in ("datum_sigma", "horizontal_sigma", "relinearize_threshold",
                     "lm_relative_tolerance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"{name}: must be > 0, got {v}")
        if min(self.initial_velocity_sigmas) <= 0.0:
            raise ValueError(f"initial_velocity_sigmas: must be > 0, got {self.initial_velocity_sigmas}")
        if any(not (s >= 1.0) for s in self.robust_schedule):
            raise ValueError(f"robust_schedule: multipliers must be >= 1, got {self.robust_schedule}")
        if self.relinearize_skip < 1 or self.lm_max_iterations < 1:
            raise ValueError("relinearize_skip and lm_max_iterations: must be >= 1")


@dataclass(frozen=True)
class ObservationBlock:
    """Points of one plane seen during knot interval ``knot`` (body frame, or scanner frame when
    ``scanner`` is set), their interval fractions (None: single pose) and sigmas [m]."""

    knot: int
    plane_id: int
    points: FloatArray
    alphas: FloatArray | None
    sigmas: FloatArray
    scanner: int | None = None


@dataclass(frozen=True)
class OptimizeSummary:
    """Outcome of :meth:`Backend.batch_optimize`: errors (0.5 sum of squares incl. robust
    losses), iterations and wall time [s]."""

    initial_error: float
    final_error: float
    iterations: int
    seconds: float


@dataclass
class _Record:
    factor: gtsam.NonlinearFactor | None
    keys: tuple[int, ...]
    isam_index: int | None = None


class Backend:
    """Factor graph of knots, planes (and optionally extrinsics, velocities, biases); see module doc."""

    def __init__(self, config: BackendConfig | None = None) -> None:
        self.config = config or BackendConfig()
        self._times: list[float] = []
        self._values = gtsam.Values()
        self._records: dict[int, _Record] = {}
        self._next_id = 0
        self._blocks: dict[int, ObservationBlock] = {}
        self._plane_blocks: dict[int, set[int]] = {}
        self._plane_priors: dict[int, int] = {}
        self._scanners: set[int] = set()
        self._imu_intervals: set[int] = set()
        self._isam: gtsam.ISAM2 | None = None
        self._isam_keys: set[int] = set()
        self._pending: list[int] = []
        self._pending_removals: list[int] = []
        self._marginals: gtsam.Marginals | None = None
        self._isam_fresh = False  # iSAM2 holds every factor and its estimate is current
        self._links: list[tuple[int, int, int]] = []  # (keep, drop, factor id) plane equality ties
        self.singular_systems: list[str] = []  # singular linear systems the solves met (retried damped)
        # (host, plane, factor id, sigma, perpendicular?) orientation ties between planes
        self._parallels: list[tuple[int, int, int, float, bool]] = []
        self._anchors: dict[int, FloatArray] = {}  # plane id -> anchor point (world) of its variable
        # fixed-lag window (window_optimize): factors by the highest knot they touch, factors on no
        # knot (plane priors and ties), and the exact summaries of the blocks that left the window
        self._by_knot: dict[int, list[int]] = {}
        self._knotless: list[int] = []
        self._summary: dict[int, FloatArray] = {}  # plane id -> scatter M of its summarised blocks
        self._summarized: dict[int, FloatArray] = {}  # block id -> its scatter (its plane's anchor)
        self._summarized_upto = 0  # blocks whose highest knot is below this are summarised
        self._open_blocks: dict[tuple[int, int, int | None, bool], int] = {}  # coalesce_blocks
        self._groups: dict[int, tuple[tuple[int, ...], gtsam.NonlinearFactor]] = {}  # knot -> group

    # ----------------------------------------------------------------- variables
    def add_pose(self, time: float, T_world_body: ArrayLike,
                 velocity_world: ArrayLike | None = None) -> int:
        """Add the next knot at ``time`` [s] (strictly after the last) with an initial guess
        (4, 4); returns its index. With an IMU, ``velocity_world`` (3,) [m/s] is its velocity
        guess (default: from the previous knots, or zero)."""
        T = _as_pose(T_world_body, "T_world_body")
        t = float(time)
        if not np.isfinite(t) or (self._times and t <= self._times[-1]):
            last = self._times[-1] if self._times else None
            raise ValueError(f"time: knots must be finite and increasing (last {last}, got {t})")
        i = len(self._times)
        self._times.append(t)
        self._values.insert(X(i), T)
        cfg = self.config
        if i == 0:
            s = cfg.datum_sigma
            if cfg.datum == "pose":
                self._add_factor(datum_prior(X(0), T, s, s))
            else:
                sig = np.array([cfg.datum_tilt_sigma, cfg.datum_tilt_sigma, s, s, s, s])
                self._add_factor(gtsam.PriorFactorPose3(X(0), T, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        elif i == 1 and cfg.imu is None:  # with an IMU, its factor determines knot 1
            dt = t - self._times[0]
            self._add_factor(initial_velocity_factor(
                X(0), X(1), self._values.atPose3(X(0)).between(T), dt, *cfg.initial_velocity_sigmas))
        if i >= 2 and cfg.use_motion_prior:
            dt1, dt2 = self._times[i - 1] - self._times[i - 2], t - self._times[i - 1]
            self._add_factor(constant_velocity_factor(X(i - 2), X(i - 1), X(i), dt1, dt2, cfg.motion))
        if cfg.imu is not None:
            if velocity_world is None:
                v = np.zeros(3)
                if i >= 1:
                    v = (T.translation() - self._values.atPose3(X(i - 1)).translation()) / (
                        t - self._times[i - 1])
            else:
                v = np.asarray(velocity_world, dtype=float).reshape(3)
            self._values.insert(V(i), v)
            # a new bias starts at the last estimate: the preintegration is linearised there
            self._values.insert(B(i), self._values.atConstantBias(B(i - 1)) if i >= 1
                                else gtsam.imuBias.ConstantBias())
            if i == 0:
                self._add_factor(gtsam.PriorFactorVector(
                    V(0), v, gtsam.noiseModel.Isotropic.Sigma(3, cfg.imu.velocity_prior_sigma)))
                sa, sg = cfg.imu.bias_prior_sigmas
                self._add_factor(gtsam.PriorFactorConstantBias(
                    B(0), gtsam.imuBias.ConstantBias(),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([sa] * 3 + [sg] * 3))))
            else:
                self._add_factor(bias_random_walk_factor(B(i - 1), B(i), t - self._times[i - 1],
                                                         cfg.imu))
        return i

    def add_velocity_prior(self, knot: int, velocity_world: ArrayLike, sigma: float) -> None:
        """A prior (3,) [m/s] on a knot's velocity, e.g. zero while the operator stands still
        (IMU configurations only)."""
        if self.config.imu is None:
            raise ValueError("add_velocity_prior: the back end was configured without an IMU")
        i = self._check_knot(knot)
        v = np.asarray(velocity_world, dtype=float).reshape(3)
        self._add_factor(gtsam.PriorFactorVector(V(i), v, gtsam.noiseModel.Isotropic.Sigma(3, float(sigma))))

    def add_plane(self, plane_id: int, normal_world: ArrayLike, offset: float,
                  horizontal: bool = False, vertical: bool = False,
                  anchor: ArrayLike | None = None) -> None:
        """Add plane ``plane_id`` (int >= 0): ``normal_world . x + offset = 0`` (the normal is
        normalised). ``horizontal`` adds a prior keeping it a floor/ceiling, ``vertical`` one
        keeping it a wall (its normal horizontal: ``n_z = 0``).

        ``anchor`` (3,), a world point near the plane's observed patch: the variable is the plane
        expressed about it (``n . (x - anchor) + d_local = 0``). A plane seen far from the world
        origin is otherwise badly conditioned (turning the normal about the origin and shifting
        the offset nearly cancel at the patch: condition numbers of 1e7-1e9 at 20 m). Estimates
        and inputs stay in the world frame; :meth:`plane_covariance` is about the anchor."""
        j = _plane_id(plane_id)
        if self._values.exists(P(j)):
            raise ValueError(f"plane_id: plane {j} already exists")
        n = np.asarray(normal_world, dtype=float).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise ValueError(f"normal_world: expected a finite non-zero 3-vector, got {n}")
        if not np.isfinite(offset):
            raise ValueError(f"offset: must be finite, got {offset}")
        a = np.zeros(3) if anchor is None else np.asarray(anchor, dtype=float).reshape(3)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"anchor: must be finite, got {a}")
        self._anchors[j] = a
        n_unit = n / np.linalg.norm(n)
        self._values.insert(P(j), gtsam.OrientedPlane3(gtsam.Unit3(n), float(offset) + float(n_unit @ a)))
        self._plane_blocks[j] = set()
        if horizontal:
            self._plane_priors[j] = self._add_factor(
                horizontal_plane_prior(P(j), n, self.config.horizontal_sigma))
        elif vertical:
            self._plane_priors[j] = self._vertical_prior(j)

    def _vertical_prior(self, j: int) -> int:
        """Add the prior keeping plane ``j`` a wall (``n_z = 0``); returns its factor id."""
        noise = gtsam.noiseModel.Isotropic.Sigma(1, self.config.vertical_sigma)
        return self._add_factor(gtsam.CustomFactor(noise, [P(j)], _vertical_error))

    def add_extrinsic(self, scanner: int, T_body_scanner: ArrayLike, sigma_rot: float,
                      sigma_trans: float) -> None:
        """Make scanner ``scanner``'s extrinsic a variable ``E(scanner)`` with a prior around
        ``T_body_scanner`` (4, 4) [rad, m]; blocks added with ``scanner=`` then depend on it."""
        s = int(scanner)
        if s in self._scanners:
            raise ValueError(f"scanner: extrinsic {s} already exists")
        T = _as_pose(T_body_scanner, "T_body_scanner")
        self._scanners.add(s)
        self._values.insert(E(s), T)
        sig = np.array([sigma_rot] * 3 + [sigma_trans] * 3, dtype=float)
        self._add_factor(gtsam.PriorFactorPose3(E(s), T, gtsam.noiseModel.Diagonal.Sigmas(sig)))

    def add_imu(self, knot: int, accel_imu: ArrayLike, gyro_imu: ArrayLike, dt: ArrayLike) -> None:
        """IMU samples of interval [knot, knot+1] (IMU frame; see :func:`slam.motion.preintegrate`)
        as one ImuFactor. Needs ``BackendConfig.imu``."""
        if self.config.imu is None:
            raise ValueError("add_imu: the back end was configured without an IMU (config.imu)")
        i = self._check_knot(knot, need_next=True)
        if i in self._imu_intervals:
            raise ValueError(f"knot: interval {i} already has IMU data")
        bias = self._values.atConstantBias(B(i))
        pim = preintegrate(self.config.imu.params(), bias, accel_imu, gyro_imu, dt)
        self._imu_intervals.add(i)
        self._add_factor(gtsam.ImuFactor(X(i), V(i), X(i + 1), V(i + 1), B(i), pim))

    # ----------------------------------------------------------------- observations
    def add_observations(self, knot: int, plane_id: int, points: ArrayLike,
                         alphas: ArrayLike | None, sigmas: ArrayLike,
                         scanner: int | None = None) -> int:
        """Add a block: points (N, 3) [m] seen on plane ``plane_id`` during interval
        [knot, knot+1] at fractions ``alphas`` (N,) (None or all 0: at the knot itself), with
        point-to-plane sigmas (N,) or scalar [m]. Body frame at each beam time, or the scanner
        frame when ``scanner`` is given. Returns the block id."""
        block = self._make_block(knot, plane_id, points, alphas, sigmas, scanner)
        key = (block.knot, block.plane_id, block.scanner, block.alphas is not None)
        if self.config.coalesce_blocks and key in self._open_blocks:
            old = self._blocks[self._open_blocks[key]]
            block = ObservationBlock(
                block.knot, block.plane_id, np.concatenate((old.points, block.points)),
                None if block.alphas is None or old.alphas is None else np.concatenate((old.alphas, block.alphas)),
                np.concatenate((old.sigmas, block.sigmas)), block.scanner)
            self.remove_observations(self._open_blocks[key])
        bid = self._add_record(None, _block_keys(block))
        self._add_block(bid, block)
        if self.config.coalesce_blocks and bid not in self._summarized:
            self._open_blocks[key] = bid
        return bid

    def _add_block(self, bid: int, block: ObservationBlock) -> None:
        self._blocks[bid] = block
        self._plane_blocks[block.plane_id].add(bid)
        top = block.knot + (1 if block.alphas is not None else 0)  # the highest knot it touches
        if top < self._summarized_upto:  # its poses are held by the window already
            self._summarize_block(bid)

    def replace_observations(self, block_id: int, points: ArrayLike, alphas: ArrayLike | None,
                             sigmas: ArrayLike) -> int:
        """Replace a block's points (same knot, plane and scanner); returns the new block id."""
        old = self._get_block(block_id)
        new = self._make_block(old.knot, old.plane_id, points, alphas, sigmas, old.scanner)
        self.remove_observations(block_id)
        bid = self._add_record(None, _block_keys(new))
        self._add_block(bid, new)
        return bid

    def remove_observations(self, block_id: int) -> None:
        """Remove an observation block."""
        blk = self._get_block(block_id)
        self._remove_factor(block_id)
        del self._blocks[block_id]
        self._plane_blocks[blk.plane_id].discard(block_id)
        key = (blk.knot, blk.plane_id, blk.scanner, blk.alphas is not None)
        if self._open_blocks.get(key) == block_id:
            del self._open_blocks[key]
        C = self._summarized.pop(block_id, None)
        if C is not None:
            self._summary[blk.plane_id] -= C

    def blocks_of_plane(self, plane_id: int) -> list[int]:
        """Ids of the observation blocks on a plane."""
        return sorted(self._plane_blocks[self._check_plane(plane_id)])

    def block(self, block_id: int) -> ObservationBlock:
        """The data of an observation block."""
        return self._get_block(block_id)

    def block_residuals(self, block_id: int) -> tuple[FloatArray, FloatArray]:
        """Whitened signed point-to-plane residuals (N,) at the current estimate and the robust
        (IRLS) weights (N,) in [0, 1] the kernel gives them (small = treated as outlier)."""
        e = self._whitened_residuals(self._get_block(block_id))
        return e, robust_weights(e, self.config.kernel)

    def _whitened_residuals(self, blk: ObservationBlock) -> FloatArray:
        """A block's signed point-to-plane residuals over their sigmas at the current estimate."""
        v = self._values
        pts = blk.points
        if blk.scanner is not None:
            Es = v.atPose3(E(blk.scanner)).matrix()
            pts = pts @ Es[:3, :3].T + Es[:3, 3]
        a = self._anchors.get(blk.plane_id)
        T_b = v.atPose3(X(blk.knot + 1)) if blk.alphas is not None else None
        terms = point_plane_terms(v.atPose3(X(blk.knot)), T_b, v.atOrientedPlane3(P(blk.plane_id)), pts,
                                  blk.alphas, jacobians=False, anchor=a)
        return np.asarray(terms.residuals / blk.sigmas)

    def trim_observations(self, max_whitened: float, min_distance: float) -> tuple[int, int]:
        """Detach the points that do not fit their plane at the current estimate: those whose
        point-to-plane residual exceeds both ``max_whitened`` sigmas and ``min_distance`` [m]
        (a wall's segment on the plane of its door or board, 1-2 cm off, or the other way
        round). Blocks keep their other points; a block left empty is removed. Returns (points
        detached, blocks changed)."""
        if not (max_whitened > 0.0 and min_distance >= 0.0):
            raise ValueError(f"trim thresholds: expected > 0 and >= 0, got {max_whitened}, {min_distance}")
        n_points = n_blocks = 0
        for bid in list(self._blocks):
            blk = self._blocks[bid]
            e = self._whitened_residuals(blk)
            out = (np.abs(e) > max_whitened) & (np.abs(e) * blk.sigmas > min_distance)
            if not out.any():
                continue
            n_points += int(out.sum())
            n_blocks += 1
            keep = ~out
            if not keep.any():
                self.remove_observations(bid)
            else:
                self.replace_observations(bid, blk.points[keep], None if blk.alphas is None else blk.alphas[keep],
                                          blk.sigmas[keep])
        return n_points, n_blocks

    # ----------------------------------------------------------------- planes
    def merge_planes(self, keep_id: int, drop_id: int) -> int:
        """Merge plane ``drop_id`` into ``keep_id``: its blocks are re-keyed onto ``keep_id`` (same
        block ids), its horizontality or verticality prior moves over if ``keep_id`` has none, and the variable
        is removed. ``keep_id`` keeps its current estimate. Returns the number of moved blocks."""
        keep, drop = self._check_plane(keep_id), self._check_plane(drop_id)
        if keep == drop:
            raise ValueError(f"merge_planes: cannot merge plane {keep} with itself")
        moved = sorted(self._plane_blocks[drop])
        for bid in moved:
            old = self._blocks[bid]
            self._open_blocks.pop((old.knot, drop, old.scanner, old.alphas is not None), None)
            new = ObservationBlock(old.knot, keep, old.points, old.alphas, old.sigmas, old.scanner)
            self._groups.pop(old.knot, None)
            self._records[bid] = _Record(None, _block_keys(new))
            self._blocks[bid] = new
            self._plane_blocks[keep].add(bid)
            C = self._summarized.get(bid)
            if C is not None:
                C = shift_anchor(C, self._anchors[drop], self._anchors[keep])
                self._summarized[bid] = C
                self._summary[keep] = self._summary.get(keep, np.zeros((4, 4))) + C
        self._summary.pop(drop, None)
        if drop in self._plane_priors:
            fid = self._plane_priors.pop(drop)
            del self._records[fid]
            if keep not in self._plane_priors:
                n = self._values.atOrientedPlane3(P(keep)).normal().point3()
                if abs(n[2]) >= 0.5:
                    self._plane_priors[keep] = self._add_factor(
                        horizontal_plane_prior(P(keep), n, self.config.horizontal_sigma))
                else:
                    self._plane_priors[keep] = self._vertical_prior(keep)
        del self._plane_blocks[drop]
        self._rekey_parallels(drop, keep)
        self._values.erase(P(drop))
        self._invalidate_isam()
        return len(moved)

    def link_planes(self, keep_id: int, drop_id: int, sigma_angle: float = 1e-5,
                    sigma_offset: float = 1e-5) -> int:
        """Tie plane ``drop_id`` to ``keep_id`` with a tight equality factor: the incremental way to
        merge (iSAM2 is not rebuilt); :meth:`merge_planes` can fold them for good later. Returns
        the factor id. The residual is ``(B_keep^T n_drop, d_drop - d_keep)`` with the normals
        oriented alike, ``B_keep`` the tangent basis of ``keep``'s normal."""
        keep, drop = self._check_plane(keep_id), self._check_plane(drop_id)
        if keep == drop:
            raise ValueError(f"link_planes: cannot link plane {keep} with itself")
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_angle, sigma_angle, sigma_offset]))
        error = _plane_equality(self._anchors[keep], self._anchors[drop])
        fid = self._add_factor(gtsam.CustomFactor(noise, [P(keep), P(drop)], error))
        self._links.append((keep, drop, fid))
        return fid

    def add_parallel(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        """Keep plane ``plane_id`` parallel to ``host_id`` (same facing), offsets free: a door set
        into its wall, a board on it. Survives merges (re-keyed onto the surviving plane).
        Returns the factor id."""
        return self._add_tie(host_id, plane_id, sigma_angle, perpendicular=False)

    def add_perpendicular(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        """Keep plane ``plane_id`` perpendicular to ``host_id`` (one residual: the dot product of
        the unit normals, sigma ``sigma_angle`` [rad]): the plane through a door's edge across its
        wall. Survives merges like :meth:`add_parallel`. Returns the factor id."""
        return self._add_tie(host_id, plane_id, sigma_angle, perpendicular=True)

    def _add_tie(self, host_id: int, plane_id: int, sigma_angle: float, perpendicular: bool) -> int:
        a, b = self._check_plane(host_id), self._check_plane(plane_id)
        if a == b:
            raise ValueError(f"add_{'perpendicular' if perpendicular else 'parallel'}: cannot tie plane {a} to itself")
        fid = self._tie_factor(a, b, sigma_angle, perpendicular)
        self._parallels.append((a, b, fid, float(sigma_angle), perpendicular))
        return fid

    def _tie_factor(self, a: int, b: int, sigma_angle: float, perpendicular: bool) -> int:
        if perpendicular:
            one = gtsam.noiseModel.Isotropic.Sigma(1, sigma_angle)
            return self._add_factor(gtsam.CustomFactor(one, [P(a), P(b)], _perpendicular_error))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_angle, sigma_angle, 1e3]))
        error = _plane_equality(self._anchors[a], self._anchors[b])
        return self._add_factor(gtsam.CustomFactor(noise, [P(a), P(b)], error))

    def _rekey_parallels(self, drop: int, keep: int | None) -> None:
        """Move the orientation ties of plane ``drop`` onto ``keep`` (None: remove them)."""
        out = []
        for a, b, fid, sigma, perp in self._parallels:
            if drop not in (a, b):
                out.append((a, b, fid, sigma, perp))
                continue
            if fid in self._records:
                self._remove_factor(fid)
            if keep is None:
                continue
            na, nb = (keep if a == drop else a), (keep if b == drop else b)
            if na != nb:
                out.append((na, nb, self._tie_factor(na, nb, sigma, perp), sigma, perp))
        self._parallels = out

    def fold_links(self) -> dict[int, int]:
        """Turn every :meth:`link_planes` tie into a real merge (blocks re-keyed onto the surviving
        plane, linked variables removed). Returns dropped id -> surviving id. iSAM2 is rebuilt at
        the next :meth:`update`; meant for the end of a run, before the batch."""
        parent: dict[int, int] = {}

        def root(j: int) -> int:
            while parent.get(j, j) != j:
                j = parent[j]
            return j

        for keep, drop, fid in self._links:
            self._records.pop(fid, None)
            rk, rd = root(keep), root(drop)
            if rk != rd:
                parent[rd] = rk
        self._links = []
        out = {j: root(j) for j in parent}
        for drop, keep in out.items():
            if drop != keep:
                self.merge_planes(keep, drop)
        self._invalidate_isam()
        return out

    def remove_plane(self, plane_id: int) -> None:
        """Remove a plane with all its observation blocks and priors."""
        j = self._check_plane(plane_id)
        for bid in sorted(self._plane_blocks[j]):
            self.remove_observations(bid)
        if j in self._plane_priors:
            self._remove_factor(self._plane_priors.pop(j))
        self._rekey_parallels(j, None)
        del self._plane_blocks[j]
        self._summary.pop(j, None)
        self._values.erase(P(j))
        self._invalidate_isam()

    # ----------------------------------------------------------------- solving
    def update(self, iterations: int = 1) -> None:
        """Incremental iSAM2 step(s) with everything added or removed since the last call."""
        if self._isam is None:
            self._rebuild_isam()
        assert self._isam is not None
        graph = gtsam.NonlinearFactorGraph()
        new_values = gtsam.Values()
        ids: list[int] = []
        for fid in self._pending:
            rec = self._records.get(fid)
            if rec is None:
                continue
            graph.add(self._factor(fid))
            ids.append(fid)
            for k in rec.keys:
                if k not in self._isam_keys and not new_values.exists(k):
                    _copy_value(new_values, self._values, k)
        removals = list(self._pending_removals)
        try:
            result = self._isam.update(graph, new_values, removals)
            for _ in range(max(iterations, 1) - 1):
                self._isam.update()
        except RuntimeError as err:
            self._invalidate_isam()  # its state is undefined after a failed update
            raise ValueError(f"iSAM2 update failed ({_name_keys(str(err))}); is every new "
                             "variable constrained by its factors?") from None
        for fid, idx in zip(ids, result.getNewFactorsIndices(), strict=True):
            self._records[fid].isam_index = int(idx)
        self._isam_keys.update(int(k) for k in new_values.keys())
        self._pending, self._pending_removals = [], []
        self._values.update(self._isam.calculateEstimate())
        self._marginals = None
        self._isam_fresh = True

    def batch_optimize(self, max_iterations: int | None = None,
                       graduated: bool = True, kernel: RobustKernel | None = None) -> OptimizeSummary:
        """A batch solve (:meth:`_solve_batch`) over every factor from the current estimate; with ``graduated``
        (and a robust kernel) first with the kernel threshold scaled by each
        ``config.robust_schedule`` multiplier, then nominal. ``kernel``: the observation blocks'
        kernel for this solve (None: ``config.kernel``). iSAM2 is rebuilt from the result at
        the next :meth:`update`."""
        own = kernel is None or kernel == self.config.kernel
        kernel = self.config.kernel if kernel is None else kernel
        graph = self._graph() if own else self._graph(kernel=kernel)
        values = self._used_values(graph)
        e0 = graph.error(values)
        robust = graduated and kernel.name != "none" and bool(self._blocks)
        scales = list(self.config.robust_schedule) if robust else []
        t0 = _time.perf_counter()
        iterations = 0
        for scale in [*scales, 1.0]:
            g = graph
            if scale != 1.0:
                k = RobustKernel(kernel.name, kernel.threshold * scale)
                g = self._graph(kernel=k)
            values, it = self._solve_batch(g, values, max_iterations)
            iterations += it
        self._values.update(values)
        self._invalidate_isam()
        self._drop_summaries()  # the held poses have moved
        return OptimizeSummary(float(e0), float(graph.error(values)), iterations,
                               _time.perf_counter() - t0)

    def _drop_summaries(self) -> None:
        self._summary, self._summarized, self._summarized_upto = {}, {}, 0

    def _summarize_block(self, bid: int) -> None:
        """Fold block ``bid`` into its plane's scatter at the current poses (held from now on) and
        robust weights (frozen): see :mod:`slam.backend.plane_summary`."""
        blk = self._blocks[bid]
        v = self._values
        pts = blk.points
        if blk.scanner is not None:
            Es = v.atPose3(E(blk.scanner)).matrix()
            pts = pts @ Es[:3, :3].T + Es[:3, 3]
        Ta = v.atPose3(X(blk.knot)).matrix()
        if blk.alphas is None:
            x = pts @ Ta[:3, :3].T + Ta[:3, 3]
        else:
            T = np.stack((Ta, v.atPose3(X(blk.knot + 1)).matrix()))
            R, t = interval_poses(T, np.zeros(pts.shape[0], dtype=np.int64), blk.alphas)
            x = np.einsum("mij,mj->mi", R, pts) + t
        j = blk.plane_id
        a = self._anchors[j]
        pl = v.atOrientedPlane3(P(j))
        e = ((x - a) @ pl.normal().point3() + pl.distance()) / blk.sigmas
        C = scatter(x, a, robust_weights(e, self.config.kernel) / blk.sigmas**2)
        self._summarized[bid] = C
        self._summary[j] = self._summary.get(j, np.zeros((4, 4))) + C
        key = (blk.knot, j, blk.scanner, blk.alphas is not None)
        if self._open_blocks.get(key) == bid:
            del self._open_blocks[key]

    def window_optimize(self, first_knot: int, max_iterations: int = 4) -> OptimizeSummary:
        """A fixed-lag step: solve (:meth:`_solve_batch`) for the knots from ``first_knot`` on
        (poses, velocities, biases) and every plane they observe, with every factor touching
        those knots and the planes' priors and ties; older variables those factors reach are held
        at their estimates. The observation blocks of older knots enter as one exact summary per
        plane (:mod:`slam.backend.plane_summary`, taken when a block leaves the window: its poses are held
        from then on), so a solve costs what the window holds, not what the walk has seen. The
        window never reopens summarised knots (``first_knot`` is raised to them). The full
        problem is left to a final :meth:`batch_optimize` (loop closures reach the old knots
        there), which drops the summaries."""
        t0 = _time.perf_counter()
        n = len(self._times)
        first = max(0, min(int(first_knot), n - 1))
        for k in range(self._summarized_upto, first):
            for fid in self._by_knot.get(k, ()):
                if fid in self._blocks and fid not in self._summarized:
                    self._summarize_block(fid)
        self._summarized_upto = max(self._summarized_upto, first)
        first = min(self._summarized_upto, n - 1)
        active: set[int] = set()
        for k in range(first, n):
            for sym in (X, V, B):
                key = int(sym(k))
                if self._values.exists(key):
                    active.add(key)
        graph = gtsam.NonlinearFactorGraph()
        used: set[int] = set()
        planes: set[int] = set()
        groups: dict[int, list[int]] = {}
        for k in range(first, n):
            for fid in self._by_knot.get(k, ()):
                rec = self._records.get(fid)
                if rec is None:
                    continue
                used.update(rec.keys)
                blk = self._blocks.get(fid)
                if blk is not None:
                    planes.add(blk.plane_id)
                    if _groupable(blk):
                        groups.setdefault(blk.knot, []).append(fid)
                        continue
                graph.add(self._factor(fid))
        for knot, bids in groups.items():
            graph.add(self._group_factor(knot, bids))
        active.update(int(P(j)) for j in planes)
        for fid in self._knotless:
            rec = self._records.get(fid)
            if rec is not None and any(k in active for k in rec.keys):
                graph.add(self._factor(fid))
                used.update(rec.keys)
        for j in sorted(planes):
            M = self._summary.get(j)
            if M is not None:
                graph.add(plane_summary_factor(int(P(j)), M))
        self._knotless = [fid for fid in self._knotless if fid in self._records]
        values = gtsam.Values()
        for k in used:
            _copy_value(values, self._values, k)
        fixed = sorted(used - active)
        sol = self._solve(graph, values, max_iterations, fixed=fixed)
        for k in active & used:
            _copy_value(self._values, sol.values, k, update=True)
        self._pending, self._pending_removals = [], []
        self._invalidate_isam()
        return OptimizeSummary(float(sol.initial_error), float(sol.final_error), sol.iterations,
                               _time.perf_counter() - t0)

    def _solve_batch(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                     max_iterations: int | None,
                     fixed: Sequence[int] = ()) -> tuple[gtsam.Values, int]:
        """:meth:`_solve`'s values and iterations."""
        sol = self._solve(graph, values, max_iterations, fixed)
        return sol.values, sol.iterations

    def _solve(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               max_iterations: int | None, fixed: Sequence[int] = ()) -> Solution:
        """:func:`slam.backend.solver.solve` with the configured iterations and tolerance; a failure of
        its Levenberg-Marquardt fallback is a ValueError naming the variable."""
        n_max = max_iterations or self.config.lm_max_iterations
        try:
            sol = solve(graph, values, n_max, self.config.lm_relative_tolerance, fixed)
            self.singular_systems.extend(_name_keys(m) for m in sol.singular)
            return sol
        except RuntimeError as err2:
            raise ValueError(f"batch optimisation failed ({_name_keys(str(err2))}); is every "
                             "variable constrained by its factors?") from None

    def error(self) -> float:
        """Total graph error (0.5 sum of whitened squares, robust losses) at the current estimate."""
        graph = self._graph()
        return float(graph.error(self._used_values(graph)))

    # ----------------------------------------------------------------- estimates
    @property
    def num_knots(self) -> int:
        return len(self._times)

    def knot_times(self) -> FloatArray:
        """Knot times (K,) [s]."""
        return np.asarray(self._times, dtype=float)

    def poses(self) -> FloatArray:
        """Current ``T_world_body`` of every knot, (K, 4, 4)."""
        return np.array([self._values.atPose3(X(i)).matrix() for i in range(len(self._times))])

    def pose(self, knot: int) -> FloatArray:
        """Current ``T_world_body`` (4, 4) of one knot."""
        return np.asarray(self._values.atPose3(X(self._check_knot(knot))).matrix())

    def plane_ids(self) -> list[int]:
        return sorted(self._plane_blocks)

    def planes(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Plane ids (P,), unit normals (P, 3) and offsets (P,) in the world frame (n.x + d = 0)."""
        ids = self.plane_ids()
        world = [self.plane(j) for j in ids]
        normals = np.array([w[0] for w in world]).reshape(-1, 3)
        return (np.asarray(ids, dtype=np.int64), normals, np.array([w[1] for w in world], dtype=float))

    def plane(self, plane_id: int) -> tuple[FloatArray, float]:
        """Unit normal (3,) and offset of one plane (world frame)."""
        j = self._check_plane(plane_id)
        p = self._values.atOrientedPlane3(P(j))
        n = np.asarray(p.normal().point3())
        return n, float(p.distance()) - float(n @ self._anchors.get(j, np.zeros(3)))

    def extrinsic(self, scanner: int) -> FloatArray:
        """Current ``T_body_scanner`` (4, 4) of a scanner added with :meth:`add_extrinsic`."""
        if int(scanner) not in self._scanners:
            raise ValueError(f"scanner: no extrinsic variable for scanner {scanner}")
        return np.asarray(self._values.atPose3(E(int(scanner))).matrix())

    def velocities(self) -> FloatArray:
        """World-frame velocities (K, 3) [m/s] of the knots (IMU configurations only)."""
        if self.config.imu is None:
            raise ValueError("velocities: the back end was configured without an IMU")
        return np.array([self._values.atVector(V(i)) for i in range(len(self._times))])

    def velocity(self, knot: int) -> FloatArray:
        """World-frame velocity (3,) [m/s] of one knot (IMU configurations only)."""
        if self.config.imu is None:
            raise ValueError("velocity: the back end was configured without an IMU")
        return np.asarray(self._values.atVector(V(self._check_knot(knot))))

    def bias(self, knot: int) -> FloatArray:
        """IMU bias (6,) of one knot: accelerometer (m/s^2) then gyroscope (rad/s)."""
        if self.config.imu is None:
            raise ValueError("bias: the back end was configured without an IMU")
        return np.asarray(self._values.atConstantBias(B(self._check_knot(knot))).vector())

    def biases(self) -> FloatArray:
        """IMU biases (K, 6): accelerometer (m/s^2) then gyroscope (rad/s) per knot."""
        if self.config.imu is None:
            raise ValueError("biases: the back end was configured without an IMU")
        return np.array([self._values.atConstantBias(B(i)).vector() for i in range(len(self._times))])

    def knot_fractions(self, times: ArrayLike) -> tuple[NDArray[np.int64], FloatArray]:
        """Knot interval index and fraction alpha of each time (see :mod:`slam.trajectory.interpolation`)."""
        return knot_fractions(self._times, times)

    def T_world_body(self, times: ArrayLike) -> FloatArray:
        """Interpolated ``T_world_body`` (M, 4, 4) at times (M,) within the knots, exactly as the
        factors place points."""
        return interpolate_trajectory(self._times, self.poses(), np.atleast_1d(times))

    def predict_pose(self, time: float) -> FloatArray:
        """Constant-velocity extrapolation (4, 4) of the trajectory to ``time`` >= the last knot
        (initial guess of the next knot, deskewing of the newest scan)."""
        K = len(self._times)
        if K == 0:
            raise ValueError("predict_pose: no knots yet")
        T_last = self.pose(K - 1)
        if K == 1:
            return T_last
        T_prev = self.pose(K - 2)
        xi = se3_log(np.linalg.inv(T_prev) @ T_last)
        a = (float(time) - self._times[-1]) / (self._times[-1] - self._times[-2])
        return np.asarray(T_last @ se3_exp(a * xi))

    # ----------------------------------------------------------------- covariances
    def pose_covariance(self, knot: int) -> FloatArray:
        """Marginal covariance (6, 6) of a knot's pose in gtsam's tangent order (rotation [rad],
        then translation [m], both in the body frame)."""
        return self._covariance(X(self._check_knot(knot)))

    def plane_covariance(self, plane_id: int) -> FloatArray:
        """Marginal covariance (3, 3) of a plane in its retract coordinates: normal direction in
        the ``Unit3.basis()`` tangent (2, rad) and offset (m)."""
        return self._covariance(P(self._check_plane(plane_id)))

    def _covariance(self, key: int) -> FloatArray:
        if self._isam_fresh and not self._pending and not self._pending_removals:
            assert self._isam is not None
            return np.asarray(self._isam.marginalCovariance(key))
        if self._marginals is None:
            graph = self._graph()
            self._marginals = gtsam.Marginals(graph, self._used_values(graph))
        return np.asarray(self._marginals.marginalCovariance(key))

    # ----------------------------------------------------------------- statistics
    def residual_statistics(self) -> dict[str, float]:
        """Counts, RMS of whitened residuals and the share of down-weighted points (w < 0.5)."""
        es = [self.block_residuals(b)[0] for b in self._blocks]
        e = np.concatenate(es) if es else np.zeros(0)
        w = robust_weights(e, self.config.kernel)
        return {
            "blocks": float(len(self._blocks)),
            "points": float(e.size),
            "rms_whitened": float(np.sqrt(np.mean(e**2))) if e.size else 0.0,
            "outlier_fraction": float(np.mean(w < 0.5)) if e.size else 0.0,
        }

    # ----------------------------------------------------------------- internals
    def _add_factor(self, factor: gtsam.NonlinearFactor) -> int:
        return self._add_record(factor, tuple(int(k) for k in factor.keys()))

    def _add_record(self, factor: gtsam.NonlinearFactor | None, keys: tuple[int, ...]) -> int:
        """A new factor id for ``factor`` on ``keys`` (None: an observation block's, built when
        first needed by :meth:`_factor`: the window and the batch use its interval's group)."""
        fid = self._next_id
        self._next_id += 1
        self._records[fid] = _Record(factor, keys)
        top = _top_knot(keys)
        if top is None:
            self._knotless.append(fid)
        else:
            self._by_knot.setdefault(top, []).append(fid)
        self._pending.append(fid)
        self._marginals = None
        self._isam_fresh = False
        return fid

    def _remove_factor(self, fid: int) -> None:
        rec = self._records.pop(fid)
        if rec.isam_index is not None:
            self._pending_removals.append(rec.isam_index)
        self._marginals = None
        self._isam_fresh = False

    def _factor(self, fid: int) -> gtsam.NonlinearFactor:
        """The factor of record ``fid`` (an observation block's built on first use)."""
        rec = self._records[fid]
        if rec.factor is None:
            rec.factor = self._block_factor(self._blocks[fid])
        return rec.factor

    def _invalidate_isam(self) -> None:
        self._isam = None
        self._isam_keys = set()
        self._marginals = None
        self._isam_fresh = False

    def _rebuild_isam(self) -> None:
        params = gtsam.ISAM2Params()
        # planes (and IMU velocities/biases) are tied to thousands of factors: relinearising one
        # re-eliminates most of the tree, so they get a coarser threshold than the poses
        thr = self.config.relinearize_threshold
        tmap = gtsam.ISAM2ThresholdMap()
        for char, value in (("x", np.full(6, thr)), ("e", np.full(6, thr)),
                            ("p", np.full(3, thr * self.config.plane_relinearize_factor)),
                            ("v", np.full(3, 0.01)), ("b", np.full(6, 1e-3))):
            tmap.insert((char, value))
        params.setRelinearizeThreshold(tmap)
        params.relinearizeSkip = self.config.relinearize_skip
        self._isam = gtsam.ISAM2(params)
        self._isam_keys = set()
        for rec in self._records.values():
            rec.isam_index = None
        self._pending = sorted(self._records)
        self._pending_removals = []

    def _graph(self, kernel: RobustKernel | None = None) -> gtsam.NonlinearFactorGraph:
        """All live factors, the observation blocks between two knots grouped per interval
        (:meth:`_group_factor`); observation blocks rebuilt with ``kernel`` if given."""
        graph = gtsam.NonlinearFactorGraph()
        groups: dict[int, list[int]] = {}
        for fid in sorted(self._records):
            blk = self._blocks.get(fid)
            if blk is not None and _groupable(blk):
                groups.setdefault(blk.knot, []).append(fid)
            elif kernel is not None and blk is not None:
                graph.add(self._block_factor(blk, kernel))
            else:
                graph.add(self._factor(fid))
        for knot, bids in groups.items():
            graph.add(self._group_factor(knot, bids, kernel))
        return graph

    def _group_factor(self, knot: int, bids: list[int],
                      kernel: RobustKernel | None = None) -> gtsam.NonlinearFactor:
        """One factor for the blocks ``bids`` of interval ``knot`` (:func:`point_planes_factor`:
        one Python call per linearisation instead of one per block; the same rows). The factor
        of the configured kernel is kept until the interval's blocks change."""
        key = tuple(sorted(bids))
        if kernel is None:
            hit = self._groups.get(knot)
            if hit is not None and hit[0] == key:
                return hit[1]
        blks = [self._blocks[b] for b in key]
        if len(blks) == 1 and kernel is None:
            factor = self._factor(key[0])
        else:
            plane_ids = sorted({b.plane_id for b in blks})
            slot = {j: i for i, j in enumerate(plane_ids)}
            alphas = [b.alphas for b in blks]
            assert all(a is not None for a in alphas)
            factor = point_planes_factor(
                X(knot), X(knot + 1), [P(j) for j in plane_ids],
                np.concatenate([np.full(b.points.shape[0], slot[b.plane_id]) for b in blks]),
                np.concatenate([b.points for b in blks]), np.concatenate(alphas),  # type: ignore[arg-type]
                np.concatenate([b.sigmas for b in blks]), kernel or self.config.kernel,
                np.array([self._anchors[j] for j in plane_ids]))
        if kernel is None:
            self._groups[knot] = (key, factor)
        return factor

    def _used_values(self, graph: gtsam.NonlinearFactorGraph) -> gtsam.Values:
        out = gtsam.Values()
        for k in graph.keyVector():
            _copy_value(out, self._values, int(k))
        return out

    def _block_factor(self, blk: ObservationBlock,
                      kernel: RobustKernel | None = None) -> gtsam.NonlinearFactor:
        kernel = kernel or self.config.kernel
        kb = X(blk.knot + 1) if blk.alphas is not None else None
        a = self._anchors.get(blk.plane_id)
        if blk.scanner is None:
            return point_plane_factor(X(blk.knot), kb, P(blk.plane_id), blk.points, blk.alphas,
                                      blk.sigmas, kernel, anchor=a)
        return scanner_point_plane_factor(X(blk.knot), kb, P(blk.plane_id), E(blk.scanner),
                                          blk.points, blk.alphas, blk.sigmas, kernel, anchor=a)

    def _make_block(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
                    sigmas: ArrayLike, scanner: int | None) -> ObservationBlock:
        j = self._check_plane(plane_id)
        al = None if alphas is None else np.asarray(alphas, dtype=float).reshape(-1)
        if al is not None and not np.any(al != 0.0):
            al = None
        i = self._check_knot(knot, need_next=al is not None)
        if scanner is not None and int(scanner) not in self._scanners:
            raise ValueError(f"scanner: no extrinsic variable for scanner {scanner} (add_extrinsic)")
        pts = np.ascontiguousarray(points, dtype=float)
        s = np.asarray(sigmas, dtype=float)
        if pts.ndim == 2 and s.ndim == 0:
            s = np.full(pts.shape[0], float(s))
        pts, al, s = check_block(pts, al, s, al is not None, "points_body" if scanner is None else "points_scanner")
        return ObservationBlock(i, j, pts, al, s, None if scanner is None else int(scanner))

    def _get_block(self, block_id: int) -> ObservationBlock:
        if block_id not in self._blocks:
            raise ValueError(f"block_id: no observation block {block_id}")
        return self._blocks[block_id]

    def _check_knot(self, knot: int, need_next: bool = False) -> int:
        i = int(knot)
        last = len(self._times) - (2 if need_next else 1)
        if i < 0 or i > last:
            what = "interval start" if need_next else "knot"
            raise ValueError(f"knot: {what} {i} outside [0, {last}]")
        return i

    def _check_plane(self, plane_id: int) -> int:
        j = int(plane_id)
        if j not in self._plane_blocks:
            raise ValueError(f"plane_id: no plane {j}")
        return j


def _block_keys(blk: ObservationBlock) -> tuple[int, ...]:
    """The keys of a block's factor (:meth:`Backend._block_factor`)."""
    keys = [X(blk.knot)] + ([X(blk.knot + 1)] if blk.alphas is not None else []) + [P(blk.plane_id)]
    return tuple(int(k) for k in keys + ([E(blk.scanner)] if blk.scanner is not None else []))


def _groupable(blk: ObservationBlock) -> bool:
    """Whether a block joins its interval's group factor: between two knots, no extrinsic."""
    return blk.alphas is not None and blk.scanner is None


def _plane_id(plane_id: int) -> int:
    j = int(plane_id)
    if j < 0 or j >= 2**56:
        raise ValueError(f"plane_id: must be an integer in [0, 2^56), got {plane_id}")
    return j


def _vertical_error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
    """Wall prior: the z component of the plane's unit normal (world frame) is zero."""
    u = v.atOrientedPlane3(this.keys()[0]).normal()
    if H is not None:
        B = u.basis()
        H[0] = np.array([[B[2, 0], B[2, 1], 0.0]])
    return np.array([u.point3()[2]])


def _perpendicular_error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
    """Perpendicularity of two planes: the dot product of their unit normals (world frame)."""
    ua = v.atOrientedPlane3(this.keys()[0]).normal()
    ub = v.atOrientedPlane3(this.keys()[1]).normal()
    na, nb = ua.point3(), ub.point3()
    if H is not None:
        H[0] = np.array([[*(nb @ ua.basis()), 0.0]])
        H[1] = np.array([[*(na @ ub.basis()), 0.0]])
    return np.array([float(na @ nb)])


def _plane_residual(a: gtsam.OrientedPlane3, b: gtsam.OrientedPlane3, anchor_a: FloatArray,
                    anchor_b: FloatArray, H: Any = None) -> FloatArray:
    """Difference of plane b from plane a (normal in a's tangent, offset at a's anchor) and, into
    ``H`` (a list of two), its analytic Jacobians wrt both planes' retract coordinates:
    ``r = (s B_a^T n_b, s (d_b + n_b . (anchor_a - anchor_b)) - d_a)`` with ``s = -1`` for the same
    plane with the opposite orientation (``n_a . n_b < 0``), else 1."""
    ua, ub = a.normal(), b.normal()
    nb = ub.point3()
    s = -1.0 if float(ua.point3() @ nb) < 0.0 else 1.0
    delta = anchor_a - anchor_b
    r = np.empty(3)
    if H is None:
        r[:2] = s * ua.errorVector(ub)
    else:
        Hp, Hq = np.zeros((2, 2), order="F"), np.zeros((2, 2), order="F")
        r[:2] = s * ua.errorVector(ub, Hp, Hq)  # B_a^T n_b and its Jacobians
        Ha, Hb = np.zeros((3, 3)), np.zeros((3, 3))
        Ha[:2, :2], Ha[2, 2] = s * Hp, -1.0
        Hb[:2, :2], Hb[2, :2], Hb[2, 2] = s * Hq, s * (delta @ ub.basis()), s
        H[0], H[1] = Ha, Hb
    r[2] = s * (b.distance() + float(nb @ delta)) - a.distance()
    return r


def _plane_equality(anchor_a: FloatArray, anchor_b: FloatArray) -> Any:
    """Error function of the equality of two (anchored) planes, 3 residuals (:func:`_plane_residual`)."""

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        keys = this.keys()
        return _plane_residual(v.atOrientedPlane3(keys[0]), v.atOrientedPlane3(keys[1]), anchor_a, anchor_b, H)

    return error


def _as_pose(T: ArrayLike, name: str) -> gtsam.Pose3:
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ValueError(f"{name}: expected a finite (4, 4) matrix, got shape {M.shape}")
    R = M[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name}: rotation block is not a rotation matrix")
    return gtsam.Pose3(gtsam.Rot3(R), M[:3, 3])


def _top_knot(keys: Sequence[int]) -> int | None:
    """The highest knot index among ``keys`` (X, V and B symbols), or None."""
    top = None
    for k in keys:
        sym = gtsam.Symbol(k)
        if chr(sym.chr()) in "xvb":
            i = int(sym.index())
            top = i if top is None else max(top, i)
    return top


def _copy_value(dst: gtsam.Values, src: gtsam.Values, key: int, update: bool = False) -> None:
    """Copy variable ``key`` from ``src`` into ``dst``: insert it if absent; overwrite it only
    with ``update``."""
    exists = dst.exists(key)
    if exists and not update:
        return
    put = dst.update if exists else dst.insert
    sym = gtsam.Symbol(key)
    c = chr(sym.chr()).lower()
    if c in "xe":
        put(key, src.atPose3(key))
    elif c == "p":
        put(key, src.atOrientedPlane3(key))
    elif c == "v":
        put(key, src.atVector(key))
    elif c == "b":
        put(key, src.atConstantBias(key))
    else:
        raise ValueError(f"unknown variable {sym.string()}")


def _name_keys(message: str) -> str:
    """First line of a gtsam error plus the variable it names (x12, p3), on one line."""
    import re

    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    first = lines[0] if lines else "gtsam error"
    m = re.search(r"Symbol: (\w+)", message)
    return f"{first} {m.group(1)}" if m else first
