"""scripts/plot_final_stage.py: the figure from the session's JSON, a one-line error on bad input."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest
from script_module import load_script


def _script() -> ModuleType:
    return load_script("plot_final_stage")


def test_the_figure_is_written_from_the_json(tmp_path: Path) -> None:
    mod = _script()
    src = Path(__file__).resolve().parents[1] / "docs" / "figures" / "final_stage_s30.json"
    out = tmp_path / "fig.png"
    assert mod.main([str(src), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000 and not list(tmp_path.glob("*.tmp.png"))


def test_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mod = _script()
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"hour": {}}))
    assert mod.main([str(bad), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no 'ten_minutes' field" in err and str(bad) in err
    bad.write_text("{")
    assert mod.main([str(bad), "--out", str(tmp_path / "x.png")]) == 2
    assert "not a readable JSON file" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
