"""ROS1 and ROS2 bag readers (rosbags ``AnyReader``): laser scans, static transforms, poses, IMU.

Scans come out as ``segmentation.Scanline`` records in the scanner frame, with
absolute per-beam times ``header.stamp + i * time_increment`` (s), merged across
topics into one stream ordered by header stamp. Every failure to read is an
``InputError`` naming the bag (and the topic): a missing path, an unreadable,
corrupt or truncated bag, an empty bag, a missing topic, a wrong message type.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Generator, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from common.rig import Rig
from segmentation import Scanline
from slam.io.errors import InputError, input_error

LASERSCAN = "sensor_msgs/msg/LaserScan"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
POSESTAMPED = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
ROS1_MAGIC = b"#ROSBAG V2.0"
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PoseSeries:
    """Timed poses ``T_frame_child`` from ``geometry_msgs/PoseStamped`` messages.

    ``times`` (n,) header stamps in s, ``positions`` (n, 3) in m and ``quaternions_xyzw``
    (n, 4), all in the frame ``frame_id`` (e.g. ``T_world_body`` for ground truth).
    """

    times: FloatArray
    positions: FloatArray
    quaternions_xyzw: FloatArray
    frame_id: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def matrices(self) -> FloatArray:
        """(n, 4, 4) homogeneous transforms."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        if len(self):
            T[:, :3, :3] = Rotation.from_quat(self.quaternions_xyzw).as_matrix()
            T[:, :3, 3] = self.positions
        return T


@dataclass(frozen=True)
class ImuSeries:
    """``sensor_msgs/Imu`` samples in the IMU frame ``frame_id``: header stamps (s),
    angular velocity (rad/s), linear acceleration (m/s^2), orientation quaternions (x, y, z, w)."""

    times: FloatArray
    angular_velocity: FloatArray
    linear_acceleration: FloatArray
    orientation_xyzw: FloatArray
    frame_id: str

    def __len__(self) -> int:
        return int(self.times.shape[0])


def is_ros1_bag(path: str | Path) -> bool:
    """True for a file starting with the ROS1 bag magic."""
    p = Path(path)
    if not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(len(ROS1_MAGIC)) == ROS1_MAGIC


def ros2_bag_dir(path: str | Path) -> Path | None:
    """The ROS2 bag directory for ``path`` (the directory itself, or the directory holding
    ``metadata.yaml`` beside a ``.db3``/``.mcap`` file), or None."""
    p = Path(path)
    if p.is_dir() and (p / "metadata.yaml").is_file():
        return p
    if p.is_file() and p.suffix in (".db3", ".mcap") and (p.parent / "metadata.yaml").is_file():
        return p.parent
    return None


def is_bag(path: str | Path) -> bool:
    """True for a ROS1 bag file or a ROS2 bag (directory or its storage file)."""
    return is_ros1_bag(path) or ros2_bag_dir(path) is not None


def _bag_path(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists():
        raise input_error(p, "no such file or directory")
    return ros2_bag_dir(p) or p


@contextmanager
def _open(path: str | Path) -> Iterator[tuple[AnyReader, Path]]:
    """An open ``AnyReader``; failures to open become ``InputError`` naming the bag."""
    p = _bag_path(path)
    reader = AnyReader([p], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as e:  # rosbags raises many types here (bare AssertionError for old ROS1 indexes)
        raise input_error(p, f"not a readable ROS bag ({_describe(e)})") from None
    try:
        yield reader, p
    finally:
        reader.close()


def _describe(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _messages(reader: AnyReader, p: Path, connections: list[Any]) -> Iterator[tuple[Any, int, Any]]:
    """(connection, log time ns, deserialized message); read errors become ``InputError``."""
    names = {c.topic for c in connections}
    topic = next(iter(names)) if len(names) == 1 else None  # which message broke is unknown otherwise
    try:
        for conn, t_ns, raw in reader.messages(connections=connections):
            yield conn, t_ns, reader.deserialize(raw, conn.msgtype)
    except InputError:
        raise
    except Exception as e:
        raise input_error(p, f"corrupt or truncated bag ({_describe(e)})", topic) from None


def topics(path: str | Path) -> dict[str, str]:
    """Topic -> message type (``pkg/msg/Name``) of every connection in the bag."""
    with _open(path) as (reader, _):
        return {c.topic: c.msgtype for c in reader.connections}


def _connections(reader: AnyReader, p: Path, topic: str, msgtype: str) -> list[Any]:
    """The connections of ``topic``, checked to exist, carry ``msgtype`` and hold messages."""
    if not reader.connections or reader.message_count == 0:
        raise input_error(p, "empty bag (no messages)")
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = ", ".join(sorted({c.topic for c in reader.connections}))
        raise input_error(p, f"no such topic (topics: {have})", topic)
    wrong = {c.msgtype for c in conns} - {msgtype}
    if wrong:
        raise input_error(p, f"has message type {', '.join(sorted(wrong))}, expected {msgtype}", topic)
    if sum(c.msgcount for c in conns) == 0:
        raise input_error(p, "no messages", topic)
    return conns


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header`` stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _scan_plan(reader: AnyReader, p: Path, topic_list: Sequence[str] | None, rig: Rig | None) -> dict[str, str | None]:
    """Topic -> scanner name (None: take the message's frame id, else the topic)."""
    names: dict[str, str | None]
    if topic_list is not None:
        by_topic = rig.by_topic() if rig is not None else {}
        names = {t: (by_topic[t].name if t in by_topic else None) for t in topic_list}
    elif rig is not None:
        names = {s.topic: s.name for s in rig.scanners}
    else:
        if not reader.connections or reader.message_count == 0:
            raise input_error(p, "empty bag (no messages)")
        names = {c.topic: None for c in reader.connections if c.msgtype == LASERSCAN and c.msgcount > 0}
        if not names:
            have = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections)
            raise input_error(p, f"no {LASERSCAN} topic with messages (topics: {have})")
    if not names:
        raise input_error(p, "no topics requested")
    for t in names:
        _connections(reader, p, t, LASERSCAN)
    return names


def read_scans(
    path: str | Path,
    topics: Sequence[str] | None = None,
    rig: Rig | None = None,
    *,
    reorder_window: float = 1.0,
) -> Generator[Scanline, None, None]:
    """Stream the ``sensor_msgs/LaserScan`` messages of a bag as Scanlines ordered by header stamp.

    Topics: ``topics`` if given, else the rig's scanner topics, else every LaserScan
    topic. ``scanner_id`` is the rig's scanner name for the topic, else the message's
    frame id, else the topic. Messages are merged across topics through a buffer that
    holds those stamped within ``reorder_window`` s of the latest log time, so memory
    stays bounded; the output is in stamp order whenever no message's stamp lags its log
    time by more than that window. The bag and its topics are checked before this returns.
    """
    with _open(path) as (reader, p):
        plan = _scan_plan(reader, p, topics, rig)
    if reorder_window < 0:
        raise ValueError(f"reorder_window must be >= 0, got {reorder_window}")
    return _iter_scans(p, plan, int(reorder_window * 1e9))


def _iter_scans(path: Path, plan: dict[str, str | None], window_ns: int) -> Generator[Scanline, None, None]:
    heap: list[tuple[int, int, Scanline]] = []
    counter = itertools.count()
    with _open(path) as (reader, p):
        conns = [c for c in reader.connections if c.topic in plan]
        for conn, t_ns, msg in _messages(reader, p, conns):
            s_ns = stamp_ns(msg.header)
            name = plan[conn.topic] or str(msg.header.frame_id) or conn.topic
            try:
                line = Scanline.from_laserscan(msg, stamp=s_ns * 1e-9, scanner_id=name)
            except ValueError as e:
                raise input_error(p, f"bad LaserScan at log time {t_ns * 1e-9:.9f} s: {e}", conn.topic) from None
            heapq.heappush(heap, (s_ns, next(counter), line))
            while heap and heap[0][0] < t_ns - window_ns:
                yield heapq.heappop(heap)[2]
        while heap:
            yield heapq.heappop(heap)[2]


def read_tf_static(path: str | Path, topic: str = "/tf_static") -> dict[tuple[str, str], FloatArray]:
    """Static transforms: (parent, child) -> 4x4 ``T_parent_child`` (maps child-frame points to
    the parent frame). An empty dict when the bag has no ``topic``; a later message for the same
    pair overrides an earlier one."""
    out: dict[tuple[str, str], FloatArray] = {}
    with _open(path) as (reader, p):
        if not any(c.topic == topic for c in reader.connections):
            return out
        conns = _connections(reader, p, topic, TFMESSAGE)
        for _, _, msg in _messages(reader, p, conns):
            for tf in msg.transforms:
                tr, q = tf.transform.translation, tf.transform.rotation
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                T[:3, 3] = (tr.x, tr.y, tr.z)
                out[(str(tf.header.frame_id), str(tf.child_frame_id))] = T
    return out


def read_poses(path: str | Path, topic: str = "/ground_truth") -> PoseSeries:
    """All ``geometry_msgs/PoseStamped`` messages of ``topic`` as arrays, in log order."""
    times, pos, quat = [], [], []
    frame = ""
    with _open(path) as (reader, p):
        for _, _, msg in _messages(reader, p, _connections(reader, p, topic, POSESTAMPED)):
            times.append(stamp_ns(msg.header) * 1e-9)
            o, q = msg.pose.position, msg.pose.orientation
            pos.append((o.x, o.y, o.z))
            quat.append((q.x, q.y, q.z, q.w))
            frame = str(msg.header.frame_id)
    return PoseSeries(np.array(times), np.array(pos).reshape(-1, 3), np.array(quat).reshape(-1, 4), frame)


def read_imu(path: str | Path, topic: str = "/imu") -> ImuSeries:
    """All ``sensor_msgs/Imu`` messages of ``topic`` as arrays, in log order."""
    times, gyro, acc, quat = [], [], [], []
    frame = ""
    with _open(path) as (reader, p):
        for _, _, msg in _messages(reader, p, _connections(reader, p, topic, IMU)):
            times.append(stamp_ns(msg.header) * 1e-9)
            w, a, q = msg.angular_velocity, msg.linear_acceleration, msg.orientation
            gyro.append((w.x, w.y, w.z))
            acc.append((a.x, a.y, a.z))
            quat.append((q.x, q.y, q.z, q.w))
            frame = str(msg.header.frame_id)
    return ImuSeries(
        np.array(times),
        np.array(gyro).reshape(-1, 3),
        np.array(acc).reshape(-1, 3),
        np.array(quat).reshape(-1, 4),
        frame,
    )


__all__ = [
    "ImuSeries",
    "InputError",
    "PoseSeries",
    "is_bag",
    "read_imu",
    "read_poses",
    "read_scans",
    "read_tf_static",
    "topics",
]
