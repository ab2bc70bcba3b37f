"""blocks.assemble_rows: row blocks placed at their starts, arrays of the final size."""

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.schedule.blocks import assemble_rows


def test_assemble_rows_places_blocks_and_leaves_other_rows_empty():
    A = sp.csr_array(sp.random(4, 9, density=0.4, random_state=1, dtype=np.float32))
    B = sp.csr_array((3, 9), dtype=np.float32)  # an empty block
    C = sp.csr_array(sp.random(2, 9, density=0.5, random_state=2, dtype=np.float32))
    blocks_ = [(1, A), (5, B), (10, C)]
    out = assemble_rows(iter(blocks_), 12, 9, np.float32, nnz=A.nnz + C.nnz)
    ref = np.zeros((12, 9), np.float32)
    ref[1:5] = A.toarray()
    ref[10:12] = C.toarray()
    np.testing.assert_array_equal(out.toarray(), ref)
    assert out.indices.dtype == np.int32 and out.has_sorted_indices
    empty = assemble_rows(iter([]), 6, 6, np.float64, nnz=0)
    assert empty.shape == (6, 6) and empty.nnz == 0


def test_assemble_rows_refuses_a_wrong_count():
    A = sp.csr_array(np.eye(3, dtype=np.float32))
    with pytest.raises(ValueError, match="3 entries, 4 announced"):
        assemble_rows(iter([(0, A)]), 3, 3, np.float32, nnz=4)
    with pytest.raises(ValueError, match="more than the 2 entries"):
        assemble_rows(iter([(0, A)]), 3, 3, np.float32, nnz=2)


def test_assemble_rows_keeps_int32_and_reports_unsorted_blocks():
    U = sp.csr_array((np.array([1.0, 2.0]), np.array([5, 1], dtype=np.int64),
                      np.array([0, 2], dtype=np.int64)), shape=(1, 8))
    U.has_sorted_indices = False
    out = assemble_rows(iter([(2, U)]), 4, 8, np.float64, nnz=2)
    assert out.indices.dtype == np.int32 and not out.has_sorted_indices
    np.testing.assert_array_equal(out.toarray()[2], [0, 2, 0, 0, 0, 1, 0, 0])


def test_assemble_rows_refuses_overlapping_or_out_of_range_blocks():
    A = sp.csr_array(np.eye(2, dtype=np.float32))
    with pytest.raises(ValueError, match="overlaps"):
        assemble_rows(iter([(2, A), (3, A)]), 6, 2, np.float32, nnz=4)
    with pytest.raises(ValueError, match="passes row 3"):
        assemble_rows(iter([(2, A)]), 3, 2, np.float32, nnz=2)


def _brute_multiply_adds(L, R):
    """Multiply-adds of L @ R, one left entry at a time."""
    L, R = sp.csr_array(L), sp.csr_array(R)
    lens = np.diff(R.indptr)
    return sum(int(lens[k]) for k in L.indices)


def test_kernel_tally_counts_whole_and_batched_products_alike():
    from bigT.schedule.blocks import KernelTally, row_product, row_product_batched

    rng = np.random.default_rng(4)
    L = sp.csr_array(sp.random(20, 50, density=0.2, random_state=rng))
    R = sp.csr_array(sp.random(50, 50, density=0.15, random_state=rng))
    R.sort_indices()
    want = _brute_multiply_adds(L, R)
    whole = KernelTally()
    ref = row_product(L, R, 0.0, tally=whole)
    assert whole.multiply_adds == want and whole.seconds > 0
    halves = []
    for lo, hi in ((0, 25), (25, 50)):
        part = R.tolil()
        part[:lo], part[hi:] = 0, 0
        halves.append(sp.csr_array(part))
    batched = KernelTally()
    work = np.array([_brute_multiply_adds(L[[i]], R) for i in range(20)], float)
    out = row_product_batched(L, [lambda h=h: h for h in halves], 0.0, work, 30, tally=batched)
    np.testing.assert_allclose(out.toarray(), ref.toarray(), rtol=1e-12)
    # every chunk of rows meets every batch: the batches' work adds up to the whole
    assert batched.multiply_adds == want
