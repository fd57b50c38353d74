"""The batch kernels of slam.frontend.batch_kernels against the numpy code they replaced."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from segmentation import Scanline
from segmentation.base import build_segmentation
from slam.frontend import batch_kernels as bk
from slam.frontend.observations import scan_segments, scan_segments_numpy
from slam.frontend.planemap import PlaneMap, plane_basis

FloatArray = NDArray[np.float64]


def _crossings_reference(dirs: FloatArray, r: FloatArray, o: FloatArray, normal: FloatArray, d: float,
                         u: FloatArray, v: FloatArray, margin: float, min_range: float,
                         min_cos: float) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The per-plane numpy code of ``TransientFilter.check`` before the kernel."""
    s = float(normal @ o) + d
    den = dirs @ normal
    behind = (s + r * den) * np.sign(s)
    steep = np.abs(den) > min_cos
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -s / den
    cross = steep & (t > min_range) & np.isfinite(t) & (behind < margin)
    k = np.flatnonzero(cross)
    x = o + t[k, None] * dirs[k]
    return np.column_stack((x @ u, x @ v)), behind[k] < -margin


def test_plane_crossings_match_the_per_plane_reference() -> None:
    rng = np.random.default_rng(11)
    total = 0
    for trial in range(20):
        m, n_planes = int(rng.integers(0, 300)), int(rng.integers(0, 6))
        a = rng.uniform(-np.pi, np.pi, m)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        dirs = np.column_stack((np.cos(a), np.sin(a))) @ R[:, :2].T
        r = rng.uniform(0.1, 8.0, m)
        o = rng.normal(size=3)
        normals = rng.normal(size=(n_planes, 3))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        offsets = rng.normal(0.0, 2.0, n_planes)
        if trial == 0 and n_planes:
            offsets[0] = -float(normals[0] @ o)  # the scanner on the plane: no crossing
        uv_axes = [plane_basis(n) for n in normals]
        us = np.array([b[0] for b in uv_axes]).reshape(-1, 3)
        vs = np.array([b[1] for b in uv_axes]).reshape(-1, 3)
        start, uv, through = bk.plane_crossings(dirs, r, o, normals, offsets, us, vs, 0.1, 0.3, 0.3)
        assert start.shape == (n_planes + 1,) and start[0] == 0
        total += int(start[-1])
        for p in range(n_planes):
            uv_ref, through_ref = _crossings_reference(dirs, r, o, normals[p], float(offsets[p]), us[p], vs[p],
                                                       0.1, 0.3, 0.3)
            lo, hi = start[p], start[p + 1]
            np.testing.assert_array_equal(through[lo:hi], through_ref)
            np.testing.assert_allclose(uv[lo:hi], uv_ref.reshape(-1, 2), rtol=0.0, atol=1e-12)
    assert total > 100  # the crossings were exercised


class _Sink:
    """Records the blocks handed to the back end."""

    def __init__(self) -> None:
        self.blocks: list[tuple[int, int, FloatArray, FloatArray, FloatArray]] = []

    def add_observations(self, knot: int, plane_id: int, points: FloatArray, alphas: FloatArray,
                         sigmas: FloatArray) -> int:
        self.blocks.append((knot, plane_id, points, alphas, sigmas))
        return len(self.blocks) - 1


def test_observation_blocks_of_many_segments_match_one_segment_at_a_time() -> None:
    """``ObservationBlocks.segments`` against the per-segment rows of the code it replaced."""
    from types import SimpleNamespace

    from slam.frontend.blocks import ObservationBlocks
    from slam.frontend.knots import KnotMirror
    from slam.result import RunStats

    rng = np.random.default_rng(5)
    knots = KnotMirror(0.05)
    knots.start(100.0, None)
    for _ in range(8):
        knots.append(np.eye(4))
    k = 30
    t = np.sort(rng.uniform(100.0, 100.4, (k, 2)), axis=1)
    segs = SimpleNamespace(virtual_times=t, virtual_body=rng.normal(size=(k, 2, 3)), virtual_sigma=rng.uniform(0.001, 0.01, k))
    js = rng.permutation(k)[:20].astype(np.int64)
    pids = rng.integers(0, 4, js.size).tolist()
    # the reference: one knot lookup per segment, rows of one-element arrays
    ref: dict[tuple[int, int], list[tuple[FloatArray, FloatArray, FloatArray]]] = {}
    for j, pid in zip(js.tolist(), pids, strict=True):
        idx, alpha = knots.fractions(segs.virtual_times[j])
        for q in range(2):
            ref.setdefault((int(idx[q]), pid), []).append(
                (segs.virtual_body[j, q], np.array([alpha[q]]), np.array([segs.virtual_sigma[j]])))
    blocks = ObservationBlocks(knots, RunStats())
    blocks.segments(segs, js[:7], pids[:7])  # type: ignore[arg-type]
    for j, pid in zip(js[7:10].tolist(), pids[7:10], strict=True):
        blocks.segment(segs, j, pid)  # type: ignore[arg-type]
    blocks.segments(segs, js[10:], pids[10:])  # type: ignore[arg-type]
    sink = _Sink()
    blocks.flush(sink)  # type: ignore[arg-type]
    assert [(b[0], b[1]) for b in sink.blocks] == list(ref)
    for (_, _, pts, al, sg), rows in zip(sink.blocks, ref.values(), strict=True):
        np.testing.assert_array_equal(pts, np.array([r[0] for r in rows]))
        np.testing.assert_array_equal(al, np.concatenate([r[1] for r in rows]))
        np.testing.assert_array_equal(sg, np.concatenate([r[2] for r in rows]))
        assert al.dtype == sg.dtype == np.float64


def _check_reference(tf: Any, scans: list[Any]) -> list[int]:
    """``TransientFilter.check`` as it was before the batch kernel: scan by scan, plane by plane."""
    from scipy.spatial import cKDTree

    from slam.frontend.transients import MIN_COS, MIN_RANGE

    pr = tf.params
    ids = tf.candidates()
    found: list[int] = []
    for p in scans:
        segs = p.segs
        valid = np.flatnonzero(segs.beam_valid)[:: pr.beam_step]
        if valid.size == 0:
            continue
        T = tf._knots.pose_at(segs.stamp) @ tf._T_body_scanner[segs.scanner]
        a = segs.beam_angles[valid]
        r = segs.beam_ranges[valid].astype(np.float64)
        dirs = np.column_stack((np.cos(a), np.sin(a))) @ T[:3, :2].T
        o = T[:3, 3]
        for pid in ids:
            plane = tf._pmap.planes[pid]
            if not plane.active or not plane.samples:
                continue
            uv, far = _crossings_reference(dirs, r, o, plane.normal, plane.d, plane.u, plane.v, pr.margin,
                                           MIN_RANGE, MIN_COS)
            if uv.shape[0] == 0:
                continue
            pts = np.concatenate(plane.samples)
            tree = cKDTree(np.column_stack((pts @ plane.u, pts @ plane.v)))
            inside = np.isfinite(tree.query(uv, distance_upper_bound=pr.near)[0])
            tf.through[pid] = tf.through.get(pid, 0) + int(np.count_nonzero(inside & far))
            tf.returned[pid] = tf.returned.get(pid, 0) + int(np.count_nonzero(inside & ~far))
        for pid in ids:
            if pid not in found and tf.through.get(pid, 0) >= pr.min_through \
                    and tf.through[pid] > pr.ratio * tf.returned.get(pid, 0):
                found.append(pid)
    return found


def test_transient_check_matches_the_scan_by_scan_reference() -> None:
    """Walls seen through by some scans and not by others: the batched check finds the same
    planes, in the same order, with the same counts as the per-scan, per-plane loop."""
    from types import SimpleNamespace

    from slam.frontend.knots import KnotMirror
    from slam.frontend.transients import TransientFilter, TransientParams

    rng = np.random.default_rng(8)
    params = TransientParams(use=True, probation=60, margin=0.1, near=0.05, min_through=30, ratio=1.0, beam_step=2)
    knots = KnotMirror(0.05)
    knots.start(0.0, None)
    for _ in range(4):
        knots.append(np.eye(4))
    found_any = 0
    for trial in range(6):
        pmaps = [PlaneMap(samples_until=60), PlaneMap(samples_until=60)]
        for x in (1.0, 2.0, -1.5, 3.0):  # walls x = const, with sampled points in a patch
            pts = np.column_stack((np.full(400, x), rng.uniform(-1.0, 1.0, 400), rng.uniform(-0.5, 0.5, 400)))
            for pm in pmaps:
                pm.extend(pm.add(np.array([1.0, 0.0, 0.0]), -x, 1, 0.0, 0.0).id, pts)
        scans = []
        for k in range(5):
            a = np.linspace(-1.2, 1.2, 240)
            # some scans see the wall at x = 1 (returns there), others pass through it to x = 3
            depth = 1.0 if (k + trial) % 3 == 0 else 3.0
            ranges = depth / np.cos(a) + rng.normal(0.0, 0.005, a.size)
            valid = rng.uniform(size=a.size) > 0.1
            segs = SimpleNamespace(beam_valid=valid if k != 2 else np.zeros(a.size, bool), stamp=0.05 * k,
                                   scanner=0, beam_angles=a, beam_ranges=ranges.astype(np.float32))
            scans.append(SimpleNamespace(segs=segs))
        T_bs = [np.eye(4)]
        new = TransientFilter(params, pmaps[0], knots, T_bs, lambda: {3})
        old = TransientFilter(params, pmaps[1], knots, T_bs, lambda: {3})
        for chunk in (scans[:2], scans[2:]):
            got = new.check(chunk)  # type: ignore[arg-type]
            assert got == _check_reference(old, chunk)
            found_any += len(got)
        assert new.through == old.through and new.returned == old.returned
    assert found_any > 0


def test_near_test_decides_as_the_2d_tree_query() -> None:
    """``_near_any`` over points sorted by u against ``cKDTree.query(distance_upper_bound=near)``,
    with queries exactly around ``near`` from a point (the last bits decide) and far off."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(12)
    near = 0.02
    for trial in range(40):
        n = int(rng.integers(1, 60))
        pts = rng.uniform(-0.3, 0.3, (n, 2)) if trial % 2 else np.round(rng.uniform(-0.3, 0.3, (n, 2)) * 50) / 50
        k = rng.integers(0, n, 200)
        ang = rng.uniform(0.0, 2.0 * np.pi, 200)
        r = near * (1.0 + rng.integers(-3, 4, 200) * 2.2e-16)
        r[:50] = rng.uniform(0.0, 0.1, 50)
        q = pts[k] + np.column_stack((r * np.cos(ang), r * np.sin(ang)))
        want = np.isfinite(cKDTree(pts).query(q, distance_upper_bound=near)[0])
        order = np.argsort(pts[:, 0], kind="stable")
        su, sv = np.ascontiguousarray(pts[order, 0]), np.ascontiguousarray(pts[order, 1])
        got = np.array([bk._near_any(su, sv, float(a), float(b), near) for a, b in q])
        np.testing.assert_array_equal(got, want)
    assert not bk._near_any(np.empty(0), np.empty(0), 0.0, 0.0, near)


def _random_segmentation(rng: np.random.Generator, n_segments: int) -> tuple[Scanline, Any]:
    """A noisy scan with dropped beams and ``n_segments`` random runs of its valid returns (gaps
    between them, single returns included), fitted by the segmenters' own code."""
    n_beams = int(rng.integers(3, 1100))
    angles = np.linspace(-2.35, 2.35, n_beams)
    ranges = rng.uniform(0.5, 8.0, n_beams) * (1.0 + rng.normal(0.0, 0.01, n_beams))
    ranges[rng.uniform(size=n_beams) < rng.uniform(0.0, 0.3)] = np.nan
    times = 100.0 + rng.uniform(0.0, 0.04) * np.arange(n_beams) / n_beams
    line = Scanline.from_ranges(ranges, angles, times)
    m = line.n_valid
    k = min(n_segments, m // 2)
    cuts = np.sort(rng.choice(m, size=2 * k, replace=False)).reshape(-1, 2) if k else np.zeros((0, 2), np.int64)
    first, last = cuts[:, 0].astype(np.int64), cuts[:, 1].astype(np.int64)
    point_labels = np.full(m, -1, dtype=np.int64)
    for j, (a, b) in enumerate(zip(first, last, strict=True)):
        point_labels[a : b + 1] = j
    return line, build_segmentation(line, point_labels, first, last, np.full(m, 0.003), "test", {})


def test_lift_segments_matches_the_numpy_scan_segments() -> None:
    """``scan_segments`` (one compiled pass) gives ``scan_segments_numpy``'s arrays byte for byte:
    random scans, segmentations, rig poses and noise; no segment, one return and 2-point runs."""
    rng = np.random.default_rng(9)
    for trial in range(300):
        line, seg = _random_segmentation(rng, int(rng.integers(0, 30)))
        if trial % 50 == 0:  # one labelled return: numpy's one-row product, kept
            labels = np.full_like(seg.labels, -1)
            labels[line.valid_index[0]] = 0
            seg = replace(seg, labels=labels, first_beam=seg.first_beam[:1], last_beam=seg.first_beam[:1],
                          centroid=seg.centroid[:1], direction=seg.direction[:1], rms=seg.rms[:1])
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = q, rng.normal(0.0, 0.5, 3)
        args = (line, seg, T, 1, trial, float(rng.uniform(0.001, 0.03)), float(rng.choice([0.0, 0.002])))
        want, got = scan_segments_numpy(*args), scan_segments(*args)
        for f in fields(want):
            a, b = getattr(want, f.name), getattr(got, f.name)
            if isinstance(a, np.ndarray):
                assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), f.name
            else:
                assert a == b, f.name


def _strided_beams_reference(angles: list, ranges: list, valid: list, T: list, step: int) -> tuple:
    """The numpy code ``frontend.transients`` used per scan before ``strided_beams_world``."""
    dirs, rs, origins, bounds = [], [], [], [0]
    for a_all, r_all, v_all, T_i in zip(angles, ranges, valid, T, strict=True):
        keep = np.flatnonzero(v_all)[::step]
        if keep.size == 0:
            continue
        a = a_all[keep]
        dirs.append(np.column_stack((np.cos(a), np.sin(a))) @ T_i[:3, :2].T)
        rs.append(r_all[keep].astype(np.float64))
        origins.append(T_i[:3, 3])
        bounds.append(bounds[-1] + keep.size)
    if not dirs:
        return np.empty((0, 3)), np.empty(0), np.array(bounds), np.empty((0, 3))
    return np.concatenate(dirs), np.concatenate(rs), np.array(bounds), np.array(origins)


def test_strided_beams_world_is_the_per_scan_numpy_code_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    for trial in range(40):
        n_scans, step = int(rng.integers(1, 7)), int(rng.integers(1, 4))
        angles, ranges, valid, T = [], [], [], []
        for i in range(n_scans):
            n = int(rng.choice([0, 1, 2, 5, 300, 1081]))
            a = np.linspace(-2.35, 2.35, n) if n > 1 else rng.uniform(-3, 3, n)
            v = rng.random(n) < rng.choice([0.0, 0.002, 0.5, 1.0])
            if trial == 0 and i == 0 and n:
                v[:] = False
                v[int(rng.integers(0, n))] = True  # one valid beam: numpy's dot product, not gemm
            T_i = np.eye(4)
            T_i[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            T_i[:3, 3] = rng.normal(size=3)
            angles.append(a)
            ranges.append(rng.uniform(0.1, 30.0, n).astype(rng.choice([np.float32, np.float64])))
            valid.append(v)
            T.append(T_i)
        ranges = [r.astype(ranges[0].dtype) for r in ranges]
        start = np.zeros(n_scans + 1, dtype=np.int64)
        np.cumsum([a.shape[0] for a in angles], out=start[1:])
        cat = np.concatenate
        got = bk.strided_beams_world(cat([np.cos(a) for a in angles]), cat([np.sin(a) for a in angles]),
                                     cat(ranges), cat(valid), start, np.array(T), step)
        ref = _strided_beams_reference(angles, ranges, valid, T, step)
        for g, r in zip(got, ref, strict=True):
            assert g.shape == r.shape and np.array_equal(g, r)
