"""The back end's block columns (slam.backend.blocks.BlockColumns): blocks stored as rows keep
their data through growth and the rewrite of removed blocks' rows."""

from __future__ import annotations

import numpy as np
from block_helpers import same_block

from slam.backend.blocks import BlockColumns, ObservationBlock


def _blocks(n: int, rows: int, seed: int = 3) -> dict[int, ObservationBlock]:
    rng = np.random.default_rng(seed)
    out = {}
    for b in range(n):
        two = b % 3 != 0
        out[2 * b + 1] = ObservationBlock(b, b % 7, rng.normal(size=(rows, 3)),
                                          rng.uniform(0, 1, rows) if two else None, rng.uniform(0.01, 0.02, rows))
    return out



def test_blocks_survive_growth_and_compaction() -> None:
    blocks = _blocks(100, 1000)
    cols = BlockColumns()
    for bid, blk in blocks.items():
        cols.put(bid, blk)
    gone = [bid for i, bid in enumerate(blocks) if i % 10 < 7]
    for bid in gone:
        cols.drop(bid)
    live = [bid for bid in blocks if bid not in gone]
    # the rows were rewritten when the garbage passed 65,536 rows (the 66th removal); 4 removals since
    assert cols.garbage == 4000 and cols.rows == 1000 * len(live) + cols.garbage
    assert cols.ids().tolist() == live and cols.count == len(live) and cols.n_points == 1000 * len(live)
    assert all(same_block(cols.block(bid), blocks[bid]) for bid in live)
    assert not any(cols.has(bid) for bid in gone) and not cols.has(0) and not cols.has(10**6)
    pts, _, sg, starts = cols.gather(np.array(live[::-1]))
    assert np.array_equal(pts, np.concatenate([blocks[b].points for b in live[::-1]]))
    assert np.array_equal(sg, np.concatenate([blocks[b].sigmas for b in live[::-1]]))
    assert starts.tolist() == [1000 * i for i in range(len(live) + 1)]


def test_block_records_are_copies() -> None:
    blk = _blocks(1, 4)[1]
    cols = BlockColumns()
    cols.put(1, blk)
    got = cols.block(1)
    got.points[:] = 0.0
    assert same_block(cols.block(1), blk)
