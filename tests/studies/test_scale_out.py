"""Scale-out failure modes: a worker killed mid-task, the whole process killed mid-run."""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fluoronav.runner import CsvLog, run_tasks, task_seeds

COLUMNS = ["trial", "seed", "value"]


def _value(seed: int) -> float:
    return float(np.random.default_rng(seed).normal())


def _dying_task(tid: int, seed: int, *, marker_dir: str) -> dict:
    """Kills its worker process the first time task 3 runs (a crash, not an exception)."""
    marker = Path(marker_dir) / f"attempt-{tid}"
    if tid == 3 and not marker.exists():
        marker.write_text("died once", encoding="utf-8")
        os._exit(1)
    return {"trial": tid, "seed": seed, "value": _value(seed)}


def test_a_killed_worker_is_retried_and_no_trial_is_lost_or_duplicated(tmp_path: Path) -> None:
    log = CsvLog(tmp_path / "trials.csv", COLUMNS)
    task = functools.partial(_dying_task, marker_dir=str(tmp_path))
    run_tasks(task, 12, 5, log, workers=2, description="killed-worker")
    assert (tmp_path / "attempt-3").exists()  # the worker did die once
    ids = [int(r["trial"]) for r in CsvLog(tmp_path / "trials.csv", COLUMNS).read()]
    assert sorted(ids) == list(range(12))


_SCRIPT = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from fluoronav.runner import CsvLog, run_tasks, task_seeds

    def task(tid, seed):
        time.sleep(0.15)
        return {"trial": tid, "seed": seed, "value": float(np.random.default_rng(seed).normal())}

    run_tasks(task, 12, 5, CsvLog(sys.argv[1], ["trial", "seed", "value"]), workers=0)
    """
)


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_a_killed_process_resumes_with_exactly_every_trial_once(tmp_path: Path) -> None:
    path = tmp_path / "trials.csv"
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script), str(path)], stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            if path.exists() and len(CsvLog(path, COLUMNS).read()) >= 4:
                break
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)  # no clean-up, as a power cut or an OOM kill
    finally:
        proc.wait(timeout=30)
    partial = [int(r["trial"]) for r in CsvLog(path, COLUMNS).read()]
    assert 4 <= len(partial) < 12
    subprocess.run([sys.executable, str(script), str(path)], check=True, stderr=subprocess.DEVNULL)
    rows = CsvLog(path, COLUMNS).read()
    assert sorted(int(r["trial"]) for r in rows) == list(range(12))
    # the resumed rows equal those of a run that was never interrupted
    ref = run_tasks(
        lambda tid, seed: {"trial": tid, "seed": seed, "value": _value(seed)},
        12,
        5,
        CsvLog(tmp_path / "ref.csv", COLUMNS),
        workers=0,
    )
    by_id = {int(r["trial"]): float(r["value"]) for r in rows}
    assert all(abs(by_id[r["trial"]] - r["value"]) < 1e-12 for r in ref)


def test_an_existing_scheduler_runs_the_tasks(tmp_path: Path) -> None:
    # the --scheduler path: a cluster started elsewhere, only its address is given to the run
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        task = functools.partial(_dying_task, marker_dir=str(tmp_path))
        rows = run_tasks(
            task, 8, 9, CsvLog(tmp_path / "trials.csv", COLUMNS), scheduler=cluster.scheduler_address
        )
    assert sorted(r["trial"] for r in rows) == list(range(8))
    ref = {tid: _value(s) for tid, s in enumerate(task_seeds(9, 8))}
    assert all(abs(r["value"] - ref[r["trial"]]) < 1e-12 for r in rows)


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_a_killed_12_trial_study_resumes_to_exactly_12_trials(tmp_path: Path) -> None:
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "fluoronav", "study", "centerline", "--trials", "12", "--seed", "4"]
    cmd += ["--out", str(out), "--workers", "0", "--oracle-landmarks", "--image-size", "384"]
    csv_path = out / "trials.csv"
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 900.0
        while time.monotonic() < deadline and proc.poll() is None:
            if csv_path.exists() and len(CsvLog(csv_path, ["trial"]).read()) >= 3:
                break
            time.sleep(0.5)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert 3 <= len(CsvLog(csv_path, ["trial"]).read()) < 12
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    trials = [int(r["trial"]) for r in CsvLog(csv_path, ["trial"]).read()]
    assert sorted(trials) == list(range(12))
    summary = __import__("json").loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["trials"] == 12 and summary["completed"] + summary["failed"] == 12
