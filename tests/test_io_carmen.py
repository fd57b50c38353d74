"""CARMEN reader on the real logs in ../shared/data/real/ and on broken copies of them."""

from __future__ import annotations

import gzip
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slam.io import InputError, open_scans
from slam.io.carmen import CarmenScan, flaser_angles, read_carmen

REAL = Path("/work/shared/data/real")
INTEL = REAL / "intel-corrected.log.gz"
needs_data = pytest.mark.skipif(not REAL.is_dir(), reason="real data not available")


@needs_data
@pytest.mark.parametrize(
    ("name", "n_scans", "n_beams", "t_first", "n_backward"),
    [("intel", 910, 180, 32.9068, 4), ("freiburg-079", 4791, 360, 0.227623, 0), ("aces", 440, 180, 21.0199, 0)],
)
def test_real_logs_scan_and_beam_counts(name: str, n_scans: int, n_beams: int, t_first: float, n_backward: int) -> None:
    recs = list(read_carmen(REAL / f"{name}-corrected.log.gz"))
    assert len(recs) == n_scans
    assert {r.scanline.n_beams for r in recs} == {n_beams}
    first = recs[0].scanline
    # the default ("open") convention: steps of 180/n deg from -90 deg
    np.testing.assert_allclose(first.angles[0], -math.pi / 2)
    np.testing.assert_allclose(np.diff(first.angles), math.pi / n_beams)
    assert recs[0].timestamp == pytest.approx(t_first)
    np.testing.assert_allclose(first.times, t_first)  # one logged time per scan, time_increment 0
    stamps = np.array([r.timestamp for r in recs])
    # file order; the intel log itself has 4 small backward steps (<= 0.86 s) in its timestamps
    steps = np.diff(stamps)
    assert np.sum(steps < 0) == n_backward and steps.min() > -1.0
    # "no return" readings (50 m / 81.83 m / 81.91 m) are masked, never points
    assert max(float(np.max(r.scanline.ranges[r.scanline.valid], initial=0.0)) for r in recs) < 50.0
    assert all(r.scanline.n_valid > 0 for r in recs[:50])


@needs_data
def test_intel_first_scan_values() -> None:
    rec = next(read_carmen(INTEL))
    assert isinstance(rec, CarmenScan) and rec.kind == "FLASER" and rec.host == "pippo"
    np.testing.assert_allclose(rec.pose_xytheta, [0.600266, -0.0320327, -0.354665])
    np.testing.assert_allclose(rec.odom_xytheta, [0.600266, -0.0320327, -0.354665])
    np.testing.assert_allclose(rec.scanline.ranges[:4], [1.09, 1.08, 1.08, 1.07])
    np.testing.assert_allclose(rec.scanline.points_xy[0], [0.0, -1.09], atol=1e-12)


def _pair_errors(path: Path, angles: dict[str, np.ndarray], n_pairs: int = 300) -> dict[str, np.ndarray]:
    """Per pair of overlapping scans seen at different headings: median point-to-line distance."""
    recs = list(read_carmen(path))
    P = np.array([r.pose_xytheta for r in recs])
    rng = np.random.default_rng(0)
    pairs = []
    for k in range(len(recs)):
        d = np.hypot(*(P[:k, :2] - P[k, :2]).T)
        dth = np.abs((P[:k, 2] - P[k, 2] + np.pi) % (2 * np.pi) - np.pi)
        cand = np.flatnonzero((d < 1.5) & (dth > np.radians(15)) & (dth < np.radians(60)))
        if cand.size:
            pairs.append((k, int(rng.choice(cand))))
    rng.shuffle(pairs)

    def world(rec: CarmenScan, ang: np.ndarray) -> np.ndarray:
        s = rec.scanline
        keep = s.valid & (s.ranges < 8.0)
        r, th = s.ranges[keep], ang[keep] + rec.pose_xytheta[2]
        return rec.pose_xytheta[:2] + np.column_stack((r * np.cos(th), r * np.sin(th)))

    out: dict[str, list[float]] = {k: [] for k in angles}
    for k, j in pairs[:n_pairs]:
        errs = {}
        for name, ang in angles.items():
            pa, pb = world(recs[j], ang), world(recs[k], ang)
            d, idx = cKDTree(pa).query(pb, k=5)
            ok = d[:, -1] < 0.3
            if ok.sum() < 20:
                break
            nb = pa[idx[ok]]
            c = nb.mean(axis=1)
            X = nb - c[:, None]
            _, v = np.linalg.eigh(np.einsum("mki,mkj->mij", X, X))
            errs[name] = float(np.median(np.abs(np.einsum("mi,mi->m", pb[ok] - c, v[:, :, 0]))))
        else:
            for name, e in errs.items():
                out[name].append(e)
    return {k: np.array(v) for k, v in out.items()}


@needs_data
def test_flaser_angle_convention_fits_the_maps_better() -> None:
    """The chosen 'open' convention makes overlapping scans agree better than 'closed' (all three logs pooled)."""
    diffs = []
    for name in ("intel", "aces", "freiburg-079"):
        path = REAL / f"{name}-corrected.log.gz"
        n = next(read_carmen(path)).scanline.n_beams
        e = _pair_errors(path, {"open": flaser_angles(n, "open"), "closed": flaser_angles(n, "closed")})
        diffs.append(e["closed"] - e["open"])
    d = np.concatenate(diffs)
    assert d.size > 500
    assert d.mean() > 2.5 * d.std() / math.sqrt(d.size)  # closed worse, by > 2.5 standard errors


def test_flaser_angles_conventions() -> None:
    np.testing.assert_allclose(flaser_angles(180)[[0, -1]], np.radians([-90.0, 89.0]))
    np.testing.assert_allclose(flaser_angles(360)[[0, -1]], np.radians([-90.0, 89.5]))
    np.testing.assert_allclose(flaser_angles(181, "closed")[[0, 90, -1]], np.radians([-90.0, 0.0, 90.0]))
    with pytest.raises(ValueError, match="angle convention"):
        flaser_angles(10, "half")  # type: ignore[arg-type]


@needs_data
def test_plain_text_equals_gzip(tmp_path: Path) -> None:
    src = REAL / "aces-corrected.log.gz"
    plain = tmp_path / "aces.log"
    with gzip.open(src, "rb") as f, open(plain, "wb") as g:
        shutil.copyfileobj(f, g)
    a = list(read_carmen(src))
    b = list(read_carmen(plain))
    assert len(a) == len(b) == 440
    np.testing.assert_array_equal(a[100].scanline.ranges, b[100].scanline.ranges)
    assert sum(1 for _ in open_scans(plain)) == 440


def _flaser_line(ranges: list[float], t: float) -> str:
    return f"FLASER {len(ranges)} {' '.join(map(str, ranges))} 1 2 0.5 1.1 2.1 0.4 {t} host {t + 0.01}\n"


def test_flaser_range_max_param_and_override(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    log.write_text("PARAM robot_front_laser_max 20.0 host 0\n" + _flaser_line([1.0, 19.0, 20.0, 0.0, 30.0], 5.0))
    s = next(read_carmen(log)).scanline
    np.testing.assert_array_equal(s.valid, [True, True, False, False, False])
    s = next(read_carmen(log, range_max=40.0, time_increment=0.001)).scanline
    np.testing.assert_array_equal(s.valid, [True, True, True, False, True])
    np.testing.assert_allclose(s.times, 5.0 + 0.001 * np.arange(5))


def test_robotlaser1_line(tmp_path: Path) -> None:
    start, res, n = -2.0, 0.01, 5
    ranges = [1.0, 2.0, 8.0, 0.5, 3.0]
    line = (
        f"ROBOTLASER1 0 {start} {res * (n - 1)} {res} 8.0 0.01 0 {n} {' '.join(map(str, ranges))} "
        "2 10 20 1.5 2.5 0.3 1.4 2.4 0.2 0.1 0.0 0.5 0.3 0.0 123.25 myhost 123.5\n"
    )
    log = tmp_path / "robot.clf"
    log.write_text("# comment\n" + line)
    rec = next(read_carmen(log))
    assert rec.kind == "ROBOTLASER1" and rec.host == "myhost"
    np.testing.assert_allclose(rec.scanline.angles, start + res * np.arange(n))
    np.testing.assert_array_equal(rec.scanline.valid, [True, True, False, True, True])  # 8.0 = max range
    np.testing.assert_allclose(rec.pose_xytheta, [1.5, 2.5, 0.3])
    np.testing.assert_allclose(rec.odom_xytheta, [1.4, 2.4, 0.2])
    assert rec.timestamp == 123.25 and rec.logger_timestamp == 123.5
    np.testing.assert_allclose(rec.scanline.times, 123.25)


@needs_data
def test_truncated_gzip_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "intel-truncated.log.gz"
    bad.write_bytes(INTEL.read_bytes()[: INTEL.stat().st_size // 2])
    with pytest.raises(InputError, match=r"intel-truncated\.log\.gz.*(truncated|unreadable)"):
        list(read_carmen(bad))


@needs_data
def test_corrupt_gzip_names_the_file(tmp_path: Path) -> None:
    data = bytearray(INTEL.read_bytes())
    data[len(data) // 3 : len(data) // 3 + 64] = bytes(range(64))
    bad = tmp_path / "intel-corrupt.log.gz"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"intel-corrupt\.log\.gz"):
        list(read_carmen(bad))


def test_malformed_lines_name_file_and_line(tmp_path: Path) -> None:
    log = tmp_path / "bad.log"
    log.write_text(_flaser_line([1.0, 2.0], 1.0) + "FLASER 3 1.0 oops 2.0 1 2 3 4 5 6 7 h 8\n")
    with pytest.raises(InputError, match=r"bad\.log: line 2: expected a number, got 'oops'"):
        list(read_carmen(log))
    log.write_text("FLASER 180 1.0 2.0\n")
    with pytest.raises(InputError, match=r"bad\.log: line 1: truncated FLASER"):
        list(read_carmen(log))


def test_missing_and_non_laser_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nope\.log: no such file"):
        read_carmen(tmp_path / "nope.log")
    odom = tmp_path / "odom.log"
    odom.write_text("ODOM 1 2 3 0 0 0 1.0 h 1.0\n")
    with pytest.raises(InputError, match=r"odom\.log: no FLASER or ROBOTLASER1 lines"):
        list(read_carmen(odom))
