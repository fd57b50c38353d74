"""A rig from a recording's own data: scanner models from the scans' geometry, extrinsics from
the transforms (``/tf_static``, the static part of ``/tf``, or a URDF), and the agreement of a
given rig with those transforms.

Frames: ``T_a_b`` maps points from frame b to frame a. The body frame is ``--base`` when given,
else the IMU's frame when the transforms know it, else the root of the transform tree that holds
the scanners. The reference scanner is the most level one (its scan plane closest to the body's
x-y plane), the first of equals in topic order.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError

from common.rig import Extrinsic, ImuMount, MessageType, Rig, ScannerConfig, ScannerModel
from common.rotations import matrix_to_rpy
from slam.io.source import MULTIECHO, SCAN_TYPES, BagSource, Echo

FloatArray = NDArray[np.float64]
Transforms = Mapping[tuple[str, str], FloatArray]  # (parent, child) -> T_parent_child

# a rig that differs from the recording's transforms by more than this is refused ...
REFUSE_ANGLE = math.radians(3.0)
REFUSE_DISTANCE = 0.05
# ... and by more than this is reported (a recalibrated rig legitimately differs a little)
WARN_ANGLE = math.radians(0.2)
WARN_DISTANCE = 0.005


class RigError(ValueError):
    """A rig that cannot be built from, or does not match, a recording; the message names it."""


@dataclass(frozen=True)
class ScanTopic:
    """A scan topic as its first message describes it (LaserScan or MultiEchoLaserScan)."""

    topic: str
    message: MessageType
    frame_id: str
    angle_min: float
    angle_increment: float
    n_beams: int
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float

    def model(self, range_sigma: float) -> ScannerModel:
        """The scanner model these messages describe (noise from elsewhere: ``range_sigma``)."""
        period = self.scan_time if self.scan_time > 0 else max(self.time_increment * self.n_beams, 1e-3)
        return ScannerModel(
            name=f"{self.topic} (from the recording)", n_beams=self.n_beams, angle_min=self.angle_min,
            angle_increment=self.angle_increment, scan_period=period, time_increment=max(self.time_increment, 0.0),
            range_min=self.range_min, range_max=self.range_max, range_sigma=range_sigma,
        )

    def check(self, recording: str | Path) -> None:
        """A RigError naming ``recording`` and the topic when its messages describe no scanner a
        rig can hold (non-finite or inconsistent angles, ranges or timing)."""
        try:
            self.model(0.01)
        except ValidationError as e:
            first = e.errors()[0]
            key = ".".join(str(x) for x in first.get("loc", ()))
            raise RigError(f"{recording} topic {self.topic}: its scans describe no usable scanner "
                           f"({key + ': ' if key else ''}{first.get('msg', 'invalid')})") from None


def _f32(x: float) -> float:
    """A float32 message field as the shortest decimal that reads back to it (0.1, not 0.10000000149)."""
    return float(str(np.float32(x)))


def _inverse(T: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


class FrameTree:
    """Transforms between named frames, composed along chains in either direction."""

    def __init__(self, transforms: Transforms, source: str) -> None:
        self.source = source
        self._edges: dict[str, list[tuple[str, FloatArray]]] = {}
        for (parent, child), T in transforms.items():
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise RigError(f"{source}: transform {parent} -> {child} is not a finite 4x4 matrix")
            self._edges.setdefault(parent, []).append((child, T))
            self._edges.setdefault(child, []).append((parent, _inverse(T)))
        self.children = {c for (_, c) in transforms}

    @property
    def frames(self) -> set[str]:
        return set(self._edges)

    def roots(self) -> list[str]:
        """Frames that are no one's child, sorted."""
        return sorted(self.frames - self.children)

    def has(self, frame: str) -> bool:
        return frame in self._edges

    def transform(self, target: str, frame: str) -> FloatArray:
        """``T_target_frame``; a RigError names the frames and the source when no chain joins them."""
        for f in (target, frame):
            if f not in self._edges:
                known = ", ".join(sorted(self.frames)) or "none"
                raise RigError(f"{self.source}: unknown frame '{f}' (frames: {known})")
        seen = {target: np.eye(4)}
        queue = deque([target])
        while queue:
            a = queue.popleft()
            for b, T_a_b in self._edges[a]:
                if b not in seen:
                    seen[b] = seen[a] @ T_a_b
                    if b == frame:
                        return seen[b]
                    queue.append(b)
        if frame in seen:
            return seen[frame]
        raise RigError(f"{self.source}: no chain of transforms joins '{target}' and '{frame}'")


def urdf_transforms(path: str | Path) -> dict[tuple[str, str], FloatArray]:
    """The joints of a URDF as (parent link, child link) -> ``T_parent_child`` at the joints'
    zero positions; a file yourdfpy cannot read is a RigError naming it."""
    import yourdfpy

    p = Path(path)
    if not p.is_file():
        raise RigError(f"{p}: no such URDF file")
    try:
        urdf = yourdfpy.URDF.load(str(p), build_scene_graph=False, load_meshes=False,
                                  build_collision_scene_graph=False, load_collision_meshes=False)
    except Exception as e:  # yourdfpy/lxml raise many kinds; all mean the same to the user
        raise RigError(f"{p}: not a readable URDF ({' '.join(str(e).split()) or type(e).__name__})") from None
    out: dict[tuple[str, str], FloatArray] = {}
    for j in urdf.robot.joints:
        T = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        out[(str(j.parent), str(j.child))] = T
    if not out:
        raise RigError(f"{p}: the URDF has no joints (no transforms between its links)")
    return out


def choose_base(tree: FrameTree, scanner_frames: Sequence[str], imu_frame: str | None) -> str:
    """The body frame: the IMU's frame if the tree knows it, else the root holding the scanners."""
    if imu_frame and tree.has(imu_frame):
        return imu_frame
    for root in tree.roots():
        try:
            for f in scanner_frames:
                tree.transform(root, f)
        except RigError:
            continue
        return root
    raise RigError(f"{tree.source}: no frame joins the scanners' frames {', '.join(scanner_frames)}; give --base")


def build_rig(name: str, scans: Sequence[ScanTopic], tree: FrameTree, base: str | None = None,
              imu: tuple[str, str] | None = None, range_sigma: Mapping[str, float] | None = None,
              default_sigma: float = 0.01) -> Rig:
    """The rig of ``scans`` (one scanner per topic) mounted as ``tree`` says, in the body frame
    ``base`` (chosen by :func:`choose_base` when None). ``imu`` is (topic, frame) when the
    recording has one; ``range_sigma`` per topic (measured), else ``default_sigma``."""
    if not scans:
        raise RigError(f"{tree.source}: no LaserScan or MultiEchoLaserScan topics")
    frames = [s.frame_id for s in scans]
    for f in frames:
        tree.transform(f, f)  # a RigError naming an unknown frame
    body = base if base is not None else choose_base(tree, frames, imu[1] if imu else None)
    scanners = []
    used: set[str] = set()
    for s in scans:
        T = tree.transform(body, s.frame_id)
        nm = _scanner_name(s.frame_id, s.topic, used)
        roll, pitch, yaw = matrix_to_rpy(T[:3, :3])
        scanners.append(ScannerConfig(
            name=nm, topic=s.topic, frame_id=s.frame_id, message=s.message,
            model=s.model((range_sigma or {}).get(s.topic, default_sigma)),
            T_body_scanner=Extrinsic(translation=[float(x) for x in T[:3, 3]], rpy=[roll, pitch, yaw]),
        ))
    level = [abs(float(sc.T_body_scanner.matrix()[2, 2])) for sc in scanners]
    reference = scanners[int(np.argmax(np.round(level, 6)))].name
    mount = ImuMount(topic=imu[0], frame_id=imu[1]) if imu else ImuMount(frame_id=body)
    return Rig(name=name, reference=reference, scanners=scanners, body_frame=body, imu=mount)


def _scanner_name(frame: str, topic: str, used: set[str]) -> str:
    """The frame id (``/`` -> ``_``) when it is free, else the topic's."""
    base = (frame or topic).strip("/").replace("/", "_") or "scanner"
    if base in used:
        base = topic.strip("/").replace("/", "_") or "scanner"
    name, k = base, 2
    while name in used:
        name, k = f"{base}_{k}", k + 1
    used.add(name)
    return name


@dataclass(frozen=True)
class RigMismatch:
    """How far one scanner of a rig is from the recording's transforms."""

    scanner: str
    angle: float  # rad
    distance: float  # m

    def __str__(self) -> str:
        return f"scanner '{self.scanner}' differs by {math.degrees(self.angle):.2f} deg / {self.distance:.3f} m"


def compare_rig(rig: Rig, tree: FrameTree, scanner_frames: Mapping[str, str]) -> list[RigMismatch]:
    """Each scanner's ``T_body_scanner`` against the recording's transform from the rig's body
    frame to the scanner's frame (``scanner_frames``: scanner name -> frame id of its messages).
    Scanners whose frames the transforms do not join are skipped (nothing to compare)."""
    out = []
    for sc in rig.scanners:
        frame = scanner_frames.get(sc.name, sc.frame)
        if not (tree.has(rig.body_frame) and tree.has(frame)):
            continue
        try:
            T_bag = tree.transform(rig.body_frame, frame)
        except RigError:
            continue
        T = sc.T_body_scanner.matrix()
        dR = T[:3, :3].T @ T_bag[:3, :3]
        angle = math.acos(max(-1.0, min(1.0, (float(np.trace(dR)) - 1.0) / 2.0)))
        out.append(RigMismatch(sc.name, angle, float(np.linalg.norm(T[:3, 3] - T_bag[:3, 3]))))
    return out


def rig_verdict(rig: Rig, mismatches: Sequence[RigMismatch], source: str) -> tuple[str | None, list[str]]:
    """(error, warnings) of a rig against the recording ``source``: an error when any scanner is
    off by more than REFUSE_ANGLE / REFUSE_DISTANCE, warnings above WARN_ANGLE / WARN_DISTANCE."""
    bad = [m for m in mismatches if m.angle > REFUSE_ANGLE or m.distance > REFUSE_DISTANCE]
    warn = [m for m in mismatches if m not in bad and (m.angle > WARN_ANGLE or m.distance > WARN_DISTANCE)]
    error = None
    if bad:
        worst = max(bad, key=lambda m: (m.angle / REFUSE_ANGLE + m.distance / REFUSE_DISTANCE))
        error = f"rig '{rig.name}' does not match the transforms of {source}: {worst}"
    return error, [f"rig '{rig.name}' differs slightly from the transforms of {source}: {m}" for m in warn]


def scan_topics(src: BagSource) -> list[ScanTopic]:
    """Every scan topic of the recording, described by its first message (topic order)."""
    out = []
    counts = src.message_counts()
    for topic, msgtype in src.topics().items():
        if msgtype not in SCAN_TYPES or counts.get(topic, 0) == 0:
            continue
        for _, _, msg in src.messages(src.connections(topic, SCAN_TYPES)):
            n = len(msg.ranges)
            out.append(ScanTopic(topic, "MultiEchoLaserScan" if msgtype == MULTIECHO else "LaserScan",
                                 str(msg.header.frame_id), _f32(msg.angle_min), _f32(msg.angle_increment), n,
                                 _f32(msg.time_increment), _f32(msg.scan_time), _f32(msg.range_min),
                                 _f32(msg.range_max)))
            break
    return out


def static_transforms(src: BagSource) -> dict[tuple[str, str], FloatArray]:
    """``/tf_static`` and the pairs of ``/tf`` whose transform never changes in the recording."""
    out = src.tf_static()
    moving: set[tuple[str, str]] = set()
    dynamic: dict[tuple[str, str], FloatArray] = {}
    for key, T in src.transforms("/tf"):
        if key in dynamic and not np.allclose(dynamic[key], T, atol=1e-9):
            moving.add(key)
        dynamic.setdefault(key, T)
    for key, T in dynamic.items():
        if key not in moving and key not in out:
            out[key] = T
    return out


def rig_from_source(src: BagSource, urdf: str | Path | None = None, base: str | None = None,
                    name: str | None = None, *, echo: Echo) -> Rig:
    """The rig of a recording: its scan topics, mounted as its transforms (or ``urdf``) say; the
    range noise measured on each MultiEchoLaserScan beam's ``echo`` (the run's ``input.echo``)."""
    scans = scan_topics(src)
    if not scans:
        raise RigError(f"{src.path}: no LaserScan or MultiEchoLaserScan topic with messages")
    for s in scans:
        s.check(src.path)
    if urdf is not None:
        tree = FrameTree(urdf_transforms(urdf), str(urdf))
    else:
        transforms = static_transforms(src)
        if not transforms:
            raise RigError(f"{src.path}: the recording has no /tf_static or static /tf transforms; "
                           "give the rig (--rig) or a URDF (--urdf)")
        tree = FrameTree(transforms, f"the transforms of {src.path}")
    imu = src.imu_topic()
    return build_rig(name or f"{Path(src.path).stem}_rig", scans, tree, base, imu, measured_noise(src, scans, echo=echo))


def measured_noise(src: BagSource, scans: Sequence[ScanTopic], n_scans: int = 200, *,
                   echo: Echo) -> dict[str, float]:
    """Each scan topic's range noise (m, at its median range) from its first ``n_scans`` scans
    (``segmentation.noise``; a MultiEchoLaserScan's ``echo`` of each beam); topics whose scans do not hold enough straight stretches are left
    out (the rig then takes the default)."""
    from segmentation.noise import estimate

    out: dict[str, float] = {}
    for s in scans:
        stream = src.scans(topics=[s.topic], echo=echo)
        try:
            lines = [line for _, line in zip(range(n_scans), stream, strict=False)]
        finally:
            stream.close()
        try:
            out[s.topic] = float(estimate(lines).sigma_ref)
        except ValueError:
            continue
    return out
