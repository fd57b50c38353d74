"""Batched point-on-plane factors: many laser points, one ``gtsam.CustomFactor``.

A block holds the N points that the body saw on one plane ``P(j)`` between two consecutive
trajectory knots ``X(i)``, ``X(i+1)``. Point k was measured at its own beam time, which maps onto
the trajectory by its fraction ``alpha_k`` in [0, 1] (see :mod:`slam.trajectory.interpolation`)::

    R_k = R_i Exp(alpha_k Log(R_i^T R_{i+1}))            body rotation at the beam time
    t_k = t_i + alpha_k (t_{i+1} - t_i)                  body position at the beam time
    e_k = (n . (R_k p_k + t_k) + d) / sigma_k            whitened signed point-to-plane distance

with the plane ``n . x + d = 0`` in the world frame (``gtsam.OrientedPlane3``) and ``p_k`` the
point in the body frame at its beam time (scanner extrinsic already applied). Variants:

* :func:`point_plane_factor` with ``pose_key_b=None``: keys ``(X(i), P(j))``; every alpha is 0.
* :func:`scanner_point_plane_factor`: points in the scanner frame and ``T_body_scanner`` a
  variable ``E(s)``: keys ``(X(i)[, X(i+1)], P(j), E(s))`` (for calibration).
* :func:`point_planes_factor`: the points of one knot interval on several planes, keys
  ``(X(i), X(i+1), P(j1), ..., P(jJ))``: the same rows as one block per plane, in one factor
  (one Python call per linearisation instead of one per plane: the call, not the arithmetic,
  is the cost of a block of a few points).

Jacobians are analytic and exact (no small-motion approximation): with right perturbations of
both poses (gtsam's ``Pose3`` retract: ``R Exp(w)``, ``t + R v``), ``D = R_i^T R_{i+1}``,
``phi = Log(D)``, ``Jr`` the SO(3) right Jacobian, ``m_k = R_k^T n`` and
``g_k = p_k x m_k`` (the derivative wrt a right rotation perturbation at the beam time)::

    H_{i+1} = [ alpha_k g_k^T Jr(alpha_k phi) Jr(phi)^-1 ,  alpha_k n^T R_{i+1} ]
    H_i     = [ (Exp(alpha_k phi) g_k)^T - H_{i+1,rot} D^T , (1 - alpha_k) n^T R_i ]
    H_plane = [ (R_k p_k + t_k)^T B, 1 ]       B = the normal's tangent basis (``Unit3.basis()``)

The two-pose terms run in a compiled loop (:mod:`slam.backend.factor_kernels`): a block holds few
points, for which numpy's per-call overhead would dominate.

Robustness (per point, wrong associations): a robust noise model on the block would weight
the whole block by its total error, so the kernel is applied inside the factor, point by point,
with gtsam's own robust-model semantics (IRLS): at every linearisation the weights
``w_k = psi(e_k) / e_k`` (Huber or Cauchy, threshold in sigmas) are recomputed from the current
residuals and the factor linearises as ``sqrt(w_k) (e_k + de_k/dx dx)``, so each Gauss-Newton /
iSAM2 step is a weighted least-squares step; when gtsam only evaluates the error (no
Jacobians requested: Levenberg-Marquardt's step acceptance) the factor returns
``sign(e_k) sqrt(2 rho(e_k))``, so its error is exactly the robust cost ``sum_k rho(e_k)``.
(Returning ``sqrt(2 rho)`` at linearisation too, with its exact derivative, gives steps that
overshoot by far for points in the outlier regime, which iSAM2 does not damp; returning
``sqrt(w) e`` as the error too makes LM judge steps on ``sum w e^2``, another cost.)
Cauchy is the SLAM configuration's kernel (``backend.robust``, 2.5 sigma; the calibration's:
3 sigma): it is redescending, so a point associated with the wrong surface
(a door 1-2 cm behind its wall) stops pulling; Huber keeps a constant pull and is convex.
:func:`robust_weights` gives the weights for diagnostics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam.backend import factor_kernels as _fk
from slam.backend.factor_kernels import two_pose_terms
from slam.trajectory.interpolation import hat3

FloatArray = NDArray[np.float64]
# the compiled kernels' codes (slam.backend.factor_kernels)
_KERNEL_CODE = {"none": 0, "huber": 1, "cauchy": 2, "geman_mcclure": 3}
KernelName = Literal["none", "huber", "cauchy", "geman_mcclure"]


@dataclass(frozen=True)
class RobustKernel:
    """Per-point robust kernel; ``threshold`` is in units of the point's sigma (unused by
    ``"none"``: :data:`NO_KERNEL`)."""

    name: KernelName
    threshold: float

    def __post_init__(self) -> None:
        if self.name not in _KERNEL_CODE:
            raise ValueError(f"robust kernel name: expected none, huber, cauchy or geman_mcclure, got {self.name!r}")
        if not (np.isfinite(self.threshold) and self.threshold > 0.0):
            raise ValueError(f"robust kernel threshold: must be > 0, got {self.threshold}")


NO_KERNEL = RobustKernel("none", 1.0)  # plain least squares


def robust_loss(e: ArrayLike, kernel: RobustKernel) -> FloatArray:
    """``rho(e)`` per whitened residual (``e^2 / 2`` without a kernel)."""
    e = np.asarray(e, dtype=float)
    k = kernel.threshold
    if kernel.name == "none":
        return 0.5 * e * e
    if kernel.name == "huber":
        a = np.abs(e)
        return np.where(a <= k, 0.5 * e * e, k * a - 0.5 * k * k)
    if kernel.name == "geman_mcclure":
        return 0.5 * k * k * e * e / (k * k + e * e)
    return 0.5 * k * k * np.log1p((e / k) ** 2)


def robust_weights(e: ArrayLike, kernel: RobustKernel) -> FloatArray:
    """IRLS weights ``w = psi(e) / e`` in [0, 1] per whitened residual."""
    e = np.asarray(e, dtype=float)
    k = kernel.threshold
    if kernel.name == "none":
        return np.ones_like(e)
    if kernel.name == "huber":
        return np.minimum(1.0, k / np.maximum(np.abs(e), 1e-300))
    if kernel.name == "geman_mcclure":
        return (k * k / (k * k + e * e)) ** 2
    return 1.0 / (1.0 + (e / k) ** 2)


def robust_residual(e: FloatArray, kernel: RobustKernel) -> FloatArray:
    """``sign(e) sqrt(2 rho(e))``: the residual whose half square is the robust loss."""
    if kernel.name == "none":
        return e
    return np.sign(e) * np.sqrt(2.0 * robust_loss(e, kernel))


def robust_rows(e: FloatArray, kernel: RobustKernel, linearize: bool) -> tuple[FloatArray, FloatArray | None]:
    """The residual vector a robust block returns for whitened residuals ``e`` (N,), and the
    IRLS row scales ``sqrt(w)`` (N,) of its Jacobian when linearising (else None).

    Without a kernel: ``e``, ``1``. With one, N + 1 rows: for an error evaluation the robust
    residuals ``sign(e) sqrt(2 rho(e))`` and 0; when linearising the IRLS rows ``sqrt(w) e``
    (Gauss-Newton steps of iteratively reweighted least squares) and one row with no Jacobian,
    ``sqrt(2 sum(rho - w e^2 / 2))`` (>= 0 for Huber, Cauchy and Geman-McClure), so that a linearisation's
    ``0.5 ||b||^2`` is the robust cost at its point: the solver takes an accepted step's error
    from the linearisation it needs next anyway (:mod:`slam.backend.solver`)."""
    if kernel.name == "none":
        return e, (np.ones_like(e) if linearize else None)
    out, sw = _fk.robust_rows(np.ascontiguousarray(e, dtype=np.float64), _KERNEL_CODE[kernel.name],
                              float(kernel.threshold), linearize)
    return out, (sw if linearize else None)


def robust_rows_dim(n: int, kernel: RobustKernel) -> int:
    """Rows of a robust block of ``n`` points (:func:`robust_rows`)."""
    return n if kernel.name == "none" else n + 1


def scaled_rows(J: FloatArray, f: FloatArray, rows: int) -> FloatArray:
    """``J * f`` (N, d) with zero rows appended up to ``rows`` (the correction row of
    :func:`robust_rows`), in one allocation."""
    n = J.shape[0]
    out = np.empty((rows, J.shape[1]))
    np.multiply(J, f, out=out[:n])
    out[n:] = 0.0
    return out


@dataclass
class PointPlaneTerms:
    """Unwhitened residuals (N,) [m] and their Jacobians for one block at one linearisation point.

    ``H_a``/``H_b`` (N, 6) are wrt right perturbations of ``T_world_body`` at knots i and i+1
    (``H_b`` is None for single-pose blocks), ``H_plane`` (N, 3) wrt the plane's retract
    coordinates, ``normal_beam`` (N, 3) is the plane normal in the body frame at each beam time
    (``R_k^T n``, for chaining to the extrinsic).
    """

    residuals: FloatArray
    H_a: FloatArray | None = None
    H_b: FloatArray | None = None
    H_plane: FloatArray | None = None
    normal_beam: FloatArray | None = None
    dres_dalpha: FloatArray | None = None  # d residual / d alpha (N,), for time offsets


def point_plane_terms(
    T_a: gtsam.Pose3,
    T_b: gtsam.Pose3 | None,
    plane: gtsam.OrientedPlane3,
    points_body: FloatArray,
    alphas: FloatArray | None,
    jacobians: bool = True,
    anchor: FloatArray | None = None,
) -> PointPlaneTerms:
    """Signed distances of body-frame points (N, 3) placed by the interpolated pose to a world plane.

    ``T_b`` None means a single-pose block (alphas ignored). ``anchor`` (3,), the plane's anchor
    point, is subtracted from both poses' translations (poses in the plane's anchor frame; a
    constant left translation leaves the right-perturbation Jacobians unchanged). See the module docstring for the
    formulas; the Jacobians are exact. Every per-point product with a shared vector is a matmul
    with a shared matrix (``np.cross`` costs ~15 us a call on small arrays).
    """
    Ma = T_a.matrix()
    Ra, ta = Ma[:3, :3], Ma[:3, 3]
    if anchor is not None:  # poses in the plane's anchor frame (a constant left translation)
        ta = ta - anchor
    n = plane.normal().point3()
    d0 = float(n @ ta) + plane.distance()
    m_a = Ra.T @ n  # plane normal in the body frame of knot i
    Bn = plane.normal().basis()
    if T_b is None:
        res = points_body @ m_a + d0
        if not jacobians:
            return PointPlaneTerms(res)
        N = points_body.shape[0]
        H_a = np.empty((N, 6))
        H_a[:, :3] = points_body @ hat3(m_a)  # p x m_a
        H_a[:, 3:] = m_a
        H_plane = np.ones((N, 3))
        H_plane[:, :2] = points_body @ (Ra.T @ Bn) + ta @ Bn  # (T p)^T B
        return PointPlaneTerms(res, H_a, None, H_plane, np.broadcast_to(m_a, points_body.shape))

    assert alphas is not None
    Mb = T_b.matrix()
    tb = Mb[:3, 3] if anchor is None else Mb[:3, 3] - anchor
    res, H_a, H_b, H_plane, m_k, dra = two_pose_terms(
        Ra, ta, Mb[:3, :3], tb, n, float(plane.distance()), Bn,
        np.ascontiguousarray(points_body, dtype=float), np.ascontiguousarray(alphas, dtype=float), jacobians,
    )
    if not jacobians:
        return PointPlaneTerms(res)
    return PointPlaneTerms(res, H_a, H_b, H_plane, m_k, dra)


def check_block(points: ArrayLike, alphas: ArrayLike | None, sigmas: ArrayLike, two_poses: bool,
                 name: str) -> tuple[FloatArray, FloatArray | None, FloatArray]:
    """A block's points (N, 3), alphas (N,) or None and sigmas (N,) as arrays, or a ValueError
    naming what is wrong (``name``: the points' argument name)."""
    p = np.ascontiguousarray(points, dtype=float)
    if (two_poses and alphas is not None and type(sigmas) is np.ndarray and p.ndim == 2 and p.shape[1] == 3
            and p.shape[0] > 0 and sigmas.dtype == np.float64 and sigmas.shape == (p.shape[0],)):
        a = np.ascontiguousarray(alphas, dtype=float)
        if a.shape == (p.shape[0],) and _fk.block_ok(p, sigmas, a):  # one compiled pass: all fine
            return p, a, sigmas
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"{name}: expected a non-empty (N, 3) array, got shape {p.shape}")
    s = np.asarray(sigmas, dtype=float)
    if s.ndim == 0:
        s = np.full(p.shape[0], float(s))
    if s.shape != (p.shape[0],) or not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError(f"sigmas: expected {p.shape[0]} finite values > 0 (or one scalar)")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains NaN or inf")
    if not two_poses:
        if alphas is not None and np.any(np.asarray(alphas) != 0.0):
            raise ValueError("alphas: a single-pose block needs every alpha = 0 (or alphas=None)")
        return p, None, s
    if alphas is None:
        raise ValueError("alphas: required for a block between two knots")
    a = np.ascontiguousarray(alphas, dtype=float)
    if a.shape != (p.shape[0],) or not np.all((a >= 0.0) & (a <= 1.0)):
        raise ValueError(f"alphas: expected {p.shape[0]} values in [0, 1]")
    return p, a, s


def point_plane_factor(
    pose_key_a: int,
    pose_key_b: int | None,
    plane_key: int,
    points_body: ArrayLike,
    alphas: ArrayLike | None,
    sigmas: ArrayLike,
    kernel: RobustKernel,
    anchor: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """One factor for N body-frame points (N, 3) [m] observed between knots a and b on a plane.

    Keys ``(pose_key_a, pose_key_b, plane_key)``, or ``(pose_key_a, plane_key)`` when
    ``pose_key_b`` is None (then alphas must be None or all 0). ``sigmas`` (N,) or scalar [m]:
    point-to-plane standard deviations from the scanner noise model. Error dimension N.
    """
    p, al, s = check_block(points_body, alphas, sigmas, pose_key_b is not None, "points_body")
    return _block_factor(pose_key_a, pose_key_b, plane_key, None, p, al, s, kernel, _anchor(anchor))


def scanner_point_plane_factor(
    pose_key_a: int,
    pose_key_b: int | None,
    plane_key: int,
    extrinsic_key: int,
    points_scanner: ArrayLike,
    alphas: ArrayLike | None,
    sigmas: ArrayLike,
    kernel: RobustKernel,
    anchor: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """Like :func:`point_plane_factor` with points (N, 3) in the scanner frame and
    ``T_body_scanner`` the Pose3 variable ``extrinsic_key`` (last key; right perturbation)."""
    p, al, s = check_block(points_scanner, alphas, sigmas, pose_key_b is not None,
                            "points_scanner")
    return _block_factor(pose_key_a, pose_key_b, plane_key, extrinsic_key, p, al, s,
                         kernel, _anchor(anchor))


def _anchor(anchor: ArrayLike | None) -> FloatArray | None:
    if anchor is None:
        return None
    a = np.asarray(anchor, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"anchor: expected a finite 3-vector, got {a}")
    return a if np.any(a != 0.0) else None


def _block_factor(
    key_a: int,
    key_b: int | None,
    plane_key: int,
    extrinsic_key: int | None,
    points: FloatArray,
    alphas: FloatArray | None,
    sigmas: FloatArray,
    kernel: RobustKernel,
    anchor: FloatArray | None = None,
) -> gtsam.CustomFactor:
    inv_s = 1.0 / sigmas
    keys = [key_a] + ([key_b] if key_b is not None else []) + [plane_key]
    if extrinsic_key is not None:
        keys.append(extrinsic_key)

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        p_b = points
        if extrinsic_key is not None:
            E = v.atPose3(extrinsic_key).matrix()
            R_bs = E[:3, :3]
            p_b = points @ R_bs.T + E[:3, 3]
        T_b = v.atPose3(key_b) if key_b is not None else None
        t = point_plane_terms(v.atPose3(key_a), T_b, v.atOrientedPlane3(plane_key), p_b, alphas, H is not None,
                              anchor)
        e = t.residuals * inv_s
        out, sw = robust_rows(e, kernel, H is not None)
        if H is None:  # error evaluation only: the robust cost
            return out
        assert sw is not None and t.H_a is not None and t.H_plane is not None and t.normal_beam is not None
        f = (sw * inv_s)[:, None]
        H[0] = scaled_rows(t.H_a, f, rows)
        j = 1
        if t.H_b is not None:
            H[1] = scaled_rows(t.H_b, f, rows)
            j = 2
        H[j] = scaled_rows(t.H_plane, f, rows)
        if extrinsic_key is not None:
            m_s = t.normal_beam @ R_bs  # plane normal in the scanner frame at each beam time
            He = np.empty((points.shape[0], 6))
            He[:, :3] = np.cross(points, m_s)
            He[:, 3:] = m_s
            H[j + 1] = scaled_rows(He, f, rows)
        return out

    rows = robust_rows_dim(points.shape[0], kernel)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows), keys, error)


_INDEX_BITS = 56  # a gtsam Symbol key: its character above these bits, its index below
_X_CHR, _P_CHR = ord("x"), ord("p")


class PlaneTable:
    """The poses and planes of one evaluation point, each read from the ``gtsam.Values`` once:
    while a solver linearises a graph of :func:`point_planes_factor` factors at ``values``
    (between ``at(values)`` and ``at(None)``), every factor takes its knots' rotations (3, 3) and
    positions (3,) (``R``, ``t`` by knot index) and its planes' unit normals (3,), offsets and
    tangent bases (3, 2) (``normals``, ``dists``, ``bases`` by the plane's slot, :meth:`slots_of`)
    from here instead of reading them again (two pose and five gtsam calls per plane and factor:
    as costly as the factor's arithmetic). Otherwise factors read their values."""

    def __init__(self) -> None:
        self.values: gtsam.Values | None = None
        self.slot: dict[int, int] = {}  # plane key -> its row in normals, dists, bases (for good)
        self.normals = np.zeros((0, 3))
        self.dists = np.zeros(0)
        self.bases = np.zeros((0, 3, 2))
        self.R = np.zeros((0, 3, 3))
        self.t = np.zeros((0, 3))

    def slots_of(self, keys: Sequence[int]) -> NDArray[np.int64]:
        """The rows (slots) of plane ``keys`` in the plane tables (new keys get new slots)."""
        for key in keys:
            if key not in self.slot:
                self.slot[key] = len(self.slot)
        n = len(self.slot)
        if n > self.dists.shape[0]:
            m = max(64, 2 * n)
            self.normals = np.concatenate((self.normals, np.zeros((m - self.dists.shape[0], 3))))
            self.bases = np.concatenate((self.bases, np.zeros((m - self.dists.shape[0], 3, 2))))
            self.dists = np.concatenate((self.dists, np.zeros(m - self.dists.shape[0])))
        return np.array([self.slot[key] for key in keys], dtype=np.int64)

    def at(self, values: gtsam.Values | None) -> None:
        """Serve the poses and planes of ``values`` from now on (None: stop serving)."""
        self.values = values
        if values is None:
            return
        keys = np.array(values.keys(), dtype=np.uint64)
        chars = keys >> np.uint64(_INDEX_BITS)
        poses = keys[chars == _X_CHR]
        if poses.shape[0]:
            index = (poses & np.uint64((1 << _INDEX_BITS) - 1)).astype(np.int64)
            top = int(index.max()) + 1
            if top > self.t.shape[0]:
                m = max(1024, 2 * top)
                self.R = np.concatenate((self.R, np.zeros((m - self.t.shape[0], 3, 3))))
                self.t = np.concatenate((self.t, np.zeros((m - self.t.shape[0], 3))))
            rows = gtsam.utilities.extractPose3(values)  # every Pose3 by increasing key: [R row-major, t]
            if rows.shape[0] == poses.shape[0]:  # the poses are the knots' (sorted: the same order)
                order = np.argsort(poses, kind="stable")
                self.R[index[order]] = rows[:, :9].reshape(-1, 3, 3)
                self.t[index[order]] = rows[:, 9:]
            else:
                for key, i in zip(poses.tolist(), index.tolist(), strict=True):
                    M = values.atPose3(key).matrix()
                    self.R[i] = M[:3, :3]
                    self.t[i] = M[:3, 3]
        planes = keys[chars == _P_CHR].tolist()
        if planes:
            slots = self.slots_of(planes).tolist()
            normals, dists, bases = self.normals, self.dists, self.bases
            for key, s in zip(planes, slots, strict=True):
                normals[s], dists[s], bases[s] = plane_row(values, key)

    def get(self, key: int) -> tuple[FloatArray, float, FloatArray]:
        """Unit normal, offset and tangent basis of plane ``key`` at the served point."""
        s = self.slot[key]
        return self.normals[s], float(self.dists[s]), self.bases[s]


def knot_index(key: int) -> int | None:
    """The knot index of pose key ``X(i)``, or None for a key of another symbol."""
    return key & ((1 << _INDEX_BITS) - 1) if key >> _INDEX_BITS == _X_CHR else None


def plane_row(values: gtsam.Values, key: int) -> tuple[FloatArray, float, FloatArray]:
    """Unit normal (3,), offset and the normal's tangent basis (3, 2) of plane ``key`` in ``values``."""
    pl = values.atOrientedPlane3(key)
    u = pl.normal()
    return u.point3(), pl.distance(), u.basis()


def point_planes_factor(
    pose_key_a: int,
    pose_key_b: int,
    plane_keys: Sequence[int],
    plane_index: ArrayLike,
    points_body: ArrayLike,
    alphas: ArrayLike,
    sigmas: ArrayLike,
    kernel: RobustKernel,
    anchors: ArrayLike | None = None,
    table: PlaneTable | None = None,
) -> gtsam.CustomFactor:
    """One factor for the N body-frame points (N, 3) [m] seen between knots a and b on several
    planes: point m on plane ``plane_keys[plane_index[m]]`` at fraction ``alphas[m]``, sigma
    ``sigmas[m]`` [m]; ``anchors`` (J, 3) the planes' anchor points (world frame; None: zero).
    Keys ``(pose_key_a, pose_key_b, *plane_keys)``. Its rows are those of one
    :func:`point_plane_factor` per plane concatenated (one robust correction row for all), so
    the error and every Gauss-Newton step are the same; a plane's Jacobian is zero on the other
    planes' rows. ``table``: where the planes are read while a solver serves them
    (:class:`PlaneTable`)."""
    pk = [int(k) for k in plane_keys]
    J = len(pk)
    if J == 0 or len(set(pk)) != J:
        raise ValueError(f"plane_keys: expected distinct keys, got {pk}")
    p, al, s = check_block(points_body, alphas, sigmas, True, "points_body")
    idx = np.ascontiguousarray(plane_index, dtype=np.int64).reshape(-1)
    if idx.shape != (p.shape[0],) or idx.min() < 0 or idx.max() >= J:
        raise ValueError(f"plane_index: expected {p.shape[0]} indices in [0, {J})")
    anc = np.zeros((J, 3)) if anchors is None else np.ascontiguousarray(anchors, dtype=float).reshape(J, 3)
    if not np.all(np.isfinite(anc)):
        raise ValueError("anchors: must be finite")
    assert al is not None
    code, thr = _KERNEL_CODE[kernel.name], float(kernel.threshold)
    inv_s = 1.0 / s
    keys = [int(pose_key_a), int(pose_key_b), *pk]

    ia, ib = knot_index(keys[0]), knot_index(keys[1])
    own_slots = np.arange(J, dtype=np.int64)
    slots = table.slots_of(pk) if table is not None else own_slots

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        if table is not None and table.values is not None and ia is not None and ib is not None:
            rows, Ha, Hb, Hp = _fk.group_rows_at(table.R, table.t, ia, ib, table.normals, table.dists, table.bases,
                                                 slots, anc, idx, p, al, inv_s, code, thr, H is not None)
        else:
            Ma, Mb = v.atPose3(pose_key_a).matrix(), v.atPose3(pose_key_b).matrix()
            normals = np.empty((J, 3))
            dists = np.empty(J)
            bases = np.empty((J, 3, 2))
            for j, key in enumerate(pk):
                normals[j], dists[j], bases[j] = plane_row(v, key)
            rows, Ha, Hb, Hp = _fk.group_rows_core(Ma[:3, :3], Ma[:3, 3].copy(), Mb[:3, :3], Mb[:3, 3].copy(), normals,
                                                   dists, bases, own_slots, anc, idx, p, al, inv_s, code, thr,
                                                   H is not None)
        if H is not None:
            H[0] = Ha
            H[1] = Hb
            for j in range(J):
                H[2 + j] = Hp[j]
        return rows

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(robust_rows_dim(p.shape[0], kernel)), keys, error)
