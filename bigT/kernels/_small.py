"""numpy/scipy versions of the kernels, for inputs below ``config.KERNEL_NUMPY_MAX_WORK``.

Why: numba compiles each kernel on its first call in a fresh install (about 1 s per
kernel and dtype, 10-25 s for a first ``bigT invert``), and a product of a few
thousand multiply-adds gains nothing from it. Below the limit the wrappers of
:mod:`bigT.kernels.csr` call these instead, so a small run never imports numba.

Same contract as the numba kernels (``_csr_kernels``), which the tests check by running
every wrapper test on both: raw CSR arrays in (validated where a docstring says so),
sums in float64 rounded once to the output dtype, a product entry kept when
``v != 0 and |v| >= threshold`` on the rounded v, rows sorted and duplicate-free.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ._constants import CSR_BAD_INDPTR, CSR_INDEX_OUT_OF_RANGE, CSR_NOT_FINITE, CSR_OK


def row_ids(indptr: np.ndarray) -> np.ndarray:
    """The row of every stored entry, shape (nnz,) int64."""
    return np.repeat(np.arange(len(indptr) - 1), np.diff(indptr).astype(np.int64))


def check_csr(indptr, indices, data, n_cols):
    """``check_csr_internal``: (status, where, canonical); the first problem by kind
    (structure, then the earliest index out of range or non-finite value)."""
    n_rows = len(indptr) - 1
    nnz = len(indices)
    if indptr[0] != 0 or indptr[n_rows] != nnz or len(data) != nnz:
        return CSR_BAD_INDPTR, 0, False
    bad_rows = np.flatnonzero(np.diff(indptr) < 0)
    if len(bad_rows):
        return CSR_BAD_INDPTR, int(bad_rows[0]), False
    problems = [(int(p[0]), status) for p, status in (
        (np.flatnonzero((indices < 0) | (indices >= n_cols)), CSR_INDEX_OUT_OF_RANGE),
        (np.flatnonzero(~np.isfinite(data)), CSR_NOT_FINITE)) if len(p)]
    if problems:
        where, status = min(problems)
        return status, where, False
    same_row = row_ids(indptr)
    canonical = bool(np.all((np.diff(indices) > 0) | (np.diff(same_row) != 0)))
    return CSR_OK, 0, canonical


def _keep(C: sp.csr_array, dtype, threshold: float):
    """C's entries rounded to ``dtype``, pruned, as sorted raw arrays."""
    C.sort_indices()
    v = C.data.astype(dtype)
    keep = (v != 0) & (np.abs(v) >= threshold)
    counts = np.bincount(row_ids(C.indptr)[keep], minlength=C.shape[0])
    indptr = np.zeros(C.shape[0] + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    return indptr, C.indices[keep], v[keep]


def _csr64(shape, indptr, indices, data) -> sp.csr_array:
    return sp.csr_array((data.astype(np.float64), indices, indptr), shape=shape)


def spgemm(a, b, threshold: float, dtype):
    """A @ B of two validated operands (``_CSR``), pruned: (indptr, indices, data)."""
    C = sp.csr_array(_csr64(a.shape, a.indptr, a.indices, a.data)
                     @ _csr64(b.shape, b.indptr, b.indices, b.data))
    return _keep(C, dtype, threshold)


def prune(indptr, indices, data, threshold: float, shape):
    """``prune_internal``."""
    return _keep(sp.csr_array((data, indices, indptr), shape=shape), data.dtype, threshold)


def top_k(indptr, indices, data, k: int):
    """``top_k_internal``: each row's k largest |v|, ties to the smaller column."""
    keep = np.ones(len(data), bool)
    for i in np.flatnonzero(np.diff(indptr) > k):
        start, stop = int(indptr[i]), int(indptr[i + 1])
        # a stable sort of the column-ordered row by -|v|: ties keep column order
        order = np.argsort(-np.abs(data[start:stop].astype(np.float64)), kind="stable")
        keep[start + order[k:]] = False
    counts = np.bincount(row_ids(indptr)[keep], minlength=len(indptr) - 1)
    out_p = np.zeros(len(indptr), indptr.dtype)
    np.cumsum(counts, out=out_p[1:])
    return out_p, indices[keep], data[keep]


def scale_rows(indptr, data, d):
    """``scale_rows_internal``: d[i] * data[p] for p in row i, a new array."""
    return data * d[row_ids(indptr)]


def scale_cols(indices, data, d):
    """``scale_cols_internal``: data[p] * d[indices[p]], a new array."""
    return data * d[indices]


def scale_cols_off_diagonal(indptr, indices, data, d, offset, indptr_out, indices_out,
                            data_out):
    """``scale_cols_off_diagonal_internal``: the entries off the block's diagonal kept,
    scaled by their column's d."""
    rows = row_ids(indptr)
    keep = indices != rows + offset
    indptr_out[0] = 0
    np.cumsum(np.bincount(rows[keep], minlength=len(indptr) - 1), out=indptr_out[1:])
    kept = int(keep.sum())
    indices_out[:kept] = indices[keep]
    data_out[:kept] = data[keep] * d[indices[keep]]


def diagonal(indptr, indices, data, out):
    """``diagonal_internal``: out[i] += A[i, i] (duplicates summed, any row order)."""
    rows = row_ids(indptr)
    on = rows == indices
    np.add.at(out, rows[on], data[on])


def add_diag_scaled(a, d, b, dtype):
    """``add_diag_scaled_internal``: A + diag(d) B, exact zeros dropped."""
    B = _csr64(b.shape, b.indptr, b.indices, b.data)
    C = sp.csr_array(_csr64(a.shape, a.indptr, a.indices, a.data)
                     + sp.csr_array(B.multiply(np.asarray(d, np.float64)[:, None])))
    return _keep(C, dtype, 0.0)


def spmm_dense(indptr, indices, data, X, out, absolute=False):
    """``spmm_dense_rows_internal`` over all rows: out += A @ X (|A| @ X when
    ``absolute``); (status, row).

    A row whose sum is not finite is reported and, as in the kernel, it and the rows
    after it are not added.
    """
    n_cols, k = X.shape
    nnz = len(indices)
    steps = np.diff(indptr)
    bad_rows = np.flatnonzero((steps < 0) | (indptr[1:] > nnz) | (indptr[:-1] < 0))
    if len(bad_rows):
        return CSR_BAD_INDPTR, int(bad_rows[0])
    used = indices[:indptr[-1]]
    out_of_range = np.flatnonzero((used < 0) | (used >= n_cols))
    if len(out_of_range):
        return CSR_INDEX_OUT_OF_RANGE, int(np.searchsorted(indptr, out_of_range[0], "right") - 1)
    # k = 1 sums in float64, k > 1 in X's dtype (the kernel's accumulators)
    acc = np.float64 if k == 1 else X.dtype
    values = data[:len(used)].astype(acc)
    A = sp.csr_array((np.abs(values) if absolute else values, used, indptr),
                     shape=(len(indptr) - 1, n_cols))
    Y = A @ X.astype(acc)
    bad = np.flatnonzero(~np.isfinite(Y).all(axis=1))
    stop = int(bad[0]) if len(bad) else len(Y)
    out[:stop] += Y[:stop]
    return (CSR_NOT_FINITE, stop) if len(bad) else (CSR_OK, 0)


def split_column_tiles(indptr, indices, data, tile_size: int):
    """``split_column_tiles_internal``: a stable sort by tile column (small-integer
    keys, so numpy's radix sort, O(nnz)) keeps each tile row-major and column-sorted."""
    n_rows = len(indptr) - 1
    tcol = indices // tile_size
    key = tcol.astype(np.uint16) if indices.size and tcol.max() < 2**16 else tcol
    order = np.argsort(key, kind="stable")
    tile_cols, starts = np.unique(tcol[order], return_index=True)
    bounds = np.append(starts, indices.size).astype(np.int64)
    rows = row_ids(indptr)[order]
    tile_indptr = np.zeros((tile_cols.size, n_rows + 1), np.int64)
    for t in range(tile_cols.size):
        counts = np.bincount(rows[bounds[t]:bounds[t + 1]], minlength=n_rows)
        np.cumsum(counts, out=tile_indptr[t, 1:])
    local = (indices[order] - tcol[order] * tile_size).astype(np.int32)
    return tile_cols.astype(np.int64), tile_indptr, local, data[order], bounds


def join_column_tiles(tile_cols, tile_indptr, local, values, bounds, tile_size,
                      indptr_out, indices_out, data_out):
    """``join_column_tiles_internal``: each tile's entries scattered to their place in
    the joined rows (the row's start plus the entries of earlier tiles in that row)."""
    counts = np.diff(tile_indptr, axis=1)  # (k, n_rows)
    indptr_out[0] = 0
    np.cumsum(counts.sum(axis=0), out=indptr_out[1:])
    fill = indptr_out[:-1].copy()
    for t in range(len(tile_cols)):
        lens = counts[t]
        part = slice(bounds[t], bounds[t + 1])
        dest = np.repeat(fill - tile_indptr[t, :-1], lens) + np.arange(bounds[t + 1] - bounds[t])
        indices_out[dest] = local[part] + tile_cols[t] * tile_size
        data_out[dest] = values[part]
        fill += lens
