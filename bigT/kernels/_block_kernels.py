"""Unchecked numba kernels of block-diagonal products on raw CSR arrays, used by
:mod:`.block_diagonal`: the products for 3 x 3 blocks (a colour F's; scalar code runs
at several times a general b x b loop's speed), the block helpers for any b.

Input rows are sorted (a pixel's b columns are then adjacent); outputs are sorted,
duplicate-free, exact zeros dropped (as scipy's products drop them). Each product is
two passes over the rows, one counting and one writing, so the output is allocated
once at its size: scipy's ``A @ blockdiag`` and its sort held the product, its
transposed workspace and a sorted copy at once, and took three times as long.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(nogil=True, cache=True)
def _cols_block_row(indptr, indices, data, blocks, i, skip_pixel, sign, out_idx, out_val,
                    q):
    """Row i of sign * (A @ blockdiag(blocks)), 3 x 3 blocks, without pixel
    ``skip_pixel``'s columns (-1: none), written at q of ``out_idx``/``out_val`` (None:
    only counted); returns the next q. Scalar accumulators: the general b x b loop
    ran at a third of this speed."""
    p = indptr[i]
    stop = indptr[i + 1]
    while p < stop:
        pix = indices[p] // 3  # one division a pixel; its entries run to column hi
        lo = pix * 3
        hi = lo + 3
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        while p < stop and indices[p] < hi:
            a = np.float64(data[p])
            k = indices[p] - lo
            s0 += a * blocks[pix, k, 0]
            s1 += a * blocks[pix, k, 1]
            s2 += a * blocks[pix, k, 2]
            p += 1
        if pix == skip_pixel:
            continue
        if out_val is None:
            q += (s0 != 0.0) + (s1 != 0.0) + (s2 != 0.0)
            continue
        if s0 != 0.0:
            out_idx[q] = lo
            out_val[q] = sign * s0
            q += 1
        if s1 != 0.0:
            out_idx[q] = lo + 1
            out_val[q] = sign * s1
            q += 1
        if s2 != 0.0:
            out_idx[q] = lo + 2
            out_val[q] = sign * s2
            q += 1
    return q


@njit(nogil=True, cache=True)
def scale_cols_blocks_internal(indptr, indices, data, blocks, start, skip_diagonal, sign,
                               out_dtype):
    """sign * (A @ blockdiag(blocks)), 3 x 3 blocks, for the row block A whose first
    row is global row ``start``; with ``skip_diagonal`` each row's own pixel's 3
    columns (the diagonal blocks) are left out. Returns (indptr, indices, data)."""
    r = indptr.shape[0] - 1
    out_ptr = np.zeros(r + 1, np.int64)
    dummy_idx = np.zeros(0, indices.dtype)
    for i in range(r):
        skip = (start + i) // 3 if skip_diagonal else -1
        out_ptr[i + 1] = _cols_block_row(indptr, indices, data, blocks, i, skip, sign,
                                         dummy_idx, None, out_ptr[i])
    out_idx = np.empty(out_ptr[r], indices.dtype)
    out_val = np.empty(out_ptr[r], out_dtype)
    for i in range(r):
        skip = (start + i) // 3 if skip_diagonal else -1
        _cols_block_row(indptr, indices, data, blocks, i, skip, sign, out_idx, out_val,
                        out_ptr[i])
    return out_ptr, out_idx, out_val


@njit(nogil=True, cache=True)
def _rows_block(indptr, indices, data, blocks, pix, local, starts, out_idx, out_val):
    """The 3 rows of pixel ``pix`` (local rows local .. local + 2) of blockdiag(blocks)
    @ A: a 3-way merge of A's 3 sorted rows, written from ``starts``' positions, or
    counted into ``starts`` (out_val None). Scalar heads and block entries: a pixel's
    rows usually share their columns, and this loop then has no unpredictable
    branch."""
    big = np.iinfo(np.int64).max
    h0, e0 = indptr[local], indptr[local + 1]
    h1, e1 = indptr[local + 1], indptr[local + 2]
    h2, e2 = indptr[local + 2], indptr[local + 3]
    q0, q1, q2 = starts[local], starts[local + 1], starts[local + 2]
    b00, b01, b02 = np.float64(blocks[pix, 0, 0]), np.float64(blocks[pix, 0, 1]), np.float64(blocks[pix, 0, 2])
    b10, b11, b12 = np.float64(blocks[pix, 1, 0]), np.float64(blocks[pix, 1, 1]), np.float64(blocks[pix, 1, 2])
    b20, b21, b22 = np.float64(blocks[pix, 2, 0]), np.float64(blocks[pix, 2, 1]), np.float64(blocks[pix, 2, 2])
    while True:
        j0 = np.int64(indices[h0]) if h0 < e0 else big
        j1 = np.int64(indices[h1]) if h1 < e1 else big
        j2 = np.int64(indices[h2]) if h2 < e2 else big
        col = min(j0, min(j1, j2))
        if col == big:
            break
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        if j0 == col:
            a0 = np.float64(data[h0])
            h0 += 1
        if j1 == col:
            a1 = np.float64(data[h1])
            h1 += 1
        if j2 == col:
            a2 = np.float64(data[h2])
            h2 += 1
        v0 = b00 * a0 + b01 * a1 + b02 * a2
        v1 = b10 * a0 + b11 * a1 + b12 * a2
        v2 = b20 * a0 + b21 * a1 + b22 * a2
        if out_val is None:
            q0 += v0 != 0.0
            q1 += v1 != 0.0
            q2 += v2 != 0.0
            continue
        if v0 != 0.0:
            out_idx[q0] = col
            out_val[q0] = v0
            q0 += 1
        if v1 != 0.0:
            out_idx[q1] = col
            out_val[q1] = v1
            q1 += 1
        if v2 != 0.0:
            out_idx[q2] = col
            out_val[q2] = v2
            q2 += 1
    starts[local], starts[local + 1], starts[local + 2] = q0, q1, q2


@njit(nogil=True, cache=True)
def scale_rows_blocks_internal(indptr, indices, data, blocks, first_pixel, out_dtype):
    """blockdiag(blocks)[rows] @ A, 3 x 3 blocks, for the row block A whose rows are
    pixels first_pixel .. (3 rows each). Returns (indptr, indices, data)."""
    r = indptr.shape[0] - 1
    counts = np.zeros(r + 1, np.int64)
    dummy_idx = np.zeros(0, indices.dtype)
    for local in range(0, r, 3):
        _rows_block(indptr, indices, data, blocks, first_pixel + local // 3, local, counts,
                    dummy_idx, None)
    out_ptr = np.zeros(r + 1, np.int64)
    for i in range(r):
        out_ptr[i + 1] = out_ptr[i] + counts[i]
    out_idx = np.empty(out_ptr[r], indices.dtype)
    out_val = np.empty(out_ptr[r], out_dtype)
    starts = out_ptr.copy()
    for local in range(0, r, 3):
        _rows_block(indptr, indices, data, blocks, first_pixel + local // 3, local, starts,
                    out_idx, out_val)
    return out_ptr, out_idx, out_val


@njit(nogil=True, cache=True)
def diagonal_blocks_internal(indptr, indices, data, start, b, out):
    """out[p] += the b x b diagonal block of the row block's pixel p (first row: global
    row ``start``); duplicates summed, rows in any order."""
    for i in range(indptr.shape[0] - 1):
        g = start + i
        lo = (g // b) * b
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if lo <= j < lo + b:
                out[i // b, g - lo, j - lo] += data[p]


@njit(nogil=True, cache=True)
def off_block_diagonal_internal(indptr, indices, data, start, b):
    """The row block without its entries in b x b diagonal blocks: (indptr, indices,
    data), order kept."""
    r = indptr.shape[0] - 1
    out_ptr = np.zeros(r + 1, np.int64)
    for i in range(r):
        lo = ((start + i) // b) * b
        n = 0
        for p in range(indptr[i], indptr[i + 1]):
            if not lo <= indices[p] < lo + b:
                n += 1
        out_ptr[i + 1] = out_ptr[i] + n
    out_idx = np.empty(out_ptr[r], indices.dtype)
    out_val = np.empty(out_ptr[r], data.dtype)
    q = 0
    for i in range(r):
        lo = ((start + i) // b) * b
        for p in range(indptr[i], indptr[i + 1]):
            if not lo <= indices[p] < lo + b:
                out_idx[q] = indices[p]
                out_val[q] = data[p]
                q += 1
    return out_ptr, out_idx, out_val
