"""What holds the memory of one SLAM run: the ``profile`` child of ``bench_memory.py``.

The run is ``run_slam`` on a bag in this process, optionally with ``tracemalloc`` on (one frame
per allocation; 1.5-2x slower). ``SlamRunner``, the back end and the export are hooked so that a
:class:`Point` is taken at evenly spaced data times of the walk, before the final solve, after
each final batch, before the planes' covariances, after them and after each export step (tables,
cloud pass, map.rrd): the process's RSS, the PSS of it and its children (the reader and the
export's processes), glibc's malloc figures, gc-tracked objects by type, gtsam counts and the deep
size of each holder of :data:`HOLDERS` (objects reachable from the runner, its result and the
export's cloud view; an object reachable from two holders is counted in the first); with
tracemalloc also the traced heap by allocating file and line. gtsam's C++ objects are invisible
to deep sizes and tracemalloc: their number is given instead (factor records, built factors,
variables), and the RSS the holders do not explain is reported as such. Without tracemalloc a
:class:`Sampler` process samples the RSS and PSS every 0.25 s, so each stage's peak (the final
batch's linearisation and elimination included, which hold the GIL) is measured from outside.
"""

from __future__ import annotations

import gc
import os
import resource
import sys
import time
import tracemalloc
import types
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

# (name, path of attributes from the profiled objects: ``runner`` the SlamRunner, ``result`` its
# SlamResult, ``cloud`` the export's CloudOutputs); shared objects are counted in the first holder
HOLDERS: tuple[tuple[str, str], ...] = (
    ("backend: block columns (BlockColumns arrays)", "runner.backend.blocks.cols"),
    ("backend: factor records (FactorGraph.records)", "runner.backend.graph.records"),
    ("backend: factor ids by knot (FactorGraph.by_knot)", "runner.backend.graph.by_knot"),
    ("backend: block ids by plane (BlockStore.plane_blocks)", "runner.backend.blocks.plane_blocks"),
    ("backend: interval-group factors (BlockStore._groups)", "runner.backend.blocks._groups"),
    ("backend: graph rest (times, anchors, pending)", "runner.backend.graph"),
    ("backend: block store rest (summaries, open blocks)", "runner.backend.blocks"),
    ("backend: incremental solver", "runner.backend.incremental"),
    ("backend: knots (motion, datum, IMU)", "runner.backend.knots"),
    ("backend: plane ties", "runner.backend.ties"),
    ("backend: rest", "runner.backend"),
    ("frontend: compacted segment rows (for segments.npz)", "runner.queues._rows"),
    ("frontend: done scans (within the pool's reach)", "runner.queues.done"),
    ("frontend: recent and pending scans", "runner.queues"),
    # before the components that refer to them
    ("frontend: knot mirror (trajectory arrays)", "runner.knots"),
    ("frontend: plane map", "runner.pmap"),
    ("frontend: segment pool", "runner.pool"),
    ("motion model (IMU)", "runner.motion"),
    ("frontend: associator", "runner.associator"),
    ("frontend: transient filter", "runner.transients"),
    ("frontend: edges", "runner.edges"),
    ("frontend: map builder (ties)", "runner.maps"),
    ("frontend: tracker", "runner.tracker"),
    ("scan preparer", "runner.preparer"),
    ("runner rest (stats, timer)", "runner"),
    ("result (SlamResult: segment rows, poses)", "result"),
    ("export: cloud view (for map.rrd)", "cloud"),
    ("input: bag source (the reader's message index)", "source"),
)
# after the holders: what the gc-tracked closure cells hold that no holder reached (the captured
# arrays of gtsam CustomFactors, whose Python function only gtsam's C++ object refers to)
CLOSURES = "closure cells not reached above (CustomFactors' captured arrays)"
# objects of other packages (tqdm, numba dispatchers, logging, ...) are not followed
_OURS = ("builtins", "numpy", "slam", "segmentation", "common", "collections", "gtsam", "rosbags")
_SKIP = (type, types.ModuleType, types.FunctionType, types.BuiltinFunctionType, types.MethodType, types.CodeType)
_TOP = 25


def deep_size(root: object, seen: set[int]) -> tuple[int, int]:
    """(bytes, objects) reachable from ``root`` not in ``seen`` (which gets them): containers and
    instances through ``gc.get_referents``, numpy arrays by their buffer (a view by its base);
    types, modules, functions and objects of other packages than ours, numpy and gtsam are not
    followed."""
    total = count = 0
    stack = [root]
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, _SKIP) or not type(obj).__module__.startswith(_OURS):
            continue
        seen.add(id(obj))
        count += 1
        if isinstance(obj, np.ndarray):
            total += sys.getsizeof(obj) if obj.base is None else 112
            if obj.base is not None:
                stack.append(obj.base)
            elif obj.dtype.hasobject:
                stack.extend(obj.ravel().tolist())
            continue
        try:
            total += sys.getsizeof(obj)
        except TypeError:
            pass
        stack.extend(gc.get_referents(obj))
    return total, count


def _attr(obj: object, path: str) -> object:
    for name in path.split(".") if path else ():
        obj = getattr(obj, name)
    return obj


def holder_sizes(roots: object, closures: bool = False) -> dict[str, dict[str, int]]:
    """Deep size (bytes) and object count of every holder of :data:`HOLDERS` (paths from
    ``roots``' attributes; a holder whose path ends in None or a missing attribute is left out);
    with ``closures`` also :data:`CLOSURES`."""
    seen: set[int] = set()
    out: dict[str, dict[str, int]] = {}
    for name, path in HOLDERS:
        try:
            root = _attr(roots, path)
        except AttributeError:
            continue
        if root is None:
            continue
        b, n = deep_size(root, seen)
        out[name] = {"bytes": b, "objects": n}
    if closures:
        b = n = 0
        for cell in [o for o in gc.get_objects() if isinstance(o, types.CellType)]:
            try:
                db, dn = deep_size(cell.cell_contents, seen)
            except ValueError:  # an empty cell
                continue
            b, n = b + db, n + dn
        out[CLOSURES] = {"bytes": b, "objects": n}
    return out


def gtsam_counts(runner: Any) -> dict[str, int]:
    """gtsam objects ``tracemalloc`` and deep sizes cannot see: factor records, built factors,
    interval groups kept, variables of the estimate; observation blocks and their points."""
    be = runner.backend
    recs = be.graph.records
    store = be.blocks
    blocks = getattr(store, "blocks", {})
    n_points = getattr(store, "n_points", None)
    if n_points is None:
        n_points = sum(b.points.shape[0] for b in blocks.values())
    block_factors = getattr(store, "_factors", {})  # since the blocks lost their records: built block factors
    return {
        "factor_records": len(recs),
        "factors_built": sum(1 for r in recs.values() if r.factor is not None) + len(block_factors),
        "group_factors": len(getattr(store, "_groups", {})),
        "values": int(be.graph.values.size()),
        "blocks": len(blocks),
        "block_points": int(n_points),
        "knots": len(be.graph.times),
        "planes": len(getattr(store, "by_plane", None) or getattr(store, "plane_blocks", {})),
        "marginals_kept": int(getattr(be, "_marginals", None) is not None),  # the whole graph's, C++
        **section_counts(be),
    }


def section_counts(backend: Any) -> dict[str, int]:
    """A sectioned final batch's figures so far (``slam.backend.sections``; none before it existed
    or for a walk solved whole): its sections, what it kept at most between passes (eliminations
    and cached factors, estimated bytes), its largest separator system (bytes of its factors'
    matrices) and section elimination (kept or not), the sections built and eliminated, the
    eliminations written to disk (over the budget)."""
    sec = getattr(backend, "sections", None)
    if sec is None or not hasattr(sec, "peak_kept_bytes") or not sec.needed():
        return {}
    return {"sections": len(sec.plan()), "section_kept_peak_bytes": int(sec.peak_kept_bytes),
            "separator_peak_bytes": int(sec.peak_separator_bytes),
            "largest_elimination_bytes": int(getattr(sec, "largest_net_bytes", 0)),
            "sections_built": int(sec.sections_built),
            "sections_solved": int(sec.sections_solved),
            "eliminations_on_disk": int(getattr(sec, "nets_spilled", 0))}


def rss_bytes(pid: int | str = "self") -> int:
    """A process's resident set size now (this one's by default)."""
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def pss_bytes(pid: int | str = "self") -> int:
    """A process's proportional set size now (shared pages split among their users; 0 if it is gone)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            return sum(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("Pss:"))
    except OSError:
        return 0


def pss_of_tree(pid: int, skip: Iterable[int] = ()) -> tuple[int, int, int]:
    """(PSS of ``pid``, PSS of it and all its descendants but ``skip``, number of processes)."""
    import psutil

    own = pss_bytes(pid)
    total, n = own, 1
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        kids = []
    for c in kids:
        if c.pid not in skip:
            total += pss_bytes(c.pid)
            n += 1
    return own, total, n


def peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


_MALLINFO2 = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
              "keepcost")


def malloc_info() -> dict[str, int]:
    """glibc's ``mallinfo2`` over all arenas (bytes): ``in_use`` (allocated chunks), ``free`` (free
    chunks malloc keeps from the heap: fragmentation or not yet returned), ``mmapped`` (large
    blocks, e.g. numpy arrays, mapped one by one); empty where there is no glibc. Python's small
    objects (pymalloc arenas) and gtsam's allocations through malloc are in these; memory mapped
    by other means (pymalloc arenas, libraries) is not."""
    import ctypes

    class _Info(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in _MALLINFO2]

    try:
        fn = ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return {}
    fn.restype = _Info
    m = fn()
    return {"in_use": m.uordblks, "free": m.fordblks, "mmapped": m.hblkhd, "heap": m.arena}


def types_by_count(top: int = _TOP) -> dict[str, int]:
    """The gc-tracked objects by type name, the ``top`` most numerous."""
    c = Counter(type(o).__name__ for o in gc.get_objects())
    return dict(c.most_common(top))


def window_peaks(series: NDArray[np.float64], t0: float, t1: float) -> dict[str, float]:
    """The largest of each sampled column within ``t0 <= t < t1`` (``series`` rows: monotonic
    time s, RSS of the estimator, its PSS, PSS of all the run's processes, processes; bytes);
    NaN where no sample falls in the window."""
    rows = series[(series[:, 0] >= t0) & (series[:, 0] < t1)] if series.size else series.reshape(0, 5)
    if rows.shape[0] == 0:
        return {"rss": float("nan"), "pss_all": float("nan"), "processes": float("nan")}
    return {"rss": float(rows[:, 1].max()), "pss_all": float(rows[:, 3].max()), "processes": float(rows[:, 4].max())}


def read_series(path: str) -> NDArray[np.float64]:
    """The sampler's rows so far (see :func:`window_peaks`); a torn last line is left out."""
    rows = []
    with open(path) as f:
        for ln in f:
            parts = ln.split()
            if len(parts) == 5 and ln.endswith("\n"):
                rows.append([float(x) for x in parts])
    return np.array(rows, dtype=float).reshape(-1, 5)


def sample_loop(pid: int, path: str, period: float) -> None:
    """Until process ``pid`` ends, every ``period`` s append to ``path`` a row: monotonic time,
    ``pid``'s RSS and PSS, the PSS of it and its descendants (this sampler left out), their
    number. Run in its own process, so it samples while the estimator holds the GIL (gtsam's
    elimination, the linearisation)."""
    me = os.getpid()
    with open(path, "w") as f:
        while True:
            t = time.monotonic()
            try:
                rss = rss_bytes(pid)
            except OSError:
                return
            own, total, n = pss_of_tree(pid, skip=(me,))
            f.write(f"{t:.3f}\t{rss}\t{own}\t{total}\t{n}\n")
            f.flush()
            time.sleep(period)


class Sampler:
    """:func:`sample_loop` over this process in a child process."""

    def __init__(self, path: str, period: float = 0.25) -> None:
        import subprocess

        self.path = path
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        open(path, "w").close()
        self._proc = subprocess.Popen([sys.executable, __file__, "sample", str(os.getpid()), path, str(period)])
        self.pid = self._proc.pid

    def series(self) -> NDArray[np.float64]:
        return read_series(self.path)

    def stop(self) -> None:
        self._proc.terminate()
        self._proc.wait()


@dataclass
class Point:
    """The memory at one point of the run (bytes); ``stage_*`` the largest sampled since the
    end of the previous point's measurement (so the peak of the stage it closes)."""

    label: str
    data_time: float  # s of data processed
    wall: float  # s since the start
    rss: int
    peak_rss: int  # ru_maxrss so far
    pss: int  # this process
    pss_all: int  # this process and its children (the reader, the export's)
    processes: int
    stage_rss_peak: float
    stage_pss_peak: float
    malloc: dict[str, int]
    traced: int
    traced_peak: int  # since the previous point
    by_line: dict[str, int]
    by_type: dict[str, int]
    gtsam: dict[str, int]
    holders: dict[str, dict[str, int]] = field(default_factory=dict)
    seconds: float = 0.0  # the measurement's own time


class Profiler:
    """Takes :class:`Point` s; ``every`` s of data apart while the runner processes knots, and
    around the final batch, the covariances and the export's steps. With ``trace`` the Python
    heap is traced (``tracemalloc``: 1.5-2x slower); with a ``sampler`` the stage peaks are
    sampled from outside."""

    def __init__(self, every: float, trace: bool = True, sampler: Sampler | None = None) -> None:
        self.every = every
        self.trace = trace
        self.sampler = sampler
        self.points: list[Point] = []
        self.runner: Any = None
        self.result: Any = None
        self.cloud: Any = None
        self.source: Any = None
        self._next = every
        self._t0 = time.perf_counter()
        self._mark = time.monotonic()
        self._in_result = False
        self._batches = 0

    def take(self, label: str, data_time: float, with_holders: bool = True) -> None:
        t_start = time.monotonic()
        rss, peak = rss_bytes(), peak_bytes()
        skip = (self.sampler.pid,) if self.sampler is not None else ()
        pss, pss_all, n_proc = pss_of_tree(os.getpid(), skip)
        stage = {"rss": float("nan"), "pss_all": float("nan")}
        if self.sampler is not None:
            stage = window_peaks(self.sampler.series(), self._mark, t_start)
        # a stage shorter than the sampling period: its end is the one figure there is
        stage = {k: float(np.nanmax([v, rss if k == "rss" else pss_all])) for k, v in stage.items()
                 if k in ("rss", "pss_all")}
        by_line: dict[str, int] = {}
        cur = tpeak = 0
        if self.trace:
            snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
            cur, tpeak = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            by_line = {f"{s.traceback[0].filename.split('/site-packages/')[-1].replace(sys.prefix, '')}:"
                       f"{s.traceback[0].lineno}": s.size for s in snap.statistics("lineno")[:_TOP]}
        runner = self.runner
        roots = types.SimpleNamespace(runner=runner, result=self.result, cloud=self.cloud, source=self.source)
        self.points.append(Point(
            label, data_time, time.perf_counter() - self._t0, rss, peak, pss, pss_all, n_proc,
            stage["rss"], stage["pss_all"], malloc_info(), cur, tpeak, by_line, types_by_count(),
            gtsam_counts(runner) if runner is not None else {},
            holder_sizes(roots, closures=True) if with_holders else {}))
        p = self.points[-1]
        self._mark = time.monotonic()
        p.seconds = self._mark - t_start
        held = sum(h["bytes"] for h in p.holders.values())
        print(f"  [{label}] data {data_time:.0f} s, wall {p.wall:.0f} s: rss {rss / 1e6:.0f} MB, pss all "
              f"{pss_all / 1e6:.0f} MB ({n_proc} processes), stage peak rss {stage['rss'] / 1e6:.0f} / pss "
              f"{stage['pss_all'] / 1e6:.0f} MB, holders {held / 1e6:.0f} MB, malloc "
              f"{ {k: round(v / 1e6) for k, v in p.malloc.items()} } MB, traced {cur / 1e6:.0f} MB, {p.gtsam}, "
              f"took {p.seconds:.1f} s", file=sys.stderr, flush=True)
        for name, h in p.holders.items():  # also here: a run cut short keeps what it measured
            print(f"    {name}: {h['bytes'] / 1e6:.1f} MB, {h['objects']} objects", file=sys.stderr, flush=True)

    def _data_time(self) -> float:
        r = self.runner
        return float(r.knots.time(r.knots.n - 1) - r.knots.time(0)) if r is not None and r.knots.n else 0.0

    def hook(self) -> Callable[[], None]:
        """Wrap the runner's knots and result, the back end's batch and covariances and the
        export's steps (``slam.run``'s names); returns the undo."""
        import slam.run
        from slam.backend.facade import Backend
        from slam.pipeline import SlamRunner

        prof = self
        saved: list[tuple[Any, str, Any]] = []

        def wrap(owner: Any, name: str, make: Callable[[Any], Callable[..., Any]]) -> None:
            old = getattr(owner, name)
            saved.append((owner, name, old))
            setattr(owner, name, make(old))

        def knot(process: Any) -> Callable[..., Any]:
            def _process_knot(runner: Any) -> None:
                prof.runner = runner
                process(runner)
                t = prof._data_time()
                if t >= prof._next:
                    prof._next += prof.every
                    prof.take("walk", t)
            return _process_knot

        def result(res_fn: Any) -> Callable[..., Any]:
            def _result(runner: Any, *args: Any, **kwargs: Any) -> Any:
                prof.take("before result", prof._data_time())
                prof._in_result = True
                try:
                    res = res_fn(runner, *args, **kwargs)
                finally:
                    prof._in_result = False
                prof.result = res
                prof.take("after result (covariances)", prof._data_time())
                return res
            return _result

        def batch(fn: Any) -> Callable[..., Any]:
            def _batch(backend: Any, *args: Any, **kwargs: Any) -> Any:
                out = fn(backend, *args, **kwargs)
                if prof._in_result:
                    prof._batches += 1
                    prof.take(f"after final batch {prof._batches}", prof._data_time())
                return out
            return _batch

        def cov(fn: Any) -> Callable[..., Any]:
            def _cov(backend: Any, *args: Any, **kwargs: Any) -> Any:
                if prof._in_result and not any(p.label == "before covariances" for p in prof.points):
                    prof.take("before covariances", prof._data_time())
                return fn(backend, *args, **kwargs)
            return _cov

        def after(label: str, keep: bool = False) -> Callable[[Any], Callable[..., Any]]:
            def make(fn: Any) -> Callable[..., Any]:
                def _step(*args: Any, **kwargs: Any) -> Any:
                    out = fn(*args, **kwargs)
                    if keep:
                        prof.cloud = out
                    prof.take(label, prof._data_time())
                    return out
                return _step
            return make

        def enter(fn: Any) -> Callable[..., Any]:
            def _enter(source: Any) -> Any:
                out = fn(source)
                if prof.source is None:  # run_slam's own (the first opened after the hook)
                    prof.source = source
                return out
            return _enter

        wrap(slam.run.BagSource, "__enter__", enter)
        wrap(SlamRunner, "_process_knot", knot)
        wrap(SlamRunner, "result", result)
        wrap(Backend, "batch_optimize", batch)
        wrap(Backend, "plane_covariance", cov)
        wrap(slam.run, "write_tables", after("export: after tables (trajectory, segments.npz)"))
        wrap(slam.run, "write_cloud_outputs", after("export: after cloud pass", keep=True))
        wrap(slam.run, "write_planes", after("export: after planes.json (the outlines from the final map)"))
        wrap(slam.run, "write_map_rrd", after("export: after map.rrd"))

        def undo() -> None:
            for owner, name, old in reversed(saved):
                setattr(owner, name, old)

        return undo


def profile_run(bag: str, out: str, points: int, trace: bool = True) -> dict[str, Any]:
    """``run_slam`` on ``bag`` with the profiler (``trace``: with ``tracemalloc``; without it the
    stage peaks are sampled by a child process); its points as plain data."""
    from common.rig import resolve_rig
    from slam.config import SlamConfig
    from slam.io.source import BagSource
    from slam.run import run_slam

    with BagSource(bag) as src:
        t0, t1 = src.time_range()
    sampler = None if trace else Sampler(f"{out.rstrip('/')}.memory_samples.tsv")
    prof = Profiler(max((t1 - t0) / points, 1.0), trace, sampler)
    if trace:
        tracemalloc.start(1)
    prof.take("start", 0.0)
    undo = prof.hook()
    try:
        # the back end in this process, where its holders can be measured
        cfg = SlamConfig.model_validate({"backend": {"pipelined": False}})
        summary = run_slam(bag, resolve_rig("itc_backpack"), cfg, out, progress=False)
    finally:
        undo()
    prof.runner = prof.result = prof.cloud = prof.source = None
    prof.take("export (after run_slam)", t1 - t0)
    gc.collect()  # what only reference cycles kept after run_slam returned
    prof.take("after run_slam and gc.collect()", t1 - t0)
    if trace:
        tracemalloc.stop()
    series = sampler.series() if sampler is not None else np.zeros((0, 5))
    if sampler is not None:
        sampler.stop()
    return {"bag": bag, "data_duration": t1 - t0, "wall": summary["timings"]["wall"], "trace": trace,
            "timings": summary["timings"], "counts": summary["counts"], "points": [asdict(p) for p in prof.points],
            "series": series.tolist()}


def growth_per_minute(rows: Iterable[tuple[float, float]]) -> float:
    """Least-squares slope (per data minute) of (data seconds, value) pairs."""
    xy = np.array(list(rows), dtype=float).reshape(-1, 2)
    if xy.shape[0] < 2 or np.ptp(xy[:, 0]) == 0:
        return float("nan")
    return float(np.polyfit(xy[:, 0] / 60.0, xy[:, 1], 1)[0])


def line_at(rows: Iterable[tuple[float, float]], minutes: float) -> float:
    """The least-squares line through (data seconds, value) pairs, evaluated at ``minutes`` of data."""
    xy = np.array(list(rows), dtype=float).reshape(-1, 2)
    if xy.shape[0] < 2 or np.ptp(xy[:, 0]) == 0:
        return float("nan")
    slope, icpt = np.polyfit(xy[:, 0] / 60.0, xy[:, 1], 1)
    return float(slope * minutes + icpt)


def stage_at(stage_peak: float, before: float, walk_at: float, data_minutes: float, minutes: float) -> float:
    """A stage's peak extrapolated to ``minutes`` of data: what it adds to the memory ``before`` it
    (its peak minus that) taken as proportional to the walk's length (the final batch, the
    covariances and the export all work on the whole walk), on top of the walk's own memory
    there (``walk_at``: the walk's line at ``minutes``)."""
    return walk_at + (stage_peak - before) * minutes / data_minutes


def report(run: dict[str, Any], horizon: float = 60.0) -> str:
    """Markdown: per holder its MB at each point of the walk, its MB per data minute and the
    line's value at ``horizon`` minutes; the process figures the holders do not explain; the
    stages' points and peaks (measured, and extrapolated to ``horizon``); the holders around the
    final stages; the most numerous objects (and with tracemalloc the largest allocation sites)."""
    pts = run["points"]
    walk = [p for p in pts if p["label"] == "walk"]
    last = next(p for p in pts if p["label"] == "before result")
    cols = [*walk, last]
    times = [p["data_time"] for p in cols]
    minutes = run["data_duration"] / 60.0
    how = "with tracemalloc" if run.get("trace", True) else "no tracemalloc"
    head = "| holder | " + " | ".join(f"{t / 60:.1f} min" for t in times) + \
        f" | MB / data min | line at {horizon:.0f} min (MB) |"
    lines = [f"{run['bag']} ({run['data_duration']:.0f} s of data, wall {run['wall']:.0f} s, {how})", "",
             head, "|---|" + "---:|" * (len(cols) + 2)]

    def row(name: str, get: Callable[[dict[str, Any]], float], scale: float = 1e-6, digits: int = 1,
            walk_only: bool = False) -> None:
        vals = [get(p) * scale for p in cols]
        pairs = list(zip(times, vals, strict=True))[:len(walk) if walk_only and len(walk) >= 2 else None]
        lines.append(f"| {name} | " + " | ".join(f"{v:.{digits}f}" for v in vals)
                     + f" | {growth_per_minute(pairs):.{digits}f} | {line_at(pairs, horizon):.{digits}f} |")

    def holder(name: str) -> Callable[[dict[str, Any]], float]:
        return lambda p: float(p["holders"].get(name, {}).get("bytes", 0))

    def count(key: str) -> Callable[[dict[str, Any]], float]:
        return lambda p: float(p["gtsam"].get(key, 0))

    def held(p: dict[str, Any]) -> float:
        return float(sum(h["bytes"] for h in p["holders"].values()))

    for name in dict.fromkeys(n for p in cols for n in p["holders"]):
        row(name, holder(name))
    row("**sum of holders**", held)
    row("process RSS (estimator)", lambda p: p["rss"])
    # the reader process has ended before the final solve: the line through the walk's points only
    row("PSS, all the run's processes (estimator + reader; line: walk only)", lambda p: p["pss_all"],
        walk_only=True)
    row("**RSS not in the holders** (gtsam C++, malloc's free chunks, libraries)", lambda p: p["rss"] - held(p))
    row("malloc: in use", lambda p: p["malloc"].get("in_use", 0))
    row("malloc: free chunks kept", lambda p: p["malloc"].get("free", 0))
    row("malloc: mmapped blocks", lambda p: p["malloc"].get("mmapped", 0))
    if run.get("trace", True):
        row("traced Python heap (tracemalloc)", lambda p: p["traced"])
    for key in ("knots", "factor_records", "factors_built", "group_factors", "values", "blocks", "block_points",
                "planes"):
        row(f"count: {key}", count(key), 1.0, 0)

    walk_rss = line_at([(p["data_time"], p["rss"]) for p in cols], horizon)
    walk_pss = line_at([(p["data_time"], p["pss_all"]) for p in (walk if len(walk) >= 2 else cols)], horizon)
    lines += ["", f"| stage (point at its end) | RSS (MB) | PSS all (MB) | peak RSS in the stage (MB) | peak PSS all "
              f"in the stage (MB) | holders (MB) | group factors kept | peak RSS at {horizon:.0f} min, extrapolated "
              f"(MB) | peak PSS at {horizon:.0f} min, extrapolated (MB) | measuring took (s) |",
              "|---|" + "---:|" * 9]
    for p in pts:
        if p["label"] == "walk" or p["label"] == "start":
            continue
        ext_rss = stage_at(p["stage_rss_peak"], last["rss"], walk_rss, minutes, horizon)
        ext_pss = stage_at(p["stage_pss_peak"], last["pss_all"], walk_pss, minutes, horizon)
        lines.append(f"| {p['label']} | {p['rss'] / 1e6:.0f} | {p['pss_all'] / 1e6:.0f} | "
                     f"{p['stage_rss_peak'] / 1e6:.0f} | {p['stage_pss_peak'] / 1e6:.0f} | {held(p) / 1e6:.0f} | "
                     f"{p['gtsam'].get('group_factors', '-')} | {ext_rss / 1e6:.0f} | {ext_pss / 1e6:.0f} | "
                     f"{p['seconds']:.0f} |")
    walk_peak = max((p["stage_rss_peak"] for p in walk), default=float("nan"))
    walk_pss_peak = max((p["stage_pss_peak"] for p in walk), default=float("nan"))
    lines.append(f"| walk (largest peak between two points) | - | - | {walk_peak / 1e6:.0f} | {walk_pss_peak / 1e6:.0f} "
                 f"| - | - | - | - | - |")

    final = [p for p in pts if p["label"] not in ("walk", "start")]
    lines += ["", "Holders at the final stages (MB):", "",
              "| holder | " + " | ".join(p["label"] for p in final) + " |", "|---|" + "---:|" * len(final)]
    for name in list(dict.fromkeys(n for p in final for n in p["holders"])):
        lines.append(f"| {name} | " + " | ".join(f"{p['holders'].get(name, {}).get('bytes', 0) / 1e6:.1f}"
                                                  for p in final) + " |")
    if run.get("trace", True) and last["by_line"]:
        lines += ["", f"Largest allocation sites at {last['data_time']:.0f} s (before the final batch), MB:", ""]
        lines += [f"- {k}: {v / 1e6:.1f}" for k, v in list(last["by_line"].items())[:15]]
    for p in (last, *[q for q in final if q["label"].startswith("after result")]):
        lines += ["", f"Most numerous gc-tracked objects at '{p['label']}': "
                  + ", ".join(f"{k} {v}" for k, v in list(p["by_type"].items())[:12])]
    return "\n".join(lines)


if __name__ == "__main__":  # the sampler's process: sample PID PATH PERIOD
    if len(sys.argv) == 5 and sys.argv[1] == "sample":
        sample_loop(int(sys.argv[2]), sys.argv[3], float(sys.argv[4]))
