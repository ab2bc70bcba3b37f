"""The memory plan and the memory-bounded product (bigT.schedule.memory, blocks)."""

import numpy as np
import pytest
import scipy.sparse as sp

from bigT import config
from bigT.errors import MemoryLimitError
from bigT.schedule import blocks, memory
from bigT.schedule.memory import (M_ROW_BYTES_PER_ENTRY, MemoryPlan, plan_memory,
                                  resident_bytes, stored_bytes)

MiB = 1 << 20


def test_resident_bytes_is_this_process():
    rss = resident_bytes()
    big = np.ones(64 * MiB // 8)  # touched: 64 MiB resident
    assert resident_bytes() >= rss + 48 * MiB
    del big


def test_plan_shares_what_is_left_after_baseline_and_fixed_parts():
    plan = plan_memory(1024 * MiB, 2, n_cols=100_000, max_tile_row_nnz=1_000_000,
                       baseline=200 * MiB)
    # the kernel's workspace: 9 float64 accumulators, a mark and a list entry per
    # column, a stamp and a slot per row of the right factor (n x n), block marks
    workspace = 9 * 8 * 100_000 + 16 * 100_000 + 16 * 100_000 + 100_000 // 8 + 64
    fixed = M_ROW_BYTES_PER_ENTRY * 1_000_000 + workspace
    assert plan.fixed_per_task == fixed
    total = (plan.baseline + 2 * (plan.fixed_per_task + plan.work_bytes_per_task)
             + plan.cache_bytes + plan.whole_bytes)
    # all of it, less the headroom (up to rounding of the integer shares)
    assert 0 <= 1024 * MiB - config.MEMORY_HEADROOM_BYTES - total <= 2
    assert plan.cache_bytes > 0 and plan.whole_bytes > 0 and plan.work_bytes_per_task > 0
    assert "memory limit 1024 MiB" in plan.describe()


def test_plan_refuses_a_limit_below_the_fixed_parts():
    with pytest.raises(MemoryLimitError, match=r"memory_limit 300 MiB is too small.*already "
                       r"holds 250 MiB.*2 tasks.*give at least (\d+) MiB") as e:
        plan_memory(300 * MiB, 2, n_cols=10_000, max_tile_row_nnz=100_000,
                    baseline=250 * MiB)
    need = int(str(e.value).split("give at least ")[1].split()[0])
    plan_memory(need * MiB + MiB, 2, n_cols=10_000, max_tile_row_nnz=100_000,
                baseline=250 * MiB)  # what it asks for is enough


def test_unlimited_plan():
    plan = plan_memory(None, 2, 10, 10)
    assert plan.limit is None and plan.describe() == "no memory limit"


def test_stored_bytes():
    A = sp.random(50, 40, density=0.1, format="csr", dtype=np.float32, random_state=0)
    A.indices = A.indices.astype(np.int32)
    A.indptr = A.indptr.astype(np.int32)
    assert stored_bytes(A.nnz, 50, 4) == A.data.nbytes + A.indices.nbytes + A.indptr.nbytes


def _batches(B, row_groups):
    out = []
    for rows in row_groups:
        keep = np.zeros(B.shape[0])
        keep[rows] = 1
        part = sp.csr_array(sp.diags(keep) @ B)
        out.append(lambda part=part: part)
    return out


@pytest.mark.parametrize("max_partial", [1, 7, 50, 10**9])
def test_row_product_batched_equals_pruned_product(max_partial):
    """Any chunking of the output rows (down to one row) and any batching of B give
    scipy's product, pruned once; empty rows of L and of B included."""
    rng = np.random.default_rng(3)
    L = sp.random(30, 40, density=0.15, format="csr", random_state=1)
    L = sp.csr_array(L.multiply(rng.random((30, 40)) > 0.0))
    L = sp.csr_array(sp.diags(np.r_[np.ones(25), np.zeros(5)]) @ L)  # 5 empty rows
    B = sp.random(40, 40, density=0.2, format="csr", random_state=2)
    B = sp.csr_array(sp.diags(np.r_[np.zeros(10), np.ones(30)]) @ B)  # empty rows of B
    ref = (L @ B).toarray()
    ref[np.abs(ref) < 0.05] = 0
    work = np.diff(L.indptr) * 8.0  # multiply-adds if every row of B held 8
    got = blocks.row_product_batched(sp.csr_array(L), _batches(B, [range(0, 20), range(20, 40)]),
                                     0.05, work, max_partial)
    assert got.has_sorted_indices and got.shape == (30, 40)
    np.testing.assert_allclose(got.toarray(), ref, atol=1e-12)


def test_row_product_batched_edge_cases():
    L = sp.csr_array((4, 6))
    B = sp.csr_array(np.eye(6))
    assert blocks.row_product_batched(L, [], 0.0, np.zeros(4), 10).nnz == 0
    got = blocks.row_product_batched(L, _batches(B, [[0, 1], [2, 3, 4, 5]]), 0.0,
                                     np.zeros(4), 10)
    assert got.shape == (4, 6) and got.nnz == 0
    # everything pruned
    L = sp.csr_array(np.full((3, 6), 1e-3))
    got = blocks.row_product_batched(L, _batches(B, [[0, 1], [2, 3, 4, 5]]), 1.0,
                                     np.full(3, 6.0), 4)
    assert got.shape == (3, 6) and got.nnz == 0


def test_warns_when_output_rows_may_outgrow_the_plan():
    from bigT.errors import MemoryLimitWarning
    from bigT.schedule.memory import warn_if_rows_outgrow

    plan = MemoryPlan(limit=512 * MiB, baseline=0, fixed_per_task=0, cache_bytes=0,
                      whole_bytes=0, work_bytes_per_task=30 * MiB)
    assert not warn_if_rows_outgrow(plan, 5 * MiB, 1.5, 3, "X.zarr")  # 22.5 MiB fits
    with pytest.warns(MemoryLimitWarning, match=r"X.zarr: term 3's tile rows may hold ~45 "
                      r"MiB per task .* 30 MiB each task has under memory_limit 512 MiB"):
        assert warn_if_rows_outgrow(plan, 5 * MiB, 3.0, 3, "X.zarr")
    unlimited = plan_memory(None, 2, 10, 10)
    assert not warn_if_rows_outgrow(unlimited, 1 << 40, 10.0, 3, "X.zarr")


def test_human_bytes():
    from bigT.schedule.memory import human_bytes

    assert [human_bytes(b) for b in (12, 3 << 10, 45 * MiB, 3 << 30)] == \
        ["12 B", "3 KiB", "45 MiB", "3.00 GiB"]


@pytest.mark.skipif(memory._glibc() is None, reason="malloc_trim is glibc's")
def test_freed_heap_pages_are_handed_back():
    """64 KB arrays come from glibc's heap; freed below a live one at its top, they stay
    resident until ``return_freed_memory``."""
    before = memory.resident_bytes()
    arrays = [np.ones(8000) for _ in range(8000)]  # 8000 x 64 KB = 512 MB
    top = np.ones(8000)  # keeps the heap's top in use: no automatic trim
    grown = memory.resident_bytes() - before
    del arrays
    memory.return_freed_memory()
    after = memory.resident_bytes() - before
    assert grown > 400 << 20
    assert after < grown / 4
    assert top.sum() == 8000


def test_freed_memory_is_handed_back_only_above_the_threshold(monkeypatch):
    """A task's trim (malloc_trim) runs only where the process holds more than its
    plan's threshold: below it the next task reuses the heap's freed pages instead of
    faulting them in again (issue #30: 20 s of a full-HD run)."""
    trims = []
    monkeypatch.setattr(memory, "return_freed_memory", lambda: trims.append(1))
    monkeypatch.setattr(memory, "resident_bytes", lambda: 500 * MiB)
    assert memory.return_freed_memory_above(600 * MiB) is False
    assert memory.return_freed_memory_above(500 * MiB) is False
    assert trims == []
    assert memory.return_freed_memory_above(499 * MiB) is True
    assert trims == [1]


def test_a_plan_trims_when_a_new_task_would_not_fit_or_past_a_share_of_memory(monkeypatch):
    """Under a limit a task hands freed pages back once a new task's fixed part and
    work share no longer fit beside what the process holds (the limit kept as when
    every task trimmed); with none, once the process holds a quarter of the memory
    available when it planned more than its baseline."""
    limited = plan_memory(1024 * MiB, 2, n_cols=100_000, max_tile_row_nnz=1_000_000,
                          baseline=200 * MiB)
    assert (limited.trim_above + limited.fixed_per_task + limited.work_bytes_per_task
            + config.MEMORY_HEADROOM_BYTES) == 1024 * MiB
    assert limited.baseline < limited.trim_above < 1024 * MiB
    monkeypatch.setattr(memory, "available_memory", lambda: 8 << 30)
    free = plan_memory(None, 16, n_cols=100_000, max_tile_row_nnz=1_000_000,
                       baseline=200 * MiB)
    assert free.trim_above == 200 * MiB + 2 * (1 << 30)  # whatever the thread count


def test_a_limited_plan_is_measured_after_a_trim(monkeypatch):
    """What earlier work freed and the heap kept is no part of a new plan's baseline
    (the plan would shrink its shares, or refuse the limit)."""
    order = []
    monkeypatch.setattr(memory, "return_freed_memory", lambda: order.append("trim"))
    monkeypatch.setattr(memory, "resident_bytes", lambda: order.append("rss") or 100 * MiB)
    plan_memory(1024 * MiB, 1, n_cols=1000, max_tile_row_nnz=1000)
    assert order == ["trim", "rss"]


def test_out_of_core_tasks_trim_only_over_their_plan(tmp_path, monkeypatch):
    """The tasks of a small out-of-core run hold far less than their plan's threshold:
    none hands memory back; with the threshold below what the process holds each one
    does. The inverse is the same either way."""
    import bigT
    from bigT.schedule import worker
    from bigT.storage import from_scipy

    rng = np.random.default_rng(3)
    A = sp.random_array((96, 96), density=0.2, format="csr", rng=rng) * 0.05
    T = from_scipy(sp.csr_array(sp.eye_array(96) + A), tmp_path / "T.zarr", tile_size=16,
                   dtype="float64")
    trimmed_by_task = []
    real = worker.return_freed_memory_above
    monkeypatch.setattr(worker, "return_freed_memory_above",
                        lambda threshold: trimmed_by_task.append(real(threshold)))
    options = dict(terms=3, prune=1e-9, in_memory=False, progress=False)
    quiet = bigT.stratified_inverse(T, tmp_path / "a.zarr", **options)
    tasks = len(trimmed_by_task)
    assert tasks >= 3 * (96 // 16) and not any(trimmed_by_task)  # a pass a term at least
    trimmed_by_task.clear()
    monkeypatch.setattr(memory, "UNLIMITED_RETAIN_SHARE", -1.0)  # a threshold below 0
    forced = bigT.stratified_inverse(T, tmp_path / "b.zarr", **options)
    assert len(trimmed_by_task) == tasks and all(trimmed_by_task)
    assert quiet.terms == forced.terms == 3
    np.testing.assert_array_equal(bigT.open(tmp_path / "a.zarr").to_scipy().toarray(),
                                  bigT.open(tmp_path / "b.zarr").to_scipy().toarray())
