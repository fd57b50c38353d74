"""Held observation blocks' rows and scatters spilled to disk (slam.backend.spill and
BlockColumns.spill): every reader gets them back byte for byte, and a walk with spilling gives
the estimate of the same walk without, bit for bit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from backend_defaults import backend_defaults
from block_helpers import same_block
from box_scene import Scene, make_scene

from slam.backend import Backend
from slam.backend.blocks import BlockColumns, ObservationBlock
from slam.backend.spill import SpillTables


def _blocks(n: int, seed: int = 5) -> dict[int, ObservationBlock]:
    rng = np.random.default_rng(seed)
    out = {}
    for b in range(n):
        m = int(rng.integers(1, 20))
        two = b % 4 != 0
        out[3 * b + 2] = ObservationBlock(b // 3, b % 5, rng.normal(size=(m, 3)),
                                          rng.uniform(0, 1, m) if two else None, rng.uniform(0.01, 0.02, m))
    return out



def test_spill_tables_read_back_what_was_written_and_remove_their_folder() -> None:
    t = SpillTables({"p": (3,), "s": ()})
    assert t.table("p").shape == (0, 3) and t.folder is None
    a, b = np.arange(12.0).reshape(4, 3), np.full((2, 3), np.pi)
    assert t.append("p", a) == 0 and t.append("p", b) == 4 and t.append("s", np.ones(5)) == 0
    assert np.array_equal(t.table("p"), np.concatenate((a, b))) and t.rows("s") == 5
    folder = t.folder
    assert folder is not None and (folder / "p").stat().st_size == 6 * 3 * 8
    rows = np.array([5, 1, 1, 3], dtype=np.int64)
    assert np.array_equal(t.read("p", rows), np.concatenate((a, b))[rows])
    big = np.random.default_rng(0).normal(size=(10_000, 3))
    t.append("p", big)
    far = np.array([6 + 9_999, 6, 6 + 5_000], dtype=np.int64)  # a sparse read of a long span: mapped
    assert np.array_equal(t.read("p", far), big[far - 6]) and t.read("p", far[:0]).shape == (0, 3)
    t.clear("s")
    assert t.rows("s") == 0 and t.table("s").shape == (0,)
    t.close()
    assert not folder.exists() and t.folder is None


def test_spilled_blocks_read_back_through_every_reader() -> None:
    blocks = _blocks(60)
    cols = BlockColumns(spill_rows=None)
    for bid, blk in blocks.items():
        cols.put(bid, blk)
    ids = list(blocks)
    rng = np.random.default_rng(1)
    scatters = {bid: rng.normal(size=(4, 4)) for bid in ids[:40]}
    for bid, C in scatters.items():
        cols.hold(bid, C)
    cols.spill()
    assert cols.spilled[ids[:40]].all() and not cols.spilled[ids[40:]].any() and cols.held_rows == 0
    assert cols.rows == sum(blocks[b].points.shape[0] for b in ids[40:])  # memory keeps the rest only
    assert all(same_block(cols.block(b), blocks[b]) for b in ids)
    assert all(np.array_equal(cols.scatter_of(b), scatters[b]) for b in ids[:40])
    order = np.array(ids[::-1][::3] + ids[5:9], dtype=np.int64)  # mixed, any order
    pts, al, sg, starts = cols.gather(order)
    assert np.array_equal(pts, np.concatenate([blocks[b].points for b in order.tolist()]))
    assert np.array_equal(sg, np.concatenate([blocks[b].sigmas for b in order.tolist()]))
    for i, b in enumerate(order.tolist()):
        if blocks[b].alphas is not None:
            assert np.array_equal(al[starts[i]:starts[i + 1]], blocks[b].alphas)
    # a spilled block held again (its plane merged) keeps its new scatter through the next spill
    C = rng.normal(size=(4, 4))
    cols.hold(ids[0], C)
    for bid in ids[40:50]:
        cols.hold(bid, scatters.setdefault(bid, rng.normal(size=(4, 4))))
    cols.drop(ids[1])
    cols.spill()
    assert np.array_equal(cols.scatter_of(ids[0]), C)
    assert all(np.array_equal(cols.scatter_of(b), scatters[b]) for b in ids[2:50])
    assert not cols.has(ids[1]) and cols.count == len(ids) - 1
    assert all(same_block(cols.block(b), blocks[b]) for b in ids if b != ids[1])
    cols.release()
    assert not cols.held.any() and cols.disk.rows("scatters") == 0
    assert all(same_block(cols.block(b), blocks[b]) for b in ids if b != ids[1])
    folder = cols.disk.folder
    assert folder is not None and folder.exists()
    cols.close()
    assert not folder.exists()


def _walk(scene: Scene, spill_rows: int | None, section_knots: int) -> Backend:
    """The box-room walk read knot by knot with a short window (blocks held early), a merge of
    two planes and a removal of held blocks midway, then the final batch (in sections of
    ``section_knots``) and a trim."""
    rng = np.random.default_rng(7)
    be = Backend(replace(backend_defaults(), window_knots=6, batch_section_knots=section_knots, batch_whole_knots=0))
    be.blocks.cols.spill_rows = spill_rows
    for j, (n, d) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
        be.add_plane(j, n + rng.normal(0.0, 0.01, 3), d + rng.normal(0.0, 0.02), horizontal=j < 2)
    be.add_plane(99, scene.planes[3, :3], scene.planes[3, 3])  # plane 3 seen twice: merged midway
    by_knot: dict[int, list[dict]] = {}
    for b in scene.blocks:
        by_knot.setdefault(b["knot"], []).append(b)
    for i, t in enumerate(scene.knot_times):
        be.add_pose(t, scene.knot_poses[0] if i == 0 else be.predict_pose(t))
        for b in by_knot.get(i - 1, []):
            j = 99 if b["plane"] == 3 and i % 2 and i <= len(scene.knot_times) // 2 else b["plane"]
            be.add_observations(b["knot"], j, b["points_body"], b["alphas"], b["sigmas"])
        if i >= 8:
            be.step()
        if i == len(scene.knot_times) // 2:
            be.merge_planes(3, 99)
            held = np.flatnonzero(be.blocks.cols.held)
            for bid in held[:: max(1, len(held) // 5)].tolist():
                be.remove_observations(bid)
    be.batch_optimize()
    be.trim_observations(2.0, 0.001)
    be.batch_optimize(2)
    return be


@pytest.mark.parametrize("section_knots", [10_000, 23])
def test_a_walk_with_spilling_is_bit_for_bit_the_walk_without(section_knots: int) -> None:
    scene = make_scene(duration=1.5, beams=61, sigma_range=0.003, seed=11)
    kept = _walk(scene, None, section_knots)
    spilled = _walk(scene, 0, section_knots)  # every window step spills its held blocks
    assert spilled.sections.needed() == (section_knots < scene.knot_times.size)
    assert spilled.blocks.cols.disk.rows("points") > 0 and kept.blocks.cols.disk.folder is None
    assert np.array_equal(kept.poses(), spilled.poses())
    for a, b in zip(kept.planes(), spilled.planes(), strict=True):
        assert np.array_equal(a, b)
    assert list(kept.blocks.blocks) == list(spilled.blocks.blocks)
    assert all(np.array_equal(kept.block(b).points, spilled.block(b).points) for b in kept.blocks.blocks)
