"""A SLAM run as a rerun recording (``map.rrd``), written without a viewer.

Entities (all in the ``world`` frame, z up, timeline ``sensor`` = the data's own time in s):

- ``world``: ``ViewCoordinates.RIGHT_HAND_Z_UP`` (static).
- ``world/scans/<scanner>``: the points of each scanner over time, one frame per
  ``frame_period``, coloured by plane id (grey = unassociated).
- ``world/segments``: segments as 3D lines over time, coloured by plane id (when given).
- ``world/planes/<id>``: each plane's extent polygon (or the regions of its outline from the
  final map) as a translucent ``Mesh3D`` patch (static)
  with its outline and label in ``world/planes/<id>/outline``.
- ``world/trajectory``: the whole path as a ``LineStrips3D`` (static); ``world/body``: the
  current pose ``T_world_body`` as a ``Transform3D`` over time, with axes.
- ``world/cloud``: the final cloud (static), coloured by plane id.

Long series go through ``rr.send_columns``; the file is written to a temporary name and
renamed when complete.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from common.atomic import OutputFileError, atomic_path
from slam.export import (
    CloudRecord,
    PlaneRecord,
    cloud_ply_layout,
    iter_cloud_ply,
)

FloatArray = NDArray[np.float64]

UNASSOCIATED_RGB = (150, 150, 150)
# matplotlib's tab20 reordered so that consecutive ids get contrasting colours.
_PALETTE = np.array(
    [
        (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
        (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207), (174, 199, 232),
        (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213), (196, 156, 148),
        (247, 182, 210), (219, 219, 141), (158, 218, 229), (57, 59, 121), (99, 121, 57),
    ],
    dtype=np.uint8,
)  # fmt: skip


def plane_colors(plane_id: NDArray[np.integer]) -> NDArray[np.uint8]:
    """RGB (N,3) per plane id: a fixed palette cycled by id; -1 (unassociated) is grey."""
    ids = np.asarray(plane_id, dtype=np.int64)
    out = _PALETTE[np.mod(ids, len(_PALETTE))]
    out[ids < 0] = UNASSOCIATED_RGB
    return out


@dataclass(frozen=True)
class SegmentLines:
    """Segments for display: endpoints (M,2,3) in the world frame at their scan's stamp (s); with
    ``rms``, their points' RMS distance to their plane (m; for the planes' outlines)."""

    stamp: FloatArray
    endpoints_world: FloatArray
    plane_id: NDArray[np.int32]
    rms: NDArray[np.float32] | None = None


@dataclass(frozen=True)
class MapOptions:
    """What goes into the recording and how much of it.

    ``max_scan_points`` and ``max_cloud_points`` cap the points logged over time and in the
    final cloud (a regular stride over the time-ordered points keeps the recording viewable
    for long walks); ``frame_period`` (s) groups the points of a scanner into frames.
    """

    app_id: str = "backpack_slam"
    frame_period: float = 0.1
    max_scan_points: int = 3_000_000
    max_cloud_points: int = 2_000_000
    point_radius: float = 0.01
    axis_length: float = 0.3
    plane_alpha: int = 90


def _stride(n: int, cap: int) -> int:
    return max(1, math.ceil(n / cap)) if cap > 0 else n + 1


def fan_triangles(n_vertices: int) -> NDArray[np.uint32]:
    """Triangle indices of a fan over a convex polygon of ``n_vertices`` (k-2, 3)."""
    k = np.arange(1, n_vertices - 1, dtype=np.uint32)
    return np.stack([np.zeros_like(k), k, k + 1], axis=1)


def _frames(times: FloatArray, t0: float, period: float) -> tuple[FloatArray, NDArray[np.int64]]:
    """Group sorted ``times`` into frames of ``period``: (frame start times, run lengths)."""
    idx = np.floor((times - t0) / period).astype(np.int64)
    frame_ids, lengths = np.unique(idx, return_counts=True)
    return (t0 + frame_ids * period).astype(np.float64), lengths.astype(np.int64)


@dataclass(frozen=True)
class CloudView:
    """The part of a cloud (world frame) that the recording shows: per scanner index its points
    in time order, every ``step``-th (``scans``, by increasing scanner index), every
    ``step``-th point of the whole cloud (``cloud``), ``step`` from :class:`MapOptions`'
    caps, and the earliest point time ``t0`` (s), where the scans' frames start."""

    t0: float
    scans: tuple[tuple[int, CloudRecord], ...]
    cloud: CloudRecord


def _take(cloud: CloudRecord, sel: NDArray[np.integer] | slice) -> CloudRecord:
    return CloudRecord(cloud.points_world[sel], cloud.scanner[sel], cloud.time[sel], cloud.plane_id[sel])


def view_of_cloud(cloud: CloudRecord, options: MapOptions | None = None) -> CloudView:
    """The :class:`CloudView` of a cloud in memory (a non-empty one)."""
    opt = options or MapOptions()
    step = _stride(len(cloud), opt.max_scan_points)
    scans = []
    for s in np.unique(cloud.scanner):
        sel = np.flatnonzero(cloud.scanner == s)
        t = cloud.time[sel]
        if not np.all(t[1:] >= t[:-1]):  # a scanner's points usually come in time order already
            sel = sel[np.argsort(t, kind="stable")]
        scans.append((int(s), _take(cloud, sel[::step])))
    return CloudView(float(np.min(cloud.time)), tuple(scans),
                     _take(cloud, slice(None, None, _stride(len(cloud), opt.max_cloud_points))))


class CloudViewPicker:
    """Picks a :class:`CloudView` out of a cloud that comes a chunk at a time (in its order): every
    ``cloud_step``-th point of the whole, and of each scanner every ``step``-th of its points, as
    :func:`view_of_cloud` picks them from the cloud held whole (when the scanner's points come in
    time order; see :attr:`unsorted`)."""

    def __init__(self, step: int, cloud_step: int) -> None:
        self.step, self.cloud_step = step, cloud_step
        self.t0 = math.inf
        self.count: dict[int, int] = {}  # points of each scanner so far
        self.last: dict[int, float] = {}  # time of its last point
        self.parts: dict[int, list[CloudRecord]] = {}
        self.unsorted: set[int] = set()  # scanners whose points did not come in time order
        self.cloud_parts: list[CloudRecord] = []
        self.n = 0  # points seen

    def take(self, c: CloudRecord) -> None:
        """The next chunk of the cloud (copies of its picked points are kept, not the chunk)."""
        if not len(c):
            return
        self.t0 = min(self.t0, float(np.min(c.time)))
        self.cloud_parts.append(_copy(c, slice((-self.n) % self.cloud_step, None, self.cloud_step)))
        self.n += len(c)
        sc = c.scanner
        # np.unique sorts every point; a count per index finds the same scanners, in order
        small = (sc.dtype.kind == "i" or (sc.dtype.kind == "u" and sc.dtype.itemsize < 8)) and (
            0 <= int(sc.min()) and int(sc.max()) < 1 << 16)
        present = np.flatnonzero(np.bincount(sc)) if small else np.unique(sc)
        for s in present.tolist():
            sel = np.flatnonzero(c.scanner == s)
            t = c.time[sel]
            if not np.all(t[1:] >= t[:-1]) or t[0] < self.last.get(s, -math.inf):
                self.unsorted.add(s)
            k = self.count.get(s, 0)
            self.parts.setdefault(s, []).append(_copy(c, sel[(-k) % self.step :: self.step]))
            self.count[s], self.last[s] = k + sel.size, float(t[-1])

    def view(self) -> CloudView:
        """The view of the points taken (the scanners in :attr:`unsorted` as picked, not in time
        order: the caller's to mend)."""
        scans = tuple((s, _concat(self.parts[s])) for s in sorted(self.parts))
        return CloudView(self.t0, scans, _concat(self.cloud_parts))


def view_strides(n: int, options: MapOptions) -> tuple[int, int]:
    """The strides (per scanner, over the whole) at which a view of a cloud of ``n`` points is
    picked (:class:`MapOptions`' caps)."""
    return _stride(n, options.max_scan_points), _stride(n, options.max_cloud_points)


def joined_view(pickers: Sequence[CloudViewPicker]) -> CloudView:
    """One view of a cloud picked in consecutive parts (each by its own :class:`CloudViewPicker`,
    at the same strides, from the part's first point): the parts' picks in order, and a scanner
    whose picked points are not in time order sorted by time (stable)."""
    parts: dict[int, list[CloudRecord]] = {}
    for p in pickers:
        for s in p.parts:
            parts.setdefault(s, []).extend(p.parts[s])
    scans = []
    for s in sorted(parts):
        c = _concat(parts[s])
        if not np.all(c.time[1:] >= c.time[:-1]):
            c = _take(c, np.argsort(c.time, kind="stable"))
        scans.append((s, c))
    cloud = _concat([c for p in pickers for c in p.cloud_parts])
    return CloudView(min(p.t0 for p in pickers), tuple(scans), cloud)


def view_of_cloud_ply(path: str | Path, options: MapOptions | None = None, chunk: int = 1 << 20) -> CloudView:
    """The :class:`CloudView` of a (non-empty) cloud.ply, the same as :func:`view_of_cloud` of the
    cloud read whole, from one pass over the file ``chunk`` points at a time (only the shown
    points are kept); a scanner whose points are not in time order takes two more passes."""
    opt = options or MapOptions()
    n, _ = cloud_ply_layout(path)
    picker = CloudViewPicker(*view_strides(n, opt))
    for c in iter_cloud_ply(path, chunk):
        picker.take(c)
    for s in picker.unsorted:
        picker.parts[s] = [_time_ordered(path, s, picker.step, chunk)]
    return picker.view()


def _copy(cloud: CloudRecord, sel: NDArray[np.integer] | slice) -> CloudRecord:
    """Points ``sel`` of a chunk, copied (so that the chunk itself is not kept)."""
    return CloudRecord(np.ascontiguousarray(cloud.points_world[sel]), np.ascontiguousarray(cloud.scanner[sel]),
                       np.ascontiguousarray(cloud.time[sel]), np.ascontiguousarray(cloud.plane_id[sel]))


def _concat(parts: Sequence[CloudRecord]) -> CloudRecord:
    return CloudRecord(np.concatenate([p.points_world for p in parts]), np.concatenate([p.scanner for p in parts]),
                       np.concatenate([p.time for p in parts]), np.concatenate([p.plane_id for p in parts]))


def _time_ordered(path: str | Path, scanner: int, step: int, chunk: int) -> CloudRecord:
    """Every ``step``-th point of ``scanner`` in (stable) time order, from a cloud.ply: a pass for
    its times, a pass for the chosen points."""
    times = np.concatenate([c.time[c.scanner == scanner] for c in iter_cloud_ply(path, chunk)])
    pick = np.argsort(times, kind="stable")[::step]  # ranks among the scanner's points, time order
    del times
    wanted = np.sort(pick)
    got, k = [], 0
    for c in iter_cloud_ply(path, chunk):
        sel = np.flatnonzero(c.scanner == scanner)
        lo, hi = np.searchsorted(wanted, [k, k + sel.size])
        got.append(_copy(c, sel[wanted[lo:hi] - k]))
        k += sel.size
    return _take(_concat(got), np.searchsorted(wanted, pick))


def write_map_rrd(
    path: str | Path,
    *,
    times: FloatArray,
    T_world_body: FloatArray,
    planes: Sequence[PlaneRecord] = (),
    cloud: CloudRecord | CloudView | None = None,
    scanner_names: Sequence[str] = (),
    segments: SegmentLines | None = None,
    options: MapOptions | None = None,
) -> Path:
    """Write the recording of a run to ``path`` (atomically); return ``path``.

    ``times`` (N,) and ``T_world_body`` (N,4,4) are the trajectory; ``cloud`` (world frame)
    gives both the scans over time (grouped per scanner by the points' own times) and the
    final cloud, either whole or as its :class:`CloudView` (e.g. of a cloud.ply, from
    :func:`view_of_cloud_ply`); ``scanner_names`` names the cloud's scanner indices (else
    ``scanner_<i>``).
    """
    opt = options or MapOptions()
    target = Path(path)
    t = np.asarray(times, dtype=np.float64)
    T = np.asarray(T_world_body, dtype=np.float64)
    if t.ndim != 1 or T.shape != (t.shape[0], 4, 4) or t.shape[0] == 0:
        raise OutputFileError(f"{target}: need times (N>0,) and T_world_body (N,4,4)")

    with atomic_path(target) as tmp:
        rec = rr.RecordingStream(opt.app_id)
        rec.save(tmp)
        try:
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            _log_trajectory(rec, t, T, opt)
            _log_planes(rec, planes, opt)
            if isinstance(cloud, CloudRecord) and len(cloud) > 0:
                cloud = view_of_cloud(cloud, opt)
            if isinstance(cloud, CloudView) and len(cloud.cloud) > 0:
                _log_scans(rec, cloud, scanner_names, opt)
                _log_cloud(rec, cloud.cloud, opt)
            if segments is not None and segments.stamp.shape[0] > 0:
                _log_segments(rec, segments, float(t[0]), opt)
            rec.flush()
        finally:
            rec.disconnect()
    return target


def _log_trajectory(rec: rr.RecordingStream, t: FloatArray, T: FloatArray, opt: MapOptions) -> None:
    positions = T[:, :3, 3]
    rec.log(
        "world/trajectory",
        rr.LineStrips3D([positions], colors=[(255, 80, 0)], radii=[opt.point_radius]),
        static=True,
    )
    quat_xyzw = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    rec.send_columns(
        "world/body",
        indexes=[rr.TimeColumn("sensor", timestamp=t)],
        columns=rr.Transform3D.columns(translation=positions, quaternion=quat_xyzw),
    )
    rec.log("world/body", rr.TransformAxes3D(opt.axis_length), static=True)


def _log_planes(rec: rr.RecordingStream, planes: Sequence[PlaneRecord], opt: MapOptions) -> None:
    """Each plane's patch and outline: one per region of its outline where it has regions (the
    separate surfaces it holds, from the final map), else its polygon."""
    for p in planes:
        polys = [np.asarray(q, dtype=np.float64).reshape(-1, 3) for q in (p.regions or (p.polygon,))]
        polys = [q for q in polys if q.shape[0] >= 3]
        if not polys:
            continue
        rgb = plane_colors(np.array([p.id]))[0]
        first = np.cumsum([0, *(q.shape[0] for q in polys)])
        vertices = np.vstack(polys)
        rec.log(
            f"world/planes/{p.id}",
            rr.Mesh3D(
                vertex_positions=vertices,
                triangle_indices=np.vstack([fan_triangles(q.shape[0]) + k for q, k in zip(polys, first[:-1], strict=True)]),
                vertex_normals=np.tile(p.normal, (vertices.shape[0], 1)),
                albedo_factor=[*rgb.tolist(), opt.plane_alpha],
            ),
            static=True,
        )
        label = f"plane {p.id}" + (f" ({p.kind})" if p.kind else "")
        rec.log(
            f"world/planes/{p.id}/outline",
            rr.LineStrips3D([np.vstack([q, q[:1]]) for q in polys], colors=[rgb] * len(polys),
                            labels=[label] * len(polys)),
            static=True,
        )


def _log_scans(rec: rr.RecordingStream, view: CloudView, names: Sequence[str], opt: MapOptions) -> None:
    for s, pts in view.scans:
        if len(pts) == 0:
            continue
        frame_t, lengths = _frames(pts.time, view.t0, opt.frame_period)
        name = names[s] if 0 <= s < len(names) else f"scanner_{s}"
        rec.send_columns(
            f"world/scans/{name}",
            indexes=[rr.TimeColumn("sensor", timestamp=frame_t)],
            columns=rr.Points3D.columns(
                positions=pts.points_world, colors=plane_colors(pts.plane_id)
            ).partition(lengths),
        )


def _log_cloud(rec: rr.RecordingStream, shown: CloudRecord, opt: MapOptions) -> None:
    rec.log(
        "world/cloud",
        rr.Points3D(shown.points_world, colors=plane_colors(shown.plane_id), radii=[opt.point_radius / 2]),
        static=True,
    )


def _log_segments(rec: rr.RecordingStream, seg: SegmentLines, t0: float, opt: MapOptions) -> None:
    order = np.argsort(seg.stamp, kind="stable")
    stamps = np.asarray(seg.stamp, dtype=np.float64)[order]
    frame_t, lengths = _frames(stamps, min(t0, float(stamps[0])), opt.frame_period)
    rec.send_columns(
        "world/segments",
        indexes=[rr.TimeColumn("sensor", timestamp=frame_t)],
        columns=rr.LineStrips3D.columns(
            # one (M, 2, 3) float32 array (what rerun stores): its numpy path, a hundred times
            # faster than a list of strips
            strips=np.asarray(seg.endpoints_world, dtype=np.float64).reshape(-1, 2, 3)[order].astype(np.float32),
            colors=plane_colors(np.asarray(seg.plane_id)[order]),
        ).partition(lengths),
    )
