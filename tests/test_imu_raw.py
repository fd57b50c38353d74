"""slam.io.imu_raw: IMU messages read as columns from their bytes, the same as deserialised."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import slam.io.source as source_mod
from simulation.run import simulate
from slam.io.imu_raw import imu_columns
from slam.io.source import BagSource, ImuSeries

_FIELDS = ("times", "angular_velocity", "linear_acceleration", "orientation_xyzw")


def _slow(bag: Path, topic: str, monkeypatch: pytest.MonkeyPatch) -> ImuSeries:
    with monkeypatch.context() as m:
        m.setattr(source_mod, "imu_columns", lambda raws, ros2: None)
        with BagSource(bag) as s:
            return s.imu(topic)


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_imu_columns_are_the_deserialised_messages(tmp_path: Path, fmt: str, monkeypatch: pytest.MonkeyPatch) -> None:
    res = simulate("demo", "itc_backpack", duration=1.0, seed=0, out=tmp_path / "run.bag", fmt=fmt, imu=True,
                   progress=False)
    with BagSource(res.bag) as s:
        found = s.imu_topic()
        assert found is not None
        topic = found[0]
        raws = [raw for _, _, raw in s._reader.messages(connections=s.connections(topic, source_mod.IMU))]
        cols = imu_columns(raws, fmt == "ros2")
        assert cols is not None, "the simulator's messages share one layout: read as columns"
        fast = s.imu(topic)
    slow = _slow(res.bag, topic, monkeypatch)
    assert len(fast) == len(slow) > 100 and fast.frame_id == slow.frame_id
    for name in _FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
    # messages of another layout (a longer frame id in one of them, cut short): not read as columns
    assert imu_columns([*raws[:5], raws[5][:-8]], fmt == "ros2") is None
    assert imu_columns([raws[0][:12]], fmt == "ros2") is None
    assert imu_columns([], fmt == "ros2") is None


def test_a_wrong_layout_falls_back_to_the_deserialiser(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Columns that disagree with the deserialised messages (a layout misread) are not used."""
    res = simulate("demo", "itc_backpack", duration=1.0, seed=0, out=tmp_path / "run.bag", fmt="ros1", imu=True,
                   progress=False)
    with BagSource(res.bag) as s:
        found = s.imu_topic()
        assert found is not None
        topic = found[0]
    slow = _slow(res.bag, topic, monkeypatch)

    def misread(raws: list[bytes], ros2: bool) -> object:
        cols = imu_columns(raws, ros2)
        assert cols is not None
        cols.angular_velocity = cols.angular_velocity[:, ::-1].copy()  # axes swapped
        return cols

    monkeypatch.setattr(source_mod, "imu_columns", misread)
    with BagSource(res.bag) as s:
        got = s.imu(topic)
    for name in _FIELDS:
        np.testing.assert_array_equal(getattr(got, name), getattr(slow, name), err_msg=name)
