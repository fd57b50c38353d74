"""The SLAM run configuration (slam.config): shipped defaults, segmenter defaults, errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.config import ConfigError
from slam.config import SLAM_SEGMENTER_DEFAULTS, SlamConfig, load_slam_config, with_segmenter

SHIPPED = Path(__file__).resolve().parents[1] / "configs" / "slam" / "default.yaml"


def test_shipped_default_yaml_is_the_built_in_default() -> None:
    assert load_slam_config(SHIPPED) == SlamConfig()


def test_segmenter_params_default_per_method() -> None:
    assert SlamConfig().segmenter.params == SLAM_SEGMENTER_DEFAULTS["ror"]
    assert SlamConfig.model_validate({"segmenter": {"method": "line_tracking"}}).segmenter.params == {}
    assert SlamConfig.model_validate({"segmenter": {"method": "ror", "params": {}}}).segmenter.params == {}
    cfg = SlamConfig.model_validate({"segmenter": {"method": "line_tracking"}})
    assert with_segmenter(cfg, "ror", {}).segmenter.params == SLAM_SEGMENTER_DEFAULTS["ror"]
    assert with_segmenter(SlamConfig(), None, {"percentage": 0.2}).segmenter.params == {
        **SLAM_SEGMENTER_DEFAULTS["ror"], "percentage": 0.2}
    assert with_segmenter(SlamConfig(), "iepf", {}).segmenter.params == {}


def test_a_wrong_key_names_the_key_and_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("backend:\n  solver: fast\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*backend\.solver"):
        load_slam_config(bad)


def test_a_wall_thickness_range_upside_down_names_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "walls.yaml"
    bad.write_text("frontend:\n  wall_thickness: [0.3, 0.05]\n")
    with pytest.raises(ConfigError, match=r"walls\.yaml.*wall_thickness"):
        load_slam_config(bad)
