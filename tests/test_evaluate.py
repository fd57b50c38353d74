"""The evaluation reports the known errors of outputs perturbed on purpose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.eval_plots import write_plots
from slam.evaluate import (
    EvaluationError,
    association_errors,
    evaluate,
    majority,
    match_planes_geometric,
    mesh_distances,
    normal_sigma_deg,
    plane_errors,
    segment_true_planes,
    trajectory_errors,
    write_eval_json,
)
from slam.export import (
    PlaneRecord,
    make_segment_table,
    write_cloud_ply,
    write_planes_json,
    write_segments_npz,
    write_trajectory_tum,
)
from slam.trajectory.interpolation import se3_exp


def _screw_walk(duration: float, rate: float, t0: float = 50.0, start: float | None = None):  # type: ignore[no-untyped-def]
    """T0 Exp((t - t0) xi): 1.2 m/s forward, a slow yaw, a little climb (interpolation is exact).

    Sampled at ``rate`` from ``start`` (default t0) for ``duration`` seconds.
    """
    t = (t0 if start is None else start) + np.arange(0.0, duration + 1e-9, 1.0 / rate)
    xi = np.array([0.0, 0.0, 0.05, 1.2, 0.0, 0.01])  # (rotation, translation) per second
    T0 = np.eye(4)
    T0[:3, 3] = [2.0, -1.0, 1.4]
    return t, T0 @ se3_exp((t - t0)[:, None] * xi)


def _yaw(theta: np.ndarray) -> np.ndarray:
    return Rotation.from_euler("z", np.asarray(theta, dtype=float)[:, None]).as_matrix()


def test_constant_offset_unaligned_vs_aligned() -> None:
    t_gt, T_gt = _screw_walk(30.0, 200.0)
    # estimate at 40 Hz, times not on the ground truth's grid
    t_est, T_est = _screw_walk(29.0, 40.0, start=50.0013)
    T_est[:, :3, 3] += [0.03, 0.04, 0.0]
    r = trajectory_errors(t_est, T_est, t_gt, T_gt)
    ate = r.ate
    # the ground truth is interpolated linearly in position between its 200 Hz samples: a chord of
    # the screw, < 1e-6 m off it
    assert ate["unaligned"].rmse == pytest.approx(0.05, abs=1e-6)
    assert ate["unaligned"].max == pytest.approx(0.05, abs=1e-6)
    assert ate["start_aligned"].rmse < 1e-6
    assert ate["se3_aligned"].rmse < 1e-6
    assert r.rpe_1m is not None and r.rpe_1m.max < 1e-6
    assert r.path_length == pytest.approx(1.2 * 29.0 * np.hypot(1, 0.01 / 1.2), rel=1e-3)
    np.testing.assert_allclose(r.T_align_start[:3, 3], [-0.03, -0.04, 0.0], atol=1e-6)


def test_yaw_drift_per_100m() -> None:
    # Ground truth: a straight 120 m walk along x at 1 m/s. Estimate: heading error growing by
    # k rad per metre, position integrated with that heading (a gyro-like yaw drift).
    k = np.radians(0.02)  # 2 deg per 100 m
    t_gt = np.arange(0.0, 120.0 + 1e-9, 0.005)
    T_gt = np.tile(np.eye(4), (t_gt.size, 1, 1))
    T_gt[:, 0, 3] = t_gt
    t_est = np.arange(0.0, 120.0 + 1e-9, 0.05)
    s = t_est
    T_est = np.tile(np.eye(4), (s.size, 1, 1))
    T_est[:, :3, :3] = _yaw(k * s)
    T_est[:, 0, 3] = np.sin(k * s) / k
    T_est[:, 1, 3] = (1 - np.cos(k * s)) / k
    r = trajectory_errors(t_est, T_est, t_gt, T_gt)

    def chord_error(length: float) -> float:
        return float(abs((np.exp(1j * k * length) - 1) / (1j * k) - length))

    L = 120.0
    assert r.drift_endpoint_per_100m == pytest.approx(chord_error(L) / L * 100, rel=1e-6)
    # pairs near the end may be up to 2 % short of 10 m: a small bias
    assert r.rot_drift_deg_per_100m == pytest.approx(2.0, rel=1e-3)
    assert r.rpe_10m is not None and r.rpe_rot_1m_deg is not None
    assert r.rpe_10m.mean == pytest.approx(chord_error(10.0), rel=2e-3)
    assert r.drift_rpe_per_100m == pytest.approx(chord_error(10.0) * 10, rel=2e-3)
    assert r.rpe_rot_1m_deg.mean == pytest.approx(0.02, rel=1e-3)
    assert r.ate["start_aligned"].max == pytest.approx(chord_error(L), rel=1e-6)
    # a straight ground truth leaves SE(3) alignment degenerate: the datum is used instead
    assert not r.se3_alignment_ok
    assert r.ate["se3_aligned"].rmse == r.ate["start_aligned"].rmse
    # once the path bends, SE(3) alignment works and spreads the error
    T_gt[:, 1, 3] = 0.5 * np.sin(t_gt / 20.0)
    T_est[:, 1, 3] += 0.5 * np.sin(t_est / 20.0)
    r2 = trajectory_errors(t_est, T_est, t_gt, T_gt)
    assert r2.se3_alignment_ok
    assert r2.ate["se3_aligned"].rmse < 0.5 * r2.ate["start_aligned"].rmse


def test_trajectory_outside_ground_truth_is_an_error() -> None:
    t_gt, T_gt = _screw_walk(5.0, 200.0)
    with pytest.raises(EvaluationError, match="time span"):
        trajectory_errors(t_gt + 100.0, T_gt, t_gt, T_gt)


def _box_mesh() -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(10.0, 8.0, 3.0)
    m.translate([100.0, 200.0, 0.0])  # far from the origin: float32 precision matters
    return np.asarray(m.vertices, dtype=float), np.asarray(m.triangles)


def _points_off_box(n: int, offset: float, seed: int = 0) -> np.ndarray:
    """Points ``offset`` outside the box faces, away from edges."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([100.0, 200.0, 0.0]), np.array([110.0, 208.0, 3.0])
    axis = rng.integers(0, 3, n)
    side = rng.integers(0, 2, n)
    p = rng.uniform(lo + 0.2, hi - 0.2, (n, 3))
    p[np.arange(n), axis] = np.where(side == 1, hi[axis] + offset, lo[axis] - offset)
    return p


def test_cloud_distance_to_mesh() -> None:
    v, f = _box_mesh()
    d = mesh_distances(_points_off_box(2000, 0.01), v, f)
    assert np.median(d) == pytest.approx(0.01, abs=2e-5)
    assert np.percentile(d, 95) == pytest.approx(0.01, abs=2e-5)


def _wall(x: float, y0: float, y1: float, z1: float = 3.0) -> np.ndarray:
    return np.array([[x, y0, 0], [x, y1, 0], [x, y1, z1], [x, y0, z1]], float)


def test_plane_errors_of_rotated_plane_and_board_on_wall() -> None:
    wall = PlaneRecord(10, np.array([-1.0, 0, 0]), 5.0, _wall(5.0, 0.0, 8.0), kind="wall")
    board = PlaneRecord(
        11, np.array([-1.0, 0, 0]), 4.985, _wall(4.985, 2.0, 4.0, 2.0), kind="board"
    )
    floor = PlaneRecord(
        12, np.array([0, 0, 1.0]), 0.0, np.array([[0, 0, 0], [5, 0, 0], [5, 8, 0], [0, 8, 0]], float),
        kind="floor",
    )  # fmt: skip
    true = [wall, board, floor]
    # estimated wall: rotated 0.5 deg about z through its centre (5, 6, 1.5), 2 cm too far out
    # and with the opposite normal sign
    ang = np.radians(0.5)
    n = _yaw(np.array([ang]))[0] @ np.array([1.0, 0, 0])
    c = np.array([5.02, 6.0, 1.5])
    u, w = np.array([-n[1], n[0], 0.0]), np.array([0, 0, 1.0])
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1.0]])
    est_wall = PlaneRecord(0, n, float(-n @ c), c + corners[:, :1] * u + corners[:, 1:] * w)
    # estimated board patch: on the board, 1 mm off
    est_board = PlaneRecord(1, np.array([-1.0, 0, 0]), 4.986, _wall(4.986, 2.5, 3.5, 1.5))
    # something far from every true plane
    stray = PlaneRecord(2, np.array([0, 1.0, 0]), -20.0, _wall(3.0, 19.0, 21.0))
    m = match_planes_geometric([est_wall, est_board, stray], true)
    assert m == {0: 10, 1: 11}
    pe = plane_errors([est_wall, est_board, stray], true)
    by = {x.est_id: x for x in pe.matches}
    assert by[0].angle_deg == pytest.approx(0.5, abs=1e-9)
    assert by[0].offset_m == pytest.approx(-0.02, abs=1e-9)  # true normal points to -x
    assert by[1].angle_deg == pytest.approx(0.0, abs=1e-9)
    assert by[1].offset_m == pytest.approx(-0.001, abs=1e-9)  # 1 mm behind the board
    assert pe.unmatched == [2]
    js = pe.to_json()
    assert js["n_matched"] == 2 and js["by_kind"]["wall"]["n"] == 1
    # a beam-based match overrides geometry (even a wrong one is taken as given)
    pe2 = plane_errors([est_board], true, by_beams={1: 10}, support={1: 0.75})
    assert pe2.matches[0].true_id == 10 and pe2.matches[0].matched_by == "beams"
    assert pe2.matches[0].offset_m == pytest.approx(0.014, abs=1e-9)


def test_plane_errors_against_the_runs_own_sigmas() -> None:
    wall = PlaneRecord(10, np.array([-1.0, 0, 0]), 5.0, _wall(5.0, 0.0, 8.0), kind="wall")
    tilt = np.radians(0.2)
    n = _yaw(np.array([tilt]))[0] @ np.array([-1.0, 0, 0])
    s_small, s_large = np.radians(0.01), np.radians(0.3)
    cov_small = np.diag([s_small**2, (0.5 * s_small) ** 2, 1e-6])
    cov_large = np.diag([(0.5 * s_large) ** 2, s_large**2, 1e-6])  # the larger axis counts
    precise = PlaneRecord(0, n, float(-n @ [5.0, 4.0, 1.0]), _wall(5.0, 1.0, 7.0), covariance=cov_small)
    vague = PlaneRecord(1, n, float(-n @ [5.0, 4.0, 1.0]), _wall(5.0, 1.0, 7.0), covariance=cov_large)
    bare = PlaneRecord(2, n, float(-n @ [5.0, 4.0, 1.0]), _wall(5.0, 1.0, 7.0))
    assert normal_sigma_deg(cov_large) == pytest.approx(0.3)
    assert np.isnan(normal_sigma_deg(None))
    pe = plane_errors([precise, vague, bare], [wall], by_beams={0: 10, 1: 10, 2: 10})
    by = {m.est_id: m for m in pe.matches}
    assert by[0].sigma_angle_deg == pytest.approx(0.01) and by[1].sigma_angle_deg == pytest.approx(0.3)
    # only the precise plane is "well determined", and its 0.2 deg error is 20 of its sigmas
    assert [m.est_id for m in pe.well_determined()] == [0]
    assert pe.normalized_angle.max == pytest.approx(20.0)
    assert pe.normalized_angle.n == 2  # the plane without a covariance is left out
    js = pe.to_json()
    assert js["well_determined"]["n"] == 1 and js["well_determined"]["angle_deg"]["max"] == pytest.approx(0.2)


def test_majority() -> None:
    w, c = majority(np.array([0, 0, 0, 1, 1, 3, 3]), np.array([5, 2, 5, -1, -1, 7, 4]), 4)
    np.testing.assert_array_equal(w, [5, -1, -1, 4])  # tie 7/4 -> smallest
    np.testing.assert_array_equal(c, [2, 0, 0, 1])


def _hand_made_beams() -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    # two scanners, 3 scans x 12 beams each; true plane ids per beam
    top = np.array(
        [
            [1, 1, 1, 1, 2, 2, 2, 2, -1, -1, 3, 3],
            [1, 1, 1, 2, 2, 2, 2, 2, -1, 3, 3, 3],
            [1, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3],
        ],
        dtype=np.int32,
    )
    left = np.full((3, 12), 4, dtype=np.int32)
    left[:, 6:] = 5
    stamps = {"top": np.array([0.0, 0.025, 0.05]), "left": np.array([0.01, 0.035, 0.06])}
    return {"top": top, "left": left}, stamps


def _hand_made_segments(plane_id: list[int]) -> object:
    # (scanner, scan, first, last): true planes by majority
    rows = [
        (0, 0, 0, 3),  # 1
        (0, 0, 4, 7),  # 2
        (0, 1, 2, 7),  # 2 (5 of 6)
        (0, 2, 0, 4),  # 1
        (0, 2, 9, 11),  # 3
        (1, 0, 0, 5),  # 4
        (1, 1, 6, 11),  # 5
        (1, 2, 0, 11),  # 4/5 tie -> 4
    ]
    s = np.array(rows)
    stamps = np.array([[0.0, 0.025, 0.05], [0.01, 0.035, 0.06]])[s[:, 0], s[:, 1]]
    return make_segment_table(["top", "left"], s[:, 0], s[:, 1], stamps, s[:, 2], s[:, 3], plane_id)


def test_association_fraction_on_hand_made_segments() -> None:
    ids, stamps = _hand_made_beams()
    # estimated planes: 20 gathers true-1 segments (+ one true-2: still majority 1),
    # 21 = true 2, 22 = true 4, 23 = a wrong plane holding a true-3 and a true-5 segment
    seg = _hand_made_segments([20, 21, 20, 20, 23, 22, -1, 23])
    true, purity = segment_true_planes(seg, ids, stamps)  # type: ignore[arg-type]
    np.testing.assert_array_equal(true, [1, 2, 2, 1, 3, 4, 5, 4])
    assert purity[2] == pytest.approx(5 / 6)
    assert purity[7] == pytest.approx(0.5)
    a = association_errors(seg, true, purity)  # type: ignore[arg-type]
    assert a.plane_true == {20: 1, 21: 2, 22: 4, 23: 3}  # 23: tie 3/4 -> smallest id
    # correct: rows 0, 1, 3 (20->1, 21->2, 20->1), 4 (23->3), 5 (22->4); wrong: 2, 7; none: 6
    assert a.n_associated == 7 and a.n_correct == 5
    assert a.fraction_associated == pytest.approx(7 / 8)
    assert a.fraction_correct == pytest.approx(5 / 8)
    assert a.fraction_correct_of_associated == pytest.approx(5 / 7)
    assert a.plane_support[20] == pytest.approx(2 / 3)

    # small chunks give the same answer
    true2, _ = segment_true_planes(seg, ids, stamps, chunk_beams=5)  # type: ignore[arg-type]
    np.testing.assert_array_equal(true2, true)
    bad_stamps = {"top": stamps["top"] + 1.0, "left": stamps["left"]}
    with pytest.raises(EvaluationError, match="stamps"):
        segment_true_planes(seg, ids, bad_stamps)  # type: ignore[arg-type]
    with pytest.raises(EvaluationError, match="'left'"):
        segment_true_planes(seg, {"top": ids["top"]}, None)  # type: ignore[arg-type]


def _write_gt(folder: Path, t: np.ndarray, T: np.ndarray) -> list[PlaneRecord]:
    import open3d as o3d

    folder.mkdir()
    write_trajectory_tum(folder / "trajectory.tum", t, T)
    v, f = _box_mesh()
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    o3d.io.write_triangle_mesh(folder / "mesh.ply", m)
    planes = [
        PlaneRecord(1, np.array([0, 0, 1.0]), 0.0,
                    np.array([[100, 200, 0], [110, 200, 0], [110, 208, 0], [100, 208, 0.0]]), "floor"),
        PlaneRecord(2, np.array([1.0, 0, 0]), -110.0,
                    np.array([[110, 200, 0], [110, 208, 0], [110, 208, 3], [110, 200, 3.0]]), "wall"),
    ]  # fmt: skip
    write_planes_json(folder / "planes.json", planes)
    ids, stamps = _hand_made_beams()
    np.savez(
        folder / "beams.npz",
        top_stamps=stamps["top"], top_plane_id=ids["top"], top_kind=np.zeros((3, 12), np.int8),
        left_stamps=stamps["left"], left_plane_id=ids["left"], left_kind=np.zeros((3, 12), np.int8),
    )  # fmt: skip
    return planes


def test_evaluate_end_to_end(tmp_path: Path) -> None:
    t_gt, T_gt = _screw_walk(20.0, 200.0, t0=0.0)
    T_gt[:, :3, 3] += [103.0, 203.0, 0.0]
    gt = tmp_path / "run.gt"
    true_planes = _write_gt(gt, t_gt, T_gt)
    run = tmp_path / "out"
    run.mkdir()
    t_est = t_gt[::5]
    write_trajectory_tum(run / "trajectory.tum", t_est, T_gt[::5])
    pts = _points_off_box(3000, 0.01, seed=3)
    write_cloud_ply(
        run / "cloud.ply", pts, np.zeros(3000), np.linspace(0, 20, 3000), np.zeros(3000)
    )
    # estimated planes: the true ones tilted 0.2 deg (floor) and shifted 3 mm (wall)
    n_floor = Rotation.from_euler("x", 0.2, degrees=True).apply([0, 0, 1.0])
    est = [
        PlaneRecord(1, n_floor, float(-n_floor @ [105, 204, 0]), true_planes[0].polygon, n_segments=4),
        PlaneRecord(2, np.array([1.0, 0, 0]), -110.003, true_planes[1].polygon + np.array([0.003, 0, 0])),
    ]  # fmt: skip
    write_planes_json(run / "planes.json", est)
    # segment plane ids: est 1 <- true-1 segments, est 2 <- true-2 segments
    write_segments_npz(run / "segments.npz", _hand_made_segments([1, 2, 2, 1, -1, -1, -1, -1]))  # type: ignore[arg-type]

    r = evaluate(run, gt)
    assert r.skipped == {}
    assert r.trajectory.ate["unaligned"].rmse < 1e-9
    assert r.cloud is not None and np.median(r.cloud.distances) == pytest.approx(0.01, abs=2e-5)
    assert r.association is not None and r.association.fraction_correct == pytest.approx(4 / 8)
    assert r.planes is not None
    by = {m.est_id: m for m in r.planes.matches}
    assert by[1].matched_by == "beams" and by[1].angle_deg == pytest.approx(0.2, abs=1e-9)
    assert by[2].offset_m == pytest.approx(0.003, abs=1e-9)

    write_eval_json(run / "eval.json", r)
    js = json.loads((run / "eval.json").read_text())
    assert js["trajectory"]["ate_m"]["se3_aligned"]["rmse"] < 1e-9
    assert js["cloud"]["distance_m"]["median"] == pytest.approx(0.01, abs=2e-5)
    assert js["planes"]["n_matched"] == 2
    pngs = write_plots(r, run)
    assert {p.name for p in pngs} >= {"trajectory_error_topview.png", "error_over_distance.png",
                                      "plane_errors.png", "cloud_to_mesh.png", "plane_extents.png"}  # fmt: skip
    for p in pngs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # missing optional files are reported as skipped, not errors
    (run / "cloud.ply").unlink()
    (run / "segments.npz").unlink()
    r2 = evaluate(run, gt)
    assert set(r2.skipped) == {"cloud", "association"} and r2.planes is not None
    assert {m.matched_by for m in r2.planes.matches} == {"geometry"}


def test_evaluate_bad_folders(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match="nope"):
        evaluate(tmp_path / "nope", tmp_path)
    (tmp_path / "run").mkdir()
    with pytest.raises(ValueError, match=r"gt"):
        evaluate(tmp_path / "run", tmp_path / "x.gt")


def _cli(argv: list[str]) -> int:
    import argparse

    from backpack_slam.commands import evaluate as cmd

    parser = argparse.ArgumentParser()
    cmd.add_parser(parser.add_subparsers())
    return cmd.run(parser.parse_args(argv))


def test_evaluate_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t_gt, T_gt = _screw_walk(15.0, 200.0, t0=0.0)
    _write_gt(tmp_path / "walk.gt", t_gt, T_gt)
    (tmp_path / "walk.bag").write_bytes(b"")  # the bag itself is not read
    run = tmp_path / "out"
    run.mkdir()
    T_est = T_gt[::5].copy()
    T_est[:, 2, 3] += 0.05
    write_trajectory_tum(run / "trajectory.tum", t_gt[::5], T_est)

    assert _cli(["evaluate", str(run), "--gt", str(tmp_path / "walk.bag")]) == 0
    out = capsys.readouterr().out
    assert "unaligned 50.0" in out and "start-aligned 0.0" in out
    assert "skipped planes" in out and "eval.json" in out
    js = json.loads((run / "eval.json").read_text())
    assert js["trajectory"]["ate_m"]["unaligned"]["rmse"] == pytest.approx(0.05)
    assert (run / "trajectory_error_topview.png").is_file()

    # the bag named in summary.json is used when --gt is not given; the .gt folder works too
    (run / "eval.json").unlink()
    (run / "summary.json").write_text(json.dumps({"bag": str(tmp_path / "walk.bag")}))
    assert _cli(["evaluate", str(run), "--no-plots"]) == 0
    assert (run / "eval.json").is_file()
    assert _cli(["evaluate", str(run), "--gt", str(tmp_path / "walk.gt"), "--no-plots"]) == 0

    from backpack_slam.commands.evaluate import GroundTruthNotFound

    with pytest.raises(GroundTruthNotFound, match=r"other\.bag"):
        _cli(["evaluate", str(run), "--gt", str(tmp_path / "other.bag")])
    with pytest.raises(EvaluationError, match="missing"):
        _cli(["evaluate", str(tmp_path / "missing"), "--gt", str(tmp_path / "walk.gt")])


def test_inside_polygon_with_margin() -> None:
    from slam.evaluate import inside_polygon_2d

    # an L shape (concave)
    poly = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 3], [0, 3.0]])
    pts = np.array([[0.5, 2.5], [2.0, 0.5], [2.0, 2.0], [4.1, 0.5], [2.0, 1.05]])
    np.testing.assert_array_equal(inside_polygon_2d(pts, poly), [True, True, False, False, False])
    np.testing.assert_array_equal(
        inside_polygon_2d(pts, poly, margin=0.2), [True, True, False, True, True]
    )


def test_geometric_match_prefers_same_facing_plane_on_tie() -> None:
    wall = PlaneRecord(1, np.array([1.0, 0, 0]), 0.0, _wall(0.0, 2.0, 8.0), kind="wall")
    back = PlaneRecord(2, np.array([-1.0, 0, 0]), 0.0, _wall(0.0, 5.0, 6.0, 2.0), kind="furniture")
    patch = _wall(0.0, 5.2, 5.8, 1.5)
    assert match_planes_geometric(
        [PlaneRecord(0, np.array([-1.0, 0, 0]), 0.0, patch)], [wall, back]
    ) == {0: 2}
    assert match_planes_geometric(
        [PlaneRecord(0, np.array([1.0, 0, 0]), 0.0, patch)], [wall, back]
    ) == {0: 1}


def test_association_per_kind_confusions_and_coplanar_surfaces() -> None:
    """Two pieces of one wall (a doorway between them), a board on the first and a door in the
    second: the map's plane over both pieces is right as a surface, not as a piece; a board
    segment on the wall's plane and a wall segment on the board's are the two confusions."""
    from slam.evaluate import coplanar_surfaces
    from slam.export import SegmentTable

    def rec(i: int, kind: str, d: float) -> PlaneRecord:
        return PlaneRecord(i, np.array([0.0, -1.0, 0.0]), d, np.empty((0, 3)), kind=kind)

    true = [rec(0, "wall", 2.0), rec(1, "wall", 2.0), rec(2, "board", 1.98), rec(3, "door", 2.015), rec(4, "wall", 2.01)]
    assert coplanar_surfaces(true) == {0: 0, 1: 0, 2: 2, 3: 3, 4: 4}
    # est plane 7: both wall pieces (0 the majority) and a board segment; 8: the board and one wall segment
    seg_true = np.array([0, 0, 0, 1, 1, 2, 2, 2, 2, 0, 3])
    plane = np.array([7, 7, 7, 7, 7, 7, 8, 8, 8, 8, -1])
    n = seg_true.size
    seg = SegmentTable(("top",), np.zeros(n, np.int32), np.arange(n), np.zeros(n), np.zeros(n, np.int32),
                       np.zeros(n, np.int32), plane.astype(np.int32))
    a = association_errors(seg, seg_true, np.ones(n), {t.id: t.kind for t in true}, coplanar_surfaces(true))
    assert a.n_associated == 10 and a.n_correct == 3 + 3
    assert a.n_correct_surface == 3 + 2 + 3 and a.fraction_correct_surface_of_associated == pytest.approx(0.8)
    assert a.by_kind["wall"] == (6, 5) and a.by_kind["board"] == (4, 3) and a.by_kind["door"] == (0, 0)
    assert (a.confusions_wall_to_child, a.confusions_child_to_wall) == (1, 1)
    assert a.confusion_fraction == pytest.approx(2 / 4)
    js = a.to_json()
    assert js["confusions"]["wall_to_child"] == 1 and js["by_kind"]["board"]["n_correct"] == 3
    # all on one surface: the single-surface figures are the same
    assert (a.confusions_pure, a.n_child_associated_pure) == (2, 4)
    # the board segment on the wall's plane ran across the board's edge (purity 0.6): among the
    # single-surface segments one confusion is left, of three board segments
    purity = np.ones(n)
    purity[5] = 0.6
    b = association_errors(seg, seg_true, purity, {t.id: t.kind for t in true}, coplanar_surfaces(true))
    assert (b.confusions_wall_to_child, b.confusions_child_to_wall) == (1, 1)
    assert (b.confusions_pure, b.n_child_associated_pure) == (1, 3)
    assert b.confusion_fraction_pure == pytest.approx(1 / 3)
    assert b.to_json()["confusions"]["single_surface"]["confusions"] == 1


def test_extent_errors_of_a_board_against_its_face() -> None:
    """A board face 1.8 x 1.2 m; an estimate 10 cm short on the left and 30 cm long at the top."""
    from slam.evaluate import extent_errors

    n = np.array([0.0, -1.0, 0.0])

    def rect(x0: float, x1: float, z0: float, z1: float) -> np.ndarray:
        return np.array([[x0, 6.0, z0], [x1, 6.0, z0], [x1, 6.0, z1], [x0, 6.0, z1]])

    err, excess = extent_errors(rect(2.7, 4.4, 0.9, 2.4), rect(2.6, 4.4, 0.9, 2.1), n)
    assert err == pytest.approx(0.3) and excess == pytest.approx(0.3)
    err, excess = extent_errors(rect(2.65, 4.4, 0.92, 2.1), rect(2.6, 4.4, 0.9, 2.1), n)
    assert err == pytest.approx(0.05) and excess == 0.0


def test_plane_extents_plot(tmp_path: Path) -> None:
    """plane_errors keeps each door's and board's outline with its face's, and the plot draws them."""
    from slam.eval_plots import plot_plane_extents
    from slam.evaluate import plane_errors

    n = np.array([0.0, -1.0, 0.0])
    face = np.array([[2.6, 6.0, 0.9], [4.4, 6.0, 0.9], [4.4, 6.0, 2.1], [2.6, 6.0, 2.1]])
    true = [PlaneRecord(10, n, 5.98, face - np.array([0.0, 0.02, 0.0]), kind="board"),
            PlaneRecord(3, n, 6.0, np.array([[0.0, 6.0, 0.0], [9.0, 6.0, 0.0], [9.0, 6.0, 2.8], [0.0, 6.0, 2.8]]),
                        kind="wall")]
    est = [PlaneRecord(5, n, 5.98, face + np.array([0.1, -0.02, 0.0]), kind="wall")]
    pe = plane_errors(est, true, {5: 10})
    assert set(pe.outlines) == {5} and pe.matches[0].extent_error_m == pytest.approx(0.1)
    out = plot_plane_extents(pe, tmp_path / "plane_extents.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("compressed", [False, True])
def test_streamed_beam_rows_give_the_in_memory_answer(tmp_path: Path, compressed: bool) -> None:
    """beams.npz read a block of scans at a time (stored or deflated, blocks smaller than a scan's
    segments, rows asked for out of order) gives the same true planes as the array in memory."""
    from slam.beam_rows import NpzRows
    from slam.evaluate import close_rows, load_ground_truth

    rng = np.random.default_rng(3)
    n_scans, n_beams = 50, 40
    ids = {name: rng.integers(-1, 6, size=(n_scans, n_beams)).astype(np.int32) for name in ("top", "left")}
    stamps = {name: np.arange(n_scans) * 0.025 + k * 0.01 for k, name in enumerate(ids)}
    path = tmp_path / "beams.npz"
    save = np.savez_compressed if compressed else np.savez
    save(path, **{f"{n}_plane_id": a for n, a in ids.items()}, **{f"{n}_stamps": s for n, s in stamps.items()})
    rows = []
    for s in range(2):
        for k in rng.permutation(n_scans)[:30]:
            cuts = np.sort(rng.choice(np.arange(1, n_beams), size=3, replace=False))
            for a, b in zip([0, *cuts], [*cuts, n_beams], strict=True):
                rows.append((s, int(k), int(a), int(b) - 1))
    r = np.array(rows)
    names = list(ids)
    seg = make_segment_table(names, r[:, 0], r[:, 1], np.array([stamps[names[s]][k] for s, k in r[:, :2]]),
                             r[:, 2], r[:, 3], np.zeros(len(r), dtype=np.int64))
    want, want_p = segment_true_planes(seg, ids, stamps)
    (tmp_path / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    gt = load_ground_truth(tmp_path)
    for chunk in (n_beams * 7, 5, 10**7):
        streamed, st = gt.beam_rows(names)
        got, got_p = segment_true_planes(seg, streamed, st, chunk_beams=chunk)
        close_rows(streamed)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(got_p, want_p)
    with NpzRows(path, "top_plane_id.npy") as reader:
        np.testing.assert_array_equal(reader.rows(30, 35), ids["top"][30:35])
        np.testing.assert_array_equal(reader.rows(3, 4), ids["top"][3:4])  # behind: opened again
        np.testing.assert_array_equal(reader.rows(45, 99), ids["top"][45:])
    with pytest.raises(KeyError):
        NpzRows(path, "right_plane_id.npy")
