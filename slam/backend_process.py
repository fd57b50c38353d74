"""The back end in its own process, one update behind the front end (``backend.pipelined``).

:class:`BackendProcess` has the :class:`slam.backend.Backend` API the pipeline and the front end
use. A forked worker process owns the real ``Backend``; every mutating call is forwarded to it in
order (batched, arguments copied at the call), so the worker's graph sees exactly the calls the
in-process back end would. Calls that return ids (knots, factor and block ids) answer at once
from the same deterministic counters (:class:`FactorIds`, which also follow the folds of linked
planes at a step, ``config.fold_links_in_window``: a fold merges what the links sent before the
step tie, known here when it is sent); the worker checks every id it makes against the one given
and fails loudly when they differ.

``step()`` is pipelined: update ``u`` sends the step and returns at once; update ``u + 1`` first
waits for step ``u``'s result (the recent knots' poses, velocities and bias, every plane, the
step's report), puts it into a local mirror that answers ``pose``/``velocity``/``bias``/``plane``
until the next result, then sends step ``u + 1`` and returns step ``u``'s report. Knots (and
planes) added after step ``u`` was sent are answered with the front end's own values moved by
the rigid correction that step ``u`` gave the last knot it saw
(``T_new = T_est(k_u) T_front(k_u)^-1 T_front``), so that the trajectory stays continuous; their
velocities (with an IMU) likewise take the step's last velocity plus the front end's change since,
rotated (``v_new = v_est(k_u) + R_C (v_front - v_front(k_u))``): the front end integrates the IMU
on from its newest velocity, which must carry what the back end estimated (rotated alone, it would
be the IMU's dead reckoning since the start of the walk, 0.1 m/s off within seconds). The
front end thus runs one update behind the back end, whatever the timing: the same input gives
the same output. :meth:`BackendProcess.collect` waits for the outstanding step (the end of the
walk); every other query (the final batch, trims, covariances, statistics) is a synchronous call
answered by the worker.

The worker is forked (Linux), dies with its parent (the kernel kills it; it also watches its
parent's pid) and hands any exception back as a one-line ``RuntimeError`` raised in the parent
(no hang: the parent waits only while the worker lives, ``slam.forked.get_from_children``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_mod
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam.backend import Backend, BackendConfig, OptimizeSummary, RobustKernel, StepReport
from slam.backend.ties import link_roots
from slam.forked import can_fork_reader, die_with_parent, get_from_children, stop_children
from slam.frontend.knots import KnotMirror

FloatArray = NDArray[np.float64]

_POLL_S = 1.0  # s between the worker's checks that its parent still lives
_FLUSH_CALLS = 256  # forwarded calls sent in one message (the worker starts on them meanwhile)
_CALLS, _STEP, _SYNC, _STOP = "calls", "step", "sync", "stop"
_RESULT, _RAISED, _FAILED = "result", "raised", "failed"


def make_backend(config: BackendConfig, pipelined: bool | None, knots: KnotMirror,
                 recent_knots: int) -> Backend | BackendProcess:
    """The back end of a run: a :class:`BackendProcess` when ``pipelined`` (None: where a
    process can be forked, :func:`slam.forked.can_fork_reader`), else an in-process
    ``Backend``. ``knots`` is the front end's mirror of the trajectory, ``recent_knots`` how many
    of the newest knots the front end refreshes after an update."""
    on = can_fork_reader() if pipelined is None else pipelined
    if on and not can_fork_reader():
        raise ValueError("backend.pipelined: true, but no process can be forked here (no fork, or a daemon process)")
    return BackendProcess(config, knots, recent_knots) if on else Backend(config)


class FactorIds:
    """The back end's id counters, kept without the graph: knots are numbered in order; factor
    ids (observation blocks included) come from one counter that every added factor advances
    (:mod:`slam.backend.graph`). Counts follow :mod:`slam.backend.knots` and
    :mod:`slam.backend.ties`; the worker checks every id against the real back end's.

    The planes' ties are kept as :class:`slam.backend.ties.PlaneTies` keeps them, as ids only
    (which planes have a floor or wall prior, the links not folded yet, the orientation ties, the
    planes folded into others), so that the ids also follow the folds of
    ``config.fold_links_in_window``: a fold gives the surviving plane a prior and re-keys the
    dropped plane's ties (new factors), and a tie or link asked for later between planes that
    became one answers as the back end does."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self.knots = 0
        self.next_factor = 0
        self.priors: set[int] = set()  # planes with a horizontality or verticality prior
        self.links: list[tuple[int, int]] = []  # (keep, drop), not folded yet
        self.ties: list[tuple[int, int, int, bool]] = []  # (host, plane, factor id, perpendicular?)
        self.folded: dict[int, int] = {}  # plane id -> the plane it was folded into

    def _factors(self, n: int) -> int:
        first = self.next_factor
        self.next_factor += n
        return first

    def add_pose(self) -> int:
        """The new knot's index (its datum, motion and IMU-state factors counted)."""
        i, cfg = self.knots, self.config
        n = 0
        if i == 0:
            n += 1  # the datum prior
        elif i == 1 and cfg.imu is None:
            n += 1  # the first interval's weak velocity prior
        if i >= 2 and cfg.use_motion_prior:
            n += 1  # the constant-velocity factor
        if cfg.imu is not None:
            n += 2 if i == 0 else 1  # velocity and bias priors, else the bias random walk
        self._factors(n)
        self.knots += 1
        return i

    def add_plane(self, plane_id: int, horizontal: bool, vertical: bool) -> None:
        """A plane: its horizontality or verticality prior."""
        if horizontal or vertical:
            self.priors.add(int(plane_id))
            self._factors(1)

    def one(self) -> int:
        """One factor (an observation block, an IMU factor, a velocity prior)."""
        return self._factors(1)

    def resolve(self, plane_id: int) -> int:
        """The plane that ``plane_id`` is now (followed through the folds)."""
        j = int(plane_id)
        while j in self.folded:
            j = self.folded[j]
        return j

    def tie(self, host_id: int, plane_id: int, perpendicular: bool) -> int:
        """A parallel or perpendicular tie's id (that of the pair's tie, if it has one already)."""
        a, b = self.resolve(host_id), self.resolve(plane_id)
        if a == b:
            what = "perpendicular" if perpendicular else "parallel"
            raise ValueError(f"add_{what}: cannot tie plane {a} to itself")
        same = next((t for t in self.ties if {t[0], t[1]} == {a, b} and t[3] == perpendicular), None)
        if same is not None:
            return same[2]
        fid = self.one()
        self.ties.append((a, b, fid, perpendicular))
        return fid

    def link(self, keep_id: int, drop_id: int) -> int:
        """An equality link's id (-1: the two planes are one already)."""
        if int(keep_id) == int(drop_id):
            raise ValueError(f"link_planes: cannot link plane {int(keep_id)} with itself")
        keep, drop = self.resolve(keep_id), self.resolve(drop_id)
        if keep == drop:
            return -1
        self.links.append((keep, drop))
        return self.one()

    def remove_plane(self, plane_id: int) -> None:
        """A plane removed: its prior and ties go."""
        j = self.resolve(plane_id)
        self.priors.discard(j)
        self.ties = [t for t in self.ties if j not in t[:2]]

    def fold_links(self) -> dict[int, int]:
        """The links folded into merges (as :meth:`slam.backend.ties.PlaneTies.fold_links`):
        dropped id -> surviving id."""
        out = link_roots(self.links)
        self.links = []
        for drop, keep in out.items():
            if drop in self.priors:  # the prior moves over (a new factor) unless keep has one
                self.priors.discard(drop)
                if keep not in self.priors:
                    self.priors.add(keep)
                    self.one()
            self._rekey_ties(drop, keep)
            self.folded[drop] = keep
        return out

    def _rekey_ties(self, drop: int, keep: int) -> None:
        """:meth:`slam.backend.ties.PlaneTies._rekey_parallels`: the dropped plane's ties made
        again on ``keep`` (new ids), once per pair."""
        pairs = {(frozenset(t[:2]), t[3]) for t in self.ties if drop not in t[:2]}
        out = []
        for a, b, fid, perp in self.ties:
            if drop not in (a, b):
                out.append((a, b, fid, perp))
                continue
            na, nb = (keep if a == drop else a), (keep if b == drop else b)
            if na != nb and (frozenset((na, nb)), perp) not in pairs:
                pairs.add((frozenset((na, nb)), perp))
                out.append((na, nb, self.one(), perp))
        self.ties = out


@dataclass
class StepResult:
    """What a step gives the front end: the report, the knot count at the step, the poses (m, 4, 4)
    (and with an IMU velocities (m, 3)) of knots ``first`` .. ``n_knots - 1``, the last knot's
    bias (6,), and every plane (ids, unit normals (P, 3), offsets; world frame)."""

    report: StepReport
    n_knots: int
    first: int
    poses: FloatArray
    velocities: FloatArray | None
    bias: FloatArray | None
    planes: dict[int, tuple[FloatArray, float]]


def _step_result(be: Backend, report: StepReport, first: int, with_imu: bool) -> StepResult:
    n = be.num_knots
    first = max(0, min(first, n))
    poses = np.array([be.pose(k) for k in range(first, n)]).reshape(-1, 4, 4)
    vel = bias = None
    if with_imu and n:
        vel = np.array([be.velocity(k) for k in range(first, n)]).reshape(-1, 3)
        bias = np.asarray(be.bias(n - 1), dtype=float)
    planes = {int(j): be.plane(int(j)) for j in be.plane_ids()}
    return StepResult(report, n, first, poses, vel, bias, planes)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _worker(config: BackendConfig, calls: Any, results: Any, parent: int) -> None:
    """The worker process: the real back end, driven by the messages on ``calls``; step results
    and synchronous answers go on ``results``, a fatal error as ``(_FAILED, one line)``."""
    die_with_parent(parent)
    try:
        be = Backend(config)
        while True:
            try:
                msg = calls.get(timeout=_POLL_S)
            except queue_mod.Empty:
                if os.getppid() != parent:  # the parent died: so does its back end
                    return
                continue
            kind = msg[0]
            if kind == _CALLS:
                for name, args, kwargs, expect in msg[1]:
                    got = getattr(be, name)(*args, **kwargs)
                    if expect is not None and got != expect:
                        raise RuntimeError(f"{name} gave id {got} where the proxy's counters gave {expect}: "
                                           "slam.backend_process.FactorIds no longer counts as the back end does")
            elif kind == _STEP:
                report = be.step()
                results.put((_RESULT, _step_result(be, report, msg[1], config.imu is not None)))
            elif kind == _SYNC:
                name, args, kwargs = msg[1]
                try:
                    attr = getattr(be, name)
                    out = attr(*args, **kwargs) if callable(attr) else attr
                except (ValueError, RuntimeError) as e:  # the caller's to handle (a missing covariance, say)
                    results.put((_RAISED, (isinstance(e, ValueError), _one_line(e))))
                    continue
                results.put((_RESULT, out))
            elif kind == _STOP:
                return
    except BaseException as e:  # handed to the parent, which raises it
        results.put((_FAILED, _one_line(e)))


def _frozen(x: Any) -> Any:
    """A copy of a call's argument as it is now (arrays are sent later, by another thread)."""
    if isinstance(x, np.ndarray):
        return x.copy()
    if isinstance(x, (list, tuple)):
        return type(x)(_frozen(v) for v in x)
    if isinstance(x, dict):
        return {k: _frozen(v) for k, v in x.items()}
    return x


def _stop(proc: Any, calls: Any) -> None:
    """Stop the worker (at the proxy's end or the interpreter's exit)."""
    if proc.is_alive():
        try:
            calls.put((_STOP,))
        except (OSError, ValueError):
            pass
        proc.join(timeout=2.0)
        stop_children([proc])
    # what is still queued for a stopped worker is moot: the interpreter's exit must not wait for
    # the queue's feeder thread, blocked on a pipe that nobody reads any more
    calls.cancel_join_thread()


class BackendProcess:
    """The :class:`slam.backend.Backend` API over a worker process (see the module doc):
    ``config`` the back end's, ``knots`` the front end's mirror of the trajectory (read when a
    step's result arrives, for the correction of the knots added since), ``recent_knots`` how
    many of the newest knots a step's result carries."""

    def __init__(self, config: BackendConfig, knots: KnotMirror, recent_knots: int) -> None:
        self.config = config
        self._knots = knots
        self._recent = recent_knots
        self._ids: FactorIds | None = FactorIds(config)  # None once a synchronous call changed the graph
        self._calls_out: list[tuple[str, tuple[Any, ...], dict[str, Any], int | None]] = []
        self._outstanding = False  # a step sent whose result is not applied yet
        self._ready: StepResult | None = None  # its result, when it arrived during a synchronous call
        self._mirror: StepResult | None = None
        self._C = np.eye(4)  # the correction of the knots and planes added after the mirror's step
        # and of those knots' velocities: what the step changed in its last knot's velocity, beyond
        # the rotation of _C (the front end integrates the IMU on from that velocity)
        self._dv = np.zeros(3)
        self._planes_added: dict[int, tuple[FloatArray, float]] = {}  # since the mirror's step was sent
        self._planes_sent: dict[int, tuple[FloatArray, float]] = {}  # since the outstanding step was sent
        ctx = mp.get_context("fork")
        self._calls = ctx.Queue()
        self._results = ctx.Queue()
        self._proc = ctx.Process(target=_worker, args=(config, self._calls, self._results, os.getpid()),
                                 name="backpack-slam-backend", daemon=True)
        self._proc.start()
        self._finalizer = weakref.finalize(self, _stop, self._proc, self._calls)

    # ----------------------------------------------------------------- transport
    def _forward(self, name: str, args: tuple[Any, ...], kwargs: dict[str, Any] | None = None,
                 expect: int | None = None) -> None:
        self._calls_out.append((name, _frozen(args), _frozen(kwargs or {}), expect))
        if len(self._calls_out) >= _FLUSH_CALLS:
            self._flush()

    def _flush(self) -> None:
        if self._calls_out:
            self._calls.put((_CALLS, self._calls_out))
            self._calls_out = []

    def _receive(self) -> tuple[str, Any]:
        kind, payload = get_from_children(self._results, [self._proc], "the back-end process")
        if kind == _FAILED:
            raise RuntimeError(f"the back-end process failed: {payload}")
        return kind, payload

    def _sync(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call ``name`` on the worker's back end and wait for the answer (a step result that
        arrives first is kept for :meth:`step`/:meth:`collect`)."""
        self._flush()
        self._calls.put((_SYNC, (name, _frozen(args), _frozen(kwargs))))
        while True:
            kind, payload = self._receive()
            if isinstance(payload, StepResult):
                self._ready = payload
                continue
            if kind == _RAISED:
                is_value, text = payload
                raise (ValueError if is_value else RuntimeError)(text)
            return payload

    def _changed_remotely(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """A synchronous call that changes the graph in ways the counters do not follow: later
        id-returning calls wait for the worker's ids."""
        self._ids = None
        return self._sync(name, *args, **kwargs)

    def close(self) -> None:
        """Stop the worker process (also done when the proxy is collected, or at exit)."""
        self._finalizer()

    # ----------------------------------------------------------------- variables
    def add_pose(self, time: float, T_world_body: ArrayLike, velocity_world: ArrayLike | None = None) -> int:
        if self._ids is None:
            return int(self._changed_remotely("add_pose", time, T_world_body, velocity_world=velocity_world))
        i = self._ids.add_pose()
        self._forward("add_pose", (time, T_world_body), {"velocity_world": velocity_world}, i)
        return i

    def add_velocity_prior(self, knot: int, velocity_world: ArrayLike, sigma: float) -> None:
        if self._ids is not None:
            self._ids.one()
        self._forward("add_velocity_prior", (knot, velocity_world, sigma))

    def add_imu(self, knot: int, accel_imu: ArrayLike, gyro_imu: ArrayLike, dt: ArrayLike) -> None:
        if self._ids is not None:
            self._ids.one()
        self._forward("add_imu", (knot, accel_imu, gyro_imu, dt))

    def add_plane(self, plane_id: int, normal_world: ArrayLike, offset: float, horizontal: bool = False,
                  vertical: bool = False, anchor: ArrayLike | None = None) -> None:
        if self._ids is not None:
            self._ids.add_plane(plane_id, horizontal, vertical)
        n = np.asarray(normal_world, dtype=float).reshape(3)
        self._planes_sent[int(plane_id)] = (n / np.linalg.norm(n), float(offset))
        self._forward("add_plane", (plane_id, normal_world, offset),
                      {"horizontal": horizontal, "vertical": vertical, "anchor": anchor})

    # ----------------------------------------------------------------- observations, ties
    def _with_id(self, name: str, *args: Any) -> int:
        if self._ids is None:
            return int(self._changed_remotely(name, *args))
        fid = self._ids.one()
        self._forward(name, args, None, fid)
        return fid

    def add_observations(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
                         sigmas: ArrayLike) -> int:
        return self._with_id("add_observations", knot, plane_id, points, alphas, sigmas)

    def _tie(self, name: str, host_id: int, plane_id: int, sigma_angle: float) -> int:
        if self._ids is None:
            return int(self._changed_remotely(name, host_id, plane_id, sigma_angle))
        fid = self._ids.tie(host_id, plane_id, name == "add_perpendicular")
        self._forward(name, (host_id, plane_id, sigma_angle), None, fid)
        return fid

    def add_parallel(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        return self._tie("add_parallel", host_id, plane_id, sigma_angle)

    def add_perpendicular(self, host_id: int, plane_id: int, sigma_angle: float) -> int:
        return self._tie("add_perpendicular", host_id, plane_id, sigma_angle)

    def link_planes(self, keep_id: int, drop_id: int, sigma_angle: float, sigma_offset: float) -> int:
        if self._ids is None:
            return int(self._changed_remotely("link_planes", keep_id, drop_id, sigma_angle, sigma_offset))
        fid = self._ids.link(keep_id, drop_id)
        self._forward("link_planes", (keep_id, drop_id, sigma_angle, sigma_offset), None, fid)
        return fid

    def remove_plane(self, plane_id: int) -> None:
        self._planes_sent.pop(int(plane_id), None)
        if self._ids is not None:
            self._ids.remove_plane(plane_id)
        self._forward("remove_plane", (plane_id,))

    def remove_observations(self, block_id: int) -> None:
        self._forward("remove_observations", (block_id,))

    def merge_planes(self, keep_id: int, drop_id: int) -> int:
        return int(self._changed_remotely("merge_planes", keep_id, drop_id))

    def fold_links(self) -> dict[int, int]:
        out: dict[int, int] = self._changed_remotely("fold_links")
        return out

    def trim_observations(self, max_whitened: float, min_distance: float) -> tuple[int, int]:
        out: tuple[int, int] = self._changed_remotely("trim_observations", max_whitened, min_distance)
        return out

    # ----------------------------------------------------------------- solving
    def step(self) -> StepReport:
        """Apply the outstanding step's result (if any), send a new step, and return the applied
        step's report (not solved when there was none): the front end runs one update behind."""
        report = self.collect() if self._outstanding else StepReport(False, 0, 0)
        if self._ids is not None and self.config.fold_links_in_window and self._ids.links:
            self._ids.fold_links()  # as the worker's step will first (Backend.step)
        self._flush()
        self._calls.put((_STEP, max(0, self._knots.n - self._recent)))
        self._outstanding = True
        self._planes_sent = {}
        return report

    def collect(self) -> StepReport:
        """Wait for the outstanding step, put its result into the mirror, and return its report
        (not solved when no step is outstanding)."""
        if not self._outstanding:
            return StepReport(False, 0, 0)
        self._flush()
        res = self._ready
        while res is None:
            _, payload = self._receive()
            if isinstance(payload, StepResult):
                res = payload
        self._ready = None
        self._outstanding = False
        self._apply(res)
        return res.report

    def _apply(self, res: StepResult) -> None:
        """The mirror from step result ``res``, with the correction of the knots and planes the
        front end added since the step was sent."""
        k = res.n_knots - 1
        self._C = np.eye(4)
        self._dv = np.zeros(3)
        if 0 <= k < self._knots.n and res.n_knots > res.first:
            self._C = res.poses[k - res.first] @ np.linalg.inv(self._knots.T[k])
            if res.velocities is not None:
                self._dv = res.velocities[k - res.first] - self._C[:3, :3] @ self._knots.V[k]
        self._planes_added = dict(self._planes_sent)
        self._mirror = res

    def batch_optimize(self, max_iterations: int | None = None, graduated: bool = True,
                       kernel: RobustKernel | None = None) -> OptimizeSummary:
        out: OptimizeSummary = self._changed_remotely("batch_optimize", max_iterations, graduated, kernel)
        return out

    def error(self) -> float:
        return float(self._sync("error"))

    @property
    def singular_systems(self) -> list[str]:
        out: list[str] = self._sync("singular_systems")
        return out

    # ----------------------------------------------------------------- estimates (the mirror)
    def _need_mirror(self, what: str) -> StepResult:
        if self._mirror is None:
            raise RuntimeError(f"{what}: no back-end step has been applied yet")
        return self._mirror

    def pose(self, knot: int) -> FloatArray:
        """``T_world_body`` (4, 4) of a knot as of the last applied step (knots added since: the
        front end's, corrected)."""
        m = self._need_mirror("pose")
        k = int(knot)
        if k >= m.n_knots:
            out: FloatArray = self._C @ self._knots.T[k]
            return out
        if k < m.first:
            raise ValueError(f"knot: {k} is older than the knots a step brings back (from {m.first})")
        return m.poses[k - m.first].copy()

    def velocity(self, knot: int) -> FloatArray:
        """World velocity (3,) of a knot as of the last applied step; knots added since: the
        step's last velocity plus the front end's change since, rotated like the poses (see the
        module doc)."""
        m = self._need_mirror("velocity")
        k = int(knot)
        if m.velocities is None:
            raise ValueError("velocity: the back end was configured without an IMU (config.imu)")
        if k >= m.n_knots:
            out: FloatArray = self._C[:3, :3] @ self._knots.V[k] + self._dv
            return out
        if k < m.first:
            raise ValueError(f"knot: {k} is older than the knots a step brings back (from {m.first})")
        return m.velocities[k - m.first].copy()

    def bias(self, knot: int) -> FloatArray:
        """IMU bias (6,) as of the last applied step (its newest knot's, for any knot from there)."""
        m = self._need_mirror("bias")
        if m.bias is None:
            raise ValueError("bias: the back end was configured without an IMU (config.imu)")
        if int(knot) < m.n_knots - 1:
            raise ValueError(f"knot: {int(knot)} is older than the newest knot of the last applied step ({m.n_knots - 1})")
        return m.bias.copy()

    def plane(self, plane_id: int) -> tuple[FloatArray, float]:
        """Unit normal (3,) and offset of a plane (world) as of the last applied step; a plane
        added since: its initial values, corrected like the knots; a plane folded into another
        (``config.fold_links_in_window``): that plane's."""
        m = self._need_mirror("plane")
        j = int(plane_id)
        if j not in m.planes and j not in self._planes_added and self._ids is not None:
            j = self._ids.resolve(j)  # folded into another plane (config.fold_links_in_window)
        if j in m.planes:
            n, d = m.planes[j]
            return n.copy(), d
        if j not in self._planes_added:
            raise ValueError(f"plane_id: no plane {j}")
        n0, d0 = self._planes_added[j]
        R, t = self._C[:3, :3], self._C[:3, 3]
        n = R @ n0
        return n, float(d0 - n @ t)

    # ----------------------------------------------------------------- estimates (the worker's)
    @property
    def num_knots(self) -> int:
        return int(self._sync("num_knots")) if self._ids is None else self._ids.knots

    def knot_times(self) -> FloatArray:
        out: FloatArray = self._sync("knot_times")
        return out

    def poses(self) -> FloatArray:
        out: FloatArray = self._sync("poses")
        return out

    def velocities(self) -> FloatArray:
        out: FloatArray = self._sync("velocities")
        return out

    def plane_ids(self) -> list[int]:
        out: list[int] = self._sync("plane_ids")
        return out

    def planes(self) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        out: tuple[NDArray[np.int64], FloatArray, FloatArray] = self._sync("planes")
        return out

    def T_world_body(self, times: ArrayLike) -> FloatArray:
        out: FloatArray = self._sync("T_world_body", times)
        return out

    def pose_covariance(self, knot: int) -> FloatArray:
        out: FloatArray = self._sync("pose_covariance", knot)
        return out

    def plane_covariance(self, plane_id: int) -> FloatArray:
        out: FloatArray = self._sync("plane_covariance", plane_id)
        return out

    def plane_covariances(self, plane_ids: Sequence[int]) -> dict[int, FloatArray]:
        out: dict[int, FloatArray] = self._sync("plane_covariances", list(plane_ids))
        return out

    def release(self) -> None:
        self._sync("release")

    def residual_statistics(self) -> dict[str, float]:
        out: dict[str, float] = self._sync("residual_statistics")
        return out
