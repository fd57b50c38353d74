"""Front end pieces: plane creation tolerances and degeneracy-aware tracking (world frame)."""

from __future__ import annotations

import numpy as np

from slam.frontend.plane_init import PlaneInitParams, PooledSegment, SegmentPool, on_plane
from slam.frontend.tracking import refine_window


def _segment(serial: int, y: float, z0: float, x0: float, x1: float, rng: np.random.Generator,
             sigma: float = 0.003, rise: float = 0.5) -> PooledSegment:
    """A slanted line on the wall plane y = const (points scattered by ``sigma`` across it)."""
    s = np.linspace(0.0, 1.0, 12)
    pts = np.column_stack((x0 + (x1 - x0) * s, np.full(12, y), z0 + rise * s))
    pts[:, 1] += rng.normal(0.0, sigma, 12)
    c = pts.mean(axis=0)
    d = pts[-1] - pts[0]
    line = np.array([c - 0.3 * d, c + 0.3 * d])
    line[:, 1] = y  # the fitted line: its offset is known far better than one point's
    return PooledSegment(
        ref=(serial, 0), time=0.01 * serial, scan_serial=serial, centroid=c,
        direction=d / np.linalg.norm(d), endpoints=pts[[0, -1]], samples=pts, line=line,
        scan_normal=np.array([1.0, 0.0, 0.0]), origin=np.array([c[0], 0.0, 1.5]))


def test_a_door_recessed_13_mm_does_not_join_its_wall() -> None:
    rng = np.random.default_rng(3)
    p = PlaneInitParams(min_support=4, min_scans=3)
    # the two tilted scanners' lines slant opposite ways across the wall
    wall = [_segment(i, 2.0, 0.2 + 0.1 * i, 0.1 * i, 0.1 * i + 0.8, rng, rise=0.5 if i % 2 else -0.5)
            for i in range(6)]
    door = _segment(9, 2.013, 0.5, 0.3, 1.0, rng)
    n, d = np.array([0.0, -1.0, 0.0]), 2.0
    assert all(on_plane(s, n, d, p) for s in wall)
    assert not on_plane(door, n, d, p)
    pool = SegmentPool(p)
    for s in [*wall, door]:
        pool.add(s)
    planes = pool.create_planes()
    assert len(planes) == 1
    assert door not in planes[0].members and len(planes[0].members) == 6
    assert abs(abs(planes[0].d) - 2.0) < 0.002


def test_tracking_leaves_an_unobserved_direction_to_the_prediction() -> None:
    """A corridor along x: walls (normals +-y), floor and a wall tilted 0.5 deg (its heading
    slightly wrong). Points say the rig sits 5 cm further along x than predicted through that
    tilt only; with the freeze the window stays at the prediction along x."""
    W = 4
    T = np.repeat(np.eye(4)[None], W, axis=0)
    for k in range(W):
        T[k, 0, 3] = 0.05 * k
    tilt = np.radians(0.5)
    planes = [(np.array([0.0, 1.0, 0.0]), -1.1), (np.array([0.0, -1.0, 0.0]), -1.1),
              (np.array([0.0, 0.0, 1.0]), 1.9), (np.array([np.sin(tilt), np.cos(tilt), 0.0]), -1.1)]
    rng = np.random.default_rng(1)
    pts, nrm, off, kis, al = [], [], [], [], []
    for k in range(W - 1):
        for n, d in planes:
            for _ in range(20):
                a = rng.uniform()
                x = 0.05 * (k + a) + rng.uniform(-2.0, 2.0)
                # a point on the plane in the world, seen 5 cm "ahead" for the tilted plane
                p_w = np.array([x, 0.0, 0.0]) + rng.uniform(-0.5, 0.5, 3)
                p_w = p_w - (n @ p_w + d) * n
                p_b = p_w - np.array([0.05 * (k + a), 0.0, 0.0])
                if n[0] != 0.0:
                    p_b[0] -= 0.05
                pts.append(p_b)
                nrm.append(n)
                off.append(d)
                kis.append(k)
                al.append(a)
    args = (np.array(kis), np.array(al), np.array(pts), np.array(nrm), np.array(off),
            np.full(len(pts), 0.001), np.array([np.radians(0.2)] * 3 + [0.01] * 3),
            np.array([0.006] * 3 + [0.002] * 3))
    inc = np.array([np.radians(0.05)] * 3 + [0.001] * 3)
    free = refine_window(T, *args, increment_sigmas=inc)
    frozen = refine_window(T, *args, increment_sigmas=inc, degenerate_ratio=float(np.sin(np.radians(3.0)) ** 2))
    assert np.abs(free[:, 0, 3] - T[:, 0, 3]).max() > 0.005  # the tilt drags the window along x
    assert np.abs(frozen[:, 0, 3] - T[:, 0, 3]).max() < 1e-3
