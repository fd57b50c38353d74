"""Streaming writer of simulated recordings as real ROS1 or ROS2 bags (rosbags).

Topics:

- one ``sensor_msgs/LaserScan`` per scanner (the rig's topic): header stamp = time
  of the first beam, ``frame_id`` = the scanner's name, ``angle_min/max/increment``,
  ``time_increment``, ``scan_time``, ``range_min/max`` from the scanner model,
  ranges float32 (``inf`` no return, ``NaN`` dropout), no intensities; ROS1 ``seq``
  counts per topic;
- ``/tf_static`` (``tf2_msgs/TFMessage``, latched in ROS1): ``body`` -> each scanner,
  i.e. ``T_body_scanner``;
- ``/ground_truth`` (``geometry_msgs/PoseStamped``, frame ``world``): ``T_world_body``
  at the trajectory rate;
- optional ``/imu`` (``sensor_msgs/Imu``, frame ``body``, orientation unknown:
  ``orientation_covariance[0] = -1``).

The bag's log time of every message is its header stamp. Messages are written as
they come (chunk by chunk, each chunk sorted by time), so memory does not grow
with the duration. The bag is written under a temporary name beside the target
and renamed when closed; on error the temporary is removed. ROS2 bags are
directories.
"""

from __future__ import annotations

import time
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.interfaces import Connection
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

from common.atomic import commit, discard, temporary_sibling
from common.rig import Rig, ScannerConfig, ScannerModel

Format = Literal["ros1", "ros2"]
LASERSCAN = "sensor_msgs/msg/LaserScan"
MULTIECHO = "sensor_msgs/msg/MultiEchoLaserScan"
LASERECHO = "sensor_msgs/msg/LaserEcho"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
POSESTAMPED = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
WORLD_FRAME = "world"
ROS2_VERSION: Literal[8, 9] = 8  # rosbag2 metadata version readable by ROS 2 Humble and later


def typestore_for(fmt: Format) -> Typestore:
    """The message definitions for a format (ROS1 Noetic + tf2_msgs/TFMessage, or ROS2 Humble)."""
    if fmt == "ros1":
        ts = get_typestore(Stores.ROS1_NOETIC)
        if TFMESSAGE not in ts.types:
            ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TFMESSAGE))
        return ts
    if fmt == "ros2":
        return get_typestore(Stores.ROS2_HUMBLE)
    raise ValueError(f"unknown bag format {fmt!r}; use 'ros1' or 'ros2'")


def split_ns(t_ns: int) -> tuple[int, int]:
    return t_ns // 1_000_000_000, t_ns % 1_000_000_000


def seconds_to_ns(t: NDArray[np.float64] | float, base_ns: int = 0) -> NDArray[np.int64]:
    """Times in s after ``base_ns`` to absolute integer ns (rounded; the base is added in
    integers so that large absolute times keep ns resolution)."""
    return base_ns + np.round(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)


def _geometry(model: ScannerModel) -> dict[str, float]:
    """A scan message's beam geometry, timing and range limits from the scanner model."""
    return {"angle_min": float(model.angle_min), "angle_max": float(model.angle_max),
            "angle_increment": float(model.angle_increment), "time_increment": float(model.time_increment),
            "scan_time": float(model.scan_period), "range_min": float(model.range_min),
            "range_max": float(model.range_max)}


class BagWriter:
    """Write one simulated recording; use as a context manager. Times are absolute ns.

    ``seconds["writing"]`` accumulates the time spent handing messages to rosbags.
    """

    def __init__(self, path: str | Path, fmt: Format, rig: Rig, imu: bool = False, imu_noise: tuple[float, float] = (0.0, 0.0)) -> None:
        self.path = Path(path)
        self.fmt: Format = fmt
        self.ts = typestore_for(fmt)
        self.rig = rig
        self.with_imu = imu
        self.imu_noise = imu_noise
        if not self.path.parent.is_dir():
            raise ValueError(f"{self.path}: the folder {self.path.parent} does not exist")
        # a ROS2 bag's storage file takes the name of its folder: that folder is written inside a
        # temporary one under its final name (a ROS1 bag is written under a temporary name)
        self.tmp = temporary_sibling(self.path)
        self._bag_path = self.tmp if fmt == "ros1" else self.tmp / self.path.name
        self._writer: Any = None
        self._serialize = self.ts.serialize_ros1 if fmt == "ros1" else self.ts.serialize_cdr
        self._types = self.ts.types
        self._seq: dict[str, int] = {}
        self._conn: dict[str, Connection] = {}
        self._pending: list[tuple[int, int, str, bytes | memoryview]] = []
        self._order = 0
        self.counts: dict[str, int] = {}
        self.seconds = {"serialisation": 0.0, "writing": 0.0}

    # -- lifecycle
    def open(self) -> BagWriter:
        if self.fmt == "ros1":
            self._writer = Writer1(self._bag_path)
        else:
            self.tmp.mkdir()
            self._writer = Writer2(self._bag_path, version=ROS2_VERSION)
        self._writer.open()
        for sc in self.rig.scanners:
            self._add(sc.topic, MULTIECHO if sc.message == "MultiEchoLaserScan" else LASERSCAN)
        self._add("/tf_static", TFMESSAGE, latched=True)
        self._add("/ground_truth", POSESTAMPED)
        if self.with_imu:
            self._add(self.rig.imu.topic, IMU)
        return self

    def close(self) -> None:
        """Flush, close and rename the bag to its final name (replacing an old one)."""
        self.flush()
        self._writer.close()
        self._writer = None
        commit(self._bag_path, self.path)
        if self._bag_path != self.tmp:
            self.tmp.rmdir()

    def abort(self) -> None:
        """Drop the temporary bag."""
        try:
            if self._writer is not None:
                self._writer.close()
        except Exception:
            pass
        self._writer = None
        discard(self.tmp)

    def __enter__(self) -> BagWriter:
        return self.open()

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        if et is None:
            self.close()
        else:
            self.abort()

    def _add(self, topic: str, msgtype: str, latched: bool = False) -> None:
        if topic in self._conn:
            raise ValueError(f"rig '{self.rig.name}': topic {topic} is used twice")
        if self.fmt == "ros1":
            conn = self._writer.add_connection(topic, msgtype, typestore=self.ts, latching=1 if latched else None)
        else:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.ts)
        self._conn[topic] = conn
        self._seq[topic] = 0
        self.counts[topic] = 0

    # -- messages
    def _header(self, topic: str, t_ns: int, frame_id: str) -> Any:
        sec, nsec = split_ns(t_ns)
        stamp = self._types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        H = self._types["std_msgs/msg/Header"]
        if self.fmt == "ros1":
            seq = self._seq[topic]
            self._seq[topic] = seq + 1
            return H(seq=seq, stamp=stamp, frame_id=frame_id)
        return H(stamp=stamp, frame_id=frame_id)

    def _queue(self, topic: str, t_ns: int, msg: Any, msgtype: str) -> None:
        self._pending.append((t_ns, self._order, topic, self._serialize(msg, msgtype)))
        self._order += 1
        self.counts[topic] += 1

    def flush(self) -> None:
        """Write the queued messages in time order."""
        t0 = time.perf_counter()
        self._pending.sort(key=lambda m: (m[0], m[1]))
        w = self._writer
        conn = self._conn
        for t_ns, _, topic, raw in self._pending:
            w.write(conn[topic], t_ns, raw)
        self._pending.clear()
        self.seconds["writing"] += time.perf_counter() - t0

    def tf_static(self, t_ns: int) -> None:
        """``/tf_static``: the rig's body frame -> every scanner's frame (``T_body_scanner``), and
        -> the IMU's frame (identity: the IMU's axes are the body's) when it has its own name."""
        ty = self._types
        transforms = []
        mounts = [(sc.frame, sc.T_body_scanner.matrix()) for sc in self.rig.scanners]
        if self.with_imu and self.rig.imu.frame_id != self.rig.body_frame:
            mounts.append((self.rig.imu.frame_id, np.eye(4)))
        for child, T in mounts:
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            transforms.append(
                ty["geometry_msgs/msg/TransformStamped"](
                    header=self._plain_header(t_ns, self.rig.body_frame),
                    child_frame_id=child,
                    transform=ty["geometry_msgs/msg/Transform"](
                        translation=ty["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                        rotation=ty["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
                    ),
                )
            )
        msg = ty[TFMESSAGE](transforms=transforms)
        self._queue("/tf_static", t_ns, msg, TFMESSAGE)

    def _plain_header(self, t_ns: int, frame_id: str) -> Any:
        """A header without a running seq (transforms inside a TFMessage)."""
        sec, nsec = split_ns(t_ns)
        stamp = self._types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        H = self._types["std_msgs/msg/Header"]
        return H(seq=0, stamp=stamp, frame_id=frame_id) if self.fmt == "ros1" else H(stamp=stamp, frame_id=frame_id)

    def scans(self, scanner: ScannerConfig, stamps_ns: NDArray[np.int64], ranges: NDArray[np.float32]) -> None:
        """LaserScan messages of one scanner: header stamps (S,) ns, ranges (S, B) float32."""
        model = scanner.scanner_model
        if ranges.ndim != 2 or ranges.shape != (len(stamps_ns), model.n_beams):
            raise ValueError(f"scanner '{scanner.name}': ranges {ranges.shape} do not match {len(stamps_ns)} scans x {model.n_beams} beams")
        empty = np.empty(0, dtype=np.float32)
        r32 = np.ascontiguousarray(ranges, dtype=np.float32)
        if scanner.message == "MultiEchoLaserScan":
            self._multi_echo(scanner, stamps_ns, r32)
            return
        LS = self._types[LASERSCAN]
        for i, t_ns in enumerate(stamps_ns.tolist()):
            msg = LS(
                header=self._header(scanner.topic, t_ns, scanner.frame),
                **_geometry(model),
                ranges=r32[i],
                intensities=empty,
            )
            self._queue(scanner.topic, t_ns, msg, LASERSCAN)

    def _multi_echo(self, scanner: ScannerConfig, stamps_ns: NDArray[np.int64], r32: NDArray[np.float32]) -> None:
        """MultiEchoLaserScan messages: one echo per beam with a return, none where the beam
        has no return (inf) or dropped out (NaN); no intensities."""
        model = scanner.scanner_model
        MS, LE = self._types[MULTIECHO], self._types[LASERECHO]
        none = LE(echoes=np.empty(0, dtype=np.float32))
        for i, t_ns in enumerate(stamps_ns.tolist()):
            row = r32[i]
            ok = np.isfinite(row)
            echoes = [LE(echoes=row[k : k + 1]) if good else none for k, good in enumerate(ok.tolist())]
            msg = MS(
                header=self._header(scanner.topic, t_ns, scanner.frame),
                **_geometry(model),
                ranges=echoes,
                intensities=[],
            )
            self._queue(scanner.topic, t_ns, msg, MULTIECHO)

    def poses(self, times_ns: NDArray[np.int64], positions: NDArray[np.float64], quaternions_xyzw: NDArray[np.float64]) -> None:
        """``/ground_truth`` PoseStamped ``T_world_body``."""
        ty = self._types
        P, Pt, Q, PS = ty["geometry_msgs/msg/Pose"], ty["geometry_msgs/msg/Point"], ty["geometry_msgs/msg/Quaternion"], ty[POSESTAMPED]
        for t_ns, p, q in zip(times_ns.tolist(), positions.tolist(), quaternions_xyzw.tolist(), strict=True):
            msg = PS(
                header=self._header("/ground_truth", t_ns, WORLD_FRAME),
                pose=P(position=Pt(x=p[0], y=p[1], z=p[2]), orientation=Q(x=q[0], y=q[1], z=q[2], w=q[3])),
            )
            self._queue("/ground_truth", t_ns, msg, POSESTAMPED)

    def imu(self, times_ns: NDArray[np.int64], gyro: NDArray[np.float64], accel: NDArray[np.float64]) -> None:
        """``/imu`` samples in the body frame (no orientation)."""
        ty = self._types
        V, Q, IM = ty["geometry_msgs/msg/Vector3"], ty["geometry_msgs/msg/Quaternion"], ty[IMU]
        no_orientation = np.zeros(9)
        no_orientation[0] = -1.0
        cov_g = np.diag(np.full(3, self.imu_noise[0] ** 2)).ravel()
        cov_a = np.diag(np.full(3, self.imu_noise[1] ** 2)).ravel()
        for t_ns, g, a in zip(times_ns.tolist(), gyro.tolist(), accel.tolist(), strict=True):
            msg = IM(
                header=self._header(self.rig.imu.topic, t_ns, self.rig.imu.frame_id),
                orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=no_orientation,
                angular_velocity=V(x=g[0], y=g[1], z=g[2]),
                angular_velocity_covariance=cov_g,
                linear_acceleration=V(x=a[0], y=a[1], z=a[2]),
                linear_acceleration_covariance=cov_a,
            )
            self._queue(self.rig.imu.topic, t_ns, msg, IMU)
