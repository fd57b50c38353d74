"""The sweep's result table ``DIR/results.parquet``: one row per cell, keyed by ``cell_id``.

Only the sweep's parent process writes it. Appending rewrites the whole table into a
temporary file renamed over the old one, so a reader or a crash never sees a partial table.
A row for a cell already in the table replaces it (a retried failure).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from common.atomic import atomic_path

RESULTS_NAME = "results.parquet"


def results_path(out_dir: str | Path) -> Path:
    return Path(out_dir) / RESULTS_NAME


def read_results(path: str | Path) -> pd.DataFrame:
    """The table, or an empty one when the file does not exist yet."""
    p = Path(path)
    if not p.exists():
        return pd.DataFrame()
    try:
        return pd.read_parquet(p)
    except Exception as e:  # pyarrow raises several types for a corrupt file
        raise ValueError(f"{p}: not a readable results table ({e})") from None


def append_rows(path: str | Path, rows: Iterable[dict[str, Any]]) -> pd.DataFrame:
    """Add ``rows`` to the table at ``path`` (atomically); returns the new table."""
    new = pd.DataFrame(list(rows))
    old = read_results(path)
    if new.empty:
        return old
    if not old.empty and "cell_id" in old:
        old = old[~old["cell_id"].isin(new["cell_id"])]
    table = pd.concat([old, new], ignore_index=True) if not old.empty else new
    with atomic_path(path) as tmp:
        table.to_parquet(tmp, index=False)
    return table


def finished_cells(table: pd.DataFrame, retry_failed: bool = False) -> set[str]:
    """Cell ids that a resumed sweep skips: every recorded cell, or only the successful ones."""
    if table.empty or "cell_id" not in table:
        return set()
    if retry_failed:
        table = table[table["status"] == "ok"]
    return set(table["cell_id"].astype(str))
