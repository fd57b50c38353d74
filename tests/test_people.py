"""People in the simulated scene: the occlusion kernel, seeded tracks, and their beams in the
ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from simulation.people import PERSON, PERSON_KIND, People, PeopleConfig, make_people
from simulation.world.spec import Walk


def _one_person(x: float, y: float, height: float = 1.8) -> People:
    return People(np.array([[[x, y], [x, y]]]), np.array([height]), 0.25, 0.0)


def test_a_ray_stops_at_the_person_in_front_of_the_wall() -> None:
    people = _one_person(3.0, 0.0)
    o = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.5]])
    u = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rng = np.array([10.0, 10.0, 2.0, 10.0])  # the third ray hits a wall before the person
    pid = np.array([5, 5, 5, 5], dtype=np.int32)
    kind = np.zeros(4, dtype=np.int8)
    cos = np.ones(4)
    n = people.occlude(o, u, np.zeros(4), rng, pid, kind, cos)
    assert n == 1
    assert rng[0] == pytest.approx(2.75) and pid[0] == PERSON and kind[0] == PERSON_KIND
    assert cos[0] == pytest.approx(1.0)
    np.testing.assert_array_equal(rng[1:], [10.0, 2.0, 10.0])  # beside, behind a wall, above the head
    np.testing.assert_array_equal(pid[1:], [5, 5, 5])


def test_walkers_are_seeded_and_move_along_the_walk() -> None:
    walk = Walk(waypoints=[[0, 0], [20, 0], [20, 6], [0, 6]], closed=True)
    cfg = PeopleConfig(walkers=3, groups=1, group_size=2)
    a = make_people(cfg, walk, 10.0, 0.0, seed=4)
    b = make_people(cfg, walk, 10.0, 0.0, seed=4)
    c = make_people(cfg, walk, 10.0, 0.0, seed=5)
    np.testing.assert_array_equal(a.tracks_xy, b.tracks_xy)
    assert not np.array_equal(a.tracks_xy, c.tracks_xy)
    assert a.count == 5
    speed = np.linalg.norm(np.diff(a.tracks_xy[:3], axis=1), axis=2) * a.rate
    assert np.all((speed > 0.3) & (speed < 2.5))  # walking, corners rounded
    assert np.all((np.median(speed, axis=1) > 0.8) & (np.median(speed, axis=1) < 1.5))
    assert np.all(np.diff(a.tracks_xy[3:], axis=1) == 0.0)  # the group stands
    # walkers stay near the walk's line: within the lateral offset of the loop's rectangle
    x, y = a.tracks_xy[:3, :, 0], a.tracks_xy[:3, :, 1]
    d = np.minimum.reduce([np.abs(y), np.abs(y - 6), np.abs(x), np.abs(x - 20)])
    assert d.max() < 0.85


def test_no_people_by_default() -> None:
    walk = Walk(waypoints=[[0, 0], [5, 0]])
    assert make_people(PeopleConfig(), walk, 3.0, 0.0, seed=1).count == 0


def test_simulated_people_appear_in_the_ground_truth(tmp_path) -> None:
    from simulation.run import SimulationConfig, simulate

    cfg = SimulationConfig.model_validate({"people": {"walkers": 4, "groups": 1}, "duration": 4.0, "seed": 2})
    res = simulate("demo", "itc_backpack", out=tmp_path / "p.bag", config=cfg, progress=False)
    beams = np.load(res.gt / "beams.npz")
    hits = sum(int((beams[k] == PERSON).sum()) for k in beams.files if k.endswith("_plane_id"))
    kinds = sum(int((beams[k] == PERSON_KIND).sum()) for k in beams.files if k.endswith("_kind"))
    assert hits > 100 and kinds == hits
    tracks = np.load(res.gt / "people.npz")
    assert tracks["tracks_xy"].shape[0] == 7
