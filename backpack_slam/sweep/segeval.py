"""A segmenter scored on a sample of a simulated bag's scans against the per-beam ground truth.

Ground-truth segments of a scanline are the maximal runs of beams carrying the same true
plane id in ``beams.npz`` (runs shorter than ``gt_min_run`` beams, invalid returns and mixed
pixels unlabelled). Each GT segment's true line, in the scanner frame, is its plane cut by
the scan plane at the time of the segment's middle beam (true trajectory and true rig), so
angles are measured against the truth rather than against a noisy fit. Scores follow
``segmentation.metrics.compare`` (the seed paper's section 3) and are pooled over the sample:
overlaps and segments-per-GT averaged over every GT segment, the median angle over every
assigned result segment, boundary precision/recall averaged over scans.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import segmentation
from common.rig import Rig
from segmentation.metrics import compare
from simulation.scanline import run_labels
from slam.evaluate import load_ground_truth
from slam.io.bag import read_scans
from slam.trajectory.interpolation import interpolate_trajectory

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SegmentationScores:
    n_scans: int
    n_gt_segments: int
    overlap1: float
    overlap2: float
    segments_per_gt: float
    median_angle_deg: float
    boundary_precision: float
    boundary_recall: float
    segments_per_scan: float
    ms_per_scan: float  # wall time of segment() per scanline (mean, ms)

    def row(self) -> dict[str, float]:
        return {f"seg_{k}": float(v) for k, v in self.__dict__.items()}


def sample_indices(n_scans: int, k: int) -> NDArray[np.int64]:
    """``k`` scan indices spread evenly over ``n_scans`` (all of them if fewer)."""
    if k <= 0 or n_scans <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.linspace(0, n_scans - 1, min(k, n_scans)).round().astype(np.int64))


def true_line_normals(
    plane_normals_world: FloatArray, plane_d: FloatArray, T_world_scanner: FloatArray
) -> FloatArray:
    """2D normals (k, 2), scanner frame, of planes (k,) cut by each scan plane z = 0 at the
    poses ``T_world_scanner`` (k, 4, 4); NaN where a plane is (nearly) parallel to the scan
    plane. Oriented away from the scanner (offset >= 0), the segmenters' convention."""
    R = T_world_scanner[:, :3, :3]
    t = T_world_scanner[:, :3, 3]
    n_s = np.einsum("kji,kj->ki", R, plane_normals_world)  # R^T n
    d_s = np.einsum("ki,ki->k", plane_normals_world, t) + plane_d  # n_s . p + d_s = 0
    n2 = n_s[:, :2]
    norm = np.linalg.norm(n2, axis=1)
    out = np.full((n2.shape[0], 2), np.nan)
    ok = norm > 1e-3
    # the line n2 . p = -d_s; flip so that the offset is >= 0
    sign = np.where(-d_s >= 0, 1.0, -1.0)
    out[ok] = (n2[ok] / norm[ok, None]) * sign[ok, None]
    return out


def score_segmenter(
    bag: str | Path,
    gt_dir: str | Path,
    rig: Rig,
    method: str,
    params: dict[str, Any],
    scans_per_scanner: int = 40,
    gt_min_run: int = 10,
    tolerance: int = 2,
) -> SegmentationScores:
    """Segment a sample of the bag's scans with ``method(**params)`` and score them."""
    seg = segmentation.get(method, **params)
    gt = load_ground_truth(gt_dir)
    names = [s.name for s in rig.scanners]
    ids, stamps = gt.beams(names)
    planes = {p.id: p for p in gt.planes}
    T_body_scanner = {s.name: s.T_body_scanner.matrix() for s in rig.scanners}
    wanted = {n: set(sample_indices(ids[n].shape[0], scans_per_scanner).tolist()) for n in names}

    o1: list[FloatArray] = []
    o2: list[FloatArray] = []
    n_assigned: list[NDArray[np.int64]] = []
    angles: list[FloatArray] = []
    precision: list[float] = []
    recall: list[float] = []
    n_segments: list[int] = []
    seconds = 0.0
    counters = dict.fromkeys(names, 0)
    for line in read_scans(bag, rig=rig):
        name = line.scanner_id
        si = counters[name]
        counters[name] += 1
        if si not in wanted[name]:
            continue
        if si >= ids[name].shape[0] or (name in stamps and abs(stamps[name][si] - line.stamp) > 1e-4):
            raise ValueError(f"{bag}: scan {si} of '{name}' does not match {gt_dir}/beams.npz")
        labels, faces = run_labels(ids[name][si], gt_min_run)
        normals = None
        if faces.size and all(int(f) in planes for f in faces):
            mid = np.array([np.flatnonzero(labels == k)[[0, -1]].mean() for k in range(faces.size)])
            times = line.times[np.round(mid).astype(np.int64)]
            T_ws = interpolate_trajectory(gt.times, gt.T_world_body, times) @ T_body_scanner[name]
            pl = [planes[int(f)] for f in faces]
            normals = true_line_normals(np.array([p.normal for p in pl]), np.array([p.d for p in pl]), T_ws)
            if not np.isfinite(normals).all():
                normals = None  # a plane parallel to the scan plane: fall back to line fits
        t0 = time.perf_counter()
        result = seg.segment(line)
        seconds += time.perf_counter() - t0
        score = compare(result, labels, line, gt_normals=normals, tolerance=tolerance)
        o1.append(score.overlap1)
        o2.append(score.overlap2)
        n_assigned.append(score.n_assigned)
        angles.append(score.result_angle_deg)
        precision.append(score.boundary_precision)
        recall.append(score.boundary_recall)
        n_segments.append(score.n_result)
    n = len(n_segments)
    if n == 0:
        raise ValueError(f"{bag}: no scans to score")
    all_angles = np.concatenate(angles)
    all_angles = all_angles[np.isfinite(all_angles)]
    n_gt = int(sum(a.size for a in o1))

    def pooled(parts: list[Any]) -> float:
        x = np.concatenate(parts).astype(np.float64)
        return float(x.mean()) if x.size else float("nan")

    return SegmentationScores(
        n_scans=n,
        n_gt_segments=n_gt,
        overlap1=pooled(o1),
        overlap2=pooled(o2),
        segments_per_gt=pooled(n_assigned),
        median_angle_deg=float(np.median(all_angles)) if all_angles.size else float("nan"),
        boundary_precision=float(np.mean(precision)),
        boundary_recall=float(np.mean(recall)),
        segments_per_scan=float(np.mean(n_segments)),
        ms_per_scan=1000.0 * seconds / n,
    )
