"""Calibration: extrinsic recovery on analytic scenes, observability, rig writer, CLI errors."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from box_scene import BOX_PLANES, SCANNERS, _pose, walking_knots

from backpack_slam.cli import main
from calibration.estimator import EstimatorConfig, estimate_extrinsics
from calibration.factors import timed_scanner_plane_factor
from calibration.observability import UnobservableWarning, parameter_sigmas, warn_unobservable
from calibration.observations import PointObservations
from calibration.rig_io import updated_rig
from common.rig import load_rig, resolve_rig, write_rig
from segmentation import Scanline
from slam.backend.factors import NO_KERNEL
from slam.motion import MotionPriorConfig
from slam.trajectory.interpolation import interpolate_trajectory, se3_exp, se3_log

CORRIDOR = np.array([
    [0.0, 0.0, 1.0, 1.3],    # floor
    [0.0, 0.0, -1.0, 1.7],   # ceiling
    [0.0, 1.0, 0.0, 1.5],    # wall y = -1.5
    [0.0, -1.0, 0.0, 1.5],   # wall y = 1.5
])


def scan_points(kt: np.ndarray, kp: np.ndarray, planes: np.ndarray, scanners: list[np.ndarray],
                beams: int = 61, offsets: tuple[float, ...] = (0.0, 0.008, 0.016),
                clock_errors: tuple[float, ...] = (0.0, 0.0, 0.0)) -> PointObservations:
    """Noise-free scanner-frame points on ``planes`` seen from the true trajectory. A scanner's
    ``clock_errors`` entry shifts its stamps: the beam really taken at t is stamped t - error."""
    angles = np.deg2rad(np.linspace(-135.0, 135.0, beams))
    dt_beam = 0.01875 / (beams - 1)
    parts = []
    for s, T_bs in enumerate(scanners):
        for i in range(kt.size - 1):
            times = kt[i] + offsets[s] + np.arange(beams) * dt_beam
            ok = times + clock_errors[s] <= kt[-1]
            times, ang = times[ok], angles[ok]
            T_ws = interpolate_trajectory(kt, kp, times + clock_errors[s]) @ T_bs
            u_s = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
            o = T_ws[:, :3, 3]
            u = np.einsum("nij,nj->ni", T_ws[:, :3, :3], u_s)
            nu = u @ planes[:, :3].T
            no = o @ planes[:, :3].T + planes[:, 3]
            lam = np.where(nu < -1e-9, -no / np.where(nu < -1e-9, nu, -1.0), np.inf)
            j = np.argmin(lam, axis=1)
            r = lam[np.arange(j.size), j]
            v = np.isfinite(r) & (r > 0.1) & (r < 30.0) & (np.abs(nu[np.arange(j.size), j]) > 0.15)
            parts.append(PointObservations(np.full(v.sum(), s), j[v].astype(np.int64),
                                           u_s[v] * r[v, None], times[v], np.full(v.sum(), 0.003)))
    return PointObservations.concatenate(parts)


def _planes(p: np.ndarray) -> dict[int, tuple[np.ndarray, float]]:
    return {j: (p[j, :3], float(p[j, 3])) for j in range(p.shape[0])}


def _perturbed(rng: np.random.Generator, deg: float, m: float) -> list[np.ndarray]:
    return [SCANNERS[0]] + [T @ se3_exp(np.concatenate([np.radians(rng.uniform(-deg, deg, 3)),
                                                         rng.uniform(-m, m, 3)])) for T in SCANNERS[1:]]


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d = se3_log(np.linalg.inv(T_true) @ T_est)
    return float(np.degrees(np.abs(d[:3]).max())), float(np.abs(T_est[:3, 3] - T_true[:3, 3]).max())


def test_recovers_perturbed_extrinsics_in_box_room() -> None:
    kt, kp = walking_knots(duration=1.5)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS)
    T0 = _perturbed(np.random.default_rng(3), 3.0, 0.05)
    # wide priors and a weak motion prior (the gait is not constant-velocity): the data decide
    wide = EstimatorConfig(sigma_rot=1.0, sigma_trans=1.0, motion=MotionPriorConfig(100.0, 100.0))
    res = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), obs, T0, 0, config=wide)
    for s in res.scanners[1:]:
        e0 = _errors(T0[s.index], SCANNERS[s.index])
        rot, tr = _errors(s.T_body_scanner, SCANNERS[s.index])
        assert e0[0] > 0.5 and e0[1] > 0.01  # the perturbation was real
        assert rot < 2e-4 and tr < 1e-5, (s.name, rot, tr)
        assert np.sqrt(np.mean(s.residuals_after**2)) < 1e-5 < np.sqrt(np.mean(s.residuals_before**2))
        assert s.covariance is not None and np.all(np.linalg.eigvalsh(s.covariance) > 0)
    assert res.scanners[0].covariance is None
    np.testing.assert_allclose(res.scanners[0].T_body_scanner, SCANNERS[0])


def test_recovers_time_offset() -> None:
    kt, kp = walking_knots(duration=1.5)
    clock = (0.0, 0.003, -0.002)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS, clock_errors=clock)
    T0 = _perturbed(np.random.default_rng(4), 1.0, 0.01)
    cfg = EstimatorConfig(sigma_rot=1.0, sigma_trans=1.0, time_offsets=True, sigma_time=0.02,
                          motion=MotionPriorConfig(100.0, 100.0))
    res = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), obs, T0, 0, config=cfg)
    for s in res.scanners[1:]:
        assert s.time_offset_sigma is not None
        assert abs(s.time_offset - clock[s.index]) < 5e-5, (s.name, s.time_offset)
        rot, tr = _errors(s.T_body_scanner, SCANNERS[s.index])
        # small bias: a shifted beam time extrapolates its stamped interval's twist (module doc)
        assert rot < 0.02 and tr < 2e-3


def test_grazing_associations_are_dropped() -> None:
    """The horizontal reference scanner's points put on the floor (a wrong association: its scan
    plane is parallel to the floor) are dropped with ``grazing_cos``, the true ones kept."""
    kt, kp = walking_knots(duration=0.5)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS, beams=31)
    ref = np.flatnonzero(obs.scanner == 0)[:40]
    wrong = PointObservations(obs.scanner[ref], np.zeros(ref.size, dtype=np.int64), obs.points_scanner[ref],
                              obs.times[ref], obs.sigmas[ref])
    both = PointObservations.concatenate([obs, wrong])
    cfg = EstimatorConfig(sigma_rot=1.0, sigma_trans=1.0, motion=MotionPriorConfig(100.0, 100.0),
                          cluster_covariance=False)
    n_ref = int(np.sum(obs.scanner == 0))
    kept = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), both, list(SCANNERS), 0,
                               config=replace(cfg, grazing_cos=0.9))
    assert [s.n_points for s in kept.scanners] == [int(np.sum(obs.scanner == s)) for s in range(3)]
    plain = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), both, list(SCANNERS), 0, config=cfg)
    assert plain.scanners[0].n_points == n_ref + ref.size


def test_time_offset_factor_jacobians_match_numerical() -> None:
    import gtsam
    from gtsam.symbol_shorthand import D, E, P, X

    rng = np.random.default_rng(0)
    kt, kp = walking_knots(duration=0.1)
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(kp[0]))
    v.insert(X(1), gtsam.Pose3(kp[1]))
    v.insert(P(0), gtsam.OrientedPlane3(gtsam.Unit3(np.array([0.3, -0.2, 0.93])), 1.2))
    v.insert(E(1), gtsam.Pose3(SCANNERS[1]))
    v.insert(D(1), np.array([0.004]))
    pts = rng.uniform(-3, 3, (5, 3))
    pts[:, 2] = 0.0
    f = timed_scanner_plane_factor(X(0), X(1), P(0), E(1), D(1), pts, rng.uniform(0, 1, 5),
                                   kt[1] - kt[0], np.full(5, 0.003), NO_KERNEL)
    A = f.linearize(v).jacobian()[0]
    eps = 1e-7
    col = 0
    for k, dim in zip([X(0), X(1), P(0), E(1), D(1)], [6, 6, 3, 6, 1], strict=True):
        for c in range(dim):
            d = np.zeros(dim)
            d[c] = eps
            vp, vm = gtsam.Values(v), gtsam.Values(v)
            if dim == 1:
                vp.update(k, v.atVector(k) + d)
                vm.update(k, v.atVector(k) - d)
            elif dim == 3:
                vp.update(k, v.atOrientedPlane3(k).retract(d))
                vm.update(k, v.atOrientedPlane3(k).retract(-d))
            else:
                vp.update(k, v.atPose3(k).retract(d))
                vm.update(k, v.atPose3(k).retract(-d))
            num = (f.unwhitenedError(vp) - f.unwhitenedError(vm)) / (2 * eps)
            np.testing.assert_allclose(A[:, col], num, rtol=1e-5, atol=1e-3)  # whitened by 3 mm
            col += 1


def test_straight_corridor_reports_translation_along_it_unobservable() -> None:
    t = np.arange(61) / 40.0
    kp = np.array([_pose(np.array([0.02 * np.sin(2 * np.pi * a), 0.0, 0.0]),
                         np.array([-2.0 + 1.2 * a, 0.1 * np.sin(a), 0.02 * np.sin(4 * np.pi * a)])) for a in t])
    obs = scan_points(t, kp, CORRIDOR, SCANNERS)
    from calibration.calibrate import reported_covariance

    res = estimate_extrinsics(t, kp, _planes(CORRIDOR), obs, list(SCANNERS), 0)
    for s in res.scanners[1:]:
        assert s.covariance is not None and s.covariance_cluster is not None
        assert reported_covariance(s) is s.covariance_cluster  # the default: cluster-robust
        assert reported_covariance(s, "marginal") is s.covariance
        for cov in (s.covariance, s.covariance_cluster):
            p = parameter_sigmas(s.name, s.T_body_scanner, cov, res.prior_sigmas)
            assert "x" in p.unobservable, p
            assert "z" not in p.unobservable and "roll" not in p.unobservable
            with pytest.warns(UnobservableWarning, match=rf"scanner '{s.name}': parameter x "):
                warn_unobservable(p)
    # the box room constrains everything
    kt, kpb = walking_knots(duration=1.5)
    res = estimate_extrinsics(kt, kpb, _planes(BOX_PLANES), scan_points(kt, kpb, BOX_PLANES, SCANNERS),
                              list(SCANNERS), 0)
    for s in res.scanners[1:]:
        assert s.covariance is not None
        assert parameter_sigmas(s.name, s.T_body_scanner, s.covariance, res.prior_sigmas).unobservable == ()


def test_rig_writer_round_trips(tmp_path: Path) -> None:
    rig = resolve_rig("itc_backpack")
    T = rig.scanner("left").T_body_scanner.matrix() @ se3_exp(np.array([0.01, -0.02, 0.03, 0.004, 0.005, -0.006]))
    C = np.diag([1e-6, 2e-6, 3e-6, 1e-7, 2e-7, 3e-7])
    C[0, 4] = C[4, 0] = 1e-8
    new = updated_rig(rig, {"left": (T, C)}, {"left": 0.0015})
    out = write_rig(tmp_path / "cal.yaml", new, header="test")
    back = load_rig(out)
    np.testing.assert_allclose(back.scanner("left").T_body_scanner.matrix(), T, atol=1e-12)
    np.testing.assert_allclose(np.array(back.scanner("left").T_body_scanner.covariance), C)
    assert back.scanner("left").time_offset == pytest.approx(0.0015)
    assert back.scanner("right") == rig.scanner("right")
    assert [p.name for p in tmp_path.iterdir()] == ["cal.yaml"]


def test_cli_rejects_malformed_rig_naming_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nreference: top\nscanners:\n  - name: top\n    topic: /scan_top\n"
                   "    T_body_scanner: {translation: [0, 0], rpy: [0, 0, 0]}\n")
    bag = tmp_path / "none.bag"
    assert main(["calibrate", str(bag), "--rig", str(bad), "--out", str(tmp_path / "o.yaml")]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "scanners.0.T_body_scanner.translation" in err[0] and str(bad) in err[0]
    assert not (tmp_path / "o.yaml").exists()


def test_no_observations_is_a_clear_error() -> None:
    kt, kp = walking_knots(duration=0.2)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS)
    with warnings.catch_warnings(), pytest.raises(ValueError, match="no points on known planes"):
        estimate_extrinsics(kt, kp, {99: (np.array([0, 0, 1.0]), 1.0)}, obs, list(SCANNERS), 0)


def test_sigmas_scale_with_residual_spread_and_outliers_do_not_bias() -> None:
    """Noise twice the stated sigma and 10 % wrong associations (points 2 cm off their plane): the
    robust scale finds the spread, the reported sigmas grow by it (not smaller than the empirical
    spread says) and cover the actual error, and the kernel keeps the outliers from biasing."""
    from calibration.estimator import robust_scale
    from calibration.observability import parameter_covariance

    rng = np.random.default_rng(12)
    kt, kp = walking_knots(duration=1.5)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS, beams=41)
    # off the plane along its normal (no errors-in-variables bias): 6 mm noise (stated: 3 mm) and
    # 10 % wrong associations 2 cm in front of or behind it (proud boards, recessed doors)
    off = rng.normal(0.0, 0.006, len(obs))
    off += 0.02 * (rng.random(len(obs)) < 0.10) * rng.choice([-1.0, 1.0], len(obs))
    T_ws = interpolate_trajectory(kt, kp, obs.times) @ np.stack([SCANNERS[s] for s in obs.scanner])
    n_scanner = np.einsum("nji,nj->ni", T_ws[:, :3, :3], BOX_PLANES[obs.plane_id, :3])
    pts = obs.points_scanner + off[:, None] * n_scanner
    obs = PointObservations(obs.scanner, obs.plane_id, pts, obs.times, obs.sigmas)
    T0 = _perturbed(np.random.default_rng(5), 1.0, 0.02)
    robust = EstimatorConfig(sigma_rot=1.0, sigma_trans=1.0, motion=MotionPriorConfig(100.0, 100.0))
    res = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), obs, T0, 0, config=robust)
    naive = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), obs, T0, 0,
                                config=replace(robust, variance_factor=False, kernel=NO_KERNEL))
    for s, n in zip(res.scanners, naive.scanners, strict=True):
        assert 1.7 < s.scale < 2.4, (s.name, s.scale)  # MAD of the whitened residuals ~ 2
        assert robust_scale(s.residuals_after / 0.003) == pytest.approx(s.scale, rel=0.35)
        if s.reference:
            continue
        assert s.covariance is not None and n.covariance is not None
        d = se3_log(np.linalg.inv(SCANNERS[s.index]) @ s.T_body_scanner)
        sig = np.sqrt(np.diag(s.covariance))
        assert np.all(np.abs(d) < 3 * sig), (s.name, d / sig)
        # the scaled sigmas exceed the naive ones by about the scale
        ratio = np.sqrt(np.diag(parameter_covariance(s.T_body_scanner, s.covariance))
                        / np.diag(parameter_covariance(n.T_body_scanner, n.covariance)))
        assert np.all(ratio > 1.4), ratio
        # the robust kernel keeps the 2 cm outliers from biasing the translation
        d_naive = se3_log(np.linalg.inv(SCANNERS[s.index]) @ n.T_body_scanner)
        assert np.linalg.norm(d[3:]) < np.linalg.norm(d_naive[3:]), (d, d_naive)


def test_robust_scale_is_the_mad_sigma() -> None:
    from calibration.estimator import robust_scale

    e = np.random.default_rng(1).normal(0.0, 2.0, 20000)
    e[:2000] += 50.0  # 10 % gross outliers barely move it
    assert robust_scale(e) == pytest.approx(2.0 * 1.15, rel=0.1)
    assert robust_scale(np.zeros(0)) == 0.0



def _room_scan(scanner: str, stamp: float, rng: np.random.Generator) -> Scanline:
    """A scanline of the walls x = -2 / 3 and y = -1.5 / 2.5 (scanner frame), 1 mm noise."""
    ang = np.linspace(-3 * np.pi / 4, 3 * np.pi / 4, 541)
    c, s = np.cos(ang), np.sin(ang)
    with np.errstate(divide="ignore"):
        r = np.min(np.stack([np.where(c > 0, 3.0 / c, np.inf), np.where(c < 0, -2.0 / c, np.inf),
                             np.where(s > 0, 2.5 / s, np.inf), np.where(s < 0, -1.5 / s, np.inf)]), axis=0)
    return Scanline.from_ranges(r + rng.normal(0.0, 0.001, r.size), ang, stamp, scanner_id=scanner,
                                time_increment=0.025 / 540)


def test_segment_log_gives_the_prepared_scans_virtual_points_on_the_associated_segments() -> None:
    """One pass: the observations are the preparer's own scanner-frame virtual points of the
    associated segments (stream order, the rig's time offsets, sigma range_sigma / sqrt(n / 2)),
    lying on the walls; a segment row the log lacks is an error."""
    from calibration.observations import SegmentLog
    from slam.config import SlamConfig
    from slam.frontend.scan_prep import ScanPreparer

    rig = updated_rig(resolve_rig("itc_backpack"), {}, {"left": 0.002})
    prep = ScanPreparer(rig, SlamConfig())
    rng = np.random.default_rng(2)
    scans = [prep.prepare(_room_scan(n, 100.0 + 0.01 * k, rng)) for k, n in enumerate(["left", "top", "left"])]
    log = SegmentLog(chunk=2)
    for scan in scans:
        log.add(scan)
    segs = [sc.segs for sc in scans if sc.segs is not None]
    assert len(segs) == 3 and all(sg.n_segments >= 3 for sg in segs)
    assert len(log) == sum(sg.n_segments for sg in segs)

    def column(name: str) -> np.ndarray:
        return np.concatenate([getattr(sg, name) for sg in segs])

    # rows as SLAM reports them: sorted by scanner, scan, first beam; every other segment associated
    scanner = np.concatenate([np.full(sg.n_segments, sc.scanner) for sc, sg in zip(scans, segs, strict=True)])
    index = np.concatenate([np.full(sg.n_segments, sc.scan_index) for sc, sg in zip(scans, segs, strict=True)])
    pid = np.where(np.arange(scanner.size) % 2 == 0, np.arange(scanner.size) + 10, -1)
    order = np.lexsort((column("first_beam"), index, scanner))
    rows = {"scanner": scanner[order], "scan_index": index[order], "first_beam": column("first_beam")[order],
            "last_beam": column("last_beam")[order], "plane_id": pid[order]}
    obs = log.observations(rig, rows, min_points=0)
    take = pid >= 0
    np.testing.assert_array_equal(obs.plane_id, np.repeat(pid[take], 2))
    v, t, n = column("virtual_scanner")[take], column("virtual_times")[take], column("n_points")[take]
    np.testing.assert_array_equal(obs.points_scanner, v.reshape(-1, 3))
    np.testing.assert_array_equal(obs.scanner, np.repeat(scanner[take], 2))
    np.testing.assert_allclose(obs.times, (t + np.where(scanner[take] == 1, 0.002, 0.0)[:, None]).ravel())
    np.testing.assert_allclose(obs.sigmas, np.repeat(0.003 / np.sqrt(n / 2.0), 2))
    p = obs.points_scanner
    wall = np.min(np.abs(np.stack([p[:, 0] - 3.0, p[:, 0] + 2.0, p[:, 1] - 2.5, p[:, 1] + 1.5])), axis=0)
    assert np.all(wall < 0.01) and np.all(p[:, 2] == 0.0)
    few = log.observations(rig, rows, min_points=int(np.median(n)) + 1)
    assert 0 < len(few) < len(obs)
    foreign = {**rows, "first_beam": rows["first_beam"] + 1}
    with pytest.raises(ValueError, match="not among the prepared scans' segments"):
        log.observations(rig, foreign)


# ---------------------------------------------------------------- coarse to fine (large initial error)
def test_loosened_slam_config_opens_the_gates_and_never_tightens() -> None:
    from calibration.calibrate import is_loosened, loosened_slam_config
    from slam.config import SlamConfig

    cfg = SlamConfig()
    fe = cfg.frontend
    wide = loosened_slam_config(cfg, np.radians(3.0), 0.05).frontend
    assert wide.sigma_rotation_deg == pytest.approx(3.0) and wide.sigma_lever_deg == pytest.approx(3.0)
    assert wide.sigma_pose == pytest.approx(0.05)
    assert wide.coplanar_distance > fe.coplanar_distance and wide.merge_distance > fe.merge_distance
    assert 1.0 <= wide.tracking_loosen < fe.tracking_loosen  # tracking gates keep their absolute width
    tiny = loosened_slam_config(cfg, np.radians(0.01), 0.0001).frontend
    assert tiny.model_dump() == {**fe.model_dump(), "tracking_loosen": fe.tracking_loosen,
                                 "max_endpoint_distance": fe.max_endpoint_distance + 3.0 * 0.0001}
    assert wide.max_endpoint_distance == pytest.approx(fe.max_endpoint_distance + 0.15)  # a wrong extrinsic moves the ends
    assert is_loosened(cfg, np.radians(3.0), 0.05) and not is_loosened(cfg, np.radians(0.01), 0.0001)


def test_calibration_options_reject_bad_schedules() -> None:
    from calibration.calibrate import CalibrationOptions

    with pytest.raises(ValueError, match="initial_uncertainty"):
        CalibrationOptions(initial_uncertainty=(-1.0, 0.05))
    with pytest.raises(ValueError, match="shrink"):
        CalibrationOptions(shrink=0.0)
    with pytest.raises(ValueError, match="max_rounds"):
        CalibrationOptions(max_rounds=0)
    with pytest.raises(ValueError, match="coarse_duration"):
        CalibrationOptions(coarse_duration=0.0)
    with pytest.raises(ValueError, match="covariance"):
        CalibrationOptions(covariance="sandwich")  # type: ignore[arg-type]


def test_coarse_rounds_read_only_the_first_seconds() -> None:
    from calibration.calibrate import _first_seconds

    lines = [Scanline.from_ranges(np.ones(5), np.linspace(-1.0, 1.0, 5), 100.0 + 0.5 * k, time_increment=0.01)
             for k in range(10)]
    head = _first_seconds(lambda rig: iter(lines), 2.0)
    assert [ln.stamp for ln in head(None)] == [100.0, 100.5, 101.0, 101.5, 102.0]  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def short_calibration_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from common.config import configs_dir
    from simulation.run import load_simulation_config, simulate

    out = tmp_path_factory.mktemp("calib") / "run.bag"
    cfg = load_simulation_config(configs_dir() / "simulation" / "calibration.yaml")
    simulate(cfg.world, cfg.rig, duration=3.0, out=out, config=cfg, progress=False)
    return out


def test_loosened_slam_keeps_a_badly_calibrated_rig_on_few_planes(short_calibration_bag: Path) -> None:
    """With the tilted scanners ~3 deg / 5 cm off, the plain gates leave many of their segments
    unassociated (plane creation, which now insists on a noise-consistent fit, no longer turns them
    into spurious planes: it leaves them out); gates opened for that uncertainty associate them
    with the planes the reference scanner sees."""
    from calibration.calibrate import run_slam
    from slam.config import SlamConfig
    from slam.io.bag import read_scans

    true = load_rig(short_calibration_bag.with_suffix(".gt") / "rig.yaml")
    T = {s.name: s.T_body_scanner.matrix() @ se3_exp(np.r_[np.radians([2.5, -2.5, 2.5]), [0.04, -0.04, 0.04]])
         for s in true.scanners if s.name != true.reference}
    bad = updated_rig(true, {n: (m, None) for n, m in T.items()})
    plain, _ = run_slam(read_scans(short_calibration_bag, rig=bad), bad, SlamConfig())
    loose, _ = run_slam(read_scans(short_calibration_bag, rig=bad), bad, SlamConfig(), (np.radians(3.0), 0.05))

    def tilted_share(res: object) -> float:
        rows = res.segment_rows  # type: ignore[attr-defined]
        tilted = rows["scanner"] != 0
        return float(np.mean(rows["plane_id"][tilted] >= 0))

    assert tilted_share(loose) > tilted_share(plain) + 0.1, (tilted_share(loose), tilted_share(plain))


def test_cluster_covariance_grows_with_errors_shared_within_a_knot_interval() -> None:
    """White noise at the stated sigma: the cluster-robust sigmas agree with the marginal ones
    (within the spread of 30 clusters). The same noise plus an error shared by all points of a
    (knot interval, scanner) (trajectory-model-like): the marginal sigmas do not see it, the
    cluster-robust ones grow."""
    kt, kp = walking_knots(duration=1.5)
    obs = scan_points(kt, kp, BOX_PLANES, SCANNERS, beams=41)
    T_ws = interpolate_trajectory(kt, kp, obs.times) @ np.stack([SCANNERS[s] for s in obs.scanner])
    n_scanner = np.einsum("nji,nj->ni", T_ws[:, :3, :3], BOX_PLANES[obs.plane_id, :3])
    rng = np.random.default_rng(21)
    white = rng.normal(0.0, 0.003, len(obs))
    group = np.searchsorted(kt, obs.times) * 3 + obs.scanner
    shared = rng.normal(0.0, 0.004, int(group.max()) + 1)[group]
    cfg = EstimatorConfig(sigma_rot=1.0, sigma_trans=1.0, motion=MotionPriorConfig(100.0, 100.0),
                          cluster_knots=(1, 3))
    ratios = []
    for off in (white, white + shared):
        o = PointObservations(obs.scanner, obs.plane_id, obs.points_scanner + off[:, None] * n_scanner,
                              obs.times, obs.sigmas)
        res = estimate_extrinsics(kt, kp, _planes(BOX_PLANES), o, list(SCANNERS), 0, config=cfg)
        r = []
        for s in res.scanners[1:]:
            assert s.covariance is not None and s.covariance_cluster is not None
            assert np.all(np.linalg.eigvalsh(s.covariance_cluster) > 0)
            assert set(s.covariance_clusters) == {1, 3}
            np.testing.assert_allclose(s.covariance_clusters[1], s.covariance_cluster)
            # 30 knot intervals < min_clusters: the 3-interval window falls back to one interval
            np.testing.assert_allclose(s.covariance_clusters[3], s.covariance_cluster)
            r.append(np.sqrt(np.diag(s.covariance_cluster) / np.diag(s.covariance)))
        ratios.append(float(np.median(r)))
    assert 0.5 < ratios[0] < 1.3, ratios
    assert ratios[1] > 1.25 * ratios[0], ratios
    with pytest.raises(ValueError, match="cluster_knots"):
        EstimatorConfig(cluster_knots=(0,))


def test_cli_rejects_a_negative_coarse_uncertainty(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o.yaml"
    assert main(["calibrate", str(tmp_path / "none.bag"), "--rig", "itc_backpack", "--out", str(out),
                 "--coarse", "-1", "50"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--coarse" in err[0]
    assert not out.exists()


def test_cli_rejects_a_non_positive_coarse_duration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o.yaml"
    assert main(["calibrate", str(tmp_path / "none.bag"), "--rig", "itc_backpack", "--out", str(out),
                 "--coarse", "3", "50", "--coarse-seconds", "0"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--coarse-seconds" in err[0]
    assert not out.exists()
