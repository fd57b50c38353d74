"""The cloud written as it comes (slam.cloud_pass, slam.export) and read a chunk at a time (slam.evaluate,
slam.rerun_map): the same numbers as holding it whole."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import slam.cloud_pass
import slam.heap
import slam.run
from common.atomic import OutputFileError
from common.rig import resolve_rig
from simulation.run import SimulationResult, simulate
from slam.config import SlamConfig
from slam.evaluate import cloud_errors, mesh_distances
from slam.export import (
    CloudRecord,
    cloud_ply_layout,
    cloud_ply_writer,
    iter_cloud_ply,
    read_cloud_ply,
    read_summary_json,
    write_cloud_ply,
)
from slam.io.bag import read_scans
from slam.io.source import BagSource, StreamIndex
from slam.pipeline import SlamResult, SlamRunner
from slam.rerun_map import (
    CloudView,
    CloudViewPicker,
    MapOptions,
    view_of_cloud,
    view_of_cloud_ply,
    view_strides,
)
from slam.trajectory.placement import place_points
from tests.test_slam_pipeline import BOX_WORLD


def _cloud(n: int, seed: int = 0, shuffled: bool = False) -> CloudRecord:
    rng = np.random.default_rng(seed)
    time = 1.7e9 + np.sort(rng.uniform(0, 60, n))
    order = rng.permutation(n) if shuffled else np.arange(n)
    return CloudRecord(rng.uniform(-40, 40, (n, 3))[order], rng.integers(0, 3, n).astype(np.int32)[order],
                       time[order], rng.integers(-1, 30, n).astype(np.int32)[order])


def _same(a: CloudRecord, b: CloudRecord) -> None:
    for name in ("points_world", "scanner", "time", "plane_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


# ------------------------------------------------------------------------------ PLY in chunks


def test_writer_in_pieces_writes_the_whole_cloud_file(tmp_path: Path) -> None:
    c = _cloud(2500)
    write_cloud_ply(tmp_path / "whole.ply", c.points_world, c.scanner, c.time, c.plane_id)
    with cloud_ply_writer(tmp_path / "pieces.ply") as w:
        for a, b in ((0, 7), (7, 7), (7, 1300), (1300, 2500)):
            w.write(c.points_world[a:b], c.scanner[a:b].astype(np.uint8), c.time[a:b], c.plane_id[a:b])
    assert w.count == 2500
    assert (tmp_path / "pieces.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    assert cloud_ply_layout(tmp_path / "pieces.ply")[0] == 2500
    _same(read_cloud_ply(tmp_path / "pieces.ply"), c)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pieces.ply", "whole.ply"]


def test_header_length_does_not_depend_on_the_count(tmp_path: Path) -> None:
    offsets = set()
    for n in (0, 1, 99, 12345):
        c = _cloud(n)
        write_cloud_ply(tmp_path / f"{n}.ply", c.points_world, c.scanner, c.time, c.plane_id)
        count, offset = cloud_ply_layout(tmp_path / f"{n}.ply")
        assert count == n
        offsets.add(offset)
    assert len(offsets) == 1


def test_failed_streamed_write_leaves_nothing(tmp_path: Path) -> None:
    c = _cloud(10)
    with pytest.raises(OutputFileError, match=r"cloud\.ply: non-finite"), cloud_ply_writer(tmp_path / "cloud.ply") as w:
        w.write(c.points_world, c.scanner, c.time, c.plane_id)
        w.write(np.full((2, 3), np.nan), [0, 0], [1.0, 2.0], [0, 0])
    assert list(tmp_path.iterdir()) == []


def test_strided_and_chunked_reads_equal_the_whole_read(tmp_path: Path) -> None:
    c = _cloud(1001)
    path = tmp_path / "cloud.ply"
    write_cloud_ply(path, c.points_world, c.scanner, c.time, c.plane_id)
    whole = read_cloud_ply(path)
    assert whole.time.dtype == np.float64 and whole.plane_id.dtype == np.int32
    chunks = list(iter_cloud_ply(path, chunk=128))
    assert [len(x) for x in chunks] == [128] * 7 + [105]
    _same(CloudRecord(*(np.concatenate([getattr(x, f) for x in chunks])
                        for f in ("points_world", "scanner", "time", "plane_id"))), c)  # fmt: skip
    for step in (2, 3, 7, 128, 1001, 5000):
        for chunk in (1, 100, 1001, 1 << 20):
            s = read_cloud_ply(path, step=step, chunk=chunk)
            _same(s, CloudRecord(c.points_world[::step], c.scanner[::step], c.time[::step], c.plane_id[::step]))


def test_reader_takes_open3d_files_and_rejects_foreign_ones(tmp_path: Path) -> None:
    import open3d as o3d

    c = _cloud(50)
    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor.from_numpy(c.points_world))
    for name, col in (("scanner", c.scanner), ("time", c.time), ("plane_id", c.plane_id)):
        pc.point[name] = o3d.core.Tensor.from_numpy(np.ascontiguousarray(col[:, None]))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "open3d.ply"), pc, write_ascii=False)
    _same(read_cloud_ply(tmp_path / "open3d.ply"), c)
    # open3d reads ours (the padded comment line included)
    write_cloud_ply(tmp_path / "ours.ply", c.points_world, c.scanner, c.time, c.plane_id)
    back = o3d.t.io.read_point_cloud(str(tmp_path / "ours.ply"))
    np.testing.assert_array_equal(back.point["positions"].numpy(), c.points_world)
    np.testing.assert_array_equal(back.point["plane_id"].numpy().ravel(), c.plane_id)

    assert o3d.t.io.write_point_cloud(str(tmp_path / "ascii.ply"), pc, write_ascii=True)
    with pytest.raises(OutputFileError, match=r"ascii\.ply: 'format ascii 1\.0' is not cloud\.ply's format"):
        read_cloud_ply(tmp_path / "ascii.ply")
    floats = o3d.t.geometry.PointCloud(o3d.core.Tensor.from_numpy(c.points_world.astype(np.float32)))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "floats.ply"), floats, write_ascii=False)
    with pytest.raises(OutputFileError, match=r"floats\.ply: not cloud\.ply's layout"):
        read_cloud_ply(tmp_path / "floats.ply")
    data = (tmp_path / "ours.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(data[:-3])
    with pytest.raises(OutputFileError, match=r"short\.ply: .* \(truncated\?\)"):
        read_cloud_ply(tmp_path / "short.ply", step=3)
    (tmp_path / "text.ply").write_text("hello\n")
    with pytest.raises(OutputFileError, match=r"text\.ply: not a PLY file"):
        cloud_ply_layout(tmp_path / "text.ply")
    with pytest.raises(OutputFileError, match=r"none\.ply: no such file"):
        read_cloud_ply(tmp_path / "none.ply")


# ---------------------------------------------------------------------- evaluation in chunks


def _box_mesh() -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(10.0, 8.0, 3.0)
    m.translate([-5.0, -4.0, 0.0])
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64)


def test_distances_in_chunks_equal_one_query() -> None:
    v, f = _box_mesh()
    pts = np.random.default_rng(3).uniform([-6, -5, -1], [6, 5, 4], (5000, 3))
    one = mesh_distances(pts, v, f, chunk=1 << 20)
    for chunk in (1, 333, 4999):
        np.testing.assert_array_equal(mesh_distances(pts, v, f, chunk=chunk), one)
    assert np.all(one >= 0) and one.max() > 0.5


def test_cloud_errors_from_the_file_equal_those_in_memory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import slam.export

    v, f = _box_mesh()
    c = _cloud(3001, seed=5)
    path = tmp_path / "cloud.ply"
    write_cloud_ply(path, c.points_world / 8, c.scanner, c.time, c.plane_id)
    c = read_cloud_ply(path)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    monkeypatch.setattr(slam.export, "_PLY_CHUNK", 256)  # the file is read in 12 chunks
    for max_points in (3001, 1000, 7):
        mem, disk = cloud_errors(c, T, v, f, max_points), cloud_errors(path, T, v, f, max_points)
        np.testing.assert_array_equal(disk.distances, mem.distances)
        np.testing.assert_array_equal(disk.associated, mem.associated)
        assert disk.n_points_total == mem.n_points_total == 3001
        assert disk.to_json() == mem.to_json()
    assert cloud_errors(path, T, v, f, 1000).distances.size == 751  # every 4th of 3001


# --------------------------------------------------------------------- the recording's view


def _same_view(a: CloudView, b: CloudView) -> None:
    assert a.t0 == b.t0
    assert [s for s, _ in a.scans] == [s for s, _ in b.scans]
    for (_, x), (_, y) in zip(a.scans, b.scans, strict=True):
        _same(x, y)
    _same(a.cloud, b.cloud)


@pytest.mark.parametrize("shuffled", [False, True])
def test_view_of_the_file_equals_the_view_in_memory(tmp_path: Path, shuffled: bool) -> None:
    c = _cloud(4000, seed=2, shuffled=shuffled)
    path = tmp_path / "cloud.ply"
    write_cloud_ply(path, c.points_world, c.scanner, c.time, c.plane_id)
    for opt in (MapOptions(max_scan_points=300, max_cloud_points=170), MapOptions()):
        mem = view_of_cloud(c, opt)
        for chunk in (97, 4000):
            _same_view(view_of_cloud_ply(path, opt, chunk=chunk), mem)
    assert len(view_of_cloud(c, MapOptions(max_scan_points=300)).scans[0][1]) < 110


# ------------------------------------------------------------------ the run's streamed export


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    folder = tmp_path_factory.mktemp("box")
    (folder / "box.yaml").write_text(BOX_WORLD)
    return simulate(folder / "box.yaml", "itc_backpack", duration=2.0, seed=3, out=folder / "box.bag",
                    progress=False)


@pytest.fixture(scope="module")
def estimate(walk: SimulationResult) -> SlamResult:
    rig = resolve_rig("itc_backpack")
    cfg = SlamConfig()
    runner = SlamRunner(rig, cfg, None)
    for line in read_scans(walk.bag, rig=rig):
        runner.add_scan(line)
    runner.finish()
    return runner.result(batch=cfg.backend.final_batch)


def _reference_cloud(bag: Path, res: SlamResult) -> tuple[CloudRecord, np.ndarray]:
    """The cloud held whole and placed in one call: every valid point within the knots, with the
    plane id of the associated segment covering its beam, and those segments' end points."""
    rig = resolve_rig("itc_backpack")
    rows = res.segment_rows
    names = list(res.scanner_names)
    T_bs = {s.name: s.T_body_scanner.matrix() for s in rig.scanners}
    kt = res.knot_times
    pb, sc, tm, pid, ends = [], [], [], [], []
    scan_index = dict.fromkeys(names, -1)
    n = 0
    for line in read_scans(bag, rig=rig):
        s = names.index(line.scanner_id)
        scan_index[line.scanner_id] += 1
        t = line.times[line.valid_index]
        ok = (t >= kt[0]) & (t <= kt[-1])
        beams = line.valid_index[ok]
        xyz = np.column_stack((line.points_xy[ok], np.zeros(beams.size)))
        T = T_bs[line.scanner_id]
        pb.append(xyz @ T[:3, :3].T + T[:3, 3])
        plane = np.full(beams.size, -1, dtype=np.int32)
        mine = np.flatnonzero((rows["scanner"] == s) & (rows["scan_index"] == scan_index[line.scanner_id])
                              & (rows["plane_id"] >= 0))
        for r in mine:
            hit = np.flatnonzero((beams >= rows["first_beam"][r]) & (beams <= rows["last_beam"][r]))
            if hit.size:
                plane[hit] = rows["plane_id"][r]
                ends += [n + hit[0], n + hit[-1]]
        sc.append(np.full(beams.size, s, dtype=np.int32))
        tm.append(t[ok])
        pid.append(plane)
        n += beams.size
    t_all = np.concatenate(tm)
    pw = place_points(kt, res.T_world_body, t_all, np.concatenate(pb))
    return CloudRecord(pw, np.concatenate(sc), t_all, np.concatenate(pid)), pw[np.asarray(ends, dtype=np.int64)]


def _reference_rms(cloud: CloudRecord, ends: np.ndarray, res: SlamResult) -> np.ndarray:
    """Each associated segment's points' RMS distance to its plane's final estimate, from the
    cloud held whole (its points between the segment's first and last, all its plane's)."""
    ids = [int(i) for i in res.plane_ids]
    out = []
    idx = {tuple(p): i for i, p in enumerate(cloud.points_world.tolist())}
    for a, b in ends.reshape(-1, 2, 3):
        lo, hi = idx[tuple(a.tolist())], idx[tuple(b.tolist())]
        j = ids.index(int(cloud.plane_id[lo]))
        r = cloud.points_world[lo:hi + 1] @ np.asarray(res.plane_normals[j]) + float(res.plane_offsets[j])
        out.append(np.sqrt(np.mean(r * r)))
    return np.asarray(out)


def _streamed(walk: SimulationResult, res: SlamResult, ply: Path, index: StreamIndex | None = None,
              processes: int = 1) -> tuple[int, Any]:
    with BagSource(walk.bag) as source:
        n, lines, _ = slam.cloud_pass.write_cloud(source, resolve_rig("itc_backpack"), res, ply, index, False,
                                                  processes, echo="first")
        return n, lines


def test_streamed_cloud_equals_the_cloud_held_whole(walk: SimulationResult, estimate: SlamResult, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    ref, ref_ends = _reference_cloud(walk.bag, estimate)
    assert len(ref) > 50_000 and ref_ends.shape[0] > 100
    n, lines = _streamed(walk, estimate, tmp_path / "default.ply")
    assert n == len(ref)
    _same(read_cloud_ply(tmp_path / "default.ply"), ref)
    np.testing.assert_array_equal(lines.endpoints_world.reshape(-1, 3), ref_ends)
    assert lines.stamp.shape[0] == lines.plane_id.shape[0] == ref_ends.shape[0] // 2
    # each segment's points' RMS distance to its plane (for the planes' outlines), as numpy has it
    assert lines.rms is not None and lines.rms.dtype == np.float32
    np.testing.assert_allclose(lines.rms, _reference_rms(ref, ref_ends, estimate), rtol=1e-5, atol=1e-9)
    assert float(np.median(lines.rms)) < 0.006  # the walk's segments lie on their planes
    # batches of a few scans, placed in odd chunks: the same file
    monkeypatch.setattr(slam.cloud_pass, "_EXPORT_BATCH", 1500)
    monkeypatch.setattr(slam.cloud_pass, "_PLACE_CHUNK", 333)
    _, small = _streamed(walk, estimate, tmp_path / "small.ply")
    assert (tmp_path / "small.ply").read_bytes() == (tmp_path / "default.ply").read_bytes()
    np.testing.assert_array_equal(small.endpoints_world, lines.endpoints_world)


def test_a_cloud_cut_by_stamp_windows_is_the_same_file(walk: SimulationResult, estimate: SlamResult,
                                                      tmp_path: Path) -> None:
    """The pass cut into parts found again by their stamps (the stream's index), written by forked
    processes: the same bytes and segments as one pass; no part files left."""
    stream = read_scans(walk.bag, rig=resolve_rig("itc_backpack"))
    for _ in stream:
        pass
    parts = slam.cloud_pass.plan_parts(stream.index, estimate.scanner_names, 3)
    assert len(parts) == 3 and parts[0].window is not None and parts[1].first_scan_index[0] > 0
    n_one, one = _streamed(walk, estimate, tmp_path / "one.ply")
    n_cut, cut = _streamed(walk, estimate, tmp_path / "cut.ply", stream.index, processes=3)
    assert n_one == n_cut and (tmp_path / "one.ply").read_bytes() == (tmp_path / "cut.ply").read_bytes()
    np.testing.assert_array_equal(one.endpoints_world, cut.endpoints_world)
    np.testing.assert_array_equal(one.stamp, cut.stamp)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.ply", "one.ply"]


def _read_with_view_caps(walk: SimulationResult) -> tuple[Any, MapOptions, Any]:
    """The walk's scans read once (so that their stream's index is complete), small view caps,
    the rig."""
    stream = read_scans(walk.bag, rig=resolve_rig("itc_backpack"))
    for _ in stream:
        pass
    return stream, MapOptions(max_scan_points=5_000, max_cloud_points=3_000), resolve_rig("itc_backpack")


def test_the_pass_picks_the_recordings_view_as_it_writes(walk: SimulationResult, estimate: SlamResult,
                                                         tmp_path: Path) -> None:
    """The view for map.rrd is picked while the points are written, at strides from the stream's
    count of returns (no second pass over the file): in one part it is the file's view at those
    strides; cut into parts, every part picks from its own first point, and the joined view holds
    cloud points only, each scanner's in time order, about as many as in one part."""
    stream, opt, rig = _read_with_view_caps(walk)
    with BagSource(walk.bag) as source:
        n, _, one = slam.cloud_pass.write_cloud(source, rig, estimate, tmp_path / "one.ply", stream.index, False, 1,
                                                echo="first", view=opt)
        _, _, cut = slam.cloud_pass.write_cloud(source, rig, estimate, tmp_path / "cut.ply", stream.index, False, 3,
                                                echo="first", view=opt)
        _, _, unindexed = slam.cloud_pass.write_cloud(source, rig, estimate, tmp_path / "bare.ply", None, False, 1,
                                                      echo="first", view=opt)
    assert one is not None and cut is not None and unindexed is not None
    step, cloud_step = view_strides(stream.index.points, opt)
    assert n <= stream.index.points and step > 1 and cloud_step > 1
    picker = CloudViewPicker(step, cloud_step)
    for c in iter_cloud_ply(tmp_path / "one.ply", 4096):
        picker.take(c)
    _same_view(one, picker.view())
    _same_view(unindexed, view_of_cloud_ply(tmp_path / "bare.ply", opt))  # no count known: from the file
    whole = read_cloud_ply(tmp_path / "cut.ply")
    assert cut.t0 == one.t0 == float(whole.time.min())
    keys = {(float(t), int(s)) for t, s in zip(whole.time, whole.scanner, strict=True)}
    assert [s for s, _ in cut.scans] == [s for s, _ in one.scans]
    for (_, a), (_, b) in zip(cut.scans, one.scans, strict=True):
        assert abs(len(a) - len(b)) <= 3 and np.all(np.diff(a.time) >= 0)
        assert all((float(t), int(s)) in keys for t, s in zip(a.time, a.scanner, strict=True))
    assert abs(len(cut.cloud) - len(one.cloud)) <= 3
    assert len(one.cloud) <= opt.max_cloud_points and sum(len(c) for _, c in one.scans) <= opt.max_scan_points + 3


@pytest.mark.parametrize("processes", [1, 3])
def test_a_pass_that_keeps_no_point_gives_what_the_written_pass_gives(walk: SimulationResult, estimate: SlamResult,
                                                                     tmp_path: Path, processes: int) -> None:
    """Without cloud.ply (``keep_points`` off: only the recording and the outlines want the pass)
    no file is made, in one part or three, and the count, the segments with their RMS and the
    recording's view are those of the pass that writes every point."""
    stream, opt, rig = _read_with_view_caps(walk)
    with BagSource(walk.bag) as source:
        n, lines, view = slam.cloud_pass.write_cloud(source, rig, estimate, tmp_path / "all.ply", stream.index, False,
                                                     processes, echo="first", view=opt)
        none = tmp_path / "none" / "cloud.ply"
        none.parent.mkdir()
        m, kept, seen = slam.cloud_pass.write_cloud(source, rig, estimate, none, stream.index, False, processes,
                                                    echo="first", view=opt, keep_points=False)
        with pytest.raises(ValueError, match="only with the stream's index"):
            slam.cloud_pass.write_cloud(source, rig, estimate, none, None, False, 1, echo="first", view=opt,
                                        keep_points=False)
    assert not list(none.parent.iterdir())
    assert m == n == read_cloud_ply(tmp_path / "all.ply").points_world.shape[0] > 0
    for field in ("stamp", "endpoints_world", "plane_id", "rms"):
        np.testing.assert_array_equal(getattr(kept, field), getattr(lines, field))
    assert view is not None and seen is not None
    _same_view(seen, view)


def test_a_run_without_cloud_ply_needs_no_room_for_it(walk: SimulationResult, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``output.cloud`` off the recording's pass writes no point: a disk too small for the
    cloud does not stop the run, and its folder holds map.rrd and planes.json, no cloud."""
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=10 << 20))
    cfg = SlamConfig.model_validate({"output": {"cloud": False, "rerun": True}})
    slam.run.run_slam(walk.bag, resolve_rig("itc_backpack"), cfg, tmp_path / "run", progress=False)
    names = {p.name for p in (tmp_path / "run").iterdir()}
    assert {"map.rrd", "planes.json"} <= names and not any("cloud" in n for n in names)


def test_the_cloud_pass_keeps_its_heap_from_creeping_up(walk: SimulationResult, estimate: SlamResult,
                                                       tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After every batch the pass looks at its resident memory and trims the heap once it rose by
    the keeper's slack (a long walk's pass would otherwise grow through an inherited heap's free
    chunks); the file is the same."""
    n_plain, _ = _streamed(walk, estimate, tmp_path / "plain.ply")
    looks: list[int] = []
    trims: list[int] = []

    class Keeper(slam.heap.HeapKeeper):
        def __init__(self) -> None:  # 1 MB more at every look, trimmed after 4 MB
            super().__init__(slack=4 << 20, rss=lambda: looks.append(1) or len(looks) << 20,
                             trim=lambda: trims.append(len(looks)) is None)

    monkeypatch.setattr(slam.cloud_pass, "_EXPORT_BATCH", 5000)
    monkeypatch.setattr(slam.cloud_pass, "HeapKeeper", Keeper)
    n, _ = _streamed(walk, estimate, tmp_path / "kept.ply")
    assert n == n_plain and n >= 50_000
    assert (tmp_path / "kept.ply").read_bytes() == (tmp_path / "plain.ply").read_bytes()
    # a look after each batch (of at least 5,000 points), trimmed at the sixth look and every sixth after (over 4 MB above the last)
    assert len(looks) >= 10 and len(trims) >= 2
    assert trims[0] == 6 and all(b - a == 6 for a, b in itertools.pairwise(trims))


def test_the_cloud_pass_keeps_nothing_per_scan_in_its_stream(walk: SimulationResult, estimate: SlamResult,
                                                             tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The pass's scan streams record no stamp or scanner id per scan (an hour's 432,000 scans:
    ~17 MB of Python floats and list slots, for nothing), but still their lag and last stamp."""
    streams: list[Any] = []
    plain = BagSource.scans

    def scans(self: BagSource, *args: Any, **kwargs: Any) -> Any:
        streams.append(plain(self, *args, **kwargs))
        return streams[-1]

    whole = read_scans(walk.bag, rig=resolve_rig("itc_backpack"))
    for _ in whole:
        pass
    monkeypatch.setattr(BagSource, "scans", scans)
    n, _ = _streamed(walk, estimate, tmp_path / "cloud.ply", whole.index)
    assert n > 0 and len(streams) == 1 and len(whole.index) > 100
    index = streams[0].index
    assert index.stamps == [] and index.scanner_ids == []
    assert index.last_stamp == whole.index.stamps[-1] and index.lag_ns == whole.index.lag_ns


def test_run_records_its_peak_memory(walk: SimulationResult, tmp_path: Path) -> None:
    cfg = SlamConfig()
    cfg = cfg.model_copy(update={"output": cfg.output.model_copy(update={"voxel": 0.05})})
    summary = slam.run.run_slam(walk.bag, resolve_rig("itc_backpack"), cfg, tmp_path / "run", progress=False)
    mem = read_summary_json(tmp_path / "run" / "summary.json")["memory"]
    assert mem == summary["memory"]
    assert 0.05 < mem["peak_rss_gb_after_estimation"] <= mem["peak_rss_gb_after_export"] < 64
    assert "ru_maxrss" in mem["definition"]
    # the thinned cloud and the recording; the file of every point is gone
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [
        "cloud.ply", "map.rrd", "planes.json", "segments.npz", "summary.json", "trajectory.tum",
        "trajectory_online.tum"]
    n = summary["counts"]["cloud_points"]
    assert 0 < n == cloud_ply_layout(tmp_path / "run" / "cloud.ply")[0]
    # a well-posed walk meets no singular linear system in its solves
    assert summary["singular_systems"] == {"count": 0, "first": []}
    # the window solver has no iSAM2 updates to count
    assert cfg.backend.solver == "window" and "isam2_updates" not in summary["counts"]


def test_the_stream_index_counts_the_clouds_points(walk: SimulationResult, estimate: SlamResult, tmp_path: Path) -> None:
    """The index counts every valid return the stream yields; the cloud pass writes each of them
    that lies within the knots (all of them on a walk whose knots span its scans)."""
    with BagSource(walk.bag) as source:
        stream = source.scans(rig=resolve_rig("itc_backpack"))
        valid = sum(int(line.valid.sum()) for line in stream)
        index = stream.index
    assert index.points == valid > 0
    n, _ = _streamed(walk, estimate, tmp_path / "cloud.ply", index)
    assert 0.9 * index.points <= n <= index.points


def test_a_run_without_room_for_its_cloud_fails_before_the_pass(walk: SimulationResult, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Too little free disk for the cloud (and the parts' rows until they are joined) is one
    OutputFileError naming the output folder, raised before the pass writes anything; no run folder."""
    from slam.export import cloud_row_bytes
    from slam.run_folder import cloud_bytes_needed

    need = cloud_bytes_needed(1_000_000, False, 2, False)
    rows = 1_000_000 * cloud_row_bytes(False)
    assert rows * 1.5 < need < rows * 1.5 * 1.1 + (64 << 20)  # the cloud and half of it in the other part's rows
    assert cloud_bytes_needed(1_000_000, False, 1, True) > cloud_bytes_needed(1_000_000, False, 1, False)

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=10 << 20))
    written: list[int] = []
    monkeypatch.setattr(slam.cloud_pass, "cloud_part", lambda *a, **k: written.append(1))
    with pytest.raises(OutputFileError, match=r"not enough free disk space for the cloud: about .* GB needed"):
        slam.run.run_slam(walk.bag, resolve_rig("itc_backpack"), SlamConfig(), tmp_path / "run", progress=False)
    assert not written
    assert not (tmp_path / "run").exists() and not list(tmp_path.iterdir())


def test_a_run_warns_before_the_walk_when_its_cloud_may_not_fit(walk: SimulationResult, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Before the walk the cloud's points are estimated from the scans' count (the first scan of
    each scanner): a file system too small for them is a warning naming the folder; one with
    room gives none, and the estimate is near the cloud's real count."""
    from slam.run import cloud_space_note

    rig = resolve_rig("itc_backpack")
    cfg = SlamConfig()
    with BagSource(walk.bag) as source:
        plan = source.scan_plan(rig=rig)
        assert cloud_space_note(source, rig, plan, cfg, tmp_path / "new" / "run", None) is None
        real = shutil.disk_usage
        seen: list[int] = []
        monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=1 << 20))
        import slam.run as run_mod
        check = run_mod.check_cloud_space
        monkeypatch.setattr(run_mod, "check_cloud_space", lambda out, points, *a: (seen.append(points), check(out, points, *a)))
        note = cloud_space_note(source, rig, plan, cfg, tmp_path / "new" / "run", None)
        assert note is not None and note.startswith("warning: ") and str(tmp_path) in note
        no_cloud = cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": False})})
        assert cloud_space_note(source, rig, plan, no_cloud, tmp_path, None) is None
        # the recording alone needs the pass but no room: it keeps no point
        rrd_only = cfg.model_copy(update={"output": cfg.output.model_copy(update={"cloud": False, "rerun": True})})
        assert cloud_space_note(source, rig, plan, rrd_only, tmp_path, None) is None
        stream = source.scans(rig=rig)
        valid = sum(int(line.valid.sum()) for line in stream)
    assert 0.8 * valid < seen[0] < 1.25 * valid
