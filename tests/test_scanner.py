"""The scanner model: exact geometry, per-beam timing on a moving rig, noise, dropouts, mixed pixels,
and the observability of the default rig's angles."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from common.rig import Extrinsic, Rig, ScannerConfig, load_rig
from simulation.rig_notes import side_extrinsic
from simulation.scanner import (
    MIXED,
    NO_RETURN,
    ScannerNoiseConfig,
    apply_measurement,
    beam_rays,
    simulate_scans,
)
from simulation.trajectory import Trajectory, walk_trajectory

RIG_YAML = Path(__file__).resolve().parents[1] / "configs" / "rig" / "itc_backpack.yaml"
NOISE_OFF = ScannerNoiseConfig(enabled=False)


@dataclass
class Hits:
    range: np.ndarray
    plane_id: np.ndarray
    kind: np.ndarray
    cos_incidence: np.ndarray


class BoxRoom:
    """Analytic stand-in for the raycaster: the inside of an axis-aligned box.

    Planes 0..5: x=lo, x=hi, y=lo, y=hi, z=lo (floor, kind 1), z=hi (ceiling, kind 2); walls kind 0."""

    def __init__(self, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> None:
        self.lo = np.asarray(lo, float)
        self.hi = np.asarray(hi, float)
        self.kinds = np.array([0, 0, 0, 0, 1, 2], dtype=np.int8)
        self.normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
        self.d = np.array([-lo[0], hi[0], -lo[1], hi[1], -lo[2], hi[2]], float)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        with np.errstate(divide="ignore", invalid="ignore"):
            t_lo = (self.lo - origins) / dirs
            t_hi = (self.hi - origins) / dirs
        t = np.where(dirs > 0, t_hi, np.where(dirs < 0, t_lo, np.inf))
        axis = np.argmin(t, axis=1)
        rng = t[np.arange(len(t)), axis]
        face = 2 * axis + (dirs[np.arange(len(t)), axis] > 0)
        cos = np.abs(dirs[np.arange(len(t)), axis])
        return Hits(rng, face.astype(np.int32), self.kinds[face], cos)


ROOM = BoxRoom((-4.0, -3.0, 0.0), (6.0, 2.5, 2.8))


def _static(T: np.ndarray, t_end: float = 2.0) -> Trajectory:
    from scipy.spatial.transform import Rotation

    times = np.arange(0, int(t_end * 200) + 1) / 200.0
    q = np.tile(Rotation.from_matrix(T[:3, :3]).as_quat(), (times.size, 1))
    return Trajectory(times, np.tile(T[:3, 3], (times.size, 1)), q)


def _scanner(rpy=(0.0, 0.0, 0.0), xyz=(0.0, 0.0, 0.0)) -> ScannerConfig:
    return ScannerConfig(name="s", topic="/s", T_body_scanner=Extrinsic(translation=list(xyz), rpy=list(rpy)))


def test_known_pose_analytic_ranges_and_plane_ids() -> None:
    T = np.eye(4)
    T[:3, 3] = [0.5, -0.5, 1.5]
    sc = _scanner()
    [blk] = simulate_scans(ROOM, _static(T), [sc], [np.array([0.1])], NOISE_OFF, np.random.default_rng(0))
    a = sc.scanner_model.beam_angles()
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (6.0 - 0.5) / c, np.where(c < 0, (-4.0 - 0.5) / c, np.inf))
        ty = np.where(s > 0, (2.5 + 0.5) / s, np.where(s < 0, (-3.0 + 0.5) / s, np.inf))
    expect = np.minimum(tx, ty)
    np.testing.assert_allclose(blk.ranges[0], expect, atol=1e-6, rtol=0)
    expect_id = np.where(tx < ty, np.where(c > 0, 1, 0), np.where(s > 0, 3, 2))
    np.testing.assert_array_equal(blk.plane_id[0], expect_id)
    np.testing.assert_array_equal(blk.kind[0], 0)
    assert blk.ranges.dtype == np.float32 and blk.plane_id.dtype == np.int32 and blk.kind.dtype == np.int8


def test_tilted_scanner_extrinsic_hits_floor_and_ceiling() -> None:
    rig = load_rig(RIG_YAML)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.9]
    left = rig.scanner("left")
    [blk] = simulate_scans(ROOM, _static(T), [left], [np.array([0.0])], NOISE_OFF, np.random.default_rng(0))
    ids = set(blk.plane_id[0].tolist())
    assert {4, 5} <= ids and (3 in ids)  # floor, ceiling, the left wall
    # the floor hit points lie on z = 0
    o, d = beam_rays(_static(T), left, np.array([0.0]))
    floor = blk.plane_id[0] == 4
    pts = o[floor] + d[floor] * blk.ranges[0][floor, None]
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-5)


def test_moving_scan_differs_from_rest_exactly_as_trajectory_says() -> None:
    walk = {"waypoints": [[-3, -1], [5, -1]], "speed": 1.4, "closed": False}
    tr = walk_trajectory(walk, 6.0, seed=1)
    sc = load_rig(RIG_YAML).scanner("right")
    stamp = 3.0
    [moving] = simulate_scans(ROOM, tr, [sc], [np.array([stamp])], NOISE_OFF, np.random.default_rng(0))
    # reference: every beam cast separately from the pose at its own time
    model = sc.scanner_model
    t_beams = stamp + model.beam_offsets()
    assert math.isclose(model.time_increment * 1440, 0.025) and math.isclose(t_beams[-1] - t_beams[0], 0.01875)
    R, t = tr.interpolate(t_beams)
    Tbs = sc.T_body_scanner.matrix()
    a = model.beam_angles()
    d_s = np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a)))
    origins = t + np.einsum("nij,j->ni", R, Tbs[:3, 3])
    dirs = np.einsum("nij,jk,nk->ni", R, Tbs[:3, :3], d_s)
    ref = ROOM.cast(origins, dirs)
    np.testing.assert_allclose(moving.ranges[0], ref.range, atol=2e-6, rtol=1e-6)
    # at rest at the first beam's pose the scan is different (the rig moved ~2.6 cm during it)
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R[0], t[0]
    [rest] = simulate_scans(ROOM, _static(T0, 4.0), [sc], [np.array([stamp])], NOISE_OFF, np.random.default_rng(0))
    diff = np.abs(moving.ranges[0] - rest.ranges[0])
    assert diff[:10].max() < 1e-4 and diff.max() > 5e-3


def _flat(n_scans: int, value: float, cos: float = 1.0):
    shape = (n_scans, 1081)
    return np.full(shape, value), np.full(shape, 3, np.int32), np.full(shape, 0, np.int8), np.full(shape, cos)


def test_noise_sigma_and_quantisation() -> None:
    r, pid, kind, cos = _flat(200, 4.0)
    cfg = ScannerNoiseConfig(mixed_prob=0.0)
    out, p2, _ = apply_measurement(r, pid, kind, cos, _scanner(), cfg, np.random.default_rng(1))
    assert 0.0027 < np.std(out) < 0.0033
    mm = out.astype(np.float64) * 1000
    np.testing.assert_allclose(mm, np.round(mm), atol=1e-3)
    assert (p2 == 3).all()
    out2, _, _ = apply_measurement(r, pid, kind, cos, _scanner(), cfg.model_copy(update={"range_sigma_per_m": 0.002}), np.random.default_rng(1))
    assert np.std(out2) > 2.5 * np.std(out)
    # seeded
    again, _, _ = apply_measurement(r, pid, kind, cos, _scanner(), cfg, np.random.default_rng(1))
    np.testing.assert_array_equal(out, again)


def test_dropouts_at_grazing_incidence() -> None:
    cfg = ScannerNoiseConfig(mixed_prob=0.0)
    r, pid, kind, _ = _flat(50, 3.0)
    cos = np.tile(np.linspace(0.0, 1.0, 1081), (50, 1))
    out, p2, k2 = apply_measurement(r, pid, kind, cos, _scanner(), cfg, np.random.default_rng(2))
    drop = np.isnan(out)
    assert drop[:, cos[0] > cfg.grazing_cos].sum() == 0
    assert drop[:, cos[0] < 0.02].mean() > 0.8
    assert (p2[drop] == NO_RETURN).all() and (k2[drop] == -1).all()


def test_invalid_returns_convention() -> None:
    r = np.array([[np.inf, 0.05, 31.0, 5.0]])
    pid = np.array([[-1, 2, 2, 2]], np.int32)
    out, p2, _ = apply_measurement(r, pid, np.zeros((1, 4), np.int8), np.ones((1, 4)), _scanner(), NOISE_OFF, np.random.default_rng(0))
    assert np.isinf(out[0, 0]) and np.isnan(out[0, 1]) and np.isinf(out[0, 2]) and out[0, 3] == 5.0
    np.testing.assert_array_equal(p2[0], [NO_RETURN, NO_RETURN, NO_RETURN, 2])


def test_mixed_pixels_between_foreground_and_background() -> None:
    r, pid, kind, cos = _flat(100, 5.0)
    r[:, 540:] = 2.0
    pid[:, 540:] = 7
    cfg = ScannerNoiseConfig(range_sigma=0.0, quantization=0.0, mixed_prob=0.5, grazing_cos=0.0)
    out, p2, k2 = apply_measurement(r, pid, kind, cos, _scanner(), cfg, np.random.default_rng(3))
    mixed = p2 == MIXED
    assert 25 < mixed.sum() < 75
    assert set(np.nonzero(mixed)[1].tolist()) <= {539, 540}
    assert ((out[mixed] > 2.0) & (out[mixed] < 5.0)).all() and (k2[mixed] == -1).all()
    assert (out[~mixed] == r[~mixed]).all()
    _none, p3, _ = apply_measurement(r, pid, kind, cos, _scanner(), cfg.model_copy(update={"mixed_prob": 0.0}), np.random.default_rng(3))
    assert not (p3 == MIXED).any()


def _information(rig: Rig, T: np.ndarray) -> np.ndarray:
    """6x6 information of point-to-plane residuals for a small body motion (rotation, translation)."""
    tr = _static(T, 1.0)
    J = []
    for sc in rig.scanners:
        [blk] = simulate_scans(ROOM, tr, [sc], [np.array([0.0])], NOISE_OFF, np.random.default_rng(0))
        o, d = beam_rays(tr, sc, np.array([0.0]))
        ok = np.isfinite(blk.ranges[0])
        p_w = o[ok] + d[ok] * blk.ranges[0][ok, None]
        n_w = ROOM.normals[blk.plane_id[0][ok]]
        p_b = (p_w - T[:3, 3]) @ T[:3, :3]
        n_b = n_w @ T[:3, :3]
        J.append(np.column_stack((np.cross(p_b, n_b), n_b)))
    Jm = np.concatenate(J)
    return Jm.T @ Jm


def test_rig_yaml_matches_documented_angles_and_is_observable() -> None:
    rig = load_rig(RIG_YAML)
    assert rig.reference == "top" and rig.scanner("top").T_body_scanner.matrix().tolist() == np.eye(4).tolist()
    assert [s.topic for s in rig.scanners] == ["/scan_top", "/scan_left", "/scan_right"]
    for side in ("left", "right"):
        t, rpy = side_extrinsic(side)
        ext = rig.scanner(side).T_body_scanner
        np.testing.assert_allclose(ext.translation, t)
        np.testing.assert_allclose(ext.rpy, rpy, atol=1e-12)
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 1.9]
    info = _information(rig, T)
    ev = np.linalg.eigvalsh(info)
    assert ev.min() > 1e-3 * ev.max()
    # the top scanner alone cannot see z, roll or pitch
    top_only = Rig(name="t", reference="top", scanners=[rig.scanner("top")])
    ev_top = np.linalg.eigvalsh(_information(top_only, T))
    assert ev_top.min() < 1e-9 * ev_top.max()
    # a pushbroom variant (scan planes across the walking direction) observes pitch worse
    push = rig.model_copy(
        update={"scanners": [rig.scanner("top")] + [
            rig.scanner(s).model_copy(update={"T_body_scanner": Extrinsic(translation=side_extrinsic(s, 0.0)[0], rpy=side_extrinsic(s, 0.0, 0.0)[1])})
            for s in ("left", "right")
        ]}
    )
    pitch = np.array([0, 1, 0, 0, 0, 0], float)
    assert pitch @ info @ pitch > 1.5 * (pitch @ _information(push, T) @ pitch)


def test_beam_times_outside_trajectory() -> None:
    with pytest.raises(ValueError, match="outside the trajectory"):
        beam_rays(_static(np.eye(4), 1.0), _scanner(), np.array([0.99]))
