"""Tracking the newest knots against the map before association (``frontend.tracking``).

When a knot is processed its predicted pose is held in the knot mirror; the scans that became
ready are associated with the loosened tracking gates (and their breaks matched to known edges
with the tracking gate), and the last ``window`` knot intervals are refined together by
Gauss-Newton against the fixed planes, from the recent scans' loosely associated segments and
breaks. The tight association then runs from the tracked poses.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from slam.frontend.association import Gates, ScanAssociator
from slam.frontend.edge_tracker import EdgeFeature
from slam.frontend.knots import KnotMirror
from slam.frontend.motion_model import MotionModel
from slam.frontend.pending import PendingScan, ScanQueues
from slam.frontend.planemap import PlaneMap
from slam.frontend.tracking import TrackingParams, refine_window

FloatArray = NDArray[np.float64]


class WindowTracker:
    """Refines the window of the newest knots (``knots``) against the map (``pmap``, planes
    fixed; ``edges``' edge planes too), with ``gates`` (the loosened ones) for the
    pre-association and the motion model's (``motion``) hold on each interval."""

    def __init__(self, params: TrackingParams, gates: Gates, knots: KnotMirror, pmap: PlaneMap, queues: ScanQueues,
                 associator: ScanAssociator, edges: EdgeFeature, motion: MotionModel,
                 children: Callable[[], dict[int, int]]) -> None:
        self.params = params
        self.gates = gates
        self._knots = knots
        self._pmap = pmap
        self._queues = queues
        self._associator = associator
        self._edges = edges
        self._motion = motion
        self._children = children

    def track(self, ready: list[PendingScan], k_new: int, T_pred: FloatArray) -> FloatArray:
        """Refine the window of the last ``window`` knots, the new one (held at ``T_pred``)
        included, against the map: loose association of the ready scans, then windowed
        Gauss-Newton over the recent scans. Returns the new knot's pose (4, 4)."""
        k0 = max(0, k_new - self.params.window)
        recent = self._queues.track(ready, self._knots.time(k0))
        if k_new < 1 or self.params.iterations == 0 or len(self._pmap) == 0 or not recent:
            return T_pred
        hosts = self._children() if self._edges.tracks() else None
        side = self._associator.map_side(self.gates)  # the map does not change while the scans are tracked
        for p, summary in zip(ready, self._associator.summaries(ready), strict=True):
            p.loose_ids = self._associator.associate(p, self.gates, summary, side).ids
            if hosts is not None:
                self._edges.match_loose(p, hosts)
        pts: list[FloatArray] = []
        kis: list[NDArray[np.int64]] = []
        al: list[FloatArray] = []
        nrm: list[FloatArray] = []
        off: list[FloatArray] = []
        sig: list[FloatArray] = []
        # the recent scans' loosely associated segments, both virtual points each (body
        # frame), gathered in one batch in the order of a loop over scans and segments
        tracked = [p for p in recent if p.loose_ids is not None]
        ids = np.concatenate([p.loose_ids for p in tracked]) if tracked else np.empty(0, dtype=np.int64)
        sel = np.flatnonzero(ids >= 0)
        if sel.size:
            idx, alpha = self._knots.fractions(np.concatenate([p.segs.virtual_times for p in tracked])[sel].ravel())
            keep = np.flatnonzero(idx >= k0)
            if keep.size:
                # the associated planes' current estimates (world frame): normal, offset
                pid = np.repeat(ids[sel], 2)[keep]
                used = np.unique(pid)
                planes = np.array([[*self._pmap.planes[j].normal.tolist(), self._pmap.planes[j].d]
                                   for j in used.tolist()])
                pid = np.searchsorted(used, pid)
                pts.append(np.concatenate([p.segs.virtual_body for p in tracked])[sel].reshape(-1, 3)[keep])
                kis.append(idx[keep] - k0)
                al.append(alpha[keep])
                nrm.append(planes[pid, :3])
                off.append(planes[pid, 3])
                sig.append(np.repeat(np.concatenate([p.segs.virtual_sigma for p in tracked])[sel], 2)[keep])
        for e_pts, e_k, e_al, e_nrm, e_off, e_sig in self._edges.tracking_rows(recent, k0):
            pts.append(e_pts)
            kis.append(e_k)
            al.append(e_al)
            nrm.append(e_nrm)
            off.append(e_off)
            sig.append(e_sig)
        if pts:
            T = self._knots.T
            T[k0 : k_new + 1] = refine_window(
                T[k0 : k_new + 1],
                np.concatenate(kis),
                np.concatenate(al),
                np.concatenate(pts),
                np.concatenate(nrm),
                np.concatenate(off),
                np.maximum(np.concatenate(sig), 0.001),
                self.params.first_prior_sigmas,
                self.params.twist_sigmas,
                iterations=self.params.iterations,
                increment_sigmas=self._motion.increment_sigmas,
                degenerate_ratio=self._motion.degenerate_ratio,
            )
        return self._knots.T[k_new].copy()
