"""Checks before a run processes anything: the rig it is given (or builds from the recording)
against the recording's transforms, and whether the rig's scanners observe every degree of
freedom or leave some to an IMU the recording does not have.

A failed check is a :class:`slam.rig_builder.RigError` naming the rig, the recording and the
cause, raised before any output is written; smaller findings come back as notes to print.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from common.rig import Rig
from slam.io.source import BagSource, Echo
from slam.rig_builder import (
    FrameTree,
    RigError,
    RigMismatch,
    ScanTopic,
    compare_rig,
    rig_from_source,
    rig_verdict,
    scan_topics,
    static_transforms,
    urdf_transforms,
)
from slam.rig_check import rig_observability


@dataclass
class RigCheck:
    """The rig a run uses, where it came from, what the checks found (one line each), and how
    far each scanner of a given rig is from the recording's transforms (``mismatches``; empty
    when the rig was built from them or there are none to compare)."""

    rig: Rig
    source: str
    notes: list[str] = field(default_factory=list)
    mismatches: list[RigMismatch] = field(default_factory=list)


def check_rig(src: BagSource, rig: Rig | None, urdf: str | Path | None, echo: Echo) -> RigCheck:
    """The run's rig: ``rig`` checked against the recording's transforms (or ``urdf``), or, when
    None, built from them (MultiEchoLaserScan noise measured on the run's ``echo``)."""
    if rig is None:
        built = rig_from_source(src, urdf=urdf, echo=echo)
        where = f"the URDF {urdf}" if urdf is not None else "the recording's transforms"
        return RigCheck(built, f"built from {where}", [
            f"rig built from {where} of {src.path}: " + ", ".join(f"{s.name} on {s.topic}" for s in built.scanners)])
    out = RigCheck(rig, "given")
    check_geometry(rig, scan_topics(src), str(src.path))
    transforms = urdf_transforms(urdf) if urdf is not None else static_transforms(src)
    if transforms:
        where = str(urdf) if urdf is not None else f"{src.path}"
        tree = FrameTree(transforms, where)
        by_topic = rig.by_topic()
        frames = {by_topic[s.topic].name: s.frame_id for s in scan_topics(src) if s.topic in by_topic}
        out.mismatches = compare_rig(rig, tree, frames)
        error, warnings = rig_verdict(rig, out.mismatches, where)
        if error is not None:
            raise RigError(error)
        out.notes += warnings
    return out


def check_geometry(rig: Rig, scans: list[ScanTopic], source: str) -> None:
    """Each scan topic's beam geometry (from its first message) against the rig's scanner model
    for that topic; a mismatch is a RigError naming the topic and the field."""
    by_topic = rig.by_topic()
    for s in scans:
        sc = by_topic.get(s.topic)
        if sc is None:
            continue
        m = sc.scanner_model
        for what, bag_value, rig_value, tol in (
            ("number of beams", float(s.n_beams), float(m.n_beams), 0.5),
            ("angle_min", s.angle_min, m.angle_min, 1e-4),
            ("angle_increment", s.angle_increment, m.angle_increment, 1e-6),
        ):
            if abs(bag_value - rig_value) > tol:
                raise RigError(f"{source}: topic {s.topic}: {what} {bag_value:g} in the recording, {rig_value:g} in "
                               f"rig '{rig.name}' (scanner '{sc.name}', model '{m.name}')")


def check_observability(rig: Rig, src: BagSource, imu_topic: str | None) -> list[str]:
    """Notes on the degrees of freedom ``rig``'s scanners leave to an IMU; a RigError when they
    leave any and the run has no IMU (``imu_topic`` None)."""
    obs = rig_observability(rig)
    if obs.observed:
        return []
    left = ", ".join(obs.unobserved_names())
    if imu_topic is None:
        raise RigError(
            f"rig '{rig.name}' leaves {left} to an IMU (its scanners do not observe it from walls, floor and "
            f"ceiling) and {src.path} has no IMU the run can use: the estimate would drift; record an IMU or add a "
            "scanner that sees it")
    return [f"rig '{rig.name}': {obs.summary()} (IMU: {imu_topic})"]
