"""A small rerun recording is written atomically and verified with the rerun CLI."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from slam.export import CloudRecord, PlaneRecord
from slam.rerun_map import (
    MapOptions,
    SegmentLines,
    _log_scans,
    fan_triangles,
    plane_colors,
    view_of_cloud,
    write_map_rrd,
)


def _rerun_cli() -> str:
    exe = Path(sys.executable).with_name("rerun")
    found = str(exe) if exe.exists() else shutil.which("rerun")
    assert found, "the rerun CLI ships with rerun-sdk and must be installed beside python"
    return found


def _rrd(*args: str) -> str:
    env = {**os.environ, "RERUN_ANALYTICS": "false"}
    res = subprocess.run(
        [_rerun_cli(), "rrd", *args], capture_output=True, text=True, env=env, timeout=60
    )
    assert res.returncode == 0, res.stderr
    return res.stdout + res.stderr


def _walk(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    t = 100.0 + 0.025 * np.arange(n)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = 1.2 * (t - t[0])
    T[:, 2, 3] = 1.5
    return t, T


def _cloud(t: np.ndarray) -> CloudRecord:
    rng = np.random.default_rng(0)
    n = 3000
    time = np.sort(rng.uniform(t[0], t[-1], n))
    pts = rng.uniform(-3, 3, (n, 3))
    return CloudRecord(pts, rng.integers(0, 3, n).astype(np.int32), time,
                       rng.integers(-1, 6, n).astype(np.int32))  # fmt: skip


def _planes() -> list[PlaneRecord]:
    floor = np.array([[0, -2, 0], [5, -2, 0], [5, 2, 0], [0, 2, 0]], float)
    wall = np.array([[0, 2, 0], [5, 2, 0], [5, 2, 3], [0, 2, 3]], float)
    return [
        PlaneRecord(0, np.array([0, 0, 1.0]), 0.0, floor, kind="floor"),
        PlaneRecord(1, np.array([0, -1.0, 0]), 2.0, wall, kind="wall"),
        PlaneRecord(2, np.array([1.0, 0, 0]), 0.0, np.zeros((0, 3))),  # no extent: skipped
        # two doors at one depth: a patch and an outline per region
        PlaneRecord(3, np.array([0, 1.0, 0]), 0.0, wall, kind="wall", outline="final_map",
                    regions=(wall[[0, 1, 2, 3, 0]] * [0.3, 1, 1], wall[[0, 1, 2, 3, 0]] * [1, 1, 1] + [0.5, 0, 0])),
    ]


def test_palette_and_fan() -> None:
    c = plane_colors(np.array([-1, 0, 20, 3]))
    assert c.dtype == np.uint8 and c.shape == (4, 3)
    assert tuple(c[0]) == (150, 150, 150)
    assert tuple(c[1]) == tuple(c[2])  # cycled
    assert tuple(c[1]) != tuple(c[3])
    np.testing.assert_array_equal(fan_triangles(5), [[0, 1, 2], [0, 2, 3], [0, 3, 4]])


def test_write_and_verify(tmp_path: Path) -> None:
    t, T = _walk()
    seg = SegmentLines(
        stamp=t[::4],
        endpoints_world=np.stack([T[::4, :3, 3], T[::4, :3, 3] + [0, 1, 0]], axis=1),
        plane_id=np.arange(len(t[::4]), dtype=np.int32) % 3 - 1,
    )
    out = write_map_rrd(
        tmp_path / "map.rrd",
        times=t,
        T_world_body=T,
        planes=_planes(),
        cloud=_cloud(t),
        scanner_names=["top", "left", "right"],
        segments=seg,
        options=MapOptions(max_scan_points=1000),
    )
    assert out.stat().st_size > 1000
    assert [p.name for p in tmp_path.iterdir()] == ["map.rrd"]  # no temporary left
    assert "verified without error" in _rrd("verify", str(out))
    printed = _rrd("print", str(out))
    for entity in (
        "/world/scans/top",
        "/world/scans/left",
        "/world/scans/right",
        "/world/segments",
        "/world/planes/0",
        "/world/planes/1/outline",
        "/world/planes/3/outline",
        "/world/trajectory",
        "/world/body",
        "/world/cloud",
    ):
        assert entity in printed, entity
    assert "/world/planes/2" not in printed
    assert "Transform3D:quaternion" in printed and "Points3D:positions" in printed


def test_a_bad_trajectory_is_one_line_and_leaves_no_file(tmp_path: Path) -> None:
    t, T = _walk()
    with pytest.raises(ValueError, match=r"map2\.rrd"):
        write_map_rrd(tmp_path / "map2.rrd", times=t, T_world_body=T[:3])
    assert not (tmp_path / "map2.rrd").exists()


def _view(argv: list[str]) -> int:
    import argparse

    from backpack_slam.commands import view as cmd

    parser = argparse.ArgumentParser()
    cmd.add_parser(parser.add_subparsers())
    return cmd.run(parser.parse_args(argv))


def test_view_command_without_display(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from backpack_slam.commands.view import ViewError, has_display

    t, T = _walk()
    write_map_rrd(tmp_path / "map.rrd", times=t, T_world_body=T)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform.startswith("linux"):
        assert not has_display()
        assert _view(["view", str(tmp_path)]) == 0
        out = capsys.readouterr().out
        assert "no display" in out and str(tmp_path / "map.rrd") in out and "rerun" in out
    assert has_display({"DISPLAY": ":0"})
    assert _view(["view", str(tmp_path / "map.rrd"), "--print"]) == 0
    assert capsys.readouterr().out.strip().endswith("map.rrd")
    with pytest.raises(ViewError, match=r"empty[/\\]map\.rrd"):
        (tmp_path / "empty").mkdir()
        _view(["view", str(tmp_path / "empty")])


class _Columns:
    """A stand-in recording that keeps what send_columns gets, as arrow arrays per entity."""

    def __init__(self) -> None:
        self.sent: dict[str, list[object]] = {}

    def send_columns(self, entity: str, indexes: list[rr.TimeColumn], columns: list[object]) -> None:
        self.sent[entity] = [c.as_arrow_array() for c in (*indexes, *columns)]  # type: ignore[attr-defined]


def test_scans_in_time_order_or_not_log_the_same_columns() -> None:
    """The view sorts a scanner's points by time only when they are not in order already."""
    t, _ = _walk()
    c = _cloud(t)
    rng = np.random.default_rng(1)
    shuffled = rng.permutation(len(c))
    mixed = CloudRecord(c.points_world[shuffled], c.scanner[shuffled], c.time[shuffled], c.plane_id[shuffled])
    logged = []
    opt = MapOptions(max_scan_points=1000)
    for cloud in (c, mixed):
        rec = _Columns()
        _log_scans(rec, view_of_cloud(cloud, opt), ["top", "left", "right"], opt)  # type: ignore[arg-type]
        logged.append(rec.sent)
    assert logged[0].keys() == logged[1].keys() and len(logged[0]) == 3
    for entity, arrays in logged[0].items():
        assert all(a.equals(b) for a, b in zip(arrays, logged[1][entity], strict=True)), entity  # type: ignore[attr-defined]


def test_segments_as_one_array_log_what_a_list_of_strips_logs() -> None:
    """The (M, 2, 3) float32 array handed to rerun for the segments gives the arrow data of a
    list of M float64 strips."""
    rng = np.random.default_rng(2)
    ends = rng.normal(size=(50, 2, 3))
    as_list = rr.LineStrips3D.columns(strips=list(ends)).partition([20, 30])
    as_array = rr.LineStrips3D.columns(strips=ends.astype(np.float32)).partition([20, 30])
    for a, b in zip(as_list, as_array, strict=True):
        assert a.as_arrow_array().equals(b.as_arrow_array())


def test_the_view_picker_takes_each_scanners_points_whatever_their_index_type() -> None:
    """Small non-negative scanner indices go through a count per index, others (negative, huge,
    unsigned 64-bit) through a sort: the same picks either way."""
    from slam.rerun_map import CloudViewPicker

    rng = np.random.default_rng(4)
    n = 500
    base = rng.integers(0, 3, n)
    views = []
    for ids in (base.astype(np.int32), base.astype(np.uint8), base.astype(np.uint64), base.astype(np.int64) - 1,
                np.where(base == 2, 1 << 40, base).astype(np.int64)):
        c = CloudRecord(np.repeat(np.arange(n, dtype=np.float64)[:, None], 3, axis=1), ids, np.arange(n) * 0.01,
                        np.zeros(n, dtype=np.int32))
        picker = CloudViewPicker(3, 7)
        for lo in range(0, n, 128):
            picker.take(CloudRecord(c.points_world[lo:lo + 128], c.scanner[lo:lo + 128], c.time[lo:lo + 128],
                                    c.plane_id[lo:lo + 128]))
        view = picker.view()
        assert [s for s, _ in view.scans] == sorted(np.unique(ids).tolist())
        views.append([part.points_world[:, 0].tolist() for _, part in view.scans])
    assert all(v == views[0] for v in views)
