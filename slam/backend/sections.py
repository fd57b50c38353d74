"""The final batch of a long walk solved one time-ordered section at a time, so that its memory
is that of one section and not of the whole walk (issue 27): the same Gauss-Newton steps as the
whole-graph batch (:mod:`slam.backend.batch`), assembled from reduced systems.

A whole-graph batch builds one factor per knot interval, linearises them all and eliminates the
system at once: its memory grows with the walk (about 56 MB per data minute on the office walk,
before the elimination). Here the knots are cut into sections of at most
``BackendConfig.batch_section_knots``. Every factor belongs to one section (an observation block
to that of its knot, another factor to that of its highest knot; the factors on planes alone to
none). A section's **interior** is its knots' variables (poses, velocities, biases) that no other
section's factor touches, and the planes that only its factors touch (an edge or a room seen
once, unless their covariance is asked for); the **separator** is everything else: the planes
seen from two sections or tied, and the knots within two of a cut. (With every plane in the
separator, the hour's separator system held its 1,000 edge planes too: a dense 4,437 x 4,437
matrix.) One damped Gauss-Newton step is then, exactly (up to the order of floating-point sums):

1. per section, in turn: linearise its factors, add the damping rows of its interior, eliminate
   the interior (gtsam's partial elimination) and keep what remains: a dense factor on the
   section's separator (its planes and its cut knots), a few MB, and the interior's conditionals
   (the elimination's Bayes net, about 11 kB per knot on the office walk) packed into flat
   arrays (:mod:`slam.backend.packed_net`): in memory while the budget allows, else on disk;
2. solve the separator: those factors, the planes' own factors (priors, ties) and the separator's
   damping rows, one small sparse system;
3. per section: back-substitute its interior through its kept conditionals (one compiled
   pass; read back from disk if they lie there), given the separator's step.

The step is accepted, halved or retried with more damping as in :func:`slam.backend.solver.solve`
(the error at a point is the sum of the sections' linearisations at zero); the trial point's
step 1 is the next iteration's. ``BackendConfig.batch_cache_bytes`` bounds what is kept between
passes in memory: the sections' factors first, built from the observations once per solve (a
kept one saves building it at every pass), then the sections' eliminations (one in memory saves
writing and reading it); an elimination that does not fit is written to disk (never eliminated
again), factors that do not fit are built again when needed. The memory is therefore
at most that budget, one section's linearisation and elimination, the knots' values and the
separator's system: it stops growing with the walk once the budget is full. A walk no longer
than one section is solved whole, unchanged.

The planes' marginal covariances come from the separator's system without damping: the exact
marginals of the whole graph (every plane is in the separator), its dense information matrix
inverted once.

Frames: poses ``T_world_body``, planes in the world frame about their anchors.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time as _time
import weakref
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P
from numpy.typing import NDArray

from slam.backend.blocks import BlockStore, interval_factors
from slam.backend.config import BackendConfig, OptimizeSummary
from slam.backend.factors import RobustKernel
from slam.backend.graph import FactorGraph, key_dim, plane_indices, top_knot
from slam.backend.marginals import dense_marginals
from slam.backend.packed_net import PackedNet, pack
from slam.backend.packed_net import solve as solve_net
from slam.backend.solver import DAMPING, MAX_DAMPING, damping_rows, predicted_end
from slam.heap import HeapKeeper, trim_heap

FloatArray = NDArray[np.float64]
# a cached interval factor's points (body point, fraction, sigma, plane index, their copies in the
# factor's arrays) and the factor's own objects, estimated
_BYTES_PER_POINT, _BYTES_PER_FACTOR = 48, 2048
_REACH = 2  # a factor spans at most this many knots below its highest (the constant-velocity prior: 3 knots)


def plan_sections(n_knots: int, section_knots: int) -> list[tuple[int, int]]:
    """Knot ranges ``[a, b)``: ``ceil(n / section_knots)`` sections of equal length (the last
    shorter), in time order."""
    if n_knots < 1 or section_knots < 1:
        raise ValueError(f"plan_sections: expected positive sizes, got {n_knots}, {section_knots}")
    size = math.ceil(n_knots / math.ceil(n_knots / section_knots))
    return [(a, min(n_knots, a + size)) for a in range(0, n_knots, size)]


def separator_knots(sections: list[tuple[int, int]]) -> set[int]:
    """The knots that factors of two sections touch: within ``_REACH`` below each cut, and the cut."""
    return {k for a, _ in sections[1:] for k in range(max(0, a - _REACH), a + 1)}


@dataclass
class Reduced:
    """The separator's damped system at one point (the sections' interiors eliminated) and the
    whole graph's error there."""

    graph: gtsam.GaussianFactorGraph
    error: float
    # each section's interior eliminated, packed (in memory within the budget, else on disk);
    # None: not kept
    nets: list[PackedNet] | None = None


class SectionedBatch:
    """The final batch (and the plane covariances) of a walk longer than one section; see the
    module doc."""

    def __init__(self, graph: FactorGraph, blocks: BlockStore, config: BackendConfig) -> None:
        self.graph = graph
        self.blocks = blocks
        self.config = config
        self.sections_solved = 0  # section eliminations so far (for the tests and the statistics)
        self.sections_built = 0  # sections' factors built (the rest came from the cache)
        # the sections' factors kept through one solve (same kernel, same observations), the
        # bytes they are estimated to hold
        self._cache: dict[tuple[int, int, str, float], tuple[gtsam.NonlinearFactorGraph, int]] = {}
        self._cache_bytes = 0
        self._nets_bytes = 0  # the eliminations kept by the latest reduce (their indices, the matrices in memory)
        self._in_memory: list[PackedNet] = []  # those of the latest reduce whose matrices are in memory
        self._caching = False  # only within optimize(): the observations change between solves
        # the most kept at once (eliminations and factors, estimated), the largest separator
        # system (its factors' matrices) and section elimination, for the statistics and the tests
        self.peak_kept_bytes = 0
        self.peak_separator_bytes = 0
        self.largest_net_bytes = 0  # the largest section's elimination (kept or not)
        self.nets_spilled = 0  # eliminations written to disk (over the budget)
        self._folder: Path | None = None
        # the planes one section alone sees (local_planes) for a graph version and plan
        self._local: tuple[tuple[int, tuple[tuple[int, int], ...]], dict[int, int]] | None = None
        self._cleanup: weakref.finalize | None = None

    def needed(self) -> bool:
        """Whether the walk is longer than one section (and than a walk solved whole)."""
        return len(self.graph.times) > max(self.config.batch_section_knots, self.config.batch_whole_knots)

    def plan(self) -> list[tuple[int, int]]:
        return plan_sections(len(self.graph.times), self.config.batch_section_knots)

    def local_planes(self, sections: list[tuple[int, int]],
                     keep_planes: Collection[int] | None = ()) -> dict[int, int]:
        """Plane keys that the factors of one section alone touch (and no factor on planes
        alone), each to that section's index: eliminated with its interior. Not those of
        ``keep_planes`` (plane ids; None: none is local). Kept until the graph changes."""
        if keep_planes is None:
            return {}
        tag = (self.graph.version, tuple(sections))
        if self._local is None or self._local[0] != tag:
            self._local = (tag, _local_planes(self.graph, self.blocks.cols.ids(), self.blocks.cols.knot,
                                              self.blocks.cols.plane, [a for a, _ in sections]))
        local = self._local[1]
        if keep_planes:
            held = {int(P(int(j))) for j in keep_planes}
            return {k: i for k, i in local.items() if k not in held}
        return local

    # ----------------------------------------------------------------- the sections' factors
    def factors(self, a: int, b: int, kernel: RobustKernel) -> gtsam.NonlinearFactorGraph:
        """The factors of the section of knots ``[a, b)``: from the cache of this solve, else
        built from the observations (and cached while ``config.batch_cache_bytes`` allows)."""
        key = (a, b, kernel.name, float(kernel.threshold))
        hit = self._cache.get(key)
        if hit is not None:
            return hit[0]
        graph, n_bytes = self._build(a, b, kernel)
        if self._caching and self._room_for_factors(n_bytes):
            self._cache[key] = (graph, n_bytes)
            self._cache_bytes += n_bytes
            self.peak_kept_bytes = max(self.peak_kept_bytes, self._cache_bytes + self._nets_bytes)
        return graph

    def clear_cache(self) -> None:
        """Let go of the cached factors (the observations or the kernel changed, or the solve ended)."""
        self._cache.clear()
        self._cache_bytes = 0

    def _spill_folder(self) -> Path:
        """The temporary folder of the eliminations on disk (made at the first; removed with
        this object or at the interpreter's exit)."""
        if self._folder is None:
            self._folder = Path(tempfile.mkdtemp(prefix="backpack_slam_sections_"))
            self._cleanup = weakref.finalize(self, shutil.rmtree, self._folder, True)
        return self._folder

    def _room_for_factors(self, n_bytes: int) -> bool:
        """Whether a section's factors of ``n_bytes`` fit the budget beside the factors cached so
        far; the eliminations held in memory by the current pass go to disk (the latest first) to
        make room, as a cached section saves building its factors at every pass while an
        elimination in memory saves only writing and reading it once."""
        budget = self.config.batch_cache_bytes
        if self._cache_bytes + n_bytes > budget:
            return False
        while self._in_memory and self._nets_bytes + self._cache_bytes + n_bytes > budget:
            net = self._in_memory.pop()
            self._nets_bytes -= net.held_bytes
            net.spill(self._spill_folder())
            self._nets_bytes += net.held_bytes
            self.nets_spilled += 1
        return self._nets_bytes + self._cache_bytes + n_bytes <= budget

    def _build(self, a: int, b: int, kernel: RobustKernel) -> tuple[gtsam.NonlinearFactorGraph, int]:
        """The factors of the section ``[a, b)`` built afresh, and the bytes they are estimated to
        hold (their points' rows and each factor's own)."""
        self.sections_built += 1
        fg, blocks, cols = self.graph, self.blocks, self.blocks.cols
        n = len(fg.times)
        two, bknot = cols.two, cols.knot
        graph = gtsam.NonlinearFactorGraph()
        groups: dict[int, list[int]] = {}
        sel = blocks.factors_of_knots(a, min(b, n - 1))  # factors by their highest knot
        for fid, k, is_block in zip(sel.ids.tolist(), sel.top.tolist(), sel.is_block.tolist(), strict=True):
            if is_block:
                if not a <= bknot[fid] < b:
                    continue
                if two[fid]:
                    groups.setdefault(int(bknot[fid]), []).append(fid)
                else:
                    graph.add(blocks.block_factor(cols.block(fid), kernel))
            elif k < b:
                low = min(i for i in _knot_indices(fg.records[fid].keys))
                if low < k - _REACH:
                    raise RuntimeError(f"factor {fid} spans knots {low}..{k}: more than the sections allow")
                graph.add(blocks.factor(fid))
        for factor in interval_factors(blocks, groups, kernel):
            graph.add(factor)
        n_points = sum(int(cols.size[np.array(bids, dtype=np.int64)].sum()) for bids in groups.values())
        return graph, _BYTES_PER_POINT * n_points + _BYTES_PER_FACTOR * graph.size()

    def plane_factors(self) -> gtsam.NonlinearFactorGraph:
        """The factors on no knot (planes' priors and ties)."""
        graph = gtsam.NonlinearFactorGraph()
        for fid in self.graph.knotless:
            rec = self.graph.records.get(fid)
            if rec is not None:
                graph.add(self.blocks.factor(fid))
        return graph

    @contextmanager
    def _serving(self, values: gtsam.Values) -> Iterator[None]:
        """The plane table serves ``values`` to the interval factors meanwhile (set once for
        all the sections: it reads every pose)."""
        table = self.blocks.planes
        table.at(values)
        try:
            yield
        finally:
            table.at(None)

    # ----------------------------------------------------------------- one step
    def reduce(self, values: gtsam.Values, kernel: RobustKernel, damping: float, keep: bool = False,
               keep_planes: Collection[int] | None = ()) -> Reduced:
        """Step 1 and the system of step 2 (module doc) at ``values``; ``damping`` 0: none. With
        ``keep``, each section's elimination is kept for :meth:`back_substitute` at this point.
        ``keep_planes``: plane ids kept in the separator even if one section alone sees them (None:
        every plane)."""
        sections = self.plan()
        sep = separator_knots(sections)
        local = self.local_planes(sections, keep_planes)
        out = gtsam.GaussianFactorGraph()
        summed: gtsam.HessianFactor | None = None  # the sections' reduced systems, added up as they come
        err = 0.0
        sep_keys: set[int] = set()
        nets: list[PackedNet] | None = [] if keep else None
        self._nets_bytes = 0
        self._in_memory = []
        heap = self._heap_keeper()
        with self._serving(values):
            for i, (a, b) in enumerate(sections):
                lin = self.factors(a, b, kernel).linearize(values)
                keys = [int(k) for k in lin.keyVector()]
                err += lin.error(_zeros(keys))  # a linearisation's error at zero is its 0.5 ||b||^2
                interior = _interior(keys, i, sections, sep, local)
                bn, rest = self._eliminate(lin, interior, damping)
                inner = set(interior)
                sep_keys.update(k for k in keys if k not in inner)
                summed = _summed(summed, rest)
                if nets is not None:  # kept first: a kept elimination saves more time per byte than factors
                    net = pack(bn)
                    self.largest_net_bytes = max(self.largest_net_bytes, net.nbytes)
                    if self._cache_bytes + self._nets_bytes + net.held_bytes <= self.config.batch_cache_bytes:
                        self._nets_bytes += net.held_bytes
                        self._in_memory.append(net)
                    else:  # on disk: read back once for the back-substitution, never eliminated again
                        net.spill(self._spill_folder())
                        self.nets_spilled += 1
                        self._nets_bytes += net.held_bytes  # its small index stays
                    nets.append(net)
                    self.peak_kept_bytes = max(self.peak_kept_bytes, self._cache_bytes + self._nets_bytes)
                del lin, rest, bn
                heap.check()
            if summed is not None:
                out.push_back(summed)
            planes = self.plane_factors()
            if planes.size():
                lin = planes.linearize(values)
                err += lin.error(_zeros([int(k) for k in lin.keyVector()]))
                out.push_back(lin)
                sep_keys.update(int(k) for k in lin.keyVector())
        if damping > 0.0:
            out.push_back(damping_rows([(k, key_dim(k)) for k in sorted(sep_keys)], set(), damping, cache=False))
        self.peak_separator_bytes = max(self.peak_separator_bytes, _graph_bytes(out))
        return Reduced(out, err, nets)

    def back_substitute(self, values: gtsam.Values, kernel: RobustKernel, damping: float,
                        sep_delta: gtsam.VectorValues,
                        nets: list[PackedNet] | None = None,
                        keep_planes: Collection[int] | None = ()) -> gtsam.VectorValues:
        """Step 3 (module doc): the whole step, the interiors solved given the separator's; each
        section from its kept elimination in ``nets`` (:attr:`Reduced.nets` of :meth:`reduce` at
        ``values`` and ``damping``), else linearised and eliminated again. ``keep_planes``: as the
        :meth:`reduce` that gave ``sep_delta``."""
        sections = self.plan()
        sep = separator_knots(sections)
        local = self.local_planes(sections, keep_planes)
        delta = gtsam.VectorValues()
        delta.insert(sep_delta)
        heap = self._heap_keeper()
        with self._serving(values):
            for i, (a, b) in enumerate(sections):
                net = nets[i] if nets is not None else None
                if net is None:
                    lin = self.factors(a, b, kernel).linearize(values)
                    interior = _interior([int(k) for k in lin.keyVector()], i, sections, sep, local)
                    bn, _ = self._eliminate(lin, interior, damping)
                    net = pack(bn)
                    del lin, bn
                for k, v in solve_net(net, sep_delta):
                    delta.insert(k, v)
                del net
                heap.check()
        return self._fill(delta, values)

    def _eliminate(self, lin: gtsam.GaussianFactorGraph, interior: list[int], damping: float) -> tuple[gtsam.GaussianBayesNet, gtsam.GaussianFactorGraph]:
        """A section's linearisation with its ``interior``'s damping rows added, the interior
        eliminated (in COLAMD's order): its conditionals and the factor left on the separator."""
        if damping > 0.0:
            lin.push_back(damping_rows([(k, key_dim(k)) for k in interior], set(), damping, cache=False))
        self.sections_solved += 1
        out: tuple[gtsam.GaussianBayesNet, gtsam.GaussianFactorGraph] = lin.eliminatePartialSequential(interior)
        return out

    @staticmethod
    def _fill(delta: gtsam.VectorValues, values: gtsam.Values) -> gtsam.VectorValues:
        for k in values.keys():  # variables no factor touches stay where they are
            if not delta.exists(k):
                delta.insert(k, np.zeros(key_dim(k)))
        return delta

    def _heap_keeper(self) -> HeapKeeper:
        """Trims the C heap during a pass over the sections once its resident memory has risen by
        ``config.batch_heap_slack_bytes``: each section's linearisation and elimination are freed
        into malloc's chunks, which the next section splits at new places, so that without it the
        pass's resident memory climbs with the sections (with the walk) while the memory in use
        does not."""
        return HeapKeeper(slack=self.config.batch_heap_slack_bytes)

    # ----------------------------------------------------------------- solving
    def optimize(self, max_iterations: int | None, graduated: bool, kernel: RobustKernel | None) -> OptimizeSummary:
        """The sectioned batch (:meth:`Backend.batch_optimize`'s arguments and result)."""
        cfg = self.config
        kernel = cfg.kernel if kernel is None else kernel
        robust = graduated and kernel.name != "none"
        scales = [*(list(cfg.robust_schedule) if robust else []), 1.0]
        t0 = _time.perf_counter()
        n_max = max_iterations or cfg.lm_max_iterations
        iterations = 0
        e0 = e1 = float("nan")
        for scale in scales:
            k = kernel if scale == 1.0 else RobustKernel(kernel.name, kernel.threshold * scale)
            self.clear_cache()
            self._caching = True
            try:
                its, first, e1 = self.solve(k, n_max, cfg.batch_relative_tolerance)
            except RuntimeError as err:
                raise ValueError(f"sectioned batch optimisation failed ({' '.join(str(err).split())[:200]}); "
                                 "is every variable constrained by its factors?") from None
            finally:
                self._caching = False
                self.clear_cache()
                trim_heap()  # what the solve let go, back to the system before the next stage
            iterations += its
            e0 = first if e0 != e0 else e0
        self.graph.restructure()
        self.blocks.drop_summaries()  # the held poses have moved
        return OptimizeSummary(e0, e1, iterations, _time.perf_counter() - t0)

    def solve(self, kernel: RobustKernel, max_iterations: int, relative_tolerance: float) -> tuple[int, float, float]:
        """Damped Gauss-Newton from the current estimate, as :func:`slam.backend.solver.solve`
        (without its Levenberg-Marquardt fallback); the estimate is updated. Returns the
        iterations and the errors before and after."""
        values = self.graph.values  # not copied: only read, and replaced by each accepted trial point
        damping = DAMPING
        red: Reduced | None = self.reduce(values, kernel, damping, keep=True)
        assert red is not None
        err0 = err = red.error
        it = 0
        for it in range(1, max_iterations + 1):
            delta = None
            while delta is None:
                try:
                    if red is None:
                        red = self.reduce(values, kernel, damping, keep=True)
                    sep_delta = red.graph.optimize()
                    # the interiors' conditionals hold at the step: the model's error there is the
                    # separator system's
                    model_err = red.graph.error(sep_delta)
                    delta = self.back_substitute(values, kernel, damping, sep_delta, red.nets)
                except RuntimeError:
                    if damping * 100.0 > MAX_DAMPING:
                        raise
                    damping *= 100.0
                red = None
            # a step the linear model says ends the solve is judged by the error alone (a pass over
            # the sections that reduces at it would be thrown away), as in solver.solve
            last = it == max_iterations or predicted_end(err, err - model_err, relative_tolerance)
            step = 1.0
            next_damping = max(DAMPING, damping / 10.0)
            for _ in range(10):
                trial = values.retract(delta if step == 1.0 else delta.scale(step))
                red_trial: Reduced | None = None
                if step == 1.0 and not last:
                    try:
                        red_trial = self.reduce(trial, kernel, next_damping, keep=True)
                        new_err = red_trial.error
                    except RuntimeError:
                        new_err = self.total_error(kernel, trial)
                else:
                    new_err = self.total_error(kernel, trial)
                if new_err <= err:
                    red = red_trial
                    break
                step *= 0.5
            else:
                break  # no step lowers the error: converged
            rel = (err - new_err) / max(err, 1e-300)
            values, err = trial, new_err
            damping = next_damping
            if rel < relative_tolerance:
                break
        self.graph.values.update(values)
        return it, err0, err

    # ----------------------------------------------------------------- errors, covariances
    def total_error(self, kernel: RobustKernel | None = None, values: gtsam.Values | None = None) -> float:
        """The whole graph's error (0.5 sum of whitened squares, robust losses) at ``values``
        (None: the current estimate), one section's factors at a time."""
        kernel = self.config.kernel if kernel is None else kernel
        values = self.graph.values if values is None else values
        total = 0.0
        heap = self._heap_keeper()
        with self._serving(values):
            for a, b in self.plan():  # one section's factors at a time
                total += float(self.factors(a, b, kernel).error(values))
                heap.check()
            total += float(self.plane_factors().error(values))
        return total

    def plane_covariances(self, plane_ids: Collection[int] | None = None) -> dict[int, FloatArray]:
        """Marginal covariance (3, 3) of the planes ``plane_ids`` (None: every plane; retract
        coordinates about its anchor) from the separator's undamped system: the whole graph's
        marginals. The planes asked for stay in the separator, the others that one section alone
        sees are eliminated with it. The separator's information matrix is dense (each section's
        reduced factor spans all its planes), so it is inverted once for all planes
        (:func:`slam.backend.marginals.dense_marginals`: by Cholesky; if it is singular, through
        its eigenvectors, and a plane the null space reaches is left out)."""
        try:
            return self._plane_covariances(plane_ids)
        finally:
            trim_heap()

    def _plane_covariances(self, plane_ids: Collection[int] | None) -> dict[int, FloatArray]:
        values = self.graph.values
        red = self.reduce(values, self.config.kernel, 0.0, keep_planes=plane_ids)
        keys = sorted(int(k) for k in red.graph.keyVector())
        first = np.concatenate(([0], np.cumsum([key_dim(k) for k in keys])))
        wanted = None if plane_ids is None else {int(P(int(j))) for j in plane_ids}
        planes = [(i, k) for i, k in enumerate(keys) if plane_indices((k,)) and (wanted is None or k in wanted)]
        info, _ = red.graph.hessian(gtsam.Ordering(keys))
        del red
        covs = dense_marginals(info, [(int(first[i]), int(first[i + 1])) for i, _ in planes])
        return {int(gtsam.Symbol(k).index()): c for (_, k), c in zip(planes, covs, strict=True) if c is not None}


def _local_planes(graph: FactorGraph, block_ids: NDArray[np.int64], block_knot: NDArray[np.int64],
                  block_plane: NDArray[np.int64], starts: list[int]) -> dict[int, int]:
    """Plane key -> section index of the planes whose factors all lie in one section (a block by
    its knot, another factor by its highest knot, as :meth:`SectionedBatch._build` assigns them)
    and that no factor on planes alone (a prior, a tie) touches."""
    first = np.asarray(starts, dtype=np.int64)
    section = np.searchsorted(first, block_knot[block_ids], side="right") - 1
    pairs = np.unique(np.stack((block_plane[block_ids], section)), axis=1)
    planes, n_sections = np.unique(pairs[0], return_counts=True)
    seen: dict[int, int] = dict(zip(pairs[0].tolist(), pairs[1].tolist(), strict=True))
    shared = set(planes[n_sections > 1].tolist())
    for rec in graph.records.values():
        ps = plane_indices(rec.keys)
        if not ps:
            continue
        top = top_knot(rec.keys)
        where = -1 if top is None else int(np.searchsorted(first, top, side="right") - 1)
        for j in ps:
            if where < 0 or seen.setdefault(j, where) != where:
                shared.add(j)
    return {int(P(j)): i for j, i in seen.items() if j not in shared}


def _zeros(keys: list[int]) -> gtsam.VectorValues:
    """Zero steps of ``keys`` (one section's variables, not the walk's)."""
    zero = gtsam.VectorValues()
    for k in keys:
        zero.insert(k, np.zeros(key_dim(k)))
    return zero


def _knot_indices(keys: tuple[int, ...]) -> list[int]:
    """Knot indices of the knot keys (X, V, B) among ``keys``."""
    return [t for t in (top_knot((k,)) for k in keys) if t is not None]


def _interior(keys: list[int], i: int, sections: list[tuple[int, int]], sep: set[int],
              local: dict[int, int]) -> list[int]:
    """The keys among ``keys`` that section ``i`` eliminates: its interior knots' variables and
    the planes it alone sees (``local``, :meth:`SectionedBatch.local_planes`)."""
    a, b = sections[i]
    return [k for k in keys if _is_interior(k, a, b, sep) or local.get(k) == i]


def _is_interior(key: int, a: int, b: int, sep: set[int]) -> bool:
    """Whether ``key`` is a knot variable of ``[a, b)`` that no other section touches."""
    k = top_knot((key,))
    return k is not None and a <= k < b and k not in sep


def _graph_bytes(graph: gtsam.GaussianFactorGraph) -> int:
    """Bytes of a linear graph's factors' matrices: a Jacobian factor's augmented matrix, a Hessian
    factor's augmented information matrix (held square)."""
    total = 0
    for f in (graph.at(i) for i in range(graph.size())):
        if isinstance(f, gtsam.JacobianFactor):
            total += int(f.rows()) * int(f.cols())
        elif isinstance(f, gtsam.HessianFactor):
            total += int(f.rows()) ** 2
    return 8 * total


def _summed(acc: gtsam.HessianFactor | None, rest: gtsam.GaussianFactorGraph) -> gtsam.HessianFactor:
    """``acc`` and a section's reduced system ``rest`` as one Hessian factor over their keys.

    Each section's elimination leaves a dense factor over every separator plane it sees (~2,000
    dimensions on the office walk): kept one per section, they grew with the walk (~7 kB per
    knot, 0.55 GB at the hour, docs/memory.md "Session 34"); added up they stay the size of the
    walk's separator, whose planes recur lap after lap."""
    g = gtsam.GaussianFactorGraph()
    if acc is not None:
        g.push_back(acc)
    g.push_back(rest)
    return gtsam.HessianFactor(g)
