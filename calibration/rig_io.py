"""Write a rig YAML with calibrated extrinsics, their covariances and time offsets (atomically).

The file is the input rig with, for each calibrated scanner, ``T_body_scanner`` replaced by the
estimate (translation [m], rpy [rad]) and its 6x6 covariance over gtsam's (rotation,
translation) tangent coordinates, and ``time_offset`` [s]; it loads with
:func:`common.rig.load_rig`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.rig import Extrinsic, Rig
from common.rotations import matrix_to_rpy

FloatArray = NDArray[np.float64]


def extrinsic_from_matrix(T: FloatArray, covariance: FloatArray | None = None) -> Extrinsic:
    """An :class:`Extrinsic` from a 4x4 ``T_body_scanner`` and an optional 6x6 covariance."""
    M = np.asarray(T, dtype=float)
    cov = None
    if covariance is not None:
        C = np.asarray(covariance, dtype=float)
        cov = (0.5 * (C + C.T)).tolist()
    return Extrinsic(translation=[float(x) for x in M[:3, 3]],
                     rpy=[float(a) for a in matrix_to_rpy(M[:3, :3])], covariance=cov)


def updated_rig(rig: Rig, extrinsics: Mapping[str, tuple[FloatArray, FloatArray | None]],
                time_offsets: Mapping[str, float] | None = None, name: str | None = None) -> Rig:
    """A copy of ``rig`` with the given scanners' ``(T_body_scanner, covariance)`` and offsets."""
    offsets = time_offsets or {}
    scanners = []
    for s in rig.scanners:
        upd: dict[str, Any] = {}
        if s.name in extrinsics:
            T, C = extrinsics[s.name]
            upd["T_body_scanner"] = extrinsic_from_matrix(T, C)
        if s.name in offsets:
            upd["time_offset"] = float(offsets[s.name])
        scanners.append(s.model_copy(update=upd))
    return rig.model_copy(update={"scanners": scanners, "name": name or rig.name})
