"""Finding a scan's breaks: where its scanline steps between a wall and a door or board
(``frontend.edges`` for the model).

Three kinds of evidence, each giving the point where the surface nearer the scanner ends:

- *pairs*: neighbouring segments, one on a wall, the other parallel to it a step off
  (``frontend.edges.break_pairs``, ``step_of``, computed inline);
- *recesses*: a wall segment that ends into unsegmented returns a door's recess behind it
  (``frontend.edges.recess_beyond``; a door seen obliquely is often left unsegmented);
- *inline steps*: a step inside a wall segment (``frontend.edges.steps_within``; a poster 5 mm
  proud is often left in its wall's segment).

The recess and inline tests depend on the scan alone and are computed once, when the scan is
prepared (``frontend.scan_prep.scan_edge_tests``); here they are only looked up for the
segments that turned out to be walls. Every candidate then passes the same checks (the beam's
incidence on the wall, the step's side and sign along the wall) in :meth:`BreakFinder._break`;
for the pairs (``point`` "midpoint" or "higher") and the recesses of a scan these run in compiled
passes over all its candidates at once (``frontend.edge_kernels``, the same numbers).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from slam.frontend import edge_kernels as ek
from slam.frontend.edges import (
    Break,
    EdgeParams,
    along_wall,
    bracket_point,
    break_sigma,
    is_flat,
    segment_end,
    segment_returns,
    steep_enough,
    surface_end,
)
from slam.frontend.knots import KnotMirror
from slam.frontend.observations import ScanSegments
from slam.frontend.pending import PendingScan
from slam.frontend.planemap import KIND_WALL, PlaneMap

FloatArray = NDArray[np.float64]
_ENDS_KEPT = 64  # scans whose recess ends are kept (a scan is asked while tracked and when associated)


def wall_test(pmap: PlaneMap, hosts: dict[int, int]) -> Callable[[int], bool]:
    """Whether a (current) plane id is a wall and not a door or board tied to one (``hosts``:
    child -> host)."""
    return lambda pid: pmap.planes[pid].kind == KIND_WALL and pid not in hosts


class BreakFinder:
    """A scan's breaks, placed in the world with the current knots (``knots``) against the map's
    walls (``pmap``). ``T_body_scanner`` (4, 4) and ``range_sigma`` (m) per scanner."""

    def __init__(self, params: EdgeParams, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray],
                 range_sigma: list[float]) -> None:
        self.params = params
        self._pmap = pmap
        self._knots = knots
        self._T_body_scanner = T_body_scanner
        self._range_sigma = range_sigma
        self._along: dict[int, tuple[FloatArray, FloatArray]] = {}  # plane id -> (its normal, along_wall of it)
        self._min_sin = float(np.sin(np.radians(params.min_incidence_deg)))
        # the recess ends of the scans asked last (:meth:`_recess_end`), by id, with the scan held
        self._ends: dict[int, tuple[PendingScan, dict[tuple[int, int], tuple[FloatArray, float, float] | None]]] = {}

    def breaks(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int]) -> list[Break]:
        """The breaks of scan ``p`` with plane ids ``ids`` per segment and the doors' and boards'
        hosts ``hosts`` (child -> wall). Found again only when the ids or hosts changed since
        the last call for this scan; else the last ones placed with the current knots."""
        memo = p.breaks_memo
        ids_key = ids.tobytes()
        if memo is not None and memo[0] == ids_key and memo[1] == hosts:
            return self._replaced(memo[2])
        out = self._find(p, ids, hosts)
        p.breaks_memo = (ids_key, dict(hosts), out)
        return out

    def _replaced(self, breaks: list[Break]) -> list[Break]:
        """The breaks placed in the world with the current trajectory (the map is unchanged)."""
        if not breaks:
            return []
        w = self._knots.place(np.array([b.point_body for b in breaks]), np.array([b.time for b in breaks]))
        u = ek.along_offsets(np.array([self._wall_row(b.host)[2] for b in breaks]), w).tolist()
        return [Break(b.host, b.step, b.side, u[i], b.point_body, w[i], b.time, b.sigma, b.serial, b.flat)
                for i, b in enumerate(breaks)]

    def _find(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int]) -> list[Break]:
        segs = p.segs
        is_wall = wall_test(self._pmap, hosts)
        pids = ids.tolist()
        wall_pid = {pid: is_wall(pid) for pid in set(pids) if pid >= 0}
        walls = [j for j, pid in enumerate(pids) if pid >= 0 and wall_pid[pid]]
        if not walls:  # every pair has a wall segment
            return []
        origin = (self._knots.pose_at(segs.stamp) @ self._T_body_scanner[segs.scanner][:, 3])[:3]
        out = self._recess_breaks(p, ids, walls, origin)
        if self.params.inline:
            out += self._inline_breaks(p, ids, walls, origin)
        wall = np.zeros(len(pids), dtype=np.bool_)
        wall[walls] = True
        if self.params.point == "bracket":
            order = np.argsort(segs.first_beam, kind="stable")
            pairs = ek.break_pairs(order, np.ascontiguousarray(segs.n_points, dtype=np.int64), wall,
                                   self.params.max_skipped_points)
            return out + self._pair_breaks(p, ids, [(int(a), int(b)) for a, b in pairs.tolist()], origin)
        return out + self._pair_breaks_batch(p, ids, wall, walls, origin)

    def _break(self, p: PendingScan, wall: int, origin: FloatArray, x_world: FloatArray, point_body: FloatArray,
               time: float, spacing: float, step_point: FloatArray, step_height: float,
               line_world: FloatArray) -> Break | None:
        """The break at ``x_world`` (world; ``point_body`` body frame at ``time``) on ``wall``, or
        None where the beam from ``origin`` meets the wall too near grazing. ``step_point``
        (world) lies on the step's side of the edge, ``step_height`` is positive for a step in
        front of the wall; ``line_world`` is the scanline's direction there (for ``flat``)."""
        ep = self.params
        n_wall = self._pmap.planes[wall].normal
        if not steep_enough(origin, x_world, n_wall, ep.min_incidence_deg):
            return None
        n_e = along_wall(n_wall)
        side = 1 if float(n_e @ (step_point - x_world)) > 0.0 else -1
        step = 1 if step_height > 0.0 else -1
        return Break(wall, step, side, float(n_e @ x_world), point_body, x_world, time,
                     break_sigma(spacing, ep.sigma), p.serial, flat=is_flat(line_world, n_wall, ep.flat_slope))

    def _pair_breaks(self, p: PendingScan, ids: NDArray[np.int64], pairs: list[tuple[int, int]],
                     origin: FloatArray) -> list[Break]:
        """Breaks between a wall segment and its neighbour a step off it."""
        ep = self.params
        segs = p.segs
        if not pairs:
            return []
        # the pairs whose boundary points lie within the gap, with those points (the end of the
        # earlier segment and the start of the later one), for all pairs at once
        jw, jo = np.array(pairs, dtype=np.int64).T
        lo = np.where(segs.first_beam[jw] < segs.first_beam[jo], jw, jo)
        hi = np.where(lo == jw, jo, jw)
        ia, ib = segs.offsets[lo + 1] - 1, segs.offsets[hi]
        ok = (segs.n_points[jo] >= ep.min_segment_points) & ~(
            np.linalg.norm(segs.points_body[ia] - segs.points_body[ib], axis=1) > ep.max_gap)
        cand = np.column_stack((jw, jo, lo, hi, ia, ib))[ok].tolist()
        if not cand:
            return []
        # per pair: the two boundary points, the other's and the wall's virtual points, placed in
        # one call for all pairs (per point the numbers of one call per pair)
        c = np.array(cand, dtype=np.int64).reshape(-1, 6)
        js = np.column_stack((c[:, 1], c[:, 0]))
        placed = self._knots.place(
            np.concatenate((segs.points_body[c[:, 4:6]], segs.virtual_body[js].reshape(-1, 4, 3)), axis=1).reshape(-1, 3),
            np.concatenate((segs.times[c[:, 4:6]], segs.virtual_times[js].reshape(-1, 4)), axis=1).ravel(),
        ).reshape(-1, 6, 3)
        out = []
        for (j_wall, j_other, lo, hi, ia, ib), w in zip(cand, placed, strict=True):
            wall = int(ids[j_wall])
            n_wall = self._pmap.planes[wall].normal
            # the six points along the wall normal; the means of the wall's and the other's two
            # virtual points (``step_of``'s numbers, with one product for all of them)
            h = (w @ n_wall).tolist()
            h_wall, h_other = (h[4] + h[5]) / 2.0, (h[2] + h[3]) / 2.0
            if int(ids[j_other]) == wall:  # both on the wall's plane: the nearer one is the wall
                d_wall = self._pmap.planes[wall].d
                if abs(h_wall + d_wall) > abs(h_other + d_wall):
                    continue
            s1, s2 = h[2] - h_wall, h[3] - h_wall  # step_of(n_wall, w[4:6], w[2:4])
            if abs(s1 - s2) > ep.step_tolerance or not ep.min_step <= abs(0.5 * (s1 + s2)) <= ep.max_step:
                continue
            # the edge point is the end of the surface nearer the scanner (the wall for a door, the
            # board for a board): beyond the edge the lower surface is shadowed or seen on the step's
            # face, by an amount that depends on the view; the higher one ends at the edge either way
            h_view = float(n_wall @ origin)
            wall_higher = abs(h_view - h_wall) < abs(h_view - h_other)
            higher_is_lo = wall_higher == (j_wall == lo)
            i_end, i_next, q = (ia, ia - 1, 0) if higher_is_lo else (ib, ib + 1, 1)
            x_world = w[q]
            pt_body, t = segs.points_body[i_end].copy(), float(segs.times[i_end])
            spacing = float(np.linalg.norm(segs.points_body[i_end] - segs.points_body[i_next]))
            if ep.point == "bracket":
                j_high = lo if higher_is_lo else hi
                k_end = int(segs.last_beam[lo]) if higher_is_lo else int(segs.first_beam[hi])
                direction = 1 if higher_is_lo else -1
                # half the step: a return on the lower surface stays off the higher one's line
                tol = min(3.0 * self._range_sigma[segs.scanner], 0.5 * abs(0.5 * (s1 + s2)))
                got = _bracket_end(segs, j_high, k_end, direction, tol)
                if got is None:
                    continue
                edge_scanner, spacing = got
                T_bs = self._T_body_scanner[segs.scanner]
                pt_body = T_bs[:3, :3] @ np.array([edge_scanner[0], edge_scanner[1], 0.0]) + T_bs[:3, 3]
                x_world = self._knots.place(pt_body[None, :], np.array([t]))[0]
            elif ep.point == "midpoint":
                x_world = 0.5 * (w[0] + w[1])
                pt_body = 0.5 * (segs.points_body[ia] + segs.points_body[ib])
                t = 0.5 * float(segs.times[ia] + segs.times[ib])
                spacing = float(np.linalg.norm(segs.points_body[ia] - segs.points_body[ib]))
            brk = self._break(p, wall, origin, x_world, pt_body, t, spacing, w[2:4].mean(axis=0), s1 + s2, w[3] - w[2])
            if brk is not None:
                out.append(brk)
        return out

    def _pair_breaks_batch(self, p: PendingScan, ids: NDArray[np.int64], wall: NDArray[np.bool_], walls: list[int],
                           origin: FloatArray) -> list[Break]:
        """:meth:`_pair_breaks` with ``point`` "midpoint" or "higher", for the segments ``walls``
        (``wall``: per segment) of the scan: the pairs found, filtered and checked in one compiled
        call (``edge_kernels.scan_pair_breaks``: the candidates, their placing and the checks)."""
        ep = self.params
        segs = p.segs
        seg_normal, seg_d, seg_along = self._segment_walls(ids, walls)
        knots = self._knots
        assert knots.t0 is not None
        jw, keep, side, step, u, flat, x_world, pt_body, t, spacing = ek.scan_pair_breaks(
            np.argsort(segs.first_beam, kind="stable"), segs.n_points, wall, ep.max_skipped_points, segs.first_beam,
            segs.offsets, segs.points_body, segs.times, segs.virtual_body, segs.virtual_times,
            ep.min_segment_points, ep.max_gap, knots.T, knots.t0, knots.dt, knots.n, ids, seg_normal, seg_d,
            seg_along, origin, ep.step_tolerance, ep.min_step, ep.max_step, self._min_sin, ep.flat_slope,
            ep.point == "midpoint")
        kept = np.flatnonzero(keep).tolist()
        if not kept:
            return []
        wall_ids, steps, sides, us, ts, spacings, flats = (
            a.tolist() for a in (ids[jw], step, side, u, t, spacing, flat))
        return [Break(wall_ids[c], steps[c], sides[c], us[c], pt_body[c], x_world[c], ts[c],
                      break_sigma(spacings[c], ep.sigma), p.serial, flat=flats[c]) for c in kept]

    def _segment_walls(self, ids: NDArray[np.int64], walls: list[int]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per segment of the scan (plane ids ``ids``), for the wall segments ``walls``: the wall's
        normal (k, 3), offset (k,) and along-wall direction (k, 3), world frame (zero elsewhere)."""
        k = ids.shape[0]
        normal, d, along = np.zeros((k, 3)), np.zeros(k), np.zeros((k, 3))
        for j in walls:
            pid = int(ids[j])
            normal[j], d[j], along[j] = self._wall_row(pid)
        return normal, d, along

    def _wall_row(self, pid: int) -> tuple[FloatArray, float, FloatArray]:
        """Plane ``pid``'s normal, offset and along-wall direction (``along_wall``, kept while the
        plane keeps its normal array: estimates replace it)."""
        plane = self._pmap.planes[pid]
        got = self._along.get(pid)
        if got is None or got[0] is not plane.normal:
            got = (plane.normal, along_wall(plane.normal))
            self._along[pid] = got
        return plane.normal, plane.d, got[1]

    def _wall_rows(self, walls: list[int]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The walls' normals (n, 3), offsets (n,) and along-wall directions (n, 3), world frame."""
        rows = [self._wall_row(pid) for pid in walls]
        return (np.array([r[0] for r in rows], dtype=np.float64).reshape(-1, 3),
                np.array([r[1] for r in rows], dtype=np.float64),
                np.array([r[2] for r in rows]).reshape(-1, 3))

    def _recess_breaks(self, p: PendingScan, ids: NDArray[np.int64], walls: list[int],
                       origin: FloatArray) -> list[Break]:
        """Breaks where a wall segment ends into a door's recess behind it; the wall is the nearer
        surface, so its end is bracketed as for a segmented pair (:meth:`_recess_end`), placed
        for all the ends in one call and checked in one compiled pass."""
        # asked of every long enough segment end that no other segment follows within three
        # beams (there the pairs handle the end); a missing test is a failed one
        tests = p.edge_tests
        keys = [(j, direction) for j in walls for direction in (1, -1) if tests.get((j, direction)) is not None]
        if not keys:
            return []
        held = self._ends.get(id(p))
        if held is None:
            held = self._ends[id(p)] = (p, {})
            if len(self._ends) > _ENDS_KEPT:
                del self._ends[next(iter(self._ends))]
        memo = held[1]
        ends = []
        for key in keys:
            if key not in memo:
                memo[key] = self._recess_end(p, *key)
            got = memo[key]
            if got is not None:
                ends.append((key[0], got))
        if not ends:
            return []
        segs = p.segs
        js = [j for j, _ in ends]
        # per end: its edge point and the first return inside the recess (body frame), the
        # wall's two virtual points; one place call for all (per point the numbers of one call per end)
        pts = np.concatenate((np.array([got[0] for _, got in ends]), segs.virtual_body[js]), axis=1)
        t = np.array([got[2] for _, got in ends])
        w = self._knots.place(pts.reshape(-1, 3), np.repeat(t, 4)).reshape(-1, 4, 3)
        wall_ids = ids[js].tolist()
        n_wall, _, n_e = self._wall_rows(wall_ids)
        keep, side, step, u, flat = ek.recess_breaks(w, n_wall, n_e, origin, self._min_sin, self.params.flat_slope)
        kept = np.flatnonzero(keep).tolist()
        if not kept:
            return []
        steps, sides, us, ts, flats = (a.tolist() for a in (step, side, u, t, flat))
        return [Break(wall_ids[c], steps[c], sides[c], us[c], ends[c][1][0][0], w[c, 0], ts[c],
                      break_sigma(ends[c][1][1], self.params.sigma), p.serial, flat=flats[c]) for c in kept]

    def _recess_end(self, p: PendingScan, j: int, direction: int) -> tuple[FloatArray, float, float] | None:
        """Segment ``j``'s end in ``direction``, where the scan's recess test passed there: its edge
        point and the first return inside the recess (2, 3) body frame, the beam spacing there (m)
        and the end point's time (s); None where the end cannot be bracketed. It depends on the
        scan alone (:meth:`_recess_breaks` keeps it for the scan)."""
        segs = p.segs
        _, k_in, depth = p.edge_tests[(j, direction)]
        tolerance = min(3.0 * self._range_sigma[segs.scanner], 0.5 * depth)
        found, ex, ey, spacing = ek.bracket_on_line(segs.beam_angles, segs.beam_ranges, segs.beam_valid,
                                                    segs.line_centroid[j], segs.line_direction[j],
                                                    segment_end(segs, j, direction), direction, tolerance)
        if not found:
            return None
        T_bs = self._T_body_scanner[segs.scanner]
        r_in, a_in = float(segs.beam_ranges[k_in]), float(segs.beam_angles[k_in])
        pts_scanner = np.array([[ex, ey, 0.0], [r_in * np.cos(a_in), r_in * np.sin(a_in), 0.0]])
        i_end = int(segs.offsets[j + 1]) - 1 if direction == 1 else int(segs.offsets[j])
        t = float(segs.times[i_end])
        return self._knots.deskewed(pts_scanner @ T_bs[:3, :3].T + T_bs[:3, 3], np.full(2, t)), spacing, t

    def _inline_breaks(self, p: PendingScan, ids: NDArray[np.int64], walls: list[int],
                       origin: FloatArray) -> list[Break]:
        """Breaks at steps inside wall segments. The surface nearer the scanner is bracketed as
        for a segmented pair, on the line through its own window of points."""
        segs = p.segs
        T_bs = self._T_body_scanner[segs.scanner]
        sigma = self._range_sigma[segs.scanner]
        W = self.params.inline_window
        out = []
        for j in walls:
            steps = p.edge_tests.get((j, 0))  # asked of every segment of 2 W points or more
            if not steps:
                continue
            beams, xy = segment_returns(segs, j)
            c2, u2 = segs.line_centroid[j], segs.line_direction[j]
            wall = int(ids[j])
            n_wall, d_wall = self._pmap.planes[wall].normal, self._pmap.planes[wall].d
            normal2 = np.array([-u2[1], u2[0]])
            toward_scanner = float(normal2 @ (-c2))  # the scanner's side of the line
            for k, depth in steps:
                left, right = xy[max(0, k + 1 - W) : k + 1], xy[k + 1 : k + 1 + W]
                right_high = (depth > 0.0) == (toward_scanner > 0.0)
                high = right if right_high else left
                k_end, direction = (int(beams[k + 1]), -1) if right_high else (int(beams[k]), 1)
                got = _bracket_on_line(segs, high.mean(axis=0), u2, k_end, direction,
                                       min(3.0 * sigma, 0.5 * abs(depth)))
                if got is None:
                    continue
                edge_scanner, spacing = got
                pts_scanner = np.zeros((3, 3))
                pts_scanner[:, :2] = (edge_scanner, left.mean(axis=0), right.mean(axis=0))
                i_k = int(segs.offsets[j]) + k
                t = float(segs.times[i_k])
                pts_body = self._knots.deskewed(pts_scanner @ T_bs[:3, :3].T + T_bs[:3, 3], np.full(3, t))
                w = self._knots.place(pts_body, np.full(3, t))
                # of the two sides the one on the wall's plane is the wall, the other the step
                on_wall = np.abs(w[1:] @ n_wall + d_wall)
                other = w[2] if on_wall[0] <= on_wall[1] else w[1]
                base = w[1] if on_wall[0] <= on_wall[1] else w[2]
                brk = self._break(p, wall, origin, w[0], pts_body[0], t, spacing, other,
                                  float(n_wall @ (other - base)), w[2] - w[1])
                if brk is not None:
                    out.append(brk)
        return out


def _bracket_end(segs: ScanSegments, j: int, k_end: int, direction: int,
                 tolerance: float) -> tuple[FloatArray, float] | None:
    """The edge where segment ``j``'s surface ends at beam ``k_end`` (walking ``direction``)."""
    return _bracket_on_line(segs, segs.line_centroid[j], segs.line_direction[j], k_end, direction, tolerance)


def _bracket_on_line(segs: ScanSegments, c2: FloatArray, u2: FloatArray, k_end: int, direction: int,
                     tolerance: float) -> tuple[FloatArray, float] | None:
    """The edge where the surface on the 2D line (``c2``, ``u2``; scanner frame) ends at beam
    ``k_end`` (walking ``direction``): the end walked over beams still on the line within
    ``tolerance`` (``surface_end``), then bracketed with the next beam (``bracket_point``);
    (point (2,) scanner frame, spacing) or None."""
    k_end = surface_end(k_end, direction, segs.beam_angles, segs.beam_ranges, segs.beam_valid, c2, u2, tolerance)
    k_next = k_end + direction
    if not 0 <= k_next < segs.beam_angles.shape[0]:
        return None
    return bracket_point(float(segs.beam_angles[k_end]), float(segs.beam_angles[k_next]), c2, u2)
