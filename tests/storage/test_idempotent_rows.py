"""Writes that tolerate retries: a tile row written twice (in turn, and at once from two
processes) lands once and reads back right; a store is finalized from the row markers
on disk, whoever wrote them; half-written rows never look complete."""

import multiprocessing as mp

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.errors import IncompleteStoreError
from bigT.storage import (
    StoreAttrs,
    clean_partial_rows,
    create_store,
    finalize_store,
    open as open_store,
    read_store_attrs,
    write_tile_row,
)

N, TS = 40, 16


def _matrix(seed=0):
    return sp.random(N, N, density=0.3, random_state=seed, format="csr", dtype=np.float64)


def _store(tmp_path, name="s.zarr"):
    path = tmp_path / name
    create_store(path, StoreAttrs((N, N), TS, "float64"))
    return path


def _write(path, i, A, barrier=None):
    attrs = read_store_attrs(path)
    a, b = attrs.tile_row_range(i)
    if barrier is not None:
        barrier.wait()
    return write_tile_row(path, attrs, i, A[a:b])


def test_second_write_of_a_row_is_a_no_op(tmp_path):
    path = _store(tmp_path)
    A = _matrix()
    assert _write(path, 1, A) is True
    files = sorted(p.name for p in (path / "rows" / "1").rglob("*"))
    other = _matrix(seed=1)  # a retry computes the same row; a different one proves no rewrite
    assert _write(path, 1, other) is False
    assert sorted(p.name for p in (path / "rows" / "1").rglob("*")) == files
    for i in (0, 2):
        _write(path, i, A)
    X = finalize_store(path)
    np.testing.assert_array_equal(X.to_scipy().toarray(), A.toarray())


def _race(path, i, seed, barrier, queue):
    try:
        queue.put(_write(path, i, _matrix(seed), barrier))
    except BaseException as exc:  # reported to the test, not lost in the child
        queue.put(repr(exc))


def test_same_row_from_two_processes_at_once(tmp_path):
    path = _store(tmp_path)
    ctx = mp.get_context("spawn")
    for i in range(3):
        barrier, queue = ctx.Barrier(2), ctx.Queue()
        procs = [ctx.Process(target=_race, args=(str(path), i, 0, barrier, queue))
                 for _ in range(2)]
        for p in procs:
            p.start()
        results = sorted([queue.get(timeout=60), queue.get(timeout=60)], key=str)
        for p in procs:
            p.join(timeout=60)
            assert p.exitcode == 0
        # one wrote it, the other found it complete (or lost the rename and let go)
        assert results == [False, True], results
    assert not list((path / "rows").glob(".*.partial"))
    X = finalize_store(path)
    np.testing.assert_array_equal(X.to_scipy().toarray(), _matrix(0).toarray())
    assert X.verify()["nnz"] == _matrix(0).nnz


def test_finalize_reads_the_markers_on_disk(tmp_path):
    path = _store(tmp_path)
    A = _matrix(2)
    _write(path, 0, A)
    _write(path, 2, A)
    with pytest.raises(IncompleteStoreError, match=r"1 of 3 tile rows not written \(rows 1\)"):
        finalize_store(path)
    _write(path, 1, A)  # "another process" adds the last row: no writer object knows it
    X = finalize_store(path)
    assert X.complete and X.nnz == A.nnz
    assert finalize_store(path).nnz == A.nnz  # finalizing twice is harmless
    np.testing.assert_array_equal(open_store(path).to_scipy().toarray(), A.toarray())


def test_half_written_rows_are_cleaned_once_and_never_read(tmp_path):
    path = _store(tmp_path)
    A = _matrix(3)
    _write(path, 0, A)
    (path / "rows" / ".1.deadbeef.partial" / "indptr").mkdir(parents=True)  # a SIGKILLed writer
    (path / "rows" / "2").mkdir()  # an unmarked row of an older writer
    partial = open_store(path, allow_incomplete=True)
    assert partial.missing_tile_rows == [1, 2]
    assert clean_partial_rows(path, 3) == 2
    assert sorted(p.name for p in (path / "rows").iterdir() if p.is_dir()) == ["0"]
    for i in (1, 2):
        _write(path, i, A)
    np.testing.assert_array_equal(finalize_store(path).to_scipy().toarray(), A.toarray())
