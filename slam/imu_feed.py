"""IMU samples for the pipeline: slicing them into knot intervals, predicting the next knot, and
the front end's IMU motion model (:class:`ImuMotion`, the IMU feature of ``slam.pipeline``).

The IMU frame is the body frame (the simulator's ``/imu`` and the usual backpack set-up; a
different ``frame_id`` is an input error). An interval ``[t_a, t_b)`` is cut at the sample
stamps into pieces: the one starting at the sample at or before ``t_a`` (clipped to ``t_a``) and
one per later sample before ``t_b`` (the last clipped to ``t_b``). Each piece gets a reading that
gtsam holds over it:

- ``instantaneous`` samples (a MEMS IMU's readings at their stamps, as the simulator writes
  them; ``imu.samples`` in the run config) get the value of the linear interpolant between samples at the piece's
  midpoint (the midpoint rule). Holding such a reading from its stamp to the next leads the
  motion by half a sample; on the office walk's noise-free IMU that alone made 8 s of dead
  reckoning from the true state 80-230 mm wrong (7-33 mm with the midpoint rule, most of it
  the start velocity taken from the sampled truth);
- ``held`` samples (the default; averages over the time to the next stamp) keep their own
  reading. See ``slam.config.ImuSection.samples`` for why this is still the default.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.frontend.knots import KnotMirror
from slam.frontend.motion_model import ConstantVelocity, MotionModel
from slam.frontend.ports import ImuSink
from slam.motion import ImuConfig, preintegrate
from slam.trajectory.interpolation import so3_exp

FloatArray = NDArray[np.float64]

MAX_GAP = 0.05  # s: a longer hole in the IMU stream inside a knot interval is an input error


@dataclass(frozen=True, eq=False)
class ImuMotionParams:
    """The front end's use of the IMU (``slam.params.imu_motion_params``): zero-velocity updates
    (``zupt``: the stance test over ``zupt_window`` s below ``zupt_threshold`` with the
    white-noise densities ``accel_noise``/``gyro_noise`` and ``gravity``, a prior of
    ``zupt_sigma`` m/s), and tracking against the IMU's prediction: ``increment_sigmas`` (6,: rad,
    m) on each knot interval's relative pose, translation directions whose information is below
    ``degenerate_ratio`` of the largest left to the IMU."""

    zupt: bool
    zupt_window: float
    zupt_threshold: float
    zupt_sigma: float
    accel_noise: float
    gyro_noise: float
    gravity: float
    increment_sigmas: FloatArray
    degenerate_ratio: float


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """Body-frame IMU samples: ``times`` (N,) s increasing, ``accel`` (N, 3) specific force
    m/s^2, ``gyro`` (N, 3) rad/s."""

    times: FloatArray
    accel: FloatArray
    gyro: FloatArray
    instantaneous: bool = False  # readings at their stamps (else: held until the next stamp)

    def __post_init__(self) -> None:
        n = self.times.shape[0]
        if self.accel.shape != (n, 3) or self.gyro.shape != (n, 3):
            raise ValueError(f"imu: need times (N,), accel (N,3), gyro (N,3); got {self.times.shape}, "
                             f"{self.accel.shape}, {self.gyro.shape}")
        if n < 2 or np.any(np.diff(self.times) <= 0):
            raise ValueError("imu: need at least two samples with increasing stamps")
        if not (np.all(np.isfinite(self.accel)) and np.all(np.isfinite(self.gyro))):
            raise ValueError("imu: samples must be finite")

    def covers(self, t_start: float, t_end: float) -> bool:
        """Whether the samples span ``[t_start, t_end]`` without a gap longer than ``MAX_GAP``."""
        if self.times[0] > t_start or self.times[-1] + MAX_GAP < t_end:
            return False
        i0 = max(int(np.searchsorted(self.times, t_start, side="right")) - 1, 0)
        i1 = int(np.searchsorted(self.times, t_end, side="left"))
        return bool(np.all(np.diff(self.times[i0 : i1 + 1]) <= MAX_GAP))

    def interval(self, t_a: float, t_b: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(accel (M, 3), gyro (M, 3), dt (M,)): the pieces of ``[t_a, t_b)`` and the readings
        gtsam holds over them (see the module doc)."""
        if not t_b > t_a:
            raise ValueError(f"imu interval: need t_b > t_a, got [{t_a}, {t_b}]")
        ok, acc, gyr, dt = _interval(self.times, self.accel, self.gyro, float(t_a), float(t_b), self.instantaneous,
                                     MAX_GAP)
        if not ok:
            raise ValueError(f"imu: no samples for {MAX_GAP * 1e3:.0f} ms or more within [{t_a:.3f}, {t_b:.3f}] s")
        return acc, gyr, dt


@nb.njit(cache=True)
def _interval(times: FloatArray, accel: FloatArray, gyro: FloatArray, t_a: float, t_b: float, instantaneous: bool,
              max_gap: float) -> tuple[bool, FloatArray, FloatArray, FloatArray]:  # pragma: no cover
    """:meth:`ImuSamples.interval` (False: a gap over ``max_gap``): the pieces' start and end
    clipped to the interval, the pieces of zero length left out, the readings held or (with
    ``instantaneous``) interpolated at each piece's midpoint, in one compiled pass (per element
    the operations of the numpy version it replaced)."""
    n = times.shape[0]
    i0 = max(int(np.searchsorted(times, t_a, side="right")) - 1, 0)
    i1 = max(int(np.searchsorted(times, t_b, side="left")), i0 + 1)
    m = i1 - i0
    start = np.empty(m)
    end = np.empty(m)
    ok = not times[i0] > t_a + max_gap
    kept = 0
    for q in range(m):
        start[q] = max(times[i0 + q], t_a)
        end[q] = min(times[i0 + q + 1] if q + 1 < m else t_b, t_b)
        d = end[q] - start[q]
        if d > max_gap:
            ok = False
        if d > 0:
            kept += 1
    acc = np.empty((kept, 3))
    gyr = np.empty((kept, 3))
    dt = np.empty(kept)
    if not ok:
        return False, acc, gyr, dt
    r = 0
    for q in range(m):
        d = end[q] - start[q]
        if not d > 0:
            continue
        dt[r] = d
        if not instantaneous:
            acc[r] = accel[i0 + q]
            gyr[r] = gyro[i0 + q]
        else:
            mid = 0.5 * (start[q] + end[q])
            j = min(max(int(np.searchsorted(times, mid, side="right")) - 1, 0), n - 2)
            w = min(max((mid - times[j]) / (times[j + 1] - times[j]), 0.0), 1.0)
            for c in range(3):
                acc[r, c] = (1.0 - w) * accel[j, c] + w * accel[j + 1, c]
                gyr[r, c] = (1.0 - w) * gyro[j, c] + w * gyro[j + 1, c]
        r += 1
    return True, acc, gyr, dt


def predict_navstate(
    config: ImuConfig,
    T_world_body: FloatArray,
    velocity_world: FloatArray,
    bias: FloatArray,
    samples: ImuSamples,
    t_a: float,
    t_b: float,
) -> tuple[FloatArray, FloatArray]:
    """Pose (4, 4) and velocity (3,) at ``t_b`` (world frame) from the state at ``t_a`` by
    integrating the IMU with ``bias`` (6,: accelerometer then gyroscope)."""
    a, g, dt = samples.interval(t_a, t_b)
    pim = preintegrate(config.params(), gtsam.imuBias.ConstantBias(bias[:3], bias[3:]), a, g, dt)
    state = gtsam.NavState(gtsam.Pose3(T_world_body), np.asarray(velocity_world, dtype=float))
    out = pim.predict(state, gtsam.imuBias.ConstantBias(bias[:3], bias[3:]))
    return np.asarray(out.pose().matrix()), np.asarray(out.velocity())


def shoe_statistic(samples: ImuSamples, t_a: float, t_b: float, accel_sigma: float, gyro_sigma: float,
                   gravity: float, up_body: FloatArray | None = None) -> float:
    """The SHOE stance statistic (Skog et al., 2010) of the samples in ``[t_a, t_b]``: the mean
    over samples of ``|f - g u|^2 / accel_sigma^2 + |w|^2 / gyro_sigma^2``, about 6 (its degrees
    of freedom) for a body at rest, far larger when walking. ``u`` is the world's up direction in
    the body frame, ``up_body`` when the orientation is known (then a smooth acceleration, which
    the mean direction would take for a tilt, counts as motion), else the mean specific-force
    direction. ``accel_sigma``/``gyro_sigma`` are per-sample noise (m/s^2, rad/s). NaN when the
    window holds fewer than three samples."""
    i0 = int(np.searchsorted(samples.times, t_a, side="left"))
    i1 = int(np.searchsorted(samples.times, t_b, side="right"))
    if i1 - i0 < 3:
        return float("nan")
    f = samples.accel[i0:i1]
    w = samples.gyro[i0:i1]
    m = f.mean(axis=0) if up_body is None else np.asarray(up_body, dtype=float)
    u = m / max(float(np.linalg.norm(m)), 1e-9)
    ra = f - gravity * u
    return float(np.mean(np.einsum("ij,ij->i", ra, ra) / accel_sigma**2 + np.einsum("ij,ij->i", w, w) / gyro_sigma**2))


def is_stationary(samples: ImuSamples, t: float, window: float, accel_sigma: float, gyro_sigma: float,
                  gravity: float, threshold: float, up_body: FloatArray | None = None) -> bool:
    """Whether the body is at rest around ``t`` (SHOE statistic over ``t +- window/2`` below
    ``threshold``)."""
    s = shoe_statistic(samples, t - 0.5 * window, t + 0.5 * window, accel_sigma, gyro_sigma, gravity, up_body)
    return bool(s < threshold)


class ImuMotion:
    """The front end's use of an IMU (``samples``, body frame): the next knot predicted by
    integrating it from the last one with the latest bias (``config``: its noise), its
    intervals and zero-velocity updates added to the back end (``sink``), the back end's
    velocities and bias mirrored, the first knot levelled (``params``)."""

    def __init__(self, samples: ImuSamples, config: ImuConfig, params: ImuMotionParams, sink: ImuSink) -> None:
        self.samples = samples
        self.config = config
        self.params = params
        self._sink = sink
        self._rate = 1.0 / float(np.median(np.diff(samples.times)))  # Hz, for the stance test's noise

    @property
    def increment_sigmas(self) -> FloatArray | None:
        return self.params.increment_sigmas

    @property
    def degenerate_ratio(self) -> float | None:
        return self.params.degenerate_ratio

    def initial_pose(self, t0: float) -> FloatArray:
        """The origin levelled by the mean specific force of the samples within 0.1 s of ``t0``
        (world z up along gravity), heading zero."""
        T = np.eye(4)
        near = (self.samples.times >= t0 - 0.1) & (self.samples.times <= t0 + 0.1)
        if not near.any():
            return T
        f = self.samples.accel[near].mean(axis=0)
        u = f / max(float(np.linalg.norm(f)), 1e-9)
        axis = np.cross(u, [0.0, 0.0, 1.0])
        s, c = float(np.linalg.norm(axis)), float(u[2])
        if s > 1e-12:
            T[:3, :3] = so3_exp(axis / s * np.arctan2(s, c))
        return T

    def start_moving(self, increments: list[FloatArray], sigmas: FloatArray | None) -> None:
        """Nothing beyond the first knot's velocity, which the runner gives it (the IMU then
        predicts the rest)."""
        return None

    def predict(self, knots: KnotMirror) -> tuple[FloatArray, FloatArray | None]:
        k = knots.n
        return predict_navstate(self.config, knots.T[k - 1], knots.V[k - 1], knots.bias, self.samples,
                                knots.time(k - 1), knots.time(k))

    def velocity(self, knots: KnotMirror, k: int) -> FloatArray | None:
        return knots.V[k]

    def add_factors(self, knots: KnotMirror, k: int) -> int:
        """The interval before knot ``k`` as preintegrated samples; a zero-velocity prior on the
        knot where the IMU says the operator stands still (returns 1 then, else 0)."""
        if k > 0:
            a, g, dt = self.samples.interval(knots.time(k - 1), knots.time(k))
            self._sink.add_imu(k - 1, a, g, dt)
        if self._at_rest(knots.time(k), knots.T[k][2, :3]):
            self._sink.add_velocity_prior(k, np.zeros(3), self.params.zupt_sigma)
            return 1
        return 0

    def _at_rest(self, t: float, up_body: FloatArray) -> bool:
        """Whether the IMU says the operator stands still at ``t``; ``up_body`` is world z in the
        body frame from the current pose estimate (the knot's third rotation row)."""
        p = self.params
        if not p.zupt:
            return False
        root_rate = np.sqrt(self._rate)  # densities -> per-sample noise
        return is_stationary(self.samples, t, p.zupt_window, p.accel_noise * root_rate, p.gyro_noise * root_rate,
                             p.gravity, p.zupt_threshold, up_body)

    def refresh(self, knots: KnotMirror, k0: int) -> None:
        """Velocities of knots ``k0`` on and the last knot's bias from the back end."""
        for k in range(k0, knots.n):
            knots.V[k] = self._sink.velocity(k)
        knots.bias = self._sink.bias(knots.n - 1)


def motion_model(samples: ImuSamples | None, config: ImuConfig | None, params: ImuMotionParams | None,
                 sink: ImuSink) -> MotionModel:
    """:class:`ImuMotion` with IMU samples (and their ``config``/``params``), else
    ``ConstantVelocity``."""
    if samples is None:
        return ConstantVelocity()
    if config is None or params is None:
        raise ValueError("imu: samples given without the IMU's configuration")
    return ImuMotion(samples, config, params, sink)
