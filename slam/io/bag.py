"""One-shot questions to a ROS1 or ROS2 bag, each opening it once (``slam.io.source.BagSource``;
a caller with several questions opens a ``BagSource`` itself): laser scans, static transforms,
poses, IMU, topics, time range. Every failure to read is an ``InputError`` naming the bag (and
the topic).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from common.rig import Rig
from slam.io.errors import InputError
from slam.io.source import BagSource, Echo, FloatArray, ImuSeries, PoseSeries, ScanStream, is_bag


def read_scans(
    path: str | Path,
    topics: Sequence[str] | None = None,
    rig: Rig | None = None,
    *,
    reorder_window: float = 1.0,
    echo: Echo = "first",
) -> ScanStream:
    """Stream the ``sensor_msgs/LaserScan`` (and ``MultiEchoLaserScan``: each beam's ``echo``)
    messages of a bag as Scanlines ordered by header stamp (see :meth:`BagSource.scans`); the bag and its topics are checked before this returns, and
    the bag is closed when the stream is closed or exhausted."""
    source = BagSource(path)
    try:
        return source.scans(topics, rig, reorder_window=reorder_window, owned=True, echo=echo)
    except BaseException:
        source.close()
        raise


def read_tf_static(path: str | Path, topic: str = "/tf_static") -> dict[tuple[str, str], FloatArray]:
    """Static transforms (parent, child) -> ``T_parent_child`` (see :meth:`BagSource.tf_static`)."""
    with BagSource(path) as source:
        return source.tf_static(topic)


def read_poses(path: str | Path, topic: str = "/ground_truth") -> PoseSeries:
    """All ``geometry_msgs/PoseStamped`` messages of ``topic`` as arrays, in log order."""
    with BagSource(path) as source:
        return source.poses(topic)


def read_imu(path: str | Path, topic: str = "/imu") -> ImuSeries:
    """All ``sensor_msgs/Imu`` messages of ``topic`` as arrays, in log order."""
    with BagSource(path) as source:
        return source.imu(topic)


def topics(path: str | Path) -> dict[str, str]:
    """Topic -> message type (``pkg/msg/Name``) of every connection in the bag."""
    with BagSource(path) as source:
        return source.topics()


def time_range(path: str | Path) -> tuple[float, float]:
    """(start, end) log time of a bag in seconds."""
    with BagSource(path) as source:
        return source.time_range()


__all__ = [
    "ImuSeries",
    "InputError",
    "PoseSeries",
    "is_bag",
    "read_imu",
    "read_poses",
    "read_scans",
    "read_tf_static",
    "time_range",
    "topics",
]
