"""What holds the memory of one SLAM run: the ``profile`` child of ``bench_memory.py``.

The run is ``run_slam`` on a bag in this process with ``tracemalloc`` on (one frame per
allocation); ``SlamRunner`` is hooked so that at evenly spaced data times of the walk, after
the estimation and after the export a :class:`Point` is taken: the process's RSS and peak,
the traced Python heap (its current size and its peak since the previous point) by allocating
file and line, gc-tracked objects by type, gtsam counts and the deep size of each holder of
:data:`HOLDERS` (objects reachable from the runner's attributes; an object reachable from two
holders is counted in the first). gtsam's C++ objects are invisible to both: their number is
given instead (factor records, built factors, variables).
"""

from __future__ import annotations

import gc
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

# (name, path of attributes from the SlamRunner); shared objects are counted in the first holder
HOLDERS: tuple[tuple[str, str], ...] = (
    ("backend: observation blocks (BlockStore.blocks)", "backend.blocks.blocks"),
    ("backend: block summaries and group factors", "backend.blocks"),
    ("backend: factor records (FactorGraph)", "backend.graph"),
    ("backend: incremental solver", "backend.incremental"),
    ("backend: rest", "backend"),
    ("frontend: scan queues (segment rows, done scans)", "queues"),
    ("frontend: plane map", "pmap"),
    ("frontend: segment pool", "pool"),
    ("frontend: map builder", "maps"),
    ("frontend: edges", "edges"),
    ("frontend: knot mirror", "knots"),
    ("frontend: tracker", "tracker"),
    ("motion model (IMU)", "motion"),
)
# objects of other packages (tqdm, numba dispatchers, logging, ...) are not followed
_OURS = ("builtins", "numpy", "slam", "segmentation", "common", "collections", "gtsam")
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


def holder_sizes(runner: object) -> dict[str, dict[str, int]]:
    """Deep size (bytes) and object count of every holder of :data:`HOLDERS`."""
    seen: set[int] = set()
    out: dict[str, dict[str, int]] = {}
    for name, path in HOLDERS:
        try:
            root = _attr(runner, path)
        except AttributeError:
            continue
        b, n = deep_size(root, seen)
        out[name] = {"bytes": b, "objects": n}
    return out


def gtsam_counts(runner: Any) -> dict[str, int]:
    """gtsam objects ``tracemalloc`` cannot see: factor records, built factors, interval groups,
    variables of the estimate, observation blocks and their points."""
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
    }


def rss_bytes() -> int:
    """This process's resident set size now."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def types_by_count(top: int = _TOP) -> dict[str, int]:
    """The gc-tracked objects by type name, the ``top`` most numerous."""
    c = Counter(type(o).__name__ for o in gc.get_objects())
    return dict(c.most_common(top))


@dataclass
class Point:
    """The memory at one point of the run (bytes)."""

    label: str
    data_time: float  # s of data processed
    wall: float  # s since the start
    rss: int
    peak_rss: int
    traced: int
    traced_peak: int  # since the previous point
    by_line: dict[str, int]
    by_type: dict[str, int]
    gtsam: dict[str, int]
    holders: dict[str, dict[str, int]] = field(default_factory=dict)


class Profiler:
    """Takes :class:`Point` s; ``every`` s of data apart while the runner processes knots."""

    def __init__(self, every: float) -> None:
        self.every = every
        self.points: list[Point] = []
        self.runner: Any = None
        self._next = every
        self._t0 = time.perf_counter()

    def take(self, label: str, data_time: float, with_holders: bool = True) -> None:
        snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
        cur, peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        by_line = {f"{s.traceback[0].filename.split('/site-packages/')[-1].replace(sys.prefix, '')}:"
                   f"{s.traceback[0].lineno}": s.size for s in snap.statistics("lineno")[:_TOP]}
        runner = self.runner
        self.points.append(Point(
            label, data_time, time.perf_counter() - self._t0, rss_bytes(), peak_bytes(), cur, peak, by_line,
            types_by_count(), gtsam_counts(runner) if runner is not None else {},
            holder_sizes(runner) if runner is not None and with_holders else {}))
        p = self.points[-1]
        print(f"  [{label}] data {data_time:.0f} s: rss {p.rss / 1e6:.0f} MB, traced {cur / 1e6:.0f} MB "
              f"(peak {peak / 1e6:.0f} MB), {p.gtsam}", file=sys.stderr, flush=True)
        for name, h in p.holders.items():  # also here: a run cut short keeps what it measured
            print(f"    {name}: {h['bytes'] / 1e6:.1f} MB, {h['objects']} objects", file=sys.stderr, flush=True)

    def hook(self, runner_cls: Any) -> Callable[[], None]:
        """Wrap ``runner_cls._process_knot`` and ``result``; returns the undo."""
        process, result = runner_cls._process_knot, runner_cls.result
        prof = self

        def _process_knot(runner: Any) -> None:
            prof.runner = runner
            process(runner)
            t0 = runner.knots.time(0)
            t = runner.knots.time(runner.knots.n - 1) - t0
            if t >= prof._next:
                prof._next += prof.every
                prof.take("walk", t)

        def _result(runner: Any, *args: Any, **kwargs: Any) -> Any:
            t = runner.knots.time(runner.knots.n - 1) - runner.knots.time(0)
            prof.take("before result", t)
            res = result(runner, *args, **kwargs)
            prof.take("estimation (after result)", t)
            return res

        runner_cls._process_knot, runner_cls.result = _process_knot, _result

        def undo() -> None:
            runner_cls._process_knot, runner_cls.result = process, result

        return undo


def profile_run(bag: str, out: str, points: int) -> dict[str, Any]:
    """``run_slam`` on ``bag`` with the profiler; its points as plain data."""
    from common.rig import resolve_rig
    from slam.config import SlamConfig
    from slam.io.source import BagSource
    from slam.pipeline import SlamRunner
    from slam.run import run_slam

    with BagSource(bag) as src:
        t0, t1 = src.time_range()
    prof = Profiler(max((t1 - t0) / points, 1.0))
    tracemalloc.start(1)
    prof.take("start", 0.0)
    undo = prof.hook(SlamRunner)
    try:
        # the back end in this process, where its holders can be measured
        cfg = SlamConfig.model_validate({"backend": {"pipelined": False}})
        summary = run_slam(bag, resolve_rig("itc_backpack"), cfg, out, progress=False)
    finally:
        undo()
    prof.take("export (after run_slam)", t1 - t0)
    tracemalloc.stop()
    return {"bag": bag, "data_duration": t1 - t0, "wall": summary["timings"]["wall"],
            "counts": summary["counts"], "points": [asdict(p) for p in prof.points]}


def growth_per_minute(rows: Iterable[tuple[float, float]]) -> float:
    """Least-squares slope (per data minute) of (data seconds, value) pairs."""
    xy = np.array(list(rows), dtype=float).reshape(-1, 2)
    if xy.shape[0] < 2 or np.ptp(xy[:, 0]) == 0:
        return float("nan")
    return float(np.polyfit(xy[:, 0] / 60.0, xy[:, 1], 1)[0])


def report(run: dict[str, Any]) -> str:
    """Markdown: per holder its MB at each point of the walk, at the end and its MB per data
    minute; then the process figures and the largest allocation sites."""
    pts = run["points"]
    walk = [p for p in pts if p["label"] == "walk"]
    last = next(p for p in pts if p["label"] == "before result")
    cols = [*walk, last]
    head = "| holder | " + " | ".join(f"{p['data_time']:.0f} s" for p in cols) + " | MB / data min |"
    lines = [f"{run['bag']} ({run['data_duration']:.0f} s of data, wall {run['wall']:.0f} s with tracemalloc)", "",
             head, "|---|" + "---:|" * (len(cols) + 1)]
    names = list(last["holders"])
    for name in names:
        vals = [p["holders"].get(name, {}).get("bytes", 0) / 1e6 for p in cols]
        g = growth_per_minute(zip([p["data_time"] for p in cols], vals, strict=True))
        lines.append(f"| {name} | " + " | ".join(f"{v:.1f}" for v in vals) + f" | {g:.2f} |")

    def row(name: str, get: Callable[[dict[str, Any]], float], scale: float = 1e-6, digits: int = 1) -> None:
        vals = [get(p) * scale for p in cols]
        g = growth_per_minute(zip([p["data_time"] for p in cols], vals, strict=True))
        lines.append(f"| {name} | " + " | ".join(f"{v:.{digits}f}" for v in vals) + f" | {g:.{digits}f} |")

    row("**sum of holders**", lambda p: sum(h["bytes"] for h in p["holders"].values()))
    row("traced Python heap (tracemalloc)", lambda p: p["traced"])
    row("process RSS", lambda p: p["rss"])
    row("RSS not traced (gtsam C++, interpreter, libraries)", lambda p: p["rss"] - p["traced"])
    for key in ("factor_records", "factors_built", "group_factors", "values", "blocks", "block_points"):
        row(f"count: {key}", lambda p, k=key: p["gtsam"].get(k, 0), 1.0, 0)
    lines += ["", "| stage | RSS (MB) | peak RSS so far (MB) | traced (MB) | traced peak in the stage (MB) |",
              "|---|---:|---:|---:|---:|"]
    for p in pts:
        if p["label"] != "walk":
            lines.append(f"| {p['label']} | {p['rss'] / 1e6:.0f} | {p['peak_rss'] / 1e6:.0f} | {p['traced'] / 1e6:.0f} "
                         f"| {p['traced_peak'] / 1e6:.0f} |")
    peak_walk = max((p["traced_peak"] for p in walk), default=0)
    lines.append(f"| walk (largest traced peak between two points) | - | - | - | {peak_walk / 1e6:.0f} |")
    lines += ["", f"Largest allocation sites at {last['data_time']:.0f} s (before the final batch), MB:", ""]
    lines += [f"- {k}: {v / 1e6:.1f}" for k, v in list(last["by_line"].items())[:15]]
    lines += ["", "Most numerous gc-tracked objects there: "
              + ", ".join(f"{k} {v}" for k, v in list(last["by_type"].items())[:12])]
    return "\n".join(lines)
