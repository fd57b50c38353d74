"""Round trips of every output writer/reader, and atomicity of the writes."""

from __future__ import annotations

from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.atomic import OutputFileError, atomic_path
from slam.export import (
    PlaneRecord,
    make_segment_table,
    read_cloud_ply,
    read_planes_json,
    read_segments_npz,
    read_summary_json,
    read_trajectory_tum,
    voxel_thin,
    write_cloud_ply,
    write_planes_json,
    write_segments_npz,
    write_summary_json,
    write_trajectory_tum,
)


def _poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 1, (n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(0, 20, (n, 3))
    return T


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name)


def test_trajectory_round_trip(tmp_path: Path) -> None:
    times = 1.7e9 + np.arange(50) * 0.025
    T = _poses(50)
    path = write_trajectory_tum(tmp_path / "trajectory.tum", times, T)
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 8
    t2, T2 = read_trajectory_tum(path)
    np.testing.assert_allclose(t2, times, rtol=0, atol=1e-9)
    # Quaternions may flip sign; compare matrices.
    np.testing.assert_allclose(T2, T, atol=1e-9)
    assert _leftovers(tmp_path) == []


def test_trajectory_bad_shapes(tmp_path: Path) -> None:
    with pytest.raises(OutputFileError, match=r"trajectory\.tum"):
        write_trajectory_tum(tmp_path / "trajectory.tum", np.arange(3.0), np.zeros((2, 4, 4)))
    assert not (tmp_path / "trajectory.tum").exists()
    (tmp_path / "bad.tum").write_text("1 2 3\n")
    with pytest.raises(OutputFileError, match=r"bad\.tum"):
        read_trajectory_tum(tmp_path / "bad.tum")


def test_trajectory_reader_is_evos(tmp_path: Path) -> None:
    from evo.tools import file_interface

    path = write_trajectory_tum(tmp_path / "trajectory.tum", 1.7e9 + np.arange(200) * 0.005, _poses(200, seed=4))
    path.write_text("# t x y z qx qy qz qw\n" + path.read_text())  # a comment line, as TUM allows
    times, T = read_trajectory_tum(path)
    ref = file_interface.read_tum_trajectory_file(str(path))
    assert np.array_equal(times, np.asarray(ref.timestamps))
    np.testing.assert_allclose(T, np.asarray(ref.poses_se3), rtol=0, atol=4e-15)
    bad = {"seven.tum": ("1 2 3 4 0 0 0\n", r"seven\.tum.*8 columns"), "empty.tum": ("# nothing\n", r"empty\.tum")}
    for name, (text, message) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(OutputFileError, match=message):
            read_trajectory_tum(tmp_path / name)


def test_trajectory_rotations_are_evos(tmp_path: Path) -> None:
    from evo.core.transformations import quaternion_matrix

    q = np.random.default_rng(2).normal(0, 1, (50, 4))  # w x y z, not of unit norm
    q[7] = 0.0  # no rotation: the identity
    rows = np.column_stack((np.arange(50.0), np.zeros((50, 3)), q[:, 1:], q[:, :1]))
    np.savetxt(tmp_path / "q.tum", rows)
    _, T = read_trajectory_tum(tmp_path / "q.tum")
    R = T[:, :3, :3]
    for qi, Ri in zip(q, R, strict=True):
        np.testing.assert_allclose(Ri, quaternion_matrix(qi)[:3, :3], rtol=0, atol=4e-15)
    assert np.array_equal(R[7], np.eye(3))


def test_planes_round_trip_and_ground_truth_format(tmp_path: Path) -> None:
    cov = np.diag([1e-6, 2e-6, 3e-6])
    planes = [
        PlaneRecord(
            id=3,
            normal=np.array([0.0, 0.0, 1.0]),
            d=0.0,
            polygon=np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], float),
            kind="floor",
            n_segments=120,
            covariance=cov,
            outline="final_map",
            regions=(np.array([[0, 0, 0], [1, 0, 0], [1, 3, 0], [0, 3, 0], [0, 0, 0]], float),
                     np.array([[3, 0, 0], [4, 0, 0], [4, 3, 0], [3, 3, 0], [3, 0, 0]], float)),
        ),
        PlaneRecord(id=7, normal=np.array([0.6, 0.8, 0.0]), d=-2.5, polygon=np.zeros((0, 3))),
    ]
    path = write_planes_json(tmp_path / "planes.json", planes)
    back = read_planes_json(path)
    assert [p.id for p in back] == [3, 7]
    np.testing.assert_allclose(back[0].polygon, planes[0].polygon)
    assert back[0].covariance is not None
    np.testing.assert_allclose(back[0].covariance, cov)
    assert back[0].kind == "floor" and back[0].n_segments == 120
    assert back[0].outline == "final_map" and len(back[0].regions) == 2
    np.testing.assert_allclose(back[0].regions[1], planes[0].regions[1])
    assert back[1].outline == "" and back[1].regions == ()
    assert back[1].covariance is None and back[1].polygon.shape == (0, 3)
    np.testing.assert_allclose(back[1].normal, [0.6, 0.8, 0.0])
    assert back[1].d == pytest.approx(-2.5)

    gt = tmp_path / "gt_planes.json"
    gt.write_text(
        '{"convention": "n . x + d = 0, world frame, metres", "planes": '
        '[{"id": 0, "kind": "wall", "normal": [2, 0, 0], "d": -4, "polygon": [[2,0,0],[2,1,0],[2,1,1]]}]}'
    )
    (g,) = read_planes_json(gt)
    np.testing.assert_allclose(g.normal, [1, 0, 0])
    assert g.d == pytest.approx(-2.0) and g.n_segments == 0

    with pytest.raises(OutputFileError, match="duplicate"):
        write_planes_json(tmp_path / "dup.json", [planes[0], planes[0]])
    (tmp_path / "broken.json").write_text('{"planes": [{"id": 1}]}')
    with pytest.raises(OutputFileError, match=r"broken\.json: plane #0: missing key"):
        read_planes_json(tmp_path / "broken.json")


def test_cloud_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n = 1000
    pts = rng.uniform(-50, 50, (n, 3))
    scanner = rng.integers(0, 3, n)
    time = 1.7e9 + np.sort(rng.uniform(0, 600, n))
    plane = rng.integers(-1, 40, n)
    count = write_cloud_ply(tmp_path / "cloud.ply", pts, scanner, time, plane)
    assert count == n
    c = read_cloud_ply(tmp_path / "cloud.ply")
    np.testing.assert_array_equal(c.points_world, pts)
    np.testing.assert_array_equal(c.scanner, scanner)
    np.testing.assert_array_equal(c.time, time)  # float64 kept exactly
    np.testing.assert_array_equal(c.plane_id, plane)
    assert c.plane_id.dtype == np.int32 and c.time.dtype == np.float64
    assert _leftovers(tmp_path) == []


def test_cloud_file_is_what_open3d_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The numpy writer (in chunks) gives open3d's PLY: the same properties and the same bytes
    after the header; empty clouds read back empty."""
    import open3d as o3d

    import slam.export

    rng = np.random.default_rng(4)
    n = 1003
    pts = rng.uniform(-50, 50, (n, 3))
    scanner = rng.integers(0, 3, n).astype(np.int32)
    time = 1.7e9 + np.sort(rng.uniform(0, 600, n))
    plane = rng.integers(-1, 40, n).astype(np.int32)
    monkeypatch.setattr(slam.export, "_PLY_CHUNK", 100)
    write_cloud_ply(tmp_path / "ours.ply", pts, scanner, time, plane)
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor.from_numpy(pts))
    for name, col in (("scanner", scanner), ("time", time), ("plane_id", plane)):
        pc.point[name] = o3d.core.Tensor.from_numpy(np.ascontiguousarray(col[:, None]))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "open3d.ply"), pc, write_ascii=False)
    ours, theirs = ((tmp_path / f).read_bytes() for f in ("ours.ply", "open3d.ply"))
    end = b"end_header\n"
    head_ours, body_ours = ours.split(end, 1)
    head_theirs, body_theirs = theirs.split(end, 1)
    assert body_ours == body_theirs
    assert [ln for ln in head_ours.splitlines() if not ln.startswith(b"comment")] == [
        ln for ln in head_theirs.splitlines() if not ln.startswith(b"comment")
    ]
    assert write_cloud_ply(tmp_path / "empty.ply", np.zeros((0, 3)), [], [], []) == 0
    assert len(read_cloud_ply(tmp_path / "empty.ply")) == 0


def test_cloud_voxel_keeps_real_points(tmp_path: Path) -> None:
    # Two tight clusters in two voxels with different attributes: each survivor must be one of
    # the input points with its own attributes (no averaging of ids).
    pts = np.array([[0.1, 0.1, 0.1], [0.12, 0.1, 0.1], [0.3, 0.1, 0.1], [1.5, 0.5, 0.5]])
    scanner = np.array([0, 1, 2, 1])
    time = np.array([10.0, 11.0, 12.0, 13.0])
    plane = np.array([5, 6, -1, 9])
    n = write_cloud_ply(tmp_path / "c.ply", pts, scanner, time, plane, voxel=1.0)
    assert n == 2
    c = read_cloud_ply(tmp_path / "c.ply")
    for p, s, t, pid in zip(c.points_world, c.scanner, c.time, c.plane_id, strict=True):
        k = int(np.flatnonzero(np.all(pts == p, axis=1))[0])
        assert (s, t, pid) == (scanner[k], time[k], plane[k])
    # the first voxel's survivor is the point nearest the voxel mean (0.1733, 0.1, 0.1)
    assert c.time[0] == 11.0
    np.testing.assert_array_equal(voxel_thin(pts, 0.05), [0, 2, 3])


def test_cloud_rejects_bad_input(tmp_path: Path) -> None:
    pts = np.zeros((3, 3))
    pts[1, 0] = np.nan
    with pytest.raises(OutputFileError, match="non-finite"):
        write_cloud_ply(tmp_path / "c.ply", pts, [0, 0, 0], [0, 1, 2], [0, 0, 0])
    with pytest.raises(OutputFileError, match="time must be"):
        write_cloud_ply(tmp_path / "c.ply", np.zeros((3, 3)), [0, 0, 0], [0, 1], [0, 0, 0])
    assert list(tmp_path.iterdir()) == []


def test_segments_round_trip(tmp_path: Path) -> None:
    t = make_segment_table(
        ["top", "left", "right"],
        scanner=[0, 2, 1],
        scan_index=[0, 0, 5],
        stamp=[0.0, 0.01, 0.135],
        first_beam=[10, 0, 500],
        last_beam=[80, 20, 1080],
        plane_id=[3, -1, 7],
    )
    write_segments_npz(tmp_path / "segments.npz", t)
    b = read_segments_npz(tmp_path / "segments.npz")
    assert b.scanner_names == ("top", "left", "right") and len(b) == 3
    for name in ("scanner", "scan_index", "stamp", "first_beam", "last_beam", "plane_id"):
        np.testing.assert_array_equal(getattr(b, name), getattr(t, name))
        assert getattr(b, name).dtype == getattr(t, name).dtype
    with pytest.raises(OutputFileError, match="scanner index"):
        make_segment_table(["a"], [1], [0], [0.0], [0], [1], [0])
    with pytest.raises(OutputFileError, match="first_beam <= last_beam"):
        make_segment_table(["a"], [0], [0], [0.0], [5], [1], [0])
    np.savez(tmp_path / "partial.npz", scanner=np.zeros(1))
    with pytest.raises(OutputFileError, match=r"partial\.npz: missing array"):
        read_segments_npz(tmp_path / "partial.npz")


def test_summary_round_trip(tmp_path: Path) -> None:
    s = {
        "segmenter": "ror",
        "counts": {"scans": np.int64(120), "planes": 14},
        "timings_s": np.array([0.5, 1.25]),
        "residual_rms": np.float32(0.003),
        "bad": float("nan"),
    }
    write_summary_json(tmp_path / "summary.json", s)
    back = read_summary_json(tmp_path / "summary.json")
    assert back["counts"] == {"scans": 120, "planes": 14}
    assert back["timings_s"] == [0.5, 1.25]
    assert back["residual_rms"] == pytest.approx(0.003)
    assert back["bad"] is None


def test_failed_write_leaves_nothing_and_keeps_old_file(tmp_path: Path) -> None:
    target = tmp_path / "summary.json"
    write_summary_json(target, {"version": 1})
    with pytest.raises(TypeError):
        write_summary_json(target, {"version": 2, "oops": object()})
    assert read_summary_json(target) == {"version": 1}

    class Boom(RuntimeError):
        pass

    with pytest.raises(Boom), atomic_path(tmp_path / "cloud.ply") as tmp:
        tmp.write_bytes(b"ply\nformat binary_little_endian 1.0\n")  # half a file
        raise Boom
    assert not (tmp_path / "cloud.ply").exists()
    assert _leftovers(tmp_path) == []


def test_failed_cloud_write_midway(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import slam.export

    def half_write(f: BinaryIO, *args: object) -> None:
        f.write(b"\0" * 10)  # the writer dies after the header and a few bytes of points
        raise KeyboardInterrupt

    monkeypatch.setattr(slam.export, "_write_ply_rows", half_write)
    with pytest.raises(KeyboardInterrupt):
        write_cloud_ply(tmp_path / "cloud.ply", np.zeros((2, 3)), [0, 0], [0.0, 1.0], [1, 1])
    assert list(tmp_path.iterdir()) == []


def test_missing_folder_is_clear(tmp_path: Path) -> None:
    with pytest.raises(OutputFileError, match="does not exist"):
        write_summary_json(tmp_path / "nope" / "summary.json", {})


def test_run_counts_take_the_runner_statistics_by_name() -> None:
    """summary.json's counts: the runner's statistics by field name, the derived ones computed,
    and ``isam2_updates`` (the runner's back-end updates) only under the iSAM2 solver."""
    from dataclasses import fields
    from types import SimpleNamespace

    from slam.run_folder import RunCounts

    derived = {"segments_associated", "isam2_updates", "cloud_points"}
    stats = {f.name: i for i, f in enumerate(fields(RunCounts)) if f.name not in derived} | {"updates": 77}
    res: Any = SimpleNamespace(stats=stats, segment_rows={"plane_id": np.array([-1, 3, 3, -1, 0])})
    isam2 = RunCounts.of(res, "isam2", cloud_points=12).to_dict()
    assert list(isam2) == [f.name for f in fields(RunCounts)]
    assert isam2["isam2_updates"] == 77 and isam2["segments_associated"] == 3 and isam2["cloud_points"] == 12
    assert all(isam2[k] == v for k, v in stats.items() if k != "updates")
    window = RunCounts.of(res, "window", cloud_points=12).to_dict()
    assert "isam2_updates" not in window and window == {k: v for k, v in isam2.items() if k != "isam2_updates"}
