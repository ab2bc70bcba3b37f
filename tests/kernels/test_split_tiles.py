"""``split_column_tiles`` (the storage writer's cut of a tile row into its tiles) and
``join_column_tiles`` (the reader's join of them), on both backends (conftest runs
every test with the numba kernel and its numpy twin), against scipy's column slicing
and stacking."""

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.kernels.csr import ColumnTiles, join_column_tiles, split_column_tiles


def _reference(A: sp.csr_array, ts: int):
    """{j: tile j of A as a csr_array} for the non-empty tiles."""
    out = {}
    for j in range(-(-A.shape[1] // ts)):
        tile = sp.csr_array(A[:, j * ts:(j + 1) * ts])
        if tile.nnz:
            out[j] = tile
    return out


@pytest.mark.parametrize("shape, ts, density", [
    ((37, 100), 16, 0.2),     # ragged last tile column
    ((64, 64), 64, 0.5),      # one tile column
    ((50, 300), 7, 0.02),     # many tile columns, most rows short
    ((20, 90), 10, 0.0),      # empty
])
def test_split_matches_scipy_slices(shape, ts, density):
    A = sp.random_array(shape, density=density, format="csr", dtype=np.float32,
                        rng=np.random.default_rng(1))
    A.sort_indices()
    tiles = split_column_tiles(A.indptr, A.indices, A.data, ts)
    ref = _reference(A, ts)
    assert list(tiles.cols) == sorted(ref)
    assert tiles.bounds[-1] == A.nnz and tiles.data.dtype == A.data.dtype
    for t, j in enumerate(tiles.cols):
        part = slice(tiles.bounds[t], tiles.bounds[t + 1])
        want = ref[int(j)]
        np.testing.assert_array_equal(tiles.indptr[t], want.indptr)
        np.testing.assert_array_equal(tiles.indices[part], want.indices)
        np.testing.assert_array_equal(tiles.data[part], want.data)


def test_unsorted_rows_keep_their_order_within_each_tile():
    """Columns out of order within a row (a caller's choice): entries land in their
    tiles in input order, the same on both backends."""
    indptr = np.array([0, 4, 6])
    indices = np.array([9, 1, 12, 3, 2, 0], np.int32)
    data = np.arange(6, dtype=np.float64)
    tiles = split_column_tiles(indptr, indices, data, 8)
    assert list(tiles.cols) == [0, 1]
    np.testing.assert_array_equal(tiles.indptr, [[0, 2, 4], [0, 2, 2]])
    np.testing.assert_array_equal(tiles.indices, [1, 3, 2, 0, 1, 4])
    np.testing.assert_array_equal(tiles.data, [1, 3, 4, 5, 0, 2])


@pytest.mark.parametrize("shape, ts, density, dtype", [
    ((37, 100), 16, 0.2, np.float32),
    ((64, 64), 64, 0.5, np.float64),
    ((50, 300), 7, 0.02, np.float32),
    ((20, 90), 10, 0.0, np.float32),
])
def test_join_matches_scipy_hstack(shape, ts, density, dtype):
    """Tiles made by scipy's column slices joined back equal the matrix; with some
    tiles left out, the matrix with those columns zeroed (a partial tile row)."""
    A = sp.random_array(shape, density=density, format="csr", dtype=dtype,
                        rng=np.random.default_rng(2))
    A.sort_indices()
    ref = _reference(A, ts)
    for keep in (sorted(ref), sorted(ref)[::2]):
        tiles = [ref[j] for j in keep]
        bounds = np.cumsum([0] + [t.nnz for t in tiles]).astype(np.int64)
        joined = ColumnTiles(
            np.array(keep, np.int64),
            np.stack([t.indptr.astype(np.int64) for t in tiles]) if tiles
            else np.zeros((0, shape[0] + 1), np.int64),
            np.concatenate([t.indices for t in tiles] or [np.empty(0, np.int32)]).astype(np.int32),
            np.concatenate([t.data for t in tiles] or [np.empty(0, dtype)]), bounds)
        indptr, indices, data = join_column_tiles(joined, ts, shape[1])
        mask = np.zeros(shape[1], bool)
        for j in keep:
            mask[j * ts:(j + 1) * ts] = True
        want = sp.csr_array(A.toarray() * mask[None, :])
        assert indices.dtype == np.int32 and data.dtype == dtype
        np.testing.assert_array_equal(indptr, want.indptr)
        np.testing.assert_array_equal(indices, want.indices)
        np.testing.assert_array_equal(data, want.data)


def test_split_then_join_is_the_identity_on_rows_spanning_many_tiles():
    A = sp.random_array((300, 5000), density=0.05, format="csr", dtype=np.float32,
                        rng=np.random.default_rng(3))
    A.sort_indices()
    indptr, indices, data = join_column_tiles(split_column_tiles(A.indptr, A.indices,
                                                                 A.data, 128), 128, 5000)
    np.testing.assert_array_equal(indptr, A.indptr)
    np.testing.assert_array_equal(indices, A.indices)
    np.testing.assert_array_equal(data, A.data)
