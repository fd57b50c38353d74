"""The SLAM run configuration (slam.config): shipped defaults, segmenter defaults, errors."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import BaseModel

import slam.config as slam_config
from common.config import ConfigError
from slam.config import SLAM_SEGMENTER_DEFAULTS, SlamConfig, load_slam_config, with_segmenter
from slam.params import components

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


def _config_models() -> list[type[BaseModel]]:
    """Every pydantic model defined in slam.config."""
    return [m for m in vars(slam_config).values()
            if isinstance(m, type) and issubclass(m, BaseModel) and m.__module__ == slam_config.__name__]


def _component_classes() -> list[type]:
    """Every dataclass in the component parameters that slam.params builds (with edges and an
    IMU), walked through their fields."""
    found: list[type] = []
    todo: list[Any] = [components(SlamConfig(), with_imu=True)]
    while todo:
        obj = todo.pop()
        if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
            continue
        if type(obj) not in found:
            found.append(type(obj))
        todo.extend(getattr(obj, f.name) for f in dataclasses.fields(obj))
    return found


@pytest.mark.parametrize("model", _config_models(), ids=lambda m: m.__name__)
def test_every_config_key_has_a_default(model: type[BaseModel]) -> None:
    assert [n for n, f in model.model_fields.items() if f.is_required()] == []


def test_params_builds_every_component() -> None:
    names = {c.__name__ for c in _component_classes()}
    assert {"Components", "Gates", "PlaneInitParams", "MapParams", "EdgeParams", "TrackingParams", "ImuMotionParams",
            "BackendConfig", "MotionPriorConfig", "ImuConfig", "RobustKernel"} <= names


@pytest.mark.parametrize(
    "cls",
    _component_classes(),
    ids=lambda c: c.__name__,
)
def test_component_parameters_take_no_defaults(cls: type) -> None:
    """Every parameter's one default is the configuration model's: a component's record has none."""
    with_default = [f.name for f in dataclasses.fields(cls)
                    if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING]
    assert with_default == []


def test_the_former_module_constants_are_keys_with_their_values() -> None:
    """The tuning constants that were fixed in slam.pipeline, now configuration keys."""
    c = components(SlamConfig(), with_imu=True)
    assert c.tracking.window == 6
    np.testing.assert_array_equal(c.tracking.first_prior_sigmas, [np.radians(0.2)] * 3 + [0.01] * 3)
    np.testing.assert_array_equal(c.tracking.twist_sigmas, [0.006] * 3 + [0.002] * 3)
    assert c.imu_motion is not None
    np.testing.assert_array_equal(c.imu_motion.increment_sigmas, [np.radians(0.05)] * 3 + [0.001] * 3)
    assert c.imu_motion.degenerate_ratio == float(np.sin(np.radians(3.0)) ** 2)
    fe = SlamConfig().frontend
    assert (fe.max_tilt_sigma_deg, fe.host_min_segments, fe.max_endpoint_distance) == (1.0, 50, 0.05)


def test_params_passes_every_field_by_name() -> None:
    """slam.params names every field of each record it builds (none left to a default)."""
    import ast

    import slam.params

    classes = {c.__name__: c for c in _component_classes()}
    tree = ast.parse(Path(slam.params.__file__).read_text())
    built = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in classes:
            cls = classes[node.func.id]
            given = [k.arg for k in node.keywords]
            if node.args:  # positional: in field order
                given = [f.name for f in dataclasses.fields(cls)][: len(node.args)] + given
            assert sorted(given) == sorted(f.name for f in dataclasses.fields(cls)), cls.__name__
            built.add(cls.__name__)
    assert built == set(classes)
