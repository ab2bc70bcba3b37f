"""bigT.kernels.row_ranges against numpy/scipy references: the counts over a
product's factors and the element-wise kernels run over row ranges on threads."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.kernels import add_diag_scaled, prune
from bigT.kernels.csr import row_work
from bigT.kernels.row_ranges import (add_diag_scaled_rows, multiply_adds, prune_rows,
                                     row_bounds, row_view, stack_rows, tile_pairs)


def _random(m, n, density, seed, dtype=np.float64, empty_rows=()):
    A = sp.random_array((m, n), density=density, format="csr", dtype=dtype,
                        rng=np.random.default_rng(seed))
    A.data -= 0.5
    A = A.tolil()
    for r in empty_rows:
        A[r, :] = 0
    return sp.csr_array(A)


def _tile_pairs_dense(left, right, ts, n_blocks):
    """Reference: every (row block, column tile) pair holding an entry of left, split by
    whether right's tile row holds any entry."""
    L = left.toarray() != 0
    R_rows = np.diff(right.indptr) > 0
    computed, skipped = np.zeros(n_blocks, int), np.zeros(n_blocks, int)
    for b in range(n_blocks):
        for t in range(-(-right.shape[0] // ts)):
            if L[b * ts:(b + 1) * ts, t * ts:(t + 1) * ts].any():
                if R_rows[t * ts:(t + 1) * ts].any():
                    computed[b] += 1
                else:
                    skipped[b] += 1
    return computed, skipped


@pytest.mark.parametrize("ts", [1, 7, 16, 100])
def test_tile_pairs_match_dense_reference(ts):
    left = _random(90, 90, 0.05, 1)
    right = _random(90, 90, 0.05, 2, empty_rows=range(14, 40))
    n_blocks = -(-90 // ts)
    got = tile_pairs(left, right, ts, n_blocks)
    want = _tile_pairs_dense(left, right, ts, n_blocks)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_tile_pairs_unsorted_rows():
    left = _random(40, 40, 0.2, 3)
    shuffled = left.copy()
    rng = np.random.default_rng(0)
    for i in range(40):  # each row's entries in a random order: same pairs
        s, e = shuffled.indptr[i], shuffled.indptr[i + 1]
        order = rng.permutation(e - s)
        shuffled.indices[s:e] = shuffled.indices[s:e][order]
        shuffled.data[s:e] = shuffled.data[s:e][order]
    shuffled.has_sorted_indices = False
    right = _random(40, 40, 0.1, 4, empty_rows=range(0, 10))
    for a, b in zip(tile_pairs(shuffled, right, 8, 5), _tile_pairs_dense(left, right, 8, 5)):
        np.testing.assert_array_equal(a, b)


def test_row_work_and_multiply_adds_match_the_definition():
    left, right = _random(60, 50, 0.1, 5), _random(50, 70, 0.1, 6)
    lengths = np.diff(right.indptr)
    want = np.array([lengths[left.indices[left.indptr[i]:left.indptr[i + 1]]].sum()
                     for i in range(60)])
    np.testing.assert_array_equal(row_work(left.indptr, left.indices, right.indptr), want)
    assert multiply_adds(left, right) == want.sum()


def test_row_bounds_cut_entries_evenly():
    A = _random(1000, 50, 0.1, 7)
    bounds = row_bounds(A.indptr, 4)
    assert bounds[0] == 0 and bounds[-1] == 1000 and np.all(np.diff(bounds) > 0)
    per_range = np.diff(A.indptr[bounds])
    assert per_range.max() - per_range.min() <= 2 * np.diff(A.indptr).max()


def test_row_view_and_stack_rows_give_back_the_matrix():
    A = _random(50, 30, 0.2, 8, dtype=np.float32)
    pieces = [row_view(A, a, b) for a, b in [(0, 13), (13, 13), (13, 50)]]
    assert np.shares_memory(pieces[2].data, A.data)  # a view, not a copy
    B = stack_rows(pieces)
    assert B.dtype == np.float32 and B.has_sorted_indices
    np.testing.assert_array_equal(B.toarray(), A.toarray())


def _assert_same_csr(got, want):
    assert got.dtype == want.dtype and got.shape == want.shape
    for name in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_add_diag_scaled_rows_is_add_diag_scaled(threads, dtype):
    A = _random(400, 300, 0.05, 9, dtype=dtype, empty_rows=range(100, 150))
    B = _random(400, 300, 0.05, 10, dtype=dtype, empty_rows=range(130, 200))
    d = np.random.default_rng(11).standard_normal(400).astype(dtype)
    d[::9] = 0.0  # rows of pixels left out: B's entries there vanish
    # exact cancellations where both hold an entry: dropped as the wrapper drops them
    both = (A.toarray() != 0) & (B.toarray() != 0)
    rows, cols = np.nonzero(both)
    dense_a = A.toarray()
    for r, c in list(zip(rows, cols))[::2]:
        if d[r] != 0:
            dense_a[r, c] = -np.float64(d[r]) * B[r, c]
    A = sp.csr_array(dense_a.astype(dtype))
    for M in (A, B):
        M.has_canonical_format = True
    got, want = add_diag_scaled_rows(A, d, B, threads), add_diag_scaled(A, d, B)
    _assert_same_csr(got, want)
    assert got.has_canonical_format
    ref = A.toarray().astype(np.float64) + d[:, None].astype(np.float64) * B.toarray()
    np.testing.assert_allclose(got.toarray(), ref, rtol=1e-6, atol=1e-7)


def test_add_diag_scaled_rows_drops_what_rounds_to_zero_in_float32():
    """A sum that is not 0 in float64 but rounds to 0 in float32 is dropped, as the
    one-thread wrapper drops it."""
    A = sp.csr_array(np.array([[1e-30, 1.0], [0.0, 2.0]], np.float32))
    B = sp.csr_array(np.array([[1e-30, 0.0], [1e-30, 3.0]], np.float32))
    d = np.array([1e-20, 1e-20], np.float32)
    for M in (A, B):
        M.has_canonical_format = True
    _assert_same_csr(add_diag_scaled_rows(A, d, B, 2), add_diag_scaled(A, d, B))


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_prune_rows_is_prune(threads, dtype):
    A = _random(300, 200, 0.1, 12, dtype=dtype, empty_rows=range(50, 120))
    A.data[::7] = 0.0  # explicit zeros: dropped as prune drops them
    A.has_canonical_format = True
    got, want = prune_rows(A, 0.25, threads), prune(A, threshold=0.25)
    assert got.dtype == want.dtype and got.has_canonical_format
    for name in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    dense = A.toarray()
    np.testing.assert_array_equal(got.toarray(), np.where(np.abs(dense) >= 0.25, dense, 0))


def _sparse_columns(n, used_cols, density, seed):
    """An (n, n) matrix whose entries lie in ``used_cols`` only, sorted rows."""
    rng = np.random.default_rng(seed)
    A = sp.random_array((n, len(used_cols)), density=density, format="csr", rng=rng)
    A.data -= 0.5
    wide = sp.csr_array((A.data, np.asarray(used_cols)[A.indices], A.indptr), shape=(n, n))
    wide.sort_indices()
    return wide


@pytest.mark.parametrize("threads", [1, 3])
def test_narrowed_product_equals_scipy_product(monkeypatch, threads):
    """left @ narrowed, widened, is scipy's left @ right entry for entry (same pattern
    at threshold 0, values to rounding), and a pruned one keeps the same entries as the
    product on the original columns."""
    from bigT import config
    from bigT.kernels import spgemm
    from bigT.kernels.row_ranges import narrow_columns

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)  # the numba paths
    n = 300
    used = np.sort(np.random.default_rng(5).choice(n, 40, replace=False))
    right = _sparse_columns(n, used, 0.2, 6)
    left = _random(n, n, 0.05, 7)
    narrowed = narrow_columns(right, threads)
    assert narrowed is not None
    np.testing.assert_array_equal(narrowed.columns, np.unique(right.indices))
    np.testing.assert_array_equal(narrowed.matrix.toarray(), right.toarray()[:, used])
    got = narrowed.widen(spgemm(left, narrowed.matrix, n_threads=threads), threads)
    want = sp.csr_array(left @ right)
    want.eliminate_zeros()
    want.sort_indices()
    assert got.shape == (n, n) and got.has_sorted_indices
    np.testing.assert_array_equal(got.indptr, want.indptr)
    np.testing.assert_array_equal(got.indices, want.indices)
    np.testing.assert_allclose(got.toarray(), (left.toarray() @ right.toarray()), atol=1e-12)
    pruned = narrowed.widen(spgemm(left, narrowed.matrix, threshold=0.05, n_threads=threads),
                            threads)
    direct = spgemm(left, right, threshold=0.05, n_threads=threads)
    np.testing.assert_array_equal(pruned.indptr, direct.indptr)
    np.testing.assert_array_equal(pruned.indices, direct.indices)
    np.testing.assert_array_equal(pruned.data, direct.data)


def test_narrow_columns_leaves_a_wide_factor(monkeypatch):
    """A factor using more than NARROW_MAX_FRACTION of its columns is not narrowed."""
    from bigT import config
    from bigT.kernels.row_ranges import NARROW_MAX_FRACTION, narrow_columns

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)
    n = 200
    used = np.arange(int(NARROW_MAX_FRACTION * n) + 1)
    assert narrow_columns(_sparse_columns(n, used, 0.9, 8), 1) is None


@pytest.mark.parametrize("threads", [1, 3])
def test_restricted_left_factor_gives_the_same_product(monkeypatch, threads):
    """restrict_to_used_rows keeps exactly left's entries over right's nonempty rows
    (dense reference), and the product with them is the product with left, bit for
    bit."""
    from bigT import config
    from bigT.kernels import spgemm
    from bigT.kernels.row_ranges import restrict_to_used_rows

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)
    n = 240
    left = _random(n, n, 0.1, 9)
    left.has_canonical_format = True
    right = _random(n, n, 0.1, 10, empty_rows=range(30, 220))
    got = restrict_to_used_rows(left, right, threads)
    used = np.diff(right.indptr) > 0
    np.testing.assert_array_equal(got.toarray(), left.toarray() * used[None, :])
    assert got.has_canonical_format
    direct = spgemm(left, right, threshold=0.01, n_threads=threads)
    restricted = spgemm(got, right, threshold=0.01, n_threads=threads)
    np.testing.assert_array_equal(restricted.indptr, direct.indptr)
    np.testing.assert_array_equal(restricted.indices, direct.indices)
    np.testing.assert_array_equal(restricted.data, direct.data)
    # most entries meeting a nonempty row: nothing to gain, left as it is
    assert restrict_to_used_rows(left, _random(n, n, 0.1, 11, empty_rows=range(5)),
                                 threads) is None


def test_shared_pools_are_kept_and_map_all_waits_for_every_task():
    """:func:`bigT.kernels.threads.shared_pool` hands back the same pool (no thread
    started twice); :func:`map_all` returns the results in order and, when a task
    fails, raises only once every other task has finished (as leaving a pool of one's
    own did)."""
    import threading
    import time

    from bigT.kernels.threads import map_all, shared_pool

    pool = shared_pool("test-map-all", 2)
    assert shared_pool("test-map-all", 2) is pool
    assert shared_pool("test-map-all", 3) is not pool
    assert map_all(pool, lambda x: x * x, range(5)) == [0, 1, 4, 9, 16]
    finished = threading.Event()

    def task(i):
        if i == 0:
            raise ValueError("first")
        time.sleep(0.2)
        finished.set()
        return i

    with pytest.raises(ValueError, match="first"):
        map_all(pool, task, range(2))
    assert finished.is_set()


def _blocks_with_diagonal(n, block_rows, dtype, seed):
    """Row blocks of a random (n, n) matrix holding most of its diagonal, global
    columns, and each block's first row."""
    A = _random(n, n, 0.1, seed, dtype=dtype).tolil()
    rng = np.random.default_rng(seed)
    for i in np.flatnonzero(rng.random(n) < 0.8):
        A[i, i] = 1.0 + rng.random()
    A = sp.csr_array(A)
    starts = list(range(0, n, block_rows))
    return [sp.csr_array(A[s:s + block_rows]) for s in starts], starts


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("threads", [1, 3])
def test_scaled_off_diagonal_rows_is_the_blocks_stacked(backend, dtype, threads):
    """The stacked off-diagonal scaling is what each block's scale_cols_off_diagonal
    (M = -T F^-1's kernel) stacked gives, bit for bit, canonical; below the numpy
    limit it is left to them (None)."""
    from bigT.kernels import scale_cols_off_diagonal
    from bigT.kernels.row_ranges import scaled_off_diagonal_rows

    blocks, starts = _blocks_with_diagonal(130, 32, dtype, 12)
    d = -np.random.default_rng(13).random(130).astype(dtype)
    got = scaled_off_diagonal_rows(blocks, starts, d, threads)
    if backend == "numpy":
        assert got is None
        return
    want = stack_rows([scale_cols_off_diagonal(B, d, s) for B, s in zip(blocks, starts)])
    assert got.shape == want.shape and got.has_canonical_format
    assert got.dtype == want.dtype and got.indices.dtype == want.indices.dtype
    np.testing.assert_array_equal(got.indptr, want.indptr)
    np.testing.assert_array_equal(got.indices, want.indices[:want.nnz])
    np.testing.assert_array_equal(got.data.view(np.uint8), want.data[:want.nnz].view(np.uint8))
    assert not got.diagonal().any() and got.nnz < sum(B.nnz for B in blocks)


@pytest.mark.parametrize("damage", ["unsorted", "duplicate", "out of range", "dtype"])
def test_scaled_off_diagonal_rows_leaves_what_it_cannot_trust(monkeypatch, damage):
    """Rows that are not sorted and duplicate-free, a column out of range, or blocks not
    of d's dtype: None (the caller makes M block by block, whose checks say what is
    wrong), never a wrong M."""
    from bigT import config
    from bigT.kernels.row_ranges import scaled_off_diagonal_rows

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", -1)
    blocks, starts = _blocks_with_diagonal(64, 32, np.float64, 14)
    d = np.ones(64)
    B = blocks[1]
    row = int(np.flatnonzero(np.diff(B.indptr) >= 2)[0])
    p = int(B.indptr[row])
    if damage == "unsorted":
        B.indices[p], B.indices[p + 1] = B.indices[p + 1], B.indices[p]
    elif damage == "duplicate":
        B.indices[p + 1] = B.indices[p]
    elif damage == "out of range":
        B.indices[int(B.indptr[-1]) - 1] = 64
    else:
        d = d.astype(np.float32)
    assert scaled_off_diagonal_rows(blocks, starts, d, 2) is None


def test_checked_tile_counts_counts_each_tile_column(backend):
    """A sound row's entries per tile column, as numpy's bincount of the tiles; None
    for a row whose columns go down (the reader's numpy checks then say why)."""
    from bigT.kernels.row_ranges import checked_tile_counts

    A = _random(50, 95, 0.2, 15)
    indptr = A.indptr.astype(np.int64)
    got = checked_tile_counts(indptr, A.indices, A.data, 95, 10)
    np.testing.assert_array_equal(got, np.bincount(A.indices // 10, minlength=10))
    indices = A.indices.copy()
    p = int(indptr[np.flatnonzero(np.diff(indptr) >= 2)[0]])
    indices[p], indices[p + 1] = indices[p + 1], indices[p]
    assert checked_tile_counts(indptr, indices, A.data, 95, 10) is None
