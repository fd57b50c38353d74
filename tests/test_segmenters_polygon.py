"""Every registered segmenter, at its defaults, recovers every face of noise-free polygon rooms.

A face counts when it has >= 30 beams and its consecutive points are <= 0.1 m
apart (half the default depth-jump gap; grazing walls whose points spread
farther are legitimately split). Recovered = one result segment whose first
and last beams are within +-1 beam of the face's.
"""

from __future__ import annotations

import numpy as np
import pytest

import segmentation as sg
from segmentation.metrics import segment_bounds
from simulation.scanline import SyntheticScan, random_room

SEEDS = range(12)


def _rooms() -> list[SyntheticScan]:
    return [random_room(seed, n_features=0, noise_sigma=0.0, min_turn_deg=60.0) for seed in SEEDS]


ROOMS = _rooms()


def _missed_faces(method: str, room: SyntheticScan) -> list[tuple[int, int, list[tuple[int, int]]]]:
    line = sg.Scanline.from_ranges(room.ranges, room.angles, room.times,
                                   range_min=room.range_min, range_max=room.range_max)
    res = sg.segment(line, method=method)
    gs, ge = segment_bounds(room.gt_labels)
    rs, re = segment_bounds(res.labels)
    pts = room.points_xy
    missed = []
    for a, b in zip(gs, ge, strict=True):
        spacing = np.hypot(*np.diff(pts[a:b + 1], axis=0).T)
        if b - a + 1 < 30 or spacing.max() > 0.1:
            continue
        if not np.any((np.abs(rs - a) <= 1) & (np.abs(re - b) <= 1)):
            near = [(int(x), int(y)) for x, y in zip(rs, re, strict=True) if y >= a - 5 and x <= b + 5]
            missed.append((int(a), int(b), near))
    return missed


def test_rooms_have_enough_faces_to_test() -> None:
    counts = [np.sum(np.bincount(r.gt_labels[r.gt_labels >= 0]) >= 30) for r in ROOMS]
    assert sum(counts) >= 40


@pytest.mark.parametrize("method", sg.available())
def test_every_face_recovered_within_one_beam(method: str) -> None:
    failures = {i: m for i, room in enumerate(ROOMS) if (m := _missed_faces(method, room))}
    assert not failures, (
        f"{method}: faces missed (room seed: [(gt first, gt last, nearby result segments)]): {failures}"
    )
