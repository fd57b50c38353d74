"""A rig from a recording's transforms or a URDF, its agreement with a given rig, and which
degrees of freedom a rig's scanners constrain."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from common.rig import resolve_rig
from common.rotations import rpy_to_matrix
from slam.rig_builder import (
    FrameTree,
    RigError,
    ScanTopic,
    build_rig,
    compare_rig,
    rig_verdict,
    urdf_transforms,
)
from slam.rig_check import rig_observability

URDF = Path(__file__).parent / "data" / "backpack_2d.urdf"


def _T(xyz: tuple[float, float, float], rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(*rpy)
    T[:3, 3] = xyz
    return T


def _scan(topic: str, frame: str) -> ScanTopic:
    return ScanTopic(topic, "MultiEchoLaserScan", frame, -math.radians(134.75), math.radians(0.25), 1079,
                     0.025 / 1440, 0.025, 0.1, 30.0)


def test_chains_compose_in_either_direction() -> None:
    tree = FrameTree({("map", "base"): _T((1, 2, 0), (0, 0, 0.5)), ("base", "laser"): _T((0.1, 0, 0.2))}, "bag")
    np.testing.assert_allclose(tree.transform("map", "laser"), _T((1, 2, 0), (0, 0, 0.5)) @ _T((0.1, 0, 0.2)))
    np.testing.assert_allclose(tree.transform("laser", "map") @ tree.transform("map", "laser"), np.eye(4), atol=1e-12)
    assert tree.roots() == ["map"]
    with pytest.raises(RigError, match="unknown frame 'nope'"):
        tree.transform("map", "nope")
    split = FrameTree({("a", "b"): np.eye(4), ("c", "d"): np.eye(4)}, "bag")
    with pytest.raises(RigError, match="no chain of transforms joins 'a' and 'd'"):
        split.transform("a", "d")


def test_cartographer_urdf_gives_the_cartographer_rig() -> None:
    tree = FrameTree(urdf_transforms(URDF), str(URDF))
    rig = build_rig("from_urdf", [_scan("horizontal_laser_2d", "horizontal_laser_link"),
                                  _scan("vertical_laser_2d", "vertical_laser_link")], tree, imu=("imu", "imu_link"))
    want = resolve_rig("cartographer_backpack_2d")
    assert rig.body_frame == "imu_link" and rig.reference == "horizontal_laser_link"
    for got, ref in zip(rig.scanners, want.scanners, strict=True):
        np.testing.assert_allclose(got.T_body_scanner.matrix(), ref.T_body_scanner.matrix(), atol=1e-5)
        assert got.scanner_model.n_beams == 1079 and got.message == "MultiEchoLaserScan"
    # base_link is the URDF's root: the same rig in that frame
    rig2 = build_rig("r", [_scan("h", "horizontal_laser_link")], tree, base="base_link")
    np.testing.assert_allclose(rig2.scanners[0].T_body_scanner.translation, [0.1007, 0.0, 0.0558])


def test_unknown_frames_and_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    tree = FrameTree(urdf_transforms(URDF), str(URDF))
    with pytest.raises(RigError, match=r"backpack_2d.urdf: unknown frame 'laser_3'"):
        build_rig("r", [_scan("t", "laser_3")], tree)
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/>")
    with pytest.raises(RigError, match=r"bad\.urdf: (not a readable URDF|the URDF has no joints)"):
        urdf_transforms(bad)
    with pytest.raises(RigError, match="no such URDF"):
        urdf_transforms(tmp_path / "none.urdf")


def test_a_wrong_rig_is_refused_and_a_slightly_off_one_reported() -> None:
    rig = resolve_rig("itc_backpack")
    truth = {(rig.body_frame, s.frame): s.T_body_scanner.matrix() for s in rig.scanners}
    frames = {s.name: s.frame for s in rig.scanners}
    same = compare_rig(rig, FrameTree(truth, "bag"), frames)
    assert [m.angle for m in same] == pytest.approx([0, 0, 0], abs=1e-7)
    assert rig_verdict(rig, same, "bag") == (None, [])
    slightly = dict(truth)
    slightly[("body", "left")] = truth[("body", "left")] @ _T((0.01, 0, 0), (math.radians(0.5), 0, 0))
    err, warn = rig_verdict(rig, compare_rig(rig, FrameTree(slightly, "bag"), frames), "bag")
    assert err is None and len(warn) == 1 and "scanner 'left' differs by 0.50 deg / 0.010 m" in warn[0]
    other = dict(truth)
    other[("body", "right")] = _T((0.3, -0.1, 0.1), (0.0, 0.7, 0.0))
    err, _ = rig_verdict(rig, compare_rig(rig, FrameTree(other, "bag"), frames), "bag")
    assert err is not None and err.startswith("rig 'itc_backpack' does not match the transforms of bag: scanner 'right'")


def test_observability_of_the_two_rigs() -> None:
    itc = rig_observability(resolve_rig("itc_backpack"))
    assert itc.observed
    carto = rig_observability(resolve_rig("cartographer_backpack_2d"))
    assert carto.unobserved_names() == ["pitch"]
    assert "left to an IMU: pitch" in carto.summary()
    rig = resolve_rig("itc_backpack")
    top = rig.model_copy(update={"scanners": [rig.scanner("top")]})
    assert sorted(rig_observability(top).unobserved_names()) == ["pitch", "roll", "z"]
