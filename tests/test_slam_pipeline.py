"""End-to-end tests of the SLAM pipeline on simulated bags (slam.pipeline, slam.run).

Worlds are small YAML files written into a temporary folder; bags are simulated once per
module and shared. Long walks (the demo, office) live in scripts/bench_slam.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import segmentation
from common.rig import resolve_rig
from simulation.run import SimulationResult, simulate
from simulation.scanner import ScannerNoiseConfig
from slam.config import SlamConfig
from slam.evaluate import evaluate
from slam.export import read_planes_json, read_segments_npz
from slam.pipeline import SlamRunner
from slam.run import run_slam

# an 8 x 6 m box room (2.8 m ceiling) with a short walk across it
BOX_WORLD = """
name: box
floor_z: 0.0
ceiling_z: 2.8
spaces:
  - {name: room, rect: [0.0, 0.0, 8.0, 6.0]}
walk:
  speed: 1.2
  waypoints:
    - [1.5, 1.5]
    - [6.0, 2.0]
    - [6.0, 4.5]
"""

# a ring corridor (1.8 m wide) round a solid 3 x 2 m block: a closed walk on which the walls
# of the start corridor leave the view and come back
RING_WORLD = """
name: ring
floor_z: 0.0
ceiling_z: 2.6
spaces:
  - {name: south, rect: [0.0, 0.0, 6.6, 1.8]}
  - {name: north, rect: [0.0, 3.8, 6.6, 5.6]}
  - {name: west, rect: [0.0, 1.8, 1.8, 3.8]}
  - {name: east, rect: [4.8, 1.8, 6.6, 3.8]}
walk:
  speed: 1.2
  closed: true
  waypoints:
    - [0.9, 0.9]
    - [5.7, 0.9]
    - [5.7, 4.7]
    - [0.9, 4.7]
"""

# a straight corridor whose end walls are out of reach (behind the top scanner's blind sector and
# beyond its 30 m range): the planes leave motion along it unobserved, the IMU observes it
LONG_CORRIDOR_WORLD = """
name: long_corridor
floor_z: 0.0
ceiling_z: 2.6
spaces:
  - {name: corridor, rect: [0.0, 0.0, 100.0, 2.0]}
walk:
  speed: 1.2
  waypoints:
    - [10.0, 1.0]
    - [60.0, 1.0]
"""

# the same kind of corridor with closed doors set 1-2 cm into both walls: their edges observe the
# walking direction
DOOR_CORRIDOR_WORLD = LONG_CORRIDOR_WORLD.replace("name: long_corridor", "name: door_corridor").replace(
    "walk:",
    "doors:\n"
    + "".join(
        f"  - {{space: corridor, side: {side}, at: {at:.2f}, recess: {0.01 + 0.005 * (k % 3):.3f}}}\n"
        for k, (side, at) in enumerate((("south" if k % 2 else "north"), 11.0 + 1.6 * k) for k in range(8))
    )
    + "walk:",
)

NO_NOISE = ScannerNoiseConfig(enabled=False)


def _fast(cfg: SlamConfig | None = None) -> SlamConfig:
    """Config without cloud and rerun outputs (the run-command test writes them)."""
    cfg = cfg or SlamConfig()
    return cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": False})})


def _simulate(folder: Path, name: str, text: str, duration: float, noise: ScannerNoiseConfig | None,
              imu: bool = False) -> SimulationResult:
    world = folder / f"{name}.yaml"
    world.write_text(text)
    return simulate(world, "itc_backpack", duration=duration, seed=3, out=folder / f"{name}.bag", noise=noise,
                    imu=imu, progress=False)


@pytest.fixture(scope="module")
def rig() -> Any:
    return resolve_rig("itc_backpack")


@pytest.fixture(scope="module")
def box_clean(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _simulate(tmp_path_factory.mktemp("box_clean"), "box", BOX_WORLD, 4.0, NO_NOISE)


@pytest.fixture(scope="module")
def box_noisy(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    """2.5 s of walking with the default scanner noise: shared by every segmenter."""
    return _simulate(tmp_path_factory.mktemp("box_noisy"), "box", BOX_WORLD, 2.5, None)


@pytest.fixture(scope="module")
def ring(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _simulate(tmp_path_factory.mktemp("ring"), "ring", RING_WORLD, 14.5, None)


def test_noise_free_box_walk_recovers_the_trajectory(box_clean: SimulationResult, rig: Any, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_slam(box_clean.bag, rig, _fast(), run_dir, progress=False)
    res = evaluate(run_dir, box_clean.gt)
    ate = res.trajectory.ate["start_aligned"]
    assert ate.rmse < 1e-3, f"ATE {1000 * ate.rmse:.2f} mm"
    assert ate.max < 2e-3
    assert res.planes is not None
    assert res.planes.angle.max < 0.05  # deg


def test_the_result_is_complete(box_noisy: SimulationResult, rig: Any) -> None:
    """The result carries every plane's marginal covariance and the run statistics as one record
    whose dictionary is what summary.json reports."""
    from slam.io.bag import read_scans

    cfg = _fast()
    cfg = cfg.model_copy(update={"health": cfg.health.model_copy(update={"departure_window": 1.0})})  # a short walk
    runner = SlamRunner(rig, cfg)
    for line in read_scans(box_noisy.bag, rig=rig):
        runner.add_scan(line)
    runner.finish()
    res = runner.result()
    assert len(res.plane_ids) >= 3
    assert sorted(res.plane_covariances) == sorted(map(int, res.plane_ids))
    for pid, cov in res.plane_covariances.items():
        assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0.0), pid
        # all from one elimination with the planes last, as gtsam.Marginals gives them one by one
        np.testing.assert_allclose(cov, runner.backend.plane_covariance(pid), rtol=1e-7, atol=1e-16)
    d = res.stats.to_dict()
    assert d["knots"] == len(res.knot_times) and d["planes"] == len(res.plane_ids) and d["scans"] > 0
    assert d["batch"]["iterations"] >= 1 and res.stats["batch"] == d["batch"]
    # the batch's change of the walk's shape against the online estimate, measured (and small here)
    assert 0.0 < d["batch"]["departure"] < cfg.health.warn_batch_departure
    assert 0.0 <= d["batch"]["departure_time"] <= res.knot_times[-1] - res.knot_times[0] - cfg.health.departure_window
    assert {"segments", "associated", "planes_created", "observation_blocks", "updates", "edge_observations",
            "trimmed_points", "pool_dropped", "singular_systems", "residuals", "imu_used"} <= set(d)
    assert res.T_world_body_online is not None and res.T_world_body_online.shape == res.T_world_body.shape
    assert runner.result(batch=False, covariances=False).plane_covariances == {}
    assert runner.result(batch=False, covariances=False).T_world_body_online is None
    assert "batch" not in runner.result(batch=False, covariances=False).stats.to_dict()


@pytest.mark.parametrize("method", segmentation.available())
def test_every_segmenter_runs_end_to_end(method: str, box_noisy: SimulationResult, rig: Any, tmp_path: Path) -> None:
    cfg = _fast(SlamConfig.model_validate({"segmenter": {"method": method}}))
    summary = run_slam(box_noisy.bag, rig, cfg, tmp_path / "run", progress=False)
    c = summary["counts"]
    assert c["knots"] >= 2.5 * cfg.trajectory.knot_rate - 1
    assert c["planes"] >= 3, c
    assert c["segments_associated"] > 0.3 * c["segments"], c
    res = evaluate(tmp_path / "run", box_noisy.gt)
    assert np.isfinite(res.trajectory.ate["start_aligned"].rmse)
    assert res.trajectory.ate["start_aligned"].rmse < 0.05, method  # a sane trajectory, not a benchmark


def test_loop_closes_onto_the_start_planes(ring: SimulationResult, rig: Any, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    summary = run_slam(ring.bag, rig, _fast(), run_dir, progress=False)
    segs = read_segments_npz(run_dir / "segments.npz")
    t0 = float(segs.stamp.min())
    # the planes that segments of the first 1.5 s went to (all walls of the start corridor)
    early = set(np.unique(segs.plane_id[(segs.stamp < t0 + 1.5) & (segs.plane_id >= 0)]).tolist())
    assert early
    late = (segs.stamp > float(segs.stamp.max()) - 1.0) & (segs.plane_id >= 0)
    assert late.sum() > 0
    on_early = np.isin(segs.plane_id[late], list(early))
    assert on_early.mean() > 0.8, f"{on_early.mean():.2f} of the last second's segments on start planes"
    # nothing between them: some planes of the start are not seen half way round
    mid = (np.abs(segs.stamp - (t0 + 7.0)) < 1.0) & (segs.plane_id >= 0)
    walls_only = {int(p["id"]) for p in _planes(run_dir) if p["kind"] == "wall"}
    assert (early & walls_only) - set(segs.plane_id[mid].tolist()), "no start wall leaves the view: not a loop"
    # duplicates: merged, or never created (each true plane has one estimated plane)
    res = evaluate(run_dir, ring.gt)
    assert res.association is not None and res.planes is not None
    assert res.association.fraction_correct_of_associated > 0.97
    true_of = [m.true_id for m in res.planes.matches]
    dup = {t for t in true_of if true_of.count(t) > 1}
    assert summary["counts"]["planes_merged"] > 0 or not dup, f"duplicated true planes {dup}"
    assert res.trajectory.ate["start_aligned"].rmse < 0.01


@pytest.mark.parametrize(("fraction", "solves"), [(0.01, 3), (0.0, 4), (0.6, 2)])
def test_a_trim_round_that_detaches_too_little_is_not_solved_again(box_noisy: SimulationResult, rig: Any,
                                                                    fraction: float, solves: int) -> None:
    """The final batch's solve, then trims detaching 1000, 500 and 5 points: a round detaching fewer
    than backend.final_trim_min_fraction of the first round's points ends the trims unsolved."""
    from slam.io.bag import read_scans

    cfg = _fast()
    cfg = cfg.model_copy(update={"backend": cfg.backend.model_copy(update={"final_trim_min_fraction": fraction})})
    runner = SlamRunner(rig, cfg)
    for line in read_scans(box_noisy.bag, rig=rig):
        runner.add_scan(line)
    runner.finish()
    rounds = iter([(1000, 5), (500, 3), (5, 1)])
    calls: list[str] = []
    solve = runner.backend.batch_optimize

    def trim(*args: Any) -> tuple[int, int]:
        calls.append("trim")
        return next(rounds)

    def optimize(*args: Any, **kwargs: Any) -> Any:
        calls.append("solve")
        return solve(*args, **kwargs)

    runner.backend.trim_observations = trim  # type: ignore[method-assign]
    runner.backend.batch_optimize = optimize  # type: ignore[method-assign]
    res = runner.result(covariances=False)
    assert calls.count("solve") == solves and calls[0] == "solve"
    assert calls.count("trim") == (2 if fraction == 0.6 else 3)
    assert res.stats["trimmed_points"] == (1500 if fraction == 0.6 else 1505)


@pytest.fixture(scope="module")
def corridor_imu(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _simulate(tmp_path_factory.mktemp("corridor"), "corridor", LONG_CORRIDOR_WORLD, 5.0, None, imu=True)


def _final_along_error(run_dir: Path, gt: Path) -> tuple[float, float]:
    """(error, true distance) of the distance walked along the corridor at the end of the run."""
    est = np.loadtxt(run_dir / "trajectory.tum")
    true = np.loadtxt(gt / "trajectory.tum")
    x_true = float(np.interp(est[-1, 0], true[:, 0], true[:, 1]) - true[0, 1])
    return abs(float(est[-1, 1] - est[0, 1]) - x_true), x_true


def test_the_imu_sample_model_comes_from_the_config(corridor_imu: SimulationResult) -> None:
    from slam.run import load_imu

    true = np.loadtxt(corridor_imu.gt / "trajectory.tum")
    t0, t1 = float(true[0, 0]), float(true[-1, 0])
    for model in ("held", "instantaneous"):
        cfg = SlamConfig.model_validate({"imu": {"samples": model}})
        samples = load_imu(corridor_imu.bag, cfg, t0, t1)
        assert samples is not None and samples.instantaneous == (model == "instantaneous")


def test_imu_observes_the_corridor_direction(corridor_imu: SimulationResult, rig: Any, tmp_path: Path) -> None:
    """From rest, 4 s of walking (3.6 m) along a corridor with no visible end: without the IMU the
    planes cannot tell how far the operator went (the estimate ends metres off); with the bag's
    IMU and a zero-velocity update while standing, most of the distance is recovered
    (the error left is what 1 s of standing tells the IMU about its bias)."""
    with_imu = run_slam(corridor_imu.bag, rig, _fast(), tmp_path / "imu", progress=False)
    assert with_imu["counts"]["imu_used"] == 1
    assert with_imu["counts"]["zero_velocity_updates"] >= 5  # of the first second standing (8 with the ADIS16448)
    err_imu, walked = _final_along_error(tmp_path / "imu", corridor_imu.gt)
    off = _fast(SlamConfig.model_validate({"imu": {"use": "off"}}))
    without = run_slam(corridor_imu.bag, rig, off, tmp_path / "off", progress=False)
    assert without["counts"]["imu_used"] == 0
    err_off, _ = _final_along_error(tmp_path / "off", corridor_imu.gt)
    assert walked > 3.0
    assert err_imu < 0.15 * walked, f"along-corridor error with the IMU {err_imu:.3f} m of {walked:.2f} m"
    assert err_off > 2 * err_imu, f"without the IMU {err_off:.3f} m, with {err_imu:.3f} m"
    # the run says so: without the IMU nothing holds the corridor's direction (slam.health)
    assert with_imu["health"]["verdict"] != "failed", with_imu["health"]
    assert without["health"]["verdict"] == "failed", without["health"]
    assert [p["code"] for p in without["health"]["problems"]] == ["unobserved_x"], without["health"]


def test_a_standing_rig_observes_one_knot_in_n(corridor_imu: SimulationResult, rig: Any, tmp_path: Path) -> None:
    """frontend.rest_observe_every: while the rig stands (the first second of the corridor walk),
    only every n-th knot's scans observe the map; the others are neither associated nor pooled,
    and the walk after the standstill is estimated as well as with every scan."""
    full = run_slam(corridor_imu.bag, rig, _fast(), tmp_path / "all", progress=False)
    cfg = _fast(SlamConfig.model_validate({"frontend": {"rest_observe_every": 5}}))
    thin = run_slam(corridor_imu.bag, rig, cfg, tmp_path / "thin", progress=False)
    assert full["counts"]["rest_idle_scans"] == 0
    assert thin["counts"]["rest_idle_scans"] >= 10  # of about 40 scans while standing still
    left_out = thin["counts"]["segments"] - thin["counts"]["segments_associated"]
    assert left_out > full["counts"]["segments"] - full["counts"]["segments_associated"]
    # the idle scans' segments are in segments.npz, not associated
    rows = np.load(tmp_path / "thin" / "segments.npz")
    assert (rows["plane_id"] >= 0).sum() == thin["counts"]["segments_associated"]
    err_full, walked = _final_along_error(tmp_path / "all", corridor_imu.gt)
    err_thin, _ = _final_along_error(tmp_path / "thin", corridor_imu.gt)
    assert err_thin < max(2.0 * err_full, 0.05), (err_thin, err_full, walked)


def test_the_gyro_deskew_fits_the_points_to_their_planes_better(corridor_imu: SimulationResult, rig: Any,
                                                                 tmp_path: Path) -> None:
    """The same IMU walk with and without the gyro's rotation between knots (``slam.trajectory.deskew``):
    with it the point-to-plane residuals are smaller."""
    on = run_slam(corridor_imu.bag, rig, _fast(), tmp_path / "on", progress=False)
    off_cfg = _fast(SlamConfig.model_validate({"trajectory": {"imu_deskew": False}}))
    off = run_slam(corridor_imu.bag, rig, off_cfg, tmp_path / "off", progress=False)
    assert on["config"]["trajectory"]["imu_deskew"] and not off["config"]["trajectory"]["imu_deskew"]
    r_on, r_off = on["residuals"]["rms_whitened"], off["residuals"]["rms_whitened"]
    # measured 0.363 against 0.392: the geodesic's misplacement of the walker's pitch is gone
    assert r_on < 0.97 * r_off, f"whitened residual RMS with the deskew {r_on:.3f}, without {r_off:.3f}"


@pytest.fixture(scope="module")
def door_corridor(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _simulate(tmp_path_factory.mktemp("doors"), "doors", DOOR_CORRIDOR_WORLD, 6.0, None, imu=True)


def test_door_edges_observe_the_corridor_direction(door_corridor: SimulationResult, rig: Any, tmp_path: Path) -> None:
    """Walking a corridor whose ends are out of reach: the planes leave the distance walked to the
    IMU, the doors' edges observe it (measured: 0.22 m off after 4.8 m without edges, 0.07 m with;
    most of the 0.07 m is IMU drift in the 2 s before the first edge has enough breaks)."""
    with_edges = run_slam(door_corridor.bag, rig, _fast(), tmp_path / "edges", progress=False)
    assert with_edges["counts"]["edges"] >= 4
    err, walked = _final_along_error(tmp_path / "edges", door_corridor.gt)
    run_slam(door_corridor.bag, rig, _fast(SlamConfig.model_validate({"edges": {"use": False}})), tmp_path / "off",
             progress=False)
    err_off, _ = _final_along_error(tmp_path / "off", door_corridor.gt)
    assert walked > 4.0
    assert err < 0.1, f"along-corridor error with edges {err:.3f} m of {walked:.2f} m"
    assert err_off > 2 * err, f"without edges {err_off:.3f} m, with {err:.3f} m"
    # a fit across a wall and its door, a few degrees off vertical, is no plane of this corridor
    oblique = [p for p in _planes(tmp_path / "edges") if p["kind"] == "other"]
    assert not oblique, oblique


def test_a_corridor_walk_without_an_imu_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The door corridor walked from a standstill without an IMU (4 s): the walls observe nothing
    along it and the doors' edges do not hold it (the map ends tens of centimetres off), so the
    run ends with the failure verdict and exit code 3, its outputs written and marked failed,
    and one line naming the cause (``slam.health``: a direction unobserved by the planes for
    3 s without an IMU). It used to print a normal summary and exit 0."""
    from backpack_slam.cli import main
    from slam.health import EXIT_FAILED

    sim = _simulate(tmp_path, "doors", DOOR_CORRIDOR_WORLD, 4.0, None, imu=False)
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("output:\n  cloud: false\n  rerun: false\n")
    out = tmp_path / "run"
    capsys.readouterr()
    rc = main(["run", str(sim.bag), "--rig", "itc_backpack", "--config", str(cfg), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.splitlines()
    assert rc == EXIT_FAILED, err
    lines = [ln for ln in err if "failure:" in ln]
    assert len(lines) == 1 and "motion along world x is not observed by the planes" in lines[0], err
    assert "no IMU" in lines[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["health"]["verdict"] == "failed" and summary["counts"]["imu_used"] == 0
    assert [p["code"] for p in summary["health"]["problems"]] == ["unobserved_x"]
    err_along, walked = _final_along_error(out, sim.gt)
    assert walked > 1.5 and err_along > 0.2, f"along-corridor error {err_along:.2f} m of {walked:.2f} m"


def test_linearisation_error_is_the_graph_error(door_corridor: SimulationResult, rig: Any) -> None:
    """The solver takes an accepted step's error from its linearisation (``slam.backend.solver``): on a
    whole SLAM graph (robust blocks, edge planes, ties, IMU, priors) ``0.5 ||b||^2`` of the
    linearisation equals the graph's error."""
    from slam.io.bag import read_scans
    from slam.pipeline import SlamRunner
    from slam.run import bag_time_range, load_imu

    cfg = SlamConfig.model_validate({"backend": {"pipelined": False}})  # the graph in this process
    t0, t1 = bag_time_range(door_corridor.bag)
    runner = SlamRunner(rig, cfg, load_imu(door_corridor.bag, cfg, t0, t1))
    for line in read_scans(door_corridor.bag, rig=rig):
        if line.stamp - t0 > 3.0:
            break
        runner.add_scan(line)
    runner.finish()
    be = runner.backend
    graph = be.blocks.whole_graph()
    values = be.graph.used_values(graph)
    assert be.num_knots > 40 and graph.size() > 100
    lin = graph.linearize(values)
    assert lin.error(values.zeroVectors()) == pytest.approx(graph.error(values), rel=1e-9)


def test_imu_on_without_imu_topic_is_one_line(box_noisy: SimulationResult, rig: Any, tmp_path: Path) -> None:
    cfg = _fast(SlamConfig.model_validate({"imu": {"use": "on"}}))
    with pytest.raises(ValueError, match=r"topic /imu: has no IMU messages") as e:
        run_slam(box_noisy.bag, rig, cfg, tmp_path / "run", progress=False)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "run").exists()


def test_tilt_sigma_flags_thin_strips() -> None:
    from slam.frontend.plane_init import tilt_sigma

    rng = np.random.default_rng(0)
    n = np.array([1.0, 0.0, 0.0])
    square = np.column_stack((np.full(40, 5.0), rng.uniform(-0.5, 0.5, 40), rng.uniform(0.5, 1.5, 40)))
    strip = square * [1.0, 1.0, 0.0] + [0.0, 0.0, 1.0] + rng.normal(0, 1e-3, (40, 3)) * [0, 0, 1]
    sig = np.full(40, 0.003)
    assert tilt_sigma(square, sig, n) < np.radians(0.3)
    assert tilt_sigma(strip, sig, n) > np.radians(1.0)  # a horizontal strip: tilt about y unseen
    # kept vertical by a prior, only the heading (tilt about z) must be observed: the strip does
    assert tilt_sigma(strip, sig, n, about=np.array([0.0, 0.0, 1.0])) < np.radians(0.3)


def _planes(run_dir: Path) -> list[dict[str, Any]]:
    return [{"id": p.id, "kind": p.kind} for p in read_planes_json(run_dir / "planes.json")]


def test_run_command_writes_every_output(box_noisy: SimulationResult, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from backpack_slam.cli import main

    out = tmp_path / "run"
    assert main(["run", str(box_noisy.bag), "--out", str(out), "--quiet"]) == 0
    for name in ("trajectory.tum", "trajectory_online.tum", "planes.json", "segments.npz", "cloud.ply", "map.rrd",
                 "summary.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    from slam.export import read_trajectory_tum

    t_b, T_b = read_trajectory_tum(out / "trajectory.tum")
    t_o, T_o = read_trajectory_tum(out / "trajectory_online.tum")  # the window's, same knots
    np.testing.assert_array_equal(t_b, t_o)
    assert np.abs(T_b[:, :3, 3] - T_o[:, :3, 3]).max() < 0.05
    printed = capsys.readouterr().out
    assert "outputs:" in printed and "cloud.ply" in printed and "map.rrd" in printed
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folders left


def test_run_command_lists_only_the_outputs_it_wrote(box_noisy: SimulationResult, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from backpack_slam.cli import main

    cfg = tmp_path / "nocloud.yaml"
    cfg.write_text("output:\n  cloud: false\n  rerun: false\n")
    # a survey format of a cloud that is turned off: refused before anything runs
    assert main(["run", str(box_noisy.bag), "--config", str(cfg), "--out", str(tmp_path / "x"),
                 "--cloud-format", "laz", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--cloud-format" in err and "output.cloud" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()
    out = tmp_path / "run"
    assert main(["run", str(box_noisy.bag), "--config", str(cfg), "--out", str(out), "--quiet"]) == 0
    line = next(s for s in capsys.readouterr().out.splitlines() if s.startswith("outputs:"))
    assert "trajectory.tum" in line and "summary.json" in line
    assert "cloud.ply" not in line and "map.rrd" not in line
    assert not (out / "cloud.ply").exists() and not (out / "map.rrd").exists()


def test_bag_without_the_rig_topics_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from backpack_slam.cli import main

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "other.bag"
    with Writer(bag) as w:
        Str = ts.types["std_msgs/msg/String"]
        conn = w.add_connection("/chatter", Str.__msgtype__, typestore=ts)
        w.write(conn, 1_000_000_000, ts.serialize_ros1(Str(data="hi"), Str.__msgtype__))
    out = tmp_path / "run"
    assert main(["run", str(bag), "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "other.bag" in err and "LaserScan" in err, err  # names the bag and what it lacks
    assert not out.exists()


def test_interrupted_run_leaves_no_output(box_noisy: SimulationResult, rig: Any, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from slam.pipeline import SlamRunner

    calls = {"n": 0}
    original = SlamRunner.add_prepared

    def interrupted(self: SlamRunner, scan: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 50:
            raise KeyboardInterrupt
        original(self, scan)

    monkeypatch.setattr(SlamRunner, "add_prepared", interrupted)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_slam(box_noisy.bag, rig, SlamConfig(), out, progress=False)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []

    # interrupted while writing the outputs: no half-written folder either, an old one survives
    monkeypatch.setattr(SlamRunner, "add_prepared", original)
    out.mkdir()
    (out / "keep.txt").write_text("old run")

    def broken(*args: Any, **kwargs: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr("slam.run.write_map_rrd", broken)
    with pytest.raises(KeyboardInterrupt):
        run_slam(box_noisy.bag, rig, SlamConfig(), out, progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    assert (out / "keep.txt").read_text() == "old run"


def test_an_oblique_plane_needs_more_support(rig: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A new plane 8 deg off vertical from 12 segments (a fit across a wall and its door) is
    rejected; allowed 12 segments, the same plane passes that rule."""
    from slam.frontend.plane_init import NewPlane, PooledSegment

    n = np.array([0.0, np.cos(np.radians(8.0)), np.sin(np.radians(8.0))])
    pts = np.column_stack((np.linspace(0.0, 1.0, 12), np.full(12, 2.0), np.linspace(0.5, 1.5, 12)))
    members = [PooledSegment(ref=(10_000 + i, 0), time=0.0, scan_serial=i, centroid=pts.mean(axis=0),
                             direction=np.array([1.0, 0.0, 0.0]), endpoints=pts[[0, -1]], samples=pts,
                             line=pts[[0, -1]], scan_normal=np.array([0.0, 0.0, 1.0]),
                             origin=np.zeros(3)) for i in range(12)]
    for support, rejected in ((40, 1), (12, 0)):
        cfg = SlamConfig.model_validate({"frontend": {"min_support_oblique": support}})
        runner = SlamRunner(rig, cfg)
        monkeypatch.setattr(runner.pool, "create_planes", lambda: [NewPlane(n, -2.0 * n[1], members, 0.001)])
        runner.maps.create_planes(0.0, runner.queues)
        assert runner.stats.planes_rejected_oblique == rejected
