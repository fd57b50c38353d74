"""Every registered segmenter recovers every face of noise-free polygon rooms.

A face counts when it has >= 30 beams and its consecutive points are <= 0.1 m
apart (half the default depth-jump gap; grazing walls whose points spread
farther are legitimately split). Recovered = one result segment whose first
and last beams are within +-``tol`` beams of the face's.

Two runs per method:

* **Thresholds set for noise-free data, +-1 beam.** A method whose defaults
  are tuned to 3 mm range noise (with margin) is run with the thresholds it
  would have for noise-free data; ``NOISE_FREE`` lists these overrides, only
  where needed. Every other method runs at its defaults.
* **Defaults, with the tolerance the method's documented behaviour gives**
  (``TOL_AT_DEFAULTS``, 1 beam unless listed), so the defaults stay covered.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import segmentation as sg
from segmentation.metrics import segment_bounds
from simulation.scanline import SyntheticScan, random_room

SEEDS = range(12)

# Thresholds for noise-free data, where a method's defaults assume 3 mm noise.
NOISE_FREE: dict[str, dict[str, Any]] = {
    # RoR's sigma = 9.5 mm is the paper's value tuned to 3 mm noise with margin; its windows accept a
    # point past a corner while it is within 3 sigma (28 mm) of the old line, i.e. for ~2 beams (module
    # docstring of segmentation.methods.ror). For noise-free data sigma is the point noise scale.
    "ror": {"sigma": 0.003},
}
# Boundary tolerance (beams) at the defaults, from each method's documented behaviour.
TOL_AT_DEFAULTS: dict[str, int] = {
    # a boundary lands up to ~2 beams past a corner at sigma = 9.5 mm (see NOISE_FREE)
    "ror": 3,
}


def _rooms() -> list[SyntheticScan]:
    return [random_room(seed, n_features=0, noise_sigma=0.0, min_turn_deg=60.0) for seed in SEEDS]


ROOMS = _rooms()


def _missed_faces(method: str, room: SyntheticScan, params: dict[str, Any],
                  tol: int) -> list[tuple[int, int, list[tuple[int, int]]]]:
    line = sg.Scanline.from_ranges(room.ranges, room.angles, room.times,
                                   range_min=room.range_min, range_max=room.range_max)
    res = sg.segment(line, method=method, **params)
    gs, ge = segment_bounds(room.gt_labels)
    rs, re = segment_bounds(res.labels)
    pts = room.points_xy
    missed = []
    for a, b in zip(gs, ge, strict=True):
        spacing = np.hypot(*np.diff(pts[a:b + 1], axis=0).T)
        if b - a + 1 < 30 or spacing.max() > 0.1:
            continue
        if not np.any((np.abs(rs - a) <= tol) & (np.abs(re - b) <= tol)):
            near = [(int(x), int(y)) for x, y in zip(rs, re, strict=True) if y >= a - 5 and x <= b + 5]
            missed.append((int(a), int(b), near))
    return missed


def test_rooms_have_enough_faces_to_test() -> None:
    counts = [np.sum(np.bincount(r.gt_labels[r.gt_labels >= 0]) >= 30) for r in ROOMS]
    assert sum(counts) >= 40


def test_overrides_name_real_methods_and_parameters() -> None:
    for method, params in NOISE_FREE.items():
        assert set(params) <= set(sg.segmenter_class(method).param_names()), method
    assert set(TOL_AT_DEFAULTS) <= set(sg.available())


@pytest.mark.parametrize("method", sg.available())
def test_every_face_recovered_within_one_beam(method: str) -> None:
    params = NOISE_FREE.get(method, {})
    failures = {i: m for i, room in enumerate(ROOMS) if (m := _missed_faces(method, room, params, 1))}
    assert not failures, (
        f"{method} {params}: faces missed (room seed: [(gt first, gt last, nearby result segments)]): {failures}"
    )


@pytest.mark.parametrize("method", sorted(NOISE_FREE))
def test_every_face_recovered_at_defaults_within_documented_tolerance(method: str) -> None:
    tol = TOL_AT_DEFAULTS.get(method, 1)
    failures = {i: m for i, room in enumerate(ROOMS) if (m := _missed_faces(method, room, {}, tol))}
    assert not failures, (
        f"{method} at defaults, +-{tol} beams: faces missed (room seed: [(gt first, gt last, nearby)]): {failures}"
    )
