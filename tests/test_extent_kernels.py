"""The planes' compiled extent index (slam.frontend.extent_index, extent_kernels) against the set
and array code it replaced: the same booleans on random extents, cells and margins."""

from __future__ import annotations

import numpy as np

from slam.frontend import kernels as fk
from slam.frontend.extent_index import ExtentIndex
from slam.frontend.planemap import PlaneMap


def _overlaps_cells_reference(ext: set[tuple[int, int]], cells: list[list[int]], dilate: int) -> bool:
    """``PlaneMap.overlaps_cells`` before the index: the set, then one pass over its cells."""
    if not ext:
        return False
    for c in cells:
        if (c[0], c[1]) in ext:
            return True
    if dilate <= 0 or not cells:
        return False
    extent = np.array(list(ext), dtype=np.int64).reshape(-1, 2)
    return bool(fk.near_cells(extent, np.array(cells, dtype=np.int64).reshape(-1, 2), int(dilate)))


def _random_map(rng: np.random.Generator, n_planes: int) -> PlaneMap:
    """Planes with random extents grown by both of the plane map's paths (``extend`` and
    ``observe_segments``), some left empty."""
    pm = PlaneMap(cell_size=float(rng.choice([0.1, 0.25, 0.5])))
    for _ in range(n_planes):
        n = rng.normal(size=3)
        pm.add(n, float(rng.normal()), 1, 0.0, 0.0)
    for _ in range(int(rng.integers(0, 12))):
        pid = int(rng.integers(0, n_planes))
        scale = float(rng.choice([0.5, 3.0, 20.0]))
        pm.extend(pid, rng.normal(0.0, scale, (int(rng.integers(0, 30)), 3)) + rng.normal(0.0, 10.0, 3))
    for _ in range(int(rng.integers(0, 6))):
        k = int(rng.integers(1, 6))
        pids = rng.integers(0, n_planes, k).tolist()
        counts = rng.integers(0, 25, k)
        bounds = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
        pts = rng.normal(0.0, float(rng.choice([1.0, 5.0])), (int(bounds[-1]), 3))
        pm.observe_segments(pids, pts, bounds, rng.random(k) < 0.8, 1.0, 0.0)
    return pm


def test_the_index_holds_the_planes_cell_sets() -> None:
    rng = np.random.default_rng(31)
    for _ in range(40):
        pm = _random_map(rng, int(rng.integers(1, 8)))
        for p in pm.planes:
            assert pm.extents.cells_of_plane(p.id) == p.cells
            assert int(pm.extents.count[p.id]) == len(p.cells)
        assert pm.extents.size == sum(len(p.cells) for p in pm.planes)


def test_overlaps_cells_matches_the_set_reference() -> None:
    rng = np.random.default_rng(32)
    hits = misses = 0
    for _ in range(60):
        pm = _random_map(rng, int(rng.integers(1, 6)))
        for _ in range(40):
            pid = int(rng.integers(0, len(pm)))
            ext = pm.planes[pid].cells
            if ext and rng.random() < 0.7:  # near the extent
                base = np.array(list(ext))[rng.integers(0, len(ext))]
                cells = (base + rng.integers(-15, 16, (int(rng.integers(0, 4)), 2))).tolist()
            else:
                cells = rng.integers(-300, 300, (int(rng.integers(0, 4)), 2)).tolist()
            dilate = int(rng.integers(-1, 14))
            got = pm.overlaps_cells(pid, cells, dilate)
            assert got == _overlaps_cells_reference(ext, cells, dilate)
            hits += got
            misses += not got
    assert hits > 300 and misses > 300


def test_pairs_near_matches_the_per_pair_reference() -> None:
    rng = np.random.default_rng(33)
    n_each = 0
    for _ in range(60):
        pm = _random_map(rng, int(rng.integers(1, 6)))
        n = int(rng.integers(0, 40))
        pair_id = rng.integers(0, len(pm), n).astype(np.int64)
        cells = np.empty((n, 3, 2), dtype=np.int64)
        for i in range(n):
            ext = pm.planes[int(pair_id[i])].cells
            base = np.array(list(ext))[rng.integers(0, len(ext))] if ext else np.zeros(2, dtype=np.int64)
            cells[i] = base + rng.integers(-12, 13, (3, 2))
        dilate = rng.integers(-1, 10, n).astype(np.int64)
        whole = rng.random(n) < 0.5
        near, each = pm.extents.pairs_near(pair_id, cells, dilate, whole)
        for i in range(n):
            ext, c, d = pm.planes[int(pair_id[i])].cells, cells[i].tolist(), int(dilate[i])
            want = _overlaps_cells_reference(ext, c, d)
            assert bool(near[i]) == want
            want_each = all(_overlaps_cells_reference(ext, [x], d) for x in c) if (want and whole[i]) else want
            assert bool(each[i]) == want_each
            n_each += bool(whole[i] and want and not want_each)
    assert n_each > 20


def test_the_table_grows_past_its_capacity() -> None:
    rng = np.random.default_rng(34)
    ix = ExtentIndex(capacity=8)
    want: dict[int, set[tuple[int, int]]] = {}
    for _ in range(50):
        pid = int(rng.integers(0, 90))
        ix.add_plane(pid)
        cells = rng.integers(-40, 40, (int(rng.integers(0, 20)), 2)).astype(np.int64)
        ix.insert_one(pid, cells)
        want.setdefault(pid, set()).update(map(tuple, cells.tolist()))
    for pid, cells in want.items():
        assert ix.cells_of_plane(pid) == cells
        if cells:
            c = np.array(list(cells))
            assert list(ix.box[pid]) == [c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max()]
    assert ix.size == sum(len(c) for c in want.values()) and ix.keys.shape[0] >= 2 * ix.size
