"""Readers and writers of scan data: CARMEN logs, ROS1/ROS2 bags, ``.npz``/CSV scanlines.

``open_scans(path)`` picks the reader from the file's content and name and returns a
stream of ``segmentation.Scanline`` records (scanner frame, absolute per-beam times).
A bag asked several questions (time range, topics, IMU, scans by stamp window) is opened once
as a ``slam.io.source.BagSource``; ``slam.io.bag`` asks one question per open.
Every reader raises ``InputError`` (a ``ValueError``) naming the file, and the topic
for bags, when the input cannot be used.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

from common.rig import Rig
from segmentation import Scanline
from slam.io import bag, carmen, scanfile
from slam.io.errors import InputError, input_error

Format = Literal["bag", "carmen", "npz", "csv"]
_CARMEN_HEADS = (b"FLASER", b"ROBOTLASER1", b"PARAM", b"ODOM", b"RLASER", b"NEFF", b"SYNC", b"TRUEPOS", b"#")


def detect_format(path: str | Path) -> Format:
    """The input format of ``path``: by magic bytes (ROS1 bag, gzip = CARMEN log, zip = .npz),
    a ROS2 bag directory, the ``.npz``/``.csv`` suffix, or CARMEN line headers in plain text."""
    p = Path(path)
    if not p.exists():
        raise input_error(p, "no such file or directory")
    if bag.is_bag(p):
        return "bag"
    if p.is_dir():
        raise input_error(p, "a directory that is not a ROS2 bag (no metadata.yaml)")
    with open(p, "rb") as f:
        head = f.read(4096)
    if head.startswith(b"\x1f\x8b"):
        return "carmen"
    if head.startswith(b"PK") or p.suffix.lower() == ".npz":
        return "npz"
    if p.suffix.lower() == ".csv":
        return "csv"
    first = next((ln.strip() for ln in head.splitlines() if ln.strip()), b"")
    if first.startswith(_CARMEN_HEADS):
        return "carmen"
    if p.suffix.lower() == ".bag":
        raise input_error(p, "not a ROS1 bag (no '#ROSBAG V2.0' header)")
    raise input_error(p, "unknown input format: expected a ROS1/ROS2 bag, a CARMEN log, .npz or .csv")


def open_scans(
    path: str | Path, *, topics: Sequence[str] | None = None, rig: Rig | None = None, **kw: Any
) -> Iterator[Scanline]:
    """A stream of the Scanlines in ``path`` (bag, CARMEN log, ``.npz`` or CSV).

    ``topics`` and ``rig`` select bag topics (see ``bag.read_scans``); other keyword
    arguments go to the format's reader (``carmen.read_carmen``: ``range_max``,
    ``time_increment``, ``angle_convention``, ``scanner_id``).
    """
    fmt = detect_format(path)
    if fmt == "bag":
        return bag.read_scans(path, topics=topics, rig=rig, **kw)
    if topics or rig is not None:
        raise input_error(path, f"topics and rigs apply to ROS bags only; this is a {fmt} file")
    if fmt == "carmen":
        return carmen.read_carmen_scans(path, **kw)
    if kw:
        raise TypeError(f"unexpected arguments for a {fmt} file: {', '.join(sorted(kw))}")
    return scanfile.read_npz(path) if fmt == "npz" else scanfile.read_csv(path)


__all__ = ["Format", "InputError", "detect_format", "open_scans"]
