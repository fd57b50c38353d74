"""A stranger's recording as a one-command job: the rig from the bag's own transforms (topics
renamed, no rig file), the Cartographer backpack layout (MultiEchoLaserScan, URDF frames, IMU),
refusals that name their cause (a rig without the IMU it needs, a rig that is not the bag's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import backpack_slam as bs
from backpack_slam.cli import main
from common.rig import resolve_rig, write_rig
from slam.evaluate import evaluate

DURATION = 8.0


def _renamed_rig(tmp: Path) -> Path:
    rig = resolve_rig("itc_backpack")
    scanners = [s.model_copy(update={"topic": f"/sensors/laser_{i}/scan", "frame_id": f"laser_{i}_link"})
                for i, s in enumerate(rig.scanners)]
    path = tmp / "renamed.yaml"
    write_rig(path, rig.model_copy(update={"name": "renamed", "scanners": scanners, "body_frame": "base_link"}))
    return path


@pytest.fixture(scope="module")
def renamed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp("renamed")
    rig = _renamed_rig(d)
    sim = bs.simulate("demo", rig, duration=DURATION, seed=3, out=d / "walk.bag")
    return sim.bag, sim.gt, rig


def test_topics_renamed_and_no_rig_file_reach_the_hand_written_rigs_accuracy(renamed, tmp_path: Path) -> None:
    bag, gt, rig = renamed
    auto = bs.run(bag, out=tmp_path / "auto")
    hand = bs.run(bag, rig=rig, out=tmp_path / "hand")
    assert any("rig built from the recording's transforms" in n for n in auto.summary["rig_checks"])
    assert auto.health.verdict in ("ok", "degraded") and hand.health.verdict in ("ok", "degraded")
    ate_auto = evaluate(auto.run_dir, gt).trajectory.ate["start_aligned"].rmse
    ate_hand = evaluate(hand.run_dir, gt).trajectory.ate["start_aligned"].rmse
    assert ate_hand < 0.005 and ate_auto < 0.005
    assert abs(ate_auto - ate_hand) < 0.001
    assert len(auto.plane_ids) == pytest.approx(len(hand.plane_ids), abs=3)


def test_the_default_rig_on_another_rigs_recording_is_refused(renamed, tmp_path: Path, capsys) -> None:
    bag, _, rig = renamed
    r = resolve_rig(rig)
    left, right = r.scanners[1], r.scanners[2]
    moved = r.model_copy(update={"scanners": [r.scanners[0],
                                              left.model_copy(update={"T_body_scanner": right.T_body_scanner}),
                                              right.model_copy(update={"T_body_scanner": left.T_body_scanner})]})
    path = tmp_path / "swapped.yaml"
    write_rig(path, moved)  # the left and right mounts swapped: 40 deg and 0.5 m off the recording's
    out = tmp_path / "out"
    assert main(["run", str(bag), "--rig", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not match the transforms of" in err[0] and "scanner 'left' differs by" in err[0]
    assert not out.exists()


@pytest.fixture(scope="module")
def cartographer(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    d = tmp_path_factory.mktemp("carto")
    with_imu = bs.simulate("demo", "cartographer_backpack_2d", duration=DURATION, seed=2, out=d / "imu.bag", imu=True)
    without = bs.simulate("demo", "cartographer_backpack_2d", duration=3.0, seed=2, out=d / "noimu.bag")
    return with_imu.bag, with_imu.gt, without.bag


def test_cartographer_layout_runs_end_to_end_with_its_imu(cartographer, tmp_path: Path) -> None:
    bag, gt, _ = cartographer
    res = bs.run(bag, out=tmp_path / "carto", progress=False)
    assert res.summary["counts"]["imu_used"] == 1
    assert any("left to an IMU: pitch" in n for n in res.summary["rig_checks"])
    ate = evaluate(res.run_dir, gt).trajectory.ate["start_aligned"].rmse
    assert ate < 0.02, ate
    assert res.health.verdict in ("ok", "degraded")
    assert np.isfinite(res.T_world_body).all()


def test_cartographer_layout_without_imu_is_refused_with_the_reason(cartographer, tmp_path: Path, capsys) -> None:
    _, _, bag = cartographer
    assert main(["run", str(bag), "--out", str(tmp_path / "x"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "leaves pitch to an IMU" in err[0] and "has no IMU" in err[0]
    assert not (tmp_path / "x").exists()


def test_rig_command_builds_the_rig_from_the_bag_or_a_urdf(cartographer, tmp_path: Path, capsys) -> None:
    bag, _, _ = cartographer
    assert main(["rig", str(bag), "--out", str(tmp_path / "rig.yaml")]) == 0
    text = capsys.readouterr().out
    assert "left to an IMU: pitch" in text and "MultiEchoLaserScan" in text
    built = resolve_rig(tmp_path / "rig.yaml")
    ref = resolve_rig("cartographer_backpack_2d")
    for a, b in zip(built.scanners, ref.scanners, strict=True):
        np.testing.assert_allclose(a.T_body_scanner.matrix(), b.T_body_scanner.matrix(), atol=1e-5)
    urdf = Path(__file__).parent / "data" / "backpack_2d.urdf"
    assert main(["rig", str(bag), "--urdf", str(urdf), "--base", "base_link"]) == 0
    assert main(["rig", str(bag), "--urdf", str(urdf), "--base", "nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown frame 'nowhere'" in err[0]


def test_a_bag_without_transforms_or_frames_unknown_to_the_urdf_is_one_line(renamed, tmp_path: Path, capsys) -> None:
    from fuzz_inputs import BagMessages

    bag, _, _ = renamed
    bm = BagMessages.read(bag, "ros1")
    bm.items = [i for i in bm.items if i.topic not in ("/tf_static", "/tf")]
    bare = tmp_path / "no_tf.bag"
    bm.write(bare)
    assert main(["run", str(bare), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_tf.bag" in err[0] and "no /tf_static" in err[0] and "--rig" in err[0]
    assert not (tmp_path / "o").exists()
    urdf = Path(__file__).parent / "data" / "backpack_2d.urdf"  # the Cartographer frames, not this bag's laser_0_link
    assert main(["run", str(bag), "--urdf", str(urdf), "--out", str(tmp_path / "u"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "backpack_2d.urdf" in err[0] and "unknown frame 'laser_0_link'" in err[0]
    assert not (tmp_path / "u").exists()


def test_a_rig_whose_scanner_geometry_is_not_the_bags_is_one_line(renamed, tmp_path: Path, capsys) -> None:
    bag, _, rig = renamed
    r = resolve_rig(rig)
    urg = r.model_copy(update={"scanners": [r.scanners[0].model_copy(update={"model": "urg04lx"}), *r.scanners[1:]]})
    path = tmp_path / "urg.yaml"
    write_rig(path, urg)
    assert main(["run", str(bag), "--rig", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "topic /sensors/laser_0/scan: number of beams 1081 in the recording, 726" in err[0]
