"""The batched map bookkeeping (``PlaneMap.observe_segments``, ``ObservationBlocks`` by chunks,
``KnotMirror.place_segments_flat``) against the one-at-a-time code it replaced."""

from __future__ import annotations

from fractions import Fraction
from types import SimpleNamespace

import numpy as np
from numpy.typing import NDArray

from slam.frontend import batch_kernels as bk
from slam.frontend.blocks import ObservationBlocks, block_order
from slam.frontend.knots import KnotMirror
from slam.frontend.planemap import PlaneMap, plane_basis
from slam.result import RunStats

FloatArray = NDArray[np.float64]


def _fma(a: float, b: float, c: float) -> float:
    """``a * b + c`` rounded once (exact rational arithmetic, then one rounding to float)."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def test_rows_dot_is_two_fused_multiply_adds_per_row() -> None:
    """``rows_dot`` computes OpenBLAS's gemv formula (the one numpy's ``a @ x`` takes on this
    project's machines) exactly, whatever BLAS is installed; against numpy itself it agrees to
    rounding (bit for bit where numpy's BLAS uses that formula)."""
    rng = np.random.default_rng(1)
    for m in [*range(0, 40), 100, 257, 1000]:
        for _ in range(10):
            a = rng.normal(size=(m, 3)) * rng.uniform(0.01, 300.0)
            x = rng.normal(size=3)
            x /= np.linalg.norm(x)
            got = bk.rows_dot(a, x)
            if m <= 40:
                ref = [float(r[0] * x[0] + r[1] * x[1] + r[2] * x[2]) if m == 1 else
                       _fma(r[2], x[2], _fma(r[0], x[0], r[1] * x[1])) for r in a]
                np.testing.assert_array_equal(got, np.array(ref, dtype=float).reshape(m))
            np.testing.assert_allclose(got, a @ x, rtol=0.0, atol=1e-12 * max(1.0, float(np.abs(a).max(initial=0.0))))


def _observe_reference(pmap: PlaneMap, pids: list[int], pts: list[FloatArray], grows: list[bool], time: float,
                       odometer: float) -> None:
    """``MapBuilder.observe``'s loop before the batch: one ``extend`` and ``seen`` per segment."""
    for pid, p, g in zip(pids, pts, grows, strict=True):
        if g:
            pmap.extend(pid, p)
        pmap.planes[pid].n_segments += 1
        pmap.seen(pid, time, odometer)


def _planes(rng: np.random.Generator, samples_until: int) -> tuple[PlaneMap, PlaneMap]:
    pmaps = (PlaneMap(samples_until=samples_until), PlaneMap(samples_until=samples_until))
    for _ in range(5):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d = float(rng.normal())
        for pm in pmaps:
            pm.add(n, d, 1, 0.0, 0.0)
    return pmaps


def _on_grid(rng: np.random.Generator, m: int) -> FloatArray:
    """Points (m, 3) often sharing a coordinate (ties of the extreme points) and a cell."""
    return np.round(rng.normal(0.0, 1.5, (m, 3)) * 4.0) / 4.0 if rng.uniform() < 0.5 else rng.normal(0.0, 1.5, (m, 3))


def test_observe_segments_matches_extend_and_seen_one_segment_at_a_time() -> None:
    rng = np.random.default_rng(3)
    for trial in range(60):
        new, old = _planes(rng, samples_until=int(rng.integers(0, 6)))
        for step in range(4):
            k = int(rng.integers(0, 9))
            pids = rng.integers(0, 5, k).tolist()
            sizes = rng.integers(0 if trial % 3 == 0 else 1, 12, k)
            pts = [_on_grid(rng, int(s)) for s in sizes]
            grows = (rng.uniform(size=k) > 0.2).tolist()
            bounds = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
            flat = np.concatenate([np.empty((0, 3)), *pts])
            t, odo = 10.0 + step * 0.3, 2.0 + step
            new.observe_segments(pids, flat, bounds, np.array(grows, dtype=bool), t, odo)
            _observe_reference(old, pids, pts, grows, t, odo)
            for a, b in zip(new.planes, old.planes, strict=True):
                assert list(a.cells) == list(b.cells)  # the same set, in the same iteration order
                assert a.n_segments == b.n_segments and a.seen_buckets == b.seen_buckets
                assert a.last_seen_time == b.last_seen_time and a.last_seen_odometer == b.last_seen_odometer
                assert (a.extremes is None) == (b.extremes is None)
                if a.extremes is not None:
                    np.testing.assert_array_equal(a.extremes, b.extremes)
                assert len(a.samples) == len(b.samples)
                for x, y in zip(a.samples, b.samples, strict=True):
                    np.testing.assert_array_equal(x, y)


def test_observe_segments_of_no_segments_changes_nothing() -> None:
    pm = PlaneMap()
    pm.add(np.array([1.0, 0.0, 0.0]), 0.0, 1, 0.0, 0.0)
    pm.observe_segments([], np.empty((0, 3)), np.zeros(1, dtype=np.int64), np.zeros(0, dtype=bool), 1.0, 1.0)
    assert pm.planes[0].n_segments == 0 and not pm.planes[0].cells and pm.planes[0].last_seen_time == 0.0


def test_grow_extremes_kernel_matches_the_numpy_method() -> None:
    rng = np.random.default_rng(4)
    for _ in range(200):
        n = rng.normal(size=3)
        u, v = plane_basis(n / np.linalg.norm(n))
        pm = PlaneMap()
        p = pm.add(n, 0.0, 1, 0.0, 0.0)
        ext = np.zeros((1, 4, 3))
        has = np.zeros(1, dtype=bool)
        for _ in range(4):
            pts = _on_grid(rng, int(rng.integers(0, 5)))
            PlaneMap._grow_extremes(p, pts)
            bk.grow_extremes(pts, np.array([0, pts.shape[0]]), np.zeros(1, dtype=np.int64), np.ones(1, dtype=bool),
                             ext, has, u[None], v[None])
            assert has[0] == (p.extremes is not None)
            if has[0]:
                np.testing.assert_array_equal(ext[0], p.extremes)


def test_place_segments_flat_is_place_segments_in_one_array() -> None:
    rng = np.random.default_rng(6)
    knots = KnotMirror(0.05)
    knots.start(0.0, None)
    for i in range(6):
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.02 * i, 0.0]
        knots.append(T)
    counts = rng.integers(1, 40, 9)
    offsets = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    segs = SimpleNamespace(offsets=offsets, n_points=counts, points_body=rng.normal(size=(offsets[-1], 3)),
                           times=np.sort(rng.uniform(0.0, 0.25, offsets[-1])))
    for js in (np.array([], dtype=np.int64), np.array([4]), np.array([8, 0, 3, 5])):
        per = np.repeat([8, 12], [js.size // 2, js.size - js.size // 2])
        flat, bounds = knots.place_segments_flat(segs, js, per)  # type: ignore[arg-type]
        parts = knots.place_segments(segs, js, per)  # type: ignore[arg-type]
        assert bounds.shape == (js.size + 1,) and bounds[0] == 0 and bounds[-1] == flat.shape[0]
        assert len(parts) == js.size
        for i, part in enumerate(parts):
            np.testing.assert_array_equal(flat[bounds[i] : bounds[i + 1]], part)


def test_block_order_groups_rows_by_first_occurrence() -> None:
    rng = np.random.default_rng(7)
    for n in (0, 1, 2, 50):
        knot = rng.integers(0, 4, n).astype(np.int64)
        pid = rng.integers(-2, 3, n).astype(np.int64)
        order, starts, first = block_order(knot, pid)
        ref: dict[tuple[int, int], list[int]] = {}
        for i, key in enumerate(zip(knot.tolist(), pid.tolist(), strict=True)):
            ref.setdefault(key, []).append(i)
        assert [(int(knot[f]), int(pid[f])) for f in first] == list(ref)
        got = [order[starts[g] : starts[g + 1]].tolist() for g in range(first.size)]
        assert got == list(ref.values())


class _Sink:
    def __init__(self) -> None:
        self.blocks: list[tuple[int, int, FloatArray, FloatArray, FloatArray]] = []

    def add_observations(self, knot: int, plane_id: int, points: FloatArray, alphas: FloatArray,
                         sigmas: FloatArray) -> int:
        self.blocks.append((knot, plane_id, points, alphas, sigmas))
        return len(self.blocks) - 1


def test_observation_blocks_with_breaks_match_the_dict_of_rows() -> None:
    """Segments and breaks interleaved: the blocks in the order first met, rows in order, the
    arrays as ``np.array`` of the rows made them."""
    rng = np.random.default_rng(9)
    knots = KnotMirror(0.05)
    knots.start(100.0, None)
    for _ in range(8):
        knots.append(np.eye(4))
    k = 12
    segs = SimpleNamespace(virtual_times=np.sort(rng.uniform(100.0, 100.4, (k, 2)), axis=1),
                           virtual_body=rng.normal(size=(k, 2, 3)), virtual_sigma=rng.uniform(0.001, 0.01, k))
    stats = RunStats()
    blocks = ObservationBlocks(knots, stats)
    ref: dict[tuple[int, int], tuple[list[FloatArray], list[float], list[float]]] = {}
    for step in range(6):
        js = rng.permutation(k)[: int(rng.integers(0, 5))].astype(np.int64)
        pids = rng.integers(0, 3, js.size).tolist()
        blocks.segments(segs, js, pids)  # type: ignore[arg-type]
        for j, pid in zip(js.tolist(), pids, strict=True):
            idx, alpha = knots.fractions(segs.virtual_times[j])
            for e in range(2):
                rows = ref.setdefault((int(idx[e]), pid), ([], [], []))
                rows[0].append(segs.virtual_body[j, e])
                rows[1].append(float(alpha[e]))
                rows[2].append(float(segs.virtual_sigma[j]))
        brk = SimpleNamespace(time=100.0 + 0.07 * step, point_body=rng.normal(size=3), sigma=0.01 * step)
        pid = int(rng.integers(0, 3))
        blocks.point(brk, pid)  # type: ignore[arg-type]
        idx, alpha = knots.fractions(np.array([brk.time]))
        rows = ref.setdefault((int(idx[0]), pid), ([], [], []))
        rows[0].append(brk.point_body)
        rows[1].append(float(alpha[0]))
        rows[2].append(float(brk.sigma))
    sink = _Sink()
    blocks.flush(sink)  # type: ignore[arg-type]
    assert [(b[0], b[1]) for b in sink.blocks] == list(ref)
    for (_, _, pts, al, sg), (rp, ra, rs) in zip(sink.blocks, ref.values(), strict=True):
        for got, want in ((pts, np.array(rp)), (al, np.array(ra)), (sg, np.array(rs))):
            np.testing.assert_array_equal(got, want)
            assert got.dtype == want.dtype and got.shape == want.shape and got.flags.c_contiguous
    assert stats.observation_blocks == len(ref) and stats.edge_observations == 6
    blocks.flush(sink)  # empty now
    assert len(sink.blocks) == len(ref)


def test_on_plane_many_matches_on_plane() -> None:
    from slam.frontend.plane_init import PooledSegment, on_plane

    rng = np.random.default_rng(10)
    p = SimpleNamespace(coplanar_distance=0.01, sample_distance=0.03)
    n_total = 0
    for _ in range(30):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d = float(rng.normal())
        items = []
        for _ in range(int(rng.integers(1, 12))):
            m = int(rng.integers(1, 9))
            base = rng.normal(size=(m + 2, 3))
            base -= (base @ n + d)[:, None] * n  # on the plane, then off by a few mm to a few cm
            base += rng.normal(0.0, rng.choice([0.001, 0.005, 0.02]), (m + 2, 1)) * n
            items.append(PooledSegment(ref=(0, 0), time=0.0, scan_serial=0, centroid=base.mean(axis=0),
                                       direction=n, endpoints=base[:2], samples=base[2:], line=base[:2],
                                       scan_normal=n, origin=np.zeros(3)))
        lines = np.array([s.line for s in items])
        samples = np.concatenate([s.samples for s in items])
        start = np.concatenate(([0], np.cumsum([s.samples.shape[0] for s in items]))).astype(np.int64)
        idx = rng.permutation(len(items))[: int(rng.integers(0, len(items) + 1))].astype(np.int64)
        got = bk.on_plane_many(lines, samples, start, idx, n, d, p.coplanar_distance, p.sample_distance)
        want = [on_plane(items[i], n, d, p) for i in idx]  # type: ignore[arg-type]
        assert got.tolist() == want
        n_total += sum(want)
    assert n_total > 10


def _overlaps_reference(ext: set[tuple[int, int]], cells: list[list[int]], dilate: int) -> bool:
    """The dilated-extent test by brute force."""
    if not ext:
        return False
    return any(abs(eu - c[0]) <= max(dilate, 0) and abs(ev - c[1]) <= max(dilate, 0) for eu, ev in ext for c in cells)


def test_overlaps_cells_matches_brute_force_as_the_extent_grows() -> None:
    rng = np.random.default_rng(13)
    pm = PlaneMap()
    pid = pm.add(np.array([0.0, 1.0, 0.0]), 0.0, 1, 0.0, 0.0).id
    assert not pm.overlaps_cells(pid, [[0, 0]], 3)  # no extent yet
    hits = 0
    for _ in range(30):
        pm.extend(pid, rng.normal(0.0, 1.0, (int(rng.integers(1, 6)), 3)))
        for _ in range(20):
            cells = rng.integers(-12, 12, (int(rng.integers(0, 4)), 2)).tolist()
            dilate = int(rng.integers(-1, 4))
            got = pm.overlaps_cells(pid, cells, dilate)
            assert got == _overlaps_reference(pm.planes[pid].cells, cells, dilate)
            hits += got
    assert hits > 50


def test_cross_rows_is_numpys_cross_bit_for_bit() -> None:
    rng = np.random.default_rng(14)
    for n in (0, 1, 2, 7, 100):
        a = rng.normal(size=3) * rng.uniform(0.01, 100.0)
        b = rng.normal(size=(n, 3)) * rng.uniform(0.01, 100.0)
        np.testing.assert_array_equal(bk.cross_rows(a, b), np.cross(a, b).reshape(-1, 3))


def test_place_subsampled_is_subsample_then_place() -> None:
    """``KnotMirror.place_segments_flat``'s one compiled call against the calls it replaced: the
    rows ``subsample_rows`` picks, gathered in numpy and placed with ``KnotMirror.place``."""
    from slam.frontend import kernels as fk
    from slam.trajectory.interpolation import se3_exp

    rng = np.random.default_rng(16)
    for _ in range(40):
        knots = KnotMirror(0.05)
        knots.start(float(rng.uniform(0.0, 100.0)), None)
        T = np.eye(4)
        for _ in range(int(rng.integers(2, 12))):
            T = T @ se3_exp(rng.normal(0.0, [0.05, 0.05, 0.2, 0.1, 0.1, 0.02]))
            knots.append(T)
        counts = rng.integers(1, 60, int(rng.integers(1, 12)))
        offsets = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
        t_end = knots.time(knots.n - 1)
        segs = SimpleNamespace(offsets=offsets, n_points=counts.astype(np.int64),
                               points_body=rng.normal(0.0, 5.0, (offsets[-1], 3)),
                               times=np.sort(rng.uniform(knots.time(0) - 0.02, t_end + 0.02, offsets[-1])))
        js = rng.permutation(counts.size)[: int(rng.integers(1, counts.size + 1))].astype(np.int64)
        per = rng.choice([1, 3, 8, 12], js.size).astype(np.int64)
        sel, splits = fk.subsample_rows(offsets, segs.n_points, js, per)
        want = knots.place(segs.points_body[sel], segs.times[sel])
        got, bounds = knots.place_segments_flat(segs, js, per)  # type: ignore[arg-type]
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(bounds, np.concatenate(([0], splits, [want.shape[0]])))
