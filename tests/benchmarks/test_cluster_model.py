"""benchmarks/cluster_model.py: the model read from a run's report, and its predictions
against the equations worked by hand on a report whose numbers are round."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))

import cluster_model as cm  # noqa: E402

N_ROWS, TILE = 1000, 250


def _costs(kind, passes, tasks, task_seconds, max_task, read=0, written=0, shared_read=0,
           vectors=0, read_calls=0, write_calls=0, peak=100 << 20):
    return {"kind": kind, "passes": passes, "tasks": tasks, "threads": 1,
            "wall_seconds": task_seconds, "task_seconds": task_seconds,
            "max_task_seconds": max_task, "kernel_seconds": 0.0, "bytes_read": read,
            "bytes_written": written, "read_calls": read_calls, "write_calls": write_calls,
            "bytes_read_shared": shared_read, "shared_bytes": vectors, "peak_resident": peak}


def _report():
    """One spectral pass (4 tasks of 0.5 s) and two terms of one power pass each
    (4 tasks of 1 s; term 2 reads a 1 MB right factor), on one thread."""
    power1 = _costs("power", 1, 4, 4.0, 1.0, read=4000, written=8000, write_calls=8)
    power2 = _costs("power", 1, 4, 4.0, 1.0, read=1_004_000, written=8000,
                    shared_read=1_000_000, read_calls=200, write_calls=8, vectors=12000,
                    peak=200 << 20)
    spectral = _costs("matvec-M", 1, 4, 2.0, 0.5)
    total = [spectral, {**power1, "passes": 2, "tasks": 8, "task_seconds": 8.0,
                        "wall_seconds": 8.0, "bytes_read": 1_008_000, "bytes_written": 16000,
                        "read_calls": 200, "write_calls": 16, "bytes_read_shared": 1_000_000,
                        "shared_bytes": 12000, "peak_resident": 200 << 20}]
    return {"n": N_ROWS, "nnz_T": 10 * N_ROWS, "tile_size": TILE, "threads": 1,
            "seconds_spectral_radius": 2.0, "memory": "no memory limit",
            "history": [{"term": 1, "seconds": 4.0 + 0.4, "nnz_P": 5000, "tasks": [power1]},
                        {"term": 2, "seconds": 4.0 + 0.4, "nnz_P": 2000, "tasks": [power2]}],
            "task_costs": total}


#: Storage and scheduler that cost nothing, so that the equations are checked term by term.
FREE = cm.Storage("free", math.inf, math.inf, 0.0)
NO_SCHEDULER = cm.Scheduler("none", 0.0, 0.0, math.inf)


def test_the_record_is_read_per_row():
    run = cm.RecordedRun.from_report(_report(), FREE)
    kinds = [(p.term, p.kind, p.passes) for p in run.passes]
    assert kinds == [(None, "matvec-M", 1), (1, "power", 1), (2, "power", 1)]
    spectral, p1, p2 = run.passes
    assert spectral.compute_per_row == pytest.approx(2.0 / N_ROWS)
    assert p1.compute_per_row == pytest.approx(4.0 / N_ROWS)
    assert p2.shared_read_per_row == pytest.approx(1000.0)
    assert p2.read_per_row == pytest.approx(4.0)
    assert p2.imbalance == pytest.approx(1.0)
    assert run.publish_per_tile_row == {1: pytest.approx(0.1), 2: pytest.approx(0.1)}
    assert run.seconds_terms == pytest.approx(8.8)


def test_one_worker_at_the_recorded_size_gives_the_recorded_time_back():
    run = cm.RecordedRun.from_report(_report(), FREE)
    p = cm.predict(run, N_ROWS, 1, FREE, NO_SCHEDULER, tile_size=TILE)
    assert p.seconds_spectral == pytest.approx(2.0)
    assert p.seconds_terms == pytest.approx((4.4, 4.4))
    assert p.seconds == pytest.approx(10.8)


def test_workers_divide_the_row_blocks_and_the_broadcast_does_not_shrink():
    """4 tasks on 4 workers: one wave of each pass; M's rows rebuilt on the workers
    that have not met them (the first pass built them, at 0.5 ms a row); the 1 MB
    factor read by every worker at 1 MB/s."""
    run = cm.RecordedRun.from_report(_report(), FREE)
    slow = cm.Storage("1 MB/s", 1e6, math.inf, 0.0)
    p = cm.predict(run, N_ROWS, 4, slow, NO_SCHEDULER, tile_size=TILE)
    m_build = 2.0 / N_ROWS * TILE  # a task's share of the first pass
    rows_io = lambda r, w: (r + w) * TILE / 1e6  # noqa: E731
    term1 = 1.0 + rows_io(4, 8) + 0.75 * m_build + 0.4
    term2 = 1.0 + rows_io(4, 8) + 0.75 ** 2 * m_build + 1.0 + 0.4
    assert p.seconds_terms == pytest.approx((term1, term2))
    assert p.seconds_spectral == pytest.approx(0.5)


def test_the_scheduler_bounds_a_pass_by_its_tasks():
    run = cm.RecordedRun.from_report(_report(), FREE)
    busy = cm.Scheduler("10 s a task", 10.0, 0.0, math.inf)
    p = cm.predict(run, N_ROWS, 4, FREE, busy, tile_size=TILE)
    assert p.seconds_spectral == pytest.approx(4 * 10.0)  # serial on the scheduler


def test_bigger_scenes_cost_more_and_more_workers_help_until_the_broadcast():
    run = cm.RecordedRun.from_report(_report(), FREE)
    table = cm.prediction_table(run, sizes=(cm.FULL_HD,), storages=(cm.SHARED_FS,))
    seconds = [p.seconds for p in table]
    assert seconds[1] < seconds[0]
    assert all(p.memory_per_worker > 0 for p in table)
    bigger = cm.predict(run, cm.UHD_4K, 8, cm.SHARED_FS, cm.DASK_DISTRIBUTED)
    assert bigger.seconds > table[3].seconds  # N = 8 at full HD


def test_a_report_without_task_costs_is_refused():
    report = _report()
    for h in report["history"]:
        h["tasks"] = []
    with pytest.raises(ValueError, match="no task costs"):
        cm.RecordedRun.from_report(report, FREE)
