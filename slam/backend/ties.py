"""Planes and what ties them: floor/ceiling and wall priors, equality links (incremental merges),
orientation ties (parallel, perpendicular), and the merges that fold two planes into one.

A tie survives the merges of the planes it holds (re-keyed onto the surviving plane) and goes
with a removed plane. The error functions have analytic Jacobians (tests check them against
numerical differentiation on the manifold).
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P
from numpy.typing import ArrayLike, NDArray

from slam.backend.blocks import BlockStore
from slam.backend.graph import FactorGraph
from slam.motion import horizontal_plane_prior

FloatArray = NDArray[np.float64]


class PlaneTies:
    """The planes of a :class:`FactorGraph`: their variables, priors, links and orientation ties."""

    def __init__(self, graph: FactorGraph, blocks: BlockStore, horizontal_sigma: float,
                 vertical_sigma: float) -> None:
        self.graph = graph
        self.blocks = blocks
        self.horizontal_sigma = horizontal_sigma
        self.vertical_sigma = vertical_sigma
        self.priors: dict[int, int] = {}  # plane id -> factor id of its horizontal/vertical prior
        self.links: list[tuple[int, int, int]] = []  # (keep, drop, factor id) equality ties
        # (host, plane, factor id, sigma, perpendicular?) orientation ties between planes
        self.parallels: list[tuple[int, int, int, float, bool]] = []

    def add_plane(self, plane_id: int, normal_world: ArrayLike, offset: float, horizontal: bool,
                  vertical: bool, anchor: ArrayLike | None) -> None:
        """See :meth:`Backend.add_plane`."""
        j = _plane_id(plane_id)
        values = self.graph.values
        if values.exists(P(j)):
            raise ValueError(f"plane_id: plane {j} already exists")
        n = np.asarray(normal_world, dtype=float).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise ValueError(f"normal_world: expected a finite non-zero 3-vector, got {n}")
        if not np.isfinite(offset):
            raise ValueError(f"offset: must be finite, got {offset}")
        a = np.zeros(3) if anchor is None else np.asarray(anchor, dtype=float).reshape(3)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"anchor: must be finite, got {a}")
        self.graph.anchors[j] = a
        n_unit = n / np.linalg.norm(n)
        values.insert(P(j), gtsam.OrientedPlane3(gtsam.Unit3(n), float(offset) + float(n_unit @ a)))
        self.blocks.add_plane(j)
        if horizontal:
            self.priors[j] = self.graph.add_factor(horizontal_plane_prior(P(j), n, self.horizontal_sigma))
        elif vertical:
            self.priors[j] = self._vertical_prior(j)

    def _vertical_prior(self, j: int) -> int:
        """Add the prior keeping plane ``j`` a wall (``n_z = 0``); returns its factor id."""
        noise = gtsam.noiseModel.Isotropic.Sigma(1, self.vertical_sigma)
        return self.graph.add_factor(gtsam.CustomFactor(noise, [P(j)], vertical_error))

    def remove_plane(self, plane_id: int) -> None:
        """Remove a plane with all its observation blocks, priors and ties."""
        j = self.blocks.check_plane(plane_id)
        for bid in self.blocks.of_plane(j):
            self.blocks.remove(bid)
        if j in self.priors:
            self.graph.remove_factor(self.priors.pop(j))
        self._rekey_parallels(j, None)
        self.blocks.drop_plane(j)
        self.graph.values.erase(P(j))
        self.graph.restructure()

    def merge(self, keep_id: int, drop_id: int) -> int:
        """See :meth:`Backend.merge_planes`."""
        keep, drop = self.blocks.check_plane(keep_id), self.blocks.check_plane(drop_id)
        if keep == drop:
            raise ValueError(f"merge_planes: cannot merge plane {keep} with itself")
        moved = self.blocks.move_plane(drop, keep)
        if drop in self.priors:
            fid = self.priors.pop(drop)
            del self.graph.records[fid]
            if keep not in self.priors:
                n = self.graph.values.atOrientedPlane3(P(keep)).normal().point3()
                if abs(n[2]) >= 0.5:
                    self.priors[keep] = self.graph.add_factor(
                        horizontal_plane_prior(P(keep), n, self.horizontal_sigma))
                else:
                    self.priors[keep] = self._vertical_prior(keep)
        self.blocks.drop_plane(drop)
        self._rekey_parallels(drop, keep)
        self.graph.values.erase(P(drop))
        self.graph.restructure()
        return moved

    def link(self, keep_id: int, drop_id: int, sigma_angle: float, sigma_offset: float) -> int:
        """See :meth:`Backend.link_planes`."""
        if int(keep_id) == int(drop_id):
            raise ValueError(f"link_planes: cannot link plane {int(keep_id)} with itself")
        keep, drop = self.blocks.check_plane(keep_id), self.blocks.check_plane(drop_id)
        if keep == drop:  # merged into one already (fold_links): nothing left to tie
            return -1
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_angle, sigma_angle, sigma_offset]))
        error = plane_equality(self.graph.anchors[keep], self.graph.anchors[drop])
        fid = self.graph.add_factor(gtsam.CustomFactor(noise, [P(keep), P(drop)], error))
        self.links.append((keep, drop, fid))
        return fid

    def fold_links(self) -> dict[int, int]:
        """See :meth:`Backend.fold_links`."""
        for _, _, fid in self.links:
            self.graph.records.pop(fid, None)
        out = link_roots([(keep, drop) for keep, drop, _ in self.links])
        self.links = []
        for drop, keep in out.items():
            if drop != keep:
                self.merge(keep, drop)
                self.blocks.folded[drop] = keep
        self.graph.restructure()
        return out

    def tie(self, host_id: int, plane_id: int, sigma_angle: float, perpendicular: bool) -> int:
        """See :meth:`Backend.add_parallel` and :meth:`Backend.add_perpendicular`."""
        a, b = self.blocks.check_plane(host_id), self.blocks.check_plane(plane_id)
        if a == b:
            raise ValueError(f"add_{'perpendicular' if perpendicular else 'parallel'}: cannot tie plane {a} to itself")
        same = next((t for t in self.parallels if {t[0], t[1]} == {a, b} and t[4] == perpendicular), None)
        if same is not None:  # the pair is tied so already (its planes were merged into these)
            return same[2]
        fid = self._tie_factor(a, b, sigma_angle, perpendicular)
        self.parallels.append((a, b, fid, float(sigma_angle), perpendicular))
        return fid

    def _tie_factor(self, a: int, b: int, sigma_angle: float, perpendicular: bool) -> int:
        if perpendicular:
            one = gtsam.noiseModel.Isotropic.Sigma(1, sigma_angle)
            return self.graph.add_factor(gtsam.CustomFactor(one, [P(a), P(b)], perpendicular_error))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_angle, sigma_angle, 1e3]))
        error = plane_equality(self.graph.anchors[a], self.graph.anchors[b])
        return self.graph.add_factor(gtsam.CustomFactor(noise, [P(a), P(b)], error))

    def _rekey_parallels(self, drop: int, keep: int | None) -> None:
        """Move the orientation ties of plane ``drop`` onto ``keep`` (None: remove them). A
        structural tie holds once per pair: one that would join two planes tied so already goes."""
        pairs = {(frozenset(t[:2]), t[4]) for t in self.parallels if drop not in t[:2]}
        out = []
        for a, b, fid, sigma, perp in self.parallels:
            if drop not in (a, b):
                out.append((a, b, fid, sigma, perp))
                continue
            if fid in self.graph.records:
                self.graph.remove_factor(fid)
            if keep is None:
                continue
            na, nb = (keep if a == drop else a), (keep if b == drop else b)
            if na != nb and (frozenset((na, nb)), perp) not in pairs:
                pairs.add((frozenset((na, nb)), perp))
                out.append((na, nb, self._tie_factor(na, nb, sigma, perp), sigma, perp))
        self.parallels = out


def link_roots(links: list[tuple[int, int]]) -> dict[int, int]:
    """The merges that fold equality links ``(keep, drop)`` (in order): each dropped plane -> the
    plane that survives it (in the order the merges are made; the pipelined back end's counters
    follow the same order, ``slam.backend_process.FactorIds``)."""
    parent: dict[int, int] = {}

    def root(j: int) -> int:
        while parent.get(j, j) != j:
            j = parent[j]
        return j

    for keep, drop in links:
        rk, rd = root(keep), root(drop)
        if rk != rd:
            parent[rd] = rk
    return {j: root(j) for j in parent}


def _plane_id(plane_id: int) -> int:
    j = int(plane_id)
    if j < 0 or j >= 2**56:
        raise ValueError(f"plane_id: must be an integer in [0, 2^56), got {plane_id}")
    return j


def vertical_error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
    """Wall prior: the z component of the plane's unit normal (world frame) is zero."""
    u = v.atOrientedPlane3(this.keys()[0]).normal()
    if H is not None:
        B = u.basis()
        H[0] = np.array([[B[2, 0], B[2, 1], 0.0]])
    return np.array([u.point3()[2]])


def perpendicular_error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
    """Perpendicularity of two planes: the dot product of their unit normals (world frame)."""
    ka, kb = this.keys()
    ua = v.atOrientedPlane3(ka).normal()
    ub = v.atOrientedPlane3(kb).normal()
    na, nb = ua.point3(), ub.point3()
    if H is not None:
        Ha, Hb = np.zeros((1, 3)), np.zeros((1, 3))
        Ha[0, :2] = nb @ ua.basis()
        Hb[0, :2] = na @ ub.basis()
        H[0], H[1] = Ha, Hb
    return np.array([float(na @ nb)])


def plane_residual(a: gtsam.OrientedPlane3, b: gtsam.OrientedPlane3, anchor_a: FloatArray,
                   anchor_b: FloatArray, H: Any = None) -> FloatArray:
    """Difference of plane b from plane a (normal in a's tangent, offset at a's anchor) and, into
    ``H`` (a list of two), its analytic Jacobians wrt both planes' retract coordinates:
    ``r = (s B_a^T n_b, s (d_b + n_b . (anchor_a - anchor_b)) - d_a)`` with ``s = -1`` for the same
    plane with the opposite orientation (``n_a . n_b < 0``), else 1."""
    ua, ub = a.normal(), b.normal()
    nb = ub.point3()
    s = -1.0 if float(ua.point3() @ nb) < 0.0 else 1.0
    delta = anchor_a - anchor_b
    r = np.empty(3)
    if H is None:
        r[:2] = s * ua.errorVector(ub)
    else:
        Hp, Hq = np.zeros((2, 2), order="F"), np.zeros((2, 2), order="F")
        r[:2] = s * ua.errorVector(ub, Hp, Hq)  # B_a^T n_b and its Jacobians
        Ha, Hb = np.zeros((3, 3)), np.zeros((3, 3))
        Ha[:2, :2], Ha[2, 2] = s * Hp, -1.0
        Hb[:2, :2], Hb[2, :2], Hb[2, 2] = s * Hq, s * (delta @ ub.basis()), s
        H[0], H[1] = Ha, Hb
    r[2] = s * (b.distance() + float(nb @ delta)) - a.distance()
    return r


def plane_equality(anchor_a: FloatArray, anchor_b: FloatArray) -> Any:
    """Error function of the equality of two (anchored) planes, 3 residuals (:func:`plane_residual`)."""

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        keys = this.keys()
        return plane_residual(v.atOrientedPlane3(keys[0]), v.atOrientedPlane3(keys[1]), anchor_a, anchor_b, H)

    return error
