"""The compiled kernels (slam.trajectory.kernels, slam.frontend.kernels) against their numpy originals."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from slam.config import SlamConfig
from slam.frontend import kernels as fk
from slam.frontend.association import Gates, WorldSegments, associate, world_segments
from slam.frontend.planemap import PlaneMap
from slam.params import gates as gates_of
from slam.trajectory import kernels as tk
from slam.trajectory.interpolation import (
    exp_coefficients,
    interpolate_poses,
    se3_exp,
    so3_exp,
    so3_log,
)


def _gates(**changes: Any) -> Gates:
    """The default configuration's gates with a 2-cell extent margin, with ``changes``: the nearest
    candidate under the gates (the parallel choice off; tests/test_parallel_choice.py tests it)."""
    return replace(gates_of(SlamConfig()), **{"extent_margin_cells": 2, "choice": None, **changes})


def _knots(rng: np.random.Generator, k: int, rot: float = 0.3) -> np.ndarray:
    """``k`` random poses ``T_world_body`` (k, 4, 4)."""
    return np.array([se3_exp(np.concatenate((rng.normal(0.0, rot, 3), rng.normal(0.0, 1.0, 3)))) for _ in range(k)])


def test_exp_coefficients_match_across_the_series_boundary() -> None:
    t = np.concatenate(([0.0, 1e-9, 1e-4], np.linspace(0.4, 0.6, 41), [1.0, 2.0, 3.1]))
    a, b, *_ = exp_coefficients(t)
    got = np.array([tk.exp_ab(float(x)) for x in t])
    np.testing.assert_allclose(got[:, 0], a, rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(got[:, 1], b, rtol=1e-15, atol=0.0)


def test_rotation_logarithm_matches_so3_log_near_zero_and_near_pi() -> None:
    rng = np.random.default_rng(2)
    for angle in (0.0, 1e-9, 5e-5, 2e-4, 0.3, 1.0, 3.0, np.pi - 0.05, np.pi - 1e-7, np.pi):
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
        out = np.empty(3)
        tk.so3_log_into(R, out)
        if angle < np.pi - 1e-6:
            np.testing.assert_allclose(out, so3_log(R), rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(so3_exp(out), R, rtol=0.0, atol=1e-12)  # a logarithm at pi


def test_placement_and_poses_match_interpolate_poses() -> None:
    rng = np.random.default_rng(3)
    T = _knots(rng, 9)
    idx = rng.integers(0, 8, 400)  # unsorted: one logarithm per run of equal intervals
    al = rng.uniform(0.0, 1.0, 400)
    al[:3] = (0.0, 1.0, 0.5)
    pts = rng.uniform(-5.0, 5.0, (400, 3))
    Tw = interpolate_poses(T[idx], T[idx + 1], al)
    R, t = tk.interval_poses(T, idx, al)
    np.testing.assert_allclose(R, Tw[:, :3, :3], rtol=0.0, atol=1e-14)
    np.testing.assert_allclose(t, Tw[:, :3, 3], rtol=0.0, atol=1e-12)
    expected = np.einsum("mij,mj->mi", Tw[:, :3, :3], pts) + Tw[:, :3, 3]
    np.testing.assert_allclose(tk.place(T, idx, al, pts), expected, rtol=0.0, atol=1e-12)
    # the same input gives the same bits
    np.testing.assert_array_equal(tk.place(T, idx, al, pts), tk.place(T, idx, al, pts))


def test_uniform_knots_match_the_numpy_fractions() -> None:
    rng = np.random.default_rng(4)
    t0, dt, n = 100.0, 0.05, 7
    T = np.concatenate((_knots(rng, n), np.zeros((5, 4, 4))))  # spare capacity past the knots
    times = np.concatenate((rng.uniform(t0 - 0.01, t0 + dt * n, 300), [t0, t0 + dt * (n - 1)]))
    x = (times - t0) / dt
    idx = np.clip(np.floor(x).astype(np.int64), 0, n - 2)
    alpha = np.clip(x - idx, 0.0, 1.0)
    got_idx, got_alpha = tk.uniform_fractions(t0, dt, n, times)
    np.testing.assert_array_equal(got_idx, idx)
    np.testing.assert_array_equal(got_alpha, alpha)
    pts = rng.uniform(-3.0, 3.0, (times.size, 3))
    Tw = interpolate_poses(T[idx], T[idx + 1], alpha)
    expected = np.einsum("mij,mj->mi", Tw[:, :3, :3], pts) + Tw[:, :3, 3]
    np.testing.assert_allclose(tk.place_uniform(T, t0, dt, n, times, pts), expected, rtol=0.0, atol=1e-12)
    for k in (0, 5, 301):
        np.testing.assert_allclose(tk.pose_uniform(T, t0, dt, n, float(times[k])), Tw[k], rtol=0.0, atol=1e-12)


def test_window_normal_equations_match_the_dense_jacobian() -> None:
    """A = J^T W J, b = J^T W r of refine_window's point residuals, formed without the dense
    Jacobian: the same numbers as the dense products (relative 1e-12)."""
    rng = np.random.default_rng(5)
    W, m, huber_k = 7, 500, 2.0
    T = _knots(rng, W, rot=0.02)
    kis = rng.integers(0, W - 1, m)
    al = rng.uniform(0.0, 1.0, m)
    pts = rng.uniform(-3.0, 3.0, (m, 3))
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    off = rng.normal(0.0, 1.0, m)
    sig = rng.uniform(0.002, 0.01, m)
    A, b, w = fk.window_normal_equations(T, kis, al, pts, nrm, off, sig, huber_k)
    Tk = interpolate_poses(T[kis], T[kis + 1], al)
    R = Tk[:, :3, :3]
    r = (np.einsum("mi,mi->m", nrm, np.einsum("mij,mj->mi", R, pts) + Tk[:, :3, 3]) + off) / sig
    Rtn = np.einsum("mji,mj->mi", R, nrm)
    g = np.concatenate((np.cross(pts, Rtn), Rtn), axis=1) / sig[:, None]
    w_ref = np.where(np.abs(r) <= huber_k, 1.0, huber_k / np.maximum(np.abs(r), 1e-12))
    J = np.zeros((m, 6 * W))
    rows, cols = np.arange(m)[:, None], 6 * kis[:, None] + np.arange(6)[None, :]
    J[rows, cols] = g * (1.0 - al)[:, None]
    J[rows, cols + 6] = g * al[:, None]
    np.testing.assert_allclose(w, w_ref, rtol=1e-12, atol=0.0)
    assert 0 < (w < 1.0).sum() < m  # both sides of the Huber corner
    np.testing.assert_allclose(A, (J * w_ref[:, None]).T @ J, rtol=0.0, atol=1e-12 * np.abs(A).max())
    np.testing.assert_allclose(b, (J * w_ref[:, None]).T @ r, rtol=0.0, atol=1e-12 * np.abs(b).max())


def _associate_numpy(segs: WorldSegments, pmap: PlaneMap, odometer: float, gates: Gates) -> np.ndarray:
    """slam.frontend.association.associate as it was before its gates were compiled (numpy over
    the (segment, plane) pairs, PlaneMap.overlaps per candidate): the reference of the test below."""
    out = np.full(segs.n, -1, dtype=np.int64)
    active = [p for p in pmap.planes if p.active]
    if not active or segs.n == 0:
        return out
    ids = np.array([p.id for p in active], dtype=np.int64)
    normals = np.array([p.normal for p in active])
    offs = np.array([p.d for p in active])
    sig_plane = np.array([p.sigma_offset for p in active])
    since = np.array([odometer - p.last_seen_odometer for p in active])
    sig_drift = np.minimum(gates.drift_rate * np.maximum(since, 0.0), gates.max_drift_sigma)
    dist_c = segs.centroid @ normals.T + offs
    sin_a = np.abs(segs.direction @ normals.T)
    lever = (gates.sigma_lever * segs.range) ** 2
    sig_d2 = (segs.sigma_centroid[:, None] ** 2 + sig_plane[None] ** 2 + gates.sigma_pose**2 + lever[:, None]
              + sig_drift[None] ** 2)
    sig_a2 = segs.sigma_direction[:, None] ** 2 + gates.sigma_rotation**2 + (sig_drift[None] / 5.0) ** 2
    m2 = dist_c**2 / sig_d2 + sin_a**2 / sig_a2
    e0 = np.abs(segs.endpoints[:, 0] @ normals.T + offs)
    e1 = np.abs(segs.endpoints[:, 1] @ normals.T + offs)
    cap = gates.max_endpoint_distance + 3.0 * sig_drift[None] + 3.0 * gates.sigma_lever * segs.range[:, None]
    facing = (normals @ segs.origin + offs) > 0.0
    ok = (m2 < gates.chi2) & (e0 < cap) & (e1 < cap) & facing[None, :]
    dilate = [gates.extent_margin_cells + min(int(3.0 * sd / pmap.cell_size), gates.max_extra_cells) for sd in sig_drift]
    seg_pts = np.concatenate((segs.endpoints, segs.centroid[:, None]), axis=1)
    for k in np.flatnonzero(ok.any(axis=1)):
        cand = np.flatnonzero(ok[k])
        cand = cand[np.argsort(m2[k, cand])]
        passing = [j for j in cand.tolist() if pmap.overlaps(int(ids[j]), seg_pts[k], dilate[j])]
        if not passing:
            continue
        best = passing[0]
        ambiguous = any(
            not ((normals[best] @ normals[j] > np.cos(np.radians(2.0)))
                 and abs(dist_c[k, best] - dist_c[k, j]) < 3.0 * np.sqrt(sig_d2[k, best]))
            for j in passing[1:]
        )
        if not ambiguous:
            out[k] = ids[best]
    return out


def test_association_matches_the_numpy_gates() -> None:
    """Walls of a few rooms (coplanar ones in different rooms, a duplicate awaiting merge, one
    merged away) and segments on and off them: the compiled gates give the same plane per
    segment as the numpy formulation, and the same m2 to rounding."""
    rng = np.random.default_rng(6)
    pmap = PlaneMap(cell_size=0.25)
    # (normal, offset, extent along the plane's u): normals towards the scanner but one
    walls = [((0.0, -1.0, 0.0), 2.0, (0.0, 4.0)), ((0.0, -1.0, 0.0), 2.0, (8.0, 12.0)),
             ((0.0, -1.0, 0.0), 2.004, (3.0, 6.0)), ((1.0, 0.0, 0.0), 1.0, (-2.0, 2.0)),
             ((0.0, 1.0, 0.0), 2.0, (0.0, 12.0)), ((0.0, 0.0, 1.0), 0.0, (-3.0, 3.0)),
             ((0.0, -1.0, 0.01), 2.0, (0.0, 3.0)), ((-1.0, 0.0, 0.0), 1.0, (-2.0, 2.0))]
    for n, d, (lo, hi) in walls:
        p = pmap.add(np.array(n), d, 1, 0.0, rng.uniform(0.0, 5.0))
        s = np.linspace(lo, hi, 60)
        pts = np.column_stack((s, rng.uniform(-2.0, 2.0, 60), rng.uniform(0.0, 2.5, 60)))
        pmap.extend(p.id, pts - (pts @ p.normal + p.d)[:, None] * p.normal)
    pmap.merge(0, 6)
    k = 300
    host = rng.integers(0, len(walls), k)
    ends = np.empty((k, 2, 3))
    for i, h in enumerate(host):
        p = pmap.planes[int(h)]
        c = -p.d * p.normal + rng.uniform(-6.0, 12.0) * p.u + rng.uniform(-1.0, 3.0) * p.v
        c += rng.normal(0.0, 0.01 if i % 3 else 0.1) * p.normal
        u = p.u * np.cos(rng.uniform(0, np.pi)) + p.v * np.sin(rng.uniform(0, np.pi))
        u += rng.normal(0.0, 0.01, 3)
        ends[i] = (c - 0.3 * u, c + 0.3 * u)
    origin = np.array([1.0, 0.5, 1.2])
    virtual = ends * 0.9 + ends[:, ::-1] * 0.1
    segs = world_segments(virtual, ends, rng.uniform(0.001, 0.004, k), 0.003, rng.integers(10, 200, k), origin)
    for gates in (_gates(), _gates().loosened(3.0)):
        got = associate(segs, pmap, 10.0, gates)
        np.testing.assert_array_equal(got, _associate_numpy(segs, pmap, 10.0, gates))
        assert 0.2 * k < (got >= 0).sum() < k  # some associated, some not


def test_world_segments_match_the_numpy_summaries() -> None:
    rng = np.random.default_rng(8)
    k = 50
    ends = rng.uniform(-4.0, 4.0, (k, 2, 3))
    ends[0, 1] = ends[0, 0]  # a degenerate segment: zero length
    virtual = ends * 0.8 + ends[:, ::-1] * 0.2
    sig, n_pts, origin = rng.uniform(0.001, 0.004, k), rng.integers(4, 300, k), np.array([0.5, -0.2, 1.1])
    ws = world_segments(virtual, ends, sig, 0.003, n_pts, origin)
    length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    c = virtual.mean(axis=1)
    np.testing.assert_allclose(ws.centroid, c, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(ws.direction, (ends[:, 1] - ends[:, 0]) / np.maximum(length, 1e-9)[:, None],
                               rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(ws.sigma_centroid, sig / np.sqrt(2.0), rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(ws.sigma_direction, 0.003 / np.maximum(length * np.sqrt(n_pts / 12.0), 1e-9),
                               rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(ws.range, np.linalg.norm(c - origin, axis=1), rtol=1e-15, atol=0.0)
    assert ws.endpoints is ends and ws.n == k


def test_subsampled_rows_match_the_per_segment_ranges() -> None:
    rng = np.random.default_rng(9)
    counts = rng.integers(1, 80, 30)
    offsets = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    js = rng.permutation(30)[:17].astype(np.int64)
    per = rng.choice([8, 12], js.size).astype(np.int64)
    rows = [np.arange(offsets[j], offsets[j + 1], max(1, int(counts[j]) // d)) for j, d in zip(js, per, strict=True)]
    sel, splits = fk.subsample_rows(offsets, counts.astype(np.int64), js, per)
    np.testing.assert_array_equal(sel, np.concatenate(rows))
    np.testing.assert_array_equal(splits, np.cumsum([r.size for r in rows])[:-1])


def test_plane_cells_match_the_numpy_floor() -> None:
    rng = np.random.default_rng(10)
    pmap = PlaneMap(cell_size=0.25)
    pid = pmap.add(np.array([0.3, 0.9, 0.1]), -2.0, 1, 0.0, 0.0).id
    pts = rng.uniform(-6.0, 6.0, (500, 3))
    p = pmap.planes[pid]
    expected = np.floor(np.column_stack((pts @ p.u, pts @ p.v)) / 0.25).astype(np.int64)
    got = pmap.cells_of(pid, pts)
    # equal but where a point lies within rounding of a cell boundary
    uv = np.column_stack((pts @ p.u, pts @ p.v)) / 0.25
    near = np.abs(uv - np.round(uv)) < 1e-12
    np.testing.assert_array_equal(got[~near], expected[~near])
    assert got.dtype == np.int64 and got.shape == (500, 2)


def test_dilated_overlap_matches_the_window_scan() -> None:
    """PlaneMap.overlaps' compiled pass over the extent answers as the scan of every cell within
    ``dilate`` of the points' cells, also after the extent grew."""
    rng = np.random.default_rng(11)
    pmap = PlaneMap(cell_size=0.25)
    pid = pmap.add(np.array([0.0, 1.0, 0.0]), -2.0, 1, 0.0, 0.0).id
    pmap.extend(pid, rng.uniform(-1.0, 1.0, (40, 3)))

    def scan(pts: np.ndarray, dilate: int) -> bool:
        ext = pmap.planes[pid].cells
        return any((cu + du, cv + dv) in ext for cu, cv in pmap.cells_of(pid, pts).tolist()
                   for du in range(-dilate, dilate + 1) for dv in range(-dilate, dilate + 1))

    for step in range(2):
        for _ in range(300):
            pts = rng.uniform(-4.0, 4.0, (3, 3))
            dilate = int(rng.integers(0, 6))
            assert pmap.overlaps(pid, pts, dilate) == scan(pts, dilate)
        if step == 0:
            pmap.extend(pid, rng.uniform(2.0, 3.0, (20, 3)))  # grows: the cached array follows


def test_association_gates_order_the_candidates_by_m2() -> None:
    rng = np.random.default_rng(12)
    k, p = 40, 9
    nrm = rng.normal(size=(p, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    off = rng.uniform(-0.05, 0.05, p)
    ends = rng.normal(0.0, 0.02, (k, 2, 3))
    c = ends.mean(axis=1)
    u = (ends[:, 1] - ends[:, 0]) / np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)[:, None]
    sc, sd, rg = rng.uniform(0.002, 0.01, k), rng.uniform(0.3, 1.0, k), rng.uniform(0.5, 5.0, k)
    sp, sdr = rng.uniform(0.002, 0.01, p), rng.uniform(0.0, 0.02, p)
    origin = np.array([0.0, 0.0, 1.0])
    ok, m2, dist, sig_d2, _, order, count = fk.association_gates(
        c, u, ends, sc, sd, rg, origin, nrm, off, sp, sdr, nrm[:, [1, 2, 0]], nrm[:, [2, 0, 1]], 0.25,
        0.004, 0.005, 0.001, 0.05, 9.21)
    ref_d2 = sc[:, None] ** 2 + sp[None] ** 2 + 0.004**2 + (0.001 * rg[:, None]) ** 2 + sdr[None] ** 2
    ref_m2 = (c @ nrm.T + off) ** 2 / ref_d2 + (u @ nrm.T) ** 2 / (sd[:, None] ** 2 + 0.005**2 + (sdr[None] / 5.0) ** 2)
    np.testing.assert_allclose(m2, ref_m2, rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(sig_d2, ref_d2, rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(dist, c @ nrm.T + off, rtol=0.0, atol=1e-15)
    cap = 0.05 + 3.0 * sdr[None] + 3.0 * 0.001 * rg[:, None]
    ref_ok = ((ref_m2 < 9.21) & (np.abs(ends[:, 0] @ nrm.T + off) < cap) & (np.abs(ends[:, 1] @ nrm.T + off) < cap)
              & ((nrm @ origin + off) > 0.0)[None])
    np.testing.assert_array_equal(ok, ref_ok)
    assert 0 < ok.sum() < ok.size and (count > 1).any()
    for i in range(k):
        np.testing.assert_array_equal(order[i, : count[i]], np.flatnonzero(ok[i])[np.argsort(m2[i, ok[i]], kind="stable")])


def _corridor_with_a_door() -> tuple[PlaneMap, int, int, np.random.Generator]:
    """Wall y = 2 (x 0-12, normal -y towards the corridor) and a door x 4-5 set 1 cm into it,
    fitted tilted by 0.5 deg about the vertical (through the door's centre), tied to the wall."""
    rng = np.random.default_rng(11)
    pmap = PlaneMap(cell_size=0.25)
    wall = pmap.add(np.array([0.0, -1.0, 0.0]), 2.0, 1, 0.0, 0.0)
    pts = np.column_stack((rng.uniform(0.0, 12.0, 400), np.full(400, 2.0), rng.uniform(0.0, 2.5, 400)))
    pmap.extend(wall.id, pts)
    a = np.radians(-0.5)  # the door's plane nears the wall towards +x
    n = np.array([np.sin(a), -np.cos(a), 0.0])
    centre = np.array([4.5, 2.01, 1.0])
    door = pmap.add(n, -float(n @ centre), 1, 0.0, 0.0)
    dp = np.column_stack((rng.uniform(4.0, 5.0, 100), np.full(100, 2.01), rng.uniform(0.0, 2.0, 100)))
    pmap.extend(door.id, dp - (dp @ door.normal + door.d)[:, None] * door.normal)
    return pmap, wall.id, door.id, rng


def _wall_segments(xs: np.ndarray, y: float, rng: np.random.Generator):
    k = xs.size
    c = np.column_stack((xs, np.full(k, y), rng.uniform(0.5, 1.5, k)))
    u = np.array([0.0, 0.0, 1.0])  # a tilted scanner's line across the wall: the tilt about the vertical is not in its angle
    ends = np.stack((c - 0.2 * u, c + 0.2 * u), axis=1)
    origin = np.array([float(xs.mean()), 0.5, 1.2])
    return world_segments(ends * 0.8 + ends[:, ::-1] * 0.2, ends, np.full(k, 0.0005), 0.003, np.full(k, 60), origin)


def test_a_tied_door_takes_neither_the_wall_beyond_its_extent_nor_by_its_tilt() -> None:
    """The door's tilt brings its plane onto the wall a metre beside the door, where the wall's
    segments (2 mm off it: the tracking's error) then lie nearer the door's plane than the
    wall's, inside the door's extent grown by 4 cells: by default they go to the door. With the
    child margin, the door's extent reaches one cell beyond the door only; with the host's
    normal, the door's plane is 1 cm from the wall everywhere."""
    pmap, wall, door, rng = _corridor_with_a_door()
    # the door's plane at x = 5.8-5.95 lies 1.3-2.7 mm before the wall's, the segments 2 mm
    segs = _wall_segments(np.linspace(5.8, 5.95, 8), 2.0 - 0.002, rng)
    hosts = {door: wall}
    base = associate(segs, pmap, 0.0, _gates(extent_margin_cells=4))
    assert (base == door).all()
    margin = associate(segs, pmap, 0.0, _gates(extent_margin_cells=4, child_margin_cells=1), hosts)
    assert (margin == wall).all()
    normal = associate(segs, pmap, 0.0, _gates(extent_margin_cells=4, child_host_normal=True), hosts)
    assert (normal == wall).all()
    # the door's own segments still go to the door either way
    on_door = _wall_segments(np.linspace(4.2, 4.8, 8), 2.01, rng)
    for g in (_gates(extent_margin_cells=4, child_margin_cells=1), _gates(extent_margin_cells=4, child_host_normal=True)):
        assert (associate(on_door, pmap, 0.0, g, hosts) == door).all()
    # without children the options change nothing
    assert (associate(segs, pmap, 0.0, _gates(extent_margin_cells=4, child_margin_cells=1)) == door).all()
