"""bigT.kernels.BlockDiagonal and its helpers against dense numpy."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.errors import ShapeMismatchError
from bigT.kernels import BlockDiagonal, diagonal_blocks, off_block_diagonal


def _dense(values):
    values = np.asarray(values)
    return np.diag(values) if values.ndim == 1 else sp.block_diag(list(values)).toarray()


@pytest.fixture(params=[1, 3])
def case(request):
    b = request.param
    rng = np.random.default_rng(b)
    m = 10
    values = rng.standard_normal(m * b) if b == 1 else rng.standard_normal((m, b, b))
    A = sp.random(4 * b, m * b, density=0.3, random_state=rng, format="csr")
    return b, BlockDiagonal(values), _dense(values), A


def test_products_match_dense(case):
    b, B, dense, A = case
    start = 3 * b
    rows = slice(start, start + A.shape[0])  # A: rows 3b:7b of an (mb, mb) matrix
    V = np.random.default_rng(0).standard_normal((A.shape[0], 2))
    np.testing.assert_allclose(B.apply(V, start), dense[rows, rows] @ V, atol=1e-14)
    got = B.scale_rows(A, start)
    np.testing.assert_allclose(got.toarray(), dense[rows, rows] @ A.toarray(), atol=1e-14)
    assert got.has_sorted_indices
    np.testing.assert_allclose(B.scale_cols(A).toarray(), A.toarray() @ dense, atol=1e-14)
    np.testing.assert_array_equal(B.rows(start, start + 2 * b, np.float64).toarray(),
                                  dense[start:start + 2 * b])


def test_block_helpers_match_dense():
    rng = np.random.default_rng(1)
    A = sp.random(9, 30, density=0.5, random_state=rng, format="csr")
    start = 12  # rows 12:21 of a 30 x 30 matrix: pixels 4, 5, 6
    dense = A.toarray()
    want = np.stack([dense[3 * k:3 * k + 3, start + 3 * k:start + 3 * k + 3] for k in range(3)])
    np.testing.assert_array_equal(diagonal_blocks(A, start, 3), want)
    off = dense.copy()
    for k in range(3):
        off[3 * k:3 * k + 3, start + 3 * k:start + 3 * k + 3] = 0
    np.testing.assert_array_equal(off_block_diagonal(A, start, 3).toarray(), off)


def test_rows_must_cover_whole_blocks():
    B = BlockDiagonal(np.ones((4, 3, 3)))
    with pytest.raises(ShapeMismatchError, match="whole 3x3 blocks"):
        B.apply(np.ones((3, 1)), start=1)
    with pytest.raises(ShapeMismatchError, match=r"\(n,\) or \(m, b, b\)"):
        BlockDiagonal(np.ones((4, 3)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_kernels_on_hard_rows(case, dtype):
    """Unsorted rows, empty rows, a zero block (a pixel left out: its columns and rows
    hold nothing, zeros dropped), float32 entries with float64 blocks; the products
    negated and without their diagonal blocks, in one pass, as M = -T F^-1 is made."""
    b, _, _, A = case
    rng = np.random.default_rng(7)
    values = rng.standard_normal((10, b, b)) if b > 1 else rng.standard_normal(10)
    values[4] = 0  # pixel 4 left out
    B, dense = BlockDiagonal(values), _dense(values)
    A = sp.csr_array(A, dtype=dtype)
    A.indptr[2 * b:] = A.indptr[2 * b]  # ... rows 2b.. emptied, then
    A = sp.csr_array((A.data[:A.indptr[-1]], A.indices[:A.indptr[-1]], A.indptr[:4 * b + 1]),
                     shape=A.shape)
    A = sp.csr_array(A + sp.random(4 * b, 10 * b, density=0.2, random_state=rng,
                                   format="csr", dtype=dtype))
    A.indices, A.data = A.indices.copy(), A.data.copy()
    for i in range(A.shape[0]):  # reverse each row: unsorted indices
        a, z = A.indptr[i], A.indptr[i + 1]
        A.indices[a:z], A.data[a:z] = A.indices[a:z][::-1].copy(), A.data[a:z][::-1].copy()
    A.has_sorted_indices = False
    start = 3 * b
    tol = 1e-5 if dtype == np.float32 else 1e-13
    prod = A.toarray().astype(np.float64) @ dense
    got = B.scale_cols(A)
    assert got.has_sorted_indices and got.dtype == dtype
    assert b == 1 or not np.any(got.data == 0)  # grey keeps the scale kernel's zeros
    np.testing.assert_allclose(got.toarray(), prod, atol=tol)
    off = -prod
    for k in range(4):
        p = start // b + k
        off[b * k:b * k + b, b * p:b * p + b] = 0
    got = B.scale_cols(A, negate=True, drop_diagonal_blocks_at=start)
    np.testing.assert_allclose(got.toarray(), off, atol=tol)
    rows = slice(start, start + A.shape[0])
    got = B.scale_rows(A, start, dtype=np.float64)
    assert got.dtype == np.float64 and (b == 1 or not np.any(got.data == 0))
    np.testing.assert_allclose(got.toarray(), dense[rows, rows] @ A.toarray(), atol=tol)


def test_diagonal_blocks_sum_duplicates():
    """A row block that is not canonical (a duplicate entry) has its blocks summed."""
    A = sp.csr_array((np.array([1.0, 2.0, 5.0]), np.array([4, 4, 0]), np.array([0, 2, 3, 3])),
                     shape=(3, 9))
    blocks = diagonal_blocks(A, 3, 3)
    assert blocks[0, 0, 1] == 3.0 and blocks.sum() == 3.0


def test_partial_blocks_and_wrong_widths_are_refused_not_read_past():
    """Rows that do not cover whole 3x3 blocks, or a block of another width, are a
    ShapeMismatchError: the kernels step three rows at a time without bounds checks
    (four rows once read past the row pointers and crashed the process)."""
    B = BlockDiagonal(np.random.default_rng(0).random((4, 3, 3)))
    four_rows = sp.random(4, 12, density=0.5, format="csr", random_state=1)
    with pytest.raises(ShapeMismatchError):
        B.scale_rows(four_rows, 0)
    with pytest.raises(ShapeMismatchError):
        B.apply(np.ones((4, 2)))
    with pytest.raises(ShapeMismatchError):
        B.scale_cols(sp.random(3, 15, density=0.5, format="csr", random_state=2))


def test_duplicate_columns_are_summed_before_the_row_merge():
    """A row block with a repeated column gives the dense product and a canonical
    result (no repeated index behind a canonical flag)."""
    rng = np.random.default_rng(3)
    B = BlockDiagonal(rng.random((2, 3, 3)))
    A = sp.csr_array((np.array([1.0, 2.0, 3.0]), np.array([1, 1, 2]), np.array([0, 3, 3, 3])),
                     shape=(3, 6))
    out = B.scale_rows(A, 0)
    dense = B.csr(np.float64).toarray()[:3, :3] @ A.toarray()
    np.testing.assert_allclose(out.toarray(), dense)
    for i in range(3):
        row = out.indices[out.indptr[i]:out.indptr[i + 1]]
        assert len(np.unique(row)) == len(row)
