"""Label bookkeeping shared by every segmenter, on the compressed (valid-point) sequence.

Segmenters produce raw labels on the valid points (-1 = unsegmented, any ids);
a segment is a maximal run of consecutive points with the same id. These
kernels split runs at depth jumps, drop runs shorter than ``min_len``, combine
a forward and a backward run, and renumber segments 0, 1, ... in scan order.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


@nb.njit(cache=True)
def finalize_runs(raw: IntArray, points: FloatArray, max_gap: float, min_len: int) -> tuple[IntArray, IntArray, IntArray]:
    """Runs of equal non-negative raw labels, split where consecutive points are > max_gap apart.

    Returns (labels renumbered in scan order with short runs set to -1, first
    point index per segment, last point index per segment).
    """
    m = raw.shape[0]
    out = np.full(m, -1, dtype=np.int64)
    first = np.empty(m, dtype=np.int64)
    last = np.empty(m, dtype=np.int64)
    k = 0
    i = 0
    g2 = max_gap * max_gap
    while i < m:
        if raw[i] < 0:
            i += 1
            continue
        j = i
        while j + 1 < m and raw[j + 1] == raw[i]:
            dx = points[j + 1, 0] - points[j, 0]
            dy = points[j + 1, 1] - points[j, 1]
            if dx * dx + dy * dy > g2:
                break
            j += 1
        if j - i + 1 >= min_len:
            for q in range(i, j + 1):
                out[q] = k
            first[k] = i
            last[k] = j
            k += 1
        i = j + 1
    return out, first[:k].copy(), last[:k].copy()


@nb.njit(cache=True)
def combine_runs(fwd: IntArray, bwd: IntArray) -> IntArray:
    """The paper's forward-backward rule (section 2.2) on two labelings of the same points.

    A point unsegmented in either labeling is unsegmented; a segment boundary
    in either labeling is a boundary. Returns raw labels (ids of the pairs'
    runs); ``finalize_runs`` then applies ``min_len`` again.
    """
    m = fwd.shape[0]
    out = np.full(m, -1, dtype=np.int64)
    k = -1
    prev_f = -2
    prev_b = -2
    for i in range(m):
        f = fwd[i]
        b = bwd[i]
        if f < 0 or b < 0:
            prev_f = -2
            prev_b = -2
            continue
        if f != prev_f or b != prev_b:
            k += 1
        out[i] = k
        prev_f = f
        prev_b = b
    return out


@nb.njit(cache=True)
def reverse_labels(labels: IntArray) -> IntArray:
    """A contiguous copy of ``labels`` in reverse order."""
    m = labels.shape[0]
    out = np.empty(m, dtype=np.int64)
    for i in range(m):
        out[i] = labels[m - 1 - i]
    return out


@nb.njit(cache=True)
def combine_directions(
    raw_fwd: IntArray, raw_bwd_reversed: IntArray, points: FloatArray, max_gap: float, min_len: int
) -> tuple[IntArray, IntArray, IntArray]:
    """Forward and backward runs combined (section 2.2), as ``finalize_runs`` returns them.

    ``raw_bwd_reversed`` are the raw labels of the backward pass in its own
    (reversed) order. Each run is finalised (depth jumps, ``min_len``) before
    combining, and the combination is finalised again.
    """
    fwd, _, _ = finalize_runs(raw_fwd, points, max_gap, min_len)
    bwd, _, _ = finalize_runs(reverse_labels(raw_bwd_reversed), points, max_gap, min_len)
    return finalize_runs(combine_runs(fwd, bwd), points, max_gap, min_len)
