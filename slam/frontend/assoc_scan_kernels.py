"""The association of one scan's segments with the map's planes in one compiled call
(``slam.frontend.association.ScanAssociator.associate``): the segments' summaries
(``kernels.segment_summaries``), the candidate pairs under the gates (``assoc_kernels.scan_pairs``),
their extent tests (``extent_kernels.pairs_near``) and the choice (``assoc_kernels.decide``), one
after the other as the Python code called them, so the same numbers; one call per scan instead of
four, without boxing the arrays passed between them.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.frontend.assoc_kernels import NONE, decide, local_steps, scan_pairs
from slam.frontend.extent_kernels import pairs_near
from slam.frontend.kernels import segment_summaries

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


DriftScalars = tuple[float, float, float, int, int, int]
TestScalars = tuple[float, float, float, float, float]
ChoiceTuple = tuple[float, float, float, float, float, float, float, float, float, bool, bool, float]
LocalTuple = tuple[float, float, float, float]


@nb.njit(cache=True)
def associate_summarised(
    centroid: FloatArray, direction: FloatArray, endpoints: FloatArray, sigma_centroid: FloatArray,
    sigma_direction: FloatArray, seg_range: FloatArray, origin: FloatArray, n_points: IntArray,
    rows: FloatArray, horizontal: BoolArray, ids: IntArray, child_rows: IntArray, is_child: BoolArray,
    odometer: float, cell_size: float, drift: DriftScalars, tests: TestScalars,
    keys: IntArray, count: IntArray, box: IntArray,
    with_choice: bool, veto: bool, hold_past_child: bool, hosts: BoolArray, has_hosts: bool, same_normal: float,
    choice: ChoiceTuple, walls: BoolArray, local: LocalTuple,
) -> tuple[IntArray, BoolArray]:
    """``association.associate_scan`` after its Python set-up, for the k segments' summaries
    (``association.WorldSegments``' arrays, world frame): per segment its plane id (``NONE``,
    ``HELD``) and whether it may grow the plane's extent. The active planes' ``rows`` (P, 12) and
    ``horizontal`` (P,), their ids ``ids`` (P,), the children's rows ``child_rows`` and
    ``is_child`` (P,); ``drift`` and ``tests`` the gates' scalars (``association._gate_scalars``),
    ``keys``, ``count``, ``box`` the plane map's extent index, ``choice`` the choice's scalars
    (``parallel_choice.choice_scalars``), ``hosts`` (P,) the walls of the host test; with
    ``local[0]`` > 0 the local step test (``assoc_kernels.local_steps``; ``local`` as
    ``parallel_choice.local_scalars``) on the walls ``walls`` (P,)."""
    k_n = centroid.shape[0]
    start, cols, cells, dist, sig_d2, pair_id, pair_dilate = scan_pairs(
        centroid, direction, endpoints, sigma_centroid, sigma_direction, seg_range, origin, rows, horizontal,
        ids, child_rows, odometer, drift[0], drift[1], drift[2], drift[3], drift[4], drift[5], cell_size,
        tests[0], tests[1], tests[2], tests[3], tests[4])
    if cols.shape[0] == 0:
        return np.full(k_n, NONE, dtype=np.int64), np.zeros(k_n, dtype=np.bool_)
    # every pair's end points and centroid against its plane's dilated extent; a door's or board's
    # pair (the choice's ``whole``) each of the three on its own
    children = child_rows.shape[0] > 0 and with_choice
    whole = np.zeros(cols.shape[0], dtype=np.bool_)
    if children:
        for i in range(cols.shape[0]):
            whole[i] = is_child[cols[i]]
    near, each = pairs_near(keys, count, box, pair_id, cells, pair_dilate, whole)
    keep = near
    shadow = np.zeros(cols.shape[0], dtype=np.bool_)
    if children:
        keep = each
        if hold_past_child:
            for i in range(cols.shape[0]):
                shadow[i] = near[i] and not each[i]
            keep = near
    weight = np.empty(k_n)
    arm = np.empty((k_n, 3))
    for k in range(k_n):
        weight[k] = float(n_points[k])
        for r in range(3):
            arm[k, r] = centroid[k, r] - origin[r]
    out, grows = decide(start, cols, near, keep, shadow, dist, sig_d2, rows, ids, same_normal, with_choice, veto,
                        sigma_centroid, weight, seg_range, arm, hosts, has_hosts, choice[0], choice[1], choice[2],
                        choice[3], choice[4], choice[5], choice[6], choice[7], choice[8], choice[9], choice[10],
                        choice[11])
    if local[0] > 0.0:
        local_steps(out, grows, dist, ids, walls, np.ascontiguousarray(rows[:, 0:3]), same_normal, endpoints, centroid,
                    sigma_centroid, weight, local[0], local[1], local[2], local[3])
    return out, grows


@nb.njit(cache=True)
def associate_segments(
    virtual_world: FloatArray, endpoints_world: FloatArray, virtual_sigma: FloatArray, point_sigma: float,
    n_points: IntArray, origin: FloatArray, min_segment_points: int,
    rows: FloatArray, horizontal: BoolArray, ids: IntArray, child_rows: IntArray, is_child: BoolArray,
    odometer: float, cell_size: float, drift: DriftScalars, tests: TestScalars,
    keys: IntArray, count: IntArray, box: IntArray,
    with_choice: bool, veto: bool, hold_past_child: bool, hosts: BoolArray, has_hosts: bool, same_normal: float,
    choice: ChoiceTuple, walls: BoolArray, local: LocalTuple,
) -> tuple[IntArray, BoolArray]:
    """``ScanAssociator.associate`` of one scan: the segments' summaries
    (``kernels.segment_summaries`` of the virtual points and end points (k, 2, 3) placed in the
    world, the virtual points' sigma (k,) (m), one point's ``point_sigma`` (m), the point counts
    (k,), the scanner at ``origin`` (3,), world frame), then :func:`associate_summarised` (the
    other arguments), then the segments of fewer than ``min_segment_points`` points left
    unassociated."""
    centroid, direction, sigma_centroid, sigma_direction, seg_range = segment_summaries(
        virtual_world, endpoints_world, virtual_sigma, point_sigma, n_points, origin)
    out, grows = associate_summarised(
        centroid, direction, endpoints_world, sigma_centroid, sigma_direction, seg_range, origin, n_points, rows,
        horizontal, ids, child_rows, is_child, odometer, cell_size, drift, tests, keys, count, box, with_choice, veto,
        hold_past_child, hosts, has_hosts, same_normal, choice, walls, local)
    for k in range(n_points.shape[0]):
        if n_points[k] < min_segment_points:
            out[k] = NONE
            grows[k] = False
    return out, grows
