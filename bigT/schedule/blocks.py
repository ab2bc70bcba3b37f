"""What runs on one tile row: pure functions on ``scipy.sparse.csr_array`` blocks.

How the blocks are wired into passes lives in :mod:`bigT.schedule.runner`; the
operators that read tiles from stores live in :mod:`bigT.schedule.operators`. Nothing
here touches dask or zarr.

Notation (paper eq. 13, docs/DESIGN.md "The math"): T is n x n, F the first bounce
(diagonal, stored as the vector ``f``; ``finv`` = 1/f, 0 on excluded pixels; for a
colour T block-diagonal, stored as its (n/3, 3, 3) blocks, ``finv`` their inverses), D
the diagonal 0/1 mask of active pixels, M = D - T F^-1.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ._backend import (BlockDiagonal, add_diag_scaled_rows, multiply_adds, prune,
                       scale_cols_off_diagonal, spgemm)


@dataclass
class KernelTally:
    """What one task's products cost: the multiply-adds the kernel did (a left entry
    (i, k) times the row k of the right factor is len(row k) of them) and the
    thread-seconds spent inside it (wall time times the kernel's threads). Per task, so
    never shared between threads; the engine adds them up per term to set the bare
    kernel's rate beside the term's whole time.

    Attributes
    ----------
    multiply_adds : int
    seconds : float
    """

    multiply_adds: int = 0
    seconds: float = 0.0

    def spgemm(self, left: sp.csr_array, right: sp.csr_array, threshold: float,
               n_threads: int) -> sp.csr_array:
        """``left @ right`` pruned at ``threshold`` (the kernel), counted: left of shape
        (r, n), right (n, n), the result (r, n)."""
        t0 = time.perf_counter()
        out = spgemm(left, right, threshold=threshold, n_threads=n_threads,
                     checked=not _trusted(right))
        # None: the kernel's default, one thread per core
        self.seconds += (time.perf_counter() - t0) * (n_threads or os.cpu_count() or 1)
        # sum over left's entries (i, k) of len(right row k): one pass over left's
        # indices (as the kernel's own per-row count, row_work)
        self.multiply_adds += multiply_adds(left, right)
        return out


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


def m_rows(T_rows: sp.csr_array, start: int, finv: np.ndarray, active_rows: np.ndarray,
           zero_diagonal: bool, minus_finv: np.ndarray | None = None,
           checked: bool = True) -> sp.csr_array:
    """Rows ``start:start + r`` of M = D - T F^-1 from the same rows of T.

    Parameters
    ----------
    T_rows : csr_array, shape (r, n), global columns
    start : int, global index of the first row
    finv : (n,) ndarray, 1/F (0 on excluded pixels); or (n/b, b, b), the inverses of
        a block-diagonal F's blocks (colour: b = 3; ``start`` and r multiples of b)
    active_rows : (r,) bool ndarray, D's diagonal on these rows
    zero_diagonal : bool
        F = diag T: M's diagonal is exactly 1 - T_ii / T_ii = 0 and is dropped instead
        of being left as rounding noise (for a block-diagonal F = T's diagonal blocks,
        M's diagonal blocks are I - B B^-1 = 0: dropped the same way).
    minus_finv : (n,) ndarray of T_rows' dtype, optional
        -finv in T_rows' dtype, made once by a caller that makes many row blocks (it is
        as long as a row: at full HD, 254 tasks each negating 2*10^6 entries cost
        ~0.2 s).
    checked : bool
        False: T_rows are as the store's reader returned them (checked there) and finv
        is the engine's, checked once: the grey kernel does not check them again
        (:func:`bigT.kernels.scale_cols_off_diagonal`).

    Returns
    -------
    csr_array, shape (r, n), sorted indices
    """
    if np.ndim(finv) == 3:
        return _m_rows_blocks(T_rows, start, BlockDiagonal(finv), active_rows,
                              zero_diagonal)
    if minus_finv is None or minus_finv.dtype != T_rows.dtype:
        minus_finv = -np.asarray(finv, dtype=T_rows.dtype)
    # one pass, no COO round trip: a tile row of a big T has ~10^7 entries and every
    # extra copy of them counts against the memory limit
    M = scale_cols_off_diagonal(T_rows, minus_finv, start, checked=checked)
    if not zero_diagonal:
        r = T_rows.shape[0]
        d = (np.asarray(active_rows, dtype=M.dtype)
             + T_rows.diagonal(k=start) * minus_finv[start:start + r])
        nz = np.flatnonzero(d)
        M = sp.csr_array(M + sp.csr_array((d[nz], (nz, nz + start)), shape=M.shape))
        M.sort_indices()
    return _narrow_indices(M)


def _narrow_indices(M: sp.csr_array) -> sp.csr_array:
    if M.nnz < 2**31 and M.shape[1] < 2**31:
        # scipy's sum may widen the indices; the memory plan counts int32 ones
        M.indices = M.indices.astype(np.int32, copy=False)
        M.indptr = M.indptr.astype(np.int32, copy=False)
    return M


def _m_rows_blocks(T_rows: sp.csr_array, start: int, finv: BlockDiagonal,
                   active_rows: np.ndarray, zero_diagonal: bool) -> sp.csr_array:
    """:func:`m_rows` for a block-diagonal F (colour). T F^-1 mixes each entry into the
    b columns of its pixel (O(b nnz)); the rows of pixels left out are empty (their X
    rows are 0 whatever M holds there, and M's other rows never reach them: F^-1's
    columns for them are 0), so the products skip them."""
    if zero_diagonal:
        M = finv.scale_cols(T_rows, negate=True, drop_diagonal_blocks_at=start)
        if np.all(active_rows):  # the kernel's output is canonical, zeros dropped
            return _narrow_indices(M)
    else:
        M = finv.scale_cols(T_rows, negate=True)
        rows = np.flatnonzero(active_rows)
        D = sp.csr_array((np.ones(len(rows), M.dtype), (rows, rows + start)), shape=M.shape)
        M = sp.csr_array(M + D)
    if not np.all(active_rows):
        M = sp.csr_array(sp.diags_array(np.asarray(active_rows, M.dtype)) @ M)
    M.eliminate_zeros()
    M.sum_duplicates()
    M.sort_indices()
    return _narrow_indices(M)


def assemble_rows(row_blocks, n_rows: int, n_cols: int, dtype, nnz: int) -> sp.csr_array:
    """An (n_rows, n_cols) CSR holding the given row blocks at their starts and empty
    rows elsewhere (a right operand restricted to some tile rows, or whole).

    Parameters
    ----------
    row_blocks : iterable of (start, csr_array of shape (r, n_cols))
        Ascending starts, consumed one at a time: a generator that reads each block
        lets it go once copied, so assembling never holds two copies.
    nnz : int
        Their total entries (the stores' tile counts give it): the arrays are
        allocated once at their final size.
    """
    idx = np.int32 if nnz < 2**31 and max(n_rows, n_cols) < 2**31 else np.int64
    indptr = np.zeros(n_rows + 1, dtype=idx)
    indices = np.empty(nnz, dtype=idx)
    data = np.empty(nnz, dtype=dtype)
    pos, is_sorted, end = 0, True, 0
    for start, B in row_blocks:
        if start < end or start + B.shape[0] > n_rows:
            raise ValueError(f"row block at {start} ({B.shape[0]} rows) overlaps the one "
                             f"before (ending at {end}) or passes row {n_rows}")
        end = start + B.shape[0]
        if pos + B.nnz > nnz:
            raise ValueError(f"row blocks hold more than the {nnz} entries announced")
        indices[pos:pos + B.nnz] = B.indices
        data[pos:pos + B.nnz] = B.data
        indptr[start + 1:start + 1 + B.shape[0]] = np.diff(B.indptr)
        is_sorted &= bool(B.has_sorted_indices)
        pos += B.nnz
    if pos != nnz:
        raise ValueError(f"row blocks hold {pos} entries, {nnz} announced")
    np.cumsum(indptr, out=indptr)
    out = sp.csr_array((data, indices, indptr), shape=(n_rows, n_cols))
    out.has_sorted_indices = is_sorted
    return out


def _trusted(right: sp.csr_array) -> bool:
    """Whether the kernel may skip its O(nnz) check of ``right``: a right factor read
    from bigT stores (whose writers checked every tile) with sorted rows. scipy works
    the sortedness out once per matrix and keeps it, and the whole right factor of a
    pass is one matrix shared by all its tasks, so the check is paid once per pass
    instead of once per tile row."""
    return bool(right.has_sorted_indices)


def row_product(left_row: sp.csr_array, right: sp.csr_array, threshold: float,
                n_threads: int = 1, tally: KernelTally | None = None) -> sp.csr_array:
    """L_i @ B with entries below ``threshold`` pruned inside the kernel's row loop.

    Parameters
    ----------
    left_row : csr_array, shape (r, n), global columns (a tile row of the left factor)
    right : csr_array, shape (n, n)
    n_threads : int
        Threads of the kernel (1 when dask already runs tile rows in parallel).
    tally : KernelTally, optional
        Counts the product's multiply-adds and kernel time.

    Returns
    -------
    csr_array, shape (r, n)
    """
    return (tally or KernelTally()).spgemm(left_row, right, threshold, n_threads)


def row_product_batched(left_row: sp.csr_array, batches, threshold: float,
                        work_per_row: np.ndarray, max_partial_entries: int,
                        n_threads: int = 1, tally: KernelTally | None = None) -> sp.csr_array:
    """L_i @ B when B is at hand only in batches of its tile rows (the memory bound).

    A product cannot be pruned before all of B has been seen (an entry's sum is only
    known then), so partial products are added unpruned. To bound them, the rows of
    L_i are taken in chunks whose unpruned partial sums hold at most
    ``max_partial_entries`` entries, and every batch of B is fetched once per chunk
    (from the tile cache when it holds it, else from disk): memory for re-reads.

    Parameters
    ----------
    left_row : csr_array, shape (r, n), global columns
    batches : list of callables
        Each returns one batch: an (n, n) csr_array holding some of B's tile rows
        (the others empty, see :func:`assemble_rows`); together they are B.
    work_per_row : (r,) ndarray
        Estimated multiply-adds of each row of L_i @ B (an estimate of the upper bound
        of its unpruned entries; the chunks are sized from it, then from the ratio of
        entries to multiply-adds seen in the chunks done).
    max_partial_entries : int
    tally : KernelTally, optional
        Counts the multiply-adds and kernel time of every partial product.

    Returns
    -------
    csr_array, shape (r, n), sorted indices; the same entries as one pruned product
    (up to rounding: partial sums are added in the output dtype).
    """
    r, n = left_row.shape
    tally = tally or KernelTally()
    if not batches:
        return empty((r, n), left_row.dtype)
    if len(batches) == 1:
        return tally.spgemm(left_row, batches[0](), threshold, n_threads)
    cum = np.concatenate([[0.0], np.cumsum(np.asarray(work_per_row, dtype=np.float64))])
    ratio = 1.0
    parts, start = [], 0
    while start < r:
        stop = int(np.searchsorted(cum, cum[start] + max_partial_entries / ratio,
                                   side="right")) - 1
        stop = min(max(stop, start + 1), r)
        chunk = left_row[start:stop]
        acc = None
        for fetch in batches:
            part = tally.spgemm(chunk, fetch(), 0.0, n_threads)
            acc = part if acc is None else sp.csr_array(acc + part)
            del part
        work = cum[stop] - cum[start]
        if work > 0 and acc.nnz:
            # the next chunk may fill in more than this one: keep a margin
            ratio = max(ratio if parts else 0.0, 1.25 * acc.nnz / work)
        parts.append(prune(acc, threshold=threshold))
        del acc
        start = stop
    out = parts[0] if len(parts) == 1 else sp.csr_array(sp.vstack(parts, format="csr"))
    out.has_sorted_indices = True
    return out


def add_scaled(A: sp.csr_array, d: np.ndarray, B: sp.csr_array,
               n_threads: int = 1) -> sp.csr_array:
    """A + diag(d) @ B (rows of a term added to rows of the sum), shapes (r, n) and
    d (r,); on ``n_threads`` row ranges at once (the whole matrices of the in-memory
    path; a task's tile row runs on its one thread)."""
    return add_diag_scaled_rows(A, np.asarray(d, dtype=A.dtype), B, n_threads)
