"""Resumable, parallel execution of independent tasks (trials, data set samples).

- Each task ``i`` gets its own seed derived from the run seed (``numpy.random.SeedSequence``), so
  results do not depend on the number of workers or the order of completion.
- Results are appended to a log file by the main process as each task completes (one writer, so no
  duplicates); a crash loses at most the tasks in flight.
- A rerun reads the log, skips finished tasks and runs the rest.
- Tasks run on a Dask ``LocalCluster`` by default, on an existing cluster with ``scheduler``, or
  in-process with ``workers=0`` (debugging, tests). Dask retries a task whose worker died.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import os
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from fluoronav.errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "CsvLog",
    "JsonlLog",
    "ResultLog",
    "finish_row",
    "mark_failed",
    "new_row",
    "run_tasks",
    "task_seeds",
]


def task_seeds(seed: int, n: int) -> list[int]:
    """Independent 63-bit seeds for tasks ``0..n−1`` of a run with ``seed``."""
    children = np.random.SeedSequence(seed).spawn(n)
    return [int(c.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1)) for c in children]


class ResultLog:
    """Append-only result file keyed by an integer id column."""

    path: Path
    id_key: str

    def done_ids(self) -> set[int]:
        return {int(r[self.id_key]) for r in self.read()}

    def read(self) -> list[dict[str, Any]]:
        raise NotImplementedError

    def append(self, row: dict[str, Any]) -> None:
        raise NotImplementedError


def _fsync_append(path: Path, text: str) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())


def _drop_partial_last_line(path: Path) -> None:
    """A crash during a write can leave a last line without its newline: remove it."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


class JsonlLog(ResultLog):
    """One JSON object per line (``manifest.jsonl``)."""

    def __init__(self, path: str | Path, *, id_key: str = "id") -> None:
        self.path = Path(path)
        self.id_key = id_key
        _drop_partial_last_line(self.path)

    def read(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        rows = []
        for line in self.path.read_text(encoding="utf-8").splitlines():
            if line.strip():
                with contextlib.suppress(json.JSONDecodeError):
                    rows.append(json.loads(line))
        return rows

    def append(self, row: dict[str, Any]) -> None:
        _fsync_append(self.path, json.dumps(row) + "\n")


class CsvLog(ResultLog):
    """CSV with a fixed header (``trials.csv``); values that are lists are JSON-encoded.

    A file resumed must have been started with these columns, or one list must begin with the
    other (columns added at the end by a later version: the rows stay aligned); otherwise
    :class:`InputError`, before any row is written out of line.
    """

    def __init__(self, path: str | Path, columns: Sequence[str], *, id_key: str = "trial") -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.id_key = id_key
        _drop_partial_last_line(self.path)
        if not self.path.exists() or self.path.stat().st_size == 0:
            _fsync_append(self.path, ",".join(self.columns) + "\n")
            return
        with open(self.path, newline="", encoding="utf-8") as fh:
            header = next(csv.reader(fh), [])
        n = min(len(header), len(self.columns))
        if header[:n] != self.columns[:n]:
            raise InputError(
                self.path,
                "written with other columns (another fluoronav version?): resume it with that version "
                "or give a new --out",
            )

    def read(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        with open(self.path, newline="", encoding="utf-8") as fh:
            return [r for r in csv.DictReader(fh) if r.get(self.id_key) not in (None, "")]

    def append(self, row: dict[str, Any]) -> None:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=self.columns, extrasaction="ignore", lineterminator="\n")
        writer.writerow({k: json.dumps(v) if isinstance(v, list | dict) else v for k, v in row.items()})
        _fsync_append(self.path, buf.getvalue())


def new_row(task_id: int, seed: int, workflow: str) -> dict[str, Any]:
    """The start of a study row: id, seed, workflow, status ``ok`` until :func:`mark_failed`."""
    return {"trial": task_id, "seed": seed, "workflow": workflow, "status": "ok", "reason": ""}


def mark_failed(row: dict[str, Any], exc: BaseException, task_id: int) -> None:
    """Record a failed task in its row (status and a one-line reason); the row is still written."""
    row["status"] = "failed"
    row["reason"] = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
    log.debug("task %d failed:\n%s", task_id, traceback.format_exc())


def finish_row(row: dict[str, Any], t0: float) -> dict[str, Any]:
    """Add the elapsed ``seconds`` since ``t0`` and replace non-finite floats by None (empty cells)."""
    row["seconds"] = time.perf_counter() - t0
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


def _iter_local(
    fn: Callable[[int, int], dict[str, Any]], todo: list[tuple[int, int]]
) -> Iterator[dict[str, Any]]:
    for tid, s in todo:
        yield fn(tid, s)


@contextlib.contextmanager
def _numba_threads(n: int) -> Iterator[None]:
    """Worker processes started in this context use ``n`` numba threads (the cores over the workers):
    a numba kernel of each worker taking every core made the OpenMP threads of the workers wait on
    each other (the environment is read when numba is imported, so it is set for the spawn)."""
    old = os.environ.get("NUMBA_NUM_THREADS")
    os.environ["NUMBA_NUM_THREADS"] = str(n)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("NUMBA_NUM_THREADS", None)
        else:
            os.environ["NUMBA_NUM_THREADS"] = old


@contextlib.contextmanager
def _client(scheduler: str | None, workers: int | None) -> Iterator[Any]:
    from dask.distributed import Client, LocalCluster  # heavy: dask, not needed in-process

    if scheduler:
        client = Client(scheduler)
        try:
            yield client
        finally:
            client.close()
        return
    n = workers if workers else max(1, min(2, os.cpu_count() or 1))
    with (
        _numba_threads(max(1, (os.cpu_count() or 1) // n)),
        LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_tasks(
    fn: Callable[[int, int], dict[str, Any]],
    n: int,
    seed: int,
    result_log: ResultLog,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    description: str = "tasks",
    on_result: Callable[[dict[str, Any]], None] | None = None,
    retries: int = 2,
) -> list[dict[str, Any]]:
    """Run ``fn(task_id, task_seed) -> row`` for task ids ``0..n−1`` not yet in ``result_log``.

    Args:
        fn: a picklable function; its row must contain ``result_log.id_key`` = task_id.
        n: number of tasks in the whole run.
        seed: run seed; task seeds come from :func:`task_seeds`.
        result_log: where rows are appended as they complete.
        scheduler: address of an existing Dask scheduler; None = a LocalCluster.
        workers: LocalCluster worker processes (default min(2, cores)); 0 = run in this process.
        description: progress bar label.
        on_result: called in this process with each new row after it is written.
        retries: how often Dask retries a task whose worker died.

    Returns:
        The rows written in this call.
    """
    seeds = task_seeds(seed, n)
    done = result_log.done_ids()
    todo = [(i, seeds[i]) for i in range(n) if i not in done]
    if done:
        log.info("%s: %d of %d already done, resuming", description, len(done & set(range(n))), n)
    written: list[dict[str, Any]] = []
    bar = tqdm(
        total=n, initial=n - len(todo), desc=description, unit="task", dynamic_ncols=True, disable=None
    )

    def _handle(row: dict[str, Any]) -> None:
        result_log.append(row)
        written.append(row)
        if on_result is not None:
            on_result(row)
        bar.update(1)

    try:
        if not todo:
            return written
        if workers == 0 and not scheduler:
            for row in _iter_local(fn, todo):
                _handle(row)
            return written
        from dask.distributed import as_completed  # heavy: dask, not needed in-process

        with _client(scheduler, workers) as client:
            futures = [
                client.submit(fn, tid, s, pure=False, retries=retries, key=f"{description}-{tid}-{s}")
                for tid, s in todo
            ]
            for fut in as_completed(futures):
                _handle(fut.result())
        return written
    finally:
        bar.close()
