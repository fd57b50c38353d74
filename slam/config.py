"""The SLAM run configuration (``configs/slam/*.yaml``), validated on load.

Every section is a strict pydantic model: an unknown key or a bad value is an
error naming the file and the key. The segmenter is chosen by name with its
parameters, so swapping segmenters is one line of configuration.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator

from common.config import ConfigError, StrictModel, load
from segmentation import segmenter_class
from slam.health import HealthSection

# The SLAM's own defaults for a segmenter's parameters, where they differ from the segmenter's:
# RoR at sigma = 6 mm separates doors set 1 cm into their walls (the paper's 9.5 mm merges them),
# and door edges are what observes the walking direction in corridors (docs/bench_slam.md).
SLAM_SEGMENTER_DEFAULTS: dict[str, dict[str, Any]] = {"ror": {"sigma": 0.006}}


class SegmenterConfig(StrictModel):
    """Which segmenter, with which parameters (see ``segmentation.available()``). Without
    ``params``, the SLAM's defaults for that method (``SLAM_SEGMENTER_DEFAULTS``, else the
    segmenter's own); given ``params`` replace them (``{}``: the segmenter's own defaults)."""

    method: str = "ror"
    params: dict[str, Any] = Field(default_factory=lambda: dict(SLAM_SEGMENTER_DEFAULTS["ror"]))
    split_steps: bool = Field(
        False, description="split each segment where its points switch between two parallel lines (a door 1 cm "
        "into its wall, a board proud of it, left in the wall's segment: segmentation.steps)")
    step_chi2: float = Field(25.0, gt=0, description="least chi-square gain of a split (one degree of freedom)")
    step_min: float = Field(0.004, ge=0, description="m, least offset between the two parts of a split")

    @model_validator(mode="before")
    @classmethod
    def _slam_defaults(cls, data: Any) -> Any:
        if isinstance(data, dict) and "params" not in data:
            method = data.get("method", "ror")
            if isinstance(method, str):
                data = {**data, "params": dict(SLAM_SEGMENTER_DEFAULTS.get(method, {}))}
        return data

    @model_validator(mode="after")
    def _known(self) -> SegmenterConfig:
        # raises ValueError naming the method or parameter; pydantic reports it with the key
        segmenter_class(self.method).make_params(**self.params)
        return self


class TrajectoryConfig(StrictModel):
    """Continuous-time trajectory: knots at ``knot_rate`` Hz, SE(3) interpolation between them."""

    knot_rate: float = Field(20.0, gt=0, le=400)
    imu_deskew: bool = Field(
        True, description="with an IMU: between knots, turn the body by what the gyro measures beyond the "
        "geodesic (slam.trajectory.deskew; at 20 Hz the geodesic misses a walker's pitch and turns by 36 mdeg RMS)")


class FrontEndConfig(StrictModel):
    """Association gates and plane creation."""

    point_sigma: float = Field(0.003, gt=0, description="range noise of one point (m)")
    model_sigma: float = Field(
        0.001, ge=0,
        description="m, added in quadrature to every virtual point: errors that do not average out over a "
        "segment (trajectory between knots, calibration, surface flatness)")
    sigma_pose: float = Field(0.004, gt=0, description="pose uncertainty at a segment for association (m)")
    sigma_rotation_deg: float = Field(0.3, gt=0, description="rotation uncertainty in the angle test (deg)")
    sigma_lever_deg: float = Field(0.05, gt=0, description="rotation uncertainty times range in the distance test (deg)")
    drift_rate: float = Field(0.003, ge=0, description="offset uncertainty per metre walked since a plane was seen")
    drift_rate_vertical: float = Field(
        0.0003, ge=0, description="the same for floors and ceilings: height drifts far less than the walls' "
        "offsets (floors and ceilings are in view all the time, gravity levels the rig)")
    max_endpoint_distance: float = Field(
        0.05, gt=0, description="m, hard cap on either endpoint's distance from a plane for association (grown by "
        "3 sigma of the drift and of the rotation's lever arm)")
    max_extra_cells: int = Field(8, ge=0, description="cap of the extent margin's growth with the drift (cells)")
    max_drift_sigma: float = Field(0.05, gt=0, description="m, cap of the drift-grown offset uncertainty")
    association_chi2: float = Field(
        9.21, gt=0, description="gate of the combined angle and distance test (9.21: chi-square, 2 dof, 99 %)")
    tracking_loosen: float = Field(8.0, ge=1, description="gate factor of the tracking (pre-)association")
    tracking_iterations: int = Field(3, ge=0)
    tracking_window: int = Field(6, ge=1, description="knot intervals refined together by tracking")
    tracking_first_prior_deg: float = Field(
        0.2, gt=0, description="deg, sigma holding the rotation of the tracking window's oldest knot")
    tracking_first_prior_position: float = Field(
        0.01, gt=0, description="m, sigma holding the position of the tracking window's oldest knot")
    tracking_twist_sigma_rotation: float = Field(
        0.006, gt=0, description="rad, sigma of the body twist's change per knot interval in tracking (rotation)")
    tracking_twist_sigma_position: float = Field(
        0.002, gt=0, description="m, the same for the translation")
    initial_motion_window: float = Field(
        1.0, ge=0, description="s of the first scans registered against each other (in the scan plane of the most "
        "level scanner) before the first knot: a recording may start while the operator walks; then the first "
        "0.3 s give the start's motion and the 2D odometry of this window predicts its knots "
        "(slam.frontend.initial_motion; a direction the first scans' lines do not observe, such as a corridor's, is "
        "held at rest); 0 = assume the walk starts at rest")
    initial_motion_min_speed: float = Field(
        0.05, ge=0, description="m/s; a start slower than this (and turning slower than initial_motion_min_rate_deg) "
        "is at rest; both stated for the reference noise (noise.reference) and raised in proportion for a noisier "
        "scanner")
    initial_motion_min_rate_deg: float = Field(3.0, ge=0, description="deg/s, see initial_motion_min_speed")
    initial_motion_rest_odometry: bool = Field(
        True, description="a walk that starts at rest also gets the window's 2D odometry as its first knots' "
        "motions (as a moving start does). Off, a room whose door and board are 1 cm from their walls let the "
        "estimate slide 0.57 m along the walking direction in the first 2 s, before the end walls (seen by the level "
        "scanner alone) became planes (issue 26, session 20); on, the demo, the small room and the 2-min office walk "
        "give the same figures as off")
    rest_observe_every: int = Field(
        1, ge=1, description="while the operator stands still (the IMU's zero-velocity test, or the tracked poses "
        "within 1 cm and 0.5 deg over 0.5 s), only every n-th knot's scans observe the map (the others are neither associated nor pooled): a standing rig repeats one view, whose systematic "
        "errors (a segment across a door's edge, a mixed return) do not average out over its repeats; 1 = all")
    transient_check: bool = Field(
        True, description="take planes of things that move (people walking by) out of the map: young planes that "
        "later scans pass through (slam.frontend.transients)")
    transient_probation: int = Field(
        60, ge=1, description="segments below which a plane is tested for being seen through")
    transient_margin: float = Field(
        0.1, gt=0, description="m, a beam crossing a plane this far before its return passes through it")
    transient_near: float = Field(
        0.02, gt=0, description="m, a beam crosses a plane where it was seen when it crosses it this near one of its "
        "points")
    transient_min_through: int = Field(40, ge=1, description="beams through a plane that make it a transient ...")
    transient_ratio: float = Field(1.0, ge=0, description="... when more than this times the beams returned from it")
    transient_beam_step: int = Field(2, ge=1, description="every n-th beam of a scan is tested")
    extent_cell: float = Field(0.25, gt=0, description="cell size of plane extents (m)")
    extent_margin_cells: int = Field(4, ge=0, description="cells by which a plane's extent is grown for association")
    min_support: int = Field(6, ge=2, description="segments a new plane needs")
    min_scans: int = Field(4, ge=2, description="distinct scans among a new plane's segments")
    min_spread: float = Field(0.04, gt=0, description="m, second principal standard deviation of a new plane's points")
    coplanar_angle_deg: float = Field(2.0, gt=0, description="deg, a new plane's members' directions lie within this of it")
    seed_min_angle_deg: float = Field(10.0, gt=0, description="deg, the two segments seeding a plane: least angle between them")
    seed_min_separation: float = Field(0.05, gt=0, description="m, ... or least distance between them when parallel")
    seed_neighbourhood: float = Field(3.0, gt=0, description="m, a new plane's members lie within this of its seed")
    seed_max_partners: int = Field(4, ge=1, description="seed pairs tried per seed segment (nearest first)")
    min_scan_plane_angle_deg: float = Field(
        15.0, gt=0, description="deg, a plane this close to a member's scan plane is that scan plane, not a surface")
    horizontal_tolerance_deg: float = Field(
        3.0, gt=0, description="deg, a segment this close to horizontal counts as horizontal (wall hypothesis)")
    max_level_scan_tilt_deg: float = Field(
        30.0, gt=0, description="deg, the wall hypothesis takes segments of scan planes this close to level only: a "
        "tilted scanner's level line lies as well on a floor or table top")
    max_tilt_sigma_deg: float = Field(
        1.0, gt=0, description="deg, a new plane's worst tilt must be observed this well by its members (a thin strip, "
        "a door frame seen edge-on, leaves the solver a nearly singular plane)")
    min_support_oblique: int = Field(
        40, ge=2, description="segments a new plane needs that is neither a wall nor a floor/ceiling (beyond "
        "vertical_tolerance_deg): a real slope is seen by tens of scanlines a second, while a fit across a wall "
        "and its door or board, a few degrees off vertical, gathers a handful (office 10 min: every such plane "
        "was one, 0.3-85 deg off)")
    coplanar_distance: float = Field(
        0.006, gt=0,
        description="m, a new plane's members: fitted line within this (raw samples within this + 3 point_sigma); "
        "below the 1-2 cm of doors and boards so that they do not join their wall")
    pool_window: float = Field(1.0, gt=0, description="s an unassociated segment waits for a plane")
    min_segment_points: int = Field(10, ge=2)
    merge_angle_deg: float = Field(1.5, gt=0)
    host_min_segments: int = Field(
        50, ge=1, description="segments of an established plane before new planes are tied to it (parallel_* and "
        "wall_faces)")
    parallel_max_offset: float = Field(
        0.05, ge=0, description="m, a new plane this close to an established one and within parallel_max_angle_deg "
        "of it is tied parallel to it (doors, boards); 0 = never")
    parallel_max_angle_deg: float = Field(
        15.0, gt=0, description="deg; a new plane from a few segments is often degrees off (office: a door's and its "
        "wall's segments of one tilted scanner, near-parallel lines 2 cm apart, fitted 4-8 deg off the wall)")
    parallel_sigma_deg: float = Field(
        0.005, gt=0, description="sigma of that parallelism tie (deg): stiff, so that a door that took a few of its "
        "wall's segments metres away cannot turn towards them (the final trim then detaches them)")
    child_margin_cells: int = Field(
        -1, ge=-1, description="cells by which the extent of a plane tied parallel to its wall (a door, a board) "
        "is grown for association, not grown with the drift; -1 = extent_margin_cells like every plane (1 with "
        "parallel_choice, where a segment's end points must both lie in a child's extent so grown). A door's "
        "extent grown by a metre reaches the wall and the boards beside it, whose segments lie 1-3 cm off the door")
    child_host_normal: bool = Field(
        False, description="associate with a plane tied parallel to its wall by the distance to the plane with the "
        "wall's normal through the centre of its extent: a door fitted a little tilted is otherwise nearer the wall's "
        "or a neighbouring board's segments at one end, takes them and tilts further (office: 0.4 deg)")
    parallel_choice: bool = Field(
        True, description="choose between parallel planes a few centimetres apart (a wall, its door, its board) "
        "from the segments' own lines once the scan's common pose offset is taken out (slam.frontend."
        "parallel_choice); a segment that fits two is held back, one that fits none goes to the pool, and only "
        "unambiguous segments grow extents. Off: the nearest plane under the pose-widened gates (the wall's "
        "segments 2 cm off a board's plane passed its gate, and its extent ran along the whole wall)")
    relative_sigma: float = Field(
        0.0015, gt=0, description="m, what a segment's own line misses of its distance to a plane once the scan's "
        "common offset is removed (flatness, the rotation's lever along the scan); stated for the reference noise")
    relative_gate: float = Field(4.0, gt=0, description="sigmas of the parallel choice's test")
    choice_sigma_lever_deg: float = Field(
        0.05, gt=0, description="deg, the rotation's error after tracking, times a segment's range, in the parallel "
        "choice's relative sigma (0.02: far wall segments refused by their wall made planes of their own, the "
        "small room's board plane ran along its wall again)")
    tracking_choice: bool = Field(
        True, description="the parallel choice in the tracking's pre-association too, as a veto: the nearest "
        "candidate under the loose gates stays where the choice (for walls, its offset prior loosened with the "
        "gates) agrees, else the segment is left out of tracking. Without it the small room's walls pulled the "
        "tracking onto its board (ATE 5.6 mm); the choice itself in tracking lost the demo's higher room's height")
    host_test: bool = Field(
        False, description="the parallel choice's host test: a segment chosen for a wall that can carry a door or "
        "board must also lie within relative_gate x sqrt(own^2 + host_sigma^2 + (host_lever x range)^2) of the wall, "
        "else it is held back (an unmapped door or board, or a segment straddling its edge). Off by default: it took "
        "the small room's confusions from 6.8 % to 0.16 %, but on the demo a board's plane lost its segments to "
        "its wall (largest position error 1.3 -> 21.9 mm) and on the office walk it removed 14 % of them (issue 26)")
    choice_lever_model: bool = Field(
        False, description="the parallel choice judges each segment by what the other segments of its scan say of "
        "the pose error (leave-one-out: a lone segment no longer sets the offset it is judged by), with the "
        "rotation's lever modelled across them in the map's association instead of added to every far segment's "
        "sigma. Off by default (issue 26, session 20): the small room's wall<->door/board confusions 3.38 -> 1.45 %, "
        "but on the demo a board 18 mm proud, now a plane of its own, was merged into its wall by the drift-grown "
        "merge tolerance (1,107 board segments on the wall)")
    hold_past_child_extent: bool = Field(
        False, description="with parallel_choice: a segment that runs past a door's or board's extent (the extent "
        "seen so far) but that the choice puts on the door or board rather than on its wall is held back; off: the "
        "door or board is no candidate for it and the wall takes it (the small room's door segments seen beyond the "
        "door's young extent went to the wall)")
    local_step_reach: float = Field(
        0.0, ge=0, description="m, with parallel_choice: a segment the association gives to a wall is compared with "
        "the wall's other segments of its scan whose ends lie within this distance of its own; one that lies a step "
        "off them (local_step_gate sigmas) while they lie nearer the wall is a door, board or poster face not yet "
        "mapped, or a segment across its edge, and goes to the pool instead, where such segments make the door's "
        "plane (office walk: most wall<->door confusions of single-surface segments happened before the door's "
        "plane existed; with it at 0.5 m the confusions fell 14.5 -> 6.5 % and 15.9 -> 6.9 % on the office seeds, 19.1 -> 1.5 % "
        "on the long wall, 21.8 -> 2.2 % on the demo). Off by default: the hour "
        "with it on was lost at 3,440 s (session 27, README: a corridor's association decays lap after lap); "
        "0 = off")
    local_step_gate: float = Field(3.0, gt=0, description="sigmas of the local step test")
    local_step_sigma: float = Field(
        0.001, gt=0, description="m, what two neighbouring segments of one wall in one scan may differ by beyond "
        "their own lines' sigmas (flatness), in the local step test")
    local_step_lever_deg: float = Field(
        0.02, ge=0, description="deg, the rotation's error in the local step test, times the two segments' "
        "separation")
    host_sigma: float = Field(
        0.0004, gt=0, description="m, what a wall's own segment misses of its distance to the wall once the scan's "
        "offset is removed, in the host test (office walk: 99 % of wall segments within 1.6 mm up to 2.5 m)")
    host_lever_deg: float = Field(0.015, gt=0, description="deg, the rotation's lever (times the range) in the host test")
    choice_sigma_pose: float = Field(
        0.002, gt=0, description="m, prior sigma of a scan's common offset from the map's planes after tracking, in "
        "the parallel choice (times tracking_loosen in the tracking's pre-association): tracking has just fitted "
        "the scan to these planes, so that several segments agreeing on a 2 cm offset from a board's plane are the "
        "wall's, not a 2 cm pose error")
    ambiguity_ratio: float = Field(
        100.0, gt=1, description="least likelihood ratio between two parallel surfaces for a segment to be assigned "
        "(else it is held back)")
    child_merge_distance: float = Field(
        0.004, gt=0, description="m, a door or board tied to its wall merges with it only when nearer than this "
        "over its extent (with parallel_choice)")
    layer_merge_distance: float = Field(
        0.012, ge=0, description="m, a door or board tied to its wall whose extent has grown longer than "
        "child_max_length and lies nearer its wall than this over that extent is a second layer of the wall, not a "
        "door or board: merged with it (an hour's corridor walls were taken over by such layers 8-13 mm in front, "
        "their door edges no longer found, and the walk slid 1 m along the corridor); 0 = off")
    child_max_length: float = Field(
        6.0, gt=0, description="m, extent (along either axis) beyond which a plane tied to its wall is no door or "
        "board for the layer test (layer_merge_distance). 3 m merged boards grown along their walls on the "
        "10-minute office walk, seed 2 (confusions 15.9 -> 29.5 %, ATE 3.1 -> 5.4 mm); at 6 m neither 10-minute "
        "seed merges any (bit for bit as without the test) and the hour's layer still merges (issue 27, session 25)")
    wall_faces: bool = Field(
        True, description="tie a new wall parallel to the other face of its wall (opposite facing, "
        "wall_thickness behind it, overlapping extents): a room's walls and the corridor's are the two faces of "
        "the same partitions, which holds the room's heading to the corridor's across a doorway")
    wall_thickness: tuple[float, float] = Field(
        (0.05, 0.3), description="m, the range of wall thicknesses for wall_faces (min, max)")
    wall_faces_sigma_deg: float = Field(0.02, gt=0, description="sigma of the two faces' parallelism tie (deg)")
    merge_distinct_offset: float = Field(
        0.008, ge=0, description="m: two parallel planes of one facing whose offsets differ by more than this and "
        "that took segments of one scan are two surfaces (a board and its wall seen side by side), merged only "
        "within child_merge_distance however far the walk has gone since (the drift-grown tolerance merged the "
        "demo's whiteboard, 18 mm proud, into its wall after 38 s); 0 = off")
    merge_distance: float = Field(0.008, gt=0, description="m, offset difference of planes merged (plus drift, see merge_drift_over)")
    merge_coobserved_max: float = Field(
        0.15, gt=0, description="m, largest offset difference of two planes merged once they were seen together "
        "(within 0.5 s): their relative offset then carries no drift, and a surface this far before another "
        "(a cabinet's front before its wall) is a surface of its own")
    merge_drift_over: Literal["gap", "since_seen"] = Field(
        "since_seen", description="distance the merge tolerance's drift grows over: walked since the older of the "
        "two planes was last seen (duplicates of a long wall, split by heading drift, keep merging), or only the "
        "gap between their observation spans (0 for a door seen with its wall; office 10 min: 282 mm ATE "
        "against 20 mm)")
    vertical_tolerance_deg: float = Field(5.0, gt=0, description="walls/floors within this of vertical/horizontal get priors")
    link_sigma: float = Field(
        1e-5, gt=0, description="m (offset) and rad (normal), sigma of the equality tie between merged planes until "
        "the final batch folds them into one")

    @model_validator(mode="after")
    def _thickness(self) -> FrontEndConfig:
        lo, hi = self.wall_thickness
        if not 0.0 < lo < hi:
            raise ValueError(f"wall_thickness: expected 0 < min < max, got ({lo}, {hi})")
        return self


class EdgeSection(StrictModel):
    """Door and board edges as observations along walls (``slam.frontend.edges``): the break
    between a wall's segment and its door's (or board's) segment in one scanline lies on the
    door's vertical edge, which the back end holds as a plane perpendicular to the wall."""

    use: bool = Field(True, description="observe door/board edges (the along-corridor direction)")
    point: Literal["bracket", "higher", "midpoint"] = Field(
        "midpoint", description="edge point: the midpoint of the gap between the two segments' boundary points, "
        "between the last and the next beam's crossings of the surface nearer the scanner (bracket), or that "
        "surface's last sample (higher). Office, 10 minutes, SE(3) ATE midpoint / bracket: seed 1 14.1 / 11.5 mm, "
        "seed 2 8.8 / 16.9 mm; registered cloud p95 7.7 / 13.3 and 6.2 / 19.1 mm (docs/bench_slam.md, session 7)")
    max_gap: float = Field(0.08, gt=0, description="m, largest gap between the two segments' boundary points")
    min_incidence_deg: float = Field(
        25.0, ge=0, le=90, description="deg from grazing: flatter beams see the step's shadow, not its edge")
    sigma: float = Field(0.003, gt=0, description="m along the wall, added to the gap's spread (gap / sqrt 12)")
    cluster_width: float = Field(0.02, gt=0, description="m, breaks of a new edge agree within this along the wall")
    min_points: int = Field(4, ge=2, description="breaks a new edge needs")
    min_scans: int = Field(3, ge=1, description="distinct scans among them")
    gate: float = Field(0.04, gt=0, description="m, a break associates with an edge this close along the wall")
    tracking_gate: float = Field(
        0.15, gt=0, description="m, the same for the tracker's pre-association (the predicted pose may be far off "
        "along a corridor); below half a door's width")
    window: float = Field(6.0, gt=0, description="s a break waits for an edge")
    merge_distance: float = Field(0.25, ge=0, description="m, edges of one door side this close are merged")
    link_sigma: float = Field(1e-5, gt=0, description="m and rad, sigma of the equality tie between merged edges")
    min_step: float = Field(0.004, gt=0, description="m, smallest step between a wall and its door or board")
    max_step: float = Field(0.04, gt=0, description="m, largest such step")
    step_tolerance: float = Field(0.005, gt=0, description="m, the step at both ends of the other segment agrees within this")
    max_skipped_points: int = Field(15, ge=0, description="a segment this short between the two (a sloped frame) is skipped")
    min_height_span: float = Field(
        0.15, ge=0, description="m, a new edge's breaks span this in height (vertical edges), unless all come "
        "from nearly horizontal scanlines")
    height_margin: float = Field(
        0.1, ge=0, description="m, a break (unless flat) matches an edge within this of the heights the edge was made from")
    flat_slope: float = Field(
        0.3, ge=0, description="a scanline whose vertical slope across the wall is below this is flat: it can only "
        "cross a vertical edge")
    perpendicular_sigma_deg: float = Field(0.02, gt=0, description="sigma of the edge plane's tie across its wall")
    inline: bool = Field(True, description="also find steps inside wall segments (a poster 5 mm proud is left "
                         "in its wall's segment)")
    inline_window: int = Field(25, ge=5, description="points either side of a split compared for a step inside a segment")
    inline_z: float = Field(5.0, gt=0, description="standard errors a step inside a segment needs")


class BackEndConfig(StrictModel):
    """Factor graph: noise, robust kernel, priors, update cadence."""

    robust: Literal["none", "huber", "cauchy", "geman_mcclure"] = Field(
        "cauchy", description="per-point robust kernel: cauchy is redescending (a segment of a door or board 1-2 cm "
        "off the wall it was associated with stops pulling); huber keeps a constant pull")
    robust_k: float = Field(2.5, gt=0, description="kernel width in sigmas")
    final_robust: Literal["same", "none", "huber", "cauchy", "geman_mcclure"] = Field(
        "same", description="kernel of the final batch (same: robust); geman_mcclure weighs a point far off "
        "~(k/e)^4 instead of Cauchy's (k/e)^2")
    motion_sigma_acc: float = Field(3.0, gt=0, description="m/s^2, constant-velocity prior")
    motion_sigma_angacc: float = Field(10.0, gt=0, description="rad/s^2")
    horizontal_prior_deg: float = Field(0.01, gt=0, description="sigma keeping floors/ceilings horizontal")
    vertical_prior_deg: float = Field(0.05, gt=0, description="sigma keeping walls vertical")
    vertical_walls: bool = True
    datum: Literal["pose", "position_yaw"] = Field(
        "position_yaw", description="prior on the first knot: the whole pose, or its position and heading only (the "
        "horizontal planes' priors level the map)")
    datum_sigma: float = Field(1e-6, gt=0, description="rad and m, sigma of the datum prior")
    datum_tilt_sigma: float = Field(
        0.1, gt=0, description="rad, sigma on the first knot's roll and pitch with position_yaw: loose, yet finite so "
        "that the system stays well conditioned")
    initial_velocity_sigmas: tuple[float, float] = Field(
        (3.0, 3.0), description="rad/s and m/s, the weak prior on the first interval's motion")
    plane_relinearize_factor: float = Field(
        10.0, gt=0, description="iSAM2: relinearisation threshold of planes, a multiple of relinearize_threshold")
    lm_max_iterations: int = Field(50, ge=1, description="Levenberg-Marquardt iterations per stage of a batch solve")
    lm_relative_tolerance: float = Field(1e-4, gt=0, description="a window solve stops below this relative error decrease")
    batch_relative_tolerance: float = Field(
        1e-3, gt=0, description="a solve of the final batch (the first and the one after each trim) stops below this "
        "relative error decrease: 1e-3 ends the 10-minute office walk's first solve after 5 iterations instead of 8 "
        "(1e-4), the trajectory within 0.01 mm of it (docs/speed.md, session 28)")
    robust_schedule: tuple[float, ...] = Field(
        (30.0, 10.0, 3.0), description="kernel-width multipliers of the graduated stages before the nominal one")
    update_every: int = Field(40, ge=1, description="knots between back-end updates (window solves or iSAM2 steps; 40: every 2 s at 20 Hz, docs/speed.md session 22)")
    pipelined: bool | None = Field(
        False, description="experimental (off: on the 10-minute office walk with an IMU it is less accurate and "
        "slower than in process, see docs/speed.md): run the back end in its own forked process, in parallel with the front end, which then "
        "works one update behind it (its estimates arrive one update later; deterministic: the same input gives the "
        "same output). None: on where a process can be forked (not inside a daemon pool worker), off otherwise; "
        "false: the back end in the front end's process")
    pipelined_collect_after: int = Field(
        40, ge=1, description="with pipelined: knots after a step was sent at which the front end takes its result "
        "(waiting for it if need be); the front end then works with estimates this many knots old. update_every or "
        "more: at the next step")
    relinearize_threshold: float = Field(0.005, gt=0, description="iSAM2: relinearise a variable whose update exceeds this")
    relinearize_skip: int = Field(5, ge=1, description="iSAM2: check for relinearisation every n updates")
    isam2_iterations: int = Field(1, ge=1, description="iSAM2 steps per update (more: nearer the optimum, slower)")
    isam2_fallback_iterations: int = Field(
        5, ge=1, description="batch iterations over the whole graph when an iSAM2 step fails even after a rebuild")
    solver: Literal["isam2", "window"] = Field(
        "window", description="incremental estimation: a fixed-lag window solved to convergence, older blocks held "
        "in exact per-plane summaries (cost per solve bounded), or iSAM2 (cost grows with the walk)")
    window_seconds: float = Field(3.0, gt=0, description="s of knots the window solver re-estimates")
    window_iterations: int = Field(4, ge=1, description="Gauss-Newton iterations per window solve")
    final_batch: bool = True
    batch_iterations: int = Field(10, ge=1)
    batch_section_seconds: float = Field(
        300.0, gt=0, description="s: a longer walk's final batch is solved in time-ordered sections of at most this "
        "length, each section's own variables eliminated in turn onto the planes and the cut knots (the same steps "
        "as a whole-graph batch), so that its memory is one section's (slam/backend/sections.py); a shorter walk is "
        "solved whole")
    batch_whole_seconds: float = Field(
        900.0, ge=0, description="s: a walk up to this long has its final batch solved whole all the same (the "
        "sectioned solve costs a third more CPU: 10-minute office walk 71 against 46 s; whole, its memory grows "
        "about 56 MB per data minute, docs/memory.md)")
    batch_cache_mb: float = Field(
        1024.0, ge=0, description="MB a sectioned final batch may keep from one pass over the sections to the "
        "next in memory, all together: first the sections' factors (about 12 kB per knot; those that do not fit "
        "are built again at every pass, slower), then each section's elimination (for the back-substitution; about "
        "11 kB per knot; one that does not fit is written to disk and read back). The batch's memory stops growing "
        "with the walk once this is full (the hour's office walk: 512 MB -> 1024 MB took its final batch from 424 "
        "to 361 s and its peak from 2.83 to 3.37 GB, the same estimate bit for bit)")
    batch_heap_slack_mb: float = Field(
        64.0, ge=0, description="MB: a pass over a sectioned final batch's sections gives malloc's free pages back "
        "to the system (malloc_trim) whenever its resident memory has risen this much since the last time: each "
        "section's linearisation and elimination are freed into malloc's chunks, which the next section splits at "
        "new places, so that the resident memory would climb with the sections while the memory in use does not")
    fold_links: Literal["step", "end"] = Field(
        "step", description="when two planes the front end found to be one surface (a wall walked past again) "
        "become one variable in the back end: 'step' at the next window step (the window then holds one plane "
        "per surface, and its cost does not grow with the times a wall is revisited), 'end' before the final "
        "batch (until then tied by an equality factor). With solver isam2: 'end'")
    final_trim_sigmas: float = Field(
        3.0, ge=0, description="after the final batch, detach the points farther from their plane than this many "
        "sigmas and final_trim_distance, then solve again (0: off)")
    final_trim_distance: float = Field(0.004, ge=0, description="m, see final_trim_sigmas")
    final_trim_iterations: int = Field(4, ge=1, description="iterations of the solve after each trim")
    final_trim_rounds: int = Field(3, ge=1, description="trims, each followed by a solve (a plane that took another "
                                   "surface's segments moves onto its own with each round)")
    final_trim_min_fraction: float = Field(
        0.01, ge=0, le=1, description="a trim after the first that detaches fewer points than this fraction of the "
        "first's ends the trims without solving again (too few to move the estimate; 0: every round solves)")


class ImuSection(StrictModel):
    """Use of the bag's IMU (``sensor_msgs/Imu``, in the body frame): gtsam preintegration
    factors between knots and IMU-predicted knots in the front end. The noise is the IMU's
    datasheet values; the defaults are the simulator's (ADIS16448, EuRoC calibration)."""

    use: Literal["auto", "on", "off"] = Field("auto", description="auto: when the bag has the topic")
    topic: str | None = Field(None, description="IMU topic; None: the rig's (rig.imu.topic)")
    samples: Literal["instantaneous", "held"] = Field(
        "instantaneous", description="how a reading is integrated: taken as the reading at its stamp "
        "(instantaneous: midpoint rule; the simulator writes such readings, and its noise-free IMU dead-reckons "
        "11.6x better this way, scripts/imu_dead_reckoning.py) or held from its stamp to the next one (an IMU "
        "that averages)")
    accel_noise: float = Field(2.0e-3, gt=0, description="accelerometer white noise (m/s^2/sqrt(Hz))")
    gyro_noise: float = Field(1.6968e-4, gt=0, description="gyroscope white noise (rad/s/sqrt(Hz))")
    accel_bias_walk: float = Field(3.0e-3, gt=0, description="accelerometer bias random walk (m/s^3/sqrt(Hz))")
    gyro_bias_walk: float = Field(1.9393e-5, gt=0, description="gyroscope bias random walk (rad/s^2/sqrt(Hz))")
    accel_bias_prior: float = Field(0.05, gt=0, description="sigma of the initial accelerometer bias (m/s^2)")
    gyro_bias_prior: float = Field(0.005, gt=0, description="sigma of the initial gyroscope bias (rad/s)")
    gravity: float = Field(9.80665, gt=0, description="m/s^2")
    integration_sigma: float = Field(
        2e-3, gt=0,
        description="position integration noise (m/sqrt(s)): the knots' linear interpolation misses ~0.5 mm of the gait bob")
    velocity_prior_sigma: float = Field(1.0, gt=0, description="m/s, sigma of the prior on the first knot's velocity")
    motion_prior: bool = Field(False, description="keep the constant-velocity prior beside the IMU factors")
    increment_sigma_deg: float = Field(
        0.05, gt=0, description="deg, tracking with an IMU: the rotation of one knot interval against the IMU-predicted one")
    increment_sigma_position: float = Field(0.001, gt=0, description="m, the same for the translation")
    degenerate_angle_deg: float = Field(
        3.0, gt=0, description="deg, tracking with an IMU: a translation direction observed only by planes within this "
        "of parallel to it is left to the IMU")
    zupt: bool = Field(True, description="zero-velocity updates where the IMU says the operator stands still")
    zupt_window: float = Field(0.5, gt=0, description="s of samples the stance test looks at")
    zupt_threshold: float = Field(8.0, gt=0, description="stance test threshold (6 +- 0.35 at rest over 0.5 s at 200 Hz)")
    zupt_sigma: float = Field(0.005, gt=0, description="m/s, sigma of a zero-velocity update")


class NoiseSection(StrictModel):
    """Each scanner's range noise, and the values that follow it.

    The rule: every noise-dependent value of this configuration (``NOISE_SCALED`` in
    ``slam.params``: the front end's point_sigma, coplanar_distance, merge_distance and
    max_endpoint_distance, the edges' sigma, min_step, step_tolerance and cluster_width, the
    back end's final_trim_distance, the outlines' extent_gate and extent_rms, and the segmenter's thresholds) is
    stated as written for ``reference`` noise. A scanner's noise is ``scanners[name]`` when given (fixed), else estimated
    from its first ``estimate_scans`` scans (``estimate``; ``segmentation.noise``: the effective
    range noise at the samples' median range), else its rig model's ``range_sigma``. A scanner up
    to ``scale_above`` times as noisy as the reference (or quieter) keeps the values as written;
    a noisier one scales its segmenter's thresholds and its points' sigmas by its noise over the
    reference, and the run's shared values by the largest such ratio of its scanners."""

    estimate: bool = Field(True, description="estimate the noise of the scanners not in 'scanners' from the recording")
    scanners: dict[str, float] = Field(
        default_factory=dict, description="m, range noise per scanner name: fixed, not estimated (the run driver "
        "writes its estimates here, so summary.json's config holds the values used)")
    reference: float = Field(0.003, gt=0, description="m, the range noise the noise-dependent values are stated for")
    scale_above: float = Field(
        1.25, ge=1, description="noise up to this many times the reference keeps the values as written (an estimate "
        "scatters by a few per cent; the values were tuned at the reference, and below it other errors dominate)")
    estimate_scans: int = Field(40, ge=1, description="scans per scanner the estimate looks at (the first ones)")

    @model_validator(mode="after")
    def _positive(self) -> NoiseSection:
        for name, sigma in self.scanners.items():
            if not sigma > 0:
                raise ValueError(f"scanners.{name}: range noise must be > 0 m, got {sigma}")
        return self


class InputSection(StrictModel):
    """How the recording's messages are read."""

    echo: Literal["first", "last", "strongest"] = Field(
        "first", description="the return of each beam of a sensor_msgs/MultiEchoLaserScan: its first echo, its "
        "last, or the strongest (by the echoes' intensities; the first where a beam has none); the chosen echo's "
        "intensity goes into the cloud. LaserScan topics have one return per beam")


class OutputConfig(StrictModel):
    cloud: bool = True
    voxel: float = Field(0.0, ge=0, description="voxel size of cloud.ply (m), 0 = every point")
    rerun: bool = True
    rerun_scan_every: int = Field(8, ge=1, description="log every n-th scan in map.rrd")
    # the planes' outlines in planes.json and map.rrd from the final map (slam.plane_extents), when
    # the cloud pass runs (cloud or rerun on); else the front end's outlines
    extent_cell: float = Field(0.05, gt=0, description="m, the square the planes' outlines are rasterised in")
    extent_min_segments: int = Field(
        3, ge=1, description="segments of a plane that must cross a square for it to be part of the plane's outline")
    extent_gate: float = Field(
        0.009, gt=0, description="m, how far a segment's end points may lie off its plane's final estimate and still "
        "count for the plane's outline (noise-scaled)")
    extent_gap: float = Field(
        0.25, ge=0, description="m, the widest empty space within one region of a plane's outline (planes.json lists "
        "each plane's regions: a wall's pieces between doorways, two doors at one depth)")
    extent_rms: float = Field(
        0.006, gt=0, description="m, the largest RMS distance of a segment's points to its plane's final estimate for "
        "the segment to count for the plane's outline (noise-scaled: a segment run across a door's edge onto its wall "
        "does not count)")


class ParallelSection(StrictModel):
    """Use of the machine's other cores; the results are the same bit for bit either way."""

    reader: bool = Field(True, description="read and segment the scans in a second process, ahead of the estimator")
    export_processes: int = Field(2, ge=1, le=64, description="processes that place and write the cloud's points")


class SlamConfig(StrictModel):
    input: InputSection = Field(default_factory=InputSection)
    segmenter: SegmenterConfig = Field(default_factory=SegmenterConfig)
    trajectory: TrajectoryConfig = Field(default_factory=TrajectoryConfig)
    frontend: FrontEndConfig = Field(default_factory=FrontEndConfig)
    edges: EdgeSection = Field(default_factory=EdgeSection)
    backend: BackEndConfig = Field(default_factory=BackEndConfig)
    imu: ImuSection = Field(default_factory=ImuSection)
    output: OutputConfig = Field(default_factory=OutputConfig)
    parallel: ParallelSection = Field(default_factory=ParallelSection)
    health: HealthSection = Field(default_factory=HealthSection)
    noise: NoiseSection = Field(default_factory=NoiseSection)


def load_slam_config(path: str | Path | None) -> SlamConfig:
    """Load a SLAM config file, or the defaults when ``path`` is None."""
    if path is None:
        return SlamConfig()
    return load(SlamConfig, path)


def with_segmenter(cfg: SlamConfig, method: str | None, params: dict[str, Any]) -> SlamConfig:
    """Override the segmenter from the command line (``--segmenter``, ``--param k=v``)."""
    if method is None and not params:
        return cfg
    seg = cfg.segmenter
    new_method = method or seg.method
    base = dict(SLAM_SEGMENTER_DEFAULTS.get(new_method, {})) if new_method != seg.method else dict(seg.params)
    try:
        return cfg.model_copy(update={"segmenter": SegmenterConfig(method=new_method, params=base | params)})
    except ValueError as e:
        raise ConfigError(f"--segmenter/--param: {e}") from None
