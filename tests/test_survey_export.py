"""Survey exports of a run's cloud (LAS, LAZ, E57, PCD): each file read back by its own library
(laspy, pye57, open3d) with the same count and coordinates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from backpack_slam.cli import main
from slam.export import write_cloud_ply, write_trajectory_tum
from slam.survey import export_cloud


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("run")
    rng = np.random.default_rng(0)
    n = 5000
    t = np.sort(rng.uniform(100.0, 110.0, n))
    pts = rng.uniform(-20, 20, (n, 3))
    write_cloud_ply(d / "cloud.ply", pts, rng.integers(0, 3, n), t, rng.integers(-1, 40, n))
    times = np.linspace(99.0, 111.0, 25)
    T = np.repeat(np.eye(4)[None], len(times), axis=0)
    ang = 0.3 * (times - 99.0)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(ang), -np.sin(ang), np.sin(ang), np.cos(ang)
    T[:, :3, 3] = np.column_stack((times - 99.0, 0.5 * (times - 99.0), np.full(len(times), 1.9)))
    write_trajectory_tum(d / "trajectory.tum", times, T)
    return d


def _cloud(run_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from slam.export import read_cloud_ply

    c = read_cloud_ply(run_dir / "cloud.ply")
    return np.array(c.points_world), np.array(c.scanner), np.array(c.time), np.array(c.plane_id)


@pytest.mark.parametrize("fmt", ["las", "laz"])
def test_las_and_laz_round_trip(run_dir: Path, tmp_path: Path, fmt: str) -> None:
    import laspy

    pts, scanner, t, pid = _cloud(run_dir)
    out = tmp_path / f"c.{fmt}"
    assert export_cloud(run_dir / "cloud.ply", out) == len(pts)
    las = laspy.read(out)
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    assert len(las.points) == len(pts)
    np.testing.assert_allclose(np.column_stack((las.x, las.y, las.z)), pts, atol=0.51e-4)
    np.testing.assert_array_equal(las.point_source_id, scanner)
    np.testing.assert_array_equal(las.plane_id, pid)
    np.testing.assert_array_equal(las.gps_time, t)
    assert list(out.parent.glob(".*tmp*")) == []


def test_pcd_round_trip(run_dir: Path, tmp_path: Path) -> None:
    import open3d as o3d

    pts, scanner, t, pid = _cloud(run_dir)
    out = tmp_path / "c.pcd"
    export_cloud(run_dir / "cloud.ply", out)
    pc = o3d.t.io.read_point_cloud(str(out))
    np.testing.assert_array_equal(pc.point.positions.numpy(), pts)
    np.testing.assert_array_equal(pc.point.time.numpy().ravel(), t)
    np.testing.assert_array_equal(pc.point.plane_id.numpy().ravel(), pid)
    np.testing.assert_array_equal(pc.point.scanner.numpy().ravel(), scanner)


def test_e57_scans_carry_the_trajectory_poses(run_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pye57

    import slam.survey

    monkeypatch.setattr(slam.survey, "E57_CHUNK", 1000)  # several scans, each with its own pose
    pts, *_ = _cloud(run_dir)
    out = tmp_path / "c.e57"
    export_cloud(run_dir / "cloud.ply", out, trajectory_tum=run_dir / "trajectory.tum")
    e57 = pye57.E57(str(out))
    assert e57.scan_count == 5
    got, local = [], []
    for i in range(e57.scan_count):
        got.append(np.column_stack([e57.read_scan(i, transform=True, ignore_missing_fields=True)[k]
                                    for k in ("cartesianX", "cartesianY", "cartesianZ")]))
        local.append(np.column_stack([e57.read_scan_raw(i)[k] for k in ("cartesianX", "cartesianY", "cartesianZ")]))
    np.testing.assert_allclose(np.vstack(got), pts, atol=1e-6)
    assert np.abs(np.vstack(local) - pts).max() > 1.0  # stored in the body frame, not the world's
    with pytest.raises(ValueError, match="trajectory"):
        export_cloud(run_dir / "cloud.ply", tmp_path / "d.e57")


def test_export_command_and_its_errors(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(run_dir), "--out", str(tmp_path / "x.laz")]) == 0
    assert (tmp_path / "x.laz").is_file()
    assert main(["export", str(run_dir), "--format", "xyz"]) == 2
    assert "unknown cloud format 'xyz'" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "nothing")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty")]) == 2
    assert "cloud.ply" in capsys.readouterr().err
