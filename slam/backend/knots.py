"""The trajectory's variables: body poses at the knots (and, with an IMU, world velocities and
biases) with the factors that come with each new knot.

Added automatically: a datum prior on the first knot (the whole pose, or position and heading
when floor/ceiling priors define the vertical: ``datum="position_yaw"``), a weak prior on the
first interval's motion (without an IMU), a constant-velocity prior on every three consecutive
knots (:mod:`slam.motion`), and with an IMU the bias random walk of each interval plus priors on
the first velocity and bias; the ImuFactor of an interval comes with :meth:`Knots.add_imu`.

The constant-velocity, bias random-walk and IMU factors are rebuildable: once the window has left
their knots they are let go (:meth:`FactorGraph.release`) and built again, the same, when a batch
needs them; an ImuFactor from its interval's samples and the bias it was preintegrated at
(:class:`ImuSamples`: 56 B per sample, ~0.6 kB per knot at 200 Hz, instead of the factor's ~2.5 kB).
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X
from numpy.typing import ArrayLike, NDArray

from slam.backend.config import BackendConfig
from slam.backend.graph import FactorGraph, as_pose
from slam.motion import (
    ImuConfig,
    bias_random_walk_factor,
    constant_velocity_factor,
    datum_prior,
    initial_velocity_factor,
    preintegrate,
)
from slam.trajectory.interpolation import se3_exp, se3_log

FloatArray = NDArray[np.float64]


class ImuSamples:
    """Each IMU interval's samples (specific force, angular rate, dt: 7 floats a sample) and the
    bias its preintegration was linearised at, in growing arrays indexed by the interval's first
    knot, so that its ImuFactor can be built again bit for bit (:meth:`Knots.imu_factor`)."""

    def __init__(self) -> None:
        self.rows = np.empty((0, 7))
        self.n_rows = 0
        self.first = np.zeros(0, dtype=np.int64)  # per interval: its first row (-1: no samples)
        self.count = np.zeros(0, dtype=np.int64)
        self.bias = np.zeros((0, 6))  # per interval: the preintegration's bias (accelerometer, gyroscope)

    def add(self, interval: int, samples: FloatArray, bias: FloatArray) -> None:
        """The samples (M, 7) of ``interval`` and its bias (6,)."""
        m = samples.shape[0]
        if self.n_rows + m > self.rows.shape[0]:
            grown = np.empty((max(2 * self.rows.shape[0], self.n_rows + m, 1024), 7))
            grown[:self.n_rows] = self.rows[:self.n_rows]
            self.rows = grown
        if interval >= self.first.shape[0]:
            size = max(2 * self.first.shape[0], interval + 1, 256)
            self.first = np.concatenate((self.first, np.full(size - self.first.shape[0], -1, dtype=np.int64)))
            self.count = np.concatenate((self.count, np.zeros(size - self.count.shape[0], dtype=np.int64)))
            self.bias = np.concatenate((self.bias, np.zeros((size - self.bias.shape[0], 6))))
        self.rows[self.n_rows:self.n_rows + m] = samples
        self.first[interval], self.count[interval] = self.n_rows, m
        self.bias[interval] = bias
        self.n_rows += m

    def of(self, interval: int) -> tuple[FloatArray, FloatArray]:
        """The interval's samples (M, 7) and bias (6,)."""
        if interval >= self.first.shape[0] or self.first[interval] < 0:
            raise KeyError(f"no IMU samples for interval {interval}")
        a = int(self.first[interval])
        return self.rows[a:a + int(self.count[interval])], self.bias[interval]


class Knots:
    """Knot variables of a :class:`FactorGraph` and their priors, motion and IMU factors."""

    def __init__(self, graph: FactorGraph, config: BackendConfig) -> None:
        self.graph = graph
        self.config = config
        self._imu_intervals: set[int] = set()
        self.imu_samples = ImuSamples()
        graph.rebuild = self._rebuild

    def add_pose(self, time: float, T_world_body: ArrayLike, velocity_world: ArrayLike | None) -> int:
        """See :meth:`Backend.add_pose`."""
        T = as_pose(T_world_body, "T_world_body")
        t = float(time)
        times, values, add = self.graph.times, self.graph.values, self.graph.add_factor
        if not np.isfinite(t) or (times and t <= times[-1]):
            last = times[-1] if times else None
            raise ValueError(f"time: knots must be finite and increasing (last {last}, got {t})")
        i = len(times)
        times.append(t)
        values.insert(X(i), T)
        cfg = self.config
        if i == 0:
            s = cfg.datum_sigma
            if cfg.datum == "pose":
                add(datum_prior(X(0), T, s, s))
            else:
                sig = np.array([cfg.datum_tilt_sigma, cfg.datum_tilt_sigma, s, s, s, s])
                add(gtsam.PriorFactorPose3(X(0), T, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        elif i == 1 and cfg.imu is None:  # with an IMU, its factor determines knot 1
            dt = t - times[0]
            add(initial_velocity_factor(X(0), X(1), values.atPose3(X(0)).between(T), dt,
                                        *cfg.initial_velocity_sigmas))
        if i >= 2 and cfg.use_motion_prior:
            dt1, dt2 = times[i - 1] - times[i - 2], t - times[i - 1]
            add(constant_velocity_factor(X(i - 2), X(i - 1), X(i), dt1, dt2, cfg.motion), rebuildable=True)
        if cfg.imu is not None:
            self._add_imu_state(i, T, velocity_world, cfg.imu)
        return i

    def _add_imu_state(self, i: int, T: gtsam.Pose3, velocity_world: ArrayLike | None, imu: ImuConfig) -> None:
        """Velocity and bias variables of new knot ``i`` with their priors or random walk."""
        times, values, add = self.graph.times, self.graph.values, self.graph.add_factor
        if velocity_world is None:
            v = np.zeros(3)
            if i >= 1:
                v = (T.translation() - values.atPose3(X(i - 1)).translation()) / (times[i] - times[i - 1])
        else:
            v = np.asarray(velocity_world, dtype=float).reshape(3)
        values.insert(V(i), v)
        # a new bias starts at the last estimate: the preintegration is linearised there
        values.insert(B(i), values.atConstantBias(B(i - 1)) if i >= 1 else gtsam.imuBias.ConstantBias())
        if i == 0:
            add(gtsam.PriorFactorVector(V(0), v, gtsam.noiseModel.Isotropic.Sigma(3, imu.velocity_prior_sigma)))
            sa, sg = imu.bias_prior_sigmas
            add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(),
                                              gtsam.noiseModel.Diagonal.Sigmas(np.array([sa] * 3 + [sg] * 3))))
        else:
            add(bias_random_walk_factor(B(i - 1), B(i), times[i] - times[i - 1], imu), rebuildable=True)

    def add_velocity_prior(self, knot: int, velocity_world: ArrayLike, sigma: float) -> None:
        """See :meth:`Backend.add_velocity_prior`."""
        self._need_imu("add_velocity_prior")
        i = self.graph.check_knot(knot)
        v = np.asarray(velocity_world, dtype=float).reshape(3)
        self.graph.add_factor(gtsam.PriorFactorVector(V(i), v, gtsam.noiseModel.Isotropic.Sigma(3, float(sigma))))

    def add_imu(self, knot: int, accel_imu: ArrayLike, gyro_imu: ArrayLike, dt: ArrayLike) -> None:
        """See :meth:`Backend.add_imu`."""
        imu = self._need_imu("add_imu")
        i = self.graph.check_knot(knot, need_next=True)
        if i in self._imu_intervals:
            raise ValueError(f"knot: interval {i} already has IMU data")
        bias = self.graph.values.atConstantBias(B(i))
        pim = preintegrate(imu.params(), bias, accel_imu, gyro_imu, dt)  # checks the samples
        samples = np.column_stack((np.asarray(accel_imu, dtype=float), np.asarray(gyro_imu, dtype=float),
                                   np.asarray(dt, dtype=float)))
        self.imu_samples.add(i, samples, np.asarray(bias.vector(), dtype=float))
        self._imu_intervals.add(i)
        self.graph.add_factor(gtsam.ImuFactor(X(i), V(i), X(i + 1), V(i + 1), B(i), pim), rebuildable=True)

    def imu_factor(self, interval: int) -> gtsam.ImuFactor:
        """The ImuFactor of ``interval`` as :meth:`add_imu` made it (from its samples and bias)."""
        imu = self._need_imu("imu_factor")
        samples, b = self.imu_samples.of(interval)
        pim = preintegrate(imu.params(), gtsam.imuBias.ConstantBias(b[:3], b[3:]), samples[:, 0:3],
                           samples[:, 3:6], samples[:, 6])
        i = interval
        return gtsam.ImuFactor(X(i), V(i), X(i + 1), V(i + 1), B(i), pim)

    def _need_imu(self, what: str) -> ImuConfig:
        if self.config.imu is None:
            raise ValueError(f"{what}: the back end was configured without an IMU (config.imu)")
        return self.config.imu

    # ----------------------------------------------------------------- estimates
    def _rebuild(self, keys: tuple[int, ...]) -> gtsam.NonlinearFactor:
        """A released factor built again from its keys: an ImuFactor on (X(i), V(i), X(i+1), V(i+1),
        B(i)), the bias random walk on (B(i-1), B(i)), else the constant-velocity factor on (X(i-2),
        X(i-1), X(i))."""
        if is_imu_keys(keys):
            return self.imu_factor(gtsam.Symbol(keys[0]).index())
        if len(keys) == 2:  # (B(i-1), B(i)): the bias random walk
            i = gtsam.Symbol(keys[1]).index()
            times = self.graph.times
            return bias_random_walk_factor(B(i - 1), B(i), times[i] - times[i - 1], self._need_imu("bias random walk"))
        return self._motion_factor(keys)

    def _motion_factor(self, keys: tuple[int, ...]) -> gtsam.NonlinearFactor:
        """The constant-velocity factor on ``keys`` (X(i-2), X(i-1), X(i)) as :meth:`add_pose` made it."""
        i = gtsam.Symbol(keys[2]).index()
        times = self.graph.times
        return constant_velocity_factor(X(i - 2), X(i - 1), X(i), times[i - 1] - times[i - 2],
                                        times[i] - times[i - 1], self.config.motion)

    def poses(self) -> FloatArray:
        """Current ``T_world_body`` of every knot, (K, 4, 4)."""
        values = self.graph.values
        return np.array([values.atPose3(X(i)).matrix() for i in range(len(self.graph.times))])

    def pose(self, knot: int) -> FloatArray:
        """Current ``T_world_body`` (4, 4) of one knot."""
        return np.asarray(self.graph.values.atPose3(X(self.graph.check_knot(knot))).matrix())

    def velocities(self) -> FloatArray:
        """World-frame velocities (K, 3) [m/s] of the knots (IMU configurations only)."""
        self._need_imu("velocities")
        return np.array([self.graph.values.atVector(V(i)) for i in range(len(self.graph.times))])

    def velocity(self, knot: int) -> FloatArray:
        """World-frame velocity (3,) [m/s] of one knot (IMU configurations only)."""
        self._need_imu("velocity")
        return np.asarray(self.graph.values.atVector(V(self.graph.check_knot(knot))))

    def bias(self, knot: int) -> FloatArray:
        """IMU bias (6,) of one knot: accelerometer (m/s^2) then gyroscope (rad/s)."""
        self._need_imu("bias")
        return np.asarray(self.graph.values.atConstantBias(B(self.graph.check_knot(knot))).vector())

    def predict_pose(self, time: float) -> FloatArray:
        """Constant-velocity extrapolation (4, 4) of the trajectory to ``time`` >= the last knot."""
        times = self.graph.times
        K = len(times)
        if K == 0:
            raise ValueError("predict_pose: no knots yet")
        T_last = self.pose(K - 1)
        if K == 1:
            return T_last
        T_prev = self.pose(K - 2)
        xi = se3_log(np.linalg.inv(T_prev) @ T_last)
        a = (float(time) - times[-1]) / (times[-1] - times[-2])
        return np.asarray(T_last @ se3_exp(a * xi))


def is_imu_keys(keys: tuple[int, ...]) -> bool:
    """Whether ``keys`` are an ImuFactor's (X, V, X, V, B)."""
    return len(keys) == 5 and [chr(gtsam.Symbol(k).chr()) for k in keys] == ["x", "v", "x", "v", "b"]
