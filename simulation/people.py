"""People in the building: walkers passing the operator and standing groups, seeded.

A person is a vertical cylinder (radius, height above the floor) that occludes the scanners'
beams; a hit on a person has plane id ``PERSON`` and kind ``person`` in the ground truth.
Walkers follow the operator's walk (its waypoints, in the opposite direction or the same one at
another speed) at a lateral offset, so that they cross the scanners' view as people in a
corridor do; groups stand beside the walk. Positions are world frame, metres; times are
simulation seconds (from 0). Same configuration and seed, same people.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.ndimage import gaussian_filter1d

from common.config import StrictModel
from simulation.world.kinds import KINDS
from simulation.world.spec import Walk

FloatArray = NDArray[np.float64]

PERSON = -3  # ground-truth plane id of a beam that hit a person
PERSON_KIND = KINDS["person"]
_TRACK_RATE = 50.0  # Hz: walkers' positions sampled on this clock, interpolated per beam


class PeopleConfig(StrictModel):
    """People in the scene (none by default)."""

    walkers: int = Field(default=0, ge=0, le=50, description="people walking along the operator's path")
    groups: int = Field(default=0, ge=0, le=20, description="groups standing beside the path")
    group_size: int = Field(default=3, ge=1, le=8)
    speed: tuple[float, float] = Field(default=(0.8, 1.5), description="walkers' speed range (m/s)")
    radius: float = Field(default=0.22, gt=0.05, le=0.5, description="a person's radius (m)")
    height: tuple[float, float] = Field(default=(1.55, 1.95), description="people's height range (m)")
    offset: tuple[float, float] = Field(
        default=(0.45, 0.8), description="walkers' lateral distance from the walk's line (m)")
    group_offset: tuple[float, float] = Field(
        default=(1.0, 1.6), description="groups' distance from the walk's line (m)")


@dataclass(frozen=True)
class People:
    """Tracks of the people: positions (P, T, 2) on a clock from 0 at ``rate`` Hz, heights (P,)."""

    tracks_xy: FloatArray
    heights: FloatArray
    radius: float
    floor_z: float
    rate: float = _TRACK_RATE

    @property
    def count(self) -> int:
        return int(self.tracks_xy.shape[0])

    def positions(self, t: float) -> FloatArray:
        """Positions (P, 2) at time ``t`` (s)."""
        k = min(max(t * self.rate, 0.0), self.tracks_xy.shape[1] - 1.0)
        i = min(int(k), self.tracks_xy.shape[1] - 2)
        a = k - i
        return (1.0 - a) * self.tracks_xy[:, i] + a * self.tracks_xy[:, i + 1]

    def occlude(self, origins_world: FloatArray, directions_world: FloatArray, times: FloatArray,
                ranges: FloatArray, plane_id: NDArray[np.int32], kind: NDArray[np.int8],
                cos_incidence: FloatArray) -> int:
        """Shorten every ray (N,) that hits a person before its surface, in place: range, plane id
        ``PERSON``, kind ``person``, incidence. Returns the number of rays that hit a person."""
        if self.count == 0:
            return 0
        return int(_occlude(np.ascontiguousarray(origins_world, dtype=np.float64),
                            np.ascontiguousarray(directions_world, dtype=np.float64),
                            np.ascontiguousarray(times, dtype=np.float64), self.tracks_xy, self.rate,
                            self.heights, self.radius, self.floor_z, ranges, plane_id, kind,
                            cos_incidence, PERSON, PERSON_KIND))


def _polyline(walk: Walk) -> tuple[FloatArray, FloatArray]:
    """The walk's line (vertices (V, 2), closed if the walk is) and cumulative arc length (V,)."""
    wp = np.asarray(walk.waypoints, dtype=np.float64)
    if walk.closed:
        wp = np.vstack((wp, wp[:1]))
    else:  # back and forth
        wp = np.vstack((wp, wp[-2::-1]))
    s = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(wp, axis=0), axis=1))))
    return wp, s


def _on_line(wp: FloatArray, s: FloatArray, at: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Points (n, 2) at arc lengths ``at`` (n,) (taken modulo the length) and the unit left
    normals (n, 2) of their segments."""
    length = float(s[-1])
    a = np.mod(at, length)
    i = np.clip(np.searchsorted(s, a, side="right") - 1, 0, len(s) - 2)
    seg = wp[i + 1] - wp[i]
    seg_len = np.maximum(np.linalg.norm(seg, axis=1), 1e-9)
    u = seg / seg_len[:, None]
    p = wp[i] + u * (a - s[i])[:, None]
    return p, np.column_stack((-u[:, 1], u[:, 0]))


def make_people(cfg: PeopleConfig, walk: Walk, duration: float, floor_z: float, seed: int) -> People:
    """The people of one simulation: ``cfg`` drawn with ``seed`` along ``walk`` for ``duration`` s."""
    rng = np.random.default_rng([seed, 31])
    wp, s = _polyline(walk)
    length = float(s[-1])
    n_t = math.ceil(duration * _TRACK_RATE) + 2
    t = np.arange(n_t) / _TRACK_RATE
    tracks: list[FloatArray] = []
    heights: list[float] = []
    for _ in range(cfg.walkers):
        v = rng.uniform(*cfg.speed) * (-1.0 if rng.random() < 0.7 else 1.0)  # most walk towards the operator
        side = rng.choice([-1.0, 1.0]) * rng.uniform(*cfg.offset)
        p, nrm = _on_line(wp, s, rng.uniform(0, length) + v * t)
        # the offset line jumps at the walk's corners: people round them over about a second
        tracks.append(gaussian_filter1d(p + side * nrm, 0.4 * _TRACK_RATE, axis=0, mode="nearest"))
        heights.append(rng.uniform(*cfg.height))
    for _ in range(cfg.groups):
        c, nrm = _on_line(wp, s, np.array([rng.uniform(0, length)]))
        centre = c[0] + rng.choice([-1.0, 1.0]) * rng.uniform(*cfg.group_offset) * nrm[0]
        for k in range(cfg.group_size):
            ang = 2 * math.pi * k / cfg.group_size + rng.uniform(-0.3, 0.3)
            ring = 0.0 if cfg.group_size == 1 else 0.45
            pos = centre + ring * np.array([math.cos(ang), math.sin(ang)])
            tracks.append(np.repeat(pos[None, :], n_t, axis=0))
            heights.append(rng.uniform(*cfg.height))
    xy = np.ascontiguousarray(np.stack(tracks)) if tracks else np.zeros((0, n_t, 2))
    return People(xy, np.asarray(heights, dtype=np.float64), cfg.radius, float(floor_z))


@nb.njit(cache=True)
def _occlude(o, u, times, tracks, rate, heights, radius, floor_z, rng, pid, kind, cos_i,
             person_id, person_kind):  # type: ignore[no-untyped-def]
    n_p, n_t = tracks.shape[0], tracks.shape[1]
    r2 = radius * radius
    hits = 0
    for m in range(o.shape[0]):
        k = min(max(times[m] * rate, 0.0), n_t - 1.0)
        i = min(int(k), n_t - 2)
        a = k - i
        ax, ay = u[m, 0], u[m, 1]
        aa = ax * ax + ay * ay
        if aa < 1e-12:
            continue
        best = rng[m] if math.isfinite(rng[m]) else np.inf
        who = -1
        for p in range(n_p):
            cx = (1.0 - a) * tracks[p, i, 0] + a * tracks[p, i + 1, 0]
            cy = (1.0 - a) * tracks[p, i, 1] + a * tracks[p, i + 1, 1]
            dx, dy = o[m, 0] - cx, o[m, 1] - cy
            b = dx * ax + dy * ay
            c = dx * dx + dy * dy - r2
            if c <= 0.0:  # the scanner inside a person: not a physical configuration
                continue
            disc = b * b - aa * c
            if disc <= 0.0:
                continue
            s = (-b - math.sqrt(disc)) / aa
            if s <= 0.0 or s >= best:
                continue
            z = o[m, 2] + s * u[m, 2]
            if z < floor_z or z > floor_z + heights[p]:
                continue
            best = s
            who = p
            hx, hy = dx + s * ax, dy + s * ay
            nn = math.sqrt(hx * hx + hy * hy)
            cos_i[m] = abs((hx * u[m, 0] + hy * u[m, 1]) / max(nn, 1e-12))
        if who >= 0:
            rng[m] = best
            pid[m] = person_id
            kind[m] = person_kind
            hits += 1
    return hits
