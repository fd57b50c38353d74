"""Running the cells of a sweep: in-process, on a local process pool or on a Dask cluster.

The parent process submits every cell not yet in ``results.parquet``, and appends each row
as its cell finishes (a tqdm bar shows progress). The cell function (``run_cell`` by default,
injectable for tests) runs in the workers; an exception escaping it is recorded as a failed
cell, so one bad cell never stops the others. Cells run grouped by simulation so that the
first cell of a group simulates and the others find the bag in the cache.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from tqdm import tqdm

from backpack_slam.sweep.cell import STATUS_FAILED, STATUS_OK, one_line_error, run_cell
from backpack_slam.sweep.plan import Cell
from backpack_slam.sweep.results import append_rows, finished_cells, read_results, results_path

CellFn = Callable[[Cell, str], dict[str, Any]]


@dataclass
class SweepSummary:
    n_cells: int  # in the grid
    n_skipped: int  # already finished before this run
    n_ok: int = 0
    n_failed: int = 0
    wall_time: float = 0.0
    failed: list[tuple[str, str]] = field(default_factory=list)  # (variant, error)


def _failed_row(cell: Cell, e: BaseException) -> dict[str, Any]:
    return cell.describe() | {"status": STATUS_FAILED, "stage": "worker", "error": one_line_error(e)}


def _limit_threads() -> None:
    """One BLAS/OpenMP thread per worker process, the pool being the parallelism. Set in the
    parent before the pool starts: spawned children inherit the environment, and the
    variables only act if set before numpy loads (it loads while the child unpickles)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _inline(fn: CellFn, cells: list[Cell], out: str) -> Iterator[tuple[Cell, dict[str, Any]]]:
    for c in cells:
        try:
            yield c, fn(c, out)
        except Exception as e:
            yield c, _failed_row(c, e)


def _pool(fn: CellFn, cells: list[Cell], out: str, workers: int) -> Iterator[tuple[Cell, dict[str, Any]]]:
    # spawn: gtsam, open3d and numba's threads do not survive fork() reliably
    _limit_threads()
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as ex:
        futures: dict[Future[dict[str, Any]], Cell] = {ex.submit(fn, c, out): c for c in cells}
        try:
            for f in as_completed(futures):
                c = futures[f]
                try:
                    yield c, f.result()
                except BrokenProcessPool:
                    raise RuntimeError(
                        "a sweep worker process died (out of memory?); finished cells are saved, rerun to resume"
                    ) from None
                except Exception as e:
                    yield c, _failed_row(c, e)
        finally:
            for f in futures:
                f.cancel()


def _dask(fn: CellFn, cells: list[Cell], out: str, client: Any) -> Iterator[tuple[Cell, dict[str, Any]]]:
    from distributed import as_completed as dask_completed

    futures = {client.submit(fn, c, out, key=f"sweep-cell-{c.cell_id}", pure=False): c for c in cells}
    try:
        for f in dask_completed(list(futures)):
            c = futures[f]
            try:
                yield c, f.result()
            except Exception as e:
                yield c, _failed_row(c, e)
    finally:
        client.cancel([f for f in futures if not f.done()])


def run_sweep(
    cells: list[Cell],
    out_dir: str | Path,
    workers: int = 1,
    dask: str | Any | None = None,
    cell_fn: CellFn = run_cell,
    retry_failed: bool = False,
    progress: bool = True,
) -> SweepSummary:
    """Run every cell of ``cells`` not finished in ``out_dir`` and record the rows.

    ``workers``: 0 runs in this process; N >= 1 a spawn process pool of N workers.
    ``dask``: a scheduler address (``tcp://host:8786``) or a ``distributed.Client``; the
    workers must be able to import backpack_slam and see ``out_dir`` (a shared folder).
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table_path = results_path(out)
    done = finished_cells(read_results(table_path), retry_failed)
    todo = [c for c in cells if c.cell_id not in done]
    summary = SweepSummary(n_cells=len(cells), n_skipped=len(cells) - len(todo))
    if not todo:
        summary.wall_time = time.perf_counter() - t0
        return summary
    # absolute: workers may run elsewhere (another cwd)
    out_s = str(out.resolve())
    own_client = None
    if dask is not None:
        if isinstance(dask, str):
            from distributed import Client

            own_client = Client(dask)
            client = own_client
        else:
            client = dask
        results = _dask(cell_fn, todo, out_s, client)
    elif workers == 0:
        results = _inline(cell_fn, todo, out_s)
    elif workers >= 1:
        results = _pool(cell_fn, todo, out_s, workers)
    else:
        raise ValueError(f"workers must be >= 0, got {workers}")
    bar = tqdm(total=len(todo), unit="cell", desc="sweep", disable=not progress)
    try:
        for cell, row in results:
            append_rows(table_path, [row])
            if row.get("status") == STATUS_OK:
                summary.n_ok += 1
            else:
                summary.n_failed += 1
                summary.failed.append((cell.variant, str(row.get("error", ""))))
            bar.set_postfix(ok=summary.n_ok, failed=summary.n_failed)
            bar.update(1)
    finally:
        bar.close()
        close = getattr(results, "close", None)
        if close is not None:
            close()
        if own_client is not None:
            own_client.close()
    summary.wall_time = time.perf_counter() - t0
    return summary
