"""``.npz`` and CSV scanline files: round trips, the accepted layouts, and broken inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from segmentation import Scanline
from slam.io import InputError, detect_format, open_scans
from slam.io.scanfile import read_csv, read_npz, write_csv, write_npz


def _scan() -> Scanline:
    angles = np.linspace(-1.0, 1.0, 21)
    ranges = 2.0 + 0.1 * np.sin(3 * angles)
    ranges[4] = np.nan
    ranges[9] = 0.0
    ranges[15] = 40.0
    return Scanline.from_ranges(ranges, angles, 10.0, scanner_id="top", range_min=0.1, range_max=30.0, time_increment=1e-3)


def test_npz_round_trip(tmp_path: Path) -> None:
    s = _scan()
    path = write_npz(tmp_path / "scan.npz", s)
    assert detect_format(path) == "npz"
    (back,) = list(open_scans(path))
    np.testing.assert_array_equal(back.angles, s.angles)
    np.testing.assert_array_equal(back.ranges, s.ranges)
    np.testing.assert_array_equal(back.times, s.times)
    np.testing.assert_array_equal(back.valid, s.valid)
    assert back.scanner_id == "top" and back.range_min == 0.1 and back.range_max == 30.0
    assert not back.valid[15]  # above range_max
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


@pytest.mark.parametrize("columns", ["polar", "xy"])
def test_csv_round_trip(tmp_path: Path, columns: str) -> None:
    s = Scanline.from_ranges(np.linspace(1, 2, 11), np.linspace(-0.5, 0.5, 11), 3.0, time_increment=0.01)
    path = write_csv(tmp_path / "scan.csv", s, columns=columns)  # type: ignore[arg-type]
    assert detect_format(path) == "csv"
    (back,) = list(open_scans(path))
    np.testing.assert_allclose(back.points_xy, s.points_xy, atol=1e-12)
    np.testing.assert_allclose(back.times, s.times)
    assert back.scanner_id == "scan"


def test_csv_invalid_rows_stay_beams(tmp_path: Path) -> None:
    p = tmp_path / "s.csv"
    p.write_text("angle, range\n0.0,1.0\n0.1,nan\n0.2,inf\n0.3,0\n0.4,1.2\n")
    (s,) = list(read_csv(p))
    assert s.n_beams == 5 and s.n_valid == 2
    np.testing.assert_array_equal(s.valid, [True, False, False, False, True])


def test_npz_points_and_multiple_scans(tmp_path: Path) -> None:
    pts = np.array([[1.0, 0.0], [1.0, 0.1], [np.nan, np.nan], [1.0, 0.3]])
    np.savez(tmp_path / "p.npz", points=pts, times=np.arange(4.0))
    (s,) = list(read_npz(tmp_path / "p.npz"))
    assert s.n_beams == 4 and s.n_valid == 3
    np.testing.assert_array_equal(s.points_xy, pts[[0, 1, 3]])
    np.savez(tmp_path / "k.npz", ranges=np.ones((3, 5)), angles=np.linspace(0, 1, 5), times=np.arange(3.0)[:, None] + np.zeros(5))
    scans = list(read_npz(tmp_path / "k.npz"))
    assert len(scans) == 3 and [x.stamp for x in scans] == [0.0, 1.0, 2.0]


def test_bad_files_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"gone\.npz: no such file"):
        open_scans(tmp_path / "gone.npz")
    np.savez(tmp_path / "nokeys.npz", foo=np.ones(3))
    with pytest.raises(InputError, match=r"nokeys\.npz: needs keys 'ranges' and 'angles', or 'points' \(has: foo\)"):
        read_npz(tmp_path / "nokeys.npz")
    np.savez(tmp_path / "shape.npz", ranges=np.ones(5), angles=np.ones(4))
    with pytest.raises(InputError, match=r"shape\.npz: key 'angles' has shape \(4,\)"):
        read_npz(tmp_path / "shape.npz")
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match=r"junk\.npz: not a readable \.npz"):
        read_npz(tmp_path / "junk.npz")
    (tmp_path / "cols.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match=r"cols\.csv: CSV header must name columns range,angle or x,y"):
        read_csv(tmp_path / "cols.csv")
    (tmp_path / "text.csv").write_text("x,y\n1,2\n3,oops\n")
    with pytest.raises(InputError, match=r"text\.csv: line 3: non-numeric"):
        read_csv(tmp_path / "text.csv")
    (tmp_path / "ragged.csv").write_text("x,y\n1,2,3\n")
    with pytest.raises(InputError, match=r"ragged\.csv: line 2: 3 fields, expected 2"):
        read_csv(tmp_path / "ragged.csv")
    (tmp_path / "what.txt").write_text("hello\n")
    with pytest.raises(InputError, match=r"what\.txt: unknown input format"):
        open_scans(tmp_path / "what.txt")
    with pytest.raises(InputError, match=r"topics and rigs apply to ROS bags only"):
        open_scans(write_npz(tmp_path / "ok.npz", _scan()), topics=["/scan"])
