"""Whole-matrix helpers of the in-memory series: counts over a product's factors, and
element-wise kernels run over row ranges on several threads.

The CSR wrappers of :mod:`bigT.kernels.csr` (``add_diag_scaled``, ``prune``) run on one
thread: the out-of-core path calls them per tile row from dask's threads, which already
keep the cores busy. In memory the same operations see the whole matrix (6*10^7 entries
at 384x512) once per term: :func:`prune_rows` and :func:`add_diag_scaled_rows` cut it
into row ranges of equal entries and run each range on the shared thread pool, in two
passes (each row's entries counted, then written at their place in arrays of the
result's size), so that no buffer as long as the operands is filled and copied out.
Every row of their results is the one-thread wrapper's row, bit for bit.

The in-memory products also shrink what the kernel walks over without changing a sum:
:func:`narrow_columns` renumbers the right factor's columns to those holding entries
(the kernel's accumulators span its columns), :func:`restrict_to_used_rows` leaves out
the left factor's entries over empty rows of the right one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .csr import _small_enough, _split_rows, add_diag_scaled, prune, row_work
from .threads import run_on_threads


def multiply_adds(left: sp.csr_array, right: sp.csr_array) -> int:
    """Multiply-adds of ``left @ right``: the sum over left's entries (i, k) of the
    length of right's row k (one pass, no temporary of nnz(left))."""
    return int(row_work(left.indptr, left.indices[:left.indptr[-1]], right.indptr).sum())


def tile_pairs(left: sp.csr_array, right: sp.csr_array, tile_size: int,
               n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row block of ``tile_size`` rows of ``left``: the tile rows of ``right`` its
    product reads (a column tile of the block holding entries, over a nonempty tile
    row of ``right``) and those skipped (that tile row empty).

    Parameters
    ----------
    left : csr_array, shape (m, n), m <= n_blocks * tile_size
    right : csr_array, shape (n, p)

    Returns
    -------
    computed, skipped : (n_blocks,) int64
    """
    starts = np.arange(0, right.shape[0], tile_size)
    nonempty = np.add.reduceat(np.diff(right.indptr), starts) > 0 if len(starts) else \
        np.zeros(0, bool)
    if _small_enough(left.nnz):
        return _tile_pairs_numpy(left, nonempty, tile_size, n_blocks)
    from ._row_kernels import tile_pairs_internal  # numba: only for a big left factor

    return tile_pairs_internal(left.indptr, left.indices, np.int64(tile_size),
                               np.int64(n_blocks), nonempty)


def _tile_pairs_numpy(left, nonempty, ts, n_blocks):
    grid = len(nonempty)
    counts = np.diff(left.indptr)
    row_block = np.repeat(np.arange(left.shape[0]) // ts, counts)
    pair = row_block * grid + np.asarray(left.indices[:left.indptr[-1]]) // ts
    hit = np.bincount(pair, minlength=n_blocks * grid).reshape(n_blocks, grid) > 0
    computed = (hit & nonempty).sum(axis=1)
    return computed, hit.sum(axis=1) - computed


def row_bounds(indptr: np.ndarray, n_parts: int) -> np.ndarray:
    """Row boundaries cutting the rows of ``indptr`` (shape (m + 1,)) into at most
    ``n_parts`` ranges of about equal entries, shape (k + 1,) int64, from 0 to m."""
    return _split_rows(np.diff(indptr), n_parts)  # each row's work: its entries


def row_view(A: sp.csr_array, r0: int, r1: int) -> sp.csr_array:
    """Rows ``r0:r1`` of A sharing A's indices and values (scipy's slice copies them)."""
    start, stop = int(A.indptr[r0]), int(A.indptr[r1])
    view = sp.csr_array((A.data[start:stop], A.indices[start:stop],
                         A.indptr[r0:r1 + 1] - A.indptr[r0]), shape=(r1 - r0, A.shape[1]),
                        copy=False)
    view.has_sorted_indices = A.has_sorted_indices
    return view


def stack_rows(pieces: list[sp.csr_array]) -> sp.csr_array:
    """Row blocks of one width stacked in order (one copy of their entries), sorted
    when they all are."""
    if len(pieces) == 1:
        return pieces[0]
    nnz = sum(int(P.indptr[-1]) for P in pieces)
    n_rows = sum(P.shape[0] for P in pieces)
    idt = np.result_type(*(P.indices.dtype for P in pieces), *(P.indptr.dtype for P in pieces))
    if nnz >= np.iinfo(idt).max:
        idt = np.dtype(np.int64)
    indptr = np.empty(n_rows + 1, idt)
    indptr[0] = 0
    indices = np.empty(nnz, idt)
    data = np.empty(nnz, np.result_type(*(P.dtype for P in pieces)))
    row = pos = 0
    for P in pieces:
        k, r = int(P.indptr[-1]), P.shape[0]
        indices[pos:pos + k] = P.indices[:k]
        data[pos:pos + k] = P.data[:k]
        indptr[row + 1:row + r + 1] = P.indptr[1:] + pos
        row, pos = row + r, pos + k
    out = sp.csr_array((data, indices, indptr), shape=(n_rows, pieces[0].shape[1]),
                       copy=False)
    out.has_sorted_indices = all(bool(P.has_sorted_indices) for P in pieces)
    return out


def scaled_off_diagonal_rows(blocks: list[sp.csr_array], starts: list[int],
                             d: np.ndarray, n_threads: int) -> sp.csr_array | None:
    """The row blocks ``blocks`` (each (r_b, n), global columns, block b starting at
    global row ``starts[b]``) stacked, each entry times d of its column and the
    main diagonal's entries left out: the blocks of
    :func:`bigT.kernels.scale_cols_off_diagonal` (of each block at its offset) then
    :func:`stack_rows`, bit for bit, but written straight into arrays of the result's
    size, block by block on ``n_threads`` threads.

    Why: M = -T F^-1 off the diagonal, in memory, from T's tile rows (the dense
    384x512 corner: 6*10^7 entries in 24 tile rows). Each block's kernel call checked
    the rows again (the store's reader has), wrote a block as long as T's, and the
    stacking copied all of them once more on one thread (0.6 s of the run's set-up).
    Here each row's place is counted first (a binary search for its diagonal entry),
    then each block written in place, its rows checked as they are written.

    Returns
    -------
    csr_array, shape (sum r_b, n), canonical; or None where the blocks are small (the
    one-thread numpy forms are quicker than loading the kernels), not all of d's dtype,
    or not sorted, duplicate-free and in range (the caller then makes it block by
    block, which checks them and says what is wrong).
    """
    d = np.asarray(d)
    if not blocks:
        return None
    n_cols = blocks[0].shape[1]
    nnz_in = sum(int(B.indptr[-1]) for B in blocks)
    if (_small_enough(nnz_in) or d.shape != (n_cols,) or d.dtype.kind != "f"
            or any(B.dtype != d.dtype or B.shape[1] != n_cols or B.format != "csr"
                   for B in blocks)):
        return None
    from ._row_kernels import off_diagonal_per_row_internal, scale_off_diagonal_into_internal

    firsts = np.cumsum([0] + [B.shape[0] for B in blocks])  # each block's first row here
    counts = np.zeros(int(firsts[-1]) + 1, np.int64)
    for B, start, r0 in zip(blocks, starts, firsts):
        off_diagonal_per_row_internal(B.indptr, B.indices, np.int64(start),
                                      counts[r0 + 1:r0 + 1 + B.shape[0]])
    indptr = np.cumsum(counts)
    nnz = int(indptr[-1])
    # stack_rows' index dtype for blocks narrowed to int32 (the kernel's results)
    idt = np.int32 if nnz < np.iinfo(np.int32).max and n_cols <= 2**31 else np.int64
    indptr = indptr.astype(idt)
    indices, data = np.empty(nnz, idt), np.empty(nnz, d.dtype)

    def write(b0: int, b1: int) -> bool:
        B = blocks[b0]
        return bool(scale_off_diagonal_into_internal(
            B.indptr, B.indices, B.data, d, np.int64(starts[b0]), indptr,
            np.int64(firsts[b0]), indices, data))

    if not all(run_on_threads(write, [(b, b + 1) for b in range(len(blocks))], n_threads)):
        return None
    out = sp.csr_array((data, indices, indptr), shape=(int(firsts[-1]), n_cols), copy=False)
    out.has_sorted_indices = True
    out.has_canonical_format = True
    return out


def checked_tile_counts(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                        n_cols: int, tile_size: int) -> np.ndarray | None:
    """The entries of each tile column of a tile row, shape (ceil(n_cols / tile_size),)
    int64, where its CSR arrays hold together: ``indptr`` (rows + 1,) monotone from 0
    to len(indices), each row's ``indices`` (nnz,) strictly increasing in
    ``0:n_cols``, every value of ``data`` (nnz,) finite; else None (the caller's own
    checks then say what is wrong). One pass on the numba kernels: the store's
    reader checks every tile row it reads (the dense 384x512 corner's T: 6*10^7
    entries, ~0.4 s in numpy's reductions, each a pass over the row)."""
    from ._row_kernels import checked_tile_counts_internal  # numba: only for big rows

    counts = np.zeros(-(-int(n_cols) // int(tile_size)), np.int64)
    ok = checked_tile_counts_internal(indptr, indices, data, np.int64(n_cols),
                                      np.int64(tile_size), counts)
    return counts if ok else None


def prune_rows(A: sp.csr_array, threshold: float, n_threads: int) -> sp.csr_array:
    """:func:`bigT.kernels.prune` of A (no ``top_k``), shape (m, n), on ``n_threads``
    row ranges at once, written straight into arrays of the result's size: one pass
    counts each row's kept entries, one writes them (no buffer as long as A, no
    copy). Trusts A to be valid CSR with finite values (the in-memory path's
    matrices, made by the kernels from stores whose writers checked them); one not
    known to be canonical is left to :func:`~bigT.kernels.prune`, which makes it so."""
    threshold = float(threshold)
    if n_threads <= 1 or _small_enough(A.nnz) or not A.has_canonical_format:
        return prune(A, threshold=threshold)
    from ._row_kernels import kept_per_row_internal, prune_into_internal  # numba

    m = A.shape[0]
    ranges = _ranges(A.indptr, n_threads)
    kept = np.zeros(m + 1, np.int64)
    run_on_threads(lambda r0, r1: kept_per_row_internal(A.indptr, A.data, threshold, r0,
                                                        r1, kept[1:]), ranges, n_threads)
    indptr = np.cumsum(kept)
    nnz = int(indptr[-1])
    idt = np.int32 if max(nnz, *A.shape) < 2**31 else np.int64
    indptr = indptr.astype(idt)
    indices, data = np.empty(nnz, idt), np.empty(nnz, A.data.dtype)
    run_on_threads(lambda r0, r1: prune_into_internal(A.indptr, A.indices, A.data,
                                                      threshold, r0, r1, indptr, indices,
                                                      data), ranges, n_threads)
    out = sp.csr_array((data, indices, indptr), shape=A.shape, copy=False)
    out.has_sorted_indices = True
    out.has_canonical_format = True
    return out


def add_diag_scaled_rows(A: sp.csr_array, d: np.ndarray, B: sp.csr_array,
                        n_threads: int) -> sp.csr_array:
    """:func:`bigT.kernels.add_diag_scaled` (A + diag(d) B, shapes (m, n), d (m,)) on
    ``n_threads`` row ranges at once, written straight into arrays of the result's
    size: one pass counts each row's entries, one writes them (no buffer as long as
    both operands, no copy). Trusts A and B as :func:`prune_rows` does; operands not
    known canonical, or of different dtypes, are left to ``add_diag_scaled``."""
    d = np.asarray(d)
    if (n_threads <= 1 or _small_enough(A.nnz + B.nnz) or A.shape != B.shape
            or d.shape != (A.shape[0],) or not A.dtype == B.dtype == d.dtype
            or A.dtype.kind != "f" or not A.has_canonical_format
            or not B.has_canonical_format or not np.isfinite(d).all()):
        return add_diag_scaled(A, d, B)
    from ._row_kernels import add_diag_scaled_into_internal, merged_per_row_internal

    m = A.shape[0]
    d64 = d.astype(np.float64)
    ranges = _ranges(A.indptr.astype(np.int64) + B.indptr, n_threads)
    counts = np.zeros(m + 1, np.int64)
    operands = (A.indptr, A.indices, A.data, d64, B.indptr, B.indices, B.data)
    run_on_threads(lambda r0, r1: merged_per_row_internal(
        *operands, r0, r1, counts[1:], np.empty(1, A.dtype)), ranges, n_threads)
    indptr = np.cumsum(counts)
    nnz = int(indptr[-1])
    idt = np.int32 if max(nnz, *A.shape) < 2**31 else np.int64
    indptr = indptr.astype(idt)
    indices, data = np.empty(nnz, idt), np.empty(nnz, A.dtype)
    run_on_threads(lambda r0, r1: add_diag_scaled_into_internal(
        *operands, r0, r1, indptr, indices, data), ranges, n_threads)
    out = sp.csr_array((data, indices, indptr), shape=A.shape, copy=False)
    out.has_sorted_indices = True
    out.has_canonical_format = True
    return out


#: A left factor is restricted (:func:`restrict_to_used_rows`) when at most this
#: fraction of its entries meet a nonempty row of the right factor.
RESTRICT_MAX_FRACTION = 0.7


def restrict_to_used_rows(left: sp.csr_array, right: sp.csr_array,
                          n_threads: int) -> sp.csr_array | None:
    """The entries (i, k) of ``left``, shape (m, n), whose row k of ``right``, shape
    (n, p), holds entries; None where more than ``RESTRICT_MAX_FRACTION`` of them do
    (or left is small, or not canonical).

    Why: the product kernel visits every entry of the left factor, whether or not its
    row of the right factor is empty; the dense 384x512 corner's terms 3 and 4 multiply
    M's 2.2*10^7 entries with right factors whose nonempty rows meet only 35% and 14%
    of them (term 4: 7*10^7 multiply-adds, 0.16-0.22 s on 2 threads, 0.11-0.17 s
    restricted). The entries left out add nothing to any sum, so the product is the
    same, bit for bit.

    Returns
    -------
    csr_array, shape (m, n), sorted and canonical as ``left``, or None
    """
    if _small_enough(left.nnz) or not left.has_canonical_format:
        return None
    used = np.diff(right.indptr) > 0
    if not used.any() or used.all():
        return None
    from ._row_kernels import kept_by_column_internal, select_by_column_into_internal

    m = left.shape[0]
    ranges = _ranges(left.indptr, n_threads)
    kept = np.zeros(m + 1, np.int64)
    run_on_threads(lambda r0, r1: kept_by_column_internal(left.indptr, left.indices, used,
                                                          r0, r1, kept[1:]),
                   ranges, n_threads)
    indptr = np.cumsum(kept)
    nnz = int(indptr[-1])
    if nnz > RESTRICT_MAX_FRACTION * left.nnz:
        return None
    indptr = indptr.astype(left.indptr.dtype)
    indices, data = np.empty(nnz, left.indices.dtype), np.empty(nnz, left.data.dtype)
    run_on_threads(lambda r0, r1: select_by_column_into_internal(
        left.indptr, left.indices, left.data, used, r0, r1, indptr, indices, data),
        ranges, n_threads)
    out = sp.csr_array((data, indices, indptr), shape=left.shape, copy=False)
    out.has_sorted_indices = True
    out.has_canonical_format = True
    return out


#: A right factor is narrowed (:func:`narrow_columns`) when at most this fraction of its
#: columns hold entries.
NARROW_MAX_FRACTION = 0.5


@dataclass(frozen=True, eq=False)
class NarrowedColumns:
    """A right factor with its empty columns left out: column c of ``matrix`` is column
    ``columns[c]`` of the original.

    Why: the product kernel's accumulators and marks span the right factor's columns
    (:func:`bigT.kernels.workspace_bytes`). In the dense 384x512 corner only 16,128 of
    196,608 columns of a term hold entries (the lit patches): the accumulators of all
    columns (12.6 MB a workspace) spread those entries over every cache line and the
    term-2 product took 1.4-1.7x longer than on the narrowed columns (same entries,
    same sums: the kernel's order of additions does not depend on column labels).

    Attributes
    ----------
    matrix : csr_array, shape (n, k), sorted rows as the original's
    columns : (k,) ndarray, increasing, the original column of each
    width : int, the original's number of columns
    """

    matrix: sp.csr_array
    columns: np.ndarray
    width: int

    def widen(self, C: sp.csr_array, n_threads: int) -> sp.csr_array:
        """C, shape (m, k), a product with :attr:`matrix` (owned: its indices are
        relabelled in place), as the product with the original, shape (m, width)."""
        nnz = int(C.indptr[-1])
        indices, indptr = C.indices[:nnz], C.indptr
        if self.width - 1 > np.iinfo(indices.dtype).max:  # the original's labels need more
            indices, indptr = indices.astype(np.int64), indptr.astype(np.int64)
        _relabel(indices, self.columns.astype(indices.dtype), indices, n_threads)
        out = sp.csr_array((C.data[:nnz], indices, indptr), shape=(C.shape[0], self.width),
                           copy=False)
        out.has_sorted_indices = C.has_sorted_indices  # the labels increase
        return out


def narrow_columns(B: sp.csr_array, n_threads: int) -> NarrowedColumns | None:
    """B, shape (n, p), with only the columns holding entries (:class:`NarrowedColumns`),
    or None where more than ``NARROW_MAX_FRACTION`` of them do (or B is small)."""
    if _small_enough(B.nnz):
        return None
    used = np.zeros(B.shape[1], bool)
    used[B.indices[:B.indptr[-1]]] = True
    columns = np.flatnonzero(used)
    if len(columns) > NARROW_MAX_FRACTION * B.shape[1]:
        return None
    labels = (np.cumsum(used) - 1).astype(B.indices.dtype)
    indices = np.empty(int(B.indptr[-1]), B.indices.dtype)
    _relabel(B.indices, labels, indices, n_threads)
    narrowed = sp.csr_array((B.data[:len(indices)], indices, B.indptr),
                            shape=(B.shape[0], len(columns)), copy=False)
    narrowed.has_sorted_indices = B.has_sorted_indices
    return NarrowedColumns(narrowed, columns, B.shape[1])


def _relabel(indices: np.ndarray, labels: np.ndarray, out: np.ndarray,
             n_threads: int) -> None:
    """out[p] = labels[indices[p]] for every entry, on ``n_threads`` equal slices."""
    from ._row_kernels import relabel_internal  # numba: only for a narrowed product

    n = len(out)
    cuts = np.linspace(0, n, max(1, n_threads) + 1).astype(np.int64)
    ranges = [(int(cuts[t]), int(cuts[t + 1])) for t in range(len(cuts) - 1)]
    run_on_threads(lambda p0, p1: relabel_internal(indices, labels, p0, p1, out), ranges,
                   n_threads)


def _ranges(indptr: np.ndarray, n_parts: int) -> list[tuple[int, int]]:
    bounds = row_bounds(indptr, n_parts)
    return [(int(bounds[t]), int(bounds[t + 1])) for t in range(len(bounds) - 1)]
