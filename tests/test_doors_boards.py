"""Doors and boards stay doors and boards (issue 26): a short walk in the small room past its door
(1.5 cm recessed) with its whiteboard (2 cm proud) across the room. The long walks are in
scripts/bench_slam.py (``--world small_room``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.rig import resolve_rig
from simulation.run import SimulationResult, simulate
from slam.config import SlamConfig
from slam.evaluate import EvalResult, evaluate
from slam.export import read_planes_json
from slam.run import run_slam


def _fast(cfg: SlamConfig) -> SlamConfig:
    return cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": False})})


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    folder = tmp_path_factory.mktemp("small_room")
    return simulate("small_room", "itc_backpack", duration=9.0, seed=3, out=folder / "small_room.bag", progress=False)


def _run(walk: SimulationResult, folder: Path, cfg: SlamConfig) -> EvalResult:
    run_slam(walk.bag, resolve_rig("itc_backpack"), _fast(cfg), folder, progress=False)
    return evaluate(folder, walk.gt, map_alignment="se3")


def test_the_door_and_the_board_keep_their_segments_and_faces(walk: SimulationResult, tmp_path: Path) -> None:
    """With the parallel choice the door's and the board's segments stay on their planes and off
    the walls'; the nearest candidate under the pose-widened
    gates (parallel_choice off) mixes them up."""
    res = _run(walk, tmp_path / "choice", SlamConfig())
    a = res.association
    assert a is not None and res.planes is not None
    assert a.fraction_correct_surface_of_associated > 0.99
    # (the door's and the board's first segments go to their walls, before their planes are made)
    assert a.n_child_associated > 100 and a.confusion_fraction < 0.08
    # the door's plane is found (its outline: the next test)
    assert [m for m in res.planes.matches if m.kind == "door"]
    old = _run(walk, tmp_path / "nearest",
               SlamConfig.model_validate({"frontend": {"parallel_choice": False}})).association
    assert old is not None
    assert old.confusion_fraction > 2.0 * a.confusion_fraction


def test_door_and_board_outlines_from_the_final_map_stay_on_their_faces(walk: SimulationResult,
                                                                       tmp_path: Path) -> None:
    """planes.json's outlines come from the final map when the cloud pass runs (here for the
    recording alone): the door's and the board's within 10 cm of their faces, where the front
    end's outlines (the extent grown during the walk) run along their walls."""
    cfg = SlamConfig()
    cfg = cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": True})})
    run_slam(walk.bag, resolve_rig("itc_backpack"), cfg, tmp_path / "final", progress=False)
    final = evaluate(tmp_path / "final", walk.gt, map_alignment="se3")
    assert {p.outline for p in read_planes_json(tmp_path / "final" / "planes.json")} == {"final_map"}
    run_slam(walk.bag, resolve_rig("itc_backpack"), _fast(SlamConfig()), tmp_path / "front", progress=False)
    front = evaluate(tmp_path / "front", walk.gt, map_alignment="se3")
    assert {p.outline for p in read_planes_json(tmp_path / "front" / "planes.json")} == {"front_end"}
    assert final.planes is not None and front.planes is not None

    def errors(res: EvalResult) -> dict[str, float]:
        assert res.planes is not None
        return {m.kind: max(m.extent_error_m, m.extent_excess_m) for m in res.planes.matches
                if m.extent_error_m == m.extent_error_m}

    ours, theirs = errors(final), errors(front)
    # the door's outline on its face, the front end's 2.4 m along its wall; the board's, seen on
    # this 9 s walk by few slanted lines near one edge, 10 cm short of it
    assert set(ours) == {"door", "board"} and ours["door"] < 0.10 and ours["board"] < 0.15
    assert theirs["door"] > 1.0


@pytest.fixture(scope="module")
def thin_walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    folder = tmp_path_factory.mktemp("small_room_thin")
    return simulate("small_room_thin", "itc_backpack", duration=40.0, seed=1, out=folder / "thin.bag", progress=False)


def test_a_standing_start_that_sets_off_keeps_its_place_along_the_walk(thin_walk: SimulationResult,
                                                                       tmp_path: Path) -> None:
    """The small room with 1 cm steps, no IMU (issue 26, session 20): the walker stands for half a
    second and sets off along the long wall. Its end walls, seen by the level scanner alone, need
    several scans from one pose to become planes; without them nothing held the walking direction
    and the estimate slid 0.57 m in the first 2 s (a health warning only). The window's odometry
    (``frontend.initial_motion_rest_odometry``) keeps the start in place."""
    on = {"frontend": {"initial_motion_rest_odometry": True}}
    res = _run(thin_walk, tmp_path / "on", SlamConfig.model_validate(on))
    assert res.trajectory.ate["start_aligned"].rmse < 0.005
    off = {"frontend": {"initial_motion_rest_odometry": False}}
    res_off = _run(thin_walk, tmp_path / "off", SlamConfig.model_validate(off))
    assert res_off.trajectory.ate["start_aligned"].rmse > 0.1


@pytest.fixture(scope="module")
def long_wall(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    folder = tmp_path_factory.mktemp("long_wall")
    return simulate("long_wall_boards", "itc_backpack", duration=12.0, seed=1, out=folder / "long_wall.bag",
                    progress=False)


def test_doors_and_boards_not_mapped_yet_do_not_go_to_their_wall(long_wall: SimulationResult, tmp_path: Path) -> None:
    """The first seconds along a wall with doors and boards 1-2 cm off it (issue 26): before their
    planes exist, the local step test sends their segments, a step off the wall's own segments of
    the same scan, to the pool instead of the wall, where they make their planes (12 s: 6 %
    confusions against 50 % without it)."""
    res = _run(long_wall, tmp_path / "local", SlamConfig.model_validate({"frontend": {"local_step_reach": 0.5}}))
    a = res.association
    assert a is not None and a.n_child_associated > 500
    assert a.confusion_fraction < 0.12
    assert a.fraction_correct_surface_of_associated > 0.98
    off = _run(long_wall, tmp_path / "off", SlamConfig())
    assert off.association is not None
    assert off.association.confusion_fraction > 3.0 * a.confusion_fraction
    assert res.trajectory.ate["start_aligned"].rmse < 0.003
