"""Bag readers: the real ROS1 bag, ROS1/ROS2 round trips written with rosbags, and broken inputs."""

from __future__ import annotations

import itertools
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from common.rig import Rig
from slam.io import InputError, detect_format, open_scans
from slam.io.bag import read_imu, read_poses, read_scans, read_tf_static, time_range, topics
from slam.io.source import BagSource, StampWindow

REAL_BAG = Path("/work/shared/data/real/obstacle_detector_scans_demo.bag")
needs_data = pytest.mark.skipif(not REAL_BAG.is_file(), reason="real data not available")


# ---- the real ROS1 bag --------------------------------------------------------------------------
@needs_data
def test_real_bag_scans() -> None:
    assert topics(REAL_BAG) == {"/front_scan": "sensor_msgs/msg/LaserScan", "/rear_scan": "sensor_msgs/msg/LaserScan"}
    scans = list(read_scans(REAL_BAG))
    ids = [s.scanner_id for s in scans]
    assert ids.count("front_scanner") == 331 and ids.count("rear_scanner") == 330
    stamps = np.array([s.stamp for s in scans])
    assert np.all(np.diff(stamps) >= 0)
    s = scans[0]
    assert s.n_beams == 726
    assert math.degrees(s.angles[0]) == pytest.approx(-135.0, abs=1e-5)
    np.testing.assert_allclose(np.degrees(np.diff(s.angles)), 0.3516, atol=1e-4)
    assert s.range_min == pytest.approx(0.02) and s.range_max == pytest.approx(5.6)
    assert s.stamp == pytest.approx(1483992048.461698, abs=1e-6)  # header stamp, not log time
    # float64 seconds near 1.5e9 s resolve 0.24 us: beam times are exact to that
    np.testing.assert_allclose(s.times - s.times[0], 9.765627e-05 * np.arange(726), atol=3e-7)
    assert 0 < s.n_valid < s.n_beams  # NaN returns are masked
    assert np.all(np.isfinite(s.points_xy))


@needs_data
def test_real_bag_topic_selection_and_rig_names() -> None:
    front = list(read_scans(REAL_BAG, topics=["/front_scan"]))
    assert len(front) == 331 and {s.scanner_id for s in front} == {"front_scanner"}
    rig = Rig.model_validate(
        {"name": "demo", "reference": "front", "scanners": [{"name": "front", "topic": "/front_scan"}, {"name": "rear", "topic": "/rear_scan"}]}
    )
    named = list(read_scans(REAL_BAG, rig=rig))
    assert {s.scanner_id for s in named} == {"front", "rear"} and len(named) == 661
    assert detect_format(REAL_BAG) == "bag"
    assert sum(1 for _ in open_scans(REAL_BAG, topics=["/rear_scan"])) == 330


@needs_data
def test_real_bag_missing_topic_and_no_tf_static() -> None:
    with pytest.raises(InputError, match=r"obstacle_detector_scans_demo\.bag topic /top_scan: no such topic"):
        read_scans(REAL_BAG, topics=["/top_scan"])
    assert read_tf_static(REAL_BAG) == {}
    with pytest.raises(InputError, match=r"topic /front_scan: has message type sensor_msgs/msg/LaserScan, expected geometry_msgs/msg/PoseStamped"):
        read_poses(REAL_BAG, "/front_scan")


@needs_data
def test_truncated_bag_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "cut.bag"
    bad.write_bytes(REAL_BAG.read_bytes()[:1_000_000])
    with pytest.raises(InputError, match=r"cut\.bag: not a readable ROS bag"):
        list(read_scans(bad))


@needs_data
def test_corrupt_bag_names_the_file(tmp_path: Path) -> None:
    data = bytearray(REAL_BAG.read_bytes())
    data[13:21] = b"\xff" * 8  # the bag header record
    bad = tmp_path / "corrupt.bag"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"corrupt\.bag: not a readable ROS bag"):
        list(read_scans(bad))


@needs_data
def test_corrupt_chunk_is_reported_while_streaming(tmp_path: Path) -> None:
    data = bytearray(REAL_BAG.read_bytes())
    data[12041 : 12041 + 8] = b"\xff" * 8  # a record header inside a chunk: found only while reading
    bad = tmp_path / "chunk.bag"
    bad.write_bytes(bytes(data))
    stream = read_scans(bad)
    with pytest.raises(InputError, match=r"chunk\.bag: corrupt or truncated bag \(ReaderError"):
        list(stream)
    with pytest.raises(InputError, match=r"chunk\.bag topic /front_scan: corrupt or truncated bag"):
        list(read_scans(bad, topics=["/front_scan"]))


def test_old_index_assertion_error_becomes_input_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bag = _write_ros1(tmp_path / "old.bag")

    def fail(self: Any) -> None:
        raise AssertionError

    monkeypatch.setattr(AnyReader, "open", fail)
    with pytest.raises(InputError, match=r"old\.bag: not a readable ROS bag \(AssertionError\)"):
        read_scans(bag)


def test_missing_empty_and_non_bag_inputs(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"none\.bag: no such file"):
        read_scans(tmp_path / "none.bag")
    text = tmp_path / "text.bag"
    text.write_text("hello\n")
    with pytest.raises(InputError, match=r"text\.bag: not a ROS1 bag"):
        open_scans(text)
    with pytest.raises(InputError, match=r"text\.bag: not a readable ROS bag"):
        read_scans(text)
    empty1 = tmp_path / "empty.bag"
    with Writer1(empty1):
        pass
    with pytest.raises(InputError, match=r"empty\.bag: empty bag"):
        read_scans(empty1)
    empty2 = tmp_path / "empty2"
    with Writer2(empty2, version=9):
        pass
    with pytest.raises(InputError, match=r"empty2: empty bag"):
        read_scans(empty2)


def test_wrong_message_type_and_no_laserscan(tmp_path: Path) -> None:
    bag = _write_ros2(tmp_path / "r2")
    with pytest.raises(InputError, match=r"r2 topic /ground_truth: has message type geometry_msgs/msg/PoseStamped, expected sensor_msgs/msg/LaserScan"):
        read_scans(bag, topics=["/ground_truth"])
    with pytest.raises(InputError, match=r"r2 topic /scan_top: has message type sensor_msgs/msg/LaserScan, expected sensor_msgs/msg/Imu"):
        read_imu(bag, "/scan_top")
    with pytest.raises(InputError, match=r"r2 topic /nope: no such topic"):
        read_poses(bag, "/nope")


# ---- round trips through rosbags writers ------------------------------------------------------
N_BEAMS = 50
SCANNERS = {"/scan_top": "top", "/scan_left": "left"}
T0 = 1_700_000_000_000_000_000
EXTRINSICS = {
    ("base_link", "top"): (np.array([0.1, 0.0, 0.5]), Rotation.from_euler("xyz", [0.0, 0.0, 0.1])),
    ("base_link", "left"): (np.array([0.0, 0.2, 0.4]), Rotation.from_euler("xyz", [0.7, 0.2, -0.3])),
}


def _stamp(ts: Any, t_ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def _header(ts: Any, t_ns: int, frame: str, ros1: bool, seq: int = 0) -> Any:
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=seq, stamp=_stamp(ts, t_ns), frame_id=frame) if ros1 else H(stamp=_stamp(ts, t_ns), frame_id=frame)


def _scan_ranges(k: int, j: int) -> np.ndarray:
    r = 1.0 + 0.01 * k + 0.1 * j + 0.001 * np.arange(N_BEAMS, dtype=np.float32)
    r[3] = np.nan
    r[7] = 0.0
    return r.astype(np.float32)


def _messages(ts: Any, ros1: bool, clock_ns: int = 0) -> list[tuple[str, str, int, Any]]:
    """(topic, type, log time ns, message): interleaved scans whose log times lag their stamps
    by different amounts (so log order differs from stamp order), tf_static, poses, IMU; the
    scans' log times moved by ``clock_ns`` more (a recorder's clock off the sensors')."""
    T = ts.types
    out: list[tuple[str, str, int, Any]] = []
    tfs = []
    for (parent, child), (t, R) in EXTRINSICS.items():
        q = R.as_quat()
        tfs.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=_header(ts, T0, parent, ros1),
                child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        )
    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0, T["tf2_msgs/msg/TFMessage"](transforms=tfs)))
    for k in range(10):
        for j, (topic, name) in enumerate(SCANNERS.items()):
            stamp = T0 + k * 25_000_000 + j * 5_000_000
            lag = 30_000_000 if j == 0 else 1_000_000  # top arrives after left's later scans
            msg = T["sensor_msgs/msg/LaserScan"](
                header=_header(ts, stamp, name, ros1, seq=k),
                angle_min=-2.0,
                angle_max=-2.0 + 0.05 * (N_BEAMS - 1),
                angle_increment=0.05,
                time_increment=1e-4,
                scan_time=0.025,
                range_min=0.1,
                range_max=30.0,
                ranges=_scan_ranges(k, j),
                intensities=np.zeros(0, dtype=np.float32),
            )
            out.append((topic, "sensor_msgs/msg/LaserScan", stamp + lag + clock_ns, msg))
        pose_t = T0 + k * 25_000_000
        q = Rotation.from_euler("z", 0.01 * k).as_quat()
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=0.1 * k, y=0.0, z=1.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        out.append(("/ground_truth", "geometry_msgs/msg/PoseStamped", pose_t, T["geometry_msgs/msg/PoseStamped"](header=_header(ts, pose_t, "world", ros1), pose=pose)))
        V = T["geometry_msgs/msg/Vector3"]
        imu = T["sensor_msgs/msg/Imu"](
            header=_header(ts, pose_t, "imu", ros1),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.zeros(9),
            angular_velocity=V(x=0.0, y=0.0, z=0.01 * k),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=V(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9),
        )
        out.append(("/imu", "sensor_msgs/msg/Imu", pose_t, imu))
    return sorted(out, key=lambda m: m[2])


def _write_ros1(path: Path, clock_ns: int = 0) -> Path:
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    msgs = _messages(ts, ros1=True, clock_ns=clock_ns)
    with Writer1(path) as w:
        conns = {(t, mt): w.add_connection(t, mt, typestore=ts) for t, mt in sorted({(m[0], m[1]) for m in msgs})}
        for topic, mt, t_ns, msg in msgs:
            w.write(conns[(topic, mt)], t_ns, ts.serialize_ros1(msg, mt))
    return path


def _write_ros2(path: Path, clock_ns: int = 0) -> Path:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = _messages(ts, ros1=False, clock_ns=clock_ns)
    with Writer2(path, version=9) as w:
        conns = {t: w.add_connection(t[0], t[1], typestore=ts) for t in sorted({(m[0], m[1]) for m in msgs})}
        for topic, mt, t_ns, msg in msgs:
            w.write(conns[(topic, mt)], t_ns, ts.serialize_cdr(msg, mt))
    return path


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_round_trip(tmp_path: Path, fmt: str) -> None:
    bag = _write_ros1(tmp_path / "run.bag") if fmt == "ros1" else _write_ros2(tmp_path / "run")
    assert detect_format(bag) == "bag"
    scans = list(read_scans(bag))
    assert len(scans) == 20
    stamps = np.array([s.stamp for s in scans])
    assert np.all(np.diff(stamps) > 0)  # merged by header stamp although log order differs
    assert [s.scanner_id for s in scans[:4]] == ["top", "left", "top", "left"]
    for i, s in enumerate(scans):
        k, j = divmod(i, 2)
        assert s.stamp == pytest.approx((T0 + k * 25_000_000 + j * 5_000_000) * 1e-9, abs=1e-6)
        np.testing.assert_allclose(s.times - s.times[0], 1e-4 * np.arange(N_BEAMS), atol=1e-6)
        np.testing.assert_allclose(s.angles, -2.0 + 0.05 * np.arange(N_BEAMS), atol=1e-6)
        np.testing.assert_array_equal(s.ranges.astype(np.float32)[~np.isnan(s.ranges)], _scan_ranges(k, j)[~np.isnan(s.ranges)])
        assert not s.valid[3] and not s.valid[7] and s.n_valid == N_BEAMS - 2
    # with a window shorter than the lag the stream falls back to log order
    log_order = list(read_scans(bag, reorder_window=0.0))
    assert [s.scanner_id for s in log_order[:3]] == ["left", "top", "left"]
    assert np.any(np.diff([s.stamp for s in log_order]) < 0)
    # rig naming
    rig = Rig.model_validate({"name": "r", "reference": "a", "scanners": [{"name": "a", "topic": "/scan_left"}]})
    assert {s.scanner_id for s in read_scans(bag, rig=rig)} == {"a"}

    tf = read_tf_static(bag)
    assert set(tf) == set(EXTRINSICS)
    for key, (t, R) in EXTRINSICS.items():
        np.testing.assert_allclose(tf[key][:3, :3], R.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(tf[key][:3, 3], t, atol=1e-12)

    gt = read_poses(bag, "/ground_truth")
    assert len(gt) == 10 and gt.frame_id == "world"
    np.testing.assert_allclose(gt.positions[:, 0], 0.1 * np.arange(10))
    np.testing.assert_allclose(np.diff(gt.times), 0.025, atol=5e-7)  # float64 s near 1.7e9
    yaw = Rotation.from_matrix(gt.matrices()[:, :3, :3]).as_euler("xyz")[:, 2]
    np.testing.assert_allclose(yaw, 0.01 * np.arange(10), atol=1e-12)

    imu = read_imu(bag, "/imu")
    assert len(imu) == 10 and imu.frame_id == "imu"
    np.testing.assert_allclose(imu.angular_velocity[:, 2], 0.01 * np.arange(10))
    np.testing.assert_allclose(imu.linear_acceleration[:, 2], 9.81)


def test_ros2_storage_file_path_is_accepted(tmp_path: Path) -> None:
    bag = _write_ros2(tmp_path / "r2")
    db = next(bag.glob("*.db3"))
    assert len(list(open_scans(db))) == 20
    moved = tmp_path / "copy"
    shutil.copytree(bag, moved)
    assert len(list(read_scans(moved, topics=["/scan_top"]))) == 10


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_one_source_answers_every_question_with_one_open(tmp_path: Path, fmt: str,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    bag = _write_ros1(tmp_path / "run.bag") if fmt == "ros1" else _write_ros2(tmp_path / "run")
    made = []
    original = AnyReader.__init__

    def counted(self: Any, *args: Any, **kwargs: Any) -> None:
        made.append(args)
        original(self, *args, **kwargs)

    monkeypatch.setattr(AnyReader, "__init__", counted)
    with BagSource(bag) as source:
        assert source.topics() == topics(bag)
        assert source.time_range() == time_range(bag)
        assert set(source.tf_static()) == set(EXTRINSICS)
        assert len(source.imu()) == len(source.poses()) == 10
        assert len(list(source.scans())) == len(list(source.scans(topics=["/scan_top"]))) * 2 == 20
        made.clear()
    assert made == []
    stream = read_scans(bag)
    list(stream)
    assert len(made) == 1  # checked and read through one open


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
@pytest.mark.parametrize("clock_s", [0.0, -5.0])
def test_scans_by_stamp_window_cut_the_stream(tmp_path: Path, fmt: str, clock_s: float) -> None:
    """Consecutive stamp windows give the whole stream's scans in its order, also when the log
    times run seconds behind the stamps (further than the reorder buffer reaches)."""
    clock = round(clock_s * 1e9)
    bag = _write_ros1(tmp_path / "run.bag", clock) if fmt == "ros1" else _write_ros2(tmp_path / "run", clock)
    with BagSource(bag) as source:
        whole = source.scans()
        lines = [(s.stamp, s.scanner_id) for s in whole]
        index = whole.index
        assert index.stamps == [s for s, _ in lines] and index.scanner_ids == [n for _, n in lines]
        assert index.in_stamp_order() and index.lag_ns == (clock + 1_000_000, clock + 30_000_000)
        for cuts in ([7], [1, 2, 13], [5, 19]):
            bounds = [None, *(index.stamps[c] for c in cuts), None]
            got = []
            for start, stop in itertools.pairwise(bounds):
                got += [(s.stamp, s.scanner_id) for s in source.scans(window=StampWindow(start, stop, index.lag_ns))]
            assert got == lines, cuts


def test_a_stream_out_of_stamp_order_says_so(tmp_path: Path) -> None:
    """Log times seconds after the stamps: the reorder buffer cannot restore stamp order, and
    the index tells (a cloud pass then reads the stream whole)."""
    with BagSource(_write_ros1(tmp_path / "late.bag", 5_000_000_000)) as source:
        stream = source.scans()
        list(stream)
        assert not stream.index.in_stamp_order()


@needs_data
def test_compact_index_reads_the_same_messages_as_rosbags() -> None:
    """The bag's index in columns (slam.io.compact_index) yields every message of the real ROS1
    bag, with its time and bytes, in the order rosbags' own index does, also by a time window,
    with the same message counts, in a sixth of the memory or less."""
    import sys

    from slam.io.compact_index import CompactIndex, open_compact

    def read(reader: AnyReader, **window: int) -> list[tuple[str, int, bytes]]:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages(connections=reader.connections, **window)]

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([REAL_BAG], default_typestore=ts) as plain:
        compact = AnyReader([REAL_BAG], default_typestore=ts)
        assert open_compact(compact) == sum(c.msgcount for c in plain.connections)
        inner = plain.readers[0]
        tuples = sum(sys.getsizeof(e) + sum(sys.getsizeof(x) for x in e) for v in inner.indexes.values() for e in v)
        indexes = compact.readers[0].indexes
        assert all(isinstance(v, CompactIndex) for v in indexes.values())
        assert sum(v.nbytes for v in indexes.values()) * 6 < tuples
        assert [c.msgcount for c in compact.connections] == [c.msgcount for c in plain.connections]
        assert read(compact) == read(plain)
        t0, t1 = plain.start_time, plain.end_time
        window = {"start": t0 + (t1 - t0) // 3, "stop": t0 + 2 * (t1 - t0) // 3}
        assert read(compact, **window) == read(plain, **window)
        assert len(read(plain, **window)) > 0
        assert "read_index_data" not in vars(compact.readers[0])  # the reader's own method again
        compact.close()
