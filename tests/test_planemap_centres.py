"""PlaneMap.cell_centres: kept per plane while its cells and its frame stay, the same numbers."""

from __future__ import annotations

import numpy as np

from slam.frontend.planemap import PlaneMap


def _fresh(pmap: PlaneMap, pid: int) -> np.ndarray:
    p = pmap.planes[pid]
    c = np.array(list(p.cells), dtype=np.float64) + 0.5
    return (c[:, :1] * p.u + c[:, 1:] * p.v) * pmap.cell_size - p.d * p.normal


def test_cell_centres_follow_the_plane_not_the_map() -> None:
    pmap = PlaneMap(cell_size=0.25)
    wall = pmap.add(np.array([1.0, 0.0, 0.0]), -2.0, 0, 0.0, 0.0)
    other = pmap.add(np.array([0.0, 1.0, 0.0]), -3.0, 0, 0.0, 0.0)
    ys, zs = np.meshgrid(np.linspace(0, 3, 13), np.linspace(0, 2, 9))
    pmap.extend(wall.id, np.column_stack((np.full(ys.size, 2.0), ys.ravel(), zs.ravel())))
    pmap.extend(other.id, np.array([[1.0, 3.0, 0.5], [1.5, 3.0, 0.5]]))
    first = pmap.cell_centres(wall.id)
    np.testing.assert_array_equal(first, _fresh(pmap, wall.id))
    # another plane's estimate changes: the wall's centres are the same object
    pmap.set_estimate(other.id, np.array([0.0, 1.0, 0.0]), -3.01)
    assert pmap.cell_centres(wall.id) is first
    # the wall's own estimate changes: computed again, as from scratch
    pmap.set_estimate(wall.id, np.array([0.9999, 0.01, 0.0]) / np.linalg.norm([0.9999, 0.01, 0.0]), -2.02)
    moved = pmap.cell_centres(wall.id)
    assert moved is not first
    np.testing.assert_array_equal(moved, _fresh(pmap, wall.id))
    # its extent grows: computed again
    pmap.extend(wall.id, np.array([[2.02, 4.5, 1.0]]))
    grown = pmap.cell_centres(wall.id)
    assert grown.shape[0] == moved.shape[0] + 1
    np.testing.assert_array_equal(grown, _fresh(pmap, wall.id))
