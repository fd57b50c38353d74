"""How the default rig ``configs/rig/itc_backpack.yaml`` is built, and why those angles.

The ITC backpack (Vosselman 2014) carries three Hokuyo UTM-30LX: one horizontal
on top and two tilted ones at the left and right of the operator's head whose
scan planes sweep floor, walls and ceiling. We reproduce it as follows (body
frame: x forward, y left, z up, origin at the top scanner, ~1.90 m above the floor):

``top``  the reference: identity extrinsic, horizontal scan plane, 270 deg field
         of view centred forward, the 90 deg blind sector behind (the operator).

``left`` / ``right`` at (-0.05, +-0.25, -0.20) m (beside and just below the top
         scanner, on the backpack frame at head height), with:

- the scan plane vertical to start with, its centre beam (scanner x) horizontal
  and pointing out of the operator's side, the scanner's +90 deg beam pointing up:
  the 270 deg field of view then covers the floor beside the operator, the side
  wall, the ceiling and the space above the operator's head, and the 90 deg blind
  sector points horizontally into the operator;
- ``YAW_OUT`` = 45 deg: the centre beam is turned 45 deg forward (left scanner
  looks forward-left, right scanner forward-right). The floor and ceiling lines
  of the two scanners then run at +45 and -45 deg to the walking direction, i.e.
  orthogonal to each other, so floor and ceiling alone fix both roll and pitch
  equally well (a line on a plane constrains the rotation about
  ``normal x line``). At 0 deg (a pure profiler across the walking direction,
  best coverage) both floor lines would be parallel to y and pitch would be
  unobservable from them; at 90 deg the planes would lie along the walking
  direction and only ever re-scan the same wall lines. 45 deg also lets the
  planes sweep obliquely across door recesses, boards and corridor ends.
- ``TILT`` = 20 deg about the centre beam, the downward half forward: wall lines
  are then slanted 20 deg from vertical, so every wall also constrains yaw
  (``n x d`` gains a vertical component) instead of roll/pitch only, and the
  downward beams reach the floor ahead of the operator's feet rather than at
  his body.

Observability of the body's motion from line-to-plane association: x and y from
walls facing those directions (the top scanner sees walls all around, the tilted
ones the side walls and, obliquely, the cross walls), z from floor and ceiling
(left/right), roll and pitch from the two orthogonal floor/ceiling line
directions, yaw from the top scanner's wall lines and the slanted ones.
``tests/test_scanner.py`` checks that the 6x6 information matrix of point-to-plane
residuals of one sweep of this rig in a box room has full rank (and that of the
pushbroom variant with ``YAW_OUT`` = 0 does not resolve pitch as well).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.rotations import matrix_to_rpy

YAW_OUT = math.radians(45.0)
TILT = math.radians(20.0)
SIDE_TRANSLATION = (-0.05, 0.25, -0.20)


def _rz(a: float) -> NDArray[np.float64]:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> NDArray[np.float64]:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def side_rotation(side: Literal["left", "right"], yaw_out: float = YAW_OUT, tilt: float = TILT) -> NDArray[np.float64]:
    """``R_body_scanner`` of a side scanner (columns: scanner x, y, z in the body frame)."""
    sign = 1.0 if side == "left" else -1.0
    # vertical scan plane: centre beam out of the side, +90 deg beam up
    x_s = np.array([0.0, sign, 0.0])
    y_s = np.array([0.0, 0.0, 1.0])
    R0 = np.column_stack((x_s, y_s, np.cross(x_s, y_s)))
    # tilt about the centre beam: the +90 deg (up) beam leans backwards, the down beams forwards
    R = R0 @ _rx(-sign * tilt)
    # turn the centre beam forward by yaw_out
    return _rz(-sign * yaw_out) @ R


def side_extrinsic(side: Literal["left", "right"], yaw_out: float = YAW_OUT, tilt: float = TILT) -> tuple[list[float], list[float]]:
    """(translation, rpy) of a side scanner as written in the rig YAML."""
    tx, ty, tz = SIDE_TRANSLATION
    sign = 1.0 if side == "left" else -1.0
    return [tx, sign * ty, tz], list(matrix_to_rpy(side_rotation(side, yaw_out, tilt)))
