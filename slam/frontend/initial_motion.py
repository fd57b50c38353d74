"""The body's motion at the start of a recording, from its first scans, before any plane exists.

A recording may start while the operator already walks. The front end predicts each knot from
the ones before it (constant velocity, or the IMU from the first knot's velocity); starting at
rest when the rig moves at 1 m/s places the first scans metres from where they were taken, the
first planes are made from smeared segments and the trajectory runs away. Even the right start
velocity is not enough: a walker's speed changes by 10-20 % within a second, a new plane's
segments must agree within millimetres (``frontend.coplanar_distance``), and until a plane
across the walking direction exists nothing corrects the prediction along it. So before the
first knot is processed, the scans of the first ``window`` seconds of one scanner are
registered in its scan plane (2D lidar odometry), and the knots of that time are predicted with
the motion they give.

The scanner is the one whose scan plane is nearest the body's horizontal (a walker moves and
turns in it); its segments' points (scanner frame, every point at its own beam time) are used.

1. **At rest or moving** (:func:`register`): one constant 2D twist ``xi = (v_x, v_y, w)`` of
   the scanner frame over the first ``REST_SPAN`` s, ``p(t0) = Exp(xi (t - t0)) p``, fitted by
   Gauss-Newton with Huber weights to the distances of the later scans' points from the lines of
   the first scan's segments, matched segment to segment (nearly parallel, near, overlapping),
   coarse to fine (the gates shrink as the scans reach further in time: at 1 m/s the scans of
   the first 0.1 s lie within 10 cm of the first). A translation direction the matched lines do
   not observe (:func:`unobserved_direction`: a corridor's parallel walls say nothing about the
   walk along them) is not trusted: the twist's component along it is set to zero (rest, the
   assumption without the initialiser), whatever the fit made of a few stray matches. Below
   ``min_speed`` and ``min_rate`` the start counts as at rest, and the front end takes exactly
   the standstill path.
2. **Odometry** (:func:`odometry`), when moving: scan after scan, the scanner's pose at its stamp
   against the lines of the first scan and of the last ``MAP_SCANS`` scans, each scan deskewed
   with the twist from the previous pose to its own; along a direction its lines do not
   observe, the pose stays at the constant-velocity prediction (which, from the rest test,
   does not move along it).
3. The knots' predicted motions (:func:`knot_increments`): the scanner's poses interpolated at
   the knot times, lifted into the body frame by the scanner's mounting
   (``T_body_scanner``); directions out of the scan plane (height, roll, pitch) are left at
   rest, for the planes to correct, and so is an unobserved direction in it: tracking holds the
   knots loosely along it (``UNOBSERVED_SIGMA``), for the IMU or the door edges to correct.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam.frontend.observations import ScanSegments
from slam.trajectory.interpolation import adjoint

FloatArray = NDArray[np.float64]
Residuals = Callable[[FloatArray], FloatArray]

REST_SPAN = 0.3  # s of scans (at most the window) the rest test's constant twist is fitted to
# coarse to fine: the scans up to this many seconds after the first, with this distance gate (m)
# and angle gate (deg) for matching a segment to a line of the first scan
STAGES = ((0.08, 0.15, 10.0), (0.16, 0.06, 5.0), (np.inf, 0.03, 3.0))
ITERATIONS = 6
MIN_POINTS = 10  # segments with fewer points are not used
MIN_MATCHES = 4  # matched segments a fit needs
OVERLAP_MARGIN = 0.3  # m, a matched segment's end points lie within the target's extent grown by this
HUBER = 0.01  # m, Huber width of the point-to-line distances (at least the range noise)
SE_SIGMAS = 3.0  # a start is moving only when its speed or turn rate is this many standard errors from rest
PRIOR_SIGMAS = np.array([3.0, 3.0, 3.0])  # m/s, m/s, rad/s: the rest test's weak prior towards rest
MAP_SCANS = 4  # odometry: the previous scans whose lines a scan is registered against (with the first)
ODOMETRY_GATE = (0.03, 3.0)  # m, deg: odometry's matching gates
ODOMETRY_PRIOR = np.array([0.05, 0.05, 0.05])  # m, m, rad: the hold on the constant-velocity prediction
# sigmas (rad, m; scanner frame) of a knot interval's motion from the odometry, for tracking: tight in
# the scan plane (rotation about its z, translation along x, y), loose out of it (a walker's bob and
# sway, which the odometry does not see)
ODOMETRY_SIGMAS = np.array([np.radians(1.0), np.radians(1.0), np.radians(0.05), 0.001, 0.001, 0.02])
# a translation direction is observed when the matched segments' normals project on it as much as this
# many segments square to it (the sum of (n . e)^2 over the matches, each segment counted once): in the
# rest test over its scans (a wall across the walk is in each of them), in the odometry in one scan
MIN_ACROSS = 3.0
ODOMETRY_MIN_ACROSS = 0.8
UNOBSERVED_SIGMA = 0.05  # m per knot interval: the hold of the odometry's motion along an unobserved direction
HOLD_WEIGHT = 1e10  # prior weight (units of the Huber width^2) that keeps an unobserved component at its prior


@dataclass(frozen=True, eq=False)
class InitialMotionParams:
    """``window`` s of scans registered (0: the walk starts at rest); the start counts as at
    rest below ``min_speed`` (m/s) and ``min_rate`` (rad/s), stated for a scanner of
    ``reference_sigma`` (m) range noise and raised in proportion for a noisier one. With
    ``rest_odometry`` a start at rest also gets the window's odometry as its knots' motions: the
    walker who stands for half a second and then sets off moves before the planes that observe
    the walking direction exist (a far end wall seen by the level scanner alone needs several
    scans from one pose to become a plane)."""

    window: float
    min_speed: float
    min_rate: float
    reference_sigma: float
    rest_odometry: bool  # a start at rest: the window's odometry still predicts its knots


@dataclass(frozen=True, eq=False)
class InitialMotion:
    """How the walk starts: ``moving`` or at rest, the start's body twist ``twist_body`` (6,:
    rad/s then m/s, body frame, gtsam's order; zeros at rest) and, when moving, the predicted
    motion of the first knot intervals (``increments``: (4, 4) each, ``T_body(k)^-1 T_body(k +
    1)``) with the sigmas (6,: rad, m, body frame) tracking holds them with (``increment_sigmas``). ``scanner`` is the index registered (-1: none), ``twist_scan`` its 2D twist (v_x, v_y
    m/s, w rad/s), ``matches`` the rest test's matched segments and ``rms`` its points' RMS
    distance (m); ``scans`` the scans of the odometry; ``unobserved`` the rest test's unobserved
    translation direction (2,: unit, the first scan's scanner frame; None: both observed) and
    ``unobserved_scans`` the odometry's scans with one."""

    twist_body: FloatArray
    moving: bool
    scanner: int = -1
    twist_scan: FloatArray | None = None
    matches: int = 0
    rms: float = float("nan")
    increments: list[FloatArray] = field(default_factory=list)
    increment_sigmas: FloatArray | None = None
    scans: int = 0
    unobserved: FloatArray | None = None
    unobserved_scans: int = 0

    @staticmethod
    def rest(scanner: int = -1) -> InitialMotion:
        return InitialMotion(np.zeros(6), False, scanner)

    def as_dict(self) -> dict[str, object]:
        """For the run's summary."""
        return {
            "moving": self.moving,
            "speed": float(np.linalg.norm(self.twist_body[3:])),
            "yaw_rate_deg": float(np.degrees(np.linalg.norm(self.twist_body[:3]))),
            "scanner": self.scanner,
            "matches": self.matches,
            "rms": None if not np.isfinite(self.rms) else self.rms,
            "odometry_knots": len(self.increments),
            "odometry_scans": self.scans,
            "unobserved_direction": None if self.unobserved is None else [float(x) for x in self.unobserved],
            "odometry_unobserved_scans": self.unobserved_scans,
        }


def level_scanner(T_body_scanner: list[FloatArray]) -> int:
    """The scanner whose scan plane is nearest the body's horizontal (its z axis along body z)."""
    return int(np.argmax([abs(float(T[2, 2])) for T in T_body_scanner]))


# ---- SE(2) ------------------------------------------------------------------------------------


def se2(x: float, y: float, th: float) -> FloatArray:
    """The pose (3, 3) of position (x, y) m and heading ``th`` rad."""
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_exp(xi: FloatArray) -> FloatArray:
    """``Exp(xi)`` (3, 3) of a twist (v_x, v_y, w) over unit time."""
    th = float(xi[2])
    if abs(th) < 1e-9:
        a, b = 1.0 - th * th / 6.0, th / 2.0
    else:
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th
    return se2(a * xi[0] - b * xi[1], b * xi[0] + a * xi[1], th)


def se2_log(P: FloatArray) -> FloatArray:
    """The twist (v_x, v_y, w) whose ``Exp`` is ``P`` (3, 3)."""
    th = float(np.arctan2(P[1, 0], P[0, 0]))
    if abs(th) < 1e-9:
        a, b = 1.0 - th * th / 6.0, th / 2.0
    else:
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th
    det = a * a + b * b
    x, y = P[0, 2], P[1, 2]
    return np.array([(a * x + b * y) / det, (-b * x + a * y) / det, th])


def se2_place(points: FloatArray, dt: FloatArray, xi: FloatArray, P: FloatArray | None = None) -> FloatArray:
    """Points (m, 2) taken ``dt`` (m,) s after a reference time, moved into the frame at that
    time by the constant twist ``xi`` (v_x, v_y, w), ``Exp(xi dt) p``, then by the pose ``P``
    (3, 3) when given."""
    th = xi[2] * dt
    c, s = np.cos(th), np.sin(th)
    small = np.abs(th) < 1e-9
    safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th * th / 6.0, s / safe)  # sin(th) / th
    b = np.where(small, th / 2.0, (1.0 - c) / safe)  # (1 - cos(th)) / th
    vx, vy = xi[0] * dt, xi[1] * dt
    x, y = points[:, 0], points[:, 1]
    qx = c * x - s * y + a * vx - b * vy
    qy = s * x + c * y + b * vx + a * vy
    if P is None:
        return np.column_stack((qx, qy))
    return np.column_stack((P[0, 0] * qx + P[0, 1] * qy + P[0, 2], P[1, 0] * qx + P[1, 1] * qy + P[1, 2]))


def lift(P: FloatArray) -> FloatArray:
    """The SE(3) pose (4, 4) of a pose (3, 3) in the scan plane (z = 0)."""
    T = np.eye(4)
    T[:2, :2] = P[:2, :2]
    T[:2, 3] = P[:2, 2]
    return T


# ---- lines and matching -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Seg:
    points: FloatArray  # (n, 2) scanner frame
    dt: FloatArray  # (n,) s after the scan's stamp


@dataclass(frozen=True, eq=False)
class _Lines:
    """Lines (L rows) in a common frame: centroid, unit direction and normal, extent along it."""

    c: FloatArray
    u: FloatArray
    n: FloatArray
    lo: FloatArray
    hi: FloatArray

    @staticmethod
    def of(placed: list[FloatArray]) -> _Lines:
        rows = [_line(p) for p in placed]
        if not rows:
            z2, z1 = np.zeros((0, 2)), np.zeros(0)
            return _Lines(z2, z2, z2, z1, z1)
        c, u, n, lo, hi = (np.array(x) for x in zip(*rows, strict=True))
        return _Lines(c, u, n, lo, hi)

    @staticmethod
    def concat(parts: list[_Lines]) -> _Lines:
        return _Lines(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("c", "u", "n", "lo", "hi")))


def _line(points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float, float]:
    """TLS line of points (m, 2): centroid, unit direction, unit normal, extent along it."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    u = vt[0]
    s = (points - c) @ u
    return c, u, np.array([-u[1], u[0]]), float(s.min()), float(s.max())


def _segments(scans: list[ScanSegments], T_body_scanner: FloatArray) -> list[list[_Seg]]:
    """Each scan's segments with at least MIN_POINTS points, in the scanner frame, times after
    the scan's stamp."""
    T_sb = np.linalg.inv(T_body_scanner)
    out = []
    for segs in scans:
        pts = segs.points_body @ T_sb[:3, :3].T + T_sb[:3, 3]
        rows = []
        for j in range(segs.n_segments):
            if segs.n_points[j] >= MIN_POINTS:
                sl = slice(int(segs.offsets[j]), int(segs.offsets[j + 1]))
                rows.append(_Seg(np.ascontiguousarray(pts[sl, :2]), segs.times[sl] - segs.stamp))
        out.append(rows)
    return out


def _match_one(lines: _Lines, placed: FloatArray, gate: float, sin_gate: float) -> int:
    """The index of the line a placed segment (m, 2) matches (the nearest nearly parallel line
    whose extent its end points overlap), -1 for none."""
    if lines.c.shape[0] == 0:
        return -1
    cs, us, _, _, _ = _line(placed)
    d = np.abs(np.einsum("ij,ij->i", cs - lines.c, lines.n))
    ends = placed[[0, -1]]
    s0 = np.einsum("ij,ij->i", ends[0] - lines.c, lines.u)
    s1 = np.einsum("ij,ij->i", ends[1] - lines.c, lines.u)
    ok = ((np.abs(lines.n @ us) <= sin_gate) & (d < gate)
          & (np.maximum(s0, s1) >= lines.lo - OVERLAP_MARGIN) & (np.minimum(s0, s1) <= lines.hi + OVERLAP_MARGIN))
    if not ok.any():
        return -1
    return int(np.flatnonzero(ok)[np.argmin(d[ok])])


def _normal_equations(f: Residuals, x0: FloatArray, huber: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The Huber-weighted normal equations of the residuals ``f(x)`` at ``x0`` (numeric
    Jacobian): ``J^T W J``, ``J^T W r``, the residuals and their weights."""
    r = f(x0)
    J = np.empty((r.size, x0.size))
    for k in range(x0.size):
        h = np.zeros(x0.size)
        h[k] = 1e-5
        J[:, k] = (f(x0 + h) - f(x0 - h)) / 2e-5
    a = np.abs(r)
    w = np.where(a <= huber, 1.0, huber / np.maximum(a, 1e-12))
    return (J * w[:, None]).T @ J, (J * w[:, None]).T @ r, r, w


def _gauss_newton(f: Residuals, x0: FloatArray, prior_x: FloatArray, prior_W: FloatArray,
                  huber: float = HUBER) -> FloatArray:
    """One Huber-weighted Gauss-Newton step of the residuals ``f(x)`` from ``x0``, with the prior
    ``(x - prior_x)^T prior_W (x - prior_x)`` (``prior_W`` (3, 3), in units of ``huber``^2)."""
    A, g, _, _ = _normal_equations(f, x0, huber)
    return x0 - np.linalg.solve(A + prior_W * huber**2, g + prior_W @ (x0 - prior_x) * huber**2)


def unobserved_directions(normals: FloatArray, min_across: float) -> FloatArray:
    """The translation directions (k, 2; unit rows, k = 0-2; the normals' frame) that matched
    segments with these unit normals (m, 2) do not observe: the eigenvectors of ``sum n n^T``
    below ``min_across`` (parallel walls observe only the direction across them)."""
    if normals.shape[0] == 0:
        return np.eye(2)
    w, V = np.linalg.eigh(normals.T @ normals)
    return np.ascontiguousarray(V[:, w < min_across].T)


def _hold_directions(dirs: FloatArray) -> FloatArray:
    """The prior weight (3, 3) that holds a 2D twist's or pose correction's translation at its
    prior along the unit directions ``dirs`` (k, 2; same frame)."""
    W = np.zeros((3, 3))
    W[:2, :2] = HOLD_WEIGHT * (dirs.T @ dirs)
    return W


# ---- 1: at rest or moving ------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Fit:
    """The rest test's fit: the 2D twist ``xi`` (v_x, v_y m/s, w rad/s), its covariance ``cov``
    (3, 3), the matched segments, the points' RMS distance (m) and the translation directions
    the matched lines do not observe (``unobserved``: (k, 2) unit rows, scanner frame), along
    which ``xi`` is held at zero."""

    xi: FloatArray
    cov: FloatArray
    matches: int
    rms: float
    unobserved: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


def register(scans: list[ScanSegments], T_body_scanner: FloatArray, t0: float, span: float,
             sigma: float = 0.0) -> Fit | None:
    """The constant 2D twist (v_x, v_y, w) of the scanner frame over ``scans`` (one scanner's,
    time order, the first one the target; those within ``span`` s of ``t0``) with its
    covariance; None when too few segments match. ``sigma`` (m) is the scanner's range noise:
    the Huber width and the distance gates are at least 1 and 3 of it. The velocity along a
    direction the matched lines do not observe is held at zero (``Fit.unobserved``)."""
    segs = _segments(scans, T_body_scanner)
    if len(segs) < 2 or not segs[0]:
        return None
    dts = [np.array(s.stamp - t0) for s in scans]
    xi = np.zeros(3)
    w_prior = np.diag(1.0 / PRIOR_SIGMAS**2)
    matches: list[tuple[_Seg, float, FloatArray, float]] = []
    dirs = np.zeros((0, 2))

    def residuals(x: FloatArray) -> FloatArray:
        return np.concatenate([se2_place(seg.points, seg.dt + dt, x) @ n + d for seg, dt, n, d in matches])

    huber = max(HUBER, sigma)
    # coarse to fine, free; then, when the final matches leave a direction unobserved, the fine
    # stage again with the velocity along it held at zero (holding it from the start would keep
    # the few lines across the walk, found only once the velocity is about right, out of reach)
    stages = [(reach, gate, angle, False) for reach, gate, angle in STAGES]
    k = 0
    while k < len(stages):
        reach, stage_gate, angle, held = stages[k]
        k += 1
        sources = [i for i in range(1, len(segs)) if float(dts[i]) <= min(reach, span) + 1e-9]
        if not sources:
            continue
        gate = max(stage_gate, 3.0 * sigma)
        sin_gate = np.sin(np.radians(angle))
        for _ in range(ITERATIONS):
            target = _Lines.of([se2_place(s.points, s.dt + dts[0], xi) for s in segs[0]])
            matches = []
            for i in sources:
                for seg in segs[i]:
                    j = _match_one(target, se2_place(seg.points, seg.dt + dts[i], xi), gate, sin_gate)
                    if j >= 0:
                        matches.append((seg, float(dts[i]), target.n[j], -float(target.n[j] @ target.c[j])))
            if len(matches) < MIN_MATCHES:
                return None
            new = _gauss_newton(residuals, xi, np.zeros(3), w_prior + _hold_directions(dirs), huber)
            done = np.abs(new - xi).max() < 1e-5
            xi = new
            if done:
                break
        if k == len(stages) and not held:
            dirs = unobserved_directions(np.array([m[2] for m in matches]), MIN_ACROSS)
            if dirs.shape[0]:
                xi[:2] -= dirs.T @ (dirs @ xi[:2])
                stages.append((reach, stage_gate, angle, True))
    A, _, r, w = _normal_equations(residuals, xi, huber)
    # the weighted residuals' scale; the points of one segment share its line's errors, so the
    # segments (not the points) count as the independent samples
    scale2 = float(np.sum(w * r * r) / max(np.sum(w) - 3.0, 1.0)) * r.size / max(len(matches), 4)
    # the held directions: known (to be zero), not free
    A = A + _hold_directions(dirs) * huber**2
    try:
        cov = np.asarray(np.linalg.inv(A), dtype=np.float64) * scale2
    except np.linalg.LinAlgError:
        cov = np.diag(PRIOR_SIGMAS**2)
    return Fit(xi, cov, len(matches), float(np.sqrt(np.mean(r * r))), dirs)


# ---- 2: odometry ---------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Odometry:
    """The scanner's pose (3, 3) at each scan's stamp (s) relative to the first scan's, the
    twist (v_x, v_y, w) of the interval before it, and the translation directions (k, 2: unit
    rows, that scan's scanner frame) its matched lines did not observe."""

    stamps: FloatArray
    poses: list[FloatArray]
    twists: list[FloatArray]
    unobserved: list[FloatArray]


def odometry(scans: list[ScanSegments], T_body_scanner: FloatArray, xi0: FloatArray, sigma: float = 0.0,
             ) -> Odometry:
    """Scan after scan from the first (whose interval's twist is ``xi0``; module doc, step 2)."""
    segs = _segments(scans, T_body_scanner)
    stamps = np.array([s.stamp for s in scans])
    poses = [np.eye(3)]
    twists = [np.asarray(xi0, dtype=np.float64)]
    unobserved = [np.zeros((0, 2))]
    placed = [_Lines.of([se2_place(s.points, s.dt, twists[0]) for s in segs[0]])]
    for i in range(1, len(segs)):
        target = _Lines.concat([placed[0], *placed[max(1, len(placed) - MAP_SCANS):]])
        P, xi, dirs = _register_scan(segs[i], target, poses[-1], twists[-1], float(stamps[i] - stamps[i - 1]), sigma)
        poses.append(P)
        twists.append(xi)
        unobserved.append(dirs @ P[:2, :2])  # first-scan frame -> this scan's
        placed.append(_Lines.of([se2_place(s.points, s.dt, xi, P) for s in segs[i]]))
    return Odometry(stamps, poses, twists, unobserved)


def _register_scan(segs: list[_Seg], target: _Lines, prev: FloatArray, xi_prev: FloatArray, h: float,
                   sigma: float = 0.0) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The pose (3, 3) of a scan ``h`` s after the one at ``prev`` (whose interval's twist was
    ``xi_prev``) against the ``target`` lines, the twist of the interval between them and the
    translation directions (k, 2: unit rows, the target's frame) the matched lines do not
    observe, along which the pose stays at the constant-velocity prediction (all of them when
    too few segments match)."""
    pred = prev @ se2_exp(xi_prev * h)
    prev_inv = np.linalg.inv(prev)
    gate, sin_gate = max(ODOMETRY_GATE[0], 3.0 * sigma), np.sin(np.radians(ODOMETRY_GATE[1]))
    huber = max(HUBER, sigma)
    w_prior = np.diag(1.0 / ODOMETRY_PRIOR**2)
    dirs = np.eye(2)

    def pose_of(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        P = pred @ se2(*x)
        return P, se2_log(prev_inv @ P) / max(h, 1e-6)

    x = np.zeros(3)
    for _ in range(ITERATIONS):
        P, xi = pose_of(x)
        matches: list[tuple[_Seg, FloatArray, float]] = []
        for seg in segs:
            j = _match_one(target, se2_place(seg.points, seg.dt, xi, P), gate, sin_gate)
            if j >= 0:
                matches.append((seg, target.n[j], -float(target.n[j] @ target.c[j])))
        if len(matches) < MIN_MATCHES:
            dirs = np.eye(2)
            break
        dirs = unobserved_directions(np.array([m[1] for m in matches]), ODOMETRY_MIN_ACROSS)
        # the correction's translation is in the predicted pose's frame
        hold = _hold_directions(dirs @ pred[:2, :2])
        new = _gauss_newton(_scan_residuals(matches, pose_of), x, np.zeros(3), w_prior + hold, huber)
        done = np.abs(new - x).max() < 1e-6
        x = new
        if done:
            break
    P, xi = pose_of(x)
    return P, xi, dirs


def _scan_residuals(matches: list[tuple[_Seg, FloatArray, float]],
                    pose_of: Callable[[FloatArray], tuple[FloatArray, FloatArray]]) -> Residuals:
    """The matched points' distances (m) from their lines as a function of the pose's correction."""

    def residuals(v: FloatArray) -> FloatArray:
        P, xi = pose_of(v)
        return np.concatenate([se2_place(seg.points, seg.dt, xi, P) @ n + d for seg, n, d in matches])

    return residuals


def pose_at(t: float, stamps: FloatArray, poses: list[FloatArray], twists: list[FloatArray]) -> FloatArray:
    """The scanner's pose (3, 3) at ``t`` (s) on the odometry's poses: from the scan before ``t``
    with the twist of the interval after it (before the first scan: back from it with the first
    interval's, after the last: on with the last's)."""
    i = int(np.searchsorted(stamps, t, side="right")) - 1
    i = min(max(i, 0), len(poses) - 1)
    xi = twists[min(i + 1, len(twists) - 1)]
    return poses[i] @ se2_exp(xi * (t - float(stamps[i])))


def knot_increments(t0: float, dt: float, t_end: float, stamps: FloatArray, poses: list[FloatArray],
                    twists: list[FloatArray], T_body_scanner: FloatArray) -> list[FloatArray]:
    """The body's motion (4, 4) over each knot interval ``[t0 + k dt, t0 + (k + 1) dt]`` up to
    ``t_end`` (s), from the odometry (module doc, step 3)."""
    T_sb = np.linalg.inv(T_body_scanner)
    out = []
    k = 0
    P_a = pose_at(t0, stamps, poses, twists)
    while t0 + (k + 1) * dt <= t_end + 1e-9:
        P_b = pose_at(t0 + (k + 1) * dt, stamps, poses, twists)
        out.append(T_body_scanner @ lift(np.linalg.inv(P_a) @ P_b) @ T_sb)
        P_a = P_b
        k += 1
    return out


# ---- the start -----------------------------------------------------------------------------------


def estimate(scans: list[ScanSegments], T_body_scanner: list[FloatArray], t0: float, dt: float,
             params: InitialMotionParams, sigma: list[float] | None = None) -> InitialMotion:
    """How the walk starts, from the scans of the first ``params.window`` s (any scanners, time
    order; see the module doc) with knots every ``dt`` s from ``t0``; ``sigma`` (m) is each
    scanner's range noise. At rest when the start is below the thresholds (raised with the
    noise), within ``SE_SIGMAS`` standard errors of rest, or cannot be measured."""
    if params.window <= 0:
        return InitialMotion.rest()
    s = level_scanner(T_body_scanner)
    noise = 0.0 if sigma is None else float(sigma[s])
    own = [p for p in scans if p.scanner == s and p.stamp <= t0 + params.window]
    span = min(REST_SPAN, params.window)
    first = [p for p in own if p.stamp <= t0 + span]
    fit = register(first, T_body_scanner[s], t0, span, noise) if len(first) >= 2 else None
    if fit is None:
        return InitialMotion.rest(s)
    xi = fit.xi
    unobserved = fit.unobserved[0] if fit.unobserved.shape[0] else None
    speed, rate = float(np.hypot(xi[0], xi[1])), abs(float(xi[2]))
    # the first scan's lines are every match's target: their errors, which the standard errors
    # do not see, grow with the noise (30 mm: 0.1-0.2 m/s and 3-6 deg/s on a standing start)
    k = max(1.0, noise / params.reference_sigma)
    # the speed's and the turn rate's standard errors (the speed's along its direction)
    u = xi[:2] / max(speed, 1e-12)
    se_speed = float(np.sqrt(max(float(u @ fit.cov[:2, :2] @ u), 0.0)))
    se_rate = float(np.sqrt(max(float(fit.cov[2, 2]), 0.0)))
    at_rest = (speed < max(k * params.min_speed, SE_SIGMAS * se_speed)
               and rate < max(k * params.min_rate, SE_SIGMAS * se_rate))
    if at_rest and not params.rest_odometry:
        return InitialMotion(np.zeros(6), False, s, xi, fit.matches, fit.rms, unobserved=unobserved)
    # moving, or at rest with the window's odometry: from rest (zero twist) or from the start's twist
    xi0 = np.zeros(3) if at_rest else xi
    twist_scan = np.array([0.0, 0.0, xi[2], xi[0], xi[1], 0.0])
    twist_body = np.zeros(6) if at_rest else adjoint(T_body_scanner[s]) @ twist_scan
    odo = odometry(own, T_body_scanner[s], xi0, noise)
    increments = knot_increments(t0, dt, float(odo.stamps[-1]), odo.stamps, odo.poses, odo.twists, T_body_scanner[s])
    held = [d for d in odo.unobserved if d.shape[0]]
    return InitialMotion(twist_body, not at_rest, s, xi, fit.matches, fit.rms, increments,
                         body_sigmas(T_body_scanner[s], np.concatenate(held) if held else None, len(held)), len(own),
                         unobserved, len(held))


def body_sigmas(T_body_scanner: FloatArray, unobserved: FloatArray | None = None, count: int = 1) -> FloatArray:
    """``ODOMETRY_SIGMAS`` (scanner frame) as sigmas (6,: rad, m) of the body's motion: the
    diagonal of the covariance moved by the adjoint of the scanner's mounting. ``unobserved``
    (k, 2: unit rows, scanner frame) are the directions the odometry's ``count`` scans with one
    did not observe: their mean outer product adds ``UNOBSERVED_SIGMA``^2 to the translation."""
    cov = np.diag(ODOMETRY_SIGMAS**2)
    if unobserved is not None and unobserved.shape[0]:
        cov[3:5, 3:5] += UNOBSERVED_SIGMA**2 * (unobserved.T @ unobserved) / max(count, 1)
    A = adjoint(T_body_scanner)
    return np.sqrt(np.diag(A @ cov @ A.T))
