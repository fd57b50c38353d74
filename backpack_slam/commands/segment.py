"""``backpack-slam segment``: line segmentation of scans from a CARMEN log, a ROS1/ROS2 bag,
or an ``.npz``/CSV scanline, with a summary, a plot and a JSON record."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

DESCRIPTION = """Segment the scans of INPUT (a CARMEN log, plain or gzip; a ROS1 .bag or ROS2 bag
directory, LaserScan topics; an .npz or CSV scanline) into lines with one of the registered
segmenters, print a summary, and optionally write a plot and a JSON record. By default each
scanner's noise model (range noise, quantisation, angular step) is estimated from its first
scans, printed, and the segmenter's parameters not given with --param are derived from it."""

#: scans per scanner the noise model is estimated from (the first ones of the input)
NOISE_SCANS = 200


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "segment", help="segment 2D scans into lines", description=DESCRIPTION
    )
    p.add_argument("input", nargs="?", metavar="INPUT", help="CARMEN log, ROS1/ROS2 bag, .npz or .csv scanline")
    p.add_argument("--method", default="ror", help="segmenter name (default: ror; see --list-methods)")
    p.add_argument(
        "--param", action="append", default=[], type=parse_param, metavar="KEY=VALUE",
        help="segmenter parameter, repeatable (e.g. --param sigma=0.01 --param direction=forward)",
    )
    p.add_argument("--topic", action="append", default=None, metavar="T", help="bag topic (LaserScan), repeatable; default: all LaserScan topics")
    p.add_argument("--scan", default=0, type=parse_scan, metavar="INDEX|all", help="which scan (0-based, negative from the end) or 'all' (default: 0)")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="write a plot (points coloured by segment)")
    p.add_argument("--json", type=Path, metavar="OUT.json", help="write labels and lines as JSON")
    p.add_argument(
        "--noise", choices=("auto", "none"), default="auto",
        help="auto (default): estimate each scanner's noise model from its first scans and derive the "
             "parameters not given with --param from it; none: the segmenter's fixed defaults",
    )
    p.add_argument("--list-methods", action="store_true", help="list the segmenters with their default parameters and exit")
    return p


def parse_param(text: str) -> tuple[str, str]:
    """``key=value`` -> (key, value); the segmenter converts the value to the parameter's type."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got '{text}'")
    return key.strip(), value.strip()


def parse_scan(text: str) -> int | None:
    """A scan index, or None for 'all'."""
    if text.strip().lower() == "all":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer scan index or 'all', got '{text}'") from None


def list_methods(out: IO[str]) -> None:
    import segmentation

    for name in segmentation.available():
        defaults = segmentation.segmenter_class(name).defaults()
        out.write(f"{name}: {' '.join(f'{k}={v}' for k, v in defaults.items())}\n")


@dataclass
class Summary:
    """Counts over the segmented scans."""

    n_scans: int = 0
    n_segments: list[int] = field(default_factory=list)
    n_valid: int = 0
    n_in_segments: int = 0
    seconds: list[float] = field(default_factory=list)
    skipped: list[tuple[int, str]] = field(default_factory=list)

    def add(self, n_segments: int, n_valid: int, n_in: int, seconds: float) -> None:
        self.n_scans += 1
        self.n_segments.append(n_segments)
        self.n_valid += n_valid
        self.n_in_segments += n_in
        self.seconds.append(seconds)

    def as_dict(self) -> dict[str, Any]:
        seg = self.n_segments
        return {
            "scans": self.n_scans,
            "skipped": [{"scan": i, "reason": r} for i, r in self.skipped],
            "segments_total": int(sum(seg)),
            "segments_per_scan_mean": (sum(seg) / len(seg)) if seg else 0.0,
            "valid_points": self.n_valid,
            "points_in_segments": self.n_in_segments,
            "time_per_scan_median_s": _median(self.seconds),
            "time_per_scan_mean_s": (sum(self.seconds) / len(self.seconds)) if self.seconds else 0.0,
        }


def _median(x: list[float]) -> float:
    if not x:
        return 0.0
    s = sorted(x)
    m = len(s) // 2
    return s[m] if len(s) % 2 else 0.5 * (s[m - 1] + s[m])


def select_scans(scans: Iterable[Any], index: int | None, source: str) -> Iterator[tuple[int, Any]]:
    """(index, scan) for every scan (index None), or the one at ``index`` (negative: from the end)."""
    if index is None:
        yield from enumerate(scans)
        return
    if index >= 0:
        n = 0
        for i, s in enumerate(scans):
            if i == index:
                yield i, s
                return
            n += 1
        raise ValueError(f"{source}: scan {index} requested but the input has {n} scan(s)")
    tail: deque[Any] = deque(maxlen=-index)
    n = 0
    for s in scans:
        tail.append(s)
        n += 1
    if n < -index:
        raise ValueError(f"{source}: scan {index} requested but the input has {n} scan(s)")
    yield n + index, tail[0]


def scan_info(index: int, line: Any) -> dict[str, Any]:
    n = line.n_beams
    return {
        "scan": index,
        "scanner_id": line.scanner_id,
        "stamp": line.stamp,
        "n_beams": n,
        "n_valid": line.n_valid,
        "angle_min": float(line.angles[0]) if n else None,
        "angle_max": float(line.angles[-1]) if n else None,
        "range_min": line.range_min,
        "range_max": line.range_max,
    }


def json_safe(obj: Any) -> Any:
    """Plain JSON values: non-finite floats become null, numpy values plain Python."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist"):
        return json_safe(obj.tolist())
    return obj


def run(args: argparse.Namespace) -> int:
    if args.list_methods:
        list_methods(sys.stdout)
        return 0
    if args.input is None:
        raise ValueError("segment: INPUT is required (or use --list-methods)")
    return segment_input(
        Path(args.input),
        method=args.method,
        params=dict(args.param),
        topics=args.topic,
        scan=args.scan,
        plot=args.plot,
        json_out=args.json,
        noise=args.noise,
        out=sys.stdout,
    )


def segment_input(
    path: Path,
    *,
    method: str = "ror",
    params: dict[str, Any] | None = None,
    topics: list[str] | None = None,
    scan: int | None = 0,
    plot: Path | None = None,
    json_out: Path | None = None,
    noise: str = "auto",
    out: IO[str] = sys.stdout,
) -> int:
    """Segment the selected scan(s) of ``path``; print a summary, write the plot and the JSON.

    ``noise="auto"``: each scanner's noise model is estimated from its first
    ``NOISE_SCANS`` scans and printed; parameters not in ``params`` come from it.
    ``noise="none"``: the segmenter's fixed defaults.
    """
    import segmentation
    from common.atomic import atomic_path
    from slam.io import detect_format, open_scans

    if noise not in ("auto", "none"):
        raise ValueError(f"segment: noise={noise!r} is invalid: must be auto or none")
    if plot is not None:
        from backpack_slam.commands._segplot import check_image_path

        check_image_path(plot, "--plot")
    if json_out is not None and json_out.is_dir():
        raise ValueError(f"--json {json_out}: is a folder")
    try:
        fixed = segmentation.get(method, **(params or {}))  # unknown names/values fail before reading
    except ValueError as e:
        raise ValueError(f"--method/--param: {e}") from None
    fmt = detect_format(path)
    source = f"{path}" + (f" topic {','.join(topics)}" if topics else "")
    models = _noise_models(path, topics, source, out) if noise == "auto" else {}
    segmenters = {sid: segmentation.get(method, m, **(params or {})) for sid, m in models.items()}
    scans = open_scans(path, topics=topics)
    header = {"input": {"path": str(path), "format": fmt, "topics": topics, "scan": "all" if scan is None else scan}}
    first_segmenter = next(iter(segmenters.values()), fixed)
    summary = Summary()
    first_panel = None
    with _json_stream(json_out, atomic_path) as js:
        if js is not None:
            extra = {"noise_models": {sid: dataclasses.asdict(m) for sid, m in models.items()},
                     "params_by_scanner": {sid: segmenter_params(g) for sid, g in segmenters.items()}}
            js.write(json.dumps(json_safe({**header, "method": method, "params": segmenter_params(first_segmenter),
                                           **extra}))[:-1])
            js.write(', "scans": [')
        n_written = 0
        warmed = False
        for index, line in _progress(select_scans(scans, scan, source), scan is None):
            segmenter = segmenters.get(line.scanner_id, fixed)
            try:
                if not warmed:  # the first call loads numba's compiled code: keep it out of the timing
                    segmenter.segment(line)
                    warmed = True
                t0 = time.perf_counter()
                seg = segmenter.segment(line)
            except ValueError as e:
                if scan is not None:
                    raise ValueError(f"{source} scan {index}: cannot segment: {e}") from None
                summary.skipped.append((index, str(e)))
                continue
            dt = time.perf_counter() - t0
            n_in = int((seg.labels[line.valid_index] >= 0).sum())
            summary.add(seg.n_segments, line.n_valid, n_in, dt)
            if first_panel is None:
                first_panel = (index, line, seg)
            if js is not None:
                record = {**scan_info(index, line), "time_s": dt, "segmentation": seg.to_dict()}
                js.write((", " if n_written else "") + json.dumps(json_safe(record)))
                n_written += 1
        if first_panel is None:  # inside the block: the JSON's temporary file is dropped
            reasons = "; ".join(f"scan {i}: {r}" for i, r in summary.skipped[:3])
            raise ValueError(f"{source}: no scan could be segmented ({reasons or 'the input has no scans'})")
        if js is not None:
            js.write('], "summary": ' + json.dumps(json_safe(summary.as_dict())) + "}\n")
    _print_summary(out, path, fmt, method, summary, first_panel, single=scan is not None)
    if plot is not None:
        _plot(plot, path, method, summary, first_panel, single=scan is not None)
        out.write(f"plot: {plot}\n")
    if json_out is not None:
        out.write(f"json: {json_out}\n")
    return 0


def segmenter_params(segmenter: Any) -> dict[str, Any]:
    return dataclasses.asdict(segmenter.params)


def _noise_models(path: Path, topics: list[str] | None, source: str, out: IO[str]) -> dict[str, Any]:
    """Each scanner's noise model from its first ``NOISE_SCANS`` scans, printed; scanners whose
    scans give no estimate are named and keep the fixed defaults."""
    from segmentation.noise import estimate
    from slam.io import open_scans

    groups: dict[str, list[Any]] = {}
    for line in open_scans(path, topics=topics):
        group = groups.setdefault(line.scanner_id, [])
        if len(group) < NOISE_SCANS:
            group.append(line)
        elif all(len(g) >= NOISE_SCANS for g in groups.values()):
            break
    models = {}
    for sid, lines in groups.items():
        try:
            models[sid] = estimate(lines)
        except ValueError as e:
            out.write(f"noise model [{sid}]: not estimated ({e}); fixed defaults\n")
            continue
        out.write(f"{models[sid]}\n")
    return models


class _json_stream:
    """Context manager: a text file at a temporary name renamed onto ``path`` on success (or None)."""

    def __init__(self, path: Path | None, atomic_path: Any) -> None:
        self.path = path
        self._atomic = atomic_path(path) if path is not None else None
        self._file: IO[str] | None = None

    def __enter__(self) -> IO[str] | None:
        if self._atomic is None or self.path is None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._atomic.__enter__()
        self._file = open(tmp, "w", encoding="utf-8")
        return self._file

    def __exit__(self, *exc: Any) -> None:
        if self._file is not None:
            self._file.close()
        if self._atomic is not None:
            self._atomic.__exit__(*exc)


def _progress(items: Iterator[tuple[int, Any]], enabled: bool) -> Iterator[tuple[int, Any]]:
    if not enabled:
        return items
    from tqdm import tqdm

    return iter(tqdm(items, desc="segmenting", unit="scan", disable=None, leave=False))


def _print_summary(out: IO[str], path: Path, fmt: str, method: str, s: Summary, first: tuple[int, Any, Any], single: bool) -> None:
    index, line, seg = first
    d = s.as_dict()
    out.write(f"input: {path} ({fmt}); method: {method}\n")
    if single:
        frac = d["points_in_segments"] / max(d["valid_points"], 1)
        out.write(
            f"scan {index} [{line.scanner_id}, t={line.stamp:.6f} s]: {line.n_beams} beams, {line.n_valid} valid; "
            f"{seg.n_segments} segments, {d['points_in_segments']} points in segments ({100 * frac:.1f}%); "
            f"{1e3 * d['time_per_scan_median_s']:.3f} ms\n"
        )
        return
    segs = s.n_segments
    frac = d["points_in_segments"] / max(d["valid_points"], 1)
    out.write(
        f"{s.n_scans} scans segmented, {len(s.skipped)} skipped; segments per scan: mean {d['segments_per_scan_mean']:.1f} "
        f"(min {min(segs)}, max {max(segs)}), {d['segments_total']} in all; {100 * frac:.1f}% of valid points in segments; "
        f"time per scan: median {1e3 * d['time_per_scan_median_s']:.3f} ms, mean {1e3 * d['time_per_scan_mean_s']:.3f} ms\n"
    )
    for i, reason in s.skipped[:5]:
        out.write(f"  skipped scan {i}: {reason}\n")


def _plot(path: Path, src: Path, method: str, s: Summary, first: tuple[int, Any, Any], single: bool) -> None:
    from backpack_slam.commands._segplot import draw_segmentation, new_figure, save_figure

    index, line, seg = first
    title = f"{src.name} scan {index} ({line.scanner_id})"
    if single:
        fig, (ax,) = new_figure(1, size=6.0)
        draw_segmentation(ax, line, seg, title)
    else:
        fig, (ax, ax2) = new_figure(2, size=5.5)
        draw_segmentation(ax, line, seg, title)
        ax2.plot(s.n_segments, lw=0.6, color="tab:blue")
        ax2.set_xlabel("segmented scan")
        ax2.set_ylabel("segments per scan", color="tab:blue")
        ax3 = ax2.twinx()
        ax3.plot([1e3 * t for t in s.seconds], lw=0.4, color="tab:orange", alpha=0.7)
        ax3.set_ylabel("time per scan (ms)", color="tab:orange")
        ax3.set_yscale("log")
        ax2.set_title(f"{method}: {s.n_scans} scans", fontsize=9)
    save_figure(fig, path)
