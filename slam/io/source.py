"""``BagSource``: one ROS1 or ROS2 bag opened once (rosbags ``AnyReader``), answering every
question a run asks of it: time range, topics, IMU samples, static transforms, poses, and the
laser scans, whole or by a window of stamps.

Scans come out as ``segmentation.Scanline`` records in the scanner frame, with absolute per-beam
times ``header.stamp + i * time_increment`` (s), merged across topics into one stream ordered by
header stamp. Every failure to read is an ``InputError`` naming the bag (and the topic): a
missing path, an unreadable, corrupt or truncated bag, an empty bag, a missing topic, a wrong
message type.

A source belongs to one process: a forked process opens its own from :attr:`BagSource.path`
(a reader's open file cannot be shared across a fork).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from common.rig import Rig
from segmentation import Scanline
from slam.io.compact_index import open_compact
from slam.io.errors import InputError, input_error
from slam.io.imu_raw import ImuColumns, imu_columns

LASERSCAN = "sensor_msgs/msg/LaserScan"
MULTIECHO = "sensor_msgs/msg/MultiEchoLaserScan"
SCAN_TYPES = (LASERSCAN, MULTIECHO)
Echo = Literal["first", "last", "strongest"]
ECHOES: tuple[Echo, ...] = ("first", "last", "strongest")
TFMESSAGE = "tf2_msgs/msg/TFMessage"
POSESTAMPED = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
ROS1_MAGIC = b"#ROSBAG V2.0"
MAX_SCAN_GAP = 60.0  # s: a SLAM run's scans further apart than this have broken stamps (the knots would span them)
_WINDOW_MARGIN_NS = 1_000_000  # log-time slack around a stamp window: a float stamp's rounding is ~0.2 us
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


@dataclass
class StreamIndex:
    """What a :class:`ScanStream` yielded, in its order: each scan's stamp (s) and scanner id
    (left empty by a stream that does not ``record`` them); ``lag_ns``, the (least, greatest)
    log time minus header stamp (ns) over every scan message read (None before the first);
    ``intensities``, whether any scan carried them; ``last_stamp``, the latest scan's stamp;
    ``points``, the valid returns of the scans yielded (the cloud's points)."""

    stamps: list[float] = field(default_factory=list)
    scanner_ids: list[str] = field(default_factory=list)
    lag_ns: tuple[int, int] | None = None
    intensities: bool = False
    last_stamp: float | None = None
    points: int = 0

    def __len__(self) -> int:
        return len(self.stamps)

    def in_stamp_order(self) -> bool:
        """Whether the scans came out in stamp order (no message lagged past the reorder buffer)."""
        s = self.stamps
        return all(a <= b for a, b in itertools.pairwise(s))


@dataclass(frozen=True)
class StampWindow:
    """The scans whose stamp (s, the Scanline's ``stamp``) is in ``[start, stop)`` (None:
    unbounded), read from the log times such scans can have: ``lag_ns`` bounds log time minus
    stamp (ns) over the bag's scan messages, as a whole pass measured them (``StreamIndex``)."""

    start: float | None
    stop: float | None
    lag_ns: tuple[int, int]

    def contains(self, stamp: float) -> bool:
        return (self.start is None or stamp >= self.start) and (self.stop is None or stamp < self.stop)

    def log_range_ns(self) -> tuple[int | None, int | None]:
        """(start, stop) log times (ns) to read: every scan in the window lies within."""
        lo, hi = self.lag_ns
        start = None if self.start is None else int(self.start * 1e9) + lo - _WINDOW_MARGIN_NS
        stop = None if self.stop is None else int(self.stop * 1e9) + hi + _WINDOW_MARGIN_NS
        return start, stop


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


_BAGS = "expected a ROS1 .bag file or a ROS2 bag folder (with metadata.yaml)"
_OTHER_FORMATS = {"carmen": "a CARMEN log", "npz": "an .npz scanline", "csv": "a CSV scanline"}


def not_a_bag(path: Path) -> InputError | None:
    """Why ``path`` (an existing file or folder) cannot be opened as a bag, naming what it is and
    what is expected (rosbags picks its reader from the name: ``*.bag`` is ROS1, anything else
    ROS2); None when it has a bag's form."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            return input_error(path, f"not a readable ROS bag: a folder without metadata.yaml; {_BAGS}")
        if path.suffix == ".bag":
            return input_error(path, "not a readable ROS bag: a ROS2 bag folder whose name ends in .bag (read as a "
                               "ROS1 bag file); rename the folder")
        return None
    if is_ros1_bag(path):
        if path.suffix != ".bag":
            return input_error(path, "not a readable ROS bag: a ROS1 bag whose name does not end in .bag (read as a "
                               "ROS2 bag); rename it to *.bag")
        return None
    if path.suffix in (".db3", ".mcap"):
        return input_error(path, f"not a readable ROS bag: a ROS2 storage file without metadata.yaml beside it; {_BAGS}")
    from slam.io import detect_format  # the package imports this module

    try:
        kind = _OTHER_FORMATS.get(detect_format(path))
    except (ValueError, OSError):
        kind = None
    if kind is not None:
        return input_error(path, f"not a ROS bag but {kind} (backpack-slam segment reads it); {_BAGS}")
    return input_error(path, f"not a readable ROS bag; {_BAGS}")


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header`` stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _describe(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


class BagSource:
    """A bag opened once (``with BagSource(path) as bag: ...``); failures to open are an
    ``InputError`` naming it. ``path`` is the bag itself (a ROS2 bag's directory)."""

    def __init__(self, path: str | Path) -> None:
        p = Path(path)
        if not p.exists():
            raise input_error(p, "no such file or directory")
        self.path = ros2_bag_dir(p) or p
        refused = not_a_bag(self.path)
        if refused is not None:
            raise refused
        self._open = True
        self._held: AnyReader | None = self._open_reader()

    def _open_reader(self) -> AnyReader:
        try:
            reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            open_compact(reader)  # the index at 20 B per message instead of rosbags' ~170 B tuples
        except Exception as e:  # rosbags raises many types here (bare AssertionError for old ROS1 indexes)
            raise input_error(self.path, f"not a readable ROS bag ({_describe(e)})") from None
        return reader

    @property
    def _reader(self) -> AnyReader:
        """The open reader, opened again if :meth:`release` let it go."""
        if self._held is None:
            if not self._open:
                raise ValueError(f"{self.path}: the bag source is closed")
            self._held = self._open_reader()
        return self._held

    def release(self) -> None:
        """Let go of the bag's reader and its message index (37 MB in columns for the hour-long,
        3-scanner office bag; 322 MB as rosbags' tuples) until the bag is next read, when it is opened again: for the time a forked reader
        process reads the bag with its own."""
        if self._held is not None:
            self._held.close()
            self._held = None

    def close(self) -> None:
        if self._open:
            self._open = False
            self.release()

    def __enter__(self) -> BagSource:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def time_range(self) -> tuple[float, float]:
        """(start, end) log time of the bag's messages in s."""
        return self._reader.start_time * 1e-9, self._reader.end_time * 1e-9

    def topics(self) -> dict[str, str]:
        """Topic -> message type (``pkg/msg/Name``) of every connection in the bag."""
        return {c.topic: c.msgtype for c in self._reader.connections}

    def connections(self, topic: str, msgtype: str | tuple[str, ...]) -> list[Any]:
        """The connections of ``topic``, checked to exist, carry ``msgtype`` (one of them, for a
        tuple) and hold messages."""
        kinds = (msgtype,) if isinstance(msgtype, str) else msgtype
        r, p = self._reader, self.path
        if not r.connections or r.message_count == 0:
            raise input_error(p, "empty bag (no messages)")
        conns = [c for c in r.connections if c.topic == topic]
        if not conns:
            have = ", ".join(sorted({c.topic for c in r.connections}))
            raise input_error(p, f"no such topic (topics: {have})", topic)
        wrong = {c.msgtype for c in conns} - set(kinds)
        if wrong:
            raise input_error(p, f"has message type {', '.join(sorted(wrong))}, expected {' or '.join(kinds)}", topic)
        if sum(c.msgcount for c in conns) == 0:
            raise input_error(p, "no messages", topic)
        return conns

    def messages(self, connections: list[Any], start: int | None = None,
                 stop: int | None = None) -> Iterator[tuple[Any, int, Any]]:
        """(connection, log time ns, deserialized message) with log time in ``[start, stop)`` (ns,
        None: unbounded), in log order; read errors become ``InputError``."""
        names = {c.topic for c in connections}
        topic = next(iter(names)) if len(names) == 1 else None  # which message broke is unknown otherwise
        try:
            for conn, t_ns, raw in self._reader.messages(connections=connections, start=start, stop=stop):
                yield conn, t_ns, self._reader.deserialize(raw, conn.msgtype)
        except InputError:
            raise
        except Exception as e:
            raise input_error(self.path, f"corrupt or truncated bag ({_describe(e)})", topic) from None

    def scan_plan(self, topics: Sequence[str] | None = None, rig: Rig | None = None) -> dict[str, str | None]:
        """Topic -> scanner name (None: take the message's frame id, else the topic) of the scans
        to read, each topic checked: ``topics`` if given, else the rig's scanner topics, else
        every LaserScan topic with messages."""
        r, p = self._reader, self.path
        names: dict[str, str | None]
        if topics is not None:
            by_topic = rig.by_topic() if rig is not None else {}
            names = {t: (by_topic[t].name if t in by_topic else None) for t in topics}
        elif rig is not None:
            names = {s.topic: s.name for s in rig.scanners}
        else:
            if not r.connections or r.message_count == 0:
                raise input_error(p, "empty bag (no messages)")
            names = {c.topic: None for c in r.connections if c.msgtype in SCAN_TYPES and c.msgcount > 0}
            if not names:
                have = ", ".join(f"{c.topic} ({c.msgtype})" for c in r.connections)
                raise input_error(p, f"no {LASERSCAN} or {MULTIECHO} topic with messages (topics: {have})")
        if not names:
            raise input_error(p, "no topics requested")
        for t in names:
            self.connections(t, SCAN_TYPES)
        return names

    def scans(
        self,
        topics: Sequence[str] | None = None,
        rig: Rig | None = None,
        *,
        reorder_window: float = 1.0,
        window: StampWindow | None = None,
        owned: bool = False,
        echo: Echo = "first",
        record: bool = True,
    ) -> ScanStream:
        """The ``sensor_msgs/LaserScan`` (and ``MultiEchoLaserScan``: the ``echo`` of each beam,
        see :func:`single_echo`; a SLAM run passes its ``input.echo``) messages as Scanlines (with
        their intensities when the messages carry them) ordered by header stamp (topics as in
        :meth:`scan_plan`; checked before this returns).

        ``scanner_id`` is the rig's scanner name for the topic, else the message's frame id, else
        the topic; a message without beams is left out. Messages are merged across topics through a buffer that holds those stamped
        within ``reorder_window`` s of the latest log time, so memory stays bounded; the output
        is in stamp order whenever no message's stamp lags its log time by more than that window.
        With ``window``, only the scans stamped within it, in the order the whole stream gives
        them when that is in stamp order. ``owned``: the stream closes this source when it is
        closed or exhausted. A stream of a rig's scans (``rig`` given: a SLAM run) is an
        ``InputError`` where its stamps jump ahead by more than :data:`MAX_SCAN_GAP` s (broken
        header stamps, such as zero or far-future ones: the trajectory would span them).
        ``record``: the stream's ``index`` keeps every scan's stamp and scanner id (else not: a
        pass that does not need them, such as the cloud pass, keeps nothing per scan)."""
        plan = self.scan_plan(topics, rig)
        if echo not in ECHOES:
            raise ValueError(f"echo must be one of {', '.join(ECHOES)}, got {echo!r}")
        if reorder_window < 0:
            raise ValueError(f"reorder_window must be >= 0, got {reorder_window}")
        return ScanStream(self, plan, int(reorder_window * 1e9), window, owned, echo,
                          MAX_SCAN_GAP if rig is not None else None, record)

    def imu(self, topic: str = "/imu") -> ImuSeries:
        """All ``sensor_msgs/Imu`` messages of ``topic`` as arrays, in log order: read as columns
        from their bytes when they share one layout (:mod:`slam.io.imu_raw`; checked against the
        deserialised first, middle and last messages), else message by message."""
        connections = self.connections(topic, IMU)
        try:
            raws = [raw for _, _, raw in self._reader.messages(connections=connections)]
        except Exception as e:
            raise input_error(self.path, f"corrupt or truncated bag ({_describe(e)})", topic) from None
        cols = imu_columns(raws, self._reader.is2)
        if cols is not None and all(self._same_imu(cols, i, raws[i]) for i in {0, len(raws) // 2, len(raws) - 1}):
            return ImuSeries(np.multiply(cols.stamp_ns, 1e-9, dtype=np.float64), cols.angular_velocity, cols.linear_acceleration,
                             cols.orientation_xyzw, cols.frame_id)
        del raws
        times, gyro, acc, quat = [], [], [], []
        frame = ""
        for _, _, msg in self.messages(connections):
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

    def _same_imu(self, cols: ImuColumns, i: int, raw: bytes) -> bool:
        """Whether row ``i`` of ``cols`` is the ``sensor_msgs/Imu`` message ``raw`` as rosbags
        deserialises it."""
        try:
            msg: Any = self._reader.deserialize(raw, IMU)
        except Exception:
            return False
        w, a, q = msg.angular_velocity, msg.linear_acceleration, msg.orientation
        return (stamp_ns(msg.header) == int(cols.stamp_ns[i]) and str(msg.header.frame_id) == cols.frame_id
                and (w.x, w.y, w.z) == tuple(cols.angular_velocity[i].tolist())
                and (a.x, a.y, a.z) == tuple(cols.linear_acceleration[i].tolist())
                and (q.x, q.y, q.z, q.w) == tuple(cols.orientation_xyzw[i].tolist()))

    def message_counts(self) -> dict[str, int]:
        """Topic -> number of messages."""
        out: dict[str, int] = {}
        for c in self._reader.connections:
            out[c.topic] = out.get(c.topic, 0) + int(c.msgcount)
        return out

    def transforms(self, topic: str) -> Iterator[tuple[tuple[str, str], FloatArray]]:
        """Every transform of the ``tf2_msgs/TFMessage`` topic in log order: ((parent, child),
        4x4 ``T_parent_child``, mapping child-frame points to the parent frame); nothing when the
        bag has no ``topic``."""
        if self.message_counts().get(topic, 0) == 0:
            return
        for _, _, msg in self.messages(self.connections(topic, TFMESSAGE)):
            for tf in msg.transforms:
                tr, q = tf.transform.translation, tf.transform.rotation
                xyzw = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
                if not (np.all(np.isfinite(xyzw)) and np.linalg.norm(xyzw) > 1e-9):
                    raise input_error(self.path, f"transform {tf.header.frame_id} -> {tf.child_frame_id}: rotation "
                                      f"quaternion (x y z w) {' '.join(f'{v:g}' for v in xyzw)} is not a rotation",
                                      topic)
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat(xyzw).as_matrix()
                T[:3, 3] = (tr.x, tr.y, tr.z)
                yield (str(tf.header.frame_id), str(tf.child_frame_id)), T

    def tf_static(self, topic: str = "/tf_static") -> dict[tuple[str, str], FloatArray]:
        """Static transforms: (parent, child) -> 4x4 ``T_parent_child``. An empty dict when the bag
        has no ``topic``; a later message for the same pair overrides an earlier one."""
        return dict(self.transforms(topic))

    def imu_topic(self) -> tuple[str, str] | None:
        """(topic, frame id) of the first ``sensor_msgs/Imu`` topic with messages, or None."""
        counts = self.message_counts()
        for topic, msgtype in self.topics().items():
            if msgtype == IMU and counts.get(topic, 0) > 0:
                for _, _, msg in self.messages(self.connections(topic, IMU)):
                    return topic, str(msg.header.frame_id)
        return None

    def poses(self, topic: str = "/ground_truth") -> PoseSeries:
        """All ``geometry_msgs/PoseStamped`` messages of ``topic`` as arrays, in log order."""
        times, pos, quat = [], [], []
        frame = ""
        for _, _, msg in self.messages(self.connections(topic, POSESTAMPED)):
            times.append(stamp_ns(msg.header) * 1e-9)
            o, q = msg.pose.position, msg.pose.orientation
            pos.append((o.x, o.y, o.z))
            quat.append((q.x, q.y, q.z, q.w))
            frame = str(msg.header.frame_id)
        return PoseSeries(np.array(times), np.array(pos).reshape(-1, 3), np.array(quat).reshape(-1, 4), frame)


class ScanStream:
    """An iterator of Scanlines in stamp order (made by :meth:`BagSource.scans`); ``index``
    records what it yielded (:class:`StreamIndex`)."""

    def __init__(self, source: BagSource, plan: dict[str, str | None], reorder_ns: int, window: StampWindow | None,
                 owned: bool, echo: Echo = "first", max_gap: float | None = None, record: bool = True) -> None:
        self.source = source
        self.index = StreamIndex()
        self._owned = owned
        # the generator holds no reference to this stream, so that dropping it closes the bag at once
        self._lines = _merged(source, self.index, plan, reorder_ns, window, echo, max_gap, record)

    def __iter__(self) -> ScanStream:
        return self

    def __next__(self) -> Scanline:
        try:
            return next(self._lines)
        except BaseException:  # the end, or an error: the bag is done with
            self.close()
            raise

    def close(self) -> None:
        """Stop reading (and close the source when the stream owns it)."""
        self._lines.close()
        if self._owned:
            self.source.close()

    def __del__(self) -> None:
        self.close()  # a stream dropped before its end (a caller that only wanted the check)


def single_echo(msg: Any, echo: Echo) -> SimpleNamespace:
    """A ``MultiEchoLaserScan`` as a LaserScan-like record: per beam its first, last or strongest
    echo (strongest: by the echoes' intensities, the first echo where there are none); a beam
    without echoes has no return (inf). Intensities, when the message has one list of them per
    beam: the chosen echo's (NaN where a beam's list does not match its echoes); else none."""
    n = len(msg.ranges)
    ranges = np.full(n, np.inf, dtype=np.float32)
    inten = msg.intensities if len(msg.intensities) == n else None
    values = np.full(n, np.nan, dtype=np.float32) if inten is not None and n else None
    for k, e in enumerate(msg.ranges):
        ech = e.echoes
        if len(ech) == 0:
            continue
        ii = inten[k].echoes if inten is not None else ()
        if echo == "first":
            j = 0
        elif echo == "last":
            j = len(ech) - 1
        else:
            j = int(np.argmax(ii)) if len(ii) == len(ech) else 0
        ranges[k] = ech[j]
        if values is not None and len(ii) == len(ech):
            values[k] = ii[j]
    return SimpleNamespace(header=msg.header, angle_min=msg.angle_min, angle_increment=msg.angle_increment,
                           time_increment=msg.time_increment, range_min=msg.range_min, range_max=msg.range_max,
                           ranges=ranges, intensities=values if values is not None else ())


def _merged(src: BagSource, index: StreamIndex, plan: dict[str, str | None], reorder_ns: int,
            window: StampWindow | None, echo: Echo = "first",
            max_gap: float | None = None, record: bool = True) -> Generator[Scanline, None, None]:
    """The scans of ``plan``'s topics (within ``window``) merged into stamp order through the
    reorder buffer (see :meth:`BagSource.scans`), each recorded in ``index`` (its stamp and
    scanner id only with ``record``); with ``max_gap``, stamps that jump ahead by more than that
    (s) are an InputError."""
    heap: list[tuple[int, int, Scanline]] = []
    counter = itertools.count()
    start, stop = window.log_range_ns() if window is not None else (None, None)
    conns = [c for c in src._reader.connections if c.topic in plan]  # the bag's order (ties in log time)
    for conn, t_ns, msg in src.messages(conns, start, stop):
        s_ns = stamp_ns(msg.header)
        lag = t_ns - s_ns
        index.lag_ns = (lag, lag) if index.lag_ns is None else (min(index.lag_ns[0], lag), max(index.lag_ns[1], lag))
        if len(msg.ranges) == 0:  # a scan without beams carries nothing (and has no first-beam time)
            continue
        if window is None or window.contains(s_ns * 1e-9):
            name = plan[conn.topic] or str(msg.header.frame_id) or conn.topic
            try:
                if conn.msgtype == MULTIECHO:
                    msg = single_echo(msg, echo)
                line = Scanline.from_laserscan(msg, stamp=s_ns * 1e-9, scanner_id=name)
            except ValueError as e:
                raise input_error(src.path, f"bad LaserScan at log time {t_ns * 1e-9:.9f} s: {e}", conn.topic) from None
            heapq.heappush(heap, (s_ns, next(counter), line))
        while heap and heap[0][0] < t_ns - reorder_ns:
            yield _recorded(index, heapq.heappop(heap)[2], max_gap, src.path, record)
    while heap:
        yield _recorded(index, heapq.heappop(heap)[2], max_gap, src.path, record)


def _recorded(index: StreamIndex, line: Scanline, max_gap: float | None = None, path: Path | None = None,
              record: bool = True) -> Scanline:
    last = index.last_stamp
    if max_gap is not None and last is not None and line.stamp - last > max_gap:
        raise input_error(path or "", f"scan stamps jump by {line.stamp - last:.6g} s (from "
                          f"{last:.6f} to {line.stamp:.6f} s, scanner {line.scanner_id}): more than "
                          f"{max_gap:g} s without a scan; broken header stamps")
    if record:
        index.stamps.append(line.stamp)
        index.scanner_ids.append(line.scanner_id)
    index.last_stamp = line.stamp
    index.intensities = index.intensities or line.intensities is not None
    index.points += int(line.points_xy.shape[0])
    return line


__all__ = [
    "BagSource",
    "ImuSeries",
    "InputError",
    "PoseSeries",
    "ScanStream",
    "StampWindow",
    "StreamIndex",
    "is_bag",
    "ros2_bag_dir",
]
