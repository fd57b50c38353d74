"""The back end's factor graph as data: variables (knot times, current estimates, plane anchors)
and factor records, with the bookkeeping every solver reads.

Variables (gtsam keys): ``X(i)`` body pose ``T_world_body`` at knot i, ``P(j)`` plane j
(``OrientedPlane3`` about its anchor, world frame), ``V(i)``/``B(i)`` world velocity and IMU bias
per knot (only with an IMU). A factor record holds its factor, its keys and its index in iSAM2.
Observation blocks have no record: their ids come from the same counter (:meth:`FactorGraph.new_id`)
and their keys, knots and iSAM2 indices live in the block columns (:mod:`slam.backend.blocks`),
so that an hour's million blocks are not a million Python objects.

Two counters tell the solvers what changed: ``version`` on every change of the factors or of
the estimate (a covariance computed at another version is stale), ``epoch`` when the graph
changed in a way an incremental iSAM2 cannot follow (merged or removed variables, estimates
moved by another solver): iSAM2 is rebuilt from the current estimate at its next update.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
_INDEX_BITS = 56  # a gtsam Symbol key: its character above these bits, its index below
_INDEX_MASK = (1 << _INDEX_BITS) - 1
_KNOT_CHARS = frozenset(map(ord, "xvb"))
_PLANE_CHAR = ord("p")


@dataclass(slots=True)
class Record:
    """One factor of the graph other than an observation block: the factor (None: released, see
    :meth:`FactorGraph.release`), its keys, its index in iSAM2 (None: not in iSAM2) and whether
    :attr:`FactorGraph.rebuild` can build it again from its keys."""

    factor: gtsam.NonlinearFactor | None
    keys: tuple[int, ...]
    isam_index: int | None
    rebuildable: bool = False


class FactorGraph:
    """Variables and the records of the factors other than observation blocks; factors (blocks
    included) added or removed since the last incremental update are pending (``pending`` ids,
    ``pending_removals`` iSAM2 indices)."""

    def __init__(self) -> None:
        self.times: list[float] = []  # knot times [s], increasing
        self.values = gtsam.Values()  # the current estimate
        self.anchors: dict[int, FloatArray] = {}  # plane id -> anchor point (world) of its variable
        self.records: dict[int, Record] = {}
        self._next_id = 0
        self.pending: list[int] = []
        self.pending_removals: list[int] = []
        # records by the highest knot they touch, and records on no knot (plane priors and ties);
        # both keep the ids of removed records (skipped by their readers)
        self.by_knot: dict[int, list[int]] = {}
        self.knotless: list[int] = []
        self.version = 0
        self.epoch = 0
        # builds a rebuildable record's factor again from its keys, the same (the knots' motion
        # factors: see slam.backend.knots)
        self.rebuild: Callable[[tuple[int, ...]], gtsam.NonlinearFactor] | None = None
        # released factors built again and kept (None: not kept): the final batch's solves all
        # need them, and building them again costs each solve the IMU's preintegration
        self.rebuilt: dict[int, gtsam.NonlinearFactor] | None = None

    def add_factor(self, factor: gtsam.NonlinearFactor, rebuildable: bool = False) -> int:
        """Add ``factor`` (not an observation block's; ``rebuildable``: :attr:`rebuild` makes it
        again from its keys); returns its id."""
        fid = self.new_id()
        keys = tuple(int(k) for k in factor.keys())
        self.records[fid] = Record(factor, keys, None, rebuildable)
        top = top_knot(keys)
        if top is None:
            self.knotless.append(fid)
        else:
            self.by_knot.setdefault(top, []).append(fid)
        return fid

    def factor(self, fid: int) -> gtsam.NonlinearFactor:
        """The factor of record ``fid``; a released one built again (kept in :attr:`rebuilt`
        while that is on, see :meth:`keep_rebuilt`)."""
        rec = self.records[fid]
        if rec.factor is not None:
            return rec.factor
        assert self.rebuild is not None
        if self.rebuilt is None:
            return self.rebuild(rec.keys)
        f = self.rebuilt.get(fid)
        if f is None:
            f = self.rebuilt[fid] = self.rebuild(rec.keys)
        return f

    def keep_rebuilt(self, keep: bool) -> None:
        """Keep the released factors built again from now on (``keep``), or let go of those kept
        and stop keeping them."""
        self.rebuilt = {} if keep else None

    def release(self, knot: int) -> None:
        """Let go of the rebuildable factors whose highest knot is ``knot`` (the window has left it)."""
        for fid in self.by_knot.get(knot, ()):
            rec = self.records.get(fid)
            if rec is not None and rec.rebuildable:
                rec.factor = None

    def new_id(self) -> int:
        """A new factor id, pending (an observation block's has no record)."""
        fid = self._next_id
        self._next_id += 1
        self.pending.append(fid)
        self.version += 1
        return fid

    def remove_factor(self, fid: int) -> None:
        """Remove the record of factor ``fid`` (from iSAM2 too, at its next update)."""
        self.removed(self.records.pop(fid).isam_index)

    def removed(self, isam_index: int | None) -> None:
        """A factor at ``isam_index`` in iSAM2 (None: not in it) was removed."""
        if isam_index is not None:
            self.pending_removals.append(isam_index)
        self.version += 1

    def restructure(self) -> None:
        """Mark a change iSAM2 cannot follow incrementally (it is rebuilt at its next update)."""
        self.epoch += 1
        self.version += 1

    def check_knot(self, knot: int, need_next: bool = False) -> int:
        """``knot`` as an index of an existing knot (with ``need_next``: of an interval's start)."""
        i = int(knot)
        last = len(self.times) - (2 if need_next else 1)
        if i < 0 or i > last:
            what = "interval start" if need_next else "knot"
            raise ValueError(f"knot: {what} {i} outside [0, {last}]")
        return i

    def used_values(self, graph: gtsam.NonlinearFactorGraph) -> gtsam.Values:
        """The current estimate of the variables ``graph`` touches."""
        keys = graph.keyVector()
        if len(keys) == self.values.size():  # every variable (its keys are the estimate's): one copy
            return gtsam.Values(self.values)
        return self.values.extract([int(k) for k in keys])


def top_knot(keys: Sequence[int]) -> int | None:
    """The highest knot index among ``keys`` (X, V and B symbols), or None."""
    top = None
    for k in keys:
        if (k >> _INDEX_BITS) in _KNOT_CHARS:  # gtsam.Symbol's character and index, by bits
            i = k & _INDEX_MASK
            top = i if top is None else max(top, i)
    return top


def plane_indices(keys: Sequence[int]) -> list[int]:
    """The plane indices of the plane keys (P symbols) among ``keys``."""
    return [k & _INDEX_MASK for k in keys if (k >> _INDEX_BITS) == _PLANE_CHAR]


_DIMS = {ord("x"): 6, ord("v"): 3, ord("b"): 6, ord("p"): 3}  # pose, velocity, IMU bias, plane


def key_dim(key: int) -> int:
    """The tangent dimension of variable ``key`` (a pose, velocity, IMU bias or plane), from its
    symbol alone: no walk-sized ``Values.dims()`` map."""
    d = _DIMS.get((key >> _INDEX_BITS) & 0xFF)
    if d is None:
        raise ValueError(f"unknown variable {gtsam.Symbol(key).string()}")
    return d


def copy_value(dst: gtsam.Values, src: gtsam.Values, key: int, update: bool = False) -> None:
    """Copy variable ``key`` from ``src`` into ``dst``: insert it if absent; overwrite it only
    with ``update``."""
    exists = dst.exists(key)
    if exists and not update:
        return
    put = dst.update if exists else dst.insert
    c = chr((key >> _INDEX_BITS) & 0xFF).lower()  # gtsam.Symbol's character
    if c == "x":
        put(key, src.atPose3(key))
    elif c == "p":
        put(key, src.atOrientedPlane3(key))
    elif c == "v":
        put(key, src.atVector(key))
    elif c == "b":
        put(key, src.atConstantBias(key))
    else:
        raise ValueError(f"unknown variable {gtsam.Symbol(key).string()}")


def as_pose(T: ArrayLike, name: str) -> gtsam.Pose3:
    """A (4, 4) rigid transform as a ``gtsam.Pose3``; anything else is a ValueError naming ``name``."""
    M = np.asarray(T, dtype=float)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ValueError(f"{name}: expected a finite (4, 4) matrix, got shape {M.shape}")
    R = M[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name}: rotation block is not a rotation matrix")
    return gtsam.Pose3(gtsam.Rot3(R), M[:3, 3])


def name_keys(message: str) -> str:
    """First line of a gtsam error plus the variable it names (x12, p3), on one line."""
    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    first = lines[0] if lines else "gtsam error"
    m = re.search(r"Symbol: (\w+)", message)
    return f"{first} {m.group(1)}" if m else first
