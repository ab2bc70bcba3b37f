"""Bad input and damaged stores: every failure is a bigT error naming store and problem."""

import os

import numpy as np
import pytest
import scipy.sparse as sp
import zarr

from bigT.errors import (BigTError, CorruptStoreError, IncompleteStoreError, InvalidMatrixError,
                         NotSquareError, ShapeMismatchError, StoreError)
from bigT.storage import from_scipy, open as open_store
from bigT.atomic import atomic_write_json
from bigT.storage._format import group_json


@pytest.fixture
def store(tmp_path):
    A = sp.csr_array(sp.random(30, 30, density=0.3, format="csr", random_state=2))
    return from_scipy(A, tmp_path / "s.zarr", tile_size=10), A


def test_errors_are_value_errors():
    assert issubclass(CorruptStoreError, ValueError) and issubclass(CorruptStoreError, BigTError)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_from_scipy_rejects_non_finite_before_writing(tmp_path, value):
    A = sp.random(10, 10, density=0.5, format="csr", random_state=0)
    A.data[5] = value
    with pytest.raises(InvalidMatrixError, match="NaN/Inf") as ei:
        from_scipy(A, tmp_path / "x.zarr")
    assert "x.zarr" in str(ei.value)
    assert not (tmp_path / "x.zarr").exists()


def test_from_scipy_shape_errors(tmp_path):
    A = sp.random(6, 8, density=0.5, format="csr", random_state=0)
    with pytest.raises(NotSquareError, match=r"\(6, 8\)"):
        from_scipy(A, tmp_path / "x.zarr", require_square=True)
    with pytest.raises(NotSquareError):
        from_scipy(A, tmp_path / "x.zarr", image_shape=(2, 3))
    B = sp.random(6, 6, density=0.5, format="csr", random_state=0)
    with pytest.raises(ShapeMismatchError, match="image shape"):
        from_scipy(B, tmp_path / "x.zarr", image_shape=(2, 2))
    with pytest.raises(ShapeMismatchError, match="needs image_shape"):
        from_scipy(B, tmp_path / "x.zarr", pixel_order="tile-major")
    with pytest.raises(ShapeMismatchError):
        from_scipy(np.ones(5), tmp_path / "x.zarr")
    with pytest.raises(InvalidMatrixError, match="float32 or float64"):
        from_scipy(B, tmp_path / "x.zarr", dtype="int64")
    with pytest.raises(InvalidMatrixError, match="overflow"):
        from_scipy(B * 1e300, tmp_path / "x.zarr", dtype="float32")
    assert not (tmp_path / "x.zarr").exists()


def test_open_not_a_store(tmp_path):
    with pytest.raises(StoreError, match="no such store"):
        open_store(tmp_path / "nope")
    (tmp_path / "plain").mkdir()
    with pytest.raises(StoreError, match="no zarr.json"):
        open_store(tmp_path / "plain")
    g = zarr.create_group(str(tmp_path / "other.zarr"), zarr_format=3)
    g.attrs["something"] = 1
    with pytest.raises(StoreError, match="not a bigT store") as ei:
        open_store(tmp_path / "other.zarr")
    assert "other.zarr" in str(ei.value)
    zarr.create_array(str(tmp_path / "arr.zarr"), shape=(3,), dtype="f4")
    with pytest.raises(StoreError, match="not a zarr v3 group"):
        open_store(tmp_path / "arr.zarr")
    (tmp_path / "bad.zarr").mkdir()
    (tmp_path / "bad.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreError, match="unreadable zarr.json"):
        open_store(tmp_path / "bad.zarr")


def test_deleted_tile_chunk(store):
    S, A = store
    os.remove(S.path / "rows" / "1" / "indices" / "c" / "0")
    T = open_store(S.path)          # the tile index is intact: open succeeds ...
    with pytest.raises(CorruptStoreError, match=r"tile row 1: .*missing or damaged") as ei:
        T.get_tile(1, 2)             # ... the read of a tile of that row fails
    assert str(S.path) in str(ei.value)
    with pytest.raises(CorruptStoreError, match=r"tile row 1: "):
        T.get_tile_row(1)
    assert (T.get_tile(0, 0) != A[0:10, 0:10]).nnz == 0  # other rows still read
    assert (T.get_tile_row(2) != A[20:30]).nnz == 0
    with pytest.raises(CorruptStoreError, match="missing chunk file rows/1/indices/c/0"):
        T.verify()
    with pytest.raises(CorruptStoreError):
        T.to_scipy()
    with pytest.raises(CorruptStoreError):
        T @ np.ones(30)


@pytest.mark.parametrize("name", ["indptr", "data"])
def test_deleted_indptr_or_data_chunk(store, name):
    S, _ = store
    os.remove(S.path / "rows" / "2" / name / "c" / "0")
    with pytest.raises(CorruptStoreError, match=r"tile row 2: "):
        open_store(S.path).get_tile(2, 2)
    with pytest.raises(CorruptStoreError, match=r"tile row 2: |missing chunk"):
        open_store(S.path).diagonal()


def test_deleted_index_chunk_detected_by_open(store):
    S, _ = store
    os.remove(S.path / "tile_indices" / "c" / "0")
    with pytest.raises(CorruptStoreError, match="s.zarr"):
        open_store(S.path)


def test_corrupted_chunk_byte_fails_checksum(store):
    S, _ = store
    chunk = S.path / "rows" / "0" / "data" / "c" / "0"
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x10
    chunk.write_bytes(bytes(raw))
    T = open_store(S.path)
    with pytest.raises(CorruptStoreError, match=r"tile row 0: .*checksum"):
        T.get_tile(0, 1)
    with pytest.raises(CorruptStoreError, match="checksum"):
        T.verify()


def test_half_written_row_in_finalized_store(store):
    """A row whose marker says incomplete while the root claims complete is caught by verify."""
    S, _ = store
    atomic_write_json(S.path / "rows" / "1" / "zarr.json", group_json({"bigT_row": {"complete": False}}))
    with pytest.raises(CorruptStoreError, match="tile row 1 has no completion marker"):
        open_store(S.path).verify()


def test_half_written_row_unfinalized(store):
    S, _ = store
    meta = S.path / "zarr.json"
    import json
    m = json.loads(meta.read_text())
    m["attributes"]["bigT"]["complete"] = False
    meta.write_text(json.dumps(m))
    atomic_write_json(S.path / "rows" / "1" / "zarr.json", group_json({"bigT_row": {"complete": False}}))
    with pytest.raises(IncompleteStoreError, match=r"1 of 3 tile rows are missing \(rows 1\)"):
        open_store(S.path)


def test_tampered_nnz_and_unsupported_version(store):
    S, _ = store
    import json
    meta = S.path / "zarr.json"
    m = json.loads(meta.read_text())
    m["attributes"]["bigT"]["nnz"] += 1
    meta.write_text(json.dumps(m))
    with pytest.raises(CorruptStoreError, match="nnz"):
        open_store(S.path)
    m["attributes"]["bigT"]["version"] = 99
    meta.write_text(json.dumps(m))
    with pytest.raises(StoreError, match="unsupported"):
        open_store(S.path)
    m["attributes"]["bigT"]["version"] = 1
    m["attributes"]["bigT"]["inner_format"] = "bsr"
    m["attributes"]["bigT"]["nnz"] -= 1
    meta.write_text(json.dumps(m))
    with pytest.raises(StoreError, match="inner_format 'bsr'"):
        open_store(S.path)


def test_deleted_middle_chunk_of_multichunk_tile(tmp_path, monkeypatch):
    from bigT import config
    monkeypatch.setattr(config, "CHUNK_ELEMENTS", 4)
    A = sp.csr_array(sp.random(12, 12, density=0.5, format="csr", random_state=3))
    S = from_scipy(A, tmp_path / "c.zarr", tile_size=6)
    chunks = sorted(os.listdir(S.path / "rows" / "1" / "data" / "c"), key=int)
    assert len(chunks) >= 3
    os.remove(S.path / "rows" / "1" / "data" / "c" / chunks[1])
    with pytest.raises(CorruptStoreError, match=r"tile row 1: non-finite"):
        open_store(S.path).get_tile(1, 0)
    with pytest.raises(CorruptStoreError, match=f"missing chunk file rows/1/data/c/{chunks[1]}"):
        open_store(S.path).verify()
    os.remove(S.path / "rows" / "0" / "indptr" / "c" / "1")
    with pytest.raises(CorruptStoreError, match=r"tile row 0: indptr"):
        open_store(S.path).get_tile(0, 1)


@pytest.mark.parametrize("damage", [None, "indptr", "range", "unsorted", "duplicate",
                                    "non-finite", "tile counts"])
def test_a_big_row_checked_by_the_kernel_says_what_numpy_says(monkeypatch, damage):
    """A tile row past config.KERNEL_NUMPY_MAX_WORK is checked in one pass of the kernels
    (bigT.kernels.row_ranges.checked_tile_counts); a damaged one gets numpy's own
    message, a sound one none, whichever checks it."""
    from bigT import config
    from bigT.storage import tiles

    A = sp.csr_array(sp.random(20, 40, density=0.3, format="csr", random_state=4))
    A.sort_indices()
    indptr, indices, data = A.indptr.astype(np.int64), A.indices.copy(), A.data.copy()
    counts = np.bincount(indices // 10, minlength=4)
    columns = np.flatnonzero(counts)
    counts = counts[columns]
    row = int(np.flatnonzero(np.diff(indptr) >= 2)[0])
    p = int(indptr[row])
    if damage == "indptr":
        indptr[row + 1] = indptr[row] - 1
    elif damage == "range":
        indices[-1] = 40
    elif damage == "unsorted":
        indices[p], indices[p + 1] = indices[p + 1], indices[p]
    elif damage == "duplicate":
        indices[p + 1] = indices[p]
    elif damage == "non-finite":
        data[p] = np.nan
    elif damage == "tile counts":
        counts = counts + 1
    args = (indptr, indices, data, 40, 10, columns, counts)
    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 10**9)
    by_numpy = tiles._row_problem(*args)
    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", -1)
    assert tiles._row_problem(*args) == by_numpy
    assert (by_numpy is None) == (damage is None)
