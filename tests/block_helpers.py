"""Comparing observation blocks in the back-end tests."""

from __future__ import annotations

import numpy as np

from slam.backend.blocks import ObservationBlock


def same_block(a: ObservationBlock, b: ObservationBlock) -> bool:
    """Whether two blocks hold the same knot, plane, points, sigmas and fractions, exactly."""
    return (a.knot == b.knot and a.plane_id == b.plane_id and np.array_equal(a.points, b.points)
            and np.array_equal(a.sigmas, b.sigmas)
            and (a.alphas is None if b.alphas is None else np.array_equal(a.alphas, b.alphas)))
