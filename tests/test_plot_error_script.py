"""scripts/plot_error_over_time.py: start-aligned errors and the plot, clear errors on bad input."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from script_module import load_script

from slam.export import write_trajectory_tum


def _script() -> ModuleType:
    return load_script("plot_error_over_time")


def _walk(t: np.ndarray, drift_x: float = 0.0) -> np.ndarray:
    T = np.tile(np.eye(4), (t.size, 1, 1))
    T[:, 0, 3] = 1.2 * t + drift_x * t
    return T


def test_errors_are_start_aligned_and_the_plot_is_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mod = _script()
    t = np.linspace(100.0, 110.0, 201)
    (tmp_path / "gt").mkdir()
    (tmp_path / "run").mkdir()
    write_trajectory_tum(tmp_path / "gt" / "trajectory.tum", t, _walk(t))
    shifted = _walk(t, drift_x=0.01)
    shifted[:, :3, 3] += [5.0, -2.0, 0.3]  # another origin: removed by the alignment at the first pose
    write_trajectory_tum(tmp_path / "run" / "trajectory.tum", t, shifted)
    ts, E = mod.start_aligned_errors(tmp_path / "gt", tmp_path / "run")
    assert ts[0] == 0.0 and abs(ts[-1] - 10.0) < 1e-9
    np.testing.assert_allclose(E[:, 0], 0.01 * (t - t[0]), atol=1e-9)
    np.testing.assert_allclose(E[:, 1:], 0.0, atol=1e-9)
    out = tmp_path / "err.png"
    assert mod.main([str(tmp_path / "gt"), str(out), f"a={tmp_path / 'run'}", "--log"]) == 0
    assert out.stat().st_size > 1000
    assert mod.main([str(tmp_path / "gt"), str(out), f"b={tmp_path / 'missing'}"]) == 2
    assert mod.main([str(tmp_path / "gt"), str(out), "no-label"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "run 'b'" in err[0] and "LABEL=RUN_DIR" in err[1]
