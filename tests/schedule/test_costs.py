"""What the tasks cost (bigT.schedule.costs): a thread's I/O counted against the bytes
on disk, a pass's costs summed by kind, the record's round trip through the inverse
store's history, and a run's report holding them."""

import json
import os
import threading

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.algorithms.records import TermRecord
from bigT.schedule import matvec as mv
from bigT.schedule.costs import (CostLedger, SharedRead, TaskCosts, by_kind,
                                 shared_read_bytes, thread_io)
from bigT.schedule.runner import ThreadRunner
from bigT.storage import disk_bytes, from_scipy

linux_only = pytest.mark.skipif(not os.path.exists("/proc/thread-self/io"),
                                reason="per-thread I/O counters are Linux's")


@linux_only
def test_thread_io_counts_this_threads_file_reads_and_writes(tmp_path):
    path = tmp_path / "blob"
    payload = os.urandom(1 << 20)
    before = thread_io()
    path.write_bytes(payload)
    written = thread_io().minus(before)
    assert written.written_bytes == len(payload)
    assert written.write_calls >= 1

    other = {}

    def read_elsewhere():  # another thread's reads are not this thread's
        other["io"] = thread_io()
        path.read_bytes()
        other["delta"] = thread_io().minus(other["io"])

    before = thread_io()
    t = threading.Thread(target=read_elsewhere)
    t.start()
    t.join()
    mine = thread_io().minus(before)
    assert other["delta"].read_bytes >= len(payload)
    assert mine.read_bytes < 4096  # only the counter file itself


@linux_only
def test_shared_read_counts_what_is_read_inside_it(tmp_path):
    path = tmp_path / "blob"
    path.write_bytes(b"x" * 100_000)
    start = shared_read_bytes()
    path.read_bytes()
    assert shared_read_bytes() == start
    with SharedRead():
        path.read_bytes()
    assert 100_000 <= shared_read_bytes() - start < 104_096


@linux_only
def test_a_matvec_pass_reads_its_store_once(tmp_path):
    """Every tile row read once (not cached): the tasks' reads are the store's files,
    metadata included, and nothing is written."""
    rng = np.random.default_rng(0)
    A = sp.random(600, 600, density=0.05, format="csr", random_state=rng, dtype=np.float32)
    store = from_scipy(A, tmp_path / "A.zarr", tile_size=100)
    runner = ThreadRunner(2)
    spec = mv.matvec_spec("matvec-A", str(store.path), 600, 100, np.float32,
                          cache_tiles=False)
    V = rng.standard_normal((600, 3))
    Y = mv.matvec(runner, spec, V)
    np.testing.assert_allclose(Y, A @ V, rtol=1e-5)
    (costs,) = runner.costs.total()
    assert (costs.kind, costs.passes, costs.tasks, costs.threads) == ("matvec-A", 1, 6, 2)
    on_disk = disk_bytes(store.path)
    assert 0.5 * on_disk <= costs.bytes_read <= on_disk + 64 * 1024
    assert costs.bytes_written == 0 and costs.bytes_read_shared == 0
    assert costs.read_calls >= 6
    assert costs.shared_bytes == V.nbytes
    assert 0 < costs.max_task_seconds <= costs.task_seconds
    assert costs.wall_seconds >= costs.max_task_seconds
    assert costs.peak_resident > 0


def test_costs_sum_by_kind_and_by_time():
    a = TaskCosts("power", passes=1, tasks=4, threads=2, wall_seconds=1.0, task_seconds=1.5,
                  max_task_seconds=0.5, bytes_read=100, bytes_written=10, peak_resident=7)
    b = TaskCosts("power", passes=1, tasks=4, threads=1, wall_seconds=2.0, task_seconds=1.0,
                  max_task_seconds=0.75, bytes_read=50, bytes_written=5, peak_resident=3)
    c = TaskCosts("matvec-M", passes=1, tasks=4, threads=2, task_seconds=0.2)
    both = a.plus(b)
    assert (both.passes, both.tasks, both.threads) == (2, 8, 2)
    assert (both.wall_seconds, both.task_seconds, both.max_task_seconds) == (3.0, 2.5, 0.75)
    assert (both.bytes_read, both.bytes_written, both.peak_resident) == (150, 15, 7)
    assert by_kind([a, c, b]) == (both, c)
    ledger = CostLedger()
    ledger.add(1.0, a)
    ledger.add(2.0, c)
    ledger.add(3.0, b)
    assert ledger.since(2.0) == (c, b)
    assert ledger.total() == (both, c)


def test_costs_round_trip_through_the_term_record():
    costs = TaskCosts("power", passes=1, tasks=3, threads=2, wall_seconds=1.25,
                      task_seconds=2.0, max_task_seconds=0.75, kernel_seconds=1.0,
                      bytes_read=10, bytes_written=20, read_calls=3, write_calls=4,
                      bytes_read_shared=5, shared_bytes=6, peak_resident=7)
    record = TermRecord(2, 1.5, 10, 20, 3, 0, 0, 0.1, 0.2, tasks=(costs,))
    d = record.to_dict()
    assert d["tasks"] == [costs.to_dict()]
    assert TermRecord.from_dict(d) == record
    bare = TermRecord(2, 1.5, 10, 20, 3, 0, 0, 0.1, 0.2)
    assert "tasks" not in bare.to_dict()  # as records written before they were kept
    assert TermRecord.from_dict(bare.to_dict()).tasks == ()
    with pytest.raises(ValueError):
        TaskCosts.from_dict({**costs.to_dict(), "bytes_read": -1})


@linux_only
def test_an_out_of_core_run_records_its_tasks(tmp_path):
    """Each term's record and the report hold the tasks' costs; the power passes
    write what the term stores hold (P and X, each tile row once) and read the held
    term's P whole once (the process's shared factor)."""
    rng = np.random.default_rng(1)
    n = 256
    A = sp.random(n, n, density=0.04, random_state=rng, format="csr")
    A = (A * (0.4 / max(abs(A).sum(0).max(), 1e-9))).tocsr()
    T = from_scipy(sp.eye(n, format="csr") + A, tmp_path / "T.zarr", tile_size=64)
    out = tmp_path / "X.zarr"
    rep = bigT.stratified_inverse(T, out, terms=3, prune=1e-6, progress=False,
                                  in_memory=False, workers=2)
    kinds = {c.kind for c in rep.task_costs}
    assert {"diag", "power"} <= kinds
    for record in rep.history:
        by = {c.kind: c for c in record.tasks}
        assert by[("diag" if record.term == 0 else "power")].tasks == n // 64
    power = {c.kind: c for c in rep.history[2].tasks}["power"]
    assert power.bytes_written > 0 and power.bytes_read > power.bytes_read_shared > 0
    root = json.loads((out / "zarr.json").read_text())["attributes"]["bigT_inverse"]
    kept = TermRecord.from_dict(root["history"][2])
    assert kept == rep.history[2]  # kept in the store's history, as reported
    assert "tasks by kind: " in rep.table()
