"""Which of the body's six degrees of freedom a rig's scanners constrain in a typical room.

A scan line on a plane constrains the body's motion through its point-to-plane residuals: for a
return at ``p`` (body frame) on a plane with normal ``n`` (body frame), a small body motion
(rotation ``w``, translation ``v``) changes the residual by ``(p x n) . w + n . v``. Summed over
every beam of every scanner that hits a room (walls, floor, ceiling), seen from a few positions
and headings, these give a 6x6 information matrix; directions with (next to) no information are
motions the planes cannot see, which only an IMU (gravity, integration) holds. A horizontal plus
a vertical cross-profiler, for example, leaves pitch to gravity: floor and wall lines stay in their
planes when the body pitches.

Order of the degrees of freedom: roll, pitch, yaw (about body x, y, z), then x, y, z (gtsam's
Pose3 tangent order). Pure numpy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig

FloatArray = NDArray[np.float64]
DOF_NAMES = ("roll", "pitch", "yaw", "x", "y", "z")
# the typical room: 7 x 5 m, 2.8 m high, the reference scanner 1.9 m above the floor
ROOM_SIZE = (7.0, 5.0, 2.8)
SCANNER_HEIGHT = 1.9
# a direction is unobserved when its information is below this fraction of the strongest one's
UNOBSERVED_RATIO = 1e-6


@dataclass(frozen=True)
class RigObservability:
    """The information matrix (6, 6) of one sweep of every scanner, summed over positions and
    headings in the room, its per-axis share and the unobserved directions (unit 6-vectors)."""

    information: FloatArray
    unobserved: list[FloatArray]

    @property
    def observed(self) -> bool:
        return not self.unobserved

    def relative(self) -> FloatArray:
        """Per degree of freedom (6,): the smallest information of any direction mostly along it,
        relative to the strongest direction's (1 = as well as anything, 0 = not at all)."""
        w, V = np.linalg.eigh(self.information)
        top = max(float(w[-1]), 1e-300)
        out = np.ones(6)
        for i in range(6):
            axis = int(np.argmax(np.abs(V[:, i])))
            out[axis] = min(out[axis], max(float(w[i]), 0.0) / top)
        return out

    def unobserved_names(self) -> list[str]:
        """Each unobserved direction named by its dominant degree of freedom."""
        return [_name(v) for v in self.unobserved]

    def summary(self) -> str:
        rel = self.relative()
        cells = ", ".join(f"{n} {'yes' if r >= UNOBSERVED_RATIO else 'NO'}" for n, r in zip(DOF_NAMES, rel, strict=True))
        if self.observed:
            return f"constrained by the scanners in a typical room: {cells}"
        return (f"constrained by the scanners in a typical room: {cells}; "
                f"left to an IMU: {', '.join(self.unobserved_names())}")


def _name(v: FloatArray) -> str:
    order = np.argsort(-np.abs(v))
    main = DOF_NAMES[int(order[0])]
    if abs(v[order[1]]) > 0.3:
        return f"{main} (with {DOF_NAMES[int(order[1])]})"
    return main


def _box_hits(origin: FloatArray, dirs: FloatArray, lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, FloatArray]:
    """First exit of rays (n, 3) from inside the box [lo, hi]: ranges (n,) and the hit face's
    inward normals (n, 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (hi - origin) / dirs
        t_lo = (lo - origin) / dirs
    t = np.where(dirs > 0, t_hi, np.where(dirs < 0, t_lo, np.inf))
    axis = np.argmin(t, axis=1)
    rng = t[np.arange(len(dirs)), axis]
    normal = np.zeros_like(dirs)
    normal[np.arange(len(dirs)), axis] = -np.sign(dirs[np.arange(len(dirs)), axis])
    return rng, normal


def rig_observability(rig: Rig, headings: int = 4) -> RigObservability:
    """The rig's observability in the typical room, standing level at three positions, facing
    ``headings`` directions along the walls (4: the four walls; walkers walk along corridors and
    walls, and a direction seen only when the rig stands oblique to every wall is not held)."""
    lo = np.array([-ROOM_SIZE[0] / 2, -ROOM_SIZE[1] / 2, 0.0])
    hi = np.array([ROOM_SIZE[0] / 2, ROOM_SIZE[1] / 2, ROOM_SIZE[2]])
    info = np.zeros((6, 6))
    for px, py in ((0.0, 0.0), (1.5, 0.8), (-2.0, -1.0)):
        for h in np.arange(headings) * (2 * np.pi / headings):
            c, s = np.cos(h), np.sin(h)
            R_wb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            t_wb = np.array([px, py, SCANNER_HEIGHT])
            for sc in rig.scanners:
                m = sc.scanner_model
                T = sc.T_body_scanner.matrix()
                a = m.beam_angles()
                d_s = np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a)))
                d_b = d_s @ T[:3, :3].T
                o_b = T[:3, 3]
                o_w = R_wb @ o_b + t_wb
                rng, n_w = _box_hits(o_w, d_b @ R_wb.T, lo, hi)
                ok = np.isfinite(rng) & (rng >= m.range_min) & (rng <= m.range_max)
                p_b = o_b + d_b[ok] * rng[ok, None]
                n_b = n_w[ok] @ R_wb
                J = np.column_stack((np.cross(p_b, n_b), n_b))
                info += J.T @ J
    w, V = np.linalg.eigh(info)
    top = max(float(w[-1]), 1e-300)
    unobserved = [V[:, i] for i in range(6) if w[i] < UNOBSERVED_RATIO * top]
    return RigObservability(info, unobserved)
