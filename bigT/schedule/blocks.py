"""What runs on one tile row: pure functions on ``scipy.sparse.csr_array`` blocks.

How the blocks are wired into a graph lives in :mod:`bigT.schedule.graph`; the
operators that read tiles from stores live in :mod:`bigT.schedule.operators`. Nothing
here touches dask or zarr.

Notation (paper eq. 13, DESIGN.md "The math"): T is n x n, F the first bounce
(diagonal, stored as the vector ``f``; ``finv`` = 1/f, 0 on excluded pixels), D the
diagonal 0/1 mask of active pixels, M = D - T F^-1.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ._backend import add_diag_scaled, prune, scale_cols, spgemm


def empty(shape, dtype) -> sp.csr_array:
    """An all-zero CSR of ``shape``."""
    return sp.csr_array(shape, dtype=dtype)


def identity_rows(start: int, stop: int, n: int, active: np.ndarray, dtype) -> sp.csr_array:
    """Rows ``start:stop`` of D = diag(active), shape (stop - start, n), global columns."""
    rows = np.flatnonzero(active[start:stop])
    return sp.csr_array(
        (np.ones(len(rows), dtype=dtype), (rows, rows + start)), shape=(stop - start, n)
    )


def diag_rows(start: int, stop: int, n: int, values: np.ndarray, dtype) -> sp.csr_array:
    """Rows ``start:stop`` of diag(values) (zeros dropped), global columns."""
    v = np.asarray(values[start:stop], dtype=dtype)
    rows = np.flatnonzero(v)
    return sp.csr_array((v[rows], (rows, rows + start)), shape=(stop - start, n))


def m_tile(T_ij: sp.csr_array, finv_cols: np.ndarray, diagonal_block: bool,
           active_rows: np.ndarray | None, zero_diagonal: bool) -> sp.csr_array:
    """Tile (i, j) of M = D - T F^-1 from tile (i, j) of T.

    Parameters
    ----------
    T_ij : csr_array, shape (r, c)
    finv_cols : (c,) ndarray, 1/F of the tile's columns (0 where excluded).
    diagonal_block : bool
        Whether i == j (then D contributes and local row == local column on the
        diagonal).
    active_rows : (r,) bool ndarray or None
        D's diagonal for the tile's rows; used when ``diagonal_block``.
    zero_diagonal : bool
        F = diag T: the diagonal of M is exactly 1 - T_ii / T_ii = 0, so it is
        dropped instead of being left as rounding noise.
    """
    M = scale_cols(T_ij, -np.asarray(finv_cols, dtype=T_ij.dtype))
    if not diagonal_block:
        return M
    coo = M.tocoo()
    off = coo.row != coo.col
    r, c, v = coo.row[off], coo.col[off], coo.data[off]
    if not zero_diagonal:
        d = np.asarray(active_rows, dtype=M.dtype) + M.diagonal()
        nz = np.flatnonzero(d)
        r = np.concatenate([r, nz])
        c = np.concatenate([c, nz])
        v = np.concatenate([v, d[nz]])
    out = sp.csr_array((v, (r, c)), shape=M.shape)
    out.sum_duplicates()
    out.sort_indices()
    return out


def hstack_tiles(tiles: list[sp.csr_array], n_rows: int, dtype) -> sp.csr_array:
    """Tiles of one tile row side by side (compact columns: only the given tiles)."""
    if not tiles:
        return empty((n_rows, 0), dtype)
    if len(tiles) == 1:
        return sp.csr_array(tiles[0])
    return sp.csr_array(sp.hstack(tiles, format="csr"))


def vstack_rows(rows: list[sp.csr_array], n_cols: int, dtype) -> sp.csr_array:
    """Tile rows (global columns) stacked, in the order of the matching tiles."""
    if not rows:
        return empty((0, n_cols), dtype)
    if len(rows) == 1:
        return sp.csr_array(rows[0])
    return sp.csr_array(sp.vstack(rows, format="csr"))


def row_product(left_tiles: list[sp.csr_array], right_rows: list[sp.csr_array],
                n_rows: int, n_cols: int, threshold: float, dtype,
                max_right_nnz: int | None = None, n_threads: int = 1) -> sp.csr_array:
    """sum_j L_ij @ B_j for the given matching pairs, entries below ``threshold`` pruned.

    Parameters
    ----------
    left_tiles : list of csr_array, shapes (n_rows, c_j)
    right_rows : list of csr_array, shapes (c_j, n_cols)
    max_right_nnz : int, optional
        Memory bound: the right rows are multiplied in batches of at most this many
        stored entries, partial sums are added unpruned and pruned once at the end
        (the same result up to rounding as one product).
    n_threads : int
        Threads of the kernel (1 when dask already runs tile rows in parallel).
    n_threads : int
        Threads of the kernel (1 when dask already runs tile rows in parallel).

    Returns
    -------
    csr_array, shape (n_rows, n_cols)
    """
    if not left_tiles:
        return empty((n_rows, n_cols), dtype)
    batches, cur, cur_nnz = [], [], 0
    for k, B in enumerate(right_rows):
        if cur and max_right_nnz is not None and cur_nnz + B.nnz > max_right_nnz:
            batches.append(cur)
            cur, cur_nnz = [], 0
        cur.append(k)
        cur_nnz += B.nnz
    batches.append(cur)
    if len(batches) == 1:
        L = hstack_tiles(left_tiles, n_rows, dtype)
        B = vstack_rows(right_rows, n_cols, dtype)
        return spgemm(L, B, threshold=threshold, n_threads=n_threads)
    acc = None
    for batch in batches:
        L = hstack_tiles([left_tiles[k] for k in batch], n_rows, dtype)
        B = vstack_rows([right_rows[k] for k in batch], n_cols, dtype)
        part = spgemm(L, B, threshold=0.0, n_threads=n_threads)
        acc = part if acc is None else sp.csr_array(acc + part)
    return prune(acc, threshold=threshold)


def add_scaled(A: sp.csr_array, d: np.ndarray, B: sp.csr_array) -> sp.csr_array:
    """A + diag(d) @ B (rows of a term added to rows of the sum)."""
    return add_diag_scaled(A, np.asarray(d, dtype=A.dtype), B)
