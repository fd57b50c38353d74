"""The echo of a MultiEchoLaserScan a run reads (``input.echo``: first, last, strongest) and the
returns' intensities, from the messages through the scans into cloud.ply and the survey exports
(LAS/LAZ, E57, PCD); a cloud without intensities has no such property."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fuzz_inputs import BagMessages, Item

import backpack_slam as bs
from backpack_slam.cli import main
from common.config import ConfigError
from slam.config import SlamConfig, load_slam_config
from slam.export import (
    cloud_ply_has_intensity,
    read_cloud_ply,
    write_cloud_ply,
    write_trajectory_tum,
)
from slam.io.source import LASERSCAN, MULTIECHO, BagSource
from slam.survey import export_cloud, las_intensity, las_intensity_scale

N_BEAMS = 5


def _echo(bm: BagMessages, values: list[float]) -> Any:
    return bm.new("sensor_msgs/msg/LaserEcho", echoes=np.asarray(values, dtype=np.float32))


def _tiny_bag(path: Path, multi_intensities: bool = True, scan_intensities: bool = True) -> Path:
    """Two scans on /multi (MultiEchoLaserScan) and two on /single (LaserScan). /multi's beam k:
    echoes (1 + k, 2 + k, 3 + k) m with intensities (10, 30, 20) + k, except beam 1 with one echo
    (5 m, intensity 7), beam 2 with none, beam 3 with an intensity list not matching its echoes."""
    bm = BagMessages("ros1", [], set())
    for i in range(2):
        stamp = 1_000_000_000 + i * 100_000_000
        ranges, inten = [], []
        for k in range(N_BEAMS):
            if k == 1:
                ranges.append(_echo(bm, [5.0]))
                inten.append(_echo(bm, [7.0]))
            elif k == 2:
                ranges.append(_echo(bm, []))
                inten.append(_echo(bm, []))
            else:
                ranges.append(_echo(bm, [1.0 + k, 2.0 + k, 3.0 + k]))
                inten.append(_echo(bm, [10.0 + k, 30.0 + k] if k == 3 else [10.0 + k, 30.0 + k, 20.0 + k]))
        multi = bm.new(MULTIECHO, header=bm.header(stamp, "multi"), angle_min=-0.5, angle_max=0.5,
                       angle_increment=0.25, time_increment=1e-4, scan_time=0.1, range_min=0.1, range_max=30.0,
                       ranges=ranges, intensities=inten if multi_intensities else [])
        bm.items.append(Item("/multi", MULTIECHO, stamp, obj=multi))
        single = bm.new(LASERSCAN, header=bm.header(stamp + 1000, "single"), angle_min=-0.5, angle_max=0.5,
                        angle_increment=0.25, time_increment=1e-4, scan_time=0.1, range_min=0.1, range_max=30.0,
                        ranges=np.array([1.0, 2.0, np.inf, 4.0, 5.0], dtype=np.float32),
                        intensities=np.array([100, 200, 300, 400, 500], dtype=np.float32) if scan_intensities
                        else np.zeros(0, dtype=np.float32))
        bm.items.append(Item("/single", LASERSCAN, stamp + 1000, obj=single))
    bm.write(path)
    return path


@pytest.mark.parametrize(("echo", "ranges", "intensities"), [
    ("first", [1.0, 5.0, np.inf, 4.0, 5.0], [10.0, 7.0, np.nan, np.nan, 14.0]),
    ("last", [3.0, 5.0, np.inf, 6.0, 7.0], [20.0, 7.0, np.nan, np.nan, 24.0]),
    ("strongest", [2.0, 5.0, np.inf, 4.0, 6.0], [30.0, 7.0, np.nan, np.nan, 34.0]),
])
def test_each_echo_choice_picks_its_echo_and_that_echos_intensity(tmp_path: Path, echo: str, ranges: list[float],
                                                                   intensities: list[float]) -> None:
    bag = _tiny_bag(tmp_path / "tiny.bag")
    with BagSource(bag) as src:
        lines = list(src.scans(topics=["/multi"], echo=echo))  # type: ignore[arg-type]
    assert len(lines) == 2
    for line in lines:
        np.testing.assert_array_equal(line.ranges, ranges)
        assert line.intensities is not None and line.intensities.dtype == np.float32
        np.testing.assert_array_equal(line.intensities, np.asarray(intensities, dtype=np.float32))


def test_laserscan_intensities_are_kept_and_absent_when_the_messages_have_none(tmp_path: Path) -> None:
    with BagSource(_tiny_bag(tmp_path / "with.bag")) as src:
        stream = src.scans(topics=["/single", "/multi"])
        lines = list(stream)
        assert stream.index.intensities
    single = [ln for ln in lines if ln.scanner_id == "single"]
    assert len(single) == 2
    np.testing.assert_array_equal(single[0].intensities, [100, 200, 300, 400, 500])
    np.testing.assert_array_equal(single[0].reversed().intensities, [500, 400, 300, 200, 100])
    with BagSource(_tiny_bag(tmp_path / "without.bag", multi_intensities=False, scan_intensities=False)) as src:
        stream = src.scans(topics=["/single", "/multi"], echo="strongest")
        lines = list(stream)
        assert not stream.index.intensities
    assert all(ln.intensities is None for ln in lines)
    multi = [ln for ln in lines if ln.scanner_id == "multi"]
    np.testing.assert_array_equal(multi[0].ranges, [1.0, 5.0, np.inf, 4.0, 5.0])  # strongest without intensities: first


def test_a_wrong_echo_is_one_line_naming_the_key_and_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "echo.yaml"
    bad.write_text("input:\n  echo: middle\n")
    with pytest.raises(ConfigError, match=r"echo\.yaml.*input\.echo"):
        load_slam_config(bad)
    assert SlamConfig().input.echo == "first"
    bag = _tiny_bag(tmp_path / "tiny.bag")
    assert main(["run", str(bag), "--config", str(bad), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "echo.yaml" in err[0] and "input.echo" in err[0]
    with BagSource(bag) as src, pytest.raises(ValueError, match="echo must be one of first, last, strongest"):
        src.scans(topics=["/multi"], echo="middle")  # type: ignore[arg-type]


# ------------------------------------------------------------------------- a run end to end

TRUE_INTENSITY = 1000.0  # + beam index: the true return is the strongest of three echoes


def _ghost_echoes(bag: Path, out: Path) -> Path:
    """The Cartographer-layout recording with every beam's return as the middle of three echoes
    (a ghost at 0.6 r before it, one at r + 2 m after it) whose intensities are 1, 1000 + beam
    index, 2: only the strongest echo is the world."""
    bm = BagMessages.read(bag, "ros1")
    for item in bm.of(["horizontal_laser_2d", "vertical_laser_2d"], MULTIECHO):
        m = bm.msg(item)
        ranges, inten = [], []
        for k, e in enumerate(m.ranges):
            if len(e.echoes) == 0:
                ranges.append(e)
                inten.append(_echo(bm, []))
                continue
            r = float(e.echoes[0])
            ranges.append(_echo(bm, [0.6 * r, r, r + 2.0]))
            inten.append(_echo(bm, [1.0, TRUE_INTENSITY + k, 2.0]))
        bm.set(item, bm.new(MULTIECHO, header=m.header, angle_min=m.angle_min, angle_max=m.angle_max,
                            angle_increment=m.angle_increment, time_increment=m.time_increment,
                            scan_time=m.scan_time, range_min=m.range_min, range_max=m.range_max, ranges=ranges,
                            intensities=inten))
    bm.write(out)
    return out


@pytest.fixture(scope="module")
def ghost_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp("ghosts")
    sim = bs.simulate("demo", "cartographer_backpack_2d", duration=6.0, seed=2, out=d / "clean.bag", imu=True)
    assert BagMessages.read(sim.bag, "ros1").of("horizontal_laser_2d", MULTIECHO)  # the layout's topic names
    bag = _ghost_echoes(sim.bag, d / "ghosts.bag")
    cfg = SlamConfig.model_validate({"input": {"echo": "strongest"}, "output": {"rerun": False}})
    res = bs.run(bag, config=cfg, out=d / "run")
    return res.run_dir, sim.gt, bag


def test_a_run_reads_the_configured_echo_and_keeps_its_intensities(ghost_run: tuple[Path, Path, Path]) -> None:
    run_dir, gt, _ = ghost_run
    ate = bs.evaluate(run_dir, gt, write=False).trajectory.ate["start_aligned"].rmse
    assert ate < 0.02, ate  # the ghosts (first and last echoes) would not make this walk
    assert cloud_ply_has_intensity(run_dir / "cloud.ply")
    c = read_cloud_ply(run_dir / "cloud.ply")
    assert c.intensity is not None and c.intensity.dtype == np.float32 and len(c) > 10_000
    assert np.all((c.intensity >= TRUE_INTENSITY) & (c.intensity < TRUE_INTENSITY + 1081))  # every point: its true echo
    assert len(np.unique(c.intensity)) > 500  # per beam, not one value


def test_reading_a_ghost_echo_fails_naming_the_echo(ghost_run: tuple[Path, Path, Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """The same recording read with ``input.echo: first`` (the ghost at 0.6 r: a scaled copy of the
    scene, whose lines fit as well as the surface's, walked at 0.6 times the speed the IMU
    measures) is 0.69 m off. The IMU factors' residuals give it away (2.5 times the IMU's noise;
    0.16 with the strongest echo) and the recording has several echoes per beam, so the run
    fails with exit code 3 and one line naming the echo it read; the strongest echo is healthy."""
    import json

    from slam.health import EXIT_FAILED

    run_dir, gt, bag = ghost_run
    good = json.loads((run_dir / "summary.json").read_text())["health"]
    assert good["verdict"] == "ok" and good["measures"]["several_echoes_share"] > 0.9, good
    assert good["measures"]["imu_rms_whitened"] < 0.5, good
    cfg = tmp_path / "first.yaml"
    cfg.write_text("input:\n  echo: first\noutput:\n  cloud: false\n  rerun: false\n")
    out = tmp_path / "first"
    capsys.readouterr()
    rc = main(["run", str(bag), "--config", str(cfg), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.splitlines()
    assert rc == EXIT_FAILED, err
    failures = [ln for ln in err if "failure:" in ln]
    assert len(failures) == 1 and "disagrees with the IMU" in failures[0], err
    assert "read the first echo (input.echo)" in failures[0] and "input.echo: last or strongest" in failures[0]
    health = json.loads((out / "summary.json").read_text())["health"]
    assert health["verdict"] == "failed" and [p["code"] for p in health["problems"]] == ["imu_disagrees"], health
    assert bs.evaluate(out, gt, write=False).trajectory.ate["start_aligned"].rmse > 0.2  # the map is wrong indeed


def test_the_runs_intensities_round_trip_through_las_e57_and_pcd(ghost_run: tuple[Path, Path, Path],
                                                                 tmp_path: Path) -> None:
    import laspy
    import open3d as o3d
    import pye57

    run_dir, _, _ = ghost_run
    c = read_cloud_ply(run_dir / "cloud.ply")
    assert c.intensity is not None
    for fmt in ("las", "laz"):
        export_cloud(run_dir / "cloud.ply", tmp_path / f"c.{fmt}")
        las = laspy.read(tmp_path / f"c.{fmt}")
        assert len(las.points) == len(c)
        np.testing.assert_array_equal(np.asarray(las.raw_intensity), c.intensity)
        np.testing.assert_array_equal(np.asarray(las.intensity),
                                      np.rint(c.intensity.astype(np.float64) * (65535.0 / float(c.intensity.max()))))
    export_cloud(run_dir / "cloud.ply", tmp_path / "c.e57", trajectory_tum=run_dir / "trajectory.tum")
    e57 = pye57.E57(str(tmp_path / "c.e57"))
    got = np.concatenate([e57.read_scan_raw(i)["intensity"] for i in range(e57.scan_count)])
    np.testing.assert_array_equal(got, c.intensity)
    export_cloud(run_dir / "cloud.ply", tmp_path / "c.pcd")
    pcd = o3d.t.io.read_point_cloud(str(tmp_path / "c.pcd"))
    np.testing.assert_array_equal(pcd.point["intensity"].numpy().ravel(), c.intensity)


# ----------------------------------------------------------------------- files without a run


def _cloud(n: int, rng: np.random.Generator) -> dict[str, Any]:
    return {"points_world": rng.uniform(-20, 20, (n, 3)), "scanner": rng.integers(0, 3, n),
            "time": np.sort(rng.uniform(100.0, 110.0, n)), "plane_id": rng.integers(-1, 40, n)}


def _trajectory(path: Path) -> Path:
    times = np.linspace(99.0, 111.0, 13)
    T = np.repeat(np.eye(4)[None], len(times), axis=0)
    T[:, :3, 3] = np.column_stack((times - 99.0, np.zeros(len(times)), np.full(len(times), 1.5)))
    write_trajectory_tum(path, times, T)
    return path


def test_intensities_with_gaps_round_trip_and_a_cloud_without_has_none(tmp_path: Path) -> None:
    import laspy
    import pye57

    rng = np.random.default_rng(4)
    n = 3000
    cloud = _cloud(n, rng)
    inten = rng.uniform(0.0, 4000.0, n).astype(np.float32)
    inten[::7] = np.nan  # points whose message had none
    write_cloud_ply(tmp_path / "cloud.ply", intensity=inten, **cloud)
    back = read_cloud_ply(tmp_path / "cloud.ply")
    np.testing.assert_array_equal(back.intensity, inten)
    np.testing.assert_array_equal(back.points_world, cloud["points_world"])
    thin = read_cloud_ply(tmp_path / "cloud.ply", step=3, chunk=100)
    np.testing.assert_array_equal(thin.intensity, inten[::3])
    scale = las_intensity_scale(tmp_path / "cloud.ply")
    assert scale == 65535.0 / float(np.nanmax(inten))
    export_cloud(tmp_path / "cloud.ply", tmp_path / "c.las")
    las = laspy.read(tmp_path / "c.las")
    np.testing.assert_array_equal(np.asarray(las.raw_intensity), inten)
    want = las_intensity(inten, scale)
    assert want[0] == 0 and want.max() == 65535
    np.testing.assert_array_equal(np.asarray(las.intensity), want)

    write_cloud_ply(tmp_path / "plain.ply", **cloud)
    assert not cloud_ply_has_intensity(tmp_path / "plain.ply")
    assert b"intensity" not in (tmp_path / "plain.ply").read_bytes()[:400]
    assert read_cloud_ply(tmp_path / "plain.ply").intensity is None
    export_cloud(tmp_path / "plain.ply", tmp_path / "p.las")
    plain = laspy.read(tmp_path / "p.las")
    assert "raw_intensity" not in plain.point_format.dimension_names and not np.asarray(plain.intensity).any()
    export_cloud(tmp_path / "plain.ply", tmp_path / "p.e57", trajectory_tum=_trajectory(tmp_path / "t.tum"))
    assert "intensity" not in pye57.E57(str(tmp_path / "p.e57")).read_scan_raw(0)
    export_cloud(tmp_path / "plain.ply", tmp_path / "p.pcd")
    assert b"intensity" not in (tmp_path / "p.pcd").read_bytes()[:400]
