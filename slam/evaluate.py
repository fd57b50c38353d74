"""Evaluation of a SLAM run against the simulator's ground truth (world frame, metres).

Metrics (each defined where it is computed):

- ATE (evo APE, translation part) of the estimated ``T_world_body`` against the ground truth
  interpolated (rotation geodesic, position linear) at the estimate's times, three ways:
  ``unaligned`` (as written: the run's world frame taken as the ground truth's),
  ``start_aligned`` (the estimate moved rigidly so that its first pose is the true first pose:
  the SLAM's datum is the start pose, so this is the error accumulated since the start) and
  ``se3_aligned`` (evo's least-squares SE(3) alignment, the usual ATE).
- RPE (evo, all pairs, pairs chosen by the ground truth's path length) over 1 m and 10 m:
  translation (m) and rotation (deg) of the relative-pose error.
- Drift per 100 m: ``endpoint`` = start-aligned position error at the last pose divided by the
  path length, times 100 (m per 100 m, i.e. %); ``rpe`` = mean 10 m translational RPE scaled to
  100 m (%); ``rotation`` = mean 10 m rotational RPE scaled to 100 m (deg per 100 m).
- Planes (after the map alignment, ``start`` by default): each estimated plane is matched to a
  true plane by the per-beam ground truth of its segments (majority vote) when ``segments.npz``
  and ``beams.npz`` allow, otherwise geometrically (normal angle, offset, extent overlap).
  Angle error = angle between the normals (deg, sign-free); offset error = signed distance of
  the estimated patch's centre to the true plane (m).
- Cloud: unsigned distance of each (aligned) cloud point to the true mesh
  (open3d ``RaycastingScene.compute_distance``), for every k-th point (at most
  ``max_cloud_points``); cloud.ply is read a chunk at a time and only those points are kept.
- Association: a segment's true plane is the majority of its beams' true plane ids; an
  estimated plane's true plane is the majority over its segments; a segment is correct when
  it is associated and both agree.
"""

from __future__ import annotations

import copy
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from common.atomic import OutputFileError, read_json, write_json
from slam.beam_rows import BeamRows, NpzRows, as_rows
from slam.export import (
    CloudRecord,
    PlaneRecord,
    SegmentTable,
    cloud_ply_layout,
    read_cloud_ply,
    read_planes_json,
    read_segments_npz,
    read_trajectory_tum,
)
from slam.frontend.planemap import plane_basis
from slam.plane_extents import rectangle, union_box
from slam.trajectory.interpolation import interpolate_trajectory

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
Alignment = Literal["start", "se3", "none"]


WELL_DETERMINED_SIGMA_DEG = 0.05  # a plane reported to within this (1 sigma) counts as well determined


class EvaluationError(ValueError):
    """Inputs that cannot be evaluated together; the message names the file."""


# ------------------------------------------------------------------------------ statistics


@dataclass(frozen=True)
class Stats:
    """Summary of a set of non-negative errors."""

    n: int
    rmse: float
    mean: float
    median: float
    p95: float
    max: float

    @staticmethod
    def of(values: ArrayLikeF) -> Stats:
        x = np.asarray(values, dtype=np.float64).ravel()
        x = x[np.isfinite(x)]
        if x.size == 0:
            nan = float("nan")
            return Stats(0, nan, nan, nan, nan, nan)
        return Stats(
            n=int(x.size),
            rmse=float(np.sqrt(np.mean(x**2))),
            mean=float(np.mean(x)),
            median=float(np.median(x)),
            p95=float(np.percentile(x, 95)),
            max=float(np.max(x)),
        )

    def to_json(self) -> dict[str, float | int]:
        return {k: getattr(self, k) for k in ("n", "rmse", "mean", "median", "p95", "max")}


ArrayLikeF = FloatArray | Sequence[float]


# ------------------------------------------------------------------------------ trajectory


@dataclass(frozen=True)
class TrajectoryEval:
    """Per-pose errors (for plots) and their statistics; positions in the ground-truth world."""

    times: FloatArray
    distance: FloatArray  # distance walked along the ground truth at each pose (m)
    gt_xyz: FloatArray
    est_xyz: FloatArray  # as written
    est_xyz_start: FloatArray  # start-aligned
    est_xyz_se3: FloatArray  # SE(3)-aligned
    err_unaligned: FloatArray
    err_start: FloatArray
    err_se3: FloatArray
    T_align_start: FloatArray  # maps the run's world into the ground truth's
    T_align_se3: FloatArray
    rpe_1m: Stats | None
    rpe_10m: Stats | None
    rpe_rot_1m_deg: Stats | None
    rpe_rot_10m_deg: Stats | None
    n_dropped: int  # estimated poses outside the ground truth's time span
    se3_alignment_ok: bool = True  # False: degenerate (straight) path, start alignment used

    @property
    def path_length(self) -> float:
        return float(self.distance[-1]) if self.distance.size else 0.0

    @property
    def ate(self) -> dict[str, Stats]:
        return {
            "unaligned": Stats.of(self.err_unaligned),
            "start_aligned": Stats.of(self.err_start),
            "se3_aligned": Stats.of(self.err_se3),
        }

    @property
    def drift_endpoint_per_100m(self) -> float:
        """Start-aligned position error at the last pose per 100 m walked (m/100 m = %)."""
        if self.path_length <= 0:
            return float("nan")
        return float(self.err_start[-1] / self.path_length * 100.0)

    @property
    def drift_rpe_per_100m(self) -> float:
        """Mean translational RPE over 10 m, as a percentage (m per 100 m)."""
        return float(self.rpe_10m.mean * 10.0) if self.rpe_10m and self.rpe_10m.n else float("nan")

    @property
    def rot_drift_deg_per_100m(self) -> float:
        """Mean rotational RPE over 10 m scaled to 100 m (deg per 100 m)."""
        r = self.rpe_rot_10m_deg
        return float(r.mean * 10.0) if r and r.n else float("nan")

    def to_json(self) -> dict[str, Any]:
        def opt(s: Stats | None) -> dict[str, float | int] | None:
            return s.to_json() if s is not None else None

        return {
            "n_poses": int(self.times.size),
            "n_dropped_outside_ground_truth": self.n_dropped,
            "path_length_m": self.path_length,
            "ate_m": {k: v.to_json() for k, v in self.ate.items()},
            "rpe_1m": {"translation_m": opt(self.rpe_1m), "rotation_deg": opt(self.rpe_rot_1m_deg)},
            "rpe_10m": {
                "translation_m": opt(self.rpe_10m),
                "rotation_deg": opt(self.rpe_rot_10m_deg),
            },
            "drift_per_100m": {
                "endpoint_percent": self.drift_endpoint_per_100m,
                "rpe_percent": self.drift_rpe_per_100m,
                "rotation_deg": self.rot_drift_deg_per_100m,
            },
            "T_align_start": self.T_align_start.tolist(),
            "T_align_se3": self.T_align_se3.tolist(),
            "se3_alignment_ok": self.se3_alignment_ok,
        }


def _evo_traj(times: FloatArray, T: FloatArray) -> Any:
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(T), timestamps=times)


def _rpe(ref: Any, est: Any, delta: float, rotation: bool) -> Stats | None:
    from evo.core import metrics
    from evo.core.filters import FilterException
    from evo.core.units import Unit

    relation = (
        metrics.PoseRelation.rotation_angle_deg
        if rotation
        else metrics.PoseRelation.translation_part
    )
    # Pairs whose path length is within tol of delta count; evo's default (10 %) lets pairs
    # near the end of the walk be up to 10 % short, which biases drift figures. 2 % (or a bit
    # more than half the pose spacing, for sparse estimates) keeps them honest.
    steps = np.linalg.norm(np.diff(ref.positions_xyz, axis=0), axis=1)
    tol = max(0.02, 0.6 * float(np.median(steps)) / delta) if steps.size else 0.02
    rpe = metrics.RPE(
        relation,
        delta=delta,
        delta_unit=Unit.meters,
        rel_delta_tol=tol,
        all_pairs=True,
        pairs_from_reference=True,
    )
    try:
        rpe.process_data((ref, est))
    except (metrics.MetricsException, FilterException):
        return None  # walk shorter than delta
    return Stats.of(rpe.error) if len(rpe.error) else None


def trajectory_errors(
    t_est: FloatArray, T_est: FloatArray, t_gt: FloatArray, T_gt: FloatArray
) -> TrajectoryEval:
    """Compare ``T_world_body`` estimates with the ground truth (interpolated at their times)."""
    from evo.core import metrics
    from evo.core.geometry import GeometryException

    inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    if np.count_nonzero(inside) < 2:
        raise EvaluationError("fewer than 2 estimated poses within the ground truth's time span")
    t = t_est[inside]
    T_ref = interpolate_trajectory(t_gt, T_gt, t)
    ref = _evo_traj(t, T_ref)
    est = _evo_traj(t, T_est[inside])

    def ape(e: Any) -> FloatArray:
        m = metrics.APE(metrics.PoseRelation.translation_part)
        m.process_data((ref, e))
        return np.asarray(m.error, dtype=np.float64)

    est_start = copy.deepcopy(est)
    T_start = np.asarray(est_start.align_origin(ref), dtype=np.float64)
    est_se3 = copy.deepcopy(est)
    try:
        r, tr, _ = est_se3.align(ref, correct_scale=False)
        T_se3 = np.eye(4)
        T_se3[:3, :3], T_se3[:3, 3] = r, tr
        se3_ok = True
    except GeometryException:
        # a straight-line path leaves the rotation about it unobservable: fall back to the datum
        est_se3, T_se3, se3_ok = est_start, T_start, False

    gt_xyz = np.asarray(ref.positions_xyz)
    steps = np.linalg.norm(np.diff(gt_xyz, axis=0), axis=1)
    return TrajectoryEval(
        times=t,
        distance=np.concatenate([[0.0], np.cumsum(steps)]),
        gt_xyz=gt_xyz,
        est_xyz=np.asarray(est.positions_xyz),
        est_xyz_start=np.asarray(est_start.positions_xyz),
        est_xyz_se3=np.asarray(est_se3.positions_xyz),
        err_unaligned=ape(est),
        err_start=ape(est_start),
        err_se3=ape(est_se3),
        T_align_start=T_start,
        T_align_se3=T_se3,
        rpe_1m=_rpe(ref, est, 1.0, rotation=False),
        rpe_10m=_rpe(ref, est, 10.0, rotation=False),
        rpe_rot_1m_deg=_rpe(ref, est, 1.0, rotation=True),
        rpe_rot_10m_deg=_rpe(ref, est, 10.0, rotation=True),
        n_dropped=int(np.count_nonzero(~inside)),
        se3_alignment_ok=se3_ok,
    )


# ---------------------------------------------------------------------------- transforms


def transform_points(T: FloatArray, points: FloatArray) -> FloatArray:
    """Points (N,3) mapped by the 4x4 transform ``T``."""
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def transform_plane(T: FloatArray, plane: PlaneRecord) -> PlaneRecord:
    """The plane (and its polygon) expressed in the frame ``T`` maps into."""
    n = T[:3, :3] @ plane.normal
    d = float(plane.d - n @ T[:3, 3])
    poly = transform_points(T, plane.polygon) if plane.polygon.size else plane.polygon
    regions = tuple(transform_points(T, r) for r in plane.regions)
    return PlaneRecord(plane.id, n, d, poly, plane.kind, plane.n_segments, plane.covariance, plane.outline, regions)


# ---------------------------------------------------------------------------- majorities


def majority(groups: IntArray, values: IntArray, n_groups: int) -> tuple[IntArray, IntArray]:
    """Most frequent non-negative value per group (ties: smallest value) and its count.

    Groups without any non-negative value get -1 and count 0.
    """
    g = np.asarray(groups, dtype=np.int64)
    v = np.asarray(values, dtype=np.int64)
    winner = np.full(n_groups, -1, dtype=np.int64)
    count = np.zeros(n_groups, dtype=np.int64)
    ok = v >= 0
    g, v = g[ok], v[ok]
    if g.size == 0:
        return winner, count
    base = int(v.max()) + 1
    keys, cnt = np.unique(g * base + v, return_counts=True)
    kg, kv = keys // base, keys % base
    order = np.lexsort((kv, -cnt, kg))
    first = np.ones(order.size, dtype=bool)
    first[1:] = kg[order[1:]] != kg[order[:-1]]
    pick = order[first]
    winner[kg[pick]] = kv[pick]
    count[kg[pick]] = cnt[pick]
    return winner, count


def segment_true_planes(
    segments: SegmentTable,
    beam_plane_ids: Mapping[str, NDArray[np.integer] | BeamRows],
    beam_stamps: Mapping[str, FloatArray] | None = None,
    chunk_beams: int = 4_000_000,
    stamp_tolerance: float = 1e-4,
) -> tuple[IntArray, FloatArray]:
    """True plane of each segment (majority of its beams' ids, -1 if none) and its purity.

    ``beam_plane_ids[name]`` is (n_scans, n_beams) per scanner (-1 = no plane): an array, or
    ``BeamRows`` read a block of about ``chunk_beams`` beams (whole scans) at a time in
    increasing scan order (``GroundTruth.beam_rows``: an hour's walk is not held at once).
    Purity is the fraction of the segment's beams carrying the winning id. When ``beam_stamps``
    is given, each segment's stamp must match its scan's first-beam time.
    """
    n = len(segments)
    true = np.full(n, -1, dtype=np.int64)
    purity = np.zeros(n, dtype=np.float64)
    for s, name in enumerate(segments.scanner_names):
        rows = np.flatnonzero(segments.scanner == s)
        if rows.size == 0:
            continue
        if name not in beam_plane_ids:
            raise EvaluationError(f"beams.npz: no ground truth for scanner '{name}'")
        ids = as_rows(beam_plane_ids[name])
        n_scans, n_beams = ids.shape
        rows = rows[np.argsort(segments.scan_index[rows], kind="stable")]
        scan = segments.scan_index[rows].astype(np.int64)
        first = segments.first_beam[rows].astype(np.int64)
        last = segments.last_beam[rows].astype(np.int64)
        if scan.min() < 0 or scan.max() >= n_scans or last.max() >= n_beams:
            raise EvaluationError(
                f"segments.npz: scanner '{name}' scan/beam indices exceed beams.npz "
                f"({n_scans} scans x {n_beams} beams)"
            )
        if beam_stamps is not None and name in beam_stamps:
            bad = np.abs(segments.stamp[rows] - beam_stamps[name][scan]) > stamp_tolerance
            if np.any(bad):
                raise EvaluationError(
                    f"segments.npz: {np.count_nonzero(bad)} segment(s) of scanner '{name}' "
                    "have stamps that disagree with beams.npz for their scan_index"
                )
        lengths = last - first + 1
        # blocks of whole scans, about chunk_beams beams each, keep the rows read and the flat
        # index arrays bounded
        per_block = max(1, chunk_beams // max(1, n_beams))
        starts = np.arange(int(scan[0]), int(scan[-1]) + 1, per_block)
        bounds = np.searchsorted(scan, starts[1:])
        for lo, part in zip(starts, np.split(np.arange(rows.size), bounds), strict=True):
            if part.size == 0:
                continue
            block = ids.rows(int(lo), int(scan[part[-1]]) + 1)
            L = lengths[part]
            local = np.repeat(np.arange(part.size), L)
            offsets = np.arange(L.sum()) - np.repeat(np.cumsum(L) - L, L)
            vals = block[np.repeat(scan[part] - lo, L), np.repeat(first[part], L) + offsets]
            w, c = majority(local, vals, part.size)
            true[rows[part]] = w
            purity[rows[part]] = c / L
    return true, purity


# ---------------------------------------------------------------------------- association


@dataclass(frozen=True)
class AssociationEval:
    """Segment-to-plane association against the per-beam ground truth.

    ``fraction_correct``: segments associated with an estimated plane whose true plane is the
    segment's own, over all segments; ``fraction_associated``: segments with any plane;
    ``fraction_correct_of_associated``: correct over associated.
    """

    n_segments: int
    n_associated: int
    n_correct: int
    n_without_truth: int
    segment_true: IntArray
    segment_purity: FloatArray
    plane_true: dict[int, int]  # estimated plane id -> true plane id (majority of segments)
    plane_support: dict[int, float]  # fraction of the plane's segments voting for it
    # segments on an estimated plane whose surface (coplanar true planes as one) is theirs; None: not asked
    n_correct_surface: int | None = None
    # per true plane kind group (``kind_group``): associated segments of that kind, and of those
    # the ones on an estimated plane whose true plane (surface, with ``surfaces``) is the segment's own
    by_kind: dict[str, tuple[int, int]] = field(default_factory=dict)
    # wall segments on a door's or board's estimated plane, and door or board segments on a wall's
    confusions_wall_to_child: int = 0
    confusions_child_to_wall: int = 0
    # the same over the segments that lie on one surface (purity >= ``PURE``): a segment the
    # segmenter ran across a door's or board's edge is on neither face, whichever plane it takes
    n_child_associated_pure: int = 0
    confusions_pure: int = 0

    @property
    def confusion_fraction_pure(self) -> float:
        """Wall<->door/board confusions over the associated door and board segments, both counted
        among the single-surface segments only (purity >= ``PURE``)."""
        n = self.n_child_associated_pure
        return self.confusions_pure / n if n else float("nan")

    @property
    def fraction_correct_surface_of_associated(self) -> float:
        """Like ``fraction_correct_of_associated``, with coplanar true planes taken as one surface."""
        if self.n_correct_surface is None or not self.n_associated:
            return float("nan")
        return self.n_correct_surface / self.n_associated

    @property
    def n_child_associated(self) -> int:
        """Associated segments whose true plane is a door or a board."""
        return sum(self.by_kind.get(k, (0, 0))[0] for k in CHILD_GROUPS)

    @property
    def confusion_fraction(self) -> float:
        """Wall<->door/board confusions over the associated door and board segments."""
        n = self.n_child_associated
        return (self.confusions_wall_to_child + self.confusions_child_to_wall) / n if n else float("nan")

    @property
    def fraction_associated(self) -> float:
        return self.n_associated / self.n_segments if self.n_segments else float("nan")

    @property
    def fraction_correct(self) -> float:
        return self.n_correct / self.n_segments if self.n_segments else float("nan")

    @property
    def fraction_correct_of_associated(self) -> float:
        return self.n_correct / self.n_associated if self.n_associated else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {
            "n_segments": self.n_segments,
            "n_associated": self.n_associated,
            "n_correct": self.n_correct,
            "n_segments_without_truth": self.n_without_truth,
            "fraction_associated": self.fraction_associated,
            "fraction_correct": self.fraction_correct,
            "fraction_correct_of_associated": self.fraction_correct_of_associated,
            "fraction_correct_surface_of_associated": self.fraction_correct_surface_of_associated
            if self.n_correct_surface is not None else None,
            "segment_purity_median": float(np.median(self.segment_purity))
            if self.segment_purity.size
            else None,
            "by_kind": {
                k: {"n_associated": n, "n_correct": c, "fraction_correct_of_associated": c / n if n else None}
                for k, (n, c) in self.by_kind.items()
            },
            "confusions": {
                "definition": "wall segments on an estimated plane whose true plane is a door or board, and "
                "door or board segments on one whose true plane is a wall; fraction over the associated "
                "door and board segments",
                "wall_to_child": self.confusions_wall_to_child,
                "child_to_wall": self.confusions_child_to_wall,
                "fraction_of_child_segments": self.confusion_fraction if self.n_child_associated else None,
                "single_surface": {
                    "definition": f"the same over the segments with purity >= {PURE} (not run across an edge)",
                    "confusions": self.confusions_pure,
                    "n_child_associated": self.n_child_associated_pure,
                    "fraction_of_child_segments": self.confusion_fraction_pure
                    if self.n_child_associated_pure else None,
                },
            },
        }


KIND_GROUPS = ("wall", "floor/ceiling", "door", "board", "other")
PURE = 0.9  # a segment with at least this share of its beams on its true plane lies on one surface
CHILD_GROUPS = ("door", "board")


def kind_group(kind: str) -> str:
    """The group of a true plane's kind (``simulation`` names): wall, floor/ceiling, door (the
    leaf), board (whiteboard, poster, pinboard faces), other (frames, edges, furniture, ...)."""
    if kind == "wall":
        return "wall"
    if kind in ("floor", "ceiling"):
        return "floor/ceiling"
    if kind == "door":
        return "door"
    if kind == "board":
        return "board"
    return "other"


def coplanar_surfaces(planes: Sequence[PlaneRecord], max_angle_deg: float = 0.05,
                      max_offset: float = 0.002) -> dict[int, int]:
    """True plane id -> the smallest id of the true planes of the same kind that lie in one plane
    with it (normals within ``max_angle_deg``, same facing, offsets within ``max_offset`` m):
    the pieces of one wall between its openings, the same wall of two rooms in a row, the
    ceiling of a room and of the corridor beside it. One map plane for them is the right map."""
    out = {int(p.id): int(p.id) for p in planes}
    cos_min = float(np.cos(np.radians(max_angle_deg)))
    ordered = sorted(planes, key=lambda q: int(q.id))
    for i, a in enumerate(ordered):
        for b in ordered[:i]:
            if (a.kind == b.kind and float(a.normal @ b.normal) > cos_min and abs(a.d - b.d) < max_offset):
                out[int(a.id)] = out[int(b.id)]
                break
    return out


def association_errors(
    segments: SegmentTable, segment_true: IntArray, segment_purity: FloatArray,
    true_kinds: Mapping[int, str] | None = None, surfaces: Mapping[int, int] | None = None,
) -> AssociationEval:
    """Score each segment's plane against its true plane (see :class:`AssociationEval`);
    ``true_kinds`` (true plane id -> kind) adds the figures per kind group and the confusions,
    ``surfaces`` (true plane id -> its surface, :func:`coplanar_surfaces`) the share of
    segments on the right surface (pieces of one plane taken as one)."""
    pid = segments.plane_id.astype(np.int64)
    assoc = pid >= 0
    plane_ids = np.unique(pid[assoc])
    # majority over each estimated plane's segments of the segments' true planes
    group = np.searchsorted(plane_ids, pid[assoc])
    w, c = majority(group, segment_true[assoc], plane_ids.size)
    n_voting = np.bincount(group, minlength=plane_ids.size)
    plane_true = {int(p): int(t) for p, t in zip(plane_ids, w, strict=True)}
    support = {
        int(p): float(k / m) if m else 0.0 for p, k, m in zip(plane_ids, c, n_voting, strict=True)
    }
    est_true = np.full(pid.shape, -1, dtype=np.int64)
    est_true[assoc] = w[group]
    correct = assoc & (segment_true >= 0) & (est_true == segment_true)
    n_surface = None
    if surfaces is not None:
        # the same majority vote with each segment's true plane taken as its surface
        surf = np.array([surfaces.get(int(t), int(t)) if t >= 0 else -1 for t in segment_true.tolist()], dtype=np.int64)
        ws, _ = majority(group, surf[assoc], plane_ids.size)
        est_surf = np.full(pid.shape, -1, dtype=np.int64)
        est_surf[assoc] = ws[group]
        correct = assoc & (surf >= 0) & (est_surf == surf)
        n_surface = int(np.count_nonzero(correct))
    by_kind: dict[str, tuple[int, int]] = {}
    w2c = c2w = n_child_pure = conf_pure = 0
    if true_kinds is not None:
        def groups(t: IntArray) -> NDArray[np.str_]:
            return np.array([kind_group(true_kinds.get(int(x), "")) if x >= 0 else "" for x in t.tolist()], dtype=object)

        g_seg = groups(segment_true)
        g_est = groups(est_true)
        for k in KIND_GROUPS:
            m = assoc & (g_seg == k)
            by_kind[k] = (int(np.count_nonzero(m)), int(np.count_nonzero(m & correct)))
        child_seg = np.isin(g_seg, CHILD_GROUPS)
        child_est = np.isin(g_est, CHILD_GROUPS)
        w2c_m = assoc & (g_seg == "wall") & child_est
        c2w_m = assoc & child_seg & (g_est == "wall")
        w2c = int(np.count_nonzero(w2c_m))
        c2w = int(np.count_nonzero(c2w_m))
        pure = segment_purity >= PURE
        n_child_pure = int(np.count_nonzero(assoc & child_seg & pure))
        conf_pure = int(np.count_nonzero((w2c_m | c2w_m) & pure))
    return AssociationEval(
        n_segments=len(segments),
        n_associated=int(np.count_nonzero(assoc)),
        n_correct=int(np.count_nonzero(assoc & (segment_true >= 0) & (est_true == segment_true))),
        n_correct_surface=n_surface,
        n_without_truth=int(np.count_nonzero(segment_true < 0)),
        segment_true=segment_true,
        segment_purity=segment_purity,
        plane_true=plane_true,
        plane_support=support,
        by_kind=by_kind,
        confusions_wall_to_child=w2c,
        confusions_child_to_wall=c2w,
        n_child_associated_pure=n_child_pure,
        confusions_pure=conf_pure,
    )


# ---------------------------------------------------------------------------------- planes


def inside_polygon_2d(
    points: FloatArray, polygon: FloatArray, margin: float = 0.0
) -> NDArray[np.bool_]:
    """Points (N,2) inside the polygon (k,2) (even-odd rule) or within ``margin`` of its edges."""
    p = np.asarray(points, dtype=np.float64)[:, None, :]
    a = polygon[None, :, :]
    b = np.roll(polygon, -1, axis=0)[None, :, :]
    crosses = (a[..., 1] > p[..., 1]) != (b[..., 1] > p[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[..., 0] + (p[..., 1] - a[..., 1]) * (b[..., 0] - a[..., 0]) / (
            b[..., 1] - a[..., 1]
        )
    inside = np.count_nonzero(crosses & (p[..., 0] < x_at), axis=1) % 2 == 1
    if margin > 0:
        ab = b - a
        tt = np.clip(
            np.sum((p - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-300), 0, 1
        )
        dist = np.linalg.norm(p - (a + tt[..., None] * ab), axis=-1).min(axis=1)
        inside |= dist <= margin
    return inside


def _centre(plane: PlaneRecord, fallback: FloatArray | None = None) -> FloatArray:
    """A point of the plane's extent: its polygon's vertex mean, else a projected fallback."""
    if plane.polygon.shape[0] >= 3:
        c = plane.polygon.mean(axis=0)
    elif fallback is not None:
        c = fallback
    else:
        c = -plane.d * plane.normal
    return c - (plane.normal @ c + plane.d) * plane.normal  # onto the plane


def match_planes_geometric(
    estimated: Sequence[PlaneRecord],
    true: Sequence[PlaneRecord],
    max_angle_deg: float = 5.0,
    max_offset: float = 0.1,
    margin: float = 0.25,
) -> dict[int, int]:
    """Match each estimated plane (ground-truth frame) to the nearest compatible true plane.

    Compatible: normals within ``max_angle_deg`` (sign-free), the estimated patch centre within
    ``max_offset`` of the true plane and at least half of the patch's vertices and centre,
    projected onto it, inside the true polygon grown by ``margin``. Among compatible planes
    the smallest |offset| wins, so that a board 1-2 cm proud of its wall matches the board;
    on a tie, the one whose normal has the same sign.
    """
    out: dict[int, int] = {}
    cos_max = np.cos(np.radians(max_angle_deg))
    for e in estimated:
        best: tuple[float, int] | None = None
        for t in true:
            if abs(float(e.normal @ t.normal)) < cos_max:
                continue
            c = _centre(e, fallback=_centre(t) if t.polygon.shape[0] >= 3 else None)
            off = float(t.normal @ c + t.d)
            if abs(off) > max_offset:
                continue
            if t.polygon.shape[0] >= 3:
                # the patch's vertices and centre, projected onto the true plane: at least half
                # must fall in the grown true polygon (a concave wall with a door cut out may
                # hold the centre in its hole)
                B = np.stack(plane_basis(t.normal))
                pts = np.vstack([e.polygon, c]) if e.polygon.shape[0] >= 3 else c[None]
                if np.mean(inside_polygon_2d(pts @ B.T, t.polygon @ B.T, margin)) < 0.5:
                    continue
            # between equally near planes (a cupboard's back against a wall) prefer the one
            # facing the same way
            score = abs(off) + (1e-4 if float(e.normal @ t.normal) < 0 else 0.0)
            if best is None or score < best[0]:
                best = (score, t.id)
        if best is not None:
            out[int(e.id)] = best[1]
    return out


@dataclass(frozen=True)
class PlaneMatch:
    est_id: int
    true_id: int
    kind: str  # the true plane's kind
    angle_deg: float
    offset_m: float  # signed distance of the estimated patch centre to the true plane
    matched_by: str  # "beams" or "geometry"
    support: float  # beams: fraction of the plane's segments voting for the true plane
    sigma_angle_deg: float = float("nan")  # the run's own 1-sigma of the normal (planes.json covariance), larger axis
    # doors and boards: the extent's error against the true face (``extent_errors``; of the
    # outline's regions on the face when the plane has regions, ``face_region``), NaN otherwise;
    # of the whole outline; the outline's regions
    extent_error_m: float = float("nan")
    extent_excess_m: float = float("nan")
    extent_whole_error_m: float = float("nan")
    extent_regions: int = 0


def extent_errors(estimated: FloatArray, true: FloatArray, normal: FloatArray) -> tuple[float, float]:
    """How far an estimated plane's extent (its polygon (k, 3), ground-truth frame) is from the
    true face's (polygon (m, 3)), both projected onto the true plane's (u horizontal, v) axes:
    the largest distance between corresponding edges of the two bounding rectangles (m), and
    by how much the estimated rectangle is longer or taller than the face (m, >= 0)."""
    B = np.stack(plane_basis(np.asarray(normal, dtype=np.float64)))
    e, t = estimated @ B.T, true @ B.T
    e_lo, e_hi, t_lo, t_hi = e.min(axis=0), e.max(axis=0), t.min(axis=0), t.max(axis=0)
    err = float(max(np.abs(e_lo - t_lo).max(), np.abs(e_hi - t_hi).max()))
    excess = float(max(0.0, ((e_hi - e_lo) - (t_hi - t_lo)).max()))
    return err, excess


def face_region(regions: Sequence[FloatArray], true: FloatArray, normal: FloatArray) -> FloatArray:
    """The part of an estimated outline on the true face (polygon (m, 3)): the bounding rectangle
    (closed (5, 3), ``slam.plane_extents.rectangle``) of the outline's regions (polygons (k, 3))
    that overlap the face, all projected onto the face's plane; all the regions' when none does."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    B = np.stack(plane_basis(n))
    t = true @ B.T
    t_lo, t_hi = t.min(axis=0), t.max(axis=0)
    boxes = [np.array([uv.min(axis=0), uv.max(axis=0)]) for uv in (r @ B.T for r in regions)]
    on = [b for b in boxes if np.all(np.minimum(b[1], t_hi) - np.maximum(b[0], t_lo) > 0.0)]
    off = float(np.mean(np.concatenate(regions) @ n))
    return rectangle(n, -off, union_box(on or boxes))


@dataclass(frozen=True)
class PlaneEval:
    matches: list[PlaneMatch]
    n_estimated: int
    n_true: int
    unmatched: list[int] = field(default_factory=list)
    # doors and boards: est id -> (its extent polygon (k, 3; its regions on the face when it has
    # regions), the true face's (m, 3), the face's normal (3,)), ground-truth frame, for the plot
    # of extents against faces
    outlines: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = field(default_factory=dict)

    @property
    def angle(self) -> Stats:
        return Stats.of([m.angle_deg for m in self.matches])

    @property
    def offset(self) -> Stats:
        return Stats.of([abs(m.offset_m) for m in self.matches])

    def well_determined(self, max_sigma_deg: float = WELL_DETERMINED_SIGMA_DEG) -> list[PlaneMatch]:
        """The matches whose plane the run itself reports to within ``max_sigma_deg`` (1 sigma of
        its normal, the larger axis): the planes a map user would rely on for their orientation."""
        return [m for m in self.matches if m.sigma_angle_deg <= max_sigma_deg]

    @property
    def normalized_angle(self) -> Stats:
        """Angle errors over the run's own sigmas (planes with a covariance): ~1 for an honest
        covariance, well above 1 where the reported precision is overconfident."""
        return Stats.of([m.angle_deg / m.sigma_angle_deg for m in self.matches if m.sigma_angle_deg > 0])

    def to_json(self) -> dict[str, Any]:
        true_ids = [m.true_id for m in self.matches]
        wd = self.well_determined()
        by_kind: dict[str, dict[str, Any]] = {}
        for kind in sorted({m.kind for m in self.matches}):
            ms = [m for m in self.matches if m.kind == kind]
            by_kind[kind] = {
                "n": len(ms),
                "angle_deg": Stats.of([m.angle_deg for m in ms]).to_json(),
                "offset_m": Stats.of([abs(m.offset_m) for m in ms]).to_json(),
            }
        return {
            "n_estimated": self.n_estimated,
            "n_true": self.n_true,
            "n_matched": len(self.matches),
            "n_true_planes_found": len(set(true_ids)),
            "n_duplicates": len(true_ids) - len(set(true_ids)),
            "unmatched_estimated_ids": self.unmatched,
            "angle_deg": self.angle.to_json(),
            "offset_m": self.offset.to_json(),
            "well_determined": {
                "definition": f"planes whose reported 1-sigma normal error is <= {WELL_DETERMINED_SIGMA_DEG} deg",
                "n": len(wd),
                "angle_deg": Stats.of([m.angle_deg for m in wd]).to_json(),
            },
            "angle_over_sigma": self.normalized_angle.to_json(),
            "by_kind": by_kind,
            "extents": {
                "definition": "door and board planes: largest distance between the edges of the estimated "
                "extent's bounding rectangle and the true face's, in the face's plane (m); excess: how much "
                "longer or taller the estimate is; of the outline's regions that overlap the face when the plane's outline "
                "has regions (planes.json 'regions': the separate surfaces it holds), whole_error_m of the whole "
                "outline",
                "planes": [{"est_id": m.est_id, "true_id": m.true_id, "kind": m.kind, "error_m": m.extent_error_m,
                            "excess_m": m.extent_excess_m, "whole_error_m": m.extent_whole_error_m,
                            "regions": m.extent_regions}
                           for m in self.matches if m.extent_error_m == m.extent_error_m],
                "max_error_m": max((m.extent_error_m for m in self.matches if m.extent_error_m == m.extent_error_m),
                                   default=None),
            },
            "planes": [m.__dict__ for m in self.matches],
        }


def normal_sigma_deg(covariance: FloatArray | None) -> float:
    """The larger 1-sigma angle (deg) of a plane's normal from its planes.json covariance (3x3
    over the normal's two tangent directions and d); NaN without one."""
    if covariance is None:
        return float("nan")
    c = np.asarray(covariance, dtype=float)[:2, :2]
    ev = np.linalg.eigvalsh(0.5 * (c + c.T))
    return float(np.degrees(np.sqrt(max(float(ev[-1]), 0.0))))


def plane_errors(
    estimated: Sequence[PlaneRecord],
    true: Sequence[PlaneRecord],
    by_beams: Mapping[int, int] | None = None,
    support: Mapping[int, float] | None = None,
) -> PlaneEval:
    """Angle and offset errors of estimated planes (already in the ground-truth frame).

    ``by_beams`` maps estimated to true ids from the per-beam ground truth; planes it does not
    map are matched geometrically.
    """
    true_by_id = {t.id: t for t in true}
    beams = {k: v for k, v in (by_beams or {}).items() if v in true_by_id}
    rest = [e for e in estimated if e.id not in beams]
    geo = match_planes_geometric(rest, true)
    matches: list[PlaneMatch] = []
    unmatched: list[int] = []
    outlines: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}
    for e in estimated:
        tid = beams.get(e.id, geo.get(e.id))
        if tid is None:
            unmatched.append(int(e.id))
            continue
        t = true_by_id[tid]
        cosang = min(1.0, abs(float(e.normal @ t.normal)))
        c = _centre(e, fallback=_centre(t) if t.polygon.shape[0] >= 3 else None)
        ext = whole = (float("nan"), float("nan"))
        if t.kind in ("door", "board") and e.polygon.shape[0] >= 3 and t.polygon.shape[0] >= 3:
            whole = extent_errors(e.polygon, t.polygon, t.normal)
            own = face_region(e.regions, t.polygon, t.normal) if e.regions else e.polygon
            ext = extent_errors(own, t.polygon, t.normal)
            outlines[int(e.id)] = (own, t.polygon, t.normal)
        matches.append(
            PlaneMatch(
                est_id=int(e.id),
                true_id=int(tid),
                kind=t.kind,
                angle_deg=float(np.degrees(np.arccos(cosang))),
                offset_m=float(t.normal @ c + t.d),
                matched_by="beams" if e.id in beams else "geometry",
                support=float((support or {}).get(e.id, float("nan")))
                if e.id in beams
                else float("nan"),
                sigma_angle_deg=normal_sigma_deg(e.covariance),
                extent_error_m=ext[0],
                extent_excess_m=ext[1],
                extent_whole_error_m=whole[0],
                extent_regions=len(e.regions),
            )
        )
    return PlaneEval(matches, len(estimated), len(true), unmatched, outlines)


# ----------------------------------------------------------------------------------- cloud


@dataclass(frozen=True)
class CloudEval:
    """Unsigned distances (m) of cloud points (ground-truth frame) to the true mesh."""

    distances: FloatArray
    associated: NDArray[np.bool_]
    n_points_total: int

    def to_json(self) -> dict[str, Any]:
        return {
            "n_points_total": self.n_points_total,
            "n_points_evaluated": int(self.distances.size),
            "distance_m": Stats.of(self.distances).to_json(),
            "distance_m_associated_points": Stats.of(self.distances[self.associated]).to_json(),
        }


def mesh_distances(
    points: FloatArray, vertices: FloatArray, triangles: NDArray[np.integer], chunk: int = 1 << 20
) -> FloatArray:
    """Unsigned distance (m) of each point (N,3) to the triangle mesh, with open3d.

    Coordinates are shifted to the mesh's centre before the float32 conversion open3d needs,
    so that far-from-origin worlds keep sub-millimetre precision. The points are queried
    ``chunk`` at a time (each point's distance does not depend on the others), so the float32
    copies open3d needs stay small.
    """
    import open3d as o3d

    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor.from_numpy(
        np.ascontiguousarray(vertices - centre, dtype=np.float32)
    )
    mesh.triangle.indices = o3d.core.Tensor.from_numpy(
        np.ascontiguousarray(triangles, dtype=np.uint32)
    )
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    out = np.empty(points.shape[0], dtype=np.float64)
    for a in range(0, points.shape[0], chunk):
        q = np.ascontiguousarray(points[a : a + chunk] - centre, dtype=np.float32)
        out[a : a + q.shape[0]] = scene.compute_distance(o3d.core.Tensor.from_numpy(q)).numpy()
    return out


def cloud_errors(
    cloud: CloudRecord | str | Path,
    T_align: FloatArray,
    vertices: FloatArray,
    triangles: NDArray[np.integer],
    max_points: int = 2_000_000,
) -> CloudEval:
    """Distances of the aligned cloud to the mesh; a regular stride caps the points evaluated.

    ``cloud`` is a cloud in memory or a cloud.ply's path; a file is read a chunk at a time and
    only the evaluated points are kept (``read_cloud_ply`` with the stride)."""
    if isinstance(cloud, CloudRecord):
        n = len(cloud)
        step = max(1, -(-n // max_points))
        sample = CloudRecord(cloud.points_world[::step], cloud.scanner[::step], cloud.time[::step],
                             cloud.plane_id[::step])
    else:
        n, _ = cloud_ply_layout(cloud)
        sample = read_cloud_ply(cloud, step=max(1, -(-n // max_points)))
    return CloudEval(
        distances=mesh_distances(transform_points(T_align, sample.points_world), vertices, triangles),
        associated=sample.plane_id >= 0,
        n_points_total=n,
    )


# ------------------------------------------------------------------------------ ground truth


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's ``<run>.gt/`` folder, loaded (world frame)."""

    folder: Path
    times: FloatArray
    T_world_body: FloatArray
    planes: list[PlaneRecord]

    def mesh(self) -> tuple[FloatArray, NDArray[np.int64]]:
        import open3d as o3d

        path = self.folder / "mesh.ply"
        if not path.is_file():
            raise EvaluationError(f"{path}: no such file")
        m = o3d.io.read_triangle_mesh(path)
        v = np.asarray(m.vertices, dtype=np.float64)
        f = np.asarray(m.triangles, dtype=np.int64)
        if f.shape[0] == 0:
            raise EvaluationError(f"{path}: no triangles")
        return v, f

    def _scanner_aliases(self) -> dict[str, str]:
        """The true rig's scanner names by their frame ids and topics (a run whose rig was built
        from the recording names its scanners by frame id), from ``rig.yaml`` when present."""
        path = self.folder / "rig.yaml"
        if not path.is_file():
            return {}
        from common.config import ConfigError
        from common.rig import load_rig

        try:
            rig = load_rig(path)
        except ConfigError:
            return {}
        out = {s.topic: s.name for s in rig.scanners}
        out.update({s.frame: s.name for s in rig.scanners})
        return out

    def beams(
        self, names: Sequence[str]
    ) -> tuple[dict[str, NDArray[np.int32]], dict[str, FloatArray]]:
        path = self.folder / "beams.npz"
        if not path.is_file():
            raise EvaluationError(f"{path}: no such file")
        ids: dict[str, NDArray[np.int32]] = {}
        stamps: dict[str, FloatArray] = {}
        alias = self._scanner_aliases()
        try:
            with np.load(path, allow_pickle=False) as z:
                for name in names:
                    key = name if f"{name}_plane_id" in z.files else alias.get(name, name)
                    if f"{key}_plane_id" not in z.files:
                        raise EvaluationError(f"{path}: no array '{name}_plane_id'")
                    ids[name] = z[f"{key}_plane_id"]
                    if f"{key}_stamps" in z.files:
                        stamps[name] = z[f"{key}_stamps"].astype(np.float64)
        except EvaluationError:
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise EvaluationError(f"{path}: not a readable .npz ({' '.join(str(e).split())})") from None
        return ids, stamps

    def beam_rows(self, names: Sequence[str]) -> tuple[dict[str, BeamRows], dict[str, FloatArray]]:
        """Like ``beams``, but each scanner's plane ids as ``NpzRows`` read from the file a block
        of scans at a time (the stamps are loaded); close them with ``close_rows``."""
        path = self.folder / "beams.npz"
        if not path.is_file():
            raise EvaluationError(f"{path}: no such file")
        alias = self._scanner_aliases()
        ids: dict[str, BeamRows] = {}
        stamps: dict[str, FloatArray] = {}
        try:
            with zipfile.ZipFile(path) as z:
                members = set(z.namelist())
            with np.load(path, allow_pickle=False) as npz:
                for name in names:
                    key = name if f"{name}_plane_id.npy" in members else alias.get(name, name)
                    if f"{key}_plane_id.npy" not in members:
                        raise EvaluationError(f"{path}: no array '{name}_plane_id'")
                    ids[name] = NpzRows(path, f"{key}_plane_id.npy")
                    if f"{key}_stamps.npy" in members:
                        stamps[name] = npz[f"{key}_stamps"].astype(np.float64)
        except EvaluationError:
            close_rows(ids)
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            close_rows(ids)
            raise EvaluationError(f"{path}: not a readable .npz ({' '.join(str(e).split())})") from None
        return ids, stamps


def close_rows(rows: Mapping[str, BeamRows]) -> None:
    """Close the files behind ``GroundTruth.beam_rows``'s readers."""
    for r in rows.values():
        if isinstance(r, NpzRows):
            r.close()


def load_ground_truth(gt_dir: str | Path) -> GroundTruth:
    """Read the ground truth's trajectory and planes (mesh and beams are read on demand)."""
    d = Path(gt_dir)
    if not d.is_dir():
        raise EvaluationError(f"{d}: ground-truth folder not found")
    times, T = read_trajectory_tum(d / "trajectory.tum")
    if times.size < 2 or np.any(np.diff(times) <= 0):
        raise EvaluationError(
            f"{d / 'trajectory.tum'}: times must be strictly increasing (>= 2 poses)"
        )
    planes = read_planes_json(d / "planes.json") if (d / "planes.json").is_file() else []
    return GroundTruth(d, times, T, planes)


# -------------------------------------------------------------------------------- top level


@dataclass(frozen=True)
class EvalResult:
    run_dir: str
    gt_dir: str
    map_alignment: Alignment
    trajectory: TrajectoryEval
    planes: PlaneEval | None
    cloud: CloudEval | None
    association: AssociationEval | None
    skipped: dict[str, str]

    def to_json(self) -> dict[str, Any]:
        return {
            "run_dir": self.run_dir,
            "gt_dir": self.gt_dir,
            "definitions": {
                "ate_unaligned": "estimate as written, its world taken as the ground truth's",
                "ate_start_aligned": "estimate moved so its first pose is the true first pose (the datum)",
                "ate_se3_aligned": "estimate aligned to the ground truth by least-squares SE(3) (evo)",
                "rpe": "evo RPE, all pairs at 1 m / 10 m (+-2 %) of ground-truth path",
                "drift_endpoint_percent": "start-aligned error of the last pose / path length * 100",
                "drift_rpe_percent": "mean 10 m translational RPE / 10 m * 100",
                "drift_rotation_deg": "mean 10 m rotational RPE * 10 (deg per 100 m)",
                "map_alignment": "transform applied to planes and cloud before comparing: "
                + self.map_alignment,
                "plane_offset_m": "signed distance of the estimated patch centre to the matched true plane",
            },
            "trajectory": self.trajectory.to_json(),
            "planes": self.planes.to_json() if self.planes else None,
            "cloud": self.cloud.to_json() if self.cloud else None,
            "association": self.association.to_json() if self.association else None,
            "skipped": self.skipped,
        }


def evaluate(
    run_dir: str | Path,
    gt_dir: str | Path,
    map_alignment: Alignment = "start",
    max_cloud_points: int = 2_000_000,
) -> EvalResult:
    """Evaluate a run folder against a ground-truth folder (see the module docstring).

    ``trajectory.tum`` is required; planes, cloud and association are evaluated when their
    files exist on both sides, and otherwise listed in ``skipped`` with the reason.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise EvaluationError(f"{run}: run folder not found")
    gt = load_ground_truth(gt_dir)
    t_est, T_est = read_trajectory_tum(run / "trajectory.tum")
    try:
        traj = trajectory_errors(t_est, T_est, gt.times, gt.T_world_body)
    except EvaluationError as e:
        raise EvaluationError(f"{run / 'trajectory.tum'} against the ground truth {gt_dir}: {e}") from None
    T_map = {"start": traj.T_align_start, "se3": traj.T_align_se3, "none": np.eye(4)}[map_alignment]
    skipped: dict[str, str] = {}

    assoc: AssociationEval | None = None
    if not (run / "segments.npz").is_file():
        skipped["association"] = f"{run / 'segments.npz'} missing"
    elif not (gt.folder / "beams.npz").is_file():
        skipped["association"] = f"{gt.folder / 'beams.npz'} missing"
    else:
        segs = read_segments_npz(run / "segments.npz")
        ids, stamps = gt.beam_rows(segs.scanner_names)
        try:
            seg_true, purity = segment_true_planes(segs, ids, stamps)
        except ValueError as e:  # a beams.npz member shorter than its header says
            raise EvaluationError(" ".join(str(e).split())) from None
        finally:
            close_rows(ids)
        assoc = association_errors(segs, seg_true, purity, {t.id: t.kind for t in gt.planes},
                                   coplanar_surfaces(gt.planes))

    planes: PlaneEval | None = None
    if not (run / "planes.json").is_file():
        skipped["planes"] = f"{run / 'planes.json'} missing"
    elif not gt.planes:
        skipped["planes"] = f"{gt.folder / 'planes.json'} missing or empty"
    else:
        est = [transform_plane(T_map, p) for p in read_planes_json(run / "planes.json")]
        planes = plane_errors(
            est,
            gt.planes,
            assoc.plane_true if assoc else None,
            assoc.plane_support if assoc else None,
        )

    cloud: CloudEval | None = None
    if not (run / "cloud.ply").is_file():
        skipped["cloud"] = f"{run / 'cloud.ply'} missing"
    elif not (gt.folder / "mesh.ply").is_file():
        skipped["cloud"] = f"{gt.folder / 'mesh.ply'} missing"
    else:
        n_points, _ = cloud_ply_layout(run / "cloud.ply")
        if n_points == 0:
            skipped["cloud"] = f"{run / 'cloud.ply'} has no points"
        else:
            v, f = gt.mesh()
            cloud = cloud_errors(run / "cloud.ply", T_map, v, f, max_points=max_cloud_points)

    return EvalResult(str(run), str(gt.folder), map_alignment, traj, planes, cloud, assoc, skipped)


def write_eval_json(path: str | Path, result: EvalResult) -> Path:
    """Atomically write ``result`` as JSON (statistics only, no per-pose arrays)."""
    return write_json(path, result.to_json())


def read_eval_json(path: str | Path) -> dict[str, Any]:
    """Read an ``eval.json``."""
    data = read_json(path)
    if not isinstance(data, dict) or "trajectory" not in data:
        raise OutputFileError(f"{path}: not an eval.json")
    return data
