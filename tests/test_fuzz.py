"""The command line under hostile input (issue 24): a short hypothesis campaign over the generator
of ``tests/fuzz_inputs.py`` (in-process, ``backpack_slam.cli.main``), the violations the long
campaigns (``scripts/fuzz_run.py``) found kept as regression cases, and SIGTERM / SIGINT through a
subprocess."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fuzz_inputs import KINDS, Materials, build_case, build_materials, spec_strategy
from fuzz_invariant import judge, python_env, run_inprocess, run_subprocess, temporaries
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def materials(tmp_path_factory: pytest.TempPathFactory) -> Materials:
    return build_materials(tmp_path_factory.mktemp("fuzz") / "materials", duration=1.0)


def _run_case(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Any]:
    case = build_case(spec, materials, folder)
    return [run_inprocess(cmd, folder) for cmd in case.commands]


# ---- the short campaign ----------------------------------------------------------------------------
QUICK_KINDS = tuple(k for k in KINDS if k != "run_dir")  # run_dir's evaluate needs seconds per case


@settings(max_examples=8, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large])
@given(data=st.data())
def test_hostile_inputs_keep_the_invariant(data: st.DataObject, materials: Materials,
                                           tmp_path_factory: pytest.TempPathFactory) -> None:
    kind = data.draw(st.sampled_from(QUICK_KINDS))
    spec = data.draw(spec_strategy(kind))
    spec.pop("signal", None)  # signals need a subprocess (below)
    if "commands" in spec:
        spec["commands"] = [c for c in spec["commands"] if c != "calibrate"] or spec["commands"][:1]
        if spec["commands"] == ["calibrate"]:
            spec["commands"] = ["run"] if kind != "scanline" else ["segment"]
    folder = tmp_path_factory.mktemp("case")
    for r in _run_case(spec, materials, folder):
        assert r.outcome != "violation", (json.dumps(spec), r.command.argv, r.violations, r.stderr[-2000:])


# ---- regressions: each violation a campaign found ------------------------------------------------
def _bag(fmt: str, *mutations: dict[str, Any], commands: tuple[str, ...] = ("run",)) -> dict[str, Any]:
    return {"kind": "bag", "seed": 1, "fmt": fmt, "mutations": list(mutations), "commands": list(commands),
            "with_rig": True}


ALL = ["/scan_top", "/scan_left", "/scan_right"]
REGRESSIONS: list[tuple[str, dict[str, Any], list[tuple[str, str]]]] = [
    # (name, spec, [(outcome, text in the error line or "") per command])
    ("all returns invalid: no usable returns, named, nothing written",
     _bag("ros1", {"name": "ranges_invalid", "topics": ALL, "scan_fraction": 1.0, "beam_fraction": 1.0, "value": "inf"},
          commands=("run", "segment")),
     [("refused", "no usable returns on the topics /scan_top, /scan_left, /scan_right"),
      ("refused", "no scan could be segmented")]),
    ("a CARMEN log given to run: refused, saying what run takes",
     {"kind": "carmen", "seed": 1, "how": "ok", "gzip": True, "lines": 5, "robotlaser": False, "fraction": 0.0,
      "commands": ["run", "segment"]},
     [("refused", "not a ROS bag but a CARMEN log (backpack-slam segment reads it); expected a ROS1 .bag file or a "
                  "ROS2 bag folder"), ("ok", "")]),
    ("a ROS1 bag not named *.bag (rosbags read it as ROS2: traceback)",
     {"kind": "bag_bytes", "seed": 1, "fmt": "ros1", "how": "wrong_suffix", "at": 0.0, "count": 1,
      "commands": ["run", "rig"]},
     [("refused", "rename it to *.bag"), ("refused", "rename it to *.bag")]),
    ("a ROS2 bag folder named *.bag",
     {"kind": "bag_bytes", "seed": 1, "fmt": "ros2", "how": "bag_suffix_dir", "at": 0.0, "count": 1,
      "commands": ["run"]},
     [("refused", "a ROS2 bag folder whose name ends in .bag")]),
    ("a ROS2 bag with a broken metadata.yaml (AnyReaderError at construction: traceback)",
     {"kind": "bag_bytes", "seed": 1, "fmt": "ros2", "how": "metadata_garbage", "at": 0.0, "count": 1,
      "commands": ["run"]},
     [("refused", "case")]),
    ("segment of an all-invalid scanline with --json: the JSON was written before the error",
     {"kind": "scanline", "seed": 1, "fmt": "csv", "how": "all_invalid", "n": 50, "scans": 1, "method": None,
      "noise": "none", "plot": False, "commands": ["segment"]},
     [("refused", "case.csv: no scan could be segmented")]),
    ("a rig's range_sigma 1e300 (OverflowError in the reader process)",
     {"kind": "rig", "seed": 1, "how": "value", "path": ["scanners", 1, "model", "range_sigma"], "value": 1e300,
      "fmt": "ros1", "commands": ["run", "rig_check"]},
     [("refused", "range_sigma"), ("refused", "range_sigma")]),
    ("a rig with a NaN extrinsic",
     {"kind": "rig", "seed": 1, "how": "value", "path": ["scanners", 1, "T_body_scanner", "translation", 0],
      "value": float("nan"), "fmt": "ros2", "commands": ["run"]},
     [("refused", "finite number")]),
    ("a config with an infinite sigma",
     {"kind": "config", "seed": 1, "special": "inf_sigma", "path": ["frontend", "point_sigma"], "value": 0,
      "fmt": "ros1", "commands": ["run"]},
     [("refused", "frontend.point_sigma")]),
    ("header stamps of zero: the knots spanned 1.7e9 s (a 253 GB allocation; calibrate hung)",
     _bag("ros1", {"name": "stamps", "topics": [*ALL, "/imu", "/ground_truth"], "fraction": 0.841, "how": "zero",
                   "seconds": 2.0, "log_too": False}, commands=("run",)),
     [("refused", "")]),
    ("scans without beams on two rig topics: their stamp was 0",
     _bag("ros2", {"name": "zero_beams", "topics": ["/scan_top", "/scan_left"], "scan_fraction": 1.0},
          commands=("run",)),
     [("refused", "number of beams 0")]),
    ("a non-finite time_increment",
     _bag("ros1", {"name": "time_increment", "topics": ["/scan_left"], "scan_fraction": 0.3, "value": "nan"}),
     [("refused", "time_increment nan is not finite")]),
    ("segment --plot without an image suffix: matplotlib's format error after the JSON was written",
     {"kind": "cli", "seed": 1, "command": "segment", "option": "--plot", "value": "/nonexistent/dir/file",
      "fmt": "ros2"},
     [("refused", "--plot /nonexistent/dir/file: unknown image format")]),
    ("segment --param sigma=inf: the error named no option",
     {"kind": "cli", "seed": 1, "command": "segment", "option": "--param", "value": "sigma=inf", "fmt": "ros1"},
     [("refused", "--method/--param:")]),
    ("a corrupt beams.npz in the ground truth: numpy's error named no file",
     {"kind": "run_dir", "seed": 1, "how": "gt_beams_corrupt", "format": "las", "plots": False, "at": 0.5,
      "commands": ["evaluate"]},
     [("refused", "beams.npz: not a readable .npz")]),
    ("a FLASER line with no beams: the error named no file",
     {"kind": "carmen", "seed": 1, "how": "count_zero", "gzip": True, "lines": 3, "robotlaser": False,
      "fraction": 0.3, "commands": ["segment"]},
     [("refused", "case.log.gz: line 3: a FLASER scan needs at least 2 beams, got 0")]),
    ("a binary rig file: UnicodeDecodeError named no file",
     {"kind": "rig", "seed": 1, "how": "binary", "path": ["name"], "value": 0, "fmt": "ros1",
      "commands": ["run", "rig_check"]},
     [("refused", "case_rig.yaml: not a text file"), ("refused", "case_rig.yaml: not a text file")]),
    ("two scanners on one topic: calibrate's IndexError",
     {"kind": "rig", "seed": 1, "how": "duplicate_topic", "path": ["name"], "value": 0, "fmt": "ros1",
      "commands": ["calibrate"]},
     [("refused", "scanner topics must be unique")]),
    ("an .npz scanline with a NaN angle: Scanline's error named no file",
     {"kind": "scanline", "seed": 1, "fmt": "npz", "how": "angles_nan", "n": 50, "scans": 1, "method": None,
      "noise": "none", "plot": False, "commands": ["segment"]},
     [("refused", "case.npz: Scanline: a beam marked valid has a NaN")]),
    ("calibrate --coarse 1e999: the estimator's error named no option",
     {"kind": "cli", "seed": 1, "command": "calibrate", "option": "--coarse", "value": "1e999", "fmt": "ros1"},
     [("refused", "--coarse inf 5: must be finite and >= 0")]),
    ("run --voxel inf: a cloud thinned to nothing, exit 0",
     {"kind": "cli", "seed": 1, "command": "run", "option": "--voxel", "value": "inf", "fmt": "ros1"},
     [("refused", "--voxel inf: must be finite and > 0")]),
    ("a trajectory at 1e300 m: evaluate went on with overflows",
     {"kind": "run_dir", "seed": 1, "how": "traj_far", "format": "las", "plots": False, "at": 0.5,
      "commands": ["evaluate"]},
     [("refused", "trajectory.tum: positions beyond")]),
    ("an .npz scanline of complex numbers: numpy's ComplexWarning on stderr, the imaginary part dropped",
     {"kind": "scanline", "seed": 835967584, "fmt": "npz", "how": "complex", "n": 3, "scans": 3,
      "method": "split_and_merge", "noise": "auto", "plot": False, "commands": ["segment"]},
     [("refused", "case.npz: key 'ranges' is complex")]),
    ("a trajectory of one pose: evaluate's and export's errors named no file",
     {"kind": "run_dir", "seed": 1769711564, "how": "traj_one", "format": "e57", "plots": False, "at": 0.7741,
      "commands": ["evaluate", "export"]},
     [("refused", "trajectory.tum against the ground truth"),
      ("refused", "trajectory.tum: 1 pose(s); E57's scan poses are interpolated between at least 2")]),
    ("run --out '': PosixPath('.') has an empty name, naming no option",
     {"kind": "cli", "seed": 1, "command": "run", "option": "--out", "value": "", "fmt": "ros1"},
     [("refused", "argument --out: '' names no file or folder to write")]),
    ("a NaN quaternion in /tf_static: scipy's 'Found zero norm quaternions' named no bag",
     {"kind": "bag", "seed": 1992354119, "fmt": "ros1", "with_rig": True, "commands": ["run", "segment"],
      "mutations": [{"name": "tf_static", "index": 1, "amount": 0.44, "how": "nan_quat"},
                    {"name": "duplicates", "topics": ["/tf_static"], "fraction": 1.0}]},
     [("refused", "case.bag topic /tf_static: transform"), ("ok", "")]),
    ("a time_increment of 1 s (beams spread over 270 s): the IMU's gap error named no bag",
     _bag("ros1", {"name": "time_increment", "topics": ["/scan_left"], "scan_fraction": 1.0, "value": "huge"},
          commands=("run", "segment")),
     [("refused", "time_increment 1 s makes the 271 beams span 270 s"),
      ("refused", "time_increment 1 s makes the 271 beams span 270 s")]),
    ("export of a run whose trajectory is empty: LAZ needs no trajectory (the judge took it for no data)",
     {"kind": "run_dir", "seed": 1905888306, "how": "traj_empty", "format": "laz", "plots": False, "at": 0.9633,
      "commands": ["evaluate", "export"]},
     [("refused", "trajectory.tum"), ("ok", "")]),
    ("calibrate over scans without beams: IndexError in the estimator (no knots)",
     _bag("ros2", {"name": "zero_beams", "topics": ALL, "scan_fraction": 1.0}, commands=("run", "calibrate")),
     [("refused", "number of beams 0"), ("refused", "case with rig")]),
    ("export to E57 of a trajectory out of order: 'knot_times: must be strictly increasing' named no file",
     {"kind": "run_dir", "seed": 1049486448, "how": "traj_unsorted", "format": "e57", "plots": False, "at": 0.1867,
      "commands": ["export"]},
     [("refused", "trajectory.tum: times must be strictly increasing")]),
    ("run --config '': '.: cannot read (Is a directory)' named no option",
     {"kind": "cli", "seed": 1742967888, "command": "run", "option": "--config", "value": "", "fmt": "ros1"},
     [("refused", "argument --config: '' names no file")]),
    ("export --out .: the same",
     {"kind": "cli", "seed": 1, "command": "export", "option": "--out", "value": ".", "fmt": "ros2"},
     [("refused", "argument --out: '.' names no file or folder to write")]),
]


@pytest.mark.parametrize(("name", "spec", "expected"), REGRESSIONS, ids=[r[0][:60] for r in REGRESSIONS])
def test_regression(name: str, spec: dict[str, Any], expected: list[tuple[str, str]], materials: Materials,
                    tmp_path: Path) -> None:
    results = _run_case(spec, materials, tmp_path)
    assert len(results) == len(expected)
    for r, (outcome, text) in zip(results, expected, strict=True):
        assert r.outcome == outcome, (name, r.command.argv, r.violations, r.stderr[-1500:])
        if text:
            assert text in r.stderr, (name, r.stderr[-1500:])


def test_run_without_segments_on_one_scanner_says_so(materials: Materials, tmp_path: Path) -> None:
    """A rig topic without a single usable return: the run goes on, degraded, and names it."""
    spec = _bag("ros1", {"name": "ranges_invalid", "topics": ["/scan_right"], "scan_fraction": 1.0,
                         "beam_fraction": 1.0, "value": "nan"})
    (r,) = _run_case(spec, materials, tmp_path)
    assert r.outcome in ("ok", "failed"), r.violations
    summary = json.loads((tmp_path / "out" / "run" / "summary.json").read_text())
    codes = [p["code"] for p in summary["health"]["problems"]]
    assert "silent_scanner_right" in codes and summary["health"]["verdict"] != "ok"
    assert "scanner 'right' gave no line segment" in r.stderr


def test_health_fails_non_finite_poses() -> None:
    from slam.health import HealthSection, assess

    T = np.tile(np.eye(4), (5, 1, 1))
    T[3, 0, 3] = np.nan
    h = assess(np.arange(5) * 0.05, T, np.zeros(3), np.zeros(3, dtype=np.int64), {0: np.array([1.0, 0, 0])},
               {"segments": 3, "segments_associated": 3}, None, False, HealthSection())
    assert h.verdict == "failed" and h.problems[0].code == "non_finite"


def test_simulated_ros2_bag_names_its_storage_file_after_itself(materials: Materials) -> None:
    """The storage file of a simulated ROS2 bag kept the temporary name it was written under."""
    names = sorted(p.name for p in materials.bags["ros2"].iterdir())
    assert names == ["base2.db3", "metadata.yaml"]


# ---- signals: a subprocess, as a user's shell sends them ----------------------------------------------
def _signalled_run(materials: Materials, folder: Path, sig: signal.Signals, group: bool) -> tuple[int, str, Path]:
    """``run`` on the materials' bag, signalled once it is writing its outputs (its temporary
    folder exists; polled, no fixed sleep) or after 90 s without it (a loaded machine)."""
    out = folder / "run"
    proc = subprocess.Popen([sys.executable, "-m", "backpack_slam.cli", "run", str(materials.bags["ros1"]), "--rig",
                             str(materials.rig), "--out", str(out), "--quiet"], cwd=folder, env=python_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 90 and not any(folder.glob(".run.tmp-*")):
        time.sleep(0.02)
    if group:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err, out


@pytest.mark.parametrize(("sig", "group", "code"), [(signal.SIGTERM, False, 143), (signal.SIGINT, True, 130)])
def test_a_signal_leaves_no_half_written_output(materials: Materials, tmp_path: Path, sig: signal.Signals, group: bool,
                                                code: int) -> None:
    rc, err, out = _signalled_run(materials, tmp_path, sig, group)
    assert "Traceback" not in err, err
    if rc == 0:  # finished before the signal: complete
        assert (out / "summary.json").is_file()
    else:
        assert rc == code, err
        assert err.strip().splitlines()[-1] == ("backpack-slam: terminated" if code == 143 else "backpack-slam: interrupted")
        # absent, or complete when the signal landed between the folder's commit and the exit
        assert not out.exists() or (out / "summary.json").is_file()
    assert temporaries(tmp_path) == []
    deadline = time.monotonic() + 10
    left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
    while left and time.monotonic() < deadline:  # the helper processes stop with it
        time.sleep(0.2)
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
    assert left == []


def test_campaign_runner_judges_a_signal_case(materials: Materials, tmp_path: Path) -> None:
    """The long campaign's subprocess runner: a SIGTERM case is ``interrupted`` (or ``ok``) and
    leaves no process behind."""
    spec = _bag("ros1", commands=("run",))
    spec["signal"] = ["TERM", 3.0, False]
    case = build_case(spec, materials, tmp_path)
    (r,) = [run_subprocess(cmd, tmp_path) for cmd in case.commands]
    assert r.outcome in ("interrupted", "ok"), (r.violations, r.stderr[-1500:])


def test_fork_runner_judges_a_forked_command(materials: Materials, tmp_path: Path) -> None:
    """The long campaign's default runner: the command forked from this process, its stderr, exit
    code and outputs judged as a subprocess's."""
    spec = {"kind": "cli", "seed": 1, "command": "run", "option": "--voxel", "value": "inf", "fmt": "ros1"}
    case = build_case(spec, materials, tmp_path)
    (r,) = [run_subprocess(cmd, tmp_path, fork=True) for cmd in case.commands]
    assert (r.outcome, r.rc) == ("refused", 2), (r.violations, r.stderr)
    assert r.stderr.strip() == "backpack-slam: error: --voxel inf: must be finite and > 0"


def test_judge_flags_what_breaks_the_invariant(tmp_path: Path) -> None:
    from fuzz_inputs import Command, Output

    out = tmp_path / "x.json"
    cmd = Command("segment", ["segment"], [Output(out, check="json")], ["case.bag"], no_usable_data=True)
    assert judge(cmd, 1, "Traceback (most recent call last):\nValueError: x\n", tmp_path, False)[0] == "violation"
    assert judge(cmd, 2, "backpack-slam: error: case.bag: bad\n", tmp_path, False) == ("refused", [])
    assert "names none" in judge(cmd, 2, "backpack-slam: error: other: bad\n", tmp_path, False)[1][0]
    out.write_text("{}")
    assert judge(cmd, 0, "", tmp_path, False)[1] == ["exit 0 over an input with no usable data"]
    (tmp_path / ".x.tmp-123.json").write_text("")
    assert any("temporary" in v for v in judge(cmd, 2, "backpack-slam: error: case.bag\n", tmp_path, False)[1])


def test_calibrate_names_the_recording_in_the_estimators_errors(materials: Materials, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A singular calibration graph (a 400 Hz knot rate) was reported without naming the recording."""
    import calibration.calibrate
    from backpack_slam.cli import main

    def singular(*args: Any, **kwargs: Any) -> None:
        raise ValueError("calibration graph is singular or failed to solve (Indeterminate linear system)")

    monkeypatch.setattr(calibration.calibrate, "calibrate_bag", singular)
    bag = materials.bags["ros1"]
    assert main(["calibrate", str(bag), "--rig", str(materials.rig), "--out", str(tmp_path / "c.yaml"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"backpack-slam: error: calibration from {bag} with rig {materials.rig}: calibration graph is "
                   "singular or failed to solve (Indeterminate linear system)")
    assert not (tmp_path / "c.yaml").exists()
