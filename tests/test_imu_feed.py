"""slam.imu_feed: slicing IMU samples into knot intervals and predicting a knot from them."""

from __future__ import annotations

import numpy as np
import pytest
from backend_defaults import backend_defaults

from slam.imu_feed import ImuSamples, predict_navstate
from slam.motion import ImuConfig


def _imu_config() -> ImuConfig:
    """The IMU configuration of the default SlamConfig()."""
    cfg = backend_defaults(imu=True).imu
    assert cfg is not None
    return cfg


def _samples(rate: float = 200.0, duration: float = 2.0, accel: tuple[float, float, float] = (0.0, 0.0, 9.80665),
             gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> ImuSamples:
    t = np.arange(0.0, duration, 1.0 / rate)
    return ImuSamples(t, np.tile(accel, (t.size, 1)), np.tile(gyro, (t.size, 1)))


def test_interval_durations_sum_to_the_interval() -> None:
    s = _samples()
    for t_a, t_b in ((0.0, 0.05), (0.0123, 0.0623), (0.5, 0.5049), (1.2, 1.95)):
        a, g, dt = s.interval(t_a, t_b)
        assert dt.sum() == pytest.approx(t_b - t_a, abs=1e-12)
        assert np.all(dt > 0) and a.shape == (dt.size, 3) and g.shape == (dt.size, 3)


def test_held_samples_start_with_the_sample_at_or_before_the_start() -> None:
    t = np.array([0.0, 0.02, 0.04, 0.06])
    acc = np.array([[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0], [4.0, 0, 0]])
    s = ImuSamples(t, acc, np.zeros((4, 3)), instantaneous=False)
    a, _, dt = s.interval(0.01, 0.05)
    np.testing.assert_allclose(a[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(dt, [0.01, 0.02, 0.01])


def test_instantaneous_samples_take_the_interpolant_at_each_piece_midpoint() -> None:
    """Readings 1, 2, 3, 4 at 0, 20, 40, 60 ms: the pieces of [10, 50) ms take the straight line
    between samples at 15, 30 and 45 ms, so a reading linear in time integrates exactly."""
    t = np.array([0.0, 0.02, 0.04, 0.06])
    acc = np.array([[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0], [4.0, 0, 0]])
    s = ImuSamples(t, acc, acc[:, ::-1].copy(), instantaneous=True)
    a, g, dt = s.interval(0.01, 0.05)
    np.testing.assert_allclose(a[:, 0], [1.75, 2.5, 3.25])
    np.testing.assert_allclose(g[:, 2], [1.75, 2.5, 3.25])
    np.testing.assert_allclose(dt, [0.01, 0.02, 0.01])
    assert float(a[:, 0] @ dt) == pytest.approx(0.04 * (1.0 + 50.0 * 0.03), rel=1e-12)  # the line's integral


def test_midpoint_rule_follows_a_swaying_torso() -> None:
    """Instantaneous gyro readings of a roll sway (5 deg at 2 Hz) at 200 Hz, 4.1 s integrated:
    holding each reading to the next stamp leads the sway by half a sample (~1 mrad, which
    tilts gravity into ~0.01 m/s^2 of false acceleration); the midpoint rule follows it."""
    rate, T = 200.0, 4.1
    t = np.arange(0.0, T + 0.5, 1.0 / rate)
    A, w = np.radians(5.0), 2.0 * np.pi * 2.0
    gyro = np.column_stack((A * w * np.cos(w * t), np.zeros_like(t), np.zeros_like(t)))
    acc = np.column_stack((np.zeros_like(t), 9.80665 * np.sin(A * np.sin(w * t)), 9.80665 * np.cos(A * np.sin(w * t))))
    cfg = _imu_config()
    roll_true = A * np.sin(w * T)
    errs = {}
    for inst in (True, False):
        s = ImuSamples(t, acc, gyro, instantaneous=inst)
        T1, _ = predict_navstate(cfg, np.eye(4), np.zeros(3), np.zeros(6), s, 0.0, T)
        errs[inst] = abs(np.arctan2(T1[2, 1], T1[2, 2]) - roll_true)
    assert errs[True] < 5e-5 and errs[False] > 1e-3, errs


def _numpy_interval(s: ImuSamples, t_a: float, t_b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The interval as numpy computed it before the compiled pass (the reference)."""
    i0 = max(int(np.searchsorted(s.times, t_a, side="right")) - 1, 0)
    i1 = max(int(np.searchsorted(s.times, t_b, side="left")), i0 + 1)
    idx = np.arange(i0, i1)
    start = np.maximum(s.times[idx], t_a)
    end = np.minimum(np.append(s.times[idx[1:]], t_b), t_b)
    dt = end - start
    keep = dt > 0
    if not s.instantaneous:
        return s.accel[idx[keep]], s.gyro[idx[keep]], dt[keep]
    mid = 0.5 * (start[keep] + end[keep])
    j = np.clip(np.searchsorted(s.times, mid, side="right") - 1, 0, s.times.size - 2)
    w = np.clip((mid - s.times[j]) / (s.times[j + 1] - s.times[j]), 0.0, 1.0)[:, None]
    return (1.0 - w) * s.accel[j] + w * s.accel[j + 1], (1.0 - w) * s.gyro[j] + w * s.gyro[j + 1], dt[keep]


@pytest.mark.parametrize("instantaneous", [False, True])
def test_the_compiled_interval_is_the_numpy_one_bit_for_bit(instantaneous: bool) -> None:
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.004, 0.006, 600))
    s = ImuSamples(t, rng.normal(0, 3, (600, 3)), rng.normal(0, 1, (600, 3)), instantaneous=instantaneous)
    starts = np.concatenate((rng.uniform(t[0], t[-1] - 0.1, 200), t[10:20]))  # on sample stamps too
    for t_a, width in zip(starts, rng.uniform(0.001, 0.08, starts.size), strict=True):
        got, ref = s.interval(float(t_a), float(t_a + width)), _numpy_interval(s, float(t_a), float(t_a + width))
        for x, y in zip(got, ref, strict=True):
            np.testing.assert_array_equal(x, y)


def test_gaps_are_errors_and_coverage_is_checked() -> None:
    t = np.concatenate((np.arange(0.0, 1.0, 0.005), np.arange(1.5, 2.0, 0.005)))
    s = ImuSamples(t, np.zeros((t.size, 3)), np.zeros((t.size, 3)))
    assert s.covers(0.0, 0.9) and not s.covers(0.0, 1.8) and not s.covers(-0.1, 0.5)
    with pytest.raises(ValueError, match="no samples"):
        s.interval(1.1, 1.2)


@pytest.mark.parametrize("bad", ["shape", "order", "nan"])
def test_bad_samples_are_rejected(bad: str) -> None:
    t = np.arange(0.0, 1.0, 0.01)
    a, g = np.zeros((t.size, 3)), np.zeros((t.size, 3))
    if bad == "shape":
        a = a[:, :2]
    elif bad == "order":
        t = t[::-1].copy()
    else:
        g[3, 1] = np.nan
    with pytest.raises(ValueError, match="imu"):
        ImuSamples(t, a, g)


def test_prediction_follows_constant_acceleration_and_rotation() -> None:
    """A body accelerating at 0.5 m/s^2 along x while turning at 0.3 rad/s about z."""
    cfg = _imu_config()
    acc, w = 0.5, 0.3
    t = np.arange(0.0, 1.0, 0.001)
    # specific force in the body frame: the body turns, so world +x acceleration appears rotated
    yaw = w * t
    f_body = np.stack((acc * np.cos(yaw), -acc * np.sin(yaw), np.full_like(t, cfg.gravity)), axis=1)
    s = ImuSamples(t, f_body, np.tile([0.0, 0.0, w], (t.size, 1)))
    T, v = predict_navstate(cfg, np.eye(4), np.array([1.0, 0.0, 0.0]), np.zeros(6), s, 0.0, 0.5)
    np.testing.assert_allclose(T[:3, 3], [1.0 * 0.5 + 0.5 * acc * 0.25, 0.0, 0.0], atol=2e-4)
    np.testing.assert_allclose(v, [1.0 + acc * 0.5, 0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(np.arctan2(T[1, 0], T[0, 0]), w * 0.5, atol=1e-6)


def test_prediction_removes_the_given_bias() -> None:
    cfg = _imu_config()
    bias = np.array([0.1, -0.05, 0.02, 0.001, 0.0, -0.002])
    s = _samples(accel=(0.1, -0.05, cfg.gravity + 0.02), gyro=(0.001, 0.0, -0.002))
    T, v = predict_navstate(cfg, np.eye(4), np.zeros(3), bias, s, 0.2, 1.2)
    np.testing.assert_allclose(T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(v, 0.0, atol=1e-9)
