"""Unchecked numba kernels on raw CSR arrays.

Every function here takes ``indptr``, ``indices``, ``data`` arrays (and row ranges) and
trusts them: the checked wrappers in :mod:`bigT.kernels.csr` validate first. All are
``nogil`` so the wrappers can run disjoint row ranges on several Python threads.

Conventions: ``indptr`` has the dtype of ``indices`` (int32 or int64); input rows are
sorted and duplicate-free unless a docstring says otherwise; values are accumulated in
float64 and rounded once to the output dtype.
"""

from __future__ import annotations

import contextlib

import numba
import numpy as np
from numba import njit, types

from ._constants import (  # noqa: F401 (the wrappers read them from here too)
    CSR_BAD_INDPTR,
    CSR_INDEX_OUT_OF_RANGE,
    CSR_NOT_FINITE,
    CSR_OK,
    GROUP,
)


@njit(nogil=True, cache=True)
def check_csr_internal(indptr, indices, data, n_cols):
    """One pass over a CSR matrix: structure, index range, finiteness, sortedness.

    Parameters
    ----------
    indptr : (n_rows + 1,) int32 or int64
    indices : (nnz,) int32 or int64
    data : (nnz,) float32 or float64
    n_cols : int

    Returns
    -------
    status : int
        ``CSR_OK`` or the first problem found (``CSR_BAD_INDPTR``,
        ``CSR_INDEX_OUT_OF_RANGE``, ``CSR_NOT_FINITE``).
    where : int
        The row (indptr problems) or the position in ``indices``/``data``.
    canonical : bool
        Every row strictly increasing (sorted and duplicate-free).
    """
    n_rows = indptr.shape[0] - 1
    nnz = indices.shape[0]
    if indptr[0] != 0 or indptr[n_rows] != nnz or data.shape[0] != nnz:
        return CSR_BAD_INDPTR, 0, False
    canonical = True
    for i in range(n_rows):
        start = indptr[i]
        stop = indptr[i + 1]
        if stop < start:
            return CSR_BAD_INDPTR, i, False
        prev = -1
        for p in range(start, stop):
            j = indices[p]
            if j < 0 or j >= n_cols:
                return CSR_INDEX_OUT_OF_RANGE, p, False
            if j <= prev:
                canonical = False
            prev = j
            v = data[p]
            if not np.isfinite(v):
                return CSR_NOT_FINITE, p, False
    return CSR_OK, 0, canonical


@njit(nogil=True, cache=True)
def _grow(arr, used, need):
    """A copy of ``arr[:used]`` in a buffer of at least ``need`` (doubling)."""
    cap = max(need, 2 * arr.shape[0], 16)
    out = np.empty(cap, arr.dtype)
    out[:used] = arr[:used]
    return out


@njit(nogil=True, cache=True)
def spgemm_rows_internal(
    r0, r1, a_indptr, a_indices, a_data, b_indptr, b_indices, b_data, n_cols,
    threshold, dense_scan_ratio, capacity,
):
    """Rows ``[r0, r1)`` of A @ B, pruned inside the row loop, in one pass.

    Gustavson's row-by-row product with a dense float64 accumulator ``acc`` (the SPA),
    kept all-zero between rows, and a marker array (``mark[j] == i - r0``: column j
    listed in row i). Both are as long as B has columns and are reused for every
    row, so the per-row cost is the multiply-adds plus the emission of the row:

    * dense-scan emission, when the row's column span (known without touching the
      products, since B's rows are sorted: ``lo = min first column``, ``hi = max last
      column`` of the B rows hit) is at most ``dense_scan_ratio`` times the row's
      multiply-adds: the scatter loop is a bare ``acc[j] += a * b`` (no marker, no
      branch), and the span is walked in column order, so the row comes out sorted
      with no sort, a nonzero accumulator being a computed entry;
    * list emission otherwise (sparse rows over a wide span): touched columns are
      listed on first touch, the entries that survive pruning are written, and only
      those kept column indices are sorted.

    An entry is kept when ``v != 0 and |v| >= threshold`` with v already rounded to
    the output dtype (so the test sees the value that is stored); exact zeros
    (cancellations) are dropped even at ``threshold = 0``, as scipy's product drops
    them. (A cap on the entries per row is a separate pass, ``top_k_internal``.)

    The result goes into buffers grown by doubling (no symbolic pass: a second pass
    would repeat all multiply-adds, and the pruned nnz is not known from structure).

    Parameters
    ----------
    r0, r1 : int
        Row range of A.
    a_indptr, a_indices, a_data : CSR arrays of A, (n_rows + 1,), (nnz_a,), (nnz_a,)
    b_indptr, b_indices, b_data : CSR arrays of B (rows sorted), same index dtype
    n_cols : int
        Columns of B.
    threshold : float
        Absolute pruning threshold, >= 0.
    dense_scan_ratio : float
        See above.
    capacity : int
        Initial buffer length (grown as needed).

    Returns
    -------
    row_nnz : (r1 - r0,) int64
    indices : (capacity,) dtype of ``b_indices``; the first ``row_nnz.sum()`` are used
    data : (capacity,) dtype of ``a_data``; likewise
    """
    n = r1 - r0
    row_nnz = np.zeros(n, np.int64)
    out_j = np.empty(max(capacity, 16), b_indices.dtype)
    out_v = np.empty(max(capacity, 16), a_data.dtype)
    acc = np.zeros(n_cols, np.float64)
    mark = np.full(n_cols, -1, np.int32)
    touched = np.empty(n_cols, b_indices.dtype)
    pos = 0
    for ii in range(n):
        i = r0 + ii
        a_start = a_indptr[i]
        a_stop = a_indptr[i + 1]
        work = 0
        lo = n_cols
        hi = -1
        for p in range(a_start, a_stop):
            k = a_indices[p]
            bs = b_indptr[k]
            be = b_indptr[k + 1]
            if be > bs:
                work += be - bs
                if b_indices[bs] < lo:
                    lo = b_indices[bs]
                if b_indices[be - 1] > hi:
                    hi = b_indices[be - 1]
        if work == 0:
            continue
        span = hi - lo + 1
        bound = min(work, span)
        if pos + bound > out_j.shape[0]:
            out_j = _grow(out_j, pos, pos + bound)
            out_v = _grow(out_v, pos, pos + bound)
        start = pos
        marker = np.int32(ii)
        if span <= dense_scan_ratio * work:
            for p in range(a_start, a_stop):
                k = a_indices[p]
                a = np.float64(a_data[p])
                for q in range(b_indptr[k], b_indptr[k + 1]):
                    acc[b_indices[q]] += a * b_data[q]
            for j in range(lo, hi + 1):
                out_v[pos] = acc[j]
                acc[j] = 0.0
                out_j[pos] = j
                if out_v[pos] != 0 and abs(out_v[pos]) >= threshold:
                    pos += 1
        else:
            pos = _row_listed(i, marker, a_indptr, a_indices, a_data, b_indptr, b_indices,
                              b_data, acc, mark, touched, threshold, pos, out_j, out_v)
        row_nnz[ii] = pos - start
    return row_nnz, out_j, out_v


@njit(nogil=True, cache=True)
def _empty_like_csr(indptr, indices, data):
    """Output arrays for a subset of a CSR matrix's entries: indptr zeroed, indices and
    data as long as the input's (a filter keeps at most all of them)."""
    return (np.zeros(indptr.shape[0], indptr.dtype), np.empty(indices.shape[0], indices.dtype),
            np.empty(data.shape[0], data.dtype))


@njit(nogil=True, cache=True)
def prune_internal(indptr, indices, data, threshold):
    """Drop |v| < threshold and exact zeros.

    Returns ``(indptr, indices, data)`` of the result, new arrays of the input dtypes;
    ``indices`` and ``data`` are the buffers written, as long as the input's: their
    first ``indptr[-1]`` entries hold the result (the wrapper copies them out only
    when most of the buffer went unused, see ``csr._used``).
    """
    n_rows = indptr.shape[0] - 1
    out_p, out_j, out_v = _empty_like_csr(indptr, indices, data)
    pos = 0
    for i in range(n_rows):
        for p in range(indptr[i], indptr[i + 1]):
            v = data[p]
            if v != 0 and abs(v) >= threshold:
                out_j[pos] = indices[p]
                out_v[pos] = v
                pos += 1
        out_p[i + 1] = pos
    return out_p, out_j, out_v


@njit(nogil=True, cache=True)
def _sift_down(heap, size, t):
    """Restore the min-heap order of ``heap[:size]`` below position t."""
    while True:
        c = 2 * t + 1
        if c >= size:
            return
        if c + 1 < size and heap[c + 1] < heap[c]:
            c += 1
        if heap[t] <= heap[c]:
            return
        heap[t], heap[c] = heap[c], heap[t]
        t = c


@njit(nogil=True, cache=True)
def _kth_largest(mags, k):
    """The k-th largest of ``mags`` (1 <= k <= len), by a size-k min-heap.

    Hand-written rather than ``np.sort``: numba compiles its sorts for several
    seconds, a cost every first run would pay for a feature most runs never use.
    """
    heap = mags[:k].copy()
    for t in range(k // 2 - 1, -1, -1):
        _sift_down(heap, k, t)
    for t in range(k, mags.shape[0]):
        if mags[t] > heap[0]:
            heap[0] = mags[t]
            _sift_down(heap, k, 0)
    return heap[0]


@njit(nogil=True, cache=True)
def top_k_internal(indptr, indices, data, top_k):
    """Keep each row's ``top_k`` largest |v| (ties to the smaller column), in column
    order: every entry above the row's k-th largest |v|, then the first entries equal
    to it, in column order, until top_k are kept.

    Returns ``(indptr, indices, data)``, new arrays of the input dtypes.
    """
    n_rows = indptr.shape[0] - 1
    out_p, out_j, out_v = _empty_like_csr(indptr, indices, data)
    pos = 0
    for i in range(n_rows):
        start = indptr[i]
        stop = indptr[i + 1]
        if stop - start <= top_k:
            for p in range(start, stop):
                out_j[pos] = indices[p]
                out_v[pos] = data[p]
                pos += 1
        else:
            mags = np.empty(stop - start, np.float64)
            for p in range(start, stop):
                mags[p - start] = abs(np.float64(data[p]))
            kth = _kth_largest(mags, top_k)
            ties = top_k
            for t in range(mags.shape[0]):
                if mags[t] > kth:
                    ties -= 1
            for p in range(start, stop):
                m = mags[p - start]
                if m > kth or (m == kth and ties > 0):
                    if m == kth:
                        ties -= 1
                    out_j[pos] = indices[p]
                    out_v[pos] = data[p]
                    pos += 1
        out_p[i + 1] = pos
    return out_p, out_j[:pos].copy(), out_v[:pos].copy()


@njit(nogil=True, cache=True)
def add_diag_scaled_internal(
    a_indptr, a_indices, a_data, d, b_indptr, b_indices, b_data, out_dtype_proto
):
    """C = A + diag(d) B by merging each pair of sorted rows in one pass.

    Entries that are exactly 0 (cancelled, or zero factors) are not stored, as in
    scipy's ``A + B``. nnz(C) <= nnz(A) + nnz(B) bounds the buffers.

    Parameters
    ----------
    a_*, b_* : CSR arrays of A and B, same shape, same index dtype, sorted rows
    d : (n_rows,) float
    out_dtype_proto : (0,) array of the output dtype

    Returns
    -------
    indptr, indices, data of C; ``indices`` and ``data`` are the buffers written (as
    ``prune_internal``'s), their first ``indptr[-1]`` entries C's
    """
    n_rows = a_indptr.shape[0] - 1
    cap = a_indices.shape[0] + b_indices.shape[0]
    out_p = np.zeros(n_rows + 1, np.int64)
    out_j = np.empty(cap, a_indices.dtype)
    out_v = np.empty(cap, out_dtype_proto.dtype)
    pos = 0
    for i in range(n_rows):
        di = np.float64(d[i])
        p = a_indptr[i]
        pe = a_indptr[i + 1]
        q = b_indptr[i]
        qe = b_indptr[i + 1]
        while p < pe and q < qe:
            ja = a_indices[p]
            jb = b_indices[q]
            if ja < jb:
                out_j[pos] = ja
                out_v[pos] = a_data[p]
                p += 1
            elif jb < ja:
                out_j[pos] = jb
                out_v[pos] = di * b_data[q]
                q += 1
            else:
                out_j[pos] = ja
                out_v[pos] = np.float64(a_data[p]) + di * b_data[q]
                p += 1
                q += 1
            if out_v[pos] != 0:
                pos += 1
        while p < pe:
            out_j[pos] = a_indices[p]
            out_v[pos] = a_data[p]
            p += 1
            if out_v[pos] != 0:
                pos += 1
        while q < qe:
            out_j[pos] = b_indices[q]
            out_v[pos] = di * b_data[q]
            q += 1
            if out_v[pos] != 0:
                pos += 1
        out_p[i + 1] = pos
    return out_p, out_j, out_v


@njit(nogil=True, cache=True)
def scale_rows_internal(indptr, data, d, out):
    """out[p] = d[i] * data[p] for p in row i. ``out`` may be ``data``."""
    for i in range(indptr.shape[0] - 1):
        di = d[i]
        for p in range(indptr[i], indptr[i + 1]):
            out[p] = di * data[p]


@njit(nogil=True, cache=True)
def scale_cols_internal(indices, data, d, out):
    """out[p] = data[p] * d[indices[p]]. ``out`` may be ``data``."""
    for p in range(indices.shape[0]):
        out[p] = data[p] * d[indices[p]]


@njit(nogil=True, cache=True)
def scale_cols_off_diagonal_internal(indptr, indices, data, d, offset, indptr_out,
                                     indices_out, data_out):
    """Row i's entries times d of their column, those in column i + ``offset`` (the
    diagonal of a row block starting at global row ``offset``) left out: one pass,
    into ``*_out`` (sized nnz; the first ``indptr_out[-1]`` entries are written)."""
    q = 0
    indptr_out[0] = 0
    for i in range(indptr.shape[0] - 1):
        diag = i + offset
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j != diag:
                indices_out[q] = j
                data_out[q] = data[p] * d[j]
                q += 1
        indptr_out[i + 1] = q


@njit(nogil=True, cache=True)
def diagonal_internal(indptr, indices, data, out):
    """out[i] = A[i, i] (sums duplicates, works on unsorted rows)."""
    for i in range(out.shape[0]):
        s = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            if indices[p] == i:
                s += data[p]
        out[i] = s


@njit(nogil=True, cache=True, inline="always")
def _entry(a, absolute):
    """An entry of A as the product uses it: |a| when ``absolute`` (a loop invariant,
    so the branch costs nothing measurable in the gather-bound loops)."""
    return abs(a) if absolute else a


@njit(nogil=True, cache=True)
def spmm_dense_rows_internal(r0, r1, indptr, indices, data, x, out, absolute=False):
    """out[r0:r1] += A[r0:r1] @ x for a dense x of shape (n_cols, k), C-contiguous;
    |A| (entries' absolute values) for A when ``absolute``. ``data`` may be float32
    with a float64 x (each entry is widened as it is used, no copy of A is made).

    Each row is summed in a k-vector that stays in L1 (float64 for k = 1, x's dtype
    for k > 1) and added to ``out`` once. The input checks are fused into the loop,
    since for k = 1 a separate validation pass would cost as much as the product: a
    row's indptr and column indices are checked before they are used, and a NaN/Inf
    anywhere in A's data (or in the rows of x that A uses) shows up as a non-finite
    row sum.

    Returns
    -------
    status : int
        ``CSR_OK``, ``CSR_BAD_INDPTR``, ``CSR_INDEX_OUT_OF_RANGE`` or
        ``CSR_NOT_FINITE``; on a problem the rows from the failing one on are not
        added.
    where : int
        The failing row.
    """
    n_cols = x.shape[0]
    k = x.shape[1]
    nnz = indices.shape[0]
    # k > 1 sums in x's dtype: float32 lanes are twice as many per vector FMA, and
    # the k-wide update is compute-bound (measured: float64 lanes lose to scipy).
    tmp = np.zeros(k, x.dtype)
    zero = np.zeros(1, x.dtype)[0]  # the column sums' start, in x's dtype
    for i in range(r0, r1):
        start = indptr[i]
        stop = indptr[i + 1]
        if start < 0 or stop < start or stop > nnz:
            return CSR_BAD_INDPTR, i
        if k == 1:
            # Four partial sums: one would chain every add on the previous one's
            # latency. The index check rides along (a never-taken branch).
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            bad = False
            p = start
            while p + 4 <= stop:
                j0 = indices[p]
                j1 = indices[p + 1]
                j2 = indices[p + 2]
                j3 = indices[p + 3]
                jmin = min(min(j0, j1), min(j2, j3))
                jmax = max(max(j0, j1), max(j2, j3))
                bad |= (jmin < 0) | (jmax >= n_cols)
                if bad:
                    break
                s0 += np.float64(_entry(data[p], absolute)) * x[j0, 0]
                s1 += np.float64(_entry(data[p + 1], absolute)) * x[j1, 0]
                s2 += np.float64(_entry(data[p + 2], absolute)) * x[j2, 0]
                s3 += np.float64(_entry(data[p + 3], absolute)) * x[j3, 0]
                p += 4
            while p < stop and not bad:
                j0 = indices[p]
                bad |= (j0 < 0) | (j0 >= n_cols)
                if not bad:
                    s0 += np.float64(_entry(data[p], absolute)) * x[j0, 0]
                p += 1
            if bad:
                return CSR_INDEX_OUT_OF_RANGE, i
            s = (s0 + s1) + (s2 + s3)
            if not np.isfinite(s):
                return CSR_NOT_FINITE, i
            out[i, 0] += s
            continue
        if k < 4:
            for p in range(start, stop):
                j = indices[p]
                if j < 0 or j >= n_cols:
                    return CSR_INDEX_OUT_OF_RANGE, i
        # the columns four at a time in scalar sums: each column's sum takes its terms
        # in the same order as one k-long loop would (the same bits), but in registers
        # (the k-long loop over a memory tmp ran ~1.7x slower at k = 4, the residual
        # probes' M U: issue #30); the first four's loop checks the row's indices
        c0 = 0
        while c0 + 4 <= k:
            s0 = zero
            s1 = s0
            s2 = s0
            s3 = s0
            for p in range(start, stop):
                a = _entry(data[p], absolute)
                j = indices[p]
                if c0 == 0 and (j < 0 or j >= n_cols):
                    return CSR_INDEX_OUT_OF_RANGE, i
                s0 += a * x[j, c0]
                s1 += a * x[j, c0 + 1]
                s2 += a * x[j, c0 + 2]
                s3 += a * x[j, c0 + 3]
            tmp[c0] = s0
            tmp[c0 + 1] = s1
            tmp[c0 + 2] = s2
            tmp[c0 + 3] = s3
            c0 += 4
        # then two at a time, alike (the row's indices are checked by now: above for
        # k < 4, else by the first four's loop): k = 2 and 3 in a loop over a memory
        # tmp ran 2.2x and 3.0x slower than k = 4 here (the spectral bracket's
        # two-support bound is k = 2)
        while c0 + 2 <= k:
            s0 = zero
            s1 = s0
            for p in range(start, stop):
                a = _entry(data[p], absolute)
                j = indices[p]
                s0 += a * x[j, c0]
                s1 += a * x[j, c0 + 1]
            tmp[c0] = s0
            tmp[c0 + 1] = s1
            c0 += 2
        if c0 < k:  # the last column (k odd), alike
            s0 = zero
            for p in range(start, stop):
                s0 += _entry(data[p], absolute) * x[indices[p], c0]
            tmp[c0] = s0
        finite = True
        for c in range(k):
            finite &= np.isfinite(tmp[c])
        if not finite:
            return CSR_NOT_FINITE, i
        orow = out[i]
        for c in range(k):
            orow[c] += tmp[c]
    return CSR_OK, 0


#: Marked emission of spgemm_grouped_internal visits columns in blocks of this shift...
BLOCK_SHIFT = 4
#: ...found through marks on super-blocks of this shift (1024 columns), so a group's
#: emission costs span / 1024 + its touched blocks, not span / 16: the span of a row
#: of the corner runs across the fold, half of n (at full HD the one-level scan cost
#: ~65 k tests per group, more than its multiply-adds).
SUPER_SHIFT = 10
#: A row done alone (a group sharing few columns) lists its columns when its span is
#: more than this many times its multiply-adds, instead of scanning the span.
ROW_LIST_RATIO = 8
#: A group uses marked scatter/emission when its column span exceeds this many times
#: the previous group's kept entries per row (measured: even at ~6x the plain scan
#: ties; at ~12x the plain scan costs as much as the scatter).
MARKED_SPAN_RATIO = 8


def _group_scatter_py(ulist, nu, avals, b_indptr, b_indices, b_data, acc):
    """acc[j, :] += avals[u, :] * B[k, j] over the listed rows k = ulist[u] of B.

    ``acc`` is (n_cols, GROUP) and ``avals`` (n_u, GROUP), both flattened. The lanes
    are loaded into locals, updated and stored as a straight block, the form LLVM
    turns into vector FMAs when its SLP vectorizer runs; "contract" allows FMA, which
    only removes roundings.
    """
    for u in range(nu):
        k = ulist[u]
        o = u * GROUP
        a0 = avals[o]
        a1 = avals[o + 1]
        a2 = avals[o + 2]
        a3 = avals[o + 3]
        a4 = avals[o + 4]
        a5 = avals[o + 5]
        a6 = avals[o + 6]
        a7 = avals[o + 7]
        for q in range(b_indptr[k], b_indptr[k + 1]):
            j = b_indices[q] * GROUP
            b = np.float64(b_data[q])
            c0 = acc[j]
            c1 = acc[j + 1]
            c2 = acc[j + 2]
            c3 = acc[j + 3]
            c4 = acc[j + 4]
            c5 = acc[j + 5]
            c6 = acc[j + 6]
            c7 = acc[j + 7]
            acc[j] = c0 + a0 * b
            acc[j + 1] = c1 + a1 * b
            acc[j + 2] = c2 + a2 * b
            acc[j + 3] = c3 + a3 * b
            acc[j + 4] = c4 + a4 * b
            acc[j + 5] = c5 + a5 * b
            acc[j + 6] = c6 + a6 * b
            acc[j + 7] = c7 + a7 * b


def _group_scatter_marked_py(ulist, nu, avals, b_indptr, b_indices, b_data, acc, touched,
                             touched_super):
    """``_group_scatter`` that also sets ``touched[j >> BLOCK_SHIFT] = 1`` and
    ``touched_super[j >> SUPER_SHIFT] = 1``.

    For rows whose computed entries are a few short runs over a wide column span
    (a product in row-major pixel order on a wide image), so the emission visits only
    the marked blocks; the extra store costs ~30 % of the scatter, paid only there.
    """
    for u in range(nu):
        k = ulist[u]
        o = u * GROUP
        a0 = avals[o]
        a1 = avals[o + 1]
        a2 = avals[o + 2]
        a3 = avals[o + 3]
        a4 = avals[o + 4]
        a5 = avals[o + 5]
        a6 = avals[o + 6]
        a7 = avals[o + 7]
        for q in range(b_indptr[k], b_indptr[k + 1]):
            jc = b_indices[q]
            touched[jc >> BLOCK_SHIFT] = 1
            touched_super[jc >> SUPER_SHIFT] = 1
            j = jc * GROUP
            b = np.float64(b_data[q])
            c0 = acc[j]
            c1 = acc[j + 1]
            c2 = acc[j + 2]
            c3 = acc[j + 3]
            c4 = acc[j + 4]
            c5 = acc[j + 5]
            c6 = acc[j + 6]
            c7 = acc[j + 7]
            acc[j] = c0 + a0 * b
            acc[j + 1] = c1 + a1 * b
            acc[j + 2] = c2 + a2 * b
            acc[j + 3] = c3 + a3 * b
            acc[j + 4] = c4 + a4 * b
            acc[j + 5] = c5 + a5 * b
            acc[j + 6] = c6 + a6 * b
            acc[j + 7] = c7 + a7 * b



@contextlib.contextmanager
def _slp_vectorizer():
    """Turn on LLVM's SLP vectorizer while compiling inside the block.

    numba runs it off by default (``NUMBA_SLP_VECTORIZE=0``); the GROUP-lane update of
    ``_group_scatter`` only becomes vector FMAs with it (measured ~20 % less CPU time
    for the whole grouped product). The flag is process-wide, so it is restored at
    once; a function another thread compiles meanwhile merely gets the same pass.
    """
    old = numba.config.SLP_VECTORIZE
    numba.config.SLP_VECTORIZE = 1
    try:
        yield
    finally:
        numba.config.SLP_VECTORIZE = old


_SCATTER_SIGNATURES = [
    types.void(
        types.int64[::1], types.int64, types.float64[::1],
        ix[::1], ix[::1], fx[::1], types.float64[::1],
    )
    for ix in (types.int32, types.int64)
    for fx in (types.float32, types.float64)
]
_MARKED_SIGNATURES = [
    types.void(*sig.args, types.uint8[::1], types.uint8[::1]) for sig in _SCATTER_SIGNATURES
]
with _slp_vectorizer():
    _group_scatter = njit(_SCATTER_SIGNATURES, nogil=True, cache=True,
                          fastmath={"contract"})(_group_scatter_py)
    _group_scatter_marked = njit(_MARKED_SIGNATURES, nogil=True, cache=True,
                                 fastmath={"contract"})(_group_scatter_marked_py)


@njit(nogil=True, cache=True)
def _group_emit(acc, lo, hi, n_rows, threshold, cursor, out_j, out_v):
    """Move the lanes of acc[lo:hi+1, :n_rows] to the rows' regions, zeroing acc.

    Row r's kept entries (``v != 0 and |v| >= threshold``) go to ``cursor[r]`` on,
    in column order; the writes are unconditional and the cursor advances by the
    test, so the loop has no data-dependent branch.
    """
    for j in range(lo, hi + 1):
        o = j * GROUP
        for r in range(n_rows):
            c = cursor[r]
            out_v[c] = acc[o + r]
            out_j[c] = j
            v = out_v[c]
            cursor[r] = c + ((v != 0) & (abs(v) >= threshold))
        for r in range(GROUP):
            acc[o + r] = 0.0


@njit(nogil=True, cache=True)
def _group_emit_marked(acc, touched, touched_super, lo, hi, n_rows, threshold, cursor,
                       out_j, out_v):
    """``_group_emit`` over the column blocks marked in ``touched`` only, found through
    the super-blocks marked in ``touched_super`` (unmarking both)."""
    n_cols = acc.shape[0] // GROUP
    per_super = 1 << (SUPER_SHIFT - BLOCK_SHIFT)
    for sb in range(lo >> SUPER_SHIFT, (hi >> SUPER_SHIFT) + 1):
        if touched_super[sb] == 0:
            continue
        touched_super[sb] = 0
        for blk in range(sb * per_super, min((sb + 1) * per_super, touched.shape[0])):
            if touched[blk] == 0:
                continue
            touched[blk] = 0
            _group_emit(acc, blk << BLOCK_SHIFT, min((blk + 1) << BLOCK_SHIFT, n_cols) - 1,
                        n_rows, threshold, cursor, out_j, out_v)


def grouped_workspace(n_cols: int, n_rows_b: int):
    """The accumulators and markers of :func:`spgemm_grouped_internal` for a B of
    shape (n_rows_b, n_cols), clean: (acc (n_cols * GROUP,) float64, acc1 (n_cols,)
    float64, stamp (n_rows_b,) int64, slot (n_rows_b,) int64, touched and
    touched_super uint8 block marks, mark (n_cols,) int64, listed (n_cols,) int64,
    epoch (1,) int64). ``bigT.kernels.workspace_bytes`` bounds its size."""
    return (np.zeros(n_cols * GROUP, np.float64), np.zeros(n_cols, np.float64),
            np.full(n_rows_b, -1, np.int64), np.zeros(n_rows_b, np.int64),
            np.zeros((n_cols >> BLOCK_SHIFT) + 1, np.uint8),
            np.zeros((n_cols >> SUPER_SHIFT) + 1, np.uint8),
            np.full(n_cols, -1, np.int64), np.empty(n_cols, np.int64),
            np.zeros(1, np.int64))


@njit(nogil=True, cache=True)
def _row_listed(i, tag, a_indptr, a_indices, a_data, b_indptr, b_indices, b_data, acc, mark,
                listed, threshold, pos, out_j, out_v):
    """Row i of A @ B with its columns listed on first touch (``mark[j] == tag``), for a
    row whose span is much wider than its multiply-adds; the kept entries are written
    from ``pos`` on in column order (only the kept columns sorted). Returns the new pos.
    The list emission of both product kernels."""
    start = pos
    nt = 0
    for p in range(a_indptr[i], a_indptr[i + 1]):
        k = a_indices[p]
        a = np.float64(a_data[p])
        for q in range(b_indptr[k], b_indptr[k + 1]):
            j = b_indices[q]
            if mark[j] != tag:
                mark[j] = tag
                listed[nt] = j
                nt += 1
            acc[j] += a * b_data[q]
    for t in range(nt):
        j = listed[t]
        out_v[pos] = acc[j]
        if out_v[pos] != 0 and abs(out_v[pos]) >= threshold:
            out_j[pos] = j
            pos += 1
        else:
            acc[j] = 0.0
    out_j[start:pos].sort()
    for p in range(start, pos):
        j = out_j[p]
        out_v[p] = acc[j]
        acc[j] = 0.0
    return pos


@njit(nogil=True, cache=True)
def spgemm_grouped_internal(
    r0, r1, a_indptr, a_indices, a_data, b_indptr, b_indices, b_data, n_cols,
    threshold, min_efficiency, capacity, acc, acc1, stamp, slot, touched, touched_super,
    mark, listed, epoch,
):
    """Rows ``[r0, r1)`` of A @ B, pruned, GROUP rows at a time.

    Why: Gustavson's scatter ``acc[j] += a * b`` costs a few cycles per multiply-add
    whatever the language (index load, value load, a read-modify-write at a random
    address), and that loop is all of scipy's time. Neighbouring rows of a transport
    matrix (neighbouring pixels) hit nearly the same rows of B, so GROUP consecutive
    rows of A are multiplied together: the union of their column sets k is listed
    once with a dense (GROUP,) vector of A's values, and each entry (j, b) of B's row k
    updates a (GROUP,) float64 accumulator row ``acc[j, :]`` with one vector FMA. One
    index/value load then serves GROUP rows; the lanes of rows that do not hold k
    multiply zeros, which is the price.

    A group whose rows share too little (useful multiply-adds / (GROUP x union
    multiply-adds) < ``min_efficiency``) is done row by row instead, with the scalar
    scatter of ``spgemm_rows_internal``: dense-scan emission, or list emission
    (:func:`_row_listed`) when the row's span exceeds ``ROW_LIST_RATIO`` times its
    multiply-adds (a row reaching across the corner's fold spans half of n: scanning
    it made the row cost O(n)).

    Rows are emitted by scanning the group's column span in order (sorted output, no
    sort), one pass for all GROUP rows, keeping ``v != 0 and |v| >= threshold`` (v
    rounded to the output dtype), so the result is the same set as
    ``spgemm_rows_internal``'s. When the span is much wider than the rows (more than
    ``MARKED_SPAN_RATIO`` times the previous group's kept entries per row), the
    scatter also marks 16-column blocks and their 1024-column super-blocks, and the
    scan visits the marked ones only.

    Time on the 96x128 stand-in corner (1 thread, CPU s): scatter 0.55, emission +
    buffers 0.39, set-up and checks < 0.05; scipy's whole product 2.15.

    The accumulators and markers span B's columns (rows), so they are the caller's
    workspace (:func:`grouped_workspace`), reused from call to call: allocating and
    zeroing ~100 bytes per column for every tile row cost more than the products of a
    full-HD term. They are left as found: the accumulators and block marks zeroed by
    the emission, and ``stamp``/``mark`` compared with tags that grow with ``epoch``
    (never a tag of an earlier call).

    Parameters and returns as ``spgemm_rows_internal`` (``min_efficiency`` in [0, 1]
    replaces ``dense_scan_ratio``), and the workspace arrays of
    :func:`grouped_workspace`.
    """
    n = r1 - r0
    row_nnz = np.zeros(n, np.int64)
    cap = max(capacity, 16)
    out_j = np.empty(cap, b_indices.dtype)
    out_v = np.empty(cap, a_data.dtype)
    tag0 = epoch[0]  # tags of this call: tag0 + (row - r0), all above the last call's
    epoch[0] = tag0 + n + 1
    max_row = 0
    for i in range(r0, r1):
        max_row = max(max_row, a_indptr[i + 1] - a_indptr[i])
    ulist = np.empty(GROUP * max_row + 1, np.int64)
    avals = np.zeros((GROUP * max_row + 1) * GROUP, np.float64)
    cursor = np.zeros(GROUP, np.int64)
    prev_per_row = n_cols
    pos = 0
    for g0 in range(r0, r1, GROUP):
        g1 = min(g0 + GROUP, r1)
        nu = 0
        useful = 0
        for r in range(g1 - g0):
            i = g0 + r
            for p in range(a_indptr[i], a_indptr[i + 1]):
                k = a_indices[p]
                useful += b_indptr[k + 1] - b_indptr[k]
                if stamp[k] != tag0 + g0 - r0:
                    stamp[k] = tag0 + g0 - r0
                    slot[k] = nu
                    ulist[nu] = k
                    for c in range(GROUP):
                        avals[nu * GROUP + c] = 0.0
                    nu += 1
                avals[slot[k] * GROUP + r] += a_data[p]
        if useful == 0:
            continue
        union_work = 0
        lo = n_cols
        hi = -1
        for u in range(nu):
            k = ulist[u]
            bs = b_indptr[k]
            be = b_indptr[k + 1]
            if be > bs:
                union_work += be - bs
                lo = min(lo, b_indices[bs])
                hi = max(hi, b_indices[be - 1])
        span = hi - lo + 1
        need = pos + (g1 - g0) * (min(span, union_work) + 1) + 1
        if need > out_j.shape[0]:
            out_j = _grow(out_j, pos, need)
            out_v = _grow(out_v, pos, need)
        if useful >= min_efficiency * GROUP * union_work:
            marked = span > MARKED_SPAN_RATIO * prev_per_row
            if marked:
                _group_scatter_marked(ulist, nu, avals, b_indptr, b_indices, b_data, acc,
                                      touched, touched_super)
            else:
                _group_scatter(ulist, nu, avals, b_indptr, b_indices, b_data, acc)
            # One pass over the span reads each accumulator line once and writes
            # row r into its own region [pos + r * bound, ...); the regions are then
            # closed up (a short move of the kept entries only).
            bound = min(span, union_work) + 1
            for r in range(g1 - g0):
                cursor[r] = pos + r * bound
            if marked:
                _group_emit_marked(acc, touched, touched_super, lo, hi, g1 - g0, threshold,
                                   cursor, out_j, out_v)
            else:
                _group_emit(acc, lo, hi, g1 - g0, threshold, cursor, out_j, out_v)
            base = pos
            for r in range(g1 - g0):
                start = pos
                src = base + r * bound
                cnt = cursor[r] - src
                if src != start:
                    for t in range(cnt):
                        out_j[start + t] = out_j[src + t]
                        out_v[start + t] = out_v[src + t]
                pos = start + cnt
                row_nnz[g0 - r0 + r] = pos - start
            prev_per_row = (pos - base) // (g1 - g0) + 1
        else:
            for r in range(g1 - g0):
                i = g0 + r
                rlo = n_cols
                rhi = -1
                work = 0
                for p in range(a_indptr[i], a_indptr[i + 1]):
                    k = a_indices[p]
                    bs = b_indptr[k]
                    be = b_indptr[k + 1]
                    if be > bs:
                        rlo = min(rlo, b_indices[bs])
                        rhi = max(rhi, b_indices[be - 1])
                        work += be - bs
                if rhi - rlo + 1 > ROW_LIST_RATIO * work:
                    start = pos
                    pos = _row_listed(i, tag0 + i - r0, a_indptr, a_indices, a_data, b_indptr, b_indices,
                                      b_data, acc1, mark, listed, threshold, pos, out_j,
                                      out_v)
                    row_nnz[i - r0] = pos - start
                    continue
                start = pos
                for p in range(a_indptr[i], a_indptr[i + 1]):
                    k = a_indices[p]
                    a = np.float64(a_data[p])
                    for q in range(b_indptr[k], b_indptr[k + 1]):
                        acc1[b_indices[q]] += a * b_data[q]
                for j in range(rlo, rhi + 1):
                    out_v[pos] = acc1[j]
                    acc1[j] = 0.0
                    out_j[pos] = j
                    if out_v[pos] != 0 and abs(out_v[pos]) >= threshold:
                        pos += 1
                row_nnz[g0 - r0 + r] = pos - start
    return row_nnz, out_j, out_v


@njit(nogil=True, cache=True)
def _tile_run_end(indices, p, end, lo, hi):
    """The end of the run of entries from ``p`` whose columns are in ``[lo, hi)``."""
    while p < end and lo <= indices[p] < hi:
        p += 1
    return p


@njit(nogil=True, cache=True)
def split_column_tiles_internal(indptr, indices, data, tile_size):
    """Cut rows into their non-empty column tiles in one counting pass and one
    scatter, no sort: rows are scattered in order, so every tile keeps its entries
    row-major and in the input's column order. Each row is walked as runs of entries
    in one tile (one run per tile when its columns are sorted), so the division by
    ``tile_size`` is paid per run, not per entry.

    Returns (tile_cols (k,) int64 ascending, tile_indptr (k, n_rows + 1) int64,
    local (nnz,) int32 columns within the tile, values (nnz,) permuted,
    bounds (k + 1,) int64: tile t's entries are ``local/values[bounds[t]:bounds[t+1]]``).
    """
    n_rows = indptr.size - 1
    top = 0
    for p in range(indices.size):
        top = max(top, indices[p])
    counts = np.zeros(top // tile_size + 1, np.int64)
    for r in range(n_rows):
        p, end = indptr[r], indptr[r + 1]
        while p < end:
            j = indices[p] // tile_size
            q = _tile_run_end(indices, p, end, j * tile_size, (j + 1) * tile_size)
            counts[j] += q - p
            p = q
    slot = np.full(counts.size, -1, np.int64)
    k = 0
    for j in range(counts.size):
        if counts[j] > 0:
            slot[j] = k
            k += 1
    tile_cols = np.empty(k, np.int64)
    bounds = np.zeros(k + 1, np.int64)
    for j in range(counts.size):
        if slot[j] >= 0:
            tile_cols[slot[j]] = j
            bounds[slot[j] + 1] = bounds[slot[j]] + counts[j]
    tile_indptr = np.zeros((k, n_rows + 1), np.int64)
    fill = bounds[:k].copy()
    local = np.empty(indices.size, np.int32)
    values = np.empty(indices.size, data.dtype)
    for r in range(n_rows):
        p, end = indptr[r], indptr[r + 1]
        while p < end:
            j = indices[p] // tile_size
            q = _tile_run_end(indices, p, end, j * tile_size, (j + 1) * tile_size)
            t, at, base = slot[j], fill[slot[j]], j * tile_size
            for e in range(q - p):
                local[at + e] = indices[p + e] - base
                values[at + e] = data[p + e]
            fill[t] = at + q - p
            tile_indptr[t, r + 1] += q - p
            p = q
    for t in range(k):
        for r in range(n_rows):
            tile_indptr[t, r + 1] += tile_indptr[t, r]
    return tile_cols, tile_indptr, local, values, bounds


@njit(nogil=True, cache=True)
def join_column_tiles_internal(tile_cols, tile_indptr, local, values, bounds, tile_size,
                               indptr_out, indices_out, data_out):
    """The inverse of :func:`split_column_tiles_internal`: rows of global columns from
    their column tiles (ascending), row by row, each tile's part of the row appended
    in turn, so rows stay column-sorted. Writes ``indptr_out`` (n_rows + 1,),
    ``indices_out`` and ``data_out`` (nnz,) in place: one counting pass, one copy."""
    k = tile_indptr.shape[0]
    n_rows = tile_indptr.shape[1] - 1
    indptr_out[0] = 0
    for r in range(n_rows):
        count = 0
        for t in range(k):
            count += tile_indptr[t, r + 1] - tile_indptr[t, r]
        indptr_out[r + 1] = indptr_out[r] + count
    for r in range(n_rows):
        at = indptr_out[r]
        for t in range(k):
            base = tile_cols[t] * tile_size
            p0 = bounds[t] + tile_indptr[t, r]
            p1 = bounds[t] + tile_indptr[t, r + 1]
            for p in range(p0, p1):
                indices_out[at] = local[p] + base
                data_out[at] = values[p]
                at += 1
