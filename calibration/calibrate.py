"""Calibrate a rig from a recording: SLAM, batch extrinsic estimation, repeat until converged.

1. Run SLAM (:class:`slam.pipeline.SlamRunner` through its public API, without its final batch:
   the calibration batch replaces it) on the bag with the current rig: trajectory, planes,
   segment-to-plane associations. Every scan is prepared once by the runner's preparer; a
   :class:`calibration.observations.SegmentLog` keeps its segments' virtual points in the scanner
   frame as the runner takes the scan.
2. Every associated segment becomes two moment-matched virtual points in its scanner frame
   (:mod:`calibration.observations`), without reading the recording again.
3. One batch graph with the extrinsics (and optionally time offsets) as variables, priors around
   the *initial* rig (:mod:`calibration.estimator`).
4. Update the rig; repeat from 1 until the extrinsics move less than ``tol_rot`` / ``tol_trans``
   (the associations improve with the calibration) or ``max_rounds`` is reached.

Coarse to fine (``CalibrationOptions.initial_uncertainty``): with a rig several degrees and
centimetres off, the tight association gates of the SLAM front end reject the tilted scanners'
segments, the pool turns them into thousands of spurious planes and iSAM2 fails. A round therefore
runs SLAM with gates loosened to the rig's *current* uncertainty (:func:`loosened_slam_config`:
angle and lever-arm gates, pose gate, endpoint cap, coplanarity and merge tolerances), so that the
tilted scanners' segments associate with the planes the reference scanner sees instead of seeding
spurious planes (the robust kernel of the back end limits how far their wrong geometry pulls the
trajectory).
Round 1 starts from ``initial_uncertainty`` (rad, m); every round's uncertainty is the
extrinsic change the previous round made times ``shrink`` (never more than before); once it is
below the tight default gates the plain SLAM configuration is used. A loosened round's batch is
one convex (Huber) solve capped at ``coarse_iterations`` without the variance-factor rounds (it
only has to bring the rig closer), without the points whose plane lies within ~26 deg of their
scanner's scan plane (``coarse_grazing_cos``: wrong associations of the loosened SLAM, e.g. the
horizontal reference scanner's segments on spurious horizontal planes, which pulled the tilted
scanners' common z by ~0.3 m), on the first ``coarse_duration`` seconds of the recording if
set (the SLAM's cost grows faster than linearly with the recording's length); the last round
(the reported estimate and covariance) always runs on the whole recording with the plain
configuration and the full estimator.

The covariance written to the rig file and used for the observability warnings is the batch's
cluster-robust one (``covariance="cluster"``, 1 s clusters; ``"marginal"``: the marginal one):
on the 120 s pipeline runs it was the better calibrated of the two (docs/calibration.md).
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calibration.estimator import BatchResult, EstimatorConfig, ScannerEstimate, estimate_extrinsics
from calibration.observability import ParameterSigmas, parameter_sigmas, warn_unobservable
from calibration.observations import SegmentLog
from calibration.rig_io import updated_rig
from common.rig import Rig
from segmentation import Scanline
from slam.config import SlamConfig
from slam.motion import MotionPriorConfig
from slam.pipeline import SlamResult, SlamRunner
from slam.trajectory.interpolation import se3_log

FloatArray = NDArray[np.float64]
ScanSource = Callable[[Rig], Iterable[Scanline]]


@dataclass(frozen=True)
class CalibrationOptions:
    """Outer-loop settings; ``estimator`` holds the graph's priors."""

    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    max_rounds: int = 3
    tol_rot: float = float(np.radians(0.005))
    tol_trans: float = 0.0002
    unobservable_ratio: float = 0.5
    initial_uncertainty: tuple[float, float] | None = None
    shrink: float = 0.1
    coarse_iterations: int = 20
    coarse_duration: float | None = None
    coarse_grazing_cos: float | None = 0.9
    covariance: Literal["cluster", "marginal"] = "cluster"

    def __post_init__(self) -> None:
        if self.max_rounds < 1:
            raise ValueError(f"max_rounds: must be >= 1, got {self.max_rounds}")
        if self.coarse_iterations < 1:
            raise ValueError(f"coarse_iterations: must be >= 1, got {self.coarse_iterations}")
        if self.coarse_duration is not None and not (math.isfinite(self.coarse_duration)
                                                     and self.coarse_duration > 0):
            raise ValueError(f"coarse_duration: must be > 0 s, got {self.coarse_duration}")
        if self.covariance not in ("cluster", "marginal"):
            raise ValueError(f"covariance: expected 'cluster' or 'marginal', got {self.covariance!r}")
        if not 0.0 < self.shrink <= 1.0:
            raise ValueError(f"shrink: must be in (0, 1], got {self.shrink}")
        u = self.initial_uncertainty
        if u is not None and not (len(u) == 2 and all(math.isfinite(x) and x >= 0 for x in u)):
            raise ValueError(f"initial_uncertainty: must be (rotation rad, translation m) >= 0, got {u}")


@dataclass
class RoundInfo:
    """One outer round: SLAM counts and the extrinsic change it produced (rad, m)."""

    round: int
    planes: int
    segments_associated: int
    points: int
    change_rot: float
    change_trans: float
    batch_seconds: float
    gate_rot: float = 0.0
    gate_trans: float = 0.0
    slam_seconds: float = 0.0
    duration: float | None = None  # seconds of the recording used (None: all)


@dataclass
class Calibration:
    """Result: the calibrated rig, the last batch, per-scanner sigmas, warnings, the rounds."""

    rig: Rig
    initial_rig: Rig
    batch: BatchResult
    sigmas: list[ParameterSigmas]
    warnings: list[str]
    rounds: list[RoundInfo]
    converged: bool


def slam_config_for_calibration(cfg: SlamConfig) -> SlamConfig:
    """The SLAM configuration used inside calibration: no final batch and no outputs."""
    return cfg.model_copy(update={
        "backend": cfg.backend.model_copy(update={"final_batch": False}),
        "output": cfg.output.model_copy(update={"cloud": False, "rerun": False}),
    })


def motion_prior_of(cfg: SlamConfig) -> MotionPriorConfig:
    """The SLAM configuration's constant-velocity prior (as :class:`slam.pipeline.SlamRunner`)."""
    dt = 1.0 / cfg.trajectory.knot_rate
    be = cfg.backend
    return MotionPriorConfig(q_ang=be.motion_sigma_angacc**2 * dt, q_lin=be.motion_sigma_acc**2 * dt)


def loosened_slam_config(cfg: SlamConfig, rot: float, trans: float) -> SlamConfig:
    """``cfg`` with the front end's gates opened for a rig whose extrinsics may be off by ``rot``
    [rad] and ``trans`` [m] (1 sigma): never tighter than ``cfg``. The angle and lever-arm tests
    get ``rot``, the pose test ``trans``, the endpoint cap 3 ``trans`` more (a wrong extrinsic moves
    a segment's ends); coplanarity (plane creation) and merging tolerate what a wrong extrinsic
    does to a segment 2 m away, so that one surface seen by several scanners stays one plane; the
    tracking gates keep their absolute width (they are a multiple of the tight ones). Merges made
    through the opened gates stay soft ties until the end (``backend.fold_links: end``) instead of
    one plane from the next window step: a wrong one then costs its tie, not the planes' estimates
    (the 3-s calibration walk with the scanners 3 deg / 5 cm off: 87.5 % of the tilted scanners'
    segments associated so, 85.4 % folded at each step)."""
    fe = cfg.frontend
    rot_deg = math.degrees(rot)
    spread = trans + 2.0 * rot
    factor = max(1.0, rot_deg / fe.sigma_rotation_deg, trans / fe.sigma_pose)
    front = fe.model_copy(update={
        "sigma_rotation_deg": max(fe.sigma_rotation_deg, rot_deg),
        "sigma_lever_deg": max(fe.sigma_lever_deg, rot_deg),
        "sigma_pose": max(fe.sigma_pose, trans),
        "max_endpoint_distance": fe.max_endpoint_distance + 3.0 * trans,
        "coplanar_distance": max(fe.coplanar_distance, spread),
        "merge_distance": max(fe.merge_distance, spread),
        "merge_angle_deg": max(fe.merge_angle_deg, 2.0 * rot_deg),
        "tracking_loosen": max(1.0, fe.tracking_loosen / factor),
    })
    back = cfg.backend.model_copy(update={"fold_links": "end"})
    return cfg.model_copy(update={"frontend": front, "backend": back})


def is_loosened(cfg: SlamConfig, rot: float, trans: float) -> bool:
    """Whether ``rot``/``trans`` open any gate of ``cfg`` (else the plain configuration runs)."""
    fe = cfg.frontend
    return math.degrees(rot) > fe.sigma_rotation_deg or trans > fe.sigma_pose


def run_slam(scans: Iterable[Scanline], rig: Rig, slam_cfg: SlamConfig,
             uncertainty: tuple[float, float] | None = None) -> tuple[SlamResult, SegmentLog]:
    """SLAM for calibration (:func:`slam_config_for_calibration`), with the gates loosened for an
    extrinsic ``uncertainty`` (rad, m) if given; with the scanner-frame segments of the scans it
    was given. Without an IMU (as here) no deskew touches the points, and the scanner-frame
    virtual points never depend on the extrinsics or a deskew."""
    cfg = slam_config_for_calibration(slam_cfg)
    loose = uncertainty is not None and is_loosened(cfg, *uncertainty)
    if loose:
        assert uncertainty is not None
        rot, trans = uncertainty
        cfg = loosened_slam_config(cfg, rot, trans)
    runner = SlamRunner(rig, cfg)
    log = SegmentLog()
    for line in scans:
        scan = runner.preparer.prepare(line)
        log.add(scan)
        runner.add_prepared(scan)
    runner.finish()
    res = runner.result(batch=False, covariances=False)
    runner.close()  # the back-end process, if any, at once (not when the runner is collected)
    return res, log


def calibrate_round(scans: ScanSource, rig: Rig, initial: Rig, slam_cfg: SlamConfig,
                    est: EstimatorConfig, uncertainty: tuple[float, float] | None = None
                    ) -> tuple[BatchResult, SlamResult, int]:
    """One round (steps 1-3) with the current ``rig``; priors around ``initial``; SLAM gates for
    an extrinsic ``uncertainty`` (rad, m; None: the plain configuration)."""
    res, log = run_slam(scans(rig), rig, slam_cfg, uncertainty)
    if len(res.knot_times) < 2:
        raise ValueError(f"no trajectory to calibrate along ({len(res.knot_times)} knot(s)): no usable scans on the "
                         "topics " + ", ".join(s.topic for s in rig.scanners))
    obs = log.observations(rig, res.segment_rows)
    planes = {int(j): (n, float(d)) for j, n, d in
              zip(res.plane_ids, res.plane_normals, res.plane_offsets, strict=True)}
    names = [s.name for s in rig.scanners]
    batch = estimate_extrinsics(
        res.knot_times, res.T_world_body, planes, obs,
        [s.T_body_scanner.matrix() for s in rig.scanners], names.index(rig.reference), names,
        [s.T_body_scanner.matrix() for s in initial.scanners], est)
    return batch, res, len(obs)


def calibrate(scans: ScanSource, rig: Rig, slam_cfg: SlamConfig,
              options: CalibrationOptions | None = None,
              progress: Callable[[str], None] | None = None,
              on_round: Callable[[RoundInfo, Rig], None] | None = None) -> Calibration:
    """Calibrate ``rig``'s non-reference scanners from the recording ``scans(rig)`` yields
    (a fresh time-ordered scan iterator per call, e.g. ``lambda r: read_scans(bag, rig=r)``);
    ``on_round`` gets every round's numbers and the rig it produced."""
    opt = options or CalibrationOptions()
    est = opt.estimator
    if est.motion == EstimatorConfig().motion:  # not chosen: the SLAM configuration's
        est = replace(est, motion=motion_prior_of(slam_cfg))
    current = rig
    rounds: list[RoundInfo] = []
    converged = False
    batch: BatchResult | None = None
    unc = opt.initial_uncertainty
    for k in range(opt.max_rounds):
        last = k == opt.max_rounds - 1
        gate = None if unc is None or (last and k > 0) else unc
        t_round = _time.perf_counter()
        loose = gate is not None and is_loosened(slam_config_for_calibration(slam_cfg), *gate)
        # a loosened round only has to bring the rig closer: one convex (Huber) solve, capped
        est_k = est if not loose else replace(est, variance_factor=False, kernel=est.start_kernel,
                                              max_iterations=min(est.max_iterations, opt.coarse_iterations),
                                              grazing_cos=opt.coarse_grazing_cos)
        dur = opt.coarse_duration if loose else None
        source = scans if dur is None else _first_seconds(scans, dur)
        batch, res, n_obs = calibrate_round(source, current, rig, slam_cfg, est_k, gate)
        d_rot, d_tr = 0.0, 0.0
        for s in batch.scanners:
            xi = se3_log(np.linalg.inv(s.T_initial) @ s.T_body_scanner)
            d_rot = max(d_rot, float(np.linalg.norm(xi[:3])))
            d_tr = max(d_tr, float(np.linalg.norm(s.T_body_scanner[:3, 3] - s.T_initial[:3, 3])))
        g_rot, g_tr = gate if loose and gate is not None else (0.0, 0.0)
        rounds.append(RoundInfo(k + 1, len(res.plane_ids), int((res.segment_rows["plane_id"] >= 0).sum()),
                                n_obs, d_rot, d_tr, batch.seconds, g_rot, g_tr,
                                _time.perf_counter() - t_round - batch.seconds, dur))
        current = _rig_of(current, batch, rig.name, opt.covariance)
        if progress is not None:
            gates = f", gates {np.degrees(g_rot):.2f} deg / {g_tr * 1e3:.1f} mm" if loose else ""
            gates += f", first {dur:g} s" if dur is not None else ""
            info = rounds[-1]
            progress(f"round {k + 1}: {len(res.plane_ids)} planes, {n_obs} points, change "
                     f"{np.degrees(d_rot):.4f} deg / {d_tr * 1e3:.3f} mm{gates}; SLAM "
                     f"{info.slam_seconds:.0f} s, batch {info.batch_seconds:.0f} s "
                     f"({batch.iterations} iterations)")
        if on_round is not None:
            on_round(rounds[-1], current)
        if unc is not None:
            unc = (min(unc[0], opt.shrink * d_rot), min(unc[1], opt.shrink * d_tr))
        if d_rot < opt.tol_rot and d_tr < opt.tol_trans and not loose:
            converged = True
            break
    assert batch is not None
    sigmas, msgs = [], []
    for s in batch.scanners:
        cov = reported_covariance(s, opt.covariance)
        if cov is None:
            continue
        p = parameter_sigmas(s.name, s.T_body_scanner, cov, batch.prior_sigmas,
                             opt.unobservable_ratio)
        sigmas.append(p)
        msgs.extend(warn_unobservable(p))
    return Calibration(current, rig, batch, sigmas, msgs, rounds, converged)


def _first_seconds(scans: ScanSource, duration: float) -> ScanSource:
    """``scans`` cut to the scanlines that start within ``duration`` s of the first one."""

    def head(rig: Rig) -> Iterable[Scanline]:
        t0 = None
        for line in scans(rig):
            t0 = line.stamp if t0 is None else t0
            if line.stamp - t0 > duration:
                return
            yield line

    return head


def reported_covariance(s: ScannerEstimate, which: str = "cluster") -> FloatArray | None:
    """The covariance written to the rig file and used for the observability warnings: the
    cluster-robust one (``which="cluster"``, if the batch computed it) or the marginal one."""
    if which == "cluster" and s.covariance_cluster is not None:
        return s.covariance_cluster
    return s.covariance


def _rig_of(rig: Rig, batch: BatchResult, name: str, which: str = "cluster") -> Rig:
    ext = {s.name: (s.T_body_scanner, reported_covariance(s, which)) for s in batch.scanners
           if s.covariance is not None}
    offs = {s.name: rig.scanner(s.name).time_offset + s.time_offset
            for s in batch.scanners if s.time_offset_sigma is not None}
    return updated_rig(rig, ext, offs, name=name)


def calibrate_bag(bag: str | Path, rig: Rig, slam_cfg: SlamConfig,
                  options: CalibrationOptions | None = None,
                  progress: Callable[[str], None] | None = None,
                  on_round: Callable[[RoundInfo, Rig], None] | None = None) -> Calibration:
    """:func:`calibrate` on a ROS bag (the rig's scanner topics)."""
    from slam.io.bag import read_scans

    echo = slam_cfg.input.echo
    read_scans(bag, rig=rig, echo=echo)  # checks the bag and its topics before the work starts
    return calibrate(lambda r: read_scans(bag, rig=r, echo=echo), rig, slam_cfg, options, progress, on_round)
