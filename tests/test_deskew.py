"""The gyro's rotation between knots (slam.trajectory.deskew) against known motions."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from slam.trajectory.deskew import deskew_table, gyro_attitude

RATE = 200.0


def _pitching(t: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """A torso yawing at 0.3 rad/s and pitching 1.5 deg at 1.8 Hz: attitude and body rates."""
    A, f, wz = np.radians(1.5), 1.8, 0.3
    def att(tt: np.ndarray) -> Rotation:
        return Rotation.from_euler("ZY", np.column_stack((wz * tt, A * np.sin(2 * np.pi * f * tt))))
    h = 1e-6
    R0, R1 = att(t - h), att(t + h)
    rates = (R0.inv() * R1).as_rotvec() / (2 * h)  # body-frame angular velocity
    return att(t), rates


def test_a_constant_rate_needs_no_correction_and_knots_get_none() -> None:
    t = np.arange(0.0, 2.0, 1.0 / RATE)
    gyro = np.tile([0.1, -0.4, 0.7], (t.size, 1))
    knots = np.arange(0.0, 2.0, 0.05)
    tab = deskew_table(t, gyro, True, knots)
    assert np.abs(tab.rotvec).max() < 1e-12
    assert np.abs(tab.at(knots[(knots >= t[0]) & (knots <= t[-1])])).max() == 0.0
    assert tab.apply(np.zeros((0, 3)), np.zeros(0)).shape == (0, 3)


def test_the_gyro_attitude_integrates_a_known_rotation() -> None:
    t = np.arange(0.0, 3.0, 1.0 / RATE)
    truth, rates = _pitching(t)
    Q = gyro_attitude(t, rates, instantaneous=True)
    err = (truth[0].inv() * truth).inv() * Q
    assert np.degrees(np.linalg.norm(err.as_rotvec(), axis=1)).max() < 1e-3


def test_geodesic_plus_deskew_follows_a_pitching_torso() -> None:
    t = np.arange(0.0, 4.0, 1.0 / RATE)
    _, rates = _pitching(t)
    knots = np.arange(0.0, 4.0, 0.05)
    tab = deskew_table(t, rates, True, knots)
    q = np.arange(0.1, 3.9, 0.0037)  # beam times between the samples
    Rq, _ = _pitching(q)
    Rk, _ = _pitching(knots)
    k = np.searchsorted(knots, q, side="right") - 1
    alpha = (q - knots[k]) / (knots[k + 1] - knots[k])
    geo = Rk[k] * Rotation.from_rotvec(alpha[:, None] * (Rk[k].inv() * Rk[k + 1]).as_rotvec())
    before = np.linalg.norm((Rq.inv() * geo).as_rotvec(), axis=1)
    after = np.linalg.norm((Rq.inv() * geo * Rotation.from_rotvec(tab.at(q))).as_rotvec(), axis=1)
    assert np.degrees(before).max() > 0.02  # the geodesic misses tens of mdeg
    assert after.max() < 0.02 * before.max()
    # a body point 20 m away: the correction moves it onto the true ray
    p = np.tile([20.0, 0.0, 0.0], (q.size, 1))
    moved = tab.apply(p, q)
    assert np.allclose(moved, p + np.cross(tab.at(q), p))
