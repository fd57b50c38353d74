"""The walking trajectory (speed, gait, smoothness, seeding, interpolation) and the IMU."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from simulation.imu import GRAVITY, ImuConfig, ideal_imu, simulate_imu
from simulation.trajectory import GaitConfig, Trajectory, walk_trajectory

LOOP = {"waypoints": [[0, 0], [30, 0], [30, 12], [0, 12]], "speed": 1.3, "stops": [], "closed": True}


@pytest.fixture(scope="module")
def traj() -> Trajectory:
    return walk_trajectory(LOOP, 60.0, seed=3)


def _straight(traj: Trajectory) -> np.ndarray:
    """Mask of samples on the first straight at full speed (after start, before the corner)."""
    x = traj.positions[:, 0]
    y = traj.positions[:, 1]
    return (x > 5) & (x < 24) & (np.abs(y) < 0.3) & (traj.times < 30)


def test_rate_and_span(traj: Trajectory) -> None:
    assert 1.0 / traj.dt >= 200.0
    assert traj.times[0] == 0.0 and traj.times[-1] >= 60.0
    np.testing.assert_allclose(np.linalg.norm(traj.quaternions, axis=1), 1.0, atol=1e-12)


def test_speed_within_spec(traj: Trajectory) -> None:
    v = np.linalg.norm(np.gradient(traj.positions[:, :2], traj.times, axis=0), axis=1)
    m = _straight(traj)
    assert m.sum() > 1000
    assert 1.0 <= np.median(v[m]) <= 1.5
    assert v.max() < 1.5 * 1.3  # sway adds a little, never a jump
    # slower at corners: around (30, 0) the walker slows down
    corner = np.linalg.norm(traj.positions[:, :2] - [30, 0], axis=1) < 1.0
    assert np.median(v[corner]) < 0.85 * np.median(v[m])
    # starts at rest
    assert v[: int(0.5 / traj.dt)].max() < 0.05


def test_bob_amplitude_and_frequency(traj: Trajectory) -> None:
    m = _straight(traj)
    z = traj.positions[m, 2]
    assert 1.7 < np.mean(z) < 2.1
    p2p = np.percentile(z, 99) - np.percentile(z, 1)
    assert 0.02 <= p2p <= 0.045
    zc = z - z.mean()
    spec = np.abs(np.fft.rfft(zc * np.hanning(zc.size)))
    freq = np.fft.rfftfreq(zc.size, traj.dt)
    f_peak = freq[np.argmax(spec)]
    assert 1.7 <= f_peak <= 2.1


def test_roll_pitch_few_degrees_and_yaw_follows_path(traj: Trajectory) -> None:
    ypr = Rotation.from_quat(traj.quaternions).as_euler("ZYX")
    m = _straight(traj)
    assert 0.5 < np.degrees(np.abs(ypr[m, 2]).max()) < 8.0  # roll
    assert 0.3 < np.degrees(np.abs(ypr[m, 1]).max()) < 8.0  # pitch
    assert np.degrees(np.abs(ypr[m, 0]).max()) < 6.0  # yaw along +x on the first straight
    second = (traj.positions[:, 0] > 29.5) & (traj.positions[:, 1] > 3) & (traj.positions[:, 1] < 9)
    assert second.any()
    assert np.degrees(np.abs(ypr[second, 0] - math.pi / 2).max()) < 8.0


def test_smooth(traj: Trajectory) -> None:
    dt = traj.dt
    acc = np.diff(traj.positions, n=2, axis=0) / dt**2
    assert np.abs(acc).max() < 8.0  # m/s^2: bob at 2 Hz is ~5, no jumps
    rot = Rotation.from_quat(traj.quaternions)
    w = (rot[:-1].inv() * rot[1:]).as_rotvec() / dt
    assert np.linalg.norm(w, axis=1).max() < math.radians(120)
    assert np.abs(np.diff(w, axis=0)).max() / dt < 20.0  # rad/s^2


def test_seeded() -> None:
    a = walk_trajectory(LOOP, 10.0, seed=1)
    b = walk_trajectory(LOOP, 10.0, seed=1)
    c = walk_trajectory(LOOP, 10.0, seed=2)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.quaternions, b.quaternions)
    assert np.abs(a.positions[:, 2] - c.positions[:, 2]).max() > 1e-3


def test_stops_and_open_walk_turns_back() -> None:
    walk = {"waypoints": [[0, 0], [8, 0], [8, 6]], "speed": 1.2, "stops": [{"waypoint": 1, "duration": 4.0}], "closed": False}
    tr = walk_trajectory(walk, 40.0, seed=0)
    v = np.linalg.norm(np.gradient(tr.positions[:, :2], tr.times, axis=0), axis=1)
    at_stop = np.linalg.norm(tr.positions[:, :2] - [8, 0], axis=1) < 0.05
    assert tr.dt * np.count_nonzero(at_stop & (v < 0.02)) > 3.0
    # back and forth: returns towards the start after reaching the end
    d_end = np.linalg.norm(tr.positions[:, :2] - [8, 6], axis=1)
    i_end = int(np.argmin(d_end))
    assert d_end[i_end] < 0.1 and tr.positions[-1, 1] < 5.5


def test_interpolate_exact_at_samples_and_between(traj: Trajectory) -> None:
    R, t = traj.interpolate(traj.times[::97])
    np.testing.assert_allclose(t, traj.positions[::97], atol=1e-12)
    np.testing.assert_allclose(R, Rotation.from_quat(traj.quaternions[::97]).as_matrix(), atol=1e-12)
    # midpoints: linear positions and slerp rotations
    k = np.arange(10, 2000, 113)
    tm = 0.5 * (traj.times[k] + traj.times[k + 1])
    R, t = traj.interpolate(tm)
    np.testing.assert_allclose(t, 0.5 * (traj.positions[k] + traj.positions[k + 1]), atol=1e-12)
    r0, r1 = Rotation.from_quat(traj.quaternions[k]), Rotation.from_quat(traj.quaternions[k + 1])
    half = r0 * Rotation.from_rotvec(0.5 * (r0.inv() * r1).as_rotvec())
    np.testing.assert_allclose(R, half.as_matrix(), atol=1e-12)
    with pytest.raises(ValueError, match="outside the trajectory"):
        traj.interpolate([traj.times[-1] + 1.0])


def test_tum(tmp_path, traj: Trajectory) -> None:
    p = tmp_path / "t.tum"
    traj.write_tum(p, time_offset=100.0)
    d = np.loadtxt(p)
    assert d.shape == (len(traj.times), 8)
    np.testing.assert_allclose(d[:, 0], traj.times + 100.0, atol=1e-8)
    np.testing.assert_allclose(d[:, 1:4], traj.positions, atol=1e-8)
    assert list(tmp_path.iterdir()) == [p]


def test_bad_walk() -> None:
    with pytest.raises(ValueError, match="waypoints"):
        walk_trajectory({"waypoints": [[0, 0]], "speed": 1.2}, 5.0, seed=0)
    with pytest.raises(ValueError, match="stops"):
        walk_trajectory({"waypoints": [[0, 0], [1, 0]], "speed": 1.2, "stops": [{"waypoint": 5, "duration": 1}]}, 5.0, 0)


def test_imu_consistent_with_trajectory(traj: Trajectory) -> None:
    gyro, accel = ideal_imu(traj)
    # at rest at the start: gravity up, no rotation
    assert abs(np.linalg.norm(accel[5]) - GRAVITY) < 1e-3 and accel[5, 2] > 0.99 * GRAVITY
    assert np.abs(gyro[5]).max() < 0.01
    # gyro = central difference of the interpolated rotations, in the body frame
    h = 1e-3
    tq = traj.times[200:-200:50]
    Ra, _ = traj.interpolate(tq - h)
    Rb, _ = traj.interpolate(tq + h)
    w = Rotation.from_matrix(np.einsum("nji,njk->nik", Ra, Rb)).as_rotvec() / (2 * h)
    np.testing.assert_allclose(gyro[200:-200:50], w, atol=0.02)
    # integrating the gyro reproduces the orientation over 10 s
    rot = Rotation.from_quat(traj.quaternions)
    est = rot[0]
    for k in range(2000):
        est = est * Rotation.from_rotvec(0.5 * (gyro[k] + gyro[k + 1]) * traj.dt)
    assert (est.inv() * rot[2000]).magnitude() < math.radians(0.5)
    # accelerometer: specific force in the body frame = R^T (a + g)
    _, p0 = traj.interpolate(tq - 2 * traj.dt)
    Rm, p1 = traj.interpolate(tq)
    _, p2 = traj.interpolate(tq + 2 * traj.dt)
    a = (p0 - 2 * p1 + p2) / (2 * traj.dt) ** 2 + [0, 0, GRAVITY]
    np.testing.assert_allclose(accel[200:-200:50], np.einsum("nji,nj->ni", Rm, a), atol=0.3)


def test_imu_noise_seeded() -> None:
    tr = walk_trajectory(LOOP, 5.0, seed=0)
    a = simulate_imu(tr, seed=4, cfg=ImuConfig())
    b = simulate_imu(tr, seed=4, cfg=ImuConfig())
    ideal = simulate_imu(tr, seed=4, noise=False)
    np.testing.assert_array_equal(a.gyro, b.gyro)
    resid = a.gyro - ideal.gyro - a.gyro_bias
    assert 0.5 < np.std(resid) / (ImuConfig().gyro_noise * math.sqrt(200.0)) < 1.5
    assert np.abs(ideal.gyro_bias).max() == 0.0


def test_gait_config_validates() -> None:
    with pytest.raises(ValueError):
        GaitConfig(rate=100.0)


def test_walk_can_start_in_motion() -> None:
    """start_speed > 0: the recording begins with the operator already walking (no rest, no
    acceleration from zero), the span unchanged; a speed above the walk's is an error."""
    walk = {"waypoints": [[0, 0], [30, 0], [30, 8], [0, 8]], "speed": 1.2, "closed": True}
    standing = walk_trajectory(walk, 12.0, 3)
    moving = walk_trajectory(walk, 12.0, 3, GaitConfig(start_speed=1.0))
    np.testing.assert_array_equal(moving.times, standing.times)
    v = np.linalg.norm(np.diff(moving.positions[:, :2], axis=0), axis=1) * 200.0
    v0 = np.linalg.norm(np.diff(standing.positions[:, :2], axis=0), axis=1) * 200.0
    assert v[:40].mean() > 0.95 and v.min() > 0.9  # walking from the first sample on
    assert v0[:40].mean() < 0.05  # the default still starts standing
    with pytest.raises(ValueError, match="start speed"):
        walk_trajectory(walk, 5.0, 3, GaitConfig(start_speed=1.5))
