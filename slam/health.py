"""A run's own health: can its estimate be trusted?

Measured from what a run produces (world frame): the fraction of segments associated with
planes, the point-to-plane residuals against the noise they were weighted with, the knots'
speeds and turn rates (a walker does not move at 17 m/s), the translation directions the
associated planes leave unobserved and for how long (without an IMU a few seconds fail the run:
edges do not hold such a direction), the IMU factors' residuals against the IMU's noise (the
scans' motion against what the IMU measured), the number of planes, and a walk that starts
moving along a direction its first scans do not observe, and the final batch's departure from the
online estimate (:func:`trajectory_departure`: a stretch the batch slid against its neighbours).
On a recording whose beams carry
several echoes, failures that reading the wrong echo causes name ``input.echo``. Each check that
fails its limit is a :class:`Problem` naming its cause; the verdict is ``failed`` when any
problem is a failure, ``degraded`` when there are only warnings, else ``ok``. A failed run
exits with :data:`EXIT_FAILED` (the CLI), still writing its outputs, marked failed in
``summary.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from common.config import StrictModel

FloatArray = NDArray[np.float64]
Verdict = Literal["ok", "degraded", "failed"]
Severity = Literal["warning", "failure"]
EXIT_FAILED = 3  # exit code of a run whose estimate cannot be trusted (2 is bad input)


class HealthSection(StrictModel):
    """Limits of the run's self-diagnosis (``health:`` in the SLAM configuration)."""

    min_associated: float = Field(default=0.5, ge=0, le=1, description="fraction of segments on planes below which the run fails")
    warn_associated: float = Field(default=0.75, ge=0, le=1, description="... below which it is degraded")
    max_rms_whitened: float = Field(default=4.0, gt=0, description="whitened residual RMS above which the run fails")
    warn_rms_whitened: float = Field(default=2.0, gt=0, description="... above which it is degraded")
    max_imu_rms_whitened: float = Field(
        default=1.0, gt=0, description="whitened RMS of the IMU factors above which the run fails: the trajectory "
        "the scans give disagrees with what the IMU measured")
    warn_imu_rms_whitened: float = Field(default=0.5, gt=0, description="... above which it is degraded")
    echo_hint_share: float = Field(
        default=0.2, ge=0, le=1, description="share of beams with several echoes from which a failure of the "
        "residuals, the association or the IMU names the echo read (input.echo) as its likely cause")
    max_speed: float = Field(default=3.0, gt=0, description="m/s: a knot faster than this is a tracking failure")
    max_turn_rate: float = Field(default=math.radians(360.0), gt=0, description="rad/s, likewise")
    max_accel: float = Field(default=30.0, gt=0, description="m/s^2 between knot intervals: a jump")
    observed_window: float = Field(default=2.0, gt=0, description="s: windows in which the planes' directions are counted")
    unobserved_min_angle_deg: float = Field(
        default=5.0, gt=0, description="a translation direction whose planes' normals all lie within this of "
        "perpendicular to it is unobserved")
    warn_unobserved_seconds: float = Field(default=10.0, gt=0, description="s unobserved in a row: degraded")
    warn_unobserved_seconds_no_imu: float = Field(
        default=1.0, gt=0, description="s unobserved in a row without an IMU: degraded (one window)")
    warn_rig_angle_deg: float = Field(
        default=0.2, gt=0, description="deg: a given rig's scanner this far from the recording's /tf_static: degraded")
    warn_rig_distance: float = Field(default=0.005, gt=0, description="m, likewise")
    max_rig_angle_deg: float = Field(
        default=0.5, gt=0, description="deg: ... this far: failed (1 deg / 2 cm on one scanner put the demo walk 18 mm "
        "off; the rig is refused before processing from 3 deg / 5 cm)")
    max_rig_distance: float = Field(default=0.01, gt=0, description="m, likewise")
    max_unobserved_start_motion: float = Field(
        default=0.1, gt=0, description="m: without an IMU, motion along a direction no plane has observed since the "
        "walk's start: failed (the motion model has no speed to carry there)")
    departure_window: float = Field(
        default=10.0, gt=0, description="s: the span over which the final batch's trajectory is compared with the "
        "online estimate (the displacement in the body frame of its start)")
    warn_batch_departure: float = Field(
        default=0.2, gt=0, description="m: the final batch changed a departure_window's displacement by more: degraded "
        "(the office walks: at most 0.07-0.13 m, the online window's cm wiggles in corridors)")
    max_batch_departure: float = Field(
        default=0.5, gt=0, description="m: ... by more: failed. The batch and the online estimate disagree on the "
        "walk's shape; one of them is wrong")
    max_unobserved_seconds: float = Field(
        default=3.0, gt=0, description="s unobserved in a row without an IMU: failed. Only planes count: without an "
        "IMU nothing else holds the position along the direction (a 6 s standing-start corridor walk without an IMU "
        "ended 0.8 m off without doors, 0.5 m with their edges observed; every no-IMU demo walk of "
        "docs/robustness.md has no unobserved window)")


@dataclass(frozen=True)
class Problem:
    """One failed check: a code, its severity, a one-line message naming the cause, and the
    measured value against its limit."""

    code: str
    severity: Severity
    message: str
    value: float
    limit: float


@dataclass(frozen=True)
class Health:
    verdict: Verdict
    problems: list[Problem]
    measures: dict[str, float] = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        return self.verdict == "failed"

    def to_dict(self) -> dict[str, Any]:
        return {"verdict": self.verdict, "problems": [asdict(p) for p in self.problems], "measures": self.measures}

    def lines(self) -> list[str]:
        """One line per problem, failures first."""
        order = sorted(self.problems, key=lambda p: p.severity != "failure")
        return [f"{p.severity}: {p.message}" for p in order]


def _verdict(problems: list[Problem]) -> Verdict:
    if any(p.severity == "failure" for p in problems):
        return "failed"
    return "degraded" if problems else "ok"


def motion_problems(knot_times: FloatArray, T_world_body: FloatArray, cfg: HealthSection) -> tuple[list[Problem], dict[str, float]]:
    """Speeds, turn rates and accelerations of the knots (T_world_body (K, 4, 4) at knot_times (K,))."""
    out: list[Problem] = []
    if len(knot_times) < 3:
        return out, {}
    dt = np.diff(knot_times)
    p = T_world_body[:, :3, 3]
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / dt
    R = T_world_body[:, :3, :3]
    cos = np.clip((np.einsum("kij,kij->k", R[:-1], R[1:]) - 1.0) / 2.0, -1.0, 1.0)
    w = np.arccos(cos) / dt
    vel = np.diff(p, axis=0) / dt[:, None]
    acc = np.linalg.norm(np.diff(vel, axis=0), axis=1) / dt[1:]
    m = {"max_speed": float(v.max()), "max_turn_rate_deg": float(np.degrees(w.max())), "max_accel": float(acc.max())}
    k = int(np.argmax(v))
    if v[k] > cfg.max_speed:
        fast = float((dt[v > cfg.max_speed]).sum())
        out.append(Problem("implausible_speed", "failure",
                           f"the trajectory moves at {v[k]:.1f} m/s at t = {knot_times[k] - knot_times[0]:.1f} s "
                           f"({fast:.1f} s above {cfg.max_speed:g} m/s): tracking lost, not walking",
                           float(v[k]), cfg.max_speed))
    k = int(np.argmax(w))
    if w[k] > cfg.max_turn_rate:
        out.append(Problem("implausible_turn", "failure",
                           f"the trajectory turns at {math.degrees(w[k]):.0f} deg/s at t = {knot_times[k] - knot_times[0]:.1f} s: "
                           "tracking lost", float(w[k]), cfg.max_turn_rate))
    k = int(np.argmax(acc))
    if acc[k] > cfg.max_accel and not out:
        out.append(Problem("tracking_jump", "warning",
                           f"the trajectory jumps at t = {knot_times[k + 1] - knot_times[0]:.1f} s "
                           f"({acc[k]:.0f} m/s^2 between knot intervals)", float(acc[k]), cfg.max_accel))
    return out, m


def trajectory_departure(knot_times: FloatArray, T_before: FloatArray, T_after: FloatArray,
                         window: float) -> tuple[float, float]:
    """How far two estimates of the same knots (``T_world_body`` (K, 4, 4) each, at
    ``knot_times`` (K,)) differ in shape: for every knot k, its displacement to the first knot
    ``window`` s later, in k's body frame, by each estimate; returns the largest difference (m)
    and its knot's time (s since the first knot). A rigid change of the whole trajectory (a datum,
    a yaw drift spread over a loop) moves it little; a stretch slid against its neighbours, a lot.
    (0, 0) for a walk shorter than ``window``."""
    t = np.asarray(knot_times, dtype=np.float64)
    j = np.searchsorted(t, t + window)
    k = np.flatnonzero(j < t.shape[0])
    if k.shape[0] == 0:
        return 0.0, 0.0
    j = j[k]

    def shape(T: FloatArray) -> FloatArray:
        return np.einsum("kji,kj->ki", T[k, :3, :3], T[j, :3, 3] - T[k, :3, 3])

    d = np.linalg.norm(shape(T_before) - shape(T_after), axis=1)
    i = int(np.argmax(d))
    return float(d[i]), float(t[k[i]] - t[0])


def batch_problems(departure: float, departure_time: float, cfg: HealthSection) -> list[Problem]:
    """The final batch's departure from the online estimate (:func:`trajectory_departure`) against
    its limits."""
    if departure <= cfg.warn_batch_departure:
        return []
    sev: Severity = "failure" if departure > cfg.max_batch_departure else "warning"
    return [Problem("batch_departure", sev,
                    f"the final batch moved the trajectory {departure:.2f} m against the online estimate within "
                    f"{cfg.departure_window:g} s at t = {departure_time:.1f} s: the two disagree on the walk's shape "
                    "and one of them is wrong", departure,
                    cfg.max_batch_departure if sev == "failure" else cfg.warn_batch_departure)]


def _unobserved_windows(seg_stamp: FloatArray, seg_normal: FloatArray, t0: float, t1: float, window: float,
                        min_angle: float) -> tuple[FloatArray, list[set[str]]]:
    """The windows of :func:`unobserved_spans` (their lengths, s) and in each the labels of the
    translation directions its associated segments' plane normals leave unobserved."""
    n_win = max(1, math.floor((t1 - t0) / window + 0.5))
    edges = np.minimum(t0 + window * np.arange(n_win + 1), t1)
    edges[-1] = max(t1, edges[-2])
    width = np.diff(edges)
    idx = np.clip(((seg_stamp - t0) / window).astype(np.int64), 0, n_win - 1)
    ok = np.all(np.isfinite(seg_normal), axis=1)
    info = np.zeros((n_win, 3, 3))
    np.add.at(info, idx[ok], np.einsum("si,sj->sij", seg_normal[ok], seg_normal[ok]))
    counts = np.bincount(idx[ok], minlength=n_win).astype(float)
    thresh = math.sin(min_angle) ** 2
    out: list[set[str]] = []
    for k in range(n_win):
        labels: set[str] = set()
        if counts[k] > 0:
            w, V = np.linalg.eigh(info[k] / counts[k])
            for i in range(3):
                if w[i] < thresh:
                    labels.add("xyz"[int(np.argmax(np.abs(V[:, i])))])
        else:
            labels = {"x", "y", "z"}
        out.append(labels)
    return width, out


def unobserved_spans(seg_stamp: FloatArray, seg_normal: FloatArray, t0: float, t1: float, window: float,
                     min_angle: float) -> dict[str, float]:
    """Longest run (s) of windows in which a world translation direction is unobserved by the
    associated segments' plane normals (seg_normal (S, 3), world frame; NaN rows: unassociated).
    Returns {direction label: seconds}; the label is the unobserved eigenvector's dominant axis.
    The windows split [t0, t1] evenly, about ``window`` long (a remainder shorter than half a
    window joins the last one rather than being judged on its few segments); a run's seconds
    are the windows' lengths."""
    return _longest_runs(*_unobserved_windows(seg_stamp, seg_normal, t0, t1, window, min_angle))


def _longest_runs(width: FloatArray, labels: list[set[str]]) -> dict[str, float]:
    """:func:`unobserved_spans` from the windows (:func:`_unobserved_windows`)."""
    runs: dict[str, float] = {}
    current: dict[str, float] = {}
    for k, lab_k in enumerate(labels):
        for lab in "xyz":
            current[lab] = current.get(lab, 0.0) + float(width[k]) if lab in lab_k else 0.0
            runs[lab] = max(runs.get(lab, 0.0), round(current[lab], 3))
    return {k: v for k, v in runs.items() if v > 0}


def _start_runs(width: FloatArray, labels: list[set[str]]) -> dict[str, float]:
    """Per direction label unobserved from the walk's first window on, how long (s) it stays so."""
    out: dict[str, float] = {}
    for lab in "xyz":
        sec = 0.0
        for k, lab_k in enumerate(labels):
            if lab not in lab_k:
                break
            sec += float(width[k])
        if sec > 0:
            out[lab] = round(sec, 3)
    return out


def silent_scanners(scanner_names: list[str], seg_scanner: NDArray[np.integer]) -> list[Problem]:
    """A warning for each scanner (index into ``scanner_names``) without a single line segment in
    the run: its topic held no usable returns, and the run went on without it."""
    seen = set(np.unique(np.asarray(seg_scanner)).tolist())
    return [Problem(f"silent_scanner_{name}", "warning", f"scanner '{name}' gave no line segment in the whole "
                    "recording (no usable returns on its topic): the run went on without it", 0.0, 1.0)
            for k, name in enumerate(scanner_names) if k not in seen]


def rig_problems(mismatches: list[tuple[str, float, float]], cfg: HealthSection) -> list[Problem]:
    """A given rig against the recording's transforms (``mismatches``: scanner name, angle rad,
    distance m; ``slam.preflight``): a scanner off by more than the warning limits degrades the
    run, by more than the failure limits fails it (a mismatch large enough to refuse the rig
    never gets here). One problem, for the worst scanner."""
    warn = [m for m in mismatches if m[1] > math.radians(cfg.warn_rig_angle_deg) or m[2] > cfg.warn_rig_distance]
    if not warn:
        return []
    name, angle, dist = max(warn, key=lambda m: m[1] / math.radians(cfg.max_rig_angle_deg) + m[2] / cfg.max_rig_distance)
    fail = angle > math.radians(cfg.max_rig_angle_deg) or dist > cfg.max_rig_distance
    return [Problem("rig_mismatch", "failure" if fail else "warning",
                    f"the rig's scanner '{name}' differs from the recording's transforms by {math.degrees(angle):.2f} deg / "
                    f"{dist:.3f} m: the map is off by about as much (run without --rig to use the recording's, or "
                    "calibrate)", max(math.degrees(angle), 0.0),
                    cfg.max_rig_angle_deg if fail else cfg.warn_rig_angle_deg)]


def _set_off_unobserved(knot_times: FloatArray, T_world_body: FloatArray, start_spans: Mapping[str, float],
                        cfg: HealthSection, found: list[Problem]) -> list[Problem]:
    """Without an IMU: a failure for each direction that no plane observed from the walk's start
    (``start_spans``: :func:`_start_runs`) while the trajectory moved along it by more than
    ``max_unobserved_start_motion``. Mid-walk the motion model carries the speed it had across a
    short gap; at the start there is no speed to carry, so any motion along the direction is a
    guess (a room walked off from a standstill, its end walls not yet planes, slid 0.57 m in 2 s).
    None where ``found`` already fails that direction."""
    out: list[Problem] = []
    failed = {p.code for p in found if p.severity == "failure"}
    for lab, sec in sorted(start_spans.items()):
        if f"unobserved_{lab}" in failed:
            continue
        axis = "xyz".index(lab)
        inside = knot_times <= knot_times[0] + sec
        moved = float(np.ptp(T_world_body[inside, axis, 3]))
        if moved > cfg.max_unobserved_start_motion:
            out.append(Problem(f"unobserved_{lab}", "failure",
                               f"the walk moved {moved:.2f} m along world {lab} in its first {sec:.1f} s, before any plane "
                               "observed that direction, and there is no IMU: how far it went is a guess of the motion "
                               "model (start where walls of two directions are in view, or record an IMU)",
                               moved, cfg.max_unobserved_start_motion))
    return out


def start_problems(start: Mapping[str, Any]) -> list[Problem]:
    """A failure when the walk starts moving (``start``: the summary's ``start`` block,
    ``slam.frontend.initial_motion``) while its first scans leave a translation direction
    unobserved: parallel walls (a corridor) say how fast the operator walks across them, not
    along them, so the first knots' speed along it is a guess (at rest), and neither the planes
    nor an IMU started from that guess can correct it (a corridor walked at 1.2 m/s ended 3 m
    off with the IMU, 8 m without)."""
    if not start.get("moving") or start.get("unobserved_direction") is None:
        return []
    return [Problem("start_unobserved", "failure",
                    "the walk starts moving, but its first scans see only parallel walls (a corridor): the start's "
                    "speed along them is unknown and the trajectory along them cannot be trusted (start the recording "
                    "standing still, or where walls of two directions are in view)", 1.0, 0.0)]


def _unobserved_message(label: str, seconds: float, with_imu: bool, severity: Severity) -> str:
    if with_imu:
        return f"motion along world {label} is not observed by the planes for {seconds:.0f} s in a row (the IMU carries it)"
    tail = ": the trajectory along it cannot be trusted" if severity == "failure" else ""
    return (f"motion along world {label} is not observed by the planes for {seconds:.1f} s in a row and there is no IMU "
            f"(parallel walls only, e.g. a corridor whose ends are out of view; door and board edges alone do not "
            f"hold it){tail}")


def _above(code: str, value: float, warn: float, fail: float, message: str) -> list[Problem]:
    """The problem ``code`` of a figure that degrades the run above ``warn`` and fails it above
    ``fail`` (none below ``warn``)."""
    if not value > warn:
        return []
    sev: Severity = "failure" if value > fail else "warning"
    return [Problem(code, sev, message, value, fail if sev == "failure" else warn)]


def assess(knot_times: FloatArray, T_world_body: FloatArray, seg_stamp: FloatArray, seg_plane_id: NDArray[np.integer],
           plane_normals: Mapping[int, FloatArray], counts: Mapping[str, float], rms_whitened: float | None,
           with_imu: bool, cfg: HealthSection, extra: list[Problem] | None = None,
           imu_rms_whitened: float | None = None, echoes: tuple[str, float] | None = None) -> Health:
    """The health of a run (module doc). ``counts`` holds at least ``segments`` and
    ``segments_associated``; ``plane_normals`` maps a final plane id to its world normal;
    ``extra``: problems found elsewhere (:func:`silent_scanners`); ``imu_rms_whitened``: the IMU
    factors' whitened RMS (None without an IMU); ``echoes``: the echo the run read and the share
    of the recording's beams with several echoes (None: single-echo scans)."""
    problems: list[Problem] = list(extra or [])
    measures: dict[str, float] = {}
    n_seg = float(counts.get("segments", 0))
    n_assoc = float(counts.get("segments_associated", 0))
    if n_seg == 0:
        problems.append(Problem("no_segments", "failure", "no line segments in the recording's scans: no usable returns",
                                0.0, 1.0))
        return Health("failed", problems, measures)
    if not np.all(np.isfinite(T_world_body)):
        problems.append(Problem("non_finite", "failure", "the trajectory holds non-finite poses (NaN or inf)", 0.0, 0.0))
        return Health("failed", problems, measures)
    frac = n_assoc / n_seg
    measures["associated_fraction"] = frac
    if frac < cfg.min_associated or frac < cfg.warn_associated:
        sev: Severity = "failure" if frac < cfg.min_associated else "warning"
        problems.append(Problem("few_associated", sev,
                                f"only {100 * frac:.0f} % of the segments lie on planes of the map (the rig, the range "
                                "noise or the scene does not fit the model)", frac,
                                cfg.min_associated if sev == "failure" else cfg.warn_associated))
    if not plane_normals:
        problems.append(Problem("no_planes", "failure", "the map has no planes", 0.0, 1.0))
    if rms_whitened is not None and math.isfinite(rms_whitened):
        measures["rms_whitened"] = rms_whitened
        problems += _above("residuals", rms_whitened, cfg.warn_rms_whitened, cfg.max_rms_whitened,
                           f"point-to-plane residuals are {rms_whitened:.1f}x the noise they were weighted with "
                           "(range noise larger than assumed, or an inconsistent map)")
    if imu_rms_whitened is not None and math.isfinite(imu_rms_whitened):
        measures["imu_rms_whitened"] = imu_rms_whitened
        problems += _above("imu_disagrees", imu_rms_whitened, cfg.warn_imu_rms_whitened, cfg.max_imu_rms_whitened,
                           f"the trajectory disagrees with the IMU: its residuals are {imu_rms_whitened:.1f}x the IMU's "
                           "noise (the scans' scale or timing does not match what the IMU measured)")
    motion, m = motion_problems(knot_times, T_world_body, cfg)
    problems += motion
    measures.update(m)
    if len(knot_times) >= 2 and plane_normals:
        normal = np.full((len(seg_plane_id), 3), np.nan)
        for pid, n in plane_normals.items():
            normal[seg_plane_id == pid] = n
        windows = _unobserved_windows(np.asarray(seg_stamp, dtype=np.float64), normal, float(knot_times[0]),
                                      float(knot_times[-1]), cfg.observed_window,
                                      math.radians(cfg.unobserved_min_angle_deg))
        spans = _longest_runs(*windows)
        warn = cfg.warn_unobserved_seconds if with_imu else cfg.warn_unobserved_seconds_no_imu
        for lab, sec in sorted(spans.items()):
            measures[f"unobserved_{lab}_seconds"] = sec
            if sec >= warn:
                sev = "failure" if (sec >= cfg.max_unobserved_seconds and not with_imu) else "warning"
                problems.append(Problem(f"unobserved_{lab}", sev, _unobserved_message(lab, sec, with_imu, sev), sec,
                                        cfg.max_unobserved_seconds if sev == "failure" else warn))
        if not with_imu:
            problems += _set_off_unobserved(knot_times, T_world_body, _start_runs(*windows), cfg, problems)
    if echoes is not None:
        measures["several_echoes_share"] = echoes[1]
        problems = _with_echo_hint(problems, *echoes, cfg)
    return Health(_verdict(problems), problems, measures)


ECHO_SENSITIVE = ("few_associated", "residuals", "imu_disagrees")  # what reading the wrong echo breaks
ECHO_CHOICES = ("first", "last", "strongest")


def _with_echo_hint(problems: list[Problem], echo: str, share: float, cfg: HealthSection) -> list[Problem]:
    """Failures an echo other than the surface's would cause name the echo read as their likely
    cause when many of the recording's beams carry several echoes (a ghost before or after the
    surface makes a scaled or bent copy of the scene: its lines are fine, its motion is not)."""
    if share < cfg.echo_hint_share:
        return problems
    others = " or ".join(e for e in ECHO_CHOICES if e != echo)
    hint = (f"; the recording has several echoes on {100 * share:.0f} % of its beams and the run read the {echo} "
            f"echo (input.echo): another echo is likely the surface, re-run with input.echo: {others}")
    return [replace(p, message=p.message + hint) if p.severity == "failure" and p.code in ECHO_SENSITIVE else p
            for p in problems]
