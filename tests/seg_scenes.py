"""Hand-made 2D scenes for the segmentation tests: a tiny polyline ray caster.

Faces are line segments ``(a, b)`` in the scanner frame; each beam takes the
nearest hit. Used only by the tests (the full simulator lives in ``simulation``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from segmentation import Scanline

FloatArray = NDArray[np.float64]

UTM_ANGLES = np.deg2rad(-135.0) + np.deg2rad(0.25) * np.arange(1081)


def raycast(faces: list[tuple[tuple[float, float], tuple[float, float]]], angles: FloatArray,
            origin: tuple[float, float] = (0.0, 0.0)) -> tuple[FloatArray, NDArray[np.int64]]:
    """Range (inf where nothing is hit) and face index (-1) of every beam from ``origin``."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.column_stack((np.cos(angles), np.sin(angles)))
    best = np.full(angles.shape[0], np.inf)
    face = np.full(angles.shape[0], -1, dtype=np.int64)
    for k, (a, b) in enumerate(faces):
        a_ = np.asarray(a, dtype=np.float64) - o
        e = np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)
        # solve t d = a + u e  for t >= 0, u in [0, 1]
        den = d[:, 0] * (-e[1]) - d[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = (a_[0] * (-e[1]) - a_[1] * (-e[0])) / den
            u = (d[:, 0] * a_[1] - d[:, 1] * a_[0]) / den
        hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1) & (t < best)
        best[hit] = t[hit]
        face[hit] = k
    return best, face


def office_faces(step_board: float = 0.02, step_door: float = 0.015) -> list:
    """A room like the paper's figure 1: wall, board proud of it, wall, corner, wall, recessed door, wall."""
    return [
        ((3.0, -4.0), (3.0, -1.5)),                 # 0 wall
        ((3.0 - step_board, -1.5), (3.0 - step_board, 0.0)),  # 1 whiteboard (proud)
        ((3.0, 0.0), (3.0, 2.5)),                   # 2 wall
        ((3.0, 2.5), (0.5, 2.5)),                   # 3 wall after the corner
        ((0.5, 2.5 + step_door), (-0.5, 2.5 + step_door)),  # 4 door leaf (recessed)
        ((-0.5, 2.5), (-7.0, 2.5)),                 # 5 wall
        ((-7.0, 2.5), (-7.0, -4.0)),                # 6 wall
        ((-7.0, -4.0), (3.0, -4.0)),                # 7 wall
        # board edges and door jambs (steep), so the steps are closed
        ((3.0, -1.5), (3.0 - step_board, -1.5)),
        ((3.0 - step_board, 0.0), (3.0, 0.0)),
        ((0.5, 2.5), (0.5, 2.5 + step_door)),
        ((-0.5, 2.5 + step_door), (-0.5, 2.5)),
    ]


def office_scanline(noise: float = 0.003, seed: int = 0, angles: FloatArray = UTM_ANGLES) -> tuple[Scanline, NDArray[np.int64]]:
    """A 1081-beam UTM-30LX-like scanline of ``office_faces`` with Gaussian range noise; (scanline, face per beam)."""
    r, face = raycast(office_faces(), angles)
    rng = np.random.default_rng(seed)
    r = r + noise * rng.standard_normal(r.shape[0])
    return Scanline.from_ranges(r, angles, 0.0, range_min=0.1, range_max=30.0, time_increment=1.7e-5), face
