"""The compiled association (slam.frontend.assoc_kernels, through association.associate_scan and
parallel_choice.choose) against the Python code it replaced, kept here as the reference: the same
plane ids, the same choices, bit for bit, on random scans and maps and on the edge cases (no
candidates, one segment, an empty scan, no active plane, children of a host wall)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from slam.config import SlamConfig
from slam.frontend import assoc_kernels as ak
from slam.frontend import kernels as fk
from slam.frontend.association import (
    Association,
    Gates,
    ScanAssociator,
    WorldSegments,
    associate_scan,
)
from slam.frontend.parallel_choice import (
    HELD,
    NONE,
    OUTLIER_NATS,
    PARALLEL_DEG,
    Choice,
    ChoiceParams,
    choose,
    families,
    local_scalars,
)
from slam.frontend.planemap import KIND_CEILING, KIND_FLOOR, KIND_WALL, PlaneMap
from slam.params import gates as config_gates
from slam.params import tracking_gates

FloatArray = NDArray[np.float64]


# --- the reference: parallel_choice before the kernels -------------------------------------------

def _families_reference(normals: FloatArray, columns: list[int]) -> dict[int, int]:
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


def _choose_reference(candidates: list[list[int]], dist: FloatArray, sigma_own: FloatArray, weight: FloatArray,
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
    fam = _families_reference(normals, used)
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
        delta, support = _common_offset_reference(members, dist, weight, tau, sp2, tau_host, hosts)
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


def _common_offset_reference(members: list[tuple[int, list[int]]], dist: FloatArray, weight: FloatArray, tau: FloatArray,
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


# --- the reference: association.associate_scan before the kernels --------------------------------

def _associate_scan_reference(segs: WorldSegments, pmap: PlaneMap, odometer: float, gates: Gates,
                   children: dict[int, int] | None = None) -> Association:
    """The segments of one scan (world frame) against the map: :class:`Association`.

    ``children`` maps the planes tied parallel to a host wall (a door set 1-2 cm into it, a board
    1-2 cm proud of it) to their host. A door's segment and the wall's next to it differ by those
    1-2 cm only, well inside the distance gate, so the nearer plane takes each; a child fitted a
    little tilted is then nearer the wall's (or a neighbouring board's) segments at one end of its
    extent, takes them, and tilts further. With ``gates.child_host_normal`` a child's distance is
    taken to the plane with its host's normal through the centre of its extent (the tie's model,
    which the child's own tilt cannot move), and with ``gates.child_margin_cells`` >= 0 its
    extent is dilated by that many cells only (a door's extent does not reach the next board).

    The per-pair gates (angle and distance, end points, facing side) and every pair's extent
    cells are computed in one compiled pass (``slam.kernels.association_gates``); the
    extents (Python sets of cells) are then tested only for the pairs under the gates.
    """
    out = np.full(segs.n, NONE, dtype=np.int64)
    active = pmap.active_planes()
    if not active or segs.n == 0:
        return Association(out, np.zeros(segs.n, dtype=bool))
    # the active planes' arrays (world frame): normal, offset, offset sigma, odometer when last
    # seen, in-plane axes u and v
    ids = [p.id for p in active]
    rows, horizontal = pmap.active_rows()
    child_rows: list[int] = []
    if children:
        pos = {pid: j for j, pid in enumerate(ids)}
        child_rows = [pos[c] for c in children if c in pos]
        if gates.child_host_normal:
            for j in child_rows:
                host = pmap.planes[children[ids[j]]]
                centre = pmap.cell_centres(ids[j])
                if not host.active or centre.shape[0] == 0:
                    continue
                n = host.normal if float(host.normal @ rows[j, 0:3]) >= 0.0 else -host.normal
                c = centre.mean(axis=0)
                c = c - (float(rows[j, 0:3] @ c) + rows[j, 3]) * rows[j, 0:3]  # onto the child's plane
                rows[j, 0:3] = n
                rows[j, 3] = -float(n @ c)
    normals = np.ascontiguousarray(rows[:, 0:3])
    since = odometer - rows[:, 5]
    rate = np.where(horizontal, gates.drift_rate_vertical, gates.drift_rate)
    sig_drift = np.minimum(rate * np.maximum(since, 0.0), gates.max_drift_sigma)
    _, _, dist_c, sig_d2, cells, order, count = fk.association_gates(
        segs.centroid, segs.direction, segs.endpoints, segs.sigma_centroid, segs.sigma_direction, segs.range,
        segs.origin, normals, np.ascontiguousarray(rows[:, 3]), np.ascontiguousarray(rows[:, 4]), sig_drift,
        np.ascontiguousarray(rows[:, 6:9]), np.ascontiguousarray(rows[:, 9:12]), float(pmap.cell_size),
        float(gates.sigma_pose), float(gates.sigma_rotation), float(gates.sigma_lever),
        float(gates.max_endpoint_distance), float(gates.chi2),
    )
    hit = np.flatnonzero(count)
    if hit.size == 0:
        return Association(out, np.zeros(segs.n, dtype=bool))
    cell = pmap.cell_size
    # per plane: the extent margin grown with the drift since it was seen (cells)
    dilate = [gates.extent_margin_cells + min(int(3.0 * sd / cell), gates.max_extra_cells) for sd in sig_drift.tolist()]
    if gates.child_margin_cells >= 0:
        for j in child_rows:
            dilate[j] = gates.child_margin_cells
    same_normal = float(np.cos(np.radians(2.0)))
    if gates.choice is not None:
        # the candidates by increasing m2 under the gates and over the (dilated) extents, then
        # the choice between parallel planes from the segments' own lines
        # a door's or board's segments end at its edges (the segmenter breaks there): both end
        # points and the centroid of a segment on it lie within its extent (dilated by the child
        # margin), where a wall's segment runs on past it
        whole = set(child_rows)
        cands: list[list[int]] = [[] for _ in range(segs.n)]
        for k in hit.tolist():
            cands[k] = [j for j in order[k, : count[k]].tolist()
                        if (all(pmap.overlaps_cells(ids[j], [c], dilate[j]) for c in cells[k, j].tolist()) if j in whole
                            else pmap.overlaps_cells(ids[j], cells[k, j].tolist(), dilate[j]))]
        weight = (np.ones(segs.n) if segs.n_points is None else segs.n_points.astype(np.float64))
        # the walls that may carry a door or board (not the children themselves, nor floors and
        # ceilings); not in the tracking's veto, whose poses are still the prediction's
        hosts = None
        if gates.choice.host_test and not gates.choice.veto:
            hosts = np.array([p.kind == KIND_WALL for p in active], dtype=bool)
            hosts[child_rows] = False
        ch = _choose_reference(cands, dist_c, segs.sigma_centroid, weight, normals, gates.choice, segs.range, hosts)
        id_arr = np.asarray(ids, dtype=np.int64)
        chosen = np.where(ch.column >= 0, id_arr[np.maximum(ch.column, 0)], ch.column)
        if not gates.choice.veto:
            grows = ch.grows & (ch.column >= 0)
            reach, gate, flat2, lever = local_scalars(gates.choice)
            if reach > 0.0:  # the local step test after the choice (its behaviour: tests/test_local_steps.py)
                walls = np.array([p.kind == KIND_WALL for p in active], dtype=bool)
                walls[child_rows] = False
                ak.local_steps(chosen, grows, dist_c, id_arr, walls, normals, same_normal, segs.endpoints, segs.centroid,
                            segs.sigma_centroid, weight, reach, gate, flat2, lever)
            return Association(chosen, grows)
    else:
        chosen = None
    for k in hit.tolist():
        # the candidates by increasing m2; the segment's two end points and centroid (world
        # frame) against their extents
        passing = [j for j in order[k, : count[k]].tolist() if pmap.overlaps_cells(ids[j], cells[k, j].tolist(), dilate[j])]
        if not passing:
            continue
        best = passing[0]
        ambiguous = False
        for j in passing[1:]:
            # same surface seen twice (a duplicate awaiting merge) is not ambiguity
            same = (float(normals[best] @ normals[j]) > same_normal) and abs(dist_c[k, best] - dist_c[k, j]) < 3.0 * np.sqrt(sig_d2[k, best])
            if not same:
                ambiguous = True
                break
        if not ambiguous:
            out[k] = ids[best]
    if chosen is not None:
        # the choice as a veto: the nearest candidate where the choice agrees, else none
        out = np.where(out == chosen, out, NONE)
    return Association(out, out >= 0)


# --- random maps and scans ------------------------------------------------------------------------

ORIGIN = np.array([0.3, -0.2, 1.2])


def _random_map(rng: np.random.Generator, n_walls: int) -> tuple[PlaneMap, dict[int, int]]:
    """Walls facing the scanner at ``ORIGIN``, each with a door or board 1-3 cm off it (a child,
    sometimes tilted by a fraction of a degree), a floor and a ceiling; extents of random patches
    (a few planes with none); one plane merged away; offsets' sigmas and sightings at random."""
    pmap = PlaneMap(cell_size=0.25)
    children: dict[int, int] = {}
    for _ in range(n_walls):
        a = rng.uniform(-np.pi, np.pi)
        n = np.array([np.cos(a), np.sin(a), 0.0])
        dist = rng.uniform(0.8, 5.0)
        wall = pmap.add(n, -float(n @ ORIGIN) + dist, KIND_WALL, 0.0, 0.0)
        t = rng.uniform(-0.01, 0.01)
        nc = np.array([np.cos(a + t), np.sin(a + t), 0.0])
        child = pmap.add(nc, -float(nc @ ORIGIN) + dist + rng.choice([-1.0, 1.0]) * rng.uniform(0.01, 0.03), KIND_WALL,
                         0.0, 0.0)
        if rng.uniform() < 0.8:
            children[child.id] = wall.id
    pmap.add(np.array([0.0, 0.0, 1.0]), 0.0, KIND_FLOOR, 0.0, 0.0)
    pmap.add(np.array([0.0, 0.0, -1.0]), 2.6, KIND_CEILING, 0.0, 0.0)
    pmap.add(np.array([0.0, 0.0, 1.0]), -0.015, KIND_FLOOR, 0.0, 0.0)  # a rug
    for p in pmap.planes:
        p.sigma_offset = float(rng.uniform(0.001, 0.01))
        p.last_seen_odometer = float(rng.uniform(0.0, 40.0))
        if rng.uniform() < 0.1:
            continue  # no extent yet
        foot = -p.d * p.normal  # the plane's point nearest the world origin
        centre = foot + rng.uniform(-3.0, 3.0) * p.u + rng.uniform(-1.0, 1.0) * p.v
        size = rng.uniform(0.2, 3.0, 2)
        m = int(rng.integers(5, 200))
        pts = centre + rng.uniform(-1.0, 1.0, (m, 1)) * size[0] * p.u + rng.uniform(-1.0, 1.0, (m, 1)) * size[1] * p.v
        pmap.extend(p.id, pts)
    if len(pmap.planes) > 4 and rng.uniform() < 0.5:
        drop = int(rng.integers(0, len(pmap.planes)))
        keep = (drop + 2) % len(pmap.planes)
        if drop not in children and keep not in children and drop not in children.values():
            pmap.merge(keep, drop)
    return pmap, children


def _random_scan(rng: np.random.Generator, pmap: PlaneMap, k: int) -> WorldSegments:
    """``k`` segments, most on (near) a plane and some of them near its extent, some anywhere."""
    centroid = np.empty((k, 3))
    direction = np.empty((k, 3))
    planes = pmap.active_planes()
    for i in range(k):
        p = planes[int(rng.integers(0, len(planes)))]
        cells = list(p.cells)
        if cells and rng.uniform() < 0.8:
            cu, cv = cells[int(rng.integers(0, len(cells)))]
            uv = (np.array([cu, cv]) + rng.uniform(-1.0, 2.0, 2)) * pmap.cell_size
        else:
            uv = rng.uniform(-4.0, 4.0, 2)
        off = rng.normal(0.0, 0.01) if rng.uniform() < 0.85 else rng.normal(0.0, 0.3)
        centroid[i] = uv[0] * p.u + uv[1] * p.v - p.d * p.normal + off * p.normal
        a = rng.uniform(0.0, np.pi)
        tilt = rng.normal(0.0, 0.01)
        d = np.cos(a) * p.u + np.sin(a) * p.v + tilt * p.normal
        direction[i] = d / np.linalg.norm(d)
    length = rng.uniform(0.1, 1.5, k)
    endpoints = np.stack((centroid - 0.5 * length[:, None] * direction, centroid + 0.5 * length[:, None] * direction),
                         axis=1) + rng.normal(0.0, 0.002, (k, 2, 3))
    rng_m = np.linalg.norm(centroid - ORIGIN, axis=1)
    n_points = rng.integers(4, 300, k)
    return WorldSegments(centroid, direction, endpoints, rng.uniform(0.0002, 0.003, k), rng.uniform(0.002, 0.03, k),
                         rng_m, ORIGIN.copy(), n_points.astype(np.int64))


def _gate_variants() -> list[Gates]:
    """The configuration's gates and tracking's, and variants that exercise every branch."""
    cfg = SlamConfig()
    g, t = config_gates(cfg), tracking_gates(cfg)
    assert g.choice is not None and t.choice is not None
    return [
        g,
        t,
        replace(g, choice=None),
        replace(g, child_host_normal=True, child_margin_cells=0),
        replace(g, choice=replace(g.choice, host_test=True)),
        replace(g, choice=replace(g.choice, walls_only=True, sigma_lever=0.0)),
        replace(t, child_margin_cells=-1, extent_margin_cells=0),
        replace(g, chi2=30.0, sigma_pose=0.03, drift_rate=0.02),
        replace(g, choice=replace(g.choice, local_reach=0.5)),
        replace(g, choice=replace(g.choice, local_reach=3.0, local_gate=1.0, local_sigma=0.0002)),
    ]


def _assert_same(a: Association, b: Association) -> None:
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.grows, b.grows)


@pytest.mark.parametrize("seed", range(12))
def test_associate_scan_matches_the_reference_on_random_scans(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pmap, children = _random_map(rng, int(rng.integers(1, 8)))
    decided = held = 0
    for _ in range(6):
        segs = _random_scan(rng, pmap, int(rng.integers(1, 60)))
        odometer = float(rng.uniform(0.0, 80.0))
        for gates in _gate_variants():
            kids = children if rng.uniform() < 0.8 else None
            got = associate_scan(segs, pmap, odometer, gates, kids)
            ref = _associate_scan_reference(segs, pmap, odometer, gates, kids)
            _assert_same(got, ref)
            decided += int((ref.ids >= 0).sum())
            held += int((ref.ids == HELD).sum())
    assert decided > 0  # associations were made


def test_associate_scan_edge_cases() -> None:
    rng = np.random.default_rng(5)
    pmap, children = _random_map(rng, 3)
    gates = _gate_variants()
    empty = _random_scan(rng, pmap, 1)
    empty = WorldSegments(empty.centroid[:0], empty.direction[:0], empty.endpoints[:0], empty.sigma_centroid[:0],
                          empty.sigma_direction[:0], empty.range[:0], ORIGIN.copy(), empty.n_points[:0])  # type: ignore[index]
    far = _random_scan(rng, pmap, 5)
    far = replace(far, centroid=far.centroid + 50.0, endpoints=far.endpoints + 50.0)  # no candidates
    one = _random_scan(rng, pmap, 1)
    for g in gates:
        for segs in (empty, far, one):
            _assert_same(associate_scan(segs, pmap, 10.0, g, children),
                         _associate_scan_reference(segs, pmap, 10.0, g, children))
        assert (associate_scan(far, pmap, 10.0, g, children).ids == NONE).all()
        assert associate_scan(empty, pmap, 10.0, g, children).ids.shape == (0,)
    none_active = PlaneMap()
    out = associate_scan(one, none_active, 0.0, gates[0], None)
    assert out.ids.tolist() == [NONE] and not out.grows.any()


def test_gate_pairs_match_association_gates() -> None:
    rng = np.random.default_rng(9)
    for trial in range(15):
        pmap, _ = _random_map(rng, int(rng.integers(1, 6)))
        segs = _random_scan(rng, pmap, int(rng.integers(0, 40)))
        rows, _ = pmap.active_rows()
        sig_drift = rng.uniform(0.0, 0.05, rows.shape[0])
        args = (segs.centroid, segs.direction, segs.endpoints, segs.sigma_centroid, segs.sigma_direction, segs.range,
                segs.origin, np.ascontiguousarray(rows[:, 0:3]), np.ascontiguousarray(rows[:, 3]),
                np.ascontiguousarray(rows[:, 4]), sig_drift, np.ascontiguousarray(rows[:, 6:9]),
                np.ascontiguousarray(rows[:, 9:12]), 0.25, 0.01, 0.02, 0.003, 0.1 + 0.05 * trial, 9.21)
        ok, _, dist, sig_d2, cells, order, count = fk.association_gates(*args)
        start, cols, pair_cells, dist2, sig_d2_2 = ak.gate_pairs(*args)
        assert np.array_equal(dist, dist2) and np.array_equal(sig_d2, sig_d2_2)
        np.testing.assert_array_equal(np.diff(start), count)
        for k in range(segs.n):
            js = order[k, : count[k]]
            np.testing.assert_array_equal(cols[start[k]:start[k + 1]], js)
            np.testing.assert_array_equal(pair_cells[start[k]:start[k + 1]], cells[k, js])
        assert count.sum() == ok.sum()


def _choice_params(rng: np.random.Generator) -> ChoiceParams:
    return ChoiceParams(relative_sigma=float(rng.uniform(0.0005, 0.003)), gate=4.0, ratio=float(rng.choice([10.0, 100.0])),
                        sigma_pose=float(rng.choice([0.0, 0.004, 0.02])), sigma_lever=float(np.radians(0.01)),
                        walls_only=bool(rng.uniform() < 0.3), veto=False, host_sigma=0.0004,
                        host_lever=float(np.radians(0.015)), host_test=True, model=False,
                        hold_past_child=False, local_reach=0.0, local_gate=3.0, local_sigma=0.001, local_lever=0.0)


def test_choose_matches_the_reference_on_random_candidates() -> None:
    """Families of parallel planes a few millimetres to centimetres apart, one common offset per
    scan, ties in distance (a duplicate plane: equal offsets), hosts, no range."""
    rng = np.random.default_rng(21)
    outcomes: set[int] = set()
    for _ in range(300):
        p_n = int(rng.integers(1, 7))
        base = rng.normal(size=(3, 3))
        base /= np.linalg.norm(base, axis=1)[:, None]
        normals = base[rng.integers(0, 3, p_n)] + rng.normal(0.0, rng.choice([0.0, 0.01, 0.05]), (p_n, 3))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        offs = np.round(rng.uniform(-0.03, 0.03, p_n), 3)  # duplicates among them
        k_n = int(rng.integers(0, 25))
        shift = rng.normal(0.0, 0.01)
        dist = offs[None, :] + shift + rng.normal(0.0, rng.choice([0.0003, 0.003]), (k_n, p_n))
        cands = [[int(j) for j in np.argsort(np.abs(dist[k]), kind="stable") if rng.uniform() < 0.7] for k in range(k_n)]
        sig = rng.uniform(0.0002, 0.002, k_n)
        weight = rng.integers(4, 200, k_n).astype(np.float64)
        seg_range = rng.uniform(0.5, 8.0, k_n) if rng.uniform() < 0.7 else None
        hosts = rng.uniform(size=p_n) < 0.5 if rng.uniform() < 0.5 else None
        params = _choice_params(rng)
        got = choose(cands, dist, sig, weight, normals, params, seg_range, hosts)
        ref = _choose_reference(cands, dist, sig, weight, normals, params, seg_range, hosts)
        np.testing.assert_array_equal(got.column, ref.column)
        np.testing.assert_array_equal(got.grows, ref.grows)
        outcomes |= set(np.minimum(ref.column, 0).tolist())
    assert outcomes == {0, NONE, HELD}  # chosen, pooled and held segments were all exercised


def test_choose_without_candidates() -> None:
    ch = choose([[], []], np.zeros((2, 1)), np.full(2, 0.001), np.ones(2), np.array([[1.0, 0.0, 0.0]]),
                _choice_params(np.random.default_rng(0)))
    assert ch.column.tolist() == [NONE, NONE] and not ch.grows.any()
    assert isinstance(ch, Choice)
    empty = choose([], np.zeros((0, 1)), np.zeros(0), np.zeros(0), np.array([[1.0, 0.0, 0.0]]),
                   _choice_params(np.random.default_rng(0)))
    assert empty.column.shape == (0,)


def test_family_labels_match_families() -> None:
    rng = np.random.default_rng(4)
    cos_min = float(np.cos(np.radians(PARALLEL_DEG)))
    for _ in range(100):
        p_n = int(rng.integers(1, 10))
        normals = rng.normal(size=(2, 3))[rng.integers(0, 2, p_n)] + rng.normal(0.0, 0.03, (p_n, 3))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        used = sorted(set(rng.integers(0, p_n, p_n).tolist()))
        label = ak.family_labels(normals, np.array(used, dtype=np.int64), cos_min)
        assert {j: int(label[j]) for j in used} == families(normals, used) == _families_reference(normals, used)
    assert OUTLIER_NATS > 0


class _Knots:
    """A stand-in for ``KnotMirror``: ``place`` row by row (a rotation and a time-dependent shift),
    ``pose_at`` a pose per stamp; it counts the points placed."""

    odometer = 0.0

    def __init__(self) -> None:
        self.R = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]
        self.placed = 0

    def place(self, points_body: FloatArray, times: FloatArray) -> FloatArray:
        self.placed += points_body.shape[0]
        return points_body @ self.R.T + times[:, None] * np.array([0.3, -0.1, 0.05])

    def pose_at(self, t: float) -> FloatArray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = [t, 2.0 * t, -t]
        return T


def _pending(rng: np.random.Generator, serial: int) -> SimpleNamespace:
    k = int(rng.integers(1, 8))
    counts = rng.integers(2, 30, k)
    offsets = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    m = int(offsets[-1])
    segs = SimpleNamespace(offsets=offsets, points_body=rng.normal(size=(m, 3)), times=rng.uniform(0.0, 1.0, m),
                           virtual_body=rng.normal(size=(k, 2, 3)), virtual_times=rng.uniform(0.0, 1.0, (k, 2)),
                           n_segments=k, stamp=float(rng.uniform()), scanner=int(rng.integers(0, 2)))
    return SimpleNamespace(serial=serial, segs=segs)


def _summaries_reference(knots: _Knots, T_body_scanner: list[FloatArray], ps: list[Any]) -> list[Any]:
    """``ScanAssociator.summaries`` before the gathered points were kept."""
    pts, tms, sizes = [], [], []
    for p in ps:
        segs = p.segs
        ends_idx = np.stack((segs.offsets[:-1], segs.offsets[1:] - 1), axis=1).ravel()
        pts += [segs.virtual_body.reshape(-1, 3), segs.points_body[ends_idx]]
        tms += [segs.virtual_times.ravel(), segs.times[ends_idx]]
        sizes += [2 * segs.n_segments, 2 * segs.n_segments]
    w = np.split(knots.place(np.concatenate(pts), np.concatenate(tms)), np.cumsum(sizes)[:-1])
    return [(w[2 * i].reshape(-1, 2, 3), w[2 * i + 1].reshape(-1, 2, 3),
             knots.pose_at(p.segs.stamp) @ T_body_scanner[p.segs.scanner][:, 3]) for i, p in enumerate(ps)]


def test_summaries_match_the_reference_over_overlapping_calls() -> None:
    """The tracking's and the observation's calls share scans (their gathered points are kept);
    every call's summaries are those of the old code, whatever was kept."""
    rng = np.random.default_rng(3)
    knots = _Knots()
    T_bs = [np.eye(4), np.eye(4)]
    T_bs[1][:3, 3] = [0.1, 0.2, 0.3]
    sa = ScanAssociator(PlaneMap(), knots, T_bs, 0.003, 4, dict)  # type: ignore[arg-type]
    scans = [_pending(rng, i) for i in range(400)]
    for first in range(0, 390, 3):
        ps = scans[first : first + int(rng.integers(1, 8))]
        got = sa.summaries(ps)  # type: ignore[arg-type]
        ref = _summaries_reference(knots, T_bs, ps)
        assert len(got) == len(ref)
        for g, r in zip(got, ref, strict=True):
            for a, b in zip(g, r, strict=True):
                assert a.shape == b.shape and np.array_equal(a, b)
    scans[5] = SimpleNamespace(serial=5, segs=_pending(rng, 5).segs)  # a serial seen before, other segments
    got = sa.summaries([scans[5]])  # type: ignore[list-item]
    np.testing.assert_array_equal(got[0][0], _summaries_reference(knots, T_bs, [scans[5]])[0][0])
    assert sa.summaries([]) == []


# --- the whole scan in one call (assoc_scan_kernels.associate_segments) ---------------------------

@pytest.mark.parametrize("seed", range(6))
def test_associate_segments_is_summaries_then_associate_scan(seed: int) -> None:
    """``ScanAssociator.associate``'s one compiled call against the Python path it replaced:
    ``world_segments``, :func:`associate_scan`, then the short segments left unassociated."""
    from slam.frontend.assoc_scan_kernels import associate_segments
    from slam.frontend.association import (
        _NO_HOSTS,
        _SAME_NORMAL,
        _gate_scalars,
        _map_inputs,
        world_segments,
    )

    rng = np.random.default_rng(100 + seed)
    pmap, children = _random_map(rng, int(rng.integers(1, 8)))
    decided = 0
    for _ in range(6):
        s = _random_scan(rng, pmap, int(rng.integers(1, 60)))
        half = rng.uniform(0.05, 0.5, s.n)[:, None] * s.direction
        virtual = np.stack((s.centroid - half, s.centroid + half), axis=1) + rng.normal(0.0, 0.001, (s.n, 2, 3))
        vsig = rng.uniform(0.0003, 0.004, s.n)
        n_points = rng.integers(1, 40, s.n).astype(np.int64)
        point_sigma, min_points, odometer = float(rng.uniform(0.001, 0.01)), int(rng.integers(1, 12)), float(rng.uniform(0, 80))
        for gates in _gate_variants():
            kids = children if rng.uniform() < 0.8 else None
            ws = world_segments(virtual, s.endpoints, vsig, point_sigma, n_points, ORIGIN)
            ref = associate_scan(ws, pmap, odometer, gates, kids)
            ref.ids[n_points < min_points] = NONE
            ref.grows[n_points < min_points] = False
            m = _map_inputs(pmap, gates, kids)
            assert m is not None
            g = _gate_scalars(gates)
            c = gates.choice
            ids, grows = associate_segments(
                virtual, np.ascontiguousarray(s.endpoints), vsig, point_sigma, n_points, ORIGIN, min_points, m.rows,
                m.horizontal, m.ids, m.child_rows, m.is_child, odometer, float(pmap.cell_size), g[0], g[1],
                pmap.extents.keys, pmap.extents.count, pmap.extents.box, c is not None, c is not None and c.veto,
                c is not None and c.hold_past_child, m.hosts, m.hosts is not _NO_HOSTS, _SAME_NORMAL, g[2], m.walls,
                local_scalars(c))
            _assert_same(Association(ids, grows), ref)
            decided += int((ids >= 0).sum())
    assert decided > 0
