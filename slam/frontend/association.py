"""Association of line segments (world frame) to map planes.

A segment ``s`` with centroid ``c``, unit direction ``u`` and two virtual
points ``v1, v2`` (see ``observations``) lies on plane ``(n, d)`` when

* its direction lies in the plane: ``|n . u|`` is small against the
  direction's uncertainty (angle test),
* its points are near the plane: ``n . c + d`` is small against the combined
  uncertainty of the segment, the plane, the current pose estimate and the
  drift accumulated since the plane was last seen (distance test, which thus
  grows with the distance walked: the loop-closing search gate),
* it overlaps the plane's known extent (dilated), so that coplanar walls of
  different rooms are not confused.

The squared Mahalanobis distance combines the two tests; the best candidate
under the chi-square gate wins, and a segment with a second candidate also
under the gate on a *different* surface (offset differing by more than the
gate) is ambiguous and left unassociated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam.frontend.planemap import PlaneMap

FloatArray = NDArray[np.float64]
CHI2_2DOF_99 = 9.21


@dataclass(frozen=True)
class WorldSegments:
    """Segments placed in the world by the current trajectory estimate (k rows)."""

    centroid: FloatArray  # (k, 3)
    direction: FloatArray  # (k, 3) unit
    endpoints: FloatArray  # (k, 2, 3)
    sigma_centroid: FloatArray  # (k,) m
    sigma_direction: FloatArray  # (k,) rad
    range: FloatArray  # (k,) m, distance of the centroid from the scanner
    origin: FloatArray  # (3,) the scanner's position, world frame

    @property
    def n(self) -> int:
        return int(self.centroid.shape[0])


@dataclass(frozen=True)
class Gates:
    """Uncertainties added to every test, and the extent margin."""

    sigma_pose: float = 0.004  # m, current pose estimate at the segment
    sigma_rotation: float = np.radians(0.3)  # rad, in the angle test
    sigma_lever: float = np.radians(0.05)  # rad, rotation error times range in the distance test
    drift_rate: float = 0.003  # m of offset uncertainty per m walked since the plane was seen
    extent_margin_cells: int = 2
    max_extra_cells: int = 8  # cap of the drift-grown extent margin
    max_drift_sigma: float = 0.05  # m, cap of the drift-grown offset uncertainty
    chi2: float = CHI2_2DOF_99
    max_endpoint_distance: float = 0.05  # m, hard cap on either endpoint's distance

    def loosened(self, factor: float) -> Gates:
        return Gates(
            self.sigma_pose * factor,
            self.sigma_rotation * factor,
            self.sigma_lever * factor,
            self.drift_rate,
            self.extent_margin_cells,
            self.max_extra_cells,
            self.max_drift_sigma,
            self.chi2,
            self.max_endpoint_distance * factor,
        )


def world_segments(virtual_world: FloatArray, endpoints_world: FloatArray, virtual_sigma: FloatArray,
                   point_sigma: float, n_points: NDArray[np.int64], origin_world: FloatArray) -> WorldSegments:
    """Summaries from the virtual points (k, 2, 3) and endpoints (k, 2, 3) already placed in the
    world; ``origin_world`` (3,) is the scanner's position (for the rotation's lever arm)."""
    c = virtual_world.mean(axis=1)
    diff = endpoints_world[:, 1] - endpoints_world[:, 0]
    length = np.linalg.norm(diff, axis=1)
    u = diff / np.maximum(length, 1e-9)[:, None]
    n = n_points.astype(np.float64)
    # TLS direction error: sigma / sqrt(sum s_i^2), sum s_i^2 ~ n L^2 / 12
    sig_dir = point_sigma / np.maximum(length * np.sqrt(n / 12.0), 1e-9)
    rng = np.linalg.norm(c - origin_world, axis=1)
    return WorldSegments(c, u, endpoints_world, virtual_sigma / np.sqrt(2.0), sig_dir, rng, origin_world)


def associate(segs: WorldSegments, pmap: PlaneMap, odometer: float, gates: Gates) -> NDArray[np.int64]:
    """Plane id per segment, or -1 (no candidate, or ambiguous)."""
    out = np.full(segs.n, -1, dtype=np.int64)
    active = [p for p in pmap.planes if p.active]
    if not active or segs.n == 0:
        return out
    # the active planes' arrays in one pass over the map (world frame)
    ids = np.array([p.id for p in active], dtype=np.int64)
    normals = np.array([p.normal for p in active])
    offs = np.array([p.d for p in active])
    sig_plane = np.array([p.sigma_offset for p in active])
    since = np.array([odometer - p.last_seen_odometer for p in active])
    sig_drift = np.minimum(gates.drift_rate * np.maximum(since, 0.0), gates.max_drift_sigma)
    dist_c = segs.centroid @ normals.T + offs  # (k, P)
    sin_a = np.abs(segs.direction @ normals.T)
    # a rotation error of the pose moves a segment by its range times the angle (lever arm)
    lever = (gates.sigma_lever * segs.range) ** 2
    sig_d2 = (
        segs.sigma_centroid[:, None] ** 2 + sig_plane[None] ** 2 + gates.sigma_pose**2 + lever[:, None] + sig_drift[None] ** 2
    )
    sig_a2 = segs.sigma_direction[:, None] ** 2 + gates.sigma_rotation**2 + (sig_drift[None] / 5.0) ** 2
    m2 = dist_c**2 / sig_d2 + sin_a**2 / sig_a2
    e0 = np.abs(segs.endpoints[:, 0] @ normals.T + offs)
    e1 = np.abs(segs.endpoints[:, 1] @ normals.T + offs)
    cap = gates.max_endpoint_distance + 3.0 * sig_drift[None] + 3.0 * gates.sigma_lever * segs.range[:, None]
    # map normals face the side they were seen from: the scanner must be on that side (this
    # keeps the two faces of a thin wall apart)
    facing = (normals @ segs.origin + offs) > 0.0
    ok = (m2 < gates.chi2) & (e0 < cap) & (e1 < cap) & facing[None, :]
    cell = pmap.cell_size
    # per plane: the extent margin grown with the drift since it was seen (cells)
    dilate = [gates.extent_margin_cells + min(int(3.0 * sd / cell), gates.max_extra_cells) for sd in sig_drift.tolist()]
    # per segment: its two end points and centroid (world frame), tested against the extents
    seg_pts = np.concatenate((segs.endpoints, segs.centroid[:, None]), axis=1)
    for k in np.flatnonzero(ok.any(axis=1)):
        cand = np.flatnonzero(ok[k])
        if cand.size > 1:
            cand = cand[np.argsort(m2[k, cand])]
        pts = seg_pts[k]
        passing = [j for j in cand.tolist() if pmap.overlaps(int(ids[j]), pts, dilate[j])]
        if not passing:
            continue
        best = passing[0]
        ambiguous = False
        for j in passing[1:]:
            # same surface seen twice (a duplicate awaiting merge) is not ambiguity
            same = (normals[best] @ normals[j] > np.cos(np.radians(2.0))) and abs(dist_c[k, best] - dist_c[k, j]) < 3.0 * np.sqrt(sig_d2[k, best])
            if not same:
                ambiguous = True
                break
        if not ambiguous:
            out[k] = ids[best]
    return out
