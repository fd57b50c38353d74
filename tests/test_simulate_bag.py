"""Round trip: simulate a short walk in the demo world into ROS1 and ROS2 bags and read it back
with plain rosbags (AnyReader) and with slam.io.bag."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from common.rig import load_rig, resolve_rig
from simulation.run import (
    SimulationConfig,
    gt_dir_for,
    load_simulation_config,
    simulate,
)

DURATION = 3.0
RIG = resolve_rig("itc_backpack")


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def run(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param) / "run.bag"
    res = simulate("demo", "itc_backpack", duration=DURATION, seed=5, out=out, fmt=request.param, imu=True, progress=False)
    return request.param, res


def _read_all(path: Path) -> dict[str, list]:
    msgs: dict[str, list] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for conn, t_ns, raw in r.messages():
            msgs.setdefault(conn.topic, []).append((t_ns, r.deserialize(raw, conn.msgtype), conn.msgtype))
    return msgs


def test_outputs_are_complete_and_atomic(run) -> None:
    fmt, res = run
    assert res.bag.is_dir() == (fmt == "ros2") and res.bag.exists()
    assert res.gt == gt_dir_for(res.bag) and res.gt.name == "run.gt"
    assert res.bag.name == ("run.bag" if fmt == "ros1" else "run")
    names = {p.name for p in res.gt.iterdir()}
    assert {"trajectory.tum", "mesh.ply", "planes.json", "beams.npz", "rig.yaml", "meta.json", "imu.npz"} <= names
    assert not [p for p in res.bag.parent.iterdir() if p.name.startswith(".")]  # no temporaries left
    meta = json.loads((res.gt / "meta.json").read_text())
    assert meta["world"] == "demo" and meta["seed"] == 5 and meta["format"] == fmt
    assert load_rig(res.gt / "rig.yaml") == RIG


def test_plain_rosbags_round_trip(run) -> None:
    fmt, res = run
    msgs = _read_all(res.bag)
    meta = json.loads((res.gt / "meta.json").read_text())
    start = meta["start_time"]
    beams = np.load(res.gt / "beams.npz")
    for sc in RIG.scanners:
        scans = msgs[sc.topic]
        n = len(scans)
        assert abs(n - 40 * DURATION) <= 1 and n == meta["counts"]["scans"][sc.name]
        m = sc.scanner_model
        _t_ns, msg, msgtype = scans[0]
        assert msgtype == "sensor_msgs/msg/LaserScan" and msg.header.frame_id == sc.name
        assert msg.angle_min == pytest.approx(-np.radians(135), abs=1e-6)
        assert msg.angle_max == pytest.approx(np.radians(135), abs=1e-6)
        assert msg.angle_increment == pytest.approx(np.radians(0.25), rel=1e-6)
        assert msg.time_increment == pytest.approx(0.025 / 1440, rel=1e-6)
        assert msg.scan_time == pytest.approx(0.025) and msg.range_min == pytest.approx(0.1) and msg.range_max == pytest.approx(30.0)
        assert len(msg.ranges) == 1081 and msg.ranges.dtype == np.float32
        stamps_ns = np.array([s[1].header.stamp.sec * 10**9 + s[1].header.stamp.nanosec for s in scans])
        assert np.abs(np.diff(stamps_ns) - 25_000_000).max() <= 1
        stamps = stamps_ns * 1e-9
        assert start <= stamps[0] < start + 0.025
        np.testing.assert_array_equal([s[0] for s in scans], [s[1].header.stamp.sec * 10**9 + s[1].header.stamp.nanosec for s in scans])
        np.testing.assert_allclose(beams[f"{sc.name}_stamps"], stamps, atol=1e-6)
        if fmt == "ros1":
            assert [s[1].header.seq for s in scans] == list(range(n))
        # per-beam ground truth agrees with validity of the ranges
        r = np.stack([s[1].ranges for s in scans])
        pid = beams[f"{sc.name}_plane_id"]
        assert pid.shape == (n, 1081) and pid.dtype == np.int32 and beams[f"{sc.name}_kind"].dtype == np.int8
        valid = np.isfinite(r)
        assert ((pid >= 0) | (pid == -2) == valid).all()
        assert valid.mean() > 0.5
        del m
    # static transforms
    [(_, tf, _)] = msgs["/tf_static"]
    got = {t.child_frame_id: t for t in tf.transforms}
    for sc in RIG.scanners:
        t = got[sc.name]
        assert t.header.frame_id == "body"
        T = sc.T_body_scanner.matrix()
        q = t.transform.rotation
        np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), T[:3, :3], atol=1e-9)
        np.testing.assert_allclose([t.transform.translation.x, t.transform.translation.y, t.transform.translation.z], T[:3, 3], atol=1e-12)
    # ground truth poses = trajectory.tum
    tum = np.loadtxt(res.gt / "trajectory.tum")
    gt = msgs["/ground_truth"]
    assert len(gt) == len(tum) and gt[0][1].header.frame_id == "world"
    pos = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for _, m, _ in gt])
    np.testing.assert_allclose(pos, tum[:, 1:4], atol=1e-8)
    np.testing.assert_allclose([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for _, m, _ in gt], tum[:, 0], atol=1e-6)
    assert np.diff(tum[:, 0]).max() <= 1 / 200 + 1e-6
    assert len(msgs["/imu"]) == len(gt)
    # every message is logged in time order
    all_t = sorted(t for v in msgs.values() for t, _, _ in v)
    assert all_t[0] == round(start * 1e9)


def test_beam_times_and_geometry_match_ground_truth(run) -> None:
    """Beams placed by the ground-truth trajectory at their own times land on their planes."""
    _fmt, res = run
    planes = json.loads((res.gt / "planes.json").read_text())
    plist = planes["planes"] if isinstance(planes, dict) else planes
    normals = {int(p["id"]): (np.asarray(p["normal"], float), float(p["d"])) for p in plist}
    tum = np.loadtxt(res.gt / "trajectory.tum")
    from simulation.trajectory import Trajectory

    traj = Trajectory(np.arange(len(tum)) / 200.0, tum[:, 1:4], tum[:, 4:8])
    msgs = _read_all(res.bag)
    beams = np.load(res.gt / "beams.npz")
    sc = RIG.scanner("left")
    _t_ns, msg, _ = msgs[sc.topic][30]
    pid = beams["left_plane_id"][30]
    stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    times = stamp + msg.time_increment * np.arange(1081) - tum[0, 0]
    R, t = traj.interpolate(times)
    a = msg.angle_min + msg.angle_increment * np.arange(1081)
    p_s = np.column_stack((np.cos(a), np.sin(a), np.zeros(1081))) * np.asarray(msg.ranges, float)[:, None]
    T = sc.T_body_scanner.matrix()
    p_w = np.einsum("nij,nj->ni", R, p_s @ T[:3, :3].T + T[:3, 3]) + t
    ok = pid >= 0
    res_ = np.array([normals[i][0] @ p + normals[i][1] for i, p in zip(pid[ok], p_w[ok], strict=True)])
    assert ok.sum() > 500
    # 3 mm noise, 1 mm quantisation; stamps rounded to ns
    assert np.sqrt(np.mean(res_**2)) < 0.006 and np.median(np.abs(res_)) < 0.004


def test_read_through_slam_io(run) -> None:
    bagio = pytest.importorskip("slam.io.bag")
    _fmt, res = run
    lines = list(bagio.read_scans(res.bag, rig=RIG))
    assert len(lines) == sum(len(_read_all(res.bag)[s.topic]) for s in RIG.scanners)
    stamps = [ln.times[0] for ln in lines]
    assert stamps == sorted(stamps)
    first = next(ln for ln in lines if ln.scanner_id == "right")
    np.testing.assert_allclose(first.times[-1] - first.times[0], 1080 * 0.025 / 1440, atol=1e-6)
    tf = bagio.read_tf_static(res.bag)
    for sc in RIG.scanners:
        np.testing.assert_allclose(tf[("body", sc.name)], sc.T_body_scanner.matrix(), atol=1e-9)
    poses = bagio.read_poses(res.bag)
    assert poses.frame_id == "world"
    np.testing.assert_allclose(poses.positions, np.loadtxt(res.gt / "trajectory.tum")[:, 1:4], atol=1e-8)
    imu = bagio.read_imu(res.bag)
    assert len(imu) == len(poses) and abs(np.median(imu.linear_acceleration[:100, 2]) - 9.81) < 0.2


def test_seeded_and_config(tmp_path) -> None:
    cfg_file = tmp_path / "sim.yaml"
    cfg_file.write_text(yaml.safe_dump({"duration": 0.5, "seed": 3, "chunk": 0.2, "noise": {"range_sigma": 0.01}}))
    cfg = load_simulation_config(cfg_file)
    a = simulate("demo", RIG, out=tmp_path / "a.bag", config=cfg, progress=False)
    b = simulate("demo", RIG, out=tmp_path / "b.bag", config=cfg, progress=False)
    ra = np.stack([m.ranges for _, m, _ in _read_all(a.bag)["/scan_top"]])
    rb = np.stack([m.ranges for _, m, _ in _read_all(b.bag)["/scan_top"]])
    np.testing.assert_array_equal(ra, rb)
    cfg_file.write_text(yaml.safe_dump({"duration": 0.5, "noise": {"sigma": 0.01}}))
    with pytest.raises(ValueError, match=r"sim.yaml.*noise.sigma"):
        load_simulation_config(cfg_file)
    with pytest.raises(ValueError, match="nope"):
        resolve_rig("nope")
    assert SimulationConfig().format == "ros1"
    shipped = load_simulation_config(Path(__file__).resolve().parents[1] / "configs" / "simulation" / "default.yaml")
    assert shipped.world == "office" and shipped.duration == 600.0 and shipped.noise.range_sigma == 0.003


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_cartographer_layout(tmp_path: Path, fmt: str) -> None:
    """The Cartographer backpack rig is written as the public recordings are: MultiEchoLaserScan
    on its topics, /tf_static from base_link to the URDF's frames, the IMU on 'imu' in imu_link;
    the echoes are the ranges of the beams with a return (the ground truth's hits)."""
    res = simulate("demo", "cartographer_backpack_2d", duration=1.0, seed=3, out=tmp_path / "c.bag", fmt=fmt,
                   imu=True, progress=False)
    msgs = _read_all(res.bag)
    assert {t: m[0][2] for t, m in msgs.items()} == {
        "horizontal_laser_2d": "sensor_msgs/msg/MultiEchoLaserScan",
        "vertical_laser_2d": "sensor_msgs/msg/MultiEchoLaserScan",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/ground_truth": "geometry_msgs/msg/PoseStamped",
        "imu": "sensor_msgs/msg/Imu",
    }
    tf = msgs["/tf_static"][0][1].transforms
    assert {(x.header.frame_id, x.child_frame_id) for x in tf} == {
        ("base_link", "horizontal_laser_link"), ("base_link", "vertical_laser_link"), ("base_link", "imu_link")}
    assert msgs["imu"][0][1].header.frame_id == "imu_link"
    beams = np.load(res.gt / "beams.npz")
    for name, topic in (("horizontal", "horizontal_laser_2d"), ("vertical", "vertical_laser_2d")):
        scans = msgs[topic]
        assert len(scans[0][1].ranges) == 1079 and scans[0][1].header.frame_id == f"{name}_laser_link"
        counts = np.array([[len(e.echoes) for e in m.ranges] for _, m, _ in scans])
        np.testing.assert_array_equal(counts == 1, beams[f"{name}_plane_id"] != -1)  # hits and mixed pixels


def test_a_silent_scanner(tmp_path: Path) -> None:
    cfg = SimulationConfig.model_validate({"silences": [{"scanner": "left", "start": 0.5, "duration": 1.0}]})
    res = simulate("demo", "itc_backpack", duration=2.0, seed=1, out=tmp_path / "s.bag", config=cfg, progress=False)
    beams = np.load(res.gt / "beams.npz")
    t_left = beams["left_stamps"] - beams["left_stamps"][0]
    assert not ((t_left > 0.55) & (t_left < 1.45)).any()
    assert len(beams["top_stamps"]) > len(beams["left_stamps"]) + 35
    bad = SimulationConfig.model_validate({"silences": [{"scanner": "middle", "start": 0.5, "duration": 1.0}]})
    with pytest.raises(ValueError, match="no scanner 'middle'"):
        simulate("demo", "itc_backpack", duration=1.0, out=tmp_path / "b.bag", config=bad, progress=False)
