"""``run_slam``: a bag in, the run folder out (the I/O edge around ``slam.pipeline``).

Outputs in ``out_dir`` (written into a temporary sibling folder that replaces
``out_dir`` only when complete, so an interrupted run leaves no half-written
output):

- ``trajectory.tum``: ``T_world_body`` at every knot (evo-compatible TUM);
- ``planes.json``: id, normal, d (``n . x + d = 0``), extent polygon, number
  of segments, 3x3 covariance (normal tangent, d), kind;
- ``segments.npz``: one row per segment with its plane (-1 = unassociated, -2 = a thing that
  moved: ``slam.frontend.transients``);
- ``cloud.ply``: every valid point placed by the final trajectory and the
  rig's extrinsics (world frame), with scanner index, time and plane id;
- ``map.rrd``: the rerun recording; ``summary.json``: config, counts,
  timings, residual statistics, peak memory after the estimation and after the export.

The bag is opened in this process (``slam.io.source.BagSource``; the reader process and the
cloud's export processes open their own); while a forked reader reads it, this process lets go of
its message index (a few hundred MB an hour) and opens the bag again for the export. The cloud is written as it is placed, never held: the
export's memory does not grow with the walk's length (``slam.cloud_pass``).
"""

from __future__ import annotations

import gc
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from common.atomic import OutputFileError, atomic_dir
from common.rig import Rig
from segmentation import Scanline
from segmentation.noise import estimate as estimate_noise_model
from slam import params
from slam.config import SlamConfig
from slam.export import write_summary_json
from slam.health import (
    Health,
    assess,
    batch_problems,
    rig_problems,
    silent_scanners,
    start_problems,
)
from slam.heap import fewer_collections, trim_heap
from slam.imu_feed import ImuSamples
from slam.io.bag import time_range as bag_time_range
from slam.io.echoes import several_echoes_share
from slam.io.errors import input_error
from slam.io.source import SCAN_TYPES, BagSource
from slam.pipeline import SlamRunner
from slam.prefetch import PreparedScans, prepared_scans
from slam.preflight import check_observability, check_rig
from slam.rerun_map import MapOptions, write_map_rrd
from slam.result import SlamResult
from slam.run_folder import (
    RunSummary,
    check_cloud_space,
    write_cloud_outputs,
    write_planes,
    write_tables,
)

# bag_time_range: a bag's (start, end) log time from its path, for callers that hold no source
__all__ = ["bag_time_range", "estimate_noise", "load_imu", "peak_rss_gb", "run_slam", "trim_heap"]

IMU_FRAMES = ("", "body", "base_link", "imu")  # frame ids taken as the rig's body frame
NOISE_READ_SECONDS = 10.0  # s of scans read at most for the noise estimate (a scanner silent at the start)


def imu_topic(cfg: SlamConfig, rig: Rig | None) -> str:
    """The IMU topic of a run: the configuration's, else the rig's."""
    return cfg.imu.topic or (rig.imu.topic if rig is not None else "/imu")


def load_imu(bag: BagSource | str | Path, cfg: SlamConfig, t_start: float, t_end: float,
             rig: Rig | None = None) -> ImuSamples | None:
    """The bag's IMU samples for the run (``cfg.imu.use``: auto = when the bag has the topic and it
    covers the scans, ``t_start``-``t_end`` s); None when the run goes without. The topic is
    :func:`imu_topic`'s; the samples' frame must be the body frame (the rig's body or IMU frame,
    or a usual name of it). ``bag``: an open source, or a path opened for this call. Errors name
    the bag and the topic."""
    if not isinstance(bag, BagSource):
        with BagSource(bag) as source:
            return load_imu(source, cfg, t_start, t_end, rig)
    ic = cfg.imu
    topic = imu_topic(cfg, rig)
    if ic.use == "off":
        return None
    if topic not in bag.topics():
        if ic.use == "on":
            raise input_error(bag.path, "has no IMU messages (imu.use is 'on')", topic)
        return None
    series = bag.imu(topic)
    frames = (*IMU_FRAMES, *((rig.body_frame, rig.imu.frame_id) if rig is not None else ()))
    if series.frame_id not in frames:
        raise input_error(bag.path, f"IMU frame '{series.frame_id}' is not the body frame ({', '.join(frames[1:])})",
                          topic)
    try:
        samples = ImuSamples(series.times, series.linear_acceleration, series.angular_velocity,
                             instantaneous=ic.samples == "instantaneous")
    except ValueError as e:
        raise input_error(bag.path, str(e), topic) from None
    if not samples.covers(t_start, t_end - 0.05):
        if ic.use == "on":
            raise input_error(bag.path, f"IMU samples do not cover the scans ({t_start:.2f}-{t_end:.2f} s) without gaps",
                              topic)
        return None
    return samples


def estimate_noise(source: BagSource, rig: Rig, cfg: SlamConfig) -> tuple[SlamConfig, dict[str, Any]]:
    """Each scanner's range noise from the recording (``noise.estimate``): the first
    ``noise.estimate_scans`` scans of every scanner without a fixed value in ``noise.scanners``
    (read for at most ``NOISE_READ_SECONDS``), through ``segmentation.noise.estimate``. Returns
    ``cfg`` with the estimates in ``noise.scanners`` (the effective noise at the samples' median
    range) and the record summary.json reports: per scanner where its noise comes from, the
    estimate, the noise its values follow and its ratio to the reference; the shared ratio."""
    nc = cfg.noise
    todo = [s.name for s in rig.scanners if s.name not in nc.scanners] if nc.estimate else []
    lines: dict[str, list[Scanline]] = {name: [] for name in todo}
    if todo:
        stream = source.scans(rig=rig, echo=cfg.input.echo)
        t_first = None
        for line in stream:
            t_first = line.stamp if t_first is None else t_first
            got = lines.get(line.scanner_id)
            if got is not None and len(got) < nc.estimate_scans:
                got.append(line)
            if line.stamp - t_first > NOISE_READ_SECONDS or all(len(v) >= nc.estimate_scans for v in lines.values()):
                break
        stream.close()
    record: dict[str, Any] = {}
    fixed = dict(nc.scanners)
    for s in rig.scanners:
        if s.name in nc.scanners:
            record[s.name] = {"source": "config", "range_sigma": nc.scanners[s.name]}
            continue
        if s.name not in lines:
            record[s.name] = {"source": "rig", "range_sigma": s.scanner_model.range_sigma}
            continue
        try:
            model = estimate_noise_model(lines[s.name])
        except ValueError as e:  # too few returns: the rig's model holds
            record[s.name] = {"source": "rig", "range_sigma": s.scanner_model.range_sigma, "estimate_failed": str(e)}
            continue
        fixed[s.name] = model.sigma_ref
        record[s.name] = {
            "source": "estimated", "range_sigma": model.sigma_ref, "range_ref": model.range_ref,
            "sigma0": model.sigma0, "slope": model.slope, "beam_sigma": model.beam_sigma,
            "quantum": model.quantum, "n_scans": model.n_scans, "n_samples": model.n_samples,
        }
    out = cfg.model_copy(update={"noise": nc.model_copy(update={"scanners": fixed})})
    levels = params.noise_levels(rig, out)
    for s, sigma, ratio in zip(rig.scanners, levels.sigma, levels.ratio, strict=True):
        record[s.name] |= {"values_follow": sigma, "ratio": ratio}
    return out, {"scanners": record, "shared_ratio": levels.shared, "reference": nc.reference}


def cloud_space_note(source: BagSource, rig: Rig, plan: dict[str, str | None], cfg: SlamConfig, out_dir: Path,
                     voxel: float | None) -> str | None:
    """A warning when the output's file system looks too small for the cloud pass (before the
    walk, so that an hour's estimate is not spent on a cloud that cannot be written): the points
    estimated as each scan topic's message count times the valid returns of its first scan,
    checked as the export will check the exact count (``slam.run_folder.check_cloud_space``);
    None when it fits or there is no cloud."""
    if not cfg.output.cloud:  # without cloud.ply the pass keeps no point (slam.run_folder.write_cloud_outputs)
        return None
    per_scan: dict[str, int] = {}
    stream = source.scans(rig=rig, echo=cfg.input.echo, record=False)
    t0: float | None = None
    for line in stream:
        t0 = line.stamp if t0 is None else t0
        per_scan.setdefault(line.scanner_id, int(line.points_xy.shape[0]))
        if len(per_scan) == len(plan) or line.stamp - t0 > NOISE_READ_SECONDS:
            break
    stream.close()
    points = 0
    for topic, name in plan.items():
        n = sum(c.msgcount for c in source.connections(topic, SCAN_TYPES))
        points += n * per_scan.get(name or topic, max(per_scan.values(), default=0))
    folder = out_dir.resolve()
    while not folder.exists():
        folder = folder.parent
    v = voxel if voxel is not None else (cfg.output.voxel or None)
    try:
        check_cloud_space(folder, points, False, cfg.parallel.export_processes, v is not None)
    except OutputFileError as e:
        return f"warning: {e} (estimated from the scans' count; the export checks the exact count and stops there)"
    return None


def peak_rss_gb() -> float:
    """The peak resident memory of this process so far (GB): ``ru_maxrss``, KiB on Linux and
    bytes on macOS."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak * (1 if sys.platform == "darwin" else 1024) / 1e9


def run_slam(
    bag: str | Path,
    rig: Rig | None,
    cfg: SlamConfig,
    out_dir: str | Path,
    progress: bool = True,
    voxel: float | None = None,
    urdf: str | Path | None = None,
    report: Callable[[str], object] | None = None,
) -> dict[str, Any]:
    """Run SLAM on ``bag`` with ``rig`` (None: built from the bag's transforms or ``urdf``) and
    ``cfg``; write the run folder; return the summary, its ``health`` block the run's verdict.

    Before anything is processed the rig is checked against the recording (a wrong rig, or one
    that leaves a degree of freedom to an IMU the run does not have, is a ``RigError``); what the
    checks note goes to ``report`` (one line each) and into the summary. Then each scanner's range
    noise is estimated from its first scans (:func:`estimate_noise`; the values that follow it:
    ``slam.config.NoiseSection``). A recording without a
    single line segment is an ``InputError`` (no usable returns), with no output written."""
    t_wall = time.perf_counter()
    with fewer_collections(), BagSource(bag) as source:
        check = check_rig(source, rig, urdf, cfg.input.echo)
        rig = check.rig
        plan = source.scan_plan(rig=rig)  # checks the bag and its topics before anything is written
        share = several_echoes_share(source, list(plan))
        t_range = source.time_range()
        imu = load_imu(source, cfg, *t_range, rig=rig)
        check.notes += check_observability(rig, source, imu_topic(cfg, rig) if imu is not None else None)
        space = cloud_space_note(source, rig, plan, cfg, Path(out_dir), voxel)
        if space is not None:
            check.notes.append(space)
        for note in check.notes:
            if report is not None:
                report(note)
        cfg, noise = estimate_noise(source, rig, cfg)
        # the scans first: a forked reader lets go of this process's bag index before the back
        # end's process is forked (which would keep a copy of it)
        scans = prepared_scans(source, rig, cfg, imu, process=cfg.parallel.reader)
        runner = SlamRunner(rig, cfg, imu)
        pace: list[list[float]] = []
        _estimate(runner, scans, t_range, progress, pace)
        if runner.stats["segments"] == 0:
            raise input_error(source.path, "no line segment in any scan: no usable returns on the topics "
                              + ", ".join(s.topic for s in rig.scanners) + " (every range invalid, or too few per scan)")
        res = runner.result(batch=cfg.backend.final_batch)
        runner.close()
        # the estimator's graph, blocks and map are not needed by the export (res holds what it
        # needs): let them go before the cloud pass forks its parts, and hand malloc's free pages
        # back (freed, they stay resident and are counted in this process while its parts run)
        del runner
        gc.collect()
        trim_heap()
        health = run_health(res, cfg, imu is not None, [(m.scanner, m.angle, m.distance) for m in check.mismatches],
                            None if share is None else (cfg.input.echo, share))
        memory = {"peak_rss_gb_after_estimation": peak_rss_gb()}

        with atomic_dir(Path(out_dir)) as tmp:
            t0 = time.perf_counter()
            write_tables(tmp, res)
            cloud = write_cloud_outputs(tmp, source, rig, cfg, res, scans.index, progress, voxel)
            planes = write_planes(tmp, res, cfg, cloud.segments)
            if cfg.output.rerun:
                write_map_rrd(tmp / "map.rrd", times=res.knot_times, T_world_body=res.T_world_body, planes=planes,
                              cloud=cloud.view, scanner_names=res.scanner_names, segments=cloud.segments,
                              options=MapOptions())
            res.timings["export"] = time.perf_counter() - t0
            memory["peak_rss_gb_after_export"] = peak_rss_gb()
            summary = RunSummary.of(bag, rig, cfg, res, cloud.points, memory, time.perf_counter() - t_wall,
                                    t_range, health, check.notes, noise, pace).to_dict()
            write_summary_json(tmp / "summary.json", summary)
    # the result, the cloud view and the scans' index are done with: what they held goes back to
    # the system before the caller goes on (an evaluation in the same process)
    del res, cloud, scans
    gc.collect()
    trim_heap()
    return summary


def run_health(res: SlamResult, cfg: SlamConfig, with_imu: bool,
               rig_mismatches: list[tuple[str, float, float]] | None = None,
               echoes: tuple[str, float] | None = None) -> Health:
    """The run's verdict on its own estimate (``slam.health``); ``rig_mismatches`` (scanner, rad,
    m) of a given rig against the recording's transforms; ``echoes``: the echo read and the share
    of beams with several (``slam.io.echoes``), None for single-echo scans."""
    rows = res.segment_rows
    normals = {int(i): n for i, n in zip(res.plane_ids, res.plane_normals, strict=True)}
    counts = {"segments": len(rows["plane_id"]), "segments_associated": int((rows["plane_id"] >= 0).sum())}
    residuals = res.stats.get("residuals") or {}
    return assess(res.knot_times, res.T_world_body, rows["stamp"], rows["plane_id"], normals, counts,
                  residuals.get("rms_whitened"), with_imu, cfg.health,
                  extra=silent_scanners(res.scanner_names, rows["scanner"]) + start_problems(res.stats.initial_motion)
                  + rig_problems(rig_mismatches or [], cfg.health)
                  + ([] if res.stats.batch is None else batch_problems(res.stats.batch.departure,
                                                                       res.stats.batch.departure_time, cfg.health)),
                  imu_rms_whitened=residuals.get("imu_rms_whitened"), echoes=echoes)


def cpu_seconds_of_tree() -> float:
    """User + system CPU seconds of this process and of its live children (the reader and back-end
    processes), so far."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in (me, *me.children(recursive=True)):
        try:
            t = p.cpu_times()
        except psutil.Error:  # a child that ended meanwhile
            continue
        total += t.user + t.system
    return total


def _estimate(runner: SlamRunner, scans: PreparedScans, t_range: tuple[float, float], progress: bool,
              pace: list[list[float]] | None = None, pace_every: float = 10.0) -> None:
    """Every scan through the runner, with a progress bar over the data's time; then its finish.
    ``pace`` gets a row (data s since the start, wall s, CPU s of the process tree) every
    ``pace_every`` s of data (the speed over the walk: summary.json ``pace``)."""
    t_start, t_end = t_range
    w0, c0, mark = time.perf_counter(), cpu_seconds_of_tree(), t_start
    bar = tqdm(
        total=round(t_end - t_start, 2),
        desc="slam",
        disable=not progress,
        leave=False,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s of data [{elapsed}<{remaining}]",
    )
    last = t_start
    for scan in scans:
        runner.add_prepared(scan)
        if pace is not None and scan.stamp - mark >= pace_every:
            mark = scan.stamp
            pace.append([round(mark - t_start, 3), round(time.perf_counter() - w0, 3),
                         round(cpu_seconds_of_tree() - c0, 3)])
        if scan.stamp - last >= 0.5:
            bar.update(round(scan.stamp - last, 2))
            last = scan.stamp
    bar.close()
    runner.finish()
