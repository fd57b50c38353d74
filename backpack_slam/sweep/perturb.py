"""Calibration errors: the rig given to SLAM with the tilted scanners' extrinsics perturbed."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from common.rig import Rig
from common.rotations import matrix_to_rpy


def random_unit(rng: np.random.Generator) -> NDArray[np.float64]:
    """A direction drawn uniformly on the unit sphere."""
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def perturb_rig(rig: Rig, rotation_deg: float, translation_m: float, seed: int) -> Rig:
    """``rig`` with every non-reference scanner's ``T_body_scanner`` replaced by
    ``T_delta T_body_scanner``: ``T_delta`` rotates by ``rotation_deg`` about a random axis
    (body frame, about the scanner's origin) and shifts by ``translation_m`` along a random
    direction. Directions are drawn from ``seed`` and the scanner's index, so the same seed
    perturbs in the same directions at every magnitude. Zero magnitudes return ``rig``."""
    if rotation_deg == 0 and translation_m == 0:
        return rig
    scanners = []
    for i, sc in enumerate(rig.scanners):
        if sc.name == rig.reference:
            scanners.append(sc)
            continue
        rng = np.random.default_rng([seed, 6, i])
        axis, shift = random_unit(rng), random_unit(rng)
        T = sc.T_body_scanner.matrix()
        R = Rotation.from_rotvec(np.radians(rotation_deg) * axis).as_matrix() @ T[:3, :3]
        t = T[:3, 3] + translation_m * shift
        ext = sc.T_body_scanner.model_copy(update={"translation": [float(x) for x in t], "rpy": list(matrix_to_rpy(R))})
        scanners.append(sc.model_copy(update={"T_body_scanner": ext}))
    return rig.model_copy(update={"scanners": scanners})
