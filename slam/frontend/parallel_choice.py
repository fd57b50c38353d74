"""The choice between parallel planes a few centimetres apart (a wall, the door set into it,
the board on it), made per scan from the segments' own fitted lines.

The association gates (``association``) are widened by the pose's uncertainty, so a wall's
segment passes the gate of the board 2 cm in front of it, and a door's segment the gate of its
wall. But the pose error moves all the segments of one scan together: along a normal ``n`` it
shifts every segment's signed distance to the planes facing ``n`` by one common ``delta``. The
segments' own lines (their centroid sigma, a fraction of a millimetre) then tell the planes
apart once ``delta`` is known, and ``delta`` is what the scan's segments on those planes agree
on:

* the candidates of one scan are grouped into *families* of parallel planes (normals within
  ``PARALLEL_DEG``, same facing);
* each (segment, candidate) pair proposes ``delta = dist``; the hypothesis of the highest
  likelihood wins: every segment it leaves unexplained (no candidate within ``gate`` sigmas)
  costs ``OUTLIER_NATS``, and ``delta`` has the pose prior ``N(0, sigma_pose^2)``; it is then
  refined to the point-weighted mean of its inliers' distances;
* each segment then takes the candidate whose distance, less ``delta``, lies within ``gate``
  of its own sigma (``sqrt(sigma_centroid^2 + relative_sigma^2)``); two such candidates on one
  surface (a duplicate awaiting merge: offsets within one sigma) keep the nearer, on two
  surfaces the likelihood ratio must exceed ``ratio``, else the segment is held back
  (``HELD``: neither associated nor pooled); none: the segment lies on none of these planes
  and is left to the pool (``NONE``), where a door's segments make the door's plane.

A segment *grows* its plane's extent only when its choice was unambiguous: it had a single
candidate in its family, or ``delta`` rested on other segments of the scan as well and only one
candidate passed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from slam.frontend import assoc_kernels as ak

FloatArray = NDArray[np.float64]
NONE, HELD = -1, -2
PARALLEL_DEG = 2.0
OUTLIER_NATS = float(np.log(100.0))  # a segment on none of the planes: 1 % as likely as on one


@dataclass(frozen=True)
class ChoiceParams:
    """``relative_sigma`` (m): what the segment's own line misses of its distance to a plane once
    the scan's common offset is removed (flatness, rotation lever along the scan); ``gate``
    (sigmas) of the relative test; ``ratio``: the least likelihood ratio between two surfaces;
    ``sigma_pose`` (m): the prior on the scan's common offset."""

    relative_sigma: float
    gate: float
    ratio: float
    sigma_pose: float
    sigma_lever: float  # rad: the rotation's error, times a segment's range, in its relative sigma
    walls_only: bool  # floors, ceilings and slopes (normal over 30 deg off horizontal) take the nearest
    veto: bool  # the association keeps the nearest candidate where the choice agrees (else none)
    # the host test (``choose``'s ``hosts``): what a wall's own segment misses of its distance to the
    # wall once the scan's offset is removed (m), and the rotation's lever in it (rad)
    host_sigma: float
    host_lever: float
    host_test: bool
    # each segment judged by the other segments of its scan (leave-one-out), the rotation's lever
    # modelled across them in the map's association (``assoc_kernels._offsets_without_each``)
    model: bool
    # a door's or board's segment past the child's extent that the choice gives to the child is
    # held back (not given to the wall, its only candidate left otherwise)
    hold_past_child: bool
    # the local step test (``assoc_kernels.local_steps``): a segment given to a wall that lies a
    # step off the wall's other segments of its scan whose ends are within ``local_reach`` (m) of
    # its own is a door, board or poster face not yet mapped (or a segment across its edge) and is
    # left to the pool; 0 = off. ``local_gate`` sigmas of the step, whose sigma adds
    # ``local_sigma`` (m, flatness) and the rotation's lever ``local_lever`` (rad) times the two
    # segments' separation to their own sigmas
    local_reach: float
    local_gate: float
    local_sigma: float
    local_lever: float


LocalScalars = tuple[float, float, float, float]


def local_scalars(params: ChoiceParams | None) -> LocalScalars:
    """The local step test's numbers as ``assoc_kernels.local_steps`` takes them: reach (0: off;
    off without a choice and in its veto), gate, the square of ``local_sigma``, lever."""
    if params is None or params.veto or params.local_reach <= 0.0:
        return (0.0, 0.0, 0.0, 0.0)
    return (float(params.local_reach), float(params.local_gate), float(params.local_sigma) ** 2,
            float(params.local_lever))


@dataclass(frozen=True)
class Choice:
    """Per segment: the chosen candidate's column (``NONE``/``HELD`` else), and whether it may
    grow the plane's extent."""

    column: NDArray[np.int64]
    grows: NDArray[np.bool_]


def families(normals: FloatArray, columns: list[int]) -> dict[int, int]:
    """Column -> family label (the smallest column of its family) for the planes ``columns``
    (rows of ``normals`` (P, 3), world frame): parallel within ``PARALLEL_DEG``, same facing.
    (:func:`choose` labels them in its compiled pass: ``assoc_kernels.family_labels``.)"""
    cos_min = float(np.cos(np.radians(PARALLEL_DEG)))
    label: dict[int, int] = {}
    for j in sorted(columns):
        for f in sorted(set(label.values())):
            if float(normals[j] @ normals[f]) > cos_min:
                label[j] = f
                break
        else:
            label[j] = j
    return label


def choose(candidates: list[list[int]], dist: FloatArray, sigma_own: FloatArray, weight: FloatArray,
           normals: FloatArray, params: ChoiceParams, seg_range: FloatArray | None = None,
           hosts: NDArray[np.bool_] | None = None, arm: FloatArray | None = None) -> Choice:
    """The choice for the k segments of one scan: ``candidates[k]`` the columns (planes) passing
    the gates and extents, by increasing Mahalanobis distance; ``dist`` (k, P) the signed
    centroid distances (m), ``sigma_own`` (k,) the centroids' sigmas (m), ``weight`` (k,) the
    segments' point counts, ``normals`` (P, 3) the planes' normals (world frame), ``seg_range``
    (k,) the segments' distances from the scanner (m; a rotation error moves a far segment
    more than the scan's common offset: ``sigma_lever`` times the range). ``hosts`` (P,) marks
    the walls that may carry a door or board not mapped yet: a segment chosen for one of them
    must also pass the host test (``host_sigma``, ``host_lever``), else it is held back. ``arm``
    (k, 3), each centroid less the scanner's position (world frame): the rotation's lever is then
    modelled across the scan's segments instead of added to each one's sigma."""
    start = np.zeros(len(candidates) + 1, dtype=np.int64)
    start[1:] = np.cumsum([len(c) for c in candidates])
    cols = np.array([j for c in candidates for j in c], dtype=np.int64)
    return choose_pairs(start, cols, np.ones(cols.size, dtype=bool), dist, sigma_own, weight, normals, params,
                        seg_range, hosts, arm)


def choose_pairs(start: NDArray[np.int64], cols: NDArray[np.int64], keep: NDArray[np.bool_], dist: FloatArray,
                 sigma_own: FloatArray, weight: FloatArray, normals: FloatArray, params: ChoiceParams,
                 seg_range: FloatArray | None = None, hosts: NDArray[np.bool_] | None = None,
                 arm: FloatArray | None = None, shadow: NDArray[np.bool_] | None = None) -> Choice:
    """:func:`choose` with the candidates as pairs: segment ``k``'s are the ``cols[i]`` where
    ``keep[i]``, ``start[k] <= i < start[k + 1]`` (in order); a pair chosen where ``shadow[i]``
    holds its segment back (a door's segment past the door's extent). One compiled call
    (``slam.frontend.assoc_kernels.choose_columns``)."""
    k_n = start.shape[0] - 1
    column, grows = ak.choose_columns(
        start, cols, np.ascontiguousarray(keep, dtype=np.bool_),
        np.zeros(cols.shape[0], dtype=np.bool_) if shadow is None else np.ascontiguousarray(shadow, dtype=np.bool_),
        np.ascontiguousarray(dist, dtype=np.float64),
        np.ascontiguousarray(sigma_own, dtype=np.float64), np.ascontiguousarray(weight, dtype=np.float64),
        np.zeros(k_n) if seg_range is None else np.ascontiguousarray(seg_range, dtype=np.float64), seg_range is not None,
        np.zeros((k_n, 3)) if arm is None else np.ascontiguousarray(arm, dtype=np.float64).reshape(-1, 3), arm is not None,
        np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3),
        np.zeros(normals.shape[0], dtype=bool) if hosts is None else np.ascontiguousarray(hosts, dtype=np.bool_),
        hosts is not None, *choice_scalars(params),
    )
    return Choice(column, grows)


ChoiceScalars = tuple[float, float, float, float, float, float, float, float, float, bool, bool, float]


@lru_cache(maxsize=16)
def choice_scalars(params: ChoiceParams | None) -> ChoiceScalars:
    """The numbers of ``params`` as ``assoc_kernels.choose_columns`` takes them after ``hosts``:
    the squares of ``relative_sigma``, ``host_sigma`` and the offset prior's sigma (Python's or
    numpy's scalar ``** 2``: the C library's ``pow``), ``gate``, ``sigma_lever``, ``host_lever``,
    the cosine of ``PARALLEL_DEG``, the log of ``ratio``, ``OUTLIER_NATS``, ``walls_only``,
    ``model`` and the exponent 2 (at run time); zeros without a choice."""
    if params is None:
        return (0.0,) * 8 + (OUTLIER_NATS, False, False, 2.0)
    return (params.relative_sigma**2, params.host_sigma**2, max(params.sigma_pose, 1e-6) ** 2, float(params.gate),
            float(params.sigma_lever), float(params.host_lever), float(np.cos(np.radians(PARALLEL_DEG))),
            float(np.log(params.ratio)), OUTLIER_NATS, bool(params.walls_only), bool(params.model), 2.0)
