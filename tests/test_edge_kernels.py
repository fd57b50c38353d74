"""The compiled edge kernels (slam.frontend.edge_kernels) and the batched BreakFinder against the
per-pair / per-end code they replaced, bit for bit."""

from __future__ import annotations

import math
from dataclasses import fields, replace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from slam.config import SlamConfig
from slam.frontend import edge_kernels as ek
from slam.frontend.edge_finder import BreakFinder, _bracket_end, wall_test
from slam.frontend.edges import (
    Break,
    EdgeMap,
    EdgeParams,
    along_wall,
    break_pairs,
    next_to_segment,
    recess_beyond,
    segment_end,
    segment_owner,
    segment_returns,
    steps_within,
)
from slam.frontend.knots import KnotMirror
from slam.frontend.observations import ScanSegments
from slam.frontend.pending import PendingScan
from slam.frontend.planemap import KIND_WALL, PlaneMap
from slam.frontend.scan_prep import scan_edge_tests
from slam.params import edge_params

# the compiled finder and the per-pair reference agree to rounding (fused multiply-adds differ by CPU)
_RTOL, _ATOL = 1e-9, 1e-12

FloatArray = NDArray[np.float64]


class _ReferenceFinder(BreakFinder):
    """``BreakFinder._find`` and ``_recess_breaks`` as they were before the kernels: the pairs one
    by one (``_pair_breaks``, kept for ``point = "bracket"``), each recess end bracketed, placed
    and checked on its own."""

    def _find(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int]) -> list[Break]:
        segs = p.segs
        is_wall = wall_test(self._pmap, hosts)
        pairs = break_pairs(segs.first_beam, segs.n_points, ids, is_wall, self.params.max_skipped_points)
        walls = [j for j, pid in enumerate(ids.tolist()) if pid >= 0 and is_wall(pid)]
        if not pairs and not walls:
            return []
        origin = (self._knots.pose_at(segs.stamp) @ self._T_body_scanner[segs.scanner][:, 3])[:3]
        out = self._recess_breaks(p, ids, walls, origin)
        if self.params.inline:
            out += self._inline_breaks(p, ids, walls, origin)
        return out + self._pair_breaks(p, ids, pairs, origin)

    def _replaced(self, breaks: list[Break]) -> list[Break]:
        if not breaks:
            return []
        w = self._knots.place(np.array([b.point_body for b in breaks]), np.array([b.time for b in breaks]))
        return [replace(b, point_world=x, u=float(along_wall(self._pmap.planes[b.host].normal) @ x))
                for b, x in zip(breaks, w, strict=True)]

    def _recess_breaks(self, p: PendingScan, ids: NDArray[np.int64], walls: list[int],
                       origin: FloatArray) -> list[Break]:
        segs = p.segs
        T_bs = self._T_body_scanner[segs.scanner]
        sigma = self._range_sigma[segs.scanner]
        out = []
        for j in walls:
            wall = int(ids[j])
            for direction in (1, -1):
                found = p.edge_tests.get((j, direction))
                if found is None:
                    continue
                _, k_in, depth = found
                k_end = segment_end(segs, j, direction)
                got = _bracket_end(segs, j, k_end, direction, min(3.0 * sigma, 0.5 * depth))
                if got is None:
                    continue
                edge_scanner, spacing = got
                r_in, a_in = float(segs.beam_ranges[k_in]), float(segs.beam_angles[k_in])
                pts_scanner = np.array([[edge_scanner[0], edge_scanner[1], 0.0],
                                        [r_in * np.cos(a_in), r_in * np.sin(a_in), 0.0]])
                i_end = int(segs.offsets[j + 1]) - 1 if direction == 1 else int(segs.offsets[j])
                t = float(segs.times[i_end])
                pts_body = self._knots.deskewed(pts_scanner @ T_bs[:3, :3].T + T_bs[:3, 3], np.full(2, t))
                w = self._knots.place(np.vstack((pts_body, segs.virtual_body[j])), np.full(4, t))
                x_world = w[0]
                n_wall = self._pmap.planes[wall].normal
                brk = self._break(p, wall, origin, x_world, pts_body[0], t, spacing, w[1],
                                  float(n_wall @ (w[1] - x_world)), w[3] - w[2])
                if brk is not None:
                    out.append(brk)
        return out


def _rotation(rng: np.random.Generator, tilt: float) -> FloatArray:
    """A rotation about z by a random angle, tilted by up to ``tilt`` rad."""
    a = rng.uniform(-np.pi, np.pi)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    b = rng.uniform(-tilt, tilt)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(b), -np.sin(b)], [0.0, np.sin(b), np.cos(b)]])
    return Rz @ Rx


def _pose(rng: np.random.Generator, tilt: float = 0.3) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = _rotation(rng, tilt)
    T[:3, 3] = rng.normal(0.0, 1.0, 3)
    return T


def _scan(rng: np.random.Generator, n_segments: int, stamp: float) -> tuple[ScanSegments, dict[tuple[int, int], Any]]:
    """A scan of ``n_segments`` segments (in shuffled order) over random beams, with random recess
    tests: not a real scene, but every number the finder reads."""
    n_beams = 360
    angles = np.linspace(-2.3, 2.3, n_beams)
    ranges = rng.uniform(0.5, 6.0, n_beams)
    valid = rng.uniform(size=n_beams) > 0.05
    cuts = np.sort(rng.choice(np.arange(1, n_beams - 1), size=2 * n_segments, replace=False)).reshape(-1, 2)
    perm = rng.permutation(n_segments)
    first, last = cuts[perm, 0], cuts[perm, 1]
    beams = [np.arange(a, b + 1) for a, b in zip(first, last, strict=True)]
    n_points = np.array([b.size for b in beams], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(n_points))).astype(np.int64)
    all_beams = np.concatenate(beams) if beams else np.zeros(0, dtype=np.int64)
    m = int(offsets[-1])
    points_body = rng.normal(0.0, 3.0, (m, 3))
    times = stamp + 1e-4 * all_beams.astype(np.float64)
    direction = rng.normal(size=(n_segments, 2))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    segs = ScanSegments(
        scanner=0, scan_index=0, stamp=stamp, first_beam=first.astype(np.int64), last_beam=last.astype(np.int64),
        n_points=n_points, offsets=offsets, points_body=points_body, times=times,
        virtual_scanner=rng.normal(size=(n_segments, 2, 3)), virtual_body=rng.normal(0.0, 3.0, (n_segments, 2, 3)),
        virtual_times=stamp + rng.uniform(0.0, 0.036, (n_segments, 2)), virtual_sigma=np.full(n_segments, 0.002),
        rms=np.full(n_segments, 0.003), line_centroid=rng.normal(0.0, 3.0, (n_segments, 2)), line_direction=direction,
        beam_angles=angles, beam_ranges=ranges, beam_valid=valid)
    tests: dict[tuple[int, int], Any] = {}
    for j in range(n_segments):
        for d in (1, -1):
            if rng.uniform() < 0.7:
                k_in = int(np.clip(segment_end(segs, j, d) + 3 * d, 0, n_beams - 1))
                tests[(j, d)] = (k_in, k_in, float(rng.uniform(0.01, 0.3)))
            elif rng.uniform() < 0.5:
                tests[(j, d)] = None
    return segs, tests


def _same_breaks(a: list[Break], b: list[Break]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        for f in fields(Break):
            u, v = getattr(x, f.name), getattr(y, f.name)
            if isinstance(u, np.ndarray):
                np.testing.assert_allclose(u, np.asarray(v, dtype=np.float64), rtol=_RTOL, atol=_ATOL, err_msg=f.name)
            elif isinstance(u, float):
                assert type(u) is type(v) and math.isclose(u, v, rel_tol=_RTOL, abs_tol=_ATOL), f.name
            else:
                assert type(u) is type(v) and u == v, f.name


@pytest.mark.parametrize("point", ["midpoint", "higher", "bracket"])
def test_break_finder_matches_the_per_pair_and_per_end_code(point: str) -> None:
    rng = np.random.default_rng({"midpoint": 1, "higher": 2, "bracket": 3}[point])
    n_breaks = 0
    for trial in range(60):
        loose = trial % 3 != 0  # loose checks let most candidates through; strict ones fail many
        params = replace(edge_params(SlamConfig()), point=point, inline=False, min_incidence_deg=rng.uniform(1.0, 30.0),
                         min_segment_points=2 if loose else 6, max_skipped_points=int(rng.integers(0, 8)),
                         **({"max_gap": 1e9, "min_step": 0.0, "max_step": 1e9, "step_tolerance": 1e9} if loose else {}))
        pmap = PlaneMap()
        for _ in range(int(rng.integers(1, 6))):
            n = np.append(rng.normal(size=2), rng.normal(0.0, 0.05))
            pmap.add(n, float(rng.normal(0.0, 3.0)), KIND_WALL if rng.uniform() < 0.7 else KIND_WALL + 1, 0.0, 0.0)
        knots = KnotMirror(0.05)
        knots.start(10.0, None)
        for _ in range(4):
            knots.append(_pose(rng))
        T_bs = [_pose(rng, tilt=1.5)]
        n_segments = int(rng.integers(0, 9)) if trial else 0
        segs, tests = _scan(rng, n_segments, 10.0 + float(rng.uniform(0.0, 0.1)))
        n_planes = len(pmap.planes)
        ids = rng.integers(-1, n_planes, n_segments).astype(np.int64)
        if n_segments >= 2 and rng.uniform() < 0.5:
            ids[rng.integers(0, n_segments)] = ids[rng.integers(0, n_segments)]  # neighbours on one plane
        hosts = {int(rng.integers(0, n_planes)): 0} if rng.uniform() < 0.3 else {}
        p = PendingScan(trial, segs, float(segs.times.max()) if segs.times.size else 10.0,
                        np.full(n_segments, -1, dtype=np.int64), edge_tests=tests)
        p_ref = replace(p)
        new = BreakFinder(params, pmap, knots, T_bs, [0.003])
        ref = _ReferenceFinder(params, pmap, knots, T_bs, [0.003])
        got = new.breaks(p, ids, hosts)
        _same_breaks(got, ref.breaks(p_ref, ids, hosts))
        # asked again (the recess ends remembered) after the knots moved
        knots.T[: knots.n, :3, 3] += 0.01
        ids2 = ids.copy()
        if n_segments:
            ids2[0] = -1
        _same_breaks(new.breaks(p, ids2, hosts), ref.breaks(p_ref, ids2, hosts))
        # and again with the same ids after the knots and a wall moved: the last breaks placed anew
        knots.T[: knots.n, :3, 3] -= 0.02
        pmap.set_estimate(0, pmap.planes[0].normal + 0.01, pmap.planes[0].d)
        _same_breaks(new.breaks(p, ids2, hosts), ref.breaks(p_ref, ids2, hosts))
        n_breaks += len(got)
    assert n_breaks > 50  # the checks were passed as well as failed


def test_break_pairs_kernel_matches_break_pairs() -> None:
    rng = np.random.default_rng(5)
    for trial in range(300):
        k = int(rng.integers(0, 12)) if trial else 0
        first = rng.permutation(np.arange(k) * 10).astype(np.int64)
        n_points = rng.integers(1, 12, k).astype(np.int64)
        ids = rng.integers(-1, 4, k).astype(np.int64)
        walls = {0: True, 1: False, 2: True, 3: bool(rng.uniform() < 0.5)}
        skip = int(rng.integers(0, 10))
        ref = break_pairs(first, n_points, ids, walls.__getitem__, skip)
        wall = np.array([pid >= 0 and walls[pid] for pid in ids.tolist()], dtype=np.bool_)
        got = ek.break_pairs(np.argsort(first, kind="stable"), n_points, wall, skip)
        assert got.shape == (len(ref), 2)
        assert [tuple(r) for r in got.tolist()] == ref


def test_a_3_vector_dot_is_numpys_and_a_stacked_product_is_one_per_pair() -> None:
    """What the kernels and the batched finder assume of numpy: ``a @ b`` of 3-vectors is
    ``a0 b0 + a1 b1 + a2 b2``, its norm the square root of that, and one stacked
    ``(n, 6, 3) @ (n, 3, 1)`` gives each pair's ``(6, 3) @ (3,)``, to rounding (numpy and numba
    may fuse multiply-adds on one CPU and not on another, so equality is to a few ulp)."""
    rng = np.random.default_rng(7)
    a = rng.normal(size=(20000, 3)) * rng.uniform(0.01, 30.0, (20000, 1))
    b = rng.normal(size=(20000, 3))
    by_numpy = np.array([x @ y for x, y in zip(a, b, strict=True)])
    by_hand = (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]
    scale = np.abs(a) @ np.ones(3) * np.abs(b).max(axis=1)  # the size of the terms: the rounding's scale
    assert np.all(np.abs(by_numpy - by_hand) <= 8 * np.finfo(float).eps * scale)
    norms = np.array([np.linalg.norm(x) for x in a])
    np.testing.assert_allclose(norms, np.sqrt((a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1]) + a[:, 2] * a[:, 2]),
                               rtol=8 * np.finfo(float).eps, atol=0.0)
    w = rng.normal(size=(500, 6, 3)) * 5.0
    n = rng.normal(size=(500, 3))
    stacked = np.matmul(w, n[:, :, None])[:, :, 0]
    per_pair = np.array([w[i] @ n[i] for i in range(500)])
    assert np.all(np.abs(stacked - per_pair) <= 8 * np.finfo(float).eps * (np.abs(w) @ np.abs(n)[:, :, None])[:, :, 0])


def _cluster_fresh(params: EdgeParams, pending: list[Break]) -> tuple[list[tuple[list[Break], float]], list[Break]]:
    em = EdgeMap(params, resolve=lambda i: i % 3)
    em.pending = list(pending)
    return em.cluster(), em.pending


def test_cluster_remembering_failed_groups_matches_clustering_afresh() -> None:
    """Breaks arrive, expire and cluster over many calls; an edge map that remembers the groups
    that made no edge finds what a fresh one finds every time."""
    rng = np.random.default_rng(9)
    params = replace(edge_params(SlamConfig()), min_points=4, min_scans=3, cluster_width=0.05, min_height_span=0.15,
                     window=2.0)
    em = EdgeMap(params, resolve=lambda i: i % 3)
    n_found = 0
    for call in range(300):
        now = 0.05 * call
        for _ in range(int(rng.integers(0, 4))):
            n_e = along_wall(np.array([0.0, 1.0, 0.0]))
            x = np.array([rng.choice([1.0, 1.03, 2.5]) + rng.normal(0.0, 0.01), 0.0, rng.uniform(0.5, 2.0)])
            em.pending.append(Break(int(rng.integers(0, 6)), int(rng.choice([-1, 1])), 1, float(n_e @ x), x, x, now,
                                    0.004, call, flat=bool(rng.uniform() < 0.2)))
        em.expire(now)
        expected, left = _cluster_fresh(params, em.pending)
        found = em.cluster()
        assert [[id(b) for b in g] for g, _ in found] == [[id(b) for b in g] for g, _ in expected]
        assert [u for _, u in found] == [u for _, u in expected]
        assert [id(b) for b in em.pending] == [id(b) for b in left]
        n_found += len(found)
    assert n_found > 3


def _reference_scan_edge_tests(segs: ScanSegments, ep: EdgeParams, range_sigma: float) -> dict[tuple[int, int], Any]:
    """``frontend.scan_prep.scan_edge_tests`` as it was before the kernel: segment by segment."""
    out: dict[tuple[int, int], Any] = {}
    owner = segment_owner(segs)
    W = ep.inline_window
    for j in range(segs.n_segments):
        n = int(segs.n_points[j])
        c2, u2 = segs.line_centroid[j], segs.line_direction[j]
        if n >= ep.min_segment_points:
            for direction in (1, -1):
                k_end = segment_end(segs, j, direction)
                if not next_to_segment(owner, k_end, direction):
                    out[(j, direction)] = recess_beyond(k_end, direction, segs.beam_angles, segs.beam_ranges,
                                                        segs.beam_valid, c2, u2, ep.min_step, ep.max_step, ep.max_gap)
        if ep.inline and n >= 2 * W:
            _, xy = segment_returns(segs, j)
            out[(j, 0)] = steps_within(xy, c2, u2, range_sigma, W, ep.min_step, ep.max_step, ep.inline_z)
    return out


def _room_scan(rng: np.random.Generator, n_segments: int, sigma: float) -> ScanSegments:
    """A scan of a room (walls at random distances, doors and posters 2-50 mm behind or proud,
    range noise ``sigma``, dropped beams) cut into ``n_segments`` random beam ranges (gaps,
    neighbours, the scan's ends), each with its returns' fitted line, sometimes perturbed."""
    n_beams = int(rng.integers(200, 1100))
    angles = np.linspace(-2.35, 2.35, n_beams)
    wall = np.repeat(rng.uniform(1.0, 6.0, 6), -(-n_beams // 6))[:n_beams]
    depth = np.zeros(n_beams)
    for _ in range(int(rng.integers(2, 8))):
        a = int(rng.integers(0, n_beams - 10))
        depth[a : a + int(rng.integers(3, 150))] = rng.choice([-1.0, 1.0]) * rng.uniform(0.002, 0.05)
    ranges = (wall + depth) / np.maximum(np.abs(np.cos(angles / 3.0)), 0.3) + rng.normal(0.0, sigma, n_beams)
    valid = rng.uniform(size=n_beams) > rng.uniform(0.0, 0.2)
    cuts = np.sort(rng.choice(np.arange(0, n_beams), size=2 * n_segments, replace=False)).reshape(-1, 2)
    cuts[:, 1] -= rng.integers(0, 2, n_segments) * (cuts[:, 1] > cuts[:, 0])  # some neighbours touch
    first, last = cuts[:, 0].astype(np.int64), cuts[:, 1].astype(np.int64)
    centroid, direction, n_points = np.zeros((n_segments, 2)), np.zeros((n_segments, 2)), np.zeros(n_segments, np.int64)
    for j in range(n_segments):
        b = np.arange(first[j], last[j] + 1)
        b = b[valid[b]]
        xy = np.column_stack((ranges[b] * np.cos(angles[b]), ranges[b] * np.sin(angles[b])))
        if b.size >= 2:
            centroid[j] = xy.mean(axis=0)
            direction[j] = np.linalg.svd(xy - centroid[j])[2][0]
        else:
            centroid[j], direction[j] = rng.normal(0.0, 3.0, 2), (1.0, 0.0)
        if rng.uniform() < 0.2:
            centroid[j] += rng.normal(0.0, 0.01, 2)
        n_points[j] = b.size if rng.uniform() < 0.9 else int(rng.integers(0, 200))
    k = n_segments
    return ScanSegments(
        scanner=0, scan_index=0, stamp=0.0, first_beam=first, last_beam=last, n_points=n_points,
        offsets=np.zeros(k + 1, np.int64), points_body=np.zeros((0, 3)), times=np.zeros(0),
        virtual_scanner=np.zeros((k, 2, 3)), virtual_body=np.zeros((k, 2, 3)), virtual_times=np.zeros((k, 2)),
        virtual_sigma=np.zeros(k), rms=np.zeros(k), line_centroid=centroid, line_direction=direction,
        beam_angles=angles, beam_ranges=ranges, beam_valid=valid)


def test_pairwise_sum_is_numpys_sum() -> None:
    rng = np.random.default_rng(5)
    for n in range(0, 400):
        a = rng.normal(0.0, 1.0, n + 7) * rng.uniform(1e-3, 1e3)
        lo = int(rng.integers(0, 8))
        assert ek._pairwise_sum(a, lo, lo + n) == np.sum(a[lo : lo + n])


@pytest.mark.parametrize("window", [5, 8, 25])
def test_scan_edge_tests_kernel_matches_the_per_segment_code(window: int) -> None:
    """The compiled pass over a scan's segments gives the per-segment functions' dict exactly
    (same keys, same ints, same floats), on noisy rooms with doors and posters, random
    segmentations and parameters; a gap within rounding of ``max_gap`` goes to the reference."""
    rng = np.random.default_rng(window)
    base = edge_params(SlamConfig())
    n_steps = n_recess = n_exact_gap = 0
    for trial in range(150):
        sigma = float(rng.choice([0.001, 0.003, 0.01]))
        segs = _room_scan(rng, int(rng.integers(1, 25)), sigma)
        ep = replace(base, inline_window=window, inline=bool(rng.uniform() < 0.9),
                     min_segment_points=int(rng.integers(2, 20)), min_step=float(rng.uniform(0.001, 0.006)),
                     max_step=float(rng.uniform(0.02, 0.06)), max_gap=float(rng.uniform(0.03, 0.3)),
                     inline_z=float(rng.uniform(2.0, 6.0)))
        if trial % 5 == 0:  # max_gap exactly Python's hypot of a tested end's gap: the kernel defers
            owner, a, r, ok = segment_owner(segs), segs.beam_angles, segs.beam_ranges, segs.beam_valid
            ends = [int(k) for j, k in enumerate(segs.last_beam) if segs.n_points[j] >= ep.min_segment_points
                    and not next_to_segment(owner, int(k), 1) and k + 1 < a.size and ok[k + 1]]
            if ends:
                k = ends[0]
                gap = math.hypot(r[k + 1] * math.cos(a[k + 1]) - r[k] * math.cos(a[k]),
                                 r[k + 1] * math.sin(a[k + 1]) - r[k] * math.sin(a[k]))
                ep = replace(ep, max_gap=gap)
                status = ek.scan_edge_tests(
                    segs.first_beam, segs.last_beam, segs.n_points, a, r, ok, np.cos(a), np.sin(a), segs.line_centroid,
                    segs.line_direction, ep.min_segment_points, ep.inline, ep.inline_window, ep.min_step, ep.max_step,
                    ep.max_gap, sigma, ep.inline_z)[0]
                n_exact_gap += int(np.any(status == 2))
        want = _reference_scan_edge_tests(segs, ep, sigma)
        got = scan_edge_tests(segs, ep, sigma)
        assert list(got) == list(want)
        assert repr(got) == repr(want)  # exact floats, Python ints and floats
        n_steps += sum(len(v) for key, v in want.items() if key[1] == 0)
        n_recess += sum(v is not None for key, v in want.items() if key[1] != 0)
    assert n_steps > 20 and n_recess > 20 and n_exact_gap >= 5


def test_scan_pair_breaks_is_candidates_place_product_and_checks_bit_for_bit() -> None:
    """``BreakFinder._pair_breaks_batch``'s one compiled call against the calls it replaced:
    ``pair_candidates``, ``KnotMirror.place``, numpy's stacked ``(n, 6, 3) @ (n, 3, 1)``, then
    ``pair_breaks``; the same arrays, byte for byte."""
    rng = np.random.default_rng(21)
    n_kept = 0
    for trial in range(200):
        loose = trial % 3 != 0
        knots = KnotMirror(0.05)
        knots.start(10.0, None)
        for _ in range(4):
            knots.append(_pose(rng))
        k = int(rng.integers(0, 10))
        segs, _ = _scan(rng, k, 10.0 + float(rng.uniform(0.0, 0.1)))
        wall = rng.uniform(size=k) < 0.6
        ids = np.where(wall, rng.integers(0, 3, k), rng.integers(-1, 3, k)).astype(np.int64)
        normal = rng.normal(size=(k, 3))
        normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-12)[:, None]
        normal[~wall] = 0.0
        d, along = rng.normal(0.0, 3.0, k), rng.normal(size=(k, 3))
        origin = rng.normal(size=3)
        scalars = ((1e9, 0.0, 1e9) if loose else (0.01, 0.005, 0.05))
        order = np.argsort(segs.first_beam, kind="stable")
        common = (order, segs.n_points, wall, int(rng.integers(0, 6)), segs.first_beam, segs.offsets, segs.points_body,
                  segs.times, segs.virtual_body, segs.virtual_times, 2 if loose else 6, 1e9 if loose else 0.2)
        midpoint = bool(rng.uniform() < 0.5)
        checks = (origin, scalars[0], scalars[1], scalars[2], float(rng.uniform(0.0, 0.5)), 0.1, midpoint)
        jw, jo, lo, ia, ib, pts, times = ek.pair_candidates(*common)
        got = ek.scan_pair_breaks(*common, knots.T, knots.t0, knots.dt, knots.n, ids, normal, d, along, *checks)
        np.testing.assert_array_equal(got[0], jw)
        if not jw.shape[0]:
            assert all(a.shape[0] == 0 for a in got)
            continue
        placed = knots.place(pts, times).reshape(-1, 6, 3)
        h = np.matmul(placed, normal[jw][:, :, None])[:, :, 0]
        want = ek.pair_breaks(h, placed, jw, jo, lo, ia, ib, ids, normal, d, along, segs.points_body, segs.times,
                              *checks)
        for a, b in zip(got[1:], want, strict=True):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        n_kept += int(want[0].sum())
    assert n_kept > 30
