"""The one translation from the run configuration to the parameters of the SLAM's components.

Every parameter has exactly one default, in the configuration model (``slam.config``, the YAML
keys); the noise-dependent ones are stated for the reference noise and scaled here to the
scanners' (:func:`noise_levels`, :func:`noise_scaled`, :func:`segmenter`; the rule is
``slam.config.NoiseSection``'s). The components' parameter records (``Gates``, ``PlaneInitParams``, ``MapParams``, ``EdgeParams``,
``TrackingParams``, ``ImuMotionParams``, ``ImuConfig``, ``MotionPriorConfig``, ``BackendConfig``)
take none of their own and are built here only: degrees become radians, sigmas become arrays,
the knot interval turns the motion prior's accelerations into densities.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from common.rig import Rig
from segmentation import NoiseModel, Segmenter, segmenter_class
from segmentation import get as get_segmenter
from slam.backend import BackendConfig
from slam.backend.factors import RobustKernel
from slam.config import SlamConfig
from slam.frontend.association import Gates
from slam.frontend.edges import EdgeParams
from slam.frontend.initial_motion import InitialMotionParams
from slam.frontend.map_builder import MapParams
from slam.frontend.parallel_choice import ChoiceParams
from slam.frontend.plane_init import PlaneInitParams
from slam.frontend.tracking import TrackingParams
from slam.frontend.transients import TransientParams
from slam.imu_feed import ImuMotionParams
from slam.motion import ImuConfig, MotionPriorConfig

# the values stated for the reference noise (``noise.reference``) that scale with the scanners' noise
NOISE_SCALED: dict[str, tuple[str, ...]] = {
    "frontend": ("point_sigma", "coplanar_distance", "merge_distance", "max_endpoint_distance", "relative_sigma"),
    "edges": ("sigma", "min_step", "step_tolerance", "cluster_width"),
    "backend": ("final_trim_distance",),
    "output": ("extent_gate", "extent_rms"),
}


@dataclass(frozen=True)
class NoiseLevels:
    """Per scanner (the rig's order): the range noise its values follow (``sigma``, m; the
    reference inside the dead band) and its ratio to the reference (``ratio``, 1 there)."""

    sigma: tuple[float, ...]
    ratio: tuple[float, ...]

    @property
    def shared(self) -> float:
        """The ratio the run's shared values scale by: the largest of its scanners'."""
        return max(self.ratio, default=1.0)


def noise_levels(rig: Rig, cfg: SlamConfig) -> NoiseLevels:
    """Each scanner's noise by the rule of ``slam.config.NoiseSection``: ``noise.scanners`` (set
    by hand, or by the run driver from its estimate), else the rig model's ``range_sigma``."""
    nc = cfg.noise
    sigma, ratio = [], []
    for s in rig.scanners:
        measured = nc.scanners.get(s.name, s.scanner_model.range_sigma)
        if measured <= nc.scale_above * nc.reference:
            sigma.append(nc.reference)
            ratio.append(1.0)
        else:
            sigma.append(float(measured))
            ratio.append(float(measured) / nc.reference)
    return NoiseLevels(tuple(sigma), tuple(ratio))


def noise_scaled(cfg: SlamConfig, ratio: float) -> SlamConfig:
    """``cfg`` with the values of ``NOISE_SCALED`` multiplied by ``ratio`` (``cfg`` itself at 1)."""
    if ratio == 1.0:
        return cfg
    update = {}
    for section, keys in NOISE_SCALED.items():
        sec = getattr(cfg, section)
        update[section] = sec.model_copy(update={k: getattr(sec, k) * ratio for k in keys})
    return cfg.model_copy(update=update)


def segmenter(cfg: SlamConfig, rig: Rig, levels: NoiseLevels, index: int) -> Segmenter:
    """Scanner ``index``'s segmenter: the configured one as given at the reference noise, else with
    the defaults derived from its noise (``Params.from_noise``) and the given thresholds that its
    noise-derived defaults scale (floats other than the noise itself) scaled by its ratio."""
    seg = cfg.segmenter
    ratio = levels.ratio[index]
    if ratio == 1.0:
        return get_segmenter(seg.method, **seg.params)
    scanner = rig.scanners[index]
    model = NoiseModel.of(levels.sigma[index], scanner.scanner_model.angle_increment, scanner_id=scanner.name)
    derived = segmenter_class(seg.method).Params.from_noise(model)
    given: dict[str, Any] = {
        k: v * ratio if k in derived and isinstance(v, float) and k not in ("point_sigma", "noise_slope") else v
        for k, v in seg.params.items()
    }
    return get_segmenter(seg.method, noise=model, **given)


def gates(cfg: SlamConfig) -> Gates:
    """The association gates (``frontend``)."""
    fe = cfg.frontend
    return Gates(
        sigma_pose=fe.sigma_pose,
        sigma_rotation=np.radians(fe.sigma_rotation_deg),
        sigma_lever=np.radians(fe.sigma_lever_deg),
        drift_rate=fe.drift_rate,
        drift_rate_vertical=fe.drift_rate_vertical,
        extent_margin_cells=fe.extent_margin_cells,
        max_extra_cells=fe.max_extra_cells,
        max_drift_sigma=fe.max_drift_sigma,
        chi2=fe.association_chi2,
        max_endpoint_distance=fe.max_endpoint_distance,
        child_margin_cells=fe.child_margin_cells if fe.child_margin_cells >= 0 or not fe.parallel_choice else 1,
        child_host_normal=fe.child_host_normal,
        choice=ChoiceParams(relative_sigma=fe.relative_sigma, gate=fe.relative_gate, ratio=fe.ambiguity_ratio,
                            sigma_pose=fe.choice_sigma_pose, sigma_lever=np.radians(fe.choice_sigma_lever_deg),
                            walls_only=False, veto=False, host_sigma=fe.host_sigma,
                            host_lever=float(np.radians(fe.host_lever_deg)), host_test=fe.host_test,
                            model=fe.choice_lever_model, hold_past_child=fe.hold_past_child_extent,
                            local_reach=fe.local_step_reach, local_gate=fe.local_step_gate,
                            local_sigma=fe.local_step_sigma, local_lever=float(np.radians(fe.local_step_lever_deg)))
        if fe.parallel_choice else None,
    )


def tracking_gates(cfg: SlamConfig) -> Gates:
    """The gates of the tracking (pre-)association: :func:`gates` loosened by ``tracking_loosen``,
    with the parallel choice (for walls only) as a veto on the nearest candidate with ``tracking_choice``."""
    g = gates(cfg).loosened(cfg.frontend.tracking_loosen)
    if g.choice is None or not cfg.frontend.tracking_choice:
        return replace(g, choice=None)
    return replace(g, choice=replace(g.choice, walls_only=True, veto=True))


def plane_init_params(cfg: SlamConfig) -> PlaneInitParams:
    """Plane creation from the pool of unassociated segments (``frontend``)."""
    fe = cfg.frontend
    return PlaneInitParams(
        min_support=fe.min_support,
        min_scans=fe.min_scans,
        coplanar_distance=fe.coplanar_distance,
        sample_distance=fe.coplanar_distance + 3.0 * fe.point_sigma,
        coplanar_angle=np.radians(fe.coplanar_angle_deg),
        min_spread=fe.min_spread,
        min_angle_between=np.radians(fe.seed_min_angle_deg),
        min_parallel_separation=fe.seed_min_separation,
        neighbourhood=fe.seed_neighbourhood,
        min_scan_plane_angle=np.radians(fe.min_scan_plane_angle_deg),
        window=fe.pool_window,
        max_partners=fe.seed_max_partners,
        vertical_walls=cfg.backend.vertical_walls,
        horizontal_tolerance=np.radians(fe.horizontal_tolerance_deg),
        max_level_scan_tilt=np.radians(fe.max_level_scan_tilt_deg),
    )


def edge_params(cfg: SlamConfig) -> EdgeParams:
    """Door and board edges (``edges``)."""
    ec = cfg.edges
    return EdgeParams(
        max_gap=ec.max_gap,
        min_incidence_deg=ec.min_incidence_deg,
        sigma=ec.sigma,
        cluster_width=ec.cluster_width,
        min_points=ec.min_points,
        min_scans=ec.min_scans,
        gate=ec.gate,
        tracking_gate=ec.tracking_gate,
        window=ec.window,
        merge_distance=ec.merge_distance,
        link_sigma=ec.link_sigma,
        min_step=ec.min_step,
        max_step=ec.max_step,
        step_tolerance=ec.step_tolerance,
        max_skipped_points=ec.max_skipped_points,
        min_height_span=ec.min_height_span,
        point=ec.point,
        height_margin=ec.height_margin,
        flat_slope=ec.flat_slope,
        perpendicular_sigma=np.radians(ec.perpendicular_sigma_deg),
        inline=ec.inline,
        inline_window=ec.inline_window,
        inline_z=ec.inline_z,
        min_segment_points=cfg.frontend.min_segment_points,
    )


def map_params(cfg: SlamConfig) -> MapParams:
    """The plane life cycle: classification, ties to a host, merges (``frontend``)."""
    fe = cfg.frontend
    return MapParams(
        min_segment_points=fe.min_segment_points,
        vertical_tolerance=np.radians(fe.vertical_tolerance_deg),
        vertical_walls=cfg.backend.vertical_walls,
        min_support_oblique=fe.min_support_oblique,
        max_tilt_sigma=np.radians(fe.max_tilt_sigma_deg),
        extent_margin_cells=fe.extent_margin_cells,
        host_min_segments=fe.host_min_segments,
        parallel_max_angle=np.radians(fe.parallel_max_angle_deg),
        parallel_max_offset=fe.parallel_max_offset,
        parallel_sigma=np.radians(fe.parallel_sigma_deg),
        wall_faces=fe.wall_faces,
        wall_thickness=fe.wall_thickness,
        wall_faces_sigma=np.radians(fe.wall_faces_sigma_deg),
        merge_angle=np.radians(fe.merge_angle_deg),
        merge_distance=fe.merge_distance,
        merge_drift_over=fe.merge_drift_over,
        merge_coobserved_max=fe.merge_coobserved_max,
        drift_rate=fe.drift_rate,
        drift_rate_vertical=fe.drift_rate_vertical,
        link_sigma=fe.link_sigma,
        child_merge_distance=fe.child_merge_distance if fe.parallel_choice else float("inf"),
        child_adopt_cells=1 if fe.parallel_choice else 1 << 20,
        layer_merge_distance=fe.layer_merge_distance,
        child_max_length=fe.child_max_length,
        distinct_offset=fe.merge_distinct_offset,
    )


def tracking_params(cfg: SlamConfig) -> TrackingParams:
    """Tracking of the newest knots against the map (``frontend.tracking_*``)."""
    fe = cfg.frontend
    return TrackingParams(
        window=fe.tracking_window,
        iterations=fe.tracking_iterations,
        first_prior_sigmas=np.array([np.radians(fe.tracking_first_prior_deg)] * 3
                                    + [fe.tracking_first_prior_position] * 3),
        twist_sigmas=np.array([fe.tracking_twist_sigma_rotation] * 3 + [fe.tracking_twist_sigma_position] * 3),
    )


def initial_motion_params(cfg: SlamConfig) -> InitialMotionParams:
    """The start's motion from the first scans (``frontend.initial_motion_*``)."""
    fe = cfg.frontend
    return InitialMotionParams(window=fe.initial_motion_window, min_speed=fe.initial_motion_min_speed,
                               min_rate=np.radians(fe.initial_motion_min_rate_deg),
                               reference_sigma=cfg.noise.reference, rest_odometry=fe.initial_motion_rest_odometry)


def transient_params(cfg: SlamConfig) -> TransientParams:
    """The see-through test of young planes (``frontend.transient_*``)."""
    fe = cfg.frontend
    return TransientParams(use=fe.transient_check, probation=fe.transient_probation, margin=fe.transient_margin,
                           near=fe.transient_near,
                           min_through=fe.transient_min_through, ratio=fe.transient_ratio,
                           beam_step=fe.transient_beam_step)


def imu_motion_params(cfg: SlamConfig) -> ImuMotionParams:
    """The front end's use of an IMU (``imu``): zero-velocity updates and IMU-predicted tracking."""
    ic = cfg.imu
    return ImuMotionParams(
        zupt=ic.zupt,
        zupt_window=ic.zupt_window,
        zupt_threshold=ic.zupt_threshold,
        zupt_sigma=ic.zupt_sigma,
        accel_noise=ic.accel_noise,
        gyro_noise=ic.gyro_noise,
        gravity=ic.gravity,
        increment_sigmas=np.array([np.radians(ic.increment_sigma_deg)] * 3 + [ic.increment_sigma_position] * 3),
        degenerate_ratio=float(np.sin(np.radians(ic.degenerate_angle_deg)) ** 2),
    )


def imu_config(cfg: SlamConfig) -> ImuConfig:
    """IMU noise for preintegration (``imu``); the IMU frame is the body frame."""
    ic = cfg.imu
    return ImuConfig(
        accel_noise_density=ic.accel_noise,
        gyro_noise_density=ic.gyro_noise,
        accel_bias_rw=ic.accel_bias_walk,
        gyro_bias_rw=ic.gyro_bias_walk,
        integration_sigma=ic.integration_sigma,
        bias_prior_sigmas=(ic.accel_bias_prior, ic.gyro_bias_prior),
        velocity_prior_sigma=ic.velocity_prior_sigma,
        gravity=ic.gravity,
        T_body_imu=None,
    )


def motion_prior(cfg: SlamConfig) -> MotionPriorConfig:
    """The constant-velocity prior: ``backend.motion_sigma_*`` (accelerations) as densities over
    one knot interval."""
    dt = 1.0 / cfg.trajectory.knot_rate
    be = cfg.backend
    return MotionPriorConfig(q_ang=be.motion_sigma_angacc**2 * dt, q_lin=be.motion_sigma_acc**2 * dt)


def backend_config(cfg: SlamConfig, with_imu: bool) -> BackendConfig:
    """The back end (``backend``), with the IMU's factors when ``with_imu``."""
    be = cfg.backend
    return BackendConfig(
        kernel=RobustKernel(be.robust, be.robust_k),
        motion=motion_prior(cfg),
        use_motion_prior=not with_imu or cfg.imu.motion_prior,
        initial_velocity_sigmas=be.initial_velocity_sigmas,
        datum=be.datum,
        datum_sigma=be.datum_sigma,
        datum_tilt_sigma=be.datum_tilt_sigma,
        vertical_sigma=np.radians(be.vertical_prior_deg),
        horizontal_sigma=np.radians(be.horizontal_prior_deg),
        relinearize_threshold=be.relinearize_threshold,
        relinearize_skip=be.relinearize_skip,
        plane_relinearize_factor=be.plane_relinearize_factor,
        lm_max_iterations=be.lm_max_iterations,
        lm_relative_tolerance=be.lm_relative_tolerance,
        batch_relative_tolerance=be.batch_relative_tolerance,
        robust_schedule=be.robust_schedule,
        imu=imu_config(cfg) if with_imu else None,
        coalesce_blocks=be.solver == "window",
        solver=be.solver,
        window_knots=round(be.window_seconds / (1.0 / cfg.trajectory.knot_rate)),
        window_iterations=be.window_iterations,
        isam2_iterations=be.isam2_iterations,
        isam2_fallback_iterations=be.isam2_fallback_iterations,
        batch_section_knots=max(1, round(be.batch_section_seconds * cfg.trajectory.knot_rate)),
        batch_cache_bytes=round(be.batch_cache_mb * 1e6),
        batch_heap_slack_bytes=round(be.batch_heap_slack_mb * 1e6),
        fold_links_in_window=be.fold_links == "step" and be.solver == "window",
        batch_whole_knots=round(be.batch_whole_seconds * cfg.trajectory.knot_rate),
    )


@dataclass(frozen=True, eq=False)
class Components:
    """Every component's parameters for one run; ``edges`` None with ``edges.use`` off, ``imu``
    and ``imu_motion`` None without an IMU."""

    gates: Gates
    tracking_gates: Gates
    plane_init: PlaneInitParams
    map: MapParams
    edges: EdgeParams | None
    tracking: TrackingParams
    initial_motion: InitialMotionParams
    transients: TransientParams
    imu: ImuConfig | None
    imu_motion: ImuMotionParams | None
    backend: BackendConfig


def components(cfg: SlamConfig, with_imu: bool) -> Components:
    """All of the above for a run with (``with_imu``) or without an IMU."""
    return Components(
        gates=gates(cfg),
        tracking_gates=tracking_gates(cfg),
        plane_init=plane_init_params(cfg),
        map=map_params(cfg),
        edges=edge_params(cfg) if cfg.edges.use else None,
        tracking=tracking_params(cfg),
        initial_motion=initial_motion_params(cfg),
        transients=transient_params(cfg),
        imu=imu_config(cfg) if with_imu else None,
        imu_motion=imu_motion_params(cfg) if with_imu else None,
        backend=backend_config(cfg, with_imu),
    )
