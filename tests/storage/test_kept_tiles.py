"""Tiles carried into a new store unchanged (``write_tile_row(..., keep=KeptTiles)``):
hard-linked, read back as the old store's, still whole once the old store is deleted,
and refused when they would clash with what is written or do not exist."""

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


def test_kept_tiles_read_back_and_survive_the_old_store(tmp_path):
    A = sp.csr_array(sp.random(N, N, density=0.4, random_state=1, format="csr"))
    B = sp.csr_array(sp.random(N, N, density=0.4, random_state=2, format="csr"))
    old = _finished(tmp_path / "old.zarr", A)
    new_path = tmp_path / "new.zarr"
    attrs = StoreAttrs((N, N), TS, "float64")
    create_store(new_path, attrs)
    for i in range(attrs.grid[0]):
        a, b = attrs.tile_row_range(i)
        # tile column 1 carried from A, the others written from B
        write_tile_row(new_path, attrs, i, _only_columns(B[a:b], (0, 2)),
                       keep=KeptTiles(old.path, (1,), (old.get_tile(i, 1).nnz,)))
    want = _only_columns(B, (0, 2)) + _only_columns(A, (1,))
    linked = new_path / "rows" / "0" / "1" / "data" / "c" / "0"
    assert os.stat(linked).st_ino == os.stat(old.path / "rows" / "0" / "1" / "data" / "c" / "0").st_ino
    shutil.rmtree(old.path)
    new = finalize_store(new_path)
    assert new.nnz == want.nnz
    np.testing.assert_array_equal(new.to_scipy().toarray(), want.toarray())
    assert new.verify() == {"tiles": new.n_tiles_stored, "nnz": want.nnz}  # raises if damaged


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
