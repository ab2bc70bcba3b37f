"""Matrix rows out of tiles: a tile row joined from its column tiles
(:func:`join_tile_row`) and any row range cut from tile rows (:func:`rows_between`).
Rows are in the store's (matrix) order, with global column indices.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import scipy.sparse as sp

from .attrs import StoreAttrs


def join_tile_row(tiles: Iterable[tuple[int, sp.csr_array]], rows: int, attrs: StoreAttrs,
                  dtype: np.dtype) -> sp.csr_array:
    """One tile row of ``rows`` rows as a csr_array of shape (rows, n_cols), sorted,
    from its stored tiles ``(j, tile)`` in ascending tile column j (the others empty).

    ``tiles`` is consumed here, so that at most two copies of the row are alive at
    once: the joined tiles and the output.
    """
    from ..kernels.csr import ColumnTiles, join_column_tiles  # numba: big rows only

    n_cols = attrs.shape[1]
    tiles = list(tiles)
    if not tiles:
        return sp.csr_array((rows, n_cols), dtype=dtype)
    bounds = np.zeros(len(tiles) + 1, np.int64)
    np.cumsum([t.nnz for _, t in tiles], out=bounds[1:])
    # tiles in ascending column order: appending each tile's part of a row keeps the
    # row's columns sorted
    joined = ColumnTiles(
        np.array([j for j, _ in tiles], np.int64),
        np.stack([np.asarray(t.indptr, np.int64) for _, t in tiles]),
        np.concatenate([t.indices for _, t in tiles]),
        np.concatenate([t.data for _, t in tiles]).astype(dtype, copy=False), bounds)
    del tiles  # two copies of the row at most: the joined tiles and the output
    indptr, indices, data = join_column_tiles(joined, attrs.tile_size, n_cols)
    out = sp.csr_array((data, indices, indptr.astype(indices.dtype)), shape=(rows, n_cols))
    out.has_sorted_indices = True
    return out


def rows_between(start: int, stop: int, attrs: StoreAttrs, dtype: np.dtype,
                 tile_row: Callable[[int], sp.csr_array]) -> sp.csr_array:
    """Matrix rows ``start:stop`` (a checked range) as a csr_array of shape
    (stop - start, n_cols), cut from the tile rows ``tile_row(i)`` it spans."""
    ts = attrs.tile_size
    parts = []
    for i in range(start // ts, -(-stop // ts)):
        r0, r1 = attrs.tile_row_range(i)
        row = tile_row(i)
        parts.append(row if (r0, r1) == (max(r0, start), min(r1, stop))
                     else row[max(r0, start) - r0:min(r1, stop) - r0])
    if len(parts) == 1:
        out = sp.csr_array(parts[0])
    elif parts:
        out = sp.csr_array(sp.vstack(parts, format="csr"))
    else:
        return sp.csr_array((0, attrs.shape[1]), dtype=dtype)
    out.has_sorted_indices = True
    return out
