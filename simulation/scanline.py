"""Synthetic 2D scanlines with ground-truth segment labels: a ray caster against polylines.

A ``World2D`` is a set of straight edges in the plane (world frame, metres).
Every edge belongs either to a named planar *face* (a wall, a whiteboard, a
door leaf) or to no face (a sloped door-frame transition, the steep edge of a
board): beams hitting the latter are ground-truth "unsegmented". ``scan``
casts the beams of a UTM-30LX-like scanner (``ScannerSpec``) from a pose
``(x, y, heading)`` and returns plain arrays in a ``SyntheticScan``: per-beam
angles (scanner frame), ranges with seeded Gaussian noise, per-beam times,
ground-truth labels and the true line of every labelled segment in the
scanner frame.

Ground-truth labels: a segment is a maximal run of consecutive beams hitting
the same face; runs are numbered 0, 1, ... in scan order, -1 marks beams on
no face and misses. Two runs on one face (split by an occluder) are two
segments, as a segmenter would see them.

This module knows worlds and sensors only; build a segmentation input with
``segmentation.Scanline.from_ranges(s.ranges, s.angles, s.times,
range_min=s.range_min, range_max=s.range_max)``.

Layouts: ``figure1`` is the seed paper's figure-1 situation (wall, whiteboard
2 cm proud with steep edges, wall, corner, wall, door leaf 1.5 cm recessed
with sloped frame transitions, wall, closed by two back walls);
``random_room`` draws star-shaped polygon rooms with optional narrow
nearly-coplanar boards and recessed doors, a random scanner pose and noise.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_EPS = 1e-12


@dataclass(frozen=True)
class ScannerSpec:
    """A UTM-30LX-like 2D scanner: beam geometry, range limits, timing and range noise.

    Beam ``k`` has angle ``angle_min + k * angle_increment`` in the scanner
    frame and is taken ``k * time_increment`` after the first beam, with
    ``time_increment = scan_period / steps_per_turn`` (25 ms per mirror turn,
    1440 steps per turn). ``noise_sigma`` is the standard deviation (m) of
    additive Gaussian range noise; ``quantization`` (m), if set, rounds ranges.
    """

    n_beams: int = 1081
    angle_min: float = float(np.deg2rad(-135.0))
    angle_increment: float = float(np.deg2rad(0.25))
    range_min: float = 0.1
    range_max: float = 30.0
    scan_period: float = 0.025
    steps_per_turn: int = 1440
    noise_sigma: float = 0.003
    quantization: float | None = None

    def __post_init__(self) -> None:
        if self.n_beams < 1:
            raise ValueError(f"ScannerSpec.n_beams={self.n_beams} is invalid: must be >= 1")
        if not self.angle_increment > 0:
            raise ValueError(f"ScannerSpec.angle_increment={self.angle_increment} is invalid: must be > 0")
        if not 0 <= self.range_min < self.range_max:
            raise ValueError(
                f"ScannerSpec range limits [{self.range_min}, {self.range_max}] are invalid: need 0 <= min < max"
            )
        if not self.noise_sigma >= 0:
            raise ValueError(f"ScannerSpec.noise_sigma={self.noise_sigma} is invalid: must be >= 0")
        if self.quantization is not None and not self.quantization > 0:
            raise ValueError(f"ScannerSpec.quantization={self.quantization} is invalid: must be > 0 or None")
        if self.scan_period <= 0 or self.steps_per_turn < 1:
            raise ValueError("ScannerSpec.scan_period must be > 0 and steps_per_turn >= 1")

    @property
    def time_increment(self) -> float:
        """Time between consecutive beams (s)."""
        return self.scan_period / self.steps_per_turn

    def angles(self) -> FloatArray:
        """Beam angles (rad) in the scanner frame."""
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class World2D:
    """Straight edges in the world frame; ``face_ids[e]`` indexes ``face_names`` or is -1 (no face)."""

    starts: FloatArray
    ends: FloatArray
    face_ids: IntArray
    face_names: tuple[str, ...]

    @classmethod
    def from_pieces(cls, pieces: Sequence[tuple[str | None, ArrayLike]]) -> World2D:
        """Build from ``(name, polyline)`` pieces: a named piece is one planar face (two
        vertices); an unnamed piece (``None``) is any polyline hitting no face."""
        starts: list[FloatArray] = []
        ends: list[FloatArray] = []
        fids: list[int] = []
        names: list[str] = []
        for name, poly in pieces:
            p = np.asarray(poly, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
                raise ValueError(f"world piece {name!r}: polyline must have shape (k>=2, 2), got {p.shape}")
            if name is not None:
                if p.shape[0] != 2:
                    raise ValueError(f"world piece {name!r}: a planar face is one straight edge (2 vertices)")
                if name in names:
                    raise ValueError(f"world piece {name!r}: face name used twice")
                names.append(name)
            for a, b in itertools.pairwise(p):
                if np.hypot(*(b - a)) < 1e-9:
                    raise ValueError(f"world piece {name!r}: zero-length edge at {a.tolist()}")
                starts.append(a)
                ends.append(b)
                fids.append(len(names) - 1 if name is not None else -1)
        return cls(np.array(starts), np.array(ends), np.array(fids, dtype=np.int64), tuple(names))


@dataclass(frozen=True, eq=False)
class SyntheticScan:
    """One simulated scanline with ground truth (scanner frame, SI units).

    angles, ranges, times, true_ranges, face_ids, gt_labels: one entry per beam.
    ``ranges`` is ``inf`` where nothing was hit within ``range_max``;
    ``face_ids`` is the world face hit (-1 = no face or miss); ``gt_labels``
    the ground-truth segment (-1 = unsegmented). ``gt_normals`` (k, 2) and
    ``gt_offsets`` (k,) give each segment's true line ``normal . p = offset``
    (offset >= 0, normal away from the scanner); ``gt_names`` its face name.
    ``pose`` is the scanner's ``(x, y, heading)`` in the world frame.
    """

    angles: FloatArray
    ranges: FloatArray
    times: FloatArray
    gt_labels: IntArray
    range_min: float
    range_max: float
    face_ids: IntArray
    true_ranges: FloatArray
    gt_normals: FloatArray
    gt_offsets: FloatArray
    gt_names: tuple[str, ...]
    noise_sigma: float
    pose: tuple[float, float, float]

    @property
    def n_beams(self) -> int:
        return int(self.angles.shape[0])

    @property
    def n_segments(self) -> int:
        return len(self.gt_names)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Returns that are finite and within the range limits."""
        with np.errstate(invalid="ignore"):
            return np.isfinite(self.ranges) & (self.ranges >= self.range_min) & (self.ranges <= self.range_max)

    @property
    def points_xy(self) -> FloatArray:
        """(n_beams, 2) points in the scanner frame; NaN rows for invalid returns."""
        r = np.where(self.valid, self.ranges, np.nan)
        return np.column_stack((r * np.cos(self.angles), r * np.sin(self.angles)))

    def label_of(self, name: str) -> int:
        """Ground-truth segment id of the (first) run on the face called ``name``."""
        try:
            return self.gt_names.index(name)
        except ValueError:
            raise ValueError(f"no ground-truth segment named {name!r}; have {', '.join(self.gt_names)}") from None


def cast_rays(world: World2D, origin: ArrayLike, directions: FloatArray) -> tuple[FloatArray, IntArray]:
    """Distance to the first edge along each unit direction (inf if none) and that edge's index (-1)."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    a = world.starts - o  # (m, 2)
    w = world.ends - world.starts  # (m, 2)
    denom = d[:, None, 0] * w[None, :, 1] - d[:, None, 1] * w[None, :, 0]  # cross(d, w), (n, m)
    cross_aw = a[:, 0] * w[:, 1] - a[:, 1] * w[:, 0]  # (m,)
    cross_ad = a[None, :, 0] * d[:, None, 1] - a[None, :, 1] * d[:, None, 0]  # cross(a, d), (n, m)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross_aw[None, :] / denom
        u = cross_ad / denom
    ok = (np.abs(denom) > _EPS) & (t > 1e-9) & (u >= -1e-12) & (u <= 1.0 + 1e-12)
    t = np.where(ok, t, np.inf)
    edge = np.argmin(t, axis=1)
    dist = t[np.arange(t.shape[0]), edge]
    edge = np.where(np.isfinite(dist), edge, -1).astype(np.int64)
    return dist, edge


def run_labels(face_ids: ArrayLike, min_run: int = 1) -> tuple[IntArray, IntArray]:
    """Label maximal runs of equal non-negative ids 0, 1, ... in order; runs shorter than
    ``min_run`` and negative ids get -1. Returns (labels, face id of each label)."""
    f = np.asarray(face_ids, dtype=np.int64)
    n = f.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels, np.empty(0, dtype=np.int64)
    change = np.flatnonzero(np.diff(f) != 0) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [n]))
    keep = (f[starts] >= 0) & (stops - starts >= min_run)
    for k, (s, e) in enumerate(zip(starts[keep], stops[keep], strict=True)):
        labels[s:e] = k
    return labels, f[starts[keep]]


def scan(
    world: World2D,
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    scanner: ScannerSpec | None = None,
    seed: int = 0,
    t0: float = 0.0,
    min_run: int = 1,
) -> SyntheticScan:
    """Simulate one scanline of ``scanner`` at ``pose = (x, y, heading)`` (world frame).

    Noise is drawn from ``numpy.random.default_rng(seed)``; same inputs, same
    output. Ground-truth runs shorter than ``min_run`` beams are unlabelled.
    """
    spec = scanner if scanner is not None else ScannerSpec()
    x, y, heading = (float(v) for v in pose)
    angles = spec.angles()
    dirs = np.column_stack((np.cos(angles + heading), np.sin(angles + heading)))
    true_r, edge = cast_rays(world, (x, y), dirs)
    hit = np.isfinite(true_r) & (true_r <= spec.range_max)
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal(spec.n_beams) * spec.noise_sigma
    ranges = np.where(hit, true_r + noise, np.inf)
    if spec.quantization is not None:
        ranges = np.where(hit, np.round(ranges / spec.quantization) * spec.quantization, ranges)
    face = np.where(hit & (edge >= 0), world.face_ids[np.maximum(edge, 0)], -1)
    face = np.where(true_r >= spec.range_min, face, -1)
    labels, label_face = run_labels(face, min_run)
    normals, offsets = _face_lines_in_scanner(world, label_face, (x, y, heading))
    return SyntheticScan(
        angles=angles,
        ranges=ranges,
        times=t0 + spec.time_increment * np.arange(spec.n_beams, dtype=np.float64),
        gt_labels=labels,
        range_min=spec.range_min,
        range_max=spec.range_max,
        face_ids=face.astype(np.int64),
        true_ranges=np.where(hit, true_r, np.inf),
        gt_normals=normals,
        gt_offsets=offsets,
        gt_names=tuple(world.face_names[int(f)] for f in label_face),
        noise_sigma=spec.noise_sigma,
        pose=(x, y, heading),
    )


def _face_lines_in_scanner(
    world: World2D, faces: IntArray, pose: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """Line (unit normal away from the scanner, offset >= 0) of each face, in the scanner frame."""
    x, y, heading = pose
    c, s = np.cos(heading), np.sin(heading)
    rot_scanner_world = np.array([[c, s], [-s, c]])
    edge_of_face = np.array([int(np.flatnonzero(world.face_ids == f)[0]) for f in faces], dtype=np.int64)
    a = (world.starts[edge_of_face] - (x, y)) @ rot_scanner_world.T
    b = (world.ends[edge_of_face] - (x, y)) @ rot_scanner_world.T
    d = b - a
    n = np.column_stack((-d[:, 1], d[:, 0])) / np.linalg.norm(d, axis=1, keepdims=True) if faces.size else d
    off = np.einsum("ij,ij->i", n, a)
    sign = np.where(off < 0, -1.0, 1.0)
    return np.ascontiguousarray(n * sign[:, None]), np.abs(off)


# ---- layouts -------------------------------------------------------------------------------------


def figure1_world(
    board_offset: float = 0.02,
    door_recess: float = 0.015,
    frame_width: float = 0.04,
) -> World2D:
    """The seed paper's figure-1 scene (world frame, scanner expected at the origin facing +x).

    A 5.5 m x 5.5 m room: front wall x = 3 with a whiteboard ``board_offset``
    proud of it (steep edges) from y = -2.2 to -0.6, the corner at (3, 1.5),
    the side wall y = 1.5 with a door leaf ``door_recess`` behind it from
    x = 1.3 to 0.4, reached through sloped frame transitions ``frame_width``
    wide, and two back walls. In scan order (counter-clockwise): back wall,
    right wall, wall, whiteboard, wall, corner, wall, door, wall.
    """
    xa, yb = 3.0, 1.5
    xb0, xb1 = -2.2, -0.6  # whiteboard extent along the front wall (y)
    xd0, xd1 = 1.3, 0.4  # door leaf extent along the side wall (x)
    fw = frame_width
    bx = xa - board_offset
    dy = yb + door_recess
    return World2D.from_pieces(
        [
            ("back_wall", [(-2.5, 1.5), (-2.5, -4.0)]),
            ("right_wall", [(-2.5, -4.0), (xa, -4.0)]),
            ("wall_left_of_board", [(xa, -4.0), (xa, xb0)]),
            (None, [(xa, xb0), (bx, xb0)]),
            ("whiteboard", [(bx, xb0), (bx, xb1)]),
            (None, [(bx, xb1), (xa, xb1)]),
            ("wall_right_of_board", [(xa, xb1), (xa, yb)]),
            ("wall_before_door", [(xa, yb), (xd0 + fw, yb)]),
            (None, [(xd0 + fw, yb), (xd0, dy)]),
            ("door", [(xd0, dy), (xd1, dy)]),
            (None, [(xd1, dy), (xd1 - fw, yb)]),
            ("wall_after_door", [(xd1 - fw, yb), (-2.5, yb)]),
        ]
    )


def figure1(
    noise_sigma: float = 0.003,
    seed: int = 0,
    *,
    quantization: float | None = None,
    board_offset: float = 0.02,
    door_recess: float = 0.015,
    frame_width: float = 0.04,
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> SyntheticScan:
    """The figure-1 scanline (see ``figure1_world``) with range noise ``noise_sigma`` (m), seeded."""
    world = figure1_world(board_offset, door_recess, frame_width)
    return scan(world, pose, ScannerSpec(noise_sigma=noise_sigma, quantization=quantization), seed)


def random_room(
    seed: int,
    *,
    n_walls: tuple[int, int] = (4, 8),
    radius: tuple[float, float] = (2.5, 6.0),
    min_turn_deg: float = 30.0,
    n_features: int | tuple[int, int] = (1, 3),
    noise_sigma: float | tuple[float, float] = (0.002, 0.005),
    quantization: float | None = None,
    min_run: int = 1,
) -> SyntheticScan:
    """A random star-shaped polygon room seen from a random pose, with ground truth.

    ``n_walls`` (inclusive range) vertices at sorted random bearings around
    the origin with random radii in ``radius``; every corner turns by at least
    ``min_turn_deg``. ``n_features`` boards (1-2 cm proud, steep edges, 0.6-1.5 m
    wide) or doors (1-2 cm recessed, sloped frames 2-5 cm, 0.8-1.0 m wide) are
    put on walls long enough. The scanner stands within 0.3 of the smallest
    radius from the origin with a random heading; ``noise_sigma`` is a value or
    an inclusive range to draw from. Everything is drawn from ``seed``.
    """
    rng = np.random.default_rng(seed)
    verts = _random_polygon(rng, n_walls, radius, np.deg2rad(min_turn_deg))
    k_feat = n_features if isinstance(n_features, int) else int(rng.integers(n_features[0], n_features[1] + 1))
    world = _room_world(rng, verts, k_feat)
    r_in = float(np.min(np.hypot(verts[:, 0], verts[:, 1])))
    rho = 0.3 * r_in * np.sqrt(rng.uniform())
    phi = rng.uniform(-np.pi, np.pi)
    pose = (rho * np.cos(phi), rho * np.sin(phi), float(rng.uniform(-np.pi, np.pi)))
    sigma = noise_sigma if isinstance(noise_sigma, float | int) else float(rng.uniform(*noise_sigma))
    spec = ScannerSpec(noise_sigma=float(sigma), quantization=quantization)
    return scan(world, pose, spec, seed=int(rng.integers(2**31)), min_run=min_run)


def _random_polygon(
    rng: np.random.Generator, n_walls: tuple[int, int], radius: tuple[float, float], min_turn: float
) -> FloatArray:
    """Counter-clockwise star-shaped polygon whose every corner turns by >= min_turn (rad)."""
    if n_walls[0] < 3 or n_walls[1] < n_walls[0]:
        raise ValueError(f"n_walls={n_walls} is invalid: need 3 <= low <= high")
    for _ in range(10_000):
        n = int(rng.integers(n_walls[0], n_walls[1] + 1))
        bearings = np.sort(rng.uniform(-np.pi, np.pi, n))
        gaps = np.diff(np.concatenate((bearings, [bearings[0] + 2 * np.pi])))
        if np.min(gaps) < 0.35 or np.max(gaps) > 0.9 * np.pi:
            continue
        r = rng.uniform(radius[0], radius[1], n)
        v = np.column_stack((r * np.cos(bearings), r * np.sin(bearings)))
        e = np.roll(v, -1, axis=0) - v
        if np.min(np.hypot(e[:, 0], e[:, 1])) < 1.0:
            continue
        h = np.arctan2(e[:, 1], e[:, 0])
        turn = np.angle(np.exp(1j * (np.roll(h, -1) - h)))
        if np.min(np.abs(turn)) >= min_turn:
            return v
    raise ValueError(f"no polygon with n_walls={n_walls}, radius={radius} and turns >= {np.rad2deg(min_turn):.0f} deg")


def _room_world(rng: np.random.Generator, verts: FloatArray, n_features: int) -> World2D:
    """Walls of the polygon, with boards and doors on randomly chosen long walls."""
    n = verts.shape[0]
    lengths = np.hypot(*(np.roll(verts, -1, axis=0) - verts).T)
    candidates = np.flatnonzero(lengths >= 2.5)
    chosen = set(rng.choice(candidates, size=min(n_features, candidates.size), replace=False).tolist())
    pieces: list[tuple[str | None, ArrayLike]] = []
    for i in range(n):
        a, b = verts[i], verts[(i + 1) % n]
        if i not in chosen:
            pieces.append((f"wall_{i}", [a, b]))
            continue
        d = (b - a) / lengths[i]
        inward = np.array([-d[1], d[0]])  # counter-clockwise polygon: the room is on the left
        is_board = bool(rng.uniform() < 0.5)
        width = rng.uniform(0.6, 1.5) if is_board else rng.uniform(0.8, 1.0)
        depth = rng.uniform(0.01, 0.02)
        s0 = rng.uniform(0.4, lengths[i] - 0.4 - width)
        p0, p1 = a + s0 * d, a + (s0 + width) * d
        pieces.append((f"wall_{i}", [a, p0]))
        if is_board:
            q0, q1 = p0 + depth * inward, p1 + depth * inward
            pieces += [(None, [p0, q0]), (f"board_{i}", [q0, q1]), (None, [q1, p1])]
        else:
            slope = rng.uniform(0.02, 0.05)
            q0, q1 = p0 + slope * d - depth * inward, p1 - slope * d - depth * inward
            pieces += [(None, [p0, q0]), (f"door_{i}", [q0, q1]), (None, [q1, p1])]
        pieces.append((f"wall_{i}_b", [p1, b]))
    return World2D.from_pieces(pieces)
