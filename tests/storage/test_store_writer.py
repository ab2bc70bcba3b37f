"""Interrupted writers, resume, full disks and bad input to BlockCSRWriter."""

import errno

import numpy as np
import pytest
import scipy.sparse as sp

import bigT.storage.writer as writer_mod
from bigT.errors import (DiskFullError, IncompleteStoreError, InvalidMatrixError,
                         ShapeMismatchError, StoreError)
from bigT.storage import BlockCSRWriter, from_scipy, open as open_store

SHAPE, TS = (37, 33), 8   # 5 tile rows, the last ragged (5 rows)


@pytest.fixture
def A():
    return sp.csr_array(sp.random(*SHAPE, density=0.25, format="csr", random_state=7,
                                  dtype=np.float64))


def _write_rows(w, A, rows):
    for i in rows:
        r0, r1 = w.tile_row_range(i)
        w.write_tile_row(i, A[r0:r1])


def _same(S, A):
    assert (S.to_scipy() != A.astype(S.dtype)).nnz == 0


def test_killed_between_rows_then_resume(tmp_path, A):
    path = tmp_path / "k.zarr"
    w = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64")
    _write_rows(w, A, [0, 1, 3])
    del w   # "killed": never finalized
    with pytest.raises(IncompleteStoreError, match=r"2 of 5 tile rows are missing") as ei:
        open_store(path)
    assert str(path) in str(ei.value)
    partial = open_store(path, allow_incomplete=True)
    assert partial.missing_tile_rows == [2, 4] and not partial.complete
    assert (partial.get_tile_row(1) != A[8:16]).nnz == 0
    assert partial.get_tile_row(2).nnz == 0

    w2 = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64", resume=True)
    assert w2.completed_tile_rows == [0, 1, 3]
    written = [w2.write_tile_row(i, A[w2.tile_row_range(i)[0]:w2.tile_row_range(i)[1]])
               for i in range(5)]
    assert written == [False, False, True, False, True]
    S = w2.finalize()
    _same(S, A)
    assert S.verify()["nnz"] == A.nnz


def test_all_rows_but_not_finalized(tmp_path, A):
    path = tmp_path / "f.zarr"
    w = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64")
    _write_rows(w, A, range(5))
    with pytest.raises(IncompleteStoreError, match="never finalized"):
        open_store(path)
    _same(BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64", resume=True).finalize(), A)


def test_raise_mid_row_leaves_half_written_row_incomplete(tmp_path, A, monkeypatch):
    path = tmp_path / "r.zarr"
    w = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64")
    _write_rows(w, A, [0, 1])
    real, calls = writer_mod.fmt.write_array_files, []

    def dying(*args):
        calls.append(args[1])
        if len(calls) == 2:        # row 2's second array: its first (indptr) is on disk
            raise KeyboardInterrupt
        real(*args)

    monkeypatch.setattr(writer_mod.fmt, "write_array_files", dying)
    with pytest.raises(KeyboardInterrupt):
        _write_rows(w, A, [2])
    monkeypatch.setattr(writer_mod.fmt, "write_array_files", real)
    assert calls == ["indptr", "indices"]
    # the half row was built aside and never became rows/2
    assert not (path / "rows" / "2").exists()
    # what a SIGKILL would leave: a hidden partial row; resume deletes it
    leftover = path / "rows" / ".2.dead.partial"
    (leftover / "indptr" / "c").mkdir(parents=True)
    with pytest.raises(IncompleteStoreError, match="3 of 5"):
        open_store(path)
    w2 = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64", resume=True)
    assert w2.completed_tile_rows == [0, 1]
    assert not leftover.exists()
    _write_rows(w2, A, range(5))
    _same(w2.finalize(), A)


def test_disk_full_keeps_complete_rows(tmp_path, A, monkeypatch):
    path = tmp_path / "full.zarr"
    w = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64")
    _write_rows(w, A, [0, 1])

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(writer_mod.fmt, "write_array_files", full)
    with pytest.raises(DiskFullError, match="disk full") as ei:
        _write_rows(w, A, [2])
    assert ei.value.path == str(path)
    monkeypatch.undo()
    partial = open_store(path, allow_incomplete=True)
    assert partial.missing_tile_rows == [2, 3, 4]
    assert (partial.get_tile_row(0) != A[0:8]).nnz == 0
    w2 = BlockCSRWriter(path, SHAPE, tile_size=TS, dtype="float64", resume=True)
    _write_rows(w2, A, range(5))
    _same(w2.finalize(), A)


def test_from_scipy_disk_full_leaves_nothing(tmp_path, A, monkeypatch):
    monkeypatch.setattr(writer_mod.fmt, "write_array_files",
                        lambda *a: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    with pytest.raises(DiskFullError):
        from_scipy(A, tmp_path / "x.zarr", tile_size=TS)
    assert list(tmp_path.iterdir()) == []


def test_writer_bad_input(tmp_path, A):
    w = BlockCSRWriter(tmp_path / "b.zarr", SHAPE, tile_size=TS)
    with pytest.raises(ShapeMismatchError, match="tile row 0"):
        w.write_tile_row(0, A[0:7])
    with pytest.raises(ShapeMismatchError, match="tile row 4"):
        w.write_tile_row(4, A[24:32])          # the ragged last tile row has 5 rows
    bad = A[0:8].copy()
    bad.data[3] = np.nan
    with pytest.raises(InvalidMatrixError, match="NaN"):
        w.write_tile_row(0, bad)
    bad.data[3] = np.inf
    with pytest.raises(InvalidMatrixError):
        w.write_tile_row(0, bad)
    oor = sp.csr_array((np.ones(2), np.array([0, 99]), np.r_[0, 1, 2, [2] * 6]), shape=(8, 33))
    with pytest.raises(InvalidMatrixError, match="out of range"):
        w.write_tile_row(0, oor)
    with pytest.raises(ShapeMismatchError):
        w.write_tile_row(9, A[0:8])
    with pytest.raises(IncompleteStoreError, match="5 of 5"):
        w.finalize()
    with pytest.raises(ShapeMismatchError, match="tile_size"):
        BlockCSRWriter(tmp_path / "b.zarr", SHAPE, tile_size=TS + 1, resume=True)
    with pytest.raises(InvalidMatrixError, match="dtype"):
        BlockCSRWriter(tmp_path / "c.zarr", SHAPE, tile_size=TS, dtype="int32")


def test_existing_paths_are_not_damaged(tmp_path, A):
    path = tmp_path / "keep.zarr"
    S = from_scipy(A, path, tile_size=TS, dtype="float64")
    with pytest.raises(StoreError, match="already exists"):
        BlockCSRWriter(path, SHAPE, tile_size=TS)
    with pytest.raises(StoreError, match="already exists"):
        from_scipy(A, path, tile_size=TS)
    nan = A.copy()
    nan.data[0] = np.nan
    with pytest.raises(InvalidMatrixError):
        from_scipy(nan, path, tile_size=TS, overwrite=True)
    _same(open_store(path), A)
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("precious")
    with pytest.raises(StoreError, match="not a bigT store"):
        from_scipy(A, other, overwrite=True)
    with pytest.raises(StoreError, match="not a bigT store"):
        BlockCSRWriter(other, SHAPE, overwrite=True)
    assert (other / "notes.txt").read_text() == "precious"
    B = sp.eye(37, 33, format="csr")
    _same(from_scipy(B, path, tile_size=TS, overwrite=True, dtype="float64"), B)
    assert S.path == path
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_tile_rows_written_from_threads(tmp_path, A):
    """The engine writes tile rows from dask worker threads; rows land in any order."""
    from concurrent.futures import ThreadPoolExecutor

    w = BlockCSRWriter(tmp_path / "t.zarr", SHAPE, tile_size=TS, dtype="float64")
    with ThreadPoolExecutor(3) as pool:
        list(pool.map(lambda i: w.write_tile_row(i, A[w.tile_row_range(i)[0]:w.tile_row_range(i)[1]]),
                      [4, 2, 0, 3, 1]))
    S = w.finalize()
    _same(S, A)
    with ThreadPoolExecutor(3) as pool:
        rows = list(pool.map(S.get_tile_row, range(S.grid[0])))
    assert (sp.vstack(rows) != A).nnz == 0
