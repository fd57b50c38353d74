"""Small hostile inputs for the command line (issue 24): a case is a JSON-able *spec* (what to
break and how), drawn from a :class:`Chooser` (a seeded ``random.Random`` for long campaigns,
hypothesis' ``draw`` for the test suite), and built by :func:`build_case` into a folder of input
files plus the commands that take them.

Kinds of input (``KINDS``):

- ``bag``: a ROS1 or ROS2 recording of the materials' rig (three 271-beam scanners, /tf_static,
  /imu at 200 Hz, /ground_truth, a few seconds of the simulated ``demo`` world) rewritten with
  rosbags after message-level corruptions (:data:`BAG_MUTATIONS`): invalid ranges, beam counts
  that disagree with the angles, zero-beam scans, bad stamps, gaps, a scanner that stops or
  never starts, wrong message types, extra topics, broken IMU samples, a /tf_static that
  contradicts the rig, ...;
- ``bag_bytes``: the same recordings corrupted byte by byte (truncated, flipped bytes, a missing
  or broken ``metadata.yaml``, a wrong name);
- ``carmen``: CARMEN logs (FLASER / ROBOTLASER1 lines, plain or gzip) with broken lines;
- ``scanline``: ``.npz`` and ``.csv`` scanlines with wrong shapes, types and values;
- ``rig``: rig YAMLs with wrong types, non-finite extrinsics or sigmas, unknown models, ...;
- ``config``: SLAM config YAMLs with unknown segmenters and out-of-range parameters;
- ``cli``: hostile option values of the commands;
- ``run_dir``: a SLAM output folder and its ground truth corrupted, for ``evaluate`` and
  ``export``.

Materials (:func:`build_materials`) are made once per campaign: the rig, a ROS1 and a ROS2 bag
simulated with it, and a SLAM run of the ROS1 bag. The invariant every command must keep is in
``tests/fuzz_invariant.py``.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import gzip
import json
import math
import random
import shutil
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

T = TypeVar("T")

KINDS = ("bag", "bag_bytes", "carmen", "scanline", "rig", "config", "cli", "run_dir")
RIG_TOPICS = ("/scan_top", "/scan_left", "/scan_right")
N_BEAMS = 271
LASERSCAN = "sensor_msgs/msg/LaserScan"
MULTIECHO = "sensor_msgs/msg/MultiEchoLaserScan"
IMU = "sensor_msgs/msg/Imu"
CUSTOM = "fuzz_msgs/msg/Custom"
RUN_FILES = ("trajectory.tum", "planes.json", "segments.npz", "cloud.ply", "map.rrd", "summary.json")


# ---- choosers: where the randomness comes from ------------------------------------------------
class Chooser(ABC):
    """The choices a spec is drawn from; subclasses take them from a seeded RNG or hypothesis."""

    @abstractmethod
    def choice(self, options: Sequence[T]) -> T: ...

    @abstractmethod
    def uniform(self, lo: float, hi: float) -> float: ...

    @abstractmethod
    def integer(self, lo: int, hi: int) -> int:
        """An integer in [lo, hi]."""

    def chance(self, p: float) -> bool:
        return self.uniform(0.0, 1.0) < p

    def subset(self, options: Sequence[T], min_size: int = 1) -> list[T]:
        k = self.integer(min_size, len(options))
        pool = list(options)
        out = []
        for _ in range(k):
            out.append(pool.pop(self.integer(0, len(pool) - 1)))
        return sorted(out, key=list(options).index)


class RandomChooser(Chooser):
    """Choices from ``random.Random(seed)``: a plain seeded loop for long campaigns."""

    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)

    def choice(self, options: Sequence[T]) -> T:
        return options[self.rng.randrange(len(options))]

    def uniform(self, lo: float, hi: float) -> float:
        return self.rng.uniform(lo, hi)

    def integer(self, lo: int, hi: int) -> int:
        return self.rng.randint(lo, hi)


class DrawChooser(Chooser):
    """Choices drawn by hypothesis (``st.data()``'s ``draw``), which shrinks them."""

    def __init__(self, draw: Callable[[Any], Any]) -> None:
        from hypothesis import strategies as st

        self.draw = draw
        self.st = st

    def choice(self, options: Sequence[T]) -> T:
        return self.draw(self.st.sampled_from(list(options)))  # type: ignore[no-any-return]

    def uniform(self, lo: float, hi: float) -> float:
        return float(self.draw(self.st.floats(lo, hi, allow_nan=False, allow_infinity=False)))

    def integer(self, lo: int, hi: int) -> int:
        return int(self.draw(self.st.integers(lo, hi)))

    def chance(self, p: float) -> bool:
        return bool(self.draw(self.st.booleans())) if 0 < p < 1 else p >= 1


# ---- hostile values ----------------------------------------------------------------------------
HOSTILE_NUMBERS: tuple[Any, ...] = (float("nan"), float("inf"), float("-inf"), -1.0, 0.0, -1e-9, 1e300, 1e-300,
                                    2**63, -(2**31))
HOSTILE_OTHERS: tuple[Any, ...] = ("abc", "", [], {}, None, True, [1.0, 2.0], {"a": 1}, "1e9999", "nan")


def hostile_value(ch: Chooser) -> Any:
    return ch.choice(HOSTILE_NUMBERS) if ch.chance(0.6) else ch.choice(HOSTILE_OTHERS)


# ---- materials ---------------------------------------------------------------------------------
@dataclass
class Materials:
    """What every case is made from: the rig YAML, a ROS1 and a ROS2 bag simulated with it (and
    their ground truth), a SLAM run folder of the ROS1 bag."""

    root: Path
    rig: Path
    bags: dict[str, Path]
    gt: Path
    run: Path

    @property
    def rig_dict(self) -> dict[str, Any]:
        return yaml.safe_load(self.rig.read_text())  # type: ignore[no-any-return]


def small_rig() -> dict[str, Any]:
    """The itc_backpack geometry with 271-beam scanners (1 deg steps): small, quick inputs."""
    model = {"name": "small", "n_beams": N_BEAMS, "angle_min": -math.radians(135.0), "angle_increment": math.radians(1.0),
             "scan_period": 0.025, "time_increment": 0.025 / 360.0, "range_min": 0.1, "range_max": 30.0,
             "range_sigma": 0.003}
    return {"name": "small", "reference": "top", "scanners": [
        {"name": "top", "topic": "/scan_top", "model": dict(model)},
        {"name": "left", "topic": "/scan_left", "model": dict(model),
         "T_body_scanner": {"translation": [-0.05, 0.25, -0.20], "rpy": [1.2217304763960306, 0.0, 0.7853981633974483]}},
        {"name": "right", "topic": "/scan_right", "model": dict(model),
         "T_body_scanner": {"translation": [-0.05, -0.25, -0.20], "rpy": [1.9198621771937625, 0.0, -0.7853981633974483]}},
    ]}


def build_materials(root: str | Path, duration: float = 3.0) -> Materials:
    """Make (or reuse) the materials in ``root``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rig = root / "rig.yaml"
    bags = {"ros1": root / "base.bag", "ros2": root / "base2"}
    gt = root / "base.gt"
    run = root / "run"
    done = root / "done.json"
    key = {"duration": duration, "version": 1}
    if done.is_file() and json.loads(done.read_text()) == key:
        return Materials(root, rig, bags, gt, run)
    from common.rig import Rig
    from simulation.run import simulate
    from slam.config import SlamConfig
    from slam.run import run_slam

    rig.write_text(yaml.safe_dump(small_rig(), sort_keys=False))
    rig_obj = Rig.model_validate(small_rig())
    simulate("demo", rig_obj, duration=duration, seed=0, out=bags["ros1"], fmt="ros1", imu=True, progress=False)
    simulate("demo", rig_obj, duration=duration, seed=0, out=root / "base2.bag", fmt="ros2", imu=True, progress=False)
    run_slam(bags["ros1"], rig_obj, SlamConfig(), run, progress=False)
    done.write_text(json.dumps(key))
    return Materials(root, rig, bags, gt, run)


# ---- cases -------------------------------------------------------------------------------------
@dataclass
class Output:
    """An output a command writes: a file or a folder (with the files it must hold when complete),
    and how to check a complete one (``json``, ``rig``, ``yaml``, ``run``, or None: exists)."""

    path: Path
    folder: bool = False
    required: tuple[str, ...] = ()
    check: str | None = None


@dataclass
class Command:
    """One command over a case's inputs: its argv (after ``backpack-slam``), what it writes, the
    strings an error line must name one of, whether the inputs hold no usable data (exit 0 then
    breaks the invariant), and an optional signal (name, delay s, to the process group)."""

    name: str
    argv: list[str]
    outputs: list[Output] = field(default_factory=list)
    culprits: list[str] = field(default_factory=list)
    no_usable_data: bool = False
    signal: tuple[str, float, bool] | None = None
    timeout: float = 180.0


@dataclass
class Case:
    spec: dict[str, Any]
    folder: Path
    commands: list[Command]


def draw_spec(ch: Chooser, kind: str | None = None) -> dict[str, Any]:
    """A case's spec: its kind, the corruptions and the commands, drawn from ``ch``."""
    kind = kind or ch.choice(KINDS)
    spec: dict[str, Any] = {"kind": kind, "seed": ch.integer(0, 2**31 - 1)}
    spec.update(SPEC_DRAWERS[kind](ch))
    return spec


def build_case(spec: dict[str, Any], materials: Materials, folder: str | Path) -> Case:
    """The input files of ``spec`` written in ``folder/in`` and the commands over them (outputs
    in ``folder/out``)."""
    folder = Path(folder)
    (folder / "in").mkdir(parents=True, exist_ok=True)
    (folder / "out").mkdir(parents=True, exist_ok=True)
    (folder / "spec.json").write_text(json.dumps(spec, indent=1))
    return Case(spec, folder, CASE_BUILDERS[spec["kind"]](spec, materials, folder))


# ---- commands ---------------------------------------------------------------------------------
def run_command(bag: Path, rig: Path | None, folder: Path, culprits: list[str], extra: Sequence[str] = (),
                no_usable: bool = False, signal: Any = None, config: Path | None = None) -> Command:
    out = folder / "out" / "run"
    argv = ["run", str(bag), "--out", str(out), "--quiet", *extra]
    if rig is not None:
        argv += ["--rig", str(rig)]
    if config is not None:
        argv += ["--config", str(config)]
    sig = tuple(signal) if signal else None
    return Command("run", argv, [Output(out, folder=True, required=("trajectory.tum", "planes.json", "segments.npz",
                                                                      "summary.json"), check="run")],
                   culprits, no_usable, sig)  # type: ignore[arg-type]


def segment_command(path: Path, folder: Path, culprits: list[str], extra: Sequence[str] = (),
                    no_usable: bool = False, plot: bool = False) -> Command:
    js = folder / "out" / "segments.json"
    argv = ["segment", str(path), "--scan", "all", "--json", str(js), *extra]
    outputs = [Output(js, check="json")]
    if plot:
        png = folder / "out" / "segments.png"
        argv += ["--plot", str(png)]
        outputs.append(Output(png))
    return Command("segment", argv, outputs, culprits, no_usable)


def rig_command(bag: Path, folder: Path, culprits: list[str]) -> Command:
    out = folder / "out" / "built_rig.yaml"
    return Command("rig", ["rig", str(bag), "--out", str(out)], [Output(out, check="rig")], culprits)


def rig_check_command(rig: Path, folder: Path, culprits: list[str]) -> Command:
    out = folder / "out" / "checked_rig.yaml"
    return Command("rig", ["rig", "--check", str(rig), "--out", str(out)], [Output(out, check="rig")], culprits)


def calibrate_command(bag: Path, rig: Path, folder: Path, culprits: list[str], extra: Sequence[str] = (),
                      no_usable: bool = False, config: Path | None = None) -> Command:
    out = folder / "out" / "calibrated.yaml"
    argv = ["calibrate", str(bag), "--rig", str(rig), "--out", str(out), "--rounds", "1", "--quiet", *extra]
    if config is not None:
        argv += ["--config", str(config)]
    return Command("calibrate", argv, [Output(out, check="rig")], culprits, no_usable, timeout=300.0)


def _bag_commands(spec: dict[str, Any], bag: Path, materials: Materials, folder: Path, culprits: list[str],
                  no_usable: bool) -> list[Command]:
    cmds = []
    for name in spec["commands"]:
        if name == "run":
            rig = materials.rig if spec.get("with_rig", True) else None
            cmds.append(run_command(bag, rig, folder, culprits, no_usable=no_usable, signal=spec.get("signal")))
        elif name == "segment":
            cmds.append(segment_command(bag, folder, culprits, no_usable=no_usable))
        elif name == "rig":
            cmds.append(rig_command(bag, folder, culprits))
        elif name == "calibrate":
            cmds.append(calibrate_command(bag, materials.rig, folder, culprits, no_usable=no_usable))
    return cmds


def _draw_commands(ch: Chooser, first: str, *more: tuple[str, float]) -> list[str]:
    """``first``, then each of ``more`` (command, chance) drawn in order."""
    return [first] + [name for name, p in more if ch.chance(p)]


def _draw_bag_commands(ch: Chooser) -> dict[str, Any]:
    cmds = _draw_commands(ch, "run", ("segment", 0.5), ("rig", 0.25), ("calibrate", 0.08))
    out: dict[str, Any] = {"commands": cmds, "with_rig": ch.chance(0.85)}
    if ch.chance(0.08):
        out["signal"] = [ch.choice(("TERM", "INT")), round(ch.uniform(0.5, 8.0), 2), ch.chance(0.5)]
    return out


# ---- bags: reading the materials, writing rosbags ------------------------------------------------
@dataclass
class Item:
    """One message of a bag: topic, type, log time (ns), and its raw bytes or its object."""

    topic: str
    msgtype: str
    log_ns: int
    raw: bytes | None = None
    obj: Any = None


class BagMessages:
    """A bag's messages in the format ``fmt`` (ros1/ros2), deserialised when touched."""

    def __init__(self, fmt: str, items: list[Item], latched: set[str]) -> None:
        from simulation.bag import typestore_for

        self.fmt = fmt
        self.ts = typestore_for(fmt)
        self.items = items
        self.latched = latched
        self.silent: dict[str, str] = {}  # topic -> type of connections written without messages

    @classmethod
    def read(cls, path: Path, fmt: str) -> BagMessages:
        from rosbags.highlevel import AnyReader

        items: list[Item] = []
        latched: set[str] = set()
        with AnyReader([path]) as r:
            for c in r.connections:
                if getattr(c.ext, "latching", None):
                    latched.add(c.topic)
            for conn, t_ns, raw in r.messages():
                items.append(Item(conn.topic, conn.msgtype, int(t_ns), raw=bytes(raw)))
        return cls(fmt, items, latched)

    def msg(self, item: Item) -> Any:
        if item.obj is None:
            assert item.raw is not None
            de = self.ts.deserialize_ros1 if self.fmt == "ros1" else self.ts.deserialize_cdr
            item.obj = de(item.raw, item.msgtype)
            item.raw = None
        return item.obj

    def set(self, item: Item, obj: Any) -> None:
        item.obj = obj
        item.raw = None

    def of(self, topics: Sequence[str] | str, msgtype: str | None = None) -> list[Item]:
        tt = (topics,) if isinstance(topics, str) else tuple(topics)
        return [i for i in self.items if i.topic in tt and (msgtype is None or i.msgtype == msgtype)]

    def new(self, msgtype: str, **kw: Any) -> Any:
        return self.ts.types[msgtype](**kw)

    def header(self, stamp_ns: int, frame: str, seq: int = 0) -> Any:
        stamp = self.new("builtin_interfaces/msg/Time", sec=int(stamp_ns // 1_000_000_000),
                         nanosec=int(stamp_ns % 1_000_000_000))
        if self.fmt == "ros1":
            return self.new("std_msgs/msg/Header", seq=seq, stamp=stamp, frame_id=frame)
        return self.new("std_msgs/msg/Header", stamp=stamp, frame_id=frame)

    def write(self, path: Path) -> None:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import Writer as Writer2

        ser = self.ts.serialize_ros1 if self.fmt == "ros1" else self.ts.serialize_cdr
        writer: Any = Writer1(path) if self.fmt == "ros1" else Writer2(path, version=8)
        with writer as w:
            conns: dict[tuple[str, str], Any] = {}
            for item in self.items:
                key = (item.topic, item.msgtype)
                if key not in conns:
                    kw: dict[str, Any] = {"typestore": self.ts}
                    if self.fmt == "ros1" and item.topic in self.latched:
                        kw["latching"] = 1
                    conns[key] = w.add_connection(item.topic, item.msgtype, **kw)
            for topic, msgtype in self.silent.items():
                if (topic, msgtype) not in conns:
                    conns[(topic, msgtype)] = w.add_connection(topic, msgtype, typestore=self.ts)
            for item in sorted(self.items, key=lambda i: i.log_ns):
                data = item.raw if item.obj is None else ser(item.obj, item.msgtype)
                w.write(conns[(item.topic, item.msgtype)], max(int(item.log_ns), 1), data)


def _replace(obj: Any, **kw: Any) -> Any:
    return dataclasses.replace(obj, **kw)


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _with_stamp(bm: BagMessages, msg: Any, stamp_ns: int) -> Any:
    stamp_ns = int(min(max(stamp_ns, 0), (2**31 - 1) * 1_000_000_000))
    seq = getattr(msg.header, "seq", 0)
    return _replace(msg, header=bm.header(stamp_ns, msg.header.frame_id, seq))


def _pick(items: list[Item], fraction: float, rng: random.Random) -> list[Item]:
    """A ``fraction`` of ``items`` (at least one when fraction > 0)."""
    if fraction <= 0 or not items:
        return []
    k = max(1, round(fraction * len(items)))
    return rng.sample(items, min(k, len(items)))


INVALID_RANGE_VALUES = ("nan", "inf", "-inf", "zero", "negative", "beyond_max", "below_min", "mixed")


def _invalid(kind: str, n: int, range_max: float, range_min: float, rng: np.random.Generator) -> np.ndarray:
    if kind == "mixed":
        kinds = [k for k in INVALID_RANGE_VALUES if k != "mixed"]
        return np.array([_invalid(kinds[int(rng.integers(len(kinds)))], 1, range_max, range_min, rng)[0]
                         for _ in range(n)], dtype=np.float32)
    value = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf, "zero": 0.0, "negative": -1.5,
             "beyond_max": range_max * 2 + 1.0, "below_min": range_min * 0.5}[kind]
    return np.full(n, value, dtype=np.float32)


def mutate_ranges_invalid(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    nrng = np.random.default_rng(rng.randrange(2**32))
    for item in _pick(bm.of(p["topics"], LASERSCAN), p["scan_fraction"], rng):
        m = bm.msg(item)
        r = np.array(m.ranges, dtype=np.float32)
        idx = nrng.permutation(r.size)[: max(1, round(p["beam_fraction"] * r.size))] if r.size else []
        r[idx] = _invalid(p["value"], len(idx), float(m.range_max), float(m.range_min), nrng)
        bm.set(item, _replace(m, ranges=r))


def mutate_beam_count(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    for item in _pick(bm.of(p["topics"], LASERSCAN), p["scan_fraction"], rng):
        m = bm.msg(item)
        r = np.array(m.ranges, dtype=np.float32)
        how = p["how"]
        if how == "short":
            m = _replace(m, ranges=r[: max(0, r.size - p["delta"])])
        elif how == "long":
            m = _replace(m, ranges=np.concatenate([r, np.full(p["delta"], 3.0, dtype=np.float32)]))
        elif how == "angle_max":
            m = _replace(m, angle_max=float(m.angle_max) + p["delta"] * 0.1)
        elif how == "increment_zero":
            m = _replace(m, angle_increment=0.0)
        elif how == "increment_negative":
            m = _replace(m, angle_increment=-float(m.angle_increment))
        elif how == "increment_nan":
            m = _replace(m, angle_increment=float("nan"))
        elif how == "angle_min_nan":
            m = _replace(m, angle_min=float("nan"))
        elif how == "angle_huge":
            m = _replace(m, angle_min=1e30, angle_max=1e30 + 1)
        elif how == "increment_huge":
            m = _replace(m, angle_increment=1e6)
        bm.set(item, m)


def mutate_zero_beams(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    for item in _pick(bm.of(p["topics"], LASERSCAN), p["scan_fraction"], rng):
        m = bm.msg(item)
        bm.set(item, _replace(m, ranges=np.zeros(0, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32)))


def mutate_stamps(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    items = sorted(bm.of(p["topics"]), key=lambda i: i.log_ns)
    items = [i for i in items if i.msgtype != "tf2_msgs/msg/TFMessage" and hasattr(bm.msg(i), "header")]
    chosen = _pick(items, p["fraction"], rng)
    prev: dict[str, int] = {}
    order = {id(i): k for k, i in enumerate(items)}
    for item in sorted(chosen, key=lambda i: order[id(i)]):
        m = bm.msg(item)
        s = _stamp_ns(m.header)
        how = p["how"]
        if how == "duplicate":
            k = order[id(item)]
            same = [i for i in items[:k] if i.topic == item.topic]
            new = _stamp_ns(bm.msg(same[-1]).header) if same else s
        elif how == "backwards":
            new = s - int(p["seconds"] * 1e9)
        elif how == "far_future":
            new = s + int(p["seconds"] * 1e9) * 1000
        elif how == "zero":
            new = 0
        elif how == "jitter":
            new = s + int(rng.uniform(-1, 1) * p["seconds"] * 1e9)
        else:
            new = s
        prev[item.topic] = new
        bm.set(item, _with_stamp(bm, m, new))
        if p.get("log_too"):
            item.log_ns = max(new, 1)


def mutate_gap(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    """Every message after ``at`` (fraction of the recording) of ``topics`` later by ``seconds``."""
    t0 = min(i.log_ns for i in bm.items)
    t1 = max(i.log_ns for i in bm.items)
    cut = t0 + p["at"] * (t1 - t0)
    shift = int(p["seconds"] * 1e9)
    for item in bm.of(p["topics"]):
        if item.log_ns > cut and item.topic != "/tf_static":
            m = bm.msg(item)
            item.log_ns += shift
            if hasattr(m, "header"):
                bm.set(item, _with_stamp(bm, m, _stamp_ns(m.header) + shift))


def mutate_topic_stops(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    """A topic's messages after ``at`` (fraction of the recording) dropped; ``at`` 0: it never
    starts (with ``keep_connection`` its connection is still in the bag, without messages)."""
    t0 = min(i.log_ns for i in bm.items)
    t1 = max(i.log_ns for i in bm.items)
    cut = t0 + p["at"] * (t1 - t0)
    if p.get("keep_connection"):
        bm.silent.update({i.topic: i.msgtype for i in bm.items if i.topic in p["topics"]})
    bm.items = [i for i in bm.items if not (i.topic in p["topics"] and i.log_ns >= cut)]


def mutate_wrong_type(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    """A topic's messages replaced by messages of another type (all, or alongside: two types on
    one topic)."""
    target = p["type"]
    new: list[Item] = []
    for item in bm.of(p["topic"]):
        m = bm.msg(item)
        s = _stamp_ns(m.header) if hasattr(m, "header") else item.log_ns
        if target == "std_msgs/msg/String":
            obj = bm.new(target, data="not a scan")
        elif target == IMU:
            obj = _imu_msg(bm, s, m.header.frame_id if hasattr(m, "header") else "x")
        elif target == "geometry_msgs/msg/PoseStamped":
            obj = bm.new(target, header=bm.header(s, "world"), pose=bm.new(
                "geometry_msgs/msg/Pose", position=bm.new("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                orientation=bm.new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)))
        else:  # a LaserScan on a non-scan topic
            obj = _scan_msg(bm, s, "x", np.full(N_BEAMS, 2.0, dtype=np.float32))
        new.append(Item(item.topic, target, item.log_ns, obj=obj))
    if p["alongside"]:
        bm.items += new
    else:
        bm.items = [i for i in bm.items if i.topic != p["topic"]] + new


def _imu_msg(bm: BagMessages, stamp_ns: int, frame: str, w: tuple[float, float, float] = (0.0, 0.0, 0.0),
             a: tuple[float, float, float] = (0.0, 0.0, 9.81)) -> Any:
    V = "geometry_msgs/msg/Vector3"
    return bm.new(IMU, header=bm.header(stamp_ns, frame),
                  orientation=bm.new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
                  orientation_covariance=np.array([-1.0] + [0.0] * 8), angular_velocity=bm.new(V, x=w[0], y=w[1], z=w[2]),
                  angular_velocity_covariance=np.zeros(9), linear_acceleration=bm.new(V, x=a[0], y=a[1], z=a[2]),
                  linear_acceleration_covariance=np.zeros(9))


def _scan_msg(bm: BagMessages, stamp_ns: int, frame: str, ranges: np.ndarray) -> Any:
    n = ranges.size
    return bm.new(LASERSCAN, header=bm.header(stamp_ns, frame), angle_min=-math.radians(135.0),
                  angle_max=-math.radians(135.0) + (n - 1) * math.radians(1.0), angle_increment=math.radians(1.0),
                  time_increment=0.025 / 360.0, scan_time=0.025, range_min=0.1, range_max=30.0, ranges=ranges,
                  intensities=np.zeros(0, dtype=np.float32))


def mutate_extra_topics(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    t0 = min(i.log_ns for i in bm.items)
    for k in range(p["count"]):
        t = t0 + k * 50_000_000
        what = p["what"]
        if what == "string":
            bm.items.append(Item("/chatter", "std_msgs/msg/String", t, obj=bm.new("std_msgs/msg/String", data="x" * k)))
        elif what == "scan":
            bm.items.append(Item("/scan_extra", LASERSCAN, t, obj=_scan_msg(
                bm, t, "extra", np.full(N_BEAMS, 1.0 + k * 0.01, dtype=np.float32))))
        elif what == "imu":
            bm.items.append(Item("/imu2", IMU, t, obj=_imu_msg(bm, t, "body")))
        elif what == "custom":  # a type the readers' typestore does not know
            from rosbags.typesys import get_types_from_msg

            if CUSTOM not in bm.ts.types:
                bm.ts.register(get_types_from_msg("int32 a\nstring b\nfloat64[] c", CUSTOM))
            bm.items.append(Item("/custom", CUSTOM, t, obj=bm.new(CUSTOM, a=k, b="x", c=np.arange(k, dtype=np.float64))))
        elif what == "tf":
            bm.items.append(Item("/tf", "tf2_msgs/msg/TFMessage", t, obj=_tf_msg(bm, t, [("odom", "body", (k * 0.1, 0, 0), (0, 0, 0, 1))])))


def mutate_imu(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    items = bm.of("/imu", IMU)
    for item in _pick(items, p["fraction"], rng):
        m = bm.msg(item)
        how = p["how"]
        V = "geometry_msgs/msg/Vector3"
        if how in ("nan", "inf", "absurd", "zero"):
            v = {"nan": float("nan"), "inf": float("inf"), "absurd": 1e9, "zero": 0.0}[how]
            m = _replace(m, angular_velocity=bm.new(V, x=v, y=v, z=v), linear_acceleration=bm.new(V, x=v, y=0.0, z=v))
        elif how == "frame":
            m = _replace(m, header=_replace(m.header, frame_id="somewhere_else"))
        elif how == "backwards":
            m = _with_stamp(bm, m, _stamp_ns(m.header) - int(0.5e9))
        elif how == "duplicate":
            m = _with_stamp(bm, m, (_stamp_ns(m.header) // 1_000_000_000) * 1_000_000_000)
        elif how == "orientation_zero":
            m = _replace(m, orientation=bm.new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=0.0))
        bm.set(item, m)
    if p["how"] == "drop_half":
        keep = set(map(id, items[: len(items) // 2]))
        bm.items = [i for i in bm.items if i.topic != "/imu" or id(i) in keep]
    if p["how"] == "drop":
        bm.items = [i for i in bm.items if i.topic != "/imu"]


def _tf_msg(bm: BagMessages, stamp_ns: int, tfs: list[tuple[str, str, Any, Any]]) -> Any:
    out = []
    for parent, child, t, q in tfs:
        out.append(bm.new(
            "geometry_msgs/msg/TransformStamped", header=bm.header(stamp_ns, parent), child_frame_id=child,
            transform=bm.new("geometry_msgs/msg/Transform",
                             translation=bm.new("geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]), z=float(t[2])),
                             rotation=bm.new("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                             w=float(q[3])))))
    return bm.new("tf2_msgs/msg/TFMessage", transforms=out)


def mutate_tf_static(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    from scipy.spatial.transform import Rotation

    items = bm.of("/tf_static")
    if not items:
        return
    item = items[0]
    m = bm.msg(item)
    tfs = list(m.transforms)
    how = p["how"]
    k = p["index"] % max(len(tfs), 1)
    if how == "drop":
        bm.items = [i for i in bm.items if i.topic != "/tf_static"]
        return
    if not tfs:
        return
    tf = tfs[k]
    tr, q = tf.transform.translation, tf.transform.rotation
    Vec = "geometry_msgs/msg/Vector3"
    Quat = "geometry_msgs/msg/Quaternion"
    if how == "shift":
        tr = bm.new(Vec, x=tr.x + p["amount"], y=tr.y, z=tr.z)
    elif how == "rotate":
        r = Rotation.from_quat([q.x, q.y, q.z, q.w]) * Rotation.from_euler("z", p["amount"] * 30, degrees=True)
        x, y, z, w = r.as_quat()
        q = bm.new(Quat, x=float(x), y=float(y), z=float(z), w=float(w))
    elif how == "nan":
        tr = bm.new(Vec, x=float("nan"), y=tr.y, z=tr.z)
    elif how == "zero_quat":
        q = bm.new(Quat, x=0.0, y=0.0, z=0.0, w=0.0)
    elif how == "unnormalised":
        q = bm.new(Quat, x=q.x * 7, y=q.y * 7, z=q.z * 7, w=q.w * 7)
    elif how == "nan_quat":
        q = bm.new(Quat, x=float("nan"), y=q.y, z=q.z, w=q.w)
    elif how == "missing_scanner":
        tfs.pop(k)
    elif how == "cycle":
        tfs.append(_tf_msg(bm, 0, [(tf.child_frame_id, tf.header.frame_id, (0, 0, 0), (0, 0, 0, 1))]).transforms[0])
    elif how == "rename_parent":
        tfs[k] = _replace(tf, header=_replace(tf.header, frame_id="elsewhere"))
    elif how == "contradicting_twice":
        extra = _replace(tf, transform=_replace(tf.transform, translation=bm.new(Vec, x=tr.x + 1.0, y=tr.y, z=tr.z)))
        tfs.append(extra)
    elif how == "self_loop":
        tfs.append(_replace(tf, child_frame_id=tf.header.frame_id))
    if how in ("shift", "rotate", "nan", "zero_quat", "unnormalised", "nan_quat"):
        tfs[k] = _replace(tf, transform=bm.new("geometry_msgs/msg/Transform", translation=tr, rotation=q))
    bm.set(item, _replace(m, transforms=tfs))


def mutate_range_limits(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    for item in _pick(bm.of(p["topics"], LASERSCAN), p["scan_fraction"], rng):
        m = bm.msg(item)
        how = p["how"]
        if how == "swapped":
            m = _replace(m, range_min=float(m.range_max), range_max=float(m.range_min))
        elif how == "max_zero":
            m = _replace(m, range_max=0.0)
        elif how == "max_nan":
            m = _replace(m, range_max=float("nan"))
        elif how == "min_negative":
            m = _replace(m, range_min=-5.0)
        elif how == "min_nan":
            m = _replace(m, range_min=float("nan"))
        elif how == "max_inf":
            m = _replace(m, range_max=float("inf"))
        bm.set(item, m)


def mutate_time_increment(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    v = {"nan": float("nan"), "negative": -1e-4, "huge": 1.0, "zero": 0.0, "inf": float("inf")}[p["value"]]
    for item in _pick(bm.of(p["topics"], LASERSCAN), p["scan_fraction"], rng):
        bm.set(item, _replace(bm.msg(item), time_increment=v))


def mutate_frame_id(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    for item in bm.of(p["topics"], LASERSCAN):
        m = bm.msg(item)
        frame = {"empty": "", "same": "laser", "unknown": "nowhere", "weird": "../\x01 é"}[p["how"]]
        bm.set(item, _replace(m, header=_replace(m.header, frame_id=frame)))


def mutate_multiecho(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    """A rig topic rewritten as MultiEchoLaserScan: 0-3 echoes per beam, intensities that may not match."""
    nrng = np.random.default_rng(rng.randrange(2**32))
    new = []
    for item in bm.of(p["topic"], LASERSCAN):
        m = bm.msg(item)
        echoes = []
        inten = []
        for r in np.asarray(m.ranges, dtype=np.float32):
            k = int(nrng.integers(0, p["max_echoes"] + 1))
            e = np.array([r] + [r + 0.5 * j for j in range(1, k)], dtype=np.float32)[:k]
            echoes.append(bm.new("sensor_msgs/msg/LaserEcho", echoes=e))
            kk = k if not p["mismatch"] else int(nrng.integers(0, 4))
            inten.append(bm.new("sensor_msgs/msg/LaserEcho", echoes=np.ones(kk, dtype=np.float32)))
        obj = bm.new(MULTIECHO, header=m.header, angle_min=m.angle_min, angle_max=m.angle_max,
                     angle_increment=m.angle_increment, time_increment=m.time_increment, scan_time=m.scan_time,
                     range_min=m.range_min, range_max=m.range_max, ranges=echoes,
                     intensities=inten if p["intensities"] else [])
        new.append(Item(item.topic, MULTIECHO, item.log_ns, obj=obj))
    bm.items = [i for i in bm.items if not (i.topic == p["topic"] and i.msgtype == LASERSCAN)] + new


def mutate_log_order(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    """Log times of a topic moved by ``seconds`` (a recorder's clock off, or messages late)."""
    for item in bm.of(p["topics"]):
        if item.topic != "/tf_static":
            item.log_ns = max(1, item.log_ns + int(p["seconds"] * 1e9))


def mutate_duplicates(bm: BagMessages, p: dict[str, Any], rng: random.Random) -> None:
    for item in _pick(bm.of(p["topics"]), p["fraction"], rng):
        bm.items.append(Item(item.topic, item.msgtype, item.log_ns, raw=item.raw, obj=item.obj))


BAG_MUTATIONS: dict[str, Callable[[BagMessages, dict[str, Any], random.Random], None]] = {
    "ranges_invalid": mutate_ranges_invalid,
    "beam_count": mutate_beam_count,
    "zero_beams": mutate_zero_beams,
    "stamps": mutate_stamps,
    "gap": mutate_gap,
    "topic_stops": mutate_topic_stops,
    "wrong_type": mutate_wrong_type,
    "extra_topics": mutate_extra_topics,
    "imu": mutate_imu,
    "tf_static": mutate_tf_static,
    "range_limits": mutate_range_limits,
    "time_increment": mutate_time_increment,
    "frame_id": mutate_frame_id,
    "multiecho": mutate_multiecho,
    "log_order": mutate_log_order,
    "duplicates": mutate_duplicates,
}


def _fraction(ch: Chooser) -> float:
    return ch.choice((1.0, 1.0, round(ch.uniform(0.0, 1.0), 3), 0.01, 0.5))


def draw_bag_mutation(ch: Chooser, name: str | None = None) -> dict[str, Any]:
    name = name or ch.choice(tuple(BAG_MUTATIONS))
    topics = ch.subset(RIG_TOPICS)
    p: dict[str, Any] = {"name": name}
    if name == "ranges_invalid":
        p.update(topics=topics, scan_fraction=_fraction(ch), beam_fraction=_fraction(ch),
                 value=ch.choice(INVALID_RANGE_VALUES))
    elif name == "beam_count":
        p.update(topics=topics, scan_fraction=_fraction(ch), delta=ch.integer(1, N_BEAMS + 5),
                 how=ch.choice(("short", "long", "angle_max", "increment_zero", "increment_negative", "increment_nan",
                                "angle_min_nan", "angle_huge", "increment_huge")))
    elif name == "zero_beams":
        p.update(topics=topics, scan_fraction=_fraction(ch))
    elif name == "stamps":
        p.update(topics=ch.subset((*RIG_TOPICS, "/imu", "/ground_truth")), fraction=_fraction(ch),
                 how=ch.choice(("duplicate", "backwards", "far_future", "zero", "jitter")),
                 seconds=ch.choice((0.001, 0.5, 2.0, 30.0, 1e5)), log_too=ch.chance(0.3))
    elif name == "gap":
        p.update(topics=ch.choice((list(RIG_TOPICS), [*RIG_TOPICS, "/imu", "/ground_truth"], topics)),
                 at=round(ch.uniform(0.05, 0.95), 3), seconds=ch.choice((1.0, 2.5, 5.0, 20.0, 600.0)))
    elif name == "topic_stops":
        p.update(topics=ch.choice((topics, ["/imu"], list(RIG_TOPICS))), at=ch.choice((0.0, round(ch.uniform(0, 1), 3))),
                 keep_connection=ch.chance(0.5))
    elif name == "wrong_type":
        p.update(topic=ch.choice((*RIG_TOPICS, "/imu", "/tf_static")), alongside=ch.chance(0.3),
                 type=ch.choice(("std_msgs/msg/String", IMU, "geometry_msgs/msg/PoseStamped", LASERSCAN)))
    elif name == "extra_topics":
        p.update(what=ch.choice(("string", "scan", "imu", "tf", "custom")), count=ch.integer(1, 40))
    elif name == "imu":
        p.update(fraction=_fraction(ch), how=ch.choice(("nan", "inf", "absurd", "zero", "frame", "backwards",
                                                         "duplicate", "orientation_zero", "drop_half", "drop")))
    elif name == "tf_static":
        p.update(index=ch.integer(0, 2), amount=round(ch.uniform(-2, 2), 3),
                 how=ch.choice(("shift", "rotate", "nan", "zero_quat", "unnormalised", "nan_quat", "missing_scanner",
                                "cycle", "rename_parent", "contradicting_twice", "self_loop", "drop")))
    elif name == "range_limits":
        p.update(topics=topics, scan_fraction=_fraction(ch),
                 how=ch.choice(("swapped", "max_zero", "max_nan", "min_negative", "min_nan", "max_inf")))
    elif name == "time_increment":
        p.update(topics=topics, scan_fraction=_fraction(ch), value=ch.choice(("nan", "negative", "huge", "zero", "inf")))
    elif name == "frame_id":
        p.update(topics=topics, how=ch.choice(("empty", "same", "unknown", "weird")))
    elif name == "multiecho":
        p.update(topic=ch.choice(RIG_TOPICS), max_echoes=ch.integer(0, 3), mismatch=ch.chance(0.5),
                 intensities=ch.chance(0.5))
    elif name == "log_order":
        p.update(topics=ch.choice((topics, ["/imu"])), seconds=ch.choice((-5.0, -0.5, 0.3, 3.0, 1e4)))
    elif name == "duplicates":
        p.update(topics=ch.choice((topics, ["/imu"], ["/tf_static"])), fraction=_fraction(ch))
    return p


def draw_bag(ch: Chooser) -> dict[str, Any]:
    n = ch.choice((1, 1, 1, 2, 3))
    return {"fmt": ch.choice(("ros1", "ros2")), "mutations": [draw_bag_mutation(ch) for _ in range(n)],
            **_draw_bag_commands(ch)}


_BAG_CACHE: dict[tuple[str, str], BagMessages] = {}


def mutated_bag(materials: Materials, fmt: str, mutations: list[dict[str, Any]], seed: int) -> BagMessages:
    key = (str(materials.bags[fmt]), fmt)
    if key not in _BAG_CACHE:
        _BAG_CACHE[key] = BagMessages.read(materials.bags[fmt], fmt)
    base = _BAG_CACHE[key]
    bm = BagMessages(fmt, [Item(i.topic, i.msgtype, i.log_ns, i.raw, copy.deepcopy(i.obj)) for i in base.items],
                     set(base.latched))
    rng = random.Random(seed)
    for p in mutations:
        BAG_MUTATIONS[p["name"]](bm, p, rng)
    return bm


def usable_returns(bm: BagMessages, topics: Sequence[str] = RIG_TOPICS) -> int:
    """Valid returns on the rig's scan topics (finite, within the message's range limits, in a
    scan whose beam angles are finite)."""
    n = 0
    for item in bm.items:
        if item.topic not in topics or item.msgtype not in (LASERSCAN, MULTIECHO):
            continue
        m = bm.msg(item)
        if not (math.isfinite(m.angle_min) and math.isfinite(m.angle_increment)):
            continue
        if item.msgtype == MULTIECHO:
            r = np.array([e.echoes[0] if len(e.echoes) else np.inf for e in m.ranges], dtype=np.float64)
        else:
            r = np.asarray(m.ranges, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > 0) & (r >= m.range_min) & (r <= m.range_max)
        n += int(ok.sum())
    return n


def bag_path(folder: Path, fmt: str, name: str = "case") -> Path:
    return folder / "in" / (f"{name}.bag" if fmt == "ros1" else name)


def build_bag(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    bm = mutated_bag(materials, spec["fmt"], spec["mutations"], spec["seed"])
    path = bag_path(folder, spec["fmt"])
    bm.write(path)
    no_usable = usable_returns(bm) == 0
    return _bag_commands(spec, path, materials, folder, [path.name], no_usable)


# ---- bags: byte-level corruption ----------------------------------------------------------------
def draw_bag_bytes(ch: Chooser) -> dict[str, Any]:
    fmt = ch.choice(("ros1", "ros2"))
    hows = ["truncate", "flip", "zero_block", "append_garbage", "empty", "wrong_suffix"]
    if fmt == "ros2":
        hows += ["no_metadata", "metadata_garbage", "metadata_truncated", "no_storage", "metadata_count",
                 "bag_suffix_dir"]
    return {"fmt": fmt, "how": ch.choice(hows), "at": round(ch.uniform(0.0, 1.0), 4), "count": ch.integer(1, 64),
            **_draw_bag_commands(ch)}


def build_bag_bytes(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    fmt, how = spec["fmt"], spec["how"]
    rng = random.Random(spec["seed"])
    path = bag_path(folder, fmt)
    src = materials.bags[fmt]
    if fmt == "ros1":
        shutil.copyfile(src, path)
        target = path
    else:
        shutil.copytree(src, path)
        target = next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    data = bytearray(target.read_bytes())
    if how == "truncate":
        target.write_bytes(bytes(data[: int(spec["at"] * len(data))]))
    elif how == "flip":
        lo = int(spec["at"] * len(data))
        for _ in range(spec["count"]):
            k = rng.randrange(lo, len(data)) if lo < len(data) else len(data) - 1
            data[k] ^= 1 << rng.randrange(8)
        target.write_bytes(bytes(data))
    elif how == "zero_block":
        lo = int(spec["at"] * len(data))
        data[lo: lo + 64 * spec["count"]] = bytes(len(data[lo: lo + 64 * spec["count"]]))
        target.write_bytes(bytes(data))
    elif how == "append_garbage":
        target.write_bytes(bytes(data) + bytes(rng.randrange(256) for _ in range(97 * spec["count"])))
    elif how == "empty":
        target.write_bytes(b"")
    elif how == "wrong_suffix":
        if fmt == "ros1":
            new = path.with_suffix(".dat")
            path.rename(new)
            path = new
        else:
            target.rename(target.with_suffix(".sqlite"))
    elif how == "no_metadata":
        (path / "metadata.yaml").unlink()
    elif how == "metadata_garbage":
        (path / "metadata.yaml").write_text(rng.choice(("{{{", "- 1\n- 2\n", "rosbag2_bagfile_information: 7\n",
                                                        "\x00\x01binary", "")))
    elif how == "metadata_truncated":
        text = (path / "metadata.yaml").read_text()
        (path / "metadata.yaml").write_text(text[: int(spec["at"] * len(text))])
    elif how == "no_storage":
        target.unlink()
    elif how == "metadata_count":
        text = (path / "metadata.yaml").read_text()
        (path / "metadata.yaml").write_text(text.replace("message_count: ", "message_count: 9"))
    elif how == "bag_suffix_dir":
        new = path.with_name("case.bag")
        path.rename(new)
        path = new
    no_usable = how in ("empty", "no_storage")
    return _bag_commands(spec, path, materials, folder, [path.name], no_usable)


# ---- CARMEN logs ---------------------------------------------------------------------------------
def _room_ranges(n: int, x: float, y: float, theta: float, fov: float = math.pi, start: float = -math.pi / 2) -> list[float]:
    """Ranges of a 6 x 4 m room (corners (0, 0) and (6, 4)) seen from (x, y, theta)."""
    out = []
    for i in range(n):
        a = theta + start + i * fov / n
        c, s = math.cos(a), math.sin(a)
        ts = []
        if c > 1e-9:
            ts.append((6 - x) / c)
        if c < -1e-9:
            ts.append(-x / c)
        if s > 1e-9:
            ts.append((4 - y) / s)
        if s < -1e-9:
            ts.append(-y / s)
        out.append(min(ts))
    return out


CARMEN_HOWS = ("ok", "count_short", "count_long", "count_zero", "count_huge", "non_numeric", "nan_tokens", "negative",
               "all_max", "missing_tail", "robotlaser_bad", "param_garbage", "timestamps_backwards", "timestamps_nan",
               "gzip_truncated", "gzip_garbage", "binary", "empty", "comments_only", "crlf", "blank_lines",
               "huge_values")


def draw_carmen(ch: Chooser) -> dict[str, Any]:
    cmds = _draw_commands(ch, "segment", ("run", 0.5), ("rig", 0.15), ("calibrate", 0.05))
    return {"how": ch.choice(CARMEN_HOWS), "gzip": ch.chance(0.5), "lines": ch.integer(1, 25),
            "robotlaser": ch.chance(0.3), "fraction": _fraction(ch), "commands": cmds}


def build_carmen(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    rng = random.Random(spec["seed"])
    how = spec["how"]
    lines = ["# CARMEN log written by tests/fuzz_inputs.py", "PARAM robot_front_laser_max 50.0 nohost 0.0"]
    bad = set(rng.sample(range(spec["lines"]), max(1, round(spec["fraction"] * spec["lines"]))))
    for k in range(spec["lines"]):
        x, y, th = 1.0 + 0.1 * k, 2.0, 0.05 * k
        t = 100.0 + 0.1 * k
        if spec["robotlaser"]:
            n = 181
            r = _room_ranges(n, x, y, th, fov=math.pi, start=-math.pi / 2)
            fov, res = math.pi, math.pi / 180
            if how == "robotlaser_bad" and k in bad:
                fov, res = rng.choice(((0.0, 0.0), (-1.0, 0.01), (float("nan"), 0.01), (math.pi, 0.0), (1e9, 1e9)))
            head = ["ROBOTLASER1", "0", f"{-math.pi / 2}", f"{fov}", f"{res}", "50.0", "0.01", "0"]
            tail = ["0", f"{x}", f"{y}", f"{th}", f"{x}", f"{y}", f"{th}", "0", "0", "0", "0", "0", f"{t}", "host", f"{t}"]
        else:
            n = 180
            r = _room_ranges(n, x, y, th)
            head = ["FLASER"]
            tail = [f"{x}", f"{y}", f"{th}", f"{x}", f"{y}", f"{th}", f"{t}", "host", f"{t}"]
        vals = [f"{v:.3f}" for v in r]
        count = str(n)
        if k in bad:
            if how == "count_short":
                count = str(n - rng.randint(1, n))
            elif how == "count_long":
                count = str(n + rng.randint(1, 50))
            elif how == "count_zero":
                count, vals = "0", []
            elif how == "count_huge":
                count = "999999999"
            elif how == "non_numeric":
                vals[rng.randrange(n)] = "abc"
            elif how == "nan_tokens":
                for j in rng.sample(range(n), rng.randint(1, n)):
                    vals[j] = rng.choice(("nan", "inf", "-inf", "NaN"))
            elif how == "negative":
                for j in rng.sample(range(n), rng.randint(1, n)):
                    vals[j] = "-1.0"
            elif how == "all_max":
                vals = ["81.83"] * n
            elif how == "missing_tail":
                tail = tail[: rng.randrange(len(tail))]
            elif how == "timestamps_backwards":
                tail[-3] = f"{t - 50.0}"
            elif how == "timestamps_nan":
                tail[-3] = "nan"
            elif how == "huge_values":
                vals[rng.randrange(n)] = "1e308"
        if how == "all_max" and k not in bad and spec["fraction"] >= 1.0:
            vals = ["81.83"] * n
        if spec["robotlaser"]:
            line = [*head, count, *vals, "0", *tail]
        else:
            line = [*head, count, *vals, *tail]
        lines.append(" ".join(line))
        if how == "param_garbage" and k in bad:
            lines.append(rng.choice(("PARAM robot_front_laser_max abc nohost 0", "PARAM robot_front_laser_max -5 h 0",
                                     "PARAM", "PARAM robot_front_laser_max nan h 0")))
    sep = "\r\n" if how == "crlf" else ("\n\n\n" if how == "blank_lines" else "\n")
    text = sep.join(lines) + sep
    if how == "comments_only":
        text = "# nothing\n# here\n"
    if how == "empty":
        text = ""
    data = text.encode()
    name = "case.log.gz" if spec["gzip"] or how.startswith("gzip") else "case.log"
    path = folder / "in" / name
    if how == "binary":
        data = b"FLASER " + bytes(rng.randrange(256) for _ in range(2000))
        name = "case.log"
        path = folder / "in" / name
        path.write_bytes(data)
    elif name.endswith(".gz"):
        z = gzip.compress(data)
        if how == "gzip_truncated":
            z = z[: max(3, int(len(z) * rng.uniform(0.1, 0.95)))]
        elif how == "gzip_garbage":
            z = z[:10] + bytes(rng.randrange(256) for _ in range(len(z) - 10))
        path.write_bytes(z)
    else:
        path.write_bytes(data)
    all_bad = spec["fraction"] >= 1.0 or len(bad) == spec["lines"]
    no_usable = how in ("empty", "comments_only") or (how in ("all_max", "count_zero") and all_bad)
    cmds: list[Command] = []
    for c in spec["commands"]:
        if c == "segment":
            cmds.append(segment_command(path, folder, [path.name], no_usable=no_usable))
        elif c == "run":
            cmds.append(run_command(path, materials.rig, folder, [path.name], no_usable=True))
        elif c == "rig":
            cmds.append(rig_command(path, folder, [path.name]))
        elif c == "calibrate":
            cmds.append(calibrate_command(path, materials.rig, folder, [path.name], no_usable=True))
    return cmds


# ---- scanlines (.npz, .csv) ---------------------------------------------------------------------
NPZ_HOWS = ("ok", "shape_mismatch", "angles_nan", "angles_decreasing", "angles_duplicate", "ranges_all_nan",
            "zero_beams", "one_beam", "ranges_2d", "ranges_3d", "times_shape", "times_nan", "points_3col", "points_nan",
            "strings", "objects", "complex", "bool", "scanner_id_array", "limits_swapped", "range_max_negative",
            "huge_values", "extra_keys", "truncated", "not_zip", "missing_keys", "empty_zip", "scalar_ranges",
            "limits_nan")
CSV_HOWS = ("ok", "no_header", "unknown_columns", "non_numeric", "ragged", "empty", "header_only", "bom", "semicolons",
            "duplicate_columns", "times_backwards", "xy_nan", "all_invalid", "binary", "huge", "one_row")


def draw_scanline(ch: Chooser) -> dict[str, Any]:
    fmt = ch.choice(("npz", "csv"))
    how = ch.choice(NPZ_HOWS if fmt == "npz" else CSV_HOWS)
    cmds = _draw_commands(ch, "segment", ("run", 0.2))
    return {"fmt": fmt, "how": how, "n": ch.choice((271, 50, 3, 1081)), "scans": ch.integer(1, 4),
            "method": ch.choice(("ror", "ror", "split_and_merge", None)), "noise": ch.choice(("auto", "none")),
            "plot": ch.chance(0.15), "commands": cmds}


def build_scanline(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    rng = random.Random(spec["seed"])
    nrng = np.random.default_rng(spec["seed"])
    n, k = spec["n"], spec["scans"]
    how = spec["how"]
    angles = -math.radians(135.0) + np.arange(n) * (math.radians(270.0) / max(n - 1, 1))
    ranges = np.array([_room_ranges(n, 3.0, 2.0, 0.3 * j, fov=math.radians(270.0), start=-math.radians(135.0))
                       for j in range(k)])
    ranges += nrng.normal(0, 0.003, ranges.shape)
    no_usable = False
    if spec["fmt"] == "npz":
        d: dict[str, Any] = {"ranges": ranges if k > 1 else ranges[0], "angles": angles}
        if how == "shape_mismatch":
            d["angles"] = angles[: max(0, n - rng.randint(1, n))]
        elif how == "angles_nan":
            a = angles.copy()
            a[rng.randrange(n)] = np.nan
            d["angles"] = a
        elif how == "angles_decreasing":
            d["angles"] = angles[::-1].copy()
        elif how == "angles_duplicate":
            d["angles"] = np.zeros(n)
        elif how == "ranges_all_nan":
            d["ranges"] = np.full_like(ranges if k > 1 else ranges[0], np.nan)
            no_usable = True
        elif how == "zero_beams":
            d = {"ranges": np.zeros(0), "angles": np.zeros(0)}
            no_usable = True
        elif how == "one_beam":
            d = {"ranges": np.array([1.0]), "angles": np.array([0.0])}
        elif how == "ranges_2d":
            d["ranges"] = ranges.reshape(k, n)
            d["angles"] = np.tile(angles, (k + 1, 1))
        elif how == "ranges_3d":
            d["ranges"] = ranges.reshape(1, k, n)
        elif how == "times_shape":
            d["times"] = np.zeros(n + 1)
        elif how == "times_nan":
            d["times"] = np.full(ranges.shape if k > 1 else n, np.nan)
        elif how == "points_3col":
            d = {"points": np.zeros((n, 3))}
        elif how == "points_nan":
            d = {"points": np.full((n, 2), np.nan)}
            no_usable = True
        elif how == "strings":
            d["ranges"] = np.array(["a"] * n)
        elif how == "objects":
            d["ranges"] = np.array([None] * n, dtype=object)
        elif how == "complex":
            d["ranges"] = (ranges if k > 1 else ranges[0]) * (1 + 1j)
        elif how == "bool":
            d["ranges"] = np.ones(n, dtype=bool)
        elif how == "scanner_id_array":
            d["scanner_id"] = np.array(["a", "b"])
        elif how == "limits_swapped":
            d["range_min"], d["range_max"] = 30.0, 0.1
        elif how == "limits_nan":
            d["range_min"], d["range_max"] = np.nan, np.nan
        elif how == "range_max_negative":
            d["range_max"] = -1.0
            no_usable = True
        elif how == "huge_values":
            r = (ranges if k > 1 else ranges[0]).copy()
            r.flat[rng.randrange(r.size)] = 1e300
            d["ranges"] = r
        elif how == "extra_keys":
            d["bogus"] = np.arange(3)
        elif how == "missing_keys":
            d = {"angles": angles}
        elif how == "empty_zip":
            d = {}
        elif how == "scalar_ranges":
            d = {"ranges": np.float64(1.0), "angles": np.float64(0.0)}
        path = folder / "in" / "case.npz"
        if how == "objects":
            np.savez(path, **{kk: v for kk, v in d.items()}, allow_pickle=True)  # type: ignore[arg-type]
        else:
            np.savez(path, **d)
        if how == "truncated":
            b = path.read_bytes()
            path.write_bytes(b[: int(len(b) * rng.uniform(0.1, 0.9))])
        elif how == "not_zip":
            path.write_bytes(b"PK\x03\x04" + bytes(rng.randrange(256) for _ in range(300)))
    else:
        path = folder / "in" / "case.csv"
        r0 = ranges[0]
        rows: list[list[Any]] = [["range", "angle", "time"]] + [[f"{r0[i]:.4f}", f"{angles[i]:.6f}", f"{i * 1e-5:.6f}"]
                                                                for i in range(n)]
        if how == "no_header":
            rows = rows[1:]
        elif how == "unknown_columns":
            rows[0] = ["foo", "bar", "baz"]
        elif how == "non_numeric":
            rows[1 + rng.randrange(n)][0] = "abc"
        elif how == "ragged":
            rows[1 + rng.randrange(n)].append("1.0")
        elif how == "empty":
            rows = []
            no_usable = True
        elif how == "header_only":
            rows = rows[:1]
            no_usable = True
        elif how == "duplicate_columns":
            rows[0] = ["range", "range", "angle"]
        elif how == "times_backwards":
            for i in range(n):
                rows[1 + i][2] = f"{-i * 1e-3:.6f}"
        elif how == "xy_nan":
            rows = [["x", "y"]] + [["nan", "nan"] for _ in range(n)]
            no_usable = True
        elif how == "all_invalid":
            for i in range(n):
                rows[1 + i][0] = rng.choice(("nan", "inf", "0", "-1"))
            no_usable = True
        elif how == "huge":
            rows[1][0] = "1e400"
        elif how == "one_row":
            rows = rows[:2]
        with open(path, "w", newline="", encoding="utf-8") as f:
            if how == "bom":
                f.write("\ufeff")
            csv.writer(f, delimiter=";" if how == "semicolons" else ",").writerows(rows)
        if how == "binary":
            path.write_bytes(bytes(rng.randrange(256) for _ in range(500)))
    cmds: list[Command] = []
    extra = ["--noise", spec["noise"]] + (["--method", spec["method"]] if spec["method"] else [])
    for c in spec["commands"]:
        if c == "segment":
            cmds.append(segment_command(path, folder, [path.name], extra, no_usable=no_usable, plot=spec["plot"]))
        elif c == "run":
            cmds.append(run_command(path, materials.rig, folder, [path.name], no_usable=True))
    return cmds


# ---- rig YAMLs --------------------------------------------------------------------------------------
RIG_PATHS: tuple[tuple[Any, ...], ...] = (
    ("name",), ("reference",), ("body_frame",), ("imu",), ("imu", "topic"), ("imu", "frame_id"), ("scanners",),
    ("scanners", 0), ("scanners", 1, "name"), ("scanners", 1, "topic"), ("scanners", 0, "model"),
    ("scanners", 1, "model", "n_beams"), ("scanners", 1, "model", "angle_min"), ("scanners", 1, "model", "angle_increment"),
    ("scanners", 2, "model", "scan_period"), ("scanners", 2, "model", "time_increment"),
    ("scanners", 0, "model", "range_min"), ("scanners", 0, "model", "range_max"), ("scanners", 1, "model", "range_sigma"),
    ("scanners", 1, "T_body_scanner", "translation"), ("scanners", 1, "T_body_scanner", "translation", 0),
    ("scanners", 2, "T_body_scanner", "rpy", 1), ("scanners", 2, "T_body_scanner", "rpy"),
    ("scanners", 1, "T_body_scanner", "covariance"), ("scanners", 1, "time_offset"), ("scanners", 0, "time_offset"),
    ("scanners", 2, "frame_id"), ("scanners", 1, "message"), ("scanners", 0, "T_body_scanner"),
)
RIG_HOWS = ("value", "value", "value", "value", "unknown_key", "delete", "duplicate_scanner", "duplicate_topic",
            "syntax", "top_list", "empty", "binary", "wrong_rig", "unknown_model", "covariance_nan",
            "covariance_not_psd", "topic_missing", "huge_offset", "translation_far", "no_scanners", "bom")


def draw_rig(ch: Chooser) -> dict[str, Any]:
    cmds = _draw_commands(ch, "run", ("rig_check", 0.5), ("calibrate", 0.07))
    return {"how": ch.choice(RIG_HOWS), "path": list(ch.choice(RIG_PATHS)), "value": hostile_value(ch),
            "fmt": ch.choice(("ros1", "ros2")), "commands": cmds}


def _set_path(d: Any, path: Sequence[Any], value: Any, delete: bool = False) -> None:
    for k in path[:-1]:
        if isinstance(d, dict):
            d = d.setdefault(k, {})
        elif isinstance(d, list) and isinstance(k, int) and k < len(d):
            d = d[k]
        else:
            return
    last = path[-1]
    if isinstance(d, dict):
        if delete:
            d.pop(last, None)
        else:
            d[last] = value
    elif isinstance(d, list) and isinstance(last, int) and last < len(d):
        if delete:
            d.pop(last)
        else:
            d[last] = value


def _dump_yaml(data: Any) -> str:
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def build_rig(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    how = spec["how"]
    d = materials.rig_dict
    path = folder / "in" / "case_rig.yaml"
    text: str | None = None
    rig_arg = str(path)
    if how == "value":
        _set_path(d, spec["path"], spec["value"])
    elif how == "delete":
        _set_path(d, spec["path"], None, delete=True)
    elif how == "unknown_key":
        _set_path(d, [*spec["path"][:-1], "bogus_key"], 1)
    elif how == "duplicate_scanner":
        d["scanners"].append(copy.deepcopy(d["scanners"][1]))
    elif how == "duplicate_topic":
        d["scanners"][2]["topic"] = d["scanners"][1]["topic"]
    elif how == "syntax":
        text = "name: [unclosed\nscanners: {a: 1\n"
    elif how == "top_list":
        text = "- 1\n- 2\n"
    elif how == "empty":
        text = ""
    elif how == "binary":
        path.write_bytes(bytes(range(256)) * 3)
    elif how == "wrong_rig":
        rig_arg = "itc_backpack"
    elif how == "unknown_model":
        d["scanners"][1]["model"] = "nonexistent_scanner"
    elif how == "covariance_nan":
        d["scanners"][1]["T_body_scanner"]["covariance"] = [[float("nan")] * 6 for _ in range(6)]
    elif how == "covariance_not_psd":
        d["scanners"][1]["T_body_scanner"]["covariance"] = (-np.eye(6)).tolist()
    elif how == "topic_missing":
        d["scanners"][1]["topic"] = "/scan_nowhere"
    elif how == "huge_offset":
        d["scanners"][1]["time_offset"] = spec["value"] if isinstance(spec["value"], float) else 1e6
    elif how == "translation_far":
        d["scanners"][1]["T_body_scanner"]["translation"] = [100.0, 0.0, 0.0]
    elif how == "no_scanners":
        d["scanners"] = []
    elif how == "bom":
        text = "\ufeff" + _dump_yaml(d)
    if how != "binary":
        path.write_text(text if text is not None else _dump_yaml(d), encoding="utf-8")
    bag = materials.bags[spec["fmt"]]
    culprits = [path.name, "itc_backpack", "rig", bag.name]
    cmds = []
    for c in spec["commands"]:
        if c == "run":
            cmd = run_command(bag, path, folder, culprits)
            cmd.argv[cmd.argv.index("--rig") + 1] = rig_arg
            cmds.append(cmd)
        elif c == "rig_check":
            cmd = rig_check_command(path, folder, culprits)
            cmd.argv[cmd.argv.index("--check") + 1] = rig_arg
            cmds.append(cmd)
        elif c == "calibrate":
            cmd = calibrate_command(bag, path, folder, culprits)
            cmd.argv[cmd.argv.index("--rig") + 1] = rig_arg
            cmds.append(cmd)
    return cmds


# ---- SLAM config YAMLs -----------------------------------------------------------------------------
CONFIG_PATHS: tuple[tuple[str, ...], ...] = (
    ("segmenter", "method"), ("segmenter", "params"), ("segmenter", "params", "sigma"),
    ("segmenter", "params", "percentage"), ("segmenter", "params", "direction"), ("segmenter", "params", "bogus"),
    ("trajectory", "knot_rate"), ("trajectory", "imu_deskew"), ("frontend", "point_sigma"), ("frontend", "model_sigma"),
    ("frontend", "sigma_pose"), ("frontend", "min_support"), ("frontend", "extent_cell"),
    ("frontend", "max_endpoint_distance"), ("frontend", "wall_thickness"), ("frontend", "pool_window"),
    ("frontend", "min_segment_points"), ("frontend", "association_chi2"), ("frontend", "tracking_window"),
    ("edges", "use"), ("edges", "max_gap"), ("edges", "window"), ("edges", "min_incidence_deg"),
    ("backend", "robust"), ("backend", "robust_k"), ("backend", "solver"), ("backend", "update_every"),
    ("backend", "window_seconds"), ("backend", "robust_schedule"), ("backend", "motion_sigma_acc"),
    ("backend", "datum_sigma"), ("backend", "final_trim_sigmas"), ("backend", "batch_iterations"),
    ("imu", "use"), ("imu", "topic"), ("imu", "accel_noise"), ("imu", "gyro_noise"), ("imu", "gravity"),
    ("imu", "zupt_window"), ("imu", "samples"), ("output", "voxel"), ("output", "cloud"), ("output", "rerun"),
    ("output", "rerun_scan_every"), ("parallel", "reader"), ("parallel", "export_processes"),
    ("health", "min_associated"), ("health", "max_speed"), ("health", "observed_window"), ("health", "max_rms_whitened"),
)
CONFIG_SPECIALS: dict[str, Any] = {
    "unknown_segmenter": {"segmenter": {"method": "no_such_segmenter"}},
    "segmenter_bad_param": {"segmenter": {"method": "ror", "params": {"sigma": -0.01}}},
    "segmenter_unknown_param": {"segmenter": {"method": "ror", "params": {"no_such_param": 1}}},
    "segmenter_nan_param": {"segmenter": {"method": "ror", "params": {"sigma": float("nan")}}},
    "segmenter_inf_param": {"segmenter": {"method": "ror", "params": {"sigma": float("inf")}}},
    "imu_on_missing_topic": {"imu": {"use": "on", "topic": "/no_imu"}},
    "imu_off": {"imu": {"use": "off"}},
    "knot_rate_max": {"trajectory": {"knot_rate": 400.0}},
    "thickness_reversed": {"frontend": {"wall_thickness": [0.3, 0.05]}},
    "inf_sigma": {"frontend": {"point_sigma": float("inf")}},
    "nan_health": {"health": {"max_speed": float("nan")}},
    "voxel_tiny": {"output": {"voxel": 1e-9}},
    "voxel_inf": {"output": {"voxel": float("inf")}},
    "no_outputs": {"output": {"cloud": False, "rerun": False}},
    "isam2": {"backend": {"solver": "isam2"}},
    "unknown_section": {"bogus": {"a": 1}},
    "syntax": None,
    "top_list": None,
    "empty": None,
}


def draw_config(ch: Chooser) -> dict[str, Any]:
    special = ch.choice((None, None, None, *CONFIG_SPECIALS))
    cmds = _draw_commands(ch, "run", ("calibrate", 0.06))
    return {"special": special, "path": list(ch.choice(CONFIG_PATHS)), "value": hostile_value(ch),
            "fmt": ch.choice(("ros1", "ros2")), "commands": cmds}


def build_config(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    path = folder / "in" / "case_config.yaml"
    special = spec["special"]
    if special == "syntax":
        path.write_text("segmenter: {method: ror\n  params: [\n")
    elif special == "top_list":
        path.write_text("- segmenter\n- ror\n")
    elif special == "empty":
        path.write_text("")
    elif special is not None:
        path.write_text(_dump_yaml(CONFIG_SPECIALS[special]))
    else:
        d: dict[str, Any] = {}
        _set_path(d, spec["path"], spec["value"])
        path.write_text(_dump_yaml(d))
    bag = materials.bags[spec["fmt"]]
    culprits = [path.name, bag.name]
    cmds = []
    for c in spec["commands"]:
        if c == "run":
            cmds.append(run_command(bag, materials.rig, folder, culprits, config=path))
        elif c == "calibrate":
            cmds.append(calibrate_command(bag, materials.rig, folder, culprits, config=path))
    return cmds


# ---- hostile option values -----------------------------------------------------------------------------
CLI_HOSTILE = ("nan", "inf", "-inf", "-1", "0", "1e-9", "1e300", "abc", "", "-0", "1e999", "9999999999999")
CLI_OPTIONS: dict[str, tuple[str, ...]] = {
    "run": ("--voxel", "--segmenter", "--param", "--cloud-format", "--out", "--urdf", "--rig", "--config"),
    "segment": ("--scan", "--method", "--param", "--topic", "--noise", "--json", "--plot"),
    "calibrate": ("--rounds", "--sigma-rot", "--sigma-trans", "--coarse", "--coarse-seconds", "--report"),
    "evaluate": ("--max-cloud-points", "--align", "--gt"),
    "export": ("--format", "--out"),
}


def draw_cli(ch: Chooser) -> dict[str, Any]:
    command = ch.choice(tuple(CLI_OPTIONS))
    option = ch.choice(CLI_OPTIONS[command])
    value = ch.choice(CLI_HOSTILE) if ch.chance(0.6) else ch.choice(
        ("sigma=nan", "sigma=-1", "sigma=abc", "direction=sideways", "nokey", "=1", "bogus=1", "sigma=inf", "xyz",
         "/dev/null", "/nonexistent/dir/file", "OUT_IS_FILE", "OUT_IS_DIR", "split_and_merge", "ror", "all", "-100000"))
    return {"command": command, "option": option, "value": value, "fmt": ch.choice(("ros1", "ros2"))}


def build_cli(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    command, option, value = spec["command"], spec["option"], spec["value"]
    bag = materials.bags[spec["fmt"]]
    if value == "OUT_IS_FILE":
        value = str(folder / "in" / "a_file")
        Path(value).write_text("x")
    elif value == "OUT_IS_DIR":
        value = str(folder / "in")
    culprits = [option, value, bag.name] if value else [option, bag.name]
    vpath = Path(value) if Path(value).is_absolute() else folder / value  # commands run in the case folder
    if command == "run":
        cmd = run_command(bag, materials.rig, folder, culprits)
        if option == "--out":
            cmd.argv[cmd.argv.index("--out") + 1] = value
            cmd.outputs = [] if value in ("", "/dev/null") or vpath.exists() else cmd.outputs
            if cmd.outputs:
                cmd.outputs[0].path = vpath
        elif option in ("--rig", "--config"):
            if option == "--rig":
                cmd.argv[cmd.argv.index("--rig") + 1] = value
            else:
                cmd.argv += [option, value]
        else:
            cmd.argv += [option, value]
        return [cmd]
    if command == "segment":
        cmd = segment_command(bag, folder, culprits)
        if option in ("--json", "--plot"):
            cmd.outputs = [o for o in cmd.outputs if o.path.suffix != (".json" if option == "--json" else ".png")]
        cmd.argv += [option, value]
        return [cmd]
    if command == "calibrate":
        cmd = calibrate_command(bag, materials.rig, folder, culprits)
        cmd.argv += [option, value] + (["5"] if option == "--coarse" else [])
        if option == "--report":
            cmd.outputs.append(Output(vpath, folder=True, required=("report.md",)) if value and not vpath.exists()
                               else Output(folder / "out" / "unused"))
        return [cmd]
    run_dir = folder / "in" / "run"
    shutil.copytree(materials.run, run_dir)
    if command == "evaluate":
        argv = ["evaluate", str(run_dir), "--no-plots"]
        if option != "--gt":
            argv += ["--gt", str(materials.gt)]
        argv += [option, value]
        return [Command("evaluate", argv, [Output(run_dir / "eval.json", check="json")], culprits)]
    out = folder / "out" / "cloud.las"
    argv = ["export", str(run_dir)]
    if option == "--out":
        argv += ["--out", value]
        outputs = [] if not value or vpath.exists() else [Output(vpath)]
    else:
        argv += ["--out", str(out), option, value]
        outputs = [Output(out)]
    return [Command("export", argv, outputs, culprits)]


# ---- run folders (evaluate, export) ---------------------------------------------------------------
RUN_DIR_HOWS = ("ok", "cloud_truncated", "cloud_header", "cloud_flip", "cloud_empty", "cloud_missing", "cloud_no_points",
                "traj_garbage", "traj_nan", "traj_one", "traj_empty", "traj_unsorted", "traj_duplicate_times",
                "traj_missing", "planes_invalid", "planes_schema", "planes_nan", "planes_missing", "segments_corrupt",
                "segments_keys", "summary_garbage", "summary_missing", "summary_bag_missing", "gt_traj_garbage",
                "gt_mesh_corrupt", "gt_planes_invalid", "gt_beams_corrupt", "gt_missing", "gt_meta_garbage",
                "traj_far", "traj_bad_quat")


def draw_run_dir(ch: Chooser) -> dict[str, Any]:
    cmds = ch.subset(("evaluate", "export"))
    return {"how": ch.choice(RUN_DIR_HOWS), "format": ch.choice(("las", "laz", "pcd", "e57")), "plots": ch.chance(0.1),
            "at": round(ch.uniform(0.0, 1.0), 4), "commands": cmds}


def build_run_dir(spec: dict[str, Any], materials: Materials, folder: Path) -> list[Command]:
    rng = random.Random(spec["seed"])
    how = spec["how"]
    run_dir = folder / "in" / "run"
    gt = folder / "in" / "case.gt"
    shutil.copytree(materials.run, run_dir)
    shutil.copytree(materials.gt, gt)
    (run_dir / "eval.json").unlink(missing_ok=True)
    for png in run_dir.glob("*.png"):
        png.unlink()
    summary = json.loads((run_dir / "summary.json").read_text())
    summary["bag"] = str(folder / "in" / "case.bag")
    (run_dir / "summary.json").write_text(json.dumps(summary))
    cloud, traj, planes = run_dir / "cloud.ply", run_dir / "trajectory.tum", run_dir / "planes.json"
    no_usable = False
    culprit = run_dir.name
    if how == "cloud_truncated":
        b = cloud.read_bytes()
        cloud.write_bytes(b[: int(len(b) * spec["at"])])
    elif how == "cloud_header":
        b = cloud.read_bytes()
        end = b.index(b"end_header")
        head = b[:end].decode("ascii").replace("element vertex", rng.choice(("element vertex 9", "element vertex -",
                                                                               "element vortex")))
        cloud.write_bytes(head.encode() + b[end:])
    elif how == "cloud_flip":
        b = bytearray(cloud.read_bytes())
        for _ in range(50):
            k = rng.randrange(len(b))
            b[k] ^= 0xFF
        cloud.write_bytes(bytes(b))
    elif how == "cloud_empty":
        cloud.write_bytes(b"")
    elif how == "cloud_missing":
        cloud.unlink()
    elif how == "cloud_no_points":
        b = cloud.read_bytes()
        end = b.index(b"end_header\n") + len(b"end_header\n")
        head = b[:end].decode("ascii")
        import re

        head = re.sub(r"element vertex \d+", "element vertex 0", head)
        cloud.write_bytes(head.encode())
        no_usable = True
    elif how.startswith("traj_"):
        lines = [ln for ln in traj.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
        if how == "traj_garbage":
            traj.write_text("this is not\na trajectory\n")
        elif how == "traj_nan":
            traj.write_text("\n".join(" ".join([ln.split()[0]] + ["nan"] * 7) for ln in lines) + "\n")
            no_usable = True
        elif how == "traj_one":
            traj.write_text(lines[0] + "\n")
        elif how == "traj_empty":
            traj.write_text("")
            no_usable = True
        elif how == "traj_unsorted":
            traj.write_text("\n".join(reversed(lines)) + "\n")
        elif how == "traj_duplicate_times":
            t0 = lines[0].split()[0]
            traj.write_text("\n".join(" ".join([t0, *ln.split()[1:]]) for ln in lines) + "\n")
        elif how == "traj_missing":
            traj.unlink()
        elif how == "traj_far":
            traj.write_text("\n".join(" ".join([ln.split()[0], "1e300", *ln.split()[2:]]) for ln in lines) + "\n")
        elif how == "traj_bad_quat":
            traj.write_text("\n".join(" ".join([*ln.split()[:4], "0", "0", "0", "0"]) for ln in lines) + "\n")
    elif how == "planes_invalid":
        planes.write_text("{not json")
    elif how == "planes_schema":
        planes.write_text(json.dumps({"planes": "nope"}))
    elif how == "planes_nan":
        data = json.loads(planes.read_text())
        planes.write_text(json.dumps(data).replace("0.", "NaN0.", 3).replace("NaN0.", "NaN", 3))
    elif how == "planes_missing":
        planes.unlink()
    elif how == "segments_corrupt":
        (run_dir / "segments.npz").write_bytes(b"PK\x03\x04garbage")
    elif how == "segments_keys":
        np.savez(run_dir / "segments.npz", bogus=np.arange(3))
    elif how == "summary_garbage":
        (run_dir / "summary.json").write_text("[1, 2")
    elif how == "summary_missing":
        (run_dir / "summary.json").unlink()
    elif how == "summary_bag_missing":
        summary.pop("bag", None)
        (run_dir / "summary.json").write_text(json.dumps(summary))
    elif how == "gt_traj_garbage":
        (gt / "trajectory.tum").write_text("1 2 3\n")
        culprit = gt.name
    elif how == "gt_mesh_corrupt":
        (gt / "mesh.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
        culprit = gt.name
    elif how == "gt_planes_invalid":
        (gt / "planes.json").write_text("nope")
        culprit = gt.name
    elif how == "gt_beams_corrupt":
        (gt / "beams.npz").write_bytes(b"garbage")
        culprit = gt.name
    elif how == "gt_missing":
        shutil.rmtree(gt)
        culprit = gt.name
    elif how == "gt_meta_garbage":
        (gt / "meta.json").write_text("{")
        culprit = gt.name
    culprits = [culprit, run_dir.name, gt.name, "cloud.ply", "trajectory.tum", "planes.json", "segments.npz",
                "summary.json"]
    cmds = []
    for c in spec["commands"]:
        if c == "evaluate":
            argv = ["evaluate", str(run_dir), "--gt", str(gt)] + ([] if spec["plots"] else ["--no-plots"])
            # evaluate skips (and names) a cloud without points: only a trajectory without poses leaves it nothing
            cmds.append(Command("evaluate", argv, [Output(run_dir / "eval.json", check="json")], culprits,
                                no_usable and how in ("traj_nan", "traj_empty")))
        else:
            out = folder / "out" / f"cloud.{spec['format']}"
            cmds.append(Command("export", ["export", str(run_dir), "--format", spec["format"], "--out", str(out)],
                                [Output(out)], culprits, how == "cloud_no_points"))  # only E57 reads the trajectory
    return cmds


SPEC_DRAWERS: dict[str, Callable[[Chooser], dict[str, Any]]] = {
    "bag": draw_bag, "bag_bytes": draw_bag_bytes, "carmen": draw_carmen, "scanline": draw_scanline, "rig": draw_rig,
    "config": draw_config, "cli": draw_cli, "run_dir": draw_run_dir,
}
CASE_BUILDERS: dict[str, Callable[[dict[str, Any], Materials, Path], list[Command]]] = {
    "bag": build_bag, "bag_bytes": build_bag_bytes, "carmen": build_carmen, "scanline": build_scanline,
    "rig": build_rig, "config": build_config, "cli": build_cli, "run_dir": build_run_dir,
}


def spec_strategy(kind: str | None = None) -> Any:
    """A hypothesis strategy of specs (of ``kind``, else any), drawn through :class:`DrawChooser`."""
    from hypothesis import strategies as st

    @st.composite
    def specs(draw: Any) -> dict[str, Any]:
        return draw_spec(DrawChooser(draw), kind)

    return specs()
