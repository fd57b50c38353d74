"""The batch kernels of slam.frontend.batch_kernels against the numpy code they replaced."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam.frontend import batch_kernels as bk
from slam.frontend.planemap import plane_basis

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
