"""``sensor_msgs/Imu`` messages read as columns straight from their serialized bytes.

An hour's IMU at 200 Hz is 720,000 messages; deserialising each into Python objects (rosbags)
and taking its fields one by one costs seconds. Every message of a topic has the same layout
when its ``frame_id`` keeps one length, so the messages laid end to end are one numpy array of
records: ROS1's serialization (packed little-endian fields, strings as a 4-byte length and the
bytes) and ROS2's CDR (a 4-byte encapsulation header, then fields aligned to their size, strings
with a 4-byte length that counts their terminating NUL). Anything else (messages of other
lengths, another encapsulation) gives None and the caller deserialises message by message.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_TAIL = 37 * 8  # orientation (4), its covariance (9), angular velocity (3), covariance (9), acceleration (3), covariance (9)
_CDR_LE = b"\x00\x01\x00\x00"


@dataclass
class ImuColumns:
    """The messages' header stamps (integer ns), frame id, angular velocity, linear acceleration
    and orientation (x, y, z, w), one row per message."""

    stamp_ns: NDArray[np.int64]
    frame_id: str
    angular_velocity: FloatArray
    linear_acceleration: FloatArray
    orientation_xyzw: FloatArray


def _tail_fields(offset: int) -> list[tuple[str, str, int]]:
    """The vectors after the header, from byte ``offset``."""
    out, o = [], offset
    for name, n in (("q", 4), ("q_cov", 9), ("w", 3), ("w_cov", 9), ("a", 3), ("a_cov", 9)):
        out.append((name, f"({n},)<f8", o))
        o += 8 * n
    return out


def _layout(first: bytes, size: int, ros2: bool) -> tuple[np.dtype[np.void], int] | None:
    """The record dtype of a message like ``first`` (``size`` bytes) and its frame id's length
    (bytes, without a terminating NUL), or None when the message does not have Imu's layout."""
    if ros2:
        if size < 16 or first[:4] != _CDR_LE:
            return None
        n = int.from_bytes(first[12:16], "little")  # the length with the NUL
        if n < 1:
            return None
        tail = 4 + (-(12 + n) % 8) + 12 + n  # after the header, aligned to 8 from the data's start
        fields = [("sec", "<i4", 4), ("nsec", "<u4", 8), ("len", "<u4", 12), ("frame", f"S{n}", 16)]
        frame_len = n - 1
    else:
        if size < 16:
            return None
        n = int.from_bytes(first[12:16], "little")
        tail = 16 + n
        fields = [("seq", "<u4", 0), ("sec", "<u4", 4), ("nsec", "<u4", 8), ("len", "<u4", 12), ("frame", f"S{n}", 16)]
        frame_len = n
    if tail + _TAIL != size:
        return None
    fields += _tail_fields(tail)
    dtype = np.dtype({"names": [f[0] for f in fields], "formats": [f[1] for f in fields],
                      "offsets": [f[2] for f in fields], "itemsize": size})
    return dtype, frame_len


def imu_columns(raws: Sequence[bytes], ros2: bool) -> ImuColumns | None:
    """The columns of serialized ``sensor_msgs/Imu`` messages (ROS2's CDR when ``ros2``, else
    ROS1's), or None when they do not all share one layout (the caller deserialises them)."""
    if not raws:
        return None
    size = len(raws[0])
    if any(len(r) != size for r in raws):
        return None
    got = _layout(bytes(raws[0][:16]), size, ros2)
    if got is None:
        return None
    dtype, frame_len = got
    rows = np.frombuffer(b"".join(raws), dtype=dtype)
    if np.any(rows["len"] != rows["len"][0]) or np.any(rows["frame"] != rows["frame"][0]):
        return None
    frame = bytes(rows["frame"][0])[:frame_len].rstrip(b"\x00").decode("utf-8", errors="replace")
    stamp = rows["sec"].astype(np.int64) * 1_000_000_000 + rows["nsec"].astype(np.int64)
    return ImuColumns(stamp, frame, np.array(rows["w"], dtype=np.float64), np.array(rows["a"], dtype=np.float64),
                      np.array(rows["q"], dtype=np.float64))
