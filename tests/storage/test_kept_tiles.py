"""Tiles carried into a new store unchanged (``write_tile_row(..., keep=KeptTiles)``):
a whole old row hard-linked, a partial one read and rewritten with the new entries,
both read back as the old store's, still whole once the old store is deleted, and
refused when they would clash with what is written or do not exist."""

import os
import shutil

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.errors import StoreError
from bigT.storage import (
    KeptTiles,
    StoreAttrs,
    create_store,
    finalize_store,
    write_tile_row,
)

N, TS = 40, 16  # tile columns 0, 1, 2 (ragged)


def _finished(path, A, ts=TS):
    attrs = StoreAttrs((N, N), ts, "float64")
    create_store(path, attrs)
    for i in range(attrs.grid[0]):
        a, b = attrs.tile_row_range(i)
        write_tile_row(path, attrs, i, A[a:b])
    return finalize_store(path)


def _only_columns(rows, tile_columns):
    """``rows`` with the entries outside ``tile_columns`` dropped."""
    keep = np.isin(np.arange(N) // TS, list(tile_columns)).astype(float)
    return sp.csr_array(rows @ sp.diags_array(keep))


def _files(row_dir):
    """{path relative to ``row_dir``: inode} of every file below a tile row's directory."""
    return {os.path.relpath(os.path.join(d, f), row_dir): os.stat(os.path.join(d, f)).st_ino
            for d, _, files in os.walk(row_dir) for f in files}


def _old_columns(old, i):
    """(tile columns, their nnz) stored in tile row ``i`` of the store ``old``."""
    lo, hi = old.tile_indptr[i], old.tile_indptr[i + 1]
    return tuple(int(j) for j in old.tile_indices[lo:hi]), tuple(int(n) for n in old.tile_nnz[lo:hi])


def test_kept_tiles_read_back_and_survive_the_old_store(tmp_path):
    """Row 0 keeps the whole old row (nothing written): its files are hard-linked.
    Rows 1 and 2 keep tile column 1 and write the others: read and rewritten."""
    A = sp.csr_array(sp.random(N, N, density=0.4, random_state=1, format="csr"))
    B = sp.csr_array(sp.random(N, N, density=0.4, random_state=2, format="csr"))
    old = _finished(tmp_path / "old.zarr", A)
    new_path = tmp_path / "new.zarr"
    attrs = StoreAttrs((N, N), TS, "float64")
    create_store(new_path, attrs)
    a, b = attrs.tile_row_range(0)
    write_tile_row(new_path, attrs, 0, sp.csr_array((b - a, N)),
                   keep=KeptTiles(old.path, *_old_columns(old, 0)))
    for i in range(1, attrs.grid[0]):
        a, b = attrs.tile_row_range(i)
        # tile column 1 carried from A, the others written from B
        write_tile_row(new_path, attrs, i, _only_columns(B[a:b], (0, 2)),
                       keep=KeptTiles(old.path, (1,), (old.get_tile(i, 1).nnz,)))
    want = sp.csr_array(sp.vstack([A[:TS], (_only_columns(B, (0, 2)) + _only_columns(A, (1,)))[TS:]]))
    linked, source = _files(new_path / "rows" / "0"), _files(old.path / "rows" / "0")
    # the whole row: every file (marker and the three arrays' metadata and chunks)
    assert len(linked) == 7 and linked == source
    for i in (1, 2):  # a partial keep is written afresh: no file shared with the old row
        assert not set(_files(new_path / "rows" / str(i)).values()) & set(
            _files(old.path / "rows" / str(i)).values())
    shutil.rmtree(old.path)
    new = finalize_store(new_path)
    assert new.nnz == want.nnz
    np.testing.assert_array_equal(new.to_scipy().toarray(), want.toarray())
    for i in range(attrs.grid[0]):
        a, b = attrs.tile_row_range(i)
        np.testing.assert_array_equal(new.get_tile_row(i).toarray(), want[a:b].toarray())
    assert new.verify() == {"tiles": new.n_tiles_stored, "nnz": want.nnz}  # raises if damaged


def test_whole_old_row_kept_beside_new_tiles_is_rewritten(tmp_path):
    """Every tile of the old row kept, and a tile column the old row lacks written:
    the row is read and rewritten, not linked, and reads back as both."""
    A = _only_columns(sp.csr_array(sp.random(N, N, density=0.4, random_state=1,
                                             format="csr")), (0, 1))
    B = sp.csr_array(sp.random(N, N, density=0.4, random_state=2, format="csr"))
    old = _finished(tmp_path / "old.zarr", A)
    assert _old_columns(old, 1)[0] == (0, 1)
    new_path = tmp_path / "new.zarr"
    attrs = StoreAttrs((N, N), TS, "float64")
    create_store(new_path, attrs)
    for i in range(attrs.grid[0]):
        a, b = attrs.tile_row_range(i)
        write_tile_row(new_path, attrs, i, _only_columns(B[a:b], (2,)),
                       keep=KeptTiles(old.path, *_old_columns(old, i)))
    assert not set(_files(new_path / "rows" / "1").values()) & set(
        _files(old.path / "rows" / "1").values())
    shutil.rmtree(old.path)
    want = A + _only_columns(B, (2,))
    new = finalize_store(new_path)
    np.testing.assert_array_equal(new.to_scipy().toarray(), want.toarray())
    assert new.verify() == {"tiles": new.n_tiles_stored, "nnz": want.nnz}


@pytest.mark.parametrize("case", ["also written", "not stored", "wrong count",
                                  "other tile size"])
def test_kept_tiles_that_cannot_be_carried_are_refused(tmp_path, case):
    A = sp.csr_array(sp.random(N, N, density=0.4, random_state=1, format="csr"))
    old = _finished(tmp_path / "old.zarr", A, ts=8 if case == "other tile size" else TS)
    attrs = StoreAttrs((N, N), TS, "float64")
    new_path = tmp_path / "new.zarr"
    create_store(new_path, attrs)
    block = _only_columns(A[:TS], (0, 1) if case == "also written" else (0,))
    count = old.get_tile(0, 1).nnz + (case == "wrong count")
    keep = KeptTiles(old.path, (7,) if case == "not stored" else (1,), (count,))
    with pytest.raises(StoreError, match="tile column|another shape"):
        write_tile_row(new_path, attrs, 0, block, keep=keep)
    assert not (new_path / "rows" / "0").exists()
    assert [p.name for p in (new_path / "rows").iterdir()] == ["zarr.json"]
