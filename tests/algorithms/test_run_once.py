"""What an in-memory run pays once: T read from its store once (F's diagonal taken from
the rows M is made from), the same F as from the store's diagonal, the same inverse."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
from inverse_helpers import dense, random_dominant

import bigT
from bigT.algorithms.first_bounce import first_bounce_of_rows, resolve_first_bounce
from bigT.algorithms.run_setup import TileRows
from bigT.storage import BlockCSR


def dark_pixels(A: np.ndarray, dark) -> np.ndarray:
    """A with the pixels ``dark`` unlit: their rows and columns zero."""
    A = A.copy()
    A[dark, :] = 0
    A[:, dark] = 0
    return A


def assert_same_first_bounce(a, b) -> None:
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), field.name
        else:
            assert x == y, field.name


@pytest.mark.parametrize("spec", ["diag", "identity"])
def test_first_bounce_of_rows_is_the_stores(make_store, spec):
    T = make_store(dark_pixels(random_dominant(70, seed=11), [4, 33, 69]), tile_size=16,
                   dtype="float32")
    rows = TileRows(T, threads=2)
    fb = first_bounce_of_rows(T, spec, rows)
    assert fb.excluded == 3
    assert_same_first_bounce(fb, resolve_first_bounce(T, spec))
    # the rows are T's, each read once, and taken one by one
    for i in range(len(rows)):
        row = rows.take(i)
        assert (row != T.get_tile_row(i)).nnz == 0
    assert rows._rows == [None] * len(rows)


def test_first_bounce_of_rows_colour(tmp_path):
    rng = np.random.default_rng(3)
    n = 3 * 30  # 30 pixels, 3 channels
    A = sp.random(n, n, density=0.2, random_state=rng).toarray() * 0.05
    for p in range(30):  # each pixel's colour mixing, well conditioned
        A[3 * p:3 * p + 3, 3 * p:3 * p + 3] = np.eye(3) + 0.1 * rng.random((3, 3))
    unlit = 3 * 7 + np.arange(3)
    A[unlit, :] = 0
    A[:, unlit] = 0
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", image_shape=(5, 6),
                        channels=3, tile_size=12)
    fb = first_bounce_of_rows(T, "diag", TileRows(T, threads=2))
    assert fb.excluded == 1
    assert_same_first_bounce(fb, resolve_first_bounce(T, "diag"))


def test_in_memory_run_reads_T_once(tmp_path, make_store, monkeypatch):
    A = dark_pixels(random_dominant(96, seed=12, density=0.2), [5, 50])
    T = make_store(A, tile_size=16)  # 6 tile rows
    options = dict(terms=3, prune=1e-6, progress=False)
    bigT.stratified_inverse(T, tmp_path / "ref.zarr", in_memory=False, **options)
    reads, diagonals = [], []
    real_row, real_diagonal = BlockCSR.get_tile_row, BlockCSR.diagonal

    def counted_row(self, i, columns=None):
        reads.append(int(i))
        return real_row(self, i, columns)

    def counted_diagonal(self, *args, **kwargs):
        diagonals.append(1)
        return real_diagonal(self, *args, **kwargs)

    monkeypatch.setattr(BlockCSR, "get_tile_row", counted_row)
    monkeypatch.setattr(BlockCSR, "diagonal", counted_diagonal)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", in_memory=True, **options)
    monkeypatch.undo()
    assert sorted(reads) == list(range(6)) and not diagonals  # F and M from one read
    assert rep.excluded_pixels == 2
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense(tmp_path / "ref.zarr"),
                               rtol=1e-6, atol=1e-9)
