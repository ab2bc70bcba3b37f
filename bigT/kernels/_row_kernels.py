"""Unchecked numba kernels that count over a CSR matrix's rows or cut them into row
ranges (the wrappers are in :mod:`bigT.kernels.row_ranges` and :mod:`bigT.kernels.csr`).

Each is one pass over ``indices`` without a temporary as long as it: the numpy forms
they replace (a gather, a cumsum, a repeat and a bincount over every entry) allocate one
or two arrays of nnz int64 each, which at 3*10^7 entries cost more than the pass.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def row_work_internal(a_indptr, a_indices, b_indptr):
    """Per row i of A: sum over its entries (i, k) of len(row k of B), shape (n_rows,)
    int64 (the multiply-adds of row i of A @ B)."""
    n_rows = a_indptr.shape[0] - 1
    out = np.empty(n_rows, np.int64)
    for i in range(n_rows):
        s = 0
        for p in range(a_indptr[i], a_indptr[i + 1]):
            k = a_indices[p]
            s += b_indptr[k + 1] - b_indptr[k]
        out[i] = s
    return out


@njit(nogil=True, cache=True)
def tile_pairs_internal(indptr, indices, tile_size, n_blocks, nonempty):
    """Per row block of ``tile_size`` rows: how many distinct column tiles its entries
    fall in whose ``nonempty[tile]`` is set (``computed``) and not set (``skipped``),
    each shape (n_blocks,) int64. Rows need not be sorted."""
    n_rows = indptr.shape[0] - 1
    computed = np.zeros(n_blocks, np.int64)
    skipped = np.zeros(n_blocks, np.int64)
    seen = np.full(nonempty.shape[0], -1, np.int64)  # the block that last counted it
    for b in range(n_blocks):
        lo, hi = -1, -1  # the columns of the tile last counted: most entries fall in it
        for i in range(b * tile_size, min(n_rows, (b + 1) * tile_size)):
            for p in range(indptr[i], indptr[i + 1]):
                j = indices[p]
                if lo <= j < hi:
                    continue
                t = j // tile_size
                lo, hi = t * tile_size, (t + 1) * tile_size
                if seen[t] != b:
                    seen[t] = b
                    if nonempty[t]:
                        computed[b] += 1
                    else:
                        skipped[b] += 1
    return computed, skipped


@njit(nogil=True, cache=True)
def kept_per_row_internal(indptr, data, threshold, r0, r1, out):
    """out[i] = the entries of row i that ``prune_internal`` keeps (|v| >= threshold
    and v != 0), for rows ``r0:r1``."""
    for i in range(r0, r1):
        kept = 0
        for p in range(indptr[i], indptr[i + 1]):
            v = data[p]
            if v != 0 and abs(v) >= threshold:
                kept += 1
        out[i] = kept


@njit(nogil=True, cache=True)
def prune_into_internal(indptr, indices, data, threshold, r0, r1, out_p, out_j, out_v):
    """Rows ``r0:r1`` of ``prune_internal``'s result written at their place in the
    result's arrays, whose row pointer ``out_p`` is already known."""
    for i in range(r0, r1):
        pos = out_p[i]
        for p in range(indptr[i], indptr[i + 1]):
            v = data[p]
            if v != 0 and abs(v) >= threshold:
                out_j[pos] = indices[p]
                out_v[pos] = v
                pos += 1


@njit(nogil=True, cache=True, inline="always")
def _kept(v, scratch):
    """Whether ``v`` is nonzero once rounded to the result's dtype (``scratch``, one
    element of it): what ``add_diag_scaled_internal`` keeps."""
    scratch[0] = v
    return scratch[0] != 0


@njit(nogil=True, cache=True)
def merged_per_row_internal(a_indptr, a_indices, a_data, d, b_indptr, b_indices, b_data,
                            r0, r1, out, scratch):
    """out[i] = the entries of row i of ``add_diag_scaled_internal``'s A + diag(d) B
    (the union of the rows' columns, less the sums that round to exactly 0), for rows
    ``r0:r1``; ``scratch`` is one element of the result's dtype."""
    for i in range(r0, r1):
        di = np.float64(d[i])
        p, pe, q, qe = a_indptr[i], a_indptr[i + 1], b_indptr[i], b_indptr[i + 1]
        kept = 0
        while p < pe and q < qe:
            ja, jb = a_indices[p], b_indices[q]
            if ja < jb:
                v = np.float64(a_data[p])
                p += 1
            elif jb < ja:
                v = di * b_data[q]
                q += 1
            else:
                v = np.float64(a_data[p]) + di * b_data[q]
                p += 1
                q += 1
            if _kept(v, scratch):
                kept += 1
        while p < pe:
            if _kept(np.float64(a_data[p]), scratch):
                kept += 1
            p += 1
        while q < qe:
            if _kept(di * b_data[q], scratch):
                kept += 1
            q += 1
        out[i] = kept


@njit(nogil=True, cache=True)
def add_diag_scaled_into_internal(a_indptr, a_indices, a_data, d, b_indptr, b_indices,
                                  b_data, r0, r1, out_p, out_j, out_v):
    """Rows ``r0:r1`` of ``add_diag_scaled_internal``'s A + diag(d) B written at their
    place in the result's arrays, whose row pointer ``out_p`` is already known
    (:func:`merged_per_row_internal`). Each value is rounded to the result's dtype
    before it is tested, and written only when kept: a row never writes past its end
    (the next row's, maybe another thread's)."""
    scratch = np.empty(1, out_v.dtype)
    for i in range(r0, r1):
        di = np.float64(d[i])
        p, pe, q, qe = a_indptr[i], a_indptr[i + 1], b_indptr[i], b_indptr[i + 1]
        pos = out_p[i]
        while p < pe or q < qe:
            if q >= qe or (p < pe and a_indices[p] < b_indices[q]):
                j, v = a_indices[p], np.float64(a_data[p])
                p += 1
            elif p >= pe or b_indices[q] < a_indices[p]:
                j, v = b_indices[q], di * b_data[q]
                q += 1
            else:
                j, v = a_indices[p], np.float64(a_data[p]) + di * b_data[q]
                p += 1
                q += 1
            if _kept(v, scratch):
                out_j[pos] = j
                out_v[pos] = scratch[0]
                pos += 1


@njit(nogil=True, cache=True)
def relabel_internal(indices, labels, p0, p1, out):
    """out[p] = labels[indices[p]] for entries ``p0:p1`` (``out`` may be ``indices``:
    each entry is read before it is written)."""
    for p in range(p0, p1):
        out[p] = labels[indices[p]]


@njit(nogil=True, cache=True)
def kept_by_column_internal(indptr, indices, keep, r0, r1, out):
    """out[i] = the entries of row i whose column c has ``keep[c]``, for rows
    ``r0:r1``."""
    for i in range(r0, r1):
        kept = 0
        for p in range(indptr[i], indptr[i + 1]):
            if keep[indices[p]]:
                kept += 1
        out[i] = kept


@njit(nogil=True, cache=True)
def select_by_column_into_internal(indptr, indices, data, keep, r0, r1, out_p, out_j,
                                   out_v):
    """Rows ``r0:r1`` of the entries ``kept_by_column_internal`` counts, written at
    their place in the result's arrays (row pointer ``out_p`` known), in row order."""
    for i in range(r0, r1):
        pos = out_p[i]
        for p in range(indptr[i], indptr[i + 1]):
            if keep[indices[p]]:
                out_j[pos] = indices[p]
                out_v[pos] = data[p]
                pos += 1


@njit(nogil=True, cache=True)
def off_diagonal_per_row_internal(indptr, indices, offset, out):
    """out[i] = the entries of row i outside column i + ``offset``, for every row of a
    row block whose rows are sorted (a binary search a row, not a pass over them:
    :func:`scale_off_diagonal_into_internal` checks the order as it writes)."""
    for i in range(indptr.shape[0] - 1):
        lo, hi = indptr[i], indptr[i + 1]
        target = i + offset
        a, b = lo, hi
        while a < b:
            mid = (a + b) // 2
            if indices[mid] < target:
                a = mid + 1
            else:
                b = mid
        out[i] = hi - lo - (1 if a < hi and indices[a] == target else 0)


@njit(nogil=True, cache=True)
def scale_off_diagonal_into_internal(indptr, indices, data, d, offset, out_p, row0,
                                     out_j, out_v):
    """The rows of a row block starting at global row ``offset`` written as
    ``scale_cols_off_diagonal_internal`` writes them (each entry times d of its column,
    the one in column i + offset left out) at rows ``row0:`` of the result, whose row
    pointer ``out_p`` is already known. False, with rows left half written, where a
    row's columns do not increase strictly, leave ``0:len(d)``, or do not fill the
    row's place (its count was made for sorted rows)."""
    n_cols = d.shape[0]
    for i in range(indptr.shape[0] - 1):
        q, end = out_p[row0 + i], out_p[row0 + i + 1]
        diag = i + offset
        prev = -1
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j <= prev or j >= n_cols:
                return False
            prev = j
            if j != diag:
                if q >= end:
                    return False
                out_j[q] = j
                out_v[q] = data[p] * d[j]
                q += 1
        if q != end:
            return False
    return True


@njit(nogil=True, cache=True)
def checked_tile_counts_internal(indptr, indices, data, n_cols, tile_size, counts):
    """Whether a tile row's CSR arrays hold together (``indptr`` monotone from 0 to
    len(indices), each row's columns strictly increasing inside ``0:n_cols``, every
    value finite), counting meanwhile the entries of each tile column into ``counts``
    (n_cols / tile_size rounded up,): one pass instead of numpy's five (a reduction
    or a temporary as long as the row each)."""
    nnz = indices.shape[0]
    rows = indptr.shape[0] - 1
    if indptr[0] != 0 or indptr[rows] != nnz:
        return False
    for i in range(rows):  # first: every row's range inside the arrays
        if indptr[i + 1] < indptr[i]:
            return False
    for i in range(rows):
        prev = -1
        tile, bound = -1, 0  # the tile column of the last entry, and where it ends
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j <= prev or j >= n_cols or not np.isfinite(data[p]):
                return False
            prev = j
            if j >= bound:  # columns increase: a division per tile, not per entry
                tile = j // tile_size
                bound = (tile + 1) * tile_size
            counts[tile] += 1
    return True
