"""The walking operator: ground-truth body poses ``T_world_body`` from a world's walk.

Frames: ``world`` is gravity aligned (z up); ``body`` is the rig (x forward, y left,
z up) with its origin at the reference (top, horizontal) scanner. The top scanner
of a backpack like ITC's sits on a mast just above the operator's head: we put it
``GaitConfig.height`` = 1.90 m above the floor (a 1.75 m operator, the scanner
~15 cm above the crown), which keeps it below 2.6-3 m ceilings with room to spare.

How the walk is built (all in seconds and metres):

1. The walk's waypoints are split into *legs* between rest points (the start,
   every stop, every sharp turn of more than ``pivot_angle`` where a person turns
   on the spot, the end). Inside a leg, corners are rounded with circular arcs of
   at most ``corner_radius``.
2. Along a leg the speed is limited by the walk speed, the lateral acceleration
   and the yaw rate on arcs (people slow down at corners) and by the
   longitudinal acceleration; it is zero at both ends of the leg.
3. Rests (stops, pivots) last their duration plus the time to turn on the spot.
4. Position and heading are resampled on a uniform clock at ``rate`` Hz and
   smoothed with a Gaussian (``smoothing`` s), which makes velocity and yaw rate
   continuous; the body yaw follows the smoothed heading.
5. Gait on top: vertical bob at the step frequency, lateral sway, roll and yaw
   at the stride frequency (half the step frequency), pitch at the step
   frequency; amplitudes scale with speed (none while standing), phases, exact
   frequency and slow amplitude modulation are drawn from the seed.

Poses between samples: positions linear, rotations slerp (``Trajectory.interpolate``);
at 200 Hz the linear-position error on the 3 cm bob is ~15 um.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from common.atomic import atomic_path
from common.config import StrictModel

FloatArray = NDArray[np.float64]


class GaitConfig(StrictModel):
    """Parameters of the walking operator (defaults: a relaxed indoor walk)."""

    height: float = Field(default=1.90, gt=0, description="reference scanner above the floor (m)")
    speed: float | None = Field(default=None, ge=0.3, le=2.0, description="walk speed (m/s); None: the world's")
    rate: float = Field(default=200.0, ge=200.0, description="pose sample rate (Hz)")
    step_frequency: float = Field(default=1.9, gt=0, description="steps per second at the walk speed (Hz)")
    bob: float = Field(default=0.03, ge=0, description="vertical bob, peak to peak (m)")
    sway: float = Field(default=0.02, ge=0, description="lateral sway amplitude (m)")
    roll: float = Field(default=math.radians(2.0), ge=0, description="roll amplitude at stride frequency (rad)")
    pitch: float = Field(default=math.radians(1.5), ge=0, description="pitch amplitude at step frequency (rad)")
    yaw: float = Field(default=math.radians(1.5), ge=0, description="yaw oscillation amplitude (rad)")
    lean: float = Field(default=math.radians(1.0), ge=0, description="slow random roll/pitch wander, std (rad)")
    variation: float = Field(default=0.1, ge=0, lt=1, description="relative random amplitude/frequency variation")
    corner_radius: float = Field(default=0.8, gt=0, description="max radius of rounded corners (m)")
    lateral_accel: float = Field(default=0.8, gt=0, description="max lateral acceleration at corners (m/s^2)")
    yaw_rate: float = Field(default=math.radians(60.0), gt=0, description="max yaw rate walking a corner (rad/s)")
    pivot_angle: float = Field(default=math.radians(100.0), gt=0, description="turns sharper than this are on the spot (rad)")
    pivot_rate: float = Field(default=math.radians(90.0), gt=0, description="yaw rate turning on the spot (rad/s)")
    accel: float = Field(default=0.6, gt=0, description="longitudinal acceleration (m/s^2)")
    smoothing: float = Field(default=0.15, gt=0, description="Gaussian smoothing of position and heading (s)")
    start_rest: float = Field(default=1.0, ge=0, description="standing still before walking (s)")
    start_speed: float = Field(
        default=0.0, ge=0, le=2.0,
        description="speed at the first sample (m/s): 0 starts standing (start_rest); above 0 the "
        "recording begins as the operator, already walking, passes this speed (start_rest ignored)",
    )
    stops: bool = Field(default=True, description="honour the walk's stops")


# ---------------------------------------------------------------------------
# The trajectory record and its interpolation


@numba.njit(cache=True, inline="always")
def _rodrigues(wx: float, wy: float, wz: float, out: Any) -> None:
    """exp of the rotation vector w into the 3x3 ``out``."""
    th2 = wx * wx + wy * wy + wz * wz
    if th2 < 1e-16:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    out[0, 0] = 1.0 - b * (wy * wy + wz * wz)
    out[0, 1] = -a * wz + b * wx * wy
    out[0, 2] = a * wy + b * wx * wz
    out[1, 0] = a * wz + b * wx * wy
    out[1, 1] = 1.0 - b * (wx * wx + wz * wz)
    out[1, 2] = -a * wx + b * wy * wz
    out[2, 0] = -a * wy + b * wx * wz
    out[2, 1] = a * wx + b * wy * wz
    out[2, 2] = 1.0 - b * (wx * wx + wy * wy)


@numba.njit(cache=True)
def pose_at(
    t: float,
    t0: float,
    dt: float,
    rotations: Any,
    rotvecs: Any,
    positions: Any,
    R_out: Any,
    t_out: Any,
    tmp: Any,
) -> None:
    """``T_world_body(t)`` on a uniform clock: slerp of rotations, linear positions.

    ``rotvecs[k]`` is ``log(R_k^T R_{k+1})`` (body frame); ``R_out``/``t_out`` receive
    the pose; ``tmp`` is a 3x3 scratch array. ``t`` must lie in the sampled span.
    """
    n = positions.shape[0]
    u = (t - t0) / dt
    k = math.floor(u)
    if k < 0:
        k = 0
    if k > n - 2:
        k = n - 2
    s = u - k
    _rodrigues(s * rotvecs[k, 0], s * rotvecs[k, 1], s * rotvecs[k, 2], tmp)
    for i in range(3):
        for j in range(3):
            R_out[i, j] = (
                rotations[k, i, 0] * tmp[0, j] + rotations[k, i, 1] * tmp[1, j] + rotations[k, i, 2] * tmp[2, j]
            )
        t_out[i] = (1.0 - s) * positions[k, i] + s * positions[k + 1, i]


@numba.njit(cache=True)
def _interpolate_many(times: Any, t0: float, dt: float, rotations: Any, rotvecs: Any, positions: Any) -> Any:
    m = times.shape[0]
    R = np.empty((m, 3, 3))
    t = np.empty((m, 3))
    tmp = np.empty((3, 3))
    for i in range(m):
        pose_at(times[i], t0, dt, rotations, rotvecs, positions, R[i], t[i], tmp)
    return R, t


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Ground-truth poses ``T_world_body`` on a uniform clock.

    ``times`` (N,) s, uniformly spaced; ``positions`` (N, 3) world frame;
    ``quaternions`` (N, 4) xyzw, rotating body into world.
    """

    times: FloatArray
    positions: FloatArray
    quaternions: FloatArray

    def __post_init__(self) -> None:
        n = self.times.shape[0]
        if n < 2 or self.positions.shape != (n, 3) or self.quaternions.shape != (n, 4):
            raise ValueError(
                f"Trajectory needs >= 2 samples with positions (N,3) and quaternions (N,4); got times {self.times.shape}, "
                f"positions {self.positions.shape}, quaternions {self.quaternions.shape}"
            )
        steps = np.diff(self.times)
        if steps[0] <= 0 or not np.allclose(steps, steps[0], rtol=1e-6, atol=1e-6):
            raise ValueError("Trajectory.times must be strictly increasing and uniformly spaced (to 1 us)")

    @property
    def dt(self) -> float:
        return float((self.times[-1] - self.times[0]) / (self.times.shape[0] - 1))

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def rotations(self) -> FloatArray:
        """(N, 3, 3) rotation matrices ``R_world_body``."""
        return self._cache()[0]

    def rotvecs(self) -> FloatArray:
        """(N-1, 3) ``log(R_k^T R_{k+1})`` in the body frame at sample k."""
        return self._cache()[1]

    def _cache(self) -> tuple[FloatArray, FloatArray]:
        c = self.__dict__.get("_kin")
        if c is None:
            rot = Rotation.from_quat(self.quaternions)
            R = np.ascontiguousarray(rot.as_matrix())
            rv = np.ascontiguousarray((rot[:-1].inv() * rot[1:]).as_rotvec())
            c = (R, rv)
            object.__setattr__(self, "_kin", c)
        return c

    def kernel_args(self) -> tuple[float, float, FloatArray, FloatArray, FloatArray]:
        """Arguments of ``pose_at`` after ``t``: (t0, dt, rotations, rotvecs, positions)."""
        R, rv = self._cache()
        return float(self.times[0]), self.dt, R, rv, np.ascontiguousarray(self.positions)

    def interpolate(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Poses at ``times``: (R (M,3,3), t (M,3)), ``R_world_body`` and ``t_world_body``.

        Rotations slerp, positions linear between samples; exact at the samples.
        """
        tq = np.ascontiguousarray(np.atleast_1d(np.asarray(times, dtype=np.float64)))
        eps = 1e-9 * max(1.0, abs(float(self.times[-1])))
        if tq.size and (tq.min() < self.times[0] - eps or tq.max() > self.times[-1] + eps):
            raise ValueError(
                f"interpolate: times [{tq.min():.6f}, {tq.max():.6f}] outside the trajectory "
                f"[{self.times[0]:.6f}, {self.times[-1]:.6f}]"
            )
        R, t = _interpolate_many(tq, *self.kernel_args())
        return R, t

    def write_tum(self, path: str | Path, time_offset: float = 0.0) -> None:
        """Write ``t tx ty tz qx qy qz qw`` (T_world_body) atomically; times + ``time_offset``."""
        data = np.column_stack((self.times + time_offset, self.positions, self.quaternions))
        with atomic_path(path) as tmp, tmp.open("w") as f:
            np.savetxt(f, data, fmt="%.9f")


# ---------------------------------------------------------------------------
# Building the walk


@dataclass(frozen=True)
class _Walk:
    waypoints: FloatArray
    speed: float
    stops: dict[int, float]
    closed: bool


def _walk_from(walk: Any) -> _Walk:
    def get(key: str, default: Any = None) -> Any:
        if isinstance(walk, Mapping):
            return walk.get(key, default)
        return getattr(walk, key, default)

    wp = np.asarray(get("waypoints"), dtype=np.float64)
    if wp.ndim != 2 or wp.shape[1] != 2 or wp.shape[0] < 2:
        raise ValueError(f"walk.waypoints must be a list of >= 2 [x, y] points, got shape {wp.shape}")
    if np.any(np.linalg.norm(np.diff(wp, axis=0), axis=1) < 1e-6):
        raise ValueError("walk.waypoints has two identical consecutive points")
    stops: dict[int, float] = {}
    for s in get("stops", None) or []:
        w = int(s["waypoint"] if isinstance(s, Mapping) else s.waypoint)
        d = float(s["duration"] if isinstance(s, Mapping) else s.duration)
        if not 0 <= w < len(wp):
            raise ValueError(f"walk.stops: waypoint {w} is not one of the {len(wp)} waypoints")
        stops[w] = stops.get(w, 0.0) + d
    return _Walk(wp, float(get("speed", 1.2)), stops, bool(get("closed", False)))


def _waypoint_sequence(walk: _Walk) -> Iterator[int]:
    """Waypoint indices in walking order, forever: loops if closed, back and forth otherwise."""
    n = len(walk.waypoints)
    if walk.closed:
        k = 0
        while True:
            yield k % n
            k += 1
    else:
        order = list(range(n)) + list(range(n - 2, 0, -1))
        k = 0
        while True:
            yield order[k % len(order)]
            k += 1


def _turn(u1: FloatArray, u2: FloatArray) -> float:
    return math.atan2(u1[0] * u2[1] - u1[1] * u2[0], u1[0] * u2[0] + u1[1] * u2[1])


def _leg_samples(vertices: FloatArray, cfg: GaitConfig, ds: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Dense samples of a leg with rounded corners: xy (M,2), heading (M,), curvature (M,)."""
    pts: list[FloatArray] = []
    hd: list[FloatArray] = []
    kap: list[FloatArray] = []
    seg = np.diff(vertices, axis=0)
    lens = np.linalg.norm(seg, axis=1)
    units = seg / lens[:, None]
    cursor = vertices[0].copy()

    def straight(a: FloatArray, b: FloatArray, u: FloatArray) -> None:
        L = float(np.linalg.norm(b - a))
        if L <= 0:
            return
        n = max(1, math.ceil(L / ds))
        s = np.arange(n) * (L / n)
        pts.append(a + s[:, None] * u)
        hd.append(np.full(n, math.atan2(u[1], u[0])))
        kap.append(np.zeros(n))

    for i in range(1, len(vertices) - 1):
        u1, u2 = units[i - 1], units[i]
        th = _turn(u1, u2)
        if abs(th) < 1e-9:
            continue
        tan_len_max = 0.45 * min(lens[i - 1], lens[i])
        r = min(cfg.corner_radius, tan_len_max / math.tan(abs(th) / 2))
        T = r * math.tan(abs(th) / 2)
        p_in = vertices[i] - T * u1
        straight(cursor, p_in, u1)
        left = np.array([-u1[1], u1[0]]) * math.copysign(1.0, th)
        center = p_in + r * left
        arc = r * abs(th)
        n = max(1, math.ceil(arc / ds))
        phi = np.arange(n) * (th / n)
        h0 = math.atan2(u1[1], u1[0])
        rel = p_in - center
        c, s = np.cos(phi), np.sin(phi)
        pts.append(center + np.column_stack((c * rel[0] - s * rel[1], s * rel[0] + c * rel[1])))
        hd.append(h0 + phi)
        kap.append(np.full(n, 1.0 / r))
        cursor = vertices[i] + T * u2
    straight(cursor, vertices[-1], units[-1])
    pts.append(vertices[-1][None, :])
    hd.append(np.array([math.atan2(units[-1][1], units[-1][0])]))
    kap.append(np.zeros(1))
    return np.concatenate(pts), np.unwrap(np.concatenate(hd)), np.concatenate(kap)


def _leg_times(xy: FloatArray, kappa: FloatArray, speed: float, cfg: GaitConfig) -> FloatArray:
    """Time at each sample of a leg that starts and ends at rest (speed-limited, accel-limited)."""
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    with np.errstate(divide="ignore"):
        v_lim = np.minimum(speed, np.minimum(np.sqrt(cfg.lateral_accel / kappa), cfg.yaw_rate / kappa))
    v = _accel_limit(v_lim, step, cfg.accel)
    dt = 2.0 * step / np.maximum(v[:-1] + v[1:], 1e-9)
    return np.concatenate(([0.0], np.cumsum(dt)))


@numba.njit(cache=True)
def _accel_limit(v_lim: Any, step: Any, accel: float) -> Any:
    n = v_lim.shape[0]
    v = v_lim.copy()
    v[0] = 0.0
    v[n - 1] = 0.0
    for i in range(1, n):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2.0 * accel * step[i - 1]))
    for i in range(n - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * accel * step[i]))
    return v


def _smooth_noise(rng: np.random.Generator, n: int, sigma_samples: float) -> FloatArray:
    """Zero-mean, unit-variance, Gaussian-correlated noise of length n (correlation
    ``sigma_samples``), scaled by the filter's theoretical gain, not the sample std."""
    x = gaussian_filter1d(rng.standard_normal(n + 8 * int(sigma_samples) + 1), sigma_samples, mode="wrap")
    return x[:n] * math.sqrt(2.0 * math.sqrt(math.pi) * sigma_samples)


def walk_trajectory(walk: Any, duration: float, seed: int, gait: GaitConfig | None = None, floor_z: float = 0.0) -> Trajectory:
    """Ground-truth ``T_world_body`` for ``duration`` s of walking ``walk`` (times from 0).

    ``walk`` has ``waypoints`` [[x, y], ...] (world frame), ``speed`` (m/s), ``stops``
    [{waypoint, duration}] and ``closed`` (loop; otherwise back and forth), as a
    mapping or an object. Same inputs and seed, same trajectory.
    """
    cfg = gait or GaitConfig()
    if not duration > 0:
        raise ValueError(f"duration must be > 0 s, got {duration}")
    w = _walk_from(walk)
    speed = cfg.speed if cfg.speed is not None else w.speed
    if not 0.1 <= speed <= 3.0:
        raise ValueError(f"walk speed {speed} m/s is not a walking speed (0.1-3 m/s)")
    if cfg.start_speed > speed:
        raise ValueError(f"start speed {cfg.start_speed} m/s is above the walk speed {speed} m/s")
    # a walk that starts in motion is the tail of a longer one: generate the lead-in (standing
    # up to speed) as well and cut it off below
    lead_max = 0.0
    if cfg.start_speed > 0:
        cfg = cfg.model_copy(update={"start_rest": 0.0})
        lead_max = math.pi / cfg.pivot_rate + speed / cfg.accel + 8.0 * cfg.smoothing + 1.0
        duration = duration + lead_max
    rng = np.random.default_rng(seed)
    ds = 0.01

    # knots (time, x, y, heading) of the whole walk, legs and rests
    seq = _waypoint_sequence(w)
    first = next(seq)
    knots_t: list[FloatArray] = []
    knots_xy: list[FloatArray] = []
    knots_h: list[FloatArray] = []
    wp = w.waypoints
    t_now = 0.0
    leg = [first]
    h_prev: float | None = None
    rest = cfg.start_rest
    leg_len = 0.0
    horizon = duration + 1.0
    while t_now < horizon:
        nxt = next(seq)
        leg.append(nxt)
        if np.allclose(wp[leg[-1]], wp[leg[-2]]):
            leg.pop()
            continue
        leg_len += float(np.linalg.norm(wp[leg[-1]] - wp[leg[-2]]))
        long_enough = leg_len > speed * (horizon - t_now) + 5.0
        stop_here = cfg.stops and w.stops.get(nxt, 0.0) > 0
        pivot = False
        if not stop_here:
            follow = _following(w, leg)
            if follow is not None:
                u1 = wp[nxt] - wp[leg[-2]]
                u2 = wp[follow] - wp[nxt]
                pivot = abs(_turn(u1, u2)) > cfg.pivot_angle
        if not (stop_here or pivot or long_enough):
            continue
        verts = wp[leg]
        xy, hd, kap = _leg_samples(verts, cfg, ds)
        tt = _leg_times(xy, kap, speed, cfg)
        if h_prev is None:
            h_prev = float(hd[0])
        # the rest before this leg: stand, turning on the spot from h_prev to the leg's heading
        dh = (float(hd[0]) - h_prev + math.pi) % (2 * math.pi) - math.pi
        rest_time = rest + abs(dh) / cfg.pivot_rate
        if rest_time > 0:
            n_r = max(2, math.ceil(rest_time / 0.01))
            tr = np.linspace(0.0, rest_time, n_r, endpoint=False)
            knots_t.append(t_now + tr)
            knots_xy.append(np.repeat(verts[:1], n_r, axis=0))
            knots_h.append(h_prev + dh * tr / rest_time)
            t_now += rest_time
        hd = hd - float(hd[0]) + (h_prev + dh)
        knots_t.append(t_now + tt[:-1])
        knots_xy.append(xy[:-1])
        knots_h.append(hd[:-1])
        t_now += float(tt[-1])
        h_prev = float(hd[-1])
        rest = w.stops.get(nxt, 0.0) if stop_here else 0.0
        leg = [nxt]
        leg_len = 0.0
    knots_t.append(np.array([t_now, t_now + 10.0]))
    knots_xy.append(np.repeat(wp[leg[-1]][None, :], 2, axis=0))
    knots_h.append(np.array([h_prev, h_prev]) if h_prev is not None else np.zeros(2))
    kt = np.concatenate(knots_t)
    kxy = np.concatenate(knots_xy)
    kh = np.concatenate(knots_h)

    # uniform clock, smoothing
    n = math.ceil((duration + 0.5) * cfg.rate) + 1
    times = np.arange(n) / cfg.rate
    sig = cfg.smoothing * cfg.rate
    pad = int(4 * sig) + 1
    tp = np.arange(-pad, n + pad) / cfg.rate
    x = gaussian_filter1d(np.interp(tp, kt, kxy[:, 0]), sig, mode="nearest")[pad:-pad]
    y = gaussian_filter1d(np.interp(tp, kt, kxy[:, 1]), sig, mode="nearest")[pad:-pad]
    heading = gaussian_filter1d(np.interp(tp, kt, kh), sig, mode="nearest")[pad:-pad]
    v = np.hypot(np.gradient(x, times), np.gradient(y, times))

    # gait: amplitude follows speed; frequency, phases and slow modulation from the seed
    var = cfg.variation
    g = np.clip(v / speed, 0.0, 1.0)
    f_step = cfg.step_frequency * (1.0 + 0.3 * var * rng.uniform(-1, 1))
    cadence = f_step * (0.5 + 0.5 * g) * (1.0 + 0.2 * var * _smooth_noise(rng, n, 2.0 * cfg.rate))
    phase = 2 * math.pi * np.cumsum(cadence) / cfg.rate + rng.uniform(0, 2 * math.pi)
    ph = rng.uniform(0, 2 * math.pi, size=4)

    def amp(a: float) -> FloatArray:
        scale = 1.0 + var * rng.uniform(-1, 1)
        return a * scale * g * (1.0 + var * np.clip(_smooth_noise(rng, n, 1.0 * cfg.rate), -2.5, 2.5))

    bob = amp(cfg.bob / 2) * np.cos(phase)
    sway = amp(cfg.sway) * np.sin(phase / 2 + ph[0])
    roll = amp(cfg.roll) * np.sin(phase / 2 + ph[0] + 0.3) + cfg.lean * _smooth_noise(rng, n, 1.5 * cfg.rate) * 0.5
    pitch = amp(cfg.pitch) * np.cos(phase + ph[1]) + cfg.lean * _smooth_noise(rng, n, 1.5 * cfg.rate) * 0.5
    yaw = heading + amp(cfg.yaw) * np.sin(phase / 2 + ph[2])

    ch, sh = np.cos(heading), np.sin(heading)
    positions = np.column_stack((x - sh * sway, y + ch * sway, floor_z + cfg.height + bob))
    quats = Rotation.from_euler("ZYX", np.column_stack((yaw, pitch, roll))).as_quat()
    if lead_max > 0:
        m = n - math.ceil(lead_max * cfg.rate)
        fast = np.flatnonzero(v[: n - m] >= cfg.start_speed)
        if fast.size == 0:
            raise ValueError(f"the walk does not reach the start speed {cfg.start_speed} m/s within "
                             f"its first {lead_max:.1f} s")
        i0 = int(fast[0])
        sl = slice(i0, i0 + m)
        return Trajectory(times[:m], positions[sl], np.ascontiguousarray(quats[sl]))
    return Trajectory(times, positions, np.ascontiguousarray(quats))


def _following(w: _Walk, leg: Sequence[int]) -> int | None:
    """The waypoint after ``leg[-1]`` in walking order, given where the leg came from."""
    n = len(w.waypoints)
    cur = leg[-1]
    prev = leg[-2]
    if w.closed:
        return (cur + 1) % n
    if cur == n - 1:
        return n - 2
    if cur == 0:
        return 1
    return cur + 1 if prev < cur else cur - 1
