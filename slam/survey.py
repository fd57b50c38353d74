"""Survey formats of a run's cloud: LAS / LAZ 1.4, E57 and PCD, streamed from ``cloud.ply``.

Every format is written a chunk of ``cloud.ply`` at a time (the cloud is never held) to a
temporary name and renamed when complete. Coordinates are the SLAM world frame: metres, z up
(levelled by the floor and ceiling), origin and heading those of the first knot. It is a local
frame with no geodetic reference, so no CRS is written (LAS: no WKT record; a reader takes the
coordinates as they are).

- **LAS / LAZ** (laspy, LAZ through lazrs): LAS 1.4, point format 6. ``gps_time`` holds the
  point's time (the recording's stamps in seconds, not GPS time: the global-encoding bit for
  adjusted standard GPS time stays clear), ``point_source_id`` the scanner index (the rig's
  order), and an extra dimension ``plane_id`` (int32, -1 = no plane). Scale 0.1 mm; the offset
  is the first chunk's minimum corner, rounded to a metre. When cloud.ply has intensities: the
  extra dimension ``raw_intensity`` (float32, the sensor's values as recorded, NaN = none) and
  the standard ``intensity`` field scaled to uint16 as ``round(raw * 65535 / max)``, ``max``
  the cloud's largest intensity (a separate pass over cloud.ply finds it), negative and missing
  values 0; without intensities both are absent or 0.
- **E57** (pye57): one E57 scan per chunk of the cloud, its points in the body frame of the
  trajectory's pose at the chunk's median time and that pose as the scan's pose (a reader that
  applies scan poses gets world coordinates). pye57 writes no per-point time stamps: a scan's
  name gives its pose's time; use LAS/LAZ or PCD for per-point times, scanners and planes. With
  intensities: the E57 ``intensity`` field (float32, the sensor's values; a missing one 0).
- **PCD**: binary, fields ``x y z`` (float64), ``scanner`` (int32), ``time`` (float64),
  ``plane_id`` (int32), and ``intensity`` (float32, NaN = none) when the cloud has them;
  written by this module because open3d writes only a whole cloud held in memory (open3d's
  tensor reader opens it).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.atomic import OutputFileError, atomic_path
from slam.export import CloudRecord, cloud_ply_format, iter_cloud_ply, read_trajectory_tum
from slam.trajectory.interpolation import interpolate_trajectory

FloatArray = NDArray[np.float64]
SurveyFormat = Literal["las", "laz", "e57", "pcd"]
FORMATS: tuple[SurveyFormat, ...] = ("las", "laz", "e57", "pcd")
LAS_SCALE = 1e-4  # m: 0.1 mm, well below the scanners' noise
E57_CHUNK = 1 << 18  # points per E57 scan

Progress = Callable[[int], object]


def survey_format(name: str) -> SurveyFormat:
    """A format name (case-insensitive) -> the format; a ValueError lists the known ones."""
    n = name.lower().lstrip(".")
    if n not in FORMATS:
        raise ValueError(f"unknown cloud format '{name}' (known: {', '.join(FORMATS)})")
    return n  # type: ignore[return-value]


def export_cloud(cloud_ply: str | Path, out: str | Path, fmt: SurveyFormat | None = None,
                 trajectory_tum: str | Path | None = None, progress: Progress | None = None) -> int:
    """Write the cloud of ``cloud_ply`` (world frame) as ``fmt`` (default: from ``out``'s
    suffix) to ``out``; E57 needs the run's ``trajectory_tum`` for its scan poses. Returns the
    number of points written; ``progress`` is called with each chunk's size."""
    src, dst = Path(cloud_ply), Path(out)
    f = survey_format(fmt or dst.suffix)
    n, _, intensity = cloud_ply_format(src)
    if n == 0:
        raise OutputFileError(f"{src}: the cloud has no points; nothing to export")
    if f == "e57":
        if trajectory_tum is None:
            raise OutputFileError(f"{dst}: E57 needs the run's trajectory.tum for the scan poses")
        times, T_world_body = read_trajectory_tum(trajectory_tum)
        if len(times) < 2:
            raise OutputFileError(f"{trajectory_tum}: {len(times)} pose(s); E57's scan poses are interpolated "
                                  "between at least 2")
        if not np.all(np.diff(times) > 0):
            raise OutputFileError(f"{trajectory_tum}: times must be strictly increasing (E57's scan poses are "
                                  "interpolated along them)")
    chunks = _counted(iter_cloud_ply(src, E57_CHUNK) if f == "e57" else iter_cloud_ply(src), progress)
    with atomic_path(dst) as tmp:
        if f in ("las", "laz"):
            _write_las(tmp, chunks, compress=f == "laz", intensity_scale=las_intensity_scale(src) if intensity else None)
        elif f == "e57":
            _write_e57(tmp, chunks, times, T_world_body)
        else:
            _write_pcd(tmp, chunks, n, intensity)
    return n


def _counted(chunks: Iterator[CloudRecord], progress: Progress | None) -> Iterator[CloudRecord]:
    for c in chunks:
        yield c
        if progress is not None:
            progress(len(c))


# ------------------------------------------------------------------------------ LAS / LAZ


def las_intensity_scale(cloud_ply: str | Path) -> float:
    """The factor from a cloud's intensities to LAS's uint16 ``intensity``: 65535 over the
    cloud's largest finite intensity (1 when none is positive)."""
    top = 0.0
    for chunk in iter_cloud_ply(cloud_ply):
        if chunk.intensity is not None:
            finite = chunk.intensity[np.isfinite(chunk.intensity)]
            if finite.size:
                top = max(top, float(finite.max()))
    return 65535.0 / top if top > 0 else 1.0


def las_intensity(raw: NDArray[np.float32], scale: float) -> NDArray[np.uint16]:
    """LAS ``intensity`` of raw intensities: ``round(raw * scale)`` within [0, 65535], 0 where
    there is none (NaN)."""
    v = np.nan_to_num(raw.astype(np.float64) * scale, nan=0.0, posinf=65535.0, neginf=0.0)
    return np.clip(np.rint(v), 0, 65535).astype(np.uint16)


def _write_las(path: Path, chunks: Iterator[CloudRecord], compress: bool, intensity_scale: float | None) -> None:
    import laspy

    first = next(chunks, None)
    if first is None:
        raise OutputFileError(f"{path}: no points")
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.add_extra_dim(laspy.ExtraBytesParams(name="plane_id", type=np.int32,
                                                description="plane id, -1 = none"))
    if intensity_scale is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="raw_intensity", type=np.float32,
                                                    description="sensor intensity, NaN = none"))
    header.offsets = np.floor(first.points_world.min(axis=0))
    header.scales = np.full(3, LAS_SCALE)
    header.generating_software = "backpack-slam"
    header.system_identifier = "backpack-slam SLAM world frame"
    with laspy.open(path, mode="w", header=header, do_compress=compress) as writer:
        for chunk in _chain(first, chunks):
            rec = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
            rec.x = chunk.points_world[:, 0]
            rec.y = chunk.points_world[:, 1]
            rec.z = chunk.points_world[:, 2]
            rec.gps_time = chunk.time
            rec.point_source_id = chunk.scanner.astype(np.uint16)
            rec.plane_id = chunk.plane_id
            if intensity_scale is not None and chunk.intensity is not None:
                rec.raw_intensity = chunk.intensity
                rec.intensity = las_intensity(chunk.intensity, intensity_scale)
            writer.write_points(rec)


def _chain(first: CloudRecord, rest: Iterator[CloudRecord]) -> Iterator[CloudRecord]:
    yield first
    yield from rest


# ------------------------------------------------------------------------------ E57


def _write_e57(path: Path, chunks: Iterator[CloudRecord], times: FloatArray, T_world_body: FloatArray) -> None:
    import pye57
    from scipy.spatial.transform import Rotation

    e57 = pye57.E57(str(path), mode="w")
    try:
        for i, chunk in enumerate(chunks):
            t_mid = float(np.median(chunk.time))
            T = interpolate_trajectory(times, T_world_body, np.array([t_mid]))[0]
            R, t = T[:3, :3], T[:3, 3]
            local = (chunk.points_world - t) @ R  # R^T (p - t), row vectors
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            data = {"cartesianX": np.ascontiguousarray(local[:, 0]), "cartesianY": np.ascontiguousarray(local[:, 1]),
                    "cartesianZ": np.ascontiguousarray(local[:, 2])}
            if chunk.intensity is not None:
                data["intensity"] = np.nan_to_num(chunk.intensity, nan=0.0).astype(np.float32)
            e57.write_scan_raw(
                data,
                name=f"chunk {i} (body frame at t = {t_mid:.3f} s)",
                rotation=np.array([w, x, y, z]), translation=t.copy(),
            )
    finally:
        e57.close()


# ------------------------------------------------------------------------------ PCD

_PCD_FIELDS = (("x", "<f8", "F"), ("y", "<f8", "F"), ("z", "<f8", "F"), ("scanner", "<i4", "I"),
               ("time", "<f8", "F"), ("plane_id", "<i4", "I"))
_PCD_INTENSITY = ("intensity", "<f4", "F")


def _pcd_fields(intensity: bool) -> tuple[tuple[str, str, str], ...]:
    return (*_PCD_FIELDS, _PCD_INTENSITY) if intensity else _PCD_FIELDS


def _pcd_header(n: int, intensity: bool) -> bytes:
    fields = _pcd_fields(intensity)
    return (
        "# .PCD v0.7 - backpack-slam cloud, SLAM world frame (m)\n"
        f"VERSION 0.7\nFIELDS {' '.join(f[0] for f in fields)}\n"
        f"SIZE {' '.join(str(np.dtype(f[1]).itemsize) for f in fields)}\nTYPE {' '.join(f[2] for f in fields)}\n"
        f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        "DATA binary\n"
    ).encode("ascii")


def _write_pcd(path: Path, chunks: Iterator[CloudRecord], n: int, intensity: bool) -> None:
    written = 0
    row = np.dtype([(name, dtype) for name, dtype, _ in _pcd_fields(intensity)])
    with path.open("wb") as f:
        f.write(_pcd_header(n, intensity))
        for chunk in chunks:
            rows = np.empty(len(chunk), dtype=row)
            rows["x"], rows["y"], rows["z"] = chunk.points_world.T
            rows["scanner"] = chunk.scanner
            rows["time"] = chunk.time
            rows["plane_id"] = chunk.plane_id
            if intensity and chunk.intensity is not None:
                rows["intensity"] = chunk.intensity
            rows.tofile(f)
            written += len(chunk)
    if written != n:
        raise OutputFileError(f"{path}: wrote {written} points of {n}")
