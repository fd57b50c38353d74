"""The command line, called in-process: ``main([...])`` with tmp_path outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from backpack_slam import cli
from backpack_slam.cli import main
from segmentation import Scanline
from slam.io.scanfile import write_npz

REAL = Path("/work/shared/data/real")
INTEL = REAL / "intel-corrected.log.gz"
BAG = REAL / "obstacle_detector_scans_demo.bag"
needs_data = pytest.mark.skipif(not REAL.is_dir(), reason="real data not available")


def _one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("backpack-slam: error: ")
    assert "Traceback" not in err
    return lines[0]


def _room_scan(path: Path) -> Path:
    """A noise-free square room seen from inside: four walls, 1081 beams."""
    angles = np.radians(-135.0) + np.radians(0.25) * np.arange(1081)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        t = np.stack([np.where(c > 0, 3.0 / c, np.inf), np.where(c < 0, -2.0 / c, np.inf),
                      np.where(s > 0, 2.5 / s, np.inf), np.where(s < 0, -4.0 / s, np.inf)])
    ranges = t.min(axis=0)
    return write_npz(path, Scanline.from_ranges(ranges, angles, 0.0, time_increment=1e-5, range_max=30.0))


def test_segment_npz_writes_plot_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scan = _room_scan(tmp_path / "room.npz")
    out_png, out_json = tmp_path / "out" / "room.png", tmp_path / "out" / "room.json"
    assert main(["segment", str(scan), "--method", "split_and_merge", "--plot", str(out_png), "--json", str(out_json)]) == 0
    text = capsys.readouterr().out
    assert "scan 0" in text and "5 segments" in text  # 4 walls, the one behind cut by the 270 deg field of view
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(out_json.read_text())
    assert data["input"]["format"] == "npz" and data["method"] == "split_and_merge"
    (rec,) = data["scans"]
    assert rec["n_beams"] == 1081 and len(rec["segmentation"]["labels"]) == 1081
    assert len(rec["segmentation"]["segments"]) == 5
    assert data["summary"]["scans"] == 1
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["room.json", "room.png"]  # no temporaries


def test_param_coercion(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scan = _room_scan(tmp_path / "room.npz")
    out_json = tmp_path / "r.json"
    args = ["segment", str(scan), "--method", "ror", "--param", "min_len=25", "--param", "sigma=0.02",
            "--param", "direction=forward", "--json", str(out_json)]
    assert main(args) == 0
    params = json.loads(out_json.read_text())["params"]
    assert params["min_len"] == 25 and isinstance(params["min_len"], int)
    assert params["sigma"] == 0.02 and params["direction"] == "forward"
    assert main(["segment", str(scan), "--param", "min_len=abc"]) == 2
    line = _one_error_line(capsys)
    assert "min_len" in line and "abc" in line
    assert main(["segment", str(scan), "--param", "novalue"]) == 2
    assert "KEY=VALUE" in _one_error_line(capsys)
    assert main(["segment", str(scan), "--param", "bogus=1"]) == 2
    line = _one_error_line(capsys)
    assert "bogus" in line and "valid:" in line and "min_len" in line


def test_unknown_method_lists_valid_ones(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scan = _room_scan(tmp_path / "room.npz")
    assert main(["segment", str(scan), "--method", "nope"]) == 2
    line = _one_error_line(capsys)
    assert "nope" in line and "ror" in line and "split_and_merge" in line


def test_list_methods(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["segment", "--list-methods"]) == 0
    out = capsys.readouterr().out
    assert any(ln.startswith("ror: ") and "sigma=0.0095" in ln for ln in out.splitlines())


def test_bad_inputs_give_one_line_naming_the_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing.log"
    assert main(["segment", str(missing)]) == 2
    assert str(missing) in _one_error_line(capsys)
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    assert main(["segment", str(junk)]) == 2
    assert "junk.bag" in _one_error_line(capsys)
    empty = tmp_path / "empty.log"
    empty.write_text("PARAM x 1 h 0\n")
    assert main(["segment", str(empty)]) == 2
    assert "empty.log" in _one_error_line(capsys)
    assert main(["segment"]) == 2
    assert "INPUT is required" in _one_error_line(capsys)
    assert main(["segment", str(empty), "--scan", "x"]) == 2
    assert "--scan" in _one_error_line(capsys)
    assert main(["frobnicate"]) == 2
    assert "frobnicate" in _one_error_line(capsys)
    assert main([]) == 2


def test_gzip_truncated_log_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not INTEL.is_file():
        pytest.skip("real data not available")
    bad = tmp_path / "cut.log.gz"
    bad.write_bytes(INTEL.read_bytes()[:20000])
    out_json = tmp_path / "cut.json"
    assert main(["segment", str(bad), "--scan", "all", "--json", str(out_json)]) == 2
    assert "cut.log.gz" in _one_error_line(capsys)
    assert not out_json.exists() and list(tmp_path.iterdir()) == [bad]  # no half-written output


@needs_data
def test_segment_real_log_scan_index_and_bag_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["segment", str(INTEL), "--scan", "300", "--method", "split_and_merge"]) == 0
    assert "scan 300" in capsys.readouterr().out
    assert main(["segment", str(INTEL), "--scan", "-1"]) == 0
    assert "scan 909" in capsys.readouterr().out
    assert main(["segment", str(INTEL), "--scan", "910"]) == 2
    assert "has 910 scan(s)" in _one_error_line(capsys)
    out_json = tmp_path / "bag.json"
    out_png = tmp_path / "bag.png"
    args = ["segment", str(BAG), "--topic", "/front_scan", "--scan", "all", "--json", str(out_json), "--plot", str(out_png)]
    assert main(args) == 0
    assert "331 scans segmented" in capsys.readouterr().out
    data = json.loads(out_json.read_text())
    assert len(data["scans"]) == 331 and {r["scanner_id"] for r in data["scans"]} == {"front_scanner"}
    assert out_png.stat().st_size > 10_000
    assert main(["segment", str(BAG), "--topic", "/nope"]) == 2
    line = _one_error_line(capsys)
    assert "obstacle_detector_scans_demo.bag topic /nope: no such topic" in line


def test_demo_writes_plots_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    log = ["--log", str(INTEL)] if INTEL.is_file() else []
    assert main(["demo", "--out", str(out), "--segmentation-only", *log]) == 0
    text = capsys.readouterr().out
    assert "figure1_segmentation.png" in text and "ror" in text
    data = json.loads((out / "segmentation_demo.json").read_text())
    assert set(data["figure1"]["results"]) == {"ror", "split_and_merge", "line_tracking"}
    assert data["figure1"]["results"]["ror"]["separates"] == {"whiteboard": True, "door": True}
    assert (out / "figure1_segmentation.png").stat().st_size > 10_000
    if INTEL.is_file():
        assert (out / "real_scan_segmentation.png").is_file() and data["real"]["n_beams"] == 180


def test_demo_runs_the_whole_chain_on_a_short_walk(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--duration", "4"]) == 0
    text = capsys.readouterr().out
    assert "ATE RMSE" in text
    for name in ("trajectory.tum", "planes.json", "cloud.ply", "cloud.laz", "map.rrd", "summary.json", "eval.json"):
        assert (out / "slam" / name).is_file(), name
    import laspy

    from slam.export import cloud_ply_layout

    assert laspy.read(out / "slam" / "cloud.laz").header.point_count == cloud_ply_layout(out / "slam" / "cloud.ply")[0]
    ate = json.loads((out / "slam" / "eval.json").read_text())["trajectory"]
    assert ate["ate_m"]["start_aligned"]["rmse"] < 0.02


def test_interrupt_and_unexpected_bugs(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    from backpack_slam.commands import segment

    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(segment, "run", interrupted)
    assert main(["segment", "x"]) == 130
    assert "interrupted" in capsys.readouterr().err

    def buggy(args: object) -> int:
        raise RuntimeError("a bug")

    monkeypatch.setattr(segment, "run", buggy)
    with pytest.raises(RuntimeError):  # real bugs keep their traceback
        main(["segment", "x"])


def test_sigterm_inside_a_constructor_stays_quiet(monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A SIGTERM that lands inside an ``__init__`` (llvmlite's ``OutputString`` while numba
    compiles) leaves an object whose ``__del__`` fails: the run still ends with the one line and
    143, and the failing ``__del__`` prints nothing ("Exception ignored" was CI's violation)."""
    import os
    import signal

    from backpack_slam.commands import segment

    class HalfBuilt:
        def __init__(self) -> None:
            os.kill(os.getpid(), signal.SIGTERM)  # the handler raises here, before _ptr is set
            self._ptr = 1

        def __del__(self) -> None:
            if self._ptr is not None:
                pass

    def compiling(args: object) -> int:
        HalfBuilt()
        return 0

    unraisable: list[object] = []
    monkeypatch.setattr(segment, "run", compiling)
    monkeypatch.setattr("sys.unraisablehook", unraisable.append)
    assert main(["segment", "x"]) == 143
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["backpack-slam: terminated"], err
    assert unraisable == []


def test_command_list_is_the_modules() -> None:
    """COMMANDS names exactly the public modules of backpack_slam/commands/, each with its parser."""
    import pkgutil

    from backpack_slam import commands

    modules = {m.name for m in pkgutil.iter_modules(commands.__path__) if not m.name.startswith("_")}
    assert {"segment", "demo"} <= set(cli.COMMANDS)
    assert set(cli.COMMANDS) == modules and len(cli.COMMANDS) == len(set(cli.COMMANDS))
    parser = cli.build_parser()
    assert parser.prog == "backpack-slam"


def test_a_handled_interrupt_clears_cpythons_unhandled_mark(capsys: pytest.CaptureFixture[str]) -> None:
    """An interrupt that escaped an extension's ``PyRun_String`` leaves CPython's mark set, and the
    interpreter would then end by SIGINT (exit status -2) instead of 130/143."""
    import ctypes
    import signal

    from backpack_slam.cli import EXIT_INTERRUPTED, _interrupted

    try:
        mark = ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt")
    except ValueError:
        pytest.skip("this interpreter has no such mark")
    mark.value = 1
    try:
        assert _interrupted(signal.SIGINT) == EXIT_INTERRUPTED
        assert mark.value == 0
    finally:
        mark.value = 0  # else this test process itself would end by SIGINT
    assert capsys.readouterr().err.strip() == "backpack-slam: interrupted"
