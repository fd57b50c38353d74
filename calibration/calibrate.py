"""Calibrate a rig from a recording: SLAM, batch extrinsic estimation, repeat until converged.

1. Run SLAM (:class:`slam.pipeline.SlamRunner`, without its final batch: the calibration batch
   replaces it) on the bag with the current rig: trajectory, planes, segment-to-plane
   associations.
2. Re-read the scans; every associated segment becomes two moment-matched virtual points in its
   scanner frame (:mod:`calibration.observations`).
3. One batch graph with the extrinsics (and optionally time offsets) as variables, priors around
   the *initial* rig (:mod:`calibration.estimator`).
4. Update the rig; repeat from 1 until the extrinsics move less than ``tol_rot`` / ``tol_trans``
   (the associations improve with the calibration) or ``max_rounds`` is reached.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from backpack_slam.rig import Rig
from calibration.estimator import BatchResult, EstimatorConfig, estimate_extrinsics
from calibration.observability import ParameterSigmas, parameter_sigmas, warn_unobservable
from calibration.observations import collect_observations
from calibration.rig_io import updated_rig
from segmentation import Scanline
from slam.config import SlamConfig
from slam.interpolation import se3_log
from slam.motion import MotionPriorConfig
from slam.pipeline import SlamResult, run_stream

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


def calibrate_round(scans: ScanSource, rig: Rig, initial: Rig, slam_cfg: SlamConfig,
                    est: EstimatorConfig) -> tuple[BatchResult, SlamResult, int]:
    """One round (steps 1-3) with the current ``rig``; priors around ``initial``."""
    res = run_stream(scans(rig), rig, slam_config_for_calibration(slam_cfg))
    obs = collect_observations(scans(rig), rig, res.segment_rows)
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
              progress: Callable[[str], None] | None = None) -> Calibration:
    """Calibrate ``rig``'s non-reference scanners from the recording ``scans(rig)`` yields
    (a fresh time-ordered scan iterator per call, e.g. ``lambda r: read_scans(bag, rig=r)``)."""
    opt = options or CalibrationOptions()
    est = opt.estimator
    if est.motion == MotionPriorConfig():
        est = replace(est, motion=motion_prior_of(slam_cfg))
    current = rig
    rounds: list[RoundInfo] = []
    converged = False
    batch: BatchResult | None = None
    for k in range(opt.max_rounds):
        batch, res, n_obs = calibrate_round(scans, current, rig, slam_cfg, est)
        d_rot, d_tr = 0.0, 0.0
        for s in batch.scanners:
            xi = se3_log(np.linalg.inv(s.T_initial) @ s.T_body_scanner)
            d_rot = max(d_rot, float(np.linalg.norm(xi[:3])))
            d_tr = max(d_tr, float(np.linalg.norm(s.T_body_scanner[:3, 3] - s.T_initial[:3, 3])))
        rounds.append(RoundInfo(k + 1, len(res.plane_ids), int((res.segment_rows["plane_id"] >= 0).sum()),
                                n_obs, d_rot, d_tr, batch.seconds))
        current = _rig_of(current, batch, rig.name)
        if progress is not None:
            progress(f"round {k + 1}: {len(res.plane_ids)} planes, {n_obs} points, change "
                     f"{np.degrees(d_rot):.4f} deg / {d_tr * 1e3:.3f} mm")
        if d_rot < opt.tol_rot and d_tr < opt.tol_trans:
            converged = True
            break
    assert batch is not None
    sigmas, msgs = [], []
    for s in batch.scanners:
        if s.covariance is None:
            continue
        p = parameter_sigmas(s.name, s.T_body_scanner, s.covariance, batch.prior_sigmas,
                             opt.unobservable_ratio)
        sigmas.append(p)
        msgs.extend(warn_unobservable(p))
    return Calibration(current, rig, batch, sigmas, msgs, rounds, converged)


def _rig_of(rig: Rig, batch: BatchResult, name: str) -> Rig:
    ext = {s.name: (s.T_body_scanner, s.covariance) for s in batch.scanners if s.covariance is not None}
    offs = {s.name: rig.scanner(s.name).time_offset + s.time_offset
            for s in batch.scanners if s.time_offset_sigma is not None}
    return updated_rig(rig, ext, offs, name=name)


def calibrate_bag(bag: str | Path, rig: Rig, slam_cfg: SlamConfig,
                  options: CalibrationOptions | None = None,
                  progress: Callable[[str], None] | None = None) -> Calibration:
    """:func:`calibrate` on a ROS bag (the rig's scanner topics)."""
    from slam.io.bag import read_scans

    read_scans(bag, rig=rig)  # checks the bag and its topics before the work starts
    return calibrate(lambda r: read_scans(bag, rig=r), rig, slam_cfg, options, progress)
