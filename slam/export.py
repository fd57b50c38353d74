"""Writers and readers of a SLAM run's output folder (all geometry in the world frame).

Files of a run folder ``DIR``:

- ``trajectory.tum``: ``T_world_body`` as TUM lines ``t tx ty tz qx qy qz qw`` (evo's format).
- ``planes.json``: planes ``n . x + d = 0`` (world frame, metres) with extent polygon (and
  where it came from, ``outline``: the final map or the front end; from the final map also the
  ``regions``, one outline per separate surface the plane holds), number of segments,
  covariance over (Unit3 tangent of the normal (2), d) and a kind guess.
  The ground truth's ``planes.json`` reads with the same reader.
- ``cloud.ply``: every valid point in the world frame with per-point ``scanner`` (int32),
  ``time`` (float64, s) and ``plane_id`` (int32, -1 = unassociated): a binary PLY in open3d's
  layout (x, y, z, scanner, time, plane_id; open3d's tensor API reads it); when the recording's
  scans carry intensities, a last property ``intensity`` (float32, the sensor's units as the
  messages give them; NaN for a point whose message had none), else no such property. Its header has a
  fixed length (the comment line is padded), so a run writes the points as they come and the
  header last; it is read back with numpy, whole or a chunk at a time.
- ``segments.npz``: one row per segment (scanner index, scan index, stamp, inclusive beam range,
  plane id).
- ``summary.json``: the run summary (config, counts, timings, residuals; the record is
  ``slam.run_folder.RunSummary``).

Every writer is atomic: it writes to a temporary name in the target folder and renames it
over the target only when complete, so an interrupted write never leaves a partial file.
"""

from __future__ import annotations

import os
import shutil
import warnings
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from common.atomic import OutputFileError, atomic_path, read_json, write_json
from slam import cloud_kernels as ck

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]

PLANE_CONVENTION = "n . x + d = 0, world frame, metres"
COVARIANCE_CONVENTION = "3x3 over (Unit3 tangent basis of the normal (2), d)"


# ------------------------------------------------------------------------------ trajectory


def write_trajectory_tum(path: str | Path, times: ArrayLike, T_world_body: ArrayLike) -> Path:
    """Write poses ``T_world_body`` (N,4,4) at ``times`` (N,) as a TUM file via evo."""
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    t = np.asarray(times, dtype=np.float64)
    T = np.asarray(T_world_body, dtype=np.float64)
    target = Path(path)
    if t.ndim != 1 or T.shape != (t.shape[0], 4, 4):
        raise OutputFileError(
            f"{target}: need times (N,) and T_world_body (N,4,4), got {t.shape} and {T.shape}"
        )
    if t.shape[0] == 0:
        raise OutputFileError(f"{target}: empty trajectory")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(T))):
        raise OutputFileError(f"{target}: non-finite times or poses")
    traj = PoseTrajectory3D(poses_se3=list(T), timestamps=t)
    with atomic_path(target) as tmp, tmp.open("w") as f:
        file_interface.write_tum_trajectory_file(f, traj)
    return target


MAX_COORDINATE = 1e7  # m: a trajectory or cloud beyond this (UTM's range) is not a survey


def read_trajectory_tum(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM file; return times (N,) and ``T_world_body`` (N,4,4). Non-finite values and
    positions beyond :data:`MAX_COORDINATE` are an ``OutputFileError`` naming the file.

    The rows are parsed into one array (numpy's text reader; ``#`` starts a comment) and the
    rotations built from the (normalised) quaternions all at once by scipy: an hour's ground truth at 200 Hz (720,000 rows) takes 0.13 GB
    instead of the ~1 GB of evo's reader (a list of strings per row, a 4x4 array per pose)."""
    p = Path(path)
    if not p.is_file():
        raise OutputFileError(f"{p}: no such file")
    try:
        with warnings.catch_warnings():  # an empty file: reported below, not as a warning
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            rows = np.loadtxt(p, dtype=np.float64, comments="#", ndmin=2)
    except ValueError as e:
        raise OutputFileError(f"{p}: not a TUM trajectory ({' '.join(str(e).split())[:200]})") from None
    if rows.shape[0] == 0:
        raise OutputFileError(f"{p}: empty trajectory")
    if rows.shape[1] != 8:
        raise OutputFileError(f"{p}: expected 8 columns (t x y z qx qy qz qw), got {rows.shape[1]}")
    times = np.ascontiguousarray(rows[:, 0])
    if not np.all(np.isfinite(rows)):
        raise OutputFileError(f"{p}: non-finite times or poses")
    T = np.zeros((rows.shape[0], 4, 4))
    q = rows[:, 4:8].copy()  # x y z w; a zero quaternion is no rotation (as evo reads it)
    q[np.einsum("ij,ij->i", q, q) < 4.0 * np.finfo(float).eps, 3] = 1.0
    T[:, :3, :3] = Rotation.from_quat(q).as_matrix()
    T[:, :3, 3] = rows[:, 1:4]
    T[:, 3, 3] = 1.0
    if np.abs(T[:, :3, 3]).max() > MAX_COORDINATE:
        raise OutputFileError(f"{p}: positions beyond {MAX_COORDINATE:g} m")
    return times, T


# ---------------------------------------------------------------------------------- planes


@dataclass(frozen=True)
class PlaneRecord:
    """A plane ``normal . x + d = 0`` in the world frame with its extent.

    ``polygon`` (k,3) is the extent in the world frame (may be empty); ``covariance`` (3,3) is
    over (Unit3 tangent of the normal, d), or None when unknown (ground truth); ``outline`` says
    where the polygon came from: ``final_map`` (the segments placed with the final trajectory,
    ``slam.plane_extents``), ``front_end`` (the extent grown during the walk) or "" (unknown);
    ``regions`` (the final map's) one outline per separate surface the plane holds.
    """

    id: int
    normal: FloatArray
    d: float
    polygon: FloatArray
    kind: str = ""
    n_segments: int = 0
    covariance: FloatArray | None = None
    outline: str = ""
    regions: tuple[FloatArray, ...] = ()


def _plane_to_dict(p: PlaneRecord) -> dict[str, Any]:
    out: dict[str, Any] = {
        "id": int(p.id),
        "kind": p.kind,
        "normal": np.asarray(p.normal, dtype=float).tolist(),
        "d": float(p.d),
        "polygon": np.asarray(p.polygon, dtype=float).reshape(-1, 3).tolist(),
        "n_segments": int(p.n_segments),
    }
    if p.covariance is not None:
        out["covariance"] = np.asarray(p.covariance, dtype=float).reshape(3, 3).tolist()
    if p.outline:
        out["outline"] = p.outline
    if p.regions:
        out["regions"] = [np.asarray(r, dtype=float).reshape(-1, 3).tolist() for r in p.regions]
    return out


def write_planes_json(path: str | Path, planes: Sequence[PlaneRecord]) -> Path:
    """Atomically write planes (world frame) as ``{"convention", "covariance", "planes"}``."""
    target = Path(path)
    ids = [int(p.id) for p in planes]
    if len(set(ids)) != len(ids):
        raise OutputFileError(f"{target}: duplicate plane ids")
    for p in planes:
        n = np.asarray(p.normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or abs(np.linalg.norm(n) - 1) > 1e-6:
            raise OutputFileError(f"{target}: plane {p.id}: normal must be a finite unit 3-vector")
    data = {
        "convention": PLANE_CONVENTION,
        "covariance": COVARIANCE_CONVENTION,
        "planes": [_plane_to_dict(p) for p in planes],
    }
    return write_json(target, data)


def read_planes_json(path: str | Path) -> list[PlaneRecord]:
    """Read a ``planes.json`` (ours or the ground truth's); normals come back unit length."""
    p = Path(path)
    data = read_json(p)
    if not isinstance(data, dict) or not isinstance(data.get("planes"), list):
        raise OutputFileError(f"{p}: expected an object with a 'planes' list")
    out: list[PlaneRecord] = []
    for i, rec in enumerate(data["planes"]):
        try:
            normal = np.asarray(rec["normal"], dtype=np.float64)
            norm = float(np.linalg.norm(normal))
            if normal.shape != (3,) or not norm > 0:
                raise ValueError("normal must be a non-zero 3-vector")
            poly = np.asarray(rec.get("polygon", []), dtype=np.float64).reshape(-1, 3)
            cov = rec.get("covariance")
            out.append(
                PlaneRecord(
                    id=int(rec["id"]),
                    normal=normal / norm,
                    d=float(rec["d"]) / norm,
                    polygon=poly,
                    kind=str(rec.get("kind", "")),
                    n_segments=int(rec.get("n_segments", 0)),
                    covariance=None
                    if cov is None
                    else np.asarray(cov, dtype=np.float64).reshape(3, 3),
                    outline=str(rec.get("outline", "")),
                    regions=tuple(np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in rec.get("regions", [])),
                )
            )
        except (KeyError, TypeError, ValueError) as e:
            what = f"missing key {e}" if isinstance(e, KeyError) else str(e)
            raise OutputFileError(f"{p}: plane #{i}: {what}") from None
    return out


# ----------------------------------------------------------------------------------- cloud


@dataclass(frozen=True)
class CloudRecord:
    """Points in the world frame with per-point scanner index, time (s) and plane id, and the
    returns' intensities (float32, NaN: none) when the cloud has them (else None)."""

    points_world: FloatArray
    scanner: IntArray
    time: FloatArray
    plane_id: IntArray
    intensity: NDArray[np.float32] | None = None

    def __len__(self) -> int:
        return int(self.points_world.shape[0])


def _as_cloud(
    points_world: ArrayLike, scanner: ArrayLike, time: ArrayLike, plane_id: ArrayLike, what: str,
    intensity: ArrayLike | None = None,
) -> CloudRecord:
    pts = np.asarray(points_world, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise OutputFileError(f"{what}: points_world must be (N,3), got {pts.shape}")
    n = pts.shape[0]
    sc = np.asarray(scanner).astype(np.int32, copy=False)
    tm = np.asarray(time, dtype=np.float64)
    pid = np.asarray(plane_id).astype(np.int32, copy=False)
    inten = None if intensity is None else np.asarray(intensity).astype(np.float32, copy=False)
    for name, col in (("scanner", sc), ("time", tm), ("plane_id", pid), ("intensity", inten)):
        if col is not None and col.shape != (n,):
            raise OutputFileError(f"{what}: {name} must be ({n},), got {col.shape}")
    if not np.all(np.isfinite(pts)):
        raise OutputFileError(f"{what}: non-finite points (invalid returns must be masked)")
    return CloudRecord(pts, sc, tm, pid, inten)


def voxel_thin(points_world: FloatArray, voxel: float) -> NDArray[np.int64]:
    """Indices (sorted) of one real point per occupied voxel: the one nearest the voxel's mean.

    Keeping a real point (rather than averaging as open3d's voxel_down_sample does) keeps its
    scanner, time and plane id consistent with its position.
    """
    if not voxel > 0:
        raise ValueError(f"voxel size must be > 0, got {voxel}")
    n = points_world.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    keys = np.floor(points_world / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    n_vox = counts.shape[0]
    mean = np.zeros((n_vox, 3))
    np.add.at(mean, inverse, points_world)
    mean /= counts[:, None]
    dist2 = np.sum((points_world - mean[inverse]) ** 2, axis=1)
    order = np.lexsort((np.arange(n), dist2, inverse))
    first = np.ones(n, dtype=bool)
    first[1:] = inverse[order[1:]] != inverse[order[:-1]]
    return np.sort(order[first])


# cloud.ply's vertex properties: (name, numpy type, PLY type), the layout open3d writes and reads
_PLY_PROPERTIES = (
    ("x", "<f8", "double"),
    ("y", "<f8", "double"),
    ("z", "<f8", "double"),
    ("scanner", "<i4", "int"),
    ("time", "<f8", "double"),
    ("plane_id", "<i4", "int"),
)
_PLY_INTENSITY = ("intensity", "<f4", "float")  # the last property of a cloud with intensities
_PLY_VERTEX = np.dtype([(name, dtype) for name, dtype, _ in _PLY_PROPERTIES])
_PLY_VERTEX_INTENSITY = np.dtype([(name, dtype) for name, dtype, _ in (*_PLY_PROPERTIES, _PLY_INTENSITY)])
_PLY_CHUNK = 1 << 20  # points packed and written, or read, at a time
_PLY_COUNT_DIGITS = 15  # the header has room for a point count of up to this many digits
_PLY_END = b"end_header\n"
_PLY_MAX_HEADER = 1 << 16  # bytes searched for the end of a header


def _ply_properties(intensity: bool) -> tuple[tuple[str, str, str], ...]:
    return (*_PLY_PROPERTIES, _PLY_INTENSITY) if intensity else _PLY_PROPERTIES


def _ply_vertex(intensity: bool) -> np.dtype[np.void]:
    return _PLY_VERTEX_INTENSITY if intensity else _PLY_VERTEX


def cloud_row_bytes(intensity: bool = False) -> int:
    """Bytes of one point's row in a cloud.ply (with the ``intensity`` property or without)."""
    return int(_ply_vertex(intensity).itemsize)


def _ply_header(n: int, intensity: bool = False) -> bytes:
    """The header of a binary little-endian PLY of ``n`` cloud points (with the ``intensity``
    property or without).

    Its length does not depend on ``n`` (the comment line is padded with spaces), so that the
    points can be written after room for the header and the header, with the count, last."""
    digits = len(str(n))
    if digits > _PLY_COUNT_DIGITS:
        raise OutputFileError(f"{n} points: too many for a cloud.ply")
    props = "".join(f"property {ply} {name}\n" for name, _, ply in _ply_properties(intensity))
    return (
        "ply\nformat binary_little_endian 1.0\ncomment written by backpack-slam (slam.export)"
        f"{' ' * (_PLY_COUNT_DIGITS - digits)}\nelement vertex {n}\n{props}end_header\n"
    ).encode("ascii")


def _write_ply_rows(f: BinaryIO, cloud: CloudRecord, start: int, stop: int, buf: NDArray[np.void]) -> None:
    """Pack points ``start:stop`` of the cloud (world frame) into PLY rows and write them."""
    rows = buf[: stop - start]
    if cloud.intensity is not None:
        ck.pack_rows_intensity(rows, cloud.points_world, cloud.scanner, cloud.time, cloud.plane_id, cloud.intensity,
                               start)
    else:
        ck.pack_rows(rows, cloud.points_world, cloud.scanner, cloud.time, cloud.plane_id, start)
    f.write(rows.data)


class PointSink(Protocol):
    """Where the cloud pass puts its points (world frame): a :class:`CloudPlyWriter`, or a
    :class:`PointCounter` when no cloud is kept."""

    intensity: bool
    count: int

    def write(self, points_world: ArrayLike, scanner: ArrayLike, time: ArrayLike, plane_id: ArrayLike,
              intensity: ArrayLike | None = None) -> None: ...


class PointCounter:
    """A :class:`PointSink` that keeps nothing and counts the points: the cloud pass of a run
    without cloud.ply (its recording's view and the planes' outlines need the pass, not the file)."""

    def __init__(self, intensity: bool = False) -> None:
        self.intensity = intensity
        self.count = 0

    def write(self, points_world: ArrayLike, scanner: ArrayLike, time: ArrayLike, plane_id: ArrayLike,
              intensity: ArrayLike | None = None) -> None:
        self.count += int(np.shape(points_world)[0])


class CloudPlyWriter:
    """Writes cloud points (world frame) into an open binary file, a chunk at a time, in
    :func:`write_cloud_ply`'s layout (with the ``intensity`` property when ``intensity``); the
    header, with the final count, is written by :meth:`finish`. Made by :func:`cloud_ply_writer`."""

    def __init__(self, f: BinaryIO, what: str, header: bool = True, intensity: bool = False) -> None:
        self._f = f
        self._what = what
        self.intensity = intensity
        self._vertex = _ply_vertex(intensity)
        self._buf = np.empty(0, dtype=self._vertex)
        self._header = header
        self.count = 0  # points written so far
        if header:
            f.write(b" " * len(_ply_header(0, intensity)))  # room for the header

    def write(self, points_world: ArrayLike, scanner: ArrayLike, time: ArrayLike, plane_id: ArrayLike,
              intensity: ArrayLike | None = None) -> None:
        """Append points (N,3) in the world frame with their scanner, time (s) and plane id (N,),
        and their intensities (N,) exactly when the writer was made with ``intensity``."""
        if (intensity is not None) != self.intensity:
            raise OutputFileError(f"{self._what}: intensities {'missing' if self.intensity else 'given'} for a cloud "
                                  f"{'with' if self.intensity else 'without'} an intensity property")
        cloud = _as_cloud(points_world, scanner, time, plane_id, self._what, intensity)
        n = len(cloud)
        if self._buf.shape[0] < min(n, _PLY_CHUNK):
            self._buf = np.empty(min(n, _PLY_CHUNK), dtype=self._vertex)
        for start in range(0, n, _PLY_CHUNK):
            _write_ply_rows(self._f, cloud, start, min(n, start + _PLY_CHUNK), self._buf)
        self.count += n

    def append_rows(self, path: str | Path, count: int) -> None:
        """Append the ``count`` bare rows that another writer made with ``header=False`` into
        ``path`` (a part of the cloud written in another process); checked by size."""
        src = Path(path)
        size = src.stat().st_size
        if size != count * self._vertex.itemsize:
            raise OutputFileError(f"{src}: {size} bytes, expected {count} cloud rows of {self._vertex.itemsize}")
        self._f.flush()
        end = self._f.seek(0, os.SEEK_END)
        with src.open("rb") as fin:
            try:  # in the kernel, without passing through Python
                done = 0
                while done < size:
                    n = os.copy_file_range(fin.fileno(), self._f.fileno(), size - done)
                    if n == 0:
                        break
                    done += n
                if done != size:
                    raise OSError("short copy")
            except (AttributeError, OSError):
                fin.seek(0)
                self._f.truncate(end)
                self._f.seek(end)
                shutil.copyfileobj(fin, self._f, 1 << 24)
        self._f.seek(0, os.SEEK_END)
        self.count += count

    def finish(self) -> None:
        """Write the header (with the number of points written) at the start of the file
        (nothing for a writer of bare rows)."""
        if self._header:
            self._f.seek(0)
            self._f.write(_ply_header(self.count, self.intensity))


@contextmanager
def cloud_ply_writer(path: str | Path, intensity: bool = False) -> Iterator[CloudPlyWriter]:
    """A :class:`CloudPlyWriter` onto a temporary name beside ``path`` (with the ``intensity``
    property or without), renamed onto ``path`` when the block succeeds (and removed on any
    exception): a cloud written as it comes, without holding it, e.g.
    ``with cloud_ply_writer(p) as w: w.write(...)``."""
    target = Path(path)
    with atomic_path(target) as tmp, tmp.open("wb") as f:
        writer = CloudPlyWriter(f, str(target), intensity=intensity)
        yield writer
        writer.finish()


def write_cloud_ply(
    path: str | Path,
    points_world: ArrayLike,
    scanner: ArrayLike,
    time: ArrayLike,
    plane_id: ArrayLike,
    voxel: float | None = None,
    intensity: ArrayLike | None = None,
) -> int:
    """Atomically write a binary PLY with attributes scanner, time, plane_id (and intensity,
    when given); return the count.

    ``voxel`` (m) thins the cloud to one real point per voxel (see :func:`voxel_thin`). The file
    has open3d's layout (x, y, z and time as doubles, scanner and plane_id as ints); it is
    written with numpy, a chunk of points at a time (open3d's writer took longer, and its
    import alone half a second); :func:`cloud_ply_writer` writes the same file from chunks.
    """
    target = Path(path)
    cloud = _as_cloud(points_world, scanner, time, plane_id, str(target), intensity)
    if voxel is not None:
        if not voxel > 0:
            raise OutputFileError(f"{target}: voxel size must be > 0, got {voxel}")
        keep = voxel_thin(cloud.points_world, voxel)
        cloud = CloudRecord(
            cloud.points_world[keep], cloud.scanner[keep], cloud.time[keep], cloud.plane_id[keep],
            None if cloud.intensity is None else cloud.intensity[keep],
        )
    with cloud_ply_writer(target, intensity=cloud.intensity is not None) as w:
        w.write(cloud.points_world, cloud.scanner, cloud.time, cloud.plane_id, cloud.intensity)
    return len(cloud)


def cloud_ply_layout(path: str | Path) -> tuple[int, int]:
    """(number of points, byte offset of the first) of a cloud.ply; a file that is not a binary
    little-endian PLY with :func:`write_cloud_ply`'s vertex properties (open3d's layout), or is
    truncated, is an OutputFileError naming it."""
    n, offset, _ = cloud_ply_format(path)
    return n, offset


def cloud_ply_has_intensity(path: str | Path) -> bool:
    """Whether a cloud.ply has the ``intensity`` property (see :func:`cloud_ply_layout`)."""
    return cloud_ply_format(path)[2]


def cloud_ply_format(path: str | Path) -> tuple[int, int, bool]:
    """(number of points, byte offset of the first, whether it has the ``intensity`` property)
    of a cloud.ply, checked as :func:`cloud_ply_layout` says."""
    p = Path(path)
    if not p.is_file():
        raise OutputFileError(f"{p}: no such file")
    with p.open("rb") as f:
        head = f.read(_PLY_MAX_HEADER)
    end = head.find(_PLY_END)
    if not head.startswith(b"ply\n") or end < 0:
        raise OutputFileError(f"{p}: not a PLY file (no 'ply' ... 'end_header' header)")
    lines = [
        ln.strip()
        for ln in head[:end].decode("ascii", errors="replace").split("\n")[1:]
        if ln.strip() and not ln.startswith(("comment", "obj_info"))
    ]
    want = [f"property {ply} {name}" for name, _, ply in _PLY_PROPERTIES]
    fmt, element, props = (lines[0] if lines else ""), (lines[1].split() if len(lines) > 1 else []), lines[2:]
    intensity = props == [*want, f"property {_PLY_INTENSITY[2]} {_PLY_INTENSITY[0]}"]
    if intensity:
        props = props[:-1]
    if fmt != "format binary_little_endian 1.0":
        raise OutputFileError(f"{p}: '{fmt}' is not cloud.ply's format (binary_little_endian 1.0)")
    if len(element) != 3 or element[:2] != ["element", "vertex"] or not element[2].isdigit() or props != want:
        raise OutputFileError(
            f"{p}: not cloud.ply's layout (one vertex element of {', '.join(w.split()[2] for w in want)} "
            f"as {', '.join(w.split()[1] for w in want)}, then optionally intensity as float)"
        )
    n, offset = int(element[2]), end + len(_PLY_END)
    size = p.stat().st_size
    row = _ply_vertex(intensity).itemsize
    if size != offset + n * row:
        raise OutputFileError(f"{p}: {size - offset} bytes of points where {n} points take {n * row} (truncated?)")
    return n, offset, intensity


def _cloud_of_rows(rows: NDArray[np.void]) -> CloudRecord:
    """The cloud of PLY rows, as views into them (no copy)."""
    n = rows.shape[0]
    x = rows["x"]
    points = np.lib.stride_tricks.as_strided(x, shape=(n, 3), strides=(x.strides[0], x.itemsize), writeable=False)
    intensity = rows["intensity"] if "intensity" in (rows.dtype.names or ()) else None
    return CloudRecord(points_world=points, scanner=rows["scanner"], time=rows["time"], plane_id=rows["plane_id"],
                       intensity=intensity)


def _ply_rows(path: str | Path, chunk: int) -> Iterator[NDArray[np.void]]:
    """The rows of a cloud.ply, ``chunk`` at a time (each read into its own array)."""
    n, offset, intensity = cloud_ply_format(path)
    vertex = _ply_vertex(intensity)
    with Path(path).open("rb") as f:
        f.seek(offset)
        for start in range(0, n, chunk):
            want = min(chunk, n - start)
            rows = np.fromfile(f, dtype=vertex, count=want)
            if rows.shape[0] != want:
                raise OutputFileError(f"{path}: truncated at point {start + rows.shape[0]} of {n}")
            yield rows


def iter_cloud_ply(path: str | Path, chunk: int = _PLY_CHUNK) -> Iterator[CloudRecord]:
    """The points of a cloud.ply (world frame) in file order, ``chunk`` points at a time: a
    pass over a cloud that is not held (only the current chunk is in memory)."""
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    for rows in _ply_rows(path, chunk):
        yield _cloud_of_rows(rows)


def read_cloud_ply(path: str | Path, step: int = 1, chunk: int = _PLY_CHUNK) -> CloudRecord:
    """Read a cloud written by :func:`write_cloud_ply` (points in the world frame): every point,
    or with ``step`` > 1 every ``step``-th one (points 0, step, 2 step, ...), read ``chunk``
    points at a time so that only the kept points are held. The columns are views into one
    array of the file's rows (40 bytes a point, 44 with intensities)."""
    if step < 1 or chunk < 1:
        raise ValueError(f"step and chunk must be >= 1, got {step} and {chunk}")
    n, _, intensity = cloud_ply_format(path)
    if step == 1:
        kept = list(_ply_rows(path, max(n, 1)))  # one read of all the rows
    else:
        kept, start = [], 0
        for rows in _ply_rows(path, chunk):
            kept.append(rows[(-start) % step :: step].copy())  # a copy: the chunk is not kept
            start += rows.shape[0]
    if len(kept) == 1:
        return _cloud_of_rows(kept[0])
    return _cloud_of_rows(np.concatenate(kept) if kept else np.zeros(0, dtype=_ply_vertex(intensity)))


# -------------------------------------------------------------------------------- segments


@dataclass(frozen=True)
class SegmentTable:
    """One row per segment: which scan of which scanner, its inclusive beam range, its plane.

    ``scanner`` indexes ``scanner_names``; ``scan_index`` is the row of that scanner's scan in
    its stream (and in the ground truth's ``beams.npz``); ``stamp`` is that scan's first-beam
    time (s); ``plane_id`` is -1 when the segment is not associated with a plane.
    """

    scanner_names: tuple[str, ...]
    scanner: NDArray[np.int32]
    scan_index: NDArray[np.int64]
    stamp: FloatArray
    first_beam: NDArray[np.int32]
    last_beam: NDArray[np.int32]
    plane_id: NDArray[np.int32]

    def __len__(self) -> int:
        return int(self.scanner.shape[0])


_SEGMENT_COLUMNS: dict[str, type[np.generic]] = {
    "scanner": np.int32,
    "scan_index": np.int64,
    "stamp": np.float64,
    "first_beam": np.int32,
    "last_beam": np.int32,
    "plane_id": np.int32,
}


def make_segment_table(
    scanner_names: Sequence[str],
    scanner: ArrayLike,
    scan_index: ArrayLike,
    stamp: ArrayLike,
    first_beam: ArrayLike,
    last_beam: ArrayLike,
    plane_id: ArrayLike,
    what: str = "segments",
) -> SegmentTable:
    """Build a validated :class:`SegmentTable` (dtypes fixed, shapes and ranges checked)."""
    raw = {
        "scanner": scanner,
        "scan_index": scan_index,
        "stamp": stamp,
        "first_beam": first_beam,
        "last_beam": last_beam,
        "plane_id": plane_id,
    }
    cols: dict[str, Any] = {}
    for name, dtype in _SEGMENT_COLUMNS.items():
        arr = np.asarray(raw[name])
        if arr.ndim != 1:
            raise OutputFileError(f"{what}: column {name} must be 1-D, got shape {arr.shape}")
        cols[name] = arr.astype(dtype, copy=False)
    n = cols["scanner"].shape[0]
    if any(c.shape[0] != n for c in cols.values()):
        raise OutputFileError(f"{what}: columns have different lengths")
    names = tuple(str(s) for s in scanner_names)
    if n and (cols["scanner"].min() < 0 or cols["scanner"].max() >= len(names)):
        raise OutputFileError(f"{what}: scanner index outside scanner_names ({len(names)})")
    if n and (np.any(cols["first_beam"] < 0) or np.any(cols["last_beam"] < cols["first_beam"])):
        raise OutputFileError(f"{what}: need 0 <= first_beam <= last_beam")
    return SegmentTable(scanner_names=names, **cols)


def write_segments_npz(path: str | Path, table: SegmentTable) -> Path:
    """Atomically write the segment table as an uncompressed ``.npz``."""
    target = Path(path)
    arrays = {name: getattr(table, name) for name in _SEGMENT_COLUMNS}
    with atomic_path(target) as tmp, tmp.open("wb") as f:
        np.savez(f, scanner_names=np.asarray(table.scanner_names, dtype=np.str_), **arrays)
    return target


def read_segments_npz(path: str | Path) -> SegmentTable:
    """Read a segment table written by :func:`write_segments_npz`."""
    p = Path(path)
    if not p.is_file():
        raise OutputFileError(f"{p}: no such file")
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise OutputFileError(f"{p}: not a readable .npz ({e})") from None
    missing = [k for k in ("scanner_names", *_SEGMENT_COLUMNS) if k not in data]
    if missing:
        raise OutputFileError(f"{p}: missing array(s) {', '.join(missing)}")
    cols = {k: data[k] for k in _SEGMENT_COLUMNS}
    return make_segment_table([str(s) for s in data["scanner_names"].tolist()], what=str(p), **cols)


# --------------------------------------------------------------------------------- summary


def write_summary_json(path: str | Path, summary: Mapping[str, Any]) -> Path:
    """Atomically write the run summary (config, counts, timings, residual statistics)."""
    return write_json(path, dict(summary))


def read_summary_json(path: str | Path) -> dict[str, Any]:
    """Read a run summary; it must be a JSON object."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise OutputFileError(f"{path}: expected a JSON object")
    return data
