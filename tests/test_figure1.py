"""The paper's figure-1 case: RoR combined at its defaults separates the whiteboard and the door."""

from __future__ import annotations

import numpy as np

import segmentation as sg
from segmentation.metrics import compare, separates
from simulation.scanline import figure1


def test_ror_combined_separates_board_and_door_over_20_seeds() -> None:
    failed: list[tuple[int, str]] = []
    angles = []
    for seed in range(20):
        s = figure1(noise_sigma=0.003, seed=seed)
        line = sg.Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min, range_max=s.range_max)
        res = sg.segment(line, method="ror")
        assert res.params["direction"] == "combined"
        for name in ("whiteboard", "door"):
            if not separates(res, s.gt_labels, s.label_of(name)):
                failed.append((seed, name))
        angles.append(compare(res, s.gt_labels, line, s.gt_normals).median_angle_deg)
    assert not failed, f"not separated (seed, object): {failed}"
    # separated objects leave the wall lines untilted
    assert np.median(angles) < 0.1
