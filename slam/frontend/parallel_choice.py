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

import numpy as np
from numpy.typing import NDArray

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


@dataclass(frozen=True)
class Choice:
    """Per segment: the chosen candidate's column (``NONE``/``HELD`` else), and whether it may
    grow the plane's extent."""

    column: NDArray[np.int64]
    grows: NDArray[np.bool_]


def families(normals: FloatArray, columns: list[int]) -> dict[int, int]:
    """Column -> family label (the smallest column of its family) for the planes ``columns``
    (rows of ``normals`` (P, 3), world frame): parallel within ``PARALLEL_DEG``, same facing."""
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
           hosts: NDArray[np.bool_] | None = None) -> Choice:
    """The choice for the k segments of one scan: ``candidates[k]`` the columns (planes) passing
    the gates and extents, by increasing Mahalanobis distance; ``dist`` (k, P) the signed
    centroid distances (m), ``sigma_own`` (k,) the centroids' sigmas (m), ``weight`` (k,) the
    segments' point counts, ``normals`` (P, 3) the planes' normals (world frame), ``seg_range``
    (k,) the segments' distances from the scanner (m; a rotation error moves a far segment
    more than the scan's common offset: ``sigma_lever`` times the range). ``hosts`` (P,) marks
    the walls that may carry a door or board not mapped yet: a segment chosen for one of them
    must also pass the host test (``host_sigma``, ``host_lever``), else it is held back."""
    k_n = len(candidates)
    column = np.full(k_n, NONE, dtype=np.int64)
    grows = np.zeros(k_n, dtype=bool)
    used = sorted({j for c in candidates for j in c})
    if not used:
        return Choice(column, grows)
    fam = families(normals, used)
    lever = 0.0 if seg_range is None else (params.sigma_lever * seg_range) ** 2
    s_rel = np.sqrt(sigma_own**2 + params.relative_sigma**2 + lever)
    tau = params.gate * s_rel
    host_lever = 0.0 if seg_range is None else (params.host_lever * seg_range) ** 2
    tau_host = params.gate * np.sqrt(sigma_own**2 + params.host_sigma**2 + host_lever)
    sp2 = max(params.sigma_pose, 1e-6) ** 2
    for f in sorted(set(fam.values())):
        members = [(k, [j for j in c if fam[j] == f]) for k, c in enumerate(candidates)]
        members = [(k, js) for k, js in members if js]
        if not members:
            continue
        if params.walls_only and abs(float(normals[f, 2])) > 0.5:
            for k, js in members:
                if column[k] == NONE:
                    column[k], grows[k] = js[0], True
            continue
        delta, support = _common_offset(members, dist, weight, tau, sp2, tau_host, hosts)
        for k, js in members:
            rho = np.array([dist[k, j] - delta for j in js])
            ok = np.flatnonzero(np.abs(rho) < tau[k])
            if ok.size == 0:
                continue  # on none of this family's planes: NONE unless another family takes it
            if column[k] >= 0 or column[k] == HELD:
                continue  # taken by a family seen earlier (planes of two facings: not expected)
            order = ok[np.argsort(np.abs(rho[ok]), kind="stable")]
            a = order[0]
            decided = True
            for b in order[1:]:
                same = abs(rho[b] - rho[a]) < s_rel[k]
                if same:
                    continue
                llr = 0.5 * (rho[b] ** 2 - rho[a] ** 2) / s_rel[k] ** 2
                if llr < np.log(params.ratio):
                    decided = False
                    break
            # a wall's segment that its own line puts off the wall by more than the host test: as
            # likely a door's or board's whose plane is not a candidate (not made yet, or the
            # segment runs past its extent, straddling its edge); neither the wall's nor pooled
            if decided and hosts is not None and hosts[js[a]] and abs(rho[a]) >= tau_host[k]:
                decided = False
            if not decided:
                column[k] = HELD
                continue
            column[k] = js[a]
            grows[k] = len(js) == 1 or (support >= 2 and ok.size == 1)
    return Choice(column, grows)


def _common_offset(members: list[tuple[int, list[int]]], dist: FloatArray, weight: FloatArray, tau: FloatArray,
                   sp2: float, tau_host: FloatArray, hosts: NDArray[np.bool_] | None) -> tuple[float, int]:
    """The scan's common offset along a family's normal and the number of segments it explains:
    the hypothesis (no offset, or one segment's distance to one of its candidates) of the highest
    likelihood, each segment left unexplained (no candidate within ``tau``) costing
    ``OUTLIER_NATS`` and the offset its prior ``N(0, sp2)``; refined to the point-weighted mean of
    its inliers' distances, where an inlier of a host wall (``hosts``) must pass the host test
    (``tau_host``): a door's segments 1 cm off the wall, inliers of the wall's wide gate, would
    pull the offset towards the door and let the segment straddling its edge onto the wall.
    (Testing all hypotheses at once in numpy is no faster: a family has a few segments.)"""
    best_score, delta, support = -np.inf, 0.0, 0
    # per segment as Python floats (the same doubles, without numpy's per-scalar cost): its
    # candidates' distances, whether each is a host wall, its weight and both gates
    rows = [([float(dist[k, j]) for j in js], [hosts is not None and bool(hosts[j]) for j in js], float(weight[k]),
             float(tau[k]), float(tau_host[k])) for k, js in members]
    # no offset at all is a hypothesis too: a lone segment 1.5 cm off its only candidate (a door's
    # off the wall's plane, the door's plane not made yet) is then unexplained rather than the
    # proof of a 1.5 cm pose error
    hyps = sorted({0.0} | {d for ds, _, _, _, _ in rows for d in ds})
    for h in hyps:
        w_in, n_in, acc = 0.0, 0, 0.0
        for ds, hs, w, t, t_host in rows:
            if len(ds) == 1:
                i, r = 0, ds[0] - h
            else:
                i, r = min(enumerate(d - h for d in ds), key=lambda ir: abs(ir[1]))
            if abs(r) < t:
                n_in += 1
                if not hs[i] or abs(r) < t_host:
                    w_in += w
                    acc += w * (h + r)
        score = n_in * OUTLIER_NATS - 0.5 * h * h / sp2
        if score > best_score:
            best_score, delta, support = score, acc / w_in if w_in > 0 else h, n_in
    return delta, support
