"""Single scanlines as ``.npz`` or CSV files, read and written.

``.npz`` keys: ``ranges`` + ``angles`` (1-D, one scanline; or ``ranges`` (k, n) with
``angles`` (n,) or (k, n) for k scanlines) with optional ``times`` (same shape as
``ranges``), or ``points`` ((n, 2) or (k, n, 2), scanner frame) with optional ``times``;
optional scalars ``scanner_id``, ``range_min``, ``range_max``.

CSV: a header row naming the columns, then one row per beam: ``range,angle`` or
``x,y`` (scanner frame, m and rad), optionally ``time``. Rows of invalid returns may
hold ``nan`` / ``inf``; they stay beams and are masked.

Writers go to a temporary name in the target directory and rename when complete
(``slam.export.atomic_path``); the directory must exist.
"""

from __future__ import annotations

import csv
import io
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from common.atomic import atomic_path
from segmentation import Scanline, validity_mask
from slam.io.errors import InputError, input_error

FloatArray = NDArray[np.float64]


def read_npz(path: str | Path) -> Iterator[Scanline]:
    """The scanline(s) of an ``.npz`` file (see the module docstring); errors name the file and key."""
    p = _existing(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise input_error(p, f"not a readable .npz file ({type(e).__name__}: {e})") from None
    try:
        return iter(_npz_scanlines(p, data))
    except InputError:
        raise
    except ValueError as e:  # values that make no scanline (a NaN angle of a valid beam)
        raise input_error(p, str(e)) from None


def _npz_scanlines(p: Path, data: dict[str, np.ndarray]) -> list[Scanline]:
    sid = str(data["scanner_id"]) if "scanner_id" in data else p.stem
    rmin = _scalar(p, data, "range_min", 0.0)
    rmax = _scalar(p, data, "range_max", float("inf"))
    times = _numeric(p, data, "times") if "times" in data else None
    if "points" in data:
        pts = _numeric(p, data, "points")
        if pts.ndim == 2:
            pts = pts[None]
        if pts.ndim != 3 or pts.shape[2] != 2:
            raise input_error(p, f"key 'points' has shape {data['points'].shape}, expected (n, 2) or (k, n, 2)")
        tt = _per_scan_times(p, times, pts.shape[:2])
        return [_from_points(pts[k], tt[k] if tt is not None else None, sid, rmin, rmax) for k in range(pts.shape[0])]
    if "ranges" not in data or "angles" not in data:
        raise input_error(p, f"needs keys 'ranges' and 'angles', or 'points' (has: {', '.join(sorted(data)) or 'none'})")
    r = _numeric(p, data, "ranges")
    a = _numeric(p, data, "angles")
    if r.ndim == 1:
        r = r[None]
    if r.ndim != 2:
        raise input_error(p, f"key 'ranges' has shape {data['ranges'].shape}, expected (n,) or (k, n)")
    if a.ndim == 1 and a.shape[0] == r.shape[1]:
        a = np.broadcast_to(a, r.shape)
    if a.shape != r.shape:
        raise input_error(p, f"key 'angles' has shape {data['angles'].shape}, does not match 'ranges' {data['ranges'].shape}")
    tt = _per_scan_times(p, times, r.shape)
    out = []
    for k in range(r.shape[0]):
        t = tt[k] if tt is not None else np.zeros(r.shape[1])
        out.append(Scanline(a[k].copy(), r[k].copy(), t.copy(), validity_mask(r[k], rmin, rmax), sid, rmin, rmax))
    return out


def _from_points(pts: FloatArray, times: FloatArray | None, sid: str, rmin: float, rmax: float) -> Scanline:
    line = Scanline.from_points(pts, times, scanner_id=sid)
    if rmin == 0.0 and rmax == float("inf"):
        return line
    valid = validity_mask(line.ranges, rmin, rmax)
    return Scanline(line.angles, line.ranges, line.times, valid, sid, rmin, rmax)


def _per_scan_times(p: Path, times: FloatArray | None, shape: tuple[int, ...]) -> FloatArray | None:
    if times is None:
        return None
    t = times[None] if times.ndim == 1 else times
    if t.shape != tuple(shape):
        raise input_error(p, f"key 'times' has shape {times.shape}, expected one time per beam {tuple(shape)}")
    return t


def _numeric(p: Path, data: dict[str, np.ndarray], key: str) -> FloatArray:
    if np.iscomplexobj(data[key]):  # numpy would drop the imaginary part with a warning
        raise input_error(p, f"key '{key}' is complex (dtype {data[key].dtype}); expected real numbers")
    try:
        return np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise input_error(p, f"key '{key}' is not numeric (dtype {data[key].dtype})") from None


def _scalar(p: Path, data: dict[str, np.ndarray], key: str, default: float) -> float:
    if key not in data:
        return default
    v = _numeric(p, data, key)
    if v.size != 1:
        raise input_error(p, f"key '{key}' must be a scalar, has shape {v.shape}")
    return float(v.reshape(()))


def read_csv(path: str | Path) -> Iterator[Scanline]:
    """The one scanline of a CSV file with columns ``range,angle`` or ``x,y`` (+ ``time``)."""
    p = _existing(path)
    try:
        with open(p, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise input_error(p, f"not a readable CSV file ({e})") from None
    rows = [r for r in rows if r and not (len(r) == 1 and not r[0].strip())]
    if not rows:
        raise input_error(p, "empty CSV file")
    header = [h.strip().lower() for h in rows[0]]
    polar = {"range", "angle"} <= set(header)
    cart = {"x", "y"} <= set(header)
    if not (polar or cart):
        raise input_error(p, f"CSV header must name columns range,angle or x,y (got: {','.join(header)})")
    body = rows[1:]
    if not body:
        raise input_error(p, "CSV file has a header but no rows")
    cols = {name: i for i, name in enumerate(header)}
    values = np.empty((len(body), len(header)))
    for j, row in enumerate(body, start=2):
        if len(row) != len(header):
            raise input_error(p, f"line {j}: {len(row)} fields, expected {len(header)}")
        try:
            values[j - 2] = [float(x) for x in row]
        except ValueError:
            raise input_error(p, f"line {j}: non-numeric value in {','.join(row)[:60]}") from None
    times = values[:, cols["time"]] if "time" in cols else None
    try:
        if polar:
            line = Scanline.from_ranges(values[:, cols["range"]], values[:, cols["angle"]], times, scanner_id=p.stem)
        else:
            line = Scanline.from_points(values[:, [cols["x"], cols["y"]]], times, scanner_id=p.stem)
    except ValueError as e:  # values that make no scanline (a NaN angle of a valid beam)
        raise input_error(p, str(e)) from None
    return iter([line])


def _existing(path: str | Path) -> Path:
    p = Path(path)
    if not p.is_file():
        raise input_error(p, "no such file" if not p.exists() else "not a file")
    return p


def write_npz(path: str | Path, scanline: Scanline) -> Path:
    """Write one scanline as ``.npz`` (ranges, angles, times, scanner_id, range limits)."""
    arrays: dict[str, Any] = {
        "ranges": scanline.ranges,
        "angles": scanline.angles,
        "times": scanline.times,
        "scanner_id": np.array(scanline.scanner_id),
        "range_min": np.array(scanline.range_min),
        "range_max": np.array(scanline.range_max),
    }
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return Path(path)


def write_csv(path: str | Path, scanline: Scanline, columns: Literal["polar", "xy"] = "polar") -> Path:
    """Write one scanline as CSV: ``range,angle,time`` per beam (``polar``) or ``x,y,time``
    per valid point (``xy``, scanner frame)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    if columns == "polar":
        w.writerow(["range", "angle", "time"])
        rows: Any = zip(scanline.ranges, scanline.angles, scanline.times, strict=True)
    elif columns == "xy":
        w.writerow(["x", "y", "time"])
        t = scanline.times[scanline.valid_index]
        rows = zip(scanline.points_xy[:, 0], scanline.points_xy[:, 1], t, strict=True)
    else:
        raise ValueError(f"columns must be 'polar' or 'xy', got {columns!r}")
    w.writerows((repr(float(a)), repr(float(b)), repr(float(c))) for a, b, c in rows)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return Path(path)


__all__ = ["read_csv", "read_npz", "write_csv", "write_npz"]
